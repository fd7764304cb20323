"""Named slices of the HumanML3D ("Guo") feature vector for any skeleton.

Layout for J joints (263-D for J = 22, 251-D for J = 21):

    0           root angular velocity about Y (rad/frame, half-angle convention)
    1:3         root linear velocity x, z in the facing frame
    3           root height y
    ric         3*(J-1) root-relative joint positions (joints 1..J-1), facing +Z
    rot6d       6*(J-1) local joint rotations, first two columns of the rotation matrix
    local_vel   3*J velocities of every joint in the facing frame
    contacts    4 foot contacts [left ankle, left foot, right ankle, right foot]
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from mfm.skeleton import Skeleton


@dataclass(frozen=True)
class FeatureLayout:
    skeleton: Skeleton

    @property
    def num_joints(self) -> int:
        return self.skeleton.num_joints

    @property
    def dim(self) -> int:
        return self.skeleton.feature_dim

    @cached_property
    def slices(self) -> dict[str, slice]:
        """The 7 feature groups, in order; also the groups whose Std is averaged for normalisation."""
        j = self.num_joints
        bounds = {
            "root_rot_vel": 1,
            "root_lin_vel": 2,
            "root_height": 1,
            "ric": 3 * (j - 1),
            "rot6d": 6 * (j - 1),
            "local_vel": 3 * j,
            "contacts": 4,
        }
        out, start = {}, 0
        for name, size in bounds.items():
            out[name] = slice(start, start + size)
            start += size
        assert start == self.dim
        return out

    @property
    def root_dims(self) -> np.ndarray:
        """Root rotation velocity, linear velocity and height (dims 0:4)."""
        return np.arange(0, 4)

    @property
    def root_motion_mask(self) -> np.ndarray:
        """Boolean (dim,) mask of the dims that carry the root's motion: its rotation and linear velocity and its
        height (dims 0:4), and every joint's velocity (``local_vel``, which holds the same travel over the ground
        seen from each joint); the rest (ric positions, 6D rotations, foot contacts) is the pose."""
        mask = np.zeros(self.dim, dtype=bool)
        mask[self.root_dims] = True
        mask[self.slices["local_vel"]] = True
        return mask

    @property
    def contact_joints(self) -> tuple[int, int, int, int]:
        s = self.skeleton
        return (s.foot_left[0], s.foot_left[1], s.foot_right[0], s.foot_right[1])

    def joint_dims(self, joint: int) -> np.ndarray:
        """Every feature dim that describes ``joint``: its ric position, 6D rotation, local velocity and
        foot contact (if any); for the root, the four root dims instead of ric/rot6d."""
        if not 0 <= joint < self.num_joints:
            raise IndexError(f"joint {joint} out of range for {self.skeleton.name} ({self.num_joints} joints)")
        sl = self.slices
        dims: list[int] = []
        if joint == 0:
            dims += list(self.root_dims)
        else:
            dims += list(range(sl["ric"].start + 3 * (joint - 1), sl["ric"].start + 3 * joint))
            dims += list(range(sl["rot6d"].start + 6 * (joint - 1), sl["rot6d"].start + 6 * joint))
        dims += list(range(sl["local_vel"].start + 3 * joint, sl["local_vel"].start + 3 * joint + 3))
        for k, contact_joint in enumerate(self.contact_joints):
            if contact_joint == joint:
                dims.append(sl["contacts"].start + k)
        return np.array(sorted(dims), dtype=np.int64)

    def dims_for_joints(self, joints) -> np.ndarray:
        """Sorted union of :meth:`joint_dims` over ``joints``."""
        dims = [self.joint_dims(int(j)) for j in joints]
        return np.unique(np.concatenate(dims)) if dims else np.zeros(0, dtype=np.int64)

    def joint_mask(self, joints) -> np.ndarray:
        """Boolean (dim,) mask of the dims of ``joints``."""
        mask = np.zeros(self.dim, dtype=bool)
        mask[self.dims_for_joints(joints)] = True
        return mask

    @property
    def lower_body_mask(self) -> np.ndarray:
        """Dims of root, legs and foot contacts (what the upper-body edit keeps)."""
        return self.joint_mask(self.skeleton.lower_body_joints)
