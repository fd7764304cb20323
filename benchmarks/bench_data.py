"""Throughput of the training data loader: one JSON line per (backend, worker count).

    python benchmarks/bench_data.py --manifest data/humanml3d-minilm/manifest.json --workers 0,2,4 --batch-size 64
    python benchmarks/bench_data.py --synthetic 400 --workers 0,2      # builds a synthetic dataset first

Fields: ``samples_per_s`` and ``batches_per_s`` over ``--batches`` batches after the first; ``first_batch_s``
(start-up: worker start, first shards opened); ``resume_first_batch_s``: first batch after ``load_state_dict`` at
the middle of the epoch (the fast-forward cost).

``--text-dim E`` builds the synthetic set with :class:`HashedTextEncoder` (E-dimensional stand-in embeddings, no
model to load) instead of the real MiniLM encoder: loader speed depends on the embedding's width, not its meaning.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from mfm.text import RANDOM_INIT_SHA256, TextEncoding
from pipeline.data.stream import LoaderOptions, MotionLoader, open_manifest


class HashedTextEncoder:
    """A stand-in text encoder of any width for speed benchmarks: each caption's embedding is a fixed pseudo-random
    N(0, 1) vector seeded by the caption's sha256 (identical captions, identical vectors).

    Why: the real encoders take seconds to load and CLIP's weights may be absent on a benchmark machine, while
    loader and training speed depend on the embedding's width only (512 for HumanML3D's CLIP ViT-B/32), never on
    what it means. Token features, if asked for, repeat the pooled vector."""

    weights_sha256 = RANDOM_INIT_SHA256

    def __init__(self, dim: int) -> None:
        if dim < 1:
            raise ValueError(f"dim must be >= 1, got {dim}")
        self.dim = dim
        self.id = f"hashed-{dim}"
        self.options: dict[str, Any] = {}

    def embed(self, text: str) -> np.ndarray:
        seed = int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "little")
        return np.random.default_rng(seed).standard_normal(self.dim).astype(np.float32)

    def encode(self, texts: list[str], *, token_features: bool = False, max_tokens: int = 32,
               batch_size: int = 64) -> TextEncoding:
        pooled = np.stack([self.embed(text) for text in texts]).astype(np.float32).reshape(len(texts), self.dim)
        if not token_features:
            return TextEncoding(pooled=pooled)
        tokens = np.repeat(pooled[:, None, :], max_tokens, axis=1)
        return TextEncoding(pooled=pooled, tokens=tokens, token_lengths=np.full(len(texts), max_tokens, np.int32))


def build_synthetic(num_clips: int, out: Path, *, text_dim: int | None = None,
                    formats: tuple[str, ...] | None = None) -> Path:
    """A synthetic HumanML3D-skeleton dataset (263-D features) via the real builder, in about 32 shards so that
    several loader workers each get shards to read. Captions are encoded by the real MiniLM encoder, or, with
    ``text_dim``, by :class:`HashedTextEncoder` at that width. ``formats``: which shard copies to write (default:
    the builder's, tar and Parquet)."""
    from preprocess.shards import BuildConfig, build_dataset
    from preprocess.sources.synthetic import SyntheticSource

    encoder = None if text_dim is None else HashedTextEncoder(text_dim)
    options: dict[str, Any] = {} if formats is None else {"formats": formats}
    config = BuildConfig(out=out, source="synthetic", text_encoder="minilm" if encoder is None else encoder.id,
                         shard_size=max(1, num_clips // 32), progress=False, **options)
    build_dataset(config, source=SyntheticSource(num_clips=num_clips), text_encoder=encoder)
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
            "batches_per_s": round(num_batches / steady, 2),
            "resume_first_batch_s": round(resume_first, 4), "resume_at_batch": per_epoch // 2}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--manifest", help="manifest.json (path or URL) of a built dataset")
    source.add_argument("--synthetic", type=int, metavar="N", help="build N synthetic clips in a temp dir first")
    parser.add_argument("--text-dim", type=int, metavar="E",
                        help="--synthetic: E-dimensional stand-in text embeddings instead of MiniLM (no model load)")
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
        manifest_path = args.manifest or build_synthetic(args.synthetic, Path(tmp) / "ds", text_dim=args.text_dim)
        manifest = open_manifest(manifest_path)
        for backend in args.backend.split(","):
            for workers in (int(w) for w in args.workers.split(",")):
                options = LoaderOptions(batch_size=args.batch_size, num_workers=workers, window=args.window,
                                        backend=backend)
                result = measure(manifest, args.split, options, args.batches, args.rank, args.world_size)
                print(json.dumps(result), flush=True)


if __name__ == "__main__":
    sys.exit(main())
