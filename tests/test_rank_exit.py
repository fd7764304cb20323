"""How a process that was one rank of several ends (pipeline.distributed.ends_rank_processes).

DistributedDataParallel keeps the gloo process group, and its threads, alive past ``destroy_process_group``; the
entry points therefore end such a process with ``os._exit`` once their atexit handlers have run, rather than let
interpreter finalization tear those threads down (a rare abort: "terminate called without an active exception").
These tests show the leak that makes it necessary, and that nothing a normal exit does is lost: the exit code,
atexit handlers, unflushed output.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from tests import rank_exit_worker
from tests.test_trainer import LAUNCH_VARS, REPO_ROOT, clean_env

WORKER = REPO_ROOT / "tests" / "rank_exit_worker.py"


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def start_rank(rank: int, port: int, out: Path, code: int) -> subprocess.Popen:
    env = clean_env()
    env.update(RANK=str(rank), LOCAL_RANK=str(rank), WORLD_SIZE="2", LOCAL_WORLD_SIZE="2", MASTER_ADDR="127.0.0.1",
               MASTER_PORT=str(port))
    env.pop("PYTHONUNBUFFERED")  # stdout to a file is block-buffered: what the exit must flush
    stdout = open(out / f"stdout-rank{rank}.txt", "w")  # noqa: SIM115 (closed by the child's exit)
    return subprocess.Popen([sys.executable, str(WORKER), str(out), str(code)], cwd=REPO_ROOT, env=env,
                            stdout=stdout, stderr=subprocess.PIPE, text=True)


@pytest.mark.multirank
def test_a_rank_ends_with_its_code_after_its_atexit_handlers_and_flushed_output(tmp_path):
    port = free_port()
    ranks = [start_rank(rank, port, tmp_path, code=3) for rank in (0, 1)]
    stderr = [proc.communicate(timeout=120)[1] for proc in ranks]
    assert [proc.returncode for proc in ranks] == [3, 3], stderr
    for rank in (0, 1):
        assert (tmp_path / f"atexit-rank{rank}.txt").read_text() == "the atexit handlers ran"
        assert (tmp_path / f"stdout-rank{rank}.txt").read_text() == f"rank {rank} returns 3"
        record = json.loads((tmp_path / f"threads-rank{rank}.json").read_text())
        # Why the exit is needed: after Dist.close (destroy_process_group) the DDP-held gloo group still runs its
        # worker threads. If a torch release frees it, this fails: ends_rank_processes can then go.
        assert record["world_size"] == 2 and "pt_gloo_runloop" in record["threads"], record


def test_a_single_process_returns_its_code(tmp_path, monkeypatch):
    """In-process (every single-process test calls main() this way) nothing exits: the code is returned."""
    for name in LAUNCH_VARS:
        monkeypatch.delenv(name, raising=False)
    assert rank_exit_worker.main(tmp_path, 5) == 5
    assert json.loads((tmp_path / "threads-rank0.json").read_text())["world_size"] == 1
