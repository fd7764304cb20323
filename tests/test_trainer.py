"""The training loop's promises at one rank (CPU, tiny model): it learns, its run folder is complete, a hard-killed
run resumes bit-exactly (weights, EMA, optimizer, RNG, data order, per-step losses), signals stop it cleanly with
128 + N, non-finite losses are skipped within a budget, and bad shards are refused or skipped as configured.

Runs that are compared bit for bit run as separate processes through tests/trainer_worker.py (same thread count
in every run; the uninterrupted reference runs of several tests may share one, each fit seeding itself afresh, while
every killed run and every resume is a fresh process); the rest run in this process through launch/train.py's
``main``.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import errno
import hashlib
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tarfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import pytest
import torch
import yaml
from conftest import REPO_ROOT, flip_byte, load_launch_script, start_two_at_a_time

import pipeline.training.run_folder as run_folder_module
import pipeline.training.trainer as trainer_module
from pipeline import checkpoint as ckpt
from pipeline.config import ConfigError, TrainConfig, from_dict, load_config, to_dict
from pipeline.data.stream import ShardVerificationError
from pipeline.distributed import Dist
from pipeline.training.run_folder import (
    RUN_LOCK,
    RUN_MARKER,
    RunFolderError,
    RunFolderInUseError,
    RunFolderLock,
    check_run_folder,
    write_run_marker,
)
from pipeline.training.trainer import EMA, NonFiniteLossError, Trainer

train_entry = load_launch_script("train")  # launch/train.py, whose main() the in-process tests call

WORKER = REPO_ROOT / "tests" / "trainer_worker.py"
LAUNCH_VARS = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "LOCAL_WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT", "GROUP_RANK",
               "ROLE_RANK", "ROLE_WORLD_SIZE", "TORCHELASTIC_RUN_ID", "ACCELERATE_USE_CPU",
               "ACCELERATE_MIXED_PRECISION")

# Resume scenario: checkpoints every 5 steps, killed in the middle of step 12 (so steps 11-12 are replayed from
# checkpoint 10), 16 steps in all. At one rank an epoch is 13 batches (checkpoint 10 lies inside epoch 0 and the
# resumed run crosses into epoch 1); with 2 workers it is 10 (checkpoint 10 lies on the epoch boundary).
MAX_STEPS, SAVE_EVERY, KILL_STEP = 16, 5, 12


# ---------------------------------------------------------------------------------------------------------------
# Shared helpers (also used by test_trainer_multirank.py)
# ---------------------------------------------------------------------------------------------------------------


def build_dataset_once(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """60 synthetic clips (53 train in 6 shards of <= 10), MiniLM captions; built once per test session.

    Built by build_shards' ``main`` in this process, whose output is byte for byte the command line's
    (tests/test_build_shards.py): a launch would spend seconds importing what this process has imported anyway."""
    from preprocess.build_shards import main as build_shards

    root = tmp_path_factory.getbasetemp() / "trainer-dataset"
    manifest = root / "manifest.json"
    if not manifest.exists():
        building = root.with_name("trainer-dataset.building")
        shutil.rmtree(building, ignore_errors=True)
        assert build_shards(["--source", "synthetic", "--num-clips", "60", "--shard-size", "10", "--out",
                             str(building), "--quiet"]) == 0
        os.rename(building, root)
    return manifest


@pytest.fixture(scope="session")
def dataset(tmp_path_factory) -> Path:
    return build_dataset_once(tmp_path_factory)


def clean_env() -> dict[str, str]:
    """This environment without any launcher variables, one intra-op thread, offline, no W&B."""
    env = {k: v for k, v in os.environ.items() if k not in LAUNCH_VARS}
    env.update(OMP_NUM_THREADS="1", HF_HUB_OFFLINE="1", WANDB_MODE="disabled", PYTHONUNBUFFERED="1")
    return env


def base_overrides(manifest: Path, out_dir: Path, *extra: str) -> list[str]:
    return [f"data.manifest={manifest}", f"train.out_dir={out_dir}", "train.log_every=1", *extra]


def resume_overrides(manifest: Path, out_dir: Path, *extra: str) -> list[str]:
    return base_overrides(manifest, out_dir, f"train.max_steps={MAX_STEPS}", f"train.save_every={SAVE_EVERY}",
                          "train.keep_last=2", *extra)


def run_worker(launcher: list[str], scenarios: list[dict[str, Any]], spec_dir: Path, timeout: float = 240,
               env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """Run tests/trainer_worker.py under ``launcher`` (e.g. [python] or [python, -m, torch.distributed.run, ...])."""
    spec_dir.mkdir(parents=True, exist_ok=True)
    spec = spec_dir / "spec.json"
    spec.write_text(json.dumps(scenarios))
    return subprocess.run(launcher + [str(WORKER), str(spec)], cwd=REPO_ROOT, env=env or clean_env(),
                          capture_output=True, text=True, timeout=timeout)


def output_of(proc: subprocess.CompletedProcess) -> str:
    return f"exit {proc.returncode}\n--- stdout\n{proc.stdout[-4000:]}\n--- stderr\n{proc.stderr[-6000:]}"


def fit_scenario(out: Path, overrides: list[str], **faults: Any) -> dict[str, Any]:
    return {"kind": "fit", "out": str(out), "overrides": overrides, "record_ids": True, **faults}


def results(out: Path, ranks: int) -> list[dict[str, Any]]:
    return [json.loads((out / f"result-rank{r}.json").read_text()) for r in range(ranks)]


def metrics_by_step(run_dir: Path) -> dict[int, dict[str, Any]]:
    """metrics.jsonl as {step: record}; fails if a step was logged twice (a resumed run must not duplicate)."""
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    steps = [r["step"] for r in records]
    assert steps == sorted(set(steps)), f"metrics.jsonl steps not strictly increasing: {steps}"
    return {r["step"]: r for r in records}


def ids_by_step(out: Path, rank: int) -> dict[int, list[list[str]]]:
    """Sample ids each step consumed on ``rank``; a step recorded twice (replayed after a kill) must agree."""
    seen: dict[int, list[list[str]]] = {}
    for line in (out / f"ids-rank{rank}.jsonl").read_text().splitlines():
        record = json.loads(line)
        if record["step"] in seen:
            assert seen[record["step"]] == record["ids"], f"step {record['step']} replayed with different samples"
        seen[record["step"]] = record["ids"]
    return seen


def complete_steps(run_dir: Path) -> list[int]:
    return [step for step, _ in ckpt.list_complete(ckpt.checkpoints_dir(run_dir))]


def assert_identical(a: Any, b: Any, where: str = "state") -> None:
    """Recursive equality with tensors compared by dtype, shape and every bit (atol = rtol = 0)."""
    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and a.dtype == b.dtype, f"{where}: {b!r} is not a {a.dtype} tensor"
        identical = a.shape == b.shape and torch.equal(a, b)
        assert identical, f"{where} differs" + (f" (max |a - b| {(a - b).abs().max()})" if a.shape == b.shape else "")
    elif isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), f"{where}: keys differ"
        for key in a:
            assert_identical(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, (list, tuple)):
        assert isinstance(b, (list, tuple)) and len(a) == len(b), f"{where}: lengths differ"
        for i, (x, y) in enumerate(zip(a, b)):
            assert_identical(x, y, f"{where}[{i}]")
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


def assert_runs_identical(run_a: Path, run_b: Path, step: int, differing: tuple[str, ...] = (),
                          log_every: int = 1, resumed_from: int = 0) -> None:
    """Final checkpoints equal bit for bit (model, EMA, optimizer, scheduler, per-rank RNG and data position,
    counters) and the same metrics at every ``log_every``-th step (but the loss of a window that a resume from
    step ``resumed_from`` cut short: it averages fewer steps); only the run folder differs, and the
    ``train.<key>`` settings named in ``differing``."""
    model_a, ema_a, state_a = ckpt.load_checkpoint(ckpt.checkpoints_dir(run_a) / ckpt.step_dir_name(step))
    model_b, ema_b, state_b = ckpt.load_checkpoint(ckpt.checkpoints_dir(run_b) / ckpt.step_dir_name(step))
    assert_identical(model_a, model_b, "model")
    assert_identical(ema_a, ema_b, "ema")
    for state in (state_a, state_b):
        for key in ("out_dir", *differing):
            del state["config"]["train"][key]
    assert_identical(state_a, state_b, "state.pt")
    metrics_a, metrics_b = metrics_by_step(run_a), metrics_by_step(run_b)
    assert sorted(metrics_a) == sorted(metrics_b) == list(range(log_every, step + 1, log_every))
    deterministic = ("loss", "grad_norm", "lr", "epoch", "samples_seen", "skipped_steps", "records_skipped")
    for s in metrics_a:
        keys = [k for k in deterministic if k != "loss" or not s - log_every < resumed_from < s]
        assert {k: metrics_a[s][k] for k in keys} == {k: metrics_b[s][k] for k in keys}, s


# ---------------------------------------------------------------------------------------------------------------
# It learns; the run folder holds what it promises
# ---------------------------------------------------------------------------------------------------------------


def test_loss_decreases_and_run_folder_is_complete(dataset, tmp_path):
    run = tmp_path / "run"
    overrides = base_overrides(dataset, run, "train.max_steps=60", "train.save_every=20", "train.keep_last=2",
                               "data.batch_size=8", "optim.lr=2e-3", "model.dropout=0.0")
    assert train_entry.main(["--config", "tiny", *overrides]) == 0

    metrics = metrics_by_step(run)
    assert sorted(metrics) == list(range(1, 61))
    # The flow-matching loss of one batch swings with its random times t: compare 10-step means.
    first = sum(metrics[s]["loss"] for s in range(1, 11)) / 10
    last = sum(metrics[s]["loss"] for s in range(51, 61)) / 10
    assert last < 0.8 * first, f"loss did not decrease: first 10 steps {first:.3f}, last 10 {last:.3f}"
    assert metrics[60]["samples_seen"] == 60 * 8 and metrics[60]["skipped_steps"] == 0

    saved = from_dict(TrainConfig, yaml.safe_load((run / "config.yaml").read_text()))
    assert saved.train.max_steps == 60 and saved.data.manifest == str(dataset)
    # keep_last=2: of the checkpoints at 20, 40, 60 the two newest remain, complete, nothing half-written
    assert complete_steps(run) == [40, 60]
    assert sorted(p.name for p in ckpt.checkpoints_dir(run).iterdir()) == ["saved.jsonl", "step-00000040",
                                                                             "step-00000060"]
    # ... and the listing of completed saves still names the pruned one
    assert [(c.step, c.name) for c in ckpt.read_saved(ckpt.checkpoints_dir(run))] == [
        (20, "step-00000020"), (40, "step-00000040"), (60, "step-00000060")]
    _, ema, state = ckpt.load_checkpoint(ckpt.checkpoints_dir(run) / "step-00000060")
    assert state["step"] == 60 and state["world_size"] == 1 and state["extra"]["samples_seen"] == 480
    assert ema is not None and state["extra"]["ema_updates"] == 60


def test_init_seed_sets_the_initial_weights_and_train_seed_the_draws(dataset, tmp_path):
    """train.init_seed: the weights start as those of a run whose train.seed is init_seed, while the flow loss's
    draws (times, noise, condition dropout) stay train.seed's; init_seed = train.seed is the run without it."""

    def one_step(name: str, *seeds: str) -> tuple[dict[str, torch.Tensor], float]:
        run = tmp_path / name  # one step at a negligible rate: the weights are the initial ones within 1e-6
        overrides = base_overrides(dataset, run, "train.max_steps=1", "train.save_every=1", "optim.lr=1e-12",
                                   "model.dropout=0.0", *seeds)
        assert train_entry.main(["--config", "tiny", *overrides]) == 0
        weights, _, _ = ckpt.load_checkpoint(ckpt.resolve_checkpoint(run))
        return weights, metrics_by_step(run)[1]["loss"]

    seed0, loss0 = one_step("seed0", "train.seed=0")
    seed1, loss1 = one_step("seed1", "train.seed=1")
    init0_draws1, loss_init0_draws1 = one_step("init0-draws1", "train.seed=1", "train.init_seed=0")
    init1_draws1, loss_init1_draws1 = one_step("init1-draws1", "train.seed=1", "train.init_seed=1")

    assert any(not torch.allclose(seed0[name], seed1[name]) for name in seed0)
    for name, value in seed0.items():
        torch.testing.assert_close(init0_draws1[name], value, rtol=0, atol=1e-6)
    # the same weights and data with train.seed=1's draws: not seed 0's loss (the data order is data.seed's)
    assert loss_init0_draws1 != loss0
    assert loss_init1_draws1 == loss1 and all(torch.equal(init1_draws1[n], seed1[n]) for n in seed1)
    with pytest.raises(ConfigError, match="train.init_seed must be >= 0"):
        load_config(TrainConfig, "tiny", ["train.init_seed=-1"])


