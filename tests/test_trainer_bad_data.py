"""Tolerant mode through the real training entry point (issue 12, item 3), CPU, the tiny preset, one rank:

* a record that decodes to non-finite features is skipped and counted, and a run interrupted and resumed is still
  bit-identical to an uninterrupted one;
* a batch whose every record is bad is not passed over: it is an empty batch that the trainer steps through (no
  update at one rank), counted, every later step keeps its planned batch, and exact resume across it holds (the
  same at two ranks, where the other rank's samples still train: tests/test_trainer_multirank.py);
* a shard that goes bad after a checkpoint: the tolerant resume finishes the checkpoint's epoch with its plan
  without that shard's records (exactly the batches that were due, minus those records), plans later epochs
  without it and says so; a strict resume refuses with a hint that names a real option;
* a remote shard that changes on the server after verification, keeping its size, ETag and Last-Modified (issue
  24, item 2): strict stops before any step trains on it (every checkpoint predates it), tolerant leaves its
  records out of their planned batches, counted.

The runs are in-process (launch/train.py's ``main``); the interruption is a SIGINT in the middle of a step, after
which the trainer writes a checkpoint of that step and returns 130.
"""

from __future__ import annotations

import hashlib
import io
import json
import re
import shutil
import signal
import tarfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from test_data_remote import needs_http, rewrite_in_place, serving
from test_trainer import (
    MAX_STEPS,
    SignalAtStep,
    assert_runs_identical,
    base_overrides,
    build_dataset_once,
    complete_steps,
    flip_byte,
    metrics_by_step,
    one_error_line,
    patch_loss,
    resume_overrides,
    train_entry,
)

import pipeline.training.trainer as trainer_module
from pipeline import checkpoint as ckpt
from pipeline.config import TrainConfig, load_config
from pipeline.data.stream import LoaderOptions, MotionLoader, backend_for_format
from pipeline.training.trainer import Trainer
from preprocess.shards import derive_dataset_id

NEVER = 10**9  # a SignalAtStep that never fires: the same hooked loss in every run that is compared


@pytest.fixture(scope="session")
def dataset(tmp_path_factory) -> Path:
    return build_dataset_once(tmp_path_factory)


def copy_dataset(manifest: Path, to: Path) -> Path:
    shutil.copytree(manifest.parent, to)
    return to / "manifest.json"


def planned_batches(manifest: Path, overrides: list[str], *, rank: int = 0, world_size: int = 1,
                    epochs: int = 1) -> list[list[str]]:
    """The sample ids of every batch of the first ``epochs`` epochs at ``rank``, from a loader built as the trainer
    builds its own."""
    cfg = load_config(TrainConfig, "tiny", overrides)
    options = LoaderOptions(batch_size=cfg.data.batch_size, num_workers=cfg.data.num_workers, seed=cfg.data.seed,
                            window=cfg.data.window, unit_length=cfg.data.unit_length,
                            shuffle_buffer=cfg.data.shuffle_buffer, caption_policy=cfg.data.caption_policy,
                            backend=backend_for_format(cfg.data.format))
    loader = MotionLoader(manifest, "train", options, rank=rank, world_size=world_size)
    return [batch["ids"] for _ in range(epochs) for batch in loader.iter_epoch()]


def shard_of(manifest: Path, sample_id: str) -> str:
    for entry in json.loads(manifest.read_text())["splits"]["train"]["shards"]:
        with tarfile.open(manifest.parent / entry["path"]) as tar:
            if any(name.startswith(sample_id + ".") for name in tar.getnames()):
                return entry["path"]
    raise AssertionError(f"{sample_id} is in no train shard")


def ids_in_shard(manifest: Path, path: str) -> set[str]:
    with tarfile.open(manifest.parent / path) as tar:
        return {name.split(".", 1)[0] for name in tar.getnames()}


