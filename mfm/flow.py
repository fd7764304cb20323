"""Conditional flow matching as trained by MFM (OT / rectified-flow path with a small σ_min).

Noise ``x0 ~ N(0, I)`` sits at ``t = 0`` and data ``x1`` at ``t = 1``::

    x_t    = t·x1 + (1 − (1 − σ_min)·t)·x0
    target = d x_t / dt = x1 − (1 − σ_min)·x0          (a velocity, not an x1-prediction)
    loss   = Σ((target − v(x_t, t))² · mask) / (Σ mask · D)   over valid frames only (MFM's masked_l2)

The diffusion objective (FLAME / FlowMDM baselines) can live beside this one behind :class:`Objective`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from collections.abc import Mapping
from typing import Any, Protocol

import numpy as np
import torch

from mfm.features import root_path
from mfm.layout import FeatureLayout
from mfm.model import valid_frame_mask
from mfm.path import MIN_NOISE_SCALE, SIGMA_MIN, data_from_velocity, velocity_from_data
from mfm.solvers import check_grid, uniform_grid


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


def cached_on_device(owner: Any, name: str, device: torch.device, make: Any) -> Any:
    """``make()`` for ``device``, made once per device and kept on ``owner`` (in its ``__dict__``: a cache, not a
    field, so frozen dataclasses hold it too). Constants a loss needs on the model's device are copied there once
    rather than every step: on a GPU a copy from the host waits for the work queued before it."""
    copies = owner.__dict__.setdefault(name, {})
    if device not in copies:
        copies[device] = make()
    return copies[device]


@functools.lru_cache(maxsize=64)
def _grid_times_on(grid_times: tuple[float, ...], dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """The grid's times on ``device``, copied once (on a GPU a copy from the host at every step would wait for the
    work queued before it)."""
    return torch.tensor(grid_times, dtype=dtype, device=device)


def _draw_device(generator: torch.Generator | None, device: torch.device | None) -> torch.device | None:
    # torch.rand/randn need the generator's own device: draw there, then move (a CPU generator can feed a GPU run).
    return generator.device if generator is not None else device


def sample_time(
    batch: int, generator: torch.Generator | None = None, device: torch.device | None = None
) -> torch.Tensor:
    """(batch,) float32 times t ~ U(0, 1)."""
    return torch.rand(batch, generator=generator, device=_draw_device(generator, device)).to(device)


TIME_SAMPLINGS = ("uniform", "logit_normal", "grid", "stratified")


def stratify_times(u: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
    """A batch's training times one per stratum: with B rows, row i gets t = (π_i + u_i) / B for a random
    permutation π (drawn from ``generator`` after ``u``), so every stratum [k/B, (k+1)/B) holds exactly one time
    while each row's time is still U(0, 1). The low-discrepancy sampler of Kingma et al. 2021 ("Variational
    Diffusion Models", appendix), which spreads one shifted grid in row order; the permutation keeps a row's
    stratum independent of its place in the batch. Not MFM's (uniform, drawn row by row)."""
    rows = u.shape[0]
    order = torch.randperm(rows, generator=generator, device=_draw_device(generator, u.device)).to(u.device)
    return (order.to(u.dtype) + u) / rows


GRID_INPUTS = ("interpolated", "own_path")
"""What a grid-trained row's network input is (``flow_matching_loss(grid_inputs=)``): 'interpolated', the point of
the straight path between its noise and its data (rectified flow's k-step distillation); 'own_path', the state the
model's own Euler steps reach from that noise (backward distillation)."""
BONE_TARGETS = ("frames", "clip_median")
"""What :func:`bone_length_loss` holds x̂1's bones to: 'frames' = each frame's bone lengths of x1; 'clip_median' =
each bone's median length over x1's valid frames, one length per bone for the whole motion."""


def warp_time(u: torch.Tensor, sampling: str = "uniform", loc: float = 0.0, scale: float = 1.0,
              grid_steps: int = 0, grid_times: tuple[float, ...] | None = None) -> torch.Tensor:
    """Training times from uniform draws ``u`` in [0, 1) by the inverse CDF of the named density (so the random
    stream, and with it exact resume and any world size's draws, is the same whatever the density).

    'uniform': t = u (MFM). 'logit_normal': t = sigmoid(loc + scale·Φ⁻¹(u)), the density Esser et al. (2024,
    "Scaling Rectified Flow Transformers") found best for rectified flows on images: more training where the
    path is neither noise nor data; loc < 0 moves it toward the noise (t = 0), loc > 0 toward the data.
    'stratified': t = u; the batch's draws were spread one per stratum first (:func:`stratify_times`, which
    :func:`flow_matching_loss` applies to the times it draws itself).
    'grid': t = floor(u·K)/K with K = ``grid_steps``, the times 0, 1/K, ..., (K−1)/K at which Euler with K steps
    evaluates the network, each equally often: the k-step distillation of a reflowed model (Liu et al. 2022,
    rectified flow, section 2.3), which spends the student's training on the times its few-step sampler visits
    (K = 2 trains t = 0 and 1/2: both the 1-step and the 2-step sampler). For a pair set (launch/distill.py), not
    for training from data. ``grid_times`` (K start times, ``ModelConfig.sampling_times``) replace 0, 1/K, ...:
    the k-th draws train ``grid_times[k]``.
    """
    if sampling in ("uniform", "stratified"):
        return u
    if sampling == "grid":
        if grid_steps < 1:
            raise ValueError(f"grid time sampling needs grid_steps >= 1, got {grid_steps!r}")
        index = torch.floor(u * grid_steps).clamp(max=grid_steps - 1)
        if grid_times is None:
            return (index / grid_steps).to(u.dtype)
        if len(grid_times) != grid_steps:
            raise ValueError(f"grid time sampling with {grid_steps} steps needs {grid_steps} grid_times, got "
                             f"{grid_times!r}")
        return _grid_times_on(tuple(grid_times), u.dtype, u.device)[index.long()]
    if sampling != "logit_normal":
        raise ValueError(f"time sampling must be one of {TIME_SAMPLINGS}, got {sampling!r}")
    if scale <= 0:
        raise ValueError(f"logit_normal scale must be > 0, got {scale!r}")
    eps = torch.finfo(torch.float32).eps
    normal = torch.special.ndtri(u.float().clamp(eps, 1 - eps))
    return torch.sigmoid(loc + scale * normal).to(u.dtype)


