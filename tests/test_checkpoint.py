import errno
import json
import logging
import os
import random
import re
import shutil
import socket
import subprocess
import sys

import numpy as np
import pytest
import torch
from conftest import flip_byte
from torch import nn

import pipeline.checkpoint as ckpt
from pipeline.checkpoint import (
    COMPLETE_MARKER,
    EMA_FILE,
    MODEL_FILE,
    STATE_FILE,
    CheckpointError,
    CorruptCheckpointError,
    IncompleteCheckpointError,
    ResumeConflictError,
    capture_rng_state,
    checkpoints_dir,
    find_latest_complete,
    is_complete,
    load_checkpoint,
    prune_checkpoints,
    resolve_resume,
    restore_rng_state,
    save_checkpoint,
)


class TiedNet(nn.Module):
    """Small model with a tied weight (two state-dict keys sharing storage), as safetensors must handle."""

    def __init__(self) -> None:
        super().__init__()
        self.embed = nn.Linear(6, 8, bias=False)
        self.body = nn.Sequential(nn.Linear(8, 8), nn.GELU(), nn.Linear(8, 8))
        self.out = nn.Linear(8, 6, bias=False)
        self.out.weight = nn.Parameter(self.embed.weight.T.contiguous())
        self.head = nn.Linear(8, 6, bias=False)
        self.head.weight = self.out.weight  # tied

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.body(self.embed(x)))


def make_training_state(seed: int = 0):
    torch.manual_seed(seed)
    model = TiedNet()
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-2, weight_decay=0.01)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: min(1.0, (step + 1) / 10))
    for _ in range(3):
        loss = model(torch.randn(4, 6)).pow(2).mean()
        loss.backward()
        optimizer.step()
        scheduler.step()
        optimizer.zero_grad()
    ema = {k: v.detach().clone() * 0.5 for k, v in model.state_dict().items()}
    return model, optimizer, scheduler, ema


def save_step(root, step, *, model=None, optimizer=None, scheduler=None, ema=None, rng=None, **overrides):
    if model is None:
        model, optimizer, scheduler, ema = make_training_state(step)
    kwargs = dict(
        model_state=model.state_dict(),
        ema_state=ema,
        optimizer_state=optimizer.state_dict(),
        scheduler_state=scheduler.state_dict(),
        rng_states=rng if rng is not None else [capture_rng_state(), capture_rng_state()],
        data_states=[{"epoch": 1, "sample_in_epoch": 40 + step}, {"epoch": 1, "sample_in_epoch": 41 + step}],
        config={"train": {"max_steps": 100}, "optim": {"betas": [0.9, 0.999]}},
        manifest={"dataset_id": "abc123", "feature_spec": {"dim": 263}},
        extra={"samples_seen": 1234 + step, "nonfinite_skips": 2},
    )
    kwargs.update(overrides)
    return save_checkpoint(root, step, **kwargs)


def draws():
    return random.random(), float(np.random.rand()), torch.rand(3)


