"""The perception's decoder rewritten for the NLL's many small decodes: the same function, its
sums in another order, so its pictures agree with `ComponentVAE.decode`'s to float rounding.

The SMC decodes every particle's latent at every frame (no two particles ever hold the same
one), and the decoder is the largest part of a score's time. Two of its parts cost more than
they need:

- Up to the first ReLU the broadcast decoder is affine in the latent (a projection tiled on a
  grid, a position embedding added, a transposed convolution), so that part is one matrix
  (D -> C x 2g x 2g) and one constant picture, taken from the weights once per scene.
- The last convolution has four output channels, too few for the CPU's convolution kernels: as
  one matrix product of every tap's channel mix, then the k x k shifted sums, it runs faster.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from xvoe.models.perception import BroadcastDecoder, ComponentVAE

__all__ = ["FoldedDecoder"]


class FoldedDecoder:
    """`vae.decode` with its first layer folded into a matrix and its last one a matrix product,
    where no gradient is taken (the SMC's draws). Under autograd (the proposal's refinement, 15
    latents a step), and for a decoder of another shape (no transposed convolution, or a last
    layer that is not a stride-1 'same' convolution), the decoder runs as it is: its backward
    took half the time of this one's."""

    def __init__(self, vae: ComponentVAE):
        self.vae, decoder = vae, vae.decoder
        self.chunk = vae.DECODE_CHUNK
        self.folded = _foldable(decoder)
        if not self.folded:
            return
        first = decoder.convs[0]
        with torch.no_grad():
            grid = decoder.position(decoder.coords).permute(2, 0, 1)                     # (C, g, g)
            constant = first(grid[None] + decoder.project.bias[:, None, None])           # (1, C, 2g, 2g)
            basis = decoder.project.weight.T[:, :, None, None].expand(-1, -1, *grid.shape[1:])  # (D, C, g, g)
            linear = F.conv_transpose2d(basis.contiguous(), first.weight, None, first.stride, first.padding,
                                        first.output_padding)                            # (D, C, 2g, 2g)
        # held channels-last: the transposed convolutions that follow run twice as fast on such maps
        # (the decoder's own broadcast sum makes them so too)
        self.shape = constant.shape[1:]
        self.constant, self.linear = (part.permute(0, 2, 3, 1).flatten(1) for part in (constant, linear))
        self.middle = list(decoder.convs[1:])
        out = decoder.out
        size, channels = out.kernel_size[0], out.out_channels
        # (k * k * C_out, C_in): every tap's channel mix, tap-major
        self.taps = out.weight.detach().permute(2, 3, 0, 1).reshape(size * size * channels, -1)
        self.bias, self.size = out.bias.detach(), size

    def __call__(self, z: Tensor) -> Tensor:
        """RGBD pictures (N, 4, H, W) of latents (N, D), as `ComponentVAE.decode` draws them."""
        if not self.folded or torch.is_grad_enabled():     # the decoder's own backward is the faster one
            return self.vae.decode(z)
        return torch.cat([self._decode(part) for part in z.split(self.chunk)])

    def _decode(self, z: Tensor) -> Tensor:
        channels, height, width = self.shape
        features = torch.addmm(self.constant, z, self.linear).view(len(z), height, width, channels).permute(0, 3, 1, 2)
        for layer in self.middle:
            features = torch.relu_(features) if isinstance(layer, nn.ReLU) else layer(features)
        return self._last(features)

    def _last(self, features: Tensor) -> Tensor:
        """The k x k 'same' convolution to RGBD: each tap's channel mix in one product, then each
        tap's picture shifted onto the output."""
        batch, _, height, width = features.shape
        size, half = self.size, self.size // 2
        mixed = torch.matmul(self.taps, features.flatten(2)).view(batch, size, size, -1, height, width)
        out = self.bias.view(1, -1, 1, 1).expand(batch, -1, height, width).clone()
        for ky in range(size):
            for kx in range(size):
                dy, dx = ky - half, kx - half
                top, bottom, left, right = max(0, -dy), height - max(0, dy), max(0, -dx), width - max(0, dx)
                out[:, :, top:bottom, left:right] += mixed[:, ky, kx, :, top + dy:bottom + dy, left + dx:right + dx]
        return out


def _foldable(decoder: BroadcastDecoder) -> bool:
    """Whether the decoder has the shape `FoldedDecoder` rewrites."""
    out = decoder.out
    return (len(decoder.convs) > 0 and isinstance(decoder.convs[0], nn.ConvTranspose2d)
            and out.kernel_size[0] == out.kernel_size[1] and out.kernel_size[0] % 2 == 1
            and out.stride == (1, 1) and out.dilation == (1, 1) and out.groups == 1
            and out.padding == (out.kernel_size[0] // 2,) * 2 and out.bias is not None)
