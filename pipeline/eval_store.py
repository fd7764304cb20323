"""Where evaluation results live, and how concurrent evaluator jobs agree on who does what.

Layout of an evaluation folder (default ``<run_dir>/eval``)::

    results/<checkpoint>/<solver>-<N>steps-g<guidance>.<key>.json   one result per (checkpoint, settings): its
                                                                     presence marks the unit done
    results.jsonl                                                     the table: one row per result and one
    results.parquet                                                   ground-truth row, rewritten from the JSONL
    claims/<key>.claim                                                "someone is evaluating this unit now"
    cache/gt-<evaluator>-<dataset>-<split>-<gt key>.npz               ground-truth embeddings per evaluator
    plots/*.png

Concurrency. Any number of jobs (cron, Slurm array, Kubernetes CronJob, two shells) may watch the same run. A unit
is claimed by creating its claim file with ``O_CREAT | O_EXCL`` while holding an exclusive ``flock`` on
``claims/.lock``; the holder refreshes the file's mtime (heartbeat) as it progresses. A claim older than the
timeout is stale (its job died) and is broken under the same lock, so exactly one job takes a unit over. The result
JSON is written atomically (temp file + ``os.replace``) before the claim is removed, and the table append skips
rows whose key is already present, so a job killed between the two steps never duplicates a row. ``flock`` works
on local disks and on NFSv4/Lustre mounts that support POSIX locks; ``O_EXCL`` alone still prevents two claims.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import socket
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

logger = logging.getLogger(__name__)

RESULTS_SUBDIR = "results"
CLAIMS_SUBDIR = "claims"
CACHE_SUBDIR = "cache"
PLOTS_SUBDIR = "plots"
TABLE_JSONL = "results.jsonl"
TABLE_PARQUET = "results.parquet"


@dataclass(frozen=True)
class Unit:
    """One piece of work: a checkpoint evaluated at one sampling point with fixed settings."""

    checkpoint_name: str
    """The checkpoint folder name, e.g. ``step-00001500``."""
    point_name: str
    """``euler-10steps-g2.5``: readable part of the result file name."""
    key: str
    """sha256 of everything that decides the numbers (checkpoint id, evaluator id, data, protocol, point)."""


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` so that readers see the old file or the whole new one, never a part."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "w", encoding="utf-8") as handle:
        handle.write(text)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)


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


class ResultsStore:
    """Claims, result files and the results table of one evaluation folder."""

    def __init__(self, root: str | Path, claim_timeout_s: float = 3600.0) -> None:
        if claim_timeout_s <= 0:
            raise ValueError(f"claim_timeout_s must be > 0, got {claim_timeout_s}")
        self.root = Path(root)
        self.claim_timeout_s = claim_timeout_s

    # -- paths -------------------------------------------------------------------------------------------------

    def result_path(self, unit: Unit) -> Path:
        return self.root / RESULTS_SUBDIR / unit.checkpoint_name / f"{unit.point_name}.{unit.key[:12]}.json"

    def claim_path(self, unit: Unit) -> Path:
        return self.root / CLAIMS_SUBDIR / f"{unit.checkpoint_name}.{unit.point_name}.{unit.key[:12]}.claim"

    @property
    def cache_dir(self) -> Path:
        return self.root / CACHE_SUBDIR

    @property
    def plots_dir(self) -> Path:
        return self.root / PLOTS_SUBDIR

    @property
    def table_jsonl(self) -> Path:
        return self.root / TABLE_JSONL

    @property
    def table_parquet(self) -> Path:
        return self.root / TABLE_PARQUET

    # -- claims ------------------------------------------------------------------------------------------------

    def is_done(self, unit: Unit) -> bool:
        return self.result_path(unit).is_file()

    def try_claim(self, unit: Unit) -> bool:
        """Claim ``unit`` for this process: False when it is done or another live job holds it."""
        if self.is_done(unit):
            return False
        path = self.claim_path(unit)
        with exclusive_lock(self.root / CLAIMS_SUBDIR / ".lock"):
            if self.is_done(unit):  # finished by another job while we waited for the lock
                return False
            if path.exists():
                age = time.time() - path.stat().st_mtime
                if age < self.claim_timeout_s:
                    return False
                logger.warning("breaking stale claim %s (no heartbeat for %.0f s > %.0f s): %s", path.name, age,
                               self.claim_timeout_s, _read_claim(path))
                path.unlink()
            try:
                fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                return False
            with os.fdopen(fd, "w", encoding="utf-8") as handle:
                json.dump({"host": socket.gethostname(), "pid": os.getpid(), "since": time.time(),
                           "unit": unit.key}, handle)
        return True

    def heartbeat(self, unit: Unit) -> None:
        """Refresh the claim so that long evaluations are not taken for dead ones."""
        with contextlib.suppress(FileNotFoundError):
            os.utime(self.claim_path(unit))

    def release(self, unit: Unit) -> None:
        with contextlib.suppress(FileNotFoundError):
            self.claim_path(unit).unlink()

    # -- results -----------------------------------------------------------------------------------------------

    def write_result(self, unit: Unit, result: Mapping[str, Any], rows: Sequence[Mapping[str, Any]]) -> Path:
        """Write the result JSON (atomically: this marks the unit done), then add its table rows."""
        path = self.result_path(unit)
        atomic_write_text(path, json.dumps(result, indent=1, sort_keys=True, allow_nan=True) + "\n")
        self.append_rows(rows)
        return path

    def read_result(self, unit: Unit) -> dict[str, Any]:
        return json.loads(self.result_path(unit).read_text(encoding="utf-8"))

    def table_rows(self) -> list[dict[str, Any]]:
        """Every row of the results table (JSONL), in the order written."""
        if not self.table_jsonl.is_file():
            return []
        rows = []
        for number, line in enumerate(self.table_jsonl.read_text(encoding="utf-8").splitlines(), start=1):
            if line.strip():
                try:
                    rows.append(json.loads(line))
                except json.JSONDecodeError as exc:  # a torn last line from a crash mid-append
                    logger.warning("%s line %d is not JSON (%s); ignored", self.table_jsonl, number, exc)
        return rows

    def append_rows(self, rows: Sequence[Mapping[str, Any]]) -> None:
        """Append rows whose ``row_key`` is not in the table yet, then rewrite the Parquet copy."""
        with exclusive_lock(self.root / ".table.lock"):
            present = {row.get("row_key") for row in self.table_rows()}
            new = [dict(row) for row in rows if row["row_key"] not in present]
            if new:
                self.root.mkdir(parents=True, exist_ok=True)
                with open(self.table_jsonl, "a", encoding="utf-8") as handle:
                    for row in new:
                        handle.write(json.dumps(row, sort_keys=True, allow_nan=True) + "\n")
                    handle.flush()
                    os.fsync(handle.fileno())
            if new or not self.table_parquet.exists():
                write_parquet(self.table_rows(), self.table_parquet)


def write_parquet(rows: Sequence[Mapping[str, Any]], path: Path) -> None:
    """The table as Parquet: one column per key seen in any row (missing values null), written atomically."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    if not rows:
        return
    columns = sorted({key for row in rows for key in row})
    table = pa.table({name: [row.get(name) for row in rows] for name in columns})
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    pq.write_table(table, tmp)
    os.replace(tmp, path)


