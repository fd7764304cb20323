"""BVH (Biovision hierarchy) export of joint-position motions, and a small reader for checking them.

What ``write_bvh`` writes
-------------------------
* Units: metres (KIT's millimetres are converted), Y up, the skeleton's own axes (HumanML3D clips
  face +Z on frame 0). Blender: *File > Import > Motion Capture (.bvh)* with its defaults
  (Scale 1, Forward -Z, Up Y) gives a correctly sized, upright armature; tick *Update Scene FPS* to
  play at the clip's frame rate.
* ``Frame Time`` = 1 / fps (the skeleton's fps unless given).
* ``ROOT`` = the skeleton's root joint, ``OFFSET 0 0 0``, channels
  ``Xposition Yposition Zposition Yrotation Xrotation Zrotation``: the position channels are the root's
  absolute position (with a zero offset every reader agrees on that). Every other ``JOINT`` has
  ``Yrotation Xrotation Zrotation``.
* Rotation order: channels are listed outermost first, so a joint's local rotation is
  ``R = Ry(a) @ Rx(b) @ Rz(c)`` (Blender calls this Euler order ``ZXY``: Z applied first), angles in
  degrees, each angle unwrapped over time. Heading (about the up axis) is the outermost angle, so the
  root's facing is one channel and the Euler singularity is at +-90 deg of pitch, not of heading.
* Rest pose: each joint's offset from its parent is the skeleton's rest direction
  (``skeleton.raw_offsets``) times the clip's own bone length (mean over frames). Clips with constant
  bone lengths (every dataset clip; anything from ``canonical_joints`` or ``features_to_joints_fk``)
  therefore re-parse to their input positions exactly (to the 1e-6 printed precision); for a clip whose
  bone lengths drift (raw network output decoded from the ric block) the bone *directions* are kept
  and a warning reports the largest position deviation. Fit such a clip onto fixed bone lengths first
  (``mfm.features.rigid_joints``, as pipeline/generation/sampling.py does) to get a BVH that reproduces it.
* Leaf joints get an ``End Site`` half a bone further along their rest direction (display only).

Why there are extra ``*_to_*`` joints
-------------------------------------
In a BVH a joint has one rotation, and it turns the offsets of *all* its children. With positions as
input and fixed offsets, a joint with several children (HumanML3D's pelvis and spine3, KIT's root and
neck) can place only one child exactly, because the angles between its child bones differ from the rest
pose and change over time. HumanML3D's own IK gets around that by storing each chain's rotation at
the chain's first child, which a BVH hierarchy cannot express. Here each such joint is split:

* the joint itself aims its *primary* child (the one whose rest offset points most upward: the spine
  from the pelvis, the neck/head from the upper spine), and its twist about that bone comes from the
  line through its other children (hip to hip, shoulder to shoulder), so the pelvis's rotation carries
  the body's heading as an animator expects;
* every other child hangs under a zero-offset joint named ``<joint>_to_<child>`` (e.g.
  ``pelvis_to_left_hip``) whose rotation, relative to the joint, is the small correction that puts
  that child exactly where it is.

So every rotation aims exactly one offset, and all positions re-parse exactly. Blender imports the
zero-offset joints as ordinary bones from the branch point to the child.

Every other rotation is the minimal one: the shortest arc turning where the bone would point if the
joint kept its parent's frame onto where it does point (no twist relative to the parent).

``read_bvh`` parses any BVH with one root (any channel order, position channels on any joint, which
like Blender it takes as the joint's translation replacing its offset) and runs forward kinematics.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple, Sequence

import numpy as np
import torch

from mfm.rotations import qbetween, quat_to_matrix
from mfm.skeleton import Skeleton

logger = logging.getLogger(__name__)

ROOT_CHANNELS = ("Xposition", "Yposition", "Zposition", "Yrotation", "Xrotation", "Zrotation")
JOINT_CHANNELS = ("Yrotation", "Xrotation", "Zrotation")
METRES_PER_UNIT = {"m": 1.0, "mm": 1e-3}
DRIFT_WARNING_M = 1e-3  # position deviation (m) past which write_bvh warns that bone lengths drift
_DECIMALS = 6  # printed digits: 1e-6 m and 1e-6 deg (2e-8 rad)


@dataclass(frozen=True)
class BVHJoint:
    """One ROOT/JOINT of a BVH hierarchy (parents come before their children)."""

    name: str
    parent: int  # index in the joint list, -1 for the root
    offset: np.ndarray  # (3,) from the parent, in the file's units
    channels: tuple[str, ...]
    end_site: np.ndarray | None = None  # (3,) End Site offset of a leaf


class BVHMotion(NamedTuple):
    joints: np.ndarray  # (T, N, 3) global positions of the ROOT/JOINT nodes, in the file's units
    names: list[str]
    fps: float


@dataclass(frozen=True)
class _Aim:
    """How write_bvh computes one node's global rotation from the joint positions."""

    joint: int  # skeleton joint at the node's head
    target: int | None  # skeleton joint its rotation points the rest offset at; None: keep the parent's frame
    twist_from: tuple[int, ...] = ()  # other children whose span fixes the twist (branch points only)


