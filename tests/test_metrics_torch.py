"""mfm.metrics_torch against its numpy reference mfm.metrics on random clips of different lengths: the same numbers
(float64: 1e-9 relative; float32: 1e-5), every clip masked to its own frames, and the same errors for bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mfm import metrics, metrics_torch
from mfm.skeleton import HUMANML3D, KIT, Skeleton

FIGURES = ("bone_length_range", "bone_length_deviation", "floor_penetration", "foot_skating_ratio",
           "contact_foot_speed", "skating_foot_speed", "mean_jerk", "pose_speed", "root_speed", "pose_spread")


def random_clips(skeleton: Skeleton, lengths: list[int], seed: int, frames: int | None = None) -> np.ndarray:
    """(N, T, J, 3) float64 clips in the skeleton's unit: a body walking about the floor, its feet dipping below and
    lifting above the contact height, joints jittering (so bones stretch and some feet skate); garbage past each
    length (padding must not count)."""
    rng = np.random.default_rng(seed)
    n, t, j = len(lengths), frames or max(lengths), skeleton.num_joints
    body = rng.normal(0.0, 0.3, (n, 1, j, 3)) + np.array([0.0, 0.9, 0.0])
    walk = np.cumsum(rng.normal(0.0, 0.03, (n, t, 1, 3)) * np.array([1.0, 0.0, 1.0]), axis=1)
    clips = body + walk + rng.normal(0.0, 0.02, (n, t, j, 3))
    feet = list(skeleton.foot_left + skeleton.foot_right)
    clips[:, :, feet, 1] = rng.uniform(-0.03, 0.12, (n, t, len(feet)))
    clips[:, :, 3] = clips[:, :, 0]  # a bone of length 0: left out of the relative deviation
    for i, length in enumerate(lengths):
        clips[i, length:] = rng.normal(0.0, 50.0, clips[i, length:].shape)
    return clips / metrics.METRES_PER_UNIT[skeleton.unit]


def assert_close(got, want, rtol: float, atol: float = 0.0) -> None:
    np.testing.assert_allclose(np.asarray(got, dtype=np.float64), np.asarray(want, dtype=np.float64), rtol=rtol,
                               atol=atol, equal_nan=True)


LENGTHS = [1, 2, 3, 4, 7, 40, 61, 64]  # a single frame (no frame pair), too short for jerk, full length


@pytest.mark.parametrize("skeleton", [HUMANML3D, KIT], ids=lambda s: s.name)
def test_plausibility_figures_equal_the_numpy_reference_in_float64(skeleton):
    clips = random_clips(skeleton, LENGTHS, seed=1)
    want = metrics.plausibility(clips, skeleton, LENGTHS)
    got = metrics_torch.plausibility(torch.from_numpy(clips), skeleton, torch.tensor(LENGTHS))
    assert set(got.names) == set(FIGURES) == set(want.names)
    for name in FIGURES:
        assert_close(getattr(got, name), getattr(want, name), rtol=1e-9, atol=1e-12)
    # the figures are not trivially equal: every kind of value occurs
    assert np.isnan(want.foot_skating_ratio[0]) and np.isnan(want.mean_jerk[2]) and want.mean_jerk[3] > 0
    assert (want.floor_penetration > 0).any() and (want.foot_skating_ratio > 0).any()
    assert (want.foot_skating_ratio[1:] < 1).any() and (want.bone_length_deviation[1:] > 0).all()


def test_plausibility_in_float32_is_within_1e_5_of_the_float64_reference():
    lengths = [40, 61, 64, 12]
    clips = random_clips(HUMANML3D, lengths, seed=2)
    want = metrics.plausibility(clips.astype(np.float32).astype(np.float64), HUMANML3D, lengths)
    got = metrics_torch.plausibility(torch.from_numpy(clips).float(), HUMANML3D, torch.tensor(lengths))
    for name in FIGURES:
        if name == "foot_skating_ratio":  # a count of thresholded pairs: float32 may tip one pair at a threshold
            assert_close(getattr(got, name), getattr(want, name), rtol=0, atol=1.5 / min(lengths))
        else:
            assert_close(getattr(got, name), getattr(want, name), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("skeleton, floor", [(HUMANML3D, False), (HUMANML3D, True), (KIT, True)],
                         ids=["humanml3d", "humanml3d-temos-floor", "kit-temos-floor"])
def test_ape_ave_equals_the_numpy_reference(skeleton, floor):
    lengths = [2, 3, 17, 40, 64]
    pred, gt = random_clips(skeleton, lengths, seed=3), random_clips(skeleton, lengths, seed=4)
    kwargs = {"face_joints": skeleton.face_joints, "metres_per_unit": metrics.METRES_PER_UNIT[skeleton.unit],
              "floor_joints": skeleton.foot_left + skeleton.foot_right if floor else None}
    want = metrics.ape_ave(pred, gt, lengths, **kwargs)
    got = metrics_torch.ape_ave(torch.from_numpy(pred), torch.from_numpy(gt), torch.tensor(lengths), **kwargs)
    assert list(got) == list(want)
    assert_close([got[k] for k in want], [want[k] for k in want], rtol=1e-9)
    assert min(want.values()) > 1e-4  # every part differs between the two sets
    got32 = metrics_torch.ape_ave(torch.from_numpy(pred).float(), torch.from_numpy(gt).float(),
                                  torch.tensor(lengths), **kwargs)
    want32 = metrics.ape_ave(pred.astype(np.float32), gt.astype(np.float32), lengths, **kwargs)
    assert_close([got32[k] for k in want], [want32[k] for k in want], rtol=1e-5)
    # without heading canonicalisation, another root
    plain = metrics.ape_ave(pred, gt, lengths, root=2)
    assert_close(list(metrics_torch.ape_ave(torch.from_numpy(pred), torch.from_numpy(gt), torch.tensor(lengths),
                                            root=2).values()), list(plain.values()), rtol=1e-9)


def test_ade_fde_equal_the_numpy_reference_with_and_without_a_frame_mask():
    lengths = [5, 17, 40, 64]
    pred, gt = random_clips(KIT, lengths, seed=5), random_clips(KIT, lengths, seed=6)
    mask = np.zeros((len(lengths), 64), bool)
    mask[:, 3:30] = True
    tensors = torch.from_numpy(pred), torch.from_numpy(gt), torch.tensor(lengths)
    for frames in (None, mask, mask[0]):
        want = metrics.ade(pred, gt, lengths, mask_frames=frames, metres_per_unit=1e-3)
        got = metrics_torch.ade(*tensors, mask_frames=None if frames is None else torch.from_numpy(frames),
                                metres_per_unit=1e-3)
        assert got == pytest.approx(want, rel=1e-9)
    assert metrics_torch.fde(*tensors, metres_per_unit=1e-3) == pytest.approx(
        metrics.fde(pred, gt, lengths, metres_per_unit=1e-3), rel=1e-9)


def test_joint_variance_per_group_equals_the_numpy_reference_per_text():
    lengths = [30, 30, 30, 12, 12, 50, 50, 50, 50]
    groups = [7, 7, 7, 2, 2, 9, 9, 9, 9]  # the evaluator's texts: every repetition of a text has its length
    clips = random_clips(HUMANML3D, lengths, seed=7)
    order = np.random.default_rng(0).permutation(len(lengths))  # groups need not be contiguous
    clips, lengths, groups = clips[order], np.asarray(lengths)[order], np.asarray(groups)[order]
    ids, values = metrics_torch.joint_variance_per_group(torch.from_numpy(clips), torch.from_numpy(groups),
                                                         torch.from_numpy(lengths))
    assert ids == [2, 7, 9]
    want = [metrics.joint_variance(clips[groups == g][:, : lengths[groups == g][0]]) for g in ids]
    assert_close(values, want, rtol=1e-9)
    with pytest.raises(ValueError, match="at least 2 samples per group"):
        metrics_torch.joint_variance_per_group(torch.from_numpy(clips), torch.arange(len(groups)),
                                               torch.from_numpy(lengths))
    with pytest.raises(ValueError, match="one length"):
        metrics_torch.joint_variance_per_group(torch.from_numpy(clips), torch.zeros(len(groups), dtype=torch.int64),
                                               torch.from_numpy(lengths))


def test_bad_inputs_raise_the_numpy_references_errors():
    clips = torch.from_numpy(random_clips(HUMANML3D, [10, 10], seed=8))
    with pytest.raises(ValueError, match=r"lengths must lie in \[1, 10\]"):
        metrics_torch.plausibility(clips, HUMANML3D, torch.tensor([0, 10]))
    with pytest.raises(ValueError, match=r"lengths must lie in \[2, 10\]"):
        metrics_torch.ape_ave(clips, clips, torch.tensor([1, 10]))
    with pytest.raises(ValueError, match="one entry per sequence"):
        metrics_torch.plausibility(clips, HUMANML3D, torch.tensor([10]))
    bad = clips.clone()
    bad[1, 3, 0, 0] = torch.nan
    with pytest.raises(ValueError, match="joints contains NaN or inf"):
        metrics_torch.plausibility(bad, HUMANML3D, torch.tensor([10, 10]))
    with pytest.raises(ValueError, match="gt_joints contains NaN or inf"):
        metrics_torch.ape_ave(clips, bad, torch.tensor([10, 10]))
    with pytest.raises(ValueError, match="skeleton 'kit'"):
        metrics_torch.plausibility(clips, KIT, torch.tensor([10, 10]))
    with pytest.raises(ValueError, match="no frame to evaluate"):
        metrics_torch.ade(clips, clips, torch.tensor([10, 10]), mask_frames=torch.zeros(10, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"\(N, T, J, 3\) tensor"):
        metrics_torch.ape_ave(clips[0], clips[0])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA: the device path is the CPU path's code")
def test_on_cuda_the_figures_equal_the_cpu_ones():
    lengths = [4, 40, 64]
    clips = torch.from_numpy(random_clips(HUMANML3D, lengths, seed=9))
    lens = torch.tensor(lengths)
    cpu, cuda = (metrics_torch.plausibility(clips.to(d), HUMANML3D, lens.to(d)) for d in ("cpu", "cuda"))
    for name in FIGURES:
        assert_close(getattr(cuda, name), getattr(cpu, name), rtol=1e-9, atol=1e-12)
    kwargs = {"face_joints": HUMANML3D.face_joints, "floor_joints": HUMANML3D.foot_left + HUMANML3D.foot_right}
    ape = [metrics_torch.ape_ave(clips.to(d), clips.flip(0).to(d), lens.to(d), **kwargs) for d in ("cpu", "cuda")]
    assert_close(list(ape[1].values()), list(ape[0].values()), rtol=1e-9)


# ---------------------------------------------------------------------------------------------------------------
# The evaluator's joints phase (pipeline.evaluation.replications) on the torch path
# ---------------------------------------------------------------------------------------------------------------


def load_bench_eval():
    """benchmarks/bench_eval.py as a module (benchmarks/ is a folder of scripts, not a package)."""
    import importlib.util
    import sys
    from pathlib import Path

    if "bench_eval" not in sys.modules:
        path = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_eval.py"
        spec = importlib.util.spec_from_file_location("bench_eval", path)
        module = importlib.util.module_from_spec(spec)
        sys.modules["bench_eval"] = module
        spec.loader.exec_module(module)
    return sys.modules["bench_eval"]


class NumpyJointMetrics:
    """mfm.metrics_torch's interface on the numpy reference, as the evaluator scored joints before: the joints
    brought to the host, then mfm.metrics (which takes tensors)."""

    plausibility = staticmethod(metrics.plausibility)
    ape_ave = staticmethod(metrics.ape_ave)
    ade = staticmethod(metrics.ade)
    fde = staticmethod(metrics.fde)

    @staticmethod
    def joint_variance_per_group(joints, groups, lengths):
        joints, groups, lens = (x.cpu().numpy() for x in (joints, groups, lengths))
        ids = np.unique(groups)
        return ids.tolist(), [metrics.joint_variance(joints[groups == g][:, : lens[groups == g][0]]) for g in ids]


def evaluation_result(monkeypatch, joint_metrics=None) -> dict:
    """The evaluator's result (PointRun.result) of a tiny run: main generation with APE/AVE, MultiModality's joint
    variance, one editing pass with ADE/FDE, plausibility figures of every kind; ``joint_metrics`` replaces
    mfm.metrics_torch in the evaluator."""
    from pipeline.evaluation import replications

    bench_eval = load_bench_eval()
    results = []
    result = replications.PointRun.result
    with monkeypatch.context() as patch:
        patch.setattr(replications.PointRun, "result", lambda run: results.append(result(run)) or results[-1])
        if joint_metrics is not None:
            patch.setattr(replications, "metrics_torch", joint_metrics, raising=False)
        bench_eval.run_evaluation_bench(bench_eval.EvalBenchSettings(
            items=8, protocol="fast", replications=2, steps=2, batch_size=8, model_preset="tiny",
            editing=("upper_body",), flame=True, multimodality=True, device="cpu", editing_passes="single",
            editing_samples=8, text_dim=32))
    return results[-1]


def flat_numbers(tree, prefix: str = "") -> dict[str, float]:
    if isinstance(tree, dict):
        return {k: v for key, value in tree.items() for k, v in flat_numbers(value, f"{prefix}/{key}").items()}
    if isinstance(tree, (list, tuple)):
        return {k: v for i, value in enumerate(tree) for k, v in flat_numbers(value, f"{prefix}[{i}]").items()}
    return {prefix: float(tree)} if isinstance(tree, (int, float)) and not isinstance(tree, bool) else {}


def test_the_evaluator_scores_joints_on_the_torch_path_with_the_numpy_paths_results(monkeypatch):
    """The joints phase scores on the device (mfm.metrics_torch, never the numpy joint metrics), and every number the
    evaluation writes is that of the numpy path on the same generated motions (1e-9 relative)."""
    reference = evaluation_result(monkeypatch, NumpyJointMetrics)

    def host_path(*args, **kwargs):
        raise AssertionError("the evaluator called a numpy joint metric")

    for name in ("plausibility", "ape_ave", "ade", "fde", "joint_variance"):
        monkeypatch.setattr(metrics, name, host_path)
    result = evaluation_result(monkeypatch)
    got, want = flat_numbers(result), flat_numbers(reference)
    timing = {k for k in want if "seconds" in k}  # wall times differ run to run
    assert set(got) == set(want)
    for key in ("/metrics/APE_root", "/metrics/AVE_mean_local", "/metrics/joint_variance",
                "/metrics/foot_skating_ratio", "/metrics/jerk_ratio", "/editing/upper_body/ade",
                "/editing/upper_body/fde", "/editing/upper_body/pose_spread", "/ground_truth/mean_jerk"):
        assert any(k.startswith(key) for k in want), key  # every kind of joint figure is compared
    for key in sorted(set(want) - timing):
        assert got[key] == pytest.approx(want[key], rel=1e-9, abs=1e-12), key


def test_the_joint_metrics_bench_compares_the_two_paths(capsys):
    """benchmarks/bench_joint_metrics.py runs both paths on the same batches and reports their agreement."""
    import importlib.util
    import json
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_joint_metrics.py"
    spec = importlib.util.spec_from_file_location("bench_joint_metrics", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    assert bench.main(["--items", "6", "--batch-size", "4", "--device", "cpu", "--repeats", "1"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["host_s"] > 0 and record["device_s"] > 0 and record["max_relative_difference"] < 1e-9
