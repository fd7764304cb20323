"""Atomic training checkpoints with a completeness marker.

Layout (one folder per optimizer step; zero-padded so names sort by step)::

    <out_dir>/checkpoints/
      step-00001000/
        model.safetensors   raw model weights
        ema.safetensors     EMA weights (absent when the run keeps no EMA)
        state.pt            {"version": 1, "step", "world_size", "optimizer", "scheduler",
                             "rng": [per rank], "data": [per rank], "config", "manifest", "extra"}
        COMPLETE            written last: JSON {"format", "version", "step", "files": {name: {bytes, sha256}}}
      step-00002000.tmp-4242   a save in progress (or one that crashed): never read, pruned later

A save writes everything into ``step-N.tmp-<pid>`` (each file fsynced), writes COMPLETE, fsyncs the folder, then
renames it to ``step-N`` and fsyncs the parent. A folder without a valid COMPLETE (missing, empty, unparsable,
or listing a file that is missing or of the wrong size) does not exist as far as :func:`find_latest_complete` and
``resume="auto"`` are concerned; :func:`load_checkpoint` also checks every file's sha256.

Only global rank 0 saves. Per-rank state (RNG, data-loader position) is gathered by the caller first, e.g.
``rng_states = dist.all_gather_object(capture_rng_state())``, and passed as lists indexed by rank.

Everything in state.pt must be tensors or plain Python values (dict/list/tuple/str/int/float/bool/None): it is
read back with ``torch.load(weights_only=True)``, which executes no pickled code.
"""

from __future__ import annotations

import errno
import hashlib
import io
import json
import logging
import os
import pickle
import random
import re
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import safetensors.torch
import torch
from safetensors import SafetensorError

from mfm.integrity import sha256_file

logger = logging.getLogger(__name__)

CHECKPOINT_VERSION = 1
MARKER_FORMAT = "mfm-checkpoint"
COMPLETE_MARKER = "COMPLETE"
MODEL_FILE = "model.safetensors"
EMA_FILE = "ema.safetensors"
STATE_FILE = "state.pt"
CHECKPOINTS_SUBDIR = "checkpoints"

_STEP_DIR = re.compile(r"^step-(\d{8})$")
_TMP_DIR = re.compile(r"^step-(\d{8})\.tmp-.+$")


class CheckpointError(RuntimeError):
    """A checkpoint cannot be used; the message names the folder or file and why."""


class IncompleteCheckpointError(CheckpointError):
    """No valid COMPLETE marker: the save never finished (or the folder is not a checkpoint)."""


class CorruptCheckpointError(CheckpointError):
    """The marker is valid but a file is missing, has the wrong size or hash, or cannot be decoded."""


# ---------------------------------------------------------------------------------------------------------------
# Names
# ---------------------------------------------------------------------------------------------------------------


def checkpoints_dir(out_dir: str | Path) -> Path:
    """``<out_dir>/checkpoints``: the folder every other function here takes as ``ckpt_root``."""
    return Path(out_dir) / CHECKPOINTS_SUBDIR


def step_dir_name(step: int) -> str:
    if not isinstance(step, int) or isinstance(step, bool) or not 0 <= step < 10**8:
        raise ValueError(f"checkpoint step must be an int in [0, 1e8), got {step!r}")
    return f"step-{step:08d}"


# ---------------------------------------------------------------------------------------------------------------
# RNG state of this process
# ---------------------------------------------------------------------------------------------------------------


def capture_rng_state() -> dict[str, Any]:
    """Python, NumPy (legacy global), torch CPU and current-CUDA-device generator states of this process."""
    name, keys, pos, has_gauss, cached_gaussian = np.random.get_state()
    return {
        "python": random.getstate(),
        "numpy": {
            "bit_generator": name,
            "keys": torch.from_numpy(keys.astype(np.int64)),
            "pos": int(pos),
            "has_gauss": int(has_gauss),
            "cached_gaussian": float(cached_gaussian),
        },
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state() if torch.cuda.is_available() else None,
    }


def restore_rng_state(state: Mapping[str, Any]) -> None:
    """Inverse of :func:`capture_rng_state` (for this process's rank)."""
    random.setstate(_as_python_random_state(state["python"]))
    np_state = state["numpy"]
    np.random.set_state(
        (
            np_state["bit_generator"],
            np_state["keys"].numpy().astype(np.uint32),
            np_state["pos"],
            np_state["has_gauss"],
            np_state["cached_gaussian"],
        )
    )
    torch.set_rng_state(state["torch"])
    if state.get("cuda") is not None:
        if torch.cuda.is_available():
            torch.cuda.set_rng_state(state["cuda"])
        else:
            logger.warning("checkpoint holds a CUDA RNG state but no GPU is visible: CUDA draws will differ")


