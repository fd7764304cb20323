"""DeepMimic motion capture (Peng et al. 2018) as shipped with pybullet: the project's embedded dataset.

Where: ``pybullet_data.getDataPath()/data/motions/humanoid3d_<name>.txt`` (JSON despite the suffix): 15
humanoid clips, 33.5 s of capture (45.6 s once the loops are tiled, see below). Only ``humanoid3d_*``
files are read: the 5 clips in ``motions/walker/`` (0walk_forward, turn_left0/1, turn_right0/1, 1.2 s
each) share the frame format but are not part of that set, and ``laikago_walk.txt`` is a quadruped.

Frame format (44 numbers): ``[dt, root_pos(3), root_quat(4), chest(4), neck(4), right_hip(4),
right_knee(1), right_ankle(4), right_shoulder(4), right_elbow(1), left_hip(4), left_knee(1),
left_ankle(4), left_shoulder(4), left_elbow(1)]``, quaternions w, x, y, z (pybullet wants x, y, z, w),
knees and elbows an angle (rad) about the joint's z axis. ``dt`` is the time to the next frame (0 on
the last). World: Y up, metres; the character faces +X in its rest pose, its right side is +Z.

Scale: DeepMimic loads ``humanoid/humanoid.urdf`` with ``globalScaling=0.25`` (pybullet_envs
deep_mimic/env/humanoid_stable_pd.py) and feeds the root positions of the clips unscaled, so the URDF
offsets are multiplied by 0.25 here. Measured at that scale the humanoid is 1.62 m tall (sole to the
top of the head sphere) with 0.42 m thighs and 0.41 m shins, and the clips' standing root heights
(0.85-0.89 m) put its feet on the floor y = 0: it is a real metric human, not a scaled one.

Joint positions come from forward kinematics over the URDF (link frames: ``p_child = p_parent +
R_parent @ (0.25 * origin)``, ``R_child = R_parent @ R_joint``; every joint origin has rpy = 0), written
vectorised over frames; tests check them against pybullet's ``getLinkState`` in DIRECT mode.

Mapping onto HumanML3D's 22 joints (so that the embedded dataset uses the 263-D representation). Each
target joint is a fixed point of one humanoid link, so every bone has constant length (a bone that
spans a DeepMimic joint always has that joint's centre as one end):

==================  =========================  =====================================================
HumanML3D joint      humanoid link               point (link frame, URDF units = 4x metres)
==================  =========================  =====================================================
pelvis               root                        origin
left/right_hip       left/right_hip              origin (hip joint centre, level with the root)
spine1               root                        half way to the chest joint (0, 0.472, 0)
spine2               chest                       origin (lower-back joint, 0.236 m above the pelvis)
spine3               chest                       (0, 0.185, 0): SMPL's spine2-spine3-neck proportion
neck                 neck                        origin (base of the neck, level with the shoulders)
head                 neck                        (0, 0.42, 0): 0.105 m above the neck, HumanML3D's
                                                 neck-head bone (0.103 m); the head sphere's centre is
                                                 at 0.175 m
left/right_collar    chest                       (-0.048, 0.877, -/+0.293): 0.22 m above the chest
                                                 joint, 0.07 m to the side (inner end of the clavicle)
left/right_shoulder  left/right_shoulder         origin
left/right_elbow     left/right_elbow            origin
left/right_wrist     left/right_wrist            origin (fixed joint at the end of the forearm)
left/right_knee      left/right_knee             origin
left/right_ankle     left/right_ankle            origin
left/right_foot      left/right_ankle            (0.46, -0.16, 0): ball of the foot, 0.115 m ahead of
                                                 and 0.04 m below the ankle, 1 cm above the sole of the
                                                 foot box (0.708 x 0.22 x 0.36 centred at (0.18, -0.09))
==================  =========================  =====================================================

Time: the source returns each clip at its own rate (``1/dt`` snapped to an integer: 16, 24, 30 or 60 fps;
the processing stage resamples). ``humanoid3d_roll`` has one frame with a double ``dt`` (a dropped
frame); clips with uneven ``dt`` are resampled onto an even grid here by slerping the pose.

Loops: clips marked ``"Loop": "wrap"`` are tiled to at least ``min_seconds`` (default 2.5 s, above
HumanML3D's 40-frame/2 s minimum); each new cycle is moved by DeepMimic's own cycle offset (the
horizontal root displacement over one cycle). Their last frame does not repeat the first exactly
(4-21 degrees off at the root, up to 58 at a joint), so before tiling the loop is closed by spreading
that mismatch linearly over the cycle (``close_loop``); a clip that is not tiled is left as captured.
``"none"`` clips are kept as they are: kick (1.53 s: 30 feature frames at 20 fps) is then shorter
than HumanML3D's 40-frame minimum and needs ``min_frames`` <= 30 to survive the processing stage.

Splits: DeepMimic has one take per motion, so no motion can be held out. Every clip is in ``train``;
``val`` and ``test`` hold one extra crop of each looping clip (``<name>-val``, ``<name>-test``), started
a third and two thirds of a cycle in and ``min_seconds`` long. They check fitting, not generalisation.
"""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from mfm.rotations import qmul, quat_to_matrix
from mfm.skeleton import HUMANML3D
from preprocess.clip import BAD_SHAPE, NAN_FRAMES, NO_CAPTIONS, UNREADABLE, Caption, Clip, SkippedInput, check_joints
from preprocess.sources.humanml3d import as_bool

