"""Preprocessing speed on the synthetic source: one JSON line per measurement.

    python benchmarks/bench_preprocess.py --num-clips 200 --workers 1 2

Stages: ``features`` = load + validate + resample + feature extraction over the whole source
(``process_source``, worker start-up included); ``build`` = the whole ``build_dataset`` (features, spill,
caption encoding, tar + Parquet shards, manifest), with the text encoder built beforehand and timed on
its own line (``text_encoder_load``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

if __package__ in (None, ""):
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from mfm.text import build_text_encoder
from preprocess.processing import ProcessingSettings, process_source
from preprocess.shards import BuildConfig, build_dataset, resolve_skeleton
from preprocess.sources import build_source


def emit(**fields) -> None:
    print(json.dumps({"benchmark": "preprocess", **fields, "cpus": os.cpu_count(), "python": platform.python_version()}),
          flush=True)


def time_features(num_clips: int, seed: int, workers: int) -> None:
    source = build_source("synthetic", None, num_clips=num_clips, seed=seed)
    items = source.list_items()
    start = time.perf_counter()
    motions = sum(len(r) for r in process_source(source, items, resolve_skeleton(source), ProcessingSettings(),
                                                   workers=workers) if isinstance(r, list))
    seconds = time.perf_counter() - start
    emit(stage="features", workers=workers, clips=len(items), motions=motions, seconds=round(seconds, 3),
         motions_per_s=round(motions / seconds, 2))


def time_build(num_clips: int, seed: int, workers: int, encoder, text_encoder: str) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        config = BuildConfig(out=Path(tmp) / "ds", source="synthetic", text_encoder=text_encoder,
                             source_options={"num_clips": num_clips, "seed": seed}, workers=workers, progress=False)
        start = time.perf_counter()
        manifest = build_dataset(config, text_encoder=encoder)
        seconds = time.perf_counter() - start
    motions = sum(s["num_motions"] for s in manifest["splits"].values())
    emit(stage="build", workers=workers, clips=num_clips, motions=motions,
         captions=manifest["text_encoder"]["num_distinct_captions"], seconds=round(seconds, 3),
         motions_per_s=round(motions / seconds, 2))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--num-clips", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--text-encoder", default="minilm")
    parser.add_argument("--stages", nargs="+", choices=("features", "build"), default=["features", "build"])
    args = parser.parse_args()

    for workers in args.workers if "features" in args.stages else []:
        time_features(args.num_clips, args.seed, workers)
    if "build" in args.stages:
        start = time.perf_counter()
        encoder = build_text_encoder(args.text_encoder)
        emit(stage="text_encoder_load", encoder=args.text_encoder, seconds=round(time.perf_counter() - start, 3))
        for workers in args.workers:
            time_build(args.num_clips, args.seed, workers, encoder, args.text_encoder)


if __name__ == "__main__":
    main()
