"""The run folder (``train.out_dir``): which folders a training run may write into, checked before it writes.

A run writes config.yaml, shard_report.json, metrics.jsonl, W&B files and checkpoints/ into its folder and, on a
resume, rewrites some of them. So the folder must be one of:

* a new folder (created, with its parents), or an existing empty one (a scheduler may create it first);
* an existing run folder: it holds ``checkpoints/`` or a ``config.yaml`` with the sections of a training config.

Anything else is refused with a :class:`RunFolderError` naming what was found: the filesystem root, a file, a path
below a file, a folder this process cannot write, or a non-empty folder that is not a run (its files would be
mixed with, or overwritten by, the run's). The trainer calls :func:`check_run_folder` on rank 0 at start-up.
"""

from __future__ import annotations

import os
from pathlib import Path

import yaml

from pipeline.checkpoint import CHECKPOINTS_SUBDIR
from pipeline.config import ConfigError

RUN_CONFIG = "config.yaml"
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
            f"{setting} is a non-empty folder that is not a run folder (no {CHECKPOINTS_SUBDIR}/ and no training "
            f"{RUN_CONFIG}; it holds {shown}): the run's files would be mixed with these. Pass a new or empty "
            f"folder, e.g. {path / 'run'}"
        )


def is_run_folder(path: str | Path) -> bool:
    """``path`` holds ``checkpoints/`` or a ``config.yaml`` that is a training config (a run wrote it)."""
    path = Path(path)
    if (path / CHECKPOINTS_SUBDIR).is_dir():
        return True
    config = path / RUN_CONFIG
    if not config.is_file():
        return False
    try:
        data = yaml.safe_load(config.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return False
    return isinstance(data, dict) and _CONFIG_SECTIONS <= set(data)


def _nearest_existing(path: Path) -> Path:
    """``path`` itself if it exists, else its nearest existing ancestor (the folder a mkdir -p would start in)."""
    while not path.exists() and path.parent != path:
        path = path.parent
    return path
