"""One rank of the trainer's multi-process tests (tests/test_trainer.py, tests/test_trainer_multirank.py).

Started by torchrun / accelerate launch (gloo, CPU) or as a plain process for one rank:

    torchrun --standalone --nproc_per_node 2 tests/trainer_worker.py SPEC.json

SPEC.json is a list of scenarios run in order in this process (one launch covers several, because starting
torch processes is most of the cost). Each scenario is a dict:

    kind          "fit" (Trainer.fit, as launch/train.py runs it), "equivalence" (Trainer.train_step on this
                  rank's slice of fixed global batches and draws; see :func:`run_equivalence`) or "validate"
                  (Trainer.validate of the initial weights, the record saved to OUT/validate-rank{r}.json)
    out           folder for this scenario's per-rank records (created)
    overrides     config overrides on top of the ``tiny`` preset (train.out_dir, data.manifest, ...)
    record_ids    fit: append {"step", "ids", "widths"} per train_step to OUT/ids-rank{r}.jsonl (sample ids and
                  padded batch widths per step)
    kill_at       fit: [rank, step]: SIGKILL this process in the middle of that step (inside the loss)
    signal_at     fit: [rank, step, "SIGTERM"|"SIGINT"]: send the signal to this process in the middle of that step
    pause_at      fit: [rank, step]: in the middle of that step write OUT/paused-rank{r} and wait (at most 300 s) until
                  OUT/go exists: the run is alive, holding its folder, while the test does something beside it
    nan_at        fit: [rank, [steps]]: the loss VALUE is NaN on that rank at those steps (gradients stay finite,
                  so only the cross-rank flag can make the other ranks skip)
    overflow_at   fit: [rank, [steps]]: with fp16, one gradient of that rank is set to inf after the backward
                  passes (after DDP's gradient all-reduce) and before unscaling: an fp16 overflow on that rank
                  alone, which only the cross-rank flag can make the other ranks skip
    mixed_precision  train.mixed_precision of the process's Dist (the same in every scenario of a spec; default
                  "no"); set it in the overrides too
    snapshot_at   fit: [steps]: before and after each of these steps s, save weights, optimizer state, EMA and the
                  fp16 loss scaler's state to
                  OUT/snap-rank{r}-step{s-1}.pt and OUT/snap-rank{r}-step{s}.pt
    steps         equivalence: number of optimizer steps
    empty_at      equivalence: [rank, [steps]]: that rank's slice of those global batches (1-based steps) is empty,
                  as a batch whose every record was skipped in tolerant mode
    continue_after_error  true: an exception of this scenario, once recorded by every rank (the barrier after an
                  error passed on this rank), does not end the process: the next scenario runs, and the process
                  exits with 1 at the end. Several refusals then share one launch; a rank that finds the others
                  elsewhere still ends the process at once

Each rank writes OUT/result-rank{r}.json: {"exit_code": int} after fit returns, or {"error": class name,
"message"} before re-raising an exception (the process then exits non-zero, like launch/train.py). A non-zero
exit code from fit ends the process with that code, as launch/train.py does.
"""

from __future__ import annotations

import functools
import json
import logging
import os
import signal
import sys
import time
from collections.abc import Mapping, Sequence
from datetime import timedelta
from pathlib import Path
from typing import Any

import torch
import torch.distributed as torch_dist

import pipeline.training.trainer as trainer_module
from pipeline.config import TrainConfig, load_config
from pipeline.data.stream import LoaderOptions, MotionLoader
from pipeline.distributed import Dist, ends_rank_processes
from pipeline.training.trainer import Draws, Trainer, draw_for_batch

REAL_BUILD_OBJECTIVE = trainer_module.build_objective
ERROR_PASSED = -1  # run_scenario's code for an exception that continue_after_error let the process outlive


class HookedObjective:
    """The config's objective with its ``loss`` replaced by the fault injector's."""

    def __init__(self, loss) -> None:
        self.loss = loss