URDF_SCALE = 0.25  # DeepMimic's globalScaling
MOTION_PREFIX = "humanoid3d_"
HELD_OUT_PHASES = {"val": 1.0 / 3.0, "test": 2.0 / 3.0}

# The 44 numbers of a frame after dt: root position, root rotation, then each joint's rotation.
FRAME_JOINTS: tuple[tuple[str, int], ...] = (
    ("chest", 4), ("neck", 4),
    ("right_hip", 4), ("right_knee", 1), ("right_ankle", 4), ("right_shoulder", 4), ("right_elbow", 1),
    ("left_hip", 4), ("left_knee", 1), ("left_ankle", 4), ("left_shoulder", 4), ("left_elbow", 1),
)
FRAME_SIZE = 1 + 3 + 4 + sum(size for _, size in FRAME_JOINTS)  # 44

# HumanML3D joint -> (humanoid link, point in the link frame in URDF units); see the module docstring.
JOINT_MAP: dict[str, tuple[str, tuple[float, float, float]]] = {
    "pelvis": ("root", (0.0, 0.0, 0.0)),
    "left_hip": ("left_hip", (0.0, 0.0, 0.0)),
    "right_hip": ("right_hip", (0.0, 0.0, 0.0)),
    "spine1": ("root", (0.0, 0.472302, 0.0)),
    "left_knee": ("left_knee", (0.0, 0.0, 0.0)),
    "right_knee": ("right_knee", (0.0, 0.0, 0.0)),
    "spine2": ("chest", (0.0, 0.0, 0.0)),
    "left_ankle": ("left_ankle", (0.0, 0.0, 0.0)),
    "right_ankle": ("right_ankle", (0.0, 0.0, 0.0)),
    "spine3": ("chest", (0.0, 0.185, 0.0)),
    "left_foot": ("left_ankle", (0.46, -0.16, 0.0)),
    "right_foot": ("right_ankle", (0.46, -0.16, 0.0)),
    "neck": ("neck", (0.0, 0.0, 0.0)),
    "left_collar": ("chest", (-0.048, 0.877, -0.293)),
    "right_collar": ("chest", (-0.048, 0.877, 0.293)),
    "head": ("neck", (0.0, 0.42, 0.0)),
    "left_shoulder": ("left_shoulder", (0.0, 0.0, 0.0)),
    "right_shoulder": ("right_shoulder", (0.0, 0.0, 0.0)),
    "left_elbow": ("left_elbow", (0.0, 0.0, 0.0)),
    "right_elbow": ("right_elbow", (0.0, 0.0, 0.0)),
    "left_wrist": ("left_wrist", (0.0, 0.0, 0.0)),
    "right_wrist": ("right_wrist", (0.0, 0.0, 0.0)),
}
assert tuple(JOINT_MAP) == HUMANML3D.joint_names

