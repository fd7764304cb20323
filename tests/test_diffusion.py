import math

import pytest
import torch

from mfm.diffusion import (
    DIFFUSION_PRESETS,
    DenoisedRange,
    GaussianDiffusion,
    cosine_alpha_bar,
    diffusion_from_preset,
    discretized_gaussian_log_likelihood,
    learned_variance_transformer,
    masked_mean,
    normal_kl,
    space_timesteps,
)
from mfm.diffusion_sampling import (
    copy_reference_root,
    ddim_sample,
    ddpm_sample,
    replacement_edit,
    reverse_diffusion,
    rotation_6d_range,
    sample_diffusion,
)
from mfm.editing import edit_mask
from mfm.features import features_to_joints
from mfm.flow import masked_mse
from mfm.guidance import classifier_free_guidance
from mfm.layout import FeatureLayout
from mfm.model import ModelConfig, valid_frame_mask
from mfm.skeleton import HUMANML3D, KIT
from mfm.solvers import seeded_generators

COSINE = GaussianDiffusion()  # 1000 cosine steps, built once (the tables are read-only)


# The 1000-step loops run thousands of tiny ops: single-threaded (10x faster measured under load).
pytestmark = pytest.mark.usefixtures("single_thread")


def closed_form_alpha_bar(step: int, num_steps: int = 1000, s: float = 0.008) -> float:
    """ᾱ after step+1 forward steps: f(t)/f(0), f(t) = cos²(((t/T) + s)/(1 + s)·π/2)."""
    f = lambda t: math.cos(((t / num_steps) + s) / (1 + s) * math.pi / 2) ** 2  # noqa: E731
    return f(step + 1) / f(0)


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


class AffineDenoiser:
    """A deterministic toy denoiser whose output a hand computation can reproduce; counts its calls."""

    def __init__(self, channels_factor: int = 1):
        self.channels_factor = channels_factor
        self.calls = 0
        self.batch_sizes = []

    def __call__(self, x, t, cond, lengths=None, *, cond_mask=None, generator=None):
        self.calls += 1
        self.batch_sizes.append(x.shape[0])
        keep = torch.ones(x.shape[0], dtype=x.dtype) if cond_mask is None else (~cond_mask).to(x.dtype)
        out = 0.5 * x * (1 + t[:, None, None]) + (cond.sum(dim=1) * keep)[:, None, None]
        if self.channels_factor == 2:
            out = torch.cat([out, torch.tanh(x + cond.sum(dim=1)[:, None, None])], dim=-1)
        return out


def point_eps_oracle(diffusion: GaussianDiffusion, point: torch.Tensor):
    """Exact ε for data concentrated on one point x*: ε = (x_t − √ᾱ·x*)/√(1 − ᾱ), ᾱ of the *training* step."""

    def denoise(x, t):
        step = torch.round(t.double() * diffusion.num_train_steps).long()
        alpha_bar = COSINE.alphas_cumprod[step].reshape(-1, 1, 1)
        return ((x - alpha_bar.sqrt() * point) / (1 - alpha_bar).sqrt()).to(x.dtype)

    return denoise


def gaussian_eps_oracle(mean: torch.Tensor, std: torch.Tensor):
    """Exact E[ε | x_t] for data ~ N(mean, std²) per feature: √(1 − ᾱ)(x − √ᾱ·mean)/(ᾱ·std² + 1 − ᾱ)."""

    def denoise(x, t):
        step = torch.round(t.double() * COSINE.num_train_steps).long()
        alpha_bar = COSINE.alphas_cumprod[step].reshape(-1, 1, 1)
        gain = (1 - alpha_bar).sqrt() / (alpha_bar * std**2 + 1 - alpha_bar)
        return (gain * (x - alpha_bar.sqrt() * mean)).to(x.dtype)

    return denoise


# ---------------------------------------------------------------------------------------------- schedule


@pytest.mark.parametrize("step", [0, 1, 10, 100, 250, 500, 750, 900, 990, 998])
def test_cosine_schedule_matches_the_closed_form(step):
    assert COSINE.alphas_cumprod[step].item() == pytest.approx(closed_form_alpha_bar(step), rel=1e-9, abs=1e-15)
    assert COSINE.alphas_cumprod.dtype == torch.float64


def test_cosine_schedule_caps_the_last_beta_only():
    betas = COSINE.betas
    assert betas[-1].item() == 0.999  # 1 − f(1)/f(999/1000) = 1 is capped
    assert bool((betas[:-1] < 0.999).all()) and bool((betas > 0).all())
    assert bool((betas[1:] > betas[:-1]).all())
    # The capped last step: ᾱ[999] = ᾱ[998]·(1 − 0.999).
    assert COSINE.alphas_cumprod[-1].item() == pytest.approx(closed_form_alpha_bar(998) * 1e-3, rel=1e-9)
    assert cosine_alpha_bar(0.0) == pytest.approx(math.cos(0.008 / 1.008 * math.pi / 2) ** 2)