# ---------------------------------------------------------------------------------------------------------------
# Exact resume after a hard kill
# ---------------------------------------------------------------------------------------------------------------


def kill_and_resume(dataset, tmp_path, overrides, extra, kill_step: int, resumed_step: int,
                    checkpoints_left: list[int] | None = None):
    """Run A uninterrupted; run B SIGKILLed in the middle of ``kill_step`` (``checkpoints_left`` then complete, when
    given), then resumed (resume=auto) from checkpoint ``resumed_step`` to the end. Returns both output folders."""
    a_out, b_out = tmp_path / "a", tmp_path / "b"
    # A and B are independent single-threaded processes: run side by side on the two cores (the worker kills B at a
    # step, not at a time, so the overlap changes nothing they compute)
    started = start_two_at_a_time({
        "a": partial(run_worker, [sys.executable], [fit_scenario(a_out, overrides(dataset, a_out / "run", *extra))],
                     a_out),
        "b": partial(kill_then_resume, fit_scenario(b_out, overrides(dataset, b_out / "run", *extra)), kill_step),
    })
    proc = started["a"].result()
    assert proc.returncode == 0, output_of(proc)
    assert_killed_and_resumed(started["b"].result(), resumed_step, checkpoints_left)
    return a_out, b_out


@dataclasses.dataclass(frozen=True)
class KilledAndResumed:
    killed: subprocess.CompletedProcess  # the run SIGKILLed at its kill step
    checkpoints_after_kill: list[int]  # the complete checkpoints it left
    resumed: subprocess.CompletedProcess  # the same run started again (resume=auto), to the end


def kill_then_resume(scenario: dict[str, Any], kill_step: int) -> KilledAndResumed:
    """Run ``scenario`` in a process SIGKILLed in the middle of ``kill_step``, then again in a fresh process."""
    out = Path(scenario["out"])
    killed = run_worker([sys.executable], [{**scenario, "kill_at": [0, kill_step]}], out)
    left = complete_steps(out / "run")
    return KilledAndResumed(killed, left, run_worker([sys.executable], [scenario], out))


def assert_killed_and_resumed(run: KilledAndResumed, resumed_step: int, checkpoints_left: list[int] | None) -> None:
    assert run.killed.returncode == -signal.SIGKILL, output_of(run.killed)
    if checkpoints_left is not None:
        assert run.checkpoints_after_kill == checkpoints_left
    assert run.resumed.returncode == 0, output_of(run.resumed)
    assert "resumed from" in run.resumed.stderr and ckpt.step_dir_name(resumed_step) in run.resumed.stderr


LENGTH_AWARE_RUN = ("data.batching=length_aware", "data.window=196", "data.pad_multiple=16",
                    "data.sort_window_batches=4", "train.max_steps=6", "train.save_every=2", "train.keep_last=2")
FLAME_EMA_RUN = ("optim.ema_every=2", "optim.ema_start=4", "optim.ema_warmup=false", "optim.ema_decay=0.5",
                 "train.max_steps=8", "train.save_every=2", "train.keep_last=0")
# The kill-and-resume cases of this file: overrides, extra overrides, kill step, the checkpoint the resume starts
# from, the complete checkpoints the kill leaves (None: not checked).
KILL_RESUME_CASES = {
    "workers-0": (resume_overrides, ("data.num_workers=0",), KILL_STEP, 10, [5, 10]),
    "workers-2": (resume_overrides, ("data.num_workers=2",), KILL_STEP, 10, [5, 10]),
    "length-aware": (base_overrides, LENGTH_AWARE_RUN, 5, 4, None),
    "flame-ema": (base_overrides, FLAME_EMA_RUN, 3, 2, [2]),
    # flags read one step late, off the log steps too (log_every 4, saves every 5)
    "deferred": (resume_overrides, ("train.step_sync=deferred", "train.log_every=4"), KILL_STEP, 10, [5, 10]),
    # a critic beside the model (train.critic_weight), its update skipped on the device with the model's
    "critic-deferred": (resume_overrides, ("train.critic_weight=0.05", "train.step_sync=deferred", "train.log_every=4"),
                        KILL_STEP, 10, [5, 10]),
    # Muon on the blocks' matrices beside AdamW (optim.optimizer=muon): both states and the schedule's link to both
    "muon": (resume_overrides, ("optim.optimizer=muon",), KILL_STEP, 10, [5, 10]),
}
UNINTERRUPTED = "uninterrupted"  # killed_and_resumed's launch of every case's run A


@pytest.fixture(scope="module")
def killed_and_resumed(dataset, tmp_path_factory) -> Callable[[str], tuple[Path, Path]]:
    """kill_and_resume for every case of KILL_RESUME_CASES, launched together (start_two_at_a_time): the
    uninterrupted runs (A) one after the other in one process (each fit seeds itself afresh; starting torch is most
    of a run's cost), each killed run (B) and its resume in processes of their own. Returns a function that checks
    one case's launches (a failed case fails its own test) and returns its A and B output folders."""
    root = tmp_path_factory.mktemp("kill-resume")

    def scenario(name: str, run: str) -> dict[str, Any]:
        overrides, extra = KILL_RESUME_CASES[name][:2]
        return fit_scenario(root / name / run, overrides(dataset, root / name / run / "run", *extra))

    started = start_two_at_a_time({
        UNINTERRUPTED: partial(run_worker, [sys.executable], [scenario(name, "a") for name in KILL_RESUME_CASES],
                               root / "a"),
        **{name: partial(kill_then_resume, scenario(name, "b"), case[2]) for name, case in KILL_RESUME_CASES.items()},
    })
    concurrent.futures.wait(started.values())  # nothing runs beside the tests below (they patch the library)

    def outcome(name: str) -> tuple[Path, Path]:
        a_out, b_out = root / name / "a", root / name / "b"
        proc = started[UNINTERRUPTED].result()
        assert results(a_out, 1) == [{"exit_code": 0}], output_of(proc)
        *_, resumed_step, checkpoints_left = KILL_RESUME_CASES[name]
        assert_killed_and_resumed(started[name].result(), resumed_step, checkpoints_left)
        return a_out, b_out

    return outcome


@pytest.mark.slow
@pytest.mark.parametrize("num_workers", [0, 2])
def test_resume_after_sigkill_is_bit_exact(killed_and_resumed, num_workers):
    """Run A: 16 steps. Run B: SIGKILLed in the middle of step 12, resume=auto from checkpoint 10, on to 16.
    Dropout is on, so equal weights also prove the global RNG was restored."""
    a_out, b_out = killed_and_resumed(f"workers-{num_workers}")

    assert_runs_identical(a_out / "run", b_out / "run", MAX_STEPS)
    ids_a, ids_b = ids_by_step(a_out, 0), ids_by_step(b_out, 0)
    assert sorted(ids_a) == list(range(1, MAX_STEPS + 1)) and ids_a == ids_b


