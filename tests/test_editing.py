import numpy as np
import pytest
import torch

from mfm.editing import (
    EDIT_SETTINGS,
    edit,
    edit_mask,
    inbetween_mask,
    interpolation_mask,
    joint_frame_mask,
    motion_to_features,
    prediction_mask,
    upper_body_mask,
)
from mfm.layout import FeatureLayout
from mfm.skeleton import HUMANML3D, KIT
from mfm.solvers import guided_velocity, initial_noise, solve, uniform_grid

HML = FeatureLayout(HUMANML3D)
KIT_LAYOUT = FeatureLayout(KIT)


def inclusive_ranges(*ranges):
    return sorted(i for lo, hi in ranges for i in range(lo, hi + 1))


# MFM's upper-body edit regenerates exactly these 263-D dims (reference notes §1.5, recomputed from edit.py).
HML_UPPER_BODY_DIMS = inclusive_ranges(
    (10, 12), (19, 21), (28, 30), (37, 66), (79, 84), (97, 102), (115, 120), (133, 192),
    (202, 204), (211, 213), (220, 222), (229, 258),
)


def motion(batch=2, frames=12, dim=5, seed=0):
    return torch.randn(batch, frames, dim, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def drifting_field(x, t):
    """An elementwise field that leaves the straight noise→data line (so rewrites are visible)."""
    return torch.sin(x) - 0.5 * x + t.view(-1, 1, 1)


# ---------------------------------------------------------------------------------------------------
# trajectory rewriting


def test_known_region_equals_the_source_with_an_exact_straight_line_field():
    # The exact OT field toward the source, v = (x1 - x)/(1 - t), equals x1 - x0 on the line: with ς = 1 every step
    # starts on the line and the last (un-rewritten) Euler step lands exactly on the source.
    source, target = motion(seed=1), motion(seed=2)
    keep = prediction_mask([12, 8], 12, FeatureLayout(HUMANML3D))[..., :5]
    goal = torch.where(keep, source, target)
    field = lambda x, t: (goal - x) / (1 - t.view(-1, 1, 1))
    result = edit(field, source, keep, steps=10, rewrite_until=1.0, seed=3)
    torch.testing.assert_close(result.x1[keep], source[keep], rtol=0, atol=1e-12)
    torch.testing.assert_close(result.x1[~keep], target[~keep], rtol=0, atol=1e-12)


def test_rewrite_until_one_leaves_only_the_last_steps_drift():
    source = motion(seed=1)
    keep = torch.zeros_like(source, dtype=torch.bool)
    keep[:, :4] = True
    x0 = initial_noise(source.shape, seed=9, dtype=torch.float64)
    steps = 8
    result = edit(drifting_field, source, keep, steps=steps, rewrite_until=1.0, x0=x0)
    t_last = (steps - 1) / steps
    on_line = (1 - t_last) * x0 + t_last * source
    expected = on_line + (1 / steps) * drifting_field(on_line, torch.full((2,), t_last, dtype=torch.float64))
    torch.testing.assert_close(result.x1[keep], expected[keep])
    assert result.nfe == steps


class RecordingField:
    def __init__(self, fn):
        self.fn, self.states, self.times = fn, [], []

    def __call__(self, x, t):
        self.states.append(x.clone())
        self.times.append(float(t[0]))
        return self.fn(x, t)


@pytest.mark.parametrize("grid", [None, [0.0, 0.05, 0.2, 0.35, 0.6, 1.0]])
def test_rewrite_happens_before_steps_starting_at_or_before_rewrite_until(grid):
    source = motion(seed=4)
    keep = torch.zeros_like(source, dtype=torch.bool)
    keep[0, :, :2] = True
    x0 = initial_noise(source.shape, seed=5, dtype=torch.float64)
    field = RecordingField(drifting_field)
    result = edit(field, source, keep, steps=10, grid=grid, rewrite_until=0.2, x0=x0, return_trajectory=True)
    times = (uniform_grid(10) if grid is None else torch.tensor(grid, dtype=torch.float64)).tolist()[:-1]
    assert field.times == pytest.approx(times)
    for state, t in zip(field.states, times):
        on_line = torch.allclose(state[keep], ((1 - t) * x0 + t * source)[keep], rtol=0, atol=1e-12)
        assert on_line == (t <= 0.2 + 1e-9), t  # inclusive at ς = 0.2 (the grid point 2/10)
        # The unknown part is never overwritten.
    assert result.x1_hat.shape[0] == len(times)
    torch.testing.assert_close(result.x1_hat[-1], result.x1)  # Euler: the last x̂1 is the final state


def test_rewrite_until_zero_is_plain_sampling_from_the_same_noise():
    source = motion(seed=6)
    keep = torch.ones_like(source, dtype=torch.bool)
    x0 = initial_noise(source.shape, seed=1, dtype=torch.float64)
    edited = edit(drifting_field, source, keep, steps=6, rewrite_until=0.0, x0=x0)
    torch.testing.assert_close(edited.x1, solve(drifting_field, x0, steps=6).x1)


def test_edit_settings_steps_per_preset_and_their_sources():
    """paper: 30 steps for every preset, cited to the MFM paper (§4.1), not edit.py. reference-debug: edit.py's
    step_size 0.01 (100 steps) except interpolate's step_size 1 (edit.py: 96-99): one Euler step."""
    paper, debug = EDIT_SETTINGS["paper"], EDIT_SETTINGS["reference-debug"]
    presets = ("prediction", "inbetween", "interpolation", "upper_body", "joints")
    assert [paper.steps_for(p) for p in presets] == [30] * 5
    assert "§4.1" in paper.source and "not from edit.py" in paper.source
    assert [debug.steps_for(p) for p in presets] == [100, 100, 1, 100, 100]
    assert "96-99" in debug.source and debug.record()["steps_per_preset"] == {"interpolation": 1}
    with pytest.raises(ValueError, match="no steps for preset 'teleport'"):
        debug.steps_for("teleport")


def test_one_step_interpolation_as_edit_py_never_sees_the_source():
    """edit.py's interpolate preset: one Euler step from t = 0 with edit_till 1.0. Its only rewrite is at t = 0, where
    the known line's point (1 − t)·x0 + t·x1 is the noise x0 itself: the result is plain one-step sampling."""
    source = motion(seed=8)
    keep = interpolation_mask([12, 12], 12, FeatureLayout(HUMANML3D), every=5)[..., :5]
    assert keep.any() and not keep.all()
    x0 = initial_noise(source.shape, seed=2, dtype=torch.float64)
    debug = EDIT_SETTINGS["reference-debug"]
    edited = edit(drifting_field, source, keep, steps=debug.steps_for("interpolation"),
                  rewrite_until=debug.rewrite_time("interpolation"), x0=x0)
    torch.testing.assert_close(edited.x1, solve(drifting_field, x0, steps=1).x1, rtol=0, atol=0)
    assert edited.nfe == 1


def test_edit_is_deterministic_given_a_seed_and_uses_the_given_noise():
    source = motion(seed=7).float()
    keep = upper_body_mask(12, FeatureLayout(HUMANML3D))[..., :5]
    a = edit(drifting_field, source, keep, steps=5, seed=11)
    b = edit(drifting_field, source, keep, steps=5, seed=11)
    c = edit(drifting_field, source, keep, steps=5, seed=12)
    d = edit(drifting_field, source, keep, steps=5, x0=initial_noise(source.shape, seed=11))
    assert torch.equal(a.x1, b.x1) and torch.equal(a.x1, d.x1)
    assert not torch.allclose(a.x1, c.x1)


def test_edit_zeroes_padding_and_accepts_other_fixed_step_solvers():
    source = motion(seed=8)
    source[1, 5:] = 0
    keep = inbetween_mask([12, 5], 12, HML)[..., :5]
    result = edit(drifting_field, source, keep, steps=4, solver="rk4", rewrite_until=0.5, lengths=[12, 5])
    assert result.nfe == 16
    assert torch.count_nonzero(result.x1[1, 5:]) == 0


class FakeTextModel(torch.nn.Module):
    """Same forward signature as MotionFlowTransformer: the condition shifts the field unless dropped."""

    def __init__(self):
        super().__init__()
        self.batches = []

    def forward(self, x, t, cond, lengths=None, *, cond_mask=None):
        self.batches.append(x.shape[0])
        kept = cond * (~cond_mask).unsqueeze(1) if cond_mask is not None else cond
        return -x + t.view(-1, 1, 1) + kept.sum(1).view(-1, 1, 1)


def test_edit_with_a_guided_model_velocity():
    model = FakeTextModel()
    source = motion(seed=9).float()
    keep = prediction_mask([12, 12], 12, HML)[..., :5]
    cond = torch.randn(2, 3)
    guided = edit(guided_velocity(model, cond, scale=2.5), source, keep, steps=4, rewrite_until=1.0)
    unconditional = edit(guided_velocity(model, cond, scale=0.0), source, keep, steps=4, rewrite_until=1.0)
    assert model.batches == [4] * 4 + [2] * 4
    assert guided.x1.shape == source.shape and not torch.allclose(guided.x1[~keep], unconditional.x1[~keep])


def test_edit_rejects_bad_inputs():
    source = motion()
    with pytest.raises(ValueError, match="bool"):
        edit(drifting_field, source, torch.ones_like(source), steps=2)
    with pytest.raises(ValueError, match="does not broadcast"):
        edit(drifting_field, source, torch.ones(2, 7, 5, dtype=torch.bool), steps=2)
    with pytest.raises(ValueError, match="rewrite_until"):
        edit(drifting_field, source, torch.ones_like(source, dtype=torch.bool), rewrite_until=1.5)
    with pytest.raises(ValueError, match="fixed-step"):
        edit(drifting_field, source, torch.ones_like(source, dtype=torch.bool), solver="dopri5")


# ---------------------------------------------------------------------------------------------------
# masks


@pytest.mark.parametrize("layout", [HML, KIT_LAYOUT], ids=["humanml3d", "kit"])
def test_frame_masks_have_the_right_shapes_and_counts(layout):
    lengths, frames = [40, 196, 101], 196
    d = layout.dim
    pred = prediction_mask(lengths, frames, layout)
    assert pred.shape == (3, frames, d) and pred.dtype == torch.bool
    assert pred[:, :, 0].sum(1).tolist() == [10, 49, 25]
    assert pred[2, :25].all() and not pred[2, 25:].any()

    between = inbetween_mask(lengths, frames, layout)
    assert between.shape == (3, frames, d)
    # ⌊0.25L⌋ + (T - ⌊0.75L⌋): 10 + 166, 49 + 49, 25 + 121
    assert between[:, :, 0].sum(1).tolist() == [176, 98, 146]
    assert between[0, 9].all() and not between[0, 10:30].any() and between[0, 30:].all()

    interp = interpolation_mask(lengths, frames, layout, every=5)
    assert interp.shape == (3, frames, d)
    # MFM's edit.py keeps i·5 for i in range(196 // 5): frames 0 … 190, 39 of them (195 is generated)
    assert interp[:, :, 0].sum(1).tolist() == [39, 39, 39]
    assert interp[:, 0].all() and interp[:, 190].all() and not interp[:, 195].any() and not interp[:, 1].any()
    assert interpolation_mask([20], 20, layout, every=5)[0, :, 0].nonzero().flatten().tolist() == [0, 5, 10, 15]
    for mask in (pred, between, interp):  # frame masks keep whole frames
        assert torch.equal(mask.all(-1), mask.any(-1))
    assert torch.equal(edit_mask("inbetween", lengths, frames, layout), between)


def test_humanml3d_upper_body_preset_regenerates_exactly_the_reference_dims():
    mask = upper_body_mask(196, HML)
    assert mask.shape == (1, 196, 263) and mask.dtype == torch.bool
    regenerated = torch.nonzero(~mask[0, 0]).flatten().tolist()
    assert len(HML_UPPER_BODY_DIMS) == 156
    assert regenerated == HML_UPPER_BODY_DIMS
    assert torch.equal(mask[0], mask[0, :1].expand(196, -1))
    assert edit_mask("upper_body", [10, 20], 196, HML).shape == (2, 196, 263)


def test_kit_upper_body_preset_regenerates_the_upper_joints():
    mask = upper_body_mask(30, KIT_LAYOUT)
    assert mask.shape == (1, 30, 251)
    upper = [j for j in range(KIT.num_joints) if j not in KIT.lower_body_joints]
    assert upper == list(range(1, 11))  # torso, neck, head and both arms
    # Each non-root joint owns 3 ric + 6 rot6d + 3 velocity dims and none of the feet contacts.
    assert int((~mask[0, 0]).sum()) == 12 * len(upper) == 120
    assert torch.equal(torch.nonzero(~mask[0, 0]).flatten(), torch.from_numpy(KIT_LAYOUT.dims_for_joints(upper)))


def test_joint_frame_mask_selects_frames_times_joint_dims():
    mask = joint_frame_mask(20, HML, frames=[0, 3, 19], joints=["left_wrist", 21])
    assert mask.shape == (1, 20, 263)
    wrist_dims = HML.dims_for_joints([20, 21])
    assert len(wrist_dims) == 24
    assert int(mask.sum()) == 3 * 24
    assert mask[0, 3, wrist_dims].all() and not mask[0, 4].any()
    by_slice = joint_frame_mask(20, HML, frames=slice(0, 5), joints=[0])
    assert by_slice[0, :5].sum(-1).tolist() == [7] * 5  # root: 4 root dims + 3 local velocity dims
    kit = joint_frame_mask(10, KIT_LAYOUT, frames=np.arange(10) % 2 == 0, joints=["left_toe"])
    assert int(kit.sum()) == 5 * 13  # 12 dims + its foot contact
    with pytest.raises(ValueError, match="unknown joint"):
        joint_frame_mask(10, HML, frames=[0], joints=["tail"])
    with pytest.raises(ValueError, match="frame indices"):
        joint_frame_mask(10, HML, frames=[10], joints=[1])


def test_mask_presets_reject_bad_arguments():
    with pytest.raises(ValueError, match="lengths"):
        prediction_mask([0, 5], 10, HML)
    with pytest.raises(ValueError, match="prefix <= suffix"):
        inbetween_mask([5], 10, HML, prefix=0.8, suffix=0.5)
    with pytest.raises(ValueError, match="unknown edit preset"):
        edit_mask("sideways", [5], 10, HML)


# ---------------------------------------------------------------------------------------------------
# source motions


def test_motion_to_features_passes_features_and_normalises(reference_data):
    features = np.load(reference_data / "humanml3d" / "new_joint_vecs_012314.npy")
    mean = np.load(reference_data / "humanml3d" / "Mean.npy")
    std = np.load(reference_data / "humanml3d" / "Std.npy")
    out = motion_to_features(features, HUMANML3D)
    assert out.dtype == torch.float32 and out.shape == features.shape
    np.testing.assert_array_equal(out.numpy(), features.astype(np.float32))
    normalised = motion_to_features(features, HUMANML3D, mean=mean, std=std)
    np.testing.assert_allclose(normalised.numpy(), (features - mean) / std, rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="D = 251"):
        motion_to_features(features, KIT)


def test_motion_to_features_converts_joints(reference_data):
    from mfm.features import joints_to_features

    joints = np.load(reference_data / "humanml3d" / "new_joints_012314.npy")
    features = np.load(reference_data / "humanml3d" / "new_joint_vecs_012314.npy")
    out = motion_to_features(joints, HUMANML3D)
    assert out.shape == (joints.shape[0] - 1, 263)
    np.testing.assert_array_equal(out.numpy(), joints_to_features(joints, HUMANML3D))
    # The joints were recovered from these features, so re-extraction reproduces the root-relative positions up to
    # the millimetres that retargeting to the uniform skeleton moves them.
    ric = HML.slices["ric"]
    np.testing.assert_allclose(out.numpy()[:, ric], features[:-1, ric], atol=1e-2)
    with pytest.raises(ValueError, match="J = 21"):
        motion_to_features(joints, KIT)
