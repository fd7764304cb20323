import dataclasses

import numpy as np
import pytest
import torch

from mfm.flow import (
    term_weight,
    warp_time,
    SIGMA_MIN,
    FlowMatchingObjective,
    TimeSampling,
    flow_matching_loss,
    interpolate,
    masked_mse,
    sample_noise,
    sample_time,
    target_velocity,
)
from mfm.model import ModelConfig, MotionFlowTransformer, valid_frame_mask
from pipeline.config import ConfigError, TrainConfig, load_config


def tiny_model(seed: int = 0, **overrides) -> MotionFlowTransformer:
    values = dict(feature_dim=6, latent_dim=32, ff_dim=64, num_layers=2, num_heads=4, cond_dim=3, max_len=64)
    values.update(overrides)
    torch.manual_seed(seed)
    return MotionFlowTransformer(ModelConfig(**values))


class AffineStub:
    """A deterministic velocity 'model' whose output a hand computation can reproduce."""

    def __call__(self, x, t, cond, lengths=None, *, cond_mask=None, generator=None):
        return 0.5 * x * (1 + t[:, None, None]) + cond.sum(dim=1)[:, None, None]


# ---------------------------------------------------------------------------------------------- path


def test_sample_time_is_uniform_and_reproducible():
    t = sample_time(50_000, torch.Generator().manual_seed(0))
    assert t.shape == (50_000,) and t.dtype == torch.float32
    assert 0.0 <= t.min() and t.max() < 1.0
    assert abs(t.mean().item() - 0.5) < 0.005 and abs(t.var().item() - 1 / 12) < 0.002
    torch.testing.assert_close(t, sample_time(50_000, torch.Generator().manual_seed(0)), rtol=0, atol=0)


def test_sample_noise_matches_shape_and_dtype():
    like = torch.zeros(3, 4, 5, dtype=torch.float64)
    noise = sample_noise(like, torch.Generator().manual_seed(0))
    assert noise.shape == like.shape and noise.dtype == torch.float64


def test_path_endpoints():
    x0, x1 = torch.randn(2, 4, 3), torch.randn(2, 4, 3)
    torch.testing.assert_close(interpolate(x0, x1, torch.zeros(2)), x0)
    torch.testing.assert_close(interpolate(x0, x1, torch.ones(2)), x1 + SIGMA_MIN * x0)
    torch.testing.assert_close(interpolate(x0, x1, torch.ones(2), sigma_min=0.0), x1)


def test_target_is_the_time_derivative_of_the_path():
    x0, x1 = torch.randn(3, 5, 2, dtype=torch.float64), torch.randn(3, 5, 2, dtype=torch.float64)
    t, h = torch.tensor([0.1, 0.5, 0.9], dtype=torch.float64), 1e-6
    finite_difference = (interpolate(x0, x1, t + h) - interpolate(x0, x1, t - h)) / (2 * h)
    torch.testing.assert_close(finite_difference, target_velocity(x0, x1), atol=1e-8, rtol=0)


def test_masked_mse_averages_per_sample_then_over_the_batch():
    prediction, target = torch.randn(2, 5, 3), torch.randn(2, 5, 3)
    mask = valid_frame_mask(torch.tensor([5, 2]), 5)
    expected = ((prediction - target)[0, :5].square().mean() + (prediction - target)[1, :2].square().mean()) / 2
    torch.testing.assert_close(masked_mse(prediction, target, mask), expected)


# ---------------------------------------------------------------------------------------------- loss


def test_loss_equals_hand_computation():
    batch, frames, dim = 3, 5, 4
    x1 = torch.randn(batch, frames, dim)
    cond = torch.randn(batch, 2)
    lengths = torch.tensor([5, 3, 1])
    loss, stats = flow_matching_loss(AffineStub(), x1, cond, lengths, generator=torch.Generator().manual_seed(7))

    # The documented draw order: t (B,), then x0 (B, T, D), from the same generator.
    generator = torch.Generator().manual_seed(7)
    t = torch.rand(batch, generator=generator).double().numpy()
    x0 = torch.randn(batch, frames, dim, generator=generator).double().numpy()
    data, c = x1.double().numpy(), cond.double().numpy()
    per_sample = []
    for b in range(batch):
        total, count = 0.0, 0
        for f in range(int(lengths[b])):
            x_t = t[b] * data[b, f] + (1 - (1 - 1e-4) * t[b]) * x0[b, f]
            out = 0.5 * x_t * (1 + t[b]) + c[b].sum()
            target = data[b, f] - (1 - 1e-4) * x0[b, f]
            total += float(np.sum((target - out) ** 2))
            count += dim
        per_sample.append(total / count)
    assert loss.item() == pytest.approx(np.mean(per_sample), rel=1e-5)
    assert stats["valid_frames"].item() == 9
    assert stats["loss"].item() == loss.item() and not stats["loss"].requires_grad


@pytest.mark.parametrize("train", [False, True])
def test_loss_ignores_padded_frames(train):
    model = tiny_model().train(train)
    lengths = torch.tensor([8, 5, 2])
    x1, cond = torch.randn(3, 8, 6), torch.randn(3, 3)
    changed = x1.clone()
    changed[~valid_frame_mask(lengths, 8)] = 100.0
    losses = []
    for data in (x1, changed):
        torch.manual_seed(11)  # same dropout masks in training mode
        loss, _ = flow_matching_loss(model, data, cond, lengths, generator=torch.Generator().manual_seed(2))
        losses.append(loss.item())
    assert losses[0] == pytest.approx(losses[1], rel=1e-6, abs=1e-7)


def test_loss_is_reproducible_from_the_generator():
    model = tiny_model().eval()
    x1, cond, lengths = torch.randn(4, 6, 6), torch.randn(4, 3), torch.tensor([6, 5, 4, 3])
    first = flow_matching_loss(model, x1, cond, lengths, generator=torch.Generator().manual_seed(5))[0]
    again = flow_matching_loss(model, x1, cond, lengths, generator=torch.Generator().manual_seed(5))[0]
    other = flow_matching_loss(model, x1, cond, lengths, generator=torch.Generator().manual_seed(6))[0]
    assert first.item() == again.item() and first.item() != other.item()


def test_cond_mask_reaches_the_model():
    model = tiny_model().eval()
    x1, cond, lengths = torch.randn(2, 6, 6), torch.randn(2, 3), torch.tensor([6, 4])
    seed = lambda: torch.Generator().manual_seed(1)  # noqa: E731
    dropped = flow_matching_loss(model, x1, cond, lengths, generator=seed(), cond_mask=torch.ones(2, dtype=torch.bool))
    zero = flow_matching_loss(model, x1, torch.zeros_like(cond), lengths, generator=seed())
    kept = flow_matching_loss(model, x1, cond, lengths, generator=seed())
    assert dropped[0].item() == pytest.approx(zero[0].item(), rel=1e-6)
    assert dropped[0].item() != kept[0].item()


