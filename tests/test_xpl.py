"""The reasoning Transformers and the dynamics: masking, causality, slot order, learning."""

import pytest
import torch
from conftest import randomise_dynamics_head

from xvoe.models.dynamics import DynamicsConfig, InteractionLSTM
from xvoe.models.reasoning import (
    ReasoningConfig,
    ReasoningTransformer,
    gaussian_nll,
    hide_slot,
    never_seen,
    occlusion_keep,
)
from xvoe.models.xpl import XPL, XPLConfig, permute_slots

D, K, T = 6, 4, 8
SMALL_REASONING = ReasoningConfig(latent_dim=D, slots=K, frames=T, width=32, layers=2, heads=4, mlp=64)
SMALL_DYNAMICS = DynamicsConfig(latent_dim=D, hidden=32, lstm=48, buffer_heads=2)


def test_observed_entries_pass_through_unchanged():
    torch.manual_seed(0)
    model = ReasoningTransformer(SMALL_REASONING)
    z = torch.randn(3, T, K, D)
    keep = torch.rand(3, T, K) > 0.4
    mean, scale = model(z, keep)
    assert torch.equal(mean[keep], z[keep])
    assert torch.all(scale[keep] == 0) and torch.all(scale[~keep] > 0)
    # the hidden entries' values never reach the model: changing them changes nothing
    z2 = z.clone()
    z2[~keep] = torch.randn(int((~keep).sum()), D) * 100
    mean2, _ = model(z2, keep)
    torch.testing.assert_close(mean2, mean)


def test_masks():
    visible = torch.zeros(1, 3, 3, dtype=torch.bool)
    visible[0, :, 0] = True               # slot 0 seen throughout
    visible[0, 1, 1] = True               # slot 1 seen at frame 1 only
    keep = occlusion_keep(visible)
    assert keep[0, :, 0].all() and keep[0, :, 2].all()    # slot 2 never seen: passed through
    assert keep[0, :, 1].tolist() == [False, True, False]
    assert never_seen(visible).tolist() == [[False, False, True]]
    hidden = hide_slot((2, 3, 3), torch.tensor([2, 0]))
    assert (~hidden[0, :, 2]).all() and hidden[0, :, :2].all() and (~hidden[1, :, 0]).all()


def test_gaussian_nll_matches_torch():
    mean, target = torch.randn(2, T, K, D), torch.randn(2, T, K, D)
    scale = torch.rand(2, T, K, D) + 0.1
    where = torch.ones(2, T, K, dtype=torch.bool)
    expected = -torch.distributions.Normal(mean, scale).log_prob(target).sum(-1).mean()
    torch.testing.assert_close(gaussian_nll(mean, scale, target, where), expected)


def test_beta_nll_scales_each_entry_and_keeps_the_scale_optimum():
    mean, target = torch.zeros(1, 1, 1, 1, requires_grad=True), torch.ones(1, 1, 1, 1)
    where = torch.ones(1, 1, 1, dtype=torch.bool)
    for scale in (0.5, 2.0):
        plain = gaussian_nll(mean, torch.tensor(scale).reshape(1, 1, 1, 1), target, where)
        weighted = gaussian_nll(mean, torch.tensor(scale).reshape(1, 1, 1, 1), target, where, beta=0.5)
        torch.testing.assert_close(weighted, plain * scale)   # scale ** (2 * beta), held constant
        grad_plain, = torch.autograd.grad(plain, mean)
        grad_weighted, = torch.autograd.grad(weighted, mean)
        torch.testing.assert_close(grad_plain, -torch.ones(1, 1, 1, 1) / scale ** 2)
        torch.testing.assert_close(grad_weighted, -torch.ones(1, 1, 1, 1) / scale)
    # the scale that minimises it is still the error's size: d/ds [s (e^2 / 2s^2 + log s)] with s held
    scale = torch.tensor(0.7, requires_grad=True)
    loss = gaussian_nll(mean.detach(), scale.reshape(1, 1, 1, 1), target * 0.7, where, beta=0.5)
    assert abs(torch.autograd.grad(loss, scale)[0].item()) < 1e-6


