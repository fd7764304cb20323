"""Metric suite checked against independent computations: closed forms, hand-made inputs, analytic MI."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import linalg

from mfm import metrics
from mfm.skeleton import HUMANML3D

# ------------------------------------------------------------------------------------------------ FID


def test_fid_of_a_set_against_itself_is_zero():
    emb = np.random.default_rng(0).normal(size=(400, 8))
    assert metrics.fid(emb, emb) == pytest.approx(0.0, abs=1e-8)


def test_fid_matches_direct_formula_on_random_data():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(300, 6)) @ rng.normal(size=(6, 6))
    b = rng.normal(loc=0.5, size=(250, 6)) * np.linspace(0.5, 2.0, 6)
    # direct: ||mu_a - mu_b||^2 + tr(Sa) + tr(Sb) - 2 tr((Sa^½ Sb Sa^½)^½)   (symmetric form, not the reference's)
    mu_a, mu_b = a.mean(0), b.mean(0)
    sa, sb = np.cov(a.T), np.cov(b.T)
    root_a = linalg.sqrtm(sa).real
    cross = linalg.sqrtm(root_a @ sb @ root_a).real
    direct = np.sum((mu_a - mu_b) ** 2) + np.trace(sa) + np.trace(sb) - 2 * np.trace(cross)
    assert metrics.fid(a, b) == pytest.approx(direct, rel=1e-8)
    assert metrics.fid(torch.tensor(a), torch.tensor(b)) == pytest.approx(direct, rel=1e-8)


def test_frechet_distance_closed_form_for_known_gaussians():
    # Diagonal covariances: d² = |Δμ|² + Σ (σ1 − σ2)²  (per-dimension standard deviations)
    mu1, mu2 = np.array([0.0, 1.0, -2.0]), np.array([3.0, 1.0, 2.0])
    s1, s2 = np.array([1.0, 4.0, 0.25]), np.array([9.0, 1.0, 0.25])  # variances
    expected = 9.0 + 16.0 + (1 - 3) ** 2 + (2 - 1) ** 2 + 0.0
    assert metrics.frechet_distance(mu1, np.diag(s1), mu2, np.diag(s2)) == pytest.approx(expected, rel=1e-10)


def test_frechet_distance_rank_deficient_covariances_stay_finite():
    sigma = np.zeros((4, 4))
    sigma[0, 0] = 1.0  # rank 1: singular product, but sqrtm of diag(1, 0, 0, 0) exists
    d = metrics.frechet_distance(np.zeros(4), sigma, np.ones(4), sigma)
    assert np.isfinite(d) and d == pytest.approx(4.0, abs=1e-3)


def test_frechet_distance_without_square_root_retries_with_eps_then_raises(caplog):
    # product [[0, 1], [0, 0]] has no square root (sqrtm gives inf): the eps retry runs, and what it returns has a
    # large imaginary part (negative eigenvalue), which must raise instead of being silently dropped
    sigma1, sigma2 = np.diag([1.0, 0.0]), np.array([[0.0, 1.0], [1.0, 0.0]])
    with caplog.at_level("WARNING", logger="mfm.metrics"), pytest.raises(ValueError, match="imaginary"):
        metrics.frechet_distance(np.zeros(2), sigma1, np.zeros(2), sigma2)
    assert "singular covariance product" in caplog.text


def test_embedding_stats_uses_unbiased_covariance():
    emb = np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 2.0], [2.0, 2.0]])
    mu, sigma = metrics.embedding_stats(emb)
    np.testing.assert_allclose(mu, [1.0, 1.0])
    np.testing.assert_allclose(sigma, np.eye(2) * 4.0 / 3.0)  # Σ (x−1)² = 4 over N−1 = 3


# ------------------------------------------------------------------------------------------------ R-precision


def test_r_precision_identical_embeddings_is_one():
    emb = np.random.default_rng(2).normal(size=(64, 16))
    assert metrics.r_precision(emb, emb) == (1.0, 1.0, 1.0)


def test_r_precision_match_exactly_second_closest():
    # 1-D: text i at 10·i, motion i at 10·i + 6 → for text i > 0 the nearest motion is motion i−1 (distance 4),
    # its own is 2nd (distance 6).
    n = 32
    text = (10.0 * np.arange(n))[:, None]
    motion = text + 6.0
    top1, top2, top3 = metrics.r_precision(text, motion)
    # text 0 has no motion at −4, so its own motion is nearest; the other 31 texts have theirs 2nd.
    assert top1 == pytest.approx(1 / 32)
    assert top2 == 1.0 and top3 == 1.0


def test_r_precision_drops_incomplete_final_batch_and_shuffle_is_seeded():
    rng = np.random.default_rng(3)
    text = rng.normal(size=(70, 4))
    # the first 64 pairs match exactly; the 6 leftover pairs are hopeless but must be dropped
    motion = text.copy()
    motion[64:] = rng.normal(size=(6, 4)) * 100
    assert metrics.r_precision(text, motion) == (1.0, 1.0, 1.0)
    a = metrics.r_precision(text, motion, generator=7)
    b = metrics.r_precision(text, motion, generator=np.random.default_rng(7))
    assert a == b and a[0] < 1.0  # shuffling brings hopeless pairs into the 64 used
    with pytest.raises(ValueError, match="at least batch_size"):
        metrics.r_precision(text[:31], motion[:31])


def test_r_precision_chance_level_for_random_embeddings():
    rng = np.random.default_rng(4)
    top1, _, top3 = metrics.r_precision(rng.normal(size=(3200, 8)), rng.normal(size=(3200, 8)))
    assert top1 == pytest.approx(1 / 32, abs=0.01)
    assert top3 == pytest.approx(3 / 32, abs=0.015)


def test_mm_dist_on_hand_made_vectors():
    text = np.array([[0.0, 0.0], [1.0, 1.0], [0.0, 0.0]])
    motion = np.array([[3.0, 4.0], [1.0, 1.0], [0.0, 2.0]])
    assert metrics.mm_dist(text, motion) == pytest.approx((5.0 + 0.0 + 2.0) / 3)


# ------------------------------------------------------------------------------------------------ diversity / MM / CI


def test_diversity_all_equal_is_zero_and_two_points_known():
    assert metrics.diversity(np.ones((400, 5)), times=300, generator=0) == 0.0
    # two clusters at distance 3: a pair is cross-cluster with probability ~1/2 for each of the 300 pairs
    emb = np.zeros((1000, 2))
    emb[500:, 0] = 3.0
    d = metrics.diversity(emb, times=300, generator=1)
    assert d == pytest.approx(1.5, abs=0.3)
    with pytest.raises(ValueError, match="at least times"):
        metrics.diversity(np.zeros((10, 2)), times=300)


def test_diversity_of_lattice_equals_mean_pair_distance_in_expectation():
    # points on the unit lattice {0..9}²; mean distance between independent uniform picks, computed exhaustively
    grid = np.stack(np.meshgrid(np.arange(10.0), np.arange(10.0)), -1).reshape(-1, 2)
    exhaustive = np.linalg.norm(grid[:, None] - grid[None], axis=-1).mean()
    draws = [metrics.diversity(grid, times=100, generator=s) for s in range(200)]
    assert np.mean(draws) == pytest.approx(exhaustive, rel=0.02)


def test_multimodality_constant_per_text_is_zero_and_known_spread():
    emb = np.repeat(np.random.default_rng(5).normal(size=(20, 1, 4)), 30, axis=1)
    assert metrics.multimodality(emb, times=10, generator=0) == pytest.approx(0.0, abs=1e-12)
    # repeats alternate between ±1 along x: pair distance is 0 or 2; each text has the same structure
    spread = np.zeros((5, 30, 3))
    spread[:, ::2, 0], spread[:, 1::2, 0] = 1.0, -1.0
    values = [metrics.multimodality(spread, times=10, generator=s) for s in range(300)]
    # P(different parity) for two independent uniform picks without replacement in each draw = 1/2 → E = 1
    assert np.mean(values) == pytest.approx(1.0, abs=0.05)
    with pytest.raises(ValueError):
        metrics.multimodality(np.zeros((4, 5, 2)), times=10)


def test_confidence_interval():
    mean, half = metrics.confidence_interval([1.0, 2.0, 3.0, 4.0])
    assert mean == 2.5
    assert half == pytest.approx(1.96 * np.sqrt(1.25) / 2.0)  # population std of 1..4 = √1.25
    means, halves = metrics.confidence_interval(np.array([[1.0, 0.0], [3.0, 0.0]]))
    np.testing.assert_allclose(means, [2.0, 0.0])
    np.testing.assert_allclose(halves, [1.96 / np.sqrt(2), 0.0])


# ------------------------------------------------------------------------------------------------ ADE / FDE


def test_ade_fde_on_hand_made_trajectories():
    n, t, j = 2, 5, 2
    gt = np.zeros((n, t, j, 3))
    pred = np.zeros((n, t, j, 3))
    # sample 0: joint 0 off by frame index along x (error f), joint 1 exact → per-frame mean f/2
    pred[0, :, 0, 0] = np.arange(t)
    # sample 1: both joints off by a 3-4-5 vector at every frame
    pred[1, :, :, 0], pred[1, :, :, 1] = 3.0, 4.0
    assert metrics.ade(pred, gt) == pytest.approx((np.mean(np.arange(t) / 2) + 5.0) / 2)
    assert metrics.fde(pred, gt) == pytest.approx((4 / 2 + 5.0) / 2)
    lengths = [3, 5]  # sample 0 valid frames 0..2
    assert metrics.ade(pred, gt, lengths) == pytest.approx((np.mean([0, 0.5, 1.0]) + 5.0) / 2)
    assert metrics.fde(pred, gt, lengths) == pytest.approx((1.0 + 5.0) / 2)
    mask = np.array([False, False, False, True, True])  # edited frames only
    assert metrics.ade(pred, gt, mask_frames=mask) == pytest.approx(((1.5 + 2.0) / 2 + 5.0) / 2)
    with pytest.raises(ValueError, match="no frame"):
        metrics.ade(pred, gt, lengths, mask_frames=np.array([[False, False, False, True, True]] * 2))


def test_ade_fde_are_metres_for_a_skeleton_in_millimetres():
    """KIT's joints are millimetres: ADE/FDE in metres divide by 1000 (METRES_PER_UNIT), not report 1000x."""
    gt = np.zeros((1, 4, 2, 3))
    pred = gt.copy()
    pred[..., 1] = 30.0  # every joint 30 mm high on every frame: 0.03 m
    scale = metrics.METRES_PER_UNIT["mm"]
    assert metrics.ade(pred, gt, metres_per_unit=scale) == pytest.approx(0.03)
    assert metrics.fde(pred, gt, metres_per_unit=scale) == pytest.approx(0.03)
    assert metrics.ade(pred / 1000, gt) == pytest.approx(metrics.ade(pred, gt, metres_per_unit=scale))
    with pytest.raises(ValueError, match="metres_per_unit"):
        metrics.fde(pred, gt, metres_per_unit=0.0)


