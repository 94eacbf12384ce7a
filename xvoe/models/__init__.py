"""The XPL networks and their size presets."""
from .config import PRESETS, PerceptionConfig, Preset, TrainConfig, preset
from .perception import ComponentVAE, PerceptionBatch

__all__ = ["PRESETS", "ComponentVAE", "PerceptionBatch", "PerceptionConfig", "Preset", "TrainConfig", "preset"]
