"""Every entry point behaves like a command-line tool: settings it refuses are one line on stderr and exit 2 (no
traceback), the output folder is ``--out`` everywhere, ``--help`` lists presets that run, ``--print-config`` shows
every key with its value, default and meaning."""

from __future__ import annotations

import subprocess
import sys
from concurrent.futures import Future
from functools import partial
from pathlib import Path

import pytest
from conftest import load_launch_script, start_two_at_a_time

REPO_ROOT = Path(__file__).resolve().parents[1]


def run(script: str, *args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(REPO_ROOT / script), *args], capture_output=True, text=True,
                          cwd=cwd, env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin", "HF_HUB_OFFLINE": "1"},
                          timeout=300)


REFUSALS = [
    ("launch/train.py", ["train.nope=1"], "unknown config key 'train.nope'"),
    ("launch/train.py", ["data.manifest=/nonexistent/manifest.json", "--out", "{tmp}/run"], "no manifest"),
    ("launch/evaluate.py", ["--checkpoint", "/nonexistent", "--protocol", "fast"], "no checkpoint or run folder"),
    ("launch/evaluate.py", ["--checkpoint", "x", "sampling.steps=abc"], "sampling.steps: expected a list"),
    ("launch/train_evaluator.py", ["data.manifest=/nonexistent/m.json"], "no manifest"),
    ("launch/sample.py", ["--checkpoint", "/nonexistent", "--text", "hi", "--out", "{tmp}/s"], "no checkpoint"),
    ("launch/contact_sheet.py", ["--checkpoint", "/nonexistent", "--text", "hi", "--out", "{tmp}/c.png"],
     "no checkpoint"),
    ("preprocess/build_shards.py", ["--source", "humanml3d", "--root", "/nonexistent", "--out", "{tmp}/d"],
     "root folder /nonexistent does not exist"),
    ("launch/export.py", ["/nonexistent", "--out", "{tmp}/e"], "no checkpoint or run folder"),
    ("launch/convert_checkpoint.py", ["--from", "mfm", "/nonexistent.pt", "--dataset", "humanml3d", "--out",
                                      "{tmp}/m"], "no such checkpoint file"),
]


@pytest.fixture(scope="module")
def refused_launches(tmp_path_factory) -> dict[tuple[str, ...], Future]:
    """Every case of REFUSALS launched at the first case's test (start_two_at_a_time: each is a single-threaded
    Python start of a few seconds). Keyed by script and arguments; each case's folder ({tmp}) is its own."""
    root = tmp_path_factory.mktemp("refusals")
    return start_two_at_a_time({(script, *args): partial(run, script, *[a.replace("{tmp}", str(root / f"case{i}"))
                                                                       for a in args])
                                for i, (script, args, _) in enumerate(REFUSALS)})


@pytest.mark.slow
@pytest.mark.parametrize("script, args, says", REFUSALS)
def test_refused_settings_are_one_line_and_exit_2(script, args, says, refused_launches):
    result = refused_launches[(script, *args)].result()
    err = [line for line in result.stderr.splitlines() if " INFO " not in line and not line.startswith("INFO")]
    assert result.returncode == 2, result.stderr
    assert len(err) == 1 and says in err[0] and "Traceback" not in result.stderr, result.stderr


def test_help_lists_the_presets_that_run_and_print_config_documents_every_key(capsys):
    train = load_launch_script("train").main
    with pytest.raises(SystemExit):
        train(["--help"])
    help_text = capsys.readouterr().out
    assert "tiny" in help_text and "humanml3d" in help_text and "eval_fast" not in help_text  # not a training preset
    assert train(["--config", "tiny", "--print-config", "--out", "runs/x", "model.num_layers=3"]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert any(line.startswith("train.out_dir = runs/x  (default: runs/default)") for line in printed)
    layers = next(line for line in printed if line.startswith("model.num_layers = 3"))
    assert "(default: 8)" in layers
    assert any(line.startswith("optim.lr = ") and "#" in line for line in printed)  # with its doc line
    evaluate = load_launch_script("evaluate").main
    assert evaluate(["--print-config", "--protocol", "fast", "--out", "ev"]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert any(line.startswith("output.dir = ev") for line in printed)
    assert any(line.startswith("protocol.replications = 3") for line in printed)