# ------------------------------------------------------------------------------------------------ jerk


def test_jerk_of_cubic_is_constant_third_difference():
    t = np.arange(20.0)
    joints = np.zeros((1, 20, 3, 3))
    joints[0, :, 1, 0] = 0.5 * t**3  # Δ³(a t³) = 6a = 3
    joints[0, :, 2, 2] = -(t**3) / 6 + 2 * t**2  # Δ³ = −1 → |.| = 1 < 3
    curve = metrics.jerk_curve(joints)
    assert curve.shape == (1, 17)
    np.testing.assert_allclose(curve, 3.0, rtol=1e-12)
    curve = metrics.jerk_curve(joints, lengths=[10])
    np.testing.assert_allclose(curve[0, :7], 3.0)
    assert np.all(curve[0, 7:] == 0.0)  # entries k >= length − 3 touch padding


def test_peak_jerk_and_area_under_jerk_on_a_spike():
    # one joint at rest, then a unit step in y at frame 10: Δ³ of a step is (1, −2, 1) at k = 7, 8, 9 (L1 per frame)
    joints = np.zeros((2, 20, 1, 3))
    joints[0, 10:, 0, 1] = 1.0
    curves = metrics.jerk_curve(joints)  # second transition is static: zero curve
    expected0 = np.zeros(17)
    expected0[[7, 8, 9]] = [1.0, 2.0, 1.0]
    np.testing.assert_allclose(curves[0], expected0)
    np.testing.assert_allclose(curves[1], 0.0)
    assert metrics.peak_jerk(curves) == pytest.approx(1.0)  # mean of (2, 0)
    gt = 0.1
    # mean curve = expected0 / 2: |0.5−0.1| + |1−0.1| + |0.5−0.1| + 14·0.1
    assert metrics.area_under_jerk(curves, gt) == pytest.approx(0.4 + 0.9 + 0.4 + 14 * 0.1)


