"""Evaluator invariant (reliability item 7): the metrics of a test set whose size (10) is not a multiple of
world_size × batch_size (2 × 4) are identical with 1 and 2 gloo ranks (torchrun, CPU), and so is the result key.
Every task runs: text-to-motion, MultiModality, FLAME metrics, editing (their batches split unevenly over ranks), each
replication on its own draw of the ground-truth items (embedded by both ranks)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from functools import partial
from pathlib import Path

import pytest
from conftest import start_two_at_a_time
from eval_worker import (
    build_synthetic_dataset,
    random_contrastive_evaluator,
    train_tiny_model,
)

WORKER = Path(__file__).with_name("eval_worker.py")


def run_ranks(nproc: int, checkpoint: Path, evaluator: Path, out: Path) -> dict:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "WANDB_MODE": "disabled"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(nproc),
           str(WORKER), str(checkpoint), str(evaluator), str(out)]
    proc = subprocess.run(cmd, cwd=WORKER.parents[1], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    (path,) = (out / "results").rglob("*.json")
    return json.loads(path.read_text())


@pytest.mark.multirank
def test_metrics_are_identical_on_one_and_two_ranks(tmp_path_factory):
    manifest = build_synthetic_dataset(tmp_path_factory.getbasetemp() / "eval-synthetic")
    run = train_tiny_model(manifest, tmp_path_factory.mktemp("multirank-run"), steps=1)
    evaluator = random_contrastive_evaluator(manifest, tmp_path_factory.mktemp("ev") / "contrastive.safetensors")
    checkpoint = run / "checkpoints" / "step-00000001"
    root = tmp_path_factory.mktemp("multirank-eval")
    # Both launches at once (mostly Python starts of the launchers and ranks; one intra-op thread in every rank)
    launches = start_two_at_a_time({nproc: partial(run_ranks, nproc, checkpoint, evaluator, root / str(nproc))
                                    for nproc in (1, 2)})
    one, two = launches[1].result(), launches[2].result()

    assert (one["world_size"], two["world_size"]) == (1, 2)
    assert one["data"]["num_items"] == 10 and one["sampling"]["batch_size"] == 4
    assert one["key"] == two["key"]
    # each replication's ground-truth items are re-drawn (the default), from seeds: the same sets on both
    assert one["protocol"]["redraw_items"] and one["data"]["ground_truth_sets"] == two["data"]["ground_truth_sets"]
    assert len({s["gt_key"] for s in one["data"]["ground_truth_sets"]}) == one["protocol"]["replications"] == 2
    for section in ("metrics", "ground_truth", "editing"):
        assert one[section] == two[section], section  # every replication's value, exactly
    assert {"fid", "r_precision_top3", "multimodality", "APE_root", "joint_variance"} <= set(one["metrics"])
    # plausibility medians need every clip of a replication: gathered from both ranks, paired with their GT clips
    assert {"foot_skating_ratio", "jerk_ratio"} <= set(one["metrics"]) & set(one["editing"]["prediction"])
    assert set(one["editing"]) == {"prediction", "upper_body"}
    assert one["nfe"] == two["nfe"] == 2
