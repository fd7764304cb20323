"""Stick-figure geometry shared by the video renderer, the trajectory plot and the contact sheet: an orthographic
camera (elevation/azimuth, Y up) projecting joints onto the image plane, the bone list, colours, the painter's
order of the bones and the floor grid. Plain numpy, plus :func:`draw_pose`, the one call that puts a still pose
on matplotlib axes; the figures themselves are in render.py, plots.py and contact_sheet.py."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from matplotlib.collections import LineCollection

from mfm.skeleton import Skeleton

KEPT_COLOR = "#2f6db5"  # blue: frames/joints taken from the source motion
EDITED_COLOR = "#e0462c"  # red: frames/joints the model generated or edited
CHAIN_COLORS = ("#d1495b", "#2f6db5", "#222222", "#edae49", "#00798c", "#6c4f9e", "#66a182")
SIDE_COLORS = {"left": "#2f6db5", "right": "#d1495b", "centre": "#333333"}  # bones by the body side they are on
FLOOR_COLOR = "#b8b8b8"
TRAJECTORY_COLOR = "#7a7a7a"
UNIT_SCALE = {"m": 1.0, "mm": 1000.0}  # skeleton units per metre


@dataclass(frozen=True)
class Camera:
    """Orthographic view: ``azimuth`` turns the camera about the up axis (0 = in front of a body facing
    +Z), ``elevation`` tilts it to look down. Image x = right, image y = up."""

    elevation_deg: float = 20.0
    azimuth_deg: float = 30.0

    def look(self) -> np.ndarray:
        """(3,) unit viewing direction, from the camera into the scene."""
        el, az = np.deg2rad(self.elevation_deg), np.deg2rad(self.azimuth_deg)
        return np.array([-np.sin(az) * np.cos(el), -np.sin(el), -np.cos(az) * np.cos(el)])

    def basis(self) -> np.ndarray:
        """(2, 3): the world directions of image right and image up."""
        az = np.deg2rad(self.azimuth_deg)
        right = np.array([np.cos(az), 0.0, -np.sin(az)])
        return np.stack((right, np.cross(right, self.look())))

    def project(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) world points -> (..., 2) image points."""
        return points @ self.basis().T


def as_numpy_joints(joints, skeleton: Skeleton, what: str = "joints") -> np.ndarray:
    """(T, J, 3) float64 numpy from numpy or torch, checked against the skeleton."""
    arr = joints.detach().cpu().numpy() if isinstance(joints, torch.Tensor) else np.asarray(joints)
    arr = arr.astype(np.float64, copy=False)
    if arr.ndim != 3 or arr.shape[1:] != (skeleton.num_joints, 3) or arr.shape[0] < 1:
        raise ValueError(f"{what} must be (T, {skeleton.num_joints}, 3) for skeleton {skeleton.name!r}, got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{what} contain NaN or inf")
    return arr


def bones(skeleton: Skeleton) -> list[tuple[int, int, int]]:
    """(parent, child, chain index) of every bone, in kinematic-chain order."""
    return [(a, b, c) for c, chain in enumerate(skeleton.kinematic_chains) for a, b in zip(chain[:-1], chain[1:])]


def bone_sides(skeleton: Skeleton) -> list[str]:
    """"left", "right" or "centre" for every bone of :func:`bones`, from its child joint's name (both skeletons
    name their sided joints left_* / right_*)."""
    names = skeleton.joint_names
    return [next((side for side in ("left", "right") if names[child].startswith(side)), "centre")
            for _, child, _ in bones(skeleton)]


def bone_depths(joints: np.ndarray, camera: Camera, bone_list: list[tuple[int, int, int]]) -> np.ndarray:
    """(..., J, 3) joints -> (..., B) depth of every bone's midpoint along the viewing direction (larger is
    farther): drawing bones in decreasing depth (painter's order) puts near limbs over far ones."""
    depth = joints @ camera.look()
    return np.stack([(depth[..., a] + depth[..., b]) / 2 for a, b, _ in bone_list], axis=-1)


def draw_pose(ax, points: np.ndarray, bone_list: list[tuple[int, int, int]], colors, *,
              depths: np.ndarray | None = None, linewidth: float = 2.0, zorder: float = 2.0) -> LineCollection:
    """Draw one pose from its image points (J, 2) as a single artist: one segment per bone, coloured by
    ``colors`` (one per bone, or one for all), in painter's order when the bones' ``depths`` (B,) are given
    (a collection draws its segments in order), else in bone order."""
    segments = np.stack([points[[a, b]] for a, b, _ in bone_list])  # (B, 2, 2)
    colors = [colors] * len(bone_list) if isinstance(colors, (str, tuple)) else list(colors)
    order = np.arange(len(bone_list)) if depths is None else np.argsort(-np.asarray(depths), kind="stable")
    lines = LineCollection(segments[order], colors=[colors[i] for i in order], linewidths=linewidth,
                           capstyle="round", zorder=zorder)
    ax.add_collection(lines)
    return lines


def metres(skeleton: Skeleton) -> float:
    """One metre in the skeleton's units."""
    try:
        return UNIT_SCALE[skeleton.unit]
    except KeyError:
        raise ValueError(f"skeleton {skeleton.name!r} has unit {skeleton.unit!r}; known: {sorted(UNIT_SCALE)}") from None


def floor_grid(camera: Camera, centre_xz: np.ndarray, radius: float, spacing: float, floor: float) -> np.ndarray:
    """Image-plane polyline (N, 2) of the world grid lines x = k*spacing and z = k*spacing within
    ``radius`` of ``centre_xz``, NaN-separated so it is one matplotlib line, relative to the centre
    (the camera follows it: the grid slides under a walking figure)."""
    cx, cz = centre_xz
    segments = []
    for axis, c in ((0, cx), (2, cz)):
        other_c = cz if axis == 0 else cx
        for k in np.arange(np.ceil((c - radius) / spacing), np.floor((c + radius) / spacing) + 1):
            line = np.zeros((3, 3))
            line[:, 1] = floor
            line[:, axis] = k * spacing
            line[:2, 2 - axis] = (other_c - radius, other_c + radius)
            line[2] = np.nan
            segments.append(line)
    if not segments:
        return np.full((1, 2), np.nan)
    points = np.concatenate(segments)
    points[:, 0] -= cx
    points[:, 2] -= cz
    return camera.project(points)


def equal_scale_limits(points: np.ndarray, aspect: float) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper image-plane limits around ``points`` (N, 2), widened so that width / height equals
    the axes' ``aspect`` (one data unit is as long across as up; cheaper than matplotlib's adjustable
    aspect, which re-solves the limits on every frame)."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    if half[0] < aspect * half[1]:
        half[0] = aspect * half[1]
    else:
        half[1] = half[0] / aspect
    return centre - half, centre + half