class Faults:
    """What to break, where: consulted by the patched loss in the middle of each step."""

    def __init__(self, scenario: Mapping[str, Any], rank: int) -> None:
        self.kill_at = _step_for_rank(scenario.get("kill_at"), rank)
        self.signal_at = None
        if scenario.get("signal_at") and scenario["signal_at"][0] == rank:
            self.signal_at = (int(scenario["signal_at"][1]), getattr(signal, scenario["signal_at"][2]))
        nan = scenario.get("nan_at")
        self.nan_steps = set(nan[1]) if nan and nan[0] == rank else set()
        self.overflow_steps = _steps_for_rank(scenario.get("overflow_at"), rank)
        self.pause_at = _step_for_rank(scenario.get("pause_at"), rank)
        self.out, self.rank = Path(scenario["out"]), rank
        self.step_in_progress = 0

    def loss(self, real_loss, *args: Any, **kwargs: Any) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """``real_loss`` (the objective's own, bound by build_faulty_objective) with this step's fault."""
        loss, stats = real_loss(*args, **kwargs)
        step = self.step_in_progress
        if step == self.kill_at:
            os.kill(os.getpid(), signal.SIGKILL)
        if self.signal_at is not None and step == self.signal_at[0]:
            os.kill(os.getpid(), self.signal_at[1])  # the trainer's handler runs here, mid-step
        if step == self.pause_at:
            (self.out / f"paused-rank{self.rank}").write_text(str(os.getpid()))
            deadline = time.monotonic() + 300
            while not (self.out / "go").exists():
                if time.monotonic() > deadline:
                    raise TimeoutError(f"paused at step {step}: {self.out / 'go'} never appeared")
                time.sleep(0.05)
        if step in self.nan_steps:
            loss = loss + loss.detach() * float("nan")  # NaN value, finite gradient
        return loss, stats


def _step_for_rank(spec: Sequence[int] | None, rank: int) -> int | None:
    return int(spec[1]) if spec and spec[0] == rank else None


def _steps_for_rank(spec: Sequence[Any] | None, rank: int) -> set[int]:
    return {int(s) for s in spec[1]} if spec and spec[0] == rank else set()


class InstrumentedTrainer(Trainer):
    """The real trainer, recording what each step consumed and snapshotting state around chosen steps."""

    def __init__(self, cfg: TrainConfig, dist: Dist, scenario: Mapping[str, Any], faults: Faults) -> None:
        super().__init__(cfg, dist)
        self.out = Path(scenario["out"])
        self.faults = faults
        self.record_ids = bool(scenario.get("record_ids"))
        self.snapshot_at = set(scenario.get("snapshot_at") or ())
        if faults.overflow_steps:
            unscale = self.loss_scaler.unscale_

            def unscale_with_overflow(optimizer):
                if self.faults.step_in_progress in self.faults.overflow_steps:
                    grad = next(p.grad for p in self.model.parameters() if p.grad is not None)
                    grad.view(-1)[0] = float("inf")
                return unscale(optimizer)

            self.loss_scaler.unscale_ = unscale_with_overflow

    def train_step(self, micro_batches, draws=None):
        step = self.step + 1
        self.faults.step_in_progress = step
        if self.record_ids:
            with open(self.out / f"ids-rank{self.dist.rank}.jsonl", "a") as f:
                f.write(json.dumps({"step": step, "ids": [list(b["ids"]) for b in micro_batches],
                                    "widths": [b["features"].shape[1] for b in micro_batches]}) + "\n")
        if step in self.snapshot_at:
            self._snapshot(step - 1)
        result = super().train_step(micro_batches, draws)
        if step in self.snapshot_at:
            self._snapshot(step)
        return result

    def _snapshot(self, step: int) -> None:
        state = {
            "model": {k: v.detach().clone() for k, v in self.dist.unwrap(self.model).state_dict().items()},
            "optimizer": self.optimizer.state_dict(),
            "ema": {k: v.clone() for k, v in self.ema.state_dict().items()},
            "scaler": self.loss_scaler.state_dict(),  # fp16's loss scale (None without fp16)
        }
        torch.save(state, self.out / f"snap-rank{self.dist.rank}-step{step}.pt")