# ---------------------------------------------------------------------------------------------------
# rotations, vectorised over frames (float64 numpy)


def _axis_rotation(axis: str, degrees: np.ndarray) -> np.ndarray:
    """(T,) angles -> (T, 3, 3) rotations about the x, y or z axis."""
    a = np.deg2rad(degrees)
    c, s = np.cos(a), np.sin(a)
    one, zero = np.ones_like(a), np.zeros_like(a)
    rows = {
        "x": ((one, zero, zero), (zero, c, -s), (zero, s, c)),
        "y": ((c, zero, s), (zero, one, zero), (-s, zero, c)),
        "z": ((c, -s, zero), (s, c, zero), (zero, zero, one)),
    }[axis]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def _euler_yxz_degrees(r: np.ndarray) -> np.ndarray:
    """(T, 3, 3) rotations -> (T, 3) angles (a, b, c) in degrees with ``R = Ry(a) Rx(b) Rz(c)``.

    R[1] = (cos b sin c, cos b cos c, -sin b), R[0, 2] = sin a cos b, R[2, 2] = cos a cos b. At the
    singularity (cos b = 0) c is set to 0 and a read from R[0, 0] = cos a, R[2, 0] = -sin a."""
    cos_b = np.hypot(r[:, 1, 0], r[:, 1, 1])
    b = np.arctan2(-r[:, 1, 2], cos_b)
    regular = cos_b > 1e-9
    a = np.where(regular, np.arctan2(r[:, 0, 2], r[:, 2, 2]), np.arctan2(-r[:, 2, 0], r[:, 0, 0]))
    c = np.where(regular, np.arctan2(r[:, 1, 0], r[:, 1, 1]), 0.0)
    return np.rad2deg(np.stack((a, b, c), axis=-1))


def _align(frm: np.ndarray, to: np.ndarray) -> np.ndarray:
    """Shortest-arc rotations (T, 3, 3) taking directions ``frm`` (T, 3) onto ``to`` (T, 3)."""
    q = qbetween(torch.from_numpy(frm), torch.from_numpy(to))
    return quat_to_matrix(q).numpy()