@dataclass(frozen=True)
class TimeSampling:
    """How :func:`flow_matching_loss` turns its uniform draws into training times: :func:`warp_time`'s arguments,
    named (``FlowMatchingObjective.training_times`` builds it from the objective's fields)."""

    name: str = "uniform"
    loc: float = 0.0
    scale: float = 1.0
    grid_steps: int = 0
    grid_times: tuple[float, ...] | None = None

    def warp(self, u: torch.Tensor) -> torch.Tensor:
        return warp_time(u, self.name, self.loc, self.scale, self.grid_steps, self.grid_times)


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


def masked_mse(
    prediction: torch.Tensor, target: torch.Tensor, frame_mask: torch.Tensor, sample_weight: torch.Tensor | None = None,
    channel_weight: torch.Tensor | None = None,
) -> torch.Tensor:
    """MDM/MFM's ``masked_l2``: per sample Σ((target − prediction)² · mask) / (Σ mask · D), then the mean over
    the batch, for (B, T, D) tensors and a (B, T) frame mask; each sample's term times ``sample_weight`` (B,) if
    given, each channel's squared error times ``channel_weight`` (D,) if given (not renormalised: the divisor stays
    Σ mask · D, as dividing those channels' std would give; :func:`feat_bias_channel_weight`).

    Every sample weighs the same whatever its length (as in the reference). This is also what makes data
    parallelism exact: the mean of equal-sized per-rank means is the global mean, with no extra collective.
    """
    mask = frame_mask.unsqueeze(-1).float()
    squared_error = (target.float() - prediction.float()).square()
    if channel_weight is not None:
        squared_error = squared_error * channel_weight.to(squared_error.device, squared_error.dtype)
    squared_error = (squared_error * mask).sum(dim=(1, 2))
    per_sample = squared_error / (mask.sum(dim=(1, 2)) * prediction.shape[-1]).clamp_min(1.0)
    if sample_weight is not None:
        per_sample = per_sample * sample_weight.to(per_sample.dtype)
    return per_sample.mean()


def feat_bias_channel_weight(layout: FeatureLayout, feat_bias: float) -> tuple[float, ...]:
    """Per-channel squared-error weights of Guo et al.'s ``feat_bias`` (text-to-motion's Comp_v6 training divides
    the std of the root groups, features 0:4, and of the foot contacts, the last 4, by feat_bias = 5): feat_bias² on
    those channels, 1 elsewhere. MDM, MFM and FlowMDM train with 1 everywhere (HumanML3D's Std.npy divided by 1.0).
    The heading of the body lives in one channel of 263 (the root's rotation velocity), so without it the network is
    barely told where a turn ends (docs/generator-study.md, "A turn is a rate, not an angle")."""
    if not feat_bias > 0:
        raise ValueError(f"feat_bias must be > 0, got {feat_bias!r}")
    weight = np.ones(layout.dim)
    weight[layout.root_dims] = feat_bias**2
    weight[layout.slices["contacts"]] = feat_bias**2
    return tuple(float(w) for w in weight)


LOSS_SPACES = ("velocity", "data")
ROOT_RATE_CHANNELS = (0, 1, 2)
"""The root's heading rate and ground velocity in Guo features (``mfm.layout.FeatureLayout`` root_rot_vel and
root_lin_vel: dims 0:3 for every skeleton)."""
TERM_WEIGHTINGS = ("data", "loss")


def term_weight(t: torch.Tensor, loss_space: str, terms_weighting: str,
                sigma_min: float = SIGMA_MIN, velocity_weight_cap: float = 0.0) -> torch.Tensor | None:
    """Per-sample weight of the temporal, bone, trajectory and foot-contact terms (which are errors of the implied
    motion x̂1).

    'data': none, as the terms were introduced: every time counts alike. 'loss': the weight the main loss puts on
    an x̂1 error at that time, relative to the data loss's, so the terms keep the same proportion to the main loss at
    every t: ``1 / max(1 − (1 − σ_min)·t, MIN_NOISE_SCALE)²`` under the velocity loss (the floor the model's
    velocity conversion uses; at most ``velocity_weight_cap`` when that is > 0, as :func:`loss_space_weight`
    caps the main loss), 1 under the data loss. Under the velocity loss with 'data', a term weighs 4 against
    the main loss's 100 at t = 0.9, where a 10-step Euler sampler takes its last step; that last step is what
    leaves the frame-to-frame jitter in the sample.
    """
    if terms_weighting not in TERM_WEIGHTINGS:
        raise ValueError(f"terms_weighting must be one of {TERM_WEIGHTINGS}, got {terms_weighting!r}")
    if terms_weighting == "data" or loss_space == "data":
        return None
    weight = (1 - (1 - sigma_min) * t.float()).clamp_min(MIN_NOISE_SCALE).square().reciprocal()
    return weight.clamp_max(velocity_weight_cap) if velocity_weight_cap > 0 else weight


