"""Gaussian diffusion (DDPM / improved DDPM) on the MFM backbone: the FLAME and FlowMDM baselines.

Conventions
-----------
* Integer steps ``s ∈ {0, …, N−1}`` index the schedule (improved DDPM's ``t``): step 0 is the least noisy,
  ``N − 1`` the noisiest, and ``ᾱ[s] = Π_{j≤s} (1 − β_j)`` (the DDPM paper's ᾱ_{s+1})::

      q(x_s | x_0) = N(√ᾱ[s]·x_0, (1 − ᾱ[s])·I)

* The denoiser is the flow model's backbone (:class:`mfm.model.MotionFlowTransformer` or any callable with its
  signature), called as ``denoiser(x_s, t_model, cond, lengths, cond_mask=...)`` with
  ``t_model = original_step / num_train_steps ∈ [0, 1)`` (:meth:`GaussianDiffusion.model_time`; after respacing the
  *original* training step is used, as improved DDPM's ``_WrappedModel``). The backbone embeds ``1000·t`` with a
  continuous sinusoid, so for N = 1000 this is exactly MDM/FlowMDM's integer-timestep embedding, and improved DDPM's
  ``rescale_timesteps`` for other N. The direction is the diffusion one (``t_model = 0`` is clean data), the reverse
  of the flow convention (t = 1 is data): a checkpoint is trained under one objective only.
* Output (B, T, D): ε (``prediction='eps'``, FLAME) or x_0 (``'x0'``, FlowMDM). With ``learn_sigma`` the output is
  (B, T, 2D) = [prediction ; v] and ``log σ² = ((v+1)/2)·log β + (1 − (v+1)/2)·log β̃`` (improved DDPM
  LEARNED_RANGE, FLAME). Without it the variance is the fixed posterior variance β̃ (``sigma_small``, FlowMDM/MDM).
  The backbone's output width is its input feature_dim; :func:`learned_variance_transformer` widens it to 2D until
  ``ModelConfig`` gets an ``output_dim``.

Loss (FLAME ``compute_loss``, improved DDPM hybrid loss)::

    L = masked_mse(prediction, ε or x_0) + λ_vlb · N · L_vb

``L_vb`` is, per element, ``KL(q(x_{s−1} | x_s, x_0) ‖ p(x_{s−1} | x_s))`` in nats, with the predicted mean
stop-gradiented (only the variance channels learn from it), averaged over valid frames × D per sample and then over
the batch (the same normalisation as :func:`mfm.flow.masked_mse`). ``λ_vlb · N`` is improved DDPM's
``RESCALED_MSE`` factor ``N / 1000`` for λ = 1e-3 (L_vlb = Σ_s L_s is estimated by N·L_s for a uniform s).
Differences between the two references, both selectable:

* FLAME (default): the KL also at step 0 (against the clipped posterior variance), nats, and (unlike FLAME, which
  averages over padded frames as well) valid frames only.
* improved DDPM: ``decoder_nll=True`` uses the discretized Gaussian decoder NLL at step 0, which assumes 8-bit data
  in [−1, 1] (images); improved DDPM reports bits, i.e. nats / ln 2: ``lambda_vlb = 1e-3 / ln 2`` reproduces its
  weighting exactly.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import torch
from torch import Tensor

from mfm.flow import VelocityModel, masked_mse, sample_noise
from mfm.model import ModelConfig, MotionFlowTransformer, valid_frame_mask

SCHEDULES = ("cosine", "linear")
PREDICTIONS = ("eps", "x0")

COSINE_S = 0.008
"""Offset s of improved DDPM's cosine schedule (``squaredcos_cap_v2``)."""
MAX_BETA = 0.999
"""Cap on β for the cosine schedule (the last step would otherwise be β = 1)."""

DIFFUSION_PRESETS: dict[str, dict] = {
    # FLAME configs/model/diffusion_hml3d.yaml: 1000 cosine steps, ε + learned range, L_simple + L_vb (×N/1000).
    "flame": dict(num_steps=1000, schedule="cosine", prediction="eps", learn_sigma=True, lambda_vlb=1e-3),
    # FlowMDM parser defaults: 1000 cosine steps, x0 prediction, sigma_small, MSE only.
    "flowmdm": dict(num_steps=1000, schedule="cosine", prediction="x0", learn_sigma=False),
    # MDM's defaults (FlowMDM inherits them): the same process; named apart so converted MDM checkpoints say so.
    "mdm": dict(num_steps=1000, schedule="cosine", prediction="x0", learn_sigma=False),
}
"""Keyword arguments of :class:`GaussianDiffusion` for the reference baselines."""


