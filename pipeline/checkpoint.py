"""Atomic training checkpoints with a completeness marker.

Layout (one folder per optimizer step; zero-padded so names sort by step)::

    <out_dir>/checkpoints/
      step-00001000/
        model.safetensors   raw model weights
        ema.safetensors     EMA weights (absent when the run keeps no EMA)
        state.pt            {"version": 1, "step", "world_size", "optimizer", "scheduler", "scaler",
                             "rng": [per rank], "data": [per rank], "config", "manifest", "extra",
                             "auxiliary"}
                            "scaler": the fp16 loss scaler's {"scale", "growth_tracker"}, None without fp16;
                            "auxiliary": what trains beside the model, by name ({"critic": ...} with
                            train.critic_weight > 0, else {}). Optional entries, so the format stays version 1
                            both ways: a file written before them loads with "scaler": None and no "auxiliary"
                            (read as {}), and older code reads new files (ignoring them)
        COMPLETE            written last: JSON {"format", "version", "step", "files": {name: {bytes, sha256}}}
      step-00002000.tmp-node7-4242   a save in progress by pid 4242 on host node7 (or one that was killed):
                                     never read; removed at the next start-up once that pid is gone, or pruned
                                     (only names of exactly this pattern, which this module writes, are removed)
      step-00001000.corrupt-20250101T120000    set aside by resume=auto (a file fails its sha256): never read,
      step-00001000.discarded-20250101T120000  never pruned, never deleted (by train.resume_discard_newer=true)
      saved.jsonl             one JSON line per completed save, appended by the trainer after the folder is in place:
                              {"step", "name", "id" (sha256 of COMPLETE), "time"}; never pruned (see record_saved)

A save writes everything into ``step-N.tmp-<host>-<pid>`` (each file fsynced), writes COMPLETE, fsyncs the folder,
then renames it to ``step-N`` and fsyncs the parent. A save that fails (a full disk) removes its temporary folder,
logs one line with the space it needed and the space free, and raises CheckpointWriteError: a half-written
checkpoint never holds space a restart needs. A folder without a valid COMPLETE (missing, empty, unparsable, or
listing a file that is missing or of the wrong size) does not exist as far as :func:`find_latest_complete` is
concerned; :func:`load_checkpoint` also checks every file's sha256, and ``resume="auto"`` does too before it picks
a checkpoint, falling back to the newest one that verifies (see :func:`resolve_resume`).

A training process starting up calls :func:`remove_stale_tmp` first: temporary folders whose writer is gone are
removed before anything else is written, so a crash or a full disk never leaves a run that cannot restart.

Only what this module wrote is ever renamed or deleted: a ``step-N`` folder whose COMPLETE marker is ours (format
``mfm-checkpoint``) and temporary folders of its own name pattern. A ``step-N`` folder without our marker (a user's
folder of that name) is never moved or deleted: a save of that step refuses to go on
(:class:`CheckpointFolderTakenError`), and the run-folder check at start-up names it (:func:`foreign_step_folders`).

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
import socket
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
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
SAVED_LISTING = "saved.jsonl"  # in <out_dir>/checkpoints: one line per completed save, never pruned

_STEP_DIR = re.compile(r"^step-(\d{8})$")
_TMP_DIR = re.compile(r"^step-(\d{8})\.tmp-(.+)$")
# The owner part of a temporary folder's name: [incomplete-|delete-][<host>-]<pid> (names from before the host was
# recorded have none: they were written on this host). ``incomplete-`` names come from earlier versions only and are
# never removed (see _is_our_tmp_name).
_TMP_OWNER = re.compile(r"^(?:(?:incomplete|delete)-)?(?:(?P<host>.+)-)?(?P<pid>\d+)$")


class CheckpointError(RuntimeError):
    """A checkpoint cannot be used; the message names the folder or file and why."""


class IncompleteCheckpointError(CheckpointError):
    """No valid COMPLETE marker: the save never finished (or the folder is not a checkpoint)."""


class CorruptCheckpointError(CheckpointError):
    """The marker is valid but a file is missing, has the wrong size or hash, or cannot be decoded."""


class CheckpointWriteError(OSError):
    """A save failed (a full disk, a quota, an I/O error) and removed its partial folder. ``errno`` is the original
    error's; ``strerror`` is one line saying which checkpoint, why and, for a full disk, the space it needed
    against the space free."""

    def __str__(self) -> str:
        return self.strerror or super().__str__()


class CheckpointFolderTakenError(CheckpointError, FileExistsError):
    """A save's ``step-N`` folder exists and is not a checkpoint this module wrote (no COMPLETE marker of ours): it
    is left as it is, and the save refused (a FileExistsError too, so the trainer stops with one line)."""


class CheckpointNotFoundError(CheckpointError, FileNotFoundError):
    """``train.resume`` names a folder that does not exist (a FileNotFoundError too, for callers that catch that)."""


class ResumeConflictError(CheckpointError):
    """An explicit resume point is older than checkpoints already in the run: training on would reach their steps
    and have to refuse (or overwrite) them after the compute is spent, so the run is refused before step 1.
    ``continue_override`` is the override that continues from the resume point anyway (the newer ones set aside)."""

    continue_override = "train.resume_discard_newer=true"


class ResumeSettingError(CheckpointError):
    """The checkpoint cannot be resumed with this run's settings: ``setting`` (e.g. ``data.batch_size``) was
    ``saved`` when it was written and is ``now`` in this run, and the data position (which samples come next) or the
    per-rank streams depend on it; or (``train.max_steps``) the checkpoint's step, ``saved``, is already past the
    run's last step, ``now``. Raised before anything in the run folder is written; the message says how to go on
    (the checkpoint's value, or a new run folder)."""

    def __init__(self, message: str, *, setting: str, saved: Any, now: Any) -> None:
        super().__init__(message)
        self.setting, self.saved, self.now = setting, saved, now


# ---------------------------------------------------------------------------------------------------------------
# Names
# ---------------------------------------------------------------------------------------------------------------


def checkpoints_dir(out_dir: str | Path) -> Path:
    """``<out_dir>/checkpoints``: the folder every other function here takes as ``ckpt_root``."""
    return Path(out_dir) / CHECKPOINTS_SUBDIR


def run_dir_of(folder: str | Path) -> Path:
    """The run folder of a checkpoint folder (``<run>/checkpoints/step-N`` -> ``<run>``); a step folder kept
    elsewhere counts its parent as its run."""
    parent = Path(folder).parent
    return parent.parent if parent.name == CHECKPOINTS_SUBDIR else parent


def step_dir_name(step: int) -> str:
    if not isinstance(step, int) or isinstance(step, bool) or not 0 <= step < 10**8:
        raise ValueError(f"checkpoint step must be an int in [0, 1e8), got {step!r}")
    return f"step-{step:08d}"


def tmp_dir_name(step: int, pid: int | None = None) -> str:
    """``step-N.tmp-<host>-<pid>``: the folder a save writes into. Host and pid name its writer, so that a later
    start-up can tell a save in progress (a live process on this host) from one that was killed."""
    return f"{step_dir_name(step)}.tmp-{_owner_tag(pid)}"


def _owner_tag(pid: int | None = None) -> str:
    return f"{_this_host()}-{os.getpid() if pid is None else pid}"


def _this_host() -> str:
    # '-' separates the host from the pid in the folder name, so the host's own '-' (and anything unsafe in a
    # folder name) becomes '_'.
    return re.sub(r"[^A-Za-z0-9.]", "_", socket.gethostname()) or "unknown_host"


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
    scaler_state: Mapping[str, Any] | None = None,
    auxiliary_state: Mapping[str, Any] | None = None,
) -> Path:
    """Write ``<ckpt_root>/step-<step>`` atomically and return its path. Call on global rank 0 only.

    ``rng_states`` / ``data_states``: one entry per rank, indexed by rank (already gathered). ``config``: the
    resolved config dict (``pipeline.config.to_dict``); ``manifest``: the dataset identity (dataset_id, feature
    spec, ...); ``extra``: counters such as samples seen; ``scaler_state``: the fp16 loss scaler's state (None
    without fp16); ``auxiliary_state``: the states of what trains beside the model, by name (``{"critic": ...}``
    with train.critic_weight > 0; stored under ``"auxiliary"``, ``{}`` without). Raises FileExistsError if a complete checkpoint for
    ``step`` already exists, and CheckpointWriteError (an OSError) if writing fails: the partial folder is then
    already removed and the reason logged (for a full disk: the space needed and the space free).
    """
    if len(rng_states) != len(data_states) or not rng_states:
        raise ValueError(
            f"rng_states ({len(rng_states)}) and data_states ({len(data_states)}) must both hold one entry per rank"
        )
    ckpt_root = Path(ckpt_root)
    final = ckpt_root / step_dir_name(step)
    if final.exists() or final.is_symlink():
        if not is_our_checkpoint_folder(final):
            raise CheckpointFolderTakenError(
                f"checkpoint {final} cannot be saved: a folder of that name is there and is not a checkpoint this "
                f"project wrote (no {COMPLETE_MARKER} marker of ours); it is left as it is: move it out of "
                f"{ckpt_root} and run again")
        if is_complete(final):
            raise FileExistsError(f"checkpoint {final} already exists and is complete; refusing to overwrite it")
        aside = move_aside(final, "corrupt")  # ours, but a listed file is missing or cut short: kept, never deleted
        logger.warning("checkpoint %s is damaged (a file it lists is missing or of the wrong size): moved aside to %s "
                       "(kept, not deleted)", final, aside.name)
    tmp = ckpt_root / tmp_dir_name(step)

    state = {
        "version": CHECKPOINT_VERSION,
        "step": step,
        "world_size": len(rng_states),
        "optimizer": dict(optimizer_state),
        "scheduler": None if scheduler_state is None else dict(scheduler_state),
        "scaler": None if scaler_state is None else dict(scaler_state),
        "rng": list(rng_states),
        "data": list(data_states),
        "config": dict(config),
        "manifest": dict(manifest),
        "extra": dict(extra or {}),
        "auxiliary": dict(auxiliary_state or {}),
    }
    metadata = {"step": str(step), "format": "pt"}
    files = {MODEL_FILE: safetensors.torch.save(_safetensors_ready(model_state, MODEL_FILE), metadata=metadata)}
    if ema_state is not None:
        files[EMA_FILE] = safetensors.torch.save(_safetensors_ready(ema_state, EMA_FILE), metadata=metadata)
    files[STATE_FILE] = _torch_bytes(state)

    try:
        ckpt_root.mkdir(parents=True, exist_ok=True)
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir()
        written = {name: _write_file(tmp / name, payload) for name, payload in files.items()}
        marker = {"format": MARKER_FORMAT, "version": CHECKPOINT_VERSION, "step": step, "files": written}
        _write_file(tmp / COMPLETE_MARKER, (json.dumps(marker, indent=1, sort_keys=True) + "\n").encode())
        _fsync_dir(tmp)
    except OSError as err:
        # Removed, not left for later: on a full disk the partial folder holds the very space the next save (or a
        # restart's first write) needs. It has no marker, so nothing has read it.
        shutil.rmtree(tmp, ignore_errors=True)
        description = describe_save_failure(final, err, sum(len(p) for p in files.values()))
        logger.error("%s", description)
        raise CheckpointWriteError(err.errno, description) from err
    os.rename(tmp, final)
    _fsync_dir(ckpt_root)
    logger.info("saved checkpoint %s", final)
    return final


