"""A non-editable install carries what a user needs: the presets (package data), the licence and a console script
per entry point, and runs from any folder (not only from a checkout)."""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = {"mfm-build-shards", "mfm-train", "mfm-sample", "mfm-evaluate", "mfm-train-evaluator", "mfm-contact-sheet",
           "mfm-convert-checkpoint", "mfm-export", "mfm-browse"}


@pytest.mark.slow
def test_a_wheel_install_has_the_presets_licence_and_console_scripts(tmp_path):
    # Built like CI's install (isolated build environment from the package index); no dependencies fetched.
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path / "dist"),
                    str(REPO_ROOT)], check=True, capture_output=True, text=True)
    (wheel,) = (tmp_path / "dist").glob("*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    presets = {p.relative_to(REPO_ROOT).as_posix() for p in (REPO_ROOT / "configs").rglob("*.yaml")}
    assert presets and presets <= names
    assert any(n.endswith("licenses/LICENSE") for n in names)
    entry_points = zipfile.ZipFile(wheel).read(next(n for n in names if n.endswith("entry_points.txt"))).decode()
    assert SCRIPTS <= {line.split(" = ")[0] for line in entry_points.splitlines() if " = " in line}

    site = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-compile", "-q", "--target", str(site),
                    str(wheel)], check=True, capture_output=True, text=True)
    env = {**os.environ, "PYTHONPATH": str(site), "OMP_NUM_THREADS": "1"}
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    loaded = subprocess.run(
        [sys.executable, "-c", "import pipeline.config as c; "
         "print(c.__file__); print(c.load_config(c.TrainConfig, 'tiny').model.num_layers)"],
        cwd=elsewhere, env=env, check=True, capture_output=True, text=True).stdout.split()
    assert loaded[0].startswith(str(site)) and int(loaded[1]) >= 1  # the installed copy found its presets
    help_text = subprocess.run([str(site / "bin" / "mfm-train"), "--help"], cwd=elsewhere, env=env, check=True,
                               capture_output=True, text=True).stdout
    assert "tiny" in help_text and "humanml3d" in help_text  # the presets it lists are the installed ones
