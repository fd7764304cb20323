"""Where a training step's time goes: the real ``Trainer.train_step`` timed, then profiled, at each batch size.

    python benchmarks/profile_train_step.py --manifest M --batch-sizes 128,512 --out runs/profile   # on a GPU
    OMP_NUM_THREADS=1 python benchmarks/profile_train_step.py --synthetic 48 --config tiny --batch-sizes 4 \\
        --steps 2 --warmup 1 --profile-steps 1 --out /tmp/profile                             # seconds on a CPU

For each batch size, one Trainer of ``--config`` (humanml3d by default: bf16 autocast and torch.compile on CUDA,
the preset's ``auto``) on random batches of the window's shape (``bench_train.random_batches``: lengths in
[window/2, window], so attention is masked as in training). It prints one JSON line per batch size:

* ``step_ms``: the median step (``--steps`` after ``--warmup``), with the weights' average updated by one
  multi-tensor lerp (``EMA.update`` as the trainer runs it), and ``step_ms_ema_per_tensor`` the same trainer with
  the average updated one tensor at a time (the trainer's loop before 2026-11-27), timed in alternating blocks;
* ``device_busy``: over ``--profile-steps`` profiled steps (``torch.profiler``), the summed device time of the
  kernels over the wall time: near 1 = the GPU is the limit; well under 1 = the host (Python, launches, the step's
  one host sync) leaves it idle;
* the profile's tables (top kernels by device time; top host operators) in ``OUT/profile_b<batch>.txt``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_data  # noqa: E402
import bench_train  # noqa: E402

from pipeline.config import TrainConfig, load_config  # noqa: E402
from pipeline.distributed import Dist  # noqa: E402
from pipeline.training.trainer import EMA, Trainer  # noqa: E402


def ema_update_per_tensor(self: EMA, model: torch.nn.Module, *, copy: bool = False) -> None:
    """The average's update one tensor at a time: what ``EMA.update`` did before its multi-tensor lerp."""
    with torch.no_grad():
        decay = self.next_decay()
        for name, value in model.state_dict().items():
            if value.dtype.is_floating_point and not copy:
                self.shadow[name].lerp_(value.detach().float(), 1.0 - decay)
            else:
                self.shadow[name].copy_(value)


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


def profile_batch_size(args: argparse.Namespace, manifest: Path, batch_size: int, out: Path) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as tmp:
        cfg = load_config(TrainConfig, args.config, [
            f"data.manifest={manifest}", f"data.batch_size={batch_size}", f"data.window={args.window}",
            "data.num_workers=0", "data.verify=off", "optim.grad_accum=1", f"train.out_dir={tmp}/run",
            "train.wandb=disabled", *args.overrides])
        with Dist(mixed_precision=cfg.train.mixed_precision) as dist:
            trainer = Trainer(cfg, dist)
            batches = bench_train.random_batches(trainer, count=4)
            timed_steps(trainer, batches, args.warmup)
            fused, per_tensor = [], []
            original = EMA.update
            for block in range(4):  # alternating blocks, so drift in the machine's speed falls on both alike
                EMA.update = original if block % 2 == 0 else ema_update_per_tensor
                (fused if block % 2 == 0 else per_tensor).extend(timed_steps(trainer, batches, args.steps // 2))
            EMA.update = original
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
            step_s = statistics.median(fused)
            return {"bench": "profile_train_step", "config": args.config, "device": str(dist.device),
                    "device_name": torch.cuda.get_device_name(dist.device) if dist.device.type == "cuda" else "cpu",
                    "precision": dist.mixed_precision, "compile": cfg.train.compile, "batch_size": batch_size,
                    "window": args.window, "params_m": round(trainer.num_parameters / 1e6, 3),
                    "step_ms": round(step_s * 1e3, 3), "samples_per_s": round(batch_size / step_s, 1),
                    "step_ms_ema_per_tensor": round(statistics.median(per_tensor) * 1e3, 3),
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
    parser.add_argument("--steps", type=int, default=20, help="timed steps, half with each EMA update")
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