def test_dynamics_is_causal():
    """The prediction of frame t+1 depends on frames <= t only."""
    torch.manual_seed(1)
    for residual in (True, False):
        model = InteractionLSTM(DynamicsConfig(**{**SMALL_DYNAMICS.__dict__, "residual": residual}))
        torch.nn.init.normal_(model.out[-1].weight, std=0.1)
        z = torch.randn(2, T, K, D)
        base = model(z)
        for t in range(T - 1):
            changed = z.clone()
            changed[:, t + 1:] += torch.randn_like(changed[:, t + 1:])
            after = model(changed)
            torch.testing.assert_close(after[:, : t + 1], base[:, : t + 1])
            assert not torch.allclose(after[:, t + 1:], base[:, t + 1:])


def test_residual_starts_from_no_change():
    model = InteractionLSTM(SMALL_DYNAMICS)
    z = torch.randn(2, T, K, D)
    torch.testing.assert_close(model(z), z)


def test_dynamics_treats_slots_alike():
    """Permuting the slots permutes the predictions: no slot is special to the dynamics."""
    torch.manual_seed(2)
    model = InteractionLSTM(SMALL_DYNAMICS)
    torch.nn.init.normal_(model.out[-1].weight, std=0.1)
    z = torch.randn(2, T, K, D)
    order = torch.tensor([2, 0, 3, 1])
    torch.testing.assert_close(model(z[:, :, order]), model(z)[:, :, order], atol=1e-5, rtol=1e-4)


def test_inert_slots_move_no_other_slot():
    """What an inert slot (a wall) does changes no other slot's prediction, though it is still
    predicted itself; without the mark it does change them. Step by step gives the same."""
    torch.manual_seed(3)
    model = InteractionLSTM(SMALL_DYNAMICS)
    randomise_dynamics_head(model)
    z = torch.randn(2, T, K, D)
    inert = torch.tensor([[False, True, False, False], [True, False, False, True]])
    moved = z.clone()
    moved[0, :, 1] += 2.0
    moved[1, :, [0, 3]] -= 2.0
    base, after = model(z, inert), model(moved, inert)
    torch.testing.assert_close(after[~inert[:, None, :].expand(-1, T, -1)], base[~inert[:, None, :].expand(-1, T, -1)])
    assert not torch.allclose(after[0, :, 1], base[0, :, 1])
    assert not torch.allclose(model(moved)[0, :, 0], model(z)[0, :, 0])
    state, steps = None, []
    for t in range(T):
        prediction, state = model.step(z[:, t], state, inert)
        steps.append(prediction)
    torch.testing.assert_close(torch.stack(steps, dim=1), base, atol=1e-5, rtol=1e-5)


def test_inert_walls_leave_the_walls_out_of_the_dynamics_loss():
    """With inert_walls, the dynamics loss is the mean over the other slots only, whatever the
    walls hold, and under any slot order; without it the walls' error counts."""
    torch.manual_seed(4)
    config = XPLConfig(reasoning=SMALL_REASONING, dynamics=SMALL_DYNAMICS, inert_walls=True)
    model = XPL(config)
    randomise_dynamics_head(model.dynamics)
    z, visible = torch.randn(2, T, K, D), torch.ones(2, T, K, dtype=torch.bool)
    walls = torch.tensor([[False, False, True, False], [False, False, False, True]])
    order = torch.stack([torch.randperm(K) for _ in range(2)])
    moved = z.clone()
    moved[0, :, 2] += 3.0
    moved[1, :, 3] -= 3.0
    model.train()
    base = model.losses(z, visible, order, walls=walls)["dynamics"]
    torch.testing.assert_close(model.losses(moved, visible, order, walls=walls)["dynamics"], base)
    model.eval()
    with torch.no_grad():
        error = ((model.dynamics(z[:, :-1], walls) - z[:, 1:]) ** 2).sum(-1)
        expected = error[~walls[:, None, :].expand(-1, T - 1, -1)].mean()
        torch.testing.assert_close(model.losses(z, visible, walls=walls)["dynamics"], expected)
        plain = XPL(XPLConfig(reasoning=SMALL_REASONING, dynamics=SMALL_DYNAMICS)).eval()
        plain.load_state_dict(model.state_dict())
        assert not torch.allclose(plain.losses(moved, visible, walls=walls)["dynamics"],
                                  plain.losses(z, visible, walls=walls)["dynamics"])