class DenoisedRange(NamedTuple):
    """Per-channel bounds of the x_0 estimate, (D,) each, in the diffusion's feature space (for our models the
    training normalisation); ``−inf`` / ``inf`` where a channel is unbounded."""

    low: Tensor
    high: Tensor


def clamp_x0(x0: Tensor, bounds: float | DenoisedRange | None) -> Tensor:
    """``x0`` (…, D) clamped to ``bounds``: a positive number c = [−c, c] on every channel (improved DDPM's
    ``clip_denoised``, c = 1), a :class:`DenoisedRange`, or None = unchanged."""
    if bounds is None:
        return x0
    if isinstance(bounds, DenoisedRange):
        low, high = (bound.to(device=x0.device, dtype=x0.dtype) for bound in bounds)
        if low.shape != x0.shape[-1:] or high.shape != x0.shape[-1:]:
            raise ValueError(f"clip_denoised bounds have shapes {tuple(low.shape)}, {tuple(high.shape)}; the x_0 "
                             f"estimate has {x0.shape[-1]} channels")
        return torch.minimum(torch.maximum(x0, low), high)
    if isinstance(bounds, bool) or not bounds > 0:
        raise ValueError(f"clip_denoised must be a positive bound, a DenoisedRange or None, got {bounds!r}")
    return x0.clamp(-bounds, bounds)


# ---------------------------------------------------------------------------------------------------
# schedules and respacing


def cosine_alpha_bar(t: float, s: float = COSINE_S) -> float:
    """Improved DDPM's ``f(t) = cos²(((t + s) / (1 + s))·π/2)`` for continuous t ∈ [0, 1] (unnormalised)."""
    return math.cos((t + s) / (1 + s) * math.pi / 2) ** 2


def named_beta_schedule(name: str, num_steps: int) -> Tensor:
    """(num_steps,) float64 betas.

    cosine: ``β_i = min(1 − f((i+1)/N) / f(i/N), 0.999)``, so ``ᾱ[i] = f((i+1)/N) / f(0)`` wherever no β is capped
    (only the last one is, for N ≥ 2).
    linear: Ho et al.'s ``linspace(1e-4, 0.02)`` scaled by 1000/N so that any N covers the same noise range.
    """
    if not isinstance(num_steps, int) or isinstance(num_steps, bool) or num_steps < 1:
        raise ValueError(f"num_steps must be a positive int, got {num_steps!r}")
    if name == "cosine":
        betas = [
            min(1.0 - cosine_alpha_bar((i + 1) / num_steps) / cosine_alpha_bar(i / num_steps), MAX_BETA)
            for i in range(num_steps)
        ]
        return torch.tensor(betas, dtype=torch.float64)
    if name == "linear":
        scale = 1000.0 / num_steps
        return torch.linspace(scale * 1e-4, scale * 0.02, num_steps, dtype=torch.float64)
    raise ValueError(f"unknown beta schedule {name!r}; known: {list(SCHEDULES)}")


def space_timesteps(num_steps: int, sections: int | str | Sequence[int]) -> list[int]:
    """Sorted schedule indices kept when respacing ``num_steps`` steps (improved DDPM ``space_timesteps``).

    sections: an int K (K ≥ 2, or K = num_steps): K evenly spaced steps including 0 and N − 1;
        ``"ddimK"``: the DDIM stride rule ``range(0, N, stride)`` with exactly K steps;
        a sequence / comma string of counts: the steps are split into that many equal sections and each section is
        spaced evenly with its own count (e.g. ``[10, 15]``).
    """
    if isinstance(sections, str):
        if sections.startswith("ddim"):
            desired = int(sections[len("ddim"):])
            for stride in range(1, num_steps):
                if len(range(0, num_steps, stride)) == desired:
                    return list(range(0, num_steps, stride))
            raise ValueError(f"cannot take exactly {desired} steps of {num_steps} with a constant stride")
        sections = [int(part) for part in sections.split(",")]
    elif isinstance(sections, int) and not isinstance(sections, bool):
        if sections == 1 and num_steps > 1:
            # The reference spacing would keep only step 0 (the least noisy) and start it from pure noise.
            raise ValueError("respacing to a single step is meaningless (it would be the least-noisy step 0); use >= 2")
        sections = [sections]
    sections = list(sections)
    if not sections or any(not isinstance(c, int) or c < 1 for c in sections):
        raise ValueError(f"section counts must be positive ints, got {sections!r}")
    size_per, extra = divmod(num_steps, len(sections))
    start, kept = 0, []
    for index, count in enumerate(sections):
        size = size_per + (1 if index < extra else 0)
        if size < count:
            raise ValueError(f"cannot take {count} steps from a section of {size} (of {num_steps} steps)")
        stride = 1.0 if count <= 1 else (size - 1) / (count - 1)
        kept.extend(start + round(k * stride) for k in range(count))
        start += size
    return sorted(set(kept))


