"""Sizes of every network and training run, grouped into named presets.

A `Preset` holds one config per stage, so that a run at one scale is one name.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields

from ..errors import XvoeError
from ..models.config import field_type, parse_value
from ..models.dynamics import DynamicsConfig
from ..models.perception import PerceptionConfig
from ..models.phydnet import PhyDNetConfig
from ..models.reasoning import ReasoningConfig
from ..models.xpl import XPLConfig


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
    xpl_train: TrainConfig = field(default_factory=lambda: TrainConfig(steps=1500, batch_size=32, warmup_steps=100,
                                                                       decay_steps=1000))
    # Transformer 2 and the existence head trained further on hidden objects (the proposal stage)
    proposal_train: TrainConfig = field(default_factory=lambda: TrainConfig(steps=4000, batch_size=32,
                                                                            warmup_steps=100, decay_steps=1500))
    # the PLATO baseline's training (None: xpl_train's). Without Transformer 1 it predicts the
    # raw latents directly, and every visible object costs its prediction error in every frame:
    # trained no longer than XPL, that cost outweighs the violations of the predictive settings
    plato_train: TrainConfig | None = None
    # the PhyDNet baseline: batch_size counts videos
    phydnet: PhyDNetConfig = field(default_factory=PhyDNetConfig)
    phydnet_train: TrainConfig = field(default_factory=lambda: TrainConfig(steps=300, batch_size=8, lr=3e-3,
                                                                           warmup_steps=20, decay_steps=300))


PRESETS: dict[str, Preset] = {
    # 2 CPU cores: 32x32 frames, a small CNN encoder and a light decoder. Each object's position is two
    # latents the decoder draws from (found whole behind walls: amodal, cut_share), and the later
    # stages weigh each latent by how much it moves the picture; walls are inert in the dynamics
    # (docs/decisions.md, "The cpu preset").
    "cpu": Preset(
        name="cpu",
        perception=PerceptionConfig(where_latents=True, amodal=True, cut_share=0.25),
        xpl=XPLConfig(weigh_by_picture=True, inert_walls=True),
    ),
    # The cpu preset before where latents: the whole latent broadcast, every latent weighed alike;
    # walls inert in the dynamics, Transformer 1 trained by the refill loss alone, its fills of
    # objects outside the picture included, and a longer XPL stage (docs/decisions.md, "The
    # cpu-broadcast preset and the shipped models").
    "cpu-broadcast": Preset(
        name="cpu-broadcast",
        perception=PerceptionConfig(),
        xpl=XPLConfig(inert_walls=True, stop_input_gradient=True, outside_refill=True),
        xpl_train=TrainConfig(steps=12_000, batch_size=32, warmup_steps=100, decay_steps=8000),
        # PLATO's predictive accuracy grows with its training time (docs/decisions.md, "PLATO's
        # training length")
        plato_train=TrainConfig(steps=60_000, batch_size=32, warmup_steps=100, decay_steps=15_000),
        # the changing pixels weighed more in PhyDNet's training loss, and trained longer
        # (docs/decisions.md, "PhyDNet's loss weight on changing pixels")
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


MODEL_CONFIGS = {"perception": PerceptionConfig, "xpl": XPLConfig, "plato": XPLConfig, "phydnet": PhyDNetConfig}


def stage_settings(stage: str, assignments: list[str]) -> tuple[dict, dict]:
    """`--set FIELD=VALUE` as typed overrides of the stage's TrainConfig and model config.
    A field is looked up in TrainConfig, then in the model's config; `train.` or `model.`
    before it picks one, and a dotted name reaches a nested config (`model.dynamics.hidden`)."""
    train, model = {}, {}
    owners = {"train": TrainConfig, "model": MODEL_CONFIGS.get(stage)}
    for text in assignments:
        name, equals, value = text.partition("=")
        if not equals or not name:
            raise XvoeError(f"--set takes FIELD=VALUE, not {text!r}")
        where, _, rest = name.partition(".")
        if where in owners and rest:
            chosen = where
            name = rest
        else:
            chosen = "train" if name.partition(".")[0] in {f.name for f in fields(TrainConfig)} else "model"
        config = owners[chosen]
        if config is None:
            raise XvoeError(f"the {stage} stage builds no network of its own: only TrainConfig fields may be set")
        target = train if chosen == "train" else model
        target[name] = parse_value(field_type(config, name), value)
    return train, model
