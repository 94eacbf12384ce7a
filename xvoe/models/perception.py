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

With `where_latents` (the `cpu` preset) the first two latents are the object's position:
the decoder draws the object relative to them, and the encoder starts them at the centroid
of the object's visible pixels and learns only a correction (for occlusion, and for where
the drawing's reference point sits). The preset also trains the encoder on object images
with a side cut off against the whole object (`cut_share`), and leaves the pixels of other
objects out of each object's own loss (`amodal`), so that a partly hidden object's latents
say where the object is, not where its visible part is. Position is then linear in the
latents by construction, for every kind of object alike. Per unit, these two latents move the
picture hundreds of times more than the others, so the later stages weigh their latent losses
by that (XPLConfig.weigh_by_picture; docs/decisions.md, "Where latents and picture weights").
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from ..errors import XvoeError

BLANK_DEPTH = 1.5                                   # beyond the far plane (255 -> 1.0)
BLANK = (1.0, 1.0, 1.0, BLANK_DEPTH)                # RGB white, depth past the background
MEAN_RANGE = 3.0                                    # mean = 6*sigmoid(a) - 3
STD_SCALE = 3.0                                     # std = 3*sigmoid(b)


@dataclass(frozen=True)
class PerceptionConfig:
    """The Component VAE: per-object encoder, spatial broadcast decoder, depth compositor."""

    image_size: int = 32            # frames are image_size x image_size RGBD
    latent_dim: int = 16            # D: size of each object's latent
    encoder: str = "cnn"            # "cnn" (small, for CPUs) or "vit" (the paper's)
    # small CNN encoder: channels of its stride-2 5x5 convolutions, then an MLP
    cnn_channels: tuple[int, ...] = (32, 32, 64, 64)
    cnn_hidden: int = 128
    cnn_coords: bool = True         # pixel coordinates as extra input channels (CoordConv)
    # ViT encoder (paper: 8-pixel patches at 128 px, width 256, 6 layers, 8 heads, MLP 1024, head 512)
    vit_patch: int = 8
    vit_width: int = 256
    vit_layers: int = 6
    vit_heads: int = 8
    vit_mlp: int = 1024
    vit_head_hidden: int = 512
    # spatial broadcast decoder: broadcast grid, then stride-2 transposed convs up to image_size
    broadcast_size: int = 8
    decoder_channels: int = 32
    decoder_kernel: int = 5
    decoder_extra_convs: int = 0    # stride-1 convs after the upsampling (paper: 1)
    # latents 0 and 1 are the object's (x, y): the decoder draws relative to them and the encoder
    # starts them at the visible pixels' centroid (off in the paper; off in checkpoints made before it)
    where_latents: bool = False
    # frame coordinates ([-1, 1]) per unit of those two latents: 0.5 spans the frame over +-2 of the
    # means' +-3, so that a pixel's move weighs more in the later stages' latent losses
    where_scale: float = 0.5
    # the per-object loss leaves out the other objects' pixels, where this one may stand hidden, so
    # a partly hidden object is decoded whole (its latents then say where it is, not its visible part)
    amodal: bool = False
    # share of the object images the encoder sees with a random side cut off while the loss asks for
    # the whole object: it learns where a partly hidden object is, and to draw it whole
    cut_share: float = 0.0
    # likelihood and prior
    sigma: float = 0.05             # pixel standard deviation of the Gaussian likelihood
    beta: float = 0.5               # weight of the KL to N(0, I)
    object_loss_weight: float = 1.0  # per-object masked reconstruction, next to the composite
    theta_init: float = 1.0         # compositing temperature |theta|, learned
    std_init: float = 0.05          # posterior std the encoder starts from (before training)

    def __post_init__(self) -> None:
        if self.encoder not in ("cnn", "vit"):
            raise XvoeError(f"encoder must be 'cnn' or 'vit', not {self.encoder!r}")
        ratio = self.image_size // self.broadcast_size
        if self.image_size % self.broadcast_size or ratio & (ratio - 1):
            raise XvoeError(f"image_size {self.image_size} must be broadcast_size {self.broadcast_size} "
                            "times a power of two")
        if self.encoder == "vit" and self.image_size % self.vit_patch:
            raise XvoeError(f"image_size {self.image_size} is not a multiple of vit_patch {self.vit_patch}")
        if self.where_latents and self.latent_dim < 3:
            raise XvoeError(f"where_latents needs latent_dim >= 3 (two for position), not {self.latent_dim}")
        if self.encoder == "vit" and self.vit_width % self.vit_heads:
            raise XvoeError(f"vit_width {self.vit_width} is not a multiple of vit_heads {self.vit_heads}")


def blank_like(images: Tensor) -> Tensor:
    """The blank value, broadcastable against (..., 4, H, W) images."""
    return images.new_tensor(BLANK).view(4, 1, 1)


def normalise(rgbd: Tensor) -> Tensor:
    """uint8 RGBD (..., H, W, 4) to float (..., 4, H, W) in [-1, 1]."""
    return (rgbd.movedim(-1, -3).float() / 127.5) - 1.0


