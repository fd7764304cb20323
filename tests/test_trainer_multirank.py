"""The training loop's promises across two real gloo ranks (torchrun and accelerate launch, CPU, tiny model).

* data parallelism is exact: 2 ranks on halves of fixed global batches == 1 process on the whole batches;
* the validation loss of 2 ranks (each on its share of the val batches, all-reduced) == 1 process's;
* a NaN on one rank makes every rank skip the same step (or all raise with nonfinite=stop), without a hang;
* a batch whose every record is bad on one rank (tolerant mode) is an empty step on that rank, not passed over:
  both ranks stay on their planned batches and at the same data position, the other rank's samples train with the
  empty rank weighing nothing in the mean, and the skipped records are counted;
* SIGTERM to one rank stops all ranks after the same step, with one complete checkpoint, exit code 143;
* a run interrupted by that SIGTERM and later by a SIGKILL, resumed twice, ends bit-identical to an
  uninterrupted run (weights, EMA, optimizer, per-rank RNG and data position, per-step losses and sample ids);
* ``accelerate launch`` with the 2-rank CPU recipe runs launch/train.py end to end.

The launches are module fixtures shared by the tests that read them: starting torch processes is most of the cost,
so every scenario that needs no launch of its own runs in one (the refusals among them go on to the next scenario
once both ranks have recorded theirs: tests/trainer_worker.py's continue_after_error).
"""

from __future__ import annotations

import json
import subprocess
import sys
from concurrent.futures import Future
from functools import partial
from pathlib import Path
from typing import Any, Callable

import pytest
import torch
from conftest import flip_byte, start_two_at_a_time
from test_trainer import (
    KILL_STEP,
    MAX_STEPS,
    REPO_ROOT,
    assert_equivalent,
    assert_identical,
    assert_runs_identical,
    build_dataset_once,
    clean_env,
    complete_steps,
    fit_scenario,
    holding_trainer,
    ids_by_step,
    metrics_by_step,
    output_of,
    results,
    resume_overrides,
    run_worker,
)
from test_trainer_bad_data import copy_dataset, planned_batches, shard_of, write_nan_into

from mfm.flops import TrainingFlops
from mfm.model import ModelConfig, MotionFlowTransformer
from pipeline import checkpoint as ckpt
from pipeline.config import TrainConfig, load_config
from pipeline.distributed import Dist
from pipeline.training.run_folder import RUN_LOCK, write_run_marker
from pipeline.training.trainer import Trainer

pytestmark = [pytest.mark.multirank, pytest.mark.slow]

TORCHRUN = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]
SIGTERM_STEP = 7  # not a multiple of save_every: the stop writes a checkpoint of its own
EQUIVALENCE_STEPS = 3
NAN_STEP = 3


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return build_dataset_once(tmp_path_factory)


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("trainer-multirank")


@pytest.fixture(scope="module")
def launches(dataset, workdir) -> dict[str, Future]:
    """The file's three independent launch sequences, started together (start_two_at_a_time: a launch leaves much
    of the two cores idle, the launcher, the rendezvous, the ranks' Python starts): the interrupted runs (three
    launches one after the other, run_interrupted), the shared launch (run_shared_launch, its data prepared here
    first) and accelerate launch (run_accelerate_launch). In the background only processes run and their files are
    read; each sequence's failure fails the tests that read it."""
    shared = prepare_shared_launch(dataset, workdir / "shared")
    return start_two_at_a_time({"interrupted": partial(run_interrupted, dataset, workdir),
                                "shared": partial(run_shared_launch, *shared),
                                "accelerate": partial(run_accelerate_launch, dataset, workdir / "accelerate" / "run")})


# ---------------------------------------------------------------------------------------------------------------
# One launch for the scenarios below that need no launch of their own
# ---------------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def shared_launch(launches) -> dict[str, Any]:
    return launches["shared"].result()


def prepare_shared_launch(dataset: Path, root: Path) -> tuple[Path, list[dict[str, Any]], dict[str, dict[str, Any]]]:
    """The scenarios of one torchrun launch, in order: the equivalence steps, the validation loss of the initial
    weights, a run with a NaN on rank 1 (skip), the runs with a batch of only bad records on rank 1, then the
    refusals, each recorded by both ranks before the next starts (a shard failing strict verification, a resume
    refused on rank 0, a run folder another trainer holds, a bad record met by rank 1), and last a run with
    nonfinite=stop, which raises on every rank and ends the processes with a non-zero code; with what each part's
    tests need, by part."""
    parts = {"misc": misc_scenarios(dataset, root / "misc"), "empty": empty_batch_scenarios(dataset, root / "empty"),
             "bad_shard": bad_shard_scenario(dataset, root / "bad-shard"),
             "refused": refused_resume_scenario(dataset, root / "refused"),
             "held": held_folder_scenario(dataset, root / "held"),
             "bad_record": bad_record_scenario(dataset, root / "bad-record"),
             "bad_record_deferred": bad_record_scenario(dataset, root / "bad-record-deferred",
                                                        "train.step_sync=deferred", "train.log_every=4")}
    for name in ("bad_shard", "refused", "held", "bad_record", "bad_record_deferred"):
        for scenario in parts[name][0]:
            scenario["continue_after_error"] = True
    scenarios = [scenario for scenarios, _ in parts.values() for scenario in scenarios]
    scenarios.append(nonfinite_stop_scenario(dataset, root / "misc" / "stop"))
    return root, scenarios, {name: context for name, (_, context) in parts.items()}


