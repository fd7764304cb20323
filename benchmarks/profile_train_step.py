"""Where a training step's time goes: the real ``Trainer.train_step`` timed, then profiled, at each batch size.

    python benchmarks/profile_train_step.py --manifest M --batch-sizes 128,512 --out runs/profile   # on a GPU
    OMP_NUM_THREADS=1 python benchmarks/profile_train_step.py --synthetic 48 --config tiny --batch-sizes 4 \\
        --steps 2 --warmup 1 --profile-steps 1 --out /tmp/profile                             # seconds on a CPU

For each batch size, one Trainer of ``--config`` (humanml3d by default: bf16 autocast and torch.compile on CUDA,
the preset's ``auto``) on random batches of the window's shape (``bench_train.random_batches``: lengths in
[window/2, window], so attention is masked as in training), built with ``train.step_sync=deferred`` (so with
fused AdamW, as on a GPU). It prints one JSON line per batch size:

* ``step_ms``: the median step, each timed to its end (the device synchronised before and after: no overlap
  between steps);
* ``streamed_ms_deferred`` / ``streamed_ms_every_step``: the time per step of ``--steps`` steps run back to back
  and then drained (the last step's flags read, the device synchronised), with the host reading each step's
  flags one step later (``train.step_sync=deferred``: it queues step k+1 before it waits for step k) or at the
  step's end (every_step: it waits for each backward pass before queueing the next step), timed in alternating
  blocks on the same trainer, so drift in the machine's speed falls on both alike; ``samples_per_s`` is the
  deferred figure;
* ``host_syncs_per_deferred_step`` (CUDA): the calls that made the host wait for the GPU during deferred steps
  (``torch.cuda.set_sync_debug_mode``), the flag reads excluded: 0 when nothing but the reads waits;
* ``device_busy``: over ``--profile-steps`` profiled steps (``torch.profiler``, each timed to its end), the summed
  device time of the kernels over the wall time: near 1 = the GPU is the limit; well under 1 = the host (Python,
  launches) leaves it idle;
* the profile's tables (top kernels by device time; top host operators) in ``OUT/profile_b<batch>.txt``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_data  # noqa: E402
import bench_train  # noqa: E402

from pipeline.config import TrainConfig, load_config  # noqa: E402
from pipeline.distributed import Dist  # noqa: E402
from pipeline.training.trainer import PendingStep, Trainer  # noqa: E402


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed_steps(trainer: Trainer, batches: list[dict[str, Any]], steps: int) -> list[float]:
    times = []
    for i in range(steps):
        synchronize(trainer.dist.device)
        start = time.perf_counter()
        trainer.train_step([batches[i % len(batches)]])
        trainer.step += 1
        synchronize(trainer.dist.device)
        times.append(time.perf_counter() - start)
    return times


def streamed_step_s(trainer: Trainer, batches: list[dict[str, Any]], steps: int, deferred: bool) -> float:
    """Seconds per step of ``steps`` steps run back to back, then drained; the host reads each step's flags one
    step later (``deferred``) or at its end (the trainer, built deferred, runs every_step's path when told)."""
    trainer.settle()
    synchronize(trainer.dist.device)
    trainer.defers_step_sync = deferred
    start = time.perf_counter()
    for i in range(steps):
        trainer.train_step([batches[i % len(batches)]])
        trainer.step += 1
    trainer.settle()
    synchronize(trainer.dist.device)
    elapsed = time.perf_counter() - start
    trainer.defers_step_sync = True
    return elapsed / steps


def host_syncs_per_deferred_step(trainer: Trainer, batches: list[dict[str, Any]], steps: int) -> float | None:
    """On CUDA: the synchronising calls (``torch.cuda.set_sync_debug_mode``'s warnings: ``.item()``, blocking
    copies, ``nonzero``...) per deferred step, the flag reads (``PendingStep.read``) excluded: 0 means the host
    never waits for the GPU between reads. None elsewhere."""
    if trainer.dist.device.type != "cuda":
        return None
    trainer.settle()
    real_read = PendingStep.read

    def unwatched_read(pending: PendingStep) -> list[float]:
        torch.cuda.set_sync_debug_mode("default")
        try:
            return real_read(pending)
        finally:
            torch.cuda.set_sync_debug_mode("warn")

    PendingStep.read = unwatched_read
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            for i in range(steps):
                trainer.train_step([batches[i % len(batches)]])
                trainer.step += 1
        finally:
            torch.cuda.set_sync_debug_mode("default")
            PendingStep.read = real_read
    trainer.settle()
    return sum("synchroniz" in str(w.message) for w in caught) / steps


def profile_batch_size(args: argparse.Namespace, manifest: Path, batch_size: int, out: Path) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as tmp:
        cfg = load_config(TrainConfig, args.config, [
            f"data.manifest={manifest}", f"data.batch_size={batch_size}", f"data.window={args.window}",
            "data.num_workers=0", "data.verify=off", "optim.grad_accum=1", f"train.out_dir={tmp}/run",
            "train.wandb=disabled", "train.step_sync=deferred", *args.overrides])
        with Dist(mixed_precision=cfg.train.mixed_precision) as dist:
            trainer = Trainer(cfg, dist)
            batches = bench_train.random_batches(trainer, count=4)
            timed_steps(trainer, batches, args.warmup)
            step_s = statistics.median(timed_steps(trainer, batches, args.steps))
            streamed: dict[bool, list[float]] = {True: [], False: []}
            for block in range(4):  # alternating blocks, so drift in the machine's speed falls on both alike
                deferred = block % 2 == 0
                streamed[deferred].append(streamed_step_s(trainer, batches, args.steps, deferred))
            activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dist.device.type == "cuda" else [])
            with profile(activities=activities) as prof:
                wall = sum(timed_steps(trainer, batches, args.profile_steps))
            events = prof.key_averages()
            device_us = sum(e.self_device_time_total for e in events if e.device_type == torch.autograd.DeviceType.CUDA)
            sort = "self_cuda_time_total" if dist.device.type == "cuda" else "self_cpu_time_total"
            (out / f"profile_b{batch_size}.txt").write_text(
                f"batch {batch_size}, {args.profile_steps} steps, wall {wall * 1e3:.1f} ms\n\n"
                + events.table(sort_by=sort, row_limit=40, max_name_column_width=90) + "\n\n"
                + events.table(sort_by="self_cpu_time_total", row_limit=25, max_name_column_width=90))
            deferred_s, every_step_s = (statistics.mean(streamed[mode]) for mode in (True, False))
            syncs = host_syncs_per_deferred_step(trainer, batches, args.steps)
            return {"bench": "profile_train_step", "config": args.config, "device": str(dist.device),
                    "device_name": torch.cuda.get_device_name(dist.device) if dist.device.type == "cuda" else "cpu",
                    "precision": dist.mixed_precision, "compile": cfg.train.compile, "batch_size": batch_size,
                    "window": args.window, "params_m": round(trainer.num_parameters / 1e6, 3),
                    "step_ms": round(step_s * 1e3, 3),
                    "streamed_ms_deferred": round(deferred_s * 1e3, 3),
                    "streamed_ms_every_step": round(every_step_s * 1e3, 3),
                    "samples_per_s": round(batch_size / deferred_s, 1),
                    "samples_per_s_every_step": round(batch_size / every_step_s, 1),
                    "host_syncs_per_deferred_step": syncs,
                    "profiled_wall_ms_per_step": round(wall * 1e3 / args.profile_steps, 3),
                    "device_busy": round(device_us / 1e6 / wall, 3) if dist.device.type == "cuda" else None}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--manifest", type=Path, help="dataset for the feature and text sizes")
    parser.add_argument("--synthetic", type=int, metavar="N", help="build N synthetic clips (512-D text) instead")
    parser.add_argument("--config", default="humanml3d")
    parser.add_argument("--batch-sizes", default="128,512")
    parser.add_argument("--window", type=int, default=196)
    parser.add_argument("--steps", type=int, default=20, help="timed steps, and steps per streamed block")
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--profile-steps", type=int, default=3)
    parser.add_argument("overrides", nargs="*", metavar="key.sub=value")
    args = parser.parse_intermixed_args(argv)
    if (args.manifest is None) == (args.synthetic is None):
        parser.error("give --manifest or --synthetic")
    if args.profile_steps < 1 or args.steps < 2:
        parser.error("--profile-steps must be at least 1 and --steps at least 2 (the figures divide by them)")
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        manifest = args.manifest or bench_data.build_synthetic(args.synthetic, Path(tmp) / "ds", text_dim=512,
                                                               formats=("tar",))
        for batch_size in (int(b) for b in args.batch_sizes.split(",")):
            record = profile_batch_size(args, manifest, batch_size, args.out)
            print(json.dumps(record), flush=True)
            with (args.out / "results.jsonl").open("a") as f:
                f.write(json.dumps(record) + "\n")


if __name__ == "__main__":
    main()
