"""Shipped models: found by name, small, and re-shipped without loss."""
import pytest
import torch

import xvoe.apps.zoo as zoo
import xvoe.training.checkpoints as checkpoints
from xvoe.errors import XvoeError
from xvoe.evaluation.scorer import load_model
from xvoe.training.recipes import recipe


def test_the_default_model_is_shipped_within_budget():
    assert "xpl" in zoo.available_models()
    total = sum(p.stat().st_size for p in zoo.WEIGHTS.glob("*.pt"))
    assert total <= zoo.BUDGET_BYTES
    scorer = load_model("xpl")
    assert scorer.vae is not None and scorer.xpl.config.use_reasoning


def test_shipping_keeps_the_weights_and_drops_the_optimiser(tmp_path, monkeypatch):
    run = tmp_path / "run"
    run.mkdir()
    for stage in ("perception", "xpl", "proposal"):    # the default recipe trains Transformer 2 in a stage of its own
        state = torch.load(zoo.WEIGHTS / f"{stage}.pt", weights_only=True)
        state["optimizer"] = {"big": torch.zeros(1000)}
        torch.save(state, run / f"{stage}.pt")
    written = zoo.ship(run, tmp_path / "weights")
    assert [p.name for p in written] == ["perception.pt", "xpl.pt", "proposal.pt"]
    slim = torch.load(tmp_path / "weights" / "xpl.pt", weights_only=True)
    assert "optimizer" not in slim
    original = torch.load(zoo.WEIGHTS / "xpl.pt", weights_only=True)
    for name, value in original["model"].items():
        torch.testing.assert_close(slim["model"][name], value)
    monkeypatch.setattr(checkpoints, "WEIGHTS", tmp_path / "weights")
    assert load_model("xpl").name == "xpl"


def test_a_run_that_is_not_its_recipes_is_not_shipped(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    for stage in ("perception", "xpl"):
        state = torch.load(zoo.WEIGHTS / f"{stage}.pt", weights_only=True)
        if stage == "xpl":
            state["train"]["steps"] = 99       # trained by hand, not as the recipe says
        torch.save(state, run / f"{stage}.pt")
    with pytest.raises(XvoeError, match=r"xpl.pt is not what its recipe makes \(train.steps: 99 != 9000\)"):
        zoo.ship(run, tmp_path / "weights")
    assert not (tmp_path / "weights").exists()


def test_a_new_perception_is_not_shipped_without_the_models_that_read_it(tmp_path):
    weights, run = tmp_path / "weights", tmp_path / "run"
    weights.mkdir()
    run.mkdir()
    for stage in ("perception", "xpl", "plato"):
        (weights / f"{stage}.pt").write_bytes((zoo.WEIGHTS / f"{stage}.pt").read_bytes())
    for stage in ("perception", "xpl"):
        state = torch.load(zoo.WEIGHTS / f"{stage}.pt", weights_only=True)
        if stage == "perception":
            first = next(iter(state["model"]))
            state["model"][first] = state["model"][first] + 1.0     # another perception
        torch.save(state, run / f"{stage}.pt")
    before = {p.name: p.read_bytes() for p in weights.iterdir()}
    with pytest.raises(XvoeError, match=r"not the shipped one, which plato.pt read"):
        zoo.ship(run, weights)
    assert {p.name: p.read_bytes() for p in weights.iterdir()} == before


def test_unshipped_names_and_runs_give_one_line_errors(tmp_path, monkeypatch):
    monkeypatch.setattr(checkpoints, "WEIGHTS", tmp_path)
    with pytest.raises(XvoeError, match="not shipped"):
        load_model("plato")
    with pytest.raises(XvoeError, match="holds no checkpoint to ship"):
        zoo.ship(tmp_path)
    (tmp_path / "xpl.pt").write_bytes((zoo.WEIGHTS / "xpl.pt").read_bytes())
    with pytest.raises(XvoeError, match="holds no perception.pt, whose latents its xpl read"):
        zoo.ship(tmp_path, tmp_path / "weights")


def test_a_phydnet_ships_on_its_own(tmp_path):
    """PhyDNet reads pixels: a run of it alone replaces phydnet.pt and leaves the rest."""
    weights, run = tmp_path / "weights", tmp_path / "run"
    weights.mkdir()
    run.mkdir()
    for stage in ("perception", "xpl"):
        (weights / f"{stage}.pt").write_bytes((zoo.WEIGHTS / f"{stage}.pt").read_bytes())
    state = torch.load(zoo.WEIGHTS / "phydnet.pt", weights_only=True)
    state["config"] = {"recipe": "cpu-short", "phydnet": {**state["config"]["phydnet"]}}
    made = recipe("cpu-short")
    state["train"] = {**state["train"], "steps": made.final_training("phydnet").steps, "lr": 4.5e-4,
                      "max_minutes": 0.0}
    state["step"], state["meta"] = made.final_training("phydnet").steps, {"data": "/somewhere/train.h5"}
    torch.save(state, run / "phydnet.pt")
    before = {p.name: p.read_bytes() for p in weights.iterdir()}
    assert [p.name for p in zoo.ship(run, weights)] == ["phydnet.pt"]
    assert {p.name: p.read_bytes() for p in weights.iterdir() if p.name != "phydnet.pt"} == before
    assert torch.load(weights / "phydnet.pt", weights_only=True)["meta"] == {"shipped_from": "run"}


@pytest.mark.parametrize("path", sorted(zoo.WEIGHTS.glob("*.pt")), ids=lambda p: p.stem)
def test_no_shipped_checkpoint_holds_a_path_of_the_machine_it_was_trained_on(path):
    meta = torch.load(path, weights_only=True)["meta"]
    assert not [value for value in meta.values() if isinstance(value, str) and value.startswith("/")]