def test_unread_entries_reach_no_other_token():
    """Entries marked unread change no other entry's prediction, whatever they hold."""
    torch.manual_seed(11)
    model = ReasoningTransformer(SMALL_REASONING).eval()
    z, keep = torch.randn(2, T, K, D), torch.rand(2, T, K) > 0.4
    unread = torch.zeros(2, T, K, dtype=torch.bool)
    unread[:, :, 1] = True
    keep[:, :, 1] = True
    moved = z.clone()
    moved[:, :, 1] += 5.0
    with torch.no_grad():
        mean, scale = model(z, keep, unread)
        mean2, scale2 = model(moved, keep, unread)
        others = ~unread
        torch.testing.assert_close(mean2[others], mean[others])
        torch.testing.assert_close(scale2[others], scale[others])
        assert not torch.allclose(model(moved, keep)[0][~keep], model(z, keep)[0][~keep])


def test_transformer1_blind_to_walls_fills_alike_whatever_the_wall_holds():
    """With refill_ignores_walls, Transformer 1's fills and its refill loss do not depend on the
    walls' latents, the walls' own entries are rebuilt by no loss, and refine needs the walls."""
    torch.manual_seed(12)
    config = XPLConfig(reasoning=SMALL_REASONING, dynamics=SMALL_DYNAMICS, inert_walls=True,
                       refill_ignores_walls=True)
    model = XPL(config)
    z, visible = torch.randn(2, T, K, D), torch.rand(2, T, K) > 0.3
    visible[:, 0] = True
    walls = torch.tensor([[False, False, True, False], [True, False, False, False]])
    moved = z.clone()
    moved[0, :, 2] += 4.0
    moved[1, :, 0] -= 4.0
    refill = torch.zeros(2, T, K, dtype=torch.bool)
    refill[:, 1:3] = True                                   # walls' entries among them
    order = torch.stack([torch.randperm(K) for _ in range(2)])
    model.eval()
    with torch.no_grad():
        others = ~walls[:, None, :].expand_as(visible)
        torch.testing.assert_close(model.refine(moved, visible, walls)[others], model.refine(z, visible, walls)[others])
        model.train()
        losses = [model.losses(x, visible, order, refill=refill, walls=walls)["refill"] for x in (z, moved)]
        torch.testing.assert_close(losses[1], losses[0])
    with pytest.raises(ValueError, match="wall slots"):
        model.refine(z, visible)


def test_stop_input_gradient_leaves_transformer1_to_the_refill_loss():
    """With stop_input_gradient the dynamics loss trains the dynamics only; without it, it
    reaches Transformer 1 through its fills (stop_target_gradient keeps the target out)."""
    torch.manual_seed(5)
    z, visible = torch.randn(2, T, K, D), torch.rand(2, T, K) > 0.3
    for stop, reaches in ((True, False), (False, True)):
        model = XPL(XPLConfig(reasoning=SMALL_REASONING, dynamics=SMALL_DYNAMICS, stop_input_gradient=stop))
        randomise_dynamics_head(model.dynamics)
        model.losses(z, visible)["dynamics"].backward()
        gradients = [p.grad for p in model.transformer1.parameters()]
        assert any(g is not None and g.abs().sum() > 0 for g in gradients) == reaches
        assert all(p.grad is not None for p in model.dynamics.parameters())


