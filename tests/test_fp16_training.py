"""fp16 mixed precision with dynamic loss scaling (pipeline/training/loss_scaling.py), CPU, the tiny preset:

* ``accelerate launch --mixed_precision fp16`` (and train.mixed_precision=fp16) resolves to fp16, a conflicting
  explicit setting is refused in one line, and a program without loss scaling refuses fp16;
* an fp16 run trains (fp16 autocast, finite decreasing loss) and records its loss scale, which grows after
  train.fp16_growth_interval clean steps;
* a forced overflow (one gradient set to inf after the backward pass, before unscaling) skips exactly that update,
  halves the scale, leaves weights, optimizer, scheduler and EMA as they were, and is counted in scaler_skips, not
  in skipped_steps nor against train.nonfinite_budget; a non-finite loss is still bad data (the scale is kept);
  overflows that push the scale below train.fp16_min_scale stop the run;
* exact resume across a checkpoint holds with fp16 (loss scale and growth tracker restored);
* at 2 gloo ranks an overflow on one rank only skips the step on both, and their weights stay identical.
"""

from __future__ import annotations

import logging
import math
import subprocess
import sys
from concurrent.futures import Future
from functools import partial
from pathlib import Path

import pytest
import torch
import yaml
from conftest import load_launch_script, selected_tests, start_two_at_a_time
from test_trainer import (
    REPO_ROOT,
    NaNAtSteps,
    assert_identical,
    assert_runs_identical,
    base_overrides,
    build_dataset_once,
    clean_env,
    complete_steps,
    fit_scenario,
    metrics_by_step,
    output_of,
    patch_loss,
    results,
    run_worker,
    train_entry,
)

from pipeline import checkpoint as ckpt
from pipeline.config import TrainConfig, TrainLoopConfig, load_config
from pipeline.distributed import Dist, MixedPrecisionError, resolve_mixed_precision
from pipeline.training.loss_scaling import LossScaler
from pipeline.training.trainer import NonFiniteLossError, Trainer

INIT_SCALE = 65536.0  # GradScaler's default initial scale, train.fp16_init_scale's default
TORCHRUN = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]


@pytest.fixture(scope="session")
def dataset(tmp_path_factory) -> Path:
    return build_dataset_once(tmp_path_factory)


def fp16_overrides(manifest: Path, out_dir: Path, *extra: str) -> list[str]:
    return base_overrides(manifest, out_dir, "train.mixed_precision=fp16", "train.tensorboard=false", *extra)


def force_overflow(monkeypatch, steps: set[int]) -> None:
    """At these (1-based) trainer steps, one gradient is set to inf after the backward pass and just before
    unscaling: the overflow an fp16 backward produces, on this process alone."""
    current = {"step": 0}
    real_train_step, real_unscale = Trainer.train_step, LossScaler.unscale_

    def train_step(self, micro_batches, draws=None):
        current["step"] = self.step + 1
        return real_train_step(self, micro_batches, draws)

    def unscale_(self, optimizer):
        if current["step"] in steps:
            grad = next(p.grad for group in optimizer.param_groups for p in group["params"] if p.grad is not None)
            grad.view(-1)[0] = float("inf")
        return real_unscale(self, optimizer)

    monkeypatch.setattr(Trainer, "train_step", train_step)
    monkeypatch.setattr(LossScaler, "unscale_", unscale_)


def final_state(run: Path, step: int) -> dict:
    return ckpt.load_checkpoint(ckpt.checkpoints_dir(run) / ckpt.step_dir_name(step))[2]


# ---------------------------------------------------------------------------------------------------------------
# Resolution
# ---------------------------------------------------------------------------------------------------------------