# ---------------------------------------------------------------------------------------------------
# Gaussian helpers


def normal_kl(mean1: Tensor, log_var1: Tensor, mean2: Tensor, log_var2: Tensor) -> Tensor:
    """Elementwise ``KL(N(mean1, e^{log_var1}) ‖ N(mean2, e^{log_var2}))`` in nats."""
    return 0.5 * (-1.0 + log_var2 - log_var1 + torch.exp(log_var1 - log_var2)
                  + (mean1 - mean2).square() * torch.exp(-log_var2))


def discretized_gaussian_log_likelihood(x: Tensor, mean: Tensor, log_scale: Tensor) -> Tensor:
    """Elementwise log-probability (nats) of the 256-level bin of ``x ∈ [−1, 1]`` under N(mean, e^{2·log_scale})
    (improved DDPM's decoder; the outermost bins extend to ±∞). Exact normal CDF instead of the tanh approximation."""
    centered = x - mean
    inv_std = torch.exp(-log_scale)
    upper = inv_std * (centered + 1.0 / 255.0)
    lower = inv_std * (centered - 1.0 / 255.0)
    log_cdf_upper = torch.special.log_ndtr(upper)
    log_survival_lower = torch.special.log_ndtr(-lower)
    bin_mass = (torch.special.ndtr(upper) - torch.special.ndtr(lower)).clamp_min(1e-12)
    return torch.where(x < -0.999, log_cdf_upper, torch.where(x > 0.999, log_survival_lower, bin_mass.log()))


def masked_mean(values: Tensor, frame_mask: Tensor) -> Tensor:
    """Per sample Σ(values · mask) / (Σ mask · D), then the batch mean: :func:`mfm.flow.masked_mse`'s normalisation
    for any elementwise (B, T, D) quantity."""
    mask = frame_mask.unsqueeze(-1).to(values.dtype)
    per_sample = (values * mask).sum(dim=(1, 2)) / (mask.sum(dim=(1, 2)) * values.shape[-1]).clamp_min(1.0)
    return per_sample.mean()


class ReversePrediction(NamedTuple):
    """The model's ``p(x_{s−1} | x_s)`` and its x_0 estimate: mean and x0 are (B, T, D), variance and log_variance
    (B, T, D) when learned, else (B, 1, 1) (fixed per step; they broadcast)."""

    mean: Tensor
    variance: Tensor
    log_variance: Tensor
    x0: Tensor


# ---------------------------------------------------------------------------------------------------
# the process


