"""One rank of tests/test_data_multirank.py, started by torchrun (gloo, CPU).

For each DataLoader worker count, each rank reads one epoch of its share of the stream twice: in one go,
and interrupted after ``cut`` batches (state saved, a fresh loader resumes). Rank 0 writes what every rank
saw to OUT as JSON: ``{num_workers: [rank 0 record, rank 1 record]}``. One launch covers all worker counts
because starting torchrun and two torch processes is most of the cost.

Usage: torchrun --standalone --nproc_per_node 2 tests/data_multirank_worker.py MANIFEST OUT 0,2
"""

from __future__ import annotations

import json
import sys

import torch.distributed as dist

from pipeline.data.stream import LoaderOptions, MotionLoader


def read_epoch(manifest: str, num_workers: int, rank: int, world_size: int) -> dict:
    options = LoaderOptions(batch_size=2, num_workers=num_workers, seed=3, window=24, shuffle_buffer=6)

    def loader() -> MotionLoader:
        return MotionLoader(manifest, "train", options, rank=rank, world_size=world_size)

    whole = [b["ids"] for b in loader().iter_epoch()]
    first = loader()
    cut = 3
    interrupted = [next(batches)["ids"] for batches in [first.iter_batches()] for _ in range(cut)]
    resumed = loader()
    resumed.load_state_dict(first.state_dict())
    interrupted += [b["ids"] for b in resumed.iter_epoch()]
    mine = {"rank": rank, "batches": whole, "interrupted": interrupted, "state_after": resumed.state_dict(),
            "batches_per_epoch": first.batches_per_epoch(0), "samples_dropped": first.samples_dropped(0)}
    return mine


def main(manifest: str, out: str, worker_counts: list[int]) -> None:
    dist.init_process_group("gloo")
    rank, world_size = dist.get_rank(), dist.get_world_size()
    results = {}
    for num_workers in worker_counts:
        everyone = [None] * world_size
        dist.all_gather_object(everyone, read_epoch(manifest, num_workers, rank, world_size))
        results[num_workers] = everyone
    if rank == 0:
        with open(out, "w") as f:
            json.dump(results, f)
    dist.barrier()
    dist.destroy_process_group()


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], [int(w) for w in sys.argv[3].split(",")])
