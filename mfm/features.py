"""HumanML3D ("Guo") motion features: joint positions <-> the (T-1, 12J-1) feature vector.

Vectorised re-implementation of EricGuo5513/HumanML3D ``motion_representation`` (``process_file``,
``recover_from_ric``, ``recover_from_rot``) and ``cal_mean_variance``. Everything runs batched over clips,
frames and joints in torch (float64 for extraction); the only Python loop is over the depth levels of
the skeleton (at most 7) when ``features_to_joints_fk`` chains rotations or ``rigid_joints`` places bones.
``rigid_joints`` / ``features_to_joints_rigid`` (not in the reference) fit recovered positions onto the
skeleton's fixed bone lengths, for exports.

Compatibility with the published dataset (``compat=True``, the default). The reference
``Skeleton.inverse_kinematics_np`` has three quirks the dataset was generated with:

* it unpacks the face joints as ``l_hip, r_hip, sdr_r, sdr_l`` although callers pass
  ``r_hip, l_hip, sdr_r, sdr_l``, so the hip vector is reversed and the root (facing) rotation is
  estimated from (shoulder span - hip span);
* every chain's first rotation is taken relative to the ROOT rotation, including the arm chains that
  start at the spine (joint 9 for HumanML3D), whose parent rotation is really spine3's;
* the root rotation of frame 0 is overwritten with the identity (``root_quat[0] = [1, 0, 0, 0]``: active
  in the code that generated the data and in the MDM/T2M forks, commented out in HumanML3D's current
  ``common/skeleton.py``), so the first frame's root angular velocity carries the whole frame-1 rotation.

Determined empirically on the published clip 012314 (tests/test_features.py): with all three,
re-extraction from its joints reproduces its features to float32 noise; dropping any one of them
breaks the match by 1e-1 or more. ``compat=False`` is the fixed variant: correct face order, chains
relative to their parent's global rotation, and the root rotations re-referenced to frame 0 (so frame 0
is still the identity that ``features_to_joints`` assumes, without the jump).

One deliberate difference in both modes: the root quaternions get ``qfix`` (sign continuity over time)
before the root angular velocity is taken. The reference skips it, which flips the sign of the
angular velocity on the frame where the facing direction crosses +-180 deg; elsewhere the two agree
exactly (the 6D block does not depend on quaternion signs).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Union

import numpy as np
import torch

from mfm.layout import FeatureLayout
from mfm.rotations import (
    cont6d_to_matrix,
    qbetween,
    qfix,
    qinv,
    qmul,
    qrot,
    quat_about_y,
    quat_to_cont6d,
    quat_to_matrix,
    rotate_about_y,
)
from mfm.skeleton import Skeleton

ArrayLike = Union[np.ndarray, torch.Tensor]
Tensor = torch.Tensor
Parts = tuple  # components of a vector (x, y, z) or quaternion (w, x, y, z), see mfm.rotations

FORWARD_SMOOTHING_SIGMA = 20.0  # frames; the reference's smooth_forward=True
_GAUSSIAN_TRUNCATE = 4.0  # scipy.ndimage.gaussian_filter1d's default kernel radius, in sigmas
_SMOOTHING_BLOCK = 256  # output frames per block of the banded smoothing product
_CHUNK_ELEMENTS = 1 << 16  # joint-frames per group of clips processed together on CPU


# ---------------------------------------------------------------------------------------------------
# numpy / torch plumbing and input checks


def _as_tensor(x: ArrayLike, dtype: torch.dtype) -> Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(dtype)
    return torch.from_numpy(np.ascontiguousarray(x, dtype=np.float64)).to(dtype)


def _like_input(result: Tensor, original: ArrayLike) -> ArrayLike:
    """Return ``result`` as the same kind of array as ``original`` (numpy in, numpy out)."""
    if isinstance(original, torch.Tensor):
        return result
    return result.detach().cpu().numpy()


def _float_dtype_of(x: ArrayLike) -> torch.dtype:
    """Keep float32/float64 (and torch half types); anything else computes in float32."""
    if isinstance(x, torch.Tensor):
        return x.dtype if x.is_floating_point() else torch.float32
    return torch.float64 if np.asarray(x).dtype == np.float64 else torch.float32


def _all_finite(x: Tensor) -> bool:
    # One reduction instead of an elementwise mask: a sum is finite iff every term is (for data of
    # physical magnitude; only overflow past 1e308 could fool it).
    return bool(torch.isfinite(x.sum()))


def _check_joints(joints: Tensor, skeleton: Skeleton) -> None:
    if joints.ndim < 3 or joints.shape[-1] != 3 or joints.shape[-2] != skeleton.num_joints:
        raise ValueError(
            f"joints must be (T, {skeleton.num_joints}, 3) or (B, T, {skeleton.num_joints}, 3) for skeleton "
            f"{skeleton.name!r}, got shape {tuple(joints.shape)}"
        )
    if joints.shape[-3] < 2:
        raise ValueError(f"need at least 2 frames to compute velocities, got {joints.shape[-3]}")
    if not _all_finite(joints):
        raise ValueError("joints contain NaN or inf")


def _check_features(features: Tensor, skeleton: Skeleton) -> None:
    if features.ndim < 2 or features.shape[-1] != skeleton.feature_dim:
        raise ValueError(
            f"features must be (..., T, {skeleton.feature_dim}) for skeleton {skeleton.name!r}, "
            f"got shape {tuple(features.shape)}"
        )


def _target_offsets(skeleton: Skeleton, target_offsets: ArrayLike | None, like: Tensor) -> Tensor:
    offsets = skeleton.target_offsets() if target_offsets is None else target_offsets
    offsets = _as_tensor(offsets, like.dtype).to(like.device)
    if offsets.shape != (skeleton.num_joints, 3):
        raise ValueError(f"target_offsets must be ({skeleton.num_joints}, 3), got {tuple(offsets.shape)}")
    return offsets


# ---------------------------------------------------------------------------------------------------
# skeleton topology, derived once per kinematic tree


@dataclass(frozen=True)
class IKConvention:
    """Which of the reference IK's quirks to reproduce (see the module docstring)."""

    swap_face_hips: bool  # facing estimated from (l_hip - r_hip) + (r_sdr - l_sdr)
    chains_from_root: bool  # each chain's first local rotation is relative to the root rotation
    identity_first_frame: bool  # frame 0's root rotation overwritten by the identity (else re-referenced)

    @staticmethod
    def of(compat: "bool | IKConvention") -> "IKConvention":
        if isinstance(compat, IKConvention):
            return compat
        return REFERENCE_IK if compat else FIXED_IK


