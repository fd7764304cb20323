"""The joint-space metrics of :mod:`mfm.metrics` in torch, on the joints' own device (CPU or CUDA).

The evaluator recovers a generated batch's joints on its device (``mfm.features.features_to_joints``); these
functions score them there, every clip of the batch at once and masked to its own ``lengths[i]`` frames (no loop
over clips or frames), so the only host transfer is the result: the per-clip figures or the batch's scalars, once
per call. Each function has the name, arguments and definition of its numpy reference in :mod:`mfm.metrics` (which
stays: other callers use it, and the tests compare the two): :func:`plausibility` (bone lengths, floor penetration,
foot skating, mean jerk, motion amount), :func:`ape_ave` (TEMOS's APE/AVE), :func:`ade` / :func:`fde` (editing) and
:func:`joint_variance_per_group` (FLAME's per-text joint variance, every text of a batch at once).

Inputs are (N, T, J, 3) tensors and (N,) integer lengths on the same device; computed in the joints' dtype (the
evaluator passes float64, where the results equal the numpy path's up to summation order, ~1e-15 relative). Bad
input raises the numpy functions' ``ValueError``; checking it costs one device synchronisation per call.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from mfm.metrics import (
    FOOT_CONTACT_HEIGHT,
    FOOT_SKATING_SPEED,
    METRES_PER_UNIT,
    MIN_BONE_LENGTH,
    TEMOS_FLOOR_MM_PER_UNIT,
    TEMOS_FLOOR_SOFTNESS,
    PlausibilityFigures,
)
from mfm.skeleton import Skeleton

_APE_AVE_KEYS = (*(f"APE_{k}" for k in ("root", "traj", "mean_local", "mean_global")),
                 *(f"AVE_{k}" for k in ("root", "traj", "mean_local", "mean_global")))


def _checked(joints: Tensor, name: str, lengths: Tensor | None, minimum: int = 1) -> Tensor:
    """``lengths`` as int64 on the joints' device (None: every clip full length), after the checks of
    ``mfm.metrics._as_numpy`` / ``_lengths_or_full``: (N, T, J, 3) joints, finite, one length per clip in
    [minimum, T]. One synchronisation for all of them."""
    if not isinstance(joints, Tensor) or joints.ndim != 4 or joints.shape[-1] != 3:
        raise ValueError(f"{name} must be an (N, T, J, 3) tensor of joint positions, got "
                         f"{tuple(joints.shape) if isinstance(joints, Tensor) else type(joints).__name__}")
    if not joints.is_floating_point():
        raise ValueError(f"{name} must be floating point, got {joints.dtype}")
    n, t = joints.shape[:2]
    lens = (torch.full((n,), t, dtype=torch.int64, device=joints.device) if lengths is None
            else torch.as_tensor(lengths, device=joints.device).to(torch.int64).reshape(-1))
    if lens.shape[0] != n:
        raise ValueError(f"lengths must have one entry per sequence ({n}), got {lens.shape[0]}")
    if n == 0:
        return lens
    finite, low, high = torch.stack([torch.isfinite(joints).all().to(torch.int64), lens.min(), lens.max()]).tolist()
    if not finite:
        raise ValueError(f"{name} contains NaN or inf")
    if low < minimum or high > t:
        raise ValueError(f"lengths must lie in [{minimum}, {t}], got min {low} max {high}")
    return lens


def _frame_mask(lens: Tensor, t: int) -> Tensor:
    """(N, T) True on each clip's frames ``< lengths[i]``."""
    return torch.arange(t, device=lens.device)[None, :] < lens[:, None]


def _masked_mean(values: Tensor, mask: Tensor, empty: float) -> Tensor:
    """Per clip (dim 0) mean of ``values`` where ``mask`` (the same shape); ``empty`` for a clip with nothing in."""
    dims = tuple(range(1, values.ndim))
    count = mask.sum(dim=dims)
    total = torch.where(mask, values, 0.0).sum(dim=dims)
    return torch.where(count > 0, total / count.clamp_min(1), empty)


# ---------------------------------------------------------------------------------------------------------------
# Plausibility (mfm.metrics.plausibility and the functions it calls)
# ---------------------------------------------------------------------------------------------------------------


