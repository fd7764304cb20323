"""Stick-figure videos of joint motions: MP4 through ffmpeg when it is on PATH, else an animated GIF.

The figure is drawn 2.5D: an orthographic projection (``stick.Camera``) onto plain 2D axes, which
renders several times faster than mplot3d. The view follows the root; the floor grid and the root's
trajectory on the floor are fixed in the world, so the grid slides under a walking figure. Only the
bone lines and the view limits change from frame to frame (artists are updated, never re-created).
Everything goes through a headless Agg canvas: no display and no global backend switch.
"""

from __future__ import annotations

import logging
import shutil
import textwrap
from pathlib import Path
from typing import Literal, Sequence

import numpy as np
from matplotlib import animation, rcParams
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from PIL import Image

from mfm.export.stick import (
    CHAIN_COLORS,
    EDITED_COLOR,
    FLOOR_COLOR,
    KEPT_COLOR,
    TRAJECTORY_COLOR,
    Camera,
    as_numpy_joints,
    bone_depths,
    bones,
    equal_scale_limits,
    floor_grid,
    metres,
)
from mfm.skeleton import Skeleton

logger = logging.getLogger(__name__)

Captions = str | Sequence[tuple[int, str]] | None
VideoFormat = Literal["auto", "mp4", "gif"]
DPI = 80
GRID_SPACING_M = 0.5
AXES_HEIGHT = 0.86  # fraction of the frame under the caption


def ffmpeg_available() -> bool:
    """Whether matplotlib's FFMpegWriter can run (``rcParams['animation.ffmpeg_path']`` on PATH).

    When the configured name is matplotlib's default ``"ffmpeg"`` and none is on PATH, the static ffmpeg
    shipped in the ``imageio-ffmpeg`` wheel (a dependency) is used, so MP4 works on a bare machine.
    """
    if shutil.which(rcParams["animation.ffmpeg_path"]) is not None:
        return True
    if rcParams["animation.ffmpeg_path"] != "ffmpeg":
        return False  # the user chose a binary on purpose: do not substitute another
    try:
        import imageio_ffmpeg
    except ImportError:
        return False
    rcParams["animation.ffmpeg_path"] = imageio_ffmpeg.get_ffmpeg_exe()
    return shutil.which(rcParams["animation.ffmpeg_path"]) is not None


def caption_per_frame(title: Captions, num_frames: int) -> list[str]:
    """One caption per frame from a fixed title or from ``[(start_frame, caption), ...]`` segments
    (each caption shows from its start frame until the next one starts; none before the first)."""
    if title is None:
        return [""] * num_frames
    if isinstance(title, str):
        return [title] * num_frames
    segments = [(int(start), str(text)) for start, text in title]
    starts = [s for s, _ in segments]
    if starts != sorted(starts) or len(set(starts)) != len(starts) or any(not 0 <= s < num_frames for s in starts):
        raise ValueError(f"caption start frames must be increasing and within 0..{num_frames - 1}, got {starts}")
    out = [""] * num_frames
    for (start, text), end in zip(segments, starts[1:] + [num_frames]):
        out[start:end] = [text] * (end - start)
    return out


def edited_per_frame(edited, num_frames: int, num_joints: int) -> np.ndarray:
    """A (T,) per-frame, (J,) per-joint or (T, J) edited mask -> (T, J) bool."""
    mask = np.asarray(edited, dtype=bool)
    if mask.shape == (num_frames, num_joints):
        return mask
    if mask.ndim == 1 and num_frames == num_joints and mask.shape == (num_frames,):
        raise ValueError(
            f"a 1-D mask of length {num_frames} is ambiguous for {num_frames} frames of {num_joints} joints: pass (T, J)"
        )
    if mask.shape == (num_frames,):
        return np.repeat(mask[:, None], num_joints, axis=1)
    if mask.shape == (num_joints,):
        return np.repeat(mask[None], num_frames, axis=0)
    raise ValueError(
        f"edited mask must be ({num_frames},), ({num_joints},) or ({num_frames}, {num_joints}), got {mask.shape}"
    )


class _OctreeGifWriter(animation.PillowWriter):
    """PillowWriter that gives each frame its palette with Pillow's fast octree quantiser: Pillow's
    default (median cut) takes ~15 ms a frame, longer than drawing it."""

    def finish(self) -> None:
        frames = [f.convert("RGB").quantize(colors=256, method=Image.Quantize.FASTOCTREE) for f in self._frames]
        frames[0].save(self.outfile, save_all=True, append_images=frames[1:], duration=int(1000 / self.fps), loop=0)


def _writer(fmt: VideoFormat, fps: float) -> tuple[animation.AbstractMovieWriter, str]:
    if fmt == "auto":
        fmt = "mp4" if ffmpeg_available() else "gif"
    if fmt == "mp4":
        if not ffmpeg_available():
            raise RuntimeError(f"MP4 needs ffmpeg ({rcParams['animation.ffmpeg_path']!r}) on PATH; use fmt='gif'")
        # h264: matplotlib adds -pix_fmt yuv420p, which players need (and which needs even frame sizes).
        return animation.FFMpegWriter(fps=fps, codec="h264"), ".mp4"
    if fmt == "gif":
        return _OctreeGifWriter(fps=fps), ".gif"
    raise ValueError(f"fmt must be 'auto', 'mp4' or 'gif', got {fmt!r}")


