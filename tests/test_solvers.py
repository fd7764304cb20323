import math

import pytest
import torch
from torch import nn

from mfm.model import ModelConfig, MotionFlowTransformer
from mfm.solvers import (
    FIXED_STEP_SOLVERS,
    check_grid,
    draw_noise,
    flow_map_amplification,
    guided_velocity,
    initial_noise,
    noise_generator_device,
    sample,
    sample_lengths,
    seeded_generators,
    solve,
    uniform_grid,
    zero_padded_frames,
)

STAGES = {"euler": 1, "midpoint": 2, "heun": 2, "rk4": 4}
ORDER = {"euler": 1, "midpoint": 2, "heun": 2, "rk4": 4}


class CountingField:
    """A velocity function that counts its own calls, independently of the solver's counter."""

    def __init__(self, fn):
        self.fn = fn
        self.calls = 0

    def __call__(self, x, t):
        assert t.shape == (x.shape[0],)
        self.calls += 1
        return self.fn(x, t)


def linear_field(rate: float):
    return lambda x, t: rate * x


def x0_batch(dtype=torch.float64):
    return torch.randn(3, 5, 4, generator=torch.Generator().manual_seed(1), dtype=dtype)


def test_solver_registry_matches_the_documented_methods():
    assert set(FIXED_STEP_SOLVERS) == set(STAGES)
    for name, tableau in FIXED_STEP_SOLVERS.items():
        assert tableau.num_stages == STAGES[name]
        assert math.isclose(sum(tableau.b), 1.0)  # consistency: exact for a constant field


@pytest.mark.parametrize("solver", sorted(STAGES))
def test_constant_field_is_integrated_exactly_with_the_documented_nfe(solver):
    x0 = x0_batch()
    c = torch.linspace(-1, 1, 4, dtype=torch.float64)
    field = CountingField(lambda x, t: c.expand_as(x))
    result = solve(field, x0, solver=solver, steps=7)
    torch.testing.assert_close(result.x1, x0 + c, rtol=0, atol=1e-12)
    assert result.nfe == field.calls == 7 * STAGES[solver]
    assert result.x1_hat is None and result.x1_hat_times is None
    torch.testing.assert_close(result.grid, uniform_grid(7))


@pytest.mark.parametrize("solver", sorted(STAGES))
def test_linear_field_error_has_the_solvers_order(solver):
    # dx/dt = λx has x(1) = x0·e^λ; halving the step divides the global error by ~2^order.
    rate, x0 = -1.3, x0_batch()
    exact = x0 * math.exp(rate)
    errors = [(solve(linear_field(rate), x0, solver=solver, steps=n).x1 - exact).abs().max().item() for n in (8, 16)]
    ratio = errors[0] / errors[1]
    assert 0.8 * 2 ** ORDER[solver] < ratio < 1.25 * 2 ** ORDER[solver], (errors, ratio)
    # Exact Runge-Kutta amplification factors: Euler (1 + λh)^N, midpoint/Heun (1 + λh + (λh)²/2)^N.
    h = rate / 8
    factor = {"euler": 1 + h, "midpoint": 1 + h + h * h / 2, "heun": 1 + h + h * h / 2,
              "rk4": 1 + h + h**2 / 2 + h**3 / 6 + h**4 / 24}[solver]
    torch.testing.assert_close(solve(linear_field(rate), x0, solver=solver, steps=8).x1, x0 * factor**8)


@pytest.mark.parametrize(
    ("solver", "power"), [("midpoint", 1), ("heun", 1), ("rk4", 3)]
)
def test_time_dependent_polynomial_fields_are_exact(solver, power):
    # v = (p+1)·t^p integrates to x0 + 1; midpoint/Heun are exact for p = 1, RK4 (Simpson) up to p = 3.
    x0 = x0_batch()
    field = lambda x, t: ((power + 1) * t**power).view(-1, 1, 1).expand_as(x)
    torch.testing.assert_close(solve(field, x0, solver=solver, steps=3).x1, x0 + 1.0, rtol=0, atol=1e-12)