REFERENCE_IK = IKConvention(swap_face_hips=True, chains_from_root=True, identity_first_frame=True)
FIXED_IK = IKConvention(swap_face_hips=False, chains_from_root=False, identity_first_frame=False)


@dataclass(frozen=True)
class _Topology:
    parents: tuple[int, ...]  # parent of every joint, -1 for the root
    ancestors: np.ndarray  # (J, J): [j, k] = 1 if bone k (parent(k) -> k) lies on the path root -> j
    rotation_ref: tuple[int, ...]  # joint whose global rotation a joint's local rotation is relative to (0 = root)
    levels: tuple[tuple[int, ...], ...]  # non-root joints grouped so every rotation_ref is in an earlier group


@lru_cache(maxsize=32)
def _topology(chains: tuple[tuple[int, ...], ...], num_joints: int, chains_from_root: bool) -> _Topology:
    parents = [-1] * num_joints
    for chain in chains:
        for parent, child in zip(chain[:-1], chain[1:]):
            parents[child] = parent
    chain_firsts = {chain[1] for chain in chains}
    ancestors = np.zeros((num_joints, num_joints))
    tree_depth = [0] * num_joints
    for j in range(1, num_joints):
        k = j
        while k > 0:
            ancestors[j, k] = 1.0
            tree_depth[j] += 1
            k = parents[k]
    # The reference IK/FK start every chain from the root rotation; the fixed variant from the parent's.
    ref = [0] + [0 if (chains_from_root and j in chain_firsts) else max(parents[j], 0) for j in range(1, num_joints)]
    level = [0] * num_joints
    for j in sorted(range(1, num_joints), key=tree_depth.__getitem__):  # refs are ancestors: done first
        level[j] = level[ref[j]] + 1
    levels = tuple(tuple(j for j in range(1, num_joints) if level[j] == d) for d in range(1, max(level) + 1))
    return _Topology(tuple(parents), ancestors, tuple(ref), levels)


def _topology_of(skeleton: Skeleton, chains_from_root: bool) -> _Topology:
    return _topology(tuple(tuple(c) for c in skeleton.kinematic_chains), skeleton.num_joints, chains_from_root)


# ---------------------------------------------------------------------------------------------------
# the steps of process_file, on components-first data: positions (3, J, N, T) for N clips of T frames,
# rotations as tuples of (J, N, T) component tensors. Each component of each joint is one contiguous
# block, so rotation maths is plain elementwise work on contiguous memory (see mfm.rotations),
# selecting joints copies whole blocks, and per-joint constants broadcast as (J, 1, 1).


def _joint_index(indices, like: Tensor) -> Tensor:
    return torch.as_tensor(list(indices), dtype=torch.long, device=like.device)


def _bones_cf(positions: Tensor, topo: _Topology) -> Tensor:
    """(3, J, ...) -> (3, J-1, ...): vectors parent -> child of joints 1..J-1."""
    return positions[:, 1:] - positions.index_select(1, _joint_index(topo.parents[1:], positions))


def _sum_bones_cf(root: Tensor, bones: Tensor, topo: _Topology) -> Tensor:
    """Positions (3, J, ...) = root (3, ...) + the bone vectors (3, J-1, ...) on each joint's path from the
    root: the translation part of forward kinematics as one product with the (J, J-1) path matrix."""
    ancestors = torch.as_tensor(topo.ancestors[:, 1:], dtype=bones.dtype, device=bones.device)
    summed = torch.matmul(ancestors, bones.reshape(3, bones.shape[1], -1))
    return root[:, None] + summed.reshape((3, ancestors.shape[0]) + tuple(bones.shape[2:]))


def _per_joint(values: np.ndarray | Tensor, like: Tensor) -> Parts:
    """(J', 3) per-joint vectors -> components (J', 1, ..., 1) broadcasting against a (J', N, T) component."""
    t = torch.as_tensor(values, dtype=like.dtype, device=like.device)
    return tuple(t[:, c].reshape((-1,) + (1,) * (like.ndim - 1)) for c in range(3))


def _squared_norm(v) -> Tensor:
    return v[0] * v[0] + v[1] * v[1] + v[2] * v[2]


