"""One rank of a two-rank run that ends the way the entry points end (``ends_rank_processes``).

``python tests/rank_exit_worker.py OUT CODE`` under a launcher's RANK / WORLD_SIZE / MASTER_* variables: trains
one DistributedDataParallel step over gloo, closes the ``Dist``, registers an atexit handler, records the threads
still running, prints a line without flushing, and returns CODE. tests/test_rank_exit.py checks what survives the
exit.
"""

from __future__ import annotations

import atexit
import json
import os
import sys
from pathlib import Path

import torch

if __name__ == "__main__":  # run as a file: import the project, not tests/'s siblings
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from pipeline.distributed import Dist, ends_rank_processes


def thread_names() -> list[str]:
    """The names of this process's threads (Linux), native ones included."""
    tasks = Path("/proc/self/task")
    return sorted((tasks / task / "comm").read_text().strip() for task in os.listdir(tasks))


@ends_rank_processes
def main(out: Path, code: int) -> int:
    with Dist(mixed_precision="no", cpu=True) as dist:
        model = dist.prepare(torch.nn.Linear(3, 2))
        optimizer = torch.optim.SGD(model.parameters(), lr=0.1)
        model(torch.ones(4, 3)).sum().backward()
        optimizer.step()
        rank, world_size = dist.rank, dist.world_size
        del model, optimizer
    atexit.register((out / f"atexit-rank{rank}.txt").write_text, "the atexit handlers ran")
    (out / f"threads-rank{rank}.json").write_text(json.dumps({"world_size": world_size, "threads": thread_names()}))
    sys.stdout.write(f"rank {rank} returns {code}")  # no newline, no flush: the exit has to flush it
    return code


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1]), int(sys.argv[2])))