def _read_claim(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except OSError as exc:
        return f"<unreadable: {exc}>"


# ---------------------------------------------------------------------------------------------------------------
# Weights & Biases
# ---------------------------------------------------------------------------------------------------------------


def log_to_wandb(run_dir: Path, mode: str, project: str, step: int, scalars: Mapping[str, float],
                 config: Mapping[str, Any]) -> bool:
    """Log evaluation scalars under the training run (its ``wandb_id.txt``) against ``eval/train_step``.

    Training logs with W&B's own step; evaluation arrives later and out of order, so it gets its own step metric
    and never collides. Without the id file a separate run grouped under the run folder's name is created.
    Returns False (and logs why) when W&B is disabled or fails: evaluation results never depend on it.
    """
    mode = os.environ.get("WANDB_MODE", mode)
    if mode == "disabled":
        return False
    try:
        import wandb

        id_file = run_dir / "wandb_id.txt"
        resume = {"id": id_file.read_text().strip(), "resume": "allow"} if id_file.is_file() else {
            "group": run_dir.name, "name": f"{run_dir.name}-eval", "job_type": "eval"}
        os.environ.setdefault("WANDB_DIR", str(run_dir))
        run = wandb.init(project=project, mode=mode, dir=str(run_dir), **resume)
        try:
            run.define_metric("eval/train_step")
            run.define_metric("eval/*", step_metric="eval/train_step")
            run.config.update({"eval": dict(config)}, allow_val_change=True)
            run.log({"eval/train_step": step, **{f"eval/{k}": v for k, v in scalars.items()}})
        finally:
            run.finish()
    except Exception as exc:  # W&B must never fail an evaluation
        logger.warning("W&B logging skipped: %s", exc)
        return False
    return True