def test_objective_wraps_the_loss():
    model = tiny_model().eval()
    x1, cond, lengths = torch.randn(2, 6, 6), torch.randn(2, 3), torch.tensor([6, 4])
    objective = FlowMatchingObjective(sigma_min=0.01)
    via_objective = objective.loss(model, x1, cond, lengths, generator=torch.Generator().manual_seed(3))[0]
    direct = flow_matching_loss(model, x1, cond, lengths, generator=torch.Generator().manual_seed(3), sigma_min=0.01)
    assert via_objective.item() == direct[0].item()
    with pytest.raises(ValueError, match="sigma_min"):
        FlowMatchingObjective(sigma_min=1.0)


def test_tiny_model_overfits_four_clips(single_thread):
    """Each clip has its own condition, so the optimal velocity is exact and the loss can approach zero.

    About 4 s on one idle core (300 steps, batch 32).
    """
    model = tiny_model(feature_dim=8, latent_dim=64, ff_dim=128, cond_dim=4, dropout=0.0, cond_drop_prob=0.0)
    frames = torch.linspace(0, 1, 16)
    clips = torch.stack([torch.sin(6.28 * (k + 1) * frames[:, None] + torch.arange(8)) for k in range(4)])
    cond, lengths = torch.randn(4, 4), torch.tensor([16, 12, 10, 8])
    x1, c, lens = clips.repeat(8, 1, 1), cond.repeat(8, 1), lengths.repeat(8)  # 8 draws of (t, noise) per clip
    optimizer = torch.optim.Adam(model.parameters(), lr=2e-3)
    generator = torch.Generator().manual_seed(0)
    losses = []
    for _ in range(300):
        loss, _ = flow_matching_loss(model, x1, c, lens, generator=generator)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    initial, final = np.mean(losses[:10]), np.mean(losses[-20:])
    assert initial / final > 10, (initial, final)


def test_data_space_loss_is_the_mse_of_the_implied_motion():
    """loss_space='data' weighs each sample's velocity error by (1 − (1 − σ)t)²: for a model predicting x1, the
    MSE of x̂1 against x1 (away from the noise-scale floor); 'velocity' is MFM's unweighted loss."""
    from mfm.flow import loss_space_weight
    from mfm.model import ModelConfig, MotionFlowTransformer

    torch.manual_seed(0)
    model = MotionFlowTransformer(ModelConfig(feature_dim=6, latent_dim=16, ff_dim=32, num_layers=1, num_heads=2,
                                              cond_dim=3, prediction="data", max_len=64)).eval()
    x1, cond, lengths = torch.randn(4, 5, 6), torch.randn(4, 3), torch.tensor([5, 3, 4, 5])
    t, x0 = torch.tensor([0.0, 0.3, 0.6, 0.9]), torch.randn(4, 5, 6)
    loss, _ = flow_matching_loss(model, x1, cond, lengths, t=t, x0=x0, loss_space="data")
    x_t = interpolate(x0, x1, t)
    with torch.no_grad():
        velocity = model(x_t, t, cond, lengths)
    noise_scale = (1 - (1 - SIGMA_MIN) * t)[:, None, None]
    x1_hat = (1 - SIGMA_MIN) * x_t + noise_scale * velocity  # the network's own output (mfm.path.velocity_from_data)
    mask = valid_frame_mask(lengths, 5).unsqueeze(-1).float()
    expected = (((x1_hat - x1) * mask).square().sum(dim=(1, 2)) / (mask.sum(dim=(1, 2)) * 6)).mean()
    torch.testing.assert_close(loss, expected, rtol=1e-3, atol=1e-5)
    unweighted, _ = flow_matching_loss(model, x1, cond, lengths, t=t, x0=x0)
    assert unweighted > loss  # every weight is <= 1
    assert loss_space_weight(t, "velocity") is None
    torch.testing.assert_close(loss_space_weight(t, "data"), (1 - (1 - SIGMA_MIN) * t) ** 2)
    with pytest.raises(ValueError, match="loss_space"):
        FlowMatchingObjective(loss_space="noise")


def test_temporal_loss_charges_jitter_not_smooth_error():
    """temporal_loss = MSE of Δ(x̂1 − x1) over valid frame pairs: 0 for an error constant in time, four times the
    error's energy for one that alternates frame to frame (white noise: twice); padding frames do not count."""
    from mfm.flow import temporal_loss

    t = torch.tensor([0.5, 0.5])
    scale = 1 - (1 - SIGMA_MIN) * 0.5  # x̂1 − x1 = (v − u)·scale
    mask = valid_frame_mask(torch.tensor([6, 4]), 6)
    constant = torch.full((2, 6, 3), 0.2) / scale
    assert temporal_loss(constant, torch.zeros_like(constant), t, mask).item() == pytest.approx(0.0, abs=1e-12)
    signs = torch.tensor([1.0, -1.0, 1.0, -1.0, 1.0, -1.0])[None, :, None]
    alternating = (0.2 * signs).expand(2, 6, 3).clone() / scale
    alternating[1, 4:] = 100.0  # padding of sample 1: ignored
    assert temporal_loss(alternating, torch.zeros_like(alternating), t, mask).item() == pytest.approx(4 * 0.04)
    objective = FlowMatchingObjective(loss_space="data", temporal_weight=2.0)
    assert objective.temporal_weight == 2.0
    with pytest.raises(ValueError, match="temporal_weight"):
        FlowMatchingObjective(temporal_weight=-1.0)


def wrist_stretched(features: np.ndarray, frames: slice, metres: float) -> torch.Tensor:
    """HumanML3D features (T, 263) with the left wrist (joint 20, a leaf) ``metres`` further from its elbow (18) on
    ``frames``, moved along the forearm in the ric block."""
    stretched = torch.as_tensor(features).clone()
    ric = slice(4, 4 + 63)
    positions = stretched[frames, ric].reshape(-1, 21, 3)
    positions[:, 20 - 1] += metres * torch.nn.functional.normalize(positions[:, 20 - 1] - positions[:, 18 - 1], dim=-1)
    stretched[frames, ric] = positions.reshape(-1, 63)
    return stretched


def test_motion_geometry_reads_the_bones_of_a_real_clip(reference_data):
    """MotionGeometry's bone lengths off normalised features = those of recover_from_ric's joints (clip 012314,
    HumanML3D's Mean/Std); bone_length_loss is 0 against itself and the squared stretch when a bone stretches."""
    from mfm.features import features_to_joints
    from mfm.flow import MotionGeometry, bone_length_loss
    from mfm.skeleton import get_skeleton

    skeleton = get_skeleton("humanml3d")
    features = np.load(reference_data / "humanml3d" / "new_joint_vecs_012314.npy").astype(np.float32)
    mean = np.load(reference_data / "humanml3d" / "Mean.npy").astype(np.float32)
    std = np.load(reference_data / "humanml3d" / "Std.npy").astype(np.float32)
    geometry = MotionGeometry.from_dataset(mean, std, skeleton)
    normalised = torch.as_tensor((features - mean) / std)[None]
    joints = features_to_joints(torch.as_tensor(features), skeleton).numpy()
    children = [j for j, p in enumerate(skeleton.parents) if p >= 0]
    expected = np.stack([np.linalg.norm(joints[:, c] - joints[:, skeleton.parents[c]], axis=-1) for c in children], 1)
    np.testing.assert_allclose(geometry.bone_lengths(normalised)[0].numpy(), expected, atol=1e-5)

    # the statistics are put on a device once, not at every loss (on a GPU each copy from the host would wait)
    assert all(a is b for a, b in zip(geometry.statistics_on(normalised.device),
                                      geometry.statistics_on(normalised.device)))

    mask = torch.ones(1, normalised.shape[1], dtype=torch.bool)
    assert bone_length_loss(normalised, normalised, mask, geometry).item() == 0.0
    stretched = wrist_stretched(features, slice(None), 0.1)
    loss = bone_length_loss(torch.as_tensor((stretched.numpy() - mean) / std)[None], normalised, mask, geometry)
    assert loss.item() == pytest.approx(0.1 ** 2 / len(children), rel=1e-3)