def run_shared_launch(root: Path, scenarios: list[dict[str, Any]], contexts: dict[str, dict[str, Any]]
                      ) -> dict[str, Any]:
    """The launch of prepare_shared_launch's scenarios, with another trainer holding the held part's run folder
    throughout. The subprocess timeout turns a hang into a failure. Returns the launch ("proc") and the contexts."""
    holder = holding_trainer(contexts["held"]["run"], "live")
    try:
        proc = run_worker(TORCHRUN, scenarios, root, timeout=400)
    finally:
        holder.kill()
        holder.wait(timeout=30)
    return {"proc": proc, **contexts, "held": {**contexts["held"], "holder_pid": holder.pid}}


# ---------------------------------------------------------------------------------------------------------------
# Data-parallel equivalence and non-finite losses
# ---------------------------------------------------------------------------------------------------------------


def misc_scenarios(dataset: Path, root: Path) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """The equivalence steps, the validation loss of the initial weights and a run with a NaN on rank 1 (skip); the
    run with nonfinite=stop (nonfinite_stop_scenario) ends the shared launch."""
    equivalence = {"kind": "equivalence", "out": str(root / "equivalence"), "steps": EQUIVALENCE_STEPS,
                   "overrides": [f"data.manifest={dataset}", f"train.out_dir={root / 'equivalence' / 'run'}",
                                 "model.dropout=0.0"]}
    self_conditioned = {"kind": "equivalence", "out": str(root / "self-conditioned"), "steps": EQUIVALENCE_STEPS,
                        "overrides": self_conditioned_overrides(dataset, root)}
    critic = {"kind": "equivalence", "out": str(root / "critic"), "steps": EQUIVALENCE_STEPS,
              "overrides": critic_overrides(dataset, root)}
    muon = {"kind": "equivalence", "out": str(root / "muon"), "steps": EQUIVALENCE_STEPS,
            "overrides": muon_overrides(dataset, root)}
    validate = {"kind": "validate", "out": str(root / "validate"), "overrides": validation_overrides(dataset, root)}
    skip = fit_scenario(root / "skip", [f"data.manifest={dataset}", f"train.out_dir={root / 'skip' / 'run'}",
                                        "train.log_every=1", "train.max_steps=5"],
                        nan_at=[1, [NAN_STEP]], snapshot_at=[NAN_STEP, 5])
    # the same with the skip decided on the device and the flags read during the next step (logged at step 5 only)
    skip_deferred = fit_scenario(root / "skip-deferred", [
        f"data.manifest={dataset}", f"train.out_dir={root / 'skip-deferred' / 'run'}", "train.log_every=5",
        "train.max_steps=5", "train.step_sync=deferred"], nan_at=[1, [NAN_STEP]], snapshot_at=[NAN_STEP, 5])
    return ([equivalence, self_conditioned, critic, muon, validate, skip, skip_deferred],
            {"root": root, "dataset": dataset})


def critic_overrides(dataset: Path, root: Path) -> list[str]:
    """A critic beside the model (train.critic_weight): its gradients are averaged over the ranks by hand."""
    return [f"data.manifest={dataset}", f"train.out_dir={root / 'critic' / 'run'}", "model.dropout=0.0",
            "train.critic_weight=0.05"]


def muon_overrides(dataset: Path, root: Path) -> list[str]:
    """Muon on the blocks' matrices, AdamW on the rest (optim.optimizer=muon), on the data-parallel gradients."""
    return [f"data.manifest={dataset}", f"train.out_dir={root / 'muon' / 'run'}", "model.dropout=0.0",
            "optim.optimizer=muon"]


def self_conditioned_overrides(dataset: Path, root: Path) -> list[str]:
    """A self-conditioned model (model.self_condition_prob): each rank runs the estimate's pass on its own chosen
    rows, a number that differs between ranks, from the second step (train.self_condition_start_step: the first
    drops the estimate's zero gradient on every rank)."""
    return [f"data.manifest={dataset}", f"train.out_dir={root / 'self-conditioned' / 'run'}", "model.dropout=0.0",
            "model.self_condition_prob=0.5", "train.self_condition_start_step=1"]


def nonfinite_stop_scenario(dataset: Path, out: Path) -> dict[str, Any]:
    return fit_scenario(out, [f"data.manifest={dataset}", f"train.out_dir={out / 'run'}", "train.log_every=1",
                              "train.max_steps=5", "train.nonfinite=stop"], nan_at=[1, [2]])


@pytest.fixture(scope="module")
def misc_launch(shared_launch) -> dict[str, Any]:
    return {**shared_launch["misc"], "proc": shared_launch["proc"]}


def validation_overrides(dataset: Path, root: Path) -> list[str]:
    """Validation batches of one motion: the test dataset's 3 val motions make 3 batches, 2 on rank 0, 1 on rank 1."""
    return [f"data.manifest={dataset}", f"train.out_dir={root / 'validate' / 'run'}", "data.batch_size=1",
            "train.val_every=1"]