def _as_python_random_state(value: Any) -> tuple:
    # random.setstate needs (version, tuple_of_ints, gauss_next); a round trip through other serialisers may
    # turn the inner tuple into a list.
    version, internal, gauss_next = value
    return (version, tuple(internal), gauss_next)


# ---------------------------------------------------------------------------------------------------------------
# Save
# ---------------------------------------------------------------------------------------------------------------


def save_checkpoint(
    ckpt_root: str | Path,
    step: int,
    *,
    model_state: Mapping[str, torch.Tensor],
    ema_state: Mapping[str, torch.Tensor] | None,
    optimizer_state: Mapping[str, Any],
    scheduler_state: Mapping[str, Any] | None,
    rng_states: Sequence[Mapping[str, Any]],
    data_states: Sequence[Any],
    config: Mapping[str, Any],
    manifest: Mapping[str, Any],
    extra: Mapping[str, Any] | None = None,
) -> Path:
    """Write ``<ckpt_root>/step-<step>`` atomically and return its path. Call on global rank 0 only.

    ``rng_states`` / ``data_states``: one entry per rank, indexed by rank (already gathered). ``config``: the
    resolved config dict (``pipeline.config.to_dict``); ``manifest``: the dataset identity (dataset_id, feature
    spec, ...); ``extra``: counters such as samples seen. Raises FileExistsError if a complete checkpoint for
    ``step`` already exists.
    """
    if len(rng_states) != len(data_states) or not rng_states:
        raise ValueError(
            f"rng_states ({len(rng_states)}) and data_states ({len(data_states)}) must both hold one entry per rank"
        )
    ckpt_root = Path(ckpt_root)
    final = ckpt_root / step_dir_name(step)
    if final.exists():
        if is_complete(final):
            raise FileExistsError(f"checkpoint {final} already exists and is complete; refusing to overwrite it")
        _set_aside(final)
    ckpt_root.mkdir(parents=True, exist_ok=True)
    tmp = ckpt_root / f"{final.name}.tmp-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()

    state = {
        "version": CHECKPOINT_VERSION,
        "step": step,
        "world_size": len(rng_states),
        "optimizer": dict(optimizer_state),
        "scheduler": None if scheduler_state is None else dict(scheduler_state),
        "rng": list(rng_states),
        "data": list(data_states),
        "config": dict(config),
        "manifest": dict(manifest),
        "extra": dict(extra or {}),
    }
    metadata = {"step": str(step), "format": "pt"}
    files = {MODEL_FILE: safetensors.torch.save(_safetensors_ready(model_state, MODEL_FILE), metadata=metadata)}
    if ema_state is not None:
        files[EMA_FILE] = safetensors.torch.save(_safetensors_ready(ema_state, EMA_FILE), metadata=metadata)
    files[STATE_FILE] = _torch_bytes(state)

    try:
        written = {name: _write_file(tmp / name, payload) for name, payload in files.items()}
        marker = {"format": MARKER_FORMAT, "version": CHECKPOINT_VERSION, "step": step, "files": written}
        _write_file(tmp / COMPLETE_MARKER, (json.dumps(marker, indent=1, sort_keys=True) + "\n").encode())
        _fsync_dir(tmp)
    except OSError:
        # Left in place on purpose, exactly as a killed process would leave it: it has no marker, so nothing
        # reads it, and prune_checkpoints removes it once a newer checkpoint is complete.
        logger.error("writing checkpoint %s failed; the partial folder %s is ignored", final, tmp)
        raise
    os.rename(tmp, final)
    _fsync_dir(ckpt_root)
    logger.info("saved checkpoint %s", final)
    return final


def _safetensors_ready(state: Mapping[str, torch.Tensor], what: str) -> dict[str, torch.Tensor]:
    """Detached, contiguous CPU tensors; tensors sharing storage (tied weights) are cloned, as safetensors needs."""
    ready: dict[str, torch.Tensor] = {}
    seen_storages: set[int] = set()
    for key, value in state.items():
        if not isinstance(value, torch.Tensor):
            raise TypeError(f"{what}: {key!r} is a {type(value).__name__}, not a tensor")
        tensor = value.detach().cpu().contiguous()
        if tensor.numel() > 0:
            if tensor.untyped_storage().data_ptr() in seen_storages:
                tensor = tensor.clone()
            seen_storages.add(tensor.untyped_storage().data_ptr())
        ready[key] = tensor
    return ready


def _torch_bytes(obj: Any) -> bytes:
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    return buffer.getvalue()


def _write_file(path: Path, payload: bytes) -> dict[str, Any]:
    """Write and fsync one file; returns its marker entry (size and sha256 of what was written)."""
    with open(path, "wb") as handle:
        handle.write(payload)
        handle.flush()
        os.fsync(handle.fileno())
    return {"bytes": len(payload), "sha256": hashlib.sha256(payload).hexdigest()}