def _retarget_cf(positions: Tensor, skeleton: Skeleton, target_offsets: Tensor) -> Tensor:
    """HumanML3D's uniform skeleton on (3, J, N, T): keep every bone's direction, give it the target
    length, and scale the root trajectory by the ratio of target to source leg length
    (``skeleton.leg_joints``, measured on frame 0 as max |component| of the offset, like the reference).

    The reference does this as IK on the source then FK with the target offsets; the root rotation and
    all local rotations cancel in that round trip, leaving each bone's global shortest-arc rotation from
    its rest direction applied to the target offset. That is what is computed here, so retargeting does
    not depend on ``compat``. When every target offset points along its rest direction (always, for
    ``skeleton.target_offsets()``) that rotation just turns the offset onto the bone, so the bone is
    rescaled instead: the same result without the quaternion work.
    """
    topo = _topology_of(skeleton, chains_from_root=True)  # either: only parents/ancestors are used
    bones = _bones_cf(positions, topo)  # (3, J-1, N, T)
    squared = _squared_norm(bones)
    if bool((squared == 0).any()):
        bad = sorted({int(j) + 1 for j in torch.nonzero(squared == 0)[:, 0].tolist()})
        raise ValueError(f"zero-length bone(s) ending at joint(s) {bad}: bone directions are undefined")
    raw = torch.as_tensor(skeleton.raw_offsets, dtype=positions.dtype, device=positions.device)
    knee, ankle = skeleton.leg_joints
    first = torch.sqrt(squared[..., 0])  # (J-1, N) bone lengths on frame 0
    source_leg = first[knee - 1] * raw[knee].abs().max() + first[ankle - 1] * raw[ankle].abs().max()
    target_leg = target_offsets[knee].abs().max() + target_offsets[ankle].abs().max()
    scale = target_leg / source_leg  # (N,)

    rest, target = raw[1:], target_offsets[1:]
    along_rest = bool((torch.linalg.cross(rest, target) == 0).all() and ((rest * target).sum(-1) >= 0).all())
    if along_rest:
        target_length = torch.linalg.vector_norm(target, dim=-1)
        new_bones = bones * (target_length[:, None, None] / torch.sqrt(squared))
    else:
        rotations = qbetween(_per_joint(rest, squared), tuple(bones), dim=0)
        new_bones = torch.stack(qrot(rotations, _per_joint(target, squared)))
    return _sum_bones_cf(positions[:, 0] * scale[:, None], new_bones, topo)


def _across_cf(positions: Tensor, face_joints: tuple[int, int, int, int]) -> Tensor:
    """(3, J, ...) -> (3, ...) unit vector across the body, (r_hip - l_hip) + (r_shoulder - l_shoulder)."""
    r_hip, l_hip, r_sdr, l_sdr = face_joints
    across = (positions[:, r_hip] - positions[:, l_hip]) + (positions[:, r_sdr] - positions[:, l_sdr])
    return across / torch.sqrt(_squared_norm(across))


def _facing_rotation(across: Tensor) -> Parts:
    """Unit vectors across the body (3, ...) -> the Y rotation taking the forward direction
    cross(up, across) to +Z, as the reference's ``qbetween(forward, [0, 0, 1])``."""
    ax, _, az = across
    zero, one = torch.zeros_like(ax), torch.ones_like(ax)
    return qbetween((az, zero, -ax), (zero, zero, one))


def _canonicalise_cf(positions: Tensor, skeleton: Skeleton, target_offsets: Tensor) -> Tensor:
    """(3, J, N, T) source joints -> retargeted, floor at y=0, frame-0 root at the XZ origin, frame 0
    facing +Z (with the face joints in their documented order: process_file is right, only its IK swaps)."""
    p = _retarget_cf(positions, skeleton, target_offsets)
    floor = p[1].amin(dim=(0, 2))  # (N,)
    origin = torch.stack((p[0, 0, :, 0], floor, p[2, 0, :, 0]))  # (3, N)
    p = p - origin[:, None, :, None]
    to_z = _facing_rotation(_across_cf(p[..., 0], skeleton.face_joints))  # components (N,)
    return torch.stack(rotate_about_y(tuple(c[:, None] for c in to_z), tuple(p)))