def loss_space_weight(t: torch.Tensor, loss_space: str, sigma_min: float = SIGMA_MIN,
                      velocity_weight_cap: float = 0.0) -> torch.Tensor | None:
    """Per-sample weight that turns the velocity error into the error of the motion it implies.

    'velocity': none (MFM). 'data': ``(1 − (1 − σ_min)·t)²``; since ``v − u = (x̂1 − x1) / (1 − (1 − σ_min)·t)`` on
    the path, the weighted velocity loss is the MSE of x̂1. The velocity loss weighs an x̂1 error by
    ``1/(1 − t)²``, up to 400× (with :data:`mfm.path.MIN_NOISE_SCALE`) at the end of the path, where a
    10-step Euler sampler never evaluates the model, and 4× at t = 0.5: the data loss spreads the model's
    accuracy evenly along the path.

    ``velocity_weight_cap`` > 0 (velocity loss only) caps that x̂1 weight: ``min(1, cap·(1 − (1 − σ_min)·t)²)`` in
    velocity space, i.e. the velocity loss where ``1/(1 − t)² ≤ cap`` and ``cap`` × the data loss nearer the data
    end. A loss between the two, in the spirit of Min-SNR-γ weighting (Hang et al. 2023); not MFM's. Why: the
    velocity loss's largest weights, all within the last few tenths of the path, dominate every batch's gradient,
    and the x̂1 the network makes from (near) noise, whose frame-to-frame jitter the sampler integrates into the
    sample, is fitted least (docs/generator-study.md).
    """
    if loss_space not in LOSS_SPACES:
        raise ValueError(f"loss_space must be one of {LOSS_SPACES}, got {loss_space!r}")
    if velocity_weight_cap < 0:
        raise ValueError(f"velocity_weight_cap must be >= 0 (0 = no cap), got {velocity_weight_cap!r}")
    if loss_space == "velocity":
        if velocity_weight_cap == 0:
            return None
        return (velocity_weight_cap * (1 - (1 - sigma_min) * t.float()).square()).clamp_max(1.0)
    if velocity_weight_cap > 0:
        raise ValueError("velocity_weight_cap applies to the velocity loss only")
    return (1 - (1 - sigma_min) * t.float()).square()


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
    loss_space: str = "velocity",
    temporal_weight: float = 0.0,
    bone_weight: float = 0.0,
    bone_target: str = "frames",
    trajectory_weight: float = 0.0,
    trajectory_min_t: float = 0.0,
    trajectory_huber: float = 0.0,
    foot_contact_weight: float = 0.0,
    root_mean_weight: float = 0.0,
    root_rate_channels: tuple[int, ...] = ROOT_RATE_CHANNELS,
    geometry: MotionGeometry | None = None,
    time_sampling: TimeSampling = TimeSampling(),
    terms_weighting: str = "data",
    velocity_weight_cap: float = 0.0,
    channel_weight: torch.Tensor | None = None,
    input_perturbation: float = 0.0,
    perturbation: torch.Tensor | None = None,
    self_condition_prob: float = 0.0,
    self_condition_rows: torch.Tensor | None = None,
    grid_inputs: str = "interpolated",
    estimate: bool = False,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """MFM's conditional flow-matching loss on a padded batch (``loss_space='velocity'``), or the same error
    weighted into the data space (:func:`loss_space_weight`), plus ``temporal_weight`` × :func:`temporal_loss` and
    ``bone_weight`` × :func:`bone_length_loss` (its ``target`` is ``bone_target``), ``trajectory_weight`` ×
    :func:`trajectory_loss` and
    ``foot_contact_weight`` × :func:`foot_contact_loss` (the three need ``geometry``), and ``root_mean_weight`` ×
    :func:`root_rate_mean_loss` over the ``root_rate_channels``.

    x1: (B, T, D) normalised motion features, padded beyond ``lengths`` (B,).
    Random draws, in this order, all from ``generator`` if given (deterministic tests and resume):
    t (B,) (with stratified time sampling, then the permutation of :func:`stratify_times`), noise x0 (B, T, D),
    the input perturbation ξ (B, T, D; only when ``input_perturbation`` > 0 and ``perturbation`` is not given),
    the self-conditioned rows (B,; only when ``self_condition_prob`` > 0), then the model's condition dropout
    (unless ``cond_mask`` is given).
    ``self_condition_prob`` p > 0 (a self-conditioned model, ``ModelConfig.self_condition_prob``; Chen et al.
    2022): a share p of the rows first runs through the model without gradient, and the x̂1 that pass implies
    (:func:`mfm.path.data_from_velocity`) is the second, trained pass's ``self_condition`` input; the other rows get
    zeros. Needs ``cond_mask`` (both passes must drop the same conditions). ``self_condition_rows`` (B,) bool, when
    given, replaces the draw of those rows.
    ``input_perturbation`` γ > 0: the model's input is built from the noise ``x0 + γ·ξ`` while the target stays
    the velocity of ``x0`` (Ning et al. 2023's DDPM-IP on the flow path; ``perturbation``, when given, replaces
    the draw of ξ). A compiled training step should draw ``cond_mask`` itself
    (:func:`mfm.model.draw_cond_drop_mask`) and pass it here.
    ``t`` (B,) and ``x0`` (B, T, D), when given, replace the draws (a data-parallel step slices them from the
    global batch's draws so that any world size computes the same thing). ``t``, drawn or given, is a uniform draw
    that ``time_sampling`` (:class:`TimeSampling`) turns into the training time (:func:`warp_time`;
    'uniform' keeps it); ``terms_weighting`` weighs the two terms over t (:func:`term_weight`);
    ``velocity_weight_cap`` caps the velocity loss's weight of an x̂1 error (:func:`loss_space_weight`);
    ``channel_weight`` (D,) weighs the main MSE's channels (:func:`masked_mse`; the two terms are not weighted).
    ``model_kwargs`` go to the model
    (per-frame conditions, token features, positional mode of the FlowMDM/FLAME variants).
    ``grid_inputs='own_path'`` (grid time sampling only, with ``cond_mask``): a row trained at the grid time k/K
    gets as input the state the model's own k Euler steps reach from its noise (:func:`own_path_inputs`, no
    gradient), and its target is the velocity from there to its ``x1`` (:func:`mfm.path.velocity_from_data`):
    a few-step student then learns its later steps from the states its earlier steps really leave, not from
    the straight path's (backward distillation, Kohler et al. 2024, "Imagine Flash"). Draws nothing more.
    Returns the scalar loss and ``{"loss": detached loss, "valid_frames": number of frames averaged}``; with
    ``estimate``, also ``"x1_hat"``, the motion the trained pass's velocity leads to from its input
    (:func:`mfm.path.data_from_velocity`, float32, in the graph: at t = 0 a student's one-step motion), and
    ``"frame_mask"`` (B, T) bool, for a loss on that motion from the same forward pass (``mfm.critic``).
    """
    if x1.dim() != 3:
        raise ValueError(f"x1 must be (B, T, D), got {tuple(x1.shape)}")
    if lengths.shape != (x1.shape[0],):
        raise ValueError(f"lengths must be ({x1.shape[0]},), got {tuple(lengths.shape)}")
    lengths = lengths.to(x1.device)
    if grid_inputs not in GRID_INPUTS:
        raise ValueError(f"grid_inputs must be one of {GRID_INPUTS}, got {grid_inputs!r}")
    own_path = grid_inputs == "own_path"
    if own_path and (time_sampling.name != "grid" or cond_mask is None or input_perturbation > 0
                     or self_condition_prob > 0):
        raise ValueError("grid_inputs='own_path' needs grid time sampling and an explicit cond_mask (both passes "
                         "drop the same conditions), without input perturbation or self-conditioning, got "
                         f"time sampling {time_sampling.name!r}, "
                         f"cond_mask {'given' if cond_mask is not None else None}, "
                         f"input_perturbation {input_perturbation!r}, self_condition_prob {self_condition_prob!r}")
    if t is None:
        t = sample_time(x1.shape[0], generator, x1.device)
        if time_sampling.name == "stratified":
            t = stratify_times(t, generator)
    t = time_sampling.warp(t)
    if x0 is None:
        x0 = sample_noise(x1, generator)
    if input_perturbation > 0 and perturbation is None:
        perturbation = sample_noise(x1, generator)
    input_noise = x0 + input_perturbation * perturbation if input_perturbation > 0 else x0  # the target keeps x0
    if own_path:
        x_t = own_path_inputs(model, x0, t, cond, lengths, cond_mask, time_sampling.grid_steps, model_kwargs,
                              time_sampling.grid_times)
        target = velocity_from_data(x1.float(), x_t.float(), t.float(), sigma_min=sigma_min).to(x1.dtype)
    else:
        x_t = interpolate(input_noise, x1, t, sigma_min)
        target = target_velocity(x0, x1, sigma_min)
    # With an explicit cond_mask the model draws nothing; not passing the generator then keeps a torch.compile'd
    # model free of a graph break (a Generator argument breaks the graph).
    model_generator = generator if cond_mask is None else None
    model_kwargs = dict(model_kwargs or {})
    if self_condition_prob > 0:
        chosen = self_condition_rows
        if chosen is None:
            chosen = draw_self_condition_rows(x1.shape[0], self_condition_prob, generator, x1.device)
        model_kwargs["self_condition"] = self_condition_estimate(model, x_t, t, cond, lengths, cond_mask, chosen,
                                                                 model_kwargs, sigma_min)
    velocity = model(x_t, t, cond, lengths, cond_mask=cond_mask, generator=model_generator, **model_kwargs)
    frame_mask = valid_frame_mask(lengths, x1.shape[1])
    loss = velocity_loss(velocity, target, x1, t, frame_mask, sigma_min=sigma_min,
                         loss_space=loss_space, temporal_weight=temporal_weight, bone_weight=bone_weight,
                         bone_target=bone_target, trajectory_weight=trajectory_weight,
                         trajectory_min_t=trajectory_min_t,
                         trajectory_huber=trajectory_huber, foot_contact_weight=foot_contact_weight,
                         root_mean_weight=root_mean_weight, root_rate_channels=root_rate_channels,
                         geometry=geometry, terms_weighting=terms_weighting,
                         velocity_weight_cap=velocity_weight_cap, channel_weight=channel_weight)
    info = {"loss": loss.detach(), "valid_frames": frame_mask.sum()}
    if estimate:
        info["x1_hat"] = data_from_velocity(velocity.float(), x_t.float(), t.float(), sigma_min=sigma_min)
        info["frame_mask"] = frame_mask
    return loss, info


