"""FlowMDM's composition evaluation in the evaluator job (pipeline/evaluation/composition.py): the composition set, the
transition windows, FlowMDM's R-precision with repeated captions, and a switch sweep end to end on CPU with the tiny
BPE + PCCAT model of tests/test_compose_cli.py (trained once per session on test_trainer.py's synthetic dataset) and
an untrained seeded evaluator (enough for the plumbing; the numbers are not meaningful)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from eval_worker import random_contrastive_evaluator
from test_sample_cli import _train_once
from test_trainer import LAUNCH_VARS, build_dataset_once

from mfm import metrics
from mfm.features import features_to_joints
from mfm.skeleton import get_skeleton
from pipeline.config import ConfigError
from pipeline.evaluation.composition import (
    build_composition_set,
    concatenated_windows,
    crop_windows,
    transition_crops,
)
from pipeline.evaluation.config import CompositionConfig, load_eval_config
from pipeline.evaluation.spaces import build_ground_truth
from pipeline.evaluation.store import ResultsStore

REPO_ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.usefixtures("single_thread")

SMALL = ["--protocol", "fast", "--steps", "2", "tasks.text_to_motion=false", "tasks.composition=true",
         "protocol.replications=2", "composition.segments_per_sequence=3", "composition.num_sequences=4",
         "composition.transition_window=20", "output.wandb=disabled", "output.plots=true"]
SWEEP = "composition.switch=[relative,0.5,absolute]"


@pytest.fixture(scope="module")
def manifest(tmp_path_factory) -> Path:
    return build_dataset_once(tmp_path_factory)


@pytest.fixture(scope="module")
def gt(manifest):
    return build_ground_truth(manifest, "test")


@pytest.fixture(scope="module")
def bpe_run(tmp_path_factory, manifest) -> Path:
    # The same run as tests/test_compose_cli.py's bpe_run fixture: trained once per session.
    return _train_once(tmp_path_factory, "compose-bpe-pccat-run", manifest, "model.positional=bpe",
                       "model.conditioning=pccat")


@pytest.fixture(scope="module")
def evaluator(manifest, tmp_path_factory) -> Path:
    return random_contrastive_evaluator(manifest, tmp_path_factory.mktemp("comp-ev") / "contrastive.safetensors")


def evaluate(*args: str) -> int:
    from launch.evaluate import main

    return main(list(args))


@pytest.fixture(scope="module")
def sweep(bpe_run, evaluator, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("comp-eval")
    assert evaluate("--checkpoint", str(bpe_run), *SMALL, SWEEP, f"evaluator.path={evaluator}",
                    f"output.dir={out}") == 0
    return out


def results_of(out: Path) -> dict[float, dict]:
    results = [json.loads(p.read_text()) for p in (out / "results").rglob("*.json")]
    return {r["composition"]["switch"]: r for r in results}


# ---------------------------------------------------------------------------------------------------------------
# settings, composition set, windows, R-precision


def test_switch_settings_name_the_baselines_and_are_checked():
    ccfg = CompositionConfig(switch=("absolute", 1.0, "relative", "humanml3d", 0.25))
    assert ccfg.switch_times()[:2] == (1.0, 0.0) and 0.08 < ccfg.switch_times()[2] < 0.09
    assert len(ccfg.switch_times()) == 4  # 'absolute' and 1.0 are one unit
    with pytest.raises(ConfigError, match="unknown name"):
        CompositionConfig(switch=("sometimes",))
    with pytest.raises(ConfigError, match="in \\[0, 1\\]"):
        CompositionConfig(switch=(1.5,))
    with pytest.raises(ConfigError, match="length_bins"):
        load_eval_config("fast", overrides=["composition.scenario=short"])
    with pytest.raises(ConfigError, match="nothing to evaluate"):
        load_eval_config("fast", overrides=["tasks.text_to_motion=false"])


def test_composition_set_is_reproducible_and_respects_the_length_bins(gt):
    ccfg = CompositionConfig(segments_per_sequence=4, num_sequences=5, transition_window=20, seed=3)
    first, again = build_composition_set(gt, ccfg), build_composition_set(gt, ccfg)
    assert first.key == again.key
    assert all(np.array_equal(a, b) for a, b in zip(first.sequences, again.sequences))
    other = build_composition_set(gt, CompositionConfig(segments_per_sequence=4, num_sequences=5,
                                                        transition_window=20, seed=4))
    assert other.key != first.key
    assert [len(s) for s in first.sequences] == [4] * 5
    chain = first.segment_items()
    assert np.all(chain[1:] != chain[:-1])  # never the same item twice in a row
    pool = first.pool_size
    assert len(set(chain[:pool].tolist())) == min(pool, len(chain))  # every item once before any is reused

    low, high = int(np.percentile(gt.lengths, 30)), int(np.percentile(gt.lengths, 80))
    binned = CompositionConfig(segments_per_sequence=3, transition_window=20, scenario="mid",
                               length_bins={"mid": (low, high)})
    cset = build_composition_set(gt, binned)
    lengths = gt.lengths[cset.segment_items()]
    assert lengths.min() >= low and lengths.max() <= high
    in_bin = set(np.flatnonzero((gt.lengths >= low) & (gt.lengths <= high)).tolist())
    assert set(cset.segment_items().tolist()) == in_bin  # num_sequences=0 covers every eligible item
    assert cset.settings["length_range"] == [low, high] and cset.key != first.key

    # a test set smaller than FlowMDM's 32 segments: every sequence is one permutation of the eligible items
    small = build_composition_set(gt, CompositionConfig(transition_window=20, num_sequences=2))
    assert small.segments_per_sequence == small.pool_size < 32 and any("not 32" in n for n in small.notes)
    assert all(sorted(s.tolist()) == sorted(small.sequences[0].tolist()) for s in small.sequences)


def test_transition_windows_are_centred_on_the_boundaries():
    lengths = [40, 35, 50]
    frames = np.arange(sum(lengths), dtype=np.float32)[:, None]  # each frame holds its own index
    crops = transition_crops(frames, lengths, 20)
    assert crops.shape == (2, 20, 1)
    for crop, boundary in zip(crops[..., 0], (40, 75)):
        assert crop.tolist() == list(range(boundary - 10, boundary + 10))
    odd = transition_crops(frames, lengths, 7)[..., 0]
    assert odd[0].tolist() == list(range(37, 44))  # 3 before, 4 from the boundary on (FlowMDM's margins)
    with pytest.raises(ValueError, match="runs past"):
        transition_crops(frames, [5, 120], 20)


def test_gt_transition_windows_crop_natural_motion_or_the_joins_of_the_set(gt):
    crops, ids = crop_windows(gt, 20, seed=0)
    assert crops.shape == (int((gt.lengths >= 20).sum()), 20, gt.features[0].shape[1])
    for crop, item in zip(crops, ids):  # each crop is a contiguous piece of its own clip
        clip = gt.features[gt.ids.index(item)]
        assert any(np.array_equal(crop, clip[s:s + 20]) for s in range(len(clip) - 19))
    assert np.array_equal(crop_windows(gt, 20, seed=0)[0], crops)
    cset = build_composition_set(gt, CompositionConfig(segments_per_sequence=3, num_sequences=2, transition_window=20))
    joins, _ = concatenated_windows(gt, cset, 20)
    assert len(joins) == cset.num_transitions == 4
    a, b = cset.sequences[0][:2]
    assert np.array_equal(joins[0][:10], gt.features[a][-10:]) and np.array_equal(joins[0][10:], gt.features[b][:10])


def test_r_precision_with_repeated_captions_follows_flowmdm():
    rng = np.random.default_rng(0)
    text = rng.normal(size=(8, 4))
    assert metrics.r_precision_distinct_captions(text, text + 1e-3, list("abcdefgh"), 8) == (1.0, 1.0, 1.0)
    # rows 0 and 1 share a caption: only row 0 is ranked among the 7 distinct ones, and row 1's motion (far from
    # everything) cannot steal its match
    motion = text.copy()
    motion[1] = 100.0
    top1 = metrics.r_precision_distinct_captions(text, motion, list("aacdefgh"), 8)[0]
    assert top1 == 1.0 and metrics.r_precision(text, motion, batch_size=8)[0] == 7 / 8


# ---------------------------------------------------------------------------------------------------------------
# the job


def test_switch_sweep_writes_one_result_per_switch_with_every_metric(sweep, gt, bpe_run):
    results = results_of(sweep)
    assert sorted(results) == [0.0, 0.5, 1.0]
    names = {"r_precision_top1", "r_precision_top2", "r_precision_top3", "fid", "mm_dist", "diversity",
             "transition_fid", "transition_diversity", "peak_jerk", "auj"}
    # contact_foot_speed is left out where no sequence (or GT clip) touches the floor: undefined
    plausibility = {"bone_length_range", "bone_length_deviation", "floor_penetration", "foot_skating_ratio",
                    "skating_foot_speed", "mean_jerk", "jerk_ratio", "pose_speed", "root_speed", "pose_spread"}
    for switch, result in results.items():
        assert result["task"] == "composition" and result["sampling"]["switch"] == switch
        for section in ("metrics", "ground_truth"):
            assert names | plausibility <= set(result[section]) <= names | plausibility | {"contact_foot_speed"}
        for name in names | plausibility:
            values = result["metrics"][name]["values"]
            assert len(values) == 2 and all(np.isfinite(values)), name
        assert "average ground-truth jerk" in result["plausibility"]["jerk_ratio_reference"]
        comp = result["composition"]
        assert (comp["num_sequences"], comp["segments_per_sequence"], comp["num_transitions"]) == (4, 3, 8)
        assert comp["transition_window"] == 20 and comp["transition_window_seconds"] == 1.0
        assert result["jerk_curve"]["frames_from_boundary"][0] == -10 and len(result["jerk_curve"]["generated"]) == 17
        assert result["protocol"]["r_precision_batch"] == 12 and result["protocol"]["notes"]
        assert result["nfe"] == 2 and result["model_passes_per_motion"] == 4
    assert results[1.0]["composition"]["absolute_steps"] == 2 and results[0.0]["composition"]["relative_steps"] == 2
    assert results[0.5]["composition"]["absolute_steps"] == 1
    # only the switch changes: the same set, the same GT; different switches give different motions
    assert len({r["composition"]["set_key"] for r in results.values()}) == 1
    assert results[0.0]["ground_truth"]["fid"] == results[1.0]["ground_truth"]["fid"]
    assert results[0.0]["metrics"]["peak_jerk"]["values"] != results[1.0]["metrics"]["peak_jerk"]["values"]
    stored = json.loads(Path(results[1.0]["composition"]["set_file"]).read_text())
    assert stored["key"] == results[1.0]["composition"]["set_key"] and len(stored["sequences"]) == 4
    assert all(len(s["text"]) == len(s["lengths"]) == 3 for s in stored["sequences"])

    rows = ResultsStore(sweep).table_rows()
    assert sorted((r["switch"], r["row_kind"]) for r in rows) == [
        (s, k) for s in (0.0, 0.5, 1.0) for k in ("generated", "ground_truth")]
    assert all(r["task"] == "composition" and "peak_jerk_ci" in r and "r_precision_top3" in r for r in rows)
    assert all("foot_skating_ratio" in r and "jerk_ratio_ci" in r for r in rows)
    assert pq.read_table(sweep / "results.parquet").num_rows == 6
    assert (sweep / "plots" / "composition_switch.png").stat().st_size > 0
    assert not (sweep / "plots" / "metrics_vs_step.png").exists()  # composition rows stay out of the T2M plots


def test_gt_jerk_is_computed_from_the_ground_truth_and_recorded(sweep, gt):
    recorded = results_of(sweep)[0.5]["composition"]["gt_jerk"]
    skeleton = get_skeleton("humanml3d")
    expected = metrics.dataset_average_jerk([features_to_joints(f.astype(np.float64), skeleton) for f in gt.features])
    assert recorded["value"] == pytest.approx(expected, rel=1e-9)
    assert recorded["num_clips"] == len(gt) and "dataset_average_jerk" in recorded["source"]
    assert list((sweep / "cache").glob("gt-jerk-*.json"))
    # AUJ of every replication is measured against it
    result = results_of(sweep)[0.5]
    curve = np.asarray(result["jerk_curve"]["ground_truth"])
    assert result["ground_truth"]["auj"]["mean"] == pytest.approx(np.abs(curve - expected).sum(), rel=1e-6)
    # ... and so is the jerk ratio of the ground-truth row: each segment's GT clip's mean jerk over it (metres)
    stored = json.loads(Path(result["composition"]["set_file"]).read_text())
    segment_items = [gt.ids.index(item) for sequence in stored["sequences"] for item in sequence["items"]]
    clip_jerk = [metrics.mean_jerk(features_to_joints(gt.features[i].astype(np.float64), skeleton))[0]
                 for i in segment_items]
    assert result["ground_truth"]["jerk_ratio"]["mean"] == pytest.approx(np.median(clip_jerk) / expected, rel=1e-9)


def test_absolute_only_baseline_is_switch_one(sweep, bpe_run, evaluator, tmp_path, capsys):
    out = tmp_path / "eval"
    assert evaluate("--checkpoint", str(bpe_run), *SMALL, "composition.switch=[absolute]",
                    f"evaluator.path={evaluator}", f"output.dir={out}") == 0
    assert "composition euler 2 steps switch 1" in capsys.readouterr().out
    (baseline,) = results_of(out).values()
    reference = results_of(sweep)[1.0]
    assert baseline["key"] == reference["key"]
    assert baseline["metrics"] == reference["metrics"]
    # the same unit in the sweep's folder is found done: nothing is evaluated again
    assert evaluate("--checkpoint", str(bpe_run), *SMALL, "composition.switch=[1.0]", f"evaluator.path={evaluator}",
                    f"output.dir={sweep}") == 0
    assert "0 result(s) written" in capsys.readouterr().out


def test_a_model_that_cannot_compose_is_refused(manifest, evaluator, tmp_path_factory, tmp_path, capsys):
    prefix_run = _train_once(tmp_path_factory, "sampling-text-run", manifest)  # test_sample_cli.py's text_run
    assert evaluate("--checkpoint", str(prefix_run), *SMALL, f"evaluator.path={evaluator}",
                    f"output.dir={tmp_path}") == 2
    err = capsys.readouterr().err
    assert "model.positional=bpe model.conditioning=pccat" in err and "absolute-only baseline" in err
    assert not (tmp_path / "results").exists()


@pytest.mark.multirank
def test_two_ranks_compute_the_numbers_of_one(sweep, bpe_run, evaluator, tmp_path):
    """4 sequences over 2 gloo ranks (round-robin), gathered back into sequence order: the sweep's numbers."""
    env = {k: v for k, v in os.environ.items() if k not in LAUNCH_VARS}
    env.update(OMP_NUM_THREADS="1", WANDB_MODE="disabled", HF_HUB_OFFLINE="1")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           str(REPO_ROOT / "launch" / "evaluate.py"), "--checkpoint", str(bpe_run), *SMALL,
           "composition.switch=[0.5]", f"evaluator.path={evaluator}", f"output.dir={tmp_path}"]
    proc = subprocess.run(cmd, cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    (two,) = results_of(tmp_path).values()
    one = results_of(sweep)[0.5]
    assert (two["world_size"], one["world_size"]) == (2, 1) and two["key"] == one["key"]
    for section in ("metrics", "ground_truth"):
        for name, value in one[section].items():
            assert two[section][name]["values"] == pytest.approx(value["values"], rel=1e-5, abs=1e-7), name
