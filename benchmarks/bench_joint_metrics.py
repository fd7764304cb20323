"""The evaluator's joints phase alone, host path against device path: one JSON line.

    python benchmarks/bench_joint_metrics.py --items 1096 --batch-size 256 --device cuda
    python benchmarks/bench_joint_metrics.py --items 256 --batch-size 64 --device cpu --threads 1

What runs, per batch of a synthetic test set (HumanML3D-sized features, lengths uniform in [40, 196] frames rounded
down to multiples of 4, batches length-sorted as the evaluator's): joint recovery of the generated and the
ground-truth motions (``features_to_joints`` in float64 on ``--device``), then the plausibility figures and TEMOS's
APE/AVE with the floor, as ``PointRun._joint_stats`` scores a main batch with ``tasks.flame``. ``host``: the joints
brought to the host and scored by the numpy reference (``mfm.metrics``, the evaluator before issue 26's device
metrics); ``device``: scored where they are (``mfm.metrics_torch``). Seconds for all batches, best of
``--repeats``, CUDA synchronised; ``max_relative_difference``: the largest relative difference between the two
paths' figures (0 where both are NaN).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from mfm import metrics, metrics_torch
from mfm.features import features_to_joints
from mfm.skeleton import HUMANML3D

DIM = HUMANML3D.feature_dim


def synthetic_batches(items: int, batch_size: int, device: torch.device, seed: int = 0):
    """(generated, ground truth, lengths) batches of float32 features on ``device``, length-sorted."""
    rng = np.random.default_rng(seed)
    lengths = np.sort(rng.integers(40, 197, items) // 4 * 4)
    batches = []
    for start in range(0, items, batch_size):
        lens = lengths[start : start + batch_size]
        shape = (len(lens), int(lens.max()), DIM)
        pair = [torch.from_numpy((0.1 * rng.standard_normal(shape)).astype(np.float32)).to(device) for _ in "ab"]
        batches.append((*pair, torch.from_numpy(lens).to(device)))
    return batches


def score(batch, joint_metrics, to_host: bool) -> list[np.ndarray]:
    raw, gt_raw, lengths = batch
    joints, gt_joints = (features_to_joints(x.double(), HUMANML3D) for x in (raw, gt_raw))
    if to_host:
        joints, gt_joints, lengths = joints.cpu().numpy(), gt_joints.cpu().numpy(), lengths.cpu().numpy()
    figures = joint_metrics.plausibility(joints, HUMANML3D, lengths)
    feet = HUMANML3D.foot_left + HUMANML3D.foot_right
    ape = joint_metrics.ape_ave(joints, gt_joints, lengths, face_joints=HUMANML3D.face_joints, floor_joints=feet)
    return [getattr(figures, name) for name in figures.names] + [np.asarray(list(ape.values()))]


def timed(batches, joint_metrics, to_host: bool, device: torch.device, repeats: int):
    best, out = float("inf"), None
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        start = time.perf_counter()
        out = [score(b, joint_metrics, to_host) for b in batches]
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        best = min(best, time.perf_counter() - start)
    return best, out


def relative_difference(a: list, b: list) -> float:
    worst = 0.0
    for x, y in zip((v for part in a for v in part), (v for part in b for v in part)):
        both_nan = np.isnan(x) & np.isnan(y)
        diff = np.where(both_nan, 0.0, np.abs(x - y) / np.maximum(np.abs(y), 1e-12))
        worst = max(worst, float(np.nanmax(diff, initial=0.0)))
    return worst


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--items", type=int, default=1096)
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    batches = synthetic_batches(args.items, args.batch_size, device)
    timed(batches[:1], metrics_torch, False, device, 1)  # warm-up: CUDA context and kernels
    host_s, host = timed(batches, metrics, True, device, args.repeats)
    device_s, on_device = timed(batches, metrics_torch, False, device, args.repeats)
    print(json.dumps({"bench": "joint_metrics", "device": str(device), "items": args.items,
                      "batch_size": args.batch_size, "torch_threads": torch.get_num_threads(),
                      "host_s": round(host_s, 4), "device_s": round(device_s, 4),
                      "speedup": round(host_s / device_s, 2),
                      "max_relative_difference": relative_difference(on_device, host)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
