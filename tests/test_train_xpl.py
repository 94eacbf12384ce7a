"""The XPL and PLATO stages through the shared training loop: learning, resume, loading."""
import numpy as np
import pytest
import torch

from xvoe.apps.zoo import KEPT
from xvoe.errors import XvoeError
from xvoe.models.config import to_dict
from xvoe.models.dynamics import DynamicsConfig
from xvoe.models.nll import InferenceConfig
from xvoe.models.reasoning import ReasoningConfig
from xvoe.models.xpl import XPL, XPLConfig
from xvoe.scenes import store
from xvoe.scenes.world import WORLD
from xvoe.training.config import TrainConfig
from xvoe.training.latent_batches import (
    LatentBatches,
    ProposalBatch,
    bridge_hidden,
    object_places,
    outside_picture,
    wall_stays,
)
from xvoe.training.latents import _Latents, _write_latents
from xvoe.training.proposal import ProposalNetworks, train_proposal
from xvoe.training.recipes import RECIPES
from xvoe.training.xpl import load_xpl, model_nll, nll_origin, nll_settings_of, train_xpl

N, T, K, D = 32, 8, 4, 6
TINY = {"steps": 100, "batch_size": 32, "lr": 3e-3, "warmup_steps": 1, "log_every": 5}


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """Objects moving at constant velocity; slot 1 hidden for two frames in every video."""
    rng = np.random.default_rng(0)
    start, velocity = rng.normal(size=(N, 1, K, D)), 0.3 * rng.normal(size=(N, 1, K, D))
    mean = (start + velocity * np.arange(T)[None, :, None, None]).astype(np.float32)
    visible = np.ones((N, T, K), bool)
    visible[:, 3:5, 1] = False
    zeros = np.zeros((N, T, D), np.float32)
    latents = _Latents(mean=mean, std=np.full_like(mean, 0.01), visible=visible, present=np.ones_like(visible),
                      pixels=visible.astype(np.int32) * 10, background_mean=zeros, background_std=zeros,
                      attrs={"config": "{}"})
    return _write_latents(tmp_path_factory.mktemp("cache") / "latents.h5", latents)


def losses(run_dir, stage):
    import csv
    return list(csv.DictReader(open(run_dir / f"{stage}.csv")))


@pytest.fixture(autouse=True)
def tiny_recipe(monkeypatch):
    """Shrink the default recipe's networks so that a stage trains in a second; Transformer 2 in
    the joint stage, so that one stage trains every part."""
    from dataclasses import replace

    import xvoe.training.proposal as proposal_stage
    import xvoe.training.xpl as stage

    default = RECIPES["cpu-short"]
    reasoning = replace(default.xpl.reasoning, width=16, layers=1, heads=2, mlp=16)
    dynamics = replace(default.xpl.dynamics, hidden=32, lstm=32, buffer_heads=2)
    # the synthetic cache has no split file, which the fills outside the picture and the walls are found in
    small = replace(default, xpl=replace(default.xpl, outside_refill=False, refill_ignores_walls=False,
                                         joint_proposal=True, reasoning=reasoning, dynamics=dynamics),
                    proposal_train=replace(default.proposal_train, focus_group="", focus_share=0.0))
    monkeypatch.setattr(stage, "recipe", lambda name: small)
    monkeypatch.setattr(proposal_stage, "recipe", lambda name: small)


def test_xpl_stage_learns_and_resumes_exactly(cache, tmp_path):
    straight = train_xpl(cache, tmp_path / "a", progress=False, **TINY)
    rows = losses(tmp_path / "a", "xpl")
    for term, share in (("dynamics", 0.8), ("refill", 0.9), ("loss", 0.8)):
        assert float(rows[-1][term]) < share * float(rows[0][term]), term
    assert "mae" in rows[0]
    # interrupted after 12 steps, then resumed: the same weights as the straight run
    train_xpl(cache, tmp_path / "b", progress=False, **{**TINY, "steps": 12})
    resumed = train_xpl(cache, tmp_path / "b", progress=False, resume=True, **TINY)
    a, b = torch.load(straight, weights_only=True), torch.load(resumed, weights_only=True)
    assert a["step"] == b["step"] == 100
    for name, value in a["model"].items():
        torch.testing.assert_close(value, b["model"][name], msg=name)
    model, state = load_xpl(tmp_path / "a")
    assert state["config"]["xpl"]["reasoning"]["latent_dim"] == D and not model.training


