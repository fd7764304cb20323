"""Training people can watch (issue 18, item 6): TensorBoard event files beside metrics.jsonl, the validation loss
every train.val_every steps (deterministic, all-reduced, without touching the training streams), and loss.png
when a run ends. Tiny in-process runs (the tiny preset, 6 steps, about a second each); the 2-rank agreement of
the validation loss is in test_trainer_multirank.py."""

from __future__ import annotations

import json
import logging
import struct
import sys
import types
from pathlib import Path

import pytest
from conftest import flip_byte, load_launch_script
from test_trainer import assert_identical, build_dataset_once, metrics_by_step
from test_trainer_bad_data import copy_dataset

import pipeline.training.reporting as reporting
from mfm.flops import TrainingFlops
from mfm.model import ModelConfig
from pipeline import checkpoint as ckpt
from pipeline.config import ConfigError, TrainConfig, load_config, wandb_mode
from pipeline.data.stream import ShardVerificationError
from pipeline.distributed import Dist
from pipeline.evaluation.store import log_to_wandb
from pipeline.training.trainer import Trainer
from preprocess.shards import derive_dataset_id

STEPS = 6
VAL_EVERY = 2


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return build_dataset_once(tmp_path_factory)


def fit(dataset: Path, run: Path, *overrides: str) -> Path:
    cfg = load_config(TrainConfig, "tiny", [f"data.manifest={dataset}", f"train.out_dir={run}", "train.log_every=1",
                                            f"train.max_steps={STEPS}", f"train.save_every={STEPS}", *overrides])
    with Dist(mixed_precision="no", cpu=True) as dist:
        assert Trainer(cfg, dist).fit() == 0
    return run


@pytest.fixture(scope="module")
def runs(dataset, tmp_path_factory) -> dict[str, Path]:
    """Two identical runs validating every 2 steps, and the same run without validation."""
    root = tmp_path_factory.mktemp("train-logging")
    return {
        "val": fit(dataset, root / "val", f"train.val_every={VAL_EVERY}"),
        "val_again": fit(dataset, root / "val_again", f"train.val_every={VAL_EVERY}"),
        "no_val": fit(dataset, root / "no_val", "train.val_every=0"),
    }