def test_permute_slots_moves_everything_together():
    torch.manual_seed(3)
    z = torch.arange(2 * T * K, dtype=torch.float).reshape(2, T, K, 1).expand(-1, -1, -1, D)
    visible = z[..., 0] % 3 == 0
    pz, pv = permute_slots(z, visible)
    assert torch.equal(pv, pz[..., 0] % 3 == 0)
    for b in range(2):   # the same order in every frame
        order = [int(v) % K for v in pz[b, 0, :, 0]]
        assert sorted(order) == list(range(K))
        assert torch.equal(pz[b, :, :, 0] % K, torch.tensor(order).expand(T, -1).float())


def toy_latents(videos=64, seed=0):
    """Objects moving at constant velocity, occluded for a stretch of frames."""
    g = torch.Generator().manual_seed(seed)
    start, velocity = torch.randn(videos, 1, K, D, generator=g), 0.3 * torch.randn(videos, 1, K, D, generator=g)
    z = start + velocity * torch.arange(T).view(1, T, 1, 1)
    visible = torch.ones(videos, T, K, dtype=torch.bool)
    visible[:, 3:5, 1] = False
    empty = torch.rand(videos, generator=g) < 0.5          # half the videos have an empty last slot
    z[empty, :, K - 1] = 0.0
    visible[empty, :, K - 1] = False
    return z, visible


def test_xpl_training_lowers_both_losses():
    torch.manual_seed(4)
    model = XPL(XPLConfig(reasoning=SMALL_REASONING, dynamics=SMALL_DYNAMICS))
    optimiser = torch.optim.Adam(model.parameters(), lr=3e-3)
    z, visible = toy_latents()
    model.train()
    first = model.losses(z, visible)
    for _ in range(60):
        losses = model.losses(z, visible)
        optimiser.zero_grad()
        losses["loss"].backward()
        optimiser.step()
    assert losses["dynamics"] < 0.3 * first["dynamics"]
    assert losses["mae"] < first["mae"] - 1.0
    # here nothing in the other slots tells whether the hidden one is empty, so the best the
    # existence head can do is the base rate (1 slot in 8 empty: entropy 0.38 nats)
    assert losses["existence"] < 0.45 < first["existence"]


def test_plato_has_no_reasoning_and_predicts_directly():
    model = XPL(XPLConfig(dynamics=DynamicsConfig(latent_dim=D, hidden=16, lstm=16, buffer_heads=2, residual=False),
                          use_reasoning=False))
    assert not hasattr(model, "transformer1")
    z, visible = toy_latents(4)
    assert torch.equal(model.refine(z, visible), z)
    assert set(model.losses(z, visible)) == {"dynamics", "loss"}
    assert not hasattr(model, "existence")


def test_explain_hides_a_never_seen_slot():
    model = XPL(XPLConfig(reasoning=SMALL_REASONING, dynamics=SMALL_DYNAMICS)).eval()
    z, visible = toy_latents(2)
    visible[0, :, 3] = False          # video 0: slot 3 never seen; video 1: everything seen somewhere
    mean, scale, slot = model.explain(z, visible)
    assert slot.tolist() == [3, -1]
    assert torch.equal(mean[1], z[1]) and torch.all(scale[1] == 0)
    assert not torch.equal(mean[0, :, 3], z[0, :, 3]) and torch.all(scale[0, :, 3] > 0)
    assert torch.equal(mean[0, :, :3], z[0, :, :3])