def test_linear_schedule_is_ho_et_al_scaled_to_the_step_count():
    torch.testing.assert_close(GaussianDiffusion(1000, "linear").betas[[0, -1]],
                               torch.tensor([1e-4, 0.02], dtype=torch.float64))
    torch.testing.assert_close(GaussianDiffusion(100, "linear").betas[[0, -1]],
                               torch.tensor([1e-3, 0.2], dtype=torch.float64))


@pytest.mark.parametrize("schedule", ["cosine", "linear"])
def test_posterior_equals_gaussian_conditioning(schedule):
    diffusion = GaussianDiffusion(1000, schedule)
    steps = torch.tensor([1, 7, 300, 999])
    x0 = torch.randn(4, 3, 2, dtype=torch.float64, generator=gen(0))
    x_t = torch.randn(4, 3, 2, dtype=torch.float64, generator=gen(1))
    mean, _ = diffusion.q_posterior(x0, x_t, steps)
    # Independent derivation: q(x_{s-1}|x0) = N(√ᾱ_prev x0, 1 − ᾱ_prev), q(x_s|x_{s-1}) = N(√α x_{s-1}, β).
    beta = diffusion.betas[steps].reshape(-1, 1, 1)
    alpha_bar_prev = diffusion.alphas_cumprod[steps - 1].reshape(-1, 1, 1)
    precision = 1 / (1 - alpha_bar_prev) + (1 - beta) / beta
    expected_mean = (alpha_bar_prev.sqrt() * x0 / (1 - alpha_bar_prev) + (1 - beta).sqrt() * x_t / beta) / precision
    torch.testing.assert_close(mean, expected_mean, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(diffusion.posterior_variance[steps], (1 / precision).reshape(-1), rtol=1e-9, atol=0)
    # Step 0: x_{-1} is the data itself (posterior mean x0, variance 0; its log clipped to β̃[1] as the reference).
    mean0, log_var0 = diffusion.q_posterior(x0, x_t, torch.zeros(4, dtype=torch.long))
    torch.testing.assert_close(mean0, x0, rtol=0, atol=1e-12)
    assert diffusion.posterior_variance[0].item() == 0.0
    assert log_var0.flatten()[0].item() == pytest.approx(math.log(diffusion.posterior_variance[1].item()))


def test_q_sample_has_the_marginal_moments():
    x0 = torch.tensor([1.5, -0.5, 0.0]).view(1, 1, 3).expand(100_000, 1, 3)
    for step in (0, 200, 600, 999):
        alpha_bar = COSINE.alphas_cumprod[step].item()
        draws = COSINE.q_sample(x0, torch.full((100_000,), step), torch.randn(100_000, 1, 3, generator=gen(step)))
        torch.testing.assert_close(draws.mean(0).flatten(), math.sqrt(alpha_bar) * x0[0, 0], atol=0.01, rtol=0)
        torch.testing.assert_close(draws.std(0).flatten(), torch.full((3,), math.sqrt(1 - alpha_bar)), atol=0.01,
                                   rtol=0.01)


def test_x0_and_eps_predictions_invert_each_other():
    x_t = torch.randn(3, 4, 5, dtype=torch.float64, generator=gen(0))
    eps = torch.randn(3, 4, 5, dtype=torch.float64, generator=gen(1))
    step = torch.tensor([0, 500, 998])
    x0 = COSINE.predict_x0_from_eps(x_t, step, eps)
    torch.testing.assert_close(COSINE.predict_eps_from_x0(x_t, step, x0), eps, rtol=1e-7, atol=1e-7)
    torch.testing.assert_close(COSINE.q_sample(x0, step, eps), x_t, rtol=1e-9, atol=1e-9)


def test_model_time_is_the_training_step_over_num_steps():
    step = torch.tensor([0, 1, 999])
    torch.testing.assert_close(COSINE.model_time(step), torch.tensor([0.0, 0.001, 0.999]))
    assert COSINE.model_time(step).dtype == torch.float32


# ---------------------------------------------------------------------------------------------- respacing


def test_space_timesteps_follows_improved_ddpm():
    fifty = space_timesteps(1000, 50)
    assert len(fifty) == 50 and fifty[0] == 0 and fifty[-1] == 999
    assert space_timesteps(1000, "ddim50") == list(range(0, 1000, 20))
    assert space_timesteps(1000, 1000) == list(range(1000))
    sections = space_timesteps(100, [2, 3])
    assert sections == [0, 49, 50, 74, 99]  # 50 + round(24.5): Python's half-to-even rounding, as the reference
    assert space_timesteps(100, "2,3") == sections
    with pytest.raises(ValueError, match="single step"):
        space_timesteps(1000, 1)
    with pytest.raises(ValueError, match="cannot take"):
        space_timesteps(10, 11)
    with pytest.raises(ValueError, match="constant stride"):
        space_timesteps(1000, "ddim3000")


def test_respaced_schedule_keeps_alpha_bar_at_the_kept_steps():
    spaced = COSINE.respaced(50)
    kept = torch.tensor(space_timesteps(1000, 50))
    assert spaced.num_steps == 50 and spaced.num_train_steps == 1000
    torch.testing.assert_close(spaced.alphas_cumprod, COSINE.alphas_cumprod[kept], rtol=1e-10, atol=0)
    torch.testing.assert_close(spaced.model_time(torch.arange(50)), (kept.double() / 1000).float())
    # The learned range uses the respaced β: the first kept step keeps its own β.
    assert spaced.betas[0].item() == pytest.approx(COSINE.betas[0].item())
    assert COSINE.respaced(1000) is COSINE
    # Respacing a respaced schedule composes through the original steps.
    twice = spaced.respaced(10)
    torch.testing.assert_close(twice.timestep_map, spaced.timestep_map[torch.tensor(space_timesteps(50, 10))])


# ---------------------------------------------------------------------------------------------- loss


@pytest.mark.parametrize("prediction", ["eps", "x0"])
def test_loss_equals_hand_computation(prediction):
    diffusion = GaussianDiffusion(1000, "cosine", prediction)
    batch, frames, dim = 3, 5, 4
    x1 = torch.randn(batch, frames, dim, generator=gen(0))
    cond = torch.randn(batch, 2, generator=gen(1))
    lengths = torch.tensor([5, 3, 1])
    loss, stats = diffusion.loss(AffineDenoiser(), x1, cond, lengths, generator=gen(7))

    # The documented draw order: step (B,) then noise (B, T, D) from the same generator.
    g = gen(7)
    step = torch.randint(1000, (batch,), generator=g)
    noise = torch.randn(batch, frames, dim, generator=g)
    total = 0.0
    for b in range(batch):
        alpha_bar = closed_form_alpha_bar(int(step[b])) if step[b] < 999 else COSINE.alphas_cumprod[-1].item()
        x_t = math.sqrt(alpha_bar) * x1[b] + math.sqrt(1 - alpha_bar) * noise[b]
        output = 0.5 * x_t * (1 + step[b] / 1000) + cond[b].sum()
        target = noise[b] if prediction == "eps" else x1[b]
        total += (output - target)[: lengths[b]].square().mean()
    torch.testing.assert_close(loss, total / batch, rtol=1e-5, atol=1e-6)
    assert stats["valid_frames"].item() == 9 and "vb" not in stats
    torch.testing.assert_close(stats["mse"], loss.detach())

    # Explicit draws reproduce the generator path.
    again, _ = diffusion.loss(AffineDenoiser(), x1, cond, lengths, step=step, noise=noise,
                              cond_mask=torch.zeros(batch, dtype=torch.bool))
    torch.testing.assert_close(again, loss)


class OutputStub:
    """A 'denoiser' returning a fixed output tensor whatever its input (to probe the loss terms)."""

    def __init__(self, output):
        self.output = output

    def __call__(self, x, t, cond, lengths=None, *, cond_mask=None, generator=None):
        return self.output


def learned_sigma_setup(batch=4, frames=6, dim=3):
    x1 = torch.randn(batch, frames, dim, generator=gen(0))
    noise = torch.randn(batch, frames, dim, generator=gen(1))
    step = torch.tensor([0, 1, 400, 999])[:batch]
    lengths = torch.tensor([6, 2, 4, 1])[:batch]
    return x1, noise, step, lengths, torch.zeros(batch, 2)


def test_learned_variance_loss_is_zero_for_the_exact_mean_and_posterior_variance():
    diffusion = diffusion_from_preset("flame")
    x1, noise, step, lengths, cond = learned_sigma_setup()
    exact = torch.cat([noise, -torch.ones_like(noise)], dim=-1)  # ε exact, v = −1 → log σ² = clipped log β̃
    loss, stats = diffusion.loss(OutputStub(exact), x1, cond, lengths, step=step, noise=noise)
    assert stats["mse"].item() == pytest.approx(0.0, abs=1e-10)
    assert stats["vb"].item() == pytest.approx(0.0, abs=1e-6)
    assert loss.item() == pytest.approx(0.0, abs=1e-6)


def test_learned_variance_vb_term_has_the_closed_form_kl():
    diffusion = diffusion_from_preset("flame")
    x1, noise, step, lengths, cond = learned_sigma_setup()
    upper = torch.cat([noise, torch.ones_like(noise)], dim=-1)  # v = +1 → log σ² = log β, exact mean
    loss, stats = diffusion.loss(OutputStub(upper), x1, cond, lengths, step=step, noise=noise)
    beta = diffusion.betas[step]
    log_clipped = diffusion.posterior_log_variance_clipped[step]
    # KL(N(m, β̃) ‖ N(m, β)) per element, the same for every element of a sample.
    per_sample = 0.5 * (-1 + beta.log() - log_clipped + (log_clipped - beta.log()).exp())
    assert stats["vb"].item() == pytest.approx(per_sample.mean().item(), rel=1e-5)
    assert loss.item() == pytest.approx(1e-3 * 1000 * per_sample.mean().item(), rel=1e-5)


def test_vb_term_trains_only_the_variance_channels():
    x1, noise, step, lengths, cond = learned_sigma_setup()
    grads = {}
    for lambda_vlb in (0.0, 1e-3):
        output = torch.randn(4, 6, 6, generator=gen(3)).requires_grad_(True)
        diffusion = GaussianDiffusion(learn_sigma=True, lambda_vlb=lambda_vlb)
        loss, _ = diffusion.loss(OutputStub(output), x1, cond, lengths, step=step, noise=noise)
        loss.backward()
        grads[lambda_vlb] = output.grad
    torch.testing.assert_close(grads[1e-3][..., :3], grads[0.0][..., :3], rtol=0, atol=0)
    assert grads[0.0][..., 3:].abs().max().item() == 0.0
    assert grads[1e-3][..., 3:].abs().max().item() > 0.0
    # Padded frames get no gradient.
    padded = ~valid_frame_mask(lengths, 6)
    assert grads[1e-3][padded].abs().max().item() == 0.0


def test_learned_range_interpolates_between_posterior_and_beta():
    diffusion = diffusion_from_preset("flame")
    x_t = torch.randn(2, 3, 2)
    step = torch.tensor([5, 700])
    for v, table in ((-1.0, diffusion.posterior_log_variance_clipped), (1.0, diffusion.betas.log())):
        output = torch.cat([torch.zeros(2, 3, 2), torch.full((2, 3, 2), v)], dim=-1)
        log_variance = diffusion.p_mean_variance(output, x_t, step).log_variance
        torch.testing.assert_close(log_variance, table[step].float().view(2, 1, 1).expand(2, 3, 2))


def test_normal_kl_known_values():
    zero = torch.zeros(3)
    assert normal_kl(zero + 0.3, zero + 0.2, zero + 0.3, zero + 0.2).abs().max().item() == 0.0
    # KL(N(0, 1) ‖ N(1, 4)) = log 2 + (1 + 1)/8 − 1/2.
    value = normal_kl(torch.tensor(0.0), torch.tensor(0.0), torch.tensor(1.0), torch.tensor(math.log(4.0)))
    assert value.item() == pytest.approx(math.log(2.0) + 2 / 8 - 0.5)


def test_discretized_decoder_likelihood_is_a_distribution_over_the_256_bins():
    bins = torch.linspace(-1, 1, 256, dtype=torch.float64)
    for mean, log_scale in ((0.1, math.log(0.05)), (-0.9, math.log(0.3)), (0.0, math.log(3.0))):
        log_p = discretized_gaussian_log_likelihood(bins, torch.full_like(bins, mean), torch.full_like(bins, log_scale))
        assert bool(torch.isfinite(log_p).all())
        assert log_p.exp().sum().item() == pytest.approx(1.0, abs=1e-9)


def test_decoder_nll_replaces_the_kl_at_step_zero_only():
    x1, noise, step, lengths, cond = learned_sigma_setup()
    output = torch.cat([noise, torch.zeros_like(noise)], dim=-1)
    stub = OutputStub(output)
    kl_only = GaussianDiffusion(learn_sigma=True)
    with_nll = GaussianDiffusion(learn_sigma=True, decoder_nll=True)
    x_t = kl_only.q_sample(x1, step, noise)
    mask = valid_frame_mask(lengths, 6)
    per_step = []
    for diffusion in (kl_only, with_nll):
        per_step.append([diffusion.variational_bound(output[i:i + 1], x1[i:i + 1], x_t[i:i + 1], step[i:i + 1],
                                                     mask[i:i + 1]).item() for i in range(4)])
    assert per_step[0][1:] == per_step[1][1:]
    assert per_step[0][0] != per_step[1][0] and math.isfinite(per_step[1][0]) and per_step[1][0] > 0
    loss, stats = with_nll.loss(stub, x1, cond, lengths, step=step, noise=noise)
    assert math.isfinite(loss.item()) and stats["vb"].item() == pytest.approx(sum(per_step[1]) / 4, rel=1e-5)


def test_masked_mean_matches_masked_mse_normalisation():
    a, b = torch.randn(3, 5, 4, generator=gen(0)), torch.randn(3, 5, 4, generator=gen(1))
    mask = valid_frame_mask(torch.tensor([5, 2, 1]), 5)
    torch.testing.assert_close(masked_mean((a - b).square(), mask), masked_mse(a, b, mask))


def test_loss_rejects_a_denoiser_with_the_wrong_number_of_channels():
    x1, noise, step, lengths, cond = learned_sigma_setup()
    with pytest.raises(ValueError, match=r"expected \(4, 6, 6\)"):
        diffusion_from_preset("flame").loss(OutputStub(noise), x1, cond, lengths, step=step, noise=noise)
    with pytest.raises(ValueError, match="prediction"):
        GaussianDiffusion(prediction="v")
    with pytest.raises(ValueError, match="schedule"):
        GaussianDiffusion(schedule="sigmoid")
    with pytest.raises(ValueError, match="preset"):
        diffusion_from_preset("ddim")
    assert set(DIFFUSION_PRESETS) == {"flame", "flowmdm", "mdm"}
    assert DIFFUSION_PRESETS["mdm"] == DIFFUSION_PRESETS["flowmdm"]  # FlowMDM keeps MDM's process


# ---------------------------------------------------------------------------------------------- sampling


@pytest.mark.parametrize(
    "sampler, steps",
    [("ddpm", None), ("ddim", None), ("ddim", 50), ("ddpm", 50), ("ddim", "ddim25")],
)
def test_every_sampler_ends_at_the_data_point_with_an_oracle(sampler, steps):
    point = torch.tensor([0.7, -1.2, 2.0], dtype=torch.float64)
    schedule = COSINE if steps is None else COSINE.respaced(steps)
    x_start = torch.randn(4, 2, 3, dtype=torch.float64, generator=gen(0))
    result = reverse_diffusion(point_eps_oracle(COSINE, point), schedule, x_start, generator=gen(1), sampler=sampler)
    torch.testing.assert_close(result.x1, point.expand(4, 2, 3), rtol=0, atol=1e-6)
    assert result.nfe == schedule.num_steps


def test_x0_prediction_oracle_ends_at_the_data_point():
    diffusion = diffusion_from_preset("flowmdm")
    point = torch.tensor([0.3, -0.4], dtype=torch.float64)
    result = reverse_diffusion(lambda x, t: point.expand_as(x), diffusion, torch.randn(3, 2, 2, dtype=torch.float64),
                               generator=gen(0), sampler="ddpm")
    torch.testing.assert_close(result.x1, point.expand(3, 2, 2), rtol=0, atol=1e-9)


GAUSS_MEAN = torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64)
GAUSS_STD = torch.tensor([0.5, 1.0, 0.2], dtype=torch.float64)