def test_fp16_resolves_from_the_config_and_from_accelerate_launch(monkeypatch, tmp_path, capsys):
    assert resolve_mixed_precision("fp16", loss_scaling=True) == "fp16"
    assert resolve_mixed_precision("auto", "fp16", loss_scaling=True) == "fp16"  # the launcher's fp16 is honoured
    assert resolve_mixed_precision("fp16", "fp16", loss_scaling=True) == "fp16"
    assert resolve_mixed_precision("fp16", "no", loss_scaling=True) == "fp16"  # "no" is accelerate's default
    for setting, launcher in (("no", "fp16"), ("bf16", "fp16"), ("fp16", "bf16")):
        with pytest.raises(MixedPrecisionError,
                           match=f"--mixed_precision {launcher} disagrees with train.mixed_precision={setting}"):
            resolve_mixed_precision(setting, launcher, loss_scaling=True)
    with pytest.raises(MixedPrecisionError, match="no fp16 loss scaling.*use bf16"):  # e.g. the evaluator's training
        resolve_mixed_precision("auto", "fp16")
    assert TrainLoopConfig(mixed_precision="fp16").mixed_precision == "fp16"

    monkeypatch.setenv("ACCELERATE_MIXED_PRECISION", "fp16")  # what accelerate launch --mixed_precision fp16 sets
    with Dist(mixed_precision="auto", loss_scaling=True, cpu=True) as dist:
        assert dist.mixed_precision == "fp16"
        with dist.autocast():
            assert torch.nn.Linear(4, 4)(torch.ones(1, 4)).dtype == torch.float16
    with pytest.raises(MixedPrecisionError):
        Dist(mixed_precision="auto", cpu=True)
    train = load_launch_script("train").main
    assert train(["--config", "tiny", "train.mixed_precision=no", f"train.out_dir={tmp_path / 'run'}"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--mixed_precision fp16 disagrees with train.mixed_precision=no" in err


# ---------------------------------------------------------------------------------------------------------------
# It trains, and the loss scale is recorded
# ---------------------------------------------------------------------------------------------------------------


# The launcher run of the next test: steps, and the clean steps after which the loss scale doubles.
LAUNCHED_STEPS, LAUNCHED_GROWTH = 16, 5


@pytest.fixture(scope="module")
def launches(dataset, tmp_path_factory, request) -> dict[str, tuple[Path, Future]]:
    """The launches of this file's two slow tests, started together (start_two_at_a_time), each when its test runs:
    accelerate launch of launch/train.py in fp16 (one process), and the torchrun overflow run (run_overflow). Per
    launch its folder and its result."""
    root = tmp_path_factory.mktemp("fp16-launches")
    wanted = selected_tests(request)
    launches = {}
    if "test_accelerate_launch_fp16_trains_on_cpu_and_records_the_loss_scale" in wanted:
        steps, growth = LAUNCHED_STEPS, LAUNCHED_GROWTH
        command = [sys.executable, "-m", "accelerate.commands.launch", "--num_processes", "1", "--num_machines", "1",
                   "--mixed_precision", "fp16", "--dynamo_backend", "no", "--cpu",
                   str(REPO_ROOT / "launch" / "train.py"), "--config", "tiny",
                   *base_overrides(dataset, root / "accelerate" / "run", "train.mixed_precision=auto",
                                   "train.tensorboard=false", f"train.max_steps={steps}", f"train.save_every={steps}",
                                   "data.batch_size=8", "optim.lr=2e-3", "model.dropout=0.0",
                                   f"train.fp16_growth_interval={growth}")]
        launches["accelerate"] = partial(subprocess.run, command, cwd=REPO_ROOT, env=clean_env(), capture_output=True,
                                         text=True, timeout=240)
    if "test_an_overflow_on_one_rank_skips_the_step_on_both" in wanted:
        launches["overflow"] = partial(run_overflow, dataset, root / "overflow")
    started = start_two_at_a_time(launches)
    return {name: (root / name, future) for name, future in started.items()}


@pytest.mark.slow
def test_accelerate_launch_fp16_trains_on_cpu_and_records_the_loss_scale(launches):
    """The real launcher (one CPU process): train.mixed_precision=auto follows its --mixed_precision fp16."""
    out, started = launches["accelerate"]
    run, steps, growth = out / "run", LAUNCHED_STEPS, LAUNCHED_GROWTH
    proc = started.result()
    assert proc.returncode == 0, output_of(proc)
    assert "precision fp16" in proc.stderr and f"loss scale {INIT_SCALE * 2 ** (steps // growth):g}" in proc.stderr

    metrics = metrics_by_step(run)
    losses = [metrics[s]["loss"] for s in range(1, steps + 1)]
    assert all(math.isfinite(loss) for loss in losses)
    assert sum(losses[-4:]) < sum(losses[:4]), f"loss did not decrease: {losses}"
    # no overflow here: the scale doubles after every `growth` clean steps, and every record says so
    assert [metrics[s]["loss_scale"] for s in metrics] == [INIT_SCALE * 2 ** (s // growth) for s in metrics]
    assert all(metrics[s]["scaler_skips"] == 0 and metrics[s]["skipped_steps"] == 0 for s in metrics)
    state = final_state(run, steps)
    assert state["scaler"] == {"scale": INIT_SCALE * 2 ** (steps // growth), "growth_tracker": steps % growth}
    assert state["extra"]["mixed_precision"] == "fp16" and state["extra"]["scaler_skips"] == 0
    assert yaml.safe_load((run / "config.yaml").read_text())["train"]["mixed_precision"] == "auto"  # as configured


# ---------------------------------------------------------------------------------------------------------------
# Overflow: skipped, counted apart, scale lowered
# ---------------------------------------------------------------------------------------------------------------


def test_a_forced_overflow_skips_exactly_that_update_and_lowers_the_scale(dataset, tmp_path, monkeypatch):
    force_overflow(monkeypatch, {2})
    cfg = load_config(TrainConfig, "tiny", fp16_overrides(dataset, tmp_path / "run"))
    with Dist(mixed_precision="fp16", loss_scaling=True) as dist:
        trainer = Trainer(cfg, dist)
        batches = trainer.loader.iter_batches()

        def step():
            [result] = trainer.train_step([next(batches)])
            trainer.step += 1
            trainer._handle_nonfinite(result)
            return result

        assert not step().overflow
        assert trainer.loss_scaler.state_dict() == {"scale": INIT_SCALE, "growth_tracker": 1}
        before = {"model": {k: v.clone() for k, v in trainer.model.state_dict().items()},
                  "optimizer": trainer.optimizer.state_dict(), "scheduler": trainer.scheduler.state_dict(),
                  "ema": trainer.ema.state_dict()}

        result = step()
        assert result.overflow and not result.skipped and not result.empty
        assert math.isfinite(result.loss) and not torch.isfinite(result.grad_norm)  # the loss was fine
        after = {"model": dict(trainer.model.state_dict()), "optimizer": trainer.optimizer.state_dict(),
                 "scheduler": trainer.scheduler.state_dict(), "ema": trainer.ema.state_dict()}
        assert_identical(before, after, "across the overflow step")
        assert all(p.grad is None for p in trainer.model.parameters())
        assert trainer.loss_scaler.state_dict() == {"scale": INIT_SCALE / 2, "growth_tracker": 0}
        assert (trainer.scaler_skips, trainer.skipped_steps, trainer.consecutive_skips) == (1, 0, 0)

        assert not step().overflow  # trains again, at the lower scale
        assert not torch.equal(before["model"]["output_proj.weight"], trainer.model.state_dict()["output_proj.weight"])
        assert trainer.loss_scaler.state_dict() == {"scale": INIT_SCALE / 2, "growth_tracker": 1}


def test_overflows_are_counted_apart_from_bad_data_and_spend_no_nonfinite_budget(dataset, tmp_path, monkeypatch):
    """Two overflows in a row, then a NaN loss, with train.nonfinite_budget=1: had the overflows counted as
    non-finite steps, the third skip in a row would exceed the budget."""
    run = tmp_path / "run"
    force_overflow(monkeypatch, {2, 3})
    patch_loss(monkeypatch, NaNAtSteps({4}))
    assert train_entry.main(["--config", "tiny", *fp16_overrides(dataset, run, "train.max_steps=6",
                                                                   "train.save_every=6",
                                                                   "train.nonfinite_budget=1")]) == 0
    metrics = metrics_by_step(run)
    assert [metrics[s]["scaler_skips"] for s in range(1, 7)] == [0, 1, 2, 2, 2, 2]
    assert [metrics[s]["skipped_steps"] for s in range(1, 7)] == [0, 0, 0, 1, 1, 1]
    # halved at each overflow; a non-finite loss leaves the scale as it was
    assert [metrics[s]["loss_scale"] for s in range(1, 7)] == [INIT_SCALE, INIT_SCALE / 2] + [INIT_SCALE / 4] * 4
    assert metrics[4]["loss"] is None and all(metrics[s]["loss"] > 0 for s in (1, 2, 3, 5, 6))
    state = final_state(run, 6)
    assert state["extra"]["scaler_skips"] == 2 and state["extra"]["skipped_steps"] == 1
    assert state["extra"]["ema_updates"] == 3 and state["scheduler"]["last_epoch"] == 3  # 3 real updates
    assert state["scaler"] == {"scale": INIT_SCALE / 4, "growth_tracker": 2}


def test_overflows_below_the_minimum_scale_stop_the_run(dataset, tmp_path, monkeypatch):
    force_overflow(monkeypatch, {1, 2})
    with pytest.raises(NonFiniteLossError, match="loss scale fell to 16384, below train.fp16_min_scale=20000"):
        train_entry.main(["--config", "tiny", *fp16_overrides(dataset, tmp_path / "run", "train.max_steps=4",
                                                                "train.fp16_min_scale=20000")])


# ---------------------------------------------------------------------------------------------------------------
# Exact resume
# ---------------------------------------------------------------------------------------------------------------


def test_exact_resume_with_fp16_restores_the_loss_scale(dataset, tmp_path, monkeypatch):
    """Run A: 8 steps. Run B: 4 steps, then resumed from its checkpoint 4 to 8. An overflow at step 2 and a growth
    interval of 3 leave the scaler mid-way at the checkpoint (scale halved, 2 of 3 clean steps), so a resume that
    restarted it (from the initial scale, or with a fresh growth tracker) would log other scales from step 5."""
    force_overflow(monkeypatch, {2})
    extra = ("train.save_every=4", "train.fp16_growth_interval=3")  # dropout stays on: the RNG state is resumed too
    run_a, run_b = tmp_path / "a", tmp_path / "b"
    assert train_entry.main(["--config", "tiny", *fp16_overrides(dataset, run_a, "train.max_steps=8", *extra)]) == 0
    assert train_entry.main(["--config", "tiny", *fp16_overrides(dataset, run_b, "train.max_steps=4", *extra)]) == 0
    assert final_state(run_b, 4)["scaler"] == {"scale": INIT_SCALE / 2, "growth_tracker": 2}
    assert train_entry.main(["--config", "tiny", *fp16_overrides(dataset, run_b, "train.max_steps=8", *extra)]) == 0

    assert complete_steps(run_b) == [4, 8]
    assert_runs_identical(run_a, run_b, 8)  # weights, EMA, optimizer, scaler, RNG, data position, per-step losses
    metrics_a, metrics_b = metrics_by_step(run_a), metrics_by_step(run_b)
    scales = [metrics_a[s]["loss_scale"] for s in range(1, 9)]
    assert scales == [INIT_SCALE, INIT_SCALE / 2, INIT_SCALE / 2, INIT_SCALE / 2, INIT_SCALE, INIT_SCALE,
                      INIT_SCALE, INIT_SCALE * 2]
    assert [metrics_b[s]["loss_scale"] for s in range(1, 9)] == scales
    assert [metrics_b[s]["scaler_skips"] for s in range(1, 9)] == [0] + [1] * 7


def test_an_fp32_checkpoint_resumes_in_fp16_from_the_initial_scale(dataset, tmp_path, caplog):
    caplog.set_level(logging.INFO)
    run = tmp_path / "run"
    fp32 = base_overrides(dataset, run, "train.tensorboard=false", "train.save_every=2")
    assert train_entry.main(["--config", "tiny", *fp32, "train.max_steps=2"]) == 0
    assert final_state(run, 2)["scaler"] is None and final_state(run, 2)["extra"]["mixed_precision"] == "no"
    assert train_entry.main(["--config", "tiny", *fp32, "train.max_steps=4", "train.mixed_precision=fp16"]) == 0
    assert "holds no fp16 loss scale (written with precision no)" in caplog.text
    metrics = metrics_by_step(run)
    assert "loss_scale" not in metrics[2] and [metrics[s]["loss_scale"] for s in (3, 4)] == [INIT_SCALE] * 2
    assert final_state(run, 4)["scaler"] == {"scale": INIT_SCALE, "growth_tracker": 2}


# ---------------------------------------------------------------------------------------------------------------
# Two ranks
# ---------------------------------------------------------------------------------------------------------------

OVERFLOW_STEP = 2


def run_overflow(dataset: Path, out: Path) -> subprocess.CompletedProcess:
    scenario = fit_scenario(out, fp16_overrides(dataset, out / "run", "train.max_steps=4", "train.save_every=4"),
                            overflow_at=[1, [OVERFLOW_STEP]], snapshot_at=[OVERFLOW_STEP, 4], mixed_precision="fp16")
    return run_worker(TORCHRUN, [scenario], out, timeout=240)


@pytest.mark.slow
@pytest.mark.multirank
def test_an_overflow_on_one_rank_skips_the_step_on_both(launches):
    """Rank 1's gradient becomes inf after DDP's all-reduce: rank 0's own gradients are finite, so only the shared
    overflow flag makes it skip; both keep identical weights and scalers."""
    out, started = launches["overflow"]
    proc = started.result()
    assert proc.returncode == 0 and results(out, 2) == [{"exit_code": 0}] * 2, output_of(proc)
    snaps = {(r, s): torch.load(out / f"snap-rank{r}-step{s}.pt")
             for r in (0, 1) for s in (OVERFLOW_STEP - 1, OVERFLOW_STEP, 4)}
    trained = ("model", "optimizer", "ema")
    for rank in (0, 1):
        before, after = snaps[rank, OVERFLOW_STEP - 1], snaps[rank, OVERFLOW_STEP]
        assert_identical({k: before[k] for k in trained}, {k: after[k] for k in trained}, f"rank {rank} across the overflow")
        assert (before["scaler"]["scale"], after["scaler"]["scale"]) == (INIT_SCALE, INIT_SCALE / 2)
    for step in (OVERFLOW_STEP, 4):
        assert_identical(snaps[0, step], snaps[1, step], f"rank 0 vs 1 after step {step}")  # weights and scalers
    assert not torch.equal(snaps[0, OVERFLOW_STEP]["model"]["output_proj.weight"],
                           snaps[0, 4]["model"]["output_proj.weight"])  # the later steps trained
    metrics = metrics_by_step(out / "run")
    assert [metrics[s]["scaler_skips"] for s in range(1, 5)] == [0, 1, 1, 1]
    assert [metrics[s]["skipped_steps"] for s in range(1, 5)] == [0] * 4
    assert [metrics[s]["loss_scale"] for s in range(1, 5)] == [INIT_SCALE] + [INIT_SCALE / 2] * 3
    state = final_state(out / "run", 4)
    assert state["scaler"] == {"scale": INIT_SCALE / 2, "growth_tracker": 2}
    assert state["extra"]["scaler_skips"] == 1 and state["extra"]["ema_updates"] == 3
