"""Sizes of every network and training run, grouped into named presets.

A `Preset` holds one config per stage; the perception stage is here now and the later
stages add their own fields to the same `Preset`. Every size a network uses is a field of
one of these dataclasses, so a checkpoint that stores its config can rebuild its model.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, is_dataclass, replace
from typing import Any

from ..errors import XvoeError
from .dynamics import DynamicsConfig
from .phydnet import PhyDNetConfig
from .reasoning import ReasoningConfig
from .xpl import XPLConfig

__all__ = ["DynamicsConfig", "PhyDNetConfig", "ReasoningConfig", "XPLConfig"]   # nested configs that from_dict rebuilds


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


@dataclass(frozen=True)
class TrainConfig:
    """One training run of one stage: the shared loop reads only these fields."""

    steps: int = 6000
    batch_size: int = 32            # frames per step, summed over all processes
    lr: float = 1e-3
    warmup_steps: int = 200         # linear warm-up of the learning rate
    decay_steps: int = 5000         # the learning rate halves every decay_steps after warm-up
    grad_clip: float = 0.0          # clip the gradient norm to this (0 = no clipping)
    seed: int = 0
    checkpoint_minutes: float = 3.0  # a checkpoint is written at least this often
    log_every: int = 10             # steps between rows of the loss CSV
    max_minutes: float = 0.0        # stop early after this much training time (0 = no limit)
    max_videos: int = 0             # videos of the data file to load (0 = all)
    data_shards: int = 0            # slices of the file that each feed batch_size/data_shards frames
                                    # per step; 0 = the number of processes of the first launch
    threads: int = 0                # torch threads per process (0 = cores / processes)
    # this share of each batch comes from the training videos of `focus_group` that have a wall
    # (e.g. permanence, where cubes must be remembered behind it; several: permanence,continuity);
    # 0 = uniform. PhyDNet, and the XPL and PLATO stages (through the split file the latent cache
    # was encoded from)
    focus_group: str = ""
    focus_share: float = 0.0


@dataclass(frozen=True)
class Preset:
    """Everything needed to build and train the model at one scale."""

    name: str
    perception: PerceptionConfig = field(default_factory=PerceptionConfig)
    perception_train: TrainConfig = field(default_factory=TrainConfig)
    xpl: XPLConfig = field(default_factory=XPLConfig)
    # about 6 minutes on 2 cores (0.25 s a step)
    xpl_train: TrainConfig = field(default_factory=lambda: TrainConfig(steps=1500, batch_size=32, warmup_steps=100,
                                                                       decay_steps=1000))
    # Transformer 2 and the existence head trained further on hidden objects (the proposal stage);
    # about 0.1 s a step on one core
    proposal_train: TrainConfig = field(default_factory=lambda: TrainConfig(steps=4000, batch_size=32,
                                                                            warmup_steps=100, decay_steps=1500))
    # the PLATO baseline's training (None: xpl_train's). Without Transformer 1 it predicts the
    # raw latents directly, and every visible object costs its prediction error in every frame:
    # trained no longer than XPL, that cost outweighs the violations of the predictive settings
    plato_train: TrainConfig | None = None
    # the PhyDNet baseline: batch_size counts videos; ~4-5 minutes on one CPU thread
    phydnet: PhyDNetConfig = field(default_factory=PhyDNetConfig)
    phydnet_train: TrainConfig = field(default_factory=lambda: TrainConfig(steps=300, batch_size=8, lr=3e-3,
                                                                           warmup_steps=20, decay_steps=300))


PRESETS: dict[str, Preset] = {
    # 2 CPU cores: 32x32 frames, a small CNN encoder and a light decoder. Each object's position is two
    # latents the decoder draws from (found whole behind walls: amodal, cut_share), and the later
    # stages weigh each latent by how much it moves the picture; walls are inert in the dynamics
    # (docs/results.md).
    "cpu": Preset(
        name="cpu",
        perception=PerceptionConfig(where_latents=True, amodal=True, cut_share=0.25),
        xpl=XPLConfig(weigh_by_picture=True, inert_walls=True),
    ),
    # The cpu preset before where latents: the whole latent broadcast, every latent weighed alike;
    # walls inert in the dynamics, Transformer 1 trained by the refill loss alone, its fills of
    # objects outside the picture included, and the XPL stage (xpl-noresidual too) trained 8 times
    # as long as in cpu: with the last two, collision S3 rose from 65 to 99 (docs/results.md). The
    # shipped models were trained with it (their checkpoints hold the full config).
    "cpu-broadcast": Preset(
        name="cpu-broadcast",
        perception=PerceptionConfig(),
        xpl=XPLConfig(inert_walls=True, stop_input_gradient=True, outside_refill=True),
        xpl_train=TrainConfig(steps=12_000, batch_size=32, warmup_steps=100, decay_steps=8000),
        # the shipped PLATO: trained 5x as long as XPL, its predictive accuracy reaches 97-100% in
        # three scenarios and 89% in continuity (3,000 steps: 3-57%); about 100 minutes on one core
        # (docs/results.md)
        plato_train=TrainConfig(steps=60_000, batch_size=32, warmup_steps=100, decay_steps=15_000),
        # the shipped PhyDNet: the changing pixels weighed 21 times in its training loss, 25 times the
        # cpu preset's steps; predictive 90-99.5% in three scenarios (300 plain steps: 0-48.5%); about
        # 2 hours on two threads (docs/results.md; the shipped run stopped at 7,479 steps, its time limit)
        phydnet=PhyDNetConfig(change_weight=20.0),
        phydnet_train=TrainConfig(steps=7500, batch_size=8, lr=2e-3, warmup_steps=100, decay_steps=2500),
    ),
    # The paper's sizes (appendix tables): 128x128, ViT encoder, D=32, 64-channel decoder; for GPUs.
    "paper": Preset(
        name="paper",
        perception=PerceptionConfig(image_size=128, latent_dim=32, encoder="vit", decoder_channels=64,
                                    decoder_extra_convs=1),
        xpl=XPLConfig(reasoning=ReasoningConfig(latent_dim=32, width=256, layers=6, heads=8, mlp=256),
                      dynamics=DynamicsConfig(latent_dim=32, hidden=512, mlp_layers=3, lstm=2056, buffer_heads=8)),
        xpl_train=TrainConfig(steps=32_000, batch_size=500, warmup_steps=1000, decay_steps=10_000,
                              checkpoint_minutes=10.0, log_every=100),
        proposal_train=TrainConfig(steps=32_000, batch_size=500, warmup_steps=1000, decay_steps=10_000,
                                   checkpoint_minutes=10.0, log_every=100),
        perception_train=TrainConfig(steps=472_000, batch_size=36, lr=4e-4, warmup_steps=2000,
                                     decay_steps=100_000, checkpoint_minutes=10.0, log_every=100),
        # the original's sizes (64x64 -> 16x16 features, ConvLSTM 128-128-64), one more halving at 128x128;
        # the paper's training table: 100 videos per batch, 70,000 steps, Adam, lr 0.001
        phydnet=PhyDNetConfig(image_size=128, encoder_channels=(16, 32, 64, 64), lstm_channels=(128, 128, 64)),
        phydnet_train=TrainConfig(steps=70_000, batch_size=100, lr=1e-3, warmup_steps=0, decay_steps=10**9,
                                  checkpoint_minutes=10.0, log_every=100),
    ),
}


def preset(name: str) -> Preset:
    """The named preset, or a one-line error listing the known ones."""
    if name not in PRESETS:
        raise XvoeError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    return PRESETS[name]


def to_dict(config: Any) -> dict:
    """A dataclass config as plain JSON-able data (tuples become lists)."""
    return asdict(config)


def from_dict(cls: type, data: dict) -> Any:
    """Rebuild a (possibly nested) config dataclass from `to_dict` output; unknown keys are an error."""
    known = {f.name: f for f in fields(cls)}
    unknown = set(data) - set(known)
    if unknown:
        raise XvoeError(f"{cls.__name__} has no field(s) {', '.join(sorted(unknown))}")
    values = {}
    for name, value in data.items():
        kind = known[name].type
        target = _dataclass_named(cls, kind)
        if target is not None and isinstance(value, dict):
            value = from_dict(target, value)
        elif isinstance(value, list):
            value = tuple(value)
        values[name] = value
    return cls(**values)


def _dataclass_named(owner: type, annotation: Any) -> type | None:
    """The config dataclass an annotation (a string under postponed evaluation) refers to."""
    name = annotation if isinstance(annotation, str) else getattr(annotation, "__name__", "")
    candidate = globals().get(name)
    return candidate if is_dataclass(candidate) else None


def override(config: Any, **changes: Any) -> Any:
    """A copy of `config` with the given fields changed; None values are ignored."""
    return replace(config, **{k: v for k, v in changes.items() if v is not None})


def override_resumed(config: Any, changes: dict | None, may_change: tuple[str, ...] = (), what: str = "run") -> Any:
    """`override` for the model config of a resumed run, which keeps its network: a change of any
    field outside `may_change` is an error rather than silently ignored (a value equal to the
    checkpoint's is not a change)."""
    changes = {k: v for k, v in (changes or {}).items() if v is not None}
    config = replace(config, **{k: v for k, v in changes.items() if k in may_change})
    shaping = sorted(k for k, v in changes.items() if k not in may_change and replace(config, **{k: v}) != config)
    if shaping:
        allowed = f"only {', '.join(may_change)} may change" if may_change else "none of it may change"
        raise XvoeError(f"a resumed {what} keeps its network: of its config {allowed}, not {', '.join(shaping)}")
    return config