def test_bone_term_held_to_the_clip_median_ignores_a_targets_frame_jitter(reference_data):
    """bone_length_loss(target='clip_median') holds x̂1's bones to each bone's median over the target's valid frames:
    a target whose left wrist is 10 cm long on every third frame (a teacher's jitter) charges a steady x̂1 nothing,
    where target='frames' charges it a third of the squared stretch; the padded frames (stretched by 1 m) count in
    neither the median nor the mean."""
    from mfm.flow import MotionGeometry, bone_length_loss, clip_median_over_frames
    from mfm.skeleton import get_skeleton

    skeleton = get_skeleton("humanml3d")
    features = np.load(reference_data / "humanml3d" / "new_joint_vecs_012314.npy").astype(np.float32)[:90]
    mean = np.load(reference_data / "humanml3d" / "Mean.npy").astype(np.float32)
    std = np.load(reference_data / "humanml3d" / "Std.npy").astype(np.float32)
    geometry = MotionGeometry.from_dataset(mean, std, skeleton)
    bones = len([p for p in skeleton.parents if p >= 0])

    valid = 84
    jittery = wrist_stretched(features, slice(0, valid, 3), 0.1)
    jittery[valid:] = wrist_stretched(features, slice(valid, None), 1.0)[valid:]
    normalise = lambda f: torch.as_tensor((f.numpy() - mean) / std)[None]
    steady, target = normalise(torch.as_tensor(features)), normalise(jittery)
    mask = torch.zeros(1, features.shape[0], dtype=torch.bool)
    mask[:, :valid] = True

    assert bone_length_loss(steady, target, mask, geometry, target="clip_median").item() < 1e-8
    assert bone_length_loss(steady, target, mask, geometry).item() == pytest.approx(0.1 ** 2 / 3 / bones, rel=1e-3)
    medians = clip_median_over_frames(geometry.bone_lengths(target), mask)
    np.testing.assert_allclose(medians[0, 0].numpy(), geometry.bone_lengths(steady)[0, 0].numpy(), atol=1e-5)
    with pytest.raises(ValueError, match="clip_median"):
        bone_length_loss(steady, target, mask, geometry, target="mean")


def test_root_path_is_the_root_of_recover_from_ric_on_a_real_clip(reference_data):
    """mfm.features.root_path integrates the root as features_to_joints places it (clip 012314), and
    MotionGeometry.root_path reads the same path off normalised features."""
    from mfm.features import features_to_joints, root_path
    from mfm.flow import MotionGeometry
    from mfm.skeleton import get_skeleton

    skeleton = get_skeleton("humanml3d")
    features = np.load(reference_data / "humanml3d" / "new_joint_vecs_012314.npy").astype(np.float32)
    mean = np.load(reference_data / "humanml3d" / "Mean.npy").astype(np.float32)
    std = np.load(reference_data / "humanml3d" / "Std.npy").astype(np.float32)
    angle, position = root_path(torch.as_tensor(features))
    joints = features_to_joints(torch.as_tensor(features), skeleton).numpy()
    np.testing.assert_allclose(position.movedim(0, -1).numpy(), joints[:, 0], atol=1e-5)
    np.testing.assert_allclose(angle.numpy(), np.concatenate([[0.0], np.cumsum(features[:-1, 0])]), atol=1e-5)
    geometry = MotionGeometry.from_dataset(mean, std, skeleton)
    heading, ground = geometry.root_path(torch.as_tensor((features - mean) / std)[None])
    np.testing.assert_allclose(heading[0].numpy(), angle.numpy(), atol=1e-4)
    np.testing.assert_allclose(ground[0].numpy(), joints[:, 0, [0, 2]], atol=1e-4)


def trajectory_geometry(dim: int = 263):
    from mfm.flow import MotionGeometry
    from mfm.skeleton import get_skeleton

    return MotionGeometry.from_dataset(np.zeros(dim, np.float32), np.ones(dim, np.float32), get_skeleton("humanml3d"))


def test_trajectory_loss_grows_with_a_persistent_rate_bias_and_ignores_padding():
    """A bias δ in the root's forward velocity (per frame) puts the root k·δ off by frame k: the term is the mean of
    (k·δ)² over valid frames, so it grows with the clip's length as the drift does (the main MSE charges δ² per frame
    whatever the length); a heading-rate bias ε costs (k·ε)² the same way; padding frames do not count."""
    from mfm.flow import trajectory_loss

    geometry = trajectory_geometry()
    clip = torch.zeros(2, 10, 263)
    mask = valid_frame_mask(torch.tensor([10, 5]), 10)
    assert trajectory_loss(clip, clip, mask, geometry).item() == 0.0
    delta, eps = 0.003, 0.01
    drifting = clip.clone()
    drifting[..., 2] = delta  # the facing frame's Z velocity (forward)
    drifting[1, 5:] = 50.0  # padding of sample 1
    frames = torch.arange(10.0)
    expected = 0.5 * ((frames * delta).square().mean() + (frames[:5] * delta).square().mean())
    assert trajectory_loss(drifting, clip, mask, geometry).item() == pytest.approx(expected.item(), rel=1e-4)
    turning = clip.clone()
    turning[..., 0] = eps
    expected = 0.5 * ((frames * eps).square().mean() + (frames[:5] * eps).square().mean())
    assert trajectory_loss(turning, clip, mask, geometry).item() == pytest.approx(expected.item(), rel=1e-4)