@lru_cache(maxsize=16)
def _smoothing_band(sigma: float, block: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """(block + 2r, block) banded matrix: column o holds the Gaussian kernel (truncated at 4 sigma,
    normalised to sum 1, as scipy) at rows o..o+2r. Cached: building it costs more than using it."""
    radius = int(_GAUSSIAN_TRUNCATE * sigma + 0.5)
    offsets = torch.arange(-radius, radius + 1, dtype=torch.float64)
    kernel = torch.exp(-0.5 * (offsets / sigma) ** 2)
    kernel = kernel / kernel.sum()
    band = torch.zeros(block + 2 * radius, block, dtype=torch.float64)
    for lag in range(2 * radius + 1):  # one diagonal per kernel tap
        band.diagonal(-lag).fill_(float(kernel[lag]))
    return band.to(dtype=dtype, device=device)


def _gaussian_smooth_last(x: Tensor, sigma: float) -> Tensor:
    """Smooth along the last dim like ``scipy.ndimage.gaussian_filter1d(x, sigma, axis=-1,
    mode='nearest')``.

    Done as matrix products: the edge-padded signal is cut into overlapping windows of
    ``block + 2 * radius`` frames, each multiplied by the same banded (block + 2r, block) kernel matrix.
    Several times faster than conv1d's float64 CPU path, with memory linear in T.
    """
    radius = int(_GAUSSIAN_TRUNCATE * sigma + 0.5)
    t = x.shape[-1]
    block = min(t, _SMOOTHING_BLOCK)
    blocks = -(-t // block)
    flat = x.reshape(-1, t)
    # 'nearest' = the edge samples repeated however far the kernel reaches; the extra right padding
    # only feeds outputs past T, which are dropped.
    right = radius + blocks * block - t
    padded = torch.cat((flat[:, :1].expand(-1, radius), flat, flat[:, -1:].expand(-1, right)), dim=1)
    windows = padded.unfold(1, block + 2 * radius, block)  # (M, blocks, block + 2r)
    band = _smoothing_band(float(sigma), block, x.dtype, x.device)
    return (windows @ band).reshape(flat.shape[0], blocks * block)[:, :t].reshape(x.shape)


def _root_rotation_cf(positions: Tensor, skeleton: Skeleton, convention: IKConvention, smooth_sigma: float | None) -> Parts:
    """(3, J, N, T) -> components (N, T) of the root (facing) rotation, frame 0 the identity."""
    face = skeleton.face_joints
    if convention.swap_face_hips:
        face = (face[1], face[0], face[2], face[3])
    across = _across_cf(positions, face)  # (3, N, T)
    if smooth_sigma is not None:
        # The reference smooths the unnormalised forward cross(up, across) = (a_z, 0, -a_x): the same as
        # smoothing a_x and a_z, since the filter is linear.
        across = _gaussian_smooth_last(across, smooth_sigma)
    root = _facing_rotation(across)
    if convention.identity_first_frame:
        root = tuple(c.clone() for c in root)
        for c, value in zip(root, (1.0, 0.0, 0.0, 0.0)):
            c[:, 0] = value
        return root
    return qmul(root, qinv(tuple(c[:, :1] for c in root)))  # Y rotations commute: order is immaterial


def _bone_rotations_cf(positions: Tensor, root: Parts, skeleton: Skeleton, convention: IKConvention) -> Parts:
    """Local rotations of joints 1..J-1, components (J-1, N, T): each bone's shortest-arc rotation from
    its rest direction, relative to the global rotation of its reference joint (``rotation_ref``)."""
    topo = _topology_of(skeleton, convention.chains_from_root)
    bones = _bones_cf(positions, topo)
    global_rotations = qbetween(_per_joint(skeleton.raw_offsets[1:], bones[0]), tuple(bones))
    ref = _joint_index(topo.rotation_ref[1:], positions)
    reference = tuple(torch.cat((r[None], g), dim=0).index_select(0, ref) for r, g in zip(root, global_rotations))
    return qmul(qinv(reference), global_rotations)


def _components_first(joints: Tensor) -> tuple[Tensor, tuple[int, ...]]:
    """(..., T, J, 3) -> ((3, J, N, T) contiguous, leading shape)."""
    lead = tuple(joints.shape[:-3])
    flat = joints.reshape((-1,) + tuple(joints.shape[-3:]))
    return flat.permute(3, 2, 0, 1).contiguous(), lead


def _components_last(x: Tensor, lead: tuple[int, ...]) -> Tensor:
    """(C, J, N, T) -> (..., T, J, C)."""
    return x.permute(2, 3, 1, 0).reshape(lead + (x.shape[3], x.shape[1], x.shape[0]))


def canonical_joints(joints: ArrayLike, skeleton: Skeleton, *, target_offsets: ArrayLike | None = None) -> ArrayLike:
    """The global positions ``process_file`` computes its features from: retargeted to the uniform
    skeleton, on the floor (min y over all joints and frames = 0), root at the XZ origin on frame 0,
    frame 0 facing +Z. (T, J, 3) or (B, T, J, 3), numpy or torch like the input, float32 out."""
    x = _as_tensor(joints, torch.float64)
    _check_joints(x, skeleton)
    positions, lead = _components_first(x)
    out = _canonicalise_cf(positions, skeleton, _target_offsets(skeleton, target_offsets, x))
    return _like_input(_components_last(out, lead).to(torch.float32), joints)


def inverse_kinematics(
    positions: ArrayLike,
    skeleton: Skeleton,
    *,
    compat: bool | IKConvention = True,
    smooth_sigma: float | None = FORWARD_SMOOTHING_SIGMA,
) -> ArrayLike:
    """Local joint rotations (..., T, J, 4) of positions (..., T, J, 3), the reference's
    ``inverse_kinematics_np`` (float64, numpy or torch like the input).

    Joint 0 holds the root (facing) rotation: the Y rotation taking the body's forward direction
    (Gaussian-smoothed over time with ``smooth_sigma`` frames; None = no smoothing) to +Z, frame 0 made
    the identity, which ``features_to_joints`` assumes when it starts the integrated root angle at 0.
    Joint j > 0 holds the rotation of bone parent(j) -> j from its rest direction, relative to the
    global rotation ``compat`` says (module docstring). Signs are continuous over time (qfix)."""
    x = _as_tensor(positions, torch.float64)
    _check_joints(x, skeleton)
    cf, lead = _components_first(x)
    convention = IKConvention.of(compat)
    root = _root_rotation_cf(cf, skeleton, convention, smooth_sigma)
    bones = _bone_rotations_cf(cf, root, skeleton, convention)
    local = torch.stack([torch.cat((r[None], b), dim=0) for r, b in zip(root, bones)])  # (4, J, N, T)
    return _like_input(_components_last(qfix(local, time_dim=-1, dim=0), lead), positions)


def _features_cf(positions: Tensor, skeleton: Skeleton, convention: IKConvention) -> Tensor:
    """(3, J, N, T) canonical positions -> (N, T-1, 12J-1) float32 features."""
    _, j, n, t = positions.shape
    layout = FeatureLayout(skeleton).slices
    out = torch.empty((n, t - 1, skeleton.feature_dim), dtype=torch.float32, device=positions.device)

    def put(name: str, parts: Parts) -> None:
        """Write components (K, N, T-1) into group ``name``, laid out (N, T-1, K*C): strided copy + cast."""
        group = out[..., layout[name]].unflatten(-1, (-1, len(parts)))
        for c, part in enumerate(parts):
            group[..., c].copy_(part.permute(1, 2, 0))

    root_rot = _root_rotation_cf(positions, skeleton, convention, FORWARD_SMOOTHING_SIGMA)
    # Sign continuity matters only for the angular velocity; the 6D block is sign-invariant.
    r_rot = qfix(root_rot, time_dim=-1)
    now = tuple(c[:, :-1] for c in r_rot)
    nxt = tuple(c[:, 1:] for c in r_rot)
    root = positions[:, 0]  # (3, N, T)

    out[..., layout["root_rot_vel"].start] = torch.asin(qmul(nxt, qinv(now))[2].clamp(-1.0, 1.0))
    lin_x, _, lin_z = rotate_about_y(nxt, tuple(root[..., 1:] - root[..., :-1]))
    out[..., layout["root_lin_vel"]] = torch.stack((lin_x, lin_z), dim=-1)
    out[..., layout["root_height"].start] = root[1, :, :-1]

    now_j = tuple(c[None] for c in now)  # broadcast over joints
    p = positions[..., :-1]
    ric = (p[0, 1:] - root[0, None, :, :-1], p[1, 1:], p[2, 1:] - root[2, None, :, :-1])
    put("ric", rotate_about_y(now_j, ric))
    local = _bone_rotations_cf(positions, root_rot, skeleton, convention)
    put("rot6d", quat_to_cont6d(tuple(c[..., :-1] for c in local)))
    put("local_vel", rotate_about_y(now_j, tuple(positions[..., 1:] - p)))

    feet = positions.index_select(1, _joint_index(skeleton.foot_left + skeleton.foot_right, positions))
    step = feet[..., 1:] - feet[..., :-1]  # (3, 4, N, T-1)
    out[..., layout["contacts"]] = (_squared_norm(step) < skeleton.contact_threshold).permute(1, 2, 0).to(out.dtype)
    return out


def joints_to_features(
    joints: ArrayLike,
    skeleton: Skeleton,
    *,
    compat: bool | IKConvention = True,
    target_offsets: ArrayLike | None = None,
) -> ArrayLike:
    """HumanML3D ``process_file``: joint positions (T, J, 3) or (B, T, J, 3) -> features (.., T-1, 12J-1),
    float32, numpy or torch like the input (computed in float64 on the input's device).

    ``target_offsets`` (J, 3) overrides ``skeleton.target_offsets()`` as the uniform skeleton.
    ``compat`` selects the reference's IK quirks (default, matches the published data) or the fixed IK.
    Raises ValueError for a wrong shape, non-finite input, fewer than 2 frames, a zero-length bone or
    an undefined facing direction (hips and shoulders collinear with the vertical).
    """
    x = _as_tensor(joints, torch.float64)
    _check_joints(x, skeleton)
    offsets = _target_offsets(skeleton, target_offsets, x)
    convention = IKConvention.of(compat)
    lead, (t, j) = tuple(x.shape[:-3]), tuple(x.shape[-3:-1])
    clips = x.reshape(-1, t, j, 3)
    # Clips go through in groups of about _CHUNK_ELEMENTS joint-frames, so that the few dozen
    # temporaries of each step stay in cache (on CPU this is ~2x faster than one huge batch).
    per_chunk = max(1, _CHUNK_ELEMENTS // (t * j)) if clips.device.type == "cpu" else clips.shape[0]
    chunks = []
    for start in range(0, clips.shape[0], per_chunk):
        positions, _ = _components_first(clips[start : start + per_chunk])
        chunks.append(_features_cf(_canonicalise_cf(positions, skeleton, offsets), skeleton, convention))
    features = torch.cat(chunks) if len(chunks) > 1 else chunks[0]
    if not _all_finite(features):
        raise ValueError("features are not finite: the facing direction is undefined on some frame")
    return _like_input(features.reshape(lead + tuple(features.shape[-2:])), joints)


# ---------------------------------------------------------------------------------------------------
# features -> joints


def root_path(features: Tensor) -> tuple[Tensor, Tensor]:
    """Integrate the root (reference ``recover_root_rot_pos``) of raw (not normalised) torch features (..., T, D):
    the heading angle about +Y (..., T, radians) and the root's position (3, ..., T). The angle and XZ start at
    0 on frame 0; the height is read from dim 3. Differentiable (training's trajectory term uses it)."""
    angle, _, position = _integrate_root(features)
    return angle, position


def _root_trajectory(features: Tensor) -> tuple[Parts, Tensor]:
    """:func:`root_path` with the heading as rotation components (..., T)."""
    _, r_rot, position = _integrate_root(features)
    return r_rot, position


def _integrate_root(features: Tensor) -> tuple[Tensor, Parts, Tensor]:
    """The heading angle, its rotation components and the position of :func:`root_path`, computed once."""
    rot_vel = features[..., 0]
    zero = torch.zeros_like(rot_vel[..., :1])
    angle = torch.cumsum(torch.cat((zero, rot_vel[..., :-1]), dim=-1), dim=-1)
    r_rot = quat_about_y(angle, as_tuple=True)
    # Frame t moves by the root-frame velocity of frame t-1, turned back into the world by frame t's rotation.
    step = (
        torch.cat((zero, features[..., :-1, 1]), dim=-1),
        torch.zeros_like(rot_vel),
        torch.cat((zero, features[..., :-1, 2]), dim=-1),
    )
    step_x, _, step_z = rotate_about_y(qinv(r_rot), step)
    position = torch.stack((torch.cumsum(step_x, dim=-1), features[..., 3], torch.cumsum(step_z, dim=-1)))
    return angle, r_rot, position


def _ric_positions(features: Tensor, skeleton: Skeleton) -> tuple[Tensor, tuple[int, ...]]:
    """The pelvis at (0, root height, 0) and the ric joints of ``features`` (..., T, D; raw), components first
    (3, J, N, T), and the leading shape."""
    layout = FeatureLayout(skeleton)
    pelvis = torch.zeros(features.shape[:-1] + (1, 3), dtype=features.dtype, device=features.device)
    pelvis[..., 0, 1] = features[..., layout.slices["root_height"]][..., 0]
    ric = features[..., layout.slices["ric"]].unflatten(-1, (skeleton.num_joints - 1, 3))
    return _components_first(torch.cat([pelvis, ric], dim=-2))


def ric_bone_lengths(features: Tensor, skeleton: Skeleton) -> Tensor:
    """(..., T, J-1): the length of every bone (parent -> joint j, for j = 1..J-1) of the ric positions of
    ``features`` (..., T, D; raw, not normalised), in every frame."""
    positions, lead = _ric_positions(features, skeleton)
    lengths = torch.sqrt(_squared_norm(_bones_cf(positions, _topology_of(skeleton, chains_from_root=True))))
    return lengths.permute(1, 2, 0).reshape(lead + (positions.shape[3], positions.shape[1] - 1))


def set_ric_bone_lengths(features: Tensor, bone_lengths: Tensor, skeleton: Skeleton) -> Tensor:
    """``features`` (..., T, D; raw) with its ric block moved so that, in every frame, every bone has the length
    ``bone_lengths`` (..., T, J-1, as :func:`ric_bone_lengths`) gives it, along the direction it has in
    ``features``. Joints are placed from the root outwards (the pelvis at (0, root height, 0) of the ric frame), so
    a parent's correction carries its children along. The other channels are ``features``' own."""
    topo = _topology_of(skeleton, chains_from_root=True)  # either: only parents/ancestors are used
    moved, lead = _ric_positions(features, skeleton)
    bones = _bones_cf(moved, topo)
    length = bone_lengths.to(features.dtype).reshape((-1,) + tuple(bone_lengths.shape[-2:])).permute(2, 0, 1)
    rescaled = bones * (length / torch.sqrt(_squared_norm(bones)).clamp_min(1e-12))
    placed = _components_last(_sum_bones_cf(moved[:, 0], rescaled, topo), lead)  # (..., T, J, 3)
    out = features.clone()
    out[..., FeatureLayout(skeleton).slices["ric"]] = placed[..., 1:, :].flatten(-2)
    return out


def restore_bone_lengths(features: Tensor, reference: Tensor, skeleton: Skeleton) -> Tensor:
    """``features`` (..., T, D; raw, not normalised) with every bone given, in every frame, the length it has in
    ``reference`` (the same motion before a filter), along the direction it has in ``features``
    (:func:`set_ric_bone_lengths`).

    Why: a Gaussian filter over time averages each joint's position along its arc, and the average of points on an
    arc lies inside it. Where a limb swings fast the filtered bone is shorter: on the synthetic set's runs σ 0.9
    took a shin from 43 to 27 cm (docs/generator-study.md, "Smoothing shortens a swinging limb"). Restoring the
    lengths keeps what the filter is for (the jitter of each bone's direction) and leaves the bone-length figures
    those of the network's output."""
    return set_ric_bone_lengths(features, ric_bone_lengths(reference.to(features.dtype), skeleton), skeleton)


def features_to_joints(features: ArrayLike, skeleton: Skeleton) -> ArrayLike:
    """Reference ``recover_from_ric``: features (..., T, 12J-1) -> joint positions (..., T, J, 3) from the
    root trajectory and the ric block. Numpy or torch like the input; float64 input stays float64,
    anything else comes out float32."""
    x = _as_tensor(features, _float_dtype_of(features))
    _check_features(x, skeleton)
    j = skeleton.num_joints
    r_rot, root = _root_trajectory(x)
    ric = x[..., FeatureLayout(skeleton).slices["ric"]].unflatten(-1, (j - 1, 3)).unbind(-1)  # (..., T, J-1) each
    rotated = rotate_about_y(tuple(c[..., None] for c in qinv(r_rot)), ric)
    out = torch.empty(x.shape[:-1] + (j, 3), dtype=x.dtype, device=x.device)
    out[..., 0, :] = root.movedim(0, -1)
    out[..., 1:, 0] = rotated[0] + root[0, ..., None]
    out[..., 1:, 1] = rotated[1]
    out[..., 1:, 2] = rotated[2] + root[2, ..., None]
    return _like_input(out, features)


def features_to_joints_fk(
    features: ArrayLike,
    skeleton: Skeleton,
    target_offsets: ArrayLike | None = None,
    *,
    compat: bool | IKConvention = True,
) -> ArrayLike:
    """Reference ``recover_from_rot``: forward kinematics over the 6D block with the target skeleton's
    offsets, the root rotation ``(cos a, 0, sin a, 0)`` from the integrated root angular velocity and the
    integrated root position. ``compat`` must match the one the features were extracted with (it says
    which global rotation each chain's first local rotation is relative to). Numpy or torch like the
    input; float64 stays float64, anything else float32."""
    x = _as_tensor(features, _float_dtype_of(features))
    _check_features(x, skeleton)
    j = skeleton.num_joints
    offsets = _target_offsets(skeleton, target_offsets, x)
    topo = _topology_of(skeleton, IKConvention.of(compat).chains_from_root)
    r_rot, root = _root_trajectory(x)
    local = cont6d_to_matrix(x[..., FeatureLayout(skeleton).slices["rot6d"]].unflatten(-1, (j - 1, 6)))  # (..., T, J-1, 3, 3)
    global_rot: list[Tensor | None] = [quat_to_matrix(torch.stack(r_rot, dim=-1))] + [None] * (j - 1)
    for level in topo.levels:  # a level needs only earlier levels: its joints go in one batched matmul
        refs = torch.stack([global_rot[topo.rotation_ref[i]] for i in level], dim=-3)
        rotated = refs @ local[..., [i - 1 for i in level], :, :]
        for k, i in enumerate(level):
            global_rot[i] = rotated[..., k, :, :]
    bones = (torch.stack(global_rot[1:], dim=-3) @ offsets[1:, :, None]).squeeze(-1)  # (..., T, J-1, 3)
    positions = _sum_bones_cf(root, bones.movedim(-1, 0).movedim(-1, 1), topo)  # (3, J, ..., T)
    return _like_input(positions.movedim(0, -1).movedim(0, -2).contiguous(), features)


def rigid_joints(joints: ArrayLike, skeleton: Skeleton, bone_lengths: ArrayLike | None = None) -> ArrayLike:
    """Joint positions (..., T, J, 3) fitted onto the skeleton with fixed bone lengths (numpy or torch like
    the input; float64 stays float64, anything else float32).

    Positions recovered from the ric block of generated features (``features_to_joints``) have bones whose
    length changes from frame to frame; a rig (BVH, a game engine) cannot play that. This is an
    inverse-kinematics fit onto the skeleton followed by forward kinematics: the root keeps its position,
    then, parents before children, each bone gets the rotation that turns its rest offset (the skeleton's
    rest direction times its length) towards the observed child *as seen from the parent already placed*,
    and FK puts the child at the end of that offset. As the offsets lie along the rest directions that
    rotation's result is just the unit aim direction times the bone length, which is what is computed.

    Aiming from the placed parent (not along the observed bone) puts every joint at the point nearest its
    observed position on the sphere the bone allows, so errors do not add up along a chain: on noisy
    features this brings the joints about 40% closer to the observed ones than keeping each bone's
    observed direction does (measured below). Where the aim has zero length the bone takes its rest direction.

    ``bone_lengths`` (J,) (root entry ignored): default ``skeleton.bone_lengths`` (the target skeleton every
    clip was retargeted to; a checkpoint's skeleton carries the dataset manifest's
    ``feature_spec.bone_lengths``); for a skeleton without them, each clip's median bone lengths over time.

    Distance to the ric positions it fits (mean / max over joints and frames; ``benchmarks/bench_rigid.py``),
    on HumanML3D clip 012314 (170 frames): clean features 0.0002 / 0.002 mm (its bones already have the
    target lengths); features + σ·Std·N(0, 1) noise (Std: the dataset's normalisation), where the ric bones'
    lengths vary by up to 63 / 122 / 235 mm over the clip for σ = 0.05 / 0.1 / 0.2: 6.8 / 36 mm,
    13.4 / 67 mm and 28.0 / 128 mm. Keeping each bone's observed direction instead gives 11.4 / 48,
    23.0 / 84 and 50.6 / 170 mm; the 6D-rotation decode ``features_to_joints_fk`` 19.3 / 79, 36.1 / 144 and
    72.0 / 295 mm.
    """
    x = _as_tensor(joints, _float_dtype_of(joints))
    if x.ndim < 3 or tuple(x.shape[-2:]) != (skeleton.num_joints, 3):
        raise ValueError(f"joints must be (..., T, {skeleton.num_joints}, 3) for skeleton {skeleton.name!r}, "
                         f"got shape {tuple(x.shape)}")
    if not _all_finite(x):
        raise ValueError("joints contain NaN or inf")
    topo = _topology_of(skeleton, chains_from_root=False)  # rotation_ref = parent: levels are tree depths
    parents = _joint_index(topo.parents, x).clamp(min=0)
    if bone_lengths is None and skeleton.bone_lengths is None:
        observed = torch.linalg.vector_norm(x - x.index_select(-2, parents), dim=-1)  # (..., T, J)
        lengths = torch.quantile(observed, 0.5, dim=-2, keepdim=True)[..., None]  # (..., 1, J, 1), numpy's median
    else:
        lengths = _as_tensor(skeleton.bone_lengths if bone_lengths is None else bone_lengths, x.dtype).to(x.device)
        if lengths.shape != (skeleton.num_joints,):
            raise ValueError(f"bone_lengths must be ({skeleton.num_joints},), got {tuple(lengths.shape)}")
        lengths = lengths[:, None]
    rest = torch.as_tensor(skeleton.raw_offsets, dtype=x.dtype, device=x.device)
    out = x.clone()  # the root stays where it was recovered; every other joint is overwritten below
    for level in topo.levels:  # a level's parents are all placed: its bones go in one batched step
        child = _joint_index(level, x)
        placed_parent = out.index_select(-2, parents[child])
        aim = x.index_select(-2, child) - placed_parent
        norm = torch.linalg.vector_norm(aim, dim=-1, keepdim=True)
        direction = torch.where(norm > 0, aim / norm.clamp(min=torch.finfo(x.dtype).tiny), rest[child])
        out[..., child, :] = placed_parent + direction * lengths[..., child, :]
    return _like_input(out, joints)


def features_to_joints_rigid(
    features: ArrayLike, skeleton: Skeleton, bone_lengths: ArrayLike | None = None
) -> ArrayLike:
    """``features_to_joints`` (recover_from_ric) fitted onto the skeleton with fixed bone lengths
    (:func:`rigid_joints`, which states the error against the ric positions): the decode for exports that
    need a rig (BVH)."""
    return rigid_joints(features_to_joints(features, skeleton), skeleton, bone_lengths)


# ---------------------------------------------------------------------------------------------------
# resampling


def resample_joints(joints: ArrayLike, src_fps: float, dst_fps: float) -> ArrayLike:
    """Linear interpolation in time (axis -3) from ``src_fps`` to ``dst_fps``: output frame k is at time
    k / dst_fps, for every such time within the input's span. An integer ratio picks every n-th frame
    exactly (like the reference's strided downsampling). Numpy or torch like the input."""
    if src_fps <= 0 or dst_fps <= 0:
        raise ValueError(f"frame rates must be positive, got src_fps={src_fps}, dst_fps={dst_fps}")
    x = _as_tensor(joints, _float_dtype_of(joints))
    if x.ndim < 3:
        raise ValueError(f"joints must be (..., T, J, 3), got shape {tuple(x.shape)}")
    t = x.shape[-3]
    if src_fps == dst_fps or t == 0:
        return _like_input(x.clone(), joints)
    ratio = float(src_fps) / float(dst_fps)
    count = int(np.floor((t - 1) / ratio + 1e-9)) + 1
    where = torch.arange(count, dtype=torch.float64) * ratio
    where = torch.where((where - where.round()).abs() < 1e-9, where.round(), where)  # exact on integer ratios
    lo = where.floor().long().clamp(max=t - 1)
    hi = (lo + 1).clamp(max=t - 1)
    w = (where - lo).to(x.dtype).to(x.device)[:, None, None]
    lo, hi = lo.to(x.device), hi.to(x.device)
    out = x[..., lo, :, :] * (1 - w) + x[..., hi, :, :] * w
    return _like_input(out, joints)


# ---------------------------------------------------------------------------------------------------
# normalisation statistics


class FeatureStats:
    """Streaming Mean/Std of feature frames, with HumanML3D's ``cal_mean_variance`` rule.

    Mean and Std are over all frames pooled (population std); then each of the 7 feature groups
    (``layout.slices``) gets its Std replaced by the mean of its per-dim stds.

    Per clip the frame sums and sums of squares are taken in float64 and then added into exact
    fixed-point integers (2**-80 resolution), so the result does not depend on the order of
    ``update`` and ``merge`` calls at all: any split of the same clips across workers, merged in any
    order, gives bit-identical Mean/Std. The variance is formed exactly from those integers
    (n*sum(x^2) - sum(x)^2), so there is no catastrophic cancellation beyond the float64 per-clip sums.
    """

    _FRACTION_BITS = 80

    def __init__(self) -> None:
        self.count = 0  # frames
        self.clips = 0
        self._sum: np.ndarray | None = None  # object arrays of Python ints, value * 2**_FRACTION_BITS
        self._sum_sq: np.ndarray | None = None

    @property
    def dim(self) -> int | None:
        return None if self._sum is None else len(self._sum)

    def _fixed(self, values: np.ndarray) -> np.ndarray:
        scaled = np.rint(np.ldexp(values, self._FRACTION_BITS))
        return np.array([int(v) for v in scaled], dtype=object)

    def _add(self, count: int, clips: int, sums: np.ndarray, sums_sq: np.ndarray) -> None:
        if self._sum is None:
            self._sum, self._sum_sq = sums.copy(), sums_sq.copy()
        elif len(sums) != len(self._sum):
            raise ValueError(f"feature dim {len(sums)} does not match the accumulated dim {len(self._sum)}")
        else:
            self._sum = self._sum + sums
            self._sum_sq = self._sum_sq + sums_sq
        self.count += count
        self.clips += clips

    def update(self, features: ArrayLike) -> None:
        """Add one clip's frames (T, D). Raises ValueError on NaN/inf (the reference skips such clips:
        the caller decides and reports)."""
        arr = features.detach().cpu().numpy() if isinstance(features, torch.Tensor) else np.asarray(features)
        arr = arr.astype(np.float64, copy=False)
        if arr.ndim != 2 or arr.shape[0] == 0:
            raise ValueError(f"features must be (T, D) with T > 0, got shape {arr.shape}")
        if not np.isfinite(arr).all():
            raise ValueError("features contain NaN or inf")
        self._add(arr.shape[0], 1, self._fixed(arr.sum(axis=0)), self._fixed((arr * arr).sum(axis=0)))

    def merge(self, other: "FeatureStats") -> "FeatureStats":
        """Add another accumulator's frames into this one (exact); returns self."""
        if other._sum is not None:
            self._add(other.count, other.clips, other._sum, other._sum_sq)
        return self

    def mean_std(self, layout: FeatureLayout) -> tuple[np.ndarray, np.ndarray]:
        """(mean, std) float32 (D,), std averaged within each feature group of ``layout``."""
        if self._sum is None or self.count == 0:
            raise ValueError("no frames accumulated")
        if layout.dim != self.dim:
            raise ValueError(f"layout has {layout.dim} dims but the statistics have {self.dim}")
        n, scale = self.count, 1 << self._FRACTION_BITS
        # Python int / int is correctly rounded, so these are the exact values rounded once to float64.
        mean = np.array([s / (n * scale) for s in self._sum], dtype=np.float64)
        var = np.array(
            [max(n * q * scale - s * s, 0) / (n * n * scale * scale) for s, q in zip(self._sum, self._sum_sq)],
            dtype=np.float64,
        )
        std = np.sqrt(var)
        for group in layout.slices.values():
            std[group] = std[group].mean()
        return mean.astype(np.float32), std.astype(np.float32)