def two_ranks_and_one_process(misc_launch: dict[str, Any], name: str, overrides: list[str],
                              equivalent: Callable[[dict[str, Any], dict[str, Any]], None] = assert_equivalent
                              ) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """The equivalence scenario ``name``: both ranks' results (their weights checked identical) and one process's
    run of the same steps on the whole global batches (``overrides`` on the tiny preset), compared by
    ``equivalent``."""
    import trainer_worker

    root = misc_launch["root"]
    assert (root / name / "result-rank0.json").exists(), output_of(misc_launch["proc"])
    ranks = [torch.load(root / name / f"equivalence-rank{r}.pt") for r in (0, 1)]
    assert_identical(ranks[0]["model"], ranks[1]["model"], "rank 0 vs rank 1 weights")
    cfg = load_config(TrainConfig, "tiny", overrides)
    batches = trainer_worker.global_batches(cfg, EQUIVALENCE_STEPS, 2 * cfg.data.batch_size)
    if cfg.model.self_condition_prob > 0:
        assert all(draws.self_condition_rows is not None for _, draws in batches)
    with Dist(mixed_precision="no") as dist:
        single = trainer_worker.run_equivalence(Trainer(cfg, dist), batches)
    equivalent(ranks[0], single)
    return ranks, single


def test_two_ranks_match_one_process_on_the_same_global_batches(misc_launch, tmp_path):
    two_ranks_and_one_process(misc_launch, "equivalence", [f"data.manifest={misc_launch['dataset']}",
                                                           f"train.out_dir={tmp_path}", "model.dropout=0.0"])


def test_self_conditioned_two_ranks_match_one_process(misc_launch, tmp_path):
    """The estimate's extra pass runs on each rank's chosen rows (or one discarded row when it has none), so the
    ranks make the same collectives and the step is the one-process step on the same global batches and draws."""
    ranks, _ = two_ranks_and_one_process(misc_launch, "self-conditioned",
                                         self_conditioned_overrides(misc_launch["dataset"], tmp_path))
    assert any(ranks[0]["model"][k].abs().sum() > 0 for k in ranks[0]["model"] if "self_condition_proj" in k)


def test_a_critic_on_two_ranks_matches_one_process(misc_launch, tmp_path):
    """The critic is not wrapped for data parallelism: its gradients are one all-reduce of a flat vector, averaged,
    and its update is taken with the model's. Two ranks on halves of fixed global batches end with the model and
    the critic of one process on the whole batches, and the same critic on both ranks."""
    ranks, single = two_ranks_and_one_process(misc_launch, "critic", critic_overrides(misc_launch["dataset"], tmp_path))
    assert_identical(ranks[0]["critic"], ranks[1]["critic"], "rank 0 vs rank 1 critic")
    torch.testing.assert_close(ranks[0]["critic"], single["critic"], rtol=1e-5, atol=1e-6)
    moved = max((single["critic"][k] - single["initial_critic"][k]).abs().max().item() for k in single["critic"]
                if k.endswith("original"))
    assert moved > 1e-5, "the critic's weights hardly moved: the comparison above would prove nothing"


def test_muon_on_two_ranks_matches_one_process(misc_launch, tmp_path):
    """Muon steps on the data-parallel (all-reduced) gradients: both ranks end with the same weights, and with one
    process's on the whole global batches up to the rounding of Muon's Newton–Schulz iterations, which torch runs
    in bf16: a last-bit difference of a gradient between the ranks' all-reduce and one process's sum can flip a
    bf16 rounding (2⁻⁸ of the value), and the five iterations carry it through the whole matrix: the change of a
    block's weights over the 3 steps then differs from one process's by about 2 % of itself. A gradient of one
    rank's half of the batches alone would give another orthogonalised direction altogether, so each tensor's
    change must agree with one process's to 10 % of its size. (Muon's step does not see the gradient's scale: a
    sum instead of a mean is the equivalence test's to catch, above.)"""
    def equivalent(result: dict[str, Any], reference: dict[str, Any]) -> None:
        torch.testing.assert_close(result["losses"], reference["losses"], rtol=1e-4, atol=1e-5)
        for name, weights in reference["model"].items():
            change = weights - reference["initial"][name]
            if change.norm() > 0:
                gap = (result["model"][name] - weights).norm() / change.norm()
                assert gap < 0.1, f"{name}: the two ranks' change differs from one process's by {gap:.2%}"
        moved = max((reference["model"][k] - reference["initial"][k]).abs().max().item() for k in reference["model"])
        assert moved > 1e-2, "the weights hardly moved: the comparison above would prove nothing"

    ranks, single = two_ranks_and_one_process(misc_launch, "muon", muon_overrides(misc_launch["dataset"], tmp_path),
                                              equivalent)
    muon_weights = [k for k in single["model"] if k.startswith("layers.") and single["model"][k].ndim == 2]
    assert muon_weights and all(not torch.equal(single["model"][k], single["initial"][k]) for k in muon_weights)