def test_foot_contact_loss_charges_the_planted_feet_only_and_ignores_padding():
    """Against a still clip, a root drifting δ per frame moves every foot joint δ per frame: the term is δ² times the
    share of (valid frame pair, foot joint) cells the clip labels planted, the implied motion's own labels do not
    count; a clip costs nothing against itself, a moving one included."""
    from mfm.flow import foot_contact_loss

    geometry = trajectory_geometry()
    clip = torch.zeros(2, 10, 263)
    clip[:, :5, 259] = 1.0  # the left ankle planted on frames 0-4
    mask = valid_frame_mask(torch.tensor([10, 5]), 10)
    assert foot_contact_loss(clip, clip, mask, geometry).item() == 0.0
    delta = 0.02
    sliding = torch.zeros_like(clip)  # its own contact labels: none
    sliding[..., 2] = delta  # the facing frame's Z velocity (forward)
    sliding[1, 5:] = 50.0  # padding of sample 1
    # sample 0: 9 pairs x 4 joints, 5 planted; sample 1: 4 pairs x 4 joints, 4 planted (frame 4's pair is padding)
    expected = 0.5 * (5 / 36 + 4 / 16) * delta**2
    assert foot_contact_loss(sliding, clip, mask, geometry).item() == pytest.approx(expected, rel=1e-4)
    walking = sliding.clone()
    walking[..., 259:263] = 1.0
    assert foot_contact_loss(walking, walking, mask, geometry).item() == 0.0
    assert foot_contact_loss(clip, walking, mask, geometry).item() > 0  # still feet against the clip's moving ones
    no_skeleton = dataclasses.replace(geometry, skeleton=None)
    with pytest.raises(ValueError, match="skeleton"):
        foot_contact_loss(sliding, clip, mask, no_skeleton)


@pytest.mark.parametrize("term", ["trajectory", "foot_contact"])
def test_a_geometric_term_adds_its_weight_times_the_implied_motions_error(term):
    """flow_matching_loss with the term's weight w = the loss without it + w × the term of (x̂1, x1) on the same
    draws; the gradient reaches the model; the objective refuses a negative weight or a missing geometry."""
    from mfm.flow import foot_contact_loss, implied_motion_error, trajectory_loss

    term_loss = {"trajectory": trajectory_loss, "foot_contact": foot_contact_loss}[term]
    weight_name = f"{term}_weight"
    torch.manual_seed(0)
    geometry = trajectory_geometry()
    model = MotionFlowTransformer(ModelConfig(feature_dim=263, latent_dim=16, ff_dim=32, num_layers=1, num_heads=2,
                                              cond_dim=4, dropout=0.0, cond_drop_prob=0.0)).eval()
    x1, cond, lengths = 0.1 * torch.randn(2, 12, 263), torch.randn(2, 4), torch.tensor([12, 7])
    x1[..., 259:263] = 1.0  # feet planted throughout
    t, x0 = torch.tensor([0.3, 0.8]), torch.randn(2, 12, 263)
    plain, _ = flow_matching_loss(model, x1, cond, lengths, t=t, x0=x0)
    with_term, _ = flow_matching_loss(model, x1, cond, lengths, t=t, x0=x0, geometry=geometry, **{weight_name: 2.0})
    velocity = model(interpolate(x0, x1, t), t, cond, lengths)
    x1_hat = x1 + implied_motion_error(velocity, target_velocity(x0, x1), t)
    value = term_loss(x1_hat, x1, valid_frame_mask(lengths, 12), geometry)
    assert value.item() > 0
    assert with_term.item() == pytest.approx(plain.item() + 2.0 * value.item(), rel=1e-5)
    with_term.backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
    objective = FlowMatchingObjective(geometry=geometry, **{weight_name: 1.0})
    assert objective.loss(model, x1, cond, lengths, t=t, x0=x0)[0].item() == pytest.approx(
        plain.item() + value.item(), rel=1e-5)
    with pytest.raises(ValueError, match=weight_name):
        FlowMatchingObjective(**{weight_name: 1.0})
    with pytest.raises(ValueError, match=weight_name):
        FlowMatchingObjective(geometry=geometry, **{weight_name: -1.0})
    with pytest.raises(ValueError, match="geometry"):
        flow_matching_loss(model, x1, cond, lengths, t=t, x0=x0, **{weight_name: 1.0})


def test_the_pseudo_huber_trajectory_term_is_the_squared_error_when_small_and_bounds_a_frames_gradient():
    """huber h: a drift far below h costs what the squared error does; a drift of metres costs about 2·h·distance,
    and the gradient it sends to a root velocity is bounded by the frames it reaches × 2h, while the squared error's
    grows with the drift; h 0 is the squared error exactly; the objective refuses h < 0."""
    from mfm.flow import pseudo_huber, trajectory_loss

    geometry = trajectory_geometry()
    clip = torch.zeros(1, 20, 263)
    mask = valid_frame_mask(torch.tensor([20]), 20)
    assert pseudo_huber(torch.tensor([0.0]), 0.1).item() == 0.0
    small = clip.clone()
    small[..., 2] = 1e-4  # 2 mm after 20 frames, against h = 0.1 m
    squared = trajectory_loss(small, clip, mask, geometry).item()
    assert trajectory_loss(small, clip, mask, geometry, huber=0.0).item() == squared
    assert trajectory_loss(small, clip, mask, geometry, huber=0.1).item() == pytest.approx(squared, rel=1e-3)
    gradients = {}
    for huber in (0.0, 0.1):
        for drift in (0.1, 1.0):  # m per frame: 1.9 m and 19 m after 20 frames
            x1_hat = clip.clone()
            x1_hat[..., 2] = drift
            x1_hat.requires_grad_(True)
            trajectory_loss(x1_hat, clip, mask, geometry, huber=huber).backward()
            gradients[huber, drift] = x1_hat.grad[0, 0, 2].abs().item()
    assert gradients[0.0, 1.0] == pytest.approx(10 * gradients[0.0, 0.1], rel=1e-3)  # squared: grows with the drift
    assert gradients[0.1, 1.0] == pytest.approx(gradients[0.1, 0.1], rel=0.05)  # pseudo-Huber: saturated
    assert gradients[0.1, 1.0] <= 2 * 0.1 * 19 / 20 + 1e-6  # 19 later frames' bounded pulls, over 20 frames
    with pytest.raises(ValueError, match="trajectory_huber"):
        FlowMatchingObjective(geometry=geometry, trajectory_weight=1.0, trajectory_huber=-0.1)


