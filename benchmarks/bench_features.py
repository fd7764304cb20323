"""Throughput of the HumanML3D feature code: one JSON line per measurement.

    python benchmarks/bench_features.py [--batch 64] [--frames 200] [--repeats 7] [--threads 1] [--device cpu]

Workload: ``batch`` clips of ``frames`` frames x 22 joints made from the real clip 012314
(../shared/reference-data, or $MFM_SHARED_DIR): time-stretched to ``frames`` frames, then per clip a
random turn about the vertical, a random offset and 5 mm of per-joint jitter.

Measurements: ``joints_to_features`` vectorised (whole batch per call, and one clip per call), the
per-frame implementation in tests/per_frame_reference.py (the baseline; a few clips, it is slow), and
``features_to_joints`` (recover_from_ric) and ``features_to_joints_fk`` (recover_from_rot) on the batch.
Each figure is the median over ``repeats`` timed runs after one warm-up run; ``motions_per_s`` is from
wall-clock time, ``motions_per_cpu_s`` from this process's CPU time (steadier on a shared machine; with
one thread it is the per-core rate). For scale: the reference ``process_file`` runs about 31 motions/s
on one core of the project's CPU machines (docs/performance-anchors.md in ../shared).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from mfm.features import features_to_joints, features_to_joints_fk, joints_to_features, resample_joints
from mfm.rotations import axis_angle_to_matrix
from mfm.skeleton import HUMANML3D

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DIR = Path(os.environ.get("MFM_SHARED_DIR", REPO_ROOT.parent / "shared"))
CLIP_PATH = SHARED_DIR / "reference-data" / "humanml3d" / "new_joints_012314.npy"


def load_per_frame_reference():
    path = REPO_ROOT / "tests" / "per_frame_reference.py"
    spec = importlib.util.spec_from_file_location("per_frame_reference", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def make_clips(batch: int, frames: int, seed: int) -> np.ndarray:
    """(batch, frames, 22, 3) float64 plausible motions derived from the real clip."""
    if not CLIP_PATH.is_file():
        sys.exit(f"reference clip not found at {CLIP_PATH} (set MFM_SHARED_DIR)")
    clip = np.load(CLIP_PATH).astype(np.float64)
    # Stretch in time to exactly `frames` frames.
    stretched = resample_joints(clip, 20.0, 20.0 * (frames - 1) / (len(clip) - 1))[:frames]
    rng = np.random.default_rng(seed)
    yaw = torch.from_numpy(np.outer(rng.uniform(-np.pi, np.pi, batch), [0.0, 1.0, 0.0]))
    turns = axis_angle_to_matrix(yaw).numpy()  # (batch, 3, 3)
    clips = np.einsum("bij,tkj->btki", turns, stretched)
    clips += rng.uniform(-2.0, 2.0, (batch, 1, 1, 3)) * [1.0, 0.0, 1.0]
    clips += rng.normal(0.0, 0.005, clips.shape)
    return clips


def measure(name: str, run: Callable[[], object], motions: int, repeats: int, **info) -> dict:
    run()  # warm-up
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        run()
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    wall_s, cpu_s = statistics.median(wall), statistics.median(cpu)
    return {
        "name": name,
        "motions": motions,
        "repeats": repeats,
        "median_wall_s": round(wall_s, 6),
        "median_cpu_s": round(cpu_s, 6),
        "motions_per_s": round(motions / wall_s, 2),
        "motions_per_cpu_s": round(motions / cpu_s, 2),
        **info,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--baseline-clips", type=int, default=3, help="clips timed with the per-frame implementation")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    clips = make_clips(args.batch, args.frames, args.seed)
    batch = torch.from_numpy(clips).to(args.device)
    info = {"frames": args.frames, "joints": HUMANML3D.num_joints, "threads": args.threads, "device": args.device}
    sync = torch.cuda.synchronize if batch.is_cuda else (lambda: None)

    def timed(fn: Callable[[], object]) -> Callable[[], object]:
        def run():
            out = fn()
            sync()
            return out

        return run

    results = [
        measure("joints_to_features", timed(lambda: joints_to_features(batch, HUMANML3D)), args.batch, args.repeats,
                impl="vectorised", batch=args.batch, **info),
        measure("joints_to_features", timed(lambda: [joints_to_features(c, HUMANML3D) for c in batch[:8]]), 8,
                args.repeats, impl="vectorised", batch=1, **info),
    ]
    per_frame = load_per_frame_reference()
    few = clips[: args.baseline_clips]
    results.append(
        measure("joints_to_features", lambda: [per_frame.joints_to_features(c, HUMANML3D) for c in few], len(few),
                max(1, args.repeats // 3), impl="per_frame", batch=1, **{**info, "device": "cpu"})
    )
    features = joints_to_features(batch, HUMANML3D)  # float32, as stored in the dataset
    results.append(measure("features_to_joints (recover_from_ric)", timed(lambda: features_to_joints(features, HUMANML3D)),
                           args.batch, args.repeats, impl="vectorised", batch=args.batch, **info))
    results.append(measure("features_to_joints_fk (recover_from_rot)",
                           timed(lambda: features_to_joints_fk(features, HUMANML3D)), args.batch, args.repeats,
                           impl="vectorised", batch=args.batch, **info))
    vectorised = results[0]["motions_per_cpu_s"]
    baseline = results[2]["motions_per_cpu_s"]
    results.append({"name": "speedup_vs_per_frame", "cpu_time_ratio": round(vectorised / baseline, 1), **info})
    for result in results:
        print(json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
