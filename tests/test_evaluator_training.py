"""Evaluator training (launch/train_evaluator.py, pipeline/evaluation/evaluator_training.py): it shows a progress
bar and says where its time went, and reading the next batch on a background thread (ReadAhead) leaves the trained
evaluator bit-identical to reading it in the loop."""

from __future__ import annotations

import json
import logging
import threading
from pathlib import Path

import pytest
from eval_worker import TINY_EVALUATOR, build_synthetic_dataset

import pipeline.evaluation.evaluator_training as evaluator_training
from pipeline.evaluation.evaluator_training import ReadAhead

STEPS = 8


@pytest.fixture(scope="module")
def manifest(tmp_path_factory) -> Path:
    return build_synthetic_dataset(tmp_path_factory.getbasetemp() / "eval-synthetic")


class InLoop:
    """What the loop did before ReadAhead: the loader's iterator, read on the training thread."""

    def __init__(self, source):
        self.source = source

    def __next__(self):
        return next(self.source)

    def close(self):
        self.source.close()


def train(manifest: Path, out: Path) -> dict:
    from launch.train_evaluator import main

    tiny = [f"model.{k}={v}" for k, v in TINY_EVALUATOR.items()]
    assert main([f"data.manifest={manifest}", f"out_dir={out}", f"optim.steps={STEPS}", "optim.log_every=4",
                 "data.batch_size=8", "data.window=64", "action_classifier=yes", *tiny,
                 "model.dropout=0.1"]) == 0  # dropout on: the global RNG is part of what must not change
    return json.loads((out / "report.json").read_text())


def test_progress_bar_timing_and_read_ahead_leave_the_evaluator_bit_identical(manifest, tmp_path, monkeypatch,
                                                                              capsys, caplog):
    caplog.set_level(logging.INFO, logger=evaluator_training.logger.name)
    report = train(manifest, tmp_path / "read-ahead")
    err = capsys.readouterr().err
    for phase in ("contrastive", "action classifier"):
        assert f"{phase}: 100%" in err and f"{STEPS}/{STEPS}" in err, err[-2000:]  # tqdm's bar, on stderr
        assert f"{phase}: {STEPS} steps in" in caplog.text and "s/step" in caplog.text  # the log line
    for phase in ("contrastive", "action_classifier"):
        timing = report["timing"][phase]
        assert timing["steps"] == STEPS and timing["s_per_step"] > 0 and 0 <= timing["data_wait_frac"] <= 1

    monkeypatch.setattr(evaluator_training, "ReadAhead", InLoop)
    train(manifest, tmp_path / "in-loop")
    for name in ("contrastive.safetensors", "action_classifier.safetensors"):
        assert (tmp_path / "read-ahead" / name).read_bytes() == (tmp_path / "in-loop" / name).read_bytes(), name


def test_read_ahead_yields_the_same_items_raises_their_errors_and_stops():
    assert list(ReadAhead(iter(range(50)))) == list(range(50))

    def failing():
        yield 1
        raise ValueError("bad shard x.tar")

    reader = ReadAhead(failing())
    assert next(reader) == 1
    with pytest.raises(ValueError, match="bad shard x.tar"):
        next(reader)

    closed = threading.Event()

    def endless():
        try:
            while True:
                yield 0
        finally:
            closed.set()

    reader = ReadAhead(endless())
    assert next(reader) == 0
    reader.close()  # the thread stops (it was blocked on a full queue) and the source is closed
    assert not reader._thread.is_alive() and closed.wait(5)


def test_attention_dropout_defaults_to_dropout_and_can_be_set_apart():
    import torch

    from mfm.evaluators import ContrastiveEvaluator, ContrastiveEvaluatorConfig

    sizes = {**TINY_EVALUATOR, "feature_dim": 12, "text_dim": 8}
    sizes.pop("dropout", None)
    default = ContrastiveEvaluator(ContrastiveEvaluatorConfig(**sizes, dropout=0.2))
    fast = ContrastiveEvaluator(ContrastiveEvaluatorConfig(**sizes, dropout=0.2, attention_dropout=0.0))
    for model, attention in ((default, 0.2), (fast, 0.0)):
        for layer in model.motion_encoder.transformer.layers:
            assert layer.self_attn.dropout == attention and layer.dropout1.p == 0.2 and layer.dropout.p == 0.2
    # None builds exactly what the evaluators trained so far were built with: the same weights from the same seed
    torch.manual_seed(0)
    a = ContrastiveEvaluator(ContrastiveEvaluatorConfig(**sizes))
    torch.manual_seed(0)
    b = ContrastiveEvaluator(ContrastiveEvaluatorConfig(**sizes, attention_dropout=0.0))
    assert all(torch.equal(x, y) for x, y in zip(a.state_dict().values(), b.state_dict().values()))
    with pytest.raises(ValueError, match="attention_dropout"):
        ContrastiveEvaluatorConfig(**sizes, attention_dropout=1.0)