# Written from each clip's joints (tests/test_sources.py checks the side-specific claims): which leg
# kicks, which arm punches, which way it turns and travels. "Left"/"right" are the performer's.
CAPTIONS: dict[str, tuple[str, ...]] = {
    "backflip": (
        "a person does a backflip.",
        "someone swings the arms, jumps up and flips backwards, landing on their feet.",
        "a person performs a standing back somersault.",
    ),
    "cartwheel": (
        "a person does a cartwheel to the left.",
        "someone raises the arms, puts the left hand down and cartwheels sideways.",
        "a person turns a cartwheel and lands standing.",
    ),
    "crawl": (
        "a person crawls forward on hands and knees.",
        "someone crawls slowly, staying low to the ground.",
        "a person is crawling on all fours.",
    ),
    "dance_a": (
        "a person dances, raising the arms and spinning a full turn to the right.",
        "someone twirls around once to the right with the arms up.",
        "a person does a dance spin.",
    ),
    "dance_b": (
        "a person dances, stepping to the right and back while raising one arm and then the other.",
        "someone sways side to side, lifting the arms above the head.",
        "a person is dancing.",
    ),
    "getup_facedown": (
        "a person lying face down pushes up and stands up.",
        "someone gets up from lying on their stomach.",
        "a person rises from the ground to standing.",
    ),
    "getup_faceup": (
        "a person lying on their back lifts the legs, rocks forward and stands up.",
        "someone gets up from lying on their back.",
        "a person rises from the floor to a standing position.",
    ),
    "jump": (
        "a person crouches and jumps forward with both feet.",
        "someone does a standing long jump, swinging the arms.",
        "a person leaps forward and lands in a crouch.",
    ),
    "kick": (
        "a person steps forward and kicks high with the right leg.",
        "someone throws a high roundhouse kick with the right foot, turning to the left.",
        "a person kicks with their right leg.",
    ),
    "punch": (
        "a person steps forward to the left and punches with the right arm.",
        "someone moves forward and throws a right punch.",
        "a person punches with their right fist.",
    ),
    "roll": (
        "a person crouches, does a forward roll and stands back up.",
        "someone rolls forward on the ground and gets back on their feet.",
        "a person performs a forward roll.",
    ),
    "run": (
        "a person runs forward.",
        "someone runs straight ahead at a fast pace.",
        "a person is running.",
    ),
    "spin": (
        "a person spins around twice to the left, swinging the legs up high.",
        "someone does a jumping spin, turning two full circles.",
        "a person turns around in circles, leaning over and kicking the legs into the air.",
    ),
    "spinkick": (
        "a person jumps, spins around to the left and kicks high with the right leg.",
        "someone does a spinning jump kick.",
        "a person performs a tornado kick with the right foot.",
    ),
    "walk": (
        "a person walks forward at a steady pace.",
        "someone walks straight ahead, swinging their arms.",
        "a person is walking forward.",
    ),
}


def default_motions_dir() -> Path:
    pybullet_data = _import_pybullet_data()  # here: the other sources must not need pybullet
    return Path(pybullet_data.getDataPath()) / "data" / "motions"


def default_urdf_path() -> Path:
    pybullet_data = _import_pybullet_data()
    return Path(pybullet_data.getDataPath()) / "humanoid" / "humanoid.urdf"


def _import_pybullet_data():
    """pybullet's data package, which ships the clips; an optional dependency (no wheel for every platform)."""
    try:
        import pybullet_data
    except ModuleNotFoundError as err:
        raise ModuleNotFoundError(
            "the embedded DeepMimic dataset comes with pybullet (pybullet_data), which is not installed: "
            "pip install 'motion-flow-matching[embedded]' (or pip install pybullet==3.2.7; Linux x86-64 has a "
            "wheel, other platforms build it from source), or build shards from your own data with --source") from err
    return pybullet_data