def _bone_length_consistency(pos: Tensor, parents: np.ndarray, lens: Tensor) -> tuple[Tensor, Tensor]:
    par = torch.as_tensor(np.asarray(parents, dtype=np.int64).reshape(-1), device=pos.device)
    if par.shape[0] != pos.shape[2]:
        raise ValueError(f"parents lists {par.shape[0]} joints, joints have {pos.shape[2]}")
    children = torch.nonzero(par >= 0).flatten()
    length = torch.linalg.vector_norm(pos[:, :, children] - pos[:, :, par[children]], dim=-1)  # (N, T, B)
    valid = _frame_mask(lens, pos.shape[1])[..., None]  # (N, T, 1)
    spread = (torch.where(valid, length, -torch.inf).amax(dim=1)
              - torch.where(valid, length, torch.inf).amin(dim=1))  # (N, B)
    mean = torch.where(valid, length, 0.0).sum(dim=1) / lens[:, None]  # (N, B)
    measurable = mean >= MIN_BONE_LENGTH
    deviation = (length - mean[:, None]).abs() / torch.where(measurable, mean, 1.0)[:, None]
    return spread.amax(dim=1), _masked_mean(deviation, (valid & measurable[:, None]).expand_as(deviation), torch.nan)


def _floor_penetration(pos: Tensor, feet: list[int], lens: Tensor) -> Tensor:
    lowest_foot = pos[:, :, feet, 1].amin(dim=-1)  # (N, T)
    lowest = torch.where(_frame_mask(lens, pos.shape[1]), lowest_foot, torch.inf).amin(dim=1)
    return torch.where(lowest < 0.0, -lowest, 0.0)


def _foot_skating(pos: Tensor, feet: list[int], fps: float, lens: Tensor, contact_height: float,
                  skating_speed: float) -> tuple[Tensor, Tensor, Tensor]:
    pairs = lens - 1
    foot = pos[:, :, feet]  # (N, T, F, 3)
    speed = torch.linalg.vector_norm(torch.diff(foot[..., [0, 2]], dim=1), dim=-1) * fps  # (N, T-1, F)
    low = foot[..., 1] < contact_height  # (N, T, F)
    in_clip = _frame_mask(pairs, pos.shape[1] - 1)  # (N, T-1)
    contact = low[:, :-1] & low[:, 1:] & in_clip[..., None]
    skating = contact & (speed > skating_speed)
    ratio = _masked_mean(skating.any(dim=-1).to(pos.dtype), in_clip, torch.nan)
    skating_mean = torch.where(pairs == 0, torch.nan, _masked_mean(speed, skating, 0.0))
    return ratio, _masked_mean(speed, contact, torch.nan), skating_mean


def _mean_jerk(pos: Tensor, lens: Tensor) -> Tensor:
    n, t = pos.shape[:2]
    if t < 4:
        return torch.full((n,), torch.nan, dtype=pos.dtype, device=pos.device)
    jerk = torch.diff(pos, n=3, dim=1).abs().sum(dim=-1).amax(dim=-1)  # (N, T-3), FlowMDM's calculate_jerk
    entries = lens - 3
    jerk = torch.where(torch.arange(t - 3, device=pos.device)[None, :] >= entries[:, None], 0.0, jerk)
    return torch.where(entries > 0, jerk.sum(dim=1) / entries.clamp_min(1), torch.nan)


def _spread(local: Tensor, lens: Tensor) -> Tensor:
    frames = _frame_mask(lens, local.shape[1])[..., None, None]  # (N, T, 1, 1)
    count = frames.sum(dim=1)  # (N, 1, 1)
    centre = torch.where(frames, local, 0.0).sum(dim=1, keepdim=True) / count[:, None]  # (N, 1, J, 3)
    square = torch.where(frames, local - centre, 0.0) ** 2
    return torch.sqrt(square.sum(dim=(1, 3)) / count[..., 0]).mean(dim=-1)


