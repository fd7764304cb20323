"""Speed of the real training step (``Trainer.train_step``): one JSON line per data source.

    python benchmarks/bench_train.py --config default data.manifest=data/deepmimic-minilm/manifest.json
    python benchmarks/bench_train.py --config humanml3d data.batch_size=128 data.window=196 \\
        data.manifest=/data/hml/manifest.json --source random,loader --steps 50        # on a GPU
    python benchmarks/bench_train.py --config tiny --synthetic 200 --source random,loader

Sources: ``random`` feeds batches of random tensors already on the device (padded to random lengths in
[window/2, window]), so it times the model, loss, backward, clipping, the flag all-reduce, AdamW and EMA alone;
``loader`` feeds the real streaming loader of ``data.manifest`` and adds the time spent waiting for batches.
Both need a manifest for the feature and text-embedding sizes (``--synthetic N`` builds a throwaway one).

Fields: ``step_s_median`` / ``step_s_p90``: the training step alone, after ``--warmup`` steps; ``samples_per_s``:
samples over the whole timed span, data waits included; ``data_wait_frac``: its share spent waiting for the
loader; ``peak_mem_mb``: the process's peak resident memory on CPU (``ru_maxrss``, including torch itself), or
``torch.cuda.max_memory_allocated`` over the timed steps on a GPU. Under torchrun, rank 0 prints (world_size is
in the record; samples_per_s counts all ranks).
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import resource
import statistics
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch

from pipeline.config import TrainConfig, load_config
from pipeline.distributed import Dist
from pipeline.training.trainer import Trainer

SOURCES = ("random", "loader")


RANDOM_CAPTION_TOKENS = 32  # a manifest that does not say how many token features it keeps


def random_batches(trainer: Trainer, count: int) -> list[dict[str, Any]]:
    """``count`` distinct batches of random tensors with the run's shapes, already on the training device, with
    record ids as the loader gives them (``Trainer.train_step`` weighs each micro-batch by its number of ids).
    The same ``trainer`` shapes always give the same batches (a fixed seed)."""
    cfg, model_config, device = trainer.cfg, trainer.model_config, trainer.dist.device
    b, window = cfg.data.batch_size, cfg.data.window
    generator = torch.Generator().manual_seed(0)
    batches = []
    for _ in range(count):
        batch = {
            "features": torch.randn(b, window, model_config.feature_dim, generator=generator),
            "lengths": torch.randint(max(1, window // 2), window + 1, (b,), generator=generator),
            "text_emb": torch.randn(b, model_config.cond_dim, generator=generator),
            "action": torch.randint(0, max(1, model_config.num_actions), (b,), generator=generator),
        }
        if model_config.conditioning == "cross_attention":
            # the caption's token features as the loader gives them: padded to the set's max_tokens, each caption
            # at least one token long
            tokens = trainer.manifest.data["text_encoder"].get("max_tokens") or RANDOM_CAPTION_TOKENS
            batch["text_tokens"] = torch.randn(b, tokens, model_config.token_dim, generator=generator)
            batch["text_token_len"] = torch.randint(1, tokens + 1, (b,), generator=generator)
        batches.append({**{k: v.to(device) for k, v in batch.items()},
                        "ids": [f"random-{len(batches)}-{i}" for i in range(b)]})
    return batches


def batch_source(trainer: Trainer, source: str) -> Iterator[dict[str, Any]]:
    if source == "random":
        return itertools.cycle(random_batches(trainer, count=4))
    return trainer.loader.iter_batches()


def peak_memory_mb(device: torch.device) -> tuple[float, str]:
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20, "cuda_max_memory_allocated"
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "cpu_maxrss"  # Linux reports KiB


def measure(trainer: Trainer, source: str, steps: int, warmup: int) -> dict[str, Any]:
    """Run ``warmup`` untimed then ``steps`` timed optimizer steps from ``source``."""
    dist, cfg = trainer.dist, trainer.cfg
    batches = batch_source(trainer, source)
    accum = cfg.optim.grad_accum
    for _ in range(warmup):
        trainer.train_step([next(batches) for _ in range(accum)])
        trainer.step += 1
    trainer.settle()  # train.step_sync=deferred: the last warm-up step's flags
    if dist.device.type == "cuda":
        torch.cuda.synchronize(dist.device)
        torch.cuda.reset_peak_memory_stats(dist.device)
    step_times, waits = [], []
    for _ in range(steps):
        start = time.perf_counter()
        micro_batches = [next(batches) for _ in range(accum)]
        fetched = time.perf_counter()
        # every_step: ends in the flag all-reduce's host sync, the step done on return; deferred: returns once the
        # previous step's flags are read, this step queued (the host at most one step ahead of the device)
        trainer.train_step(micro_batches)
        trainer.step += 1
        step_times.append(time.perf_counter() - fetched)
        waits.append(fetched - start)
    drain = time.perf_counter()
    trainer.settle()  # deferred: the queued last step, counted in the last step's time
    if dist.device.type == "cuda":
        torch.cuda.synchronize(dist.device)
    step_times[-1] += time.perf_counter() - drain
    total = sum(step_times) + sum(waits)
    peak, peak_kind = peak_memory_mb(dist.device)
    samples = steps * accum * cfg.data.batch_size * dist.world_size
    device_name = torch.cuda.get_device_name(dist.device) if dist.device.type == "cuda" else "cpu"
    return {
        "bench": "train_step", "source": source, "device": device_name, "world_size": dist.world_size,
        "threads": torch.get_num_threads(), "precision": dist.mixed_precision,
        "step_sync": "deferred" if trainer.defers_step_sync else "every_step",
        "params_m": round(trainer.num_parameters / 1e6, 3),
        "layers": trainer.model_config.num_layers, "latent_dim": trainer.model_config.latent_dim,
        "batch_size": cfg.data.batch_size, "grad_accum": accum, "window": cfg.data.window,
        "num_workers": cfg.data.num_workers if source == "loader" else None,
        "steps": steps, "warmup": warmup,
        "step_s_median": round(statistics.median(step_times), 5),
        "step_s_p90": round(statistics.quantiles(step_times, n=10)[-1], 5) if steps >= 2 else round(step_times[0], 5),
        "samples_per_s": round(samples / total, 2),
        "data_wait_frac": round(sum(waits) / total, 4),
        "peak_mem_mb": round(peak, 1), "peak_mem_kind": peak_kind,
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="default", help="preset name or YAML path (as launch/train.py)")
    parser.add_argument("overrides", nargs="*", metavar="key.sub=value", help="config overrides")
    parser.add_argument("--source", default="random,loader", help=f"comma-separated subset of {','.join(SOURCES)}")
    parser.add_argument("--steps", type=int, default=20, help="timed optimizer steps per source")
    parser.add_argument("--warmup", type=int, default=3, help="untimed steps first (allocator, loader start-up)")
    parser.add_argument("--synthetic", type=int, metavar="N", help="build N synthetic clips in a temp dir first")
    args = parser.parse_intermixed_args(argv)
    sources = args.source.split(",")
    if not set(sources) <= set(SOURCES) or args.steps < 1 or args.warmup < 0:
        parser.error(f"--source must be a subset of {SOURCES}, --steps >= 1, --warmup >= 0")
    logging.basicConfig(level=logging.WARNING)

    with tempfile.TemporaryDirectory() as tmp:
        overrides = list(args.overrides) + [f"train.out_dir={tmp}/run", "train.wandb=disabled"]
        if args.synthetic:
            sys.path.insert(0, str(Path(__file__).resolve().parent))
            from bench_data import build_synthetic

            overrides.append(f"data.manifest={build_synthetic(args.synthetic, Path(tmp) / 'ds')}")
        cfg = load_config(TrainConfig, args.config, overrides)
        with Dist(mixed_precision=cfg.train.mixed_precision) as dist:
            trainer = Trainer(cfg, dist)
            for source in sources:
                dist.print0(json.dumps({"config": args.config, "overrides": list(args.overrides),
                                        **measure(trainer, source, args.steps, args.warmup)}))


if __name__ == "__main__":
    main()