def test_dataset_average_jerk_weights_frames():
    a = np.zeros((10, 1, 3))
    a[:, 0, 0] = np.arange(10.0) ** 3 / 6  # jerk 1 on 7 frames
    b = np.zeros((5, 1, 3))  # jerk 0 on 2 frames
    assert metrics.dataset_average_jerk([a, b]) == pytest.approx(7 / 9)


def test_dataset_average_jerk_of_real_clip_is_in_the_humanml3d_range(reference_data):
    joints = np.load(reference_data / "humanml3d" / "new_joints_012314.npy")
    value = metrics.dataset_average_jerk([joints])
    # FlowMDM's HumanML3D constant is 0.033; a single real clip should be the same order of magnitude
    assert 0.005 < value < 0.2


def test_transition_windows_centred_and_padded_at_ends():
    seq = np.arange(100.0)[:, None]  # frame index as feature
    windows, real = metrics.transition_windows(seq, [50, 5, 98], window=10)
    assert windows.shape == (3, 10, 1) and real.shape == (3, 10)
    np.testing.assert_array_equal(windows[0, :, 0], np.arange(45, 55))  # l = 5 before, r = 5 from the boundary
    assert real[0].all()
    np.testing.assert_array_equal(windows[1, :, 0], np.arange(0, 10))  # [0, 10) exactly fits
    np.testing.assert_array_equal(windows[2, :, 0], [93, 94, 95, 96, 97, 98, 99, 99, 99, 99])
    np.testing.assert_array_equal(real[2], [True] * 7 + [False] * 3)
    odd, real_odd = metrics.transition_windows(seq, [3], window=7)  # l = 3, r = 4
    np.testing.assert_array_equal(odd[0, :, 0], np.arange(0, 7))
    assert real_odd.all()
    left, real_left = metrics.transition_windows(seq, [2], window=8)  # wants frames −2..5
    np.testing.assert_array_equal(left[0, :, 0], [0, 0, 0, 1, 2, 3, 4, 5])
    np.testing.assert_array_equal(real_left[0], [False, False] + [True] * 6)
    np.testing.assert_array_equal(metrics.boundaries_from_lengths([70, 80, 90]), [70, 150])