@pytest.mark.slow
def test_deferred_step_sync_resumes_bit_exactly(killed_and_resumed):
    """train.step_sync=deferred, whose scheduler step and EMA count follow one step behind the update: a run
    SIGKILLed in the middle of step 12 and resumed from checkpoint 10 ends as the uninterrupted run does."""
    a_out, b_out = killed_and_resumed("deferred")
    assert_runs_identical(a_out / "run", b_out / "run", MAX_STEPS, log_every=4, resumed_from=10)


@pytest.mark.slow
def test_a_critic_beside_the_model_resumes_bit_exactly(killed_and_resumed):
    """train.critic_weight > 0 with train.step_sync=deferred: the critic's weights, spectral-norm vectors and Adam
    state are part of the checkpoint (state.pt's "auxiliary"), so a run SIGKILLed in the middle of step 12 and
    resumed from checkpoint 10 ends as the uninterrupted run does, critic included; the critic took every update."""
    a_out, b_out = killed_and_resumed("critic-deferred")
    assert_runs_identical(a_out / "run", b_out / "run", MAX_STEPS, log_every=4, resumed_from=10)
    _, _, state = ckpt.load_checkpoint(ckpt.checkpoints_dir(a_out / "run") / ckpt.step_dir_name(MAX_STEPS))
    critic = state["auxiliary"]["critic"]
    assert {int(s["step"]) for s in critic["optimizer"]["state"].values()} == {MAX_STEPS}
    assert any(k.endswith("_u") for k in critic["critic"]), "the spectral norms' power-iteration vectors are kept"
    metrics = metrics_by_step(a_out / "run")
    assert all(m["critic_loss"] is not None and m["adversarial_loss"] is not None for m in metrics.values())


@pytest.mark.slow
def test_muon_with_adamw_resumes_bit_exactly(killed_and_resumed):
    """optim.optimizer=muon: Muon's momentum, AdamW's moments and both optimizers' scheduled learning rates come
    back from the checkpoint, so a run SIGKILLed in the middle of step 12 and resumed from checkpoint 10 ends as
    the uninterrupted run does."""
    a_out, b_out = killed_and_resumed("muon")
    assert_runs_identical(a_out / "run", b_out / "run", MAX_STEPS)
    _, _, state = ckpt.load_checkpoint(ckpt.checkpoints_dir(b_out / "run") / ckpt.step_dir_name(MAX_STEPS))
    assert state["optimizer"]["muon"]["state"] and state["optimizer"]["adamw"]["state"]
    assert all("momentum_buffer" in s for s in state["optimizer"]["muon"]["state"].values())


@pytest.mark.slow
def test_length_aware_batches_of_varying_width_train_and_resume_bit_exactly(killed_and_resumed):
    """data.batching=length_aware: the trainer steps through batches whose width changes from step to step (each
    the longest clip rounded up to 16, below the 196-frame window), and a run SIGKILLed in the middle of step 5 and
    resumed from checkpoint 4 ends bit-identical to an uninterrupted one, with the same samples and widths per step."""
    a_out, b_out = killed_and_resumed("length-aware")

    assert_runs_identical(a_out / "run", b_out / "run", 6)
    assert ids_by_step(a_out, 0) == ids_by_step(b_out, 0)
    widths = {}
    for out in (a_out, b_out):
        for line in (out / "ids-rank0.jsonl").read_text().splitlines():
            record = json.loads(line)
            assert widths.setdefault(record["step"], record["widths"]) == record["widths"], record["step"]
    assert sorted(widths) == list(range(1, 7))
    assert all(w % 16 == 0 or w == 196 for step in widths.values() for w in step)
    assert len({w for step in widths.values() for w in step}) > 1 and min(min(step) for step in widths.values()) < 196


# ---------------------------------------------------------------------------------------------------------------
# Signals
# ---------------------------------------------------------------------------------------------------------------


class SignalAtStep:
    """A loss that sends ``signum`` to this process during the ``step``-th call (the middle of that step)."""

    def __init__(self, step: int, signum: int, times: int = 1) -> None:
        self.step, self.signum, self.times, self.calls = step, signum, times, 0

    def __call__(self, *args, **kwargs):
        self.calls += 1
        if self.calls == self.step:
            for _ in range(self.times):
                # raise_signal, not os.kill: the process-directed kill may land on a torch worker thread and two
                # of them can then coalesce into one Python handler call; raise_signal delivers to this thread
                # and runs the handler before it returns, once per signal.
                signal.raise_signal(self.signum)
        return self.__wrapped__(*args, **kwargs)


class HookedObjective:
    """The config's objective with its ``loss`` replaced by a test hook (the hook calls the real one through
    its ``__wrapped__``)."""

    def __init__(self, loss) -> None:
        self.loss = loss


def patch_loss(monkeypatch, loss) -> None:
    real_build = trainer_module.build_objective

    def build(cfg, manifest):
        loss.__wrapped__ = real_build(cfg, manifest).loss
        return HookedObjective(loss)

    monkeypatch.setattr(trainer_module, "build_objective", build)


def test_sigint_finishes_the_step_saves_and_exits_130(dataset, tmp_path, monkeypatch):
    run = tmp_path / "run"
    patch_loss(monkeypatch, SignalAtStep(3, signal.SIGINT))
    previous = signal.getsignal(signal.SIGINT)
    code = train_entry.main(["--config", "tiny", *base_overrides(dataset, run, "train.max_steps=50",
                                                                   "train.save_every=20")])
    assert code == 128 + signal.SIGINT == 130
    assert complete_steps(run) == [3]  # stopped after the step in progress, with one checkpoint of it
    assert sorted(metrics_by_step(run)) == [1, 2, 3]
    assert signal.getsignal(signal.SIGINT) is previous  # the handler is uninstalled again


@pytest.mark.parametrize("sigint_before", ["python_default", "ignored"])
def test_a_second_signal_aborts_at_once(dataset, tmp_path, monkeypatch, sigint_before):
    """Ctrl-C twice: the user does not want to wait for the step to end (e.g. a hung data read). Also when the
    process started with SIGINT ignored, as a job a non-interactive shell puts in the background does."""
    run = tmp_path / "run"
    before = signal.SIG_IGN if sigint_before == "ignored" else signal.default_int_handler
    original = signal.signal(signal.SIGINT, before)  # set both ways: a background job starts with SIG_IGN
    try:
        patch_loss(monkeypatch, SignalAtStep(2, signal.SIGINT, times=2))
        with pytest.raises(KeyboardInterrupt):
            train_entry.main(["--config", "tiny", *base_overrides(dataset, run, "train.max_steps=50")])
        assert complete_steps(run) == []
        assert signal.getsignal(signal.SIGINT) == before  # the trainer put back what it found
    finally:
        signal.signal(signal.SIGINT, original)


# ---------------------------------------------------------------------------------------------------------------
# Non-finite losses
# ---------------------------------------------------------------------------------------------------------------


class NaNAtSteps:
    def __init__(self, steps: set[int]) -> None:
        self.steps, self.calls = steps, 0

    def __call__(self, *args, **kwargs):
        self.calls += 1
        loss, stats = self.__wrapped__(*args, **kwargs)
        if self.calls in self.steps:
            loss = loss * float("nan")
        return loss, stats


def test_nonfinite_budget_exceeded_raises(dataset, tmp_path, monkeypatch):
    run = tmp_path / "run"
    patch_loss(monkeypatch, NaNAtSteps({2, 5, 6, 7}))
    with pytest.raises(NonFiniteLossError, match="3 consecutive skipped steps exceed train.nonfinite_budget=2"):
        train_entry.main(["--config", "tiny", *base_overrides(dataset, run, "train.max_steps=20",
                                                                "train.nonfinite_budget=2")])
    metrics = metrics_by_step(run)
    assert sorted(metrics) == [1, 2, 3, 4, 5, 6]  # step 7 raised before it was logged
    assert [metrics[s]["skipped_steps"] for s in range(1, 7)] == [0, 1, 1, 1, 2, 3]
    assert metrics[2]["loss"] is None and metrics[3]["loss"] > 0  # a skipped step has no loss to average


@pytest.mark.parametrize("step_sync", ["every_step", "deferred"])
def test_skipped_step_leaves_weights_and_optimizer_untouched(dataset, tmp_path, monkeypatch, step_sync):
    """Also when the skip is decided on the device (deferred: fused AdamW's found_inf, the EMA's weight 0)."""
    patch_loss(monkeypatch, NaNAtSteps({2}))
    cfg = load_config(TrainConfig, "tiny", base_overrides(dataset, tmp_path / "run", f"train.step_sync={step_sync}"))
    with Dist(mixed_precision="no") as dist:
        trainer = Trainer(cfg, dist)
        batches = trainer.loader.iter_batches()
        trainer.train_step([next(batches)])
        trainer.step += 1
        trainer.settle()
        before = {k: v.clone() for k, v in trainer.model.state_dict().items()}
        optimizer_before = trainer.optimizer.state_dict()
        ema_before, ema_updates, lr = trainer.ema.state_dict(), trainer.ema.num_updates, trainer.scheduler.get_last_lr()
        [result] = trainer.train_step([next(batches)]) + trainer.settle()
        assert result.skipped and result.step == 2
        assert (trainer.ema.num_updates, trainer.scheduler.get_last_lr()) == (ema_updates, lr)
        assert_identical(before, dict(trainer.model.state_dict()), "model")
        assert_identical(optimizer_before, trainer.optimizer.state_dict(), "optimizer")
        assert_identical(ema_before, trainer.ema.state_dict(), "ema")
        assert all(p.grad is None for p in trainer.model.parameters())


