"""Start-up verification time (pipeline.data.stream.verify_shards, strict) of a dataset, every split, both backends.

    python benchmarks/bench_verify.py data/synthetic-minilm/manifest.json --cache DIR|off [--evict] [--runs N]

``--evict`` drops the dataset's files from the page cache before each run (posix_fadvise DONTNEED: no root
needed), so a run reads them from disk as a first start after a reboot would; ``--cache off`` hashes every
shard (what every start did before the verification cache). Run it with ``PYTHONPATH`` pointing at another
checkout to time that code (a code without the cache ignores ``--cache``)."""

from __future__ import annotations

import argparse
import inspect
import os
import time


def evict(folder: str) -> None:
    for root, _, files in os.walk(folder):
        for name in files:
            fd = os.open(os.path.join(root, name), os.O_RDONLY)
            try:
                os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
            finally:
                os.close(fd)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("manifest")
    parser.add_argument("--cache", default="off", help="cache folder, or 'off'")
    parser.add_argument("--evict", action="store_true", help="drop the files from the page cache before each run")
    parser.add_argument("--runs", type=int, default=1)
    parser.add_argument("--backends", default="webdataset,parquet")
    args = parser.parse_args()

    from pipeline.data.stream import open_manifest, verify_shards

    kwargs = {}
    if "cache" in inspect.signature(verify_shards).parameters:
        kwargs["cache"] = False if args.cache == "off" else args.cache
    folder = os.path.dirname(os.path.abspath(args.manifest)) if "://" not in args.manifest else None
    for backend in args.backends.split(","):
        for run in range(args.runs):
            if args.evict and folder:
                evict(folder)
            started = time.perf_counter()
            manifest = open_manifest(args.manifest)
            shards = cached = 0
            for split in manifest.data["splits"]:
                report = verify_shards(manifest, split, mode="strict", backend=backend, **kwargs)
                shards += report.num_checked
                cached += getattr(report, "num_from_cache", 0)
            print(f"{backend:10s} run {run}: {time.perf_counter() - started:7.3f} s  ({shards} shards, "
                  f"{cached} from the cache)", flush=True)


if __name__ == "__main__":
    main()