def rewrite_record_features(manifest: Path, shard: str, change: Callable[[np.ndarray], np.ndarray], *,
                            member: str | None = None, resign_id: bool = True) -> None:
    """Replace one record's features in ``shard`` by ``change(features)``, in place (same byte count), and record the
    shard's new sha256 in the manifest; ``resign_id``: the dataset id too, as its builder would have written it.
    ``member``: the record's ``.features.npy`` entry (default: the shard's first)."""
    file = manifest.parent / shard
    with tarfile.open(file) as tar:
        info = (tar.getmember(member) if member is not None
                else next(m for m in tar.getmembers() if m.name.endswith(".features.npy")))
        features = np.load(io.BytesIO(tar.extractfile(info).read()))
    payload = io.BytesIO()
    np.save(payload, change(features), allow_pickle=False)
    assert len(payload.getvalue()) == info.size
    with open(file, "r+b") as handle:
        handle.seek(info.offset_data)
        handle.write(payload.getvalue())
    data = json.loads(manifest.read_text())
    entry = next(e for split in data["splits"].values() for e in split.get("shards", ()) if e["path"] == shard)
    entry["sha256"] = hashlib.sha256(file.read_bytes()).hexdigest()
    if resign_id:
        data["dataset_id"] = derive_dataset_id(data)
    manifest.write_text(json.dumps(data, indent=1))


