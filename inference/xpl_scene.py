"""The learned scene of one video, for the Pyro model: XPL's decoder, compositor and dynamics.

The latents of what is seen are fixed (Transformer 1's refined latents); one never-seen slot
is left free for a hidden object. Rendering decodes the hidden object's latents and
composites them with the fixed slots and the background; its dynamics are XPL's, run with
the particle's trajectory in the free slot so the hidden object interacts with the others.
The seen objects' own motion is evidence too: their latents in the frames the encoder saw them
are observed under the dynamics' one-step prediction (the model's `motion_t` sites), so a hidden
object that explains a ball bouncing back raises the likelihood. Transformer 1's fills of the other
frames feed the dynamics' history but are not observations: they are the model's guesses, made
without the hidden object, and scoring them as data counted that guess against it.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from xvoe.models.dynamics import DynamicsState
from xvoe.models.perception import ComponentVAE
from xvoe.models.slots import push_behind, scene_layers
from xvoe.models.xpl import XPL

from .model import Drawing, Step


class XPLScene(nn.Module):
    def __init__(self, vae: ComponentVAE, xpl: XPL, refined: Tensor, background: Tensor, visible: Tensor,
                 occluder: Tensor, hidden: int):
        """refined: (T, K, D) latents; background: (T, 4, H, W) decoded background; visible:
        (T, K) what the encoder saw; occluder: (K,) the walls, whose motion is no evidence;
        hidden: the slot a hidden object would take (a never-seen one). As in the MSE score
        (xvoe.models.slots.scene_layers), a wall is drawn only where it was seen, and an object not seen
        in a frame stands behind the walls there: the seen objects' fills, and the hidden object
        in every frame."""
        super().__init__()
        self.vae, self.xpl, self.hidden = vae, xpl, hidden
        self.frames, self.slots, self.dim = refined.shape
        self.register_buffer("refined", refined)
        self.register_buffer("background", background)
        occupied = visible.any(0)
        with torch.no_grad():   # (T, K, 4, H, W); the free slot, never seen, stays blank
            layers, walls = scene_layers(vae, refined[None], occupied[None], visible[None], occluder[None])
            self.register_buffer("layers", layers[0])
            self.register_buffer("walls", walls[0, :, 0])   # (T, 1, H, W)
        self.register_buffer("moving", occupied & ~occluder)
        self.register_buffer("occluder", occluder[None])      # (1, K)
        self.register_buffer("visible", visible)
        with torch.no_grad():
            self._fixed = self._partial_composite()
            self._empty = self._composite(self.layers[None])[0]
            # every particle without a hidden object sees the encoder's scene: its dynamics run once, fused
            self._empty_steps = xpl.predict(refined[None], self.occluder)[0]          # (T-1, K, D)

    def initial(self, particles: int) -> tuple[Tensor, Tensor]:
        """The latent prior of the perception module, N(0, I)."""
        zeros = self.refined.new_zeros(particles, self.dim)
        return zeros, torch.ones_like(zeros)

    def advance(self, t: int, latents: Tensor, alive: Tensor, memory: DynamicsState | None) -> Step:
        """The dynamics run on frame t with the hidden slot holding each particle's latents (N, D)
        where it holds an object, and elsewhere what the encoder made of that slot's empty
        pixels, as during training: the next latent of the hidden slot and of the seen moving
        ones. The dynamics' memory is that of the particles holding an object, in their order,
        carried and resampled with them; the others share the scene's one run."""
        prediction = self._empty_steps[t].expand(len(latents), self.slots, self.dim).clone()
        if alive.any():
            scene = self.refined[t].expand(int(alive.sum()), self.slots, self.dim).clone()
            scene[:, self.hidden] = latents[alive]
            prediction[alive], memory = self.xpl.dynamics.step(scene, memory, self.inert())
        return Step(prediction[:, self.hidden], memory, prediction[:, self.moving])

    def seen_motion(self, t: int) -> tuple[Tensor, Tensor]:
        """The seen moving objects' refined latents (M, D) at frame t and which of them the
        encoder saw (M,): the data. Transformer 1's fills of the other frames feed the dynamics'
        history but are not observed."""
        return self.refined[t, self.moving], self.visible[t, self.moving]

    def select(self, memory: DynamicsState | None, index: Tensor) -> DynamicsState | None:
        """The dynamics' memory of the particles `index`: its tensors hold one row per slot."""
        if memory is None:
            return None

        def pick(tensor: Tensor) -> Tensor:
            return tensor.reshape(-1, self.slots, *tensor.shape[1:])[index].reshape(-1, *tensor.shape[1:])

        return type(memory)(*(pick(part) for part in memory))

    def inert(self) -> Tensor | None:
        """The slots whose effect the dynamics leave out (XPLConfig.inert_walls): the walls."""
        return self.occluder if self.xpl.config.inert_walls else None

    def empty(self) -> Tensor:
        """Expected frames (T, 4, H, W) without a hidden object."""
        return self._empty

    def empty_frame(self, t: int) -> Tensor:
        return self._empty[t]

    def draw_frame(self, t: int, latents: Tensor) -> Drawing:
        """Frame t (M, 4, H, W) with the hidden object at each of the latents (M, D)."""
        return self.draw_frames(latents, torch.full((len(latents),), t, dtype=torch.long, device=latents.device))

    def draw_frames(self, latents: Tensor, frames: Tensor) -> Drawing:
        """Expected frames (F, 4, H, W) at the frame indices `frames` (F,) with the hidden
        object's latents there (F, D), its exposure (F,): how many pixels it holds in front of
        everything else, where the encoder would have seen it, and its area (F,). Only the
        hidden latents are decoded, and added to the softmax the fixed layers left
        (`_partial_composite`)."""
        pictures = self.vae.decode(latents)
        return Drawing(*self._composite_hidden(push_behind(pictures, self.walls[frames]), frames),
                       self.area(pictures, frames))

    def area(self, pictures: Tensor, frames: Tensor | slice = slice(None)) -> Tensor:
        """Pixels (B, T) that pictures (B, T, 4, H, W) of the hidden slot draw in front of the
        background, before the walls push them back: the compositor's share of each pixel
        between the picture and the background alone. An object has its size here wherever it
        is in the picture; a latent that decodes to the blank has almost none."""
        own = self.vae.composite_logits(pictures)
        return torch.sigmoid(own - self.vae.composite_logits(self.background[frames])).sum(dim=(-3, -2, -1))

    def _composite(self, layers: Tensor) -> Tensor:
        """Frames (B, T, 4, H, W) of slot pictures (B, T, K, 4, H, W) over the background."""
        background = self.background.expand(len(layers), *self.background.shape)[:, :, None]
        return self.vae.composite(torch.cat([background, layers], dim=2))

    def _partial_composite(self) -> tuple[Tensor, Tensor, Tensor]:
        """The compositor's softmax over the background and every slot but the hidden one,
        unnormalised: its per-pixel largest logit, sum of weights and weighted sum of pictures
        (T, [4 or 1], H, W). A particle's picture of the hidden slot then costs one more term,
        not a softmax over all slots."""
        others = [k for k in range(self.slots) if k != self.hidden]
        layers = torch.cat([self.background[:, None], self.layers[:, others]], dim=1)     # (T, S, 4, H, W)
        logits = self.vae.composite_logits(layers)
        top = logits.max(dim=1).values
        weights = torch.exp(logits - top[:, None])
        return top, weights.sum(dim=1), (weights * layers).sum(dim=1)

    def _composite_hidden(self, pictures: Tensor, frames: Tensor | slice = slice(None)) -> tuple[Tensor, Tensor]:
        """Frames (B, T, 4, H, W) with the hidden slot's pictures (B, T, 4, H, W): the same
        softmax as `_composite`, finished from the fixed layers' partial sums; `frames` picks
        the frames the pictures are of. Also the hidden slot's exposure (B, T): its share of
        the softmax summed over the pixels (about 1 where it is nearest, 0 behind a wall)."""
        top, total, weighted = (part[frames] for part in self._fixed)
        logits = self.vae.composite_logits(pictures)
        peak = torch.maximum(top, logits)
        fixed, own = torch.exp(top - peak), torch.exp(logits - peak)
        normaliser = total * fixed + own
        exposure = (own / normaliser).sum(dim=(-3, -2, -1))
        return (weighted * fixed + pictures * own) / normaliser, exposure
