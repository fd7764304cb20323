"""One rank of tests/test_data_multirank.py, started by torchrun (gloo, CPU).

For each batching (fixed windows, length-aware) and DataLoader worker count, each rank reads one epoch of its
share of the stream twice: in one go, and interrupted after ``cut`` batches (state saved, a fresh loader resumes).
Rank 0 writes what every rank saw to OUT as JSON: ``{batching: {num_workers: [rank 0 record, rank 1 record]}}``.
One launch covers them all because starting torchrun and two torch processes is most of the cost.

Usage: torchrun --standalone --nproc_per_node 2 tests/data_multirank_worker.py MANIFEST OUT 0,2 fixed,length_aware
"""

from __future__ import annotations

import json
import sys

import torch.distributed as dist

from pipeline.data.stream import LoaderOptions, MotionLoader


def read_epoch(manifest: str, num_workers: int, batching: str, rank: int, world_size: int) -> dict:
    options = LoaderOptions(batch_size=2, num_workers=num_workers, seed=3, window=48, shuffle_buffer=6,
                            batching=batching, pad_multiple=8, sort_window_batches=3)

    def loader() -> MotionLoader:
        return MotionLoader(manifest, "train", options, rank=rank, world_size=world_size)

    whole_batches = list(loader().iter_epoch())
    whole = [b["ids"] for b in whole_batches]
    first = loader()
    cut = 3
    interrupted = [next(batches)["ids"] for batches in [first.iter_batches()] for _ in range(cut)]
    resumed = loader()
    resumed.load_state_dict(first.state_dict())
    interrupted += [b["ids"] for b in resumed.iter_epoch()]
    mine = {"rank": rank, "batches": whole, "interrupted": interrupted, "state_after": resumed.state_dict(),
            "batches_per_epoch": first.batches_per_epoch(0), "samples_dropped": first.samples_dropped(0),
            "widths": [b["features"].shape[1] for b in whole_batches]}
    return mine


def main(manifest: str, out: str, worker_counts: list[int], batchings: list[str]) -> None:
    dist.init_process_group("gloo")
    rank, world_size = dist.get_rank(), dist.get_world_size()
    results: dict[str, dict[int, list]] = {}
    for batching in batchings:
        for num_workers in worker_counts:
            everyone = [None] * world_size
            dist.all_gather_object(everyone, read_epoch(manifest, num_workers, batching, rank, world_size))
            results.setdefault(batching, {})[num_workers] = everyone
    if rank == 0:
        with open(out, "w") as f:
            json.dump(results, f)
    dist.barrier()
    dist.destroy_process_group()


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], [int(w) for w in sys.argv[3].split(",")], sys.argv[4].split(","))
