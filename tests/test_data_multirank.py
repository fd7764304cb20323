"""Two real gloo ranks (torchrun, CPU) each read one epoch, with fixed windows and with length-aware batches:
every sample at most once across ranks, the documented remainder dropped, equal batch counts, and an interrupted +
resumed epoch identical to an uninterrupted one; length-aware batches hold the same samples as fixed windows in
narrower batches."""

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
           str(WORKER), str(manifest), str(out), "0,2", "fixed,length_aware"]
    proc = subprocess.run(cmd, cwd=WORKER.parents[1], env=env, capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    results = json.loads(out.read_text())
    assert sorted(results) == ["fixed", "length_aware"]
    for batching, by_workers in results.items():
        assert sorted(by_workers) == ["0", "2"]
        for num_workers, ranks in by_workers.items():
            check_one_epoch(ranks, f"{batching}, {num_workers}")
    for num_workers, ranks in results["length_aware"].items():
        fixed = results["fixed"][num_workers]
        assert [r["batches_per_epoch"] for r in ranks] == [r["batches_per_epoch"] for r in fixed]
        assert {i for r in ranks for b in r["batches"] for i in b} == {i for r in fixed for b in r["batches"] for i in b}
        assert all(w == 48 for r in fixed for w in r["widths"])
        widths = [w for r in ranks for w in r["widths"]]
        assert sum(widths) < 0.9 * 48 * len(widths), "length-aware batches are not narrower than the window"


def check_one_epoch(ranks: list[dict], case: str) -> None:
    assert [r["rank"] for r in ranks] == [0, 1]
    per_epoch = ranks[0]["batches_per_epoch"]
    assert per_epoch > 0 and all(len(r["batches"]) == per_epoch for r in ranks), f"{case} workers: ranks got unequal batch counts"
    ids = [i for r in ranks for batch in r["batches"] for i in batch]
    assert len(ids) == len(set(ids)), "a sample was read twice in one epoch"
    all_ids = {motion_id(n) for n in range(sum(UNEVEN))}
    assert set(ids) <= all_ids and len(ids) == len(all_ids) - ranks[0]["samples_dropped"]
    for r in ranks:
        assert r["interrupted"] == r["batches"], f"rank {r['rank']}: resumed epoch differs"
        assert (r["state_after"]["epoch"], r["state_after"]["batches_in_epoch"]) == (1, 0)
