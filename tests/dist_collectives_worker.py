"""One rank of tests/test_distributed.py: exercises every Dist collective and writes what it saw as JSON.

Run by the test under torchrun / accelerate launch with 2 CPU ranks; usage: dist_collectives_worker.py OUT_DIR.
Values are chosen so each rank's contribution is distinguishable (rank r contributes r + 1 rows, etc.).
It also runs the checkpoint flow the trainer uses: gather per-rank RNG state, save on rank 0, rank 0 resolves the
resume path and broadcasts it, every rank loads and restores its own RNG state.
"""

import json
import sys
from pathlib import Path

import torch

from pipeline.checkpoint import (
    capture_rng_state,
    load_checkpoint,
    resolve_resume,
    restore_rng_state,
    save_checkpoint,
)
from pipeline.distributed import Dist


def collectives(dist: Dist) -> dict:
    rank = dist.rank
    local = torch.tensor([float(rank), 10.0 - rank])
    before = local.clone()
    return {
        "rank": rank,
        "world_size": dist.world_size,
        "local_rank": dist.local_rank,
        "is_main": dist.is_main,
        "device": str(dist.device),
        "max": dist.all_reduce_max(local).tolist(),
        "min": dist.all_reduce_min(local).tolist(),
        "sum": dist.all_reduce_sum(local).tolist(),
        "input_untouched": bool(torch.equal(local, before)),
        "bool_max": dist.all_reduce_max(torch.tensor([rank == 1, False])).tolist(),
        "any_rank1": dist.any_across_ranks(rank == 1),
        "any_none": dist.any_across_ranks(False),
        "all_rank1": dist.all_across_ranks(rank == 1),
        "all_true": dist.all_across_ranks(True),
        "broadcast": dist.broadcast_object({"from": rank, "path": f"ckpt-of-rank-{rank}"}),
        "broadcast_src1": dist.broadcast_object(rank * 100, src=1),
        "all_gather": dist.all_gather_object({"rank": rank}),
        # uneven rows: rank r contributes r + 1 rows of value r
        "gather": dist.gather_tensor(torch.full((rank + 1, 2), float(rank))).tolist(),
        "gather_bool": dist.gather_tensor(torch.tensor([rank == 0] * (2 - rank))).tolist(),
    }


def checkpoint_round_trip(dist: Dist, ckpt_root: Path) -> dict:
    torch.manual_seed(100 + dist.rank)  # each rank has its own stream
    rng_states = dist.all_gather_object(capture_rng_state())
    expected = torch.rand(4)  # this rank's next draws after the capture
    data_states = dist.all_gather_object({"rank": dist.rank, "sample_in_epoch": 10 * dist.rank})
    if dist.is_main:
        model = torch.nn.Linear(3, 2)
        save_checkpoint(
            ckpt_root, 5, model_state=model.state_dict(), ema_state=None,
            optimizer_state=torch.optim.SGD(model.parameters(), lr=0.1).state_dict(), scheduler_state=None,
            rng_states=rng_states, data_states=data_states, config={}, manifest={"dataset_id": "x"},
        )
    dist.barrier()
    resume = dist.broadcast_object(resolve_resume("auto", ckpt_root) if dist.is_main else None)
    _, _, state = load_checkpoint(resume)
    restore_rng_state(state["rng"][dist.rank])
    return {
        "resume": resume.name,
        "rng_restored": bool(torch.equal(torch.rand(4), expected)),
        "data_state": state["data"][dist.rank],
    }


def main(out_dir: Path) -> None:
    with Dist(mixed_precision="no") as dist:
        result = collectives(dist)
        result.update(checkpoint_round_trip(dist, out_dir / "checkpoints"))
        dist.barrier()
    (out_dir / f"rank{result['rank']}.json").write_text(json.dumps(result))


if __name__ == "__main__":
    main(Path(sys.argv[1]))
