"""benchmarks/length_sweep.py on the session's tiny text checkpoint: one JSON line per caption and length, whose
readings are the caption checks' of the motions launch/sample.py makes with the same seed."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import load_benchmark
from test_sample_cli import sample, text_run  # noqa: F401  (the session's tiny checkpoint, a fixture)

from mfm.caption_checks import check_caption


def length_sweep():
    return load_benchmark("length_sweep")


@pytest.mark.usefixtures("single_thread")
def test_sweep_reads_each_length_and_seed_as_sampling_does(text_run, tmp_path, capsys):  # noqa: F811
    texts = ["a person turns around to the left.", "a person jumps up in place twice."]
    out = tmp_path / "sweep.json"
    assert length_sweep().main(["--checkpoint", str(text_run), "--text", texts[0], "--text", texts[1],
                                "--lengths", "20,32", "--seeds", "0,1", "--steps", "2", "--out", str(out)]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    assert [(line["text"], line["frames"]) for line in lines] == [(t, n) for t in texts for n in (20, 32)]
    assert all(len(line["shown"]) == 2 for line in lines) and lines[0]["shown"][0].endswith("°")
    rows = json.loads(out.read_text())["rows"]
    # Seed 1's reading of the turn at 32 frames is the caption check of the motion sample.py makes for the same
    # prompts, lengths and seed.
    results = sample(text_run, tmp_path / "s1", "--text", texts[0], "--text", texts[0], "--text", texts[1],
                     "--text", texts[1], "--length", "20", "--length", "32", "--length", "20", "--length", "32",
                     "--seed", "1", "--steps", "2", "--no-video", "--no-bvh")
    joints = [np.load(tmp_path / "s1" / f["path"]) for s in results["samples"] for f in s["files"]
              if f["kind"] == "joints"]
    assert rows[1]["observed"][1] == check_caption(joints[1], texts[0])["observed"]
    assert isinstance(rows[1]["observed"][1]["heading_change_deg"], float)


@pytest.mark.usefixtures("single_thread")
def test_sweep_samples_the_raw_weights_when_asked(text_run, tmp_path, capsys):  # noqa: F811
    text = "a person jumps up in place twice."
    out = tmp_path / "sweep.json"
    assert length_sweep().main(["--checkpoint", str(text_run), "--text", text, "--lengths", "24", "--seeds", "0",
                                "--steps", "2", "--model-weights", "model", "--out", str(out)]) == 0
    written = json.loads(out.read_text())
    assert written["options"]["weights"] == "model"
    joints = {}
    for weights in ("model", "ema"):
        results = sample(text_run, tmp_path / weights, "--text", text, "--length", "24", "--seed", "0",
                         "--steps", "2", "--model-weights", weights, "--no-video", "--no-bvh")
        joints[weights] = [np.load(tmp_path / weights / f["path"]) for s in results["samples"] for f in s["files"]
                           if f["kind"] == "joints"][0]
    # The raw and the EMA weights make different motions, and the sweep read the raw one's.
    assert not np.allclose(joints["model"], joints["ema"])
    assert written["rows"][0]["observed"][0] == check_caption(joints["model"], text)["observed"]