def test_ddim_follows_the_probability_flow_of_gaussian_data():
    # For data ~ N(μ, s²) the exact DDIM/probability-flow map is affine: x_T ↦ μ + s·(x_T − √ᾱ_T μ)/√(ᾱ_T s² + 1 − ᾱ_T).
    x_start = torch.randn(500, 1, 3, dtype=torch.float64, generator=gen(0))
    alpha_bar = COSINE.alphas_cumprod[-1]
    exact = GAUSS_MEAN + GAUSS_STD * (x_start - alpha_bar.sqrt() * GAUSS_MEAN) / (
        alpha_bar * GAUSS_STD**2 + 1 - alpha_bar).sqrt()
    oracle = gaussian_eps_oracle(GAUSS_MEAN, GAUSS_STD)
    full = reverse_diffusion(oracle, COSINE, x_start, generator=gen(1), sampler="ddim")
    fifty = reverse_diffusion(oracle, COSINE.respaced(50), x_start, generator=gen(1), sampler="ddim")
    assert (full.x1 - exact).abs().max().item() < 0.01
    assert (fifty.x1 - exact).abs().max().item() < 0.1
    assert (fifty.x1 - full.x1).abs().mean().item() < 0.02


def test_ddpm_with_an_oracle_samples_the_gaussian_data_distribution():
    oracle = gaussian_eps_oracle(GAUSS_MEAN, GAUSS_STD)
    x_start = torch.randn(4000, 1, 3, dtype=torch.float64, generator=gen(0))
    result = reverse_diffusion(oracle, COSINE, x_start, generator=gen(1), sampler="ddpm")
    # Each step is affine in x plus Gaussian noise, so the output law is Gaussian with moments from a recursion.
    mean = torch.zeros(3, dtype=torch.float64)
    var = torch.ones(3, dtype=torch.float64)
    for s in reversed(range(1000)):
        ab = COSINE.alphas_cumprod[s]
        gain = (1 - ab) / (ab * GAUSS_STD**2 + 1 - ab)  # ε̂ = gain·(x − √ab μ)/√(1 − ab)
        x0_slope = (1 - gain) / ab.sqrt()
        x0_offset = gain * GAUSS_MEAN
        slope = COSINE.posterior_mean_coef1[s] * x0_slope + COSINE.posterior_mean_coef2[s]
        mean = slope * mean + COSINE.posterior_mean_coef1[s] * x0_offset
        var = slope**2 * var + (COSINE.posterior_variance[s] if s > 0 else 0.0)
    samples = result.x1.reshape(-1, 3)
    torch.testing.assert_close(samples.mean(0), mean, atol=4 * (var / 4000).sqrt().max().item(), rtol=0)
    torch.testing.assert_close(samples.var(0), var, rtol=0.1, atol=0)
    # ...and that law is the data's (fixed small variance is near-exact at 1000 steps).
    torch.testing.assert_close(mean, GAUSS_MEAN, atol=0.02, rtol=0)
    torch.testing.assert_close(var.sqrt(), GAUSS_STD, rtol=0.05, atol=0)