# ---------------------------------------------------------------------------------------------------------------
# train.step_sync=deferred: the update decided on the device, the flags read one step later
# ---------------------------------------------------------------------------------------------------------------


def test_deferred_flags_are_read_during_the_next_step_and_at_log_and_save_steps(dataset, tmp_path, monkeypatch):
    """Each step's flags are read once: during the next step, after its forward pass (so on a GPU the host queues
    that step before it waits), or at once at a log or save step. The decisions are every_step's: the NaN step is
    skipped and counted, the other steps train to the same weights, bit for bit (every_step given fused AdamW here
    too, as on a GPU), and the same EMA within rounding (a multiply-add for the device-weighted update)."""
    real_adamw = torch.optim.AdamW
    monkeypatch.setattr(torch.optim, "AdamW", lambda *args, **kwargs: real_adamw(*args, **{**kwargs, "fused": True}))
    loss = NaNAtSteps({3})  # its calls count the forward passes made so far (one micro-batch per step)
    patch_loss(monkeypatch, loss)
    reads: list[tuple[int, int]] = []
    real_read = trainer_module.PendingStep.read

    def read(self):
        reads.append((self.step, loss.calls))
        return real_read(self)

    monkeypatch.setattr(trainer_module.PendingStep, "read", read)
    steps = ("train.max_steps=8", "train.log_every=4", "train.save_every=6", "train.keep_last=0")
    runs = {mode: tmp_path / mode for mode in ("deferred", "every_step")}
    for mode, run in runs.items():
        loss.calls = 0
        assert train_entry.main(["--config", "tiny", *base_overrides(dataset, run, *steps),
                                 "train.log_every=4", f"train.step_sync={mode}"]) == 0
        if mode == "deferred":
            assert reads == [(k, k if k in (4, 6, 8) else k + 1) for k in range(1, 9)]
    assert len(reads) == 8  # every_step reads no pending step
    deferred, every_step = metrics_by_step(runs["deferred"]), metrics_by_step(runs["every_step"])
    assert sorted(deferred) == sorted(every_step) == [4, 8]
    for step in (4, 8):
        assert deferred[step]["skipped_steps"] == every_step[step]["skipped_steps"] == 1
        assert deferred[step]["lr"] == every_step[step]["lr"]
        assert deferred[step]["loss"] == every_step[step]["loss"]
    for step in (6, 8):
        model_d, ema_d, state_d = ckpt.load_checkpoint(ckpt.checkpoints_dir(runs["deferred"]) / ckpt.step_dir_name(step))
        model_e, ema_e, state_e = ckpt.load_checkpoint(ckpt.checkpoints_dir(runs["every_step"])
                                                       / ckpt.step_dir_name(step))
        assert state_d["extra"]["ema_updates"] == state_e["extra"]["ema_updates"] == step - 1
        assert state_d["scheduler"] == state_e["scheduler"]
        assert_identical(model_d, model_e, f"model at step {step}")
        for name in model_e:
            torch.testing.assert_close(ema_d[name], ema_e[name], rtol=1e-5, atol=1e-7, msg=name)


def test_a_deferred_step_reads_no_tensor_on_the_host(dataset, tmp_path):
    """Between its flag reads a deferred step asks the host for no tensor value (no ``.item()``, ``float()``,
    ``bool()`` of a tensor, nor the optimizer's step count, which fused AdamW keeps on the device): each would make
    the host wait for the GPU."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class ScalarReads(TorchDispatchMode):
        def __init__(self) -> None:
            super().__init__()
            self.count = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            self.count += func is torch.ops.aten._local_scalar_dense.default
            return func(*args, **(kwargs or {}))

    cfg = load_config(TrainConfig, "tiny", base_overrides(dataset, tmp_path / "run", "train.step_sync=deferred"))
    with Dist(mixed_precision="no") as dist:
        trainer = Trainer(cfg, dist)
        batches = trainer.loader.iter_batches()
        for _ in range(2):  # the first steps create AdamW's state
            trainer.train_step([next(batches)])
            trainer.step += 1
        with ScalarReads() as reads:
            for _ in range(2):
                outcomes = trainer.train_step([next(batches)])
                trainer.step += 1
        assert reads.count == 0
        assert [outcome.step for outcome in outcomes] == [3]


def test_deferred_sigint_stops_after_the_next_step_with_its_checkpoint(dataset, tmp_path, monkeypatch):
    run = tmp_path / "run"
    patch_loss(monkeypatch, SignalAtStep(3, signal.SIGINT))
    code = train_entry.main(["--config", "tiny", *base_overrides(dataset, run, "train.max_steps=50",
                                                                   "train.save_every=20", "train.log_every=2",
                                                                   "train.step_sync=deferred")])
    assert code == 130
    assert complete_steps(run) == [4]  # step 3's flags were read during step 4, which ends and is saved
    assert sorted(metrics_by_step(run)) == [2, 4]


def test_deferred_step_sync_is_refused_with_fp16():
    with pytest.raises(ValueError, match="train.step_sync=deferred does not go with train.mixed_precision=fp16"):
        from_dict(TrainConfig, {"train": {"step_sync": "deferred", "mixed_precision": "fp16"}})
    assert trainer_module.resolve_step_sync("auto", torch.device("cuda"), "bf16")
    assert not trainer_module.resolve_step_sync("auto", torch.device("cuda"), "fp16")
    assert not trainer_module.resolve_step_sync("auto", torch.device("cpu"), "no")
    with pytest.raises(ValueError, match="here from the launcher"):
        trainer_module.resolve_step_sync("deferred", torch.device("cpu"), "fp16")


# ---------------------------------------------------------------------------------------------------------------
# The EMA of the weights: our warm-up by default, FLAME's copy-until-step-N schedule as options
# ---------------------------------------------------------------------------------------------------------------


def ema_run(steps: int, decay: float, **schedule: Any) -> tuple[EMA, dict[str, torch.Tensor],
                                                               dict[int, dict[str, torch.Tensor]]]:
    """An EMA(decay, **schedule) of a model whose weights become new random values at every step 1..``steps``,
    updated after each as the trainer does: the EMA, the initial weights and the weights after every step."""
    torch.manual_seed(0)
    model = torch.nn.Linear(3, 2)
    initial = {k: v.clone() for k, v in model.state_dict().items()}
    ema = EMA(model, decay, **schedule)
    weights = {}
    for step in range(1, steps + 1):
        with torch.no_grad():
            for p in model.parameters():
                p.copy_(torch.randn_like(p))
        weights[step] = {k: v.clone() for k, v in model.state_dict().items()}
        ema.after_step(model, step)
    return ema, initial, weights


def test_ema_default_is_every_step_with_the_warmup_as_before():
    ema, initial, weights = ema_run(30, 0.9)  # optim.ema_every=1 ema_start=0 ema_warmup=true: the defaults
    expected = {k: v.clone().float() for k, v in initial.items()}
    for n in range(1, 31):  # the formula the trainer always had: every step, min(decay, (1 + n)/(10 + n))
        decay = min(0.9, (1 + n) / (10 + n))
        expected = {k: v.lerp(weights[n][k], 1.0 - decay) for k, v in expected.items()}
    assert_identical(expected, ema.shadow, "ema")
    assert ema.num_updates == 30


@pytest.mark.parametrize("copy", [False, True])
def test_an_ema_update_weighted_on_the_device_is_the_update_or_none(copy):
    """train.step_sync=deferred's EMA update (``applied``: a device bool): True gives the host-decided update (the
    copy exactly; the average within rounding, a multiply-add instead of lerp), False leaves the average as it was."""
    torch.manual_seed(0)
    model = torch.nn.Linear(3, 2)
    decided, gated = EMA(model, 0.9), EMA(model, 0.9)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(torch.randn_like(p))
    before = {k: v.clone() for k, v in gated.shadow.items()}
    gated.update(model, copy=copy, applied=torch.tensor(False))
    assert_identical(before, gated.shadow, "ema after a skipped update")
    gated.num_updates = 0  # the trainer takes the count back after a skip
    decided.update(model, copy=copy)
    gated.update(model, copy=copy, applied=torch.tensor(True))
    for name, value in decided.shadow.items():
        torch.testing.assert_close(gated.shadow[name], value, rtol=0 if copy else 1e-6, atol=0 if copy else 1e-7)


def test_ema_reproduces_flames_schedule_copy_until_ema_start_then_average_every_ema_every_steps():
    """FLAME's diffusion_module.py: on_train_batch_end calls step_ema when global_step % ema_update == 0 (global_step:
    optimizer steps done); step_ema copies the weights while global_step <= ema_start, else ema = decay * ema +
    (1 - decay) * weights (src/models/ema.py), with diffusion_hml3d.yaml's ema_start 100, ema_update 10, decay 0.99."""
    flame_schedule = {"every": 10, "start": 100, "warmup": False}
    ema, initial, weights = ema_run(135, 0.99, **flame_schedule)
    flame = dict(initial)
    for step in range(1, 136):
        if step % 10 == 0:
            flame = dict(weights[step]) if step <= 100 else {k: 0.99 * v + 0.01 * weights[step][k]
                                                             for k, v in flame.items()}
        if step in (9, 10, 100, 109):  # the initial weights before step 10, then a copy of them until step 100
            replay, _, _ = ema_run(step, 0.99, **flame_schedule)
            assert_identical(flame, replay.shadow, f"ema after step {step}")
    for k in flame:  # then FLAME's average, which differs from ours by float rounding only (lerp vs a·x + b·y)
        torch.testing.assert_close(ema.shadow[k], flame[k], rtol=1e-6, atol=1e-7)
    assert ema.num_updates == 13
    # our warm-up would have averaged with min(0.99, (1 + n)/(10 + n)) = 0.57 at the first average: far from FLAME
    warm, _, _ = ema_run(135, 0.99, every=10, start=100)
    assert max((warm.shadow[k] - flame[k]).abs().max().item() for k in flame) > 1e-2