class GaussianDiffusion:
    """A discrete Gaussian diffusion with its training loss (an :class:`mfm.flow.Objective`).

    num_steps: training steps N (FLAME / FlowMDM: 1000).
    schedule: ``'cosine'`` (improved DDPM ``squaredcos_cap_v2``, β ≤ 0.999) or ``'linear'`` (Ho et al.).
    prediction: ``'eps'`` (FLAME) or ``'x0'`` (FlowMDM) — what the first D output channels are.
    learn_sigma: the denoiser outputs 2D channels, the last D interpolate the log-variance (FLAME).
    lambda_vlb: weight λ of the variational bound term, applied as ``λ·N`` to the per-step term (module docstring).
    decoder_nll: use improved DDPM's discretized decoder NLL at step 0 instead of FLAME's KL (needs data in [−1, 1]).

    Tables (float64, CPU; per-device copies are cached): ``betas``, ``alphas_cumprod`` (ᾱ), ``alphas_cumprod_prev``,
    ``posterior_variance`` (β̃), ``posterior_log_variance_clipped`` (log β̃ with β̃[0] replaced by β̃[1], as the
    reference: β̃[0] = 0), ``posterior_mean_coef1/2``; ``timestep_map`` (long) holds the original training step of
    each index (the identity unless :meth:`respaced`).
    """

    def __init__(
        self,
        num_steps: int = 1000,
        schedule: str = "cosine",
        prediction: str = "eps",
        learn_sigma: bool = False,
        lambda_vlb: float = 1e-3,
        decoder_nll: bool = False,
    ) -> None:
        if schedule not in SCHEDULES:
            raise ValueError(f"GaussianDiffusion.schedule must be one of {list(SCHEDULES)}, got {schedule!r}")
        if prediction not in PREDICTIONS:
            raise ValueError(f"GaussianDiffusion.prediction must be one of {list(PREDICTIONS)}, got {prediction!r}")
        if not (isinstance(lambda_vlb, (int, float)) and lambda_vlb >= 0.0 and math.isfinite(lambda_vlb)):
            raise ValueError(f"GaussianDiffusion.lambda_vlb must be a finite number >= 0, got {lambda_vlb!r}")
        self.schedule = schedule
        self.prediction = prediction
        self.learn_sigma = bool(learn_sigma)
        self.lambda_vlb = float(lambda_vlb)
        self.decoder_nll = bool(decoder_nll)
        self.num_train_steps = num_steps
        betas = named_beta_schedule(schedule, num_steps)
        self._set_schedule(betas, torch.arange(num_steps))

    def _set_schedule(self, betas: Tensor, timestep_map: Tensor) -> None:
        if betas.dim() != 1 or not bool(((betas > 0) & (betas <= 1)).all()):
            raise ValueError("betas must be a 1-D tensor with values in (0, 1]")
        self.num_steps = betas.numel()
        self.timestep_map = timestep_map.long()
        self.betas = betas
        alphas = 1.0 - betas
        self.alphas_cumprod = torch.cumprod(alphas, dim=0)
        self.alphas_cumprod_prev = torch.cat([torch.ones(1, dtype=torch.float64), self.alphas_cumprod[:-1]])
        self.posterior_variance = betas * (1.0 - self.alphas_cumprod_prev) / (1.0 - self.alphas_cumprod)
        # β̃[0] = 0: the reference clips its log to β̃[1]; a single-step schedule has no β̃[1], and β̃ = β there.
        first = self.posterior_variance[1:2] if self.num_steps > 1 else betas[:1]
        self.posterior_log_variance_clipped = torch.log(torch.cat([first, self.posterior_variance[1:]]))
        self.posterior_mean_coef1 = betas * self.alphas_cumprod_prev.sqrt() / (1.0 - self.alphas_cumprod)
        self.posterior_mean_coef2 = (1.0 - self.alphas_cumprod_prev) * alphas.sqrt() / (1.0 - self.alphas_cumprod)
        self._device_tables: dict[torch.device, dict[str, Tensor]] = {}

    def __repr__(self) -> str:
        respaced = "" if self.num_steps == self.num_train_steps else f", respaced to {self.num_steps}"
        return (f"GaussianDiffusion(num_steps={self.num_train_steps}{respaced}, schedule={self.schedule!r}, "
                f"prediction={self.prediction!r}, learn_sigma={self.learn_sigma}, lambda_vlb={self.lambda_vlb}, "
                f"decoder_nll={self.decoder_nll})")

    @property
    def output_channels_factor(self) -> int:
        """The denoiser outputs ``factor · D`` channels: 2 with a learned variance, else 1."""
        return 2 if self.learn_sigma else 1

    # -------------------------------------------------------------------------------- tables

    _TABLES = (
        "betas", "alphas_cumprod", "alphas_cumprod_prev", "posterior_variance", "posterior_log_variance_clipped",
        "posterior_mean_coef1", "posterior_mean_coef2", "timestep_map",
    )

    def _tables(self, device: torch.device) -> dict[str, Tensor]:
        # Gathering on the step's own device avoids a host sync per training step.
        if device not in self._device_tables:
            self._device_tables[device] = {name: getattr(self, name).to(device) for name in self._TABLES}
        return self._device_tables[device]

    def _gather(self, name: str, step: Tensor, like: Tensor) -> Tensor:
        """``table[step]`` shaped (B, 1, …) to broadcast against ``like``, in like's dtype (float64 lookup)."""
        values = self._tables(step.device)[name][step]
        return values.reshape(-1, *([1] * (like.dim() - 1))).to(like.dtype)

    def _check_step(self, step: Tensor, batch: int) -> Tensor:
        if step.shape != (batch,) or step.is_floating_point():
            raise ValueError(
                f"step must be an integer tensor of shape ({batch},), got {tuple(step.shape)} {step.dtype}"
            )
        return step.long()

    def model_time(self, step: Tensor) -> Tensor:
        """(B,) float32 ``t_model = timestep_map[step] / num_train_steps`` passed to the denoiser."""
        original = self._tables(step.device)["timestep_map"][step.long()]
        return (original.double() / self.num_train_steps).float()

    def sample_step(
        self, batch: int, generator: torch.Generator | None = None, device: torch.device | None = None
    ) -> Tensor:
        """(batch,) long steps uniform in [0, num_steps) (FLAME's UniformSampler), drawn on the generator's device."""
        draw_device = generator.device if generator is not None else device
        return torch.randint(self.num_steps, (batch,), generator=generator, device=draw_device).to(device)

    # -------------------------------------------------------------------------------- forward process

    def q_sample(self, x0: Tensor, step: Tensor, noise: Tensor) -> Tensor:
        """A draw of ``q(x_s | x_0) = N(√ᾱ[s]·x_0, (1 − ᾱ[s])·I)`` from the given standard-normal ``noise``."""
        step = self._check_step(step, x0.shape[0])
        alpha_bar = self._gather("alphas_cumprod", step, x0)
        return alpha_bar.sqrt() * x0 + (1.0 - alpha_bar).sqrt() * noise

    def q_posterior(self, x0: Tensor, x_t: Tensor, step: Tensor) -> tuple[Tensor, Tensor]:
        """Mean and clipped log-variance of ``q(x_{s−1} | x_s, x_0)`` (the log-variance broadcastable (B, 1, 1))."""
        step = self._check_step(step, x_t.shape[0])
        coef1 = self._gather("posterior_mean_coef1", step, x_t)
        coef2 = self._gather("posterior_mean_coef2", step, x_t)
        mean = coef1 * x0 + coef2 * x_t
        return mean, self._gather("posterior_log_variance_clipped", step, x_t)

    def predict_x0_from_eps(self, x_t: Tensor, step: Tensor, eps: Tensor) -> Tensor:
        """``x_0 = (x_s − √(1 − ᾱ)·ε) / √ᾱ``."""
        alpha_bar = self._gather("alphas_cumprod", step, x_t)
        return (x_t - (1.0 - alpha_bar).sqrt() * eps) / alpha_bar.sqrt()

    def predict_eps_from_x0(self, x_t: Tensor, step: Tensor, x0: Tensor) -> Tensor:
        """``ε = (x_s − √ᾱ·x_0) / √(1 − ᾱ)``."""
        alpha_bar = self._gather("alphas_cumprod", step, x_t)
        return (x_t - alpha_bar.sqrt() * x0) / (1.0 - alpha_bar).sqrt()

    # -------------------------------------------------------------------------------- reverse process

    def split_output(self, output: Tensor, x_t: Tensor) -> tuple[Tensor, Tensor | None]:
        """(prediction (B, T, D), variance values (B, T, D) or None) from the denoiser's raw output."""
        expected = (*x_t.shape[:-1], self.output_channels_factor * x_t.shape[-1])
        if tuple(output.shape) != expected:
            content = "[prediction ; variance]" if self.learn_sigma else "the prediction"
            raise ValueError(f"denoiser output has shape {tuple(output.shape)}, expected {expected} "
                             f"({content} for learn_sigma={self.learn_sigma})")
        if not self.learn_sigma:
            return output, None
        prediction, variance_values = output.chunk(2, dim=-1)
        return prediction, variance_values

    def p_mean_variance(
        self, output: Tensor, x_t: Tensor, step: Tensor, *, clip_denoised: float | DenoisedRange | None = None
    ) -> ReversePrediction:
        """``p(x_{s−1} | x_s)`` from the denoiser's ``output`` at ``x_t`` and schedule index ``step`` (B,).

        clip_denoised: bounds of the x_0 estimate before the posterior (and DDIM's step), see :func:`clamp_x0`:
            a number c = [−c, c] on every channel (FLAME's ``clip_denoised=True`` is c = 1 on its raw SMPL
            features), or per-channel :class:`DenoisedRange`; None (default) = no clamp.
        """
        step = self._check_step(step, x_t.shape[0])
        prediction, variance_values = self.split_output(output, x_t)
        min_log = self._gather("posterior_log_variance_clipped", step, x_t)
        if variance_values is None:
            # FlowMDM/MDM's sigma_small: the posterior variance β̃ (β̃[0] = 0, so step 0 adds no noise).
            # Kept (B, 1, 1): broadcasting is enough, and exp over an expanded float64 view is slow.
            log_variance = min_log
            variance = self._gather("posterior_variance", step, x_t)
        else:
            max_log = self._gather("betas", step, x_t).log()
            fraction = (variance_values + 1.0) / 2.0
            log_variance = fraction * max_log + (1.0 - fraction) * min_log
            variance = log_variance.exp()
        x0 = prediction if self.prediction == "x0" else self.predict_x0_from_eps(x_t, step, prediction)
        x0 = clamp_x0(x0, clip_denoised)
        mean, _ = self.q_posterior(x0, x_t, step)
        return ReversePrediction(mean=mean, variance=variance, log_variance=log_variance, x0=x0)

    def ddim_step(self, x0: Tensor, x_t: Tensor, step: Tensor, eta: float) -> tuple[Tensor, Tensor]:
        """DDIM (Song et al. eq. 12): mean and standard deviation σ (B, 1, …) of ``x_{s−1}`` given the x_0 estimate.

        ``σ = η·√((1 − ᾱ_prev)/(1 − ᾱ))·√(1 − ᾱ/ᾱ_prev)``; ``mean = √ᾱ_prev·x_0 + √(1 − ᾱ_prev − σ²)·ε(x_0)``.
        """
        step = self._check_step(step, x_t.shape[0])
        eps = self.predict_eps_from_x0(x_t, step, x0)
        alpha_bar = self._gather("alphas_cumprod", step, x_t)
        alpha_bar_prev = self._gather("alphas_cumprod_prev", step, x_t)
        sigma = eta * ((1 - alpha_bar_prev) / (1 - alpha_bar)).sqrt() * (1 - alpha_bar / alpha_bar_prev).sqrt()
        mean = alpha_bar_prev.sqrt() * x0 + (1 - alpha_bar_prev - sigma.square()).clamp_min(0.0).sqrt() * eps
        return mean, sigma

    def respaced(self, steps: int | str | Sequence[int]) -> GaussianDiffusion:
        """The same process on a subset of its steps (:func:`space_timesteps`), for sampling with fewer steps.

        New betas ``1 − ᾱ[k_j]/ᾱ[k_{j−1}]`` keep ᾱ at the kept steps; the learned variance range uses the new β and
        β̃ (improved DDPM); the denoiser still sees the original steps through ``timestep_map``.
        """
        kept = space_timesteps(self.num_steps, steps)
        if len(kept) == self.num_steps:
            return self
        kept_tensor = torch.tensor(kept)
        alpha_bar = self.alphas_cumprod[kept_tensor]
        previous = torch.cat([torch.ones(1, dtype=torch.float64), alpha_bar[:-1]])
        spaced = copy.copy(self)
        spaced._set_schedule(1.0 - alpha_bar / previous, self.timestep_map[kept_tensor])
        return spaced

    # -------------------------------------------------------------------------------- loss

    def variational_bound(self, output: Tensor, x0: Tensor, x_t: Tensor, step: Tensor, frame_mask: Tensor) -> Tensor:
        """Scalar ``L_vb`` in nats (per-sample mean over valid frames × D, then the batch mean): the KL between the
        true posterior and ``p(x_{s−1} | x_s)``, or with ``decoder_nll`` the decoder NLL at step 0. Gradients flow
        through every channel of ``output``: :meth:`loss` passes the prediction channels detached."""
        step = self._check_step(step, x_t.shape[0])
        true_mean, true_log_variance = self.q_posterior(x0, x_t, step)
        model = self.p_mean_variance(output, x_t, step)
        terms = normal_kl(true_mean, true_log_variance, model.mean, model.log_variance)
        if self.decoder_nll:
            nll = -discretized_gaussian_log_likelihood(x0, model.mean, 0.5 * model.log_variance)
            terms = torch.where((step == 0).reshape(-1, 1, 1), nll, terms)
        return masked_mean(terms.float(), frame_mask)

    def loss(
        self,
        model: VelocityModel,
        x1: Tensor,
        cond: Tensor,
        lengths: Tensor,
        *,
        generator: torch.Generator | None = None,
        cond_mask: Tensor | None = None,
        step: Tensor | None = None,
        noise: Tensor | None = None,
        model_kwargs: Mapping[str, Any] | None = None,
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """Diffusion training loss on a padded batch x1 (B, T, D) of clean motions (the :class:`Objective` call).

        Draws, in this order and all from ``generator`` if given: step (B,) uniform in [0, N), noise (B, T, D), then
        the model's condition dropout (unless ``cond_mask`` is given). ``step`` / ``noise`` replace the draws (e.g. a
        data-parallel slice of the global batch's draws). The model sees ``x_s = q_sample(x1, step, noise)`` and
        ``t_model = step / N``. ``model_kwargs`` go to the model (per-frame conditions, token features, positional
        mode of the model variants).
        Returns the loss and detached stats ``{"loss", "mse", "vb" (learn_sigma only), "valid_frames"}``.
        """
        if x1.dim() != 3:
            raise ValueError(f"x1 must be (B, T, D), got {tuple(x1.shape)}")
        if lengths.shape != (x1.shape[0],):
            raise ValueError(f"lengths must be ({x1.shape[0]},), got {tuple(lengths.shape)}")
        lengths = lengths.to(x1.device)
        if step is None:
            step = self.sample_step(x1.shape[0], generator, x1.device)
        step = self._check_step(step.to(x1.device), x1.shape[0])
        if noise is None:
            noise = sample_noise(x1, generator)
        x_t = self.q_sample(x1, step, noise)
        # As flow_matching_loss: with an explicit cond_mask the model draws nothing (no generator, no graph break).
        model_generator = generator if cond_mask is None else None
        output = model(x_t, self.model_time(step), cond, lengths, cond_mask=cond_mask, generator=model_generator,
                       **(model_kwargs or {}))
        prediction, variance_values = self.split_output(output, x_t)
        frame_mask = valid_frame_mask(lengths, x1.shape[1])
        target = noise if self.prediction == "eps" else x1
        mse = masked_mse(prediction, target, frame_mask)
        stats = {"mse": mse.detach(), "valid_frames": frame_mask.sum()}
        loss = mse
        if variance_values is not None:
            # improved DDPM: the bound trains only the variance; the mean is left to the simple loss.
            frozen = torch.cat([prediction.detach(), variance_values], dim=-1)
            vb = self.variational_bound(frozen, x1, x_t, step, frame_mask)
            loss = mse + (self.lambda_vlb * self.num_steps) * vb
            stats["vb"] = vb.detach()
        stats["loss"] = loss.detach()
        return loss, stats


def diffusion_from_preset(name: str, **overrides) -> GaussianDiffusion:
    """A :class:`GaussianDiffusion` from :data:`DIFFUSION_PRESETS` (``'flame'``, ``'flowmdm'``, ``'mdm'``) with overrides."""
    if name not in DIFFUSION_PRESETS:
        raise ValueError(f"unknown diffusion preset {name!r}; known: {sorted(DIFFUSION_PRESETS)}")
    return GaussianDiffusion(**{**DIFFUSION_PRESETS[name], **overrides})


# ---------------------------------------------------------------------------------------------------
# denoiser plumbing


def learned_variance_transformer(config: ModelConfig) -> MotionFlowTransformer:
    """FLAME's denoiser shape on the MFM backbone: the final Linear maps the latent to 2·D channels [ε ; v]
    (FLAME: Linear(768 → 2·147)); the rest of the network is unchanged (padded frames are still zeroed)."""
    return MotionFlowTransformer(dataclasses.replace(config, output_dim=2 * config.feature_dim))


