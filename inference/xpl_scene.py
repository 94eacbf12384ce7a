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
from xvoe.models.slots import push_behind
from xvoe.models.xpl import XPL

from .decoder import FoldedDecoder
from .identity import Identity
from .model import Drawing, Step

__all__ = ["XPLScene"]


class XPLScene(nn.Module):
    def __init__(self, vae: ComponentVAE, xpl: XPL, refined: Tensor, background: Tensor, visible: Tensor,
                 occluder: Tensor, hidden: int, layers: Tensor, walls: Tensor, identity: Identity | None = None):
        """refined: (V, T, K, D) latents of each of the scene's V explanations of what was seen
        (one object, or two identical ones: `inference.identity`), a particle's `version` picking
        one; background: (T, 4, H, W) decoded background; visible: (V, T, K) what each says the
        encoder saw; occluder: (K,) the walls, whose motion is no evidence; hidden: the slot a
        hidden object would take (a never-seen one); layers: the slot pictures (V, T, K, 4, H, W)
        of `refined` as the MSE score draws them (`xvoe.models.slots.scene_layers`: a wall drawn
        only where it was seen, and an object not seen in a frame behind the walls there: the
        seen objects' fills, and the hidden object in every frame), the free slot blank; walls:
        the nearest wall's depth (T, 1, H, W) in them, the same in every version (`nearest_wall`);
        identity: which seen object the second version makes two, None where there is none."""
        super().__init__()
        self.vae, self.xpl, self.hidden, self.identity = vae, xpl, hidden, identity
        self.decode = FoldedDecoder(vae)      # the hidden slot's pictures, drawn for every particle
        self.versions, self.frames, self.slots, self.dim = refined.shape
        self.register_buffer("refined", refined)
        self.register_buffer("background", background)
        self.register_buffer("layers", layers)
        self.register_buffer("walls", walls)
        occupied = visible.any(1)
        wall_slots = occluder.expand(self.versions, -1)
        self.register_buffer("moving", occupied.any(0) & ~occluder)
        # the slots whose next latent is read (the hidden one and the seen moving ones): the dynamics step only them
        stepped = self.moving.clone()
        stepped[hidden] = True
        self.register_buffer("stepped", stepped.nonzero()[:, 0])
        self.register_buffer("occluder", occluder[None])      # (1, K)
        self.register_buffer("visible", visible)
        self.register_buffer("first_sighting", visible & (visible.cumsum(dim=1) == 1))
        with torch.no_grad():
            self._fixed = self._partial_composite()
            self._empty = self._composite(self.layers)
            # every particle without a hidden object sees its version's scene: its dynamics run once, fused
            self._empty_steps = xpl.predict(refined, wall_slots)     # (V, T-1, K, D)

    def initial(self, particles: int) -> tuple[Tensor, Tensor]:
        """The latent prior of the perception module, N(0, I)."""
        zeros = self.refined.new_zeros(particles, self.dim)
        return zeros, torch.ones_like(zeros)

    def advance(self, t: int, latents: Tensor, alive: Tensor, version: Tensor, memory: DynamicsState | None) -> Step:
        """The dynamics run on frame t of each particle's version of the scene with the hidden
        slot holding its latents (N, D) where it holds an object, and elsewhere what the encoder
        made of that slot's empty pixels, as during training: the next latent of the hidden slot
        and of the seen moving ones. The dynamics' memory is that of the particles holding an
        object, in their order, carried and resampled with them; the others share their
        version's one run."""
        prediction = self._empty_steps[version, t]
        if alive.any():
            scene = self.refined[version[alive], t]
            scene[:, self.hidden] = latents[alive]
            stepped, memory = self.xpl.dynamics.step(scene, memory, self.inert(), self.stepped)
            prediction[alive.nonzero(), self.stepped] = stepped
        return Step(prediction[:, self.hidden], memory, prediction[:, self.moving])

    def seen_motion(self, t: int) -> tuple[Tensor, Tensor, Tensor]:
        """The seen moving objects' refined latents (V, M, D) at frame t, which of them the encoder
        saw (V, M), and which it saw for the first time (V, M), in each version: the data.
        Transformer 1's fills of the other frames feed the dynamics' history but are not observed."""
        return tuple(part[:, t][:, self.moving] for part in (self.refined, self.visible, self.first_sighting))

    def select(self, memory: DynamicsState | None, index: Tensor) -> DynamicsState | None:
        """The dynamics' memory of the particles `index`: its tensors hold one row per stepped slot."""
        if memory is None:
            return None
        rows = len(self.stepped)

        def pick(tensor: Tensor) -> Tensor:
            return tensor.reshape(-1, rows, *tensor.shape[1:])[index].reshape(-1, *tensor.shape[1:])

        return type(memory)(*(pick(part) for part in memory))

    def inert(self) -> Tensor | None:
        """The slots whose effect the dynamics leave out (XPLConfig.inert_walls): the walls."""
        return self.occluder if self.xpl.config.inert_walls else None

    def empty(self, version: int = 0) -> Tensor:
        """Expected frames (T, 4, H, W) of one version without a hidden object."""
        return self._empty[version]

    def empty_frame(self, t: int) -> Tensor:
        """Frame t of every version (V, 4, H, W) without a hidden object."""
        return self._empty[:, t]

    def draw_frame(self, t: int, latents: Tensor, version: Tensor) -> Drawing:
        """Frame t (M, 4, H, W) of each particle's version with the hidden object at each of
        the latents (M, D)."""
        return self.draw_frames(latents, torch.full((len(latents),), t, dtype=torch.long, device=latents.device),
                                version)

    def draw_frames(self, latents: Tensor, frames: Tensor, version: Tensor | None = None) -> Drawing:
        """Expected frames (F, 4, H, W) at the frame indices `frames` (F,) of the versions
        `version` (F,; None: the first) with the hidden object's latents there (F, D), its
        exposure (F,): how many pixels it holds in front of everything else, where the encoder
        would have seen it, and its area (F,). Only the hidden latents are decoded, and added to
        the softmax the fixed layers left (`_partial_composite`)."""
        pictures = self.decode(latents)
        version = torch.zeros_like(frames) if version is None else version
        return Drawing(*self._composite_hidden(push_behind(pictures, self.walls[frames]), frames, version),
                       self.area(pictures, frames))

    def area(self, pictures: Tensor, frames: Tensor | slice = slice(None)) -> Tensor:
        """Pixels (B, T) that pictures (B, T, 4, H, W) of the hidden slot draw in front of the
        background, before the walls push them back: the compositor's share of each pixel
        between the picture and the background alone. An object has its size here wherever it
        is in the picture; a latent that decodes to the blank has almost none."""
        own = self.vae.composite_logits(pictures)
        return torch.sigmoid(own - self.vae.composite_logits(self.background[frames])).sum(dim=(-3, -2, -1))

    def _composite(self, layers: Tensor) -> Tensor:
        """Frames (V, T, 4, H, W) of slot pictures (V, T, K, 4, H, W) over the background."""
        background = self.background.expand(len(layers), *self.background.shape)[:, :, None]
        return self.vae.composite(torch.cat([background, layers], dim=2))

    def _partial_composite(self) -> tuple[Tensor, Tensor, Tensor]:
        """The compositor's softmax over the background and every slot but the hidden one,
        unnormalised, in each version: its per-pixel largest logit, sum of weights and weighted
        sum of pictures (V, T, [4 or 1], H, W). A particle's picture of the hidden slot then costs
        one more term, not a softmax over all slots."""
        others = [k for k in range(self.slots) if k != self.hidden]
        background = self.background.expand(self.versions, *self.background.shape)[:, :, None]
        layers = torch.cat([background, self.layers[:, :, others]], dim=2)     # (V, T, S, 4, H, W)
        logits = self.vae.composite_logits(layers)
        top = logits.max(dim=2).values
        weights = torch.exp(logits - top[:, :, None])
        return top, weights.sum(dim=2), (weights * layers).sum(dim=2)

    def _composite_hidden(self, pictures: Tensor, frames: Tensor, version: Tensor) -> tuple[Tensor, Tensor]:
        """Frames (F, 4, H, W) with the hidden slot's pictures (F, 4, H, W): the same softmax
        as `_composite`, finished from the fixed layers' partial sums; `frames` and `version`
        (F,) pick the frame and version each picture is of. Also the hidden slot's exposure
        (F,): its share of the softmax summed over the pixels (about 1 where it is nearest, 0
        behind a wall)."""
        top, total, weighted = (part[version, frames] for part in self._fixed)
        logits = self.vae.composite_logits(pictures)
        peak = torch.maximum(top, logits)
        fixed, own = torch.exp(top - peak), torch.exp(logits - peak)
        normaliser = total * fixed + own
        exposure = (own / normaliser).sum(dim=(-3, -2, -1))
        return (weighted * fixed + pictures * own) / normaliser, exposure