# ------------------------------------------- APE / AVE (TEMOS's definition, reported by FLAME's paper), FLAME's others


def _random_walk_body(rng, t=40):
    """A fake 22-joint HumanML3D body: a T-pose (rest offsets) walking along a random path, turning in place."""
    rest = np.zeros((22, 3))
    for child, parent in enumerate(HUMANML3D.parents):
        if parent >= 0:
            rest[child] = rest[parent] + HUMANML3D.raw_offsets[child] * HUMANML3D.bone_lengths[child]
    rest[:, 1] += 1.0
    yaw = np.cumsum(rng.normal(scale=0.05, size=t))
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.stack([np.stack([c, 0 * c, -s], -1), np.stack([0 * c, 1 + 0 * c, 0 * c], -1), np.stack([s, 0 * c, c], -1)], -2)
    body = np.einsum("jk,tkl->tjl", rest, rot)
    path = np.cumsum(rng.normal(scale=0.05, size=(t, 3)), axis=0) * np.array([1, 0.1, 1])
    return body + path[:, None] + rng.normal(scale=0.01, size=(t, 22, 3))


def test_ape_ave_identical_is_zero_and_height_offset_known():
    rng = np.random.default_rng(6)
    gt = np.stack([_random_walk_body(rng) for _ in range(3)])
    zero = metrics.ape_ave(gt, gt, face_joints=HUMANML3D.face_joints)
    assert all(v == pytest.approx(0.0, abs=1e-12) for v in zero.values())
    pred = gt + np.array([0.0, 0.2, 0.0])  # everything 20 cm higher
    out = metrics.ape_ave(pred, gt, [40, 30, 25])
    assert out["APE_root"] == pytest.approx(0.2) and out["APE_mean_global"] == pytest.approx(0.2)
    assert out["APE_mean_local"] == pytest.approx(0.2)  # local keeps height, removes only the root's xz
    assert out["APE_traj"] == pytest.approx(0.0, abs=1e-12)
    assert all(out[k] == pytest.approx(0.0, abs=1e-12) for k in out if k.startswith("AVE"))
    # TEMOS re-estimates each clip's floor from its feet: a clip lifted as a whole is the same motion
    feet = HUMANML3D.foot_left + HUMANML3D.foot_right
    floored = metrics.ape_ave(pred, gt, [40, 30, 25], floor_joints=feet)
    assert all(v == pytest.approx(0.0, abs=1e-9) for v in floored.values())


