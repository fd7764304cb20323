"""The output smoothing that keeps the bones' lengths (``model.output_smoothing_keeps_bones``): a Gaussian filter
over time shortens a limb that swings fast; restoring each bone's length per frame keeps the filter's smoothing of
the bones' directions and nothing else. Checked on the real HumanML3D clip (../shared/reference-data)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from scipy.ndimage import gaussian_filter1d

from mfm.diffusion_sampling import BoneKeeping, smooth_over_time
from mfm.features import features_to_joints, restore_bone_lengths, ric_bone_lengths, set_ric_bone_lengths
from mfm.layout import FeatureLayout
from mfm.metrics import bone_lengths
from mfm.model import ModelConfig
from mfm.skeleton import get_skeleton

HUMANML3D = get_skeleton("humanml3d")
CLIP = "012314"


@pytest.fixture
def clip(reference_data: Path) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(features (170, 263) float64, Mean, Std) of the real HumanML3D clip."""
    folder = reference_data / "humanml3d"
    features = torch.as_tensor(np.load(folder / f"new_joint_vecs_{CLIP}.npy"), dtype=torch.float64)
    mean = torch.as_tensor(np.load(folder / "Mean.npy"), dtype=torch.float64)
    std = torch.as_tensor(np.load(folder / "Std.npy"), dtype=torch.float64)
    return features, mean, std


def bones_of(features: torch.Tensor) -> np.ndarray:
    return bone_lengths(features_to_joints(features.numpy(), HUMANML3D), HUMANML3D.parents)


def directions_of(features: torch.Tensor) -> np.ndarray:
    joints = features_to_joints(features.numpy(), HUMANML3D)
    parents = HUMANML3D.parents
    children = np.flatnonzero(parents >= 0)
    vectors = joints[:, children] - joints[:, parents[children]]
    return vectors / np.linalg.norm(vectors, axis=-1, keepdims=True)


def test_restoring_gives_every_bone_its_length_back_along_the_smoothed_direction(clip):
    features, mean, std = clip
    jittered = features.clone()
    jittered[1::2, FeatureLayout(HUMANML3D).slices["ric"]] *= 1.06  # every other frame's pose 6 % larger
    smoothed = smooth_over_time(jittered[None], [len(jittered)], 3.0)[0]
    # the plain filter changes the lengths (the average of a 1.06 and a 1.0 pose, and arcs cut short) ...
    assert np.abs(bones_of(smoothed) - bones_of(jittered)).max() > 0.01
    restored = restore_bone_lengths(smoothed, jittered, HUMANML3D)
    # ... restoring gives each frame's bones their lengths before the filter, in the filter's directions
    np.testing.assert_allclose(bones_of(restored), bones_of(jittered), atol=1e-6)
    np.testing.assert_allclose(directions_of(restored), directions_of(smoothed), atol=1e-6)
    ric = FeatureLayout(HUMANML3D).slices["ric"]
    other = torch.ones(features.shape[-1], dtype=torch.bool)
    other[ric] = False
    torch.testing.assert_close(restored[:, other], smoothed[:, other], rtol=0, atol=0)


def test_a_clip_whose_bones_already_have_their_lengths_is_left_as_it_is(clip):
    features, _, _ = clip
    torch.testing.assert_close(restore_bone_lengths(features, features, HUMANML3D), features, rtol=0, atol=1e-9)


def test_smoothing_with_bone_keeping_on_normalised_batches_leaves_padding_alone(clip):
    features, mean, std = clip
    normalised = torch.zeros(2, 170, features.shape[-1], dtype=torch.float64)
    normalised[0] = (features - mean) / std
    normalised[1, :90] = (features[40:130] - mean) / std
    normalised[1, 90:] = 7.0  # padding: must come back as it went in
    lengths = [170, 90]
    plain = smooth_over_time(normalised, lengths, 1.5)
    kept = smooth_over_time(normalised, lengths, 1.5, BoneKeeping(HUMANML3D, mean, std))
    assert torch.equal(kept[1, 90:], normalised[1, 90:])
    for b, n in enumerate(lengths):
        before = bones_of(normalised[b, :n] * std + mean)
        np.testing.assert_allclose(bones_of(kept[b, :n] * std + mean), before, atol=1e-6)
        assert np.abs(bones_of(plain[b, :n] * std + mean) - before).max() > 1e-3
    assert torch.equal(smooth_over_time(normalised, lengths, 0.0, BoneKeeping(HUMANML3D, mean, std)), normalised)