def scalars(run: Path) -> dict[str, list[tuple[int, float]]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    folder = run / reporting.TENSORBOARD_SUBDIR
    assert list(folder.glob("events.out.tfevents.*")), f"no TensorBoard event file in {folder}"
    accumulator = EventAccumulator(str(folder))
    accumulator.Reload()
    return {tag: [(e.step, e.value) for e in accumulator.Scalars(tag)] for tag in accumulator.Tags()["scalars"]}


# ---------------------------------------------------------------------------------------------------------------
# Validation loss
# ---------------------------------------------------------------------------------------------------------------


def test_val_loss_is_logged_at_every_multiple_of_val_every(runs):
    metrics = metrics_by_step(runs["val"])  # one line per step: train and val records of a step are one line
    assert sorted(metrics) == list(range(1, STEPS + 1))
    val_steps = [step for step, record in metrics.items() if "val_loss" in record]
    assert val_steps == list(range(VAL_EVERY, STEPS + 1, VAL_EVERY))
    for step in val_steps:
        record = metrics[step]
        assert record["val_loss"] > 0 and record["val_weights"] == "ema"
        assert record["val_samples"] == 3  # the whole (3-motion) val split of the test dataset, in one batch
        assert record["loss"] is not None  # the step's train entries are on the same line
    assert len({metrics[s]["val_loss"] for s in val_steps}) == len(val_steps)  # the weights change between them


def test_val_loss_is_deterministic(runs):
    a, b = metrics_by_step(runs["val"]), metrics_by_step(runs["val_again"])
    assert [a[s].get("val_loss") for s in a] == [b[s].get("val_loss") for s in b]


def test_validation_does_not_change_training(runs):
    """Same losses, gradient norms and final weights, EMA, optimizer and RNG state (bit for bit) with and
    without validation: it draws from streams of its own and leaves the weights and the data order alone."""
    with_val, without = metrics_by_step(runs["val"]), metrics_by_step(runs["no_val"])
    for key in ("loss", "grad_norm", "lr", "samples_seen"):
        assert [with_val[s][key] for s in with_val] == [without[s][key] for s in without], key
    assert not any("val_loss" in record for record in without.values())
    final = ckpt.step_dir_name(STEPS)
    model_a, ema_a, state_a = ckpt.load_checkpoint(ckpt.checkpoints_dir(runs["val"]) / final)
    model_b, ema_b, state_b = ckpt.load_checkpoint(ckpt.checkpoints_dir(runs["no_val"]) / final)
    assert_identical(model_a, model_b, "model")
    assert_identical(ema_a, ema_b, "ema")
    for key in ("optimizer", "rng", "data"):
        assert_identical(state_a[key], state_b[key], key)


def test_raw_weights_are_validated_on_request(dataset, runs, tmp_path):
    run = fit(dataset, tmp_path / "raw", f"train.val_every={VAL_EVERY}", "train.val_weights=model")
    raw, ema = metrics_by_step(run), metrics_by_step(runs["val"])
    assert [raw[s]["loss"] for s in raw] == [ema[s]["loss"] for s in ema]
    assert raw[VAL_EVERY]["val_weights"] == "model" and raw[VAL_EVERY]["val_loss"] != ema[VAL_EVERY]["val_loss"]


def test_a_manifest_without_val_split_skips_validation_with_one_line(dataset, tmp_path, caplog):
    manifest = copy_dataset(dataset, tmp_path / "data")
    data = json.loads(manifest.read_text())
    del data["splits"]["val"]
    data["dataset_id"] = derive_dataset_id(data)  # a dataset built without one
    manifest.write_text(json.dumps(data))
    with caplog.at_level(logging.INFO):
        run = fit(manifest, tmp_path / "run", f"train.val_every={VAL_EVERY}")
    lines = [r.getMessage() for r in caplog.records if "validation off" in r.getMessage()]
    assert len(lines) == 1 and "no 'val' split" in lines[0]
    metrics = metrics_by_step(run)
    assert sorted(metrics) == list(range(1, STEPS + 1)) and not any("val_loss" in r for r in metrics.values())


def corrupt_val_shard(dataset: Path, to: Path) -> tuple[Path, str]:
    manifest = copy_dataset(dataset, to)
    shard = json.loads(manifest.read_text())["splits"]["val"]["shards"][0]
    shard_path = shard if isinstance(shard, str) else shard["path"]
    flip_byte(manifest.parent / shard_path, 600)
    return manifest, shard_path


def test_a_bad_val_shard_is_refused_before_step_1_in_strict_mode(dataset, tmp_path):
    manifest, shard = corrupt_val_shard(dataset, tmp_path / "data")
    with pytest.raises(ShardVerificationError, match=shard):
        fit(manifest, tmp_path / "run", f"train.val_every={VAL_EVERY}")
    assert not (tmp_path / "run" / "metrics.jsonl").exists()


@pytest.mark.parametrize("damage, verify", [("flipped byte", "strict"), ("record count", "off")])
def test_a_bad_val_shard_through_the_script_is_one_line_and_exit_2(dataset, tmp_path, capsys, damage, verify):
    """Issue 24, item 9: was a traceback and exit 1. Strict verification finds a flipped byte; without it, reading
    the val batches finds a shard holding fewer records than the manifest says. Either way before step 1, and
    nothing in the run folder is written."""
    if damage == "flipped byte":
        manifest, shard = corrupt_val_shard(dataset, tmp_path / "data")
    else:
        manifest = copy_dataset(dataset, tmp_path / "data")
        data = json.loads(manifest.read_text())
        entry = data["splits"]["val"]["shards"][0]
        entry["num_motions"] += 1
        manifest.write_text(json.dumps(data, indent=1))
        shard = entry["path"]
    run = tmp_path / "run"
    code = load_launch_script("train").main(["--config", "tiny", f"data.manifest={manifest}", f"train.out_dir={run}",
                                             f"train.val_every={VAL_EVERY}", f"data.verify={verify}"])
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("error: ")]
    assert code == 2 and len(errors) == 1 and "Traceback" not in err, err
    assert shard in errors[0]
    assert not run.exists() or not any(run.iterdir())