def _orthonormal_frame(aim: np.ndarray, across: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frames (..., 3, 3) with columns [aim, across made orthogonal to aim, their cross product], and
    a mask of the frames where ``across`` is (nearly) parallel to ``aim`` and gives no twist."""
    u = aim / np.linalg.norm(aim, axis=-1, keepdims=True)
    w = across - np.sum(across * u, axis=-1, keepdims=True) * u
    w_norm = np.linalg.norm(w, axis=-1, keepdims=True)
    degenerate = w_norm[..., 0] <= 1e-6 * np.linalg.norm(across, axis=-1)
    w = w / np.where(w_norm > 0, w_norm, 1.0)
    return np.stack((u, w, np.cross(u, w)), axis=-1), degenerate


# ---------------------------------------------------------------------------------------------------
# hierarchy


def _children(skeleton: Skeleton) -> list[list[int]]:
    """Children of every joint in kinematic-chain order."""
    parents = skeleton.parents
    children: list[list[int]] = [[] for _ in range(skeleton.num_joints)]
    for chain in skeleton.kinematic_chains:
        for child in chain[1:]:
            if child not in children[parents[child]]:
                children[parents[child]].append(child)
    return children


def _hierarchy(skeleton: Skeleton, offsets: np.ndarray) -> tuple[list[BVHJoint], list[_Aim]]:
    """BVH joints (depth-first, parents first) and how each one's rotation is found; ``offsets`` (J, 3)
    are the rest offsets of the skeleton's joints in metres. See the module docstring."""
    names = skeleton.joint_names
    children = _children(skeleton)
    nodes: list[BVHJoint] = []
    aims: list[_Aim] = []

    def add(joint: int, parent_node: int, offset: np.ndarray, name: str) -> None:
        kids = children[joint]
        channels = ROOT_CHANNELS if parent_node < 0 else JOINT_CHANNELS
        if not kids:
            # Half the incoming bone further along the rest direction: just gives Blender a tail.
            end_site = 0.5 * offsets[joint] if joint > 0 else np.array([0.0, 0.1, 0.0])
            nodes.append(BVHJoint(name, parent_node, offset, channels, end_site))
            aims.append(_Aim(joint, None))
            return
        primary = max(kids, key=lambda k: skeleton.raw_offsets[k][1])  # first of ties: chain order
        others = tuple(k for k in kids if k != primary)
        index = len(nodes)
        nodes.append(BVHJoint(name, parent_node, offset, channels))
        aims.append(_Aim(joint, primary, others))
        for kid in kids:
            if kid == primary:
                add(kid, index, offsets[kid], names[kid])
            else:
                branch = len(nodes)
                nodes.append(BVHJoint(f"{names[joint]}_to_{names[kid]}", index, np.zeros(3), JOINT_CHANNELS))
                aims.append(_Aim(joint, kid))
                add(kid, branch, offsets[kid], names[kid])

    root = int(np.flatnonzero(skeleton.parents < 0)[0])
    add(root, -1, np.zeros(3), names[root])
    return nodes, aims


def _twist_vector(points: np.ndarray, joint: int, others: tuple[int, ...]) -> np.ndarray:
    """The line through a branch point's other children (hip to hip), or the one other child's offset."""
    if len(others) >= 2:
        return points[..., others[0], :] - points[..., others[1], :]
    return points[..., others[0], :] - points[..., joint, :]


def _global_rotations(positions: np.ndarray, offsets: np.ndarray, nodes: list[BVHJoint], aims: list[_Aim]) -> np.ndarray:
    """(T, N, 3, 3) global rotation of every BVH node so that FK with ``offsets`` lands each aimed joint
    on its position (exactly, when the clip's bone lengths equal the offsets' lengths)."""
    t = positions.shape[0]
    out = np.empty((t, len(nodes), 3, 3))
    identity = np.broadcast_to(np.eye(3), (t, 3, 3))
    for i, (node, aim) in enumerate(zip(nodes, aims)):
        parent = identity if node.parent < 0 else out[:, node.parent]
        if aim.target is None:
            out[:, i] = parent
            continue
        bone = positions[:, aim.target] - positions[:, aim.joint]
        # Minimal rotation: from where the rest offset points in the parent's frame to the bone.
        minimal = _align(np.einsum("tij,j->ti", parent, offsets[aim.target]), bone) @ parent
        if aim.twist_from:
            rest_across = _twist_vector(offsets, aim.joint, aim.twist_from)
            rest_frame, rest_degenerate = _orthonormal_frame(offsets[aim.target], rest_across)
            if rest_degenerate:
                raise ValueError(f"rest offsets of the children of joint {aim.joint} are collinear: no twist reference")
            frame, degenerate = _orthonormal_frame(bone, _twist_vector(positions, aim.joint, aim.twist_from))
            twisted = frame @ rest_frame.T
            out[:, i] = np.where(degenerate[:, None, None], minimal, twisted)
        else:
            out[:, i] = minimal
    return out


def _local_rotations(global_rotations: np.ndarray, nodes: list[BVHJoint]) -> np.ndarray:
    """(T, N, 3, 3) global -> local rotations, parent^T @ child (the root's local rotation is its global)."""
    local = global_rotations.copy()
    for i, node in enumerate(nodes):
        if node.parent >= 0:
            local[:, i] = np.swapaxes(global_rotations[:, node.parent], -1, -2) @ global_rotations[:, i]
    return local


def _forward_kinematics(nodes: list[BVHJoint], motion: np.ndarray) -> np.ndarray:
    """Global positions (T, N, 3) of the nodes from the channel values (T, C), channels in node order."""
    t = motion.shape[0]
    positions = np.zeros((t, len(nodes), 3))
    rotations = np.zeros((t, len(nodes), 3, 3))
    column = 0
    for i, node in enumerate(nodes):
        values = dict(zip((c.lower() for c in node.channels), motion[:, column : column + len(node.channels)].T))
        column += len(node.channels)
        local = np.broadcast_to(np.eye(3), (t, 3, 3))
        for channel in node.channels:
            if channel.lower().endswith("rotation"):
                local = local @ _axis_rotation(channel[0].lower(), values[channel.lower()])
        if any(c.lower().endswith("position") for c in node.channels):
            translation = np.stack([values.get(f"{axis}position", np.zeros(t)) for axis in "xyz"], axis=-1)
        else:
            translation = np.broadcast_to(node.offset, (t, 3))
        if node.parent < 0:
            rotations[:, i], positions[:, i] = local, translation
        else:
            parent_rotation = rotations[:, node.parent]
            rotations[:, i] = parent_rotation @ local
            positions[:, i] = positions[:, node.parent] + np.einsum("tij,tj->ti", parent_rotation, translation)
    return positions


# ---------------------------------------------------------------------------------------------------
# writing


def _node_of(nodes: list[BVHJoint], name: str) -> int:
    for i, node in enumerate(nodes):
        if node.name == name:
            return i
    raise KeyError(name)


def _check_joints(joints: np.ndarray, skeleton: Skeleton) -> None:
    if joints.ndim != 3 or joints.shape[1:] != (skeleton.num_joints, 3) or joints.shape[0] < 1:
        raise ValueError(f"joints must be (T, {skeleton.num_joints}, 3) for skeleton {skeleton.name!r}, got {joints.shape}")
    if not np.isfinite(joints).all():
        raise ValueError("joints contain NaN or inf")


def _hierarchy_text(nodes: list[BVHJoint]) -> str:
    children: list[list[int]] = [[] for _ in nodes]
    for i, node in enumerate(nodes):
        if node.parent >= 0:
            children[node.parent].append(i)
    lines = ["HIERARCHY"]
    fmt = f"{{:.{_DECIMALS}f}}"

    def vector(v: np.ndarray) -> str:
        return " ".join(fmt.format(float(x) + 0.0) for x in v)  # + 0.0: no "-0.000000"

    def emit(i: int, depth: int) -> None:
        node, pad = nodes[i], "  " * depth
        lines.append(f"{pad}{'ROOT' if node.parent < 0 else 'JOINT'} {node.name}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}  OFFSET {vector(node.offset)}")
        lines.append(f"{pad}  CHANNELS {len(node.channels)} {' '.join(node.channels)}")
        for child in children[i]:
            emit(child, depth + 1)
        if node.end_site is not None:
            lines.extend([f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET {vector(node.end_site)}", f"{pad}  }}"])
        lines.append(f"{pad}}}")

    emit(0, 0)
    return "\n".join(lines) + "\n"


def write_bvh(path: str | Path, joints: np.ndarray, skeleton: Skeleton, fps: float | None = None) -> Path:
    """Write joint positions (T, J, 3), in the skeleton's units (``skeleton.unit``), as a BVH file in
    metres that Blender imports; returns the path. See the module docstring for the hierarchy, the
    rotation order (``Yrotation Xrotation Zrotation``: R = Ry Rx Rz) and why ``<joint>_to_<child>``
    joints appear. Bone lengths are the clip's own (mean over frames), so ``read_bvh`` gives back
    the input positions when the clip's bone lengths are constant."""
    path = Path(path)
    fps = skeleton.fps if fps is None else float(fps)
    if not fps > 0:
        raise ValueError(f"{path}: fps must be positive, got {fps}")
    if skeleton.unit not in METRES_PER_UNIT:
        raise ValueError(f"skeleton {skeleton.name!r} has unit {skeleton.unit!r}; known: {sorted(METRES_PER_UNIT)}")
    positions = np.asarray(joints.detach().cpu().numpy() if isinstance(joints, torch.Tensor) else joints, dtype=np.float64)
    _check_joints(positions, skeleton)
    positions = positions * METRES_PER_UNIT[skeleton.unit]

    parents = skeleton.parents
    bones = positions[:, 1:] - positions[:, parents[1:]]
    lengths = np.linalg.norm(bones, axis=-1)  # (T, J-1)
    if (lengths.mean(axis=0) == 0).any():
        bad = [skeleton.joint_names[j + 1] for j in np.flatnonzero(lengths.mean(axis=0) == 0)]
        raise ValueError(f"{path}: zero-length bone(s) ending at {bad}: their directions are undefined")
    if (lengths == 0).any():
        raise ValueError(f"{path}: a bone has zero length on some frame: its direction is undefined there")
    offsets = np.zeros((skeleton.num_joints, 3))
    offsets[1:] = skeleton.raw_offsets[1:] / np.linalg.norm(skeleton.raw_offsets[1:], axis=-1, keepdims=True)
    offsets[1:] *= lengths.mean(axis=0)[:, None]

    nodes, aims = _hierarchy(skeleton, offsets)
    rotations = _global_rotations(positions, offsets, nodes, aims)
    local = _local_rotations(rotations, nodes)
    angles = np.stack([_euler_yxz_degrees(local[:, i]) for i in range(len(nodes))], axis=1)  # (T, N, 3)
    angles = np.unwrap(angles, period=360.0, axis=0)  # any one angle +-360 is the same rotation
    motion = np.concatenate((positions[:, 0], angles.reshape(len(positions), -1)), axis=1)

    reparsed = _forward_kinematics(nodes, motion)[:, [_node_of(nodes, n) for n in skeleton.joint_names]]
    deviation = np.abs(reparsed - positions).max()
    if deviation > DRIFT_WARNING_M:
        drift = (lengths.max(axis=0) - lengths.min(axis=0)).max()
        logger.warning(
            "%s: bone lengths vary by up to %.4f m over the clip; the BVH keeps each bone's direction with its "
            "mean length, so its joints deviate from the input by up to %.4f m", path, drift, deviation,
        )

    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", encoding="ascii") as f:
        f.write(_hierarchy_text(nodes))
        f.write(f"MOTION\nFrames: {len(motion)}\nFrame Time: {1.0 / fps:.8f}\n")
        np.savetxt(f, motion + 0.0, fmt=f"%.{_DECIMALS}f", delimiter=" ")
    return path


# ---------------------------------------------------------------------------------------------------
# reading


class _Tokens:
    """Whitespace tokens of a BVH file with the position, for error messages naming the file."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.items = path.read_text(encoding="utf-8", errors="replace").split()
        self.at = 0

    def next(self, what: str) -> str:
        if self.at >= len(self.items):
            raise ValueError(f"{self.path}: file ends where {what} was expected")
        self.at += 1
        return self.items[self.at - 1]

    def expect(self, *words: str) -> None:
        for word in words:
            token = self.next(repr(word))
            if token.lower() != word.lower():
                raise ValueError(f"{self.path}: expected {word!r}, found {token!r} (token {self.at})")

    def number(self, what: str) -> float:
        token = self.next(what)
        try:
            return float(token)
        except ValueError:
            raise ValueError(f"{self.path}: {what} must be a number, found {token!r} (token {self.at})") from None


def _parse_joint(tokens: _Tokens, name: str, parent: int, nodes: list[BVHJoint]) -> None:
    tokens.expect("{", "OFFSET")
    offset = np.array([tokens.number("an OFFSET value") for _ in range(3)])
    tokens.expect("CHANNELS")
    count = int(tokens.number("the channel count"))
    channels = tuple(tokens.next("a channel name") for _ in range(count))
    known = {f"{a}{kind}" for a in "xyz" for kind in ("position", "rotation")}
    if any(c.lower() not in known for c in channels) or len({c.lower() for c in channels}) != count:
        raise ValueError(f"{tokens.path}: joint {name!r} has invalid channels {channels}")
    index = len(nodes)
    nodes.append(BVHJoint(name, parent, offset, channels))
    while True:
        token = tokens.next(f"JOINT, End Site or '}}' in joint {name!r}")
        if token == "}":
            return
        if token.upper() == "JOINT":
            _parse_joint(tokens, tokens.next("a joint name"), index, nodes)
        elif token.lower() == "end":
            tokens.expect("Site", "{", "OFFSET")
            end = np.array([tokens.number("an End Site OFFSET value") for _ in range(3)])
            tokens.expect("}")
            nodes[index] = BVHJoint(name, parent, offset, channels, end)
        else:
            raise ValueError(f"{tokens.path}: unexpected {token!r} in joint {name!r} (token {tokens.at})")


def read_bvh(path: str | Path, joint_names: Sequence[str] | None = None) -> BVHMotion:
    """Parse a BVH file and run its forward kinematics: ``(joints (T, N, 3), names, fps)`` for every
    ROOT/JOINT in file order (in the file's units), or for ``joint_names`` in that order."""
    path = Path(path)
    tokens = _Tokens(path)
    tokens.expect("HIERARCHY", "ROOT")
    nodes: list[BVHJoint] = []
    _parse_joint(tokens, tokens.next("the root name"), -1, nodes)
    tokens.expect("MOTION", "Frames:")
    frames = int(tokens.number("the frame count"))
    tokens.expect("Frame", "Time:")
    frame_time = tokens.number("the frame time")
    if frames < 0 or not frame_time > 0:
        raise ValueError(f"{path}: invalid MOTION header (Frames: {frames}, Frame Time: {frame_time})")
    width = sum(len(n.channels) for n in nodes)
    values = tokens.items[tokens.at :]
    if len(values) != frames * width:
        raise ValueError(f"{path}: {frames} frames of {width} channels need {frames * width} values, found {len(values)}")
    try:
        motion = np.array(values, dtype=np.float64).reshape(frames, width)
    except ValueError:
        raise ValueError(f"{path}: the MOTION section contains a non-number") from None
    positions = _forward_kinematics(nodes, motion)
    names = [n.name for n in nodes]
    if joint_names is not None:
        missing = [n for n in joint_names if n not in names]
        if missing:
            raise ValueError(f"{path}: no joint(s) {missing} in the file")
        names = list(joint_names)
        positions = positions[:, [_node_of(nodes, n) for n in names]]
    return BVHMotion(positions, names, 1.0 / frame_time)