def test_classifier_free_guidance_is_one_batched_pass():
    model = AffineDenoiser(channels_factor=2)
    x = torch.randn(3, 4, 2, generator=gen(0))
    t = torch.full((3,), 0.4)
    cond = torch.randn(3, 5, generator=gen(1))
    conditional = model(x, t, cond, cond_mask=torch.zeros(3, dtype=torch.bool))
    unconditional = model(x, t, cond, cond_mask=torch.ones(3, dtype=torch.bool))
    model.calls, model.batch_sizes = 0, []
    guided = classifier_free_guidance(model, cond, scale=8.0, guided_channels=2)(x, t)
    assert model.calls == 1 and model.batch_sizes == [6]
    mixed = unconditional[..., :2] + 8.0 * (conditional[..., :2] - unconditional[..., :2])
    torch.testing.assert_close(guided[..., :2], mixed)
    torch.testing.assert_close(guided[..., 2:], conditional[..., 2:])  # the learned variance of the conditional half
    all_mixed = classifier_free_guidance(model, cond, scale=8.0)(x, t)
    torch.testing.assert_close(all_mixed, unconditional + 8.0 * (conditional - unconditional))
    torch.testing.assert_close(classifier_free_guidance(model, cond, scale=1.0)(x, t), conditional)
    torch.testing.assert_close(classifier_free_guidance(model, cond, scale=0.0)(x, t), unconditional)
    assert model.batch_sizes[-2:] == [3, 3]


