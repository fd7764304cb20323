"""The run folder (``train.out_dir``): which folders a training run may write into, checked before it writes.

A run writes config.yaml, shard_report.json, metrics.jsonl, W&B files and checkpoints/ into its folder and, on a
resume, rewrites some of them. So the folder must be one of:

* a new folder (created, with its parents), or an existing empty one (a scheduler may create it first);
* a run folder of ours: it holds the run marker ``mfm-run.json`` (:data:`RUN_MARKER`), which the trainer (and the
  checkpoint converter) write into every run folder before anything else;
* a run folder made by an earlier version of this project, before the marker existed (:func:`is_earlier_run`).

What a folder holds otherwise (a ``checkpoints/`` subfolder, a ``config.yaml``) does not make it a run: another
project's folder may have both. Anything else is refused with a :class:`RunFolderError` naming what was found: the
filesystem root, a file, a path below a file, a folder this process cannot write, a non-empty folder that is not a
run (its files would be mixed with, or overwritten by, the run's), or a run whose ``checkpoints/`` holds a
``step-XXXXXXXX`` folder that is not a checkpoint we wrote (a save would meet it). The trainer calls
:func:`check_run_folder` on rank 0 at start-up and :func:`write_run_marker` once the resume is decided.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import yaml

from pipeline import checkpoint as ckpt
from pipeline.config import ConfigError

RUN_CONFIG = "config.yaml"
RUN_MARKER = "mfm-run.json"
RUN_MARKER_FORMAT = "mfm-run"
RUN_MARKER_VERSION = 1
_CONFIG_SECTIONS = frozenset({"data", "model", "optim", "train"})
_SHOWN_ENTRIES = 5


class RunFolderError(ConfigError):
    """``train.out_dir`` cannot hold this run; the message says what is there and what to pass instead."""


def check_run_folder(out_dir: str | Path) -> None:
    """Raise RunFolderError unless ``out_dir`` is a new, empty, or existing run folder this process can write."""
    path = Path(out_dir)
    setting = f"train.out_dir={str(out_dir)!r}"
    resolved = path.resolve()
    if resolved.parent == resolved:
        raise RunFolderError(f"{setting} is the filesystem root: give the run a folder of its own, e.g. runs/NAME")
    if path.exists() and not path.is_dir():
        raise RunFolderError(f"{setting} is a file, not a run folder: pass a new folder, e.g. runs/NAME")
    existing = _nearest_existing(resolved)
    if not existing.is_dir():
        raise RunFolderError(f"{setting} lies below {existing}, which is a file: pass a new folder, e.g. runs/NAME")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise RunFolderError(f"{setting}: {existing} is not writable by this user")
    if existing != resolved:
        return  # a new folder: created when the run writes its files
    entries = sorted(entry.name for entry in path.iterdir())
    if entries and not is_run_folder(path):
        shown = ", ".join(entries[:_SHOWN_ENTRIES]) + (f" and {len(entries) - _SHOWN_ENTRIES} more"
                                                      if len(entries) > _SHOWN_ENTRIES else "")
        raise RunFolderError(
            f"{setting} is a non-empty folder that is not a run folder (no {RUN_MARKER} of ours, nor the "
            f"{RUN_CONFIG} and complete checkpoint of a run from an earlier version; it holds {shown}): the run's "
            f"files would be mixed with these. Pass a new or empty folder, e.g. {path / 'run'}"
        )
    foreign = ckpt.foreign_step_folders(ckpt.checkpoints_dir(path))
    if foreign:
        raise RunFolderError(
            f"{setting}: {foreign[0]} is not a checkpoint this project wrote (no {ckpt.COMPLETE_MARKER} marker of "
            f"ours), and a save of that step would meet it: move it out of {foreign[0].parent} and run again"
        )


def is_run_folder(path: str | Path) -> bool:
    """``path`` holds our run marker, or is a run of an earlier version of this project (:func:`is_earlier_run`)."""
    return has_run_marker(path) or is_earlier_run(path)


def has_run_marker(path: str | Path) -> bool:
    """``path`` holds ``mfm-run.json`` as the trainer writes it (a JSON object of format ``mfm-run``)."""
    try:
        data = json.loads((Path(path) / RUN_MARKER).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return False
    return isinstance(data, dict) and data.get("format") == RUN_MARKER_FORMAT


def is_earlier_run(path: str | Path) -> bool:
    """A run folder written by a version of this project from before the run marker, recognised by what another
    tool does not write by accident, both at once: a ``config.yaml`` that is a training config of ours (its data,
    model, optim and train sections) and at least one complete ``checkpoints/step-XXXXXXXX`` folder whose COMPLETE
    marker is ours (format ``mfm-checkpoint``, every file it lists there with its size). A folder with only one of
    them (or a bare ``checkpoints/``) is not taken for a run; a run of an earlier version that stopped before its
    first checkpoint holds nothing to resume and is refused like any other folder. The trainer adds the marker when
    it resumes such a run."""
    path = Path(path)
    config = path / RUN_CONFIG
    try:
        data = yaml.safe_load(config.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return False
    if not (isinstance(data, dict) and _CONFIG_SECTIONS <= set(data)):
        return False
    return any(ckpt.is_complete(folder) for folder in ckpt.our_step_folders(ckpt.checkpoints_dir(path)))


def write_run_marker(out_dir: str | Path, *, written_by: str) -> Path:
    """Put ``mfm-run.json`` into ``out_dir`` (created if needed) unless it is there: from then on the folder is a run
    of ours. Written atomically; ``written_by`` names the writer (e.g. ``pipeline/training/trainer.py``)."""
    folder = Path(out_dir)
    marker = folder / RUN_MARKER
    if has_run_marker(folder):
        return marker
    folder.mkdir(parents=True, exist_ok=True)
    payload = {"format": RUN_MARKER_FORMAT, "version": RUN_MARKER_VERSION, "written_by": written_by,
               "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    tmp = folder / f".{RUN_MARKER}.tmp-{os.getpid()}"
    tmp.write_text(json.dumps(payload, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, marker)
    return marker


def _nearest_existing(path: Path) -> Path:
    """``path`` itself if it exists, else its nearest existing ancestor (the folder a mkdir -p would start in)."""
    while not path.exists() and path.parent != path:
        path = path.parent
    return path