def visible_centroid(images: Tensor) -> Tensor:
    """(x, y) in [-1, 1] (pixel centres, y downwards) of the non-blank pixels of masked images
    (N,4,H,W); 0 for an image with none (an empty slot), so no NaN can arise."""
    size = images.shape[-1]
    shown = (images[:, 3] < (1.0 + BLANK_DEPTH) / 2).to(images.dtype)         # blank depth is beyond 1.0
    ramp = torch.linspace(-1, 1, size, dtype=images.dtype, device=images.device)
    count = shown.sum((1, 2)).clamp_min(1.0)
    return torch.stack([(shown * ramp).sum((1, 2)) / count, (shown * ramp[:, None]).sum((1, 2)) / count], dim=-1)


def to_uint8(images: Tensor) -> Tensor:
    """Float (..., 4, H, W) in [-1, 1] back to uint8 (..., H, W, 4); blank depth clips to far."""
    return ((images.clamp(-1, 1) + 1.0) * 127.5).round().to(torch.uint8).movedim(-3, -1)


class CNNEncoder(nn.Module):
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


class ViTEncoder(nn.Module):
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


def build_encoder(config: PerceptionConfig) -> nn.Module:
    return CNNEncoder(config) if config.encoder == "cnn" else ViTEncoder(config)


class BroadcastDecoder(nn.Module):
    """Spatial broadcast decoder: latent tiled on a small grid plus a position embedding,
    stride-2 transposed convolutions up to full size, RGBD out.

    With `where_latents` the position embedding is an MLP of each grid cell's coordinates
    relative to the first two latents (times where_scale), and only the others are tiled:
    shifting those two by one grid cell shifts the picture by image_size / broadcast_size pixels.

    The output layer starts at the blank value with small weights, so every slot begins as
    "nothing here": without that the encoder saturates its means at +-3 within a few steps.
    """

    def __init__(self, config: PerceptionConfig):
        super().__init__()
        width, kernel, grid = config.decoder_channels, config.decoder_kernel, config.broadcast_size
        self.grid, self.where, self.where_scale = grid, config.where_latents, config.where_scale
        if self.where:
            self.project = nn.Linear(config.latent_dim - 2, width)
            # appearance scales the shape's features (colour where the object is); zero at first, so the
            # decoder starts as a plain sum of the two
            self.gate = nn.Linear(config.latent_dim - 2, width)
            nn.init.zeros_(self.gate.weight)
            nn.init.zeros_(self.gate.bias)
            self.relative_position = nn.Sequential(nn.Linear(2, width), nn.ReLU(), nn.Linear(width, width))
            # each cell's centre in the coordinates of visible_centroid (pixel centres spanning [-1, 1])
            centres = ((torch.arange(grid) + 0.5) * (config.image_size / grid) - 0.5) * 2 / (config.image_size - 1) - 1
            ys, xs = torch.meshgrid(centres, centres, indexing="ij")
            self.register_buffer("cells", torch.stack([xs, ys], dim=-1), persistent=False)      # (g, g, 2)
        else:
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
        if self.where:
            relative = self.cells - self.where_scale * z[:, None, None, :2]                 # (N, g, g, 2)
            appearance = z[:, 2:]
            shape = self.relative_position(relative).permute(0, 3, 1, 2)
            gate = 1 + self.gate(appearance)[:, :, None, None]
            features = self.project(appearance)[:, :, None, None] + shape * gate
        else:
            features = self.project(z)[:, :, None, None] + self.position(self.coords).permute(2, 0, 1)
        return self.out(self.convs(features))


