"""What an install holds: the library packages only (mfm, pipeline, preprocess; not the checkout's launch/ and
configs/, names many projects use), the presets as package data inside pipeline (pipeline/presets/, built from the
repository's configs/), the licence and a console script per command, pointing into the library; it runs from any
folder. A checkout (or an editable install of one) reads the repository's configs/, the folder users edit."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = {"mfm-build-shards", "mfm-train", "mfm-distill", "mfm-sample", "mfm-evaluate", "mfm-train-evaluator",
           "mfm-contact-sheet", "mfm-convert-checkpoint", "mfm-export", "mfm-browse"}
LIBRARY = ("mfm", "pipeline", "preprocess")
"""The installed top-level packages."""
PRESETS_PACKAGE = "pipeline.presets"
"""Where an install carries configs/ (pyproject.toml's package-dir)."""


def pyproject() -> dict:
    tomllib = pytest.importorskip("tomllib", reason="tomllib is Python 3.11+")
    return tomllib.loads((REPO_ROOT / "pyproject.toml").read_text(encoding="utf-8"))


def test_the_installed_packages_are_the_library_and_every_package_folder_of_it():
    """pyproject.toml lists its packages (so that configs/ can be installed as pipeline.presets): a package folder
    added later and not listed would be missing from installs; launch/ and configs/ are not installed as such."""
    setuptools = pyproject()["tool"]["setuptools"]
    listed = set(setuptools["packages"])
    folders = {".".join(init.parent.relative_to(REPO_ROOT).parts) for top in LIBRARY
               for init in (REPO_ROOT / top).rglob("__init__.py")}
    presets = {PRESETS_PACKAGE} | {f"{PRESETS_PACKAGE}.{d.name}" for d in (REPO_ROOT / "configs").iterdir()
                                    if d.is_dir() and any(d.glob("*.yaml"))}
    assert listed == folders | presets, f"missing: {sorted(folders | presets - listed)}, extra: " \
                                        f"{sorted(listed - folders - presets)}"
    assert {name.split(".")[0] for name in listed} == set(LIBRARY)
    assert setuptools["package-dir"] == {PRESETS_PACKAGE: "configs"}
    assert not (REPO_ROOT / "configs" / "__init__.py").exists()  # configs/ is a folder of presets, not a package


def test_console_scripts_point_into_the_library():
    scripts = pyproject()["project"]["scripts"]
    assert set(scripts) == SCRIPTS
    for name, target in scripts.items():
        module, _, function = target.partition(":")
        assert module.split(".")[0] in LIBRARY and function == "main", (name, target)
        assert (REPO_ROOT / Path(*module.split("."))).with_suffix(".py").is_file(), (name, target)


def test_a_checkout_reads_the_presets_users_edit():
    from pipeline.config import CONFIG_DIR, TrainConfig, available_presets

    assert CONFIG_DIR == REPO_ROOT / "configs"
    assert "synthetic" in available_presets(TrainConfig)


@pytest.mark.slow
def test_a_launch_file_runs_from_a_checkout_as_before(tmp_path):
    """``python launch/train.py --config synthetic`` (here with --print-config) from another folder imports the
    checkout it sits in and its configs/."""
    result = subprocess.run([sys.executable, str(REPO_ROOT / "launch" / "train.py"), "--config", "synthetic",
                             "--print-config"], cwd=tmp_path, capture_output=True, text=True, timeout=300,
                            env={**os.environ, "PYTHONPATH": "", "OMP_NUM_THREADS": "1"})
    assert result.returncode == 0, result.stderr
    assert any(line.startswith("data.manifest = ") for line in result.stdout.splitlines()), result.stdout


def copy_of_the_sources(dest: Path) -> Path:
    """What a wheel is built from, without the checkout's build/ (setuptools packs a stale build/lib into wheels)."""
    skip = shutil.ignore_patterns("__pycache__", "*.egg-info", "build")
    dest.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(REPO_ROOT / name, dest / name)
    for name in (*LIBRARY, "configs", "launch"):
        shutil.copytree(REPO_ROOT / name, dest / name, ignore=skip)
    return dest


@pytest.mark.slow
def test_a_wheel_install_holds_the_library_presets_licence_and_console_scripts(tmp_path):
    # Built like CI's install (isolated build environment from the package index); no dependencies fetched.
    source = copy_of_the_sources(tmp_path / "source")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path / "dist"),
                    str(source)], check=True, capture_output=True, text=True)
    (wheel,) = (tmp_path / "dist").glob("*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    top_level = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert top_level == set(LIBRARY)  # no configs/ or launch/ beside them
    presets = {"pipeline/presets/" + p.relative_to(REPO_ROOT / "configs").as_posix()
               for p in (REPO_ROOT / "configs").rglob("*.yaml")}
    assert presets and presets <= names, sorted(presets - names)
    assert any(n.endswith("licenses/LICENSE") for n in names)
    entry_points = zipfile.ZipFile(wheel).read(next(n for n in names if n.endswith("entry_points.txt"))).decode()
    targets = dict(line.split(" = ") for line in entry_points.splitlines() if " = " in line)
    assert SCRIPTS <= set(targets)
    assert all(target.split(".")[0] in LIBRARY for target in targets.values()), targets

    site = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-compile", "-q", "--target", str(site),
                    str(wheel)], check=True, capture_output=True, text=True)
    # another project's top-level configs/ installed beside ours does not take our presets' place
    (site / "configs").mkdir()
    (site / "configs" / "tiny.yaml").write_text("model: {num_layers: not-ours}\n")
    env = {**os.environ, "PYTHONPATH": str(site), "OMP_NUM_THREADS": "1"}
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    loaded = subprocess.run(
        [sys.executable, "-c", "import pipeline.config as c; "
         "print(c.__file__); print(c.CONFIG_DIR); print(c.load_config(c.TrainConfig, 'tiny').model.num_layers)"],
        cwd=elsewhere, env=env, check=True, capture_output=True, text=True).stdout.split()
    assert loaded[0].startswith(str(site))
    assert loaded[1] == str(site / "pipeline" / "presets")  # the installed copy found its own presets
    assert int(loaded[2]) >= 1
    help_text = subprocess.run([str(site / "bin" / "mfm-train"), "--help"], cwd=elsewhere, env=env, check=True,
                               capture_output=True, text=True).stdout
    assert "tiny" in help_text and "humanml3d" in help_text  # the presets it lists are the installed ones