def test_round_trip_is_exact(tmp_path):
    model, optimizer, scheduler, ema = make_training_state()
    rank0 = capture_rng_state()
    expected_rank0 = draws()
    rank1 = capture_rng_state()  # a different state: the "other rank"
    expected_rank1 = draws()
    path = save_step(tmp_path, 1000, model=model, optimizer=optimizer, scheduler=scheduler, ema=ema, rng=[rank0, rank1])
    assert path == tmp_path / "step-00001000"
    assert sorted(os.listdir(path)) == sorted([MODEL_FILE, EMA_FILE, STATE_FILE, COMPLETE_MARKER])

    model_state, ema_state, state = load_checkpoint(path)
    reference = model.state_dict()
    assert model_state.keys() == reference.keys()
    for key, value in reference.items():
        assert torch.equal(model_state[key], value), key
    for key, value in ema.items():
        assert torch.equal(ema_state[key], value), key

    # optimizer and scheduler restore into fresh objects, bit for bit
    fresh_model, fresh_opt, fresh_sched, _ = make_training_state(seed=99)
    fresh_model.load_state_dict(model_state)
    fresh_opt.load_state_dict(state["optimizer"])
    fresh_sched.load_state_dict(state["scheduler"])
    assert fresh_opt.state_dict()["param_groups"] == optimizer.state_dict()["param_groups"]
    for pid, entry in optimizer.state_dict()["state"].items():
        for name, value in entry.items():
            assert torch.equal(fresh_opt.state_dict()["state"][pid][name], value), (pid, name)
    assert fresh_sched.state_dict() == scheduler.state_dict()

    # per-rank RNG: restoring rank r's state reproduces rank r's next draws
    for rank, expected in ((0, expected_rank0), (1, expected_rank1)):
        random.seed(12345)
        np.random.seed(12345)
        torch.manual_seed(12345)
        restore_rng_state(state["rng"][rank])
        got = draws()
        assert got[0] == expected[0] and got[1] == expected[1] and torch.equal(got[2], expected[2])

    assert state["step"] == 1000 and state["version"] == 1 and state["world_size"] == 2
    assert state["data"] == [{"epoch": 1, "sample_in_epoch": 1040}, {"epoch": 1, "sample_in_epoch": 1041}]
    assert state["extra"] == {"samples_seen": 2234, "nonfinite_skips": 2}
    assert state["manifest"]["dataset_id"] == "abc123"
    assert state["config"]["optim"]["betas"] == [0.9, 0.999]
    marker = json.loads((path / COMPLETE_MARKER).read_text())
    assert marker["step"] == 1000 and set(marker["files"]) == {MODEL_FILE, EMA_FILE, STATE_FILE}


def test_tied_weights_survive_and_training_resumes_identically(tmp_path):
    """Continue 2 steps from the checkpoint vs. from the live objects: identical parameters."""
    model, optimizer, scheduler, ema = make_training_state()
    path = save_step(tmp_path, 3, model=model, optimizer=optimizer, scheduler=scheduler, ema=ema)
    model_state, _, state = load_checkpoint(path)
    resumed, resumed_opt, resumed_sched, _ = make_training_state(seed=7)
    resumed.load_state_dict(model_state)
    resumed_opt.load_state_dict(state["optimizer"])
    resumed_sched.load_state_dict(state["scheduler"])
    batches = [torch.randn(4, 6) for _ in range(2)]
    for net, opt, sched in ((model, optimizer, scheduler), (resumed, resumed_opt, resumed_sched)):
        for batch in batches:
            net(batch).pow(2).mean().backward()
            opt.step()
            sched.step()
            opt.zero_grad()
    for (name, a), (_, b) in zip(model.state_dict().items(), resumed.state_dict().items(), strict=True):
        assert torch.equal(a, b), name


def test_no_ema_is_allowed(tmp_path):
    path = save_step(tmp_path, 5, ema_state=None)
    assert not (path / EMA_FILE).exists()
    _, ema_state, _ = load_checkpoint(path)
    assert ema_state is None


def test_find_latest_complete_ignores_folder_without_marker(tmp_path):
    for step in (10, 20, 30):
        save_step(tmp_path, step)
    (tmp_path / "step-00000030" / COMPLETE_MARKER).unlink()
    (tmp_path / "step-00000040.tmp-999").mkdir()  # an in-progress save
    assert find_latest_complete(tmp_path) == tmp_path / "step-00000020"
    assert resolve_resume("auto", tmp_path) == tmp_path / "step-00000020"