def test_two_ranks_give_the_validation_loss_of_one_process(misc_launch, tmp_path):
    root, dataset = misc_launch["root"], misc_launch["dataset"]
    assert (root / "validate" / "validate-rank1.json").exists(), output_of(misc_launch["proc"])
    ranks = [json.loads((root / "validate" / f"validate-rank{r}.json").read_text()) for r in (0, 1)]
    cfg = load_config(TrainConfig, "tiny", validation_overrides(dataset, tmp_path))
    with Dist(mixed_precision="no") as dist:
        single = Trainer(cfg, dist).validate()
    assert single["val_samples"] == ranks[0]["val_samples"] == ranks[1]["val_samples"] == 3
    assert ranks[0]["val_loss"] == ranks[1]["val_loss"]  # every rank holds the all-reduced mean
    assert ranks[0]["val_loss"] == pytest.approx(single["val_loss"], rel=0, abs=1e-6)


def test_nan_on_one_rank_is_skipped_by_every_rank_at_the_same_step(misc_launch):
    out = misc_launch["root"] / "skip"
    assert results(out, 2) == [{"exit_code": 0}] * 2, output_of(misc_launch["proc"])
    snaps = {(r, s): torch.load(out / f"snap-rank{r}-step{s}.pt") for r in (0, 1) for s in (NAN_STEP - 1, NAN_STEP, 5)}
    for rank in (0, 1):
        # rank 0's own loss and gradients were finite: only the shared flag made it skip
        assert_identical(snaps[rank, NAN_STEP - 1], snaps[rank, NAN_STEP], f"rank {rank} across the skipped step")
    for step in (NAN_STEP, 5):
        assert_identical(snaps[0, step]["model"], snaps[1, step]["model"], f"rank 0 vs 1 after step {step}")
    after_skip, final = snaps[0, NAN_STEP]["model"], snaps[0, 5]["model"]
    assert not torch.equal(after_skip["output_proj.weight"], final["output_proj.weight"])  # later steps trained
    metrics = metrics_by_step(out / "run")
    assert [metrics[s]["skipped_steps"] for s in range(1, 6)] == [0, 0, 1, 1, 1]
    assert metrics[NAN_STEP]["loss"] is None and all(metrics[s]["loss"] > 0 for s in (1, 2, 4, 5))
    _, _, state = ckpt.load_checkpoint(ckpt.checkpoints_dir(out / "run") / "step-00000005")
    assert state["extra"]["skipped_steps"] == 1 and state["extra"]["ema_updates"] == 4
    # the log's model FLOPs and samples are both summed over the ranks: their ratio is one sample's FLOPs
    model = MotionFlowTransformer(ModelConfig(**state["extra"]["model_config"]))
    per_sample = TrainingFlops(model).per_sample(state["config"]["data"]["window"])
    for record in metrics.values():
        assert record["model_tflops"] * 1e12 / record["samples_per_s"] == pytest.approx(per_sample)
        assert 0 <= record["padding_frac"] < 1 and record["mfu"] is None


def test_deferred_nan_on_one_rank_is_skipped_on_the_device_by_every_rank(misc_launch):
    """train.step_sync=deferred: rank 1's NaN at NAN_STEP reaches rank 0 in the step's flags, and both skip the
    update on the device (fused AdamW's found_inf, the EMA's weight 0) before either host reads them; the run then
    goes on as every_step's does."""
    out = misc_launch["root"] / "skip-deferred"
    assert results(out, 2) == [{"exit_code": 0}] * 2, output_of(misc_launch["proc"])
    snaps = {(r, s): torch.load(out / f"snap-rank{r}-step{s}.pt") for r in (0, 1) for s in (NAN_STEP - 1, NAN_STEP, 5)}
    for rank in (0, 1):  # the learning rate is the scheduler's, stepped when the host reads: compared below
        before, after = snaps[rank, NAN_STEP - 1], snaps[rank, NAN_STEP]
        for part in ("model", "ema"):
            assert_identical(before[part], after[part], f"rank {rank}'s {part} across the skipped step")
        assert_identical(before["optimizer"]["state"], after["optimizer"]["state"], f"rank {rank}'s AdamW state")
    for step in (NAN_STEP, 5):
        assert_identical(snaps[0, step]["model"], snaps[1, step]["model"], f"rank 0 vs 1 after step {step}")
    metrics = metrics_by_step(out / "run")
    assert sorted(metrics) == [5] and metrics[5]["skipped_steps"] == 1
    _, _, state = ckpt.load_checkpoint(ckpt.checkpoints_dir(out / "run") / "step-00000005")
    _, _, every_step = ckpt.load_checkpoint(ckpt.checkpoints_dir(misc_launch["root"] / "skip" / "run")
                                            / "step-00000005")
    assert state["extra"]["skipped_steps"] == 1 and state["extra"]["ema_updates"] == 4
    assert state["scheduler"] == every_step["scheduler"]  # four scheduler steps, as every_step's


def test_nan_with_nonfinite_stop_raises_on_every_rank(misc_launch):
    proc, out = misc_launch["proc"], misc_launch["root"] / "stop"
    assert proc.returncode != 0
    assert [r.get("error") for r in results(out, 2)] == ["NonFiniteLossError"] * 2, output_of(proc)
    assert "train.nonfinite=stop" in results(out, 2)[0]["message"]
    assert complete_steps(out / "run") == []  # stopped before the update, nothing saved after it
    assert sorted(metrics_by_step(out / "run")) == [1]