def velocity_loss(
    velocity: torch.Tensor,
    target: torch.Tensor,
    x1: torch.Tensor,
    t: torch.Tensor,
    frame_mask: torch.Tensor,
    *,
    sigma_min: float = SIGMA_MIN,
    loss_space: str = "velocity",
    temporal_weight: float = 0.0,
    bone_weight: float = 0.0,
    bone_target: str = "frames",
    trajectory_weight: float = 0.0,
    trajectory_min_t: float = 0.0,
    trajectory_huber: float = 0.0,
    foot_contact_weight: float = 0.0,
    root_mean_weight: float = 0.0,
    root_rate_channels: tuple[int, ...] = ROOT_RATE_CHANNELS,
    geometry: MotionGeometry | None = None,
    terms_weighting: str = "data",
    velocity_weight_cap: float = 0.0,
    channel_weight: torch.Tensor | None = None,
) -> torch.Tensor:
    """:func:`flow_matching_loss` of a velocity the model made at times ``t`` against its ``target``: the weighted
    MSE, plus the temporal term of the implied motion's error, the bone term, whose bones are ``x1``'s (the
    clip the path leads to; per frame, or each bone's clip median with ``bone_target='clip_median'``), the
    trajectory term, whose path is ``x1``'s (counted only for the rows whose ``t`` is
    at least ``trajectory_min_t``; pseudo-Huber per frame beyond ``trajectory_huber`` m when > 0), and the
    foot-contact term, whose contact labels are ``x1``'s, and the root-rate mean term."""
    weight = loss_space_weight(t, loss_space, sigma_min, velocity_weight_cap)
    loss = masked_mse(velocity, target, frame_mask, weight, channel_weight)
    terms = term_weight(t, loss_space, terms_weighting, sigma_min, velocity_weight_cap)
    if temporal_weight > 0:
        loss = loss + temporal_weight * temporal_loss(velocity, target, t, frame_mask, sigma_min, terms)
    geometric = bone_weight > 0 or trajectory_weight > 0 or foot_contact_weight > 0
    if geometric and geometry is None:
        raise ValueError("bone_weight, trajectory_weight or foot_contact_weight > 0 needs the motion geometry "
                         "(normalisation and skeleton)")
    error = implied_motion_error(velocity, target, t, sigma_min) if geometric or root_mean_weight > 0 else None
    if root_mean_weight > 0:
        loss = loss + root_mean_weight * root_rate_mean_loss(error, frame_mask, root_rate_channels, terms)
    if geometric:
        x1_hat = x1.float() + error
        if bone_weight > 0:
            loss = loss + bone_weight * bone_length_loss(x1_hat, x1, frame_mask, geometry, terms,
                                                         target=bone_target)
        if trajectory_weight > 0:
            loss = loss + trajectory_weight * trajectory_loss(x1_hat, x1, frame_mask, geometry,
                                                              _from_time(terms, t, trajectory_min_t),
                                                              huber=trajectory_huber)
        if foot_contact_weight > 0:
            loss = loss + foot_contact_weight * foot_contact_loss(x1_hat, x1, frame_mask, geometry, terms)
    return loss


def root_rate_mean_loss(x1_error: torch.Tensor, frame_mask: torch.Tensor,
                        channels: tuple[int, ...] = ROOT_RATE_CHANNELS,
                        sample_weight: torch.Tensor | None = None) -> torch.Tensor:
    """The squared clip mean of an implied-motion error ``x̂1 − x1`` (B, T, D) over the valid frames, summed over the
    root's rate ``channels`` (normalised units; per sample, then the batch mean).

    Why: the features give the root as per-frame rates, and the clip mean of a rate is what the caption fixes
    ("up in place": 0 m/s; "turns around": 180° over however many frames). The main MSE charges that mean error once
    among every frame's and channel's error: on the synthetic preset a forward drift of 0.09 m/s of "jumps up in
    place", which is 0.5 m over 173 frames, costs about a thousandth of the loss, and the network kept it in x̂1 at
    t = 0 (docs/generator-study.md, "The root's clip mean"). This term charges it alone. Unlike
    :func:`trajectory_loss` it does not grow with the clip's length or weigh the slow wander of a long walk's path,
    only the one number per channel a caption can fix. Needs no geometry. Ours; not part of MFM."""
    mask = frame_mask.unsqueeze(-1).float()
    rates = x1_error[..., list(channels)].float() * mask
    mean = rates.sum(dim=1) / mask.sum(dim=1).clamp_min(1.0)
    return _weighted_mean(mean.square().sum(dim=-1), sample_weight)


