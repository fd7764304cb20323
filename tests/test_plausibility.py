"""Plausibility figures of mfm.metrics (bone lengths, floor, foot skating, jerk) against hand-made joints whose
answers are known by construction, not recomputed the way the code does."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from mfm import metrics
from mfm.features import features_to_joints
from mfm.skeleton import HUMANML3D

FPS = HUMANML3D.fps
FEET = HUMANML3D.foot_left + HUMANML3D.foot_right  # ankles 7, 8 and toes 10, 11
NUM_BONES = HUMANML3D.num_joints - 1


def rest_pose(foot_height: float = 0.0) -> np.ndarray:
    """(J, 3) HumanML3D's target skeleton in its rest pose, its lowest foot joint at ``foot_height`` (the four foot
    joints lie within 1.1 cm of each other in height)."""
    offsets, parents = HUMANML3D.target_offsets(), HUMANML3D.parents
    pose = np.zeros((HUMANML3D.num_joints, 3))
    for joint in range(1, HUMANML3D.num_joints):
        assert parents[joint] < joint  # a parent is placed before its children
        pose[joint] = pose[parents[joint]] + offsets[joint]
    assert np.ptp(pose[list(FEET), 1]) < 0.011
    pose[:, 1] += foot_height - pose[list(FEET), 1].min()
    return pose


def standing(frames: int, foot_height: float = 0.0) -> np.ndarray:
    return np.repeat(rest_pose(foot_height)[None], frames, axis=0)


def sliding(frames: int, speed: float, foot_height: float) -> np.ndarray:
    """The rest pose gliding along +x at ``speed`` m/s (no stepping: every foot joint moves with the body)."""
    clip = standing(frames, foot_height)
    clip[..., 0] += (speed / FPS) * np.arange(frames)[:, None]
    return clip


def rigidly_moved(clip: np.ndarray, seed: int) -> np.ndarray:
    """(T, J, 3) ``clip`` under an arbitrary rigid motion: a different rotation and translation every frame."""
    rotations = Rotation.random(len(clip), random_state=seed).as_matrix()  # (T, 3, 3)
    shifts = np.random.default_rng(seed).normal(size=(len(clip), 1, 3))
    return np.einsum("tij,tkj->tki", rotations, clip) + shifts


def tumbling(frames: int, seed: int = 0) -> np.ndarray:
    """The rest pose tumbling rigidly through space."""
    return rigidly_moved(standing(frames), seed)


# ------------------------------------------------------------------------------------------------ bone lengths


def test_a_rigid_skeleton_keeps_its_bone_lengths_however_it_moves():
    spread, deviation = metrics.bone_length_consistency(tumbling(30), HUMANML3D.parents)
    assert spread.shape == deviation.shape == (1,)
    assert spread[0] == pytest.approx(0.0, abs=1e-12) and deviation[0] == pytest.approx(0.0, abs=1e-12)
    lengths = metrics.bone_lengths(tumbling(5), HUMANML3D.parents)[0]
    np.testing.assert_allclose(lengths, np.broadcast_to(HUMANML3D.bone_lengths[1:], (5, NUM_BONES)), atol=1e-12)


def test_a_stretched_bone_gives_its_stretch_and_relative_deviation():
    frames, stretch, ankle, toe = 10, 0.03, 7, 10  # left shin (knee 4 -> ankle 7) longer by 3 cm on frame 4
    clip = standing(frames)
    shin = clip[4, ankle] - clip[4, 4]
    clip[4, [ankle, toe]] += stretch * shin / np.linalg.norm(shin)  # the toe follows: its own bone is unchanged
    moved = rigidly_moved(clip, seed=1)  # a rigid motion on top changes nothing

    spread, deviation = metrics.bone_length_consistency(moved, HUMANML3D.parents)
    assert spread[0] == pytest.approx(stretch, abs=1e-12)
    # One bone of rest length L: mean m = L + s/T; |len − m| is s/T on T − 1 frames and s(T − 1)/T on one.
    rest = HUMANML3D.bone_lengths[ankle]
    mean = rest + stretch / frames
    per_frame = ((frames - 1) * stretch / frames + stretch * (frames - 1) / frames) / frames / mean
    assert deviation[0] == pytest.approx(per_frame / NUM_BONES, rel=1e-9)  # the other bones deviate by 0


# ------------------------------------------------------------------------------------------------ the floor


def test_a_clip_lowered_by_ten_centimetres_penetrates_the_floor_by_ten_centimetres():
    clip = standing(12)
    clip[5:, :, 1] -= 0.10  # from frame 5 on, the whole body sinks 10 cm
    assert metrics.floor_penetration(clip, FEET)[0] == pytest.approx(0.10, abs=1e-12)
    assert metrics.floor_penetration(standing(12, foot_height=0.2), FEET)[0] == 0.0  # above the floor: none
    # only the foot joints count: a hand below the floor (a push-up) is no penetration
    push_up = standing(4)
    push_up[:, 20, 1] = -0.3
    assert metrics.floor_penetration(push_up, FEET)[0] == 0.0


# ------------------------------------------------------------------------------------------------ foot skating


@pytest.mark.parametrize("speed", [1.2, 0.8])
def test_feet_sliding_on_the_floor_skate_at_the_sliding_speed(speed):
    skating = metrics.foot_skating(sliding(16, speed, foot_height=0.01), FEET, FPS)
    assert skating.ratio[0] == 1.0
    assert skating.contact_speed[0] == pytest.approx(speed, rel=1e-9)
    assert skating.skating_speed[0] == pytest.approx(speed, rel=1e-9)
    one_frame = metrics.foot_skating(sliding(1, speed, foot_height=0.01), FEET, FPS)  # no frame pair: undefined
    assert np.isnan([one_frame.ratio, one_frame.contact_speed, one_frame.skating_speed]).all()


def test_slow_sliding_is_contact_without_skating_and_lifted_feet_never_skate():
    slow = metrics.foot_skating(sliding(16, 0.3, foot_height=0.0), FEET, FPS)  # below 0.5 m/s
    assert slow.ratio[0] == 0.0 and slow.skating_speed[0] == 0.0
    assert slow.contact_speed[0] == pytest.approx(0.3, rel=1e-9)
    lifted = metrics.foot_skating(sliding(16, 1.2, foot_height=0.06), FEET, FPS)  # above the 5 cm contact height
    assert lifted.ratio[0] == 0.0 and lifted.skating_speed[0] == 0.0 and np.isnan(lifted.contact_speed[0])
    # the thresholds are parameters: a 10 cm contact height makes the lifted feet touch, 2 m/s stops the skating
    assert metrics.foot_skating(sliding(16, 1.2, 0.06), FEET, FPS, contact_height=0.1).ratio[0] == 1.0
    assert metrics.foot_skating(sliding(16, 1.2, 0.0), FEET, FPS, skating_speed=2.0).ratio[0] == 0.0


def test_one_foot_skating_for_part_of_the_clip():
    frames, left_toe = 11, 10  # 10 frame pairs; the left toe slides at 1 m/s during the first 4 of them
    clip = standing(frames, foot_height=0.02)
    clip[:, left_toe, 2] += (1.0 / FPS) * np.minimum(np.arange(frames), 4)  # 5 cm per frame, then it stops
    skating = metrics.foot_skating(clip, FEET, FPS)
    assert skating.ratio[0] == pytest.approx(4 / 10)
    assert skating.skating_speed[0] == pytest.approx(1.0, rel=1e-9)
    # 4 feet × 10 pairs in contact; only 4 joint-pairs move, at 1 m/s
    assert skating.contact_speed[0] == pytest.approx(4 * 1.0 / 40, rel=1e-9)


# ------------------------------------------------------------------------------------------------ jerk


def test_mean_jerk_of_a_cubic_path_is_its_constant_third_difference():
    frames, a = 20, 0.002
    clip = standing(frames)
    clip[..., 0] += a * np.arange(frames)[:, None] ** 3  # x = a·t³: third difference 6a on every frame and joint
    assert metrics.mean_jerk(clip)[0] == pytest.approx(6 * a, rel=1e-9)
    assert np.isnan(metrics.mean_jerk(clip[:3])[0])  # fewer than 4 frames: no jerk


def test_jerk_ratio_is_one_against_itself_and_above_one_with_high_frequency_noise():
    frames = 40
    clip = standing(frames)
    clip[..., 0] += 0.5 * np.sin(2 * np.pi * np.arange(frames) / 40)[:, None]  # a smooth sway
    assert metrics.jerk_ratio(clip, clip)[0] == pytest.approx(1.0, rel=1e-12)
    noisy = clip.copy()
    noisy[..., 1] += 0.005 * (-1.0) ** np.arange(frames)[:, None]  # ±5 mm every other frame
    ratio = metrics.jerk_ratio(noisy, clip)[0]
    # The alternating term alone has a third difference of 8 · 5 mm = 4 cm on every frame; the sway's is < 2 mm.
    assert ratio > 1.0
    assert metrics.mean_jerk(noisy)[0] == pytest.approx(0.04 + metrics.mean_jerk(clip)[0], rel=0.05)
    assert np.isnan(metrics.jerk_ratio(clip, standing(frames))[0])  # a still ground truth has no jerk to compare
    with pytest.raises(ValueError, match="reference jerks"):
        metrics.jerk_ratio(clip, np.stack([clip, clip]))


# ------------------------------------------------------------------------------------------------ motion amount


def test_a_gliding_body_travels_at_its_speed_without_moving_its_pose():
    amount = metrics.motion_amount(sliding(16, 1.2, foot_height=0.0), FPS)
    assert amount.root_speed[0] == pytest.approx(1.2, rel=1e-9)
    assert amount.pose_speed[0] == pytest.approx(0.0, abs=1e-12)
    assert amount.pose_spread[0] == pytest.approx(0.0, abs=1e-12)
    frozen = metrics.motion_amount(standing(16), FPS)  # what a collapsed generator draws: no speed at all
    assert frozen.root_speed[0] == 0.0 and frozen.pose_speed[0] == 0.0
    assert frozen.pose_spread[0] == pytest.approx(0.0, abs=1e-12)
    assert np.isnan(metrics.motion_amount(standing(1), FPS).pose_speed[0])  # one frame: no frame pair


def test_a_swinging_arm_gives_its_tip_speeds_averaged_over_the_joints():
    frames, omega = 21, 2.0  # rad/s: the right shoulder's children rotate about the shoulder in the xy plane
    shoulder, arm = 17, (19, 21)  # right shoulder -> elbow 19 -> wrist 21
    clip = standing(frames)
    offsets = clip[0, list(arm)] - clip[0, shoulder]
    radii = np.linalg.norm(offsets[:, :2], axis=1)
    for f in range(frames):
        rotation = Rotation.from_euler("z", omega * f / FPS).as_matrix()
        clip[f, list(arm)] = clip[f, shoulder] + offsets @ rotation.T
    amount = metrics.motion_amount(clip, FPS)
    # each moving joint covers a chord of its circle per frame: 2 r sin(ω / 2 fps) · fps; the other joints stay put
    chord_speed = 2 * radii * np.sin(omega / FPS / 2) * FPS
    assert amount.pose_speed[0] == pytest.approx(chord_speed.sum() / HUMANML3D.num_joints, rel=1e-9)
    assert amount.root_speed[0] == 0.0
    walking = clip.copy()
    walking[..., 2] += (0.8 / FPS) * np.arange(frames)[:, None]  # the whole body carried along +z at 0.8 m/s
    carried = metrics.motion_amount(walking, FPS)
    assert carried.pose_speed[0] == pytest.approx(amount.pose_speed[0], rel=1e-9)  # translation is not pose motion
    assert carried.root_speed[0] == pytest.approx(0.8, rel=1e-9)
    assert carried.pose_spread[0] == pytest.approx(amount.pose_spread[0], rel=1e-9)


def test_pose_spread_is_the_rms_excursion_and_ignores_jitter_speed():
    frames, wrist, amplitude = 40, 21, 0.2  # the wrist alone sways ±0.2 m along x: RMS amplitude / √2 over periods
    sway = standing(frames)
    sway[:, wrist, 0] += amplitude * np.sin(2 * np.pi * np.arange(frames) / 20)
    amount = metrics.motion_amount(sway, FPS)
    assert amount.pose_spread[0] == pytest.approx(amplitude / np.sqrt(2) / HUMANML3D.num_joints, rel=1e-9)
    jitter = standing(frames)
    jitter[:, wrist, 0] += 0.01 * (-1.0) ** np.arange(frames)  # 1 cm back and forth every frame: fast, small
    shaky = metrics.motion_amount(jitter, FPS)
    assert shaky.pose_spread[0] == pytest.approx(0.01 / HUMANML3D.num_joints, rel=1e-9)
    assert shaky.pose_speed[0] == pytest.approx(0.02 * FPS / HUMANML3D.num_joints, rel=1e-9)


# ------------------------------------------------------------------------------------------------ lengths, API


def test_padding_frames_past_each_length_are_ignored():
    short, long_ = sliding(9, 1.2, foot_height=0.01), tumbling(14, seed=3)
    short[3:, 4, 0] += 0.05  # some real bone stretching in the short clip
    padded = np.zeros((2, 20, HUMANML3D.num_joints, 3))
    padded[0, :9], padded[1, :14] = short, long_
    padded[0, 9:] = 1e3 * np.random.default_rng(0).normal(size=(11, HUMANML3D.num_joints, 3))  # wild padding
    padded[1, 14:] = -5.0  # everything under the floor, bones collapsed
    lengths = np.array([9, 14])
    batch = metrics.plausibility(padded, HUMANML3D, lengths)
    alone = [metrics.plausibility(short, HUMANML3D), metrics.plausibility(long_, HUMANML3D)]
    for name in batch.names:
        expected = np.concatenate([getattr(a, name) for a in alone])
        np.testing.assert_allclose(getattr(batch, name), expected, rtol=1e-9, atol=1e-12, err_msg=name)
    assert metrics.plausibility(torch.from_numpy(padded), HUMANML3D, torch.tensor(lengths)).names == batch.names


def test_plausibility_collects_every_figure_and_summarises_medians():
    clips = np.stack([sliding(16, 1.2, 0.01), sliding(16, 0.3, 0.01), sliding(16, 1.2, 0.3)])
    figures = metrics.plausibility(clips, HUMANML3D)
    assert figures.names == ("bone_length_range", "bone_length_deviation", "floor_penetration",
                             "foot_skating_ratio", "contact_foot_speed", "skating_foot_speed", "mean_jerk", "pose_speed",
                             "root_speed", "pose_spread")
    np.testing.assert_allclose(figures.foot_skating_ratio, [1.0, 0.0, 0.0])
    summary = figures.summary()
    assert summary["foot_skating_ratio"] == 0.0 and summary["skating_foot_speed"] == 0.0
    assert summary["contact_foot_speed"] == pytest.approx(0.75)  # median of 1.2 and 0.3; the lifted clip has none
    assert figures.clip(2)["contact_foot_speed"] is None and figures.clip(0)["skating_foot_speed"] == pytest.approx(1.2)
    assert figures.select([2]).summary()["contact_foot_speed"] is None

    swaying = clips + 0.1 * np.sin(np.arange(16) / 3.0)[None, :, None, None]
    with_gt = metrics.plausibility(swaying, HUMANML3D, gt_joints=swaying)
    assert with_gt.names[-1] == "jerk_ratio" and with_gt.summary()["jerk_ratio"] == pytest.approx(1.0)
    still = np.stack([standing(16)] * 3)  # a ground truth that does not move has no jerk: no ratio
    assert metrics.plausibility(swaying, HUMANML3D, gt_joints=still).summary()["jerk_ratio"] is None
    both = metrics.PlausibilityFigures.concatenate([figures, figures.select([0])])
    assert len(both) == 4 and "jerk_ratio" not in both.names
    side = metrics.plausibility_side_by_side(figures, figures.select([0]))
    assert side["foot_skating_ratio"] == {"generated": 0.0, "ground_truth": 1.0}
    assert set(side) == set(figures.names)


def test_figures_are_in_metres_whatever_the_skeleton_unit():
    clip = sliding(16, 1.2, foot_height=-0.02)
    clip[4:, 7, 0] += 0.01
    in_metres = metrics.plausibility(clip, HUMANML3D)
    in_mm = metrics.plausibility(clip * 1000, dataclasses.replace(HUMANML3D, unit="mm"))
    for name in in_metres.names:
        np.testing.assert_allclose(getattr(in_mm, name), getattr(in_metres, name), rtol=1e-9, err_msg=name)
    assert in_metres.floor_penetration[0] == pytest.approx(0.02)


def test_a_real_humanml3d_clip_is_rigid_on_the_floor(reference_data):
    """The figures of real ground truth (clip 012314, a tennis serve), as README's plausibility table quotes them."""
    features = np.load(reference_data / "humanml3d" / "new_joint_vecs_012314.npy").astype(np.float64)
    figures = metrics.plausibility(features_to_joints(features, HUMANML3D), HUMANML3D)
    clip = figures.clip(0)
    assert clip["bone_length_range"] < 1e-5 and clip["bone_length_deviation"] < 1e-6  # retargeted: fixed bones
    assert clip["floor_penetration"] == 0.0 and not np.signbit(figures.floor_penetration[0])  # lowest joint at y = 0
    # the serve pivots on the toes: real motion skates a little by this definition
    assert clip["foot_skating_ratio"] == pytest.approx(29 / 169)
    assert clip["contact_foot_speed"] == pytest.approx(0.301, abs=1e-3)
    assert clip["mean_jerk"] == pytest.approx(0.0707, abs=1e-4)
    assert clip["pose_speed"] == pytest.approx(0.451, abs=1e-3) and clip["root_speed"] == pytest.approx(0.646, abs=1e-3)
    assert clip["pose_spread"] > 0.05
