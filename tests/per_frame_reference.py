"""A straightforward per-frame implementation of HumanML3D's feature extraction, written independently
of ``mfm.features``: one frame and one joint at a time, with its own numpy quaternion helpers and the
reference's structure (uniform skeleton as IK then FK, chain loops, scipy's Gaussian filter).

It is the oracle the vectorised code is tested against and the baseline of
``benchmarks/bench_features.py``. Not for production use: it is slow on purpose.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d

from mfm.skeleton import Skeleton

UP = np.array([0.0, 1.0, 0.0])
FORWARD = np.array([0.0, 0.0, 1.0])
IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def q_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


def q_conj(q: np.ndarray) -> np.ndarray:
    return np.array([q[0], -q[1], -q[2], -q[3]])


def q_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """q v q* via the quaternion sandwich (a different formula from the vectorised code's)."""
    return q_mul(q_mul(q, np.array([0.0, *v])), q_conj(q))[1:]


def q_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    q = np.array([np.linalg.norm(a) * np.linalg.norm(b) + a @ b, *np.cross(a, b)])
    return q / np.linalg.norm(q)


def q_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix whose columns are the rotated basis vectors."""
    return np.stack([q_rotate(q, e) for e in np.eye(3)], axis=1)


def cont6d_to_matrix(d6: np.ndarray) -> np.ndarray:
    x = d6[:3] / np.linalg.norm(d6[:3])
    z = np.cross(x, d6[3:])
    z = z / np.linalg.norm(z)
    return np.stack([x, np.cross(z, x), z], axis=1)


def parents_of(skeleton: Skeleton) -> list[int]:
    parents = [-1] * skeleton.num_joints
    for chain in skeleton.kinematic_chains:
        for a, b in zip(chain[:-1], chain[1:]):
            parents[b] = a
    return parents


def facing_quat(frame: np.ndarray, r_hip: int, l_hip: int, r_sdr: int, l_sdr: int) -> np.ndarray:
    across = (frame[r_hip] - frame[l_hip]) + (frame[r_sdr] - frame[l_sdr])
    forward = np.cross(UP, across / np.linalg.norm(across))
    return q_between(forward / np.linalg.norm(forward), FORWARD)


def ik_frame(frame: np.ndarray, root_quat: np.ndarray, skeleton: Skeleton, compat: bool) -> np.ndarray:
    """Local rotations of one frame, chain by chain like the reference's inverse_kinematics_np."""
    quats = np.zeros((skeleton.num_joints, 4))
    quats[0] = root_quat
    global_of = {0: root_quat}
    for chain in skeleton.kinematic_chains:
        rotation = root_quat if compat else global_of[chain[0]]
        for a, b in zip(chain[:-1], chain[1:]):
            bone = frame[b] - frame[a]
            bone_rotation = q_between(skeleton.raw_offsets[b], bone / np.linalg.norm(bone))
            quats[b] = q_mul(q_conj(rotation), bone_rotation)
            rotation = q_mul(rotation, quats[b])
            global_of[b] = rotation
    return quats


def fk_frame(quats: np.ndarray, root_pos: np.ndarray, offsets: np.ndarray, skeleton: Skeleton, compat: bool) -> np.ndarray:
    joints = np.zeros((skeleton.num_joints, 3))
    joints[0] = root_pos
    global_of = {0: quats[0]}
    for chain in skeleton.kinematic_chains:
        rotation = quats[0] if compat else global_of[chain[0]]
        for a, b in zip(chain[:-1], chain[1:]):
            rotation = q_mul(rotation, quats[b])
            global_of[b] = rotation
            joints[b] = q_rotate(rotation, offsets[b]) + joints[a]
    return joints


def uniform_skeleton(positions: np.ndarray, skeleton: Skeleton, target_offsets: np.ndarray) -> np.ndarray:
    parents = parents_of(skeleton)
    source_offsets = np.zeros_like(target_offsets)
    for j in range(1, skeleton.num_joints):
        source_offsets[j] = np.linalg.norm(positions[0, j] - positions[0, parents[j]]) * skeleton.raw_offsets[j]
    knee, ankle = skeleton.leg_joints
    source_leg = np.abs(source_offsets[knee]).max() + np.abs(source_offsets[ankle]).max()
    target_leg = np.abs(target_offsets[knee]).max() + np.abs(target_offsets[ankle]).max()
    scale = target_leg / source_leg
    out = np.zeros_like(positions)
    r_hip, l_hip, r_sdr, l_sdr = skeleton.face_joints
    for t in range(len(positions)):
        root_quat = facing_quat(positions[t], l_hip, r_hip, r_sdr, l_sdr)  # any root rotation cancels
        quats = ik_frame(positions[t], root_quat, skeleton, compat=True)
        out[t] = fk_frame(quats, positions[t, 0] * scale, target_offsets, skeleton, compat=True)
    return out


def canonical_positions(joints: np.ndarray, skeleton: Skeleton, target_offsets: np.ndarray | None = None) -> np.ndarray:
    target = skeleton.target_offsets() if target_offsets is None else np.asarray(target_offsets, dtype=np.float64)
    positions = uniform_skeleton(np.asarray(joints, dtype=np.float64), skeleton, target)
    floor = min(positions[t, j, 1] for t in range(len(positions)) for j in range(skeleton.num_joints))
    root_xz = positions[0, 0] * np.array([1.0, 0.0, 1.0])
    to_z = facing_quat(positions[0], *skeleton.face_joints)
    out = np.zeros_like(positions)
    for t in range(len(positions)):
        for j in range(skeleton.num_joints):
            p = positions[t, j] - np.array([0.0, floor, 0.0]) - root_xz
            out[t, j] = q_rotate(to_z, p)
    return out


def joints_to_features(
    joints: np.ndarray, skeleton: Skeleton, *, compat: bool = True, target_offsets: np.ndarray | None = None
) -> np.ndarray:
    positions = canonical_positions(joints, skeleton, target_offsets)
    n = len(positions)
    r_hip, l_hip, r_sdr, l_sdr = skeleton.face_joints
    if compat:
        r_hip, l_hip = l_hip, r_hip

    forwards = np.zeros((n, 3))
    for t in range(n):
        across = (positions[t, r_hip] - positions[t, l_hip]) + (positions[t, r_sdr] - positions[t, l_sdr])
        forwards[t] = np.cross(UP, across / np.linalg.norm(across))
    forwards = gaussian_filter1d(forwards, 20, axis=0, mode="nearest")
    root_quats = [q_between(f / np.linalg.norm(f), FORWARD) for f in forwards]
    if compat:
        root_quats[0] = IDENTITY
    else:
        root_quats = [q_mul(q, q_conj(root_quats[0])) for q in root_quats]

    quats = np.stack([ik_frame(positions[t], root_quats[t], skeleton, compat) for t in range(n)])
    for t in range(1, n):  # sign continuity, per joint
        for j in range(skeleton.num_joints):
            if quats[t, j] @ quats[t - 1, j] < 0:
                quats[t, j] = -quats[t, j]

    rows = []
    left, right = skeleton.foot_left, skeleton.foot_right
    for t in range(n - 1):
        r_now, r_next = quats[t, 0], quats[t + 1, 0]
        root_step = positions[t + 1, 0] - positions[t, 0]
        row = [np.arcsin(np.clip(q_mul(r_next, q_conj(r_now))[2], -1, 1))]
        row += list(q_rotate(r_next, root_step)[[0, 2]])
        row.append(positions[t, 0, 1])
        for j in range(1, skeleton.num_joints):
            local = positions[t, j] - positions[t, 0] * np.array([1.0, 0.0, 1.0])
            row += list(q_rotate(r_now, local))
        for j in range(1, skeleton.num_joints):
            m = q_to_matrix(quats[t, j])
            row += list(m[:, 0]) + list(m[:, 1])
        for j in range(skeleton.num_joints):
            row += list(q_rotate(r_now, positions[t + 1, j] - positions[t, j]))
        for j in (*left, *right):
            step = positions[t + 1, j] - positions[t, j]
            row.append(float(step @ step < skeleton.contact_threshold))
        rows.append(row)
    return np.array(rows, dtype=np.float32)


def _root_trajectory(features: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    angle, position = 0.0, np.zeros(3)
    rotations, positions = [], []
    for t in range(len(features)):
        if t > 0:
            angle += features[t - 1, 0]
        rotation = np.array([np.cos(angle), 0.0, np.sin(angle), 0.0])
        if t > 0:
            position = position + q_rotate(q_conj(rotation), np.array([features[t - 1, 1], 0.0, features[t - 1, 2]]))
        rotations.append(rotation)
        positions.append(np.array([position[0], features[t, 3], position[2]]))
    return rotations, positions


def features_to_joints(features: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    features = np.asarray(features, dtype=np.float64)
    rotations, roots = _root_trajectory(features)
    out = np.zeros((len(features), skeleton.num_joints, 3))
    for t in range(len(features)):
        out[t, 0] = roots[t]
        for j in range(1, skeleton.num_joints):
            ric = features[t, 4 + 3 * (j - 1) : 4 + 3 * j]
            out[t, j] = q_rotate(q_conj(rotations[t]), ric) + roots[t] * np.array([1.0, 0.0, 1.0])
    return out


def features_to_joints_fk(
    features: np.ndarray, skeleton: Skeleton, target_offsets: np.ndarray | None = None, *, compat: bool = True
) -> np.ndarray:
    features = np.asarray(features, dtype=np.float64)
    offsets = skeleton.target_offsets() if target_offsets is None else np.asarray(target_offsets, dtype=np.float64)
    rotations, roots = _root_trajectory(features)
    start = 4 + 3 * (skeleton.num_joints - 1)
    out = np.zeros((len(features), skeleton.num_joints, 3))
    for t in range(len(features)):
        out[t, 0] = roots[t]
        global_of = {0: q_to_matrix(rotations[t])}
        for chain in skeleton.kinematic_chains:
            matrix = global_of[0] if compat else global_of[chain[0]]
            for a, b in zip(chain[:-1], chain[1:]):
                matrix = matrix @ cont6d_to_matrix(features[t, start + 6 * (b - 1) : start + 6 * b])
                global_of[b] = matrix
                out[t, b] = matrix @ offsets[b] + out[t, a]
    return out