# ---------------------------------------------------------------------------------------------------------------
# A batch of only bad records on one rank (tolerant mode; issue 12, item 3)
# ---------------------------------------------------------------------------------------------------------------

EMPTY_STEP = 3  # every record of rank 1's batch at this step decodes to NaN
EMPTY_RUN_STEPS = 7  # an epoch is 5 batches per rank at 2 ranks: the run crosses into epoch 1


def empty_batch_scenarios(dataset: Path, root: Path) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """A tolerant run in which rank 1's whole batch at EMPTY_STEP is bad, then the equivalence steps with rank 1's
    slice of global batch 2 empty."""
    manifest = copy_dataset(dataset, root / "data")
    overrides = [f"data.manifest={manifest}", "data.verify=tolerant", "train.log_every=1",
                 f"train.max_steps={EMPTY_RUN_STEPS}", "train.save_every=100"]
    plans = [planned_batches(manifest, overrides, rank=rank, world_size=2, epochs=2) for rank in (0, 1)]
    assert len(plans[0]) == 10, "the dataset changed: adjust EMPTY_RUN_STEPS to cross the end of epoch 0"
    bad_ids = plans[1][EMPTY_STEP - 1]
    for sample_id in bad_ids:
        write_nan_into(manifest, sample_id)
    fit = fit_scenario(root / "fit", [*overrides, f"train.out_dir={root / 'fit' / 'run'}"])
    equivalence = {"kind": "equivalence", "out": str(root / "equivalence"), "steps": EQUIVALENCE_STEPS,
                   "empty_at": [1, [2]],
                   "overrides": [f"data.manifest={dataset}", f"train.out_dir={root / 'equivalence' / 'run'}",
                                 "model.dropout=0.0", "data.verify=tolerant"]}
    return [fit, equivalence], {"root": root, "dataset": dataset, "plans": plans, "bad_ids": bad_ids}


@pytest.fixture(scope="module")
def empty_batch_launch(shared_launch) -> dict[str, Any]:
    return {**shared_launch["empty"], "proc": shared_launch["proc"]}


def test_a_batch_of_only_bad_records_on_one_rank_keeps_both_ranks_on_their_plan(empty_batch_launch):
    """The loader used to pass the empty batch over: rank 1 then trained its next batch at that step and ran one
    batch ahead of rank 0 (and of its plan) for the rest of the run, crossing into the next epoch a step early."""
    launch = empty_batch_launch
    out, plans, bad_ids = launch["root"] / "fit", launch["plans"], launch["bad_ids"]
    assert results(out, 2) == [{"exit_code": 0}] * 2, output_of(launch["proc"])
    steps = range(1, EMPTY_RUN_STEPS + 1)
    for rank in (0, 1):  # the planned batch at every step, less the bad records (bad again in epoch 1)
        expected = {step: [[i for i in plans[rank][step - 1] if i not in bad_ids]] for step in steps}
        assert expected[EMPTY_STEP] == ([[]] if rank == 1 else [plans[0][EMPTY_STEP - 1]])
        assert ids_by_step(out, rank) == expected, f"rank {rank} left its planned batches"
    skipped_so_far = [sum(i in bad_ids for ids in plans[1][:step] for i in ids) for step in steps]

    _, _, state = ckpt.load_checkpoint(ckpt.checkpoints_dir(out / "run") / ckpt.step_dir_name(EMPTY_RUN_STEPS))
    epoch_batches = len(plans[0]) // 2
    assert [(d["epoch"], d["batches_in_epoch"]) for d in state["data"]] == [(1, EMPTY_RUN_STEPS - epoch_batches)] * 2
    assert [d["records_skipped"] for d in state["data"]] == [0, skipped_so_far[-1]]
    assert [d["empty_batches"] for d in state["data"]] == [0, 1]
    # Rank 0 had samples at that step: a real update on both ranks, nothing skipped.
    extra = state["extra"]
    assert extra["empty_steps"] == 0 and extra["skipped_steps"] == 0 and extra["ema_updates"] == EMPTY_RUN_STEPS
    metrics = metrics_by_step(out / "run")
    assert sorted(metrics) == list(range(1, EMPTY_RUN_STEPS + 1))
    assert all(metrics[step]["loss"] > 0 for step in metrics)  # finite at the empty step too: rank 0's mean
    assert [metrics[s]["records_skipped"] for s in sorted(metrics)] == skipped_so_far
    assert [metrics[s]["empty_batches"] for s in sorted(metrics)] == [0, 0] + [1] * 5
    # Every other sample of epoch 0 was trained once: nothing lost besides the bad records, nothing twice.
    trained = [i for rank in (0, 1) for step in range(1, epoch_batches + 1) for i in ids_by_step(out, rank)[step][0]]
    planned = [i for rank in (0, 1) for ids in plans[rank][:epoch_batches] for i in ids]
    assert sorted(trained) == sorted(set(planned) - set(bad_ids)) and len(set(trained)) == len(trained)


