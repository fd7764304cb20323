"""Samples while training (train.preview_every, pipeline/training/previews.py): rank 0's previews appear as PNGs in
the run folder, as a TensorBoard image and plausibility scalars, and in metrics.jsonl; and a run with previews on
is bit-identical to one with them off (weights, EMA, optimizer, RNG states, data position, per-step losses).

The runs compared bit for bit are separate processes (tests/trainer_worker.py), as in tests/test_trainer.py.
"""

from __future__ import annotations

import sys

import pytest
from test_trainer import (  # noqa: F401 - dataset is a fixture
    dataset,
    assert_runs_identical,
    base_overrides,
    fit_scenario,
    metrics_by_step,
    output_of,
    run_worker,
)

from pipeline.config import ConfigError, TrainLoopConfig
from pipeline.training import reporting
from pipeline.training.previews import PREVIEW_SUBDIR

STEPS, PREVIEW_EVERY = 4, 2
# Given prompts: the preview builds the dataset's text encoder (MiniLM), whose construction draws from the global
# torch RNG; the runs have dropout on, so a preview that left that draw behind would change the weights.
PROMPTS = "train.preview_prompts=[a person waves with the left hand, a person jumps forward]"


def tensorboard_events(run):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    accumulator = EventAccumulator(str(run / reporting.TENSORBOARD_SUBDIR), size_guidance={"images": 0})
    accumulator.Reload()
    return accumulator


@pytest.fixture(scope="module")
def runs(dataset, tmp_path_factory):
    root = tmp_path_factory.mktemp("previews")
    common = (f"train.max_steps={STEPS}", f"train.save_every={STEPS}", "model.dropout=0.1")
    scenarios = {
        "off": ("train.preview_every=0",),
        "captions": (f"train.preview_every={PREVIEW_EVERY}", "train.preview_count=3"),
        "prompts": (f"train.preview_every={PREVIEW_EVERY}", PROMPTS),
    }
    # One process runs the three (starting torch is most of the cost); every fit seeds itself afresh.
    proc = run_worker([sys.executable], [fit_scenario(root / name, base_overrides(dataset, root / name / "run",
                                                                                  *common, *extra))
                                         for name, extra in scenarios.items()], root / "spec")
    assert proc.returncode == 0, output_of(proc)
    return {name: root / name / "run" for name in scenarios}


@pytest.mark.parametrize("name", ["captions", "prompts"])
def test_previews_leave_training_bit_identical(runs, name):
    assert_runs_identical(runs["off"], runs[name], STEPS,
                          differing=("preview_every", "preview_count", "preview_prompts"))


@pytest.mark.parametrize("name", ["captions", "prompts"])
def test_previews_are_pngs_tensorboard_images_and_plausibility_scalars(runs, name):
    run = runs[name]
    steps = list(range(PREVIEW_EVERY, STEPS + 1, PREVIEW_EVERY))
    pngs = sorted((run / PREVIEW_SUBDIR).iterdir())
    assert [p.name for p in pngs] == [f"step-{s:08d}.png" for s in steps]
    assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in pngs)

    metrics = metrics_by_step(run)
    preview_steps = [s for s, record in metrics.items() if "preview_mean_jerk" in record]
    assert preview_steps == steps
    for step in steps:
        record = metrics[step]
        assert record["preview_pose_speed"] > 0 and 0 <= record["preview_foot_skating_ratio"] <= 1
        assert "loss" in record  # one line per step: the preview joins the step's train record

    events = tensorboard_events(run)
    images = events.Images(reporting.PREVIEW_IMAGE_TAG)
    assert [e.step for e in images] == steps and all(e.width > 0 and e.height > 0 for e in images)
    for tag in ("preview/mean_jerk", "preview/foot_skating_ratio", "preview/pose_speed"):
        assert [e.step for e in events.Scalars(tag)] == steps, tag
        assert [e.value for e in events.Scalars(tag)] == pytest.approx(
            [metrics[s][tag.replace("preview/", "preview_")] for s in steps])


def test_no_previews_when_off(runs):
    assert not (runs["off"] / PREVIEW_SUBDIR).exists()
    assert reporting.PREVIEW_IMAGE_TAG not in tensorboard_events(runs["off"]).Tags()["images"]
    assert not any(k.startswith("preview_") for r in metrics_by_step(runs["off"]).values() for k in r)


@pytest.mark.parametrize("fields, message", [
    ({"preview_every": -1}, "train.preview_every must be >= 0"),
    ({"preview_count": 0}, "train.preview_count must be >= 1"),
    ({"preview_prompts": ("a person walks", " ")}, "train.preview_prompts must be non-empty strings"),
])
def test_bad_preview_settings_are_refused(fields, message):
    with pytest.raises(ConfigError, match=message):
        TrainLoopConfig(**fields)


def test_previews_are_on_by_default():
    assert TrainLoopConfig().preview_every == 500 and TrainLoopConfig().preview_prompts == ()