def _motion_amount(pos: Tensor, fps: float, lens: Tensor, root: int = 0) -> tuple[Tensor, Tensor, Tensor]:
    in_clip = _frame_mask(lens - 1, pos.shape[1] - 1)  # (N, T-1)
    local = pos - pos[:, :, root : root + 1]
    local_speed = torch.linalg.vector_norm(torch.diff(local, dim=1), dim=-1).mean(dim=-1) * fps  # (N, T-1)
    root_speed = torch.linalg.vector_norm(torch.diff(pos[:, :, root][..., [0, 2]], dim=1), dim=-1) * fps
    return (_masked_mean(local_speed, in_clip, torch.nan), _masked_mean(root_speed, in_clip, torch.nan),
            _spread(local, lens))


def plausibility(joints: Tensor, skeleton: Skeleton, lengths: Tensor | None = None, *,
                 contact_height: float = FOOT_CONTACT_HEIGHT,
                 skating_speed: float = FOOT_SKATING_SPEED) -> PlausibilityFigures:
    """:func:`mfm.metrics.plausibility` of (N, T, J, 3) joints on their device: the per-clip figures, brought to
    the host once as numpy (N,) arrays (no ``jerk_ratio``: the evaluator gives each row its reference)."""
    lens = _checked(joints, "joints", lengths)
    if joints.shape[2] != skeleton.num_joints:
        raise ValueError(f"joints have {joints.shape[2]} joints, skeleton {skeleton.name!r} {skeleton.num_joints}")
    if skeleton.fps <= 0:
        raise ValueError(f"fps must be positive, got {skeleton.fps}")
    pos = joints * METRES_PER_UNIT[skeleton.unit]
    feet = list(skeleton.foot_left + skeleton.foot_right)
    bone_range, bone_deviation = _bone_length_consistency(pos, skeleton.parents, lens)
    ratio, contact_speed, skating_foot_speed = _foot_skating(pos, feet, skeleton.fps, lens, contact_height,
                                                             skating_speed)
    pose_speed, root_speed, pose_spread = _motion_amount(pos, skeleton.fps, lens)
    figures = (bone_range, bone_deviation, _floor_penetration(pos, feet, lens), ratio, contact_speed,
               skating_foot_speed, _mean_jerk(pos, lens), pose_speed, root_speed, pose_spread)
    host = torch.stack(figures).to(torch.float64).cpu().numpy()  # one transfer for the ten (N,) figures
    names = ("bone_length_range", "bone_length_deviation", "floor_penetration", "foot_skating_ratio",
             "contact_foot_speed", "skating_foot_speed", "mean_jerk", "pose_speed", "root_speed", "pose_spread")
    return PlausibilityFigures(**dict(zip(names, host)))


# ---------------------------------------------------------------------------------------------------------------
# APE / AVE (mfm.metrics.ape_ave: TEMOS's definition)
# ---------------------------------------------------------------------------------------------------------------


def _yaw_rotation(angle: Tensor) -> Tensor:
    """(..., 3, 3) rotations about +y as ``mfm.metrics._yaw_rotation`` (row vectors, ``p @ R``)."""
    c, s = torch.cos(angle), torch.sin(angle)
    z, o = torch.zeros_like(angle), torch.ones_like(angle)
    return torch.stack([torch.stack([c, z, s], -1), torch.stack([z, o, z], -1), torch.stack([-s, z, c], -1)], -2)


def _heading(joints: Tensor, face_joints: tuple[int, int, int, int]) -> Tensor:
    r_hip, l_hip, r_sh, l_sh = face_joints
    across = joints[..., r_hip, :] - joints[..., l_hip, :] + joints[..., r_sh, :] - joints[..., l_sh, :]
    return torch.atan2(across[..., 2], -across[..., 0])


def _canonical_parts(joints: Tensor, root: int, face_joints: tuple[int, int, int, int] | None):
    """``mfm.metrics._canonical_parts``: global joints, root, xz trajectory, local pose of every clip."""
    ground = joints.new_tensor([1.0, 0.0, 1.0])
    g = joints - joints[:, :1, root : root + 1] * ground
    if face_joints is not None:
        g = g @ _yaw_rotation(_heading(g[:, 0], face_joints))[:, None]
    root_pos = g[:, :, root]  # (N, T, 3)
    local = torch.cat([g[:, :, :root], g[:, :, root + 1 :]], dim=2) - (root_pos * ground)[:, :, None]
    if face_joints is not None:
        local = local @ _yaw_rotation(_heading(g, face_joints))
    return g, root_pos, root_pos[..., [0, 2]], local


