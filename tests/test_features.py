"""HumanML3D feature extraction (mfm.features, mfm.rotations): golden tests on the published clip 012314,
round trips, KIT, batching, the per-frame oracle, normalisation statistics and the rotation helpers."""

from __future__ import annotations

import dataclasses
import random
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from mfm import features as F
from mfm import rotations as R
from mfm.layout import FeatureLayout
from mfm.skeleton import HUMANML3D, KIT, Skeleton

sys.path.insert(0, str(Path(__file__).resolve().parent))
import per_frame_reference as oracle  # noqa: E402

CLIP = "012314"


# ---------------------------------------------------------------------------------------------------
# fixtures and helpers


@pytest.fixture
def published(reference_data: Path) -> tuple[np.ndarray, np.ndarray]:
    """(joints (170, 22, 3), features (170, 263)) of the real HumanML3D clip."""
    folder = reference_data / "humanml3d"
    return np.load(folder / f"new_joints_{CLIP}.npy"), np.load(folder / f"new_joint_vecs_{CLIP}.npy")


@pytest.fixture
def published_skeleton(published) -> Skeleton:
    """HumanML3D with the bone lengths measured on the published joints (those ARE the target skeleton;
    the preset's lengths are rounded to 0.1 mm)."""
    return HUMANML3D.with_bone_lengths_from(published[0])