def test_euler_follows_an_arbitrary_grid():
    grid = [0.0, 0.1, 0.5, 0.6, 1.0]
    x0 = x0_batch()
    field = CountingField(lambda x, t: t.view(-1, 1, 1).expand_as(x))
    result = solve(field, x0, grid=grid)
    expected = sum(t * (t_next - t) for t, t_next in zip(grid[:-1], grid[1:]))
    torch.testing.assert_close(result.x1, x0 + expected)
    assert result.nfe == field.calls == 4
    torch.testing.assert_close(result.grid, torch.tensor(grid, dtype=torch.float64))


@pytest.mark.parametrize("grid", [[0.0], [0.0, 0.5, 0.5, 1.0], [0.0, 0.7, 0.3, 1.0], [-0.1, 1.0], [0.0, 1.2]])
def test_bad_grids_are_rejected(grid):
    with pytest.raises(ValueError, match="grid"):
        check_grid(grid)


def test_unknown_solver_is_rejected_with_the_known_names():
    with pytest.raises(ValueError, match="unknown solver 'nope'.*euler.*dopri5"):
        solve(linear_field(1.0), x0_batch(), solver="nope")


def test_dopri5_is_accurate_and_counts_every_evaluation():
    rate, x0 = 0.7, x0_batch()
    field = CountingField(linear_field(rate))
    result = solve(field, x0, solver="dopri5", rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(result.x1, x0 * math.exp(rate), rtol=1e-7, atol=1e-7)
    assert result.nfe == field.calls > 6
    # Looser tolerances take fewer evaluations.
    loose = CountingField(linear_field(rate))
    assert solve(loose, x0, solver="dopri5", rtol=1e-3, atol=1e-3).nfe == loose.calls < field.calls


def test_torchdiffeq_fixed_grid_methods_step_on_the_grid():
    x0 = x0_batch()
    field = CountingField(linear_field(-0.5))
    result = solve(field, x0, solver="explicit_adams", steps=5)
    assert result.nfe == field.calls
    torch.testing.assert_close(result.x1, x0 * math.exp(-0.5), rtol=1e-3, atol=1e-3)


@pytest.mark.parametrize("solver", sorted(STAGES))
def test_x1_hat_trajectory_has_one_estimate_per_step(solver):
    rate, x0 = -0.9, x0_batch()
    grid = [0.0, 0.25, 0.4, 0.8, 1.0]
    result = solve(linear_field(rate), x0, solver=solver, grid=grid, return_trajectory=True)
    assert result.x1_hat.shape == (4, *x0.shape)
    torch.testing.assert_close(result.x1_hat_times, torch.tensor(grid[:-1], dtype=torch.float64))
    # Each estimate is the state at the step start plus (1 - t)·v there: recompute the states step by step.
    state = x0
    for i, (t, t_next) in enumerate(zip(grid[:-1], grid[1:])):
        torch.testing.assert_close(result.x1_hat[i], state + (1 - t) * rate * state)
        state = solve(linear_field(rate), state, solver=solver, grid=[t, t_next]).x1
    torch.testing.assert_close(state, result.x1)
    assert result.nfe == 4 * STAGES[solver]


def test_last_euler_estimate_is_the_result():
    result = solve(linear_field(0.3), x0_batch(), steps=6, return_trajectory=True)
    torch.testing.assert_close(result.x1_hat[-1], result.x1)


def test_adaptive_trajectory_records_every_evaluation():
    field = CountingField(linear_field(0.4))
    result = solve(field, x0_batch(), solver="dopri5", return_trajectory=True)
    assert result.x1_hat.shape[0] == result.x1_hat_times.shape[0] == result.nfe == field.calls


# ---------------------------------------------------------------------------------------------------
# classifier-free guidance


class ToyModel(nn.Module):
    """Same forward signature as MotionFlowTransformer; the condition is zeroed where cond_mask is True."""

    def __init__(self, cond_dim: int = 3, feature_dim: int = 4):
        super().__init__()
        self.weight = nn.Parameter(torch.randn(cond_dim, feature_dim, generator=torch.Generator().manual_seed(0)))
        self.batches: list[int] = []

    def forward(self, x, t, cond, lengths=None, *, cond_mask=None):
        self.batches.append(x.shape[0])
        if cond_mask is not None:
            cond = cond * (~cond_mask).unsqueeze(1)
        v = torch.tanh(x) * (1 + t.view(-1, 1, 1)) + (cond @ self.weight).unsqueeze(1) + 0.1
        if lengths is not None:
            v = v * (torch.arange(x.shape[1]).unsqueeze(0) < lengths.unsqueeze(1)).unsqueeze(-1)
        return v


def toy_inputs(batch=3, frames=6):
    g = torch.Generator().manual_seed(5)
    return (torch.randn(batch, frames, 4, generator=g), torch.rand(batch, generator=g),
            torch.randn(batch, 3, generator=g))


def test_guidance_scale_one_is_the_conditional_field_in_one_pass():
    model = ToyModel()
    x, t, cond = toy_inputs()
    v = guided_velocity(model, cond, scale=1.0)(x, t)
    assert model.batches == [3]
    torch.testing.assert_close(v, model(x, t, cond))


def test_batched_guidance_equals_two_separate_passes():
    model = ToyModel()
    x, t, cond = toy_inputs()
    lengths = torch.tensor([6, 4, 2])
    v = guided_velocity(model, cond, scale=2.5, lengths=lengths)(x, t)
    assert model.batches == [6]  # one forward of the doubled batch
    v_cond = model(x, t, cond, lengths, cond_mask=torch.zeros(3, dtype=torch.bool))
    v_uncond = model(x, t, cond, lengths, cond_mask=torch.ones(3, dtype=torch.bool))
    torch.testing.assert_close(v, v_uncond + 2.5 * (v_cond - v_uncond))
    assert not torch.allclose(v, v_cond)


def test_conditional_channels_take_the_conditional_field_and_the_rest_is_guided():
    """model.guided_features='pose': the masked channels follow the conditional field unguided, the others are
    the usual mix, still from one batched pass; an all-False mask is no exception; a mask of the wrong size is
    refused."""
    model = ToyModel()
    x, t, cond = toy_inputs()
    mask = torch.tensor([True, False, False, True])
    v = guided_velocity(model, cond, scale=2.5, conditional_channels=mask)(x, t)
    assert model.batches == [6]
    v_cond = model(x, t, cond, cond_mask=torch.zeros(3, dtype=torch.bool))
    v_uncond = model(x, t, cond, cond_mask=torch.ones(3, dtype=torch.bool))
    mixed = v_uncond + 2.5 * (v_cond - v_uncond)
    torch.testing.assert_close(v[..., mask], v_cond[..., mask])
    torch.testing.assert_close(v[..., ~mask], mixed[..., ~mask])
    assert not torch.allclose(v[..., mask], mixed[..., mask])
    none = guided_velocity(model, cond, scale=2.5, conditional_channels=torch.zeros(4, dtype=torch.bool))(x, t)
    torch.testing.assert_close(none, mixed)
    with pytest.raises(ValueError, match="conditional_channels"):
        guided_velocity(model, cond, scale=2.5, conditional_channels=torch.ones(3, dtype=torch.bool))(x, t)


def test_pose_guidance_leaves_the_root_motion_channels_to_the_conditional_field():
    """guided_feature_mask('pose'): the root's rotation/linear velocity, its height and every joint's velocity;
    'all': no mask."""
    from mfm.guidance import guided_feature_mask
    from mfm.layout import FeatureLayout
    from mfm.skeleton import get_skeleton

    for name, dim in (("humanml3d", 263), ("kit", 251)):
        skeleton = get_skeleton(name)
        mask = guided_feature_mask("pose", skeleton)
        slices = FeatureLayout(skeleton).slices
        assert mask.shape == (dim,) and mask[:4].all() and mask[slices["local_vel"]].all()
        assert int(mask.sum()) == 4 + 3 * skeleton.num_joints
        assert not mask[slices["ric"]].any() and not mask[slices["rot6d"]].any() and not mask[slices["contacts"]].any()
        assert guided_feature_mask("all", skeleton) is None
    with pytest.raises(ValueError, match="guided_features"):
        guided_feature_mask("trajectory", get_skeleton("humanml3d"))


def test_guidance_scale_zero_is_the_unconditional_field_and_null_cond_is_used():
    model = ToyModel()
    x, t, cond = toy_inputs()
    torch.testing.assert_close(guided_velocity(model, cond, scale=0.0)(x, t), model(x, t, torch.zeros_like(cond)))
    assert model.batches[0] == 3

    class ExplicitNull(ToyModel):  # ignores cond_mask: only an explicit null condition makes it unconditional
        def forward(self, x, t, cond, lengths=None, *, cond_mask=None):
            return super().forward(x, t, cond, lengths)

    explicit = ExplicitNull()
    null = torch.full((3,), 0.5)
    v = guided_velocity(explicit, cond, scale=3.0, null_cond=null)(x, t)
    v_null = explicit(x, t, null.expand_as(cond))
    torch.testing.assert_close(v, v_null + 3.0 * (explicit(x, t, cond) - v_null))


def test_guidance_works_with_the_real_model_and_action_ids():
    config = ModelConfig(feature_dim=5, latent_dim=16, ff_dim=32, num_layers=1, num_heads=2, num_actions=4,
                         dropout=0.0)
    model = MotionFlowTransformer(config).eval()
    x = torch.randn(2, 7, 5, generator=torch.Generator().manual_seed(0))
    t, actions, lengths = torch.tensor([0.2, 0.9]), torch.tensor([1, 3]), torch.tensor([7, 5])
    with torch.no_grad():
        v = guided_velocity(model, actions, scale=2.0, lengths=lengths)(x, t)
        v_cond = model(x, t, actions, lengths, cond_mask=torch.zeros(2, dtype=torch.bool))
        v_uncond = model(x, t, actions, lengths, cond_mask=torch.ones(2, dtype=torch.bool))
    torch.testing.assert_close(v, v_uncond + 2.0 * (v_cond - v_uncond), rtol=1e-5, atol=1e-5)


# ---------------------------------------------------------------------------------------------------
# sampling


def tiny_text_model(feature_dim=6, cond_dim=8):
    torch.manual_seed(0)
    config = ModelConfig(feature_dim=feature_dim, latent_dim=16, ff_dim=32, num_layers=2, num_heads=2,
                         cond_dim=cond_dim, dropout=0.1)
    return MotionFlowTransformer(config).eval()


def test_sample_is_deterministic_given_a_seed_and_zero_on_padding():
    model = tiny_text_model()
    cond = torch.randn(3, 8, generator=torch.Generator().manual_seed(2))
    lengths = [10, 4, 7]
    first = sample(model, cond, lengths, num_frames=10, steps=5, guidance=2.5, seed=123)
    again = sample(model, cond, lengths, num_frames=10, steps=5, guidance=2.5, seed=123)
    other = sample(model, cond, lengths, num_frames=10, steps=5, guidance=2.5, seed=124)
    assert first.x1.shape == (3, 10, 6)
    assert torch.equal(first.x1, again.x1)
    assert not torch.allclose(first.x1, other.x1)
    assert first.nfe == 5
    for b, length in enumerate(lengths):
        assert torch.count_nonzero(first.x1[b, length:]) == 0
        assert torch.count_nonzero(first.x1[b, :length]) == length * 6
    # An explicit generator seeded the same way is the same draw.
    from_generator = sample(model, cond, lengths, num_frames=10, steps=5, generator=torch.Generator().manual_seed(123))
    assert torch.equal(first.x1, from_generator.x1)


def test_sample_with_guidance_one_matches_a_conditional_solve_from_the_same_noise():
    model = tiny_text_model()
    cond = torch.randn(2, 8, generator=torch.Generator().manual_seed(3))
    lengths = torch.tensor([9, 9])
    result = sample(model, cond, lengths, num_frames=9, solver="heun", steps=3, guidance=1.0, seed=7,
                    return_trajectory=True)
    x0 = initial_noise((2, 9, 6), seed=7)
    with torch.no_grad():
        expected = solve(lambda x, t: model(x, t, cond, lengths), x0, solver="heun", steps=3)
    torch.testing.assert_close(result.x1, expected.x1)
    assert result.nfe == 6 and result.x1_hat.shape == (3, 2, 9, 6)


def test_sample_integrates_from_given_noise_with_its_padding_zeroed():
    model = tiny_text_model()
    cond = torch.randn(2, 8, generator=torch.Generator().manual_seed(4))
    lengths = [9, 5]
    drawn = sample(model, cond, lengths, num_frames=9, steps=4, seed=11)
    noise = draw_noise((2, 9, 6), torch.Generator().manual_seed(11), lengths=torch.tensor(lengths))
    noise[1, 5:] = 7.0  # padding given as garbage is zeroed, as the sampler's own draw is
    assert torch.equal(sample(model, cond, lengths, num_frames=9, steps=4, noise=noise).x1, drawn.x1)
    with pytest.raises(ValueError, match="noise must be"):
        sample(model, cond, lengths, num_frames=9, steps=4, noise=noise[:, :8])


@pytest.mark.parametrize("rate", [-0.5, 0.0, 2.0])
def test_flow_map_amplification_of_a_linear_field_is_its_euler_growth(rate):
    """v = k·x: 10 Euler steps map x0 to (1 + k/10)^10 · x0, so every direction is amplified by exactly that
    factor; what the map does on padded frames does not count."""
    x0, direction = x0_batch(), torch.randn(3, 5, 4, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    lengths = torch.tensor([5, 3, 1])

    def solve_from(noise):
        out = solve(linear_field(rate), noise, solver="euler", steps=10).x1.clone()
        out[1, 3:] = torch.randn(2, 4, dtype=out.dtype)  # padding: garbage that differs between the two calls
        return out

    amplification = flow_map_amplification(solve_from, x0, direction, lengths)
    torch.testing.assert_close(amplification, torch.full((3,), (1 + rate / 10) ** 10, dtype=torch.float32))
    with pytest.raises(ValueError, match="perturbation"):
        flow_map_amplification(solve_from, x0, direction, lengths, perturbation=0.0)


def test_flow_map_amplification_sees_a_map_that_ignores_or_scatters_the_noise():
    x0, direction = x0_batch(), torch.randn(3, 5, 4, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    lengths = torch.tensor([5, 5, 5])
    constant = flow_map_amplification(lambda noise: torch.ones_like(noise), x0, direction, lengths)
    assert torch.equal(constant, torch.zeros(3))
    # A map with sharp basins (the sign of each element): a perturbation across a boundary moves the endpoint by 2.
    near = x0.clone()
    near[0, 0, 0] = 1e-5
    sharp = flow_map_amplification(torch.sign, near, torch.ones_like(near) * -1, lengths)
    assert sharp[0] > 100 and torch.equal(sharp[1:], torch.zeros(2))


def test_sample_with_dopri5_reports_counted_evaluations():
    model = tiny_text_model()
    cond = torch.randn(2, 8, generator=torch.Generator().manual_seed(4))
    result = sample(model, cond, [5, 3], num_frames=5, solver="dopri5", guidance=2.5, rtol=1e-3, atol=1e-3)
    assert result.nfe >= 6 and result.nfe % 1 == 0
    assert torch.count_nonzero(result.x1[1, 3:]) == 0


def test_sample_rejects_bad_lengths():
    model = tiny_text_model()
    with pytest.raises(ValueError, match=r"lengths must be in \[1, 10\]"):
        sample(model, torch.zeros(2, 8), [11, 3], num_frames=10)
    with pytest.raises(ValueError, match="batch"):
        sample(model, torch.zeros(3, 8), [5, 3], num_frames=10)


def test_zero_padded_frames_masks_the_velocity():
    fn = zero_padded_frames(lambda x, t: torch.ones_like(x), torch.tensor([2, 3]))
    v = fn(torch.zeros(2, 4, 1), torch.zeros(2))
    assert v[:, :, 0].tolist() == [[1, 1, 0, 0], [1, 1, 1, 0]]


def test_zero_padded_frames_leaves_a_window_no_motion_is_shorter_than_untouched():
    field = lambda x, t: torch.full_like(x, 2.0)  # noqa: E731
    fn = zero_padded_frames(field, torch.tensor([4, 4]))
    assert torch.equal(fn(torch.zeros(2, 4, 1), torch.zeros(2)), torch.full((2, 4, 1), 2.0))
    # the same lengths in a wider window still zero the frames past them
    assert fn(torch.zeros(2, 6, 1), torch.zeros(2))[:, :, 0].tolist() == [[2, 2, 2, 2, 0, 0]] * 2


class LengthsSpy(nn.Module):
    """The model, recording the lengths each pass was given (None: the unmasked pass)."""

    def __init__(self, model):
        super().__init__()
        self.model = model
        self.config = model.config
        self.seen = []

    def forward(self, x, t, cond, lengths=None, **kwargs):
        self.seen.append(None if lengths is None else lengths.tolist())
        return self.model(x, t, cond, lengths, **kwargs)


class FullLengthsGiven(nn.Module):
    """The model, always handed the lengths (the masked pass), as the samplers did before PassLengths."""

    def __init__(self, model):
        super().__init__()
        self.model = model
        self.config = model.config

    def forward(self, x, t, cond, lengths=None, **kwargs):
        if lengths is None:
            lengths = torch.full((x.shape[0],), x.shape[1], dtype=torch.long)
        return self.model(x, t, cond, lengths, **kwargs)


@pytest.mark.parametrize("guidance", [2.5, 1.0, 0.0])
def test_passes_whose_window_every_motion_fills_run_unmasked_and_others_keep_their_lengths(guidance):
    model = LengthsSpy(tiny_text_model())
    cond = torch.randn(2, 8, generator=torch.Generator().manual_seed(6))
    sample(model, cond, [9, 9], num_frames=9, steps=3, guidance=guidance, seed=1)
    assert model.seen == [None] * 3
    model.seen.clear()
    sample(model, cond, [9, 5], num_frames=9, steps=3, guidance=guidance, seed=1)
    halves = 2 if guidance not in (0.0, 1.0) else 1
    assert model.seen == [[9, 5] * halves] * 3


@pytest.mark.parametrize("variant", [
    {}, {"length_token": True}, {"progress_positions": True}, {"frames_per_token": 2}, {"positional": "bpe"},
])
def test_a_motion_filling_its_window_is_sampled_bit_identical_unmasked_or_masked(variant):
    """The unmasked pass is the same arithmetic as the masked one when no frame is padding, in every layout that
    reads the lengths (length token, progress positions, grouped frames, blended positions)."""
    torch.manual_seed(0)
    config = ModelConfig(feature_dim=6, latent_dim=16, ff_dim=32, num_layers=2, num_heads=2, cond_dim=8,
                         max_frames=16, **variant)
    model = MotionFlowTransformer(config).eval()
    cond = torch.randn(3, 8, generator=torch.Generator().manual_seed(7))
    unmasked = sample(model, cond, [11, 11, 11], num_frames=11, steps=4, guidance=2.5, seed=3)
    masked = sample(FullLengthsGiven(model), cond, [11, 11, 11], num_frames=11, steps=4, guidance=2.5, seed=3)
    assert torch.equal(unmasked.x1, masked.x1)
    assert torch.count_nonzero(unmasked.x1) == unmasked.x1.numel()


def test_sample_lengths_draws_from_the_distribution_deterministically():
    pool = [40, 40, 40, 120, 196]
    first = sample_lengths(pool, 500, torch.Generator().manual_seed(0))
    again = sample_lengths(pool, 500, torch.Generator().manual_seed(0))
    assert torch.equal(first, again) and first.dtype == torch.long
    assert set(first.tolist()) == {40, 120, 196}
    assert 0.5 < (first == 40).float().mean().item() < 0.7  # 3/5 of the pool
    clipped = sample_lengths(pool, 100, torch.Generator().manual_seed(0), max_length=100)
    assert clipped.max().item() == 100
    with pytest.raises(ValueError, match="non-empty"):
        sample_lengths([], 3)


def test_draw_noise_per_motion_depends_on_seed_and_length_only():
    lengths = torch.tensor([5, 3])
    batched = draw_noise((2, 5, 4), seeded_generators([1, 2]), lengths=lengths)
    assert batched[1, 3:].abs().max().item() == 0.0
    torch.testing.assert_close(batched[1, :3], initial_noise((3, 4), seed=2), rtol=0, atol=0)
    torch.testing.assert_close(batched[0], initial_noise((5, 4), seed=1), rtol=0, atol=0)
    # One generator: the whole block in one draw, as initial_noise.
    torch.testing.assert_close(draw_noise((2, 5, 4), torch.Generator().manual_seed(9)),
                               initial_noise((2, 5, 4), seed=9), rtol=0, atol=0)
    # No lengths: every frame of every row.
    assert draw_noise((2, 5, 4), seeded_generators([1, 2]))[1, 3:].abs().min().item() > 0.0


def test_noise_device_draws_on_the_cpu_by_default_or_on_the_models_device():
    assert noise_generator_device("cpu", "cuda:1") == torch.device("cpu")
    assert noise_generator_device("model", "cuda:1") == torch.device("cuda:1")
    assert noise_generator_device("model", torch.device("cpu")) == torch.device("cpu")
    with pytest.raises(ValueError, match="noise_device"):
        noise_generator_device("gpu", "cpu")
    assert all(g.device == torch.device("cpu") for g in seeded_generators([1, 2]))
    model = MotionFlowTransformer(ModelConfig(feature_dim=4, cond_dim=3, latent_dim=16, num_layers=1, num_heads=2,
                                              ff_dim=16, dropout=0.0)).eval()
    cond, lengths = torch.randn(2, 3), torch.tensor([6, 4])
    run = dict(num_frames=6, steps=2, guidance=1.5, seed=4)
    # on a CPU model both draw from a CPU generator: the same motions
    torch.testing.assert_close(sample(model, cond, lengths, noise_device="model", **run).x1,
                               sample(model, cond, lengths, **run).x1, rtol=0, atol=0)
    with pytest.raises(ValueError, match="noise_device"):
        sample(model, cond, lengths, noise_device="gpu", **run)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (the CPU case is tested above)")
def test_noise_on_a_cuda_model_is_drawn_there_and_keeps_the_per_motion_contract():
    generators = seeded_generators([1, 2], device="cuda")
    noise = draw_noise((2, 5, 4), generators, lengths=torch.tensor([5, 3]), device="cuda")
    assert noise.device.type == "cuda" and noise[1, 3:].abs().max().item() == 0.0
    again = draw_noise((1, 3, 4), seeded_generators([2], device="cuda"), lengths=[3], device="cuda")
    torch.testing.assert_close(noise[1:, :3], again, rtol=0, atol=0)  # a motion's noise: its seed and length only
    assert not torch.equal(noise.cpu(), draw_noise((2, 5, 4), seeded_generators([1, 2]), lengths=torch.tensor([5, 3])))


def test_is_adaptive_names_torchdiffeqs_adaptive_methods_only():
    from mfm.solvers import is_adaptive

    assert is_adaptive("dopri5") and is_adaptive("adaptive_heun")
    assert not any(is_adaptive(m) for m in ("euler", "midpoint", "rk4", "implicit_adams", "ddpm", "unknown"))