def test_a_bad_val_shard_is_left_out_in_tolerant_mode(dataset, tmp_path, caplog):
    manifest, _ = corrupt_val_shard(dataset, tmp_path / "data")
    with caplog.at_level(logging.INFO):
        run = fit(manifest, tmp_path / "run", f"train.val_every={VAL_EVERY}", "data.verify=tolerant")
    assert "validation off" in caplog.text and "no usable motion" in caplog.text  # its only shard was bad
    assert sorted(metrics_by_step(run)) == list(range(1, STEPS + 1))


# ---------------------------------------------------------------------------------------------------------------
# What the run trained on: every file of the split accounted for, the dataset id derived (issue 24, items 1 and 7)
# ---------------------------------------------------------------------------------------------------------------


def without_last_train_shard(dataset: Path, to: Path) -> tuple[Path, list[str]]:
    """A copy whose manifest no longer lists the last train shard (tar and Parquet entries), with its totals and
    lengths made to agree and its dataset id left as it was; the files stay in train/."""
    manifest = copy_dataset(dataset, to)
    data = json.loads(manifest.read_text())
    train = data["splits"]["train"]
    dropped = [train["shards"].pop(), train["parquet"].pop()]
    kept = train["num_motions"] - dropped[0]["num_motions"]
    train["lengths"] = train["lengths"][:kept]
    train["num_motions"], train["num_frames"] = kept, sum(train["lengths"])
    manifest.write_text(json.dumps(data))
    return manifest, sorted(entry["path"] for entry in dropped)