def test_a_shipped_checkpoint_trains_further_from_its_step(cache, tmp_path):
    first = torch.load(train_xpl(cache, tmp_path / "a", stage="plato", progress=False, **{**TINY, "steps": 40}),
                       weights_only=True)
    (tmp_path / "b").mkdir()
    torch.save({key: first[key] for key in KEPT}, tmp_path / "b" / "plato.pt")   # what `xvoe ship` keeps
    with pytest.warns(UserWarning, match="no optimiser state.*step 40"):
        further = train_xpl(cache, tmp_path / "b", stage="plato", progress=False, resume=True, **TINY)
    assert torch.load(further, weights_only=True)["step"] == 100
    # the log starts where the shipped weights left off, not at a fresh model's loss
    fresh, after = losses(tmp_path / "a", "plato"), losses(tmp_path / "b", "plato")
    assert int(after[0]["step"]) == 45
    assert float(after[0]["loss"]) < min(float(row["loss"]) for row in fresh if int(row["step"]) <= 25)


def test_plato_and_the_no_residual_ablation(cache, tmp_path):
    short = {**TINY, "steps": 5}
    plato = train_xpl(cache, tmp_path, stage="plato", progress=False, **short)
    ablation = train_xpl(cache, tmp_path, stage="xpl-noresidual", progress=False, **short)
    assert plato.name == "plato.pt" and ablation.name == "xpl-noresidual.pt"
    model, _ = load_xpl(tmp_path, stage="plato")
    assert not model.config.use_reasoning and not model.config.dynamics.residual
    model, _ = load_xpl(tmp_path, stage="xpl-noresidual")
    assert model.config.use_reasoning and not model.config.dynamics.residual


def test_a_fresh_network_takes_its_shape_from_the_cache_its_variant_from_the_stage_the_rest_from_overrides(
        cache, tmp_path):
    """`--set stop_target_gradient=false` reaches the network; an override of what the data or the
    stage decide does not build a network that could not train on them."""
    overrides = {"stop_target_gradient": False, "use_reasoning": True, "dynamics.latent_dim": 3}
    train_xpl(cache, tmp_path, stage="plato", progress=False, model_overrides=overrides, **{**TINY, "steps": 1})
    config = load_xpl(tmp_path, stage="plato")[0].config
    assert not config.stop_target_gradient
    assert not config.use_reasoning and config.dynamics.latent_dim == D


def test_a_recipe_can_train_plato_longer_than_xpl(cache, tmp_path, monkeypatch):
    """Recipe.plato_train, where set, is the plato stage's training; the other stages keep xpl_train."""
    from dataclasses import replace

    import xvoe.training.xpl as stage

    base = stage.recipe("cpu-short")
    xpl_train = TrainConfig(**{**TINY, "steps": 3})
    longer = replace(base, xpl_train=xpl_train, plato_train=replace(xpl_train, steps=7, lr=2e-3))
    monkeypatch.setattr(stage, "recipe", lambda name: longer)
    plato = torch.load(train_xpl(cache, tmp_path, stage="plato", progress=False), weights_only=True)
    ablation = torch.load(train_xpl(cache, tmp_path, stage="xpl-noresidual", progress=False), weights_only=True)
    assert (plato["step"], plato["train"]["lr"]) == (7, 2e-3)
    assert (ablation["step"], ablation["train"]["lr"]) == (3, xpl_train.lr)