# ----------------------------------------------------------------------------------------------------
# The humanoid model
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class HumanoidJoint:
    """The URDF joint that attaches ``link`` to ``parent``, with its origin already scaled to metres."""

    link: str
    parent: str
    kind: str  # "spherical" | "revolute" | "fixed"
    origin: tuple[float, float, float]
    axis: tuple[float, float, float]


def read_humanoid_urdf(path: Path, scale: float = URDF_SCALE) -> tuple[HumanoidJoint, ...]:
    """The joints of DeepMimic's humanoid URDF in file order (parents before children). pybullet's copy
    ends with a NUL byte, which XML parsers reject: it is stripped."""
    root = ET.fromstring(path.read_bytes().rstrip(b"\0\r\n \t"))
    joints = []
    for element in root.iter("joint"):
        origin = element.find("origin")
        rpy = [float(v) for v in origin.get("rpy", "0 0 0").split()]
        if any(abs(v) > 1e-9 for v in rpy):
            raise ValueError(f"{path}: joint {element.get('name')} has rpy {rpy}; this reader assumes none")
        axis = element.find("axis")
        joints.append(
            HumanoidJoint(
                link=element.find("child").get("link"),
                parent=element.find("parent").get("link"),
                kind=element.get("type"),
                origin=tuple(scale * float(v) for v in origin.get("xyz").split()),
                axis=tuple(float(v) for v in axis.get("xyz").split()) if axis is not None else (0.0, 0.0, 1.0),
            )
        )
    return tuple(joints)


# ----------------------------------------------------------------------------------------------------
# Poses: parse, resample, forward kinematics
# ----------------------------------------------------------------------------------------------------


@dataclass
class PoseTrack:
    """A clip's poses: root position (T, 3), root quaternion (T, 4) and each joint's rotation, wxyz
    quaternions (T, 4) for spherical joints, angles (T, 1) for revolute ones."""

    root_pos: np.ndarray
    root_quat: np.ndarray
    joint_rot: dict[str, np.ndarray]

    def __len__(self) -> int:
        return self.root_pos.shape[0]


def parse_frames(frames: np.ndarray) -> tuple[np.ndarray, PoseTrack]:
    """(T, 44) frames -> (dt (T,), poses). Quaternions are normalised (the files round to 6 digits)."""
    dt = frames[:, 0]
    root_pos = frames[:, 1:4]
    root_quat = _normalised(frames[:, 4:8])
    joint_rot, column = {}, 8
    for name, size in FRAME_JOINTS:
        block = frames[:, column : column + size]
        joint_rot[name] = _normalised(block) if size == 4 else block
        column += size
    return dt, PoseTrack(root_pos, root_quat, joint_rot)


def _normalised(q: np.ndarray) -> np.ndarray:
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def frame_rate(dt: np.ndarray) -> float:
    """The clip's rate: 1/median(dt) over the frames that have a successor, snapped to an integer when
    within 0.1% (the files store dt rounded, e.g. 0.016666)."""
    rate = 1.0 / float(np.median(dt[:-1]))
    return float(round(rate)) if abs(rate - round(rate)) < 1e-3 * rate else rate


def resample_evenly(dt: np.ndarray, poses: PoseTrack, fps: float) -> PoseTrack:
    """Poses on an even time grid at ``fps`` when the file's ``dt`` is uneven (roll's dropped frame):
    lerp for positions and angles, slerp for quaternions. Even clips come back unchanged."""
    steps = dt[:-1]
    if np.allclose(steps, 1.0 / fps, rtol=1e-3, atol=0):
        return poses
    times = np.concatenate(([0.0], np.cumsum(steps)))
    grid = np.arange(int(math.floor(times[-1] * fps + 1e-6)) + 1) / fps
    index = np.clip(np.searchsorted(times, grid, side="right") - 1, 0, len(times) - 2)
    frac = ((grid - times[index]) / (times[index + 1] - times[index]))[:, None]

    def lerp(x: np.ndarray) -> np.ndarray:
        return x[index] * (1 - frac) + x[index + 1] * frac

    return PoseTrack(
        root_pos=lerp(poses.root_pos),
        root_quat=_slerp(poses.root_quat[index], poses.root_quat[index + 1], frac),
        joint_rot={
            name: _slerp(rot[index], rot[index + 1], frac) if rot.shape[1] == 4 else lerp(rot)
            for name, rot in poses.joint_rot.items()
        },
    )


