"""Figure of the clean-motion estimates x̂1 along an ODE trajectory (MFM paper, Figure 4 style): one
panel per integration step, each showing a few frames of that step's estimate overlaid as stick
figures (light = early frames, dark = late), labelled with the step's time t.

The estimates come from ``solve(..., return_trajectory=True)``: ``result.x1_hat[:, b]`` is (K, T, D)
for sample b, in the model's (normalised) feature space; pass the dataset's ``mean``/``std`` to undo
the normalisation, or pass joints (K, T, J, 3) decoded some other way.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure

from mfm.export.stick import FLOOR_COLOR, KEPT_COLOR, Camera, bones, draw_pose, equal_scale_limits, floor_grid, metres
from mfm.features import features_to_joints
from mfm.skeleton import Skeleton

DPI = 100
TITLE_PX = 30
SNAPSHOT_ALPHA = (0.25, 1.0)  # lightness of the first and last overlaid frame


def _to_numpy(x, name: str) -> np.ndarray:
    arr = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
    if not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"{name} must be numeric, got dtype {arr.dtype}")
    return arr.astype(np.float64, copy=False)


def estimates_to_joints(x1_hat, skeleton: Skeleton, mean=None, std=None) -> np.ndarray:
    """(K, T, D) features (normalised if ``mean``/``std`` are given) or (K, T, J, 3) joints -> (K, T, J, 3)
    joints in the skeleton's units (features decoded with ``features_to_joints``, the ric block)."""
    arr = _to_numpy(x1_hat, "x1_hat")
    if arr.ndim == 4 and arr.shape[2:] == (skeleton.num_joints, 3):
        joints = arr
    elif arr.ndim == 3 and arr.shape[-1] == skeleton.feature_dim:
        if (mean is None) != (std is None):
            raise ValueError("pass both mean and std (to undo the normalisation) or neither")
        if mean is not None:
            arr = arr * _to_numpy(std, "std") + _to_numpy(mean, "mean")
        joints = features_to_joints(arr, skeleton)
    else:
        raise ValueError(
            f"x1_hat must be (K, T, {skeleton.feature_dim}) features or (K, T, {skeleton.num_joints}, 3) joints "
            f"for skeleton {skeleton.name!r}, got shape {arr.shape} (for a batch, pick one sample: x1_hat[:, b])"
        )
    if not np.isfinite(joints).all():
        raise ValueError("x1_hat contains NaN or inf")
    return joints


def _panel_steps(num_steps: int, max_panels: int) -> np.ndarray:
    """Up to ``max_panels`` step indices, evenly spread, always including the first and the last."""
    if num_steps <= max_panels:
        return np.arange(num_steps)
    return np.unique(np.round(np.linspace(0, num_steps - 1, max_panels)).astype(int))


def _snapshot_frames(frames: int | Sequence[int], num_frames: int) -> np.ndarray:
    if isinstance(frames, (int, np.integer)):
        if frames < 1:
            raise ValueError(f"frames must be at least 1, got {frames}")
        return np.unique(np.round(np.linspace(0, num_frames - 1, min(int(frames), num_frames))).astype(int))
    chosen = np.asarray(list(frames), dtype=int)
    if chosen.size == 0 or (chosen < 0).any() or (chosen >= num_frames).any():
        raise ValueError(f"snapshot frames must be within 0..{num_frames - 1}, got {chosen.tolist()}")
    return chosen


def _shade(color: str, amount: float) -> tuple[float, float, float]:
    """``color`` blended with white: amount 1 = the colour, 0 = white (opaque 'fading' that stays
    readable where snapshots overlap)."""
    rgb = np.array(to_rgb(color))
    return tuple(1.0 - amount * (1.0 - rgb))


def plot_x1_trajectory(
    path: str | Path,
    x1_hat,
    times,
    skeleton: Skeleton,
    *,
    mean=None,
    std=None,
    frames: int | Sequence[int] = 5,
    max_panels: int = 8,
    panel_px: int = 200,
    title: str | None = None,
    color: str = KEPT_COLOR,
    camera: Camera = Camera(elevation_deg=15.0, azimuth_deg=60.0),
) -> Path:
    """Save a PNG with one panel per integration step (at most ``max_panels``, evenly chosen, first and
    last included) of the x̂1 estimates (K, T, D) or (K, T, J, 3) at ``times`` (K,). Each panel overlays
    ``frames`` snapshots (a count spread over the clip, or explicit frame indices) at their world
    positions, so the root's travel shows. All panels share the view of the final estimate (earlier,
    blurrier estimates are drawn at the same scale; parts outside it are cut off). Returns ``path``."""
    joints = estimates_to_joints(x1_hat, skeleton, mean, std)
    t = _to_numpy(times, "times").reshape(-1)
    if len(t) != len(joints):
        raise ValueError(f"times has {len(t)} entries for {len(joints)} estimates")
    if max_panels < 1:
        raise ValueError(f"max_panels must be at least 1, got {max_panels}")
    steps = _panel_steps(len(joints), max_panels)
    shown = _snapshot_frames(frames, joints.shape[1])
    bone_list = bones(skeleton)
    metre = metres(skeleton)

    final = joints[-1][shown]
    floor = final[..., 1].min()
    projected = camera.project(joints[:, shown])  # (K, S, J, 2)
    final_points = camera.project(final).reshape(-1, 2)
    margin = 0.15 * (final_points.max(axis=0) - final_points.min(axis=0)).max() + 0.1 * metre
    lo, hi = equal_scale_limits(np.concatenate((final_points - margin, final_points + margin)), aspect=1.0)
    centre_xz = final[:, 0][:, [0, 2]].mean(axis=0)
    radius = np.linalg.norm(final[..., [0, 2]] - centre_xz, axis=-1).max() + 0.3 * metre
    grid = floor_grid(camera, centre_xz, radius, 0.5 * metre, floor)
    grid += camera.project(np.array([centre_xz[0], 0.0, centre_xz[1]]))  # floor_grid is centre-relative

    width_px = panel_px * len(steps)
    title_px = TITLE_PX if title is not None else 0
    fig = Figure(figsize=(width_px / DPI, (panel_px + title_px) / DPI), dpi=DPI)
    FigureCanvasAgg(fig)
    top = panel_px / (panel_px + title_px)  # square panels below the title
    for n, k in enumerate(steps):
        ax = fig.add_axes((n / len(steps), 0.0, 1.0 / len(steps), top))
        ax.set_axis_off()
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.plot(grid[:, 0], grid[:, 1], color=FLOOR_COLOR, lw=0.5, zorder=0)
        for s, frame_points in enumerate(projected[k]):
            amount = SNAPSHOT_ALPHA[0] + (SNAPSHOT_ALPHA[1] - SNAPSHOT_ALPHA[0]) * s / max(len(shown) - 1, 1)
            draw_pose(ax, frame_points, bone_list, _shade(color, amount), linewidth=1.4, zorder=1 + s)
        ax.text(0.5, 0.02, f"t = {t[k]:.2f}", transform=ax.transAxes, ha="center", va="bottom", fontsize=9)
    if title is not None:
        fig.text(0.5, 0.98, title, ha="center", va="top", fontsize=10)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png", dpi=DPI, facecolor="white")
    return path