def test_the_trajectory_term_from_a_minimum_time_counts_only_the_rows_trained_at_or_after_it():
    """trajectory_min_t = 0.5 with rows at t = 0.3 and 0.8: the loss is the plain loss + w × (the term of the t = 0.8
    row alone) / 2 (the batch mean still divides by both rows); the main loss, the other terms and the draws are
    untouched; min_t 0 is the term over every row; the objective refuses min_t outside [0, 1)."""
    from mfm.flow import implied_motion_error, trajectory_loss

    torch.manual_seed(0)
    geometry = trajectory_geometry()
    model = MotionFlowTransformer(ModelConfig(feature_dim=263, latent_dim=16, ff_dim=32, num_layers=1, num_heads=2,
                                              cond_dim=4, dropout=0.0, cond_drop_prob=0.0)).eval()
    x1, cond, lengths = 0.1 * torch.randn(2, 12, 263), torch.randn(2, 4), torch.tensor([12, 7])
    t, x0 = torch.tensor([0.3, 0.8]), torch.randn(2, 12, 263)
    plain, _ = flow_matching_loss(model, x1, cond, lengths, t=t, x0=x0, bone_weight=1.0, geometry=geometry)
    velocity = model(interpolate(x0, x1, t), t, cond, lengths)
    x1_hat = x1 + implied_motion_error(velocity, target_velocity(x0, x1), t)
    mask = valid_frame_mask(lengths, 12)
    per_row = [trajectory_loss(x1_hat[i : i + 1], x1[i : i + 1], mask[i : i + 1], geometry).item() for i in (0, 1)]
    assert min(per_row) > 0
    late, _ = flow_matching_loss(model, x1, cond, lengths, t=t, x0=x0, bone_weight=1.0, geometry=geometry,
                                 trajectory_weight=2.0, trajectory_min_t=0.5)
    assert late.item() == pytest.approx(plain.item() + 2.0 * per_row[1] / 2, rel=1e-5)
    every, _ = flow_matching_loss(model, x1, cond, lengths, t=t, x0=x0, bone_weight=1.0, geometry=geometry,
                                  trajectory_weight=2.0)
    assert every.item() == pytest.approx(plain.item() + 2.0 * sum(per_row) / 2, rel=1e-5)
    objective = FlowMatchingObjective(geometry=geometry, bone_weight=1.0, trajectory_weight=2.0, trajectory_min_t=0.5)
    assert objective.loss(model, x1, cond, lengths, t=t, x0=x0)[0].item() == pytest.approx(late.item(), rel=1e-6)
    for bad in (-0.1, 1.0):
        with pytest.raises(ValueError, match="trajectory_min_t"):
            FlowMatchingObjective(geometry=geometry, trajectory_weight=1.0, trajectory_min_t=bad)


def test_uniform_time_sampling_keeps_the_draws_and_logit_normal_is_its_inverse_cdf():
    u = torch.rand(20_000, generator=torch.Generator().manual_seed(0))
    assert torch.equal(warp_time(u, "uniform"), u)
    t = warp_time(u, "logit_normal", loc=0.0, scale=1.0)
    logits = torch.logit(t.double())
    assert abs(logits.mean().item()) < 0.03 and abs(logits.std().item() - 1.0) < 0.03
    shifted = warp_time(u, "logit_normal", loc=-1.0, scale=0.5)
    assert abs(torch.logit(shifted.double()).mean().item() + 1.0) < 0.02
    assert torch.all(torch.diff(warp_time(torch.linspace(0, 1, 101), "logit_normal")) >= 0)  # monotone in u
    assert torch.isfinite(warp_time(torch.tensor([0.0, 1.0]), "logit_normal")).all()
    with pytest.raises(ValueError):
        warp_time(u, "cosine")


def test_grid_time_sampling_draws_the_k_step_eulers_times_equally_often():
    u = torch.rand(20_000, generator=torch.Generator().manual_seed(0))
    for steps in (1, 2, 4):
        t = warp_time(u, "grid", grid_steps=steps)
        values, counts = torch.unique(t, return_counts=True)
        assert torch.allclose(values, torch.arange(steps) / steps)  # 0, 1/K, ..., (K-1)/K: never t = 1
        assert (counts.float() / len(u) - 1 / steps).abs().max() < 0.02
    assert warp_time(torch.tensor([1.0]), "grid", grid_steps=2).item() == 0.5  # u = 1 (never drawn) stays on the grid
    with pytest.raises(ValueError, match="grid_steps"):
        warp_time(u, "grid")
    with pytest.raises(ValueError, match="time_grid_steps"):
        FlowMatchingObjective(time_sampling="grid")


def test_stratified_times_hold_one_per_stratum_each_row_still_uniform():
    """stratify_times: a batch of B times has exactly one in each [k/B, (k+1)/B); over batches each row's time is
    U(0, 1) (the permutation, not the row's place, picks its stratum); the loss draws it after t, before x0."""
    from mfm.flow import stratify_times
    generator = torch.Generator().manual_seed(0)
    batches = []
    for _ in range(4000):
        t = stratify_times(torch.rand(8, generator=generator), generator)
        assert sorted(torch.floor(t * 8).long().tolist()) == list(range(8))
        batches.append(t)
    rows = torch.stack(batches)  # (4000, 8)
    for row in rows.T:  # each row's histogram over 4 bins of [0, 1): 1/4 each
        shares = torch.histc(row, bins=4, min=0, max=1) / len(row)
        assert (shares - 0.25).abs().max() < 0.03
    assert torch.equal(warp_time(rows[0], "stratified"), rows[0])

    torch.manual_seed(0)
    model = MotionFlowTransformer(ModelConfig(feature_dim=6, latent_dim=16, ff_dim=32, num_layers=1, num_heads=2,
                                              cond_dim=4, dropout=0.0, cond_drop_prob=0.0)).eval()
    x1, cond, lengths = torch.randn(4, 8, 6), torch.randn(4, 4), torch.tensor([8, 5, 7, 8])
    drawn, _ = flow_matching_loss(model, x1, cond, lengths, generator=torch.Generator().manual_seed(3),
                                  time_sampling=TimeSampling("stratified"))
    replay = torch.Generator().manual_seed(3)
    t = stratify_times(torch.rand(4, generator=replay), replay)
    x0 = torch.randn(x1.shape, generator=replay)
    given, _ = flow_matching_loss(model, x1, cond, lengths, t=t, x0=x0)
    assert torch.allclose(drawn, given)
    with pytest.raises(ConfigError, match="stratified"):
        load_config(TrainConfig, "tiny", ["train.flow_time_sampling=stratified", "model.shortcut_levels=2"])


def test_the_loss_trains_at_the_warped_time():
    torch.manual_seed(0)
    model = MotionFlowTransformer(ModelConfig(feature_dim=6, latent_dim=16, ff_dim=32, num_layers=1, num_heads=2,
                                              cond_dim=4, dropout=0.0, cond_drop_prob=0.0)).eval()
    x1, cond, lengths = torch.randn(3, 8, 6), torch.randn(3, 4), torch.tensor([8, 5, 7])
    u, x0 = torch.tensor([0.2, 0.5, 0.9]), torch.randn(3, 8, 6)
    warped = warp_time(u, "logit_normal", -0.5, 1.0)
    loss_warped, _ = flow_matching_loss(model, x1, cond, lengths, t=u, x0=x0,
                                        time_sampling=TimeSampling("logit_normal", -0.5, 1.0))
    loss_direct, _ = flow_matching_loss(model, x1, cond, lengths, t=warped, x0=x0)
    assert torch.allclose(loss_warped, loss_direct)


def test_terms_weighted_as_the_loss_follow_the_velocity_loss_and_leave_the_data_loss_alone():
    t = torch.tensor([0.0, 0.5, 0.9, 0.999])
    assert term_weight(t, "velocity", "data") is None and term_weight(t, "data", "loss") is None
    weights = term_weight(t, "velocity", "loss")
    expected = torch.tensor([1.0, 1 / (1 - (1 - SIGMA_MIN) * 0.5) ** 2, 1 / (1 - (1 - SIGMA_MIN) * 0.9) ** 2, 400.0])
    assert torch.allclose(weights, expected, rtol=1e-5)
    with pytest.raises(ValueError):
        term_weight(t, "velocity", "time")