def _temos_floor_heights(joints: Tensor, foot_joints: Sequence[int], lens: Tensor) -> Tensor:
    """``mfm.metrics.temos_floor_heights`` (TEMOS's softmin floor, in millimetres) of every clip: (N,)."""
    mm = TEMOS_FLOOR_MM_PER_UNIT
    valid = _frame_mask(lens, joints.shape[1])
    heights = joints[:, :, list(foot_joints), 1].amin(dim=2) * mm  # (N, T)
    low = torch.where(valid, heights, torch.inf).amin(dim=1)
    high = torch.where(valid, heights, -torch.inf).amax(dim=1)
    return (low - torch.log(TEMOS_FLOOR_SOFTNESS + torch.exp(low - high))) / mm


def _masked_variance(x: Tensor, mask: Tensor, lens: Tensor) -> Tensor:
    count = lens.reshape(-1, *([1] * (x.ndim - 2))).to(x.dtype)
    mean = torch.where(mask, x, 0.0).sum(dim=1) / count
    return (torch.where(mask, x - mean[:, None], 0.0) ** 2).sum(dim=1) / (count - 1.0)


def ape_ave(pred_joints: Tensor, gt_joints: Tensor, lengths: Tensor | None = None, *, root: int = 0,
            face_joints: tuple[int, int, int, int] | None = None, floor_joints: Sequence[int] | None = None,
            metres_per_unit: float = 1.0) -> dict[str, float]:
    """:func:`mfm.metrics.ape_ave` (TEMOS's APE/AVE: frame-weighted APE, sequence-weighted AVE with the T − 1
    variance, floor and heading canonicalisation as there) of (N, T, J, 3) joints on their device; the eight
    scalars come to the host once."""
    lens = _checked(pred_joints, "pred_joints", lengths, minimum=2)
    if gt_joints.shape != pred_joints.shape:
        raise ValueError(f"pred_joints {tuple(pred_joints.shape)} and gt_joints {tuple(gt_joints.shape)} must have "
                         f"the same shape")
    _checked(gt_joints, "gt_joints", lens, minimum=2)
    if not metres_per_unit > 0:
        raise ValueError(f"metres_per_unit must be > 0, got {metres_per_unit}")
    n, t, j = pred_joints.shape[:3]
    if not 0 <= root < j:
        raise ValueError(f"root index {root} out of range for {j} joints")
    clips = [pred_joints, gt_joints]
    if metres_per_unit != 1.0:
        clips = [clip * metres_per_unit for clip in clips]
    if floor_joints is not None:
        up = pred_joints.new_tensor([0.0, 1.0, 0.0])
        clips = [clip - _temos_floor_heights(clip, floor_joints, lens)[:, None, None, None] * up for clip in clips]
    valid = _frame_mask(lens, t)  # (N, T)
    names = ("mean_global", "root", "traj", "mean_local")
    values = {}
    for name, p, g in zip(names, _canonical_parts(clips[0], root, face_joints),
                          _canonical_parts(clips[1], root, face_joints)):
        mask = valid.reshape(n, t, *([1] * (p.ndim - 2)))
        error = torch.linalg.vector_norm(p - g, dim=-1).reshape(n, t, -1).mean(dim=-1)
        values[f"APE_{name}"] = torch.where(valid, error, 0.0).sum() / lens.sum()
        spread = [_masked_variance(x, mask, lens) for x in (p, g)]
        values[f"AVE_{name}"] = torch.linalg.vector_norm(spread[0] - spread[1], dim=-1).reshape(n, -1).mean(-1).mean()
    return dict(zip(_APE_AVE_KEYS, torch.stack([values[k] for k in _APE_AVE_KEYS]).tolist()))


# ---------------------------------------------------------------------------------------------------------------
# Editing (ADE / FDE) and FLAME's joint variance
# ---------------------------------------------------------------------------------------------------------------


