"""Conditional flow matching as trained by MFM (OT / rectified-flow path with a small σ_min).

Noise ``x0 ~ N(0, I)`` sits at ``t = 0`` and data ``x1`` at ``t = 1``::

    x_t    = t·x1 + (1 − (1 − σ_min)·t)·x0
    target = d x_t / dt = x1 − (1 − σ_min)·x0          (a velocity, not an x1-prediction)
    loss   = Σ((target − v(x_t, t))² · mask) / (Σ mask · D)   over valid frames only (MFM's masked_l2)

The diffusion objective (FLAME / FlowMDM baselines) can live beside this one behind :class:`Objective`.
"""

from __future__ import annotations

from dataclasses import dataclass
from collections.abc import Mapping
from typing import Any, Protocol

import torch

from mfm.model import valid_frame_mask
from mfm.path import SIGMA_MIN


class VelocityModel(Protocol):
    """What the loss calls: :class:`mfm.model.MotionFlowTransformer` (or a DDP/compiled wrapper of it)."""

    def __call__(
        self,
        x: torch.Tensor,
        t: torch.Tensor,
        cond: torch.Tensor,
        lengths: torch.Tensor | None = None,
        *,
        cond_mask: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
        **model_kwargs: Any,
    ) -> torch.Tensor: ...


class Objective(Protocol):
    """A training objective: one scalar loss per batch plus detached statistics for logging (no host syncs)."""

    def loss(
        self,
        model: VelocityModel,
        x1: torch.Tensor,
        cond: torch.Tensor,
        lengths: torch.Tensor,
        *,
        generator: torch.Generator | None = None,
        cond_mask: torch.Tensor | None = None,
        model_kwargs: Mapping[str, Any] | None = None,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]: ...


def _draw_device(generator: torch.Generator | None, device: torch.device | None) -> torch.device | None:
    # torch.rand/randn need the generator's own device: draw there, then move (a CPU generator can feed a GPU run).
    return generator.device if generator is not None else device


def sample_time(
    batch: int, generator: torch.Generator | None = None, device: torch.device | None = None
) -> torch.Tensor:
    """(batch,) float32 times t ~ U(0, 1)."""
    return torch.rand(batch, generator=generator, device=_draw_device(generator, device)).to(device)


def sample_noise(like: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
    """x0 ~ N(0, I) with the shape, dtype and device of ``like``."""
    noise = torch.randn(like.shape, generator=generator, device=_draw_device(generator, like.device))
    return noise.to(device=like.device, dtype=like.dtype)


def _per_sample(t: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """Reshape (B,) times to broadcast against ``like`` (B, ...)."""
    return t.reshape(-1, *([1] * (like.dim() - 1))).to(like.dtype)


def interpolate(x0: torch.Tensor, x1: torch.Tensor, t: torch.Tensor, sigma_min: float = SIGMA_MIN) -> torch.Tensor:
    """Point on the probability path: ``x_t = t·x1 + (1 − (1 − σ_min)·t)·x0``; t is (B,)."""
    t = _per_sample(t, x1)
    return t * x1 + (1 - (1 - sigma_min) * t) * x0


def target_velocity(x0: torch.Tensor, x1: torch.Tensor, sigma_min: float = SIGMA_MIN) -> torch.Tensor:
    """Time derivative of :func:`interpolate`: ``x1 − (1 − σ_min)·x0`` (independent of t)."""
    return x1 - (1 - sigma_min) * x0


def masked_mse(prediction: torch.Tensor, target: torch.Tensor, frame_mask: torch.Tensor) -> torch.Tensor:
    """MDM/MFM's ``masked_l2``: per sample Σ((target − prediction)² · mask) / (Σ mask · D), then the mean over
    the batch, for (B, T, D) tensors and a (B, T) frame mask.

    Every sample weighs the same whatever its length (as in the reference). This is also what makes data
    parallelism exact: the mean of equal-sized per-rank means is the global mean, with no extra collective.
    """
    mask = frame_mask.unsqueeze(-1).float()
    squared_error = ((target.float() - prediction.float()).square() * mask).sum(dim=(1, 2))
    per_sample = squared_error / (mask.sum(dim=(1, 2)) * prediction.shape[-1]).clamp_min(1.0)
    return per_sample.mean()


def flow_matching_loss(
    model: VelocityModel,
    x1: torch.Tensor,
    cond: torch.Tensor,
    lengths: torch.Tensor,
    *,
    generator: torch.Generator | None = None,
    sigma_min: float = SIGMA_MIN,
    cond_mask: torch.Tensor | None = None,
    t: torch.Tensor | None = None,
    x0: torch.Tensor | None = None,
    model_kwargs: Mapping[str, Any] | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """MFM's conditional flow-matching loss on a padded batch.

    x1: (B, T, D) normalised motion features, padded beyond ``lengths`` (B,).
    Random draws, in this order, all from ``generator`` if given (deterministic tests and resume):
    t (B,), noise x0 (B, T, D), then the model's condition dropout (unless ``cond_mask`` is given). A compiled
    training step should draw ``cond_mask`` itself (:func:`mfm.model.draw_cond_drop_mask`) and pass it here.
    ``t`` (B,) and ``x0`` (B, T, D), when given, replace the draws (a data-parallel step slices them from the
    global batch's draws so that any world size computes the same thing). ``model_kwargs`` go to the model
    (per-frame conditions, token features, positional mode of the FlowMDM/FLAME variants).
    Returns the scalar loss and ``{"loss": detached loss, "valid_frames": number of frames averaged}``.
    """
    if x1.dim() != 3:
        raise ValueError(f"x1 must be (B, T, D), got {tuple(x1.shape)}")
    if lengths.shape != (x1.shape[0],):
        raise ValueError(f"lengths must be ({x1.shape[0]},), got {tuple(lengths.shape)}")
    lengths = lengths.to(x1.device)
    if t is None:
        t = sample_time(x1.shape[0], generator, x1.device)
    if x0 is None:
        x0 = sample_noise(x1, generator)
    x_t = interpolate(x0, x1, t, sigma_min)
    # With an explicit cond_mask the model draws nothing; not passing the generator then keeps a torch.compile'd
    # model free of a graph break (a Generator argument breaks the graph).
    model_generator = generator if cond_mask is None else None
    velocity = model(x_t, t, cond, lengths, cond_mask=cond_mask, generator=model_generator, **(model_kwargs or {}))
    frame_mask = valid_frame_mask(lengths, x1.shape[1])
    loss = masked_mse(velocity, target_velocity(x0, x1, sigma_min), frame_mask)
    return loss, {"loss": loss.detach(), "valid_frames": frame_mask.sum()}


@dataclass(frozen=True)
class FlowMatchingObjective:
    """:func:`flow_matching_loss` as an :class:`Objective`."""

    sigma_min: float = SIGMA_MIN

    def __post_init__(self) -> None:
        if not 0.0 <= self.sigma_min < 1.0:
            raise ValueError(f"FlowMatchingObjective.sigma_min must be in [0, 1), got {self.sigma_min!r}")

    def loss(
        self,
        model: VelocityModel,
        x1: torch.Tensor,
        cond: torch.Tensor,
        lengths: torch.Tensor,
        *,
        generator: torch.Generator | None = None,
        cond_mask: torch.Tensor | None = None,
        t: torch.Tensor | None = None,
        x0: torch.Tensor | None = None,
        model_kwargs: Mapping[str, Any] | None = None,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        return flow_matching_loss(
            model, x1, cond, lengths, generator=generator, sigma_min=self.sigma_min, cond_mask=cond_mask,
            t=t, x0=x0, model_kwargs=model_kwargs,
        )