def implied_motion_error(
    velocity: torch.Tensor, target: torch.Tensor, t: torch.Tensor, sigma_min: float = SIGMA_MIN
) -> torch.Tensor:
    """``x̂1 − x1``: the error of the motion a velocity leads to, ``(v − u)·(1 − (1 − σ_min)·t)`` on the path."""
    return (velocity.float() - target.float()) * (1 - (1 - sigma_min) * t.float())[:, None, None]


@dataclass(frozen=True)
class MotionGeometry:
    """What it takes to read joint positions off normalised Guo features: the dataset's Mean/Std and the skeleton's
    kinematic tree (``parents``, −1 for the root). ``ric`` is the slice of the root-relative joint positions
    (joints 1..J−1) and ``root_height`` the index of the root's height (``mfm.layout.FeatureLayout``)."""

    mean: torch.Tensor
    std: torch.Tensor
    parents: tuple[int, ...]
    ric: slice
    root_height: int
    skeleton: Any = None
    """The :class:`mfm.skeleton.Skeleton` (world-frame joints and foot contacts need it)."""

    @classmethod
    def from_dataset(cls, mean: Any, std: Any, skeleton: Any) -> MotionGeometry:
        from mfm.layout import FeatureLayout

        layout = FeatureLayout(skeleton)
        return cls(torch.as_tensor(mean, dtype=torch.float32), torch.as_tensor(std, dtype=torch.float32),
                   tuple(int(p) for p in skeleton.parents), layout.slices["ric"], layout.slices["root_height"].start,
                   skeleton)

    def raw(self, features: torch.Tensor) -> torch.Tensor:
        """Normalised (B, T, D) features back in the dataset's units (float32)."""
        mean, std = self.statistics_on(features.device)
        return features.float() * std + mean

    def statistics_on(self, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
        """(mean, std) on ``device``, copied there once (:func:`cached_on_device`)."""
        return cached_on_device(self, "_statistics_on", device, lambda: (self.mean.to(device), self.std.to(device)))

    def joints(self, features: torch.Tensor) -> torch.Tensor:
        """(B, T, J, 3) positions in the facing frame, root above the origin, from normalised (B, T, D) features."""
        raw = self.raw(features)
        others = raw[..., self.ric].reshape(*raw.shape[:-1], -1, 3)
        root = torch.zeros_like(others[..., :1, :])
        root[..., 1] = raw[..., self.root_height : self.root_height + 1]
        return torch.cat([root, others], dim=-2)

    def root_path(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The root's integrated heading (B, T, radians) and ground position (B, T, 2: X, Z in metres) from
        normalised (B, T, D) features (:func:`mfm.features.root_path`)."""
        angle, position = root_path(self.raw(features))
        return angle, torch.stack((position[0], position[2]), dim=-1)

    def feet(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The foot joints' world positions (B, T, 4, 3; the root's path integrated as :func:`root_path`, the
        reference ``recover_from_ric``) and the features' own foot-contact labels (B, T, 4, raw 0/1), both in the
        layout's contact order [left ankle, left foot, right ankle, right foot]."""
        from mfm.features import features_to_joints
        from mfm.layout import FeatureLayout

        if self.skeleton is None:
            raise ValueError("MotionGeometry.feet needs the skeleton (MotionGeometry.from_dataset)")
        layout = FeatureLayout(self.skeleton)
        raw = self.raw(features)
        joints = features_to_joints(raw, self.skeleton)
        return joints[..., list(layout.contact_joints), :], raw[..., layout.slices["contacts"]]

    def bone_lengths(self, features: torch.Tensor) -> torch.Tensor:
        """(B, T, J − 1) length of every bone (non-root joint to its parent)."""
        joints = self.joints(features)
        children = [j for j, p in enumerate(self.parents) if p >= 0]
        parents = [self.parents[j] for j in children]
        return (joints[..., children, :] - joints[..., parents, :]).norm(dim=-1)


def bone_length_loss(x1_hat: torch.Tensor, x1: torch.Tensor, frame_mask: torch.Tensor,
                     geometry: MotionGeometry, sample_weight: torch.Tensor | None = None,
                     target: str = "frames") -> torch.Tensor:
    """MSE (m²) between the bone lengths of the implied motion x̂1 and those of the clip x1, over valid frames (per
    sample, then the batch mean). The ric block gives every joint its own position, so nothing else holds a
    generated skeleton together: this term does (MDM's geometric losses in the same spirit; not part of MFM).

    ``target`` (:data:`BONE_TARGETS`): 'frames' holds each frame's bones to that frame's of x1; 'clip_median' to
    each bone's median length over x1's valid frames. Why: a reflow student's x1 is its teacher's raw output, whose
    bones vary from frame to frame, and 'frames' teaches the student that variation as if it were the motion's; a
    body's bones do not change length, and the median of a motion's lengths is the length its skeleton has (the
    synthetic preset's students held to it keep their bones within 0.1 cm of the clips', docs/few-step.md, "Bones
    held to their median"). For mocap clips the two targets agree. Ours, not MFM's."""
    if target not in BONE_TARGETS:
        raise ValueError(f"bone_length_loss target must be one of {BONE_TARGETS}, got {target!r}")
    mask = frame_mask.unsqueeze(-1).float()
    target_lengths = geometry.bone_lengths(x1)
    if target == "clip_median":
        target_lengths = clip_median_over_frames(target_lengths, frame_mask)
    error = (geometry.bone_lengths(x1_hat) - target_lengths).square() * mask
    per_sample = error.sum(dim=(1, 2)) / (mask.sum(dim=(1, 2)) * error.shape[-1]).clamp_min(1.0)
    return _weighted_mean(per_sample, sample_weight)


def clip_median_over_frames(values: torch.Tensor, frame_mask: torch.Tensor) -> torch.Tensor:
    """Each sample's median over its valid frames: (B, T, C) values with a (B, T) mask -> (B, 1, C). A sample with
    no valid frame gets 0 (its terms are masked out anyway)."""
    valid = frame_mask.unsqueeze(-1).expand_as(values)
    masked = torch.where(valid, values, torch.full_like(values, float("nan")))
    return torch.nanmedian(masked, dim=1, keepdim=True).values.nan_to_num(0.0)


def trajectory_loss(x1_hat: torch.Tensor, x1: torch.Tensor, frame_mask: torch.Tensor,
                    geometry: MotionGeometry, sample_weight: torch.Tensor | None = None,
                    huber: float = 0.0) -> torch.Tensor:
    """Squared error of the root's integrated path, the implied motion x̂1's against the clip x1's, over valid
    frames (per sample, then the batch mean): the ground position's (m², X and Z summed) plus the heading's
    (rad², i.e. as if measured 1 m from the root).

    ``huber`` > 0 (m): each frame's squared distance ``e`` becomes the pseudo-Huber ``2·h²·(√(1 + e/h²) − 1)``,
    ``e`` itself for distances well below ``h`` and growing only linearly beyond, so the gradient a frame sends back
    is at most ``2·h`` whatever its error. Why it was tried: a walk's path early in training is metres off, and its
    squared error's gradient, summed back along the integral over every later frame, is a heavy tail that could
    crowd the main loss out of the clipped update. On the synthetic preset it did not: bounded, the term still cost
    the counts and no longer cured the drift (docs/generator-study.md, "... with its tail bounded"). 0: the squared
    error.

    Why: the features give the root as per-frame rates (heading rate, velocity in the facing frame), and the main
    MSE weighs an error of a rate the same whether it comes and goes or persists. A persistent bias of 3 mm per
    frame, nothing per frame against a walk's 2-5 cm, is 0.5 m after 173 frames: "jumps up in place" drifts, and
    a turn's total angle grows with the clip's length. Integrated, that bias is the error that grows; this term
    weighs it so. Ours (in the spirit of MDM's geometric losses on positions); not part of MFM."""
    hat_angle, hat_ground = geometry.root_path(x1_hat)
    angle, ground = geometry.root_path(x1)
    mask = frame_mask.float()
    error = (hat_ground - ground).square().sum(dim=-1) + (hat_angle - angle).square()
    if huber > 0:
        error = pseudo_huber(error, huber)
    per_sample = (error * mask).sum(dim=1) / mask.sum(dim=1).clamp_min(1.0)
    return _weighted_mean(per_sample, sample_weight)


def pseudo_huber(squared: torch.Tensor, scale: float) -> torch.Tensor:
    """``2·scale²·(√(1 + squared/scale²) − 1)`` of a squared distance: the squared distance itself below ``scale``,
    linear in the distance above it (slope ``2·scale``)."""
    return 2.0 * scale ** 2 * (torch.sqrt(1.0 + squared / scale ** 2) - 1.0)


def foot_contact_loss(x1_hat: torch.Tensor, x1: torch.Tensor, frame_mask: torch.Tensor,
                      geometry: MotionGeometry, sample_weight: torch.Tensor | None = None) -> torch.Tensor:
    """Squared error (m² per frame) of the implied motion x̂1's foot-joint displacements against the clip x1's, in
    the world frame, over the frame pairs (t, t + 1) in which x1's features label that joint in contact with the
    ground (its contact channel at t > 0.5); per sample over its valid frame pairs and the four foot joints, then
    the batch mean.

    Why: a foot the clip plants should stay planted; the main MSE sees a sliding foot only as small errors spread
    over the ric, velocity and contact channels, and the bone term not at all. In the spirit of MDM's foot-contact
    loss (``lambda_fc``), which penalises the predicted foot joints' velocity itself where the ground truth's is at
    most 0.01; ours compares it with the clip's, so the clip itself costs nothing (HumanML3D's contact labels allow
    feet up to about 4.5 cm per frame). Not part of MFM."""
    feet_hat, _ = geometry.feet(x1_hat)
    feet, contacts = geometry.feet(x1)
    pairs = (frame_mask[:, 1:] & frame_mask[:, :-1]).float()
    planted = (contacts[:, :-1] > 0.5).float() * pairs.unsqueeze(-1)  # the label of frame t: the pair (t, t + 1)
    error = ((feet_hat[:, 1:] - feet_hat[:, :-1]) - (feet[:, 1:] - feet[:, :-1])).square().sum(dim=-1) * planted
    per_sample = error.sum(dim=(1, 2)) / (pairs.sum(dim=1) * error.shape[-1]).clamp_min(1.0)
    return _weighted_mean(per_sample, sample_weight)


def temporal_loss(
    velocity: torch.Tensor, target: torch.Tensor, t: torch.Tensor, frame_mask: torch.Tensor,
    sigma_min: float = SIGMA_MIN, sample_weight: torch.Tensor | None = None,
) -> torch.Tensor:
    """MSE of the frame-to-frame change of the implied motion's error, ``Δ(x̂1 − x1)``, over pairs of valid
    frames (per sample, then the batch mean), with ``x̂1 − x1 = (v − u)·(1 − (1 − σ_min)·t)`` on the path.

    An error that is smooth in time costs little here; frame-to-frame jitter — what makes generated joints
    shake, bones change length and feet slide — costs twice its energy. The feature-space analogue of MDM's
    velocity loss (``lambda_vel``, on joint positions); not part of MFM.
    """
    error = implied_motion_error(velocity, target, t, sigma_min)
    pairs = (frame_mask[:, 1:] & frame_mask[:, :-1]).unsqueeze(-1).float()
    change = (error[:, 1:] - error[:, :-1]).square() * pairs
    per_sample = change.sum(dim=(1, 2)) / (pairs.sum(dim=(1, 2)) * error.shape[-1]).clamp_min(1.0)
    return _weighted_mean(per_sample, sample_weight)


def _from_time(sample_weight: torch.Tensor | None, t: torch.Tensor, min_t: float) -> torch.Tensor | None:
    """``sample_weight`` with the rows whose time is below ``min_t`` set to 0 (``min_t`` 0: unchanged)."""
    if min_t <= 0:
        return sample_weight
    counted = (t.float() >= min_t).float()
    return counted if sample_weight is None else sample_weight * counted


def _weighted_mean(per_sample: torch.Tensor, sample_weight: torch.Tensor | None) -> torch.Tensor:
    return (per_sample if sample_weight is None else per_sample * sample_weight.to(per_sample.dtype)).mean()


PER_SAMPLE_MODEL_INPUTS = ("segments", "frame_cond", "text_tokens", "text_token_len", "positional_mode")
"""The model's keyword inputs that hold one row per sample (sliced with the batch); the others (block_drop_mask,
attention_chunk) apply to the whole pass."""


def own_path_inputs(model: VelocityModel, x0: torch.Tensor, t: torch.Tensor, cond: torch.Tensor,
                    lengths: torch.Tensor, cond_mask: torch.Tensor, grid_steps: int,
                    model_kwargs: Mapping[str, Any] | None = None,
                    grid_times: tuple[float, ...] | None = None) -> torch.Tensor:
    """Each row's state after its own Euler steps from ``x0`` on the grid t_0 = 0 < t_1 < ... < t_{K-1} < 1 (K =
    ``grid_steps``; ``grid_times``, or 0, 1/K, ... when None): a row at t = t_k (B,) takes the K-step sampler's
    first k steps ``x += (t_{j+1} − t_j)·v(x, t_j)`` (guidance 1), without gradient; a row at t = 0 keeps its noise.
    K − 1 passes of the whole batch whatever the rows' times, so every data-parallel rank makes the same model calls
    (DDP broadcasts buffers at each forward)."""
    if grid_times is not None and len(grid_times) != grid_steps:
        raise ValueError(f"own_path_inputs needs {grid_steps} grid_times, got {grid_times!r}")
    # the sampler's own grid (float64, as mfm.solvers.solve steps on it)
    grid = uniform_grid(grid_steps) if grid_times is None else check_grid([*grid_times, 1.0])
    starts = grid[:-1]
    distance = (t.double().cpu()[:, None] - starts[None, :]).abs()
    steps_taken = distance.argmin(dim=1).to(t.device)
    if not bool((distance.min(dim=1).values < 1e-6).all()):
        raise ValueError(f"own_path_inputs needs times on the grid {starts.tolist()}, got {t.tolist()}")
    x = x0
    with torch.no_grad():
        for step in range(grid_steps - 1):
            velocity = model(x, torch.full_like(t, float(grid[step])), cond, lengths, cond_mask=cond_mask,
                             **dict(model_kwargs or {}))
            size = float(grid[step + 1] - grid[step])
            x = torch.where((steps_taken > step)[:, None, None], x + size * velocity.to(x.dtype), x)
    return x


def draw_self_condition_rows(batch: int, prob: float, generator: torch.Generator | None = None,
                             device: torch.device | None = None) -> torch.Tensor:
    """(B,) bool: which rows a self-conditioned training pass feeds the network's own estimate (share ``prob``)."""
    return torch.rand(batch, generator=generator, device=_draw_device(generator, device)).to(device) < prob


def self_condition_estimate(model: VelocityModel, x_t: torch.Tensor, t: torch.Tensor, cond: torch.Tensor,
                            lengths: torch.Tensor, cond_mask: torch.Tensor | None, chosen: torch.Tensor,
                            model_kwargs: Mapping[str, Any], sigma_min: float = SIGMA_MIN) -> torch.Tensor:
    """Self-conditioning's input for a training pass (Chen et al. 2022): for the ``chosen`` (B,) rows, the x̂1 that
    a gradient-free pass of ``model`` at the same ``x_t``, ``t`` and dropped conditions implies; zeros for the
    others. Only the chosen rows run, so the extra cost is their share of a forward pass. When no row is chosen the
    first row runs anyway and is discarded: every data-parallel rank then makes the same number of model calls
    (DDP broadcasts buffers at each forward, a collective that must meet its partners on every rank)."""
    if cond_mask is None:
        raise ValueError("self-conditioning needs an explicit cond_mask, so that the estimate's pass and the trained "
                         "pass drop the same conditions (draw it with mfm.model.draw_cond_drop_mask)")
    estimate = torch.zeros_like(x_t)
    any_chosen = bool(chosen.any())
    rows = chosen.nonzero().squeeze(1) if any_chosen else torch.zeros(1, dtype=torch.long, device=x_t.device)
    kwargs = {name: (value.index_select(0, rows) if name in PER_SAMPLE_MODEL_INPUTS and torch.is_tensor(value)
                     else value) for name, value in model_kwargs.items()}
    x_rows, t_rows = x_t.index_select(0, rows), t.index_select(0, rows)
    with torch.no_grad():
        velocity = model(x_rows, t_rows, cond.index_select(0, rows), lengths.index_select(0, rows),
                         cond_mask=cond_mask.index_select(0, rows), **kwargs)
    if any_chosen:
        estimate[rows] = data_from_velocity(velocity.float(), x_rows.float(), t_rows.float(),
                                            sigma_min=sigma_min).to(x_t.dtype)
    return estimate


@dataclass(frozen=True)
class FlowMatchingObjective:
    """:func:`flow_matching_loss` as an :class:`Objective`."""

    sigma_min: float = SIGMA_MIN
    loss_space: str = "velocity"
    temporal_weight: float = 0.0
    bone_weight: float = 0.0
    bone_target: str = "frames"
    """What the bone term holds the bones to (:data:`BONE_TARGETS`)."""
    trajectory_weight: float = 0.0
    trajectory_min_t: float = 0.0
    """The trajectory term counts only for rows trained at t >= this (0: every row)."""
    trajectory_huber: float = 0.0
    """The trajectory term's per-frame error is pseudo-Huber beyond this distance in m (0: squared error)."""
    foot_contact_weight: float = 0.0
    root_mean_weight: float = 0.0
    """Weight of :func:`root_rate_mean_loss` (0: off, MFM)."""
    input_perturbation: float = 0.0
    """γ of the input perturbation (Ning et al. 2023, DDPM-IP): the model's input is built from the noise
    ``x0 + γ·ξ`` and the target stays the velocity of ``x0``, so the network also learns to steer states a little
    off the training paths back to them, as sampling's own errors put it (0: off, MFM)."""
    self_condition_prob: float = 0.0
    """The share of rows trained with the model's own estimate as input (``ModelConfig.self_condition_prob``, which
    the model must have; :func:`self_condition_estimate`). 0: off (MFM)."""
    geometry: MotionGeometry | None = None
    time_sampling: str = "uniform"
    time_loc: float = 0.0
    time_scale: float = 1.0
    time_grid_steps: int = 0
    time_grid_times: tuple[float, ...] | None = None
    """time_sampling='grid': the K start times trained (``ModelConfig.sampling_times``); None: 0, 1/K, ..."""
    grid_inputs: str = "interpolated"
    """:data:`GRID_INPUTS`: 'own_path' trains each grid time from the state the model's own Euler steps reach
    (backward distillation; a few-step student's option, needs ``time_sampling='grid'``)."""
    terms_weighting: str = "data"
    velocity_weight_cap: float = 0.0
    channel_weight: tuple[float, ...] | None = None
    """Per-channel weights of the main MSE (:func:`feat_bias_channel_weight`); None: every channel 1 (MFM)."""

    @property
    def training_times(self) -> TimeSampling:
        """The objective's time density as :func:`flow_matching_loss` takes it."""
        return TimeSampling(self.time_sampling, self.time_loc, self.time_scale, self.time_grid_steps,
                            self.time_grid_times)

    def channel_weight_on(self, device: torch.device) -> torch.Tensor | None:
        """``channel_weight`` as a tensor on ``device``, made once per device (:func:`cached_on_device`)."""
        if self.channel_weight is None:
            return None
        return cached_on_device(self, "_channel_weight_tensors", device,
                                lambda: torch.tensor(self.channel_weight, dtype=torch.float32, device=device))

    def __post_init__(self) -> None:
        if self.time_sampling not in TIME_SAMPLINGS or self.time_scale <= 0:
            raise ValueError(f"FlowMatchingObjective.time_sampling must be one of {TIME_SAMPLINGS} with time_scale "
                             f"> 0, got {self.time_sampling!r}, {self.time_scale!r}")
        if self.time_sampling == "grid" and self.time_grid_steps < 1:
            raise ValueError(f"FlowMatchingObjective.time_sampling='grid' needs time_grid_steps >= 1, got "
                             f"{self.time_grid_steps!r}")
        if self.time_grid_times is not None and (self.time_sampling != "grid"
                                                 or len(self.time_grid_times) != self.time_grid_steps):
            raise ValueError(f"FlowMatchingObjective.time_grid_times are the {self.time_grid_steps} times of "
                             f"time_sampling='grid', got {self.time_grid_times!r} with {self.time_sampling!r}")
        if self.grid_inputs not in GRID_INPUTS or (self.grid_inputs == "own_path" and self.time_sampling != "grid"):
            raise ValueError(f"FlowMatchingObjective.grid_inputs must be one of {GRID_INPUTS} ('own_path' with "
                             f"time_sampling='grid'), got {self.grid_inputs!r} with {self.time_sampling!r}")
        if self.bone_weight < 0 or (self.bone_weight > 0 and self.geometry is None):
            raise ValueError(f"FlowMatchingObjective.bone_weight must be >= 0 and needs a geometry when > 0, got "
                             f"{self.bone_weight!r}")
        if self.bone_target not in BONE_TARGETS:
            raise ValueError(f"FlowMatchingObjective.bone_target must be one of {BONE_TARGETS}, got "
                             f"{self.bone_target!r}")
        if self.trajectory_weight < 0 or (self.trajectory_weight > 0 and self.geometry is None):
            raise ValueError(f"FlowMatchingObjective.trajectory_weight must be >= 0 and needs a geometry when > 0, "
                             f"got {self.trajectory_weight!r}")
        if not 0.0 <= self.trajectory_min_t < 1.0:
            raise ValueError(f"FlowMatchingObjective.trajectory_min_t must be in [0, 1), got {self.trajectory_min_t!r}")
        if self.trajectory_huber < 0:
            raise ValueError(f"FlowMatchingObjective.trajectory_huber must be >= 0, got {self.trajectory_huber!r}")
        if self.foot_contact_weight < 0 or (self.foot_contact_weight > 0 and (
                self.geometry is None or self.geometry.skeleton is None)):
            raise ValueError(f"FlowMatchingObjective.foot_contact_weight must be >= 0 and needs a geometry with its "
                             f"skeleton when > 0, got {self.foot_contact_weight!r}")
        if self.input_perturbation < 0:
            raise ValueError(f"FlowMatchingObjective.input_perturbation must be >= 0, got {self.input_perturbation!r}")
        if not 0.0 <= self.self_condition_prob <= 1.0:
            raise ValueError(f"FlowMatchingObjective.self_condition_prob must be in [0, 1], got "
                             f"{self.self_condition_prob!r}")
        if self.root_mean_weight < 0:
            raise ValueError(f"FlowMatchingObjective.root_mean_weight must be >= 0, got {self.root_mean_weight!r}")
        if self.temporal_weight < 0:
            raise ValueError(f"FlowMatchingObjective.temporal_weight must be >= 0, got {self.temporal_weight!r}")
        if not 0.0 <= self.sigma_min < 1.0:
            raise ValueError(f"FlowMatchingObjective.sigma_min must be in [0, 1), got {self.sigma_min!r}")
        if self.terms_weighting not in TERM_WEIGHTINGS:
            raise ValueError(f"FlowMatchingObjective.terms_weighting must be one of {TERM_WEIGHTINGS}, got "
                             f"{self.terms_weighting!r}")
        if self.loss_space not in LOSS_SPACES:
            raise ValueError(f"FlowMatchingObjective.loss_space must be one of {LOSS_SPACES}, got {self.loss_space!r}")
        if self.velocity_weight_cap < 0 or (self.velocity_weight_cap > 0 and self.loss_space != "velocity"):
            raise ValueError(f"FlowMatchingObjective.velocity_weight_cap must be >= 0 and applies to the velocity "
                             f"loss only, got {self.velocity_weight_cap!r} with loss_space {self.loss_space!r}")

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
        self_condition_rows: torch.Tensor | None = None,
        estimate: bool = False,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        return flow_matching_loss(
            model, x1, cond, lengths, generator=generator, sigma_min=self.sigma_min, cond_mask=cond_mask,
            t=t, x0=x0, model_kwargs=model_kwargs, loss_space=self.loss_space,
            temporal_weight=self.temporal_weight, bone_weight=self.bone_weight, bone_target=self.bone_target,
            trajectory_weight=self.trajectory_weight, trajectory_min_t=self.trajectory_min_t,
            trajectory_huber=self.trajectory_huber, foot_contact_weight=self.foot_contact_weight,
            root_mean_weight=self.root_mean_weight, geometry=self.geometry,
            time_sampling=self.training_times,
            terms_weighting=self.terms_weighting,
            velocity_weight_cap=self.velocity_weight_cap,
            channel_weight=self.channel_weight_on(x1.device),
            input_perturbation=self.input_perturbation,
            self_condition_prob=self.self_condition_prob, self_condition_rows=self_condition_rows,
            grid_inputs=self.grid_inputs, estimate=estimate,
        )