def write_nan_into(manifest: Path, sample_id: str) -> None:
    """Put a NaN in one record's features, in place (same bytes count), and record the shard's new sha256 in the
    manifest: a dataset built with a bad record, whose shards all verify."""

    def with_nan(features: np.ndarray) -> np.ndarray:
        features[len(features) // 2, 0] = np.nan
        return features

    rewrite_record_features(manifest, shard_of(manifest, sample_id), with_nan, member=f"{sample_id}.features.npy")


def final_data_state(run: Path) -> dict:
    _, _, state = ckpt.load_checkpoint(ckpt.checkpoints_dir(run) / ckpt.step_dir_name(MAX_STEPS))
    return state["data"][0]


def fit(monkeypatch, overrides: list[str], signal_at_step: int = NEVER,
        trained: dict[int, list[str]] | None = None) -> int:
    """launch/train.py's main; ``trained`` (if given) collects the sample ids of every step, by step number."""
    monkeypatch.undo()  # patch_loss wraps whatever build_objective is in place: start from the real one
    patch_loss(monkeypatch, SignalAtStep(signal_at_step, signal.SIGINT))
    if trained is not None:
        real_step = Trainer.train_step

        def recording_step(self, micro_batches, draws=None):
            trained[self.step + 1] = [i for b in micro_batches for i in b["ids"]]
            return real_step(self, micro_batches, draws)

        monkeypatch.setattr(Trainer, "train_step", recording_step)
    return train_entry.main(["--config", "tiny", *overrides])


def test_tolerant_training_skips_a_nonfinite_record_and_resumes_bit_exactly(dataset, tmp_path, monkeypatch, capsys):
    manifest = copy_dataset(dataset, tmp_path / "data")
    strict = resume_overrides(manifest, tmp_path / "strict")
    bad_id = planned_batches(manifest, strict)[9][0]  # trained at step 10, after the interruption at step 7
    write_nan_into(manifest, bad_id)

    assert fit(monkeypatch, strict) == 2  # strict: the run stops, one line naming the shard and the record
    assert f"record '{bad_id}': features contain NaN" in one_error_line(capsys)

    run_a, run_b = tmp_path / "a", tmp_path / "b"
    assert fit(monkeypatch, resume_overrides(manifest, run_a, "data.verify=tolerant")) == 0
    assert fit(monkeypatch, resume_overrides(manifest, run_b, "data.verify=tolerant"), signal_at_step=7) == 130
    assert complete_steps(run_b) == [5, 7]
    assert fit(monkeypatch, resume_overrides(manifest, run_b, "data.verify=tolerant")) == 0

    assert_runs_identical(run_a, run_b, MAX_STEPS)
    assert final_data_state(run_a)["records_skipped"] == final_data_state(run_b)["records_skipped"] == 1
    # Each metrics.jsonl line shows the running count: 0 until the bad record's batch (step 10), then 1, in the
    # uninterrupted run and across the resume alike.
    for run in (run_a, run_b):
        metrics = metrics_by_step(run)
        assert [metrics[step]["records_skipped"] for step in sorted(metrics)] == [0] * 9 + [1] * (MAX_STEPS - 9)


def test_a_batch_of_only_bad_records_is_an_empty_step_in_the_plan_and_resumes_bit_exactly(dataset, tmp_path,
                                                                                          monkeypatch):
    """Every record of the batch due at step 10 decodes to NaN. The loader used to pass that batch over, so step 10
    trained the batch planned for step 11 and the rank ran one batch ahead of its plan for the rest of the run
    (at several ranks: ahead of the other ranks). Now step 10 is an empty step: no sample, no update (one rank),
    counted; every other step trains exactly its planned batch; a run interrupted before it and resumed ends
    bit-identical to an uninterrupted one."""
    manifest = copy_dataset(dataset, tmp_path / "data")
    plan = planned_batches(manifest, resume_overrides(manifest, tmp_path / "plan"), epochs=2)
    epoch_batches = len(plan) // 2
    bad_step = 10  # after the interruption at step 7 and the checkpoint at step 5
    bad_ids = plan[bad_step - 1]
    for sample_id in bad_ids:
        write_nan_into(manifest, sample_id)

    run_a, run_b = tmp_path / "a", tmp_path / "b"
    trained_a: dict[int, list[str]] = {}
    trained_b: dict[int, list[str]] = {}
    tolerant_a = resume_overrides(manifest, run_a, "data.verify=tolerant")
    tolerant_b = resume_overrides(manifest, run_b, "data.verify=tolerant")
    assert fit(monkeypatch, tolerant_a, trained=trained_a) == 0
    assert fit(monkeypatch, tolerant_b, signal_at_step=7, trained=trained_b) == 130
    assert complete_steps(run_b) == [5, 7]
    assert fit(monkeypatch, tolerant_b, trained=trained_b) == 0

    steps = range(1, MAX_STEPS + 1)
    expected = {step: [i for i in plan[step - 1] if i not in bad_ids] for step in steps}  # bad in epoch 1 too
    assert [step for step in steps if not expected[step]] == [bad_step]  # (in epoch 1 the bad records are spread)
    assert trained_a == expected  # lockstep with the plan: the empty batch takes its step, nothing shifts
    assert trained_b == expected
    assert_runs_identical(run_a, run_b, MAX_STEPS)

    _, _, state = ckpt.load_checkpoint(ckpt.checkpoints_dir(run_a) / ckpt.step_dir_name(MAX_STEPS))
    data = state["data"][0]
    assert (data["epoch"], data["batches_in_epoch"]) == (1, MAX_STEPS - epoch_batches)  # the planned position
    skipped_so_far = [sum(i in bad_ids for ids in plan[:step] for i in ids) for step in steps]
    assert data["records_skipped"] == skipped_so_far[-1] and data["empty_batches"] == 1
    # One rank, one micro-batch: the step had no sample anywhere, so no update (optimizer, schedule, EMA).
    assert state["extra"]["empty_steps"] == 1 and state["extra"]["skipped_steps"] == 0
    assert state["extra"]["ema_updates"] == MAX_STEPS - 1 and state["scheduler"]["last_epoch"] == MAX_STEPS - 1
    for run in (run_a, run_b):
        metrics = metrics_by_step(run)
        before, after = range(1, bad_step), range(bad_step, MAX_STEPS + 1)
        assert [metrics[s]["records_skipped"] for s in sorted(metrics)] == skipped_so_far
        assert [metrics[s]["empty_batches"] for s in sorted(metrics)] == [0] * len(before) + [1] * len(after)
        assert [metrics[s]["empty_steps"] for s in sorted(metrics)] == [0] * len(before) + [1] * len(after)
        assert metrics[bad_step]["loss"] is None  # nothing to average, not a NaN
        assert all(metrics[s]["loss"] > 0 for s in metrics if s != bad_step)


def test_tolerant_resume_after_a_shard_went_bad_finishes_the_epoch_without_it(dataset, tmp_path, monkeypatch,
                                                                              caplog, capsys):
    manifest = copy_dataset(dataset, tmp_path / "data")
    run = tmp_path / "run"
    tolerant = resume_overrides(manifest, run, "data.verify=tolerant")
    planned = planned_batches(manifest, tolerant)  # epoch 0: 13 batches at one rank
    assert fit(monkeypatch, tolerant, signal_at_step=5) == 130 and complete_steps(run) == [5]

    bad = shard_of(manifest, planned[7][0])  # a shard with records due at step 8, after the checkpoint
    lost = ids_in_shard(manifest, bad)
    flip_byte(manifest.parent / bad, (manifest.parent / bad).stat().st_size // 2)

    assert fit(monkeypatch, resume_overrides(manifest, run, "data.verify=strict")) == 2
    assert re.search(rf"{bad}: bad shard \(corrupted.*data\.verify=tolerant", one_error_line(capsys))

    trained: dict[int, list[str]] = {}
    real_step = Trainer.train_step

    def recording_step(self, micro_batches, draws=None):
        trained[self.step + 1] = [i for b in micro_batches for i in b["ids"]]
        return real_step(self, micro_batches, draws)

    caplog.set_level("WARNING")
    monkeypatch.undo()
    patch_loss(monkeypatch, SignalAtStep(NEVER, signal.SIGINT))
    monkeypatch.setattr(Trainer, "train_step", recording_step)
    assert train_entry.main(["--config", "tiny", *tolerant]) == 0

    assert "RESUMING WITH CHANGED SHARDS" in caplog.text and bad in caplog.text
    due = [[i for i in ids if i not in lost] for ids in planned[5:]]  # the rest of epoch 0, minus the shard
    assert [trained[step] for step in range(6, 14)] == due  # a batch left with no record is an empty step
    assert not lost & {i for step in range(14, MAX_STEPS + 1) for i in trained[step]}  # epoch 1: planned without it
    state = final_data_state(run)
    assert state["epoch"] == 1 and state["excluded_shards"] == [bad] and state["carried_epoch"] is None
    assert state["records_skipped"] == sum(i in lost for ids in planned[5:] for i in ids) > 0
    metrics = metrics_by_step(run)  # the running count in every log line: none before the shard went bad
    assert all(metrics[step]["records_skipped"] == 0 for step in range(1, 6))
    assert metrics[MAX_STEPS]["records_skipped"] == state["records_skipped"]
    assert [metrics[step]["records_skipped"] for step in sorted(metrics)] == sorted(
        metrics[step]["records_skipped"] for step in metrics)  # never decreases
    report = json.loads((run / "shard_report.json").read_text())
    assert [b["path"] for b in report["bad"]] == [bad] and not report["verified"]


@needs_http
@pytest.mark.parametrize("verify", ["strict", "tolerant"])
def test_a_remote_shard_changed_after_verification_is_never_trained_on(dataset, tmp_path, monkeypatch, capsys,
                                                                       verify):
    """Issue 24, item 2, through the real trainer and no kill: the dataset is served over HTTP by a server that, like
    nginx, derives the ETag from size and mtime. Right after the trainer verified the train split, the shard read
    last in epoch 0 is rewritten in place with its old mtime (size, ETag, Last-Modified unchanged). It used to be
    trained on. Strict: the run stops with ShardChangedError (one line naming the URL, exit 2) before any step saw a
    record of it, so every checkpoint on disk (saved every 2 steps) predates it. Tolerant: the run ends; every step trained exactly
    its planned batch without the shard's records, counted in records_skipped."""
    root = tmp_path / "served"
    shutil.copytree(dataset.parent, root)
    local = root / "manifest.json"
    steps = 13  # epoch 0 at one rank
    planned = planned_batches(local, base_overrides(local, tmp_path / "plan"))
    first_use = {}
    for step, ids in enumerate(planned, start=1):
        for sample_id in ids:
            first_use.setdefault(shard_of(local, sample_id), step)
    changed = max(first_use, key=first_use.get)
    lost = ids_in_shard(local, changed)
    assert first_use[changed] > 4  # read after checkpoints 2 and 4

    trained: dict[int, list[str]] = {}
    real_step, real_verify = Trainer.train_step, trainer_module.verify_shards

    def recording_step(self, micro_batches, draws=None):
        trained[self.step + 1] = [i for b in micro_batches for i in b["ids"]]
        return real_step(self, micro_batches, draws)

    def verify_then_change(manifest, split, **kwargs):
        report = real_verify(manifest, split, **kwargs)
        if split == "train":
            rewrite_in_place(root / changed)
        return report

    monkeypatch.setattr(Trainer, "train_step", recording_step)
    monkeypatch.setattr(trainer_module, "verify_shards", verify_then_change)
    run = tmp_path / "run"
    with serving(root) as (base, _):
        argv = ["--config", "tiny", *base_overrides(f"{base}/manifest.json", run, f"train.max_steps={steps}",
                                                    "train.save_every=2", "train.keep_last=0", f"data.verify={verify}")]
        if verify == "strict":
            assert train_entry.main(argv) == 2  # ShardChangedError: one line, exit 2 (the error contract)
            assert f"{base}/{changed}: changed since it was verified" in one_error_line(capsys)
            assert not lost & {i for ids in trained.values() for i in ids}
            # the step that met the shard runs with an empty stand-in and stops every rank before its update
            assert sorted(trained) == list(range(1, max(trained) + 1)) and max(trained) <= first_use[changed]
            assert complete_steps(run) == list(range(2, first_use[changed], 2))  # saved before the shard was read
            return
        assert train_entry.main(argv) == 0
    assert trained == {step: [i for i in planned[step - 1] if i not in lost] for step in range(1, steps + 1)}
    skipped = sum(i in lost for ids in planned for i in ids)
    assert skipped > 0 and metrics_by_step(run)[steps]["records_skipped"] == skipped


# ---------------------------------------------------------------------------------------------------------------
# Bad data stops the run with one line and exit 2, before training or at the step that meets it (issue 24, item 9)
# ---------------------------------------------------------------------------------------------------------------


def overcount_shard(manifest: Path, index: int = 1) -> str:
    """Make the manifest say one record more than train shard ``index`` holds (the shard's bytes untouched, so
    only a count of its records can tell); returns the shard's path."""
    data = json.loads(manifest.read_text())
    entry = data["splits"]["train"]["shards"][index]
    entry["num_motions"] += 1
    manifest.write_text(json.dumps(data, indent=1))
    return entry["path"]


@pytest.mark.parametrize("bad, verify, workers", [
    ("count", "strict", 0),  # verification counts the records before training
    ("count", "off", 0),  # the reader counts them when it reaches the shard's end, during training
    ("count", "off", 2),  # ... in a DataLoader worker process
    ("nan", "strict", 2),  # a non-finite record, decoded in a worker
])
def test_bad_data_stops_the_run_with_one_line_and_exit_2(dataset, tmp_path, monkeypatch, capsys, bad, verify,
                                                         workers):
    """These were a traceback and exit 1 (from a worker: a message holding the worker's traceback); the README
    promises one ``error:`` line naming the file and the reason, and exit 2. A run that met the bad data during
    training stopped at that step, before its update: no metrics line, no checkpoint after it."""
    manifest = copy_dataset(dataset, tmp_path / "data")
    run = tmp_path / "run"
    overrides = resume_overrides(manifest, run, f"data.verify={verify}", f"data.num_workers={workers}")
    if bad == "count":
        shard = overcount_shard(manifest)
        says = (f"{shard}: bad shard (record count: holds 10 records, manifest says 11)" if verify == "strict"
                else f"{shard}: holds 10 records where the manifest says 11")
    else:
        # due at step 4; not the batch's first record, which the batcher reads with the batch before
        bad_id = planned_batches(manifest, overrides)[3][1]
        write_nan_into(manifest, bad_id)
        says = f"{shard_of(manifest, bad_id)}: record '{bad_id}': features contain NaN or inf"

    assert fit(monkeypatch, overrides) == 2
    assert says in one_error_line(capsys)
    if verify == "strict" and bad == "count":
        assert not (run / "metrics.jsonl").exists() and complete_steps(run) == []  # refused before training
        return
    logged = sorted(metrics_by_step(run))
    stopped_at = logged[-1] + 1
    assert logged == list(range(1, stopped_at)) and stopped_at <= MAX_STEPS
    assert all(step < stopped_at for step in complete_steps(run))
    if bad == "nan":
        assert stopped_at == 4  # the bad record's step: the worker's error comes in that batch's place


def test_deferred_bad_record_stops_the_run_during_the_next_step(dataset, tmp_path, monkeypatch, capsys):
    """train.step_sync=deferred: the bad record's step (3, neither a log nor a save step) skips its update on the
    device; the host reads its flag during step 4 and stops there with the same one line and exit 2, before step
    4's update and its log line."""
    manifest = copy_dataset(dataset, tmp_path / "data")
    run = tmp_path / "run"
    overrides = resume_overrides(manifest, run, "data.verify=strict", "data.num_workers=0",
                                 "train.step_sync=deferred", "train.log_every=4")
    bad_id = planned_batches(manifest, overrides)[2][1]  # due at step 3
    write_nan_into(manifest, bad_id)
    assert fit(monkeypatch, overrides) == 2
    assert f"{shard_of(manifest, bad_id)}: record '{bad_id}': features contain NaN or inf" in one_error_line(capsys)
    assert not (run / "metrics.jsonl").exists() or metrics_by_step(run) == {}
    assert complete_steps(run) == []


@pytest.mark.parametrize("stop", ["bad_record_in_a_worker", "nonfinite_budget"])
def test_a_run_stopped_by_an_error_leaves_no_worker_process_behind(dataset, tmp_path, monkeypatch, stop):
    """The error that stops the run is raised while its traceback, and the trainer that may store it, still hold the
    batch stream: the stream drops its DataLoader when it raises (a worker's non-finite record), and fit() closes it
    whatever else ended training (here the non-finite budget, raised by the trainer itself), so the worker
    processes are gone when the error leaves fit, not when the error is collected (seen in this suite: 10-14 s
    later, a join of abandoned workers inside some other test)."""
    import multiprocessing

    from test_trainer import NaNAtSteps

    from pipeline.data.stages import DataError
    from pipeline.distributed import Dist
    from pipeline.training.trainer import NonFiniteLossError

    manifest = copy_dataset(dataset, tmp_path / "data")
    overrides = resume_overrides(manifest, tmp_path / "run", "data.verify=off", "data.num_workers=2",
                                 "train.nonfinite_budget=1")
    if stop == "bad_record_in_a_worker":
        write_nan_into(manifest, planned_batches(manifest, overrides)[3][1])  # due at step 4
        error, says = DataError, "features contain NaN or inf"
    else:
        patch_loss(monkeypatch, NaNAtSteps({2, 3}))
        error, says = NonFiniteLossError, "2 consecutive skipped steps exceed train.nonfinite_budget=1"
    before = set(multiprocessing.active_children())
    with Dist(cpu=True) as dist:
        trainer = Trainer(load_config(TrainConfig, "tiny", overrides), dist)
        with pytest.raises(error, match=says) as caught:
            trainer.fit()
        assert caught.value.__traceback__ is not None and trainer.step == 3  # all of it still alive here
        assert set(multiprocessing.active_children()) - before == set()