def test_guidance_one_sample_equals_the_conditional_sample_and_nfe_counts_batched_passes():
    diffusion = GaussianDiffusion(learn_sigma=True)
    cond = torch.randn(2, 3, generator=gen(0))
    lengths = torch.tensor([4, 2])
    model = AffineDenoiser(channels_factor=2)
    guided_one = ddpm_sample(model, diffusion, cond, lengths, num_frames=4, feature_dim=2, steps=10, guidance=1.0,
                             seed=3)
    assert guided_one.nfe == 10 and model.calls == 10 and set(model.batch_sizes) == {2}

    g = gen(3)
    x_start = torch.randn(2, 4, 2, generator=g) * valid_frame_mask(lengths, 4).unsqueeze(-1)
    keep = torch.zeros(2, dtype=torch.bool)
    plain = reverse_diffusion(lambda x, t: model(x, t, cond, lengths, cond_mask=keep), diffusion.respaced(10),
                              x_start, generator=g, frame_mask=valid_frame_mask(lengths, 4))
    torch.testing.assert_close(guided_one.x1, plain.x1, rtol=0, atol=0)

    model.calls, model.batch_sizes = 0, []
    guided = ddim_sample(model, diffusion, cond, lengths, num_frames=4, feature_dim=2, steps=10, guidance=2.5,
                         return_trajectory=True)
    assert guided.nfe == 10 and model.calls == 10 and set(model.batch_sizes) == {4}
    expected_times = diffusion.respaced(10).timestep_map.flip(0).double() / 1000
    torch.testing.assert_close(guided.grid, expected_times.float().double())
    assert guided.x1_hat.shape == (10, 2, 4, 2)