@pytest.mark.slow
def test_flame_ema_schedule_in_training_and_exact_resume_across_ema_start(killed_and_resumed):
    """optim.ema_every=2 ema_start=4 ema_warmup=false: checkpoints 2 and 4 hold EMA = the weights, 6 the average of
    4's and 6's (decay 0.5); a run SIGKILLed in step 3 and resumed from checkpoint 2 crosses ema_start and ends bit
    for bit as the uninterrupted one."""
    a_out, b_out = killed_and_resumed("flame-ema")
    saved = {step: ckpt.load_checkpoint(ckpt.checkpoints_dir(a_out / "run") / ckpt.step_dir_name(step))
             for step in (2, 4, 6, 8)}
    for step in (2, 4):
        model, ema, _ = saved[step]
        assert_identical({k: v.float() for k, v in model.items()}, ema, f"ema at step {step}")
    (model4, _, _), (model6, ema6, state6) = saved[4], saved[6]
    for k in ema6:
        torch.testing.assert_close(ema6[k], 0.5 * model4[k].float() + 0.5 * model6[k].float(), rtol=1e-6, atol=1e-7)
    assert any(not torch.equal(ema6[k], model6[k].float()) for k in ema6)  # an average now, no longer a copy
    assert state6["extra"]["ema_updates"] == 3 and saved[8][2]["extra"]["ema_updates"] == 4
    assert_runs_identical(a_out / "run", b_out / "run", 8)


# ---------------------------------------------------------------------------------------------------------------
# Gradient accumulation
# ---------------------------------------------------------------------------------------------------------------


def test_grad_accumulation_matches_one_big_batch(dataset, tmp_path):
    import trainer_worker

    cfg = load_config(TrainConfig, "tiny", base_overrides(dataset, tmp_path / "run", "model.dropout=0.0"))
    batches = trainer_worker.global_batches(cfg, steps=3, global_batch=8)
    outcomes = []
    for micro_batches in (1, 2):
        with Dist(mixed_precision="no") as dist:
            outcomes.append(trainer_worker.run_equivalence(Trainer(cfg, dist), batches, micro_batches))
    whole, accumulated = outcomes
    assert_equivalent(accumulated, whole)