def tiny_config(overrides: Sequence[str]) -> TrainConfig:
    return load_config(TrainConfig, "tiny", list(overrides))


# ---------------------------------------------------------------------------------------------------------------
# Data-parallel equivalence: the same global batches and draws, split over any number of ranks
# ---------------------------------------------------------------------------------------------------------------


def global_batches(cfg: TrainConfig, steps: int, global_batch: int) -> list[tuple[dict[str, Any], Draws]]:
    """``steps`` fixed global batches (read at world size 1) with their loss draws from a fixed generator."""
    options = LoaderOptions(batch_size=global_batch, num_workers=0, seed=cfg.data.seed, window=cfg.data.window,
                            unit_length=cfg.data.unit_length, shuffle_buffer=cfg.data.shuffle_buffer)
    batches = MotionLoader(cfg.data.manifest, "train", options).iter_batches()
    generator = torch.Generator().manual_seed(1234)
    out = []
    for _ in range(steps):
        batch = next(batches)
        draws = draw_for_batch(batch, cfg.model.cond_drop_prob, generator, cfg.model.self_condition_prob)
        out.append((batch, draws))
    return out


def slice_batch(batch: Mapping[str, Any], draws: Draws, part: int, parts: int) -> tuple[dict[str, Any], Draws]:
    """Rows ``[part·B/parts, (part+1)·B/parts)`` of every per-sample entry of a batch and of its draws."""
    size = draws.t.shape[0] // parts
    rows = slice(part * size, (part + 1) * size)
    sliced = {k: v[rows] for k, v in batch.items()}
    return sliced, _rows_of(draws, rows)


def _rows_of(draws: Draws, rows: slice) -> Draws:
    chosen = None if draws.self_condition_rows is None else draws.self_condition_rows[rows]
    return Draws(draws.t[rows], draws.x0[rows], draws.cond_mask[rows], self_condition_rows=chosen)


def empty_slice(batch: Mapping[str, Any], draws: Draws) -> tuple[dict[str, Any], Draws]:
    """No row of a batch: what the loader yields when every record of a batch was skipped (tolerant mode)."""
    none = slice(0, 0)
    return {k: v[none] for k, v in batch.items()}, _rows_of(draws, none)


def run_equivalence(trainer: Trainer, batches: list[tuple[dict[str, Any], Draws]], micro_batches: int = 1,
                    empty_steps: Sequence[int] = ()) -> dict:
    """Each rank trains on its 1/world_size of every global batch (split further into ``micro_batches``
    accumulated micro-batches); returns the final weights, EMA, and per step the global loss and gradient norm.
    At ``empty_steps`` (1-based) this rank's pieces are empty.

    AdamW's eps is raised to 1e-3 here: the attention key bias has an exactly-zero gradient in exact arithmetic
    (softmax ignores a shift), and with eps=1e-8 Adam turns the float rounding left there into lr-sized steps of
    random sign, so weights of runs that summed in another order would differ by ~lr. The promise under test is
    about gradients; the gradient norms are compared too (a sum-instead-of-mean bug would show there, not in
    Adam's scale-invariant update)."""
    critic_optimizer = [] if trainer.critic is None else [trainer.critic.optimizer]
    for optimizer in [trainer.optimizer, *critic_optimizer]:
        for group in optimizer.param_groups:
            group["eps"] = 1e-3
    dist = trainer.dist
    initial = {k: v.detach().clone() for k, v in dist.unwrap(trainer.model).state_dict().items()}
    initial_critic = None if trainer.critic is None else {
        k: v.clone() for k, v in trainer.critic.state_dict()["critic"].items()}
    parts = dist.world_size * micro_batches
    losses, grad_norms = [], []
    for step, (batch, draws) in enumerate(batches, start=1):
        pieces = [slice_batch(batch, draws, dist.rank * micro_batches + i, parts) for i in range(micro_batches)]
        if step in empty_steps:
            pieces = [empty_slice(batch, draws) for _ in pieces]
        *_, result = trainer.train_step([p[0] for p in pieces], draws=[p[1] for p in pieces]) + trainer.settle()
        trainer.step += 1
        losses.append(result.loss)
        grad_norms.append(float(result.grad_norm))
    return {
        "model": {k: v.detach().clone() for k, v in dist.unwrap(trainer.model).state_dict().items()},
        "ema": trainer.ema.state_dict(),
        "initial": initial,
        "losses": losses,
        "grad_norms": grad_norms,
        # train.critic_weight > 0: the critic's weights before and after
        **({} if trainer.critic is None else {"critic": trainer.critic.state_dict()["critic"],
                                               "initial_critic": initial_critic}),
    }