def test_ric_bone_lengths_are_the_joints_bone_lengths_and_setting_them_moves_only_the_ric_block(clip):
    features, _, _ = clip
    lengths = ric_bone_lengths(features, HUMANML3D)
    assert lengths.shape == (170, HUMANML3D.num_joints - 1)
    # the joints' bones (parents[j] -> j, in joint order) are the ric block's: recovery only rotates and translates
    np.testing.assert_allclose(lengths.numpy(), bones_of(features)[0], atol=1e-6)  # bones_of: (1, T, J-1)
    torch.testing.assert_close(set_ric_bone_lengths(features, lengths, HUMANML3D), features, rtol=0, atol=1e-9)
    wanted = lengths * torch.linspace(0.9, 1.1, 170, dtype=torch.float64)[:, None]  # a skeleton that grows
    moved = set_ric_bone_lengths(features, wanted, HUMANML3D)
    torch.testing.assert_close(ric_bone_lengths(moved, HUMANML3D), wanted, rtol=0, atol=1e-9)
    np.testing.assert_allclose(directions_of(moved), directions_of(features), atol=1e-9)
    batched = set_ric_bone_lengths(torch.stack([features, features]), torch.stack([wanted, lengths]), HUMANML3D)
    torch.testing.assert_close(batched[0], moved, rtol=0, atol=1e-12)
    torch.testing.assert_close(batched[1], features, rtol=0, atol=1e-9)


def test_smoothed_bone_keeping_filters_each_bones_length_as_a_number(clip):
    """"smoothed": the bones get their lengths before the filter smoothed over time with the same σ, so a
    frame's length jitter is not put back (each frame's own, "frame", puts it back); the directions are the plain
    filter's in both, and the padding is left alone."""
    features, mean, std = clip
    jittered = features.clone()
    jittered[1::2, FeatureLayout(HUMANML3D).slices["ric"]] *= 1.06  # every other frame's pose 6 % larger
    normalised = torch.zeros(2, 170, features.shape[-1], dtype=torch.float64)
    normalised[0] = (jittered - mean) / std
    normalised[1, :90] = (jittered[40:130] - mean) / std
    normalised[1, 90:] = 7.0
    lengths, sigma = [170, 90], 1.5
    plain = smooth_over_time(normalised, lengths, sigma)
    per_frame = smooth_over_time(normalised, lengths, sigma, BoneKeeping(HUMANML3D, mean, std))
    smoothed = smooth_over_time(normalised, lengths, sigma, BoneKeeping(HUMANML3D, mean, std, lengths="smoothed"))
    assert torch.equal(smoothed[1, 90:], normalised[1, 90:])
    for b, n in enumerate(lengths):
        before = ric_bone_lengths(normalised[b, :n] * std + mean, HUMANML3D).numpy()
        expected = gaussian_filter1d(before, sigma=sigma, axis=0)
        np.testing.assert_allclose(ric_bone_lengths(smoothed[b, :n] * std + mean, HUMANML3D).numpy(), expected,
                                   atol=1e-9)
        np.testing.assert_allclose(directions_of(smoothed[b, :n] * std + mean),
                                   directions_of(plain[b, :n] * std + mean), atol=1e-9)
        jitter = {name: np.abs(np.diff(ric_bone_lengths(x[b, :n] * std + mean, HUMANML3D).numpy(), axis=0)).mean()
                  for name, x in (("frame", per_frame), ("smoothed", smoothed))}
        assert jitter["smoothed"] < 0.2 * jitter["frame"]  # the 6 % every other frame is smoothed away


def test_the_setting_maps_to_its_bone_keeping():
    mean, std = torch.zeros(263), torch.ones(263)
    assert BoneKeeping.for_setting(False, HUMANML3D, mean, std) is None
    assert BoneKeeping.for_setting(True, HUMANML3D, mean, std).lengths == "frame"
    assert BoneKeeping.for_setting("smoothed", HUMANML3D, mean, std).lengths == "smoothed"
    with pytest.raises(ValueError, match="output_smoothing_keeps_bones"):
        BoneKeeping.for_setting(1, HUMANML3D, mean, std)


def test_the_model_option_is_validated():
    assert ModelConfig().output_smoothing_keeps_bones is False  # FLAME's plain filter unless a preset says so
    assert ModelConfig(output_smoothing_keeps_bones="smoothed").output_smoothing_keeps_bones == "smoothed"
    for wrong in ("yes", 1, 0, None):
        with pytest.raises(ValueError, match="output_smoothing_keeps_bones"):
            ModelConfig(output_smoothing_keeps_bones=wrong)


def test_a_sample_request_and_launch_sample_take_the_three_settings(capsys):
    import argparse

    from pipeline.generation.request import SampleRequest, SamplingError, add_request_flags, flag_values

    parser = argparse.ArgumentParser()
    add_request_flags(parser)
    for text, setting in (("true", True), ("off", False), ("smoothed", "smoothed")):
        assert flag_values(parser.parse_args(["--smoothing-keeps-bones", text]))["smoothing_keeps_bones"] == setting
        request = SampleRequest("run", "out", texts=("a person walks",), smoothing_keeps_bones=setting)
        assert request.smoothing_keeps_bones == setting
    with pytest.raises(SystemExit):
        parser.parse_args(["--smoothing-keeps-bones", "maybe"])
    assert "true, false or smoothed, got 'maybe'" in capsys.readouterr().err
    with pytest.raises(SamplingError, match="smoothing_keeps_bones must be true, false or smoothed"):
        SampleRequest("run", "out", texts=("a person walks",), smoothing_keeps_bones="maybe")