def test_the_xpl_checkpoint_stores_its_recipes_nll_settings_as_plain_data(cache, tmp_path, monkeypatch):
    """The recipe's NLL settings, written into xpl.pt and read back as they were (a resumed run
    keeps them); the other stages store none."""
    from dataclasses import replace

    import xvoe.training.xpl as stage

    settings = InferenceConfig(pixel_sigma=0.7, smc_pilot=(4, 8), smc_proposal_widening=2.0, method="importance")
    chosen = replace(stage.recipe("cpu-short"), nll=settings)
    monkeypatch.setattr(stage, "recipe", lambda name: chosen)
    path = train_xpl(cache, tmp_path, progress=False, **{**TINY, "steps": 2})
    stored = torch.load(path, weights_only=True)["config"]
    assert nll_settings_of(stored) == settings
    assert all(isinstance(value, (str, int, float, bool, tuple)) for value in stored["nll"].values())
    train_xpl(cache, tmp_path, progress=False, resume=True, **{**TINY, "steps": 3})
    assert nll_settings_of(torch.load(path, weights_only=True)["config"]) == settings
    plato = train_xpl(cache, tmp_path, stage="plato", progress=False, **{**TINY, "steps": 2})
    assert nll_settings_of(torch.load(plato, weights_only=True)["config"]) is None


def test_a_models_nll_settings_are_its_checkpoints_else_its_recipes_else_the_defaults(monkeypatch):
    from dataclasses import replace

    import xvoe.training.xpl as stage

    stored = InferenceConfig(pixel_sigma=0.7)
    chosen = replace(RECIPES["paper"], nll=InferenceConfig(motion_sigma=0.3))
    monkeypatch.setattr(stage, "recipe", lambda name: chosen)
    assert model_nll({"recipe": "paper", "nll": to_dict(stored)}) == stored
    assert model_nll({"recipe": "paper"}) == chosen.nll
    assert model_nll({"recipe": "a recipe of another xvoe"}) == InferenceConfig()
    assert [nll_origin(config) for config in ({"recipe": "paper", "nll": to_dict(stored)}, {"recipe": "paper"},
                                              {"recipe": "a recipe of another xvoe"})] == ["checkpoint", "recipe",
                                                                                           "defaults"]


def test_batches_do_not_depend_on_the_process_count(cache):
    one = LatentBatches(str(cache), batch_size=8, shards=2, seed=3).batch(7)
    halves = [LatentBatches(str(cache), batch_size=8, shards=2, rank=r, world=2, seed=3).batch(7) for r in (0, 1)]
    assert torch.equal(one.mean, torch.cat([h.mean for h in halves]))
    assert torch.equal(one.order, torch.cat([h.order for h in halves]))
    with pytest.raises(XvoeError, match="multiple of the 4 processes: train in 1, 2 processes, or change"):
        LatentBatches(str(cache), batch_size=8, shards=2, rank=0, world=4, seed=3)


def test_batches_refuse_a_test_splits_cache_and_a_batch_past_memory_before_reading_it(cache, tmp_path):
    """For every stage on the latent cache (the proposal stage's too): impossible events are no
    training data, and a batch the machine cannot hold is named before the cache is loaded."""
    import h5py

    tested = tmp_path / "tested.h5"
    tested.write_bytes(cache.read_bytes())
    with h5py.File(tested, "a") as file:
        file.attrs["source_split"] = "test"
    with pytest.raises(XvoeError, match="encoded from a test split; training on impossible events is refused"):
        LatentBatches(str(tested), batch_size=8, shards=1)
    with pytest.raises(XvoeError, match=f"--batch-size {10**15} needs"):
        LatentBatches(str(cache), batch_size=10**15, shards=1)


def test_errors(cache, tmp_path):
    with pytest.raises(XvoeError, match="stage"):
        train_xpl(cache, tmp_path, stage="phydnet", progress=False)
    with pytest.raises(XvoeError, match="no xpl checkpoint"):
        load_xpl(tmp_path / "empty")
    train_xpl(cache, tmp_path, progress=False, **{**TINY, "steps": 2})
    with pytest.raises(XvoeError, match="exists"):
        train_xpl(cache, tmp_path, progress=False, **TINY)