def render_motion(
    path: str | Path,
    joints,
    skeleton: Skeleton,
    fps: float | None = None,
    *,
    title: Captions = None,
    edited=None,
    colors: tuple[str, str] = (KEPT_COLOR, EDITED_COLOR),
    trajectory: bool = True,
    fmt: VideoFormat = "auto",
    size_px: int = 320,
    camera: Camera = Camera(),
) -> Path:
    """Render joints (T, J, 3) in the skeleton's units as a stick-figure video; returns the path written
    (``path`` with suffix ``.mp4``, or ``.gif`` when ``fmt='gif'`` or ffmpeg is missing under 'auto').

    ``title``: one caption, or ``[(start_frame, caption), ...]`` for captions that change over segments.
    ``edited``: bool mask, (T,) per frame, (J,) per joint or (T, J); a bone is drawn in ``colors[1]``
    where its child joint is edited/generated and in ``colors[0]`` where it is kept. Without a mask,
    each kinematic chain has its own colour. ``trajectory``: draw the root's path on the floor so far.
    """
    arr = as_numpy_joints(joints, skeleton)
    fps = skeleton.fps if fps is None else float(fps)
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    if size_px < 64:
        raise ValueError(f"size_px must be at least 64, got {size_px}")
    num_frames = len(arr)
    captions = caption_per_frame(title, num_frames)
    bone_list = bones(skeleton)
    children = [child for _, child, _ in bone_list]
    if edited is None:
        chain_colors = np.array([CHAIN_COLORS[chain % len(CHAIN_COLORS)] for _, _, chain in bone_list], dtype=object)
        bone_colors = np.repeat(chain_colors[None], num_frames, axis=0)
    else:
        bone_colors = np.where(edited_per_frame(edited, num_frames, skeleton.num_joints)[:, children], colors[1], colors[0])

    metre = metres(skeleton)
    floor = arr[..., 1].min()
    root = arr[:, 0].copy()
    root[:, 1] = floor
    height = (arr[..., 1] - floor).max()
    spread = np.linalg.norm((arr - root[:, None])[..., [0, 2]], axis=-1).max()
    radius = 1.1 * max(spread, 0.35 * height, 0.3 * metre)  # half-width of the floor square in view
    projected = camera.project(arr)  # (T, J, 2)
    # Painter's order: farther bones get lower z-orders, in 2..3.
    bone_zorder = 2 + np.argsort(np.argsort(-bone_depths(arr, camera, bone_list), axis=1), axis=1) / len(bone_list)
    centres = camera.project(root)  # (T, 2)
    box = np.array([[x, y, z] for x in (-radius, radius) for y in (0.0, 1.1 * height) for z in (-radius, radius)])
    view_lo, view_hi = equal_scale_limits(camera.project(box), aspect=1.0 / AXES_HEIGHT)

    side = size_px + size_px % 2  # even: h264 with yuv420p needs it
    fig = Figure(figsize=(side / DPI, side / DPI), dpi=DPI)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.0, 0.0, 1.0, AXES_HEIGHT))
    ax.set_axis_off()
    lo, hi = root[:, [0, 2]].min(axis=0) - radius, root[:, [0, 2]].max(axis=0) + radius
    grid_centre, grid_radius = (lo + hi) / 2, (hi - lo).max() / 2
    grid = floor_grid(camera, grid_centre, grid_radius, GRID_SPACING_M * metre, floor)
    grid_shift = camera.project(np.array([grid_centre[0], 0.0, grid_centre[1]]))  # floor_grid is centre-relative
    ax.plot(grid[:, 0] + grid_shift[0], grid[:, 1] + grid_shift[1], color=FLOOR_COLOR, lw=0.6, zorder=0)
    path_line = ax.plot([], [], color=TRAJECTORY_COLOR, lw=1.2, zorder=1)[0] if trajectory else None
    lines = [ax.plot([], [], lw=2.2, solid_capstyle="round", zorder=2)[0] for _ in bone_list]
    wrap = max(20, side // 6)
    caption = fig.text(0.5, 0.985, "", ha="center", va="top", fontsize=8)
    counter = fig.text(0.02, 0.02, "", fontsize=6, color="#555555")

    def draw(f: int) -> None:
        ax.set_xlim(centres[f, 0] + view_lo[0], centres[f, 0] + view_hi[0])
        ax.set_ylim(centres[f, 1] + view_lo[1], centres[f, 1] + view_hi[1])
        for line, (a, b, _), color, z in zip(lines, bone_list, bone_colors[f], bone_zorder[f]):
            line.set_data(projected[f, [a, b], 0], projected[f, [a, b], 1])
            line.set_color(color)
            line.set_zorder(z)
        if path_line is not None:
            path_line.set_data(centres[: f + 1, 0], centres[: f + 1, 1])
        caption.set_text(textwrap.fill(captions[f], wrap))
        counter.set_text(f"{f + 1}/{num_frames}")

    writer, suffix = _writer(fmt, fps)
    out = Path(path).with_suffix(suffix)
    out.parent.mkdir(parents=True, exist_ok=True)
    with writer.saving(fig, str(out), dpi=DPI):
        for f in range(num_frames):
            draw(f)
            writer.grab_frame()
    logger.info("wrote %s (%d frames at %g fps)", out, num_frames, fps)
    return out