def test_sampling_is_seeded_and_zeroes_padding():
    diffusion = GaussianDiffusion()
    cond = torch.randn(2, 3, generator=gen(0))
    lengths = [5, 3]
    kwargs = dict(num_frames=5, feature_dim=2, steps=20, guidance=2.0)
    a = ddpm_sample(AffineDenoiser(), diffusion, cond, lengths, seed=1, **kwargs)
    b = ddpm_sample(AffineDenoiser(), diffusion, cond, lengths, seed=1, **kwargs)
    c = ddpm_sample(AffineDenoiser(), diffusion, cond, lengths, seed=2, **kwargs)
    torch.testing.assert_close(a.x1, b.x1, rtol=0, atol=0)
    assert not torch.equal(a.x1, c.x1)
    assert a.x1[1, 3:].abs().max().item() == 0.0 and a.x1[1, :3].abs().min().item() > 0.0
    with pytest.raises(ValueError, match="eta"):
        sample_diffusion(AffineDenoiser(), diffusion, cond, lengths, sampler="ddpm", eta=0.5, **kwargs)
    with pytest.raises(ValueError, match="sampler"):
        sample_diffusion(AffineDenoiser(), diffusion, cond, lengths, sampler="euler", **kwargs)


@pytest.mark.parametrize("sampler", ["ddpm", "ddim"])
def test_per_motion_generators_make_samples_independent_of_the_batch(sampler):
    # One generator per motion: a motion's initial and per-step noise depend on its seed and length only, so it
    # comes out the same alone or batched with a longer motion (the denoiser treats rows independently).
    diffusion = GaussianDiffusion()
    cond = torch.randn(2, 3, generator=gen(0))
    kwargs = dict(feature_dim=2, steps=10, guidance=2.0, sampler=sampler, eta=0.5 if sampler == "ddim" else 0.0)
    batched = sample_diffusion(AffineDenoiser(), diffusion, cond, [6, 4], num_frames=6,
                               generator=seeded_generators([7, 8]), **kwargs)
    alone = sample_diffusion(AffineDenoiser(), diffusion, cond[1:], [4], num_frames=4,
                             generator=seeded_generators([8]), **kwargs)
    torch.testing.assert_close(batched.x1[1, :4], alone.x1[0], rtol=0, atol=1e-6)
    assert batched.x1[1, 4:].abs().max().item() == 0.0
    swapped = sample_diffusion(AffineDenoiser(), diffusion, cond.flip(0), [4, 6], num_frames=6,
                               generator=seeded_generators([8, 7]), **kwargs)
    torch.testing.assert_close(swapped.x1.flip(0), batched.x1, rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="3 generators for a batch of 2"):
        sample_diffusion(AffineDenoiser(), diffusion, cond, [6, 4], num_frames=6,
                         generator=seeded_generators([1, 2, 3]), **kwargs)


