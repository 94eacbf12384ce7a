"""The perception module of XPL (and PLATO): a Component VAE over the objects of a frame.

Each object is encoded alone, from the RGBD frame blanked outside its mask, into a Gaussian
posterior (mean 6*sigmoid-3, std 3*sigmoid). A spatial broadcast decoder turns a latent back
into an RGBD picture of that object on the blank, and a near-hard z-buffer (a softmax over
slots of -1000*|theta|*depth) composites the decoded slots into the frame.

Pixels are scaled to [-1, 1]. "Blank" (nothing there) is white with a depth beyond the far
plane, so an empty slot always loses the z-buffer to the background and to every object.
The background (the pixels of id 0: floor and sky) is one more component, encoded and
decoded by the same networks and composited like the slots; its loss counts only its own
pixels, so the decoder fills in the background behind the objects.

"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from ..domains import COUNT, NON_NEGATIVE, POSITIVE, check_config, within
from ..errors import XvoeError

__all__ = ["BLANK", "PerceptionConfig", "normalise", "to_uint8", "BroadcastDecoder", "PerceptionBatch",
           "ComponentVAE"]

_BLANK_DEPTH = 1.5                                   # beyond the far plane (255 -> 1.0)
BLANK = (1.0, 1.0, 1.0, _BLANK_DEPTH)                # RGB white, depth past the background
_MEAN_RANGE = 3.0                                    # mean = 6*sigmoid(a) - 3
_STD_SCALE = 3.0                                     # std = 3*sigmoid(b)


@dataclass(frozen=True)
class PerceptionConfig:
    """The Component VAE: per-object encoder, spatial broadcast decoder, depth compositor."""

    image_size: int = within(32, COUNT)            # frames are image_size x image_size RGBD
    latent_dim: int = within(16, COUNT)            # D: size of each object's latent
    encoder: str = "cnn"            # "cnn" (small, for CPUs) or "vit" (the paper's)
    # small CNN encoder: channels of its stride-2 5x5 convolutions, then an MLP
    cnn_channels: tuple[int, ...] = within((32, 32, 64, 64), COUNT)
    cnn_hidden: int = within(128, COUNT)
    cnn_coords: bool = True         # pixel coordinates as extra input channels (CoordConv)
    # ViT encoder (paper: 8-pixel patches at 128 px, width 256, 6 layers, 8 heads, MLP 1024, head 512)
    vit_patch: int = within(8, COUNT)
    vit_width: int = within(256, COUNT)
    vit_layers: int = within(6, COUNT)
    vit_heads: int = within(8, COUNT)
    vit_mlp: int = within(1024, COUNT)
    vit_head_hidden: int = within(512, COUNT)
    # spatial broadcast decoder: broadcast grid, then stride-2 transposed convs up to image_size
    broadcast_size: int = within(8, COUNT)
    decoder_channels: int = within(32, COUNT)
    decoder_kernel: int = within(5, COUNT)
    decoder_extra_convs: int = within(0, NON_NEGATIVE)    # stride-1 convs after the upsampling (paper: 1)
    # likelihood and prior
    sigma: float = within(0.05, POSITIVE)             # pixel standard deviation of the Gaussian likelihood
    beta: float = within(0.5, NON_NEGATIVE)               # weight of the KL to N(0, I)
    object_loss_weight: float = within(1.0, NON_NEGATIVE)  # per-object masked reconstruction, next to the composite
    theta_init: float = within(1.0, POSITIVE)         # compositing temperature |theta|, learned
    std_init: float = within(0.05, POSITIVE)          # posterior std the encoder starts from (before training)

    def __post_init__(self) -> None:
        check_config(self)      # each field in its domain before the relations between them are checked
        if self.encoder not in ("cnn", "vit"):
            raise XvoeError(f"encoder must be 'cnn' or 'vit', not {self.encoder!r}")
        ratio = self.image_size // self.broadcast_size
        if self.image_size % self.broadcast_size or ratio & (ratio - 1):
            raise XvoeError(f"image_size {self.image_size} must be broadcast_size {self.broadcast_size} "
                            "times a power of two")
        if self.encoder == "vit" and self.image_size % self.vit_patch:
            raise XvoeError(f"image_size {self.image_size} is not a multiple of vit_patch {self.vit_patch}")
        if self.encoder == "vit" and self.vit_width % self.vit_heads:
            raise XvoeError(f"vit_width {self.vit_width} is not a multiple of vit_heads {self.vit_heads}")


def _blank_like(images: Tensor) -> Tensor:
    """The blank value, broadcastable against (..., 4, H, W) images."""
    return images.new_tensor(BLANK).view(4, 1, 1)


def normalise(rgbd: Tensor) -> Tensor:
    """uint8 RGBD (..., H, W, 4) to float (..., 4, H, W) in [-1, 1]."""
    return (rgbd.movedim(-1, -3).float() / 127.5) - 1.0


def to_uint8(images: Tensor) -> Tensor:
    """Float (..., 4, H, W) in [-1, 1] back to uint8 (..., H, W, 4) on the CPU, to draw or save;
    blank depth clips to far."""
    return ((images.clamp(-1, 1) + 1.0) * 127.5).round().to(torch.uint8).movedim(-3, -1).cpu()


class _CNNEncoder(nn.Module):
    """Small CPU encoder: stride-2 5x5 convolutions, then an MLP to the 2D posterior parameters."""

    def __init__(self, config: PerceptionConfig):
        super().__init__()
        layers, channels, size = [], 4 + 2 * config.cnn_coords, config.image_size
        self.coords = config.cnn_coords
        if self.coords:     # pixel coordinates as two more input channels make position easy to read out
            ramp = torch.linspace(-1, 1, size)
            self.register_buffer("grid", torch.stack(torch.meshgrid(ramp, ramp, indexing="xy")), persistent=False)
        for width in config.cnn_channels:
            layers += [nn.Conv2d(channels, width, 5, stride=2, padding=2), nn.ReLU()]
            channels, size = width, (size + 1) // 2
        self.convs = nn.Sequential(*layers)
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(channels * size * size, config.cnn_hidden), nn.ReLU(),
                                  nn.Linear(config.cnn_hidden, 2 * config.latent_dim))

    def forward(self, images: Tensor) -> Tensor:
        if self.coords:
            images = torch.cat([images, self.grid.expand(len(images), -1, -1, -1)], dim=1)
        return self.head(self.convs(images))


class _ViTEncoder(nn.Module):
    """The paper's encoder: patch embedding, CLS token, pre-LN Transformer, MLP head."""

    def __init__(self, config: PerceptionConfig):
        super().__init__()
        width, patches = config.vit_width, (config.image_size // config.vit_patch) ** 2
        self.embed = nn.Conv2d(4, width, config.vit_patch, stride=config.vit_patch)
        self.cls = nn.Parameter(torch.zeros(1, 1, width))
        self.position = nn.Parameter(torch.randn(1, patches + 1, width) * 0.02)
        layer = nn.TransformerEncoderLayer(width, config.vit_heads, config.vit_mlp, dropout=0.0,
                                           activation="gelu", batch_first=True, norm_first=True)
        self.blocks = nn.TransformerEncoder(layer, config.vit_layers, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(width)
        self.head = nn.Sequential(nn.Linear(width, config.vit_head_hidden), nn.LeakyReLU(),
                                  nn.Linear(config.vit_head_hidden, 2 * config.latent_dim))

    def forward(self, images: Tensor) -> Tensor:
        tokens = self.embed(images).flatten(2).transpose(1, 2)              # (N, P, W)
        tokens = torch.cat([self.cls.expand(len(tokens), -1, -1), tokens], dim=1) + self.position
        return self.head(self.norm(self.blocks(tokens)[:, 0]))


def _build_encoder(config: PerceptionConfig) -> nn.Module:
    return _CNNEncoder(config) if config.encoder == "cnn" else _ViTEncoder(config)


class BroadcastDecoder(nn.Module):
    """Spatial broadcast decoder: latent tiled on a small grid plus a position embedding,
    stride-2 transposed convolutions up to full size, RGBD out.

    The output layer starts at the blank value with small weights, so every slot begins as
    "nothing here": without that the encoder saturates its means at +-3 within a few steps.
    """

    def __init__(self, config: PerceptionConfig):
        super().__init__()
        width, kernel, grid = config.decoder_channels, config.decoder_kernel, config.broadcast_size
        self.grid = grid
        self.project = nn.Linear(config.latent_dim, width)
        self.position = nn.Linear(4, width)
        ys, xs = torch.meshgrid(torch.linspace(0, 1, grid), torch.linspace(0, 1, grid), indexing="ij")
        self.register_buffer("coords", torch.stack([xs, ys, 1 - xs, 1 - ys], dim=-1), persistent=False)
        layers = []
        for _ in range(int(math.log2(config.image_size // grid))):
            layers += [nn.ConvTranspose2d(width, width, kernel, stride=2, padding=kernel // 2, output_padding=1),
                       nn.ReLU()]
        for _ in range(config.decoder_extra_convs):
            layers += [nn.Conv2d(width, width, kernel, padding=kernel // 2), nn.ReLU()]
        self.convs = nn.Sequential(*layers)
        self.out = nn.Conv2d(width, 4, 3, padding=1)
        with torch.no_grad():
            self.out.weight.mul_(0.1)
            self.out.bias.copy_(torch.tensor(BLANK))

    def forward(self, z: Tensor) -> Tensor:
        features = self.project(z)[:, :, None, None] + self.position(self.coords).permute(2, 0, 1)
        return self.out(self.convs(features))


@dataclass
class PerceptionBatch:
    """A batch of frames cut into per-object inputs (see xvoe.training.data.perception_batch).

    frames (B,4,H,W) targets; objects (M,4,H,W) the masked images of the slots with pixels,
    which sit at (object_frame, object_slot); background (B,4,H,W) with
    background_mask (B,1,H,W) = 1 on id-0 pixels; noise (B,K+1,D) for the reparameterisation (component 0 is
    the background), blank_noise (1,D) for the shared blank input.
    """

    frames: Tensor
    objects: Tensor
    object_frame: Tensor
    object_slot: Tensor
    background: Tensor
    background_mask: Tensor
    noise: Tensor
    blank_noise: Tensor
    slots: int

    def to(self, device: torch.device | str) -> PerceptionBatch:
        moved = {name: getattr(self, name).to(device) for name in self.__dataclass_fields__ if name != "slots"}
        return PerceptionBatch(**moved, slots=self.slots)

    @property
    def images(self) -> int:
        """Object images the model encodes and decodes for this batch (objects, backgrounds, blank)."""
        return len(self.objects) + len(self.frames) + 1


class ComponentVAE(nn.Module):
    """Encoder, decoder and compositor of the perception module, and its training loss."""

    def __init__(self, config: PerceptionConfig):
        super().__init__()
        self.config = config
        self.encoder = _build_encoder(config)
        self.decoder = BroadcastDecoder(config)
        self.theta = nn.Parameter(torch.tensor(float(config.theta_init)))
        self._start_with_small_std(config.std_init)

    def _start_with_small_std(self, std: float) -> None:
        """Bias the std half of the encoder's output so the posterior starts narrow: with
        std = 3*sigmoid(0) = 1.5 the decoder first sees mostly noise and learns slowly."""
        last = [m for m in self.encoder.head.modules() if isinstance(m, nn.Linear)][-1]
        with torch.no_grad():
            last.bias[self.config.latent_dim:] = math.log(std / (_STD_SCALE - std))

    def posterior(self, images: Tensor) -> tuple[Tensor, Tensor]:
        """Mean in (-3, 3) and std in (0, 3) of q(z | masked image); images (N,4,H,W)."""
        a, b = self.encoder(images).chunk(2, dim=-1)
        return _MEAN_RANGE * (2 * torch.sigmoid(a) - 1), _STD_SCALE * torch.sigmoid(b)

    DECODE_CHUNK = 64   # latents per decoder pass outside training

    def decode(self, z: Tensor) -> Tensor:
        """RGBD pictures (N,4,H,W) of latents (N,D), each object alone on the blank.

        Without gradients the latents go through in chunks: a thousand at once make
        feature maps of half a gigabyte that fall out of the CPU caches (docs/decisions.md,
        "Speed and memory")."""
        if torch.is_grad_enabled() or len(z) <= self.DECODE_CHUNK:
            return self.decoder(z)
        return torch.cat([self.decoder(chunk) for chunk in z.split(self.DECODE_CHUNK)])

    def composite(self, layers: Tensor) -> Tensor:
        """Z-buffer the components (..., S, 4, H, W) into frames (..., 4, H, W)."""
        weights = torch.softmax(self.composite_logits(layers), dim=-4)
        return (weights * layers).sum(dim=-4)

    def composite_logits(self, layers: Tensor) -> Tensor:
        """The compositor's softmax logits (..., 1, H, W) of pictures (..., 4, H, W): nearer wins."""
        return -1000.0 * self.theta.abs() * layers[..., 3:4, :, :]

    def blank(self) -> Tensor:
        """The input every empty slot sees: (1,4,H,W) of the blank value."""
        size = self.config.image_size
        return self.theta.new_tensor(BLANK).view(1, 4, 1, 1).expand(1, 4, size, size)

    def forward_batch(self, batch: PerceptionBatch, sample: bool = True) -> dict[str, Tensor]:
        """Encode every component of a batch, decode (a posterior sample or the mean), composite.

        Empty slots are not encoded one by one: they all see the same blank input, which is
        encoded once and its decoding stands in for every slot without pixels.
        """
        count = len(batch.frames)
        inputs = torch.cat([batch.objects, batch.background, self.blank()])
        mean, std = self.posterior(inputs)
        z = mean
        if sample:
            z = mean + std * torch.cat([batch.noise[batch.object_frame, batch.object_slot + 1], batch.noise[:, 0],
                                        batch.blank_noise])
        objects, background, blank = self.decode(z).split([len(batch.objects), count, 1])
        layers = blank.expand(count, batch.slots + 1, *blank.shape[1:]).clone()
        layers[:, 0] = background
        layers[batch.object_frame, batch.object_slot + 1] = objects
        return {"mean": mean, "std": std, "objects": objects, "background": background, "blank": blank,
                "layers": layers, "composite": self.composite(layers)}

    def loss(self, batch: PerceptionBatch) -> dict[str, Tensor]:
        """Negative ELBO per frame: composite and per-object Gaussian likelihoods plus beta*KL.

        The per-object term is needed: with the composite alone the decoder can hide every
        object behind the background, where it gets no gradient.
        """
        out, count = self.forward_batch(batch), len(batch.frames)
        scale = 0.5 / self.config.sigma ** 2
        error = (out["composite"] - batch.frames).pow(2)
        per_frame = scale * error.flatten(1).sum(1)
        object_nll = self.object_nll(out["objects"], batch)
        per_frame = per_frame + self.config.object_loss_weight * _sum_by(object_nll, batch.object_frame, count)
        background_error = batch.background_mask * (out["background"] - batch.background).pow(2)
        per_frame = per_frame + scale * background_error.flatten(1).sum(1)
        kl = _kl_normal(out["mean"], out["std"])
        kl_objects, kl_background, kl_blank = kl.split([len(batch.objects), count, 1])
        per_frame = per_frame + self.config.beta * (_sum_by(kl_objects, batch.object_frame, count) + kl_background)
        blank_nll = scale * (out["blank"] - self.blank()).pow(2).sum() + self.config.beta * kl_blank.sum()
        mse = error.mean().detach()
        return {"loss": per_frame.mean() + blank_nll, "mse": mse, "kl": kl.mean().detach(),
                "psnr": 10 * torch.log10(4.0 / mse.clamp_min(1e-10))}

    def object_nll(self, pictures: Tensor, batch: PerceptionBatch) -> Tensor:
        """Per-object Gaussian NLL (M,) of decoded pictures against the masked object images."""
        error = (pictures - batch.objects).pow(2)
        return 0.5 / self.config.sigma ** 2 * error.flatten(1).sum(1)

    def forward(self, batch: PerceptionBatch) -> dict[str, Tensor]:
        """The training objective (what DistributedDataParallel calls)."""
        return self.loss(batch)


def _kl_normal(mean: Tensor, std: Tensor) -> Tensor:
    """KL(N(mean, std^2) || N(0, I)) summed over the last axis; std floored to avoid log(0)."""
    std = std.clamp_min(1e-6)
    return 0.5 * (mean.pow(2) + std.pow(2) - 1.0).sum(-1) - std.log().sum(-1)


def _sum_by(values: Tensor, index: Tensor, count: int) -> Tensor:
    """Sum `values` into `count` bins by `index` (per-object terms into their frames)."""
    return values.new_zeros(count).index_add(0, index, values)