def test_the_temporal_term_weighted_as_the_loss_is_each_sample_times_its_weight():
    torch.manual_seed(0)
    model = MotionFlowTransformer(ModelConfig(feature_dim=6, latent_dim=16, ff_dim=32, num_layers=1, num_heads=2,
                                              cond_dim=4, dropout=0.0, cond_drop_prob=0.0)).eval()
    x1, cond, lengths = torch.randn(2, 8, 6), torch.randn(2, 4), torch.tensor([8, 6])
    t, x0 = torch.tensor([0.3, 0.9]), torch.randn(2, 8, 6)
    def loss(**kw):
        return flow_matching_loss(model, x1[i:i + 1], cond[i:i + 1], lengths[i:i + 1], t=t[i:i + 1], x0=x0[i:i + 1],
                                  **kw)[0]
    for i in range(2):
        plain, term_data = loss(), loss(temporal_weight=2.0)
        term_loss = loss(temporal_weight=2.0, terms_weighting="loss")
        w = 1 / (1 - (1 - SIGMA_MIN) * t[i]) ** 2
        assert torch.allclose(term_loss - plain, (term_data - plain) * w, rtol=1e-4)


def test_a_capped_velocity_loss_is_the_velocity_loss_near_the_noise_and_cap_times_the_data_loss_near_the_data():
    """velocity_weight_cap: the x̂1 weight min(1/(1 − t)², cap), i.e. min(1, cap·(1 − t)²) in velocity space; each
    sample's loss is the uncapped one there and cap × the data-space loss beyond, and the terms follow under 'loss'."""
    from mfm.flow import loss_space_weight
    from mfm.model import ModelConfig, MotionFlowTransformer

    t = torch.tensor([0.0, 0.5, 0.7, 0.95])
    noise_scale = 1 - (1 - SIGMA_MIN) * t
    capped = loss_space_weight(t, "velocity", velocity_weight_cap=9.0)
    torch.testing.assert_close(capped, torch.tensor([1.0, 1.0, float(9 * noise_scale[2] ** 2),
                                                     float(9 * noise_scale[3] ** 2)]))
    assert capped[2] < 1  # 1/(1 − 0.7)² ≈ 11 > 9: capped
    torch.testing.assert_close(term_weight(t, "velocity", "loss", velocity_weight_cap=9.0),
                               torch.minimum(noise_scale.square().reciprocal(), torch.tensor(9.0)))

    torch.manual_seed(0)
    model = MotionFlowTransformer(ModelConfig(feature_dim=6, latent_dim=16, ff_dim=32, num_layers=1, num_heads=2,
                                              cond_dim=3, prediction="data", max_len=64)).eval()
    x1, cond, lengths = torch.randn(2, 5, 6), torch.randn(2, 3), torch.tensor([5, 4])
    x0 = torch.randn(2, 5, 6)
    for time, factor in ((0.2, None), (0.9, 9.0)):  # 1/(1 − 0.2)² < 9: unchanged; at 0.9: 9 × the data loss
        tt = torch.full((2,), time)
        got, _ = flow_matching_loss(model, x1, cond, lengths, t=tt, x0=x0, velocity_weight_cap=9.0)
        if factor is None:
            expected, _ = flow_matching_loss(model, x1, cond, lengths, t=tt, x0=x0)
        else:
            data_loss, _ = flow_matching_loss(model, x1, cond, lengths, t=tt, x0=x0, loss_space="data")
            expected = factor * data_loss
        torch.testing.assert_close(got, expected, rtol=1e-4, atol=1e-6)
    with pytest.raises(ValueError, match="velocity loss only"):
        FlowMatchingObjective(loss_space="data", velocity_weight_cap=9.0)
    with pytest.raises(ValueError, match="velocity_weight_cap"):
        FlowMatchingObjective(velocity_weight_cap=-1.0)


# ---------------------------------------------------------------------------------------------- feat_bias


@pytest.mark.parametrize(("skeleton", "dim"), [("humanml3d", 263), ("kit", 251)])
def test_feat_bias_weighs_the_root_and_contact_channels_only(skeleton, dim):
    from mfm.flow import feat_bias_channel_weight
    from mfm.layout import FeatureLayout
    from mfm.skeleton import get_skeleton

    weight = np.array(feat_bias_channel_weight(FeatureLayout(get_skeleton(skeleton)), 5.0))
    assert weight.shape == (dim,)
    expected = np.ones(dim)
    expected[[0, 1, 2, 3, dim - 4, dim - 3, dim - 2, dim - 1]] = 25.0  # Guo's std / 5 is a squared error × 25
    np.testing.assert_array_equal(weight, expected)
    with pytest.raises(ValueError, match="feat_bias must be > 0"):
        feat_bias_channel_weight(FeatureLayout(get_skeleton(skeleton)), 0.0)


def test_channel_weight_scales_each_channels_squared_error():
    gen = torch.Generator().manual_seed(0)
    prediction, target = torch.randn(2, 5, 4, generator=gen), torch.randn(2, 5, 4, generator=gen)
    mask = valid_frame_mask(torch.tensor([5, 3]), 5)
    weight = torch.tensor([4.0, 1.0, 1.0, 0.5])
    per_channel = [masked_mse(prediction[..., [c]], target[..., [c]], mask) for c in range(4)]
    # The divisor stays Σ mask · D: the weighted loss is the weighted mean of the per-channel losses.
    expected = sum(w * loss for w, loss in zip(weight, per_channel)) / 4
    torch.testing.assert_close(masked_mse(prediction, target, mask, channel_weight=weight), expected)
    torch.testing.assert_close(masked_mse(prediction, target, mask, channel_weight=torch.ones(4)),
                               masked_mse(prediction, target, mask))


def test_flow_objective_applies_its_channel_weight():
    model = tiny_model().eval()
    x1, cond, lengths = torch.randn(2, 5, 6), torch.randn(2, 3), torch.tensor([5, 4])
    t, x0 = torch.tensor([0.3, 0.6]), torch.randn(2, 5, 6)
    weight = (9.0, 1.0, 1.0, 1.0, 1.0, 1.0)
    weighted = FlowMatchingObjective(channel_weight=weight)
    got, _ = weighted.loss(model, x1, cond, lengths, t=t, x0=x0)
    # Made once per device, not every step.
    assert weighted.channel_weight_on(x1.device) is weighted.channel_weight_on(x1.device)
    assert weighted == FlowMatchingObjective(channel_weight=weight)  # the cache is not a field
    plain, _ = FlowMatchingObjective().loss(model, x1, cond, lengths, t=t, x0=x0)
    velocity = model(interpolate(x0, x1, t), t, cond, lengths)
    first = masked_mse(velocity[..., :1], target_velocity(x0, x1)[..., :1], valid_frame_mask(lengths, 5)) / 6
    torch.testing.assert_close(got, plain + 8 * first, rtol=1e-5, atol=1e-6)


