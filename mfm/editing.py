"""Motion editing by trajectory rewriting (MFM Algorithm 1) and the masks that say what is kept.

Editing integrates the same flow as sampling, but before each step whose start time ``t <= rewrite_until`` (ς) the
known part of the state is overwritten with its point on the straight noise→data line of the *initial* noise,
``(1 - t)·x0 + t·x1_known``; after ς the solver runs unconstrained so the generated and known parts blend. The final
step is never followed by a replacement (as the reference ``sample_euler_replacement_edit_till``), so even with
ς = 1 the known frames carry the last step's drift ``h·(v - (x1_known - x0))``, which is zero for a field that is
exact on the known line.

Masks are bool tensors broadcastable to (B, T, D), True = keep (known, taken from the source motion); they are built
from the skeleton's FeatureLayout (joint dims, lower-body joints), never from hand-written index lists. Presets follow
MFM's edit.py: ``prediction``, ``inbetween``, ``interpolation`` (frame masks) and ``upper_body`` (keep root, legs and
foot contacts, regenerate the upper body).

The source motion must be in the model's feature space, i.e. normalised with the training Mean/Std
(:func:`motion_to_features` does the conversion from joints and the normalisation).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from mfm.layout import FeatureLayout
from mfm.model import valid_frame_mask
from mfm.skeleton import Skeleton
from mfm.solvers import (
    FIXED_STEP_SOLVERS,
    SolveResult,
    VelocityFn,
    check_lengths,
    initial_noise,
    solve,
    zero_padded_frames,
)

# A grid time counts as "<= rewrite_until" within this tolerance, so ς = 0.2 includes the grid point 6/30 whatever
# its last-bit rounding.
REWRITE_TIME_TOLERANCE = 1e-9


def as_bool_mask(keep_mask: Tensor | np.ndarray, shape: torch.Size, device: torch.device) -> Tensor:
    mask = torch.as_tensor(keep_mask, device=device)
    if mask.dtype != torch.bool:
        raise ValueError(f"keep_mask must be a bool tensor (True = keep), got {mask.dtype}")
    try:
        torch.broadcast_shapes(mask.shape, shape)
    except RuntimeError:
        raise ValueError(f"keep_mask of shape {tuple(mask.shape)} does not broadcast to the motion {tuple(shape)}") from None
    if mask.dim() != len(shape):
        raise ValueError(f"keep_mask must be (B or 1, T, D) like the motion {tuple(shape)}, got {tuple(mask.shape)}")
    return mask


@torch.no_grad()
def edit(
    velocity_fn: VelocityFn,
    x1_known: Tensor,
    keep_mask: Tensor | np.ndarray,
    *,
    steps: int = 30,
    rewrite_until: float = 0.2,
    grid: Sequence[float] | Tensor | None = None,
    solver: str = "euler",
    seed: int = 0,
    generator: torch.Generator | None = None,
    x0: Tensor | None = None,
    lengths: Sequence[int] | Tensor | None = None,
    return_trajectory: bool = False,
) -> SolveResult:
    """Regenerate the unknown part of ``x1_known`` (B, T, D) where ``keep_mask`` is False.

    velocity_fn: guided (mfm.solvers.guided_velocity with a text/action condition) or unconditional (scale 0).
    rewrite_until: ς in [0, 1]; the known part is rewritten before every step starting at ``t <= ς`` (inclusive,
        as the reference's ``t <= edit_till``). ς = 0 rewrites only at t = 0, where the line point is x0 itself,
        so it is plain sampling from x0.
    grid / steps / solver: any fixed step grid (default ``steps`` uniform steps) and fixed-step solver (MFM:
        Euler); the rewrite happens at the grid times, before each step.
    x0: the initial noise (B, T, D); default drawn from ``generator`` or a CPU generator seeded with ``seed``.
    lengths: valid frames per sample; padded frames of x0 and of the velocity are zeroed (see mfm.solvers.sample).
    """
    if x1_known.dim() != 3:
        raise ValueError(f"x1_known must be (B, T, D), got {tuple(x1_known.shape)}")
    if not 0.0 <= rewrite_until <= 1.0:
        raise ValueError(f"rewrite_until must be in [0, 1], got {rewrite_until}")
    if solver not in FIXED_STEP_SOLVERS:
        raise ValueError(f"trajectory rewriting needs a fixed-step solver {sorted(FIXED_STEP_SOLVERS)}, got {solver!r}")
    keep = as_bool_mask(keep_mask, x1_known.shape, x1_known.device)
    if x0 is None:
        x0 = initial_noise(x1_known.shape, seed=seed, generator=generator, device=x1_known.device,
                           dtype=x1_known.dtype)
    elif x0.shape != x1_known.shape:
        raise ValueError(f"x0 has shape {tuple(x0.shape)}, expected the motion's {tuple(x1_known.shape)}")
    if lengths is not None:
        lengths = check_lengths(lengths, x1_known.shape[1]).to(x1_known.device)
        x0 = x0 * valid_frame_mask(lengths, x1_known.shape[1]).unsqueeze(-1).to(x0.dtype)
        velocity_fn = zero_padded_frames(velocity_fn, lengths)

    def rewrite_known(state: Tensor, t: float, step_index: int) -> Tensor:
        if t > rewrite_until + REWRITE_TIME_TOLERANCE:
            return state
        return torch.where(keep, (1.0 - t) * x0 + t * x1_known, state)

    return solve(velocity_fn, x0, solver=solver, steps=steps, grid=grid, return_trajectory=return_trajectory,
                 before_step=rewrite_known)


# ---------------------------------------------------------------------------------------------------
# settings: steps, ς and guidance of a flow edit


@dataclass(frozen=True)
class EditSettings:
    """How a flow edit integrates: Euler steps, ς per preset, guidance scale, and where the values come from."""

    name: str
    steps: int
    """Euler steps of every preset not in ``steps_per_preset``."""
    rewrite_until: Mapping[str, float]
    """ς per mask preset (EDIT_MASK_PRESETS) and ``'joints'`` (a custom joint/frame mask)."""
    guidance: float
    source: str
    steps_per_preset: Mapping[str, int] = field(default_factory=dict)
    """Presets whose Euler steps differ from ``steps`` (edit.py's interpolation: one step)."""

    def rewrite_time(self, preset: str) -> float:
        if preset not in self.rewrite_until:
            raise ValueError(f"edit settings {self.name!r} have no ς for preset {preset!r}")
        return float(self.rewrite_until[preset])

    def steps_for(self, preset: str) -> int:
        """Euler steps of ``preset`` (a mask preset or ``'joints'``) under these settings."""
        if preset not in self.rewrite_until:
            raise ValueError(f"edit settings {self.name!r} have no steps for preset {preset!r}")
        return int(self.steps_per_preset.get(preset, self.steps))

    def record(self) -> dict[str, Any]:
        """What a results file says about these settings."""
        return {"settings": self.name, "steps": self.steps, "steps_per_preset": dict(self.steps_per_preset),
                "rewrite_until": dict(self.rewrite_until), "guidance": self.guidance, "source": self.source}


_EDIT_KINDS = ("prediction", "inbetween", "interpolation", "upper_body", "joints")

EDIT_SETTINGS: dict[str, EditSettings] = {
    "paper": EditSettings(
        name="paper", steps=30, rewrite_until={kind: 0.2 for kind in _EDIT_KINDS}, guidance=1.0,
        source="MFM paper §4.1 (implementation details): N = 30 Euler steps, 'restrict the editing to the initial "
               "t = 0.2' (ς = 0.2), not from edit.py; guidance 1.0 as the reference edit.py: 48 sets "
               "(cfg.guidance_param = 1.0, i.e. the conditional field alone)"),
    "reference-debug": EditSettings(
        name="reference-debug", steps=100,
        rewrite_until={"prediction": 0.5, "inbetween": 1.0, "interpolation": 1.0, "upper_body": 0.1, "joints": 0.1},
        guidance=1.0, steps_per_preset={"interpolation": 1},
        source="motionfm edit.py is_debug presets (guidance_param 1.0 at :48): step_size 0.01 = 100 steps with "
               "edit_till in_between 1.0 (:72-77), upper_body 0.1 (:78-82), prediction 0.5 (:83-87); interpolate "
               "step_size 1 = one step (:96-99; it keeps config_base's edit_till 1.0, and its one rewrite at t = 0 "
               "puts the initial noise itself on the known part, so the source never enters); our custom joints "
               "mask takes the upper body's 100 steps and 0.1"),
}
"""Named edit settings; ``'paper'`` is the default everywhere (launch/sample.py edits and the evaluator).
``'paper'``'s values come from the MFM paper's text (§4.1), ``'reference-debug'``'s from edit.py's debug presets."""
DEFAULT_EDIT_SETTINGS = "paper"


def edit_settings(name: str) -> EditSettings:
    if name not in EDIT_SETTINGS:
        raise ValueError(f"unknown edit settings {name!r}; known: {', '.join(EDIT_SETTINGS)}")
    return EDIT_SETTINGS[name]


# ---------------------------------------------------------------------------------------------------
# masks (True = keep)


def _frames_to_feature_mask(frame_keep: Tensor, layout: FeatureLayout) -> Tensor:
    """(B, T) frame mask -> (B, T, D) feature mask keeping every dim of the kept frames."""
    return frame_keep.unsqueeze(-1).expand(-1, -1, layout.dim).contiguous()


def _fraction_index(lengths: Tensor, fraction: float) -> Tensor:
    """⌊fraction·L⌋ per sample, computed in float64 like the reference's ``int(fraction * length)``."""
    return torch.floor(lengths.double() * fraction).long()


def prediction_mask(
    lengths: Sequence[int] | Tensor, num_frames: int, layout: FeatureLayout, *, prefix: float = 0.25
) -> Tensor:
    """(B, T, D): keep frames [0, ⌊prefix·L⌋) of each sample, generate the rest (motion prediction)."""
    if not 0.0 <= prefix <= 1.0:
        raise ValueError(f"prefix must be in [0, 1], got {prefix}")
    lengths = check_lengths(lengths, num_frames)
    frames = torch.arange(num_frames).unsqueeze(0)
    return _frames_to_feature_mask(frames < _fraction_index(lengths, prefix).unsqueeze(1), layout)


def inbetween_mask(
    lengths: Sequence[int] | Tensor,
    num_frames: int,
    layout: FeatureLayout,
    *,
    prefix: float = 0.25,
    suffix: float = 0.75,
) -> Tensor:
    """(B, T, D): keep [0, ⌊prefix·L⌋) and [⌊suffix·L⌋, T), generate the middle (in-betweening).
    As the reference, the kept suffix runs to the end of the window, padding included."""
    if not 0.0 <= prefix <= suffix <= 1.0:
        raise ValueError(f"need 0 <= prefix <= suffix <= 1, got prefix={prefix}, suffix={suffix}")
    lengths = check_lengths(lengths, num_frames)
    frames = torch.arange(num_frames).unsqueeze(0)
    keep = (frames < _fraction_index(lengths, prefix).unsqueeze(1)) | (
        frames >= _fraction_index(lengths, suffix).unsqueeze(1)
    )
    return _frames_to_feature_mask(keep, layout)


def interpolation_mask(
    lengths: Sequence[int] | Tensor, num_frames: int, layout: FeatureLayout, *, every: int = 5
) -> Tensor:
    """(B, T, D): keep frames 0, k, 2k, … below ``⌊T/k⌋·k`` of the whole window (MFM's edit.py keeps
    ``i·k for i in range(T // k)``: frames 0 … 190 of a 196-frame window, not 195), generate the frames between.
    ``lengths`` fixes the batch size and is validated against ``num_frames``."""
    if not isinstance(every, int) or every < 1:
        raise ValueError(f"every must be a positive int, got {every!r}")
    lengths = check_lengths(lengths, num_frames)
    frames = torch.arange(num_frames)
    on_grid = (frames % every == 0) & (frames < (num_frames // every) * every)
    keep = on_grid.unsqueeze(0).expand(lengths.shape[0], -1)
    return _frames_to_feature_mask(keep, layout)


def upper_body_mask(num_frames: int, layout: FeatureLayout) -> Tensor:
    """(1, T, D): keep the root, leg and foot-contact dims (``layout.lower_body_mask``) on every frame and
    regenerate the upper body."""
    dims = torch.from_numpy(layout.lower_body_mask)
    return dims.view(1, 1, -1).expand(1, num_frames, -1).contiguous()


def _joint_indices(joints: Iterable[int | str], layout: FeatureLayout) -> list[int]:
    names = layout.skeleton.joint_names
    indices = []
    for joint in joints:
        if isinstance(joint, str):
            if joint not in names:
                raise ValueError(f"unknown joint {joint!r} for skeleton {layout.skeleton.name!r}; known: {names}")
            indices.append(names.index(joint))
        else:
            indices.append(int(joint))
    return indices


def _frame_selection(frames: Iterable[int] | slice | Tensor | np.ndarray, num_frames: int) -> Tensor:
    """(T,) bool from frame indices, a slice or a (T,) bool mask."""
    selected = torch.zeros(num_frames, dtype=torch.bool)
    if isinstance(frames, slice):
        selected[frames] = True
        return selected
    frames = torch.as_tensor(frames if isinstance(frames, (Tensor, np.ndarray)) else list(frames))
    if frames.dtype == torch.bool:
        if frames.shape != (num_frames,):
            raise ValueError(f"a bool frame mask must have shape ({num_frames},), got {tuple(frames.shape)}")
        return frames.clone()
    frames = frames.long().reshape(-1)
    if frames.numel() and (int(frames.min()) < -num_frames or int(frames.max()) >= num_frames):
        raise ValueError(f"frame indices must be in [0, {num_frames}), got {frames.tolist()}")
    selected[frames] = True
    return selected


def joint_frame_mask(
    num_frames: int,
    layout: FeatureLayout,
    frames: Iterable[int] | slice | Tensor | np.ndarray,
    joints: Iterable[int | str],
) -> Tensor:
    """(1, T, D): True on the dims of ``joints`` (indices or skeleton joint names; see
    :meth:`FeatureLayout.joint_dims`) at ``frames`` (indices, a slice or a (T,) bool mask).

    Used as a keep mask it keeps exactly those joints at those frames; its complement ``~mask`` keeps everything
    else, i.e. regenerates those joints at those frames.
    """
    dims = torch.from_numpy(layout.joint_mask(_joint_indices(joints, layout)))
    selected = _frame_selection(frames, num_frames)
    return (selected.view(1, -1, 1) & dims.view(1, 1, -1)).contiguous()


def _upper_body_preset(lengths: Sequence[int] | Tensor, num_frames: int, layout: FeatureLayout) -> Tensor:
    """:func:`upper_body_mask` repeated over the batch, for the uniform preset signature."""
    batch = check_lengths(lengths, num_frames).shape[0]
    return upper_body_mask(num_frames, layout).expand(batch, -1, -1).contiguous()


MaskPreset = Callable[..., Tensor]

EDIT_MASK_PRESETS: dict[str, MaskPreset] = {
    "prediction": prediction_mask,
    "inbetween": inbetween_mask,
    "interpolation": interpolation_mask,
    "upper_body": _upper_body_preset,
}
"""Uniform signature ``preset(lengths, num_frames, layout, **options) -> (B, T, D)`` for command lines."""


def edit_mask(
    preset: str, lengths: Sequence[int] | Tensor, num_frames: int, layout: FeatureLayout, **options
) -> Tensor:
    """The keep mask of a named preset (``EDIT_MASK_PRESETS``), (B, T, D); ``options`` go to the preset."""
    if preset not in EDIT_MASK_PRESETS:
        raise ValueError(f"unknown edit preset {preset!r}; known: {sorted(EDIT_MASK_PRESETS)}")
    return EDIT_MASK_PRESETS[preset](lengths, num_frames, layout, **options)


# ---------------------------------------------------------------------------------------------------
# source motions


def motion_to_features(
    motion: np.ndarray | Tensor,
    skeleton: Skeleton,
    *,
    mean: np.ndarray | Tensor | None = None,
    std: np.ndarray | Tensor | None = None,
    target_offsets: np.ndarray | None = None,
) -> Tensor:
    """A source motion as float32 features (T', D) ready for :func:`edit`.

    motion: (T, D) HumanML3D-style features of ``skeleton`` (returned as they are, T' = T), or (T, J, 3) joint
        positions, converted with ``mfm.features.joints_to_features`` (T' = T - 1, as HumanML3D's extraction;
        ``target_offsets`` is passed on, e.g. KIT's measured target skeleton).
    mean, std: the training normalisation (D,); if given the result is ``(features - mean) / std``.
    """
    array = torch.as_tensor(np.asarray(motion) if not isinstance(motion, Tensor) else motion)
    if array.dim() == 2:
        if array.shape[1] != skeleton.feature_dim:
            raise ValueError(
                f"a (T, D) motion for skeleton {skeleton.name!r} must have D = {skeleton.feature_dim}, "
                f"got {tuple(array.shape)}"
            )
        features = array.to(torch.float32)
    elif array.dim() == 3:
        if array.shape[1:] != (skeleton.num_joints, 3):
            raise ValueError(
                f"a (T, J, 3) motion for skeleton {skeleton.name!r} must have J = {skeleton.num_joints}, "
                f"got {tuple(array.shape)}"
            )
        # Imported here: joint conversion is only needed for joint inputs, and mfm.features is a large module.
        from mfm.features import joints_to_features

        features = joints_to_features(array, skeleton, target_offsets=target_offsets).to(torch.float32)
    else:
        raise ValueError(f"motion must be (T, D) features or (T, J, 3) joints, got shape {tuple(array.shape)}")
    if not bool(torch.isfinite(features).all()):
        raise ValueError("motion features contain NaN or inf")
    if (mean is None) != (std is None):
        raise ValueError("pass both mean and std to normalise, or neither")
    if mean is not None:
        features = (features - torch.as_tensor(mean, dtype=torch.float32)) / torch.as_tensor(std, dtype=torch.float32)
    return features