def test_transformer2_reads_transformer1s_fills_and_proposes_only_the_explained_slot():
    torch.manual_seed(0)
    visible = torch.ones(2, T, K, dtype=torch.bool)
    visible[:, :, 3] = False                         # never seen: the slot to explain
    visible[:, 2:5, 0] = False                       # occluded: Transformer 1 fills these frames
    refined = torch.randn(2, T, K, D)
    other = refined.clone()
    other[:, 2:5, 0] += 3.0                          # other fills of the occluded frames
    model = XPL(XPLConfig(reasoning=SMALL_REASONING, dynamics=SMALL_DYNAMICS)).eval()
    with torch.no_grad():
        first, scale, slot = model.explain(refined, visible)
        second, _, _ = model.explain(other, visible)
    assert slot.tolist() == [3, 3]
    assert torch.equal(first[:, :, :3], refined[:, :, :3])       # only the explained slot is proposed
    assert torch.all(scale[:, :, :3] == 0) and torch.all(scale[:, :, 3] > 0)
    assert not torch.equal(first[:, :, 3], second[:, :, 3])      # the fills are part of what it reads


@pytest.mark.parametrize("residual", [True, False])
def test_the_dynamics_step_by_step_matches_the_whole_sequence(residual):
    torch.manual_seed(0)
    dynamics = InteractionLSTM(DynamicsConfig(latent_dim=5, hidden=16, lstm=12, buffer_heads=2, residual=residual))
    randomise_dynamics_head(dynamics)
    z = torch.randn(3, 6, 4, 5)
    whole, state, steps = dynamics(z), None, []
    for t in range(z.shape[1]):
        prediction, state = dynamics.step(z[:, t], state)
        steps.append(prediction)
    torch.testing.assert_close(torch.stack(steps, dim=1), whole, atol=1e-5, rtol=1e-5)


def test_the_dynamics_step_for_some_slots_is_the_whole_steps_rows():
    """Stepping only the slots whose prediction is read gives their rows of the full step, frame
    after frame, every slot still acting on them."""
    torch.manual_seed(0)
    dynamics = InteractionLSTM(DynamicsConfig(latent_dim=5, hidden=16, lstm=12, buffer_heads=2))
    randomise_dynamics_head(dynamics)
    z, receivers, inert = torch.randn(3, 6, 4, 5), torch.tensor([0, 2]), torch.tensor([[False, True, False, False]])
    full = some = None
    for t in range(z.shape[1]):
        whole, full = dynamics.step(z[:, t], full, inert)
        chosen, some = dynamics.step(z[:, t], some, inert, receivers)
        torch.testing.assert_close(chosen, whole[:, receivers], atol=1e-6, rtol=1e-6)
    assert some.hidden.shape == (3 * 2, 12)
    torch.testing.assert_close(some.hidden, full.hidden.reshape(3, 4, 12)[:, receivers].reshape(6, 12))


def test_outside_entries_join_the_refill_loss_as_the_cached_latent():
    """Hidden entries of seen objects marked outside the picture are rebuilt towards the cache's
    latent there, with the refill spans; visible or never-seen entries marked outside are not."""
    torch.manual_seed(1)
    z, visible = torch.randn(2, T, K, D), torch.ones(2, T, K, dtype=torch.bool)
    visible[:, :3, 0] = False               # slot 0 comes into the picture at frame 3
    visible[:, :, 1] = False                # slot 1 is never seen
    refill = torch.zeros(2, T, K, dtype=torch.bool)
    refill[:, 5:7, 2] = True
    outside = torch.zeros(2, T, K, dtype=torch.bool)
    outside[:, :4, :2] = True               # frame 3 of slot 0 is visible, slot 1 is never seen
    model = XPL(XPLConfig(reasoning=SMALL_REASONING, dynamics=SMALL_DYNAMICS)).eval()
    with torch.no_grad():
        without, marked = (model.losses(z, visible, refill=refill, outside=o)["refill"] for o in (None, outside))
        refined = model.transformer1(z, occlusion_keep(visible) & ~refill)[0]
    square = ((refined - z) ** 2).sum(-1)
    rebuilt = refill.clone()
    rebuilt[:, :3, 0] = True
    torch.testing.assert_close(without, (square * refill).sum() / refill.sum())
    torch.testing.assert_close(marked, (square * rebuilt).sum() / rebuilt.sum())