def test_root_rate_mean_loss_charges_the_clip_mean_of_the_root_rates_only_and_ignores_padding():
    """A persistent bias δ of the forward rate costs δ² whatever the clip's length; an error that comes and goes
    (+a, −a) costs nothing however large; channels outside the root's rates (its height, the pose) cost nothing;
    each channel's squared mean adds; padding frames do not count; the batch mean is over samples."""
    from mfm.flow import ROOT_RATE_CHANNELS, root_rate_mean_loss

    assert ROOT_RATE_CHANNELS == (0, 1, 2)
    mask = valid_frame_mask(torch.tensor([10, 4]), 10)
    error = torch.zeros(2, 10, 263)
    assert root_rate_mean_loss(error, mask).item() == 0.0
    biased = error.clone()
    biased[..., 2] = 0.3
    biased[1, 4:] = 50.0  # padding of sample 1
    assert root_rate_mean_loss(biased, mask).item() == pytest.approx(0.09, rel=1e-6)
    alternating = error.clone()
    alternating[..., 1] = torch.tensor([1.0, -1.0]).repeat(5)
    assert root_rate_mean_loss(alternating, mask).item() == pytest.approx(0.0, abs=1e-7)
    elsewhere = error.clone()
    elsewhere[..., 3:] = 1.0  # the root's height and everything after it
    assert root_rate_mean_loss(elsewhere, mask).item() == 0.0
    both = error.clone()
    both[0, :, 0], both[0, :, 2] = 0.5, -0.5  # sample 0 only: 0.25 + 0.25, the batch mean over 2 samples
    assert root_rate_mean_loss(both, mask).item() == pytest.approx(0.25, rel=1e-6)
    assert root_rate_mean_loss(both, mask, channels=(2,)).item() == pytest.approx(0.125, rel=1e-6)
    weighted = root_rate_mean_loss(biased, mask, sample_weight=torch.tensor([2.0, 0.0]))
    assert weighted.item() == pytest.approx(0.09, rel=1e-6)


def test_the_root_mean_term_adds_its_weight_times_the_implied_motions_clip_mean_error():
    """flow_matching_loss with root_mean_weight w = the loss without it + w × root_rate_mean_loss(x̂1 − x1) on the same
    draws, without any geometry; the gradient reaches the model; the objective refuses a negative weight."""
    from mfm.flow import implied_motion_error, root_rate_mean_loss

    torch.manual_seed(0)
    model = MotionFlowTransformer(ModelConfig(feature_dim=263, latent_dim=16, ff_dim=32, num_layers=1, num_heads=2,
                                              cond_dim=4, dropout=0.0, cond_drop_prob=0.0)).eval()
    x1, cond, lengths = 0.1 * torch.randn(2, 12, 263), torch.randn(2, 4), torch.tensor([12, 7])
    t, x0 = torch.tensor([0.3, 0.8]), torch.randn(2, 12, 263)
    plain, _ = flow_matching_loss(model, x1, cond, lengths, t=t, x0=x0)
    with_term, _ = flow_matching_loss(model, x1, cond, lengths, t=t, x0=x0, root_mean_weight=2.0)
    velocity = model(interpolate(x0, x1, t), t, cond, lengths)
    value = root_rate_mean_loss(implied_motion_error(velocity, target_velocity(x0, x1), t),
                                valid_frame_mask(lengths, 12))
    assert value.item() > 0
    assert with_term.item() == pytest.approx(plain.item() + 2.0 * value.item(), rel=1e-5)
    with_term.backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
    objective = FlowMatchingObjective(root_mean_weight=1.0)
    assert objective.loss(model, x1, cond, lengths, t=t, x0=x0)[0].item() == pytest.approx(
        plain.item() + value.item(), rel=1e-5)
    with pytest.raises(ValueError, match="root_mean_weight"):
        FlowMatchingObjective(root_mean_weight=-1.0)


def test_input_perturbation_builds_the_input_from_perturbed_noise_and_keeps_the_target():
    """γ > 0: the model sees interpolate(x0 + γ·ξ, x1, t) and is charged against the velocity of x0, exactly; ξ is
    drawn after t and x0 from the same generator (or given); γ 0 draws nothing more, so a run without the option
    keeps its random stream; the objective refuses γ < 0."""
    from mfm.flow import masked_mse, sample_noise, sample_time

    torch.manual_seed(0)
    model = MotionFlowTransformer(ModelConfig(feature_dim=263, latent_dim=16, ff_dim=32, num_layers=1, num_heads=2,
                                              cond_dim=4, dropout=0.0, cond_drop_prob=0.0)).eval()
    x1, cond, lengths = torch.randn(2, 12, 263), torch.randn(2, 4), torch.tensor([12, 7])
    t, x0, xi = torch.tensor([0.3, 0.8]), torch.randn(2, 12, 263), torch.randn(2, 12, 263)
    mask = valid_frame_mask(lengths, 12)
    perturbed, _ = flow_matching_loss(model, x1, cond, lengths, t=t, x0=x0, input_perturbation=0.1, perturbation=xi)
    velocity = model(interpolate(x0 + 0.1 * xi, x1, t), t, cond, lengths)
    assert perturbed.item() == pytest.approx(masked_mse(velocity, target_velocity(x0, x1), mask).item(), rel=1e-6)
    plain, _ = flow_matching_loss(model, x1, cond, lengths, t=t, x0=x0)
    assert perturbed.item() != pytest.approx(plain.item(), rel=1e-4)
    ignored, _ = flow_matching_loss(model, x1, cond, lengths, t=t, x0=x0, perturbation=xi)  # γ 0: ξ unused
    assert ignored.item() == plain.item()

    drawn_here = torch.Generator().manual_seed(5)
    drawn, _ = flow_matching_loss(model, x1, cond, lengths, generator=drawn_here, input_perturbation=0.1)
    replay = torch.Generator().manual_seed(5)
    t_draw, x0_draw = sample_time(2, replay), sample_noise(x1, replay)
    xi_draw = sample_noise(x1, replay)
    expected, _ = flow_matching_loss(model, x1, cond, lengths, t=t_draw, x0=x0_draw, input_perturbation=0.1,
                                     perturbation=xi_draw)
    assert drawn.item() == pytest.approx(expected.item(), rel=1e-6)
    assert torch.equal(drawn_here.get_state(), replay.get_state())
    without, with_zero = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    flow_matching_loss(model, x1, cond, lengths, generator=without)
    flow_matching_loss(model, x1, cond, lengths, generator=with_zero, input_perturbation=0.0)
    assert torch.equal(without.get_state(), with_zero.get_state())
    assert FlowMatchingObjective(input_perturbation=0.1).loss(
        model, x1, cond, lengths, t=t, x0=x0, generator=torch.Generator().manual_seed(5))[0].item() > 0
    with pytest.raises(ValueError, match="input_perturbation"):
        FlowMatchingObjective(input_perturbation=-0.1)


