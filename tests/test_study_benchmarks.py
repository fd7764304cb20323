"""benchmarks/synthetic_judge.py and benchmarks/root_mean_probe.py (the synthetic preset study's judge and probe) on the
session's tiny text checkpoint."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import load_benchmark
from test_sample_cli import text_run  # noqa: F401  (the session's tiny checkpoint, a fixture)


@pytest.mark.usefixtures("single_thread")
def test_the_judge_summarises_its_sheets_and_sweeps(text_run, tmp_path, capsys):  # noqa: F811
    """The summary's sheet figures are the sheets' own (one seed: equal); the jump sweep counts 3 captions × 2
    lengths, and its travel is the root's ground distance in the longest "3 times" motion as sampling makes it in
    the same batch; --steps, --guidance, --model-weights, --smoothing and --smoothing-keeps-bones reach every part."""
    judge = load_benchmark("synthetic_judge")
    from length_sweep import sample_joints

    out = tmp_path / "judge"
    assert judge.main(["--checkpoint", str(text_run), "--out", str(out), "--rows", "3", "--seeds", "1",
                       "--jump-lengths", "20,28", "--sweep-lengths", "20,32", "--steps", "2", "--guidance", "1.5", "--model-weights", "model",
                       "--smoothing", "0.6", "--smoothing-keeps-bones", "smoothed"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    whole_sheet = json.loads((out / "sheet-s1.json").read_text())
    assert (summary["guidance"], whole_sheet["guidance"], whole_sheet["steps"]) == (1.5, 1.5, 2)
    assert (summary["model_weights"], whole_sheet["weights"]) == ("model", "model")
    assert (summary["smoothing_keeps_bones"], whole_sheet["smoothing_keeps_bones"]) == ("smoothed", "smoothed")
    assert (summary["smoothing"], whole_sheet["smoothing_sigma"]) == (0.6, 0.6)
    sheet = whole_sheet["against_dataset_clips"]
    assert (out / "sheet-s1.png").stat().st_size > 0
    assert summary["sheet"]["caption_match"] == sheet["caption_match"]
    assert summary["sheet"]["bones_cm"] == pytest.approx(100 * sheet["plausibility"]["bone_length_range"]["generated"])
    assert summary["sheet"]["all_per_seed"] == [sheet["caption_checks"]["generated"]["all"]["share"]]
    jumps = summary["jump_sweep"]
    assert (jumps["of"], jumps["frames"], len(jumps["travel_m"])) == (6, 28, 1)
    cells = [(text, n) for text in judge.IN_PLACE_JUMPS for n in (20, 28)]  # each motion's noise: seed + its index
    motion = sample_joints(str(text_run), [t for t, _ in cells], [n for _, n in cells], 1,
                           {"device": "cpu", "weights": "model", "steps": 2, "guidance": 1.5,
                            "smoothing": 0.6, "smoothing_keeps_bones": "smoothed"})[-1]
    moved = motion[-1, 0] - motion[0, 0]
    assert jumps["travel_m"][0] == pytest.approx(float(np.hypot(moved[0], moved[2])), abs=1e-3)
    assert set(summary["length_sweep"]["turns_deg"]) == {f"{text} @{n}" for text in (
        "a person turns around to the left.", "a person turns 90 degrees to the left.") for n in (20, 32)}
    assert 0.0 <= summary["length_sweep"]["passed"] <= 1.0
    sweep_options = json.loads((out / "length_sweep.json").read_text())["options"]
    assert (sweep_options["guidance"], sweep_options["weights"], sweep_options["smoothing"],
            sweep_options["smoothing_keeps_bones"]) == (1.5, "model", 0.6, "smoothed")


@pytest.mark.usefixtures("single_thread")
def test_the_root_mean_probe_ends_on_the_last_euler_estimate(text_run, capsys):  # noqa: F811
    """With Euler steps the sample is the last step's x̂1 (x + (1 − t)·v), so the last two readings agree, at one
    step (the sample is x̂1 at t = 0) and at three; one line per caption with a reading per step and the sample."""
    probe = load_benchmark("root_mean_probe")
    for steps in (1, 3):
        capsys.readouterr()
        probe.main(["--checkpoint", str(text_run), "--text", "a person jumps up in place twice.", "--text",
                    "a person turns around to the left.", "--lengths", "24", "--seeds", "0,1",
                    "--steps", str(steps)])
        lines = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
        assert [line["text"] for line in lines] == ["a person jumps up in place twice.",
                                                    "a person turns around to the left."]
        for line in lines:
            assert len(line["forward_m_per_s"]) == len(line["heading_change_deg"]) == steps + 1
            assert line["times"][-1] == "sample" and len(line["sample_forward_m_per_s_by_seed"]) == 2
            assert line["forward_m_per_s"][-1] == pytest.approx(line["forward_m_per_s"][-2], abs=2e-3)
            assert line["heading_change_deg"][-1] == pytest.approx(line["heading_change_deg"][-2], abs=0.2)
            assert np.mean(line["sample_forward_m_per_s_by_seed"]) == pytest.approx(line["forward_m_per_s"][-1],
                                                                                    abs=2e-3)