def test_temos_floor_is_their_softmin_of_the_lowest_foot_in_millimetres():
    feet = [0, 1]
    clip = np.zeros((3, 3, 3))
    clip[:, 0, 1] = [0.1, 0.3, 0.2]  # metres; the lowest foot joint per frame: 0.05, 0.3, 0.2
    clip[:, 1, 1] = [0.05, 0.4, 0.9]
    clip[:, 2, 1] = -5.0  # not a foot joint
    low, high = 50.0, 300.0  # millimetres: TEMOS's get_floor runs on millimetre joints (compute.py: 154-159)
    # TEMOS: softmin(x) = -softmax(-x), softmax(y) = max(y) + log(softness + exp(min(y) - max(y))), softness 0.5
    expected_mm = -((-low) + np.log(0.5 + np.exp((-high) - (-low))))
    floor = metrics.temos_floor_height(clip, feet)
    assert floor == pytest.approx(expected_mm / 1000.0, abs=1e-15)
    assert floor == pytest.approx(0.05 + np.log(2.0) / 1000.0, abs=1e-15)  # log 2 mm above the lowest foot
    # the same clip in millimetres: the same floor, in millimetres
    assert metrics.temos_floor_height(clip * 1000.0, feet, millimetres_per_unit=1.0) == pytest.approx(expected_mm)
    # the formula applied to metres (before issue 25): 0.34 m under the lowest foot for this 0.25 m range
    in_metres = metrics.temos_floor_height(clip, feet, millimetres_per_unit=1.0)
    assert 0.05 - in_metres == pytest.approx(np.log(0.5 + np.exp(-0.25)))
    with pytest.raises(ValueError, match="millimetres_per_unit"):
        metrics.temos_floor_height(clip, feet, millimetres_per_unit=0.0)


def test_ape_of_the_real_clip_against_itself_lifted_for_part_of_its_frames_is_the_lift(reference_data):
    """The real HumanML3D clip 012314 against itself lifted by 15 cm over frames 60-99 (not the frame of its lowest
    foot): with TEMOS's floor (in millimetres) both clips get the same floor, so the root and joint APE are exactly
    the lift averaged over the frames, the trajectory's is zero. The softmin applied to metres gave the lifted clip
    a different floor (its foot-height range grows) and so an error on every frame."""
    joints = np.load(reference_data / "humanml3d" / "new_joints_012314.npy").astype(np.float64)  # (170, 22, 3)
    feet = HUMANML3D.foot_left + HUMANML3D.foot_right
    assert not 60 <= int(joints[:, feet, 1].min(axis=1).argmin()) < 100
    lift, frames = 0.15, slice(60, 100)
    lifted = joints.copy()
    lifted[frames, :, 1] += lift
    expected = lift * 40 / len(joints)
    out = metrics.ape_ave(lifted[None], joints[None], face_joints=HUMANML3D.face_joints, floor_joints=feet)
    for name in ("APE_root", "APE_mean_global", "APE_mean_local"):
        assert out[name] == pytest.approx(expected, rel=1e-9), name
    assert out["APE_traj"] == pytest.approx(0.0, abs=1e-12)
    assert out["AVE_root"] > 0  # the lift changes the height's variance
    # both floors: 0.69 mm above the lowest foot (y = 0 in HumanML3D), lifted or not
    assert metrics.temos_floor_height(lifted, feet) == metrics.temos_floor_height(joints, feet) == pytest.approx(
        np.log(2.0) / 1000.0)
    # the metre formula's floors differ by centimetres between the two clips: the bias the fix removes
    metre_floors = [metrics.temos_floor_height(c, feet, millimetres_per_unit=1.0) for c in (lifted, joints)]
    assert abs(metre_floors[0] - metre_floors[1]) > 0.03
    # the same clips in millimetres (KIT's unit) give the same APE in metres
    in_mm = metrics.ape_ave(lifted[None] * 1000.0, joints[None] * 1000.0, face_joints=HUMANML3D.face_joints,
                            floor_joints=feet, metres_per_unit=1e-3)
    assert all(in_mm[k] == pytest.approx(out[k], rel=1e-9, abs=1e-12) for k in out)


