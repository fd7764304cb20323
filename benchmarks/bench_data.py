"""Throughput of the training data loader: one JSON line per (backend, worker count).

    python benchmarks/bench_data.py --manifest data/humanml3d-minilm/manifest.json --workers 0,2,4 --batch-size 64
    python benchmarks/bench_data.py --synthetic 400 --workers 0,2      # builds a synthetic dataset first

Fields: ``samples_per_s`` over ``--batches`` batches after the first; ``first_batch_s`` (start-up: worker
start, first shards opened); ``resume_first_batch_s``: first batch after ``load_state_dict`` at the middle
of the epoch (the fast-forward cost).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

from pipeline.data import LoaderOptions, MotionLoader, open_manifest


def build_synthetic(num_clips: int, out: Path) -> Path:
    """A synthetic HumanML3D-skeleton dataset with the real MiniLM text encoder, via the real builder."""
    from preprocess.shards import BuildConfig, build_dataset
    from preprocess.sources.synthetic import SyntheticSource

    config = BuildConfig(out=out, source="synthetic", text_encoder="minilm", shard_size=max(1, num_clips // 32),
                         progress=False)
    build_dataset(config, source=SyntheticSource(num_clips=num_clips))
    return out / "manifest.json"


def measure(manifest, split: str, options: LoaderOptions, num_batches: int, rank: int, world_size: int) -> dict:
    loader = MotionLoader(manifest, split, options, rank=rank, world_size=world_size)
    per_epoch = loader.batches_per_epoch(0)
    start = time.perf_counter()
    batches = loader.iter_batches()
    next(batches)
    first = time.perf_counter() - start
    start = time.perf_counter()
    samples = 0
    for _ in range(num_batches):
        samples += len(next(batches)["ids"])
    steady = time.perf_counter() - start
    del batches

    resumed = MotionLoader(manifest, split, options, rank=rank, world_size=world_size)
    resumed.load_state_dict({**resumed.state_dict(), "batches_in_epoch": per_epoch // 2})
    start = time.perf_counter()
    next(resumed.iter_batches())
    resume_first = time.perf_counter() - start
    return {"bench": "data_loader", "backend": options.backend, "num_workers": options.num_workers,
            "batch_size": options.batch_size, "world_size": world_size, "batches": num_batches,
            "batches_per_epoch": per_epoch, "samples_dropped_per_epoch": loader.samples_dropped(0),
            "first_batch_s": round(first, 4), "samples_per_s": round(samples / steady, 1),
            "resume_first_batch_s": round(resume_first, 4), "resume_at_batch": per_epoch // 2}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--manifest", help="manifest.json (path or URL) of a built dataset")
    source.add_argument("--synthetic", type=int, metavar="N", help="build N synthetic clips in a temp dir first")
    parser.add_argument("--split", default="train")
    parser.add_argument("--backend", default="webdataset", help="webdataset, parquet, or both (comma-separated)")
    parser.add_argument("--workers", default="0,2", help="comma-separated DataLoader worker counts")
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--batches", type=int, default=50, help="batches timed after the first")
    parser.add_argument("--window", type=int, default=196)
    parser.add_argument("--world-size", type=int, default=1, help="read rank --rank's share of this world")
    parser.add_argument("--rank", type=int, default=0)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)

    with tempfile.TemporaryDirectory() as tmp:
        manifest_path = args.manifest or build_synthetic(args.synthetic, Path(tmp) / "ds")
        manifest = open_manifest(manifest_path)
        for backend in args.backend.split(","):
            for workers in (int(w) for w in args.workers.split(",")):
                options = LoaderOptions(batch_size=args.batch_size, num_workers=workers, window=args.window,
                                        backend=backend)
                result = measure(manifest, args.split, options, args.batches, args.rank, args.world_size)
                print(json.dumps(result), flush=True)


if __name__ == "__main__":
    sys.exit(main())
