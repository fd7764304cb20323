"""Where evaluation results live, and how concurrent evaluator jobs agree on who does what.

Layout of an evaluation folder (default ``<run_dir>/eval``)::

    results/<checkpoint>/<solver>-<N>steps-g<guidance>.<key>.json   one result per (checkpoint, settings): its
                                                                     presence marks the unit done
    results.jsonl                                                     the table: one row per result and one
    results.parquet                                                   ground-truth row, rewritten from the JSONL
    claims/<key>.claim                                                "someone is evaluating this unit now"
    checkpoints_seen.jsonl                                            every checkpoint a watcher has listed: one
                                                                      deleted before any result is reported
    cache/gt-<evaluator>-<dataset>-<split>-<gt key>.npz               ground-truth embeddings per evaluator and
                                                                      set (re-drawn items: one per replication;
                                                                      -padtext: with the mdm caption lengths)
    plots/*.png
    index.html                                                        the table and plots to browse
    mfm-eval.json                                                     the folder's marker: an evaluation folder of ours

One table, one test set: every row records the test set its result was scored on (``dataset_id``, derived from the
manifest when it was read, and ``split``); rows on another test set than the table's are refused before their result
file is written (:class:`MixedTestSetError`), so numbers on two test sets never stand side by side.

The folder is one of ours, or the evaluator writes nothing into it (:func:`check_eval_folder`): a new or empty folder
(the marker is written first), one holding our marker, or one an earlier version wrote before the marker existed
(only the names above, with its results table or listing among them). Anything else (another tool's ``index.html``
and ``plots/``, say) is refused before anything is written, so the evaluator never overwrites what it did not
write; the page itself is also written only over a page of ours (pipeline/generation/browse.py).

Concurrency. Any number of jobs (cron, Slurm array, Kubernetes CronJob, two shells) may watch the same run. A unit
is claimed by creating its claim file with ``O_CREAT | O_EXCL`` while holding an exclusive ``flock`` on
``claims/.lock`` (``pipeline.claims.take_claim``, shared with the trainer's run-folder lock); the holder refreshes the file's mtime (heartbeat) as it progresses. A claim records its holder's
host, pid and pid namespace: a claim from this host (and namespace) whose pid is no longer alive is stale at once, so
a restarted job picks up the units of the job it replaces (a killed job must not block its checkpoint for
``output.claim_timeout_s``). Claims from other hosts, or whose pid is alive (or reused), are stale only without a
heartbeat for ``claim_timeout_s``. Stale claims are broken under the same lock, so exactly one job takes a unit
over. The result JSON is written atomically (temp file + ``os.replace``) before the claim is removed, and the table
append skips rows whose key is already present, so a job killed between the two steps never duplicates a row.
``flock`` works on local disks and on NFSv4/Lustre mounts that support POSIX locks; ``O_EXCL`` alone still prevents
two claims.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline import checkpoint as ckpt
from pipeline.claims import (  # noqa: F401  (this_pid_namespace: part of this module's API)
    ClaimHolder,
    exclusive_lock,
    parse_record,
    read_record_text,
    take_claim,
    this_pid_namespace,
)

logger = logging.getLogger(__name__)

RESULTS_SUBDIR = "results"
CLAIMS_SUBDIR = "claims"
CACHE_SUBDIR = "cache"
PLOTS_SUBDIR = "plots"
TABLE_JSONL = "results.jsonl"
TABLE_PARQUET = "results.parquet"
SEEN_JSONL = "checkpoints_seen.jsonl"
PAGE_FILE = "index.html"  # pipeline.generation.browse.PAGE_FILE
EVAL_MARKER = "mfm-eval.json"
EVAL_MARKER_FORMAT = "mfm-eval"
# Every name an evaluation folder of ours holds at its top (the layout above, its lock files); a folder written before
# the marker existed is recognised by holding only these (and temporary files), its table or listing among them.
_EVAL_ENTRIES = frozenset({RESULTS_SUBDIR, CLAIMS_SUBDIR, CACHE_SUBDIR, PLOTS_SUBDIR, TABLE_JSONL, TABLE_PARQUET,
                           SEEN_JSONL, PAGE_FILE, EVAL_MARKER, ".seen.lock", ".table.lock"})
_EARLIER_EVAL_SIGNS = frozenset({RESULTS_SUBDIR, TABLE_JSONL, SEEN_JSONL})
_TEMPORARY_FILE = re.compile(r"^\.[^/]+\.tmp-\d+$")  # atomic_write_text's and write_page's temporary files
_SHOWN_ENTRIES = 5


class EvalFolderError(FileExistsError):
    """The evaluation folder (``output.dir``, default ``<run>/eval``) holds files that are not an evaluation's of
    ours: refused before anything is written; the message names the folder, what is there and what to pass."""


def check_eval_folder(root: str | Path) -> None:
    """Raise EvalFolderError unless ``root`` is new, empty, or an evaluation folder of ours (our marker, or one written
    by an earlier version before the marker: only the evaluator's own names, its table or listing among them)."""
    root = Path(root)
    if root.exists() and not root.is_dir():
        raise EvalFolderError(f"evaluation folder {root} is a file: pass a new or empty folder with output.dir=...")
    if not root.is_dir():
        return
    entries = sorted(entry.name for entry in root.iterdir())
    # Every rank checks while the main rank may be writing the marker: its temporary file is ours, not a stranger's.
    marker_in_progress = re.compile(rf"^\.{re.escape(EVAL_MARKER)}\.tmp-\d+$")
    if (all(marker_in_progress.match(name) for name in entries) or has_eval_marker(root)
            or _is_earlier_eval_folder(entries)):
        return
    shown = ", ".join(entries[:_SHOWN_ENTRIES]) + (f" and {len(entries) - _SHOWN_ENTRIES} more"
                                                  if len(entries) > _SHOWN_ENTRIES else "")
    raise EvalFolderError(
        f"evaluation folder {root} is a non-empty folder that is not an evaluation folder of ours (no {EVAL_MARKER}; "
        f"it holds {shown}): the evaluator's {PAGE_FILE}, {PLOTS_SUBDIR}/ and tables would overwrite or mix with "
        f"these. Pass a new or empty folder with output.dir=..., e.g. output.dir={root / 'eval'}")


def has_eval_marker(root: str | Path) -> bool:
    return ckpt.holds_marker(root, EVAL_MARKER, EVAL_MARKER_FORMAT)


def _is_earlier_eval_folder(entries: Sequence[str]) -> bool:
    known = all(name in _EVAL_ENTRIES or _TEMPORARY_FILE.match(name) for name in entries)
    return known and any(name in _EARLIER_EVAL_SIGNS for name in entries)


def write_eval_marker(root: str | Path) -> None:
    """Put ``mfm-eval.json`` into ``root`` (created if needed) unless it is there; call after
    :func:`check_eval_folder` and before anything else is written."""
    root = Path(root)
    if not has_eval_marker(root):
        atomic_write_text(root / EVAL_MARKER, json.dumps({"format": EVAL_MARKER_FORMAT, "version": 1,
                                                          "written_by": "pipeline/evaluation/store.py"}) + "\n")


class MixedTestSetError(ValueError):
    """Rows on another test set (dataset id, split) than the results table already holds: refused, nothing written."""


@dataclass(frozen=True)
class ScoredData:
    """The test set a result was computed on: the dataset id derived from the manifest's shard list, and the split."""

    dataset_id: str
    split: str

    @classmethod
    def of(cls, row: Mapping[str, Any]) -> ScoredData:
        """Of a table row (or a result's ``data`` section: the same keys)."""
        return cls(str(row.get("dataset_id")), str(row.get("split")))

    def describe(self) -> str:
        return f"test set {self.dataset_id[:16]} (split {self.split!r})"


@dataclass(frozen=True)
class Unit:
    """One piece of work: a checkpoint evaluated at one sampling point with fixed settings."""

    checkpoint_name: str
    """The checkpoint folder name, e.g. ``step-00001500``."""
    point_name: str
    """``euler-10steps-g2.5``: readable part of the result file name."""
    key: str
    """sha256 of everything that decides the numbers (checkpoint id, evaluator id, data, protocol, point)."""


@dataclass(frozen=True)
class SeenCheckpoint:
    """A complete checkpoint an evaluator job has listed (one line of ``checkpoints_seen.jsonl``)."""

    run: str
    """The run folder, resolved: one evaluation folder may serve several runs (``output.dir=``)."""
    name: str
    step: int
    checkpoint_id: str


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` so that readers see the old file or the whole new one, never a part."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "w", encoding="utf-8") as handle:
        handle.write(text)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)


class ResultsStore:
    """Claims, result files and the results table of one evaluation folder."""

    def __init__(self, root: str | Path, claim_timeout_s: float = 3600.0) -> None:
        if claim_timeout_s <= 0:
            raise ValueError(f"claim_timeout_s must be > 0, got {claim_timeout_s}")
        self.root = Path(root)
        self.claim_timeout_s = claim_timeout_s

    def open_folder(self, *, write_marker: bool) -> None:
        """Refuse a folder that is not an evaluation folder of ours (:func:`check_eval_folder`, on every rank, so all
        refuse alike); then, with ``write_marker`` (the main rank), put the marker in before anything else."""
        check_eval_folder(self.root)
        if write_marker:
            write_eval_marker(self.root)

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
        with exclusive_lock(self.root / CLAIMS_SUBDIR / ".lock"):
            if self.is_done(unit):  # finished by another job while we waited for the lock
                return False
            return take_claim(self.claim_path(unit), self.claim_timeout_s, unit=unit.key)

    def holder(self, unit: Unit) -> ClaimHolder | None:
        """The job holding ``unit`` per its claim file, or None when the unit is not claimed."""
        path = self.claim_path(unit)
        try:
            age = time.time() - path.stat().st_mtime
        except FileNotFoundError:
            return None
        return ClaimHolder.from_record(parse_record(read_record_text(path)), max(age, 0.0))

    def heartbeat(self, unit: Unit) -> None:
        """Refresh the claim so that long evaluations are not taken for dead ones."""
        with contextlib.suppress(FileNotFoundError):
            os.utime(self.claim_path(unit))

    def release(self, unit: Unit) -> None:
        with contextlib.suppress(FileNotFoundError):
            self.claim_path(unit).unlink()

    # -- checkpoints seen ------------------------------------------------------------------------------------

    @property
    def seen_jsonl(self) -> Path:
        return self.root / SEEN_JSONL

    def record_seen(self, checkpoints: Sequence[SeenCheckpoint]) -> None:
        """Remember checkpoints a watcher listed, so that one deleted (pruned by training's ``keep_last``) before
        any job evaluated it is reported by later jobs too, not only by the job that saw it."""
        with exclusive_lock(self.root / ".seen.lock"):
            known = set(self.seen())
            new = [c for c in checkpoints if c not in known]
            if new:
                with open(self.seen_jsonl, "a", encoding="utf-8") as handle:
                    handle.writelines(json.dumps({"run": c.run, "name": c.name, "step": c.step,
                                                  "checkpoint_id": c.checkpoint_id, "seen": time.time()}) + "\n"
                                      for c in new)
                    handle.flush()
                    os.fsync(handle.fileno())

    def seen(self) -> list[SeenCheckpoint]:
        """Every checkpoint recorded by :meth:`record_seen`, oldest record first (a torn last line is skipped)."""
        if not self.seen_jsonl.is_file():
            return []
        out = []
        for line in self.seen_jsonl.read_text(encoding="utf-8").splitlines():
            try:
                record = json.loads(line)
                out.append(SeenCheckpoint(str(record["run"]), str(record["name"]), int(record["step"]),
                                          str(record["checkpoint_id"])))
            except (json.JSONDecodeError, KeyError, TypeError, ValueError):
                continue
        return out

    def has_result_for(self, checkpoint_name: str, checkpoint_id: str) -> bool:
        """Whether any result (any setting) was written for this checkpoint: then it was evaluated, not lost."""
        for path in (self.root / RESULTS_SUBDIR / checkpoint_name).glob("*.json"):
            try:
                if json.loads(path.read_text(encoding="utf-8"))["checkpoint"]["id"] == checkpoint_id:
                    return True
            except (OSError, json.JSONDecodeError, KeyError, TypeError):
                continue
        return False

    # -- results -----------------------------------------------------------------------------------------------

    def write_result(self, unit: Unit, result: Mapping[str, Any], rows: Sequence[Mapping[str, Any]]) -> Path:
        """Write the result JSON (atomically: this marks the unit done), then add its table rows; both under the
        table's lock, after checking that the rows are on the table's test set (MixedTestSetError, nothing
        written)."""
        path = self.result_path(unit)
        with exclusive_lock(self.root / ".table.lock"):
            present = self.table_rows()
            self._refuse_mixed(present, rows)
            atomic_write_text(path, json.dumps(result, indent=1, sort_keys=True, allow_nan=True) + "\n")
            self._append_locked(present, rows)
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

    def scored_data(self) -> list[ScoredData]:
        """The test sets the table's results were computed on, in the order first written (one, or none yet)."""
        return list(dict.fromkeys(ScoredData.of(row) for row in self.table_rows()))

    def append_rows(self, rows: Sequence[Mapping[str, Any]]) -> None:
        """Append rows whose ``row_key`` is not in the table yet, then rewrite the Parquet copy. Rows on another test
        set than the table's are refused (MixedTestSetError), none of them written."""
        with exclusive_lock(self.root / ".table.lock"):
            present = self.table_rows()
            self._refuse_mixed(present, rows)
            self._append_locked(present, rows)

    def _refuse_mixed(self, present: Sequence[Mapping[str, Any]], rows: Sequence[Mapping[str, Any]]) -> None:
        """One table, one test set: FID or R-precision on two test sets side by side would read as comparable."""
        earlier = list(dict.fromkeys(ScoredData.of(row) for row in present))
        both = list(dict.fromkeys([*earlier, *(ScoredData.of(row) for row in rows)]))
        if len(both) > 1:
            new = [data for data in both if data not in earlier]
            raise MixedTestSetError(
                f"{self.table_jsonl}: holds results on {', '.join(d.describe() for d in earlier)}"
                + (f"; refusing to add results on {', '.join(d.describe() for d in new)}" if new else
                   " (written before the table refused a second test set)")
                + ": one table never mixes test sets. Evaluate into another folder: output.dir=...")

    def _append_locked(self, present: Sequence[Mapping[str, Any]], rows: Sequence[Mapping[str, Any]]) -> None:
        """Append the rows not in ``present`` (the table as read under the lock) and rewrite the Parquet copy."""
        keys = {row.get("row_key") for row in present}
        new = [dict(row) for row in rows if row["row_key"] not in keys]
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


# ---------------------------------------------------------------------------------------------------------------
# Weights & Biases
# ---------------------------------------------------------------------------------------------------------------


def log_to_wandb(run_dir: Path, mode: str, project: str, step: int, scalars: Mapping[str, float],
                 config: Mapping[str, Any]) -> bool:
    """Log evaluation scalars under the training run (its ``wandb_id.txt``) against ``eval/train_step``.

    Training logs with W&B's own step; evaluation arrives later and out of order, so it gets its own step metric
    and never collides. Without the id file a separate run grouped under the run folder's name is created.
    Returns False (and logs why) when W&B is disabled or fails: evaluation results never depend on it. ``mode`` is
    the resolved one (pipeline.config.wandb_mode): ``WANDB_MODE`` does not override it here.
    """
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