def _per_joint_error(pred_joints: Tensor, gt_joints: Tensor, lengths: Tensor | None,
                     metres_per_unit: float) -> tuple[Tensor, Tensor]:
    """(N, T) per-frame error averaged over joints [m], and the checked lengths."""
    lens = _checked(pred_joints, "pred_joints", lengths)
    if gt_joints.shape != pred_joints.shape:
        raise ValueError(f"pred_joints {tuple(pred_joints.shape)} and gt_joints {tuple(gt_joints.shape)} must have "
                         f"the same shape")
    _checked(gt_joints, "gt_joints", lens)
    if isinstance(metres_per_unit, bool) or not metres_per_unit > 0:
        raise ValueError(f"metres_per_unit must be > 0, got {metres_per_unit!r}")
    return (torch.linalg.vector_norm(pred_joints - gt_joints, dim=-1) * metres_per_unit).mean(dim=-1), lens


def ade(pred_joints: Tensor, gt_joints: Tensor, lengths: Tensor | None = None, mask_frames: Tensor | None = None, *,
        metres_per_unit: float = 1.0) -> float:
    """:func:`mfm.metrics.ade` on the joints' device: per clip the mean over its frames ``< lengths[i]`` that are
    True in ``mask_frames`` ((N, T) or (T,) bool), then the mean over clips."""
    err, lens = _per_joint_error(pred_joints, gt_joints, lengths, metres_per_unit)
    n, t = err.shape
    valid = _frame_mask(lens, t)
    if mask_frames is not None:
        mask = torch.as_tensor(mask_frames, device=err.device).to(torch.bool)
        try:
            valid = valid & mask.broadcast_to((n, t))
        except RuntimeError:
            raise ValueError(f"mask_frames of shape {tuple(mask.shape)} does not broadcast to (N, T) = {(n, t)}"
                             ) from None
    counts = valid.sum(dim=1)
    empty = torch.nonzero(counts == 0).flatten().tolist()
    if empty:
        raise ValueError(f"samples {empty} have no frame to evaluate (mask ∩ length)")
    return float(((err * valid).sum(dim=1) / counts).mean())


def fde(pred_joints: Tensor, gt_joints: Tensor, lengths: Tensor | None = None, *,
        metres_per_unit: float = 1.0) -> float:
    """:func:`mfm.metrics.fde` on the joints' device: the error at each clip's last frame, averaged over clips."""
    err, lens = _per_joint_error(pred_joints, gt_joints, lengths, metres_per_unit)
    return float(err[torch.arange(err.shape[0], device=err.device), lens - 1].mean())


def joint_variance_per_group(joints: Tensor, groups: Tensor, lengths: Tensor) -> tuple[list[int], list[float]]:
    """:func:`mfm.metrics.joint_variance` of every group of clips at once (FLAME's per-text joint variance: a group
    is the generations of one text): for each group its frames ``< length`` (the group's clips share it), the
    variance over the group's clips (ddof 0) summed over xyz, averaged over frames and joints. Returns the group
    ids in increasing order and their variances."""
    lens = _checked(joints, "samples", lengths)
    ids, inverse, count = torch.unique(torch.as_tensor(groups, device=joints.device), return_inverse=True,
                                       return_counts=True)
    shape = (len(ids), *joints.shape[1:])
    first = torch.full((len(ids),), lens.numel(), dtype=torch.int64, device=joints.device)
    first = first.scatter_reduce(0, inverse, torch.arange(lens.numel(), device=joints.device), "amin")
    group_len = lens[first]
    smallest, mismatched = torch.stack([count.min(), (lens != group_len[inverse]).sum()]).tolist()
    if smallest < 2:
        raise ValueError(f"joint_variance needs at least 2 samples per group, got {smallest}")
    if mismatched:
        raise ValueError(f"the clips of a group must have one length: {mismatched} clips differ from their group's")
    size = count.to(joints.dtype).reshape(-1, 1, 1, 1)
    mean = joints.new_zeros(shape).index_add_(0, inverse, joints) / size
    variance = joints.new_zeros(shape).index_add_(0, inverse, (joints - mean[inverse]) ** 2) / size
    per_frame = variance.sum(dim=-1).mean(dim=-1)  # (G, T)
    frames = _frame_mask(group_len, joints.shape[1])
    values = torch.where(frames, per_frame, 0.0).sum(dim=1) / group_len
    return ids.tolist(), values.tolist()
