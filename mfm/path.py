"""The probability path shared by the flow-matching loss and the velocity field's parametrisation.

MFM's OT path with a small σ_min, noise ``x0`` at ``t = 0`` and data ``x1`` at ``t = 1``::

    x_t = t·x1 + (1 − (1 − σ_min)·t)·x0          v = d x_t / dt = x1 − (1 − σ_min)·x0

Eliminating ``x0`` gives the velocity as a function of the data point the path ends at::

    v = (x1 − (1 − σ_min)·x_t) / (1 − (1 − σ_min)·t)

which is how a network that predicts ``x1`` (``ModelConfig.prediction = "data"``) still presents a velocity field
to the loss, the solvers, guidance and editing. Kept in its own module because both :mod:`mfm.model` and
:mod:`mfm.flow` need it and ``flow`` imports ``model``.
"""

from __future__ import annotations

import torch

SIGMA_MIN = 1e-4
"""MFM's σ_min (FlowMatching.training_losses default)."""

MIN_NOISE_SCALE = 0.05
"""Smallest ``1 − (1 − σ_min)·t`` the data→velocity conversion divides by. Without a floor the conversion would
amplify an x1 error by up to 1/σ_min = 10⁴ near t = 1; 0.05 is the clip of Li & He, "Back to Basics: Let Denoising
Generative Models Denoise" (2025), who parametrise flow matching this way."""


def preconditioning(t: torch.Tensor, sigma_min: float = SIGMA_MIN) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """EDM-style ``(c_in, c_skip, c_out)`` (Karras et al. 2022, §5) for the flow path ``x_t = a·x0 + t·x1``,
    ``a = 1 − (1 − σ_min)·t``, with unit-variance x0 and x1: the network sees ``c_in·x_t`` (unit variance) and
    ``x̂1 = c_skip·x_t + c_out·F``, where ``c_skip = t / (a² + t²)`` is the least-squares share of x1 in x_t and
    ``c_out = a / √(a² + t²)`` the spread of what is left, so F's target has unit variance at every t. At t = 0 this
    is x1 prediction (F = x̂1); towards t = 1 the input passes through and F only corrects it. Shapes follow ``t``."""
    a = 1 - (1 - sigma_min) * t
    norm = (a.square() + t.square()).sqrt()
    return 1 / norm, t / norm.square(), a / norm


def velocity_from_data(
    x1_hat: torch.Tensor,
    x_t: torch.Tensor,
    t: torch.Tensor,
    *,
    sigma_min: float = SIGMA_MIN,
    min_noise_scale: float = MIN_NOISE_SCALE,
) -> torch.Tensor:
    """Velocity of the path through ``x_t`` at time ``t`` (B,) that ends at the predicted data ``x1_hat``."""
    return (x1_hat - (1 - sigma_min) * x_t) / _noise_scale(t, x_t, sigma_min, min_noise_scale)


def data_from_velocity(
    velocity: torch.Tensor,
    x_t: torch.Tensor,
    t: torch.Tensor,
    *,
    sigma_min: float = SIGMA_MIN,
    min_noise_scale: float = MIN_NOISE_SCALE,
) -> torch.Tensor:
    """The data point ``x̂1`` a velocity at ``x_t`` and times ``t`` (B,) or scalar leads to: the inverse of
    :func:`velocity_from_data` with the same floor, so it recovers a data-predicting network's x̂1 exactly (beyond
    the floor, near t = 1, it scales a velocity network's step by the floored noise scale instead of the true one)."""
    return (1 - sigma_min) * x_t + _noise_scale(t, x_t, sigma_min, min_noise_scale) * velocity


def _noise_scale(t: torch.Tensor, x_t: torch.Tensor, sigma_min: float, min_noise_scale: float) -> torch.Tensor:
    """``1 − (1 − σ_min)·t`` floored at ``min_noise_scale``, shaped to broadcast over ``x_t``: one floor for both
    directions of the data/velocity conversion, so that each inverts the other exactly."""
    t = torch.as_tensor(t, device=x_t.device).reshape(-1, *([1] * (x_t.dim() - 1))).to(x_t.dtype)
    return (1 - (1 - sigma_min) * t).clamp_min(min_noise_scale)
