"""PhyDNet (Le Guen & Thome, CVPR 2020): a pixel-space video predictor, the paper's baseline.

A convolutional encoder maps each RGBD frame to a feature map; two recurrent branches run
on it: the PhyCell, whose physical predictor is an Euler step of a PDE-like operator built
from filters constrained to approximate spatial derivatives, followed by a Kalman-like
correction with the observed features; and a ConvLSTM for what the PDE cannot say. Their
states are decoded (each by its own head, then a shared decoder) into the next frame.

Moment constraint: the moment matrix of a k x k filter w (row index i, column index j,
centre c = (k-1)/2) is

    M[p, q] = sum_ij (i-c)^p / p!  (j-c)^q / q!  w[i, j]  =  (A w A^T)[p, q],
    A[p, i] = (i-c)^p / p!.

A Taylor expansion shows that a cross-correlation with w is sum_pq M[p, q] d^(p+q)/di^p dj^q
up to order k-1, so M = one-hot(p, q) makes w a finite-difference stencil of that
derivative. A is a Vandermonde matrix with distinct nodes, hence invertible, so
w = A^-1 T A^-T sets the moments to any target T exactly: that is `project_moments`. The
k^2 filters of the PhyCell are started there and trained with the moment loss towards
their one-hot targets, as in the paper.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor, nn

from ..domains import COUNT, NON_NEGATIVE, check_config, within
from ..errors import XvoeError
from .perception import normalise

__all__ = ["PhyDNetConfig", "PhyDNet", "widen_lstm_kernel", "PhyDNetObjective"]


@dataclass(frozen=True)
class PhyDNetConfig:
    """Every size of the network. Defaults are the CPU sizes (32x32 RGBD frames)."""

    image_size: int = within(32, COUNT)
    channels: int = within(4, COUNT)                               # RGBD
    # encoder: a stride-1 conv to the first width, then one stride-2 conv per further width;
    # the decoder mirrors it. The last width is the feature map the two branches work on: 16x16,
    # as in the original at 64x64 (docs/decisions.md, "The baselines' training")
    encoder_channels: tuple[int, ...] = within((16, 32), COUNT)
    phycell_kernel: int = within(7, COUNT)                         # k: k^2 derivative filters up to order k-1
    phycell_layers: int = within(1, COUNT)
    gain_kernel: int = within(3, COUNT)                            # the correction gain's convolution
    lstm_channels: tuple[int, ...] = within((32,), COUNT)          # ConvLSTM layers (the original: 128, 128, 64)
    # a ConvLSTM layer moves what it remembers by (kernel - 1) / 2 cells a frame: at 3, one cell
    # of the 16x16 map, slower than a cube falls behind a wall (~3 cells a frame); the original
    # reaches 3 with its 3 stacked layers (docs/decisions.md, "The baselines' training").
    # `widen_lstm_kernel` widens a trained network's gates
    lstm_kernel: int = within(3, COUNT)
    moment_weight: float = within(1.0, NON_NEGATIVE)                      # weight of the moment loss
    # extra weight, in the training loss only, of the pixels that change from one frame to the
    # next (the moving objects and what a wall uncovers: a few percent of a frame). 0 is the
    # published plain MSE; the surprise is the plain squared error whatever this is
    change_weight: float = within(0.0, NON_NEGATIVE)

    def __post_init__(self) -> None:
        check_config(self)      # each field in its domain before the relations between them are checked
        scale = 2 ** (len(self.encoder_channels) - 1)
        if not self.encoder_channels or self.image_size % scale:
            raise XvoeError(f"image_size {self.image_size} must be a multiple of {scale} "
                            f"(one halving per encoder width after the first: {self.encoder_channels})")
        if self.phycell_kernel < 1 or self.phycell_kernel % 2 == 0:
            raise XvoeError(f"phycell_kernel must be odd, not {self.phycell_kernel}")
        if not self.lstm_channels:
            raise XvoeError("lstm_channels needs at least one ConvLSTM layer")

    @property
    def feature_size(self) -> int:
        return self.image_size // 2 ** (len(self.encoder_channels) - 1)


# --- moments ---------------------------------------------------------------------------

def _moment_basis(k: int, dtype: torch.dtype = torch.float64) -> Tensor:
    """A (k, k) with A[p, i] = (i - c)^p / p!, so that the moments of w are A w A^T."""
    offsets = torch.arange(k, dtype=dtype) - (k - 1) / 2
    orders = torch.arange(k)
    factorials = torch.tensor([math.factorial(int(p)) for p in orders], dtype=dtype)
    return offsets[None, :] ** orders[:, None].to(dtype) / factorials[:, None]


def _kernel_moments(weights: Tensor) -> Tensor:
    """Moment matrices (..., k, k) of filters (..., k, k)."""
    basis = _moment_basis(weights.shape[-1], weights.dtype).to(weights.device)
    return basis @ weights @ basis.T


def _kernels_with_moments(moments: Tensor) -> Tensor:
    """The filters (..., k, k) whose moment matrices are exactly `moments` (..., k, k)."""
    inverse = torch.linalg.inv(_moment_basis(moments.shape[-1], torch.float64)).to(moments.device)
    return (inverse @ moments.double() @ inverse.T).to(moments.dtype)


def _derivative_targets(k: int) -> Tensor:
    """(k*k, k, k): target f = p*k + q is one-hot at (p, q): filter f ~ d^(p+q)/di^p dj^q."""
    return torch.eye(k * k).reshape(k * k, k, k)


# --- the cells ---------------------------------------------------------------------------

class _PhyCellLayer(nn.Module):
    """h~ = h + Phi(h) (physical predictor), then h = h~ + K * (x - h~) with K = sigmoid(conv[h~, x]).

    A gain in (0, 1), like a Kalman gain, keeps the corrected state between the prediction and
    the observation; a gain that may leave that range (tanh) lets the state grow from frame to
    frame, and training then diverges.
    """

    def __init__(self, channels: int, kernel: int, gain_kernel: int):
        super().__init__()
        filters = kernel * kernel
        self.derivatives = nn.Conv2d(channels, filters, kernel, padding=kernel // 2)
        self.norm = nn.GroupNorm(kernel, filters)        # one group per derivative order along i
        self.combine = nn.Conv2d(filters, channels, 1)    # Phi: a learned mix of the derivatives
        self.gain = nn.Conv2d(2 * channels, channels, gain_kernel, padding=gain_kernel // 2)

    def forward(self, observed: Tensor, state: Tensor) -> Tensor:
        predicted = state + self.combine(self.norm(self.derivatives(state)))
        gain = torch.sigmoid(self.gain(torch.cat([predicted, observed], dim=1)))
        return predicted + gain * (observed - predicted)


class _ConvLSTMCell(nn.Module):
    def __init__(self, inputs: int, hidden: int, kernel: int):
        super().__init__()
        self.hidden = hidden
        self.gates = nn.Conv2d(inputs + hidden, 4 * hidden, kernel, padding=kernel // 2)

    def forward(self, x: Tensor, state: tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor]:
        h, c = state
        i, f, o, g = self.gates(torch.cat([x, h], dim=1)).chunk(4, dim=1)
        c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
        return torch.sigmoid(o) * torch.tanh(c), c


def _conv_block(inputs: int, outputs: int, stride: int) -> nn.Sequential:
    # No normalisation in the encoder and decoder: a per-frame GroupNorm subtracts each feature
    # map's mean, and with it the colour of the floor and sky, which differs in every video.
    return nn.Sequential(nn.Conv2d(inputs, outputs, 3, stride=stride, padding=1), nn.LeakyReLU(0.2))


def _up_block(inputs: int, outputs: int) -> nn.Sequential:
    return nn.Sequential(nn.ConvTranspose2d(inputs, outputs, 4, stride=2, padding=1), nn.LeakyReLU(0.2))


class PhyDNet(nn.Module):
    """Encoder, PhyCell and ConvLSTM branches, decoder; next-frame prediction with teacher forcing."""

    def __init__(self, config: PhyDNetConfig):
        super().__init__()
        self.config = config
        widths = config.encoder_channels
        self.encoder = nn.Sequential(_conv_block(config.channels, widths[0], 1),
                                     *(_conv_block(a, b, 2) for a, b in zip(widths, widths[1:])))
        features = widths[-1]
        self.encode_physics = _conv_block(features, features, 1)
        self.encode_residual = _conv_block(features, features, 1)
        self.phycell = nn.ModuleList(_PhyCellLayer(features, config.phycell_kernel, config.gain_kernel)
                                     for _ in range(config.phycell_layers))
        sizes = (features, *config.lstm_channels)
        self.lstm = nn.ModuleList(_ConvLSTMCell(a, b, config.lstm_kernel) for a, b in zip(sizes, sizes[1:]))
        self.decode_physics = _conv_block(features, features, 1)
        self.decode_residual = _conv_block(config.lstm_channels[-1], features, 1)
        self.decoder = nn.Sequential(*(_up_block(a, b) for a, b in zip(widths[::-1], widths[-2::-1])),
                                     nn.Conv2d(widths[0], config.channels, 3, padding=1))
        self.register_buffer("moment_targets", _derivative_targets(config.phycell_kernel), persistent=False)
        self.project_moments()

    # moments of the PhyCell filters
    def filters(self) -> list[Tensor]:
        """The derivative filters of each PhyCell layer: (k*k, channels, k, k)."""
        return [layer.derivatives.weight for layer in self.phycell]

    def moments(self) -> list[Tensor]:
        """Their moment matrices (k*k, channels, k, k), to compare with `moment_targets`."""
        return [_kernel_moments(weight) for weight in self.filters()]

    @torch.no_grad()
    def project_moments(self) -> None:
        """Set every PhyCell filter to the stencil whose moments are exactly its one-hot target."""
        stencils = _kernels_with_moments(self.moment_targets)
        for weight in self.filters():
            weight.copy_(stencils[:, None].expand_as(weight))

    def moment_loss(self) -> Tensor:
        """Mean squared distance of the filters' moment matrices to their targets."""
        targets = self.moment_targets[:, None]
        return torch.stack([(m - targets).pow(2).mean() for m in self.moments()]).mean()

    # prediction
    def forward(self, frames: Tensor) -> Tensor:
        """frames (B, T, C, H, W) in [-1, 1] -> predictions (B, T-1, C, H, W) of frames 1..T-1,
        the one of frame t+1 made from frames 0..t only."""
        batch, steps = frames.shape[:2]
        if frames.shape[2:] != (self.config.channels, self.config.image_size, self.config.image_size):
            raise XvoeError(f"PhyDNet expects frames (B, T, {self.config.channels}, {self.config.image_size}, "
                            f"{self.config.image_size}), not {tuple(frames.shape)}")
        encoded = self.encoder(frames[:, :-1].flatten(0, 1))
        physics_in = self.encode_physics(encoded).unflatten(0, (batch, steps - 1))
        residual_in = self.encode_residual(encoded).unflatten(0, (batch, steps - 1))
        physics, residual = self._recur(physics_in, residual_in)
        mixed = self.decode_physics(physics.flatten(0, 1)) + self.decode_residual(residual.flatten(0, 1))
        return self.decoder(mixed).unflatten(0, (batch, steps - 1))

    def _recur(self, physics_in: Tensor, residual_in: Tensor) -> tuple[Tensor, Tensor]:
        """Run both branches over time; their top states (B, T-1, ·, h, w) after each observed frame."""
        physics_states = [torch.zeros_like(physics_in[:, 0]) for _ in self.phycell]
        lstm_states = [(residual_in.new_zeros(len(residual_in), cell.hidden, *residual_in.shape[-2:]),) * 2
                       for cell in self.lstm]
        physics_out, residual_out = [], []
        for t in range(physics_in.shape[1]):
            x = physics_in[:, t]
            for i, layer in enumerate(self.phycell):
                x = physics_states[i] = layer(x, physics_states[i])
            physics_out.append(x)
            x = residual_in[:, t]
            for i, cell in enumerate(self.lstm):
                lstm_states[i] = cell(x, lstm_states[i])
                x = lstm_states[i][0]
            residual_out.append(x)
        return torch.stack(physics_out, 1), torch.stack(residual_out, 1)

    def squared_error(self, frames: Tensor) -> Tensor:
        """(B, T-1, C, H, W): the squared one-step prediction error of frames 1..T-1, which both
        the training loss and the surprise are made of."""
        return (self(frames) - frames[:, 1:]).pow(2)

    def loss(self, frames: Tensor) -> dict[str, Tensor]:
        """Training terms: next-frame MSE over frames 1..T-1 (weighted towards the pixels that
        change if `change_weight` > 0) plus the weighted moment loss; `prediction` is the plain MSE."""
        error = self.squared_error(frames)
        prediction = error.mean()
        fitted = prediction
        if self.config.change_weight > 0:
            weight = 1 + self.config.change_weight * _change_mask(frames)
            fitted = (weight * error).sum() / (weight.sum() * error.shape[2])
        moment = self.moment_loss()
        return {"loss": fitted + self.config.moment_weight * moment, "prediction": prediction,
                "moment": moment}

    @torch.no_grad()
    def surprise(self, frames: Tensor) -> Tensor:
        """Per-frame surprise (B, T): sum over pixels and channels of the squared one-step
        prediction error; 0 at frame 0, which nothing predicts."""
        error = self.squared_error(frames).flatten(2).sum(2)
        return torch.cat([error.new_zeros(len(error), 1), error], dim=1)