def test_replacement_edit_with_per_motion_generators_is_independent_of_the_batch():
    layout = FeatureLayout(HUMANML3D)
    lengths = torch.tensor([40, 32])
    keep = edit_mask("inbetween", lengths, 40, layout)
    reference = torch.randn(2, 40, layout.dim, generator=gen(0)) * valid_frame_mask(lengths, 40).unsqueeze(-1)
    denoise = point_eps_oracle(COSINE, torch.full((layout.dim,), 0.25))
    batched = replacement_edit(denoise, COSINE, reference, keep, steps=8, lengths=lengths,
                               generator=seeded_generators([3, 4]), restore_known=False)
    alone = replacement_edit(denoise, COSINE, reference[1:, :32], keep[1:, :32], steps=8, lengths=lengths[1:],
                             generator=seeded_generators([4]), restore_known=False)
    torch.testing.assert_close(batched.x1[1, :32], alone.x1[0], rtol=0, atol=1e-5)


# ---------------------------------------------------------------------------------------------- editing


class RecordingDenoiser:
    def __init__(self, fn):
        self.fn = fn
        self.inputs = []

    def __call__(self, x, t):
        self.inputs.append((x.clone(), t.clone()))
        return self.fn(x, t)


def test_replacement_edit_rewrites_the_known_part_with_fresh_noise_every_step():
    layout = FeatureLayout(HUMANML3D)
    lengths = torch.tensor([40, 32])
    frames = 40
    keep = edit_mask("inbetween", lengths, frames, layout)
    reference = torch.randn(2, frames, layout.dim, generator=gen(0))
    generated_point = torch.full((layout.dim,), 0.25)
    recorder = RecordingDenoiser(point_eps_oracle(COSINE, generated_point))
    schedule_steps = 25
    result = replacement_edit(recorder, COSINE, reference, keep, steps=schedule_steps, lengths=lengths, seed=4)
    assert result.nfe == schedule_steps == len(recorder.inputs)

    spaced = COSINE.respaced(schedule_steps)
    valid = valid_frame_mask(lengths, frames).unsqueeze(-1)
    kept = keep & valid
    residuals = []
    for call, (x, t) in enumerate(recorder.inputs):
        index = schedule_steps - 1 - call
        alpha_bar = spaced.alphas_cumprod[index].item()
        residual = (x - math.sqrt(alpha_bar) * reference) / math.sqrt(1 - alpha_bar)
        residuals.append(residual[kept])
        assert abs(residual[kept].std().item() - 1.0) < 0.05  # a fresh q_sample of the reference at this step
    # Fresh noise at every step: consecutive residuals are uncorrelated.
    for first, second in zip(residuals[:-1], residuals[1:]):
        assert abs(torch.corrcoef(torch.stack([first, second]))[0, 1].item()) < 0.05

    # Output: the kept part is the reference exactly, the rest what the denoiser generates, padding zero.
    torch.testing.assert_close(result.x1[kept], reference[kept], rtol=0, atol=0)
    torch.testing.assert_close(result.x1[~keep & valid], generated_point.expand(2, frames, -1)[~keep & valid],
                               rtol=0, atol=1e-4)
    assert result.x1[~valid.expand_as(keep)].abs().max().item() == 0.0


def test_replacement_edit_raw_output_keeps_the_step_zero_estimate():
    # FLAME's raw chain output: at step 0 the posterior mean is the x0 estimate, so a denoiser that ignores the
    # reference returns its own estimate in the kept part too; one that recovers the reference returns it.
    # float64: the step-0 x0 estimate divides by √(1 − ᾱ[0]) ≈ 6e-3, which float32 cancellation would blur.
    reference = torch.randn(1, 8, 3, generator=gen(0), dtype=torch.float64)
    keep = torch.zeros(1, 8, 3, dtype=torch.bool)
    keep[:, :2] = True
    elsewhere = torch.tensor([0.5, 0.5, 0.5], dtype=torch.float64)
    raw = replacement_edit(point_eps_oracle(COSINE, elsewhere), COSINE, reference, keep, steps=20,
                           restore_known=False, sampler="ddim")
    torch.testing.assert_close(raw.x1, elsewhere.expand(1, 8, 3), rtol=0, atol=1e-9)
    faithful = replacement_edit(point_eps_oracle(COSINE, reference), COSINE, reference, keep, steps=20,
                                restore_known=False)
    torch.testing.assert_close(faithful.x1, reference, rtol=0, atol=1e-9)


# ---------------------------------------------------------------------------------------------- backbone