def describe_save_failure(final: Path, err: OSError, needed_bytes: int) -> str:
    """One line saying which checkpoint was not saved and why; for a full disk (or quota) also the space the
    checkpoint needs against the space free there, which is what the user has to fix."""
    line = f"checkpoint {final} was not saved ({err}); its partial folder was removed"
    if err.errno in (errno.ENOSPC, errno.EDQUOT):
        try:
            free = shutil.disk_usage(final.parent if final.parent.exists() else final.parent.parent).free
        except OSError:
            free = -1
        free_text = "unknown" if free < 0 else _megabytes(free)
        line += f": it needs {_megabytes(needed_bytes)}, {free_text} free on {final.parent}"
    return line


def _megabytes(count: int) -> str:
    return f"{count / 1e6:.1f} MB"


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


def is_our_checkpoint_folder(folder: str | Path) -> bool:
    """Whether ``folder`` (not a link) holds a COMPLETE marker this module wrote: a JSON object of format
    ``mfm-checkpoint``, whatever its version and whether or not its files are still all there. Only such folders
    are ever renamed or deleted here."""
    folder = Path(folder)
    if folder.is_symlink() or not folder.is_dir():
        return False
    return holds_marker(folder, COMPLETE_MARKER, MARKER_FORMAT)


def holds_marker(folder: str | Path, name: str, marker_format: str) -> bool:
    """Whether ``folder/name`` is a JSON object of format ``marker_format``: the marker by which one of our jobs
    owns a folder (a checkpoint's COMPLETE, a run's mfm-run.json, an evaluation folder's mfm-eval.json)."""
    try:
        marker = json.loads((Path(folder) / name).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return False
    return isinstance(marker, dict) and marker.get("format") == marker_format


def our_step_folders(ckpt_root: str | Path) -> list[Path]:
    """The ``step-N`` folders of ``ckpt_root`` that are checkpoints of ours (:func:`is_our_checkpoint_folder`)."""
    return [folder for folder in _step_named(ckpt_root) if is_our_checkpoint_folder(folder)]


def foreign_step_folders(ckpt_root: str | Path) -> list[Path]:
    """The entries of ``ckpt_root`` named ``step-N`` that are not checkpoints of ours: never read, renamed or
    deleted, and a save of their step is refused."""
    return [folder for folder in _step_named(ckpt_root) if not is_our_checkpoint_folder(folder)]


def _step_named(ckpt_root: str | Path) -> list[Path]:
    ckpt_root = Path(ckpt_root)
    if not ckpt_root.is_dir():
        return []
    return sorted(child for child in ckpt_root.iterdir() if _STEP_DIR.match(child.name))


def _is_our_tmp_name(name: str) -> bool:
    """``step-N.tmp-[delete-][<host>-]<pid>``: a temporary folder this module writes (a save under way, or a pruned
    checkpoint being deleted). ``step-N.tmp-incomplete-...`` folders are not: earlier versions renamed any ``step-N``
    folder without a valid marker to that name, a user's folder included, so they are kept for the user."""
    match = _TMP_DIR.match(name)
    return bool(match and _TMP_OWNER.match(match.group(2)) and not match.group(2).startswith("incomplete-"))


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
    return _step_folders(ckpt_root, is_complete)


def _step_folders(ckpt_root: str | Path, usable: Callable[[Path], bool]) -> list[tuple[int, Path]]:
    """``(step, path)`` of every ``step-N`` folder of ``ckpt_root`` that ``usable`` accepts, oldest first; the
    others are logged as incomplete and skipped."""
    ckpt_root = Path(ckpt_root)
    if not ckpt_root.is_dir():
        return []
    found = []
    for child in ckpt_root.iterdir():
        match = _STEP_DIR.match(child.name)
        if not (match and child.is_dir()):
            continue
        if usable(child):
            found.append((int(match.group(1)), child))
        else:
            logger.warning("ignoring incomplete checkpoint folder %s", child)
    return sorted(found)


def find_latest_complete(ckpt_root: str | Path) -> Path | None:
    """The newest complete checkpoint folder in ``ckpt_root``, or None."""
    complete = list_complete(ckpt_root)
    return complete[-1][1] if complete else None


def resolve_checkpoint(path: str | Path) -> Path:
    """A complete checkpoint folder from ``path``: a ``step-XXXXXXXX`` folder itself, or a run folder /
    ``checkpoints/`` folder, in which case its newest complete checkpoint."""
    path = Path(path)
    if (path / COMPLETE_MARKER).exists():
        return path
    for root in (checkpoints_dir(path), path):
        if root.is_dir():
            latest = find_latest_complete(root)
            if latest is not None:
                return latest
    if not path.exists():
        raise FileNotFoundError(f"no checkpoint or run folder at {path}")
    raise FileNotFoundError(f"{path} holds no complete checkpoint (a step-XXXXXXXX folder with a COMPLETE marker)")


def resolve_resume(resume: str | Path, ckpt_root: str | Path, *, discard_newer: bool = False) -> Path | None:
    """What ``train.resume`` means for this run (call on rank 0, broadcast the answer).

    ``"auto"``: the newest checkpoint in ``ckpt_root`` whose files all verify (sha256), or None for a fresh run.
    A newer one that fails is renamed ``step-N.corrupt-<time>`` (never deleted: it may be all that is left of those
    steps) and the one before it is tried; CorruptCheckpointError if checkpoints existed and none verifies.
    ``"never"``: None, but FileExistsError if ``ckpt_root`` already holds complete checkpoints (a fresh run would
    interleave with them). Anything else is a checkpoint folder that must exist (CheckpointNotFoundError, a
    FileNotFoundError) and be complete (IncompleteCheckpointError / CorruptCheckpointError); if ``ckpt_root``
    holds checkpoints newer than it, the run would meet them later and could neither overwrite nor keep them, so
    this refuses at once (ResumeConflictError) unless ``discard_newer``, which renames them
    ``step-N.discarded-<time>``.
    """
    if resume == "auto":
        return _newest_verified(Path(ckpt_root))
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
        raise CheckpointNotFoundError(f"train.resume={str(resume)!r}: no such checkpoint folder")
    looks_like_run = any(path.glob("step-*")) or (path / CHECKPOINTS_SUBDIR).is_dir()
    if looks_like_run and not (path / COMPLETE_MARKER).exists():
        raise IncompleteCheckpointError(
            f"train.resume={str(resume)!r} is a run or checkpoints folder, not a checkpoint: pass one of its "
            "step-XXXXXXXX folders, or set train.out_dir to that run and resume=auto"
        )
    marker = read_marker(path)
    verify_files(path, marker, hashes=False)
    _check_nothing_newer(path, int(marker["step"]), Path(ckpt_root), discard_newer)
    return path


def _newest_verified(ckpt_root: Path) -> Path | None:
    """resume=auto: the newest finished checkpoint whose files match their sha256; newer corrupt ones set aside."""
    moved: list[Path] = []
    for _, path in reversed(_finished(ckpt_root)):
        try:
            verify_files(path, read_marker(path), hashes=True)
        except CorruptCheckpointError as err:
            aside = move_aside(path, "corrupt")
            logger.warning("checkpoint %s is corrupt (%s): moved aside to %s (kept, not deleted); trying the one "
                           "before it", path.name, err, aside.name)
            moved.append(aside)
            continue
        if moved:
            logger.warning("resume=auto: resuming from %s, the newest checkpoint that verifies", path)
        return path
    if moved:
        raise CorruptCheckpointError(
            f"no checkpoint in {ckpt_root} verifies; the corrupt one(s) were moved aside "
            f"({', '.join(p.name for p in moved)}): to start this run over from step 0, rerun with train.resume=never"
        )
    return None


def _finished(ckpt_root: Path) -> list[tuple[int, Path]]:
    """``(step, path)`` of every ``step-N`` folder with a valid marker (its save finished), oldest first; their
    files may since have changed. Folders without one are logged and skipped, as :func:`list_complete` does."""
    return _step_folders(ckpt_root, _has_marker)


def _has_marker(path: Path) -> bool:
    try:
        read_marker(path)
    except IncompleteCheckpointError:
        return False
    return True


def _check_nothing_newer(path: Path, step: int, ckpt_root: Path, discard: bool) -> None:
    """An explicit resume point at ``step``: refuse (or, with ``discard``, set aside) finished checkpoints of
    ``ckpt_root`` at later steps, before any compute is spent reaching them."""
    newer = [folder for folder_step, folder in _finished(ckpt_root) if folder_step > step]
    if not newer:
        return
    names = ", ".join(folder.name for folder in newer)
    if not discard:
        raise ResumeConflictError(
            f"train.resume={str(path)!r} is step {step}, but {ckpt_root} already holds newer checkpoint(s) {names}: "
            f"the run would stop when it reaches them. To continue from {path.name} and move the newer one(s) aside "
            f"(renamed step-N.discarded-<time>, not deleted), rerun with {ResumeConflictError.continue_override}; "
            "to continue from the newest instead, use train.resume=auto"
        )
    for folder in newer:
        aside = move_aside(folder, "discarded")
        logger.warning("train.resume_discard_newer: moved %s aside to %s (kept, not deleted)", folder.name, aside.name)


def move_aside(folder: Path, label: str) -> Path:
    """Rename checkpoint ``folder`` to ``<name>.<label>-<local time>``: out of every reader's and the pruner's way,
    but kept for the user to inspect or delete."""
    stamp = time.strftime("%Y%m%dT%H%M%S")
    aside = folder.with_name(f"{folder.name}.{label}-{stamp}")
    suffix = 1
    while aside.exists():
        aside = folder.with_name(f"{folder.name}.{label}-{stamp}-{suffix}")
        suffix += 1
    os.rename(folder, aside)
    return aside


def remove_stale_tmp(ckpt_root: str | Path) -> list[Path]:
    """Remove the temporary folders (``step-N.tmp-...``) whose writer is gone; call at start-up, on rank 0, before
    the run writes anything.

    A save that was killed (or, before it cleaned up after itself, failed on a full disk) leaves its temporary
    folder; on a full disk that folder is what makes every restart fail at its first write. Kept: folders of a
    live process on this host other than this one (a save in progress) and folders written on another host (whose
    process cannot be checked from here; :func:`prune_checkpoints` removes them once a newer checkpoint is
    complete). A folder of this very pid is from an earlier process (containers reuse pids): this one has not
    saved yet. Returns the folders removed; one that cannot be removed is logged and skipped.
    """
    ckpt_root = Path(ckpt_root)
    if not ckpt_root.is_dir():
        return []
    removed = []
    for child in sorted(ckpt_root.iterdir()):
        match = _TMP_DIR.match(child.name)
        if not (match and child.is_dir() and not child.is_symlink()):
            continue
        if not _is_our_tmp_name(child.name):  # only a temporary folder of our own name pattern is ever removed
            logger.info("keeping %s: not a temporary folder name this code writes (set aside by an earlier version, "
                        "or not ours); delete it yourself once you know what it holds", child)
            continue
        owner = _TMP_OWNER.match(match.group(2))
        host = owner["host"]
        if host is not None and host != _this_host():
            logger.info("keeping %s: written on host %s, whose processes cannot be checked from here", child, host)
            continue
        if _pid_alive(int(owner["pid"])):
            logger.info("keeping %s: its writer, pid %s on this host, is still running", child, owner["pid"])
            continue
        try:
            shutil.rmtree(child)
        except OSError as err:
            logger.warning("could not remove the unfinished checkpoint folder %s: %s", child, err)
            continue
        logger.warning("removed the unfinished checkpoint folder %s (its writer is gone)", child)
        removed.append(child)
    return removed


def _pid_alive(pid: int) -> bool:
    """Whether ``pid`` is a running process on this host other than this one."""
    return pid != os.getpid() and process_exists(pid)


def process_exists(pid: int) -> bool:
    """Whether a process with this pid exists on this host (signal 0 checks without signalling; the evaluator's
    claims use it too). ``PermissionError`` means it exists under another user: alive. Not a valid pid (0 and
    negative ones would address a process group; too large for the OS): False. A reused pid reads as alive."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, owned by another user
        return True
    except (OverflowError, OSError):
        return False
    return True


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
    state.setdefault("scaler", None)  # written before fp16 loss scaling existed
    return model_state, ema_state, state


def _load_safetensors(file: Path) -> dict[str, torch.Tensor]:
    try:
        return safetensors.torch.load_file(file, device="cpu")
    except SafetensorError as err:
        raise CorruptCheckpointError(f"{file}: cannot be read ({err})") from err


# ---------------------------------------------------------------------------------------------------------------
# The listing of completed saves
# ---------------------------------------------------------------------------------------------------------------


def checkpoint_id(marker: Mapping[str, Any]) -> str:
    """The identity of one save: sha256 of its COMPLETE marker as sorted-key JSON (the marker lists every file's
    sha256, so a re-saved checkpoint gets a new id). The evaluator keys its results by it."""
    return hashlib.sha256(json.dumps(marker, sort_keys=True, default=str).encode()).hexdigest()


@dataclass(frozen=True)
class SavedCheckpoint:
    """One line of ``saved.jsonl``: a save that completed, whether or not its folder still exists."""

    step: int
    name: str
    checkpoint_id: str
    time: str
    """When the save completed (UTC, ISO 8601)."""


def record_saved(ckpt_root: str | Path, folder: str | Path) -> None:
    """Append ``{"step", "name", "id", "time"}`` for the complete checkpoint ``folder`` (its COMPLETE marker written
    and the folder renamed into place) to ``<ckpt_root>/saved.jsonl``. The listing is append-only and
    ``train.keep_last`` never prunes it, so a checkpoint deleted before any evaluator saw it is still known
    (``launch/evaluate.py --watch`` reports it as pruned before evaluation). Rank 0 only, after the save. A failure to
    append is logged, never raised: the checkpoint itself is complete."""
    folder = Path(folder)
    listing = Path(ckpt_root) / SAVED_LISTING
    try:
        marker = read_marker(folder)
        line = json.dumps({"step": int(marker["step"]), "name": folder.name, "id": checkpoint_id(marker),
                           "time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}) + "\n"
        with open(listing, "a+b") as handle:
            handle.seek(0, os.SEEK_END)
            if handle.tell() > 0:  # a line torn by a crash must not swallow this one
                handle.seek(-1, os.SEEK_END)
                if handle.read(1) != b"\n":
                    line = "\n" + line
            handle.write(line.encode())
            handle.flush()
            os.fsync(handle.fileno())
    except (OSError, CheckpointError) as err:
        logger.warning("%s saved, but not listed in %s: %s", folder.name, listing, err)


def read_saved(ckpt_root: str | Path) -> list[SavedCheckpoint]:
    """Every save listed in ``<ckpt_root>/saved.jsonl``, oldest first (unreadable lines are skipped)."""
    listing = Path(ckpt_root) / SAVED_LISTING
    try:
        text = listing.read_text(encoding="utf-8")
    except (FileNotFoundError, NotADirectoryError):
        return []
    out = []
    for line in text.splitlines():
        try:
            record = json.loads(line)
            out.append(SavedCheckpoint(int(record["step"]), str(record["name"]), str(record["id"]),
                                       str(record.get("time", ""))))
        except (json.JSONDecodeError, KeyError, TypeError, ValueError):
            continue
    return out


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
        if (match and child.is_dir() and not child.is_symlink() and _is_our_tmp_name(child.name)
                and int(match.group(1)) <= newest_step):
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
        doomed = folder.with_name(f"{folder.name}.tmp-delete-{_owner_tag()}")
        os.rename(folder, doomed)
        folder = doomed
    shutil.rmtree(folder)