@pytest.mark.parametrize(
    "breakage",
    ["empty_marker", "garbage_marker", "truncated_model", "missing_state", "marker_of_other_step"],
)
def test_broken_final_folder_is_not_complete(tmp_path, breakage):
    save_step(tmp_path, 10)
    path = save_step(tmp_path, 20)
    if breakage == "empty_marker":
        (path / COMPLETE_MARKER).write_bytes(b"")
    elif breakage == "garbage_marker":
        (path / COMPLETE_MARKER).write_bytes(b"\x00\xff{not json")
    elif breakage == "truncated_model":
        data = (path / MODEL_FILE).read_bytes()
        (path / MODEL_FILE).write_bytes(data[: len(data) // 2])
    elif breakage == "missing_state":
        (path / STATE_FILE).unlink()
    elif breakage == "marker_of_other_step":
        shutil.copy(tmp_path / "step-00000010" / COMPLETE_MARKER, path / COMPLETE_MARKER)
    assert not is_complete(path)
    assert find_latest_complete(tmp_path) == tmp_path / "step-00000010"
    with pytest.raises(CheckpointError):
        load_checkpoint(path)


def test_same_size_corruption_is_caught_by_hash_on_load(tmp_path):
    path = save_step(tmp_path, 10)
    flip_byte(path / STATE_FILE, (path / STATE_FILE).stat().st_size // 2)
    with pytest.raises(CorruptCheckpointError, match="sha256"):
        load_checkpoint(path)


class SimulatedCrash(OSError):
    pass


@pytest.mark.parametrize("mode", ["raise_after_first_file", "zero_byte_file"])
def test_crash_mid_write_keeps_previous_checkpoint(tmp_path, monkeypatch, mode):
    previous = save_step(tmp_path, 10)
    real_write = ckpt._write_file
    calls = []

    def crashing_write(path, payload):
        calls.append(path.name)
        if mode == "raise_after_first_file" and len(calls) == 2:
            raise SimulatedCrash("disk full")
        if mode == "zero_byte_file" and path.name == STATE_FILE:
            path.write_bytes(b"")  # a kill after open() but before any byte reached the disk
            raise SimulatedCrash("killed")
        return real_write(path, payload)

    monkeypatch.setattr(ckpt, "_write_file", crashing_write)
    with pytest.raises(ckpt.CheckpointWriteError, match="step-00000020 was not saved") as err:
        save_step(tmp_path, 20)
    monkeypatch.undo()
    assert isinstance(err.value, OSError) and isinstance(err.value.__cause__, SimulatedCrash)

    # A failed save removes its partial folder itself (on a full disk it holds the space a restart needs).
    assert sorted(p.name for p in tmp_path.iterdir()) == ["step-00000010"]
    assert find_latest_complete(tmp_path) == previous
    assert resolve_resume("auto", tmp_path) == previous
    model_state, _, state = load_checkpoint(previous)
    assert state["step"] == 10 and model_state

    # A save that was killed leaves its partial folder: never read, and retention clears it once a newer
    # checkpoint commits.
    killed = tmp_path / ckpt.tmp_dir_name(20, pid=os.getpid() + 1)
    killed.mkdir()
    (killed / STATE_FILE).write_bytes(b"")
    assert resolve_resume("auto", tmp_path) == previous
    save_step(tmp_path, 30)
    removed = prune_checkpoints(tmp_path, keep_last=3)
    assert removed == [killed]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["step-00000010", "step-00000030"]


def test_saving_over_a_complete_step_is_refused(tmp_path):
    save_step(tmp_path, 10)
    with pytest.raises(FileExistsError, match="step-00000010"):
        save_step(tmp_path, 10)


def test_a_step_folder_we_did_not_write_is_never_moved_or_deleted(tmp_path):
    """Issue 24, finding 4: a user's folder named checkpoints/step-N was moved aside (step-N.tmp-incomplete-...) by a
    save and deleted at the next start-up. A step-N folder without our COMPLETE marker is now left as it is: the save
    of that step is refused, naming it, and no start-up or prune touches it."""
    theirs = tmp_path / "step-00000010"
    theirs.mkdir()
    (theirs / MODEL_FILE).write_bytes(b"the user's own file")
    (theirs / "COMPLETE").write_text('{"format": "someone-else"}')
    with pytest.raises(ckpt.CheckpointFolderTakenError, match=r"step-00000010 cannot be saved: .*not a checkpoint this "
                                                              r"project wrote"):
        save_step(tmp_path, 10)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["step-00000010"]
    assert (theirs / MODEL_FILE).read_bytes() == b"the user's own file"
    save_step(tmp_path, 20)
    assert ckpt.remove_stale_tmp(tmp_path) == [] and prune_checkpoints(tmp_path, keep_last=1) == []
    assert ckpt.foreign_step_folders(tmp_path) == [theirs] and (theirs / MODEL_FILE).exists()


def test_saving_over_a_damaged_checkpoint_of_ours_moves_it_aside_and_keeps_it(tmp_path):
    damaged = save_step(tmp_path, 10)
    (damaged / MODEL_FILE).write_bytes(b"cut short")  # ours (our marker), but a file is not what it lists
    path = save_step(tmp_path, 10)
    assert is_complete(path)
    (aside,) = [p for p in tmp_path.iterdir() if p.name.startswith("step-00000010.corrupt-")]
    assert (aside / MODEL_FILE).read_bytes() == b"cut short"
    assert ckpt.remove_stale_tmp(tmp_path) == [] and aside.exists()


def test_retention_keeps_last_k(tmp_path):
    for step in range(1, 6):
        save_step(tmp_path, step)
    removed = prune_checkpoints(tmp_path, keep_last=2)
    assert sorted(p.name for p in removed) == ["step-00000001", "step-00000002", "step-00000003"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["step-00000004", "step-00000005"]
    assert prune_checkpoints(tmp_path, keep_last=0) == []  # 0 keeps all
    assert len(list(tmp_path.iterdir())) == 2


def test_retention_never_removes_newest_complete_nor_newer_partials(tmp_path):
    save_step(tmp_path, 1)
    save_step(tmp_path, 2)
    newer_partial = tmp_path / "step-00000003"  # no marker: a save that crashed after... nothing; not ours to delete
    newer_partial.mkdir()
    in_progress = tmp_path / "step-00000004.tmp-77"
    in_progress.mkdir()
    stale = tmp_path / "step-00000001.tmp-55"
    stale.mkdir()
    removed = prune_checkpoints(tmp_path, keep_last=1)
    assert sorted(p.name for p in removed) == ["step-00000001", "step-00000001.tmp-55"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["step-00000002", "step-00000003", "step-00000004.tmp-77"]
    assert find_latest_complete(tmp_path) == tmp_path / "step-00000002"


def test_retention_with_nothing_complete_deletes_nothing(tmp_path):
    (tmp_path / "step-00000001.tmp-1").mkdir()
    assert prune_checkpoints(tmp_path, keep_last=1) == []
    assert (tmp_path / "step-00000001.tmp-1").exists()


def test_retention_survives_a_failed_delete(tmp_path, monkeypatch, caplog):
    for step in (1, 2, 3):
        save_step(tmp_path, step)

    def failing_rmtree(path, *args, **kwargs):
        raise PermissionError(13, "read-only", str(path))

    monkeypatch.setattr(ckpt.shutil, "rmtree", failing_rmtree)
    with caplog.at_level(logging.WARNING, logger="pipeline.checkpoint"):
        removed = prune_checkpoints(tmp_path, keep_last=1)
    assert removed == []
    assert "could not delete" in caplog.text
    assert find_latest_complete(tmp_path) == tmp_path / "step-00000003"


def test_resume_rules(tmp_path):
    root = checkpoints_dir(tmp_path / "run")
    assert root == tmp_path / "run" / "checkpoints"
    assert resolve_resume("auto", root) is None  # nothing yet: fresh start
    assert resolve_resume("never", root) is None
    with pytest.raises(FileNotFoundError, match="no such checkpoint folder"):
        resolve_resume(str(tmp_path / "missing" / "step-00000100"), root)

    path = save_step(root, 100)
    assert resolve_resume(str(path), root) == path
    assert resolve_resume("auto", root) == path
    with pytest.raises(FileExistsError, match="resume=never"):
        resolve_resume("never", root)
    with pytest.raises(IncompleteCheckpointError, match="step-XXXXXXXX"):
        resolve_resume(str(tmp_path / "run"), root)  # a run folder, not a checkpoint

    (path / COMPLETE_MARKER).unlink()
    with pytest.raises(IncompleteCheckpointError, match="COMPLETE"):
        resolve_resume(str(path), root)


def test_load_missing_folder_and_future_version(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_checkpoint(tmp_path / "step-00000001")
    path = save_step(tmp_path, 1)
    marker = json.loads((path / COMPLETE_MARKER).read_text())
    marker["version"] = 2
    (path / COMPLETE_MARKER).write_text(json.dumps(marker))
    with pytest.raises(CheckpointError, match="version 2"):
        load_checkpoint(path)


def test_per_rank_lists_must_agree(tmp_path):
    with pytest.raises(ValueError, match="one entry per rank"):
        save_step(tmp_path, 1, rng_states=[capture_rng_state()], data_states=[{}, {}])
    assert not tmp_path.exists() or not any(tmp_path.iterdir())


def test_non_tensor_in_model_state_is_rejected(tmp_path):
    with pytest.raises(TypeError, match="model.safetensors: 'step' is a int"):
        save_step(tmp_path, 1, model_state={"w": torch.zeros(2), "step": 3})


# ---------------------------------------------------------------------------------------------------------------
# A full disk, killed saves, corrupt and conflicting checkpoints (issue 12, items 4 and 5)
# ---------------------------------------------------------------------------------------------------------------


def test_a_save_on_a_full_disk_removes_its_folder_and_logs_space_needed_and_free(tmp_path, monkeypatch, caplog):
    """ENOSPC in the middle of a save: the partial folder is gone (it would hold the space a restart needs), one
    error line gives the space needed against the space free, and the next save succeeds."""
    previous = save_step(tmp_path, 10)
    real_write = ckpt._write_file

    def full_disk(path, payload):
        if path.parent.name.startswith("step-00000020") and path.name == STATE_FILE:
            path.write_bytes(payload[: len(payload) // 2])  # the disk fills up part-way through a file
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real_write(path, payload)

    monkeypatch.setattr(ckpt, "_write_file", full_disk)
    monkeypatch.setattr(ckpt.shutil, "disk_usage", lambda path: shutil._ntuple_diskusage(10**9, 10**9 - 12345, 12345))
    with caplog.at_level(logging.ERROR, logger="pipeline.checkpoint"), pytest.raises(ckpt.CheckpointWriteError) as err:
        save_step(tmp_path, 20)
    monkeypatch.undo()

    assert err.value.errno == errno.ENOSPC
    assert sorted(p.name for p in tmp_path.iterdir()) == ["step-00000010"]  # nothing partial left behind
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and errors[0] == str(err.value)
    needed = re.search(r"it needs ([\d.]+) MB, 0\.0 MB free on (\S+)$", errors[0])
    assert needed and "No space left on device" in errors[0] and needed.group(2) == str(tmp_path)

    saved = save_step(tmp_path, 20)  # space freed: the same save now goes through
    size = sum(f.stat().st_size for f in saved.iterdir() if f.name != COMPLETE_MARKER)
    assert float(needed.group(1)) == pytest.approx(size / 1e6, abs=0.05)
    assert find_latest_complete(tmp_path) == saved and is_complete(previous)


def dead_pid() -> int:
    """The pid of a process that has exited (and been reaped)."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_start_up_removes_unfinished_folders_of_dead_writers_only(tmp_path):
    host, gone = socket.gethostname().replace("-", "_"), dead_pid()
    complete = save_step(tmp_path, 10)
    aside = tmp_path / "step-00000030.corrupt-20250101T000000"
    aside.mkdir()
    stale = [
        tmp_path / ckpt.tmp_dir_name(20, pid=gone),  # a save killed on a full disk
        tmp_path / f"step-00000020.tmp-{gone}",  # named before the host was recorded
        tmp_path / f"step-00000020.tmp-delete-{host}-{gone}",  # a prune killed while deleting
        tmp_path / ckpt.tmp_dir_name(40, pid=os.getpid()),  # an earlier process with this pid (a container restart)
    ]
    kept = [
        tmp_path / ckpt.tmp_dir_name(40, pid=os.getppid()),  # a live process on this host: a save in progress
        tmp_path / "step-00000040.tmp-other_host-1",  # another host's: cannot be checked from here
        # set aside by an earlier version from ANY step-N folder without a valid marker, a user's included: kept
        tmp_path / f"step-00000020.tmp-incomplete-{host}-{gone}",
        tmp_path / "step-00000020.tmp-backup",  # not a name this code writes
    ]
    for folder in stale + kept:
        folder.mkdir()
        (folder / MODEL_FILE).write_bytes(b"x" * 100)

    assert sorted(ckpt.remove_stale_tmp(tmp_path)) == sorted(stale)
    assert sorted(tmp_path.iterdir()) == sorted([complete, aside, *kept])
    assert ckpt.remove_stale_tmp(tmp_path / "missing") == []


def test_auto_resume_sets_a_corrupt_newest_checkpoint_aside_and_falls_back(tmp_path, caplog):
    for step in (10, 20, 30):
        save_step(tmp_path, step)
    model_file = tmp_path / "step-00000030" / MODEL_FILE
    flip_byte(model_file, model_file.stat().st_size - 8)  # one flipped byte, same size
    flipped = model_file.read_bytes()
    assert is_complete(tmp_path / "step-00000030")  # sizes alone do not see it

    with caplog.at_level(logging.WARNING, logger="pipeline.checkpoint"):
        assert resolve_resume("auto", tmp_path) == tmp_path / "step-00000020"
    aside = [p for p in tmp_path.iterdir() if p.name.startswith("step-00000030.")]
    assert len(aside) == 1 and re.fullmatch(r"step-00000030\.corrupt-\d{8}T\d{6}", aside[0].name)
    assert (aside[0] / MODEL_FILE).read_bytes() == flipped  # moved, not deleted
    assert "step-00000030 is corrupt" in caplog.text and aside[0].name in caplog.text
    assert prune_checkpoints(tmp_path, keep_last=1) == [tmp_path / "step-00000010"]  # never pruned
    assert aside[0].exists()


def test_auto_resume_refuses_when_no_checkpoint_verifies(tmp_path):
    path = save_step(tmp_path, 10)
    flip_byte(path / STATE_FILE, (path / STATE_FILE).stat().st_size // 2)
    with pytest.raises(CorruptCheckpointError, match="train.resume=never"):
        resolve_resume("auto", tmp_path)
    assert [p.name.split(".")[1].split("-")[0] for p in tmp_path.iterdir()] == ["corrupt"]
    assert resolve_resume("never", tmp_path) is None  # the way to start over that the message names


def test_explicit_older_resume_refuses_newer_checkpoints_or_sets_them_aside(tmp_path, caplog):
    older = save_step(tmp_path, 10)
    save_step(tmp_path, 20)
    save_step(tmp_path, 30)
    with pytest.raises(ResumeConflictError, match="train.resume_discard_newer=true") as err:
        resolve_resume(str(older), tmp_path)
    assert "step-00000020, step-00000030" in str(err.value) and "resume=auto" in str(err.value)
    assert [step for step, _ in ckpt.list_complete(tmp_path)] == [10, 20, 30]  # refused: nothing touched
    assert resolve_resume(str(tmp_path / "step-00000030"), tmp_path) == tmp_path / "step-00000030"

    with caplog.at_level(logging.WARNING, logger="pipeline.checkpoint"):
        assert resolve_resume(str(older), tmp_path, discard_newer=True) == older
    assert sorted(p.name.split(".")[0] for p in tmp_path.iterdir() if ".discarded-" in p.name) == [
        "step-00000020", "step-00000030"]
    assert "moved step-00000020 aside" in caplog.text
    assert find_latest_complete(tmp_path) == older
    assert is_complete(save_step(tmp_path, 20))  # training on from 10 can save its own step 20