def test_an_empty_slice_on_one_rank_weighs_nothing_in_the_global_mean(empty_batch_launch, tmp_path):
    """Rank 1's slice of global batch 2 is empty: the step must equal one process training on rank 0's slice
    alone (the mean over the samples the step holds), with the gradient all-reduce done on both ranks."""
    import trainer_worker

    launch = empty_batch_launch
    root, dataset = launch["root"] / "equivalence", launch["dataset"]
    assert (root / "result-rank0.json").exists() and (root / "result-rank1.json").exists(), output_of(launch["proc"])
    ranks = [torch.load(root / f"equivalence-rank{r}.pt") for r in (0, 1)]
    assert_identical(ranks[0]["model"], ranks[1]["model"], "rank 0 vs rank 1 weights")

    cfg = load_config(TrainConfig, "tiny", [f"data.manifest={dataset}", f"train.out_dir={tmp_path}",
                                            "model.dropout=0.0"])
    batches = trainer_worker.global_batches(cfg, EQUIVALENCE_STEPS, 2 * cfg.data.batch_size)
    batches[1] = trainer_worker.slice_batch(*batches[1], part=0, parts=2)  # only rank 0's samples at step 2
    with Dist(mixed_precision="no") as dist:
        single = trainer_worker.run_equivalence(Trainer(cfg, dist), batches)
    assert_equivalent(ranks[0], single)


# ---------------------------------------------------------------------------------------------------------------
# Bad data met by one rank during training (strict mode; issue 24, item 9)
# ---------------------------------------------------------------------------------------------------------------

BAD_RECORD_STEP = 3  # rank 1's batch at this step holds a record that decodes to NaN


def bad_record_scenario(dataset: Path, root: Path, *extra: str) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    manifest = copy_dataset(dataset, root / "data")
    overrides = [f"data.manifest={manifest}", "data.verify=strict", "train.log_every=1", "train.max_steps=6",
                 "train.save_every=100", f"train.out_dir={root / 'run'}", *extra]
    bad_id = planned_batches(manifest, overrides, rank=1, world_size=2)[BAD_RECORD_STEP - 1][1]  # not the first:
    write_nan_into(manifest, bad_id)  # the batcher reads a batch's first record with the batch before
    return [fit_scenario(root, overrides)], {"root": root, "manifest": manifest, "bad_id": bad_id}


def test_bad_data_met_by_one_rank_stops_every_rank_at_that_step_with_its_error(shared_launch):
    """Rank 1 alone reads the bad record. It used to raise there, alone: rank 0, waiting in the step's
    all-reduce, died on the broken connection with a traceback (under NCCL it would wait for the collective
    timeout). Now the error travels in the step's flags: both ranks stop at that step, before its update, with rank
    1's error (launch/train.py prints it in one line, exit 2). The subprocess timeout turns a hang into a failure."""
    proc, part = shared_launch["proc"], shared_launch["bad_record"]
    root, manifest, bad_id = part["root"], part["manifest"], part["bad_id"]
    assert proc.returncode != 0
    outcomes = results(root, 2)
    assert [o.get("error") for o in outcomes] == ["RecordError"] * 2, output_of(proc)
    assert outcomes[0]["message"] == outcomes[1]["message"]
    assert f"{shard_of(manifest, bad_id)}: record '{bad_id}': features contain NaN" in outcomes[0]["message"]
    assert sorted(ids_by_step(root, 0)) == sorted(ids_by_step(root, 1)) == list(range(1, BAD_RECORD_STEP + 1))
    assert ids_by_step(root, 1)[BAD_RECORD_STEP] == [[]]  # rank 1 took part in that step with an empty stand-in
    assert sorted(metrics_by_step(root / "run")) == list(range(1, BAD_RECORD_STEP))  # that step never completed
    assert complete_steps(root / "run") == []


def test_deferred_bad_data_met_by_one_rank_stops_every_rank_during_the_next_step(shared_launch):
    """train.step_sync=deferred (flags read one step late; log_every 4, so step 3 is read during step 4): rank 1
    takes part in step 4 with a stand-in again (its stream ended with the error), rank 0 with its batch; both
    read the flag there and stop with rank 1's error, before step 4's update, nothing logged or saved."""
    proc, part = shared_launch["proc"], shared_launch["bad_record_deferred"]
    root, manifest, bad_id = part["root"], part["manifest"], part["bad_id"]
    outcomes = results(root, 2)
    assert [o.get("error") for o in outcomes] == ["RecordError"] * 2, output_of(proc)
    assert outcomes[0]["message"] == outcomes[1]["message"]
    assert f"{shard_of(manifest, bad_id)}: record '{bad_id}': features contain NaN" in outcomes[0]["message"]
    ids = [ids_by_step(root, rank) for rank in (0, 1)]
    assert sorted(ids[0]) == sorted(ids[1]) == list(range(1, BAD_RECORD_STEP + 2))
    assert ids[1][BAD_RECORD_STEP] == ids[1][BAD_RECORD_STEP + 1] == [[]] and ids[0][BAD_RECORD_STEP + 1] != [[]]
    assert not (root / "run" / "metrics.jsonl").exists() or metrics_by_step(root / "run") == {}
    assert complete_steps(root / "run") == []


