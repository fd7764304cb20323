"""Skeletons as data: kinematic chains, raw offsets, target bone lengths and the constants of
HumanML3D's feature extraction (EricGuo5513/HumanML3D ``paramUtil.py`` / ``motion_representation``).

A skeleton with J joints gives 12*J - 1 feature dims (263 for HumanML3D's 22 joints, 251 for KIT's 21).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Skeleton:
    """A fixed joint hierarchy and the constants HumanML3D's feature extraction needs.

    ``raw_offsets`` are unit directions of each joint from its parent in the rest pose; the
    target skeleton (what every clip is retargeted to) is ``raw_offsets * bone_lengths``.
    """

    name: str
    joint_names: tuple[str, ...]
    kinematic_chains: tuple[tuple[int, ...], ...]
    raw_offsets: np.ndarray  # (J, 3) unit directions, row 0 = root
    bone_lengths: np.ndarray | None  # (J,) target length of the bone ending at each joint (root 0); None: take from a reference clip
    face_joints: tuple[int, int, int, int]  # (r_hip, l_hip, r_shoulder, l_shoulder)
    foot_left: tuple[int, int]  # (ankle, foot)
    foot_right: tuple[int, int]
    leg_joints: tuple[int, int]  # (knee, ankle) of one leg: its length scales the root height when retargeting
    fps: float
    contact_threshold: float  # squared per-frame foot displacement below which a foot touches the ground
    unit: str  # "m" or "mm"
    lower_body_joints: tuple[int, ...] = field(default=())  # kept by the upper-body editing preset

    def __post_init__(self) -> None:
        j = len(self.joint_names)
        if self.raw_offsets.shape != (j, 3):
            raise ValueError(f"{self.name}: raw_offsets must be ({j}, 3), got {self.raw_offsets.shape}")
        if self.bone_lengths is not None and self.bone_lengths.shape != (j,):
            raise ValueError(f"{self.name}: bone_lengths must be ({j},), got {self.bone_lengths.shape}")
        seen = sorted({i for chain in self.kinematic_chains for i in chain})
        if seen != list(range(j)):
            raise ValueError(f"{self.name}: kinematic chains must cover joints 0..{j - 1} exactly")

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    @property
    def feature_dim(self) -> int:
        return 12 * self.num_joints - 1

    @property
    def parents(self) -> np.ndarray:
        """Parent index of every joint (-1 for the root), read off the kinematic chains."""
        parents = np.full(self.num_joints, -1, dtype=np.int64)
        for chain in self.kinematic_chains:
            for parent, child in zip(chain[:-1], chain[1:]):
                parents[child] = parent
        return parents

    def target_offsets(self) -> np.ndarray:
        """(J, 3) rest-pose offsets of the uniform target skeleton every clip is retargeted to."""
        if self.bone_lengths is None:
            raise ValueError(
                f"skeleton {self.name!r} has no built-in target bone lengths: pass a reference clip "
                "(the reference code uses KIT clip 03950_gt) to take them from"
            )
        return (self.raw_offsets * self.bone_lengths[:, None]).astype(np.float64)

    def with_bone_lengths_from(self, joints: np.ndarray) -> "Skeleton":
        """A copy whose target bone lengths are measured on frame 0 of ``joints`` (J, 3) or (T, J, 3),
        as the reference code does with its example clip."""
        frame = np.asarray(joints, dtype=np.float64)
        frame = frame[0] if frame.ndim == 3 else frame
        lengths = np.zeros(self.num_joints)
        parents = self.parents
        for child in range(1, self.num_joints):
            lengths[child] = np.linalg.norm(frame[child] - frame[parents[child]])
        return Skeleton(**{**self.__dict__, "bone_lengths": lengths})


HUMANML3D = Skeleton(
    name="humanml3d",
    joint_names=(
        "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
        "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
        "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
        "left_wrist", "right_wrist",
    ),
    kinematic_chains=((0, 2, 5, 8, 11), (0, 1, 4, 7, 10), (0, 3, 6, 9, 12, 15), (9, 14, 17, 19, 21), (9, 13, 16, 18, 20)),
    raw_offsets=np.array(
        [[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, -1, 0], [0, 1, 0], [0, -1, 0],
         [0, -1, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1], [0, 1, 0], [1, 0, 0], [-1, 0, 0], [0, 0, 1],
         [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0]],
        dtype=np.float64,
    ),
    # Bone lengths (m) of HumanML3D's target skeleton (example 000021, frame 0), measured on the
    # published clip 012314, where they are constant over frames to 2e-6 m.
    bone_lengths=np.array(
        [0.0, 0.103074, 0.109883, 0.131568, 0.393623, 0.390188, 0.14319, 0.432433, 0.425643, 0.057365,
         0.143382, 0.149419, 0.21936, 0.137487, 0.143383, 0.103039, 0.131614, 0.122984, 0.25684,
         0.263092, 0.266012, 0.269876],
        dtype=np.float64,
    ),
    face_joints=(2, 1, 17, 16),
    foot_left=(7, 10),
    foot_right=(8, 11),
    leg_joints=(5, 8),
    fps=20.0,
    contact_threshold=0.002,
    unit="m",
    lower_body_joints=(0, 1, 2, 4, 5, 7, 8, 10, 11),
)

KIT = Skeleton(
    name="kit",
    joint_names=(
        # Sides follow the reference's face joints (r_hip 11, l_hip 16, r_shoulder 5, l_shoulder 8).
        "root", "torso_lower", "torso_upper", "neck", "head", "right_shoulder", "right_elbow",
        "right_wrist", "left_shoulder", "left_elbow", "left_wrist", "right_hip", "right_knee",
        "right_ankle", "right_ball", "right_toe", "left_hip", "left_knee", "left_ankle", "left_ball",
        "left_toe",
    ),
    kinematic_chains=((0, 11, 12, 13, 14, 15), (0, 16, 17, 18, 19, 20), (0, 1, 2, 3, 4), (3, 5, 6, 7), (3, 8, 9, 10)),
    raw_offsets=np.array(
        [[0, 0, 0], [0, 1, 0], [0, 1, 0], [0, 1, 0], [0, 1, 0], [1, 0, 0], [0, -1, 0], [0, -1, 0],
         [-1, 0, 0], [0, -1, 0], [0, -1, 0], [1, 0, 0], [0, -1, 0], [0, -1, 0], [0, 0, 1], [0, 0, 1],
         [-1, 0, 0], [0, -1, 0], [0, -1, 0], [0, 0, 1], [0, 0, 1]],
        dtype=np.float64,
    ),
    # The reference takes KIT's target skeleton from clip 03950_gt, which is not redistributable here:
    # supply a reference clip (Skeleton.with_bone_lengths_from) or let the KIT reader measure one.
    bone_lengths=None,
    face_joints=(11, 16, 5, 8),
    foot_left=(19, 20),
    foot_right=(14, 15),
    leg_joints=(17, 18),
    fps=12.5,
    contact_threshold=0.05,
    unit="mm",
    lower_body_joints=(0, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20),
)

SKELETONS: dict[str, Skeleton] = {s.name: s for s in (HUMANML3D, KIT)}


def get_skeleton(name: str) -> Skeleton:
    try:
        return SKELETONS[name]
    except KeyError:
        raise KeyError(f"unknown skeleton {name!r}; known: {sorted(SKELETONS)}") from None