def synthetic_clip(skeleton: Skeleton, lengths: np.ndarray, frames: int, seed: int, *, turn_per_frame: float = 0.02) -> np.ndarray:
    """A smooth random motion built by forward kinematics (scipy rotations, proper parent chaining):
    every joint swings about a random axis, the body turns at ``turn_per_frame`` rad/frame and walks
    forward, the pelvis at about one leg length above the lowest rest-pose joint."""
    rng = np.random.default_rng(seed)
    j = skeleton.num_joints
    parents = oracle.parents_of(skeleton)
    t = np.arange(frames)[:, None]
    axes = rng.normal(size=(j, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = 0.35 * np.sin(2 * np.pi * rng.uniform(0.01, 0.05, j) * t + rng.uniform(0, 2 * np.pi, j))
    local = Rotation.from_rotvec((angles[..., None] * axes).reshape(-1, 3)).as_matrix().reshape(frames, j, 3, 3)
    yaw = Rotation.from_rotvec(np.outer(turn_per_frame * np.arange(frames), [0.0, 1.0, 0.0])).as_matrix()
    local[:, 0] = yaw @ local[:, 0]
    offsets = skeleton.raw_offsets * lengths[:, None]
    leg = lengths[list(skeleton.leg_joints)].sum()
    step = np.einsum("tij,j->ti", yaw, [0.0, 0.0, 0.3 * leg / skeleton.fps])
    joints = np.zeros((frames, j, 3))
    joints[:, 0] = np.cumsum(step, axis=0) + [0.0, 2.2 * leg, 0.0]
    rotation = np.zeros((frames, j, 3, 3))
    rotation[:, 0] = local[:, 0]
    for child in range(1, j):  # joints are numbered parents first in both presets
        parent = parents[child]
        rotation[:, child] = rotation[:, parent] @ local[:, child]
        joints[:, child] = joints[:, parent] + np.einsum("tij,j->ti", rotation[:, parent], offsets[child])
    return joints


def kit_skeleton_and_clip(frames: int = 60) -> tuple[Skeleton, np.ndarray]:
    """KIT target skeleton measured on one synthetic clip (mm), and a clip of a differently sized body."""
    rng = np.random.default_rng(7)
    reference_lengths = np.r_[0.0, rng.uniform(60.0, 450.0, KIT.num_joints - 1)]
    reference_clip = synthetic_clip(KIT, reference_lengths, 2, seed=1)
    skeleton = KIT.with_bone_lengths_from(reference_clip)
    source_lengths = reference_lengths * rng.uniform(0.8, 1.25, KIT.num_joints)
    return skeleton, synthetic_clip(KIT, source_lengths, frames, seed=2)


def max_abs(a, b) -> float:
    return float(np.abs(np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)).max())


# ---------------------------------------------------------------------------------------------------
# golden tests on the published clip


def test_recover_from_ric_reproduces_published_joints(published):
    joints, features = published
    assert max_abs(F.features_to_joints(features, HUMANML3D), joints) < 1e-5


def test_recover_from_rot_reproduces_published_joints(published, published_skeleton):
    joints, features = published
    assert max_abs(F.features_to_joints_fk(features, published_skeleton), joints) < 5e-5
    # The preset's bone lengths (rounded to 0.1 mm) are within a few tenths of a millimetre.
    assert max_abs(F.features_to_joints_fk(features, HUMANML3D), joints) < 3e-4


# Deviations of the reference's own output on these joints (float32 arithmetic), plus ~5 % headroom.
PUBLISHED_TOLERANCE = {
    "root_rot_vel": 3.2e-4,
    "root_lin_vel": 1.45e-4,
    "root_height": 4e-7,
    "ric": 7.1e-3,
    "rot6d": 1.4e-2,
    "local_vel": 4.4e-4,
    "contacts": 0.0,
}


def test_reextraction_matches_published_features(published, published_skeleton):
    joints, features = published
    ours = F.joints_to_features(joints, published_skeleton)
    expected = features[: len(joints) - 1]  # joints has 170 frames -> 169 feature frames
    assert ours.shape == expected.shape == (169, 263) and ours.dtype == np.float32
    layout = FeatureLayout(HUMANML3D).slices
    for name, tolerance in PUBLISHED_TOLERANCE.items():
        assert max_abs(ours[:, layout[name]], expected[:, layout[name]]) <= tolerance, name
    for name, mean_tolerance in (("ric", 1.6e-4), ("rot6d", 1.06e-4)):
        assert np.abs(ours[:, layout[name]] - expected[:, layout[name]]).mean() <= mean_tolerance, name


@pytest.mark.parametrize("quirk", ["swap_face_hips", "chains_from_root", "identity_first_frame"])
def test_every_reference_quirk_is_needed_to_match(published, published_skeleton, quirk):
    """The empirical finding behind compat=True: turning off any one quirk breaks the match."""
    joints, features = published
    convention = dataclasses.replace(F.REFERENCE_IK, **{quirk: False})
    ours = F.joints_to_features(joints, published_skeleton, compat=convention)
    assert max_abs(ours, features[:169]) > 0.1


def test_fixed_ik_differs_from_published_only_in_rotation_dependent_groups(published, published_skeleton):
    joints, features = published
    fixed = F.joints_to_features(joints, published_skeleton, compat=False)
    layout = FeatureLayout(HUMANML3D).slices
    assert max_abs(fixed[:, layout["root_height"]], features[:169, layout["root_height"]]) < 4e-7
    assert np.array_equal(fixed[:, layout["contacts"]], features[:169, layout["contacts"]])
    assert max_abs(fixed[:, layout["rot6d"]], features[:169, layout["rot6d"]]) > 0.1


# ---------------------------------------------------------------------------------------------------
# canonical positions and round trips


@pytest.mark.parametrize("compat", [True, False])
def test_round_trip_real_clip(published, compat):
    joints, _ = published
    canonical = F.canonical_joints(joints, HUMANML3D)
    features = F.joints_to_features(joints, HUMANML3D, compat=compat)
    assert max_abs(F.features_to_joints(features, HUMANML3D), canonical[:-1]) < 1e-5
    assert max_abs(F.features_to_joints_fk(features, HUMANML3D, compat=compat), canonical[:-1]) < 1e-5


@pytest.mark.parametrize("compat", [True, False])
def test_round_trip_retargets_a_different_body(compat):
    source_lengths = HUMANML3D.bone_lengths * np.random.default_rng(3).uniform(0.85, 1.2, HUMANML3D.num_joints)
    clip = synthetic_clip(HUMANML3D, source_lengths, 90, seed=4)
    canonical = F.canonical_joints(clip, HUMANML3D)
    features = F.joints_to_features(clip, HUMANML3D, compat=compat)
    assert max_abs(F.features_to_joints(features, HUMANML3D), canonical[:-1]) < 1e-5
    assert max_abs(F.features_to_joints_fk(features, HUMANML3D, compat=compat), canonical[:-1]) < 1e-5


def test_canonical_joints_are_retargeted_floored_centred_and_facing_z():
    clip = synthetic_clip(HUMANML3D, HUMANML3D.bone_lengths * 1.1, 40, seed=5)
    canonical = F.canonical_joints(clip, HUMANML3D).astype(np.float64)
    parents = oracle.parents_of(HUMANML3D)
    lengths = np.linalg.norm(canonical[:, 1:] - canonical[:, parents[1:]], axis=-1)
    assert np.allclose(lengths, HUMANML3D.bone_lengths[1:], atol=1e-6)
    assert abs(canonical[..., 1].min()) < 1e-6
    assert np.allclose(canonical[0, 0, [0, 2]], 0.0, atol=1e-6)
    r_hip, l_hip, r_sdr, l_sdr = HUMANML3D.face_joints
    across = canonical[0, r_hip] - canonical[0, l_hip] + canonical[0, r_sdr] - canonical[0, l_sdr]
    forward = np.cross([0.0, 1.0, 0.0], across)
    assert np.allclose(forward / np.linalg.norm(forward), [0.0, 0.0, 1.0], atol=1e-6)
    # A body 1.1x larger everywhere (bones, root height, stride) is scaled back exactly: the root by the
    # leg-length ratio, the bones to the target lengths.
    same_body = F.canonical_joints(synthetic_clip(HUMANML3D, HUMANML3D.bone_lengths, 40, seed=5), HUMANML3D)
    assert max_abs(canonical, same_body) < 1e-6


def test_root_angular_velocity_has_no_sign_flip_when_turning_past_180_degrees():
    """qfix on the root rotation (the reference skips it and flips the sign on the crossing frame)."""
    clip = synthetic_clip(HUMANML3D, HUMANML3D.bone_lengths, 200, seed=6, turn_per_frame=0.05)  # 10 rad
    rot_vel = F.joints_to_features(clip, HUMANML3D, compat=False)[:, 0]
    assert (rot_vel > 0).all() or (rot_vel < 0).all()
    assert np.isclose(np.abs(rot_vel[30:-30]).mean(), 0.025, atol=0.004)  # half-angle per frame


# ---------------------------------------------------------------------------------------------------
# rigid decode: ric positions fitted onto fixed bone lengths


def bone_lengths_of(joints, skeleton: Skeleton = HUMANML3D) -> np.ndarray:
    """(..., T, J, 3) -> (..., T, J-1) lengths of the bones ending at joints 1..J-1."""
    return np.linalg.norm(joints[..., 1:, :] - joints[..., skeleton.parents[1:], :], axis=-1)


@pytest.fixture
def noisy_features(published, reference_data) -> np.ndarray:
    """The published features + 0.1 * Std of Gaussian noise: what an imperfect generator gives."""
    std = np.load(reference_data / "humanml3d" / "Std.npy").astype(np.float64)
    features = published[1].astype(np.float64)
    return features + 0.1 * std * np.random.default_rng(0).standard_normal(features.shape)


def test_rigid_decode_of_clean_features_is_the_ric_decode(published):
    features = published[1]
    ric, rigid = F.features_to_joints(features, HUMANML3D), F.features_to_joints_rigid(features, HUMANML3D)
    lengths = bone_lengths_of(rigid)
    assert (lengths.max(axis=0) - lengths.min(axis=0)).max() < 1e-6  # float32 noise
    assert np.abs(lengths - HUMANML3D.bone_lengths[1:]).max() < 1e-6
    assert np.linalg.norm(rigid - ric, axis=-1).max() < 1e-5  # the preset's lengths are rounded to 1e-6 m


def test_rigid_decode_of_noisy_features_keeps_the_skeleton_exactly(noisy_features):
    ric = F.features_to_joints(noisy_features, HUMANML3D)
    rigid = F.features_to_joints_rigid(noisy_features, HUMANML3D)
    ric_lengths = bone_lengths_of(ric)
    assert (ric_lengths.max(axis=0) - ric_lengths.min(axis=0)).max() > 0.05  # ric bones stretch by centimetres
    np.testing.assert_allclose(bone_lengths_of(rigid), np.broadcast_to(HUMANML3D.bone_lengths[1:], ric_lengths.shape),
                               rtol=0, atol=1e-12)
    np.testing.assert_array_equal(rigid[:, 0], ric[:, 0])  # the root stays where it was recovered
    distance = np.linalg.norm(rigid - ric, axis=-1)
    assert distance.mean() < 0.02 and distance.max() < 0.1  # rigid_joints' docstring: about 13 / 67 mm at this noise
    # Every joint lies where its bone, aimed from the placed parent at the ric joint, ends: the nearest point
    # to the ric joint the fixed bone allows.
    parents = HUMANML3D.parents[1:]
    aim = ric[:, 1:] - rigid[:, parents]
    expected = rigid[:, parents] + aim / np.linalg.norm(aim, axis=-1, keepdims=True) * HUMANML3D.bone_lengths[1:, None]
    np.testing.assert_allclose(rigid[:, 1:], expected, atol=1e-12)


def test_rigid_decode_batches_takes_torch_and_other_bone_lengths(published, noisy_features):
    batch = np.stack([noisy_features, published[1].astype(np.float64)])
    rigid = F.features_to_joints_rigid(torch.from_numpy(batch), HUMANML3D)
    assert isinstance(rigid, torch.Tensor) and rigid.dtype == torch.float64
    for clip, features in zip(rigid.numpy(), batch):
        np.testing.assert_allclose(clip, F.features_to_joints_rigid(features, HUMANML3D), atol=1e-12)
    assert F.features_to_joints_rigid(published[1], HUMANML3D).dtype == np.float32

    doubled = 2.0 * HUMANML3D.bone_lengths
    lengths = bone_lengths_of(F.features_to_joints_rigid(noisy_features, HUMANML3D, bone_lengths=doubled))
    np.testing.assert_allclose(lengths, np.broadcast_to(doubled[1:], lengths.shape), atol=1e-12)
    # A skeleton without target lengths keeps each clip's median bone lengths.
    unknown = dataclasses.replace(HUMANML3D, bone_lengths=None)
    ric = F.features_to_joints(batch, HUMANML3D)
    lengths = bone_lengths_of(F.rigid_joints(ric, unknown))
    np.testing.assert_allclose(lengths, np.broadcast_to(np.median(bone_lengths_of(ric), axis=1)[:, None],
                                                        lengths.shape), atol=1e-12)
    with pytest.raises(ValueError, match="bone_lengths must be"):
        F.rigid_joints(ric, HUMANML3D, bone_lengths=np.ones(3))
    with pytest.raises(ValueError, match="joints must be"):
        F.rigid_joints(ric[..., :3, :], HUMANML3D)


# ---------------------------------------------------------------------------------------------------
# KIT


def test_kit_synthetic_clip_has_251_dims_and_round_trips():
    skeleton, clip = kit_skeleton_and_clip()
    features = F.joints_to_features(clip, skeleton)
    assert features.shape == (len(clip) - 1, 251)
    canonical = F.canonical_joints(clip, skeleton)
    assert max_abs(F.features_to_joints(features, skeleton), canonical[:-1]) < 1e-2  # mm
    assert max_abs(F.features_to_joints_fk(features, skeleton), canonical[:-1]) < 1e-2


def test_kit_matches_the_per_frame_oracle():
    skeleton, clip = kit_skeleton_and_clip(frames=30)
    ours = F.joints_to_features(clip, skeleton)
    reference = oracle.joints_to_features(clip, skeleton)
    assert max_abs(ours, reference) < 1e-3  # mm-scale values: float32 output is ~1e-4 mm


def test_kit_without_target_lengths_says_what_to_do():
    with pytest.raises(ValueError, match="03950_gt"):
        F.joints_to_features(np.zeros((4, 21, 3)) + np.arange(21)[:, None], KIT)


# ---------------------------------------------------------------------------------------------------
# batching, array types


def test_batch_equals_per_clip_and_numpy_equals_torch(published):
    joints, _ = published
    rng = np.random.default_rng(8)
    batch = joints[None, :60].astype(np.float64) + rng.normal(0.0, 0.01, (3, 60, 22, 3))
    batched = F.joints_to_features(batch, HUMANML3D)
    assert batched.shape == (3, 59, 263)
    for i in range(3):
        assert np.array_equal(batched[i], F.joints_to_features(batch[i], HUMANML3D))
    as_torch = F.joints_to_features(torch.from_numpy(batch), HUMANML3D)
    assert isinstance(as_torch, torch.Tensor) and as_torch.dtype == torch.float32
    assert np.array_equal(as_torch.numpy(), batched)
    recovered = F.features_to_joints(torch.from_numpy(batched), HUMANML3D)
    assert isinstance(recovered, torch.Tensor) and recovered.shape == (3, 59, 22, 3)
    assert np.allclose(recovered.numpy(), F.features_to_joints(batched, HUMANML3D))
    fk = F.features_to_joints_fk(torch.from_numpy(batched), HUMANML3D)
    for i in range(3):
        assert np.allclose(fk[i].numpy(), F.features_to_joints_fk(batched[i], HUMANML3D), atol=1e-6)


def test_chunked_processing_gives_the_same_features(published, monkeypatch):
    joints, _ = published
    batch = np.stack([joints[:50], joints[50:100], joints[100:150]])
    whole = F.joints_to_features(batch, HUMANML3D)
    monkeypatch.setattr(F, "_CHUNK_ELEMENTS", 1)  # one clip per chunk
    assert np.array_equal(F.joints_to_features(batch, HUMANML3D), whole)


# ---------------------------------------------------------------------------------------------------
# the per-frame oracle


@pytest.mark.parametrize("compat", [True, False])
def test_vectorised_matches_per_frame_oracle(published, compat):
    joints = published[0][:48]
    assert max_abs(F.joints_to_features(joints, HUMANML3D, compat=compat), oracle.joints_to_features(joints, HUMANML3D, compat=compat)) < 1e-6


def test_vectorised_matches_oracle_with_offsets_off_the_rest_directions(published):
    """Target offsets not parallel to the raw offsets take the general (rotation) retargeting path."""
    joints = published[0][:40]
    offsets = HUMANML3D.target_offsets() + np.random.default_rng(9).normal(0.0, 0.02, (22, 3)) * (np.arange(22) > 0)[:, None]
    ours = F.joints_to_features(joints, HUMANML3D, target_offsets=offsets)
    assert max_abs(ours, oracle.joints_to_features(joints, HUMANML3D, target_offsets=offsets)) < 1e-6
    canonical = F.canonical_joints(joints, HUMANML3D, target_offsets=offsets)
    assert max_abs(canonical, oracle.canonical_positions(joints, HUMANML3D, offsets)) < 1e-6


@pytest.mark.parametrize("compat", [True, False])
def test_recovery_matches_per_frame_oracle(published, compat):
    features = F.joints_to_features(published[0][:60], HUMANML3D, compat=compat).astype(np.float64)
    assert max_abs(F.features_to_joints(features, HUMANML3D), oracle.features_to_joints(features, HUMANML3D)) < 1e-9
    ours = F.features_to_joints_fk(features, HUMANML3D, compat=compat)
    assert max_abs(ours, oracle.features_to_joints_fk(features, HUMANML3D, compat=compat)) < 1e-9


# ---------------------------------------------------------------------------------------------------
# input errors


def test_bad_inputs_raise_clear_errors(published):
    joints = published[0][:10]
    with pytest.raises(ValueError, match="22, 3"):
        F.joints_to_features(joints[:, :21], HUMANML3D)
    with pytest.raises(ValueError, match="at least 2 frames"):
        F.joints_to_features(joints[:1], HUMANML3D)
    broken = joints.copy()
    broken[3, 5, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        F.joints_to_features(broken, HUMANML3D)
    collapsed = joints.copy()
    collapsed[:, 4] = collapsed[:, 1]  # knee on the hip
    with pytest.raises(ValueError, match="zero-length bone.*4"):
        F.joints_to_features(collapsed, HUMANML3D)
    with pytest.raises(ValueError, match="263"):
        F.features_to_joints(np.zeros((5, 251)), HUMANML3D)


# ---------------------------------------------------------------------------------------------------
# smoothing and resampling


@pytest.mark.parametrize("frames", [7, 170, 600])  # shorter than the kernel radius, one block, several blocks
def test_gaussian_smoothing_matches_scipy(frames):
    signal = np.cumsum(np.random.default_rng(frames).normal(size=(3, frames)), axis=1)
    ours = F._gaussian_smooth_last(torch.from_numpy(signal), 20.0).numpy()
    assert max_abs(ours, gaussian_filter1d(signal, 20, axis=-1, mode="nearest")) < 1e-10


def test_resample_joints(published):
    joints = published[0].astype(np.float64)
    assert np.array_equal(F.resample_joints(joints, 60, 20), joints[::3])
    assert np.array_equal(F.resample_joints(joints, 20, 20), joints)
    down = F.resample_joints(joints, 30, 20)  # output frame k at source frame 1.5k
    assert down.shape[0] == int((len(joints) - 1) / 1.5) + 1
    assert np.allclose(down[1], (joints[1] + joints[2]) / 2)
    up = F.resample_joints(torch.from_numpy(joints), 20, 40)
    assert isinstance(up, torch.Tensor) and up.shape[0] == 2 * len(joints) - 1
    assert np.allclose(up[1].numpy(), (joints[0] + joints[1]) / 2)
    with pytest.raises(ValueError, match="positive"):
        F.resample_joints(joints, 0, 20)


# ---------------------------------------------------------------------------------------------------
# normalisation statistics


def random_feature_clips(count: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [
        (rng.normal(size=(int(rng.integers(20, 80)), 263)) * rng.uniform(0.01, 2.0, 263) + rng.uniform(-1, 1, 263)).astype(np.float32)
        for _ in range(count)
    ]


def test_feature_stats_follow_cal_mean_variance():
    clips = random_feature_clips(5, seed=10)
    stats = F.FeatureStats()
    for clip in clips:
        stats.update(clip)
    layout = FeatureLayout(HUMANML3D)
    mean, std = stats.mean_std(layout)
    pooled = np.concatenate(clips).astype(np.float64)
    expected_std = pooled.std(axis=0)
    for group in layout.slices.values():
        expected_std[group] = expected_std[group].mean()
    assert mean.dtype == std.dtype == np.float32 and stats.count == len(pooled) and stats.clips == 5
    assert np.allclose(mean, pooled.mean(axis=0), rtol=1e-6, atol=1e-7)
    assert np.allclose(std, expected_std, rtol=1e-6)
    for group in layout.slices.values():
        assert np.all(std[group] == std[group][0])


def test_feature_stats_merge_is_exactly_order_independent():
    clips = random_feature_clips(8, seed=11)
    layout = FeatureLayout(HUMANML3D)
    sequential = F.FeatureStats()
    for clip in clips:
        sequential.update(clip)
    shuffled = clips[:]
    random.Random(0).shuffle(shuffled)
    parts = [F.FeatureStats() for _ in range(3)]
    for i, clip in enumerate(shuffled):
        parts[i % 3].update(clip)
    merged = F.FeatureStats().merge(parts[2]).merge(parts[0]).merge(parts[1])
    for a, b in zip(sequential.mean_std(layout), merged.mean_std(layout)):
        assert np.array_equal(a, b)


def test_feature_stats_reject_bad_input():
    stats = F.FeatureStats()
    with pytest.raises(ValueError, match="no frames"):
        stats.mean_std(FeatureLayout(HUMANML3D))
    with pytest.raises(ValueError, match="NaN"):
        stats.update(np.full((3, 263), np.nan))
    stats.update(np.zeros((3, 263)))
    with pytest.raises(ValueError, match="dim"):
        stats.update(np.zeros((3, 251)))
    with pytest.raises(ValueError, match="251"):
        stats.mean_std(FeatureLayout(KIT))


# ---------------------------------------------------------------------------------------------------
# rotation helpers


def random_quats(n: int, seed: int) -> torch.Tensor:
    return R.qnormalize(torch.from_numpy(np.random.default_rng(seed).normal(size=(n, 4))))


def test_quaternion_algebra_matches_matrices():
    q, r = random_quats(50, 1), random_quats(50, 2)
    v = torch.from_numpy(np.random.default_rng(3).normal(size=(50, 3)))
    mq, mr = R.quat_to_matrix(q), R.quat_to_matrix(r)
    assert torch.allclose(R.quat_to_matrix(R.qmul(q, r)), mq @ mr)
    assert torch.allclose(R.qrot(q, v), (mq @ v[..., None])[..., 0])
    assert torch.allclose(R.qrot(R.qmul(R.qinv(q), q), v), v)
    scipy_matrix = Rotation.from_quat(q[:, [1, 2, 3, 0]].numpy()).as_matrix()
    assert np.allclose(mq.numpy(), scipy_matrix)
    back = R.matrix_to_quat(mq)
    assert torch.allclose(back, q * torch.sign(q[:, :1]))
    assert torch.allclose(R.quat_to_cont6d(q), torch.cat((mq[..., 0], mq[..., 1]), dim=-1))
    assert torch.allclose(R.cont6d_to_matrix(R.quat_to_cont6d(q)), mq)


def test_component_layouts_and_tuples_agree():
    q, r = random_quats(24, 4), random_quats(24, 5)
    v = torch.from_numpy(np.random.default_rng(6).normal(size=(24, 3)))
    as_tuple = R.qrot(R.qmul(tuple(q.unbind(-1)), tuple(r.unbind(-1))), tuple(v.unbind(-1)))
    assert torch.allclose(torch.stack(as_tuple, -1), R.qrot(R.qmul(q, r), v))
    first = R.qrot(R.qmul(q.T.contiguous(), r.T.contiguous(), dim=0), v.T.contiguous(), dim=0)
    assert torch.allclose(first.T, R.qrot(R.qmul(q, r), v))
    y_only = R.quat_about_y(torch.linspace(-3, 3, 24, dtype=torch.float64))
    assert torch.allclose(R.rotate_about_y(y_only, v), R.qrot(y_only, v))


def test_qbetween_including_opposite_vectors():
    v0 = torch.tensor([[1.0, 0, 0], [0, 2.0, 0], [0.3, -0.2, 0.9], [0, 0, 1.0]], dtype=torch.float64)
    v1 = torch.tensor([[0, 1.0, 0], [0, -1.0, 0], [1.0, 1.0, 1.0], [0, 0, 5.0]], dtype=torch.float64)
    q = R.qbetween(v0, v1)
    rotated = R.qrot(q, v0)
    assert torch.allclose(rotated / rotated.norm(dim=-1, keepdim=True), v1 / v1.norm(dim=-1, keepdim=True))
    assert torch.allclose(q.norm(dim=-1), torch.ones(4, dtype=torch.float64))
    assert torch.isnan(R.qbetween(torch.zeros(3), torch.ones(3))).all()


def test_qfix_makes_signs_continuous_without_changing_rotations():
    angles = torch.linspace(0, 12, 60, dtype=torch.float64)
    q = R.quat_about_y(angles)[:, None, :].repeat(1, 2, 1)  # (T, J, 4), crosses w = 0 twice
    q = q * torch.where(q[..., :1] < 0, -1.0, 1.0)  # canonical w >= 0, as qbetween gives
    fixed = R.qfix(q, time_dim=0)
    assert ((fixed[1:] * fixed[:-1]).sum(-1) > 0).all()
    assert torch.allclose(R.quat_to_matrix(fixed), R.quat_to_matrix(q))
    as_tuple = R.qfix(tuple(q.movedim(-1, 0)), time_dim=0)
    assert torch.allclose(torch.stack(as_tuple, -1), fixed)


def test_axis_angle_to_matrix_matches_scipy_including_tiny_angles():
    rng = np.random.default_rng(12)
    vectors = np.concatenate([rng.normal(size=(20, 3)), rng.normal(size=(5, 3)) * 1e-7, np.zeros((1, 3))])
    ours = R.axis_angle_to_matrix(torch.from_numpy(vectors)).numpy()
    assert np.allclose(ours, Rotation.from_rotvec(vectors).as_matrix(), atol=1e-12)
