"""Reverse-diffusion sampling (DDPM ancestral, DDIM) and FLAME's replacement editing.

Every sampler runs :func:`reverse_diffusion` over the (optionally respaced) schedule of a
:class:`mfm.diffusion.GaussianDiffusion`, from index N−1 down to 0, one denoiser evaluation per step:

* ``ddpm``: ``x_{s−1} = mean + σ·z`` with the model's variance (fixed β̃ or learned), no noise at step 0
  (FLAME's and FlowMDM's sampler; both run all 1000 steps).
* ``ddim``: Song et al.'s update with ``eta`` (0 = deterministic); step 0 returns the x_0 estimate.

Results are :class:`mfm.solvers.SolveResult` so evaluation code treats flow and diffusion samples alike: ``x1`` is the
sample, ``nfe`` the number of denoiser evaluations (a classifier-free-guided evaluation is one batched pass of size 2B,
as in mfm.solvers), ``grid`` the float64 ``t_model`` of each step in the order taken (descending), and with
``return_trajectory`` ``x1_hat`` (K, B, T, D) holds the x_0 estimate of every step at ``x1_hat_times`` (= grid).

Randomness: the initial noise and every step's noise come, in that order, from one generator (default: a CPU
generator seeded with ``seed``), drawn on the generator's device and moved, so a seed gives the same samples on every
device. ``generator`` may also be one generator per motion (:func:`mfm.solvers.seeded_generators`): each motion then
draws its own valid frames' noise from its own stream (:func:`mfm.solvers.draw_noise`), so its sample does not depend
on the batch it is in (the pipeline's sampling and evaluation do this, as for flow models). Padded frames
(``>= lengths``) of the state are zeroed after every step, so they are exactly zero in the output.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor

from mfm.diffusion import DenoisedRange, GaussianDiffusion
from mfm.guidance import classifier_free_guidance
from mfm.editing import as_bool_mask
from mfm.features import ric_bone_lengths, set_ric_bone_lengths
from mfm.layout import FeatureLayout
from mfm.model import BONE_KEEPING, is_bone_keeping, valid_frame_mask
from mfm.skeleton import Skeleton
from mfm.solvers import (
    NoiseGenerators,
    SolveResult,
    check_lengths,
    draw_noise,
    model_feature_dim,
    sampling_inputs,
)

logger = logging.getLogger(__name__)

DenoiseFn = Callable[[Tensor, Tensor], Tensor]
"""``(x_s (B, T, D), t_model (B,)) -> output (B, T, D) or (B, T, 2D)``, e.g. from
:func:`mfm.guidance.classifier_free_guidance`."""

BeforeStep = Callable[[Tensor, int], Tensor]
"""``(x_s, schedule index s) -> x_s``, applied before the denoiser call of each step (replacement editing)."""

SAMPLERS = ("ddpm", "ddim")


def _schedule_for(diffusion: GaussianDiffusion, steps: int | str | Sequence[int] | None) -> GaussianDiffusion:
    return diffusion if steps is None else diffusion.respaced(steps)


def _draw_generator(seed: int, generator: NoiseGenerators | None) -> NoiseGenerators:
    return torch.Generator().manual_seed(seed) if generator is None else generator


@torch.no_grad()
def reverse_diffusion(
    denoise_fn: DenoiseFn,
    diffusion: GaussianDiffusion,
    x_start: Tensor,
    *,
    generator: NoiseGenerators,
    sampler: str = "ddpm",
    eta: float = 0.0,
    clip_denoised: float | DenoisedRange | None = None,
    frame_mask: Tensor | None = None,
    before_step: BeforeStep | None = None,
    return_trajectory: bool = False,
) -> SolveResult:
    """Run the reverse chain of ``diffusion`` (every index, N−1 → 0) from ``x_start`` (the noisiest state).

    frame_mask: (B, T) valid frames; the state is zeroed elsewhere after every step.
    clip_denoised: bounds of every step's x_0 estimate (:func:`mfm.diffusion.clamp_x0`); None = none.
    before_step: maps the state before each step's denoiser call (see :func:`replacement_edit`).
    """
    if sampler not in SAMPLERS:
        raise ValueError(f"unknown sampler {sampler!r}; known: {list(SAMPLERS)}")
    if sampler == "ddpm" and eta != 0.0:
        raise ValueError("eta is a DDIM parameter; the DDPM sampler takes none")
    if not eta >= 0.0:
        raise ValueError(f"eta must be >= 0, got {eta}")
    valid = None if frame_mask is None else frame_mask.unsqueeze(-1).to(x_start.dtype)
    # Per-motion noise draws need each row's length every step: read it off the device once, not per step.
    lengths = None if frame_mask is None else frame_mask.sum(dim=1).tolist()
    x = x_start
    nfe = 0
    estimates: list[Tensor] = []
    times: list[float] = []
    for index in reversed(range(diffusion.num_steps)):
        if before_step is not None:
            x = before_step(x, index)
        step = torch.full((x.shape[0],), index, dtype=torch.long, device=x.device)
        t_model = diffusion.model_time(step).to(x.dtype)
        output = denoise_fn(x, t_model)
        nfe += 1
        prediction = diffusion.p_mean_variance(output, x, step, clip_denoised=clip_denoised)
        if sampler == "ddpm":
            mean, std = prediction.mean, (0.5 * prediction.log_variance).exp()
        else:
            mean, std = diffusion.ddim_step(prediction.x0, x, step, eta)
        # No noise at step 0 (the reference multiplies it by zero; not drawing it changes no result).
        if index > 0 and (sampler == "ddpm" or eta > 0.0):
            x = mean + std * draw_noise(x.shape, generator, lengths=lengths, device=x.device, dtype=x.dtype)
        else:
            x = mean
        if valid is not None:
            x = x * valid
        times.append(float(t_model[0]))
        if return_trajectory:
            estimates.append(prediction.x0)
    grid = torch.tensor(times, dtype=torch.float64)
    x1_hat = torch.stack(estimates) if return_trajectory else None
    return SolveResult(x1=x, nfe=nfe, x1_hat=x1_hat, x1_hat_times=grid.clone() if return_trajectory else None,
                       grid=grid)


@torch.no_grad()
def sample_diffusion(
    model: Callable[..., Tensor],
    diffusion: GaussianDiffusion,
    cond: Tensor,
    lengths: Sequence[int] | Tensor,
    *,
    num_frames: int,
    feature_dim: int | None = None,
    sampler: str = "ddpm",
    steps: int | str | Sequence[int] | None = None,
    eta: float = 0.0,
    guidance: float = 2.5,
    null_cond: Tensor | None = None,
    clip_denoised: float | DenoisedRange | None = None,
    seed: int = 0,
    generator: NoiseGenerators | None = None,
    return_trajectory: bool = False,
    precision: str = "fp32",
) -> SolveResult:
    """Generate B = len(lengths) motions (B, num_frames, D) with a diffusion denoiser, as :func:`mfm.solvers.sample`.

    model: the denoiser, ``model(x, t_model, cond, lengths, cond_mask=...)``, in eval mode.
    steps: None = every training step (FLAME / FlowMDM: 1000); otherwise respaced
        (:func:`mfm.diffusion.space_timesteps`: an int K, ``"ddimK"`` or section counts).
    guidance: classifier-free scale (FLAME 8.0, FlowMDM 2.5); mixes the prediction channels only, a learned variance
        comes from the conditional half (FLAME).
    clip_denoised: bounds of the x_0 estimates (:func:`mfm.diffusion.clamp_x0`): c = [−c, c] on every channel
        (FLAME's ``True`` = 1.0, on its raw SMPL features), per-channel (:func:`rotation_6d_range`: FLAME's clamp on
        our normalised features) or None (default).
    feature_dim defaults to ``model.config.feature_dim``. precision: ``fp32`` or ``bf16`` (the denoiser's passes under
    bf16 autocast, its output fp32; the chain's arithmetic stays fp32: :func:`mfm.guidance.classifier_free_guidance`).
    """
    device, cond, lengths = sampling_inputs(model, cond, lengths, num_frames)
    dim = model_feature_dim(model, feature_dim)
    generator = _draw_generator(seed, generator)
    frame_mask = valid_frame_mask(lengths, num_frames)
    x_start = draw_noise((lengths.shape[0], num_frames, dim), generator, lengths=lengths, device=device)
    x_start = x_start * frame_mask.unsqueeze(-1)
    denoise_fn = classifier_free_guidance(model, cond, scale=guidance, lengths=lengths, null_cond=null_cond,
                                          guided_channels=dim, precision=precision)
    return reverse_diffusion(denoise_fn, _schedule_for(diffusion, steps), x_start, generator=generator,
                             sampler=sampler, eta=eta, clip_denoised=clip_denoised, frame_mask=frame_mask,
                             return_trajectory=return_trajectory)


def ddpm_sample(*args, **kwargs) -> SolveResult:
    """:func:`sample_diffusion` with the ancestral DDPM sampler."""
    return sample_diffusion(*args, sampler="ddpm", **kwargs)


def ddim_sample(*args, eta: float = 0.0, **kwargs) -> SolveResult:
    """:func:`sample_diffusion` with the DDIM sampler (``eta = 0``: deterministic)."""
    return sample_diffusion(*args, sampler="ddim", eta=eta, **kwargs)


@torch.no_grad()
def replacement_edit(
    denoise_fn: DenoiseFn,
    diffusion: GaussianDiffusion,
    x1_known: Tensor,
    keep_mask: Tensor | np.ndarray,
    *,
    steps: int | str | Sequence[int] | None = None,
    sampler: str = "ddpm",
    eta: float = 0.0,
    lengths: Sequence[int] | Tensor | None = None,
    clip_denoised: float | DenoisedRange | None = None,
    restore_known: bool = True,
    seed: int = 0,
    generator: NoiseGenerators | None = None,
    return_trajectory: bool = False,
) -> SolveResult:
    """FLAME's editing: regenerate ``x1_known`` (B, T, D) where ``keep_mask`` is False.

    Before the denoiser call of **every** reverse step s (N−1 → 0), the kept part of the state is overwritten with
    ``q_sample(x1_known, s, fresh noise)`` (FLAME ``edit_noise`` in ``p_sample_loop_progressive``); with a respaced
    schedule ᾱ is the respaced one, i.e. the original ᾱ at the kept step.

    What the kept part of the output is: after the last (step 0) replacement the state's kept part is
    ``√ᾱ[0]·x1_known + √(1 − ᾱ[0])·z`` and the DDPM step 0 returns the posterior mean, which at step 0 is the x_0
    estimate itself (``posterior_mean_coef2[0] = 0``); DDIM's step 0 returns it too. So FLAME's raw output keeps the
    known part only approximately (exactly for a denoiser that recovers it); FLAME then overwrites the translation with
    the reference when ``use_reference_translation`` (:func:`copy_reference_root`, after its smoothing) but leaves the
    kept joints as generated.
    ``restore_known=True`` (default) copies ``x1_known`` into the kept part of the output, so it equals the source
    exactly; ``False`` returns the raw chain output (FLAME's joints).

    denoise_fn: guided or unconditional (:func:`mfm.guidance.classifier_free_guidance`).
    keep_mask: bool, broadcastable (B or 1, T, D), True = keep (mfm.editing presets).
    lengths: valid frames; the state is zeroed beyond them after every step and in the output.
    """
    if x1_known.dim() != 3:
        raise ValueError(f"x1_known must be (B, T, D), got {tuple(x1_known.shape)}")
    keep = as_bool_mask(keep_mask, x1_known.shape, x1_known.device)
    schedule = _schedule_for(diffusion, steps)
    generator = _draw_generator(seed, generator)
    frame_mask = None
    if lengths is not None:
        lengths = check_lengths(lengths, x1_known.shape[1]).to(x1_known.device)
        frame_mask = valid_frame_mask(lengths, x1_known.shape[1])
    row_lengths = None if lengths is None else lengths.tolist()  # once, not per step (see reverse_diffusion)
    x_start = draw_noise(x1_known.shape, generator, lengths=row_lengths, device=x1_known.device,
                         dtype=x1_known.dtype)
    if frame_mask is not None:
        x_start = x_start * frame_mask.unsqueeze(-1).to(x_start.dtype)

    def replace_known(x: Tensor, index: int) -> Tensor:
        step = torch.full((x.shape[0],), index, dtype=torch.long, device=x.device)
        noise = draw_noise(x.shape, generator, lengths=row_lengths, device=x.device, dtype=x.dtype)
        return torch.where(keep, schedule.q_sample(x1_known, step, noise), x)

    result = reverse_diffusion(denoise_fn, schedule, x_start, generator=generator, sampler=sampler, eta=eta,
                               clip_denoised=clip_denoised, frame_mask=frame_mask, before_step=replace_known,
                               return_trajectory=return_trajectory)
    if restore_known:
        x = torch.where(keep, x1_known, result.x1)
        if frame_mask is not None:
            x = x * frame_mask.unsqueeze(-1).to(x.dtype)
        result.x1 = x
    return result


# ---------------------------------------------------------------------------------------------------------------
# How the baselines' authors sampled them


@dataclass(frozen=True)
class BaselineSampling:
    """A baseline's own sampling settings, applied by default to checkpoints of its diffusion preset."""

    guidance: float
    smoothing_sigma: float
    """Gaussian smoothing of the output over time (frames), σ in frames; 0: none."""
    source: str
    every_training_step: bool = False
    """Sample every step of the training schedule (no respacing), whatever step count a sweep asks for."""
    clip_denoised: bool = False
    """Clamp every step's x_0 estimate as the authors' sampler does; on our features :func:`rotation_6d_range`."""
    ema_weights: bool = False
    """The authors sample the EMA of the weights."""

    def record(self) -> dict[str, Any]:
        """What a results file says about these settings."""
        return dataclasses.asdict(self)

    def as_run(self, *, every_training_step: bool = True, clip_denoised: bool = True,
               ema_weights: bool = True) -> BaselineSampling:
        """These settings as a run applies them: each switch given False (the run turned that setting off) reads
        False, the others stay the authors'. Shared by the evaluator (``sampling.baseline_*``) and the sampler
        (pipeline/generation/request.py)."""
        return dataclasses.replace(self, every_training_step=self.every_training_step and every_training_step,
                                   clip_denoised=self.clip_denoised and clip_denoised,
                                   ema_weights=self.ema_weights and ema_weights)


BASELINE_SAMPLING: dict[str, BaselineSampling] = {
    "flame": BaselineSampling(
        guidance=8.0, smoothing_sigma=1.0, every_training_step=True, clip_denoised=True, ema_weights=True,
        source="kakaobrain/flame: configs/model/diffusion_hml3d.yaml: 16 guidance_scale 8.0; t2m_sample.py: 53, "
               "edit_motion.py: 79-82 and src/models/diffusion_module.py: 174-176 smooth every output with scipy "
               "gaussian_filter1d(sigma=1, axis=time); diffusion_module.py: 61-65 samples with "
               "space_timesteps(1000, [1000]) = all 1,000 training steps (sampling_strategy ddpm, "
               "diffusion_hml3d.yaml: 11); src/utils/sample_util.py: 90 clip_denoised=True (gaussian_diffusion.py: "
               "322-327 clamps the x0 estimate to [-1, 1]); sample_util.py: 43-68 and edit_motion.py: 64 sample the "
               "EMA model (diffusion_hml3d.yaml: 8-10 decay 0.99 every 10 steps, copied until step 100)"),
}
"""Keyed by :data:`mfm.diffusion.DIFFUSION_PRESETS` name; presets without an entry sample with our defaults. (FLAME's
edits' translation copy belongs to its editing procedure, which every diffusion checkpoint's edits follow:
:func:`copy_reference_root`.)"""


FLAME_X0_BOUND = 1.0
"""FLAME's ``clip_denoised=True``: improved DDPM's ``x.clamp(-1, 1)`` of the x_0 estimate, in FLAME's raw features."""

ROTATION_6D_RANGE_RECORD = "6D rotation channels in [-1, 1] (raw units); others unclamped"
"""What results files say about the bounds :func:`rotation_6d_range` sets."""


def rotation_6d_range(layout: FeatureLayout, mean: Tensor, std: Tensor) -> DenoisedRange:
    """FLAME's x_0 clamp carried to our features: the 6D rotation channels bounded to [−1, 1] in raw units, the
    others unbounded; as bounds in the training normalisation ``(raw − mean) / std`` the sampler runs in.

    FLAME clamps every channel of its raw 147-D estimate (3 root translation channels in metres + 24 joints × 6D)
    to [−1, 1]. A 6D channel is a component of two unit columns of a rotation matrix, so on those channels the
    clamp only trims estimates that leave the range every valid rotation lies in; ours (``layout.slices['rot6d']``)
    have the same meaning and get the same bound. Its translation channels (absolute AMASS root positions, bounded
    to a ±1 m box) have no counterpart in our features, whose root is velocities and a height; our joint positions,
    velocities and foot contacts do not exist in FLAME's features; those stay unclamped. Clamping our normalised
    features to [−1, 1] instead would bound every channel to ±1 std of the data, nothing like FLAME's clamp.
    """
    mean = torch.as_tensor(mean).detach().to("cpu", torch.float64).reshape(-1)
    std = torch.as_tensor(std).detach().to("cpu", torch.float64).reshape(-1)
    if mean.shape != (layout.dim,) or std.shape != (layout.dim,):
        raise ValueError(f"mean and std must have the skeleton's {layout.dim} channels, got {tuple(mean.shape)} and "
                         f"{tuple(std.shape)}")
    if not bool((std > 0).all()):
        raise ValueError("std must be positive on every channel to map the raw bounds into the normalisation")
    low = torch.full((layout.dim,), -math.inf, dtype=torch.float64)
    high = torch.full((layout.dim,), math.inf, dtype=torch.float64)
    rot = layout.slices["rot6d"]
    low[rot] = (-FLAME_X0_BOUND - mean[rot]) / std[rot]
    high[rot] = (FLAME_X0_BOUND - mean[rot]) / std[rot]
    return DenoisedRange(low.float(), high.float())  # on the CPU: clamp_x0 moves them to the estimate's device


def copy_reference_root(x: Tensor, reference: Tensor, keep: Tensor | np.ndarray, layout: FeatureLayout) -> Tensor:
    """FLAME's ``use_reference_translation`` on our features: ``x`` (B, T, D) with the root dims of ``reference``
    (``layout.root_dims``: rotation velocity, root-frame linear velocity, height) wherever ``keep`` keeps them.
    FLAME's ``edit_motion.py``: 93–94 (``configs/edit_motion.yaml``: 4 ``use_reference_translation: true``) does
    it after its smoothing (79–82), so its edited output's translation is the reference's exactly.

    FLAME's translation is the root position itself; ours is integrated from these four dims (the heading from the
    rotation velocity, the position from the rotated linear velocity, the height as is), so copying them on every
    frame (a joint edit such as the upper body's, the only kind FLAME's code has) makes the output's root trajectory
    and heading equal the reference's. On the kept frames of a frame edit (prediction, in-between) it copies the
    root's motion there; positions after regenerated frames keep the offset those frames integrated. The
    regenerated frames' root is never copied: there it is what the task asks the model for (FLAME's code would
    keep the translation on every frame, but has no frame edits).
    """
    keep = as_bool_mask(keep, x.shape, x.device)
    root = torch.zeros(x.shape[-1], dtype=torch.bool, device=x.device)
    root[torch.as_tensor(layout.root_dims, device=x.device)] = True
    return torch.where(keep & root, reference.to(x.dtype), x)


@dataclass(frozen=True)
class BoneKeeping:
    """What :func:`smooth_over_time` needs to give every bone back its length after the filter
    (``ModelConfig.output_smoothing_keeps_bones``): the skeleton and the dataset's Mean/Std, since the bone
    lengths are those of the raw features, and which lengths: each frame's own before the filter ("frame"), or
    those lengths smoothed over time with the filter's σ ("smoothed")."""

    skeleton: Skeleton
    mean: Tensor
    std: Tensor
    lengths: Literal["frame", "smoothed"] = "frame"

    @classmethod
    def for_setting(cls, setting: bool | str, skeleton: Skeleton, mean: Tensor, std: Tensor) -> "BoneKeeping | None":
        """The bone keeping a setting of :data:`mfm.model.BONE_KEEPING` asks for (None: the plain filter)."""
        if not is_bone_keeping(setting):
            raise ValueError(f"output_smoothing_keeps_bones must be one of {BONE_KEEPING}, got {setting!r}")
        if setting is False:
            return None
        return cls(skeleton, mean, std, "smoothed" if setting == "smoothed" else "frame")


def _filter_valid_frames(array: np.ndarray, lengths: Sequence[int], sigma: float) -> np.ndarray:
    """``array`` (B, T, ...) with each sample's first ``lengths[b]`` frames Gaussian-filtered over time as FLAME's
    ``gaussian_filter1d(motion, sigma, axis=1)`` (scipy: reflected edges, kernel truncated at 4σ); padded frames as
    they are."""
    from scipy.ndimage import gaussian_filter1d

    out = array.copy()
    for b, length in enumerate(lengths):
        out[b, :length] = gaussian_filter1d(array[b, :length], sigma=sigma, axis=0)
    return out


def smooth_over_time(x: Tensor, lengths: Sequence[int] | Tensor, sigma: float,
                     keep_bones: BoneKeeping | None = None) -> Tensor:
    """``x`` (B, T, D) smoothed along time over each sample's valid frames, as FLAME's
    ``gaussian_filter1d(motion, sigma, axis=1)`` (scipy: reflected edges, kernel truncated at 4σ); padded frames
    stay as they are. Smoothing commutes with a per-channel affine normalisation, so normalised and raw features
    give the same motion. With ``keep_bones`` (``x`` normalised by its mean/std) every bone of the smoothed ric
    positions then gets back a length of ``x``'s along its smoothed direction (:func:`mfm.features.
    set_ric_bone_lengths`; ours, not FLAME's): the one it had in that frame ("frame"), or its lengths over the
    frames smoothed with the same σ ("smoothed": the filter then acts on each bone's length as a number instead of
    shortening it along its arc, and a frame's length jitter is not put back)."""
    if sigma <= 0:
        return x
    lengths = check_lengths(lengths, x.shape[1])
    frames = lengths.tolist()
    smoothed = torch.from_numpy(_filter_valid_frames(x.detach().cpu().double().numpy(), frames, sigma))
    smoothed = smoothed.to(dtype=x.dtype, device=x.device)
    if keep_bones is None:
        return smoothed
    mean = keep_bones.mean.to(x.device, torch.float64)
    std = keep_bones.std.to(x.device, torch.float64)
    bone_lengths = ric_bone_lengths(x.double() * std + mean, keep_bones.skeleton)  # (B, T, J-1)
    if keep_bones.lengths == "smoothed":
        bone_lengths = torch.from_numpy(_filter_valid_frames(bone_lengths.cpu().numpy(), frames, sigma))
    restored = set_ric_bone_lengths(smoothed.double() * std + mean, bone_lengths.to(x.device), keep_bones.skeleton)
    valid = valid_frame_mask(lengths.to(x.device), x.shape[1]).unsqueeze(-1)
    return torch.where(valid, ((restored - mean) / std).to(x.dtype), smoothed)