def test_ape_ave_one_oscillating_joint():
    t, j = 10, 4
    gt = np.zeros((1, t, j, 3))
    pred = gt.copy()
    a = 0.3
    pred[0, :, 2, 0] = a * (-1.0) ** np.arange(t)  # joint 2 alternates ±a in x
    out = metrics.ape_ave(pred, gt)
    assert out["APE_mean_global"] == pytest.approx(a / j)
    assert out["APE_mean_local"] == pytest.approx(a / (j - 1))
    assert out["APE_root"] == 0.0 and out["APE_traj"] == 0.0
    var = a**2 * t / (t - 1)  # mean 0, Σ x² = t a², denominator t − 1
    assert out["AVE_mean_global"] == pytest.approx(var / j)
    assert out["AVE_mean_local"] == pytest.approx(var / (j - 1))
    assert out["AVE_root"] == 0.0


def test_heading_is_zero_facing_plus_z_and_quarter_turn_facing_plus_x():
    rest = np.zeros((22, 3))
    for child, parent in enumerate(HUMANML3D.parents):
        if parent >= 0:
            rest[child] = rest[parent] + HUMANML3D.raw_offsets[child] * HUMANML3D.bone_lengths[child]
    # HumanML3D's rest pose faces +z (feet point +z, right side at −x)
    assert metrics._heading(rest[None], HUMANML3D.face_joints)[0] == pytest.approx(0.0, abs=1e-12)
    to_plus_x = np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]])  # row vectors: (0, 0, 1) @ R = (1, 0, 0)
    assert metrics._heading((rest @ to_plus_x)[None], HUMANML3D.face_joints)[0] == pytest.approx(np.pi / 2)


def test_ape_ave_invariant_to_ground_translation_and_heading_with_face_joints():
    rng = np.random.default_rng(8)
    gt = _random_walk_body(rng)[None]
    theta = 1.1
    c, s = np.cos(theta), np.sin(theta)
    rot = np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])
    moved = gt @ rot + np.array([5.0, 0.0, -3.0])
    out = metrics.ape_ave(moved, gt, face_joints=HUMANML3D.face_joints)
    assert all(v == pytest.approx(0.0, abs=1e-9) for v in out.values()), out
    # without heading canonicalisation the rotation is an error (translation still is not)
    assert metrics.ape_ave(moved, gt)["APE_mean_global"] > 0.1
    shifted = metrics.ape_ave(gt + np.array([5.0, 0.0, -3.0]), gt)
    assert shifted["APE_mean_global"] == pytest.approx(0.0, abs=1e-12)


def test_ape_ave_of_a_batch_is_that_of_its_clips_one_at_a_time():
    """ape_ave computes every clip of a batch at once, each masked to its own length (padding frames hold garbage
    here): the figures equal those of the clips one by one, APE weighted by frames and AVE by clips (TEMOS)."""
    rng = np.random.default_rng(12)
    lengths = np.array([2, 9, 23, 40, 40])
    pred = np.stack([_random_walk_body(rng, t=40) for _ in lengths]) + rng.normal(0, 0.05, (5, 40, 22, 3))
    gt = np.stack([_random_walk_body(rng, t=40) for _ in lengths])
    pred[0, 2:] = 1e3  # padding: must not count
    settings = {"face_joints": HUMANML3D.face_joints, "floor_joints": HUMANML3D.foot_left + HUMANML3D.foot_right}
    batched = metrics.ape_ave(pred, gt, lengths, **settings)
    single = [metrics.ape_ave(p[None, :n], g[None, :n], **settings) for p, g, n in zip(pred, gt, lengths)]
    for name, value in batched.items():
        weights = lengths if name.startswith("APE") else np.ones(len(lengths))
        expected = sum(w * s[name] for w, s in zip(weights, single)) / weights.sum()
        assert value == pytest.approx(expected, rel=1e-12, abs=1e-15), name
    floors = metrics.temos_floor_heights(pred, settings["floor_joints"], lengths)
    assert floors[1] == metrics.temos_floor_height(pred[1, :9], settings["floor_joints"])


