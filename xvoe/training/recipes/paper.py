"""The paper's scale (its appendix tables): 128x128, ViT encoder, D=32, 64-channel decoder; for GPUs."""
from ...models.dynamics import DynamicsConfig
from ...models.nll import InferenceConfig
from ...models.perception import PerceptionConfig
from ...models.phydnet import PhyDNetConfig
from ...models.reasoning import ReasoningConfig
from ...models.xpl import XPLConfig
from ..config import TrainConfig
from .recipe import Recipe

__all__ = ["RECIPE"]     # read by name: xvoe.training.recipes

XPL_TRAIN = TrainConfig(steps=32_000, batch_size=500, warmup_steps=1000, decay_steps=10_000, checkpoint_minutes=10.0,
                        log_every=100)

RECIPE = Recipe(
    name="paper",
    # the NLL's defaults: none has been chosen on a validation split at this scale
    nll=InferenceConfig(),
    train_videos=10_000,
    perception=PerceptionConfig(image_size=128, latent_dim=32, encoder="vit", decoder_channels=64,
                                decoder_extra_convs=1),
    xpl=XPLConfig(reasoning=ReasoningConfig(latent_dim=32, width=256, layers=6, heads=8, mlp=256),
                  dynamics=DynamicsConfig(latent_dim=32, hidden=512, mlp_layers=3, lstm=2056, buffer_heads=8)),
    xpl_train=XPL_TRAIN,
    # the proposal stage and PLATO as long as XPL: neither has a run of its own chosen at this scale
    proposal_train=XPL_TRAIN,
    plato_train=XPL_TRAIN,
    perception_train=TrainConfig(steps=472_000, batch_size=36, lr=4e-4, warmup_steps=2000,
                                 decay_steps=100_000, checkpoint_minutes=10.0, log_every=100),
    # the original's sizes (64x64 -> 16x16 features, ConvLSTM 128-128-64), one more halving at 128x128;
    # the paper's training table: 100 videos per batch, 70,000 steps, Adam, lr 0.001
    phydnet=PhyDNetConfig(image_size=128, encoder_channels=(16, 32, 64, 64), lstm_channels=(128, 128, 64)),
    phydnet_train=TrainConfig(steps=70_000, batch_size=100, lr=1e-3, warmup_steps=0, decay_steps=10**9,
                              checkpoint_minutes=10.0, log_every=100),
)