# ---------------------------------------------------------------------------------------------------------------
# Scenarios
# ---------------------------------------------------------------------------------------------------------------


def run_scenario(scenario: Mapping[str, Any], dist: Dist) -> int:
    out = Path(scenario["out"])
    out.mkdir(parents=True, exist_ok=True)
    cfg = tiny_config(scenario.get("overrides", []))
    result_file = out / f"result-rank{dist.rank}.json"
    faults = Faults(scenario, dist.rank)

    def build_faulty_objective(config: TrainConfig, manifest, **phase) -> HookedObjective:
        # One per objective the trainer builds (a start step gives it one per phase), each with its own real loss.
        return HookedObjective(functools.partial(faults.loss, REAL_BUILD_OBJECTIVE(config, manifest, **phase).loss))

    trainer_module.build_objective = build_faulty_objective
    try:
        if scenario["kind"] == "equivalence":
            trainer = Trainer(cfg, dist)
            batches = global_batches(cfg, int(scenario["steps"]), cfg.data.batch_size * dist.world_size)
            empty = _steps_for_rank(scenario.get("empty_at"), dist.rank)
            torch.save(run_equivalence(trainer, batches, empty_steps=empty), out / f"equivalence-rank{dist.rank}.pt")
            code = 0
        elif scenario["kind"] == "validate":
            record = Trainer(cfg, dist).validate()
            (out / f"validate-rank{dist.rank}.json").write_text(json.dumps(record))
            code = 0
        else:
            code = InstrumentedTrainer(cfg, dist, scenario, faults).fit()
    except Exception as err:
        result_file.write_text(json.dumps({"error": type(err).__name__, "message": str(err)}))
        if not wait_for_other_ranks(dist, after_error=True) or not scenario.get("continue_after_error"):
            raise
        logging.getLogger(__name__).error("scenario %s: %s: %s (going on to the next scenario)", out,
                                          type(err).__name__, err)
        return ERROR_PASSED
    finally:
        trainer_module.build_objective = REAL_BUILD_OBJECTIVE
    result_file.write_text(json.dumps({"exit_code": code}))
    wait_for_other_ranks(dist, after_error=False)
    return code


def wait_for_other_ranks(dist: Dist, after_error: bool) -> bool:
    """Every rank has written its record before any exits: once one rank's process ends with a non-zero code,
    torchrun terminates the others. After an error the other ranks may be elsewhere (a one-rank failure), so
    that wait gives up after a while instead of hanging. Returns whether every rank reached it."""
    if not dist.is_distributed:
        return True
    if not after_error:
        dist.barrier()
        return True
    try:
        torch_dist.monitored_barrier(timeout=timedelta(seconds=30))
    except RuntimeError:
        return False
    return True


@ends_rank_processes  # as the entry points end: tests/test_rank_exit.py
def main(spec_path: str) -> int:
    scenarios = json.loads(Path(spec_path).read_text())
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    torch.set_num_threads(1)  # bitwise comparisons across processes: same intra-op split everywhere
    precisions = {scenario.get("mixed_precision", "no") for scenario in scenarios}
    if len(precisions) != 1:
        raise ValueError(f"one Dist per process: every scenario of a spec needs the same mixed_precision, got {precisions}")
    errors_passed = False
    with Dist(mixed_precision=precisions.pop(), loss_scaling=True) as dist:
        for scenario in scenarios:
            code = run_scenario(scenario, dist)
            if code == ERROR_PASSED:
                errors_passed = True
            elif code != 0:
                return code
    return 1 if errors_passed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