def test_transformer2_is_asked_for_seen_objects_often(tmp_path):
    """Half the rebuilt slots are drawn among the seen objects (mapped to the permuted order):
    with two of four slots never seen, about 3/4 of the draws hit a seen one, not 1/2."""
    visible = np.zeros((N, T, K), bool)
    visible[:, :, :2] = True
    mean = np.zeros((N, T, K, D), np.float32)
    zeros = np.zeros((N, T, D), np.float32)
    path = _write_latents(tmp_path / "half.h5", _Latents(mean=mean, std=mean, visible=visible, present=visible,
                                                        pixels=visible.astype(np.int32), background_mean=zeros,
                                                        background_std=zeros, attrs={"config": "{}"}))
    batches = LatentBatches(str(path), batch_size=32, shards=1, seed=5)
    hits = total = 0
    for step in range(40):
        batch = batches.batch(step)
        original = batch.order[torch.arange(len(batch)), batch.hidden]
        hits += int((original < 2).sum())
        total += len(batch)
    assert 0.68 < hits / total < 0.82


def test_the_proposal_stage_trains_transformer2_alone_and_overlays_xpl(cache, tmp_path):
    with pytest.raises(XvoeError, match="train the xpl stage first"):
        train_proposal(tmp_path, cache, progress=False)
    train_xpl(cache, tmp_path, progress=False, **{**TINY, "steps": 20})
    joint, _ = load_xpl(tmp_path)
    path = train_proposal(tmp_path, progress=False, **{**TINY, "steps": 150})      # the cache from xpl.pt's meta
    mae = [float(row["mae"]) for row in losses(tmp_path, "proposal")]
    assert np.mean(mae[-5:]) < np.mean(mae[:5]) - 0.5      # a row's batch noise is about 0.5
    state = torch.load(path, weights_only=True)
    assert state["model"] and all(name.startswith(("transformer2.", "existence.")) for name in state["model"])
    tuned, loaded = load_xpl(tmp_path)
    assert loaded["proposal"] == str(path)
    for name, value in joint.state_dict().items():      # Transformer 1 and the dynamics are xpl.pt's
        same = torch.equal(value, tuned.state_dict()[name])
        assert same != name.startswith(("transformer2.", "existence.")), name
    untouched, _ = load_xpl(tmp_path, proposal=False)
    assert all(torch.equal(v, joint.state_dict()[k]) for k, v in untouched.state_dict().items())
    with pytest.raises(XvoeError, match="keeps its network"):
        train_proposal(tmp_path, progress=False, overwrite=True, model_overrides={"inert_walls": False}, **TINY)
    # an xpl.pt trained again no longer matches: a clear error, not a silent mix
    train_xpl(cache, tmp_path, progress=False, overwrite=True, **{**TINY, "steps": 21})
    with pytest.raises(XvoeError, match="another xpl.pt"):
        load_xpl(tmp_path)


def test_transformer2_can_be_left_to_the_proposal_stage(cache, tmp_path):
    """joint_proposal off: the joint stage trains Transformer 1 and the dynamics alone (Transformer 2
    and the existence head keep their first weights, however long it runs), such an xpl.pt is not
    scored without its proposal.pt, and the proposal stage trains them from there."""
    frozen = ("transformer2.", "existence.")
    short, long = (load_xpl(train_xpl(cache, tmp_path / run, progress=False, model_overrides={"joint_proposal": False},
                                      **{**TINY, "steps": steps}), proposal=False)[0].state_dict()
                   for run, steps in (("short", 10), ("long", 30)))
    for name, value in short.items():
        assert torch.equal(value, long[name]) == name.startswith(frozen), name
    assert "mae" not in losses(tmp_path / "long", "xpl")[0]
    with pytest.raises(XvoeError, match="leaves Transformer 2 to the proposal stage.*xvoe train proposal"):
        load_xpl(tmp_path / "long")
    train_proposal(tmp_path / "long", progress=False, **{**TINY, "steps": 10})
    tuned = load_xpl(tmp_path / "long")[0].state_dict()
    assert all(torch.equal(value, tuned[name]) != name.startswith(frozen) for name, value in long.items())


def test_the_proposal_stage_resumes_exactly(cache, tmp_path):
    for run in ("a", "b"):
        train_xpl(cache, tmp_path / run, progress=False, **{**TINY, "steps": 10})
    straight = train_proposal(tmp_path / "a", progress=False, **{**TINY, "steps": 30})
    train_proposal(tmp_path / "b", progress=False, **{**TINY, "steps": 12})
    resumed = train_proposal(tmp_path / "b", progress=False, resume=True, **{**TINY, "steps": 30})
    a, b = torch.load(straight, weights_only=True), torch.load(resumed, weights_only=True)
    for name, value in a["model"].items():
        torch.testing.assert_close(value, b["model"][name], msg=name)