def _slerp(q0: np.ndarray, q1: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Shortest-arc spherical interpolation of unit quaternions (N, 4) at fractions t (N, 1)."""
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.clip(np.abs(dot), -1.0, 1.0)
    theta = np.arccos(dot)
    sin_theta = np.sin(theta)
    near = sin_theta < 1e-6
    w0 = np.where(near, 1 - t, np.sin((1 - t) * theta) / np.where(near, 1, sin_theta))
    w1 = np.where(near, t, np.sin(t * theta) / np.where(near, 1, sin_theta))
    return _normalised(w0 * q0 + w1 * q1)


def _rotation_matrices(q_wxyz: np.ndarray) -> np.ndarray:
    return quat_to_matrix(torch.from_numpy(np.ascontiguousarray(q_wxyz, dtype=np.float64))).numpy()


def _revolute_matrices(angle: np.ndarray, axis: tuple[float, float, float]) -> np.ndarray:
    """(T, 1) angles about a unit ``axis`` -> (T, 3, 3), as a quaternion (cos a/2, sin a/2 * axis)."""
    half = angle[:, 0] / 2
    q = np.concatenate((np.cos(half)[:, None], np.sin(half)[:, None] * np.asarray(axis)[None]), axis=1)
    return _rotation_matrices(q)


def link_frames(poses: PoseTrack, model: tuple[HumanoidJoint, ...]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """World frame ``(position (T, 3), rotation (T, 3, 3))`` of every humanoid link, by forward
    kinematics over the URDF. The root link is fixed to the base, whose pose the frame gives."""
    frames = {"base": (poses.root_pos, _rotation_matrices(poses.root_quat))}
    for joint in model:
        parent_pos, parent_rot = frames[joint.parent]
        position = parent_pos + parent_rot @ np.asarray(joint.origin)
        if joint.kind == "spherical":
            rotation = parent_rot @ _rotation_matrices(poses.joint_rot[joint.link])
        elif joint.kind == "revolute":
            rotation = parent_rot @ _revolute_matrices(poses.joint_rot[joint.link], joint.axis)
        elif joint.kind == "fixed":
            rotation = parent_rot
        else:
            raise ValueError(f"humanoid joint {joint.link}: unsupported type {joint.kind!r}")
        frames[joint.link] = (position, rotation)
    return frames


def humanml3d_joints(poses: PoseTrack, model: tuple[HumanoidJoint, ...], scale: float = URDF_SCALE) -> np.ndarray:
    """(T, 22, 3) HumanML3D joint positions (metres, Y up) of a pose track; see the mapping table."""
    frames = link_frames(poses, model)
    points = []
    for link, point in JOINT_MAP.values():
        position, rotation = frames[link]
        points.append(position + rotation @ (scale * np.asarray(point)))
    return np.stack(points, axis=1)


# ----------------------------------------------------------------------------------------------------
# Loops
# ----------------------------------------------------------------------------------------------------


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return qmul(torch.from_numpy(np.ascontiguousarray(a)), torch.from_numpy(np.ascontiguousarray(b))).numpy()


def close_loop(poses: PoseTrack) -> PoseTrack:
    """A looping clip whose last pose equals its first (up to the horizontal root offset).

    DeepMimic's wrap clips do not close exactly (the last frame is off by 4-21 degrees at the root and
    up to 58 degrees at a joint), so a tiled copy would jump at every seam. The mismatch of each
    rotation is spread linearly over the clip: ``q'(t) = slerp(1, q(0) q(T-1)^-1, t/(T-1)) q(t)``
    (angles and the root height the same way, linearly); frame 0 is unchanged.
    """
    n = len(poses)
    ramp = (np.arange(n, dtype=np.float64) / (n - 1))[:, None]
    identity = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (n, 1))

    def close_rotation(q: np.ndarray) -> np.ndarray:
        mismatch = _qmul(q[0], q[-1] * np.array([1.0, -1.0, -1.0, -1.0]))
        return _normalised(_qmul(_slerp(identity, np.tile(mismatch, (n, 1)), ramp), q))

    def close_angle(a: np.ndarray) -> np.ndarray:
        return a + (a[0] - a[-1]) * ramp

    root_pos = poses.root_pos.copy()
    root_pos[:, 1:2] = close_angle(root_pos[:, 1:2])
    return PoseTrack(
        root_pos=root_pos,
        root_quat=close_rotation(poses.root_quat),
        joint_rot={name: close_rotation(r) if r.shape[1] == 4 else close_angle(r) for name, r in poses.joint_rot.items()},
    )


def tile_cycles(joints: np.ndarray, cycles: int) -> np.ndarray:
    """``cycles`` copies of a closed loop end to end, each moved by the cycle's horizontal root offset
    (DeepMimic's own cycle offset, vertical part zeroed). The frame two cycles share appears once."""
    offset = (joints[-1, 0] - joints[0, 0]) * np.array([1.0, 0.0, 1.0])
    body = joints[:-1]
    pieces = [body + k * offset for k in range(cycles)]
    pieces.append(joints[-1:] + (cycles - 1) * offset)
    return np.concatenate(pieces, axis=0)


def cycles_for(frames: int, fps: float, min_seconds: float) -> int:
    """How many cycles of a ``frames``-frame loop reach ``min_seconds``."""
    return max(1, math.ceil(min_seconds * fps / (frames - 1) - 1e-9))


# ----------------------------------------------------------------------------------------------------
# The source
# ----------------------------------------------------------------------------------------------------


class DeepMimicSource:
    """DeepMimic's 15 humanoid clips as HumanML3D-skeleton clips (see the module docstring).

    Options: ``root`` (a folder of ``humanoid3d_*.txt`` clips; default pybullet's), ``urdf`` (default
    pybullet's ``humanoid/humanoid.urdf``), ``min_seconds`` (looping clips are tiled to at least this,
    default 2.5), ``held_out`` (add the val/test crops of looping clips, default True).
    """

    name = "deepmimic"
    skeleton = "humanml3d"
    # The kick take is 1.5 s (30 feature frames) and does not loop, so it cannot be tiled: with HumanML3D's
    # 40-frame minimum the embedded dataset would lose the "kick" action entirely. Builds of this source
    # default to 24 frames (KIT-ML's minimum) instead; --min-frames still overrides it.
    default_min_frames = 24
    # 15 train motions: shards of 5 let 2 ranks (or 3 data workers) each read whole shards.
    default_shard_size = 5

    def __init__(
        self,
        root: str | Path | None = None,
        *,
        urdf: str | Path | None = None,
        min_seconds: float = 2.5,
        held_out: bool = True,
    ) -> None:
        self.motions_dir = Path(root) if root is not None else default_motions_dir()
        self.urdf_path = Path(urdf) if urdf is not None else default_urdf_path()
        if not self.urdf_path.is_file():
            raise FileNotFoundError(f"deepmimic: humanoid model {self.urdf_path} not found")
        self.model = read_humanoid_urdf(self.urdf_path)
        self.min_seconds = float(min_seconds)
        if not self.min_seconds >= 0:
            raise ValueError(f"deepmimic: min_seconds must be >= 0, got {min_seconds!r}")
        self.held_out = as_bool(held_out)
        paths = sorted(self.motions_dir.glob(f"{MOTION_PREFIX}*.txt"))
        if not paths:
            raise FileNotFoundError(f"deepmimic: no {MOTION_PREFIX}*.txt clips in {self.motions_dir}")
        # Which clips loop decides which items exist; 15 small files, read once here.
        self.looping = {path.stem[len(MOTION_PREFIX) :]: _is_looping(path) for path in paths}

    def list_items(self) -> list[str]:
        items = list(self.looping)
        if self.held_out:
            items += [f"{clip}-{split}" for clip, loops in self.looping.items() if loops for split in HELD_OUT_PHASES]
        return sorted(items)

    def load(self, item: str) -> Clip | SkippedInput:
        clip_name, split = _parse_item(item)
        path = self.motions_dir / f"{MOTION_PREFIX}{clip_name}.txt"
        motion = read_motion_file(path)
        if isinstance(motion, SkippedInput):
            return replace(motion, id=item)
        frames, loops = motion
        if clip_name not in CAPTIONS:
            return SkippedInput(item, str(path), NO_CAPTIONS, f"no captions written for clip {clip_name!r}")
        if split in HELD_OUT_PHASES and not loops:
            raise ValueError(f"deepmimic: clip {clip_name!r} does not loop, so it has no held-out item {item!r}")
        dt, poses = parse_frames(frames)
        fps = frame_rate(dt)
        joints, meta = self._joints(resample_evenly(dt, poses, fps), fps, loops, split)
        problem = check_joints(joints, HUMANML3D.num_joints)
        if problem is not None:
            return SkippedInput(item, str(path), *problem)
        return Clip(
            id=item,
            joints=joints.astype(np.float32),
            fps=fps,
            skeleton=self.skeleton,
            captions=[Caption(text) for text in CAPTIONS[clip_name]],
            split=split,
            source=self.name,
            action=clip_name,
            path=str(path),
            meta=meta,
        )

    def _joints(self, poses: PoseTrack, fps: float, loops: bool, split: str) -> tuple[np.ndarray, dict]:
        """The train clip: the take, tiled to ``min_seconds`` when it loops. A val/test crop: as long as
        the train clip, started a third / two thirds of a cycle in."""
        cycle = len(poses) - 1
        length = (cycles_for(len(poses), fps, self.min_seconds) if loops else 1) * cycle + 1
        start = round(HELD_OUT_PHASES[split] * cycle) if split in HELD_OUT_PHASES else 0
        cycles = math.ceil((start + length - 1) / cycle)
        if cycles > 1:
            poses = close_loop(poses)
        joints = humanml3d_joints(poses, self.model)
        if cycles > 1:
            joints = tile_cycles(joints, cycles)
        meta = {"loop": loops, "cycles": cycles, "loop_closed": cycles > 1, "start_frame": start}
        return joints[start : start + length], meta


def read_motion_file(path: Path) -> tuple[np.ndarray, bool] | SkippedInput:
    """``(frames (T, 44), loops)`` of a DeepMimic clip file, or why it cannot be used."""
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
        frames = np.asarray(document["Frames"], dtype=np.float64)
    except Exception as err:  # a bad file is a skip, never a crash of the worker
        return SkippedInput("", str(path), UNREADABLE, f"{type(err).__name__}: {err}")
    if frames.ndim != 2 or frames.shape[1] != FRAME_SIZE or frames.shape[0] < 2:
        return SkippedInput("", str(path), BAD_SHAPE, f"expected (T>=2, {FRAME_SIZE}) frames, got {frames.shape}")
    if not np.isfinite(frames).all():
        return SkippedInput("", str(path), NAN_FRAMES, "frames hold NaN/inf")
    if not (frames[:-1, 0] > 0).all():
        return SkippedInput("", str(path), BAD_SHAPE, "a frame other than the last has a non-positive dt")
    return frames, document.get("Loop") == "wrap"


def _parse_item(item: str) -> tuple[str, str]:
    """``walk`` -> (walk, train); ``walk-val`` -> (walk, val)."""
    clip_name, _, suffix = item.rpartition("-")
    if clip_name and suffix in HELD_OUT_PHASES:
        return clip_name, suffix
    return item, "train"


def _is_looping(path: Path) -> bool:
    try:
        return json.loads(path.read_text(encoding="utf-8")).get("Loop") == "wrap"
    except (OSError, ValueError):
        return False  # load() reports the unreadable file
