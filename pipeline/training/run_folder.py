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

One trainer at a time (:class:`RunFolderLock`). Two trainers on one folder resume from each other's checkpoints
and cut each other's metrics.jsonl back to their own resume step. So rank 0 holds the lock file ``mfm-run.lock``
from before it writes anything until the run ends: an exclusive POSIX record lock (``lockf``) on it, which the
kernel drops when the process ends however it ends (NFS: when the client's lease ends), with the holder's record
in it (host, pid, pid namespace, start time: :mod:`pipeline.claims`, the format of the evaluator's claims). A
second trainer is refused in one line naming that holder (:class:`RunFolderInUseError`, exit 2); a lock file left
by a killed trainer is taken over at once with a log line naming it (its lock died with it; a filesystem without
locks falls back on the evaluator's rule: a holder certainly dead on this host, :func:`pipeline.claims.dead_holder`).
The file is removed when the run ends (a clean end, a signal's clean stop, an exception); a folder that holds
nothing else counts as empty.
"""

from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import time
import uuid
from pathlib import Path
from typing import Any

import yaml

from pipeline import checkpoint as ckpt
from pipeline.claims import ClaimHolder, dead_holder, holder_record, parse_record
from pipeline.config import ConfigError

logger = logging.getLogger(__name__)

RUN_CONFIG = "config.yaml"
RUN_MARKER = "mfm-run.json"
RUN_MARKER_FORMAT = "mfm-run"
RUN_MARKER_VERSION = 1
RUN_LOCK = "mfm-run.lock"
_CONFIG_SECTIONS = frozenset({"data", "model", "optim", "train"})
_SHOWN_ENTRIES = 5


class RunFolderError(ConfigError):
    """``train.out_dir`` cannot hold this run; the message says what is there and what to pass instead."""


class RunFolderInUseError(RunFolderError):
    """Another training process that is still running holds ``train.out_dir``; the message names it."""


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
    entries = sorted(entry.name for entry in path.iterdir() if entry.name != RUN_LOCK)  # a killed run's lock
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
    return ckpt.holds_marker(path, RUN_MARKER, RUN_MARKER_FORMAT)


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


# ---------------------------------------------------------------------------------------------------------------
# One trainer at a time
# ---------------------------------------------------------------------------------------------------------------

# errno values of a filesystem that has no POSIX locks (some FUSE mounts, Lustre without -o flock)
_NO_LOCKS = frozenset({errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOTSUP, errno.ENOSYS})


class RunFolderLock:
    """The exclusive hold of one run folder by this process, from :meth:`acquire` to :meth:`release` (see the module
    docstring). Only this object opens the lock file in the holding process: a POSIX lock is dropped when the
    process closes ANY descriptor of the file, so a second lock of the same folder in one process is refused."""

    _held: dict[str, RunFolderLock] = {}  # resolved lock path -> the lock this process holds on it

    def __init__(self, path: Path, fd: int, record: dict[str, Any]) -> None:
        self.path, self._fd, self.record = path, fd, record

    @classmethod
    def acquire(cls, out_dir: str | Path) -> RunFolderLock:
        """Take ``out_dir`` (created if needed) for this process, or raise :class:`RunFolderInUseError` naming the
        trainer that holds it. A lock file of a trainer that is gone is taken over, with a warning naming it."""
        folder = Path(out_dir)
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / RUN_LOCK
        _refuse_if_held_here(out_dir, path)
        while True:
            fd = _open_lock_file(out_dir, path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC)
            try:
                locked = _try_lock(fd)
                previous = parse_record(_read(fd))
                if locked is False:
                    raise _in_use(out_dir, path, previous)
                if not _same_file(fd, path):  # its holder released (removed) it between our open and our lock
                    os.close(fd)
                    continue
                if locked is None:
                    _check_record_without_locks(out_dir, path, previous)
                elif previous:
                    logger.warning("run folder %s: taking over %s from %s: %s", folder, RUN_LOCK,
                                   ClaimHolder.from_record(previous).describe(),
                                   dead_holder(previous) or "its trainer is no longer running (its lock went with it)")
                record = holder_record(run_dir=str(folder.resolve()), token=uuid.uuid4().hex)
                _write(fd, record)
            except BaseException:
                os.close(fd)
                raise
            lock = cls(path, fd, record)
            cls._held[str(path.resolve())] = lock
            return lock

    @property
    def held(self) -> bool:
        return self._fd is not None

    def release(self) -> None:
        """Remove the lock file (while still holding the lock, so that no one takes a file about to vanish), then
        drop the lock. Idempotent."""
        if self._fd is None:
            return
        try:
            if _same_file(self._fd, self.path) and parse_record(_read(self._fd)) == self.record:
                self.path.unlink()
        except OSError as exc:
            logger.warning("could not remove the run folder lock %s (%s): the next start takes it over", self.path, exc)
        finally:
            os.close(self._fd)
            self._fd = None
            RunFolderLock._held.pop(str(self.path.resolve()), None)


def refuse_if_in_use(out_dir: str | Path) -> None:
    """Raise :class:`RunFolderInUseError` when a running trainer holds ``out_dir``: the early check, before the slow
    part of a start-up (:meth:`RunFolderLock.acquire` decides, later, before anything is written). Creates nothing."""
    path = Path(out_dir) / RUN_LOCK
    _refuse_if_held_here(out_dir, path)
    try:
        fd = _open_lock_file(out_dir, path, os.O_RDWR | os.O_CLOEXEC)
    except RunFolderError as exc:
        if isinstance(exc.__cause__, (FileNotFoundError, NotADirectoryError)):
            return  # no lock file: nobody holds the folder (or it does not exist yet)
        raise
    try:
        locked = _try_lock(fd)
        previous = parse_record(_read(fd))
        if locked is False:
            raise _in_use(out_dir, path, previous)
        if locked is None:
            _check_record_without_locks(out_dir, path, previous)
    finally:
        os.close(fd)  # also drops the lock the probe may have got


def _open_lock_file(out_dir: str | Path, path: Path, flags: int) -> int:
    try:
        return os.open(path, flags, 0o644)
    except OSError as exc:
        raise RunFolderError(f"train.out_dir={str(out_dir)!r}: cannot open its lock file {path}: "
                             f"{exc.strerror or exc}") from exc


def _try_lock(fd: int) -> bool | None:
    """Lock the whole file, without waiting: True, False (another process holds it), None (no locks here)."""
    try:
        fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        if exc.errno in (errno.EACCES, errno.EAGAIN):
            return False
        if exc.errno in _NO_LOCKS:
            return None
        raise
    return True


def _refuse_if_held_here(out_dir: str | Path, path: Path) -> None:
    held = RunFolderLock._held.get(str(path.resolve()))
    if held is not None:
        raise _in_use(out_dir, path, held.record)


def _check_record_without_locks(out_dir: str | Path, path: Path, previous: dict[str, Any] | None) -> None:
    """No POSIX locks on this filesystem: the record alone decides. A holder that is certainly dead (this host, its
    pid gone) is taken over; any other counts as running (refused, saying how to free the folder)."""
    logger.warning("%s: this filesystem does not support file locks; the run folder is held by the record in the "
                   "file only", path)
    if not previous:
        return
    reason = dead_holder(previous)
    if reason is None:
        raise _in_use(out_dir, path, previous, note=f"; this filesystem has no file locks, so a holder that cannot be "
                                                    f"checked from here counts as running: remove {path} if it is gone")
    logger.warning("run folder %s: taking over %s from %s: %s", path.parent, RUN_LOCK,
                   ClaimHolder.from_record(previous).describe(), reason)


def _in_use(out_dir: str | Path, path: Path, record: dict[str, Any] | None, note: str = "") -> RunFolderInUseError:
    holder = ClaimHolder.from_record(record).describe() if record else "a process that has not written its record yet"
    return RunFolderInUseError(
        f"train.out_dir={str(out_dir)!r} is in use by another training run: {holder} holds {path}{note}. Two "
        "trainers on one folder resume from each other's checkpoints and overwrite each other's metrics.jsonl: wait "
        "for that run to end (or stop it), or use another train.out_dir")


def _same_file(fd: int, path: Path) -> bool:
    try:
        on_disk = os.stat(path)
    except FileNotFoundError:
        return False
    opened = os.fstat(fd)
    return (on_disk.st_dev, on_disk.st_ino) == (opened.st_dev, opened.st_ino)


def _read(fd: int) -> str:
    return os.pread(fd, 1 << 16, 0).decode("utf-8", errors="replace")


def _write(fd: int, record: dict[str, Any]) -> None:
    data = (json.dumps(record) + "\n").encode()
    os.ftruncate(fd, 0)
    os.pwrite(fd, data, 0)
    os.fsync(fd)