def test_wall_stays_fills_the_frames_the_wall_was_away_from_the_nearest_seen_one():
    mean = torch.arange(2 * 5 * 3, dtype=torch.float32).reshape(2, 5, 3, 1)
    visible = torch.zeros(2, 5, 3, dtype=torch.bool)
    visible[0, 2:4, 1] = True             # video 0: the wall (slot 1) is down in frames 2 and 3
    visible[:, :, 0] = True
    walls = torch.zeros(2, 3, dtype=torch.bool)
    walls[:, 1] = True                    # video 1's wall is never seen: left alone
    stays, seen = wall_stays(mean, visible, walls)
    assert stays[0, :, 1, 0].tolist() == [mean[0, 2, 1, 0]] * 3 + [mean[0, 3, 1, 0]] * 2
    assert seen[0, :, 1].all() and not seen[1, :, 1].any()
    assert torch.equal(stays[:, :, [0, 2]], mean[:, :, [0, 2]]) and torch.equal(stays[1], mean[1])


def test_bridge_hidden_interpolates_between_seen_frames_and_holds_beyond_them():
    mean = torch.arange(6, dtype=torch.float32).view(1, 6, 1, 1).repeat(1, 1, 3, 2)
    mean[0, 2:4, 0] = 99.0                     # what the encoder made of a hidden object: no measurement
    visible = torch.zeros(1, 6, 3, dtype=torch.bool)
    visible[0, [1, 4], 0] = True               # slot 0 seen in frames 1 and 4
    visible[0, :4, 1] = True                   # slot 1 leaves the view after frame 3
    bridged = bridge_hidden(mean, visible)
    assert bridged[0, :, 0, 0].tolist() == [1, 1, 2, 3, 4, 4]
    assert bridged[0, :, 1, 1].tolist() == [0, 1, 2, 3, 3, 3]
    assert torch.equal(bridged[0, :, 2], mean[0, :, 2])      # seen in no frame: left as it is
    assert torch.equal(bridged[visible], mean[visible])       # seen frames never change

def test_transformer2_never_sees_the_slot_it_rebuilds_not_even_through_transformer1():
    """In the proposal stage the rebuilt slot is emptied before Transformer 1 refines the
    others: what stood there may change freely without changing the loss (only the target may)."""
    torch.manual_seed(0)
    xpl = XPL(XPLConfig(reasoning=ReasoningConfig(latent_dim=D, slots=K, frames=T, width=16, layers=1, heads=2,
                                                  mlp=16),
                        dynamics=DynamicsConfig(latent_dim=D, hidden=16, lstm=16, buffer_heads=2))).eval()
    networks = ProposalNetworks(xpl, torch.zeros(D))
    mean, target = torch.randn(3, T, K, D), torch.randn(3, T, K, D)
    visible = torch.ones(3, T, K, dtype=torch.bool)
    visible[:, 2:5, 0] = False                   # slot 0 partly occluded: Transformer 1 fills it
    order = torch.stack([torch.randperm(K) for _ in range(3)])
    hidden = torch.tensor([1, 2, 3])             # in the permuted order
    batch = ProposalBatch(mean, visible, order, hidden, torch.zeros_like(visible), visible[:, 0] & False,
                          target=target)
    loss = networks(batch)["mae"]
    moved = mean.clone()
    original = order[torch.arange(3), hidden]    # the rebuilt slots in the stored order
    moved[torch.arange(3), :, original] += 5.0
    moved_batch = ProposalBatch(moved, visible, order, hidden, batch.refill, batch.walls, target=target)
    torch.testing.assert_close(networks(moved_batch)["mae"], loss)
    other = mean.clone()
    other[torch.arange(3), :, (original + 1) % K] += 5.0
    assert not torch.allclose(networks(ProposalBatch(other, visible, order, hidden, batch.refill, batch.walls,
                                                  target=target))["mae"], loss)