def test_an_unlisted_train_shard_stops_strict_training_in_one_line(dataset, tmp_path, capsys):
    manifest, dropped = without_last_train_shard(dataset, tmp_path / "data")
    run = tmp_path / "run"
    code = load_launch_script("train").main(["--config", "tiny", f"data.manifest={manifest}", f"train.out_dir={run}"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and f"the manifest does not list ({', '.join(dropped)})" in err[0], err
    assert not (run / "metrics.jsonl").exists()


def test_tolerant_training_reports_unlisted_shards_and_records_the_derived_dataset_id(dataset, tmp_path):
    """Issue 24.1: the run trained on fewer clips than the folder holds while shard_report.json said verified: true,
    and its checkpoints carried the id the manifest claimed."""
    manifest, dropped = without_last_train_shard(dataset, tmp_path / "data")
    stored = json.loads(manifest.read_text())["dataset_id"]
    run = fit(manifest, tmp_path / "run", "data.verify=tolerant")
    report = json.loads((run / "shard_report.json").read_text())
    assert report["verified"] is False and report["unlisted_files"] == dropped and report["unlisted_files_checked"]
    assert report["dataset_id"] != stored and any("not the id derived" in p for p in report["manifest_problems"])
    _, _, state = ckpt.load_checkpoint(ckpt.checkpoints_dir(run) / ckpt.step_dir_name(STEPS))
    assert state["manifest"]["dataset_id"] == report["dataset_id"]


def test_a_train_shard_outside_the_manifests_folder_is_read_only_when_allowed(dataset, tmp_path, capsys):
    """Issue 24.7: a shard path may not leave the manifest's folder (here an absolute path) unless
    data.allow_external_shards=true."""
    manifest = copy_dataset(dataset, tmp_path / "data")
    data = json.loads(manifest.read_text())
    entry = data["splits"]["train"]["shards"][0]
    outside = tmp_path / "elsewhere" / "shard.tar"
    outside.parent.mkdir()
    (manifest.parent / entry["path"]).rename(outside)
    entry["path"] = str(outside)
    data["dataset_id"] = derive_dataset_id(data)
    manifest.write_text(json.dumps(data))
    args = ["--config", "tiny", f"data.manifest={manifest}", f"train.out_dir={tmp_path / 'run'}"]
    assert load_launch_script("train").main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"shard path '{outside}' is absolute" in err[0] and "data.allow_external_shards" in err[0]
    run = fit(manifest, tmp_path / "allowed", "data.allow_external_shards=true")
    assert json.loads((run / "shard_report.json").read_text())["verified"] is True


# ---------------------------------------------------------------------------------------------------------------
# W&B: an explicit mode wins over WANDB_MODE (issue 24, item 9)
# ---------------------------------------------------------------------------------------------------------------


class FakeWandb(types.ModuleType):
    """Stands in for the wandb package (not a dependency): records the mode of every run started, and makes the
    wandb folder the real package would."""

    def __init__(self) -> None:
        super().__init__("wandb")
        self.modes: list[str] = []

    def init(self, *, mode: str, dir: str, **settings):  # wandb.init's own argument names
        self.modes.append(mode)
        (Path(dir) / "wandb").mkdir(exist_ok=True)
        run = types.SimpleNamespace(config=types.SimpleNamespace(update=lambda *a, **k: None))
        run.log = run.define_metric = run.finish = lambda *a, **k: None
        return run


@pytest.fixture
def fake_wandb(monkeypatch) -> FakeWandb:
    fake = FakeWandb()
    monkeypatch.setitem(sys.modules, "wandb", fake)
    monkeypatch.delenv("WANDB_MODE", raising=False)
    monkeypatch.delenv("WANDB_DIR", raising=False)
    return fake


@pytest.mark.parametrize("setting, environment, used", [
    ("disabled", "offline", None),  # was: the environment's offline, and a wandb folder in the run
    ("offline", "disabled", "offline"),
    ("auto", "online", "online"),  # auto (the default) follows WANDB_MODE ...
    ("auto", None, "offline"),  # ... else offline, as before
])
def test_an_explicit_train_wandb_wins_over_wandb_mode(fake_wandb, tmp_path, monkeypatch, setting, environment,
                                                      used):
    if environment is not None:
        monkeypatch.setenv("WANDB_MODE", environment)
    run = tmp_path / "run"
    run.mkdir()
    cfg = load_config(TrainConfig, "tiny", [f"train.out_dir={run}", f"train.wandb={setting}",
                                            "train.tensorboard=false"])
    with Dist(mixed_precision="no", cpu=True) as dist:
        reporting.MetricsSink(run, cfg, dist, ModelConfig(), num_parameters=0).close()
    assert fake_wandb.modes == ([used] if used else [])
    assert (run / "wandb").exists() == bool(used)


def test_an_explicit_evaluation_wandb_wins_over_wandb_mode(fake_wandb, tmp_path, monkeypatch):
    """The evaluator's output.wandb: the same rule; auto follows WANDB_MODE, else the training run's mode."""
    monkeypatch.setenv("WANDB_MODE", "offline")
    assert not log_to_wandb(tmp_path, wandb_mode("disabled"), "mfm", 4, {"fid": 1.0}, {})
    assert fake_wandb.modes == [] and not (tmp_path / "wandb").exists()
    assert wandb_mode("auto", fallback=wandb_mode("disabled")) == "offline"  # the environment's, for auto
    monkeypatch.delenv("WANDB_MODE")
    assert wandb_mode("auto", fallback=wandb_mode("disabled")) == "disabled"  # the training run's
    assert wandb_mode("auto", fallback=wandb_mode("auto")) == "offline"
    assert log_to_wandb(tmp_path, wandb_mode("online"), "mfm", 4, {"fid": 1.0}, {})
    assert fake_wandb.modes == ["online"]


# ---------------------------------------------------------------------------------------------------------------
# Model FLOPs, MFU and padding (issue 26)
# ---------------------------------------------------------------------------------------------------------------


def batches_of(dataset: Path, run: Path, *overrides: str) -> tuple[list[dict], TrainingFlops]:
    """The STEPS batches a run of these settings trains on, read by a Trainer's own loader (not fitted), and that
    trainer's FLOP count."""
    cfg = load_config(TrainConfig, "tiny", [f"data.manifest={dataset}", f"train.out_dir={run}", *overrides])
    with Dist(mixed_precision="no", cpu=True) as dist:
        trainer = Trainer(cfg, dist)
        stream = trainer.loader.iter_batches()
        try:
            return [next(stream) for _ in range(STEPS)], trainer.training_flops
        finally:
            stream.close()


@pytest.mark.parametrize("batching", ["fixed", "length_aware"])
def test_each_log_line_has_the_model_flops_of_its_batches_their_padding_and_no_mfu_on_a_cpu(dataset, tmp_path,
                                                                                         batching):
    overrides = ("train.val_every=0", f"data.batching={batching}", "data.window=196")  # clips of 40-196 frames
    run = fit(dataset, tmp_path / "run", *overrides)
    batches, flops = batches_of(dataset, tmp_path / "probe", *overrides)
    metrics = metrics_by_step(run)
    for step, batch in zip(sorted(metrics), batches, strict=True):
        record = metrics[step]  # one batch per line (train.log_every=1)
        rows, width = batch["features"].shape[:2]
        # both rates share the line's elapsed time, so their ratio is the batch's FLOPs per sample
        assert record["model_tflops"] * 1e12 / record["samples_per_s"] == pytest.approx(flops.per_sample(width))
        assert record["padding_frac"] == pytest.approx(1 - batch["lengths"].sum().item() / (rows * width))
        assert record["mfu"] is None  # a CPU has no dense bf16 peak
    widths = {batch["features"].shape[1] for batch in batches}
    assert (len(widths) > 1) == (batching == "length_aware"), widths  # length-aware batches meet several widths


def test_mfu_is_the_logged_model_flops_over_the_devices_peak(dataset, tmp_path, monkeypatch):
    import pipeline.training.trainer as trainer_module
    from mfm.flops import PeakLookup

    monkeypatch.setattr(trainer_module, "device_peak", lambda device: PeakLookup(0.002, "a 2 GFLOP/s test device"))
    metrics = metrics_by_step(fit(dataset, tmp_path / "run", "train.val_every=0"))
    for record in metrics.values():
        assert record["mfu"] == pytest.approx(record["model_tflops"] / 0.002) and record["mfu"] > 0


# ---------------------------------------------------------------------------------------------------------------
# TensorBoard
# ---------------------------------------------------------------------------------------------------------------


def test_tensorboard_holds_the_scalars_of_metrics_jsonl(runs):
    metrics = metrics_by_step(runs["val"])
    events = scalars(runs["val"])
    for key in ("loss", "grad_norm", "lr", "samples_per_s", "samples_seen"):
        logged = events[f"train/{key}"]
        assert [step for step, _ in logged] == list(range(1, STEPS + 1)), key
        assert [value for _, value in logged] == pytest.approx([metrics[s][key] for s in metrics], rel=1e-6), key
    val = events["val/loss"]
    assert [step for step, _ in val] == list(range(VAL_EVERY, STEPS + 1, VAL_EVERY))
    assert [value for _, value in val] == pytest.approx([metrics[s]["val_loss"] for s, _ in val], rel=1e-6)
    assert "val/loss" not in scalars(runs["no_val"])


def test_tensorboard_can_be_turned_off(dataset, tmp_path):
    run = fit(dataset, tmp_path / "run", "train.tensorboard=false")
    assert not (run / reporting.TENSORBOARD_SUBDIR).exists()


def test_tensorboard_without_its_package_is_refused_before_training(dataset, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(reporting, "tensorboard_available", lambda: False)
    train_entry = load_launch_script("train")
    run = tmp_path / "run"
    code = train_entry.main(["--config", "tiny", f"data.manifest={dataset}", f"train.out_dir={run}"])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "train.tensorboard=false" in err[0] and "pip install tensorboard" in err[0]
    assert not run.exists()


def test_scalar_tags():
    record = {"step": 4, "loss": 1.5, "grad_norm": None, "epoch": 0, "val_loss": 2.0, "val_weights": "ema",
              "val_samples": 3, "nan": float("nan"), "flag": True}
    assert reporting.scalar_tags(record) == {"train/loss": 1.5, "train/epoch": 0.0, "val/loss": 2.0,
                                                 "val/samples": 3.0}


# ---------------------------------------------------------------------------------------------------------------
# loss.png
# ---------------------------------------------------------------------------------------------------------------


def png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR", f"{path} is not a PNG"
    return struct.unpack(">II", data[16:24])


def test_loss_png_is_written_when_the_run_ends(runs):
    for name in ("val", "no_val"):
        png = runs[name] / reporting.LOSS_PLOT
        width, height = png_size(png)
        assert width >= 400 and height >= 300 and png.stat().st_size > 10_000


def test_loss_plot_reads_the_whole_metrics_file(tmp_path):
    """Many points over decades (log scale, a smoothed line), val points, a torn last line; nothing to plot yet
    gives no file."""
    metrics = tmp_path / "metrics.jsonl"
    lines = [json.dumps({"step": s, "loss": 10.0 / s, **({"val_loss": 12.0 / s} if s % 20 == 0 else {})})
             for s in range(1, 201)]
    metrics.write_text("\n".join(lines) + '\n{"step": 201, "lo')
    png = reporting.write_loss_plot(metrics, tmp_path / "loss.png")
    assert png == tmp_path / "loss.png" and png_size(png)[0] >= 400
    assert not list(tmp_path.glob(".*.png"))  # written atomically, no temporary file left
    metrics.write_text(json.dumps({"step": 1, "loss": None}) + "\n")
    assert reporting.write_loss_plot(metrics, tmp_path / "none.png") is None
    assert not (tmp_path / "none.png").exists()


def test_a_plotting_failure_is_logged_and_never_fatal(dataset, tmp_path, monkeypatch, caplog):
    def broken(*args, **kwargs):
        raise RuntimeError("no fonts")

    monkeypatch.setattr(reporting, "write_loss_plot", broken)
    with caplog.at_level(logging.WARNING):
        run = fit(dataset, tmp_path / "run")
    assert "could not draw" in caplog.text and "no fonts" in caplog.text
    assert sorted(metrics_by_step(run)) == list(range(1, STEPS + 1))


# ---------------------------------------------------------------------------------------------------------------
# Settings
# ---------------------------------------------------------------------------------------------------------------


def test_settings_are_typed_and_checked():
    cfg = load_config(TrainConfig, "tiny", ["train.val_every=100", "train.val_batches=4", "train.val_weights=model",
                                            "train.tensorboard=false"])
    assert (cfg.train.val_every, cfg.train.val_batches, cfg.train.val_weights, cfg.train.tensorboard) == (
        100, 4, "model", False)
    defaults = TrainConfig().train
    assert (defaults.val_every, defaults.val_batches, defaults.val_weights, defaults.tensorboard) == (
        500, 16, "ema", True)
    for bad in ("train.val_every=-1", "train.val_batches=0", "train.val_weights=raw", "train.tensorboard=1"):
        with pytest.raises(ConfigError):
            load_config(TrainConfig, "tiny", [bad])
