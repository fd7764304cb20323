"""Claim files: which process holds something, and whether that process is certainly gone.

Two holders use them: the evaluator's claims on units (``pipeline.evaluation.store``: one file per unit, refreshed
as a heartbeat, removed once its result is written) and the trainer's lock on its run folder
(``pipeline.training.run_folder``: one file held for the whole run). Both write the same holder record, a small
JSON object: ``host``, ``pid``, ``pid_ns`` (the pid namespace: two containers may share a host name while their
pids mean different processes), ``since`` (when it was taken, epoch seconds) and what is held. And both take over
from a holder that is certainly dead without waiting: :func:`dead_holder` says so when the record's host and pid
namespace are this process's and its pid no longer exists. A holder on another host or in another namespace, or
whose pid is alive (or was reused), cannot be told dead from here; what happens then is the user's rule (the
evaluator's heartbeat timeout; the run folder's kernel lock).

:func:`take_claim` is the evaluator's protocol: a claim file is created with ``O_CREAT | O_EXCL`` (so two
processes never both create it), and a stale one (its holder dead, or silent for ``stale_after_s``) is removed
first, under an exclusive ``flock`` on a guard file (:func:`exclusive_lock`) that every contender takes, so that
exactly one of them breaks it and takes it over.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import socket
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.checkpoint import process_exists

logger = logging.getLogger(__name__)


def this_pid_namespace() -> str | None:
    """The pid namespace of this process (Linux), recorded in claims: two containers may share a host name while
    their pids mean different processes, so a pid is only checked within the namespace that wrote it."""
    try:
        return os.readlink("/proc/self/ns/pid")
    except OSError:
        return None


def holder_record(**held: Any) -> dict[str, Any]:
    """This process as a claim's holder: host, pid, pid namespace, the time now, and ``held`` (what it holds)."""
    return {"host": socket.gethostname(), "pid": os.getpid(), "pid_ns": this_pid_namespace(), "since": time.time(),
            **held}


def read_record_text(path: Path) -> str:
    """The claim file's text, or a note saying why it could not be read (for log lines)."""
    try:
        return path.read_text(encoding="utf-8")
    except OSError as exc:
        return f"<unreadable: {exc}>"


def parse_record(text: str) -> dict[str, Any] | None:
    """The claim's fields, or None for a claim cut short (its holder killed between creating and writing it)."""
    try:
        record = json.loads(text)
    except json.JSONDecodeError:
        return None
    return record if isinstance(record, dict) else None


def dead_holder(record: Mapping[str, Any] | None) -> str | None:
    """Why the claim's holder is certainly dead (its pid is gone on this very host and pid namespace), or None
    when that cannot be told from here (another host or namespace, an unreadable claim, a live pid)."""
    if not record or record.get("host") != socket.gethostname():
        return None
    pid, namespace = record.get("pid"), record.get("pid_ns")
    if not isinstance(pid, int) or isinstance(pid, bool) or pid <= 0:  # os.kill(0 or -n) would signal a group
        return None
    if namespace is not None and namespace != this_pid_namespace():
        return None
    if process_exists(pid):  # a reused pid reads as alive: only delays the takeover to the user's rule
        return None
    return f"its job, pid {pid} on this host ({record['host']}), is no longer running"


@dataclass(frozen=True)
class ClaimHolder:
    """Who holds something, as its claim file says: what a process that was turned away reports."""

    host: str | None
    pid: int | None
    since: float | None
    """When the claim was made (epoch seconds)."""
    heartbeat_age_s: float | None = None
    """Seconds since the holder last refreshed the claim (None: the claim has no heartbeat)."""

    @classmethod
    def from_record(cls, record: Mapping[str, Any] | None, heartbeat_age_s: float | None = None) -> ClaimHolder:
        record = record or {}
        host, pid, since = record.get("host"), record.get("pid"), record.get("since")
        return cls(host if isinstance(host, str) else None,
                   pid if isinstance(pid, int) and not isinstance(pid, bool) else None,
                   float(since) if isinstance(since, (int, float)) and not isinstance(since, bool) else None,
                   heartbeat_age_s)

    def describe(self) -> str:
        if self.host is None:
            return "an unknown job (unreadable claim)"
        parts = [f"pid {self.pid} on {self.host}"]
        if self.since is not None:
            parts.append("started " + time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(self.since)))
        if self.heartbeat_age_s is not None:
            parts.append(f"heartbeat {self.heartbeat_age_s:.0f} s ago")
        return ", ".join(parts)


@contextlib.contextmanager
def exclusive_lock(path: Path) -> Iterator[None]:
    """Hold an exclusive ``flock`` on ``path`` (created if needed) for the block."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)


def take_claim(path: Path, stale_after_s: float, **held: Any) -> bool:
    """Create the claim file ``path`` for this process (:func:`holder_record` with ``held``); False when a live
    holder has it. A claim whose holder is dead (:func:`dead_holder`) is taken over at once, one without a heartbeat
    (its mtime) for ``stale_after_s`` after that; both are logged. Call it while holding the guard lock every
    contender takes (:func:`exclusive_lock`), so that only one of them breaks a stale claim."""
    if path.exists() and not break_if_stale(path, stale_after_s):
        return False
    try:
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
        return False
    with os.fdopen(fd, "w", encoding="utf-8") as handle:
        json.dump(holder_record(**held), handle)
    return True


def break_if_stale(path: Path, stale_after_s: float) -> bool:
    """Remove the claim at ``path`` if its holder is dead (at once when its pid is gone on this host, else after
    ``stale_after_s`` without a heartbeat); True when it is free now. Call it under the guard lock."""
    try:
        age = time.time() - path.stat().st_mtime
    except FileNotFoundError:  # released meanwhile (a release does not take the guard lock)
        return True
    text = read_record_text(path)
    reason = dead_holder(parse_record(text))
    if reason is not None:
        logger.warning("taking over claim %s at once: %s (claim: %s)", path.name, reason, text)
    elif age < stale_after_s:
        return False
    else:
        logger.warning("breaking stale claim %s (no heartbeat for %.0f s > %.0f s): %s", path.name, age,
                       stale_after_s, text)
    with contextlib.suppress(FileNotFoundError):
        path.unlink()
    return True