def test_mclip_score_orthogonal_parallel_antiparallel():
    text = np.array([[1.0, 0.0], [0.0, 2.0], [3.0, 0.0]])
    motion = np.array([[0.0, 5.0], [0.0, 0.1], [-1.0, 0.0]])
    assert metrics.mclip_score(text, motion) == pytest.approx((0.0 + 1.0 - 1.0) / 3)


def _correlated_gaussian(rng, n, d, rho):
    x = rng.normal(size=(n, d))
    y = rho * x + np.sqrt(1 - rho**2) * rng.normal(size=(n, d))
    return x, y


def test_mid_equals_analytic_mutual_information_for_gaussians():
    rng = np.random.default_rng(9)
    d, rho = 3, 0.6
    x, y = _correlated_gaussian(rng, 40000, d, rho)
    analytic = -0.5 * d * np.log(1 - rho**2)  # d independent pairs with correlation ρ
    assert metrics.mutual_information_divergence(y, x, x) == pytest.approx(analytic, abs=0.02)
    assert metrics.mutual_information_divergence(y, x) == pytest.approx(analytic, abs=0.02)


def test_mid_penalises_generations_that_ignore_the_text():
    rng = np.random.default_rng(10)
    d, rho = 3, 0.6
    x, y = _correlated_gaussian(rng, 40000, d, rho)
    x_unaligned = rng.normal(size=x.shape)  # same marginal, independent of the text
    # E[PMI] = I + ½ E[D²x + D²y − D²z]; per pair: ½(1 + 1 − 2/(1−ρ²)) = −ρ²/(1−ρ²)
    analytic = d * (-0.5 * np.log(1 - rho**2) - rho**2 / (1 - rho**2))
    assert metrics.mutual_information_divergence(y, x_unaligned, x) == pytest.approx(analytic, abs=0.03)


def test_mid_measures_shifted_generations_about_the_real_means():
    rng = np.random.default_rng(11)
    d, rho = 3, 0.6
    x, y = _correlated_gaussian(rng, 40000, d, rho)
    delta = np.full(d, 0.5)
    # aligned but shifted by δ: E[D²x] = d + |δ|², E[D²z] = 2d + |δ|²/(1−ρ²) → MID = I − ½|δ|² ρ²/(1−ρ²)
    analytic = -0.5 * d * np.log(1 - rho**2) - 0.5 * delta @ delta * rho**2 / (1 - rho**2)
    assert metrics.mutual_information_divergence(y, x + delta, x) == pytest.approx(analytic, abs=0.02)


def test_joint_variance_known_spread():
    samples = np.zeros((4, 3, 2, 3))
    samples[[0, 1], ..., 0] = 1.0
    samples[[2, 3], ..., 0] = -1.0  # x = ±1 around mean 0: variance 1 per frame and joint
    assert metrics.joint_variance(samples) == pytest.approx(1.0)
    assert metrics.joint_variance(np.ones((5, 3, 2, 3))) == 0.0


def test_action_accuracy():
    logits = torch.tensor([[0.1, 2.0, 0.0], [3.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 5.0, 0.0]])
    assert metrics.action_accuracy(logits, torch.tensor([1, 0, 0, 1])) == 0.75
    with pytest.raises(ValueError, match="labels must lie"):
        metrics.action_accuracy(logits, [1, 0, 3, 1])


def test_bad_inputs_raise_clear_errors():
    with pytest.raises(ValueError, match="pair row by row"):
        metrics.mm_dist(np.zeros((3, 2)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"\(N, T, J, 3\)"):
        metrics.jerk_curve(np.zeros((10, 4, 3)))
    with pytest.raises(ValueError, match="NaN"):
        metrics.fid(np.full((5, 2), np.nan), np.zeros((5, 2)))
