"""Contact sheets: many motions on one PNG, to compare them at a glance (generated against ground truth,
one checkpoint against another).

One row per motion, its caption as the row title, then ``frames`` evenly spaced frames of it as stick figures
(frame 0 and the last frame included). Every panel of a row shares one fixed world view, so the figure walks
across the panels as it travels: the floor grid and the root's path over the whole clip (grey) stay put. Bones
are coloured by the body side they are on (``stick.SIDE_COLORS``: left blue, right red, centre dark), the sheet's
header says so, and each panel is labelled with its time in seconds. Drawn 2.5D like the videos (an orthographic
``stick.Camera`` onto plain axes, near bones over far ones) through a headless Agg canvas.

Pixel size: ``frames * panel_px`` wide, ``HEADER_PX + rows * (ROW_TITLE_PX + panel_px)`` high.
"""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from mfm.export.stick import (
    FLOOR_COLOR,
    SIDE_COLORS,
    TRAJECTORY_COLOR,
    Camera,
    as_numpy_joints,
    bone_depths,
    bone_sides,
    bones,
    draw_pose,
    equal_scale_limits,
    floor_grid,
    metres,
)
from mfm.skeleton import Skeleton

DPI = 100
HEADER_PX = 26
ROW_TITLE_PX = 22
GRID_SPACING_M = 0.5  # doubled until at most MAX_GRID_LINES lines cross the floor: a long run stays readable
MAX_GRID_LINES = 12
VIEW_MARGIN_M = 0.25  # empty floor around the motion in every panel
CHAR_PX = 5.6  # average width of a 9 pt caption character at DPI 100, to shorten captions that would not fit
# From in front of the body's right side, a little above: a body walking forward (+Z, the way HumanML3D clips face
# on frame 0) moves to the right across a row, and both the side and the front of the body show.
SHEET_CAMERA = Camera(elevation_deg=15.0, azimuth_deg=-55.0)


def sheet_frames(num_frames: int, count: int) -> np.ndarray:
    """``count`` frame indices evenly spread over a clip, first and last included (repeats in a clip shorter
    than ``count``, so every row has the same number of panels)."""
    return np.round(np.linspace(0, num_frames - 1, count)).astype(int)


class _RowView:
    """The world view every panel of one row shares: image-plane limits around the whole motion (its floor
    shadow included, so the ground under the feet shows) and the floor grid and root path in image points."""

    def __init__(self, joints: np.ndarray, skeleton: Skeleton, camera: Camera) -> None:
        metre = metres(skeleton)
        floor = joints[..., 1].min()
        shadows = joints.copy()
        shadows[..., 1] = floor
        points = camera.project(np.concatenate((joints, shadows)).reshape(-1, 3))
        margin = VIEW_MARGIN_M * metre
        self.lo, self.hi = equal_scale_limits(np.concatenate((points - margin, points + margin)), aspect=1.0)
        xz = joints[..., [0, 2]].reshape(-1, 2)
        centre = (xz.min(axis=0) + xz.max(axis=0)) / 2
        radius = (xz.max(axis=0) - xz.min(axis=0)).max() / 2 + 2 * margin
        spacing = GRID_SPACING_M * metre
        while 2 * radius / spacing > MAX_GRID_LINES:
            spacing *= 2
        self.grid = floor_grid(camera, centre, radius, spacing, floor)
        self.grid += camera.project(np.array([centre[0], 0.0, centre[1]]))  # floor_grid is centre-relative
        root_path = joints[:, 0].copy()
        root_path[:, 1] = floor
        self.root_path = camera.project(root_path)


def render_contact_sheet(
    path: str | Path,
    motions: Sequence,
    titles: Sequence[str],
    skeleton: Skeleton,
    *,
    frames: int = 6,
    fps: float | None = None,
    title: str | None = None,
    panel_px: int = 160,
    camera: Camera = SHEET_CAMERA,
) -> Path:
    """Write a PNG contact sheet of ``motions`` (each (T, J, 3) in the skeleton's units, numpy or torch; lengths
    may differ) with one row per motion titled by ``titles``; ``frames`` panels per row; ``fps`` (default the
    skeleton's) labels the panels in seconds; ``title`` heads the sheet. Returns ``path``."""
    arrays = [as_numpy_joints(m, skeleton, f"motion {i}") for i, m in enumerate(motions)]
    if not arrays:
        raise ValueError("no motions to draw")
    if len(titles) != len(arrays):
        raise ValueError(f"{len(titles)} titles for {len(arrays)} motions")
    if frames < 1:
        raise ValueError(f"frames must be at least 1, got {frames}")
    if panel_px < 64:
        raise ValueError(f"panel_px must be at least 64, got {panel_px}")
    fps = skeleton.fps if fps is None else float(fps)
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")

    width = frames * panel_px
    row_px = ROW_TITLE_PX + panel_px
    height = HEADER_PX + len(arrays) * row_px
    fig = Figure(figsize=(width / DPI, height / DPI), dpi=DPI)
    FigureCanvasAgg(fig)
    max_chars = int((width - 8) / CHAR_PX)

    def from_top(px: float) -> float:
        return 1.0 - px / height

    renderer = fig.canvas.get_renderer()
    right = width - 6.0  # the legend is laid out from the right edge, each word measured as drawn
    for side, label in (("centre", "centre"), ("right", "right side"), ("left", "left side")):
        word = fig.text(right / width, from_top(HEADER_PX / 2), label, color=SIDE_COLORS[side], va="center",
                        ha="right", fontsize=8, weight="bold")
        right -= word.get_window_extent(renderer).width + 10
    if title is not None:  # bold characters are about 15% wider
        fig.text(4 / width, from_top(HEADER_PX / 2), textwrap.shorten(title, int((right - 8) / (1.15 * CHAR_PX)),
                 placeholder="…"), va="center", fontsize=9, weight="bold")

    bone_list = bones(skeleton)
    colors = [SIDE_COLORS[side] for side in bone_sides(skeleton)]
    for row, (joints, caption) in enumerate(zip(arrays, titles)):
        top = HEADER_PX + row * row_px
        fig.text(4 / width, from_top(top + ROW_TITLE_PX / 2),
                 textwrap.shorten(str(caption), max_chars, placeholder="…"), va="center", fontsize=9)
        view = _RowView(joints, skeleton, camera)
        shown = sheet_frames(len(joints), frames)
        projected = camera.project(joints[shown])  # (frames, J, 2)
        depths = bone_depths(joints[shown], camera, bone_list)
        for column, frame in enumerate(shown):
            ax = fig.add_axes((column * panel_px / width, from_top(top + row_px), panel_px / width, panel_px / height))
            ax.set_xticks([])
            ax.set_yticks([])
            for spine in ax.spines.values():  # a thin frame tells the panels apart
                spine.set_color("#dddddd")
            ax.set_xlim(view.lo[0], view.hi[0])
            ax.set_ylim(view.lo[1], view.hi[1])
            ax.plot(view.grid[:, 0], view.grid[:, 1], color=FLOOR_COLOR, lw=0.5, zorder=0)
            ax.plot(view.root_path[:, 0], view.root_path[:, 1], color=TRAJECTORY_COLOR, lw=0.8, alpha=0.6, zorder=1)
            draw_pose(ax, projected[column], bone_list, colors, depths=depths[column], linewidth=1.8, zorder=2)
            ax.text(0.03, 0.03, f"{frame / fps:.1f} s", transform=ax.transAxes, fontsize=7, color="#666666")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png", dpi=DPI, facecolor="white")
    return path