@dataclass
class PerceptionBatch:
    """A batch of frames cut into per-object inputs (see xvoe.data.perception_batch).

    frames (B,4,H,W) targets; objects (M,4,H,W) the masked images of the slots with pixels,
    which sit at (object_frame, object_slot), and object_inputs what the encoder sees of them
    (the same, or cut: data.cut_objects), with object_known (M,1,H,W) = 0 on the pixels of
    the other objects (what stands behind them is unknown); background (B,4,H,W) with
    background_mask (B,1,H,W) = 1 on id-0 pixels; noise (B,K+1,D) for the reparameterisation (component 0 is
    the background), blank_noise (1,D) for the shared blank input.
    """

    frames: Tensor
    objects: Tensor
    object_inputs: Tensor
    object_known: Tensor
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
        self.encoder = build_encoder(config)
        self.decoder = BroadcastDecoder(config)
        self.theta = nn.Parameter(torch.tensor(float(config.theta_init)))
        self._start_with_small_std(config.std_init)

    def _start_with_small_std(self, std: float) -> None:
        """Bias the std half of the encoder's output so the posterior starts narrow: with
        std = 3*sigmoid(0) = 1.5 the decoder first sees mostly noise and learns slowly."""
        last = [m for m in self.encoder.head.modules() if isinstance(m, nn.Linear)][-1]
        with torch.no_grad():
            last.bias[self.config.latent_dim:] = math.log(std / (STD_SCALE - std))

    def posterior(self, images: Tensor) -> tuple[Tensor, Tensor]:
        """Mean in (-3, 3) and std in (0, 3) of q(z | masked image); images (N,4,H,W).

        With where latents the first two means are 6*sigmoid(a + c)-3 with c the logit that
        puts them at the visible pixels' centroid (divided by where_scale) when a = 0."""
        a, b = self.encoder(images).chunk(2, dim=-1)
        if self.config.where_latents:
            start = torch.logit((visible_centroid(images) / self.config.where_scale + MEAN_RANGE) / (2 * MEAN_RANGE))
            a = torch.cat([a[:, :2] + start, a[:, 2:]], dim=-1)
        return MEAN_RANGE * (2 * torch.sigmoid(a) - 1), STD_SCALE * torch.sigmoid(b)

    DECODE_CHUNK = 64   # latents per decoder pass outside training (benchmarks/decode.py)

    def decode(self, z: Tensor) -> Tensor:
        """RGBD pictures (N,4,H,W) of latents (N,D), each object alone on the blank.

        Without gradients the latents go through in chunks: a thousand at once make
        feature maps of half a gigabyte that fall out of the CPU caches (docs/decisions.md,
        "Decoding in chunks")."""
        if torch.is_grad_enabled() or len(z) <= self.DECODE_CHUNK:
            return self.decoder(z)
        return torch.cat([self.decoder(chunk) for chunk in z.split(self.DECODE_CHUNK)])

    @torch.no_grad()
    def latent_sensitivity(self, z: Tensor, step: float = 1e-2) -> Tensor:
        """How much each latent moves the picture: the mean over latents z (N, D) of the squared
        pixel change per unit of latent d (D,), by finite differences through the decoder (the
        diagonal of the decoder's Gauss-Newton metric). Latent losses that weigh every latent
        alike match pixel losses only where these are about equal."""
        base = self.decode(z)
        moved = z[None].repeat(z.shape[1], 1, 1) + step * torch.eye(z.shape[1], dtype=z.dtype, device=z.device)[:, None]
        change = (self.decode(moved.flatten(0, 1)).unflatten(0, moved.shape[:2]) - base) / step
        return change.pow(2).flatten(2).sum(2).mean(1)

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
        inputs = torch.cat([batch.object_inputs, batch.background, self.blank()])
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
        object behind the background, where it gets no gradient. With `amodal` it leaves out
        the other objects' pixels: behind a wall the decoder may draw the whole object, which
        the composite then hides, so its latents can say where it is, not where its visible
        part is.
        """
        out, count = self.forward_batch(batch), len(batch.frames)
        scale = 0.5 / self.config.sigma ** 2
        error = (out["composite"] - batch.frames).pow(2)
        per_frame = scale * error.flatten(1).sum(1)
        object_nll = self.object_nll(out["objects"], batch)
        per_frame = per_frame + self.config.object_loss_weight * _sum_by(object_nll, batch.object_frame, count)
        background_error = batch.background_mask * (out["background"] - batch.background).pow(2)
        per_frame = per_frame + scale * background_error.flatten(1).sum(1)
        kl = kl_normal(out["mean"], out["std"])
        kl_objects, kl_background, kl_blank = kl.split([len(batch.objects), count, 1])
        per_frame = per_frame + self.config.beta * (_sum_by(kl_objects, batch.object_frame, count) + kl_background)
        blank_nll = scale * (out["blank"] - self.blank()).pow(2).sum() + self.config.beta * kl_blank.sum()
        mse = error.mean().detach()
        return {"loss": per_frame.mean() + blank_nll, "mse": mse, "kl": kl.mean().detach(),
                "psnr": 10 * torch.log10(4.0 / mse.clamp_min(1e-10))}

    def object_nll(self, pictures: Tensor, batch: PerceptionBatch) -> Tensor:
        """Per-object Gaussian NLL (M,) of decoded pictures against the masked object images;
        with `amodal`, not on the other objects' pixels, where the object may stand hidden."""
        error = (pictures - batch.objects).pow(2)
        if self.config.amodal:
            error = error * batch.object_known
        return 0.5 / self.config.sigma ** 2 * error.flatten(1).sum(1)

    def forward(self, batch: PerceptionBatch) -> dict[str, Tensor]:
        """The training objective (what DistributedDataParallel calls)."""
        return self.loss(batch)


def kl_normal(mean: Tensor, std: Tensor) -> Tensor:
    """KL(N(mean, std^2) || N(0, I)) summed over the last axis; std floored to avoid log(0)."""
    std = std.clamp_min(1e-6)
    return 0.5 * (mean.pow(2) + std.pow(2) - 1.0).sum(-1) - std.log().sum(-1)


def _sum_by(values: Tensor, index: Tensor, count: int) -> Tensor:
    """Sum `values` into `count` bins by `index` (per-object terms into their frames)."""
    return values.new_zeros(count).index_add(0, index, values)