def walled_cache(train_file, path):
    """A cache of the training split's visibility (latents all zero) that names the split."""
    with store.open_dataset(train_file) as file:
        columns = list(file["states"].attrs["state_columns"])
        visible = file["states"][..., columns.index("visible")] > 0.25
    mean = np.zeros(visible.shape + (D,), np.float32)
    zeros = np.zeros(visible.shape[:2] + (D,), np.float32)
    latents = _Latents(mean=mean, std=mean, visible=visible, present=visible, pixels=visible.astype(np.int32),
                      background_mean=zeros, background_std=zeros,
                      attrs={"config": "{}", "source": str(train_file)})
    return _write_latents(path, latents)


def test_a_focus_group_fills_its_share_of_each_latent_batch(train_file, tmp_path):
    """With focus_group, half of each batch (the second half) are that group's videos with a wall,
    found through the split file the cache came from; at share 0 the batches are the uniform ones."""
    import h5py

    with h5py.File(train_file) as file:
        groups, walls = file["group"].asstr()[:], file["has_wall"][:].astype(bool)
    focus = np.flatnonzero((groups == "continuity") & walls)
    assert 0 < len(focus) < len(groups)
    cache = walled_cache(train_file, tmp_path / "latents.h5")
    focused = LatentBatches(str(cache), batch_size=8, shards=1, seed=2, focus_group="continuity", focus_share=0.5)
    plain = LatentBatches(str(cache), batch_size=8, shards=1, seed=2)
    unfocused = LatentBatches(str(cache), batch_size=8, shards=1, seed=2, focus_group="continuity", focus_share=0.0)
    videos = [focused.draw(step)[0].numpy() for step in range(20)]
    assert all(np.isin(video[4:], focus).all() for video in videos)
    uniform = np.concatenate([plain.draw(step)[0].numpy() for step in range(20)])
    assert not np.isin(uniform, focus).all()
    assert all(torch.equal(a, b) for a, b in zip(plain.draw(5), unfocused.draw(5)))
    with pytest.raises(XvoeError, match="needs a focus_group"):
        LatentBatches(str(cache), batch_size=8, shards=1, focus_share=0.5)
    with pytest.raises(XvoeError, match="focus_group names no group 'continuty'"):
        LatentBatches(str(cache), batch_size=8, shards=1, focus_group="continuty", focus_share=0.5)
    moved = tmp_path / "moved.h5"
    cache.rename(moved)
    (tmp_path / "elsewhere").mkdir()
    with h5py.File(moved, "a") as file:
        file.attrs["source"] = str(tmp_path / "elsewhere" / "train.h5")
    with pytest.raises(XvoeError, match="focus_group needs the split file"):
        LatentBatches(str(moved), batch_size=8, shards=1, focus_group="continuity", focus_share=0.5)


def test_outside_picture_needs_the_whole_object_beyond_an_edge():
    """An object counts as outside once its farthest corner, however it turns, is past an edge."""
    size = 4.0                    # half side
    reach = size * np.sqrt(2)
    places = np.array([[32, 32, size], [32, WORLD + reach + 0.1, size], [32, WORLD + reach - 0.1, size],
                       [-reach - 0.1, 10, size], [-reach + 0.1, 10, size], [WORLD + 3, -reach - 0.1, size]],
                      np.float32)
    assert outside_picture(places).tolist() == [False, True, False, True, False, True]


def test_batches_mark_the_hidden_entries_outside_the_picture(train_file, tmp_path):
    """The training videos' cubes fall in from above: the batches mark their entries before they
    come into view, and only entries that are hidden and wholly outside the picture."""
    cache = walled_cache(train_file, tmp_path / "latents.h5")
    batches = LatentBatches(str(cache), batch_size=32, shards=1, seed=2, outside=True)
    places = object_places(str(cache), 0, len(batches.visible))
    marked = batches.outside.numpy()
    assert marked.any() and not (marked & batches.visible.numpy()).any()
    assert (places[..., 1][marked] - places[..., 2][marked] * np.sqrt(2) >= WORLD).mean() > 0.5   # above
    batch = batches.batch(0)
    assert batch.outside.shape == batch.visible.shape and not (batch.outside & batch.visible).any()
    assert LatentBatches(str(cache), batch_size=32, shards=1).batch(0).outside is None