def test_own_path_inputs_feed_each_grid_time_the_models_own_euler_state_and_charge_the_way_to_its_motion():
    """grid_inputs='own_path' (backward distillation): a row at t = k/K sees the state the model's own first k
    Euler steps reach from its noise (no gradient) and is charged against the velocity from there to its x1; a row
    at t = 0 is trained exactly as with the straight path; an oracle that heads for x1 from anywhere has zero loss."""
    from mfm.flow import own_path_inputs
    from mfm.path import velocity_from_data

    torch.manual_seed(0)
    model = MotionFlowTransformer(ModelConfig(feature_dim=6, latent_dim=16, ff_dim=32, num_layers=1, num_heads=2,
                                              cond_dim=4, dropout=0.0, cond_drop_prob=0.0)).eval()
    x1, cond, lengths = torch.randn(3, 8, 6), torch.randn(3, 4), torch.tensor([8, 5, 7])
    x0, keep = torch.randn(3, 8, 6), torch.tensor([False, True, False])  # row 1's condition dropped
    t = torch.tensor([0.0, 0.5, 0.5])
    grid = TimeSampling("grid", grid_steps=2)
    with torch.no_grad():
        first = model(x0, torch.zeros(3), cond, lengths, cond_mask=keep)
    expected_input = torch.cat([x0[:1], x0[1:] + 0.5 * first[1:]])
    assert torch.allclose(own_path_inputs(model, x0, t, cond, lengths, keep, 2), expected_input)
    expected_target = velocity_from_data(x1, expected_input, t)
    expected = masked_mse(model(expected_input, t, cond, lengths, cond_mask=keep), expected_target,
                          valid_frame_mask(lengths, 8))
    own, _ = flow_matching_loss(model, x1, cond, lengths, t=t, x0=x0, cond_mask=keep, time_sampling=grid,
                                grid_inputs="own_path")
    assert own.item() == pytest.approx(expected.item(), rel=1e-5)
    straight, _ = flow_matching_loss(model, x1, cond, lengths, t=t, x0=x0, cond_mask=keep, time_sampling=grid)
    assert own.item() != pytest.approx(straight.item(), rel=1e-3)
    at_noise = torch.zeros(3)
    assert flow_matching_loss(model, x1, cond, lengths, t=at_noise, x0=x0, cond_mask=keep, time_sampling=grid,
                              grid_inputs="own_path")[0].item() == pytest.approx(
        flow_matching_loss(model, x1, cond, lengths, t=at_noise, x0=x0, cond_mask=keep)[0].item(), rel=1e-6)

    def oracle(x, times, cond, lengths=None, *, cond_mask=None, generator=None):
        """Heads for x1 from anywhere, except that its first step aims 1 off: later states leave the straight path."""
        return velocity_from_data(x1 + (times == 0).float()[:, None, None], x, times)

    thirds = torch.tensor([1 / 3, 2 / 3, 2 / 3])
    visited = own_path_inputs(oracle, x0, thirds, cond, lengths, keep, 3)
    assert (visited - interpolate(x0, x1, thirds)).abs().min() > 0.1  # off the straight path
    zero, _ = flow_matching_loss(oracle, x1, cond, lengths, t=thirds, x0=x0, cond_mask=keep,
                                 time_sampling=TimeSampling("grid", grid_steps=3), grid_inputs="own_path")
    assert zero.item() == pytest.approx(0.0, abs=1e-10)


def test_own_path_inputs_refuse_what_they_cannot_replay():
    model = AffineStub()
    x1, cond, lengths = torch.randn(2, 4, 3), torch.randn(2, 2), torch.tensor([4, 3])
    keep, grid = torch.tensor([True, True]), TimeSampling("grid", grid_steps=2)
    with pytest.raises(ValueError, match="own_path"):
        flow_matching_loss(model, x1, cond, lengths, cond_mask=keep, grid_inputs="own_path")  # uniform times
    with pytest.raises(ValueError, match="cond_mask"):
        flow_matching_loss(model, x1, cond, lengths, time_sampling=grid, grid_inputs="own_path")
    with pytest.raises(ValueError, match="own_path"):
        flow_matching_loss(model, x1, cond, lengths, cond_mask=keep, time_sampling=grid, grid_inputs="own_path",
                           input_perturbation=0.1)
    with pytest.raises(ValueError, match="grid_inputs"):
        flow_matching_loss(model, x1, cond, lengths, grid_inputs="straight")
    with pytest.raises(ValueError, match="grid_inputs"):
        FlowMatchingObjective(grid_inputs="own_path")
    from mfm.flow import own_path_inputs
    with pytest.raises(ValueError, match="on the grid"):
        own_path_inputs(model, torch.randn(2, 4, 3), torch.tensor([0.0, 0.3]), cond, lengths, keep, 2)


def test_grid_times_replace_the_uniform_grid_in_training_and_in_the_own_path():
    """ModelConfig.sampling_times as the grid: warp_time's k-th K-quantile trains grid_times[k]; the own path steps
    0 -> 0.9 with the step 0.9, as Euler on mfm.solvers.step_grid's 0 -> 0.9 -> 1 does; step_grid applies only to
    its own step count."""
    from mfm.flow import own_path_inputs
    from mfm.solvers import solve, step_grid, uniform_grid

    u = torch.tensor([0.0, 0.3, 0.49, 0.5, 0.99])
    assert warp_time(u, "grid", grid_steps=2, grid_times=(0.0, 0.9)).tolist() == pytest.approx([0, 0, 0, 0.9, 0.9])
    with pytest.raises(ValueError, match="grid_times"):
        warp_time(u, "grid", grid_steps=3, grid_times=(0.0, 0.9))
    assert step_grid(2, (0.0, 0.9)).tolist() == [0.0, 0.9, 1.0]
    assert step_grid(1, (0.0, 0.9)) is None and step_grid(2, None) is None
    assert torch.equal(step_grid(3, (0.0, 1 / 3, 2 / 3)), uniform_grid(3))

    torch.manual_seed(0)
    model = MotionFlowTransformer(ModelConfig(feature_dim=6, latent_dim=16, ff_dim=32, num_layers=1, num_heads=2,
                                              cond_dim=4, dropout=0.0, cond_drop_prob=0.0)).eval()
    x0, cond, lengths, keep = torch.randn(2, 8, 6), torch.randn(2, 4), torch.tensor([8, 6]), torch.ones(2, dtype=bool)
    t = torch.tensor([0.9, 0.0])
    visited = own_path_inputs(model, x0, t, cond, lengths, keep, 2, grid_times=(0.0, 0.9))

    def field(x, times):
        return model(x, times, cond, lengths, cond_mask=keep)

    first_step = solve(field, x0, grid=[0.0, 0.9]).x1  # the 2-step sampler's first step on 0 -> 0.9 -> 1
    assert torch.allclose(visited[0], first_step[0], atol=1e-6) and torch.equal(visited[1], x0[1])
    with pytest.raises(ValueError, match="on the grid"):
        own_path_inputs(model, x0, torch.tensor([0.5, 0.0]), cond, lengths, keep, 2, grid_times=(0.0, 0.9))
    with pytest.raises(ValueError, match="time_grid_times"):
        FlowMatchingObjective(time_grid_times=(0.0, 0.9))  # uniform times
    assert FlowMatchingObjective(time_sampling="grid", time_grid_steps=2, time_grid_times=(0.0, 0.9)).loss(
        model, torch.randn(2, 8, 6), cond, lengths, cond_mask=keep,
        generator=torch.Generator().manual_seed(0))[0].item() > 0
