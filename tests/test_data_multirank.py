"""Two real gloo ranks (torchrun, CPU) each read one epoch: every sample at most once across ranks, the
documented remainder dropped, equal batch counts, and an interrupted + resumed epoch identical to an
uninterrupted one."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from test_data import UNEVEN, motion_id, write_fixture_dataset

WORKER = Path(__file__).with_name("data_multirank_worker.py")


@pytest.mark.multirank
def test_two_gloo_ranks_read_each_sample_once(tmp_path):
    manifest = write_fixture_dataset(tmp_path / "data")
    out = tmp_path / "ranks.json"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           str(WORKER), str(manifest), str(out), "0,2"]
    proc = subprocess.run(cmd, cwd=WORKER.parents[1], env=env, capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    results = json.loads(out.read_text())
    assert sorted(results) == ["0", "2"]
    for num_workers, ranks in results.items():
        check_one_epoch(ranks, num_workers)


def check_one_epoch(ranks: list[dict], num_workers: str) -> None:
    assert [r["rank"] for r in ranks] == [0, 1]
    per_epoch = ranks[0]["batches_per_epoch"]
    assert per_epoch > 0 and all(len(r["batches"]) == per_epoch for r in ranks), f"workers {num_workers}: ranks got unequal batch counts"
    ids = [i for r in ranks for batch in r["batches"] for i in batch]
    assert len(ids) == len(set(ids)), "a sample was read twice in one epoch"
    all_ids = {motion_id(n) for n in range(sum(UNEVEN))}
    assert set(ids) <= all_ids and len(ids) == len(all_ids) - ranks[0]["samples_dropped"]
    for r in ranks:
        assert r["interrupted"] == r["batches"], f"rank {r['rank']}: resumed epoch differs"
        assert (r["state_after"]["epoch"], r["state_after"]["batches_in_epoch"]) == (1, 0)