def _fsync_dir(path: Path) -> None:
    """Make a rename / new entries in ``path`` durable. Some filesystems cannot fsync a directory: skip there."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    except OSError as err:
        if err.errno not in (errno.EINVAL, errno.ENOTSUP):
            raise
    finally:
        os.close(fd)


def _set_aside(folder: Path) -> None:
    """Rename an incomplete ``step-N`` folder (not written by this module) out of the way, as a stale tmp."""
    aside = folder.with_name(f"{folder.name}.tmp-incomplete-{os.getpid()}")
    logger.warning("moving incomplete checkpoint folder %s aside to %s", folder, aside)
    os.rename(folder, aside)


# ---------------------------------------------------------------------------------------------------------------
# Completeness, discovery, resume
# ---------------------------------------------------------------------------------------------------------------


def read_marker(path: str | Path) -> dict[str, Any]:
    """The parsed COMPLETE marker of checkpoint folder ``path``; IncompleteCheckpointError if absent or invalid."""
    path = Path(path)
    marker_path = path / COMPLETE_MARKER
    try:
        marker = json.loads(marker_path.read_text(encoding="utf-8"))
    except FileNotFoundError as err:
        raise IncompleteCheckpointError(f"{path}: no {COMPLETE_MARKER} marker (the save did not finish)") from err
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise IncompleteCheckpointError(f"{marker_path}: unreadable marker ({err})") from err
    is_marker = isinstance(marker, dict) and marker.get("format") == MARKER_FORMAT
    if not (is_marker and isinstance(marker.get("files"), dict)):
        raise IncompleteCheckpointError(f"{marker_path}: not a {MARKER_FORMAT} marker")
    if marker.get("version") != CHECKPOINT_VERSION:
        raise CheckpointError(
            f"{marker_path}: checkpoint format version {marker.get('version')!r}; this code reads {CHECKPOINT_VERSION}"
        )
    match = _STEP_DIR.match(path.name)
    if match and int(match.group(1)) != marker.get("step"):
        raise IncompleteCheckpointError(f"{marker_path}: marker step {marker.get('step')} does not match the folder")
    if MODEL_FILE not in marker["files"] or STATE_FILE not in marker["files"]:
        raise IncompleteCheckpointError(f"{marker_path}: marker does not list {MODEL_FILE} and {STATE_FILE}")
    return marker


def verify_files(path: str | Path, marker: Mapping[str, Any], *, hashes: bool) -> None:
    """Check each file the marker lists exists with its size (and sha256 if ``hashes``)."""
    path = Path(path)
    for name, expected in marker["files"].items():
        file = path / name
        try:
            size = file.stat().st_size
        except FileNotFoundError as err:
            raise CorruptCheckpointError(f"{file}: listed in {COMPLETE_MARKER} but missing") from err
        if size != expected["bytes"]:
            raise CorruptCheckpointError(f"{file}: {size} bytes, the marker says {expected['bytes']}")
        if hashes and sha256_file(file) != expected["sha256"]:
            raise CorruptCheckpointError(f"{file}: sha256 differs from the marker (the file changed after the save)")


def is_complete(path: str | Path) -> bool:
    """Valid marker and every listed file present with the right size (hashes are checked on load)."""
    try:
        verify_files(path, read_marker(path), hashes=False)
    except (IncompleteCheckpointError, CorruptCheckpointError):
        return False
    return True


def list_complete(ckpt_root: str | Path) -> list[tuple[int, Path]]:
    """``(step, path)`` of every complete ``step-N`` folder, oldest first (empty if the folder does not exist)."""
    ckpt_root = Path(ckpt_root)
    if not ckpt_root.is_dir():
        return []
    found = []
    for child in ckpt_root.iterdir():
        match = _STEP_DIR.match(child.name)
        if match and child.is_dir():
            if is_complete(child):
                found.append((int(match.group(1)), child))
            else:
                logger.warning("ignoring incomplete checkpoint folder %s", child)
    return sorted(found)


def find_latest_complete(ckpt_root: str | Path) -> Path | None:
    """The newest complete checkpoint folder in ``ckpt_root``, or None."""
    complete = list_complete(ckpt_root)
    return complete[-1][1] if complete else None


def resolve_resume(resume: str | Path, ckpt_root: str | Path) -> Path | None:
    """What ``train.resume`` means for this run (call on rank 0, broadcast the answer).

    ``"auto"``: the newest complete checkpoint in ``ckpt_root``, or None for a fresh run. ``"never"``: None, but
    FileExistsError if ``ckpt_root`` already holds complete checkpoints (a fresh run would interleave with them).
    Anything else is a checkpoint folder that must exist (FileNotFoundError) and be complete
    (IncompleteCheckpointError / CorruptCheckpointError).
    """
    if resume == "auto":
        return find_latest_complete(ckpt_root)
    if resume == "never":
        existing = list_complete(ckpt_root)
        if existing:
            raise FileExistsError(
                f"train.resume=never but {ckpt_root} already holds {len(existing)} complete checkpoint(s) "
                f"(newest {existing[-1][1].name}); use another train.out_dir, delete them, or resume=auto"
            )
        return None
    path = Path(resume)
    if not path.exists():
        raise FileNotFoundError(f"train.resume={str(resume)!r}: no such checkpoint folder")
    looks_like_run = any(path.glob("step-*")) or (path / CHECKPOINTS_SUBDIR).is_dir()
    if looks_like_run and not (path / COMPLETE_MARKER).exists():
        raise IncompleteCheckpointError(
            f"train.resume={str(resume)!r} is a run or checkpoints folder, not a checkpoint: pass one of its "
            "step-XXXXXXXX folders, or set train.out_dir to that run and resume=auto"
        )
    verify_files(path, read_marker(path), hashes=False)
    return path


# ---------------------------------------------------------------------------------------------------------------
# Load
# ---------------------------------------------------------------------------------------------------------------


def load_checkpoint(
    path: str | Path, *, verify_hashes: bool = True
) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor] | None, dict[str, Any]]:
    """``(model_state, ema_state or None, state)`` of a complete checkpoint, on CPU.

    Checks the marker, every file's size and (by default) sha256, and the state's format version. Fails with
    FileNotFoundError (no such folder), IncompleteCheckpointError, CorruptCheckpointError or CheckpointError;
    it never returns partial data.
    """
    path = Path(path)
    if not path.is_dir():
        raise FileNotFoundError(f"no checkpoint folder at {path}")
    marker = read_marker(path)
    verify_files(path, marker, hashes=verify_hashes)
    model_state = _load_safetensors(path / MODEL_FILE)
    ema_state = _load_safetensors(path / EMA_FILE) if EMA_FILE in marker["files"] else None
    state_path = path / STATE_FILE
    try:
        state = torch.load(state_path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError) as err:
        raise CorruptCheckpointError(f"{state_path}: cannot be read ({err})") from err
    if not isinstance(state, dict) or state.get("version") != CHECKPOINT_VERSION:
        version = state.get("version") if isinstance(state, dict) else None
        raise CheckpointError(f"{state_path}: state format version {version!r}; this code reads {CHECKPOINT_VERSION}")
    if state.get("step") != marker["step"]:
        raise CorruptCheckpointError(f"{state_path}: step {state.get('step')} but the marker says {marker['step']}")
    return model_state, ema_state, state


def _load_safetensors(file: Path) -> dict[str, torch.Tensor]:
    try:
        return safetensors.torch.load_file(file, device="cpu")
    except SafetensorError as err:
        raise CorruptCheckpointError(f"{file}: cannot be read ({err})") from err


# ---------------------------------------------------------------------------------------------------------------
# Retention
# ---------------------------------------------------------------------------------------------------------------


def prune_checkpoints(ckpt_root: str | Path, keep_last: int) -> list[Path]:
    """Delete complete checkpoints older than the ``keep_last`` newest (0 keeps all) and stale ``.tmp`` folders.

    The newest complete checkpoint is never deleted, nor is anything when none is complete. A ``.tmp`` folder is
    stale when its step is not newer than the newest complete checkpoint. A folder that cannot be deleted is
    logged and skipped (training goes on). Returns the folders removed.
    """
    if keep_last < 0:
        raise ValueError(f"keep_last must be >= 0 (0 keeps all), got {keep_last}")
    ckpt_root = Path(ckpt_root)
    complete = list_complete(ckpt_root)
    if not complete:
        return []
    newest_step = complete[-1][0]
    doomed = [path for _, path in complete[:-keep_last]] if keep_last > 0 else []
    for child in sorted(ckpt_root.iterdir()):
        match = _TMP_DIR.match(child.name)
        if match and child.is_dir() and int(match.group(1)) <= newest_step:
            doomed.append(child)
    removed = []
    for folder in doomed:
        try:
            _remove_folder(folder)
        except OSError as err:
            logger.warning("could not delete old checkpoint folder %s: %s", folder, err)
            continue
        removed.append(folder)
    return removed


def _remove_folder(folder: Path) -> None:
    # Rename first: a crash during rmtree then leaves a `.tmp` folder (pruned next time), never a `step-N` folder
    # that is missing files.
    if _STEP_DIR.match(folder.name):
        doomed = folder.with_name(f"{folder.name}.tmp-delete-{os.getpid()}")
        os.rename(folder, doomed)
        folder = doomed
    shutil.rmtree(folder)