def test_learned_variance_backbone_trains_and_samples():
    config = ModelConfig(feature_dim=6, latent_dim=32, ff_dim=64, num_layers=2, num_heads=4, cond_dim=3, max_len=64)
    torch.manual_seed(0)
    model = learned_variance_transformer(config)
    diffusion = diffusion_from_preset("flame")
    x1 = torch.randn(3, 7, 6, generator=gen(0))
    cond = torch.randn(3, 3, generator=gen(1))
    lengths = torch.tensor([7, 4, 2])
    output = model(x1, torch.rand(3), cond, lengths)
    assert output.shape == (3, 7, 12) and output[1, 4:].abs().max().item() == 0.0
    loss, stats = diffusion.loss(model, x1, cond, lengths, generator=gen(2))
    loss.backward()
    assert math.isfinite(loss.item()) and stats["vb"].item() > 0
    assert model.output_proj.weight.grad is not None
    model.eval()
    result = ddpm_sample(model, diffusion, cond, lengths, num_frames=7, steps=5, guidance=8.0)
    assert result.x1.shape == (3, 7, 6) and result.nfe == 5
    assert bool(torch.isfinite(result.x1).all()) and result.x1[2, 2:].abs().max().item() == 0.0


# ---------------------------------------------------------------------------------------------- FLAME's own way


def test_flame_clamp_bounds_the_raw_6d_rotations_only():
    """FLAME clamps its raw x0 estimate to [-1, 1]; on our features the 6D rotation channels (the ones with that
    range) get that bound in raw units, expressed in the normalisation; every other channel stays free."""
    for skeleton in (HUMANML3D, KIT):
        layout = FeatureLayout(skeleton)
        mean = torch.linspace(-0.5, 0.5, layout.dim)
        std = torch.linspace(0.1, 2.0, layout.dim)
        low, high = rotation_6d_range(layout, mean, std)
        rot = layout.slices["rot6d"]
        torch.testing.assert_close(low[rot] * std[rot] + mean[rot], torch.full_like(low[rot], -1.0))
        torch.testing.assert_close(high[rot] * std[rot] + mean[rot], torch.full_like(high[rot], 1.0))
        others = torch.ones(layout.dim, dtype=torch.bool)
        others[rot] = False
        assert bool(torch.isinf(low[others]).all() and torch.isinf(high[others]).all())
    with pytest.raises(ValueError, match="positive"):
        rotation_6d_range(FeatureLayout(HUMANML3D), torch.zeros(263), torch.zeros(263))


def test_x0_clamp_keeps_every_estimate_in_range_over_flames_1000_steps_and_is_off_when_off():
    layout = FeatureLayout(HUMANML3D)
    bounds = rotation_6d_range(layout, torch.zeros(layout.dim), torch.full((layout.dim,), 0.5))  # raw ±1 = ±2 here
    far = torch.full((layout.dim,), 3.0)  # every channel's data point beyond the 6D bound
    denoise = point_eps_oracle(COSINE, far)
    x_start = torch.randn(1, 2, layout.dim, generator=gen(0))
    clamped = reverse_diffusion(denoise, COSINE, x_start, generator=gen(1), clip_denoised=bounds,
                                return_trajectory=True)
    assert clamped.nfe == 1000  # every training step: FLAME's sampler
    rot = layout.slices["rot6d"]
    assert float(clamped.x1_hat[..., rot].max()) <= 2.0 + 1e-6 and float(clamped.x1[..., rot].max()) <= 2.0 + 1e-6
    torch.testing.assert_close(clamped.x1[..., :rot.start], far[:rot.start].expand(1, 2, -1), rtol=0, atol=1e-3)
    free = reverse_diffusion(denoise, COSINE, x_start, generator=gen(1), clip_denoised=None)
    torch.testing.assert_close(free.x1, far.expand(1, 2, -1), rtol=0, atol=1e-3)  # no clamp: the data point
    assert float(free.x1[..., rot].min()) > 2.5
    with pytest.raises(ValueError, match="channels"):
        reverse_diffusion(denoise, COSINE, x_start, generator=gen(1),
                          clip_denoised=DenoisedRange(torch.zeros(3), torch.ones(3)))


def test_reference_translation_copy_gives_the_output_the_references_root_trajectory():
    """FLAME's use_reference_translation: the root dims copied where the edit keeps them. Upper body (FLAME's joint
    edit): the output's root joint follows the reference on every frame; the other dims stay as generated. A frame
    edit copies the root on its kept frames only."""
    layout = FeatureLayout(HUMANML3D)
    lengths = torch.tensor([16, 16])
    reference = 0.1 * torch.randn(2, 16, layout.dim, generator=gen(0))
    generated = 0.1 * torch.randn(2, 16, layout.dim, generator=gen(1))

    def root(features):
        return features_to_joints(features.double(), HUMANML3D)[..., 0, :]

    assert (root(generated) - root(reference)).abs().max() > 1e-2
    upper = copy_reference_root(generated, reference, edit_mask("upper_body", lengths, 16, layout), layout)
    torch.testing.assert_close(root(upper), root(reference), rtol=0, atol=1e-9)
    torch.testing.assert_close(upper[..., 4:], generated[..., 4:], rtol=0, atol=0)
    keep = edit_mask("prediction", lengths, 16, layout)  # keeps frames 0-3
    predicted = copy_reference_root(generated, reference, keep, layout)
    torch.testing.assert_close(predicted[:, :4, :4], reference[:, :4, :4], rtol=0, atol=0)
    torch.testing.assert_close(predicted[:, 4:], generated[:, 4:], rtol=0, atol=0)