def bad_shard_scenario(dataset: Path, root: Path) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    manifest = copy_dataset(dataset, root / "data")
    bad = json.loads(manifest.read_text())["splits"]["train"]["shards"][1]["path"]
    flip_byte(manifest.parent / bad, (manifest.parent / bad).stat().st_size // 2)
    overrides = [f"data.manifest={manifest}", "data.verify=strict", "train.max_steps=4", f"train.out_dir={root / 'run'}"]
    return [fit_scenario(root, overrides)], {"root": root, "bad": bad}


def test_a_shard_that_fails_strict_verification_stops_every_rank_with_the_same_error(shared_launch):
    """Rank 0 verifies the shards and decides; the other ranks must end with the same error (which launch/train.py
    prints in one line, exit 2), not a generic one, and nothing is written into the run folder."""
    proc, root, bad = shared_launch["proc"], shared_launch["bad_shard"]["root"], shared_launch["bad_shard"]["bad"]
    assert proc.returncode != 0
    outcomes = results(root, 2)
    assert [o.get("error") for o in outcomes] == ["ShardVerificationError"] * 2, output_of(proc)
    assert outcomes[0]["message"] == outcomes[1]["message"] and bad in outcomes[0]["message"]
    assert not (root / "run" / "metrics.jsonl").exists() and complete_steps(root / "run") == []


# ---------------------------------------------------------------------------------------------------------------
# SIGTERM, SIGKILL and exact resume
# ---------------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def uninterrupted(interrupted) -> Path:
    """The run of ``interrupted`` without interruptions: the first scenario of the launch stopped by SIGTERM."""
    out = interrupted["uninterrupted"]
    assert results(out, 2) == [{"exit_code": 0}] * 2, output_of(interrupted["sigterm"])
    return out


@pytest.fixture(scope="module")
def interrupted(launches) -> dict[str, Any]:
    return launches["interrupted"].result()


def run_interrupted(dataset: Path, workdir: Path) -> dict[str, Any]:
    """The same run, stopped by SIGTERM to rank 1 during step 7, resumed, SIGKILLed (rank 0) during step 12,
    resumed again from checkpoint 10 to the end. At 2 ranks an epoch is 5 batches per rank, so the first resume
    starts inside an epoch and the second on an epoch boundary. The uninterrupted run goes first in the launch of
    the SIGTERM (one launch less; every fit seeds itself afresh, and the resumed runs are fresh processes)."""
    out, uninterrupted_out = workdir / "interrupted", workdir / "uninterrupted"
    scenario = fit_scenario(out, resume_overrides(dataset, out / "run"))
    uninterrupted = fit_scenario(uninterrupted_out, resume_overrides(dataset, uninterrupted_out / "run"))
    sigterm = run_worker(TORCHRUN, [uninterrupted, {**scenario, "signal_at": [1, SIGTERM_STEP, "SIGTERM"]}], out)
    _, _, stop_state = ckpt.load_checkpoint(ckpt.checkpoints_dir(out / "run") / ckpt.step_dir_name(SIGTERM_STEP))
    after_sigterm = {"checkpoints": complete_steps(out / "run"), "results": results(out, 2),
                     "last_steps": [max(ids_by_step(out, r)) for r in (0, 1)],
                     "metrics_steps": sorted(metrics_by_step(out / "run")), "stop_state": stop_state}
    sigkill = run_worker(TORCHRUN, [{**scenario, "kill_at": [0, KILL_STEP]}], out)
    _, _, resume_state = ckpt.load_checkpoint(ckpt.checkpoints_dir(out / "run") / ckpt.step_dir_name(10))
    after_sigkill = {"checkpoints": complete_steps(out / "run"), "resume_state": resume_state}
    final = run_worker(TORCHRUN, [scenario], out)
    return {"out": out, "sigterm": sigterm, "after_sigterm": after_sigterm, "sigkill": sigkill,
            "after_sigkill": after_sigkill, "final": final, "uninterrupted": uninterrupted_out}


def test_sigterm_to_one_rank_stops_every_rank_after_one_step_with_a_checkpoint(interrupted):
    proc, seen = interrupted["sigterm"], interrupted["after_sigterm"]
    # torchrun reports the failed rank's code and exits non-zero itself
    assert proc.returncode != 0 and "exitcode  : 143" in proc.stderr, output_of(proc)
    # both ranks returned 143 from fit (rank 0 may then be terminated by torchrun while tearing down)
    assert seen["results"] == [{"exit_code": 143}] * 2, output_of(proc)
    assert seen["last_steps"] == [SIGTERM_STEP] * 2  # no rank started another step
    assert seen["checkpoints"] == [5, SIGTERM_STEP]  # the periodic one and exactly one stop checkpoint
    assert seen["metrics_steps"] == list(range(1, SIGTERM_STEP + 1))
    state = seen["stop_state"]
    assert state["step"] == SIGTERM_STEP and state["world_size"] == 2 and len(state["rng"]) == len(state["data"]) == 2
    assert [(d["epoch"], d["batches_in_epoch"]) for d in state["data"]] == [(1, 2)] * 2  # mid-epoch


def test_resume_after_sigterm_and_sigkill_is_bit_exact_on_two_ranks(interrupted, uninterrupted):
    assert interrupted["sigkill"].returncode != 0, output_of(interrupted["sigkill"])
    assert interrupted["after_sigkill"]["checkpoints"] == [SIGTERM_STEP, 10]
    resume_state = interrupted["after_sigkill"]["resume_state"]
    assert [(d["epoch"], d["batches_in_epoch"]) for d in resume_state["data"]] == [(2, 0)] * 2  # epoch boundary
    final = interrupted["final"]
    assert final.returncode == 0, output_of(final)
    assert results(interrupted["out"], 2) == [{"exit_code": 0}] * 2
    assert_runs_identical(uninterrupted / "run", interrupted["out"] / "run", MAX_STEPS)
    for rank in (0, 1):
        expected = ids_by_step(uninterrupted, rank)
        assert sorted(expected) == list(range(1, MAX_STEPS + 1))
        assert ids_by_step(interrupted["out"], rank) == expected, f"rank {rank} saw other samples"
    assert ids_by_step(uninterrupted, 0)[1] != ids_by_step(uninterrupted, 1)[1]  # the ranks read different data


# ---------------------------------------------------------------------------------------------------------------
# accelerate launch
# ---------------------------------------------------------------------------------------------------------------


def run_accelerate_launch(dataset: Path, run: Path) -> subprocess.CompletedProcess:
    env = clean_env()
    env["ACCELERATE_USE_CPU"] = "1"
    command = [sys.executable, "-m", "accelerate.commands.launch", "--multi_gpu", "--num_processes", "2",
               "--num_machines", "1", "--mixed_precision", "no", "--dynamo_backend", "no", "--main_process_port", "0",
               str(REPO_ROOT / "launch" / "train.py"), "--config", "tiny", f"data.manifest={dataset}",
               f"train.out_dir={run}", "train.max_steps=4", "train.save_every=2", "train.log_every=2"]
    return subprocess.run(command, cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=240)


def test_accelerate_launch_two_cpu_ranks_end_to_end(launches, workdir):
    run = workdir / "accelerate" / "run"
    proc = launches["accelerate"].result()
    assert proc.returncode == 0, output_of(proc)
    assert "world size 2" in proc.stderr
    assert complete_steps(run) == [2, 4]
    _, _, state = ckpt.load_checkpoint(ckpt.checkpoints_dir(run) / "step-00000004")
    assert state["world_size"] == 2 and state["extra"]["samples_seen"] == 4 * 4 * 2
    assert [s["batches_in_epoch"] for s in state["data"]] == [4, 4]  # each rank read its own 4 batches
    metrics = metrics_by_step(run)
    assert sorted(metrics) == [2, 4] and metrics[4]["samples_seen"] == 32


# ---------------------------------------------------------------------------------------------------------------
# A start refused on rank 0 is refused on every rank (issue 12, item 5)
# ---------------------------------------------------------------------------------------------------------------


def refused_resume_scenario(dataset: Path, root: Path) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    run = root / "run"
    for step in (2, 4):
        ckpt.save_checkpoint(ckpt.checkpoints_dir(run), step, model_state={"w": torch.zeros(2)}, ema_state=None,
                             optimizer_state={}, scheduler_state=None, rng_states=[{}, {}], data_states=[{}, {}],
                             config={}, manifest={})
    write_run_marker(run, written_by="tests/test_trainer_multirank.py")  # a run of ours, as the trainer marks one
    older = ckpt.checkpoints_dir(run) / "step-00000002"
    scenario = fit_scenario(root / "out", [f"data.manifest={dataset}", f"train.out_dir={run}",
                                           "train.max_steps=6", f"train.resume={older}"])
    return [scenario], {"root": root, "run": run}


def test_a_resume_refused_on_rank_0_ends_every_rank_before_training(shared_launch):
    """Rank 0 alone resolves train.resume; an explicit resume point older than the run's checkpoints is refused
    there, and the other rank must raise the same refusal at once rather than wait for a broadcast that never
    comes (resolve_resume only reads markers, so placeholder checkpoints do)."""
    proc, root, run = shared_launch["proc"], shared_launch["refused"]["root"], shared_launch["refused"]["run"]
    assert proc.returncode != 0, output_of(proc)
    for result in results(root / "out", 2):
        assert result["error"] == "ResumeConflictError" and "train.resume_discard_newer=true" in result["message"]
    assert complete_steps(run) == [2, 4] and not (run / "config.yaml").exists()


def held_folder_scenario(dataset: Path, root: Path) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """A run into a folder that another trainer holds (shared_launch starts the holder before the launch and ends
    it after)."""
    run = root / "run"
    scenario = fit_scenario(root / "out", [f"data.manifest={dataset}", f"train.out_dir={run}", "train.max_steps=4"])
    return [scenario], {"root": root, "run": run}


def test_a_run_folder_held_by_another_trainer_is_refused_on_every_rank(shared_launch):
    """Issue 24, item 5: only rank 0 checks and takes the run folder's lock; when another trainer holds the folder,
    every rank raises the same one-line refusal (naming the holder) at once instead of waiting for rank 0 in a
    collective, and nothing is written."""
    proc, part = shared_launch["proc"], shared_launch["held"]
    assert proc.returncode != 0, output_of(proc)
    for result in results(part["root"] / "out", 2):
        assert result["error"] == "RunFolderInUseError" and f"pid {part['holder_pid']} on " in result["message"], result
    assert [p.name for p in part["run"].iterdir()] == [RUN_LOCK]  # the holder's, nothing of the refused run