def assert_equivalent(result: dict[str, Any], reference: dict[str, Any]) -> None:
    """Two ways of computing the same optimizer steps agree to float rounding (see run_equivalence)."""
    torch.testing.assert_close(result["losses"], reference["losses"], rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(result["grad_norms"], reference["grad_norms"], rtol=1e-5, atol=1e-7)
    for key in ("model", "ema"):
        torch.testing.assert_close(result[key], reference[key], rtol=1e-5, atol=1e-6)
    moved = max((reference["model"][k] - reference["initial"][k]).abs().max().item() for k in reference["model"])
    assert moved > 1e-3, "the weights hardly moved: the comparison above would prove nothing"


# ---------------------------------------------------------------------------------------------------------------
# Bad shards, through the real entry point
# ---------------------------------------------------------------------------------------------------------------


@pytest.fixture
def corrupted_dataset(dataset, tmp_path) -> tuple[Path, str, set[str]]:
    """A copy of the dataset with one byte of one train tar flipped; returns (manifest, shard path, its ids)."""
    copy = tmp_path / "corrupt"
    shutil.copytree(dataset.parent, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    shards = manifest["splits"]["train"]["shards"]
    assert len(shards) >= 2
    bad = shards[1]["path"]
    with tarfile.open(copy / bad) as tar:
        ids = {name.split(".", 1)[0] for name in tar.getnames()}
    flip_byte(copy / bad, (copy / bad).stat().st_size // 2)
    return copy / "manifest.json", bad, ids


def test_strict_verification_fails_before_training_naming_the_shard(corrupted_dataset, tmp_path, capsys):
    manifest, bad, _ = corrupted_dataset
    run = tmp_path / "run"
    assert train_entry.main(["--config", "tiny", *base_overrides(manifest, run, "data.verify=strict")]) == 2
    error = one_error_line(capsys)  # one line and exit 2, not a traceback (issue 24, item 9)
    assert bad in error and "corrupted" in error
    cfg = load_config(TrainConfig, "tiny", base_overrides(manifest, run, "data.verify=strict"))
    with Dist(mixed_precision="no", cpu=True) as dist, pytest.raises(ShardVerificationError, match=re.escape(bad)):
        Trainer(cfg, dist)  # the trainer's own exception, which launch/train.py turns into that line
    assert not (run / "metrics.jsonl").exists() and complete_steps(run) == []


def test_tolerant_verification_skips_the_shard_and_reports_it(corrupted_dataset, tmp_path, monkeypatch, caplog):
    manifest, bad, bad_ids = corrupted_dataset
    run = tmp_path / "run"
    seen: set[str] = set()
    real_step = Trainer.train_step

    def recording_step(self, micro_batches, draws=None):
        seen.update(i for b in micro_batches for i in b["ids"])
        return real_step(self, micro_batches, draws)

    monkeypatch.setattr(Trainer, "train_step", recording_step)
    caplog.set_level("WARNING")
    code = train_entry.main(["--config", "tiny", *base_overrides(manifest, run, "data.verify=tolerant",
                                                                   "train.max_steps=12")])
    assert code == 0 and complete_steps(run)[-1] == 12
    report = json.loads((run / "shard_report.json").read_text())
    assert report["mode"] == "tolerant" and report["samples_lost"] == 10
    assert [b["path"] for b in report["bad"]] == [bad] and "corrupted" in report["bad"][0]["reason"]
    assert bad in caplog.text and "skipping 1 bad shard" in caplog.text
    assert len(seen) > 30 and not seen & bad_ids  # 12 steps x 4 samples read, none from the bad shard


def test_learning_rate_schedules():
    """Warm-up is linear to 1; 'constant' stays there (MFM), 'cosine' falls to min_ratio exactly at total_steps, 'wsd'
    holds 1 and then falls in a straight line over its decay_fraction."""
    from pipeline.training.trainer import lr_lambda

    constant = lr_lambda(4, "constant", total_steps=100)
    assert [constant(s) for s in range(5)] == [0.25, 0.5, 0.75, 1.0, 1.0] and constant(10_000) == 1.0
    cosine = lr_lambda(4, "cosine", total_steps=104, min_ratio=0.1)
    assert [cosine(s) for s in range(4)] == [0.25, 0.5, 0.75, 1.0]
    assert cosine(54) == pytest.approx(0.55)  # half way: the middle of [0.1, 1]
    assert cosine(104) == pytest.approx(0.1) and cosine(500) == pytest.approx(0.1)
    values = [cosine(s) for s in range(4, 105)]
    assert all(a >= b for a, b in zip(values, values[1:]))
    # wsd: the peak until the last quarter (25) of the 100 steps after warm-up, from step 79 a straight line to 0.1
    wsd = lr_lambda(4, "wsd", total_steps=104, min_ratio=0.1, decay_fraction=0.25)
    assert [wsd(s) for s in range(4)] == [0.25, 0.5, 0.75, 1.0]
    assert all(wsd(s) == 1.0 for s in range(4, 80))
    assert wsd(90) == pytest.approx(1.0 - 0.9 * 11 / 25) and wsd(104) == pytest.approx(0.1)
    assert wsd(500) == pytest.approx(0.1)
    decay = [wsd(s) for s in range(79, 105)]
    assert all(a > b for a, b in zip(decay, decay[1:]))
    assert len({round(a - b, 12) for a, b in zip(decay, decay[1:])}) == 1  # linear
    # the wsd knob leaves cosine as it was
    assert [lr_lambda(4, "cosine", 104, 0.1, decay_fraction=0.25)(s) for s in range(110)] == [
        cosine(s) for s in range(110)]
    with pytest.raises(Exception, match="decay_fraction"):
        load_config(TrainConfig, "tiny", ["optim.schedule=wsd", "optim.decay_fraction=0"])
    with pytest.raises(Exception, match="min_lr_ratio"):
        load_config(TrainConfig, "tiny", ["optim.min_lr_ratio=1.5"])
    with pytest.raises(Exception, match="schedule"):
        load_config(TrainConfig, "tiny", ["optim.schedule=linear"])
    with pytest.raises(Exception, match="prediction"):
        load_config(TrainConfig, "tiny", ["train.objective=diffusion", "model.prediction=data"])


# ---------------------------------------------------------------------------------------------------------------
# Nothing lost, nothing stuck: a full disk, corrupt or newer checkpoints, the run folder (issue 12, items 4, 5, 8)
# ---------------------------------------------------------------------------------------------------------------


def continue_overrides(manifest: Path, run: Path, *extra: str) -> list[str]:
    """Train to step 6 with a checkpoint every 2 steps, all kept (the four-step run below continued)."""
    return base_overrides(manifest, run, "train.max_steps=6", "train.save_every=2", "train.keep_last=0", *extra)


@pytest.fixture(scope="module")
def four_step_run(dataset, tmp_path_factory) -> Path:
    """A tiny run stopped at step 4 with checkpoints 2 and 4 (trained once; tests work on copies)."""
    run = tmp_path_factory.mktemp("four-step") / "run"
    assert train_entry.main(["--config", "tiny", *continue_overrides(dataset, run, "train.max_steps=4")]) == 0
    assert complete_steps(run) == [2, 4]
    return run


def test_the_trajectory_term_from_a_start_step_leaves_the_run_before_it_unchanged(four_step_run, dataset, tmp_path):
    """train.flow_trajectory_start_step=2: steps 1-2 are the run without the term, bit for bit (the term draws
    nothing); from step 3 the loss is the one with it."""
    run = tmp_path / "late"
    assert train_entry.main(["--config", "tiny", *continue_overrides(
        dataset, run, "train.max_steps=4", "train.flow_trajectory_weight=0.5",
        "train.flow_trajectory_start_step=2")]) == 0
    step_2 = ckpt.step_dir_name(2)
    plain_model, plain_ema, _ = ckpt.load_checkpoint(ckpt.checkpoints_dir(four_step_run) / step_2)
    late_model, late_ema, _ = ckpt.load_checkpoint(ckpt.checkpoints_dir(run) / step_2)
    assert_identical(plain_model, late_model, "model")
    assert_identical(plain_ema, late_ema, "ema")
    plain, late = metrics_by_step(four_step_run), metrics_by_step(run)
    assert [late[s]["loss"] for s in (1, 2)] == [plain[s]["loss"] for s in (1, 2)]
    # From step 3 the term adds a positive amount (a loss of the same draws, larger by about 0.5 x the term).
    assert late[3]["loss"] > plain[3]["loss"] + 1e-4, (late[3]["loss"], plain[3]["loss"])


def copy_of(run: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    return copy


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file below ``folder`` with its bytes: a start that was refused must leave all of them as they were."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def one_error_line(capsys: pytest.CaptureFixture[str]) -> str:
    """The launcher's message: exactly one ``error:`` line on stderr and no traceback."""
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("error: ")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def forbid_training(monkeypatch) -> None:
    def trained(self, micro_batches, draws=None):
        raise AssertionError("a training step ran although the start should have been refused")

    monkeypatch.setattr(Trainer, "train_step", trained)


def test_full_disk_at_a_save_stops_the_run_cleanly_and_a_restart_continues(dataset, tmp_path, monkeypatch, capsys,
                                                                           caplog):
    """Item 4: ENOSPC while writing checkpoint 4. The save removes its partial folder, logs one line with the space
    needed and free, the run stops (exit 1, one line naming the checkpoint to resume from); the same command run
    again once there is space resumes from checkpoint 2 and finishes."""
    run = tmp_path / "run"
    real_write = ckpt._write_file

    def full_disk(path: Path, payload: bytes):
        if path.parent.name.startswith("step-00000004."):
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real_write(path, payload)

    monkeypatch.setattr(ckpt, "_write_file", full_disk)
    caplog.set_level("INFO")
    assert train_entry.main(["--config", "tiny", *continue_overrides(dataset, run)]) == 1
    error = one_error_line(capsys)
    assert "the run stopped at step 4" in error and "No space left on device" in error
    assert re.search(r"it needs [\d.]+ MB, [\d.]+ MB free on ", error) and "continues from step-00000002" in error
    assert sorted(p.name for p in ckpt.checkpoints_dir(run).iterdir()) == ["saved.jsonl", "step-00000002"]  # nothing partial
    assert [c.step for c in ckpt.read_saved(ckpt.checkpoints_dir(run))] == [2]  # the failed save is not listed
    save_errors = [r for r in caplog.records if r.name == "pipeline.checkpoint" and r.levelname == "ERROR"]
    assert len(save_errors) == 1 and "MB free" in save_errors[0].getMessage()

    monkeypatch.setattr(ckpt, "_write_file", real_write)  # space freed
    caplog.clear()
    assert train_entry.main(["--config", "tiny", *continue_overrides(dataset, run)]) == 0
    assert "step-00000002 at step 2" in caplog.text
    assert complete_steps(run) == [2, 4, 6]
    assert sorted(metrics_by_step(run)) == list(range(1, 7))
    assert [c.step for c in ckpt.read_saved(ckpt.checkpoints_dir(run))] == [2, 4, 6]


def test_every_completed_save_is_listed_in_saved_jsonl_and_pruning_keeps_the_lines(four_step_run, dataset, tmp_path,
                                                                                    monkeypatch):
    """Training appends one line per completed save to checkpoints/saved.jsonl (step, name, id, time), once the
    COMPLETE marker is written and the folder is in place; train.keep_last prunes folders, never lines. It is how
    the evaluator learns of a checkpoint saved and pruned while no evaluator job ran."""
    run = copy_of(four_step_run, tmp_path)
    root = ckpt.checkpoints_dir(run)
    real_record = ckpt.record_saved
    listed_when_complete = []

    def record_saved(ckpt_root, folder):
        listed_when_complete.append(Path(folder).name.startswith("step-") and ckpt.is_complete(folder))
        real_record(ckpt_root, folder)

    monkeypatch.setattr(ckpt, "record_saved", record_saved)
    overrides = continue_overrides(dataset, run, "train.max_steps=8", "train.keep_last=1")
    assert train_entry.main(["--config", "tiny", *overrides]) == 0
    assert complete_steps(run) == [8] and listed_when_complete == [True, True]
    saved = ckpt.read_saved(root)
    assert [(c.step, c.name) for c in saved] == [(2, "step-00000002"), (4, "step-00000004"), (6, "step-00000006"),
                                                 (8, "step-00000008")]
    assert saved[-1].checkpoint_id == ckpt.checkpoint_id(ckpt.read_marker(root / "step-00000008"))
    assert all(re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", c.time) for c in saved)


def test_unfinished_checkpoint_folders_of_dead_processes_are_removed_before_anything_is_written(
        four_step_run, dataset, tmp_path, monkeypatch):
    """Item 4: a save killed on a full disk left its folder; at start-up it is removed before the run writes
    (otherwise that write is the one that fails), whichever step it was for."""
    run = copy_of(four_step_run, tmp_path)
    host = re.sub(r"[^A-Za-z0-9.]", "_", socket.gethostname())
    stale = [ckpt.checkpoints_dir(run) / f"step-00000008.tmp-{dead_pid()}",  # named before hosts were recorded
             ckpt.checkpoints_dir(run) / f"step-00000005.tmp-{host}-{dead_pid()}"]
    for folder in stale:
        folder.mkdir()
        (folder / ckpt.MODEL_FILE).write_bytes(bytes(4096))
    real_write_run_files = Trainer._write_run_files

    def write_run_files(self) -> None:
        assert not any(folder.exists() for folder in stale), "the run wrote its files before removing the folders"
        real_write_run_files(self)

    monkeypatch.setattr(Trainer, "_write_run_files", write_run_files)
    assert train_entry.main(["--config", "tiny", *continue_overrides(dataset, run)]) == 0
    assert not any(folder.exists() for folder in stale) and complete_steps(run) == [2, 4, 6]


def test_auto_resume_moves_a_corrupt_newest_checkpoint_aside_and_falls_back(four_step_run, dataset, tmp_path,
                                                                             caplog):
    """Item 5: one flipped byte (same size) in the newest model.safetensors. resume=auto resumes from the
    checkpoint before it, keeps the corrupt one under another name, says so, and trains on to the end."""
    run = copy_of(four_step_run, tmp_path)
    model_file = ckpt.checkpoints_dir(run) / "step-00000004" / ckpt.MODEL_FILE
    flip_byte(model_file, model_file.stat().st_size - 8)
    corrupt = model_file.read_bytes()
    caplog.set_level("INFO")
    assert train_entry.main(["--config", "tiny", *continue_overrides(dataset, run)]) == 0
    aside = [p for p in ckpt.checkpoints_dir(run).iterdir() if p.name.startswith("step-00000004.corrupt-")]
    assert len(aside) == 1 and (aside[0] / ckpt.MODEL_FILE).read_bytes() == corrupt  # renamed, never deleted
    assert "step-00000004 is corrupt" in caplog.text and aside[0].name in caplog.text
    assert "step-00000002 at step 2" in caplog.text  # resumed from the one before
    assert complete_steps(run) == [2, 4, 6]
    assert sorted(metrics_by_step(run)) == list(range(1, 7))


def test_explicit_older_resume_is_refused_before_any_step_while_newer_checkpoints_exist(
        four_step_run, dataset, tmp_path, monkeypatch, capsys):
    """Item 5: resuming explicitly from checkpoint 2 while (a corrupt) checkpoint 4 exists used to train two steps
    and then die on checkpoint 4. Now it is refused before training with the command that continues; that command
    moves checkpoint 4 aside (renamed, kept) and trains to the end."""
    run = copy_of(four_step_run, tmp_path)
    model_file = ckpt.checkpoints_dir(run) / "step-00000004" / ckpt.MODEL_FILE
    flip_byte(model_file, model_file.stat().st_size - 8)
    older = ckpt.checkpoints_dir(run) / "step-00000002"
    before = snapshot(run)
    forbid_training(monkeypatch)
    argv = ["--config", "tiny", *continue_overrides(dataset, run, f"train.resume={older}")]
    assert train_entry.main(argv) == 2
    error = one_error_line(capsys)
    assert "step-00000004" in error and "train.resume=auto" in error
    assert error.endswith("python launch/train.py " + " ".join(argv) + " train.resume_discard_newer=true")
    assert snapshot(run) == before  # nothing written, nothing moved

    monkeypatch.undo()
    assert train_entry.main([*argv, "train.resume_discard_newer=true"]) == 0
    assert len([p for p in ckpt.checkpoints_dir(run).iterdir() if p.name.startswith("step-00000004.discarded-")]) == 1
    assert complete_steps(run) == [2, 4, 6]
    assert sorted(metrics_by_step(run)) == list(range(1, 7))


def test_a_refused_resume_leaves_the_run_folder_untouched(four_step_run, dataset, tmp_path, monkeypatch, capsys):
    """Item 8: a changed batch size cannot resume the data stream; the refusal used to come after config.yaml had
    been overwritten with the refused settings."""
    run = copy_of(four_step_run, tmp_path)
    before = snapshot(run)
    forbid_training(monkeypatch)
    assert train_entry.main(["--config", "tiny", *continue_overrides(dataset, run, "data.batch_size=2")]) == 2
    assert "data.batch_size" in one_error_line(capsys)
    assert snapshot(run) == before


def test_resuming_with_a_max_steps_below_the_checkpoints_step_is_refused_untouched(four_step_run, dataset, tmp_path,
                                                                                     monkeypatch, capsys):
    """Issue 24, item 9: train.max_steps=3 on a run at step 4 trained nothing, exited 0 and rewrote config.yaml
    with max_steps 3 (and wrote a new TensorBoard file and loss.png). Now it is refused, and every file of the run
    is as it was, none added."""
    run = copy_of(four_step_run, tmp_path)
    before = snapshot(run)
    forbid_training(monkeypatch)
    assert train_entry.main(["--config", "tiny", *continue_overrides(dataset, run, "train.max_steps=3")]) == 2
    error = one_error_line(capsys)
    assert "step-00000004" in error and "already at step 4 > train.max_steps=3" in error
    assert snapshot(run) == before


def test_a_resume_refused_for_a_changed_data_setting_is_one_line_through_the_script(four_step_run, dataset,
                                                                                     tmp_path):
    """Item 8: a data setting the saved data position depends on changed (data.batch_size 4 -> 2) between the
    checkpoint and the restart: one ``error:`` line naming the setting, both values and how to go on, exit 2, not a
    traceback, and the run folder as it was."""
    run = copy_of(four_step_run, tmp_path)
    before = snapshot(run)
    proc = subprocess.run([sys.executable, str(REPO_ROOT / "launch" / "train.py"), "--config", "tiny",
                           *continue_overrides(dataset, run, "data.batch_size=2")],
                          cwd=REPO_ROOT, env=clean_env(), capture_output=True, text=True, timeout=240, check=False)
    assert proc.returncode == 2, output_of(proc)
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1 and "Traceback" not in proc.stderr, output_of(proc)
    assert proc.stderr.rstrip("\n").endswith(errors[0])  # the last line, after the run's INFO log lines
    assert "step-00000004" in errors[0] and "data.batch_size was 4 in the checkpoint and is 2 now" in errors[0]
    assert "Resume with data.batch_size=4" in errors[0] and "another train.out_dir" in errors[0]
    assert snapshot(run) == before


# ---------------------------------------------------------------------------------------------------------------
# One trainer per run folder (issue 24, item 5)
# ---------------------------------------------------------------------------------------------------------------

# A stand-in for a trainer holding its run folder: it takes the lock as rank 0 does, says so, then dies at once
# without releasing it (kill -9) or stays alive holding it.
_HOLDING_TRAINER = """
import os, signal, sys, time
from pipeline.training.run_folder import RunFolderLock
RunFolderLock.acquire(sys.argv[1])
print("held", flush=True)
if sys.argv[2] == "die":
    os.kill(os.getpid(), signal.SIGKILL)
time.sleep(600)
"""


def holding_trainer(run: Path, then: str) -> subprocess.Popen:
    """A process holding ``run``'s lock; ``then`` is 'die' (returns once it is dead and reaped) or 'live'."""
    proc = subprocess.Popen([sys.executable, "-c", _HOLDING_TRAINER, str(run), then], cwd=REPO_ROOT,
                            env={**clean_env(), "PYTHONPATH": str(REPO_ROOT)}, stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    if then == "die":
        assert proc.wait(timeout=30) == -signal.SIGKILL
    return proc


def test_a_second_trainer_on_a_running_run_is_refused_and_the_run_loses_nothing(dataset, tmp_path, capsys):
    """Issue 24, item 5: two trainers on one run folder. The second resumed from the first's checkpoint and both
    wrote metrics.jsonl (60 of 150 steps were lost). Now run A (a real trainer, paused in the middle of step 8
    after checkpoints 3 and 6) holds the folder; a second start there is refused in one line naming A (pid, host,
    start time), exit 2, writing nothing; A then finishes with every step logged once and every checkpoint."""
    out, run = tmp_path / "a", tmp_path / "a" / "run"
    overrides = base_overrides(dataset, run, "train.max_steps=12", "train.save_every=3", "train.keep_last=0")
    out.mkdir()
    (out / "spec.json").write_text(json.dumps([{**fit_scenario(out, overrides), "pause_at": [0, 8]}]))
    first = subprocess.Popen([sys.executable, str(WORKER), str(out / "spec.json")], cwd=REPO_ROOT, env=clean_env(),
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 240
        while not (out / "paused-rank0").exists():
            assert first.poll() is None and time.monotonic() < deadline, output_of(first)
            time.sleep(0.1)
        assert complete_steps(run) == [3, 6] and (run / RUN_LOCK).is_file()
        before = snapshot(run)
        assert train_entry.main(["--config", "tiny", *overrides]) == 2
        error = one_error_line(capsys)
        assert f"in use by another training run: pid {first.pid} on {socket.gethostname()}, started 20" in error
        assert snapshot(run) == before  # the second start wrote nothing
    finally:
        (out / "go").write_text("")
        stdout, stderr = first.communicate(timeout=240)
    assert first.returncode == 0, f"{stdout[-3000:]}\n{stderr[-6000:]}"
    assert sorted(metrics_by_step(run)) == list(range(1, 13)) and complete_steps(run) == [3, 6, 9, 12]
    assert sorted(ids_by_step(out, 0)) == list(range(1, 13))
    assert not (run / RUN_LOCK).exists()  # released at the end


def test_a_killed_trainers_lock_is_taken_over_and_a_live_ones_refused(four_step_run, dataset, tmp_path, monkeypatch,
                                                                        capsys, caplog):
    """A live holder: refused before anything is written (also before the shards are verified), naming it. Once it
    is killed (its lock file stays behind, naming a dead pid) the same command takes the folder over, says so, and
    trains on; the lock file is gone at the end. A folder holding only a killed trainer's lock counts as empty."""
    run = copy_of(four_step_run, tmp_path)
    holder = holding_trainer(run, "live")
    try:
        before = snapshot(run)
        verified = []
        monkeypatch.setattr(trainer_module, "verify_shards", lambda *a, **k: verified.append(a))
        forbid_training(monkeypatch)
        with pytest.raises(RunFolderInUseError, match=rf"pid {holder.pid} on "):
            with Dist(cpu=True) as dist:
                Trainer(load_config(TrainConfig, "tiny", continue_overrides(dataset, run)), dist)
        assert verified == [] and snapshot(run) == before
        monkeypatch.undo()
    finally:
        holder.kill()
        holder.wait(timeout=30)
    assert json.loads((run / RUN_LOCK).read_text())["pid"] == holder.pid  # left behind by the killed holder
    caplog.set_level("WARNING")
    assert train_entry.main(["--config", "tiny", *continue_overrides(dataset, run)]) == 0
    assert f"taking over {RUN_LOCK} from pid {holder.pid} on {socket.gethostname()}, started 20" in caplog.text
    assert "no longer running" in caplog.text
    assert complete_steps(run) == [2, 4, 6] and sorted(metrics_by_step(run)) == list(range(1, 7))
    assert not (run / RUN_LOCK).exists()

    fresh = tmp_path / "fresh"
    holding_trainer(fresh, "die")
    assert [p.name for p in fresh.iterdir()] == [RUN_LOCK]
    check_run_folder(fresh)  # a new run killed before it wrote anything: its folder is still an empty one


def test_the_run_folder_lock_is_one_per_folder_and_released(tmp_path):
    lock = RunFolderLock.acquire(tmp_path / "run")
    record = json.loads((tmp_path / "run" / RUN_LOCK).read_text())
    assert (record["pid"], record["host"]) == (os.getpid(), socket.gethostname()) and record["since"] <= time.time()
    with pytest.raises(RunFolderInUseError, match=rf"pid {os.getpid()} on "):  # also from this very process
        RunFolderLock.acquire(tmp_path / "run")
    assert (tmp_path / "run" / RUN_LOCK).is_file() and lock.held
    lock.release()
    lock.release()
    assert not (tmp_path / "run" / RUN_LOCK).exists()
    RunFolderLock.acquire(tmp_path / "run").release()


def test_without_file_locks_the_record_decides(tmp_path, monkeypatch, caplog):
    """A filesystem without POSIX locks (lockf: ENOLCK): the holder's record alone decides, as for the evaluator's
    claims. A holder certainly dead on this host is taken over, any other is refused, saying how to free the folder."""
    def no_locks(fd, operation):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(run_folder_module.fcntl, "lockf", no_locks)
    run = tmp_path / "run"
    run.mkdir()
    for holder, refused in ((dead_pid(), False), (os.getppid(), True)):
        (run / RUN_LOCK).write_text(json.dumps({"host": socket.gethostname(), "pid": holder, "since": time.time()}))
        if refused:
            with pytest.raises(RunFolderInUseError, match=rf"pid {holder} on .*no file locks.*remove {re.escape(str(run))}"):
                RunFolderLock.acquire(run)
            continue
        caplog.set_level("WARNING")
        RunFolderLock.acquire(run).release()
        assert f"taking over {RUN_LOCK} from pid {holder}" in caplog.text and "does not support file locks" in caplog.text
        assert not (run / RUN_LOCK).exists()


@pytest.mark.parametrize("kind", ["file", "folder_that_is_not_a_run"])
def test_out_dir_that_is_not_a_run_folder_is_refused_before_writing(dataset, tmp_path, monkeypatch, capsys, kind):
    """Item 8: train.out_dir=README.md was a bare FileExistsError; a folder of other files was trained into."""
    if kind == "file":
        out = tmp_path / "README.md"
        out.write_text("# notes\n")
    else:
        out = tmp_path / "project"
        out.mkdir()
        (out / "notes.txt").write_text("mine\n")
        (out / "config.yaml").write_text("tool: something else\n")  # not a training config
    before, paths = snapshot(tmp_path), sorted(tmp_path.rglob("*"))
    forbid_training(monkeypatch)
    assert train_entry.main(["--config", "tiny", *base_overrides(dataset, out)]) == 2
    error = one_error_line(capsys)
    assert f"train.out_dir='{out}'" in error
    assert ("is a file" if kind == "file" else "not a run folder (no mfm-run.json of ours") in error
    assert snapshot(tmp_path) == before and sorted(tmp_path.rglob("*")) == paths  # nothing written or created


def test_run_folder_rules(tmp_path):
    """Item 8: what train.out_dir may be, checked before anything is written (``/`` is never written to here)."""
    for root in ("/", "/tmp/.."):
        with pytest.raises(RunFolderError, match="filesystem root"):
            check_run_folder(root)
    a_file = tmp_path / "README.md"
    a_file.write_text("hi\n")
    with pytest.raises(RunFolderError, match="is a file"):
        check_run_folder(a_file)
    with pytest.raises(RunFolderError, match="which is a file"):
        check_run_folder(a_file / "run")
    other = tmp_path / "other"
    other.mkdir()
    for i in range(7):
        (other / f"f{i}.txt").write_text("")
    with pytest.raises(RunFolderError, match=r"it holds f0.txt, f1.txt, f2.txt, f3.txt, f4.txt and 2 more"):
        check_run_folder(other)

    check_run_folder(tmp_path / "new" / "nested" / "run")  # created when the run writes
    (tmp_path / "empty").mkdir()
    check_run_folder(tmp_path / "empty")  # e.g. made by the scheduler
    marked = tmp_path / "marked"
    write_run_marker(marked, written_by="test")
    (marked / "slurm-1.out").write_text("")
    check_run_folder(marked)  # a run of ours, stopped before it wrote anything else
    assert json.loads((marked / RUN_MARKER).read_text())["format"] == "mfm-run"


def test_a_folder_is_a_run_by_our_marker_not_by_its_checkpoints_subfolder(tmp_path):
    """Issue 24, finding 4: another project's folder with a checkpoints/ subfolder was taken for a run and had its
    config.yaml and metrics.jsonl overwritten. A run is what our marker says; a run of an earlier version (before the
    marker) is recognised by our training config.yaml together with a checkpoint carrying our COMPLETE marker."""
    config_text = yaml.safe_dump(to_dict(load_config(TrainConfig, "tiny")))
    theirs = tmp_path / "theirs"
    (theirs / "checkpoints" / "epoch-3").mkdir(parents=True)
    (theirs / "config.yaml").write_text("lr: 0.1\n")
    (theirs / "metrics.jsonl").write_text('{"their": 1}\n')
    with_our_config = tmp_path / "their-config-is-like-ours"
    (with_our_config / "checkpoints").mkdir(parents=True)
    (with_our_config / "config.yaml").write_text(config_text)  # a training config, but no checkpoint of ours
    for folder in (theirs, with_our_config):
        with pytest.raises(RunFolderError, match="not a run folder"):
            check_run_folder(folder)

    earlier = tmp_path / "earlier-version-run"
    (earlier / "config.yaml").parent.mkdir()
    (earlier / "config.yaml").write_text(config_text)
    step = earlier / "checkpoints" / "step-00000004"
    step.mkdir(parents=True)
    files = {}
    for name in (ckpt.MODEL_FILE, ckpt.STATE_FILE):
        (step / name).write_bytes(b"weights")
        files[name] = {"bytes": 7, "sha256": hashlib.sha256(b"weights").hexdigest()}
    marker = {"format": "mfm-checkpoint", "version": 1, "step": 4, "files": files}
    (step / "COMPLETE").write_text(json.dumps({**marker, "files": {}}))  # not a complete checkpoint: no run
    with pytest.raises(RunFolderError, match="not a run folder"):
        check_run_folder(earlier)
    (step / "COMPLETE").write_text(json.dumps(marker))
    check_run_folder(earlier)  # runs made before the marker keep working (the trainer then adds the marker)

    (earlier / "checkpoints" / "step-00000008").mkdir()  # a user's folder of a checkpoint's name
    with pytest.raises(RunFolderError, match=r"step-00000008 is not a checkpoint this project wrote"):
        check_run_folder(earlier)


def test_training_into_another_projects_folder_with_checkpoints_is_refused_untouched(dataset, tmp_path, monkeypatch,
                                                                                      capsys):
    """Issue 24, finding 4, end to end: launch/train.py refuses, in one line and exit 2, writing nothing."""
    out = tmp_path / "theirs"
    (out / "checkpoints").mkdir(parents=True)
    (out / "config.yaml").write_text("their: config\n")
    (out / "metrics.jsonl").write_text('{"their": 1}\n')
    before, paths = snapshot(tmp_path), sorted(tmp_path.rglob("*"))
    forbid_training(monkeypatch)
    assert train_entry.main(["--config", "tiny", *base_overrides(dataset, out)]) == 2
    error = one_error_line(capsys)
    assert f"train.out_dir='{out}' is a non-empty folder that is not a run folder" in error
    assert snapshot(tmp_path) == before and sorted(tmp_path.rglob("*")) == paths


@pytest.mark.parametrize("override", ["train.max_steps=many", "train.no_such_key=1",
                                      "train.resume_discard_newer=true"])
def test_bad_settings_are_one_line_and_exit_code_2(tmp_path, capsys, override):
    """Item 8: config errors from launch/train.py are one line on stderr, not a traceback, as evaluate.py's."""
    assert train_entry.main(["--config", "tiny", f"train.out_dir={tmp_path / 'run'}", override]) == 2
    error = one_error_line(capsys)
    assert override.split("=")[0] in error or "no_such_key" in error
    assert not (tmp_path / "run").exists()


def test_bad_override_through_the_script_is_one_stderr_line(tmp_path):
    proc = subprocess.run([sys.executable, str(REPO_ROOT / "launch" / "train.py"), "--config", "tiny",
                           f"train.out_dir={tmp_path / 'run'}", "train.max_steps=many"],
                          cwd=REPO_ROOT, env=clean_env(), capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 2, output_of(proc)
    assert len(proc.stderr.strip().splitlines()) == 1 and proc.stderr.startswith("error: train.max_steps")
    assert not (tmp_path / "run").exists()


def test_build_objective_weighs_root_and_contacts_by_feat_bias():
    from types import SimpleNamespace

    from pipeline.training.trainer import build_objective

    manifest = SimpleNamespace(data={"feature_spec": {"skeleton": "humanml3d"}})
    assert build_objective(load_config(TrainConfig, "tiny"), manifest).channel_weight is None  # MFM: 1 everywhere
    weight = build_objective(load_config(TrainConfig, "tiny", ["train.flow_feat_bias=5"]), manifest).channel_weight
    assert len(weight) == 263 and weight[0] == weight[3] == weight[262] == 25.0 and weight[4] == weight[258] == 1.0


def test_build_objective_gives_the_foot_contact_term_its_weight_and_the_datasets_geometry():
    from types import SimpleNamespace

    from pipeline.training.trainer import build_objective

    manifest = SimpleNamespace(data={"feature_spec": {"skeleton": "humanml3d"},
                                     "normalization": {"mean": [0.0] * 263, "std": [1.0] * 263}})
    objective = build_objective(load_config(TrainConfig, "tiny", ["train.flow_foot_contact_weight=3"]), manifest)
    assert objective.foot_contact_weight == 3.0
    assert objective.geometry is not None and objective.geometry.skeleton.name == "humanml3d"
    assert build_objective(load_config(TrainConfig, "tiny"), manifest).foot_contact_weight == 0.0


def test_build_objective_gives_the_bone_term_its_target():
    from types import SimpleNamespace

    from pipeline.training.trainer import build_objective

    manifest = SimpleNamespace(data={"feature_spec": {"skeleton": "humanml3d"},
                                     "normalization": {"mean": [0.0] * 263, "std": [1.0] * 263}})
    median = build_objective(load_config(TrainConfig, "tiny", ["train.flow_bone_weight=2",
                                                               "train.flow_bone_target=clip_median"]), manifest)
    assert (median.bone_weight, median.bone_target) == (2.0, "clip_median")
    assert build_objective(load_config(TrainConfig, "tiny", ["train.flow_bone_weight=2"]),
                           manifest).bone_target == "frames"


def test_build_objective_gives_the_trajectory_term_its_minimum_time_and_pseudo_huber_scale():
    from types import SimpleNamespace

    from pipeline.training.trainer import build_objective

    manifest = SimpleNamespace(data={"feature_spec": {"skeleton": "humanml3d"},
                                     "normalization": {"mean": [0.0] * 263, "std": [1.0] * 263}})
    objective = build_objective(load_config(TrainConfig, "tiny", ["train.flow_trajectory_weight=0.1",
                                                                  "train.flow_trajectory_min_t=0.5",
                                                                  "train.flow_trajectory_huber=0.2"]), manifest)
    assert (objective.trajectory_weight, objective.trajectory_min_t, objective.trajectory_huber) == (0.1, 0.5, 0.2)
    default = build_objective(load_config(TrainConfig, "tiny"), manifest)
    assert (default.trajectory_min_t, default.trajectory_huber) == (0.0, 0.0)


def test_build_objective_gives_the_root_mean_term_and_the_input_perturbation_their_settings():
    from types import SimpleNamespace

    from pipeline.training.trainer import build_objective

    manifest = SimpleNamespace(data={"feature_spec": {"skeleton": "humanml3d"},
                                     "normalization": {"mean": [0.0] * 263, "std": [1.0] * 263}})
    objective = build_objective(load_config(TrainConfig, "tiny", ["train.flow_root_mean_weight=1.5",
                                                                  "train.flow_input_perturbation=0.1"]), manifest)
    assert (objective.root_mean_weight, objective.input_perturbation) == (1.5, 0.1)
    default = build_objective(load_config(TrainConfig, "tiny"), manifest)
    assert (default.root_mean_weight, default.input_perturbation) == (0.0, 0.0)