@torch.no_grad()
def widen_lstm_kernel(net: PhyDNet, kernel: int) -> PhyDNet:
    """A copy of `net` whose ConvLSTM gates have `kernel` x `kernel` filters, the trained ones in
    the centre and zeros around: the same predictions, but room to learn to carry what it
    remembers further per frame (a 3x3 ConvLSTM on the 16x16 map moves a memory one cell a
    frame; a cube falling behind a wall moves three)."""
    old = net.config.lstm_kernel
    if kernel < old or kernel % 2 == 0:
        raise XvoeError(f"the ConvLSTM kernel can only widen to a larger odd size, not {old} -> {kernel}")
    wider = PhyDNet(replace(net.config, lstm_kernel=kernel))
    state = net.state_dict()
    pad = (kernel - old) // 2
    for i, _ in enumerate(net.lstm):
        name = f"lstm.{i}.gates.weight"
        state[name] = nn.functional.pad(state[name], (pad,) * 4)
    wider.load_state_dict(state)
    return wider.train(net.training)


def _change_mask(frames: Tensor, threshold: float = 2 / 255) -> Tensor:
    """(B, T-1, 1, H, W): 1 where any channel of frame t+1 differs from frame t by more than the
    threshold, else 0. Frames are in [-1, 1], so 2/255 is one uint8 level (a change of exactly one
    level may fall on either side of it in float32; two levels or more always count)."""
    return ((frames[:, 1:] - frames[:, :-1]).abs().amax(dim=2, keepdim=True) > threshold).to(frames.dtype)


class PhyDNetObjective(nn.Module):
    """What the training loop calls: uint8 videos (B, T, H, W, C) in, the loss terms out."""

    def __init__(self, net: PhyDNet):
        super().__init__()
        self.net = net

    def forward(self, videos: Tensor) -> dict[str, Tensor]:
        return self.net.loss(normalise(videos))
