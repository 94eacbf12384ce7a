"""The NLL surprise through the real model's code path, with tiny untrained networks."""
import warnings

import pyro
import torch
from pyro.util import check_model_guide_match

from inference.model import InferenceConfig
from inference.surprise import nll_surprise
from xvoe.models.config import PerceptionConfig
from xvoe.models.dynamics import DynamicsConfig
from xvoe.models.perception import ComponentVAE
from xvoe.models.reasoning import ReasoningConfig
from xvoe.models.xpl import XPL, XPLConfig

T, K, D = 5, 4, 6


def tiny_models():
    torch.manual_seed(0)
    vae = ComponentVAE(PerceptionConfig(image_size=16, latent_dim=D, cnn_channels=(8, 8), cnn_hidden=16,
                                        decoder_channels=8)).eval()
    xpl = XPL(XPLConfig(reasoning=ReasoningConfig(latent_dim=D, slots=K, frames=T, width=16, layers=1, heads=2, mlp=16),
                        dynamics=DynamicsConfig(latent_dim=D, hidden=16, lstm=16, buffer_heads=2))).eval()
    return vae, xpl


def video(hidden_free=True):
    torch.manual_seed(1)
    visible = torch.ones(T, K, dtype=torch.bool)
    if hidden_free:
        visible[:, 3] = False
    occluder = torch.zeros(K, dtype=torch.bool)
    occluder[0] = True
    return (torch.rand(T, 4, 16, 16) * 2 - 1, torch.randn(T, K, D), visible, torch.randn(T, D), occluder)


def test_real_model_and_guide_match_and_estimates_are_sane():
    vae, xpl = tiny_models()
    pyro.set_rng_seed(0)
    result = nll_surprise(vae, xpl, *video(), InferenceConfig(particles=16))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_model_guide_match(result.estimate.model_trace, result.estimate.guide_trace)
    assert result.hidden_slot == 3
    assert 1.0 <= result.ess <= 16.0 + 1e-9 and 0.0 <= result.p_hidden <= 1.0
    assert torch.isfinite(torch.tensor(result.nll))
    sites = {name for name, node in result.estimate.model_trace.nodes.items() if node["type"] == "sample"}
    assert {"exists", "z_0", f"z_{T - 1}", "frames", "seen_motion"} <= sites


def test_without_a_free_slot_no_hidden_object_is_proposed():
    vae, xpl = tiny_models()
    pyro.set_rng_seed(0)
    result = nll_surprise(vae, xpl, *video(hidden_free=False), InferenceConfig(particles=8))
    assert result.hidden_slot == -1 and result.p_hidden == 0.0
    assert abs(result.ess - 8.0) < 1e-6           # every particle is the same scene: equal weights
