"""The training data stream: exactly once per epoch, equal batch counts on every rank, bit-exact resume.

Stages, in order (each a named function or class; the per-sample ones live in ``pipeline.data.stages``)::

    split_shards(manifest, split)              shard list from the manifest (paths resolved against its location)
    plan_epoch(...)                            per-epoch shuffle of the shards from (seed, epoch), then every
                                               shard assigned to one reader slot (rank × DataLoader worker)
    shuffle_buffer_order(...)                  the slot's sample order: a shuffle buffer seeded by
                                               (seed, epoch, slot), computed from counts before reading
    length_grouped_order(...)                  data.batching=length_aware only: that order regrouped so that
                                               clips of similar length (the manifest's lengths) share a batch
    ordered_records(...)                       read the slot's shards (webdataset tar or Parquet) and emit raw
                                               records in that order, skipping already-consumed ones undecoded
    DecodeTarRecord | DecodeParquetRow         → MotionRecord (features, all captions, spans, text embeddings)
    PickCaption                                one caption, motion cut to its span
    CropToWindow                               MDM/MFM random crop (multiple of unit_length, ≤ window frames)
    Normalize                                  manifest Mean/Std
    Collate                                    padded batch + masks (keys: see ``pipeline.data.stages.Collate``),
                                               padded to the window, or (length_aware) to the batch's longest clip

The per-reader part runs as a ``webdataset.DataPipeline`` inside each DataLoader worker (or in the main
process with ``num_workers=0``). Unlike open_clip, the shuffle buffer acts before decoding: its order is
computed from the sample counts, so a resumed stream can skip consumed positions without decoding them;
the order is statistically the same as a buffer placed after normalisation.

Exactly once, equal batches (the policy). Each epoch the shard list is shuffled with (seed, epoch) and dealt
to ``world_size × max(1, num_workers)`` reader slots, each shard to the currently least-loaded slot (by the
manifest's per-shard counts), so every process can compute every slot's sample count without any
communication. Every reader yields the same number of full batches, ``min over slots of
(slot samples // batch_size)``; the samples past that point in each slot are dropped for this epoch
(``EpochPlan.samples_dropped``). Which samples are dropped changes from epoch to epoch because the shard
assignment and the buffer order do. A sample is never seen twice in an epoch because each shard belongs to
exactly one slot. Fewer shards than reader slots is refused: a reader without a shard would hang its rank.

Length-aware batches (``LoaderOptions.batching="length_aware"``, training's ``data.batching``). The slot's
emission order, cut to the epoch's batch count as above, is regrouped before anything is read
(:func:`~pipeline.data.stages.length_grouped_order`): windows of ``sort_window_batches`` batches' worth of consecutive
samples are sorted by the manifest's clip lengths (capped at the window), cut into batches, and the batches of each
window put in an order drawn from (seed, epoch, slot). Each batch is then padded to its longest cropped clip rounded up
to ``pad_multiple`` frames, at most the window. The samples of an epoch, the batch count of every reader and rank,
and what is dropped are exactly those of fixed windows; only which samples share a batch changes. The grouping uses
the manifest's lengths (the whole record, capped at the window), the width the clips as cropped, so a manifest whose
lengths are wrong costs padding, never a sample or exactness. A manifest without per-record lengths (or with a list
that does not match its counts) is refused naming it. Memory: a reader holds at most a shuffle buffer plus one sort
window of raw records.

Resume. ``state_dict()`` is ``{epoch, batches_in_epoch, seed, world_size, num_workers, ...}``; it is the same
on every rank. Every random draw is a function of (seed, epoch, slot) or (seed, epoch, sample id), never of
what has been consumed, so a resumed loader recomputes the slot orders, drops the first
``batches_in_epoch`` batches' worth of sample positions before reading, and produces bit-identical next
batches. Cost of the fast-forward: shards whose samples were all consumed are not opened; the (at most a
shuffle buffer's worth of) remaining shards are read from their start, but skipped records are not decoded;
Parquet reads only the row groups that hold needed rows (a remote part checked while read is downloaded
whole). A changed world size, worker count, batch size or seed is refused. With workers, the DataLoader takes
batches from workers round-robin; the workers are rotated on resume so that worker ``k`` of the new iterator
plays the reader that owns the next batch, and each batch carries its (epoch, index) stamp, which the loader
checks.

Verification. Every reader of shards (training, the evaluator's ground truth, evaluator training, tools)
checks them first with :func:`verify_shards`: the split's totals against its shard counts and lengths, and
every shard's size, sha256, real record count and record ids (unique in the split), in one read per shard; then
that the split's folders hold no file the manifest does not list (:func:`unlisted_files`, local data), and that
the manifest's stored dataset id is the one derived from its shard list (``Manifest.dataset_id``: everything
records the derived id). ``strict`` refuses a bad shard, an unlisted file, an inconsistent manifest or an edited id,
naming the file or manifest and the reason; ``tolerant`` leaves bad shards out (``exclude_shards``), goes on under the
derived id, and reports everything it found (``verified`` false). A shard read and
found good is remembered in a small cache (``pipeline.data.shard_cache``: manifest entry, record ids, and the file's
size + mtime/ctime/inode, or a URL's content hash such as GCS's md5Hash); a later start takes an unchanged shard's
verdict from it without reading it (``VerificationReport.num_from_cache``). A URL known only by a weak validator
(an ETag, which nginx derives from size and mtime, Last-Modified, a version id) is hashed on every start.

Remote shards are checked again as they are read (``LoaderOptions.check_remote_bytes``; every mode but ``off``):
the reader downloads a remote shard whole into a local spool, hashing it as the bytes arrive (the one read it
makes anyway), and compares size and sha256 with the manifest before it parses a single record
(:func:`checked_remote_copy`). A shard changed since verification is therefore never used, whenever it changed (an
in-place rewrite that keeps the server's ETag, an object replaced between two epochs): strict raises
:class:`ShardChangedError` naming the URL from the batch iterator, so the trainer stops before the next step, let
alone the next checkpoint; tolerant skips the shard's records (counted, logged), keeping the batch plan. Local
shards are not re-hashed while read (their stat fingerprint was checked at start).

The local shard cache (``LoaderOptions.cache_dir``, training's ``data.cache_dir``; off by default;
:mod:`pipeline.data.download_cache`). A remote shard is downloaded once into it, hashed as it is written and kept
(under its manifest sha256) only when it matches the manifest, then read from the local copy every later epoch and
run instead of the spool above (:func:`cached_remote_copy`); bytes that do not match raise
:class:`ShardChangedError` as above and nothing is kept. Each open checks the copy's size (a truncated copy is
downloaded again); :func:`verify_shards` given the cache (``downloads``) checks remote shards from their copies,
hashing each in full (a damaged copy is downloaded again), so a start needs no network for shards already there.
Local shards are never copied. Counts: ``MotionLoader.shards_from_cache`` / ``shards_fetched`` and the report's
``num_cache_served`` / ``num_downloaded``.

Where data lives. Shard and manifest locations are local paths or any fsspec URL (``s3://``, ``gs://``,
``https://``, ``memory://``, ...; ``pipeline.data.locations``; the cloud packages are the ``remote`` extra). Shard paths
in the manifest are relative to the manifest's own location; one that leaves it (an absolute path, a URL, '..') is
refused unless ``allow_external_shards`` (:meth:`Manifest.shard_location`). Transient errors (connection reset,
timeout, HTTP 5xx/429) are retried with exponential back-off (``LoaderOptions.retries``/``retry_backoff_s``); a shard
read that fails half way is re-opened and the records already yielded are passed over (:func:`read_shard`), so the
stream, and exact resume, are the same as without the failure.

Tolerant mode at run time (``LoaderOptions.tolerate_bad_data``). A record that fails to decode or validate
(e.g. non-finite features) is left out of its batch, counted and logged; it keeps its place in the stream
until the batch is collated, so batch boundaries, the resume position and every later batch are the same as
if it had been read (the skip is a function of the record's bytes, so a resumed run skips it again at the
same place; exact resume holds). A batch whose every record was skipped is NOT passed over: it is yielded as
an empty batch (zero rows, ``ids == []``; counted in ``empty_batches``), so every rank still takes exactly one
planned batch per step and all ranks agree on the number of batches per epoch and on the data position (a
rank that passed it over would run one batch ahead of the others and could run out of batches a step before
them, which hangs a collective). The trainer steps through an empty batch with zero weight in the loss
(``pipeline.training.trainer.Trainer.train_step``). Shards excluded
since the checkpoint (a shard that went bad after it; or readmitted, repaired ones): the checkpoint's epoch
is finished with the plan it started with, so the batches still due are the ones that were due, except that
the records of newly excluded shards are left out of their batches (counted as skipped records, their files
never opened) and readmitted shards wait for the next epoch; every later epoch is planned with the shards
excluded now. The state records that rule (``carried_epoch``) until the epoch ends, so a second resume in
the same epoch continues the same way. Strict mode refuses a changed exclusion list in the middle of an epoch
(at an epoch boundary there is nothing to finish: the next epoch is planned with the current list).

Accelerate. Never pass this loader (or a DataLoader built from it) through ``accelerator.prepare()``: it is
already sharded by rank, and prepare() would shard it again and silently drop data (accelerate issue 3547).
The trainer moves batches to its device itself.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import heapq
import itertools
import json
import logging
import os
import tarfile
import tempfile
import time
import urllib.parse
from collections import Counter
from dataclasses import dataclass, field, replace
from typing import Any, BinaryIO, Callable, Iterable, Iterator, Mapping, Sequence

import numpy as np
import webdataset as wds
from torch.utils.data import DataLoader, IterableDataset, get_worker_info
from webdataset.tariterators import group_by_keys, tar_file_expander

from pipeline.data.locations import (  # noqa: F401  (is_url, resolve_location, open_binary: part of this module's API)
    DEFAULT_RETRY,
    READ_BUFFER,
    RemoteSupportMissing,
    RetriesExhausted,
    RetryPolicy,
    call_with_retries,
    describe,
    fingerprint,
    http_status,
    is_transient,
    is_url,
    local_path,
    open_binary,
    open_seekable,
    require_support,
    resolve_location,
    scheme_of,
    wait_before_retry,
)
from pipeline.data.download_cache import DownloadMismatch, ShardDownloadCache
from pipeline.data.shard_cache import RACY_S, VerificationCache
from pipeline.data.stages import (
    CAPTION_POLICIES,
    SKIPPED_RECORDS_KEY,
    Collate,
    CropToWindow,
    DataError,
    DecodeParquetRow,
    DecodeTarRecord,
    MotionRecord,
    Normalize,
    ParquetRow,
    PickCaption,
    RecordSpec,
    SkipBadRecords,
    SkippedRecord,
    length_grouped_order,
    shuffle_buffer_order,
)
from preprocess.shards import (
    PAIRS_KEY,
    MANIFEST_NAME,
    READABLE_FORMAT_VERSIONS,
    ManifestError,
    dataset_id_problem,
    derive_dataset_id,
    load_manifest,
    shard_path_problem,
)

logger = logging.getLogger(__name__)

BACKENDS = ("webdataset", "parquet")
BATCHINGS = ("fixed", "length_aware")


def backend_for_format(fmt: str) -> str:
    """The loader backend that reads a config's ``format``: "tar" shards -> webdataset, "parquet" -> parquet."""
    if fmt not in ("tar", "parquet"):
        raise ValueError(f"data format must be 'tar' or 'parquet', got {fmt!r}")
    return "parquet" if fmt == "parquet" else "webdataset"
_MANIFEST_LIST_KEY = {"webdataset": "shards", "parquet": "parquet"}
_TAG_SHARD_SHUFFLE = 11
_TAG_SAMPLE_SHUFFLE = 12
_TAG_LENGTH_BATCHES = 13
STATE_VERSION = 1


# Locations (local paths and fsspec URLs: is_url, resolve_location, open_binary, ...), retries (RetryPolicy) and
# file fingerprints live in pipeline.data.locations, imported above; the verification cache in pipeline.data.shard_cache.


# ----------------------------------------------------------------------------------------------------------
# Manifest
# ----------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Manifest:
    """A dataset's ``manifest.json`` and where it was read from (shard paths are relative to it).

    ``dataset_id`` is derived from the manifest's shard list each time a manifest is read
    (``preprocess.shards.derive_dataset_id``), never taken from the file: what a run, checkpoint or result records is
    the id of the data it read. A stored id that differs is reported (:attr:`dataset_id_problem`) and refused by
    strict verification. ``allow_external_shards``: whether shard paths may leave the manifest's own folder (see
    :meth:`shard_location`)."""

    data: Mapping[str, Any]
    location: str
    allow_external_shards: bool = False

    def split(self, name: str) -> Mapping[str, Any]:
        splits = self.data.get("splits", {})
        if name not in splits:
            raise ManifestError(f"{self.location}: no split {name!r} (has {sorted(splits)})")
        return splits[name]

    @functools.cached_property
    def dataset_id(self) -> str:
        """The id derived from the shard list (format 1: from the files' sha256s only)."""
        return derive_dataset_id(self.data)

    @property
    def stored_dataset_id(self) -> str:
        """The id written in the file (trust :attr:`dataset_id`)."""
        return str(self.data.get("dataset_id", ""))

    @functools.cached_property
    def dataset_id_problem(self) -> str | None:
        """Why the stored id is not the derived one (the manifest was edited after the build), or None."""
        return dataset_id_problem(self.data)

    def shard_location(self, path: str) -> str:
        """Where a shard path of this manifest points: resolved under the manifest's own folder or URL. An absolute
        path, a URL (``file://``, another host or scheme) or a '..' segment (also percent-encoded, for a URL
        manifest) is refused with a ManifestError unless ``allow_external_shards``; a ``pipe:`` path (a shell
        command to webdataset) is refused always."""
        if scheme_of(path) == "pipe":
            raise ManifestError(f"{self.location}: shard path {path!r} is a shell command (pipe:), which a manifest "
                                "may not name")
        problem = shard_path_problem(path)
        decoded = urllib.parse.unquote(path)
        if problem is None and is_url(self.location) and shard_path_problem(decoded):  # a server reads %2e%2e as ..
            problem = f"{shard_path_problem(decoded)} once percent-decoded ({decoded!r})"
        if problem is not None and not self.allow_external_shards:
            raise ManifestError(f"{self.location}: shard path {path!r} {problem}: shards must lie under the manifest's "
                                "own location (set data.allow_external_shards=true to read it anyway)")
        return resolve_location(self.location, path)

    @property
    def record_spec(self) -> RecordSpec:
        text = self.data["text_encoder"]
        return RecordSpec(
            feature_dim=int(self.data["feature_spec"]["dim"]),
            text_dim=int(text["dim"]),
            token_features=bool(text.get("token_features", False)),
            max_tokens=int(text.get("max_tokens", 0)),
            noise_seeds=PAIRS_KEY in self.data,
        )

    @property
    def pair_set_source(self) -> str | None:
        """For a distillation pair set (pipeline/generation/pairs.py): where the teacher's dataset, whose training
        captions the pairs are made of, was read; None for any other dataset."""
        if PAIRS_KEY not in self.data:
            return None
        return (self.data.get("builder") or {}).get("options", {}).get("source_manifest")

    @property
    def mean(self) -> np.ndarray:
        return np.asarray(self.data["normalization"]["mean"], np.float32)

    @property
    def std(self) -> np.ndarray:
        return np.asarray(self.data["normalization"]["std"], np.float32)

    @property
    def action_classes(self) -> tuple[str, ...]:
        return tuple(self.data.get("action_classes") or ())

    def consistency_problems(self, split: str, backends: Sequence[str] = BACKENDS) -> list[str]:
        """Where the split's own numbers disagree: ``num_motions`` against the number of ``lengths`` and against
        the sum of the shard counts of each listed backend, ``num_frames`` against the sum of ``lengths``, a
        shard listed twice. The loader plans epochs from the shard counts alone, so a disagreement means that
        either the counts or the totals are wrong; :func:`verify_shards` then finds which shard (by reading
        it) and refuses (strict) or reports it (tolerant)."""
        entry = self.split(split)
        where = f"split {split!r}"
        if not isinstance(entry, Mapping):
            return [f"{where}: not a JSON object"]
        problems = []
        total = entry.get("num_motions")
        lengths = entry.get("lengths")
        if not isinstance(total, int) or total < 0:
            return [f"{where}: num_motions is {total!r}, not a count"]
        if lengths is not None and len(lengths) != total:
            problems.append(f"{where}: num_motions is {total} but {len(lengths)} lengths are listed")
        if lengths is not None and "num_frames" in entry and entry["num_frames"] != sum(lengths):
            problems.append(f"{where}: num_frames is {entry['num_frames']} but the lengths add up to {sum(lengths)}")
        for backend in backends:
            files = entry.get(_MANIFEST_LIST_KEY[backend]) or []
            if not files:
                continue
            counts = [f.get("num_motions") if isinstance(f, Mapping) else None for f in files]
            if not all(isinstance(n, int) for n in counts):
                problems.append(f"{where}: {_MANIFEST_LIST_KEY[backend]} entries without an integer num_motions")
                continue
            counted = sum(counts)
            if counted != total:
                problems.append(f"{where}: num_motions is {total} but the counts of its {len(files)} "
                                f"{_MANIFEST_LIST_KEY[backend]} entries add up to {counted}")
            paths = Counter(f.get("path") for f in files if isinstance(f, Mapping))
            twice = sorted(str(path) for path, n in paths.items() if n > 1)
            if twice:
                problems.append(f"{where}: {_MANIFEST_LIST_KEY[backend]} entries listed more than once: {twice}")
        return problems


def _check_remote_manifest(data: Any, location: str) -> None:
    """The fields the loader relies on, for a manifest read from a URL (``load_manifest`` checks local ones)."""
    if not isinstance(data, dict):
        raise ManifestError(f"{location}: a manifest must be a JSON object")
    if data.get("format_version") not in READABLE_FORMAT_VERSIONS:
        raise ManifestError(f"{location}: format_version {data.get('format_version')!r}, this code reads versions "
                            f"{', '.join(map(str, READABLE_FORMAT_VERSIONS))}")
    missing = [key for key in ("feature_spec", "normalization", "text_encoder", "splits") if key not in data]
    if missing:
        raise ManifestError(f"{location}: missing keys {missing}")


def open_manifest(location: str | os.PathLike | Manifest, *, retry: RetryPolicy | None = None,
                  allow_external_shards: bool = False) -> Manifest:
    """Read ``manifest.json`` from a local path (or its dataset folder) with the builder's ``load_manifest``, or
    from a URL (``https://host/ds/manifest.json``, ``s3://bucket/ds/manifest.json``, or the folder URL ending in
    ``/``), retrying transient errors (``retry``). Files are not checked here: see :func:`verify_shards`, which also
    refuses (strict) or reports (tolerant) a stored dataset id that is not the derived one; here it is logged.
    ``allow_external_shards``: see :meth:`Manifest.shard_location`. A :class:`Manifest` is returned as it is."""
    if isinstance(location, Manifest):
        return location
    location = os.fspath(location)
    if not is_url(location):
        path = os.path.join(location, MANIFEST_NAME) if os.path.isdir(location) else location
        manifest = Manifest(data=load_manifest(path, verify="none"), location=os.path.abspath(path),
                            allow_external_shards=allow_external_shards)
    else:
        if location.endswith("/"):
            location += MANIFEST_NAME
        try:
            require_support(location)

            def read() -> Any:
                with open_binary(location) as stream:
                    return json.loads(stream.read())

            data = call_with_retries(read, location, "reading the manifest", retry)
        except (OSError, ValueError, RetriesExhausted, RemoteSupportMissing) as exc:
            raise ManifestError(f"{location}: cannot read manifest: {exc}") from exc
        _check_remote_manifest(data, location)
        manifest = Manifest(data=data, location=location, allow_external_shards=allow_external_shards)
    _warn_inconsistent(manifest)
    return manifest


def _warn_inconsistent(manifest: Manifest) -> None:
    """Say at once when a manifest contradicts itself or carries an id that is not its own; whether that stops a
    reader is the verification mode's decision (:func:`verify_shards`), taken when the split is read."""
    splits = manifest.data.get("splits")
    if not isinstance(splits, Mapping):
        raise ManifestError(f"{manifest.location}: 'splits' must be a JSON object")
    for split in splits:
        for problem in manifest.consistency_problems(split):
            logger.warning("%s: inconsistent manifest: %s", manifest.location, problem)
    if manifest.dataset_id_problem:
        logger.warning("%s: %s; everything read from it records the derived id %s", manifest.location,
                       manifest.dataset_id_problem, manifest.dataset_id)
    if manifest.data.get("format_version") == 1:
        logger.info("%s: a format-1 manifest, whose dataset id covers its files' sha256s but not which split lists "
                    "them, nor counts or lengths; rebuilding gives a format-2 manifest (and a new id)",
                    manifest.location)


@dataclass(frozen=True)
class ShardInfo:
    """One shard (a tar or a Parquet part) as the manifest lists it."""

    path: str  # as written in the manifest, relative to it: the name used in reports and exclude lists
    url: str  # resolved location
    num_motions: int
    bytes: int
    sha256: str
    lengths: tuple[int, ...] | None = field(default=None, repr=False, compare=False)
    """Frames of each record in file order, from the split's ``lengths`` list; None when the manifest has no list
    that matches its counts (:func:`split_lengths_problem` says why). Only length-aware batching reads it."""


def split_lengths_problem(entry: Mapping[str, Any], shards: Sequence[ShardInfo]) -> str | None:
    """Why the split's ``lengths`` cannot give each shard's record lengths (None: they can). The builder lists one
    length per record, in shard order (each backend's list holds the same records in the same order)."""
    lengths = entry.get("lengths")
    total = sum(s.num_motions for s in shards)
    if lengths is None:
        return "it lists no 'lengths'"
    if not isinstance(lengths, list) or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0
                                                for n in lengths):
        return "its 'lengths' are not a list of frame counts"
    if len(lengths) != total:
        return f"it lists {len(lengths)} lengths for {total} records"
    return None


def split_shards(manifest: Manifest, split: str, backend: str = "webdataset") -> list[ShardInfo]:
    """Stage 1: the shards of a split in manifest order."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    entries = manifest.split(split).get(_MANIFEST_LIST_KEY[backend]) or []
    if not entries:
        raise ManifestError(f"{manifest.location}: split {split!r} lists no {backend} files")
    shards = []
    for index, e in enumerate(entries):
        try:
            shard = ShardInfo(path=str(e["path"]), url="", num_motions=int(e["num_motions"]), bytes=int(e["bytes"]),
                              sha256=str(e["sha256"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise ManifestError(f"{manifest.location}: split {split!r}, {_MANIFEST_LIST_KEY[backend]} entry {index}: "
                                f"malformed ({type(exc).__name__}: {exc})") from exc
        if shard.num_motions < 0 or shard.bytes < 0:
            raise ManifestError(f"{manifest.location}: {shard.path}: negative num_motions or bytes in the manifest")
        shards.append(replace(shard, url=manifest.shard_location(shard.path)))
    if split_lengths_problem(manifest.split(split), shards) is None:
        lengths, start = manifest.split(split)["lengths"], 0
        for index, shard in enumerate(shards):
            shards[index] = replace(shard, lengths=tuple(lengths[start:start + shard.num_motions]))
            start += shard.num_motions
    return shards


# ----------------------------------------------------------------------------------------------------------
# Epoch plan: shard shuffle and assignment to reader slots
# ----------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class EpochPlan:
    """Which shards each reader slot (slot = rank × readers_per_rank + worker) reads in one epoch, and how
    many batches every reader yields. Computed identically by every process from the manifest counts."""

    epoch: int
    world_size: int
    readers_per_rank: int
    batch_size: int
    slot_shards: tuple[tuple[int, ...], ...]  # indices into the loader's shard list, in reading order
    slot_samples: tuple[int, ...]

    @property
    def num_slots(self) -> int:
        return len(self.slot_shards)

    def slot(self, rank: int, reader: int) -> int:
        return rank * self.readers_per_rank + reader

    @property
    def batches_per_reader(self) -> int:
        return min(self.slot_samples) // self.batch_size

    @property
    def batches_per_rank(self) -> int:
        return self.batches_per_reader * self.readers_per_rank

    @property
    def samples_in_epoch(self) -> int:
        return sum(self.slot_samples)

    @property
    def samples_used(self) -> int:
        return self.num_slots * self.batches_per_reader * self.batch_size

    @property
    def samples_dropped(self) -> int:
        return self.samples_in_epoch - self.samples_used


def shard_order(num_shards: int, seed: int, epoch: int, shuffle: bool) -> np.ndarray:
    """Stage 2: the epoch's shard order, a permutation drawn from (seed, epoch)."""
    if not shuffle:
        return np.arange(num_shards)
    return np.random.default_rng(np.random.SeedSequence([seed, epoch, _TAG_SHARD_SHUFFLE])).permutation(num_shards)


def assign_shards(order: Sequence[int], shard_sizes: Sequence[int], num_slots: int) -> list[list[int]]:
    """Stage 3: deal shards, in ``order``, each to the least-loaded slot (ties → lowest slot). Balancing
    by sample count keeps the per-epoch remainder small with uneven shards; the first ``num_slots`` shards
    go one to each slot, so no slot is empty when there are enough shards."""
    heap = [(0, slot) for slot in range(num_slots)]
    slots: list[list[int]] = [[] for _ in range(num_slots)]
    for shard in order:
        load, slot = heapq.heappop(heap)
        slots[slot].append(int(shard))
        heapq.heappush(heap, (load + int(shard_sizes[shard]), slot))
    return slots


def plan_epoch(shard_sizes: Sequence[int], *, epoch: int, seed: int, world_size: int, readers_per_rank: int,
               batch_size: int, shuffle: bool) -> EpochPlan:
    num_slots = world_size * readers_per_rank
    slots = assign_shards(shard_order(len(shard_sizes), seed, epoch, shuffle), shard_sizes, num_slots)
    return EpochPlan(epoch=epoch, world_size=world_size, readers_per_rank=readers_per_rank,
                     batch_size=batch_size, slot_shards=tuple(tuple(s) for s in slots),
                     slot_samples=tuple(sum(shard_sizes[i] for i in s) for s in slots))


def slot_sample_order(num_samples: int, *, seed: int, epoch: int, slot: int, shuffle: bool,
                      buffer_size: int) -> np.ndarray:
    """Stage 4: the order in which one slot emits its samples (positions in its concatenated shards)."""
    if not shuffle:
        return np.arange(num_samples, dtype=np.int64)
    rng = np.random.default_rng(np.random.SeedSequence([seed, epoch, slot, _TAG_SAMPLE_SHUFFLE]))
    return shuffle_buffer_order(num_samples, buffer_size, rng)


# ----------------------------------------------------------------------------------------------------------
# Shard verification (before any record is used)
# ----------------------------------------------------------------------------------------------------------

VERIFY_MODES = ("strict", "tolerant", "off")
VERIFICATION_CHECKS = ("manifest_totals", "size", "sha256", "record_count", "unique_ids", "unlisted_files",
                       "dataset_id")


class ShardVerificationError(DataError, RuntimeError):
    """A shard is missing, truncated, corrupted or does not hold the records the manifest says, or the
    manifest contradicts itself (strict verification). The message names the file and the reason."""


@dataclass(frozen=True)
class BadShard:
    path: str
    reason: str
    num_motions: int  # as the manifest counts it: what the epoch plan would have used


@dataclass(frozen=True)
class VerificationReport:
    split: str
    backend: str
    mode: str
    num_checked: int
    bad: tuple[BadShard, ...] = ()
    manifest_problems: tuple[str, ...] = ()
    """Disagreements of the split's totals with its shard counts and lengths (tolerant mode goes on with the
    shard counts, which verification has checked against the shards themselves)."""
    num_from_cache: int = 0
    """Shards of ``num_checked`` whose verdict came from the verification cache: hashed by an earlier check, and
    unchanged since by their size and fingerprint (``pipeline.data.shard_cache``)."""
    dataset_id: str = ""
    """The id derived from the manifest's shard list: the id of the data this report is about."""
    unlisted_files: tuple[str, ...] = ()
    """Entries of the split's folders that no split of the manifest lists (paths relative to the manifest): data
    the manifest does not account for, e.g. a shard whose entry was removed (:func:`unlisted_files`)."""
    unlisted_files_checked: bool = False
    """Whether the split's folders were listed (local data only: object stores and HTTP servers are not)."""
    num_cache_served: int = 0
    """Remote shards checked from their copy in the local shard cache (``data.cache_dir``), not downloaded."""
    num_downloaded: int = 0
    """Remote shards downloaded into the local shard cache by this verification (none there, or a copy found
    damaged)."""

    @property
    def bad_paths(self) -> tuple[str, ...]:
        """Pass this to ``MotionLoader(exclude_shards=...)``; broadcast rank 0's copy to keep ranks equal."""
        return tuple(b.path for b in self.bad)

    @property
    def samples_lost(self) -> int:
        return sum(b.num_motions for b in self.bad)

    @property
    def verified(self) -> bool:
        """Every shard was checked and matched the manifest, the manifest agrees with itself and carries its own
        dataset id, and the split's folders hold no file it does not list."""
        return self.mode != "off" and not self.bad and not self.manifest_problems and not self.unlisted_files

    def as_dict(self) -> dict[str, Any]:
        """For run folders and results files: what was checked, and what was found."""
        return {"split": self.split, "backend": self.backend, "mode": self.mode, "verified": self.verified,
                "checks": list(VERIFICATION_CHECKS) if self.mode != "off" else [],
                "num_checked": self.num_checked, "num_from_cache": self.num_from_cache,
                "num_cache_served": self.num_cache_served, "num_downloaded": self.num_downloaded,
                "samples_lost": self.samples_lost,
                "bad": [{"path": b.path, "reason": b.reason, "num_motions": b.num_motions} for b in self.bad],
                "manifest_problems": list(self.manifest_problems), "dataset_id": self.dataset_id,
                "unlisted_files": list(self.unlisted_files), "unlisted_files_checked": self.unlisted_files_checked}


class _HashingReader:
    """A read-only stream that hashes every byte read through it, so that one read of a shard gives its
    sha256 and its records: the tar is parsed from exactly the bytes that are hashed."""

    def __init__(self, stream: BinaryIO):
        self._stream = stream
        self._digest = hashlib.sha256()
        self.size = 0

    def read(self, size: int = -1) -> bytes:
        block = self._stream.read(size)
        self._digest.update(block)
        self.size += len(block)
        return block

    def drain(self, chunk: int = 1 << 20) -> None:
        """Read (and hash) the rest: the tar parser stops at the end-of-archive marker, before the padding."""
        while self.read(chunk):
            pass

    @property
    def sha256(self) -> str:
        return self._digest.hexdigest()


def _hash_stream(stream: BinaryIO, chunk: int = 1 << 20) -> tuple[int, str]:
    reader = _HashingReader(stream)
    reader.drain(chunk)
    return reader.size, reader.sha256


@dataclass(frozen=True)
class ShardContent:
    """What one read of a shard found: its size and sha256, and the ids of its records in file order
    (``record_ids`` is None when they could not be listed, ``listing_error`` says why)."""

    bytes: int
    sha256: str
    record_ids: tuple[str, ...] | None
    listing_error: str | None = None


# The errors a damaged tar raises from the parser (the same list the training reader turns into ShardReadError).
_TAR_ERRORS = (OSError, ValueError, EOFError, KeyError, tarfile.TarError)


def _tar_records(stream: BinaryIO, url: str) -> Iterator[dict]:
    """The raw webdataset samples of a tar stream, grouped by key: how training reads a shard, and how
    verification counts its records, so that both see the same records."""
    return group_by_keys(tar_file_expander([{"url": url, "stream": stream}]))


def _read_tar_content(shard: ShardInfo) -> ShardContent:
    """Hash the tar and list its records' keys in the same pass."""
    with open_binary(shard.url) as stream:
        reader = _HashingReader(stream)
        keys: list[str] = []
        error = None
        try:
            keys = [str(raw["__key__"]) for raw in _tar_records(reader, shard.url)]
        except _TAR_ERRORS as exc:
            if is_transient(exc):  # the connection, not the shard: read it again (check_shard retries)
                raise
            error = f"{type(exc).__name__}: {exc}"
        reader.drain()
    return ShardContent(bytes=reader.size, sha256=reader.sha256, record_ids=None if error else tuple(keys),
                        listing_error=error)


def _read_parquet_content(shard: ShardInfo) -> ShardContent:
    """Hash the Parquet part, then (only when it matches the manifest) read its ``id`` column."""
    import pyarrow.parquet as pq

    with open_binary(shard.url) as stream:
        size, sha = _hash_stream(stream)
    if size != shard.bytes or sha != shard.sha256:
        return ShardContent(bytes=size, sha256=sha, record_ids=None, listing_error="not read (bytes differ)")
    try:
        source = open_seekable(shard.url)
        with contextlib.nullcontext() if isinstance(source, str) else source, pq.ParquetFile(source) as part:
            ids = part.read(columns=["id"]).column("id").to_pylist()
    except (OSError, ValueError, KeyError) as exc:
        if is_transient(exc):
            raise
        return ShardContent(bytes=size, sha256=sha, record_ids=None, listing_error=f"{type(exc).__name__}: {exc}")
    return ShardContent(bytes=size, sha256=sha, record_ids=tuple(str(i) for i in ids))


_CONTENT_READERS: dict[str, Callable[[ShardInfo], ShardContent]] = {
    "webdataset": _read_tar_content,
    "parquet": _read_parquet_content,
}


@dataclass(frozen=True)
class ShardCheck:
    """The verdict on one shard: why it cannot be trusted (None: it matches the manifest), and its record ids."""

    reason: str | None
    record_ids: tuple[str, ...] = ()
    from_cache: bool = False
    """The verdict (good) and the ids came from the verification cache: the file was not read."""


def _size_problem(size: int, expected: int) -> str | None:
    if size < expected:
        return f"truncated: {size} bytes, manifest says {expected}"
    if size != expected:
        return f"size mismatch: {size} bytes, manifest says {expected}"
    return None


def check_shard(shard: ShardInfo, backend: str = "webdataset", *, retry: RetryPolicy | None = None,
                cache: VerificationCache | None = None, downloads: ShardDownloadCache | None = None) -> ShardCheck:
    """Check one shard against its manifest entry: missing / truncated / size / sha256 / records that cannot
    be listed / record count / an id twice. The count is checked even when the sha256 matches: a count
    lowered or raised in the manifest leaves the shard's bytes (and so its hash) unchanged.

    With a ``cache``, a shard hashed by an earlier check whose manifest entry and fingerprint (size and mtime,
    ctime, inode; a content hash for URLs: ``Fingerprint.identifies_content`` in pipeline.data.locations) are unchanged is taken as verified
    without reading it; a shard that is read and passes is remembered, when its fingerprint can be trusted (a URL
    with only an ETag / Last-Modified / version id never is: it is hashed on every start). Transient errors
    (connection reset, timeout, HTTP 5xx/429) are retried per ``retry``; one that outlasts the retries raises
    :class:`~pipeline.data.locations.RetriesExhausted` (it says nothing about the shard). 404 / missing is
    ``missing``, 403 / permission ``unreadable``.

    With ``downloads`` (the local shard cache, ``data.cache_dir``) a remote shard is checked from its cached copy
    (:func:`_check_cached_copy`); the verification cache is not used for it."""
    if downloads is not None and local_path(shard.url) is None:
        return _check_cached_copy(shard, backend, retry, downloads)
    started = time.time()
    try:
        before = fingerprint(shard.url, retry)
    except (ImportError, RetriesExhausted):
        raise
    except (FileNotFoundError, PermissionError) as exc:
        return ShardCheck(_unreadable_reason(exc))
    except Exception as exc:  # noqa: BLE001  a permanent error of some filesystem: read the file to know more
        if local_path(shard.url) is not None:
            return ShardCheck(_unreadable_reason(exc))
        logger.debug("%s: no metadata (%s); reading it", shard.url, exc)  # e.g. a server that answers no HEAD
        before = None
    if before is not None and before.size is not None:
        problem = _size_problem(before.size, shard.bytes)
        if problem:
            return ShardCheck(problem)
    if cache is not None and before is not None:
        ids = cache.lookup(shard.url, backend, shard.bytes, shard.sha256, shard.num_motions, before)
        if ids is not None:
            return ShardCheck(None, ids, from_cache=True)
    try:
        content = call_with_retries(lambda: _CONTENT_READERS[backend](shard), shard.url, "verifying the shard", retry)
    except (ImportError, RetriesExhausted):
        raise
    except Exception as exc:  # noqa: BLE001  permanent (not retried): cannot be opened or read
        return ShardCheck(_unreadable_reason(exc))
    check = _content_verdict(shard, content)
    if cache is not None:
        if check.reason is not None:
            cache.forget(shard.url)
        elif before is not None and before.trusted(started, RACY_S):
            try:
                after = fingerprint(shard.url, retry)
            except (OSError, ValueError, RetriesExhausted):
                after = None
            if after == before:  # unchanged while it was read: the bytes hashed are the ones fingerprinted
                cache.remember(shard.url, backend, shard.bytes, shard.sha256, shard.num_motions, before,
                               check.record_ids)
    return check


def _check_cached_copy(shard: ShardInfo, backend: str, retry: RetryPolicy | None,
                       downloads: ShardDownloadCache) -> ShardCheck:
    """Check a remote shard from its copy in the local shard cache, downloading it there first when it is not
    (verified as it is written: bytes that are not the manifest's are the verdict, and nothing is kept). The copy
    is hashed in full, a local read: a copy damaged on disk since it was written (the same size, other bytes) is
    removed (warning), downloaded again, and the new copy checked."""
    for attempt in range(2):
        def download() -> bool:
            fetched_before = downloads.fetched
            _open_cache_entry(shard, downloads).close()
            return downloads.fetched > fetched_before

        try:
            downloaded = call_with_retries(download, shard.url, "downloading the shard into the shard cache", retry)
        except (ImportError, RetriesExhausted):
            raise
        except ShardChangedError as exc:
            if not isinstance(exc.__cause__, DownloadMismatch):
                raise
            return ShardCheck(f"{exc.__cause__.reason} (nothing was kept in the shard cache)")
        except Exception as exc:  # noqa: BLE001  permanent (not retried): cannot be downloaded
            return ShardCheck(_unreadable_reason(exc))
        check = check_shard(replace(shard, url=downloads.entry_path(shard.sha256)), backend, retry=retry)
        if check.reason is None or downloaded or attempt:
            return check
        downloads.discard(shard.sha256, f"{shard.url}: its copy in the shard cache is bad ({check.reason})")
    raise AssertionError("unreachable")


def _unreadable_reason(exc: BaseException) -> str:
    """The verdict on a shard that cannot be read: ``missing`` (no such file, HTTP 404), else ``unreadable``
    with the error (a permission error, HTTP 403, ...)."""
    cause = exc.__cause__
    status = http_status(exc) or (http_status(cause) if cause is not None else None)
    if isinstance(exc, FileNotFoundError) and status in (None, 404):
        return "missing"
    if isinstance(exc, FileNotFoundError) and cause is not None:
        exc = cause  # fsspec's HTTP info(): FileNotFoundError(url) from the HTTP error that says what happened
    return f"unreadable: {describe(exc)}"


def _content_verdict(shard: ShardInfo, content: ShardContent) -> ShardCheck:
    problem = _size_problem(content.bytes, shard.bytes)
    if problem:
        return ShardCheck(problem)
    if content.sha256 != shard.sha256:
        return ShardCheck(f"corrupted: sha256 {content.sha256[:16]}…, manifest says {shard.sha256[:16]}…")
    if content.record_ids is None:
        return ShardCheck(f"unreadable records: {content.listing_error}")
    found = len(content.record_ids)
    if found != shard.num_motions:
        return ShardCheck(f"record count: holds {found} records, manifest says {shard.num_motions}")
    twice = sorted(i for i, n in Counter(content.record_ids).items() if n > 1)
    if twice:
        return ShardCheck(f"duplicate record ids: {twice[:3]} ({len(twice)} in all)")
    return ShardCheck(None, content.record_ids)


def verify_shards(manifest: Manifest | str | os.PathLike, split: str, mode: str = "strict",
                  backend: str = "webdataset", *, retry: RetryPolicy | None = None,
                  cache: str | os.PathLike | bool | None = None,
                  downloads: ShardDownloadCache | None = None) -> VerificationReport:
    """Check a split against its manifest before any of it is used: every shard (:func:`check_shard`), record
    ids unique across the split, and the split's totals against its shard counts and lengths.

    ``strict`` raises :class:`ShardVerificationError` naming the first bad shard (or the manifest and what
    disagrees); ``tolerant`` checks them all and reports the bad ones (pass ``report.bad_paths`` as
    ``exclude_shards``; every rank must exclude the same list, so verify on every rank (deterministic) or
    broadcast rank 0's list) and the manifest's inconsistencies; ``off`` checks nothing. A shard whose ids
    repeat ids of an earlier good shard is bad: sample ids seed every random draw and name evaluation items.

    ``cache``: where verdicts are remembered so that an unchanged shard is not hashed again on the next start
    (``pipeline.data.shard_cache``): None → ``$MFM_VERIFY_CACHE`` or the user's cache folder, False → no cache (hash
    everything), a folder. ``retry``: transient errors (network) are retried; one that outlasts the retries raises
    :class:`~pipeline.data.locations.RetriesExhausted` naming the URL, in both modes (an unreachable shard is not a bad
    one, and tolerant mode must not drop data for a network outage).

    ``downloads``: the local shard cache (``data.cache_dir``): remote shards are checked from their cached copies,
    downloaded there first when missing (:func:`check_shard`); the report counts both (``num_cache_served``,
    ``num_downloaded``).
    """
    if mode not in VERIFY_MODES:
        raise ValueError(f"verify mode must be one of {VERIFY_MODES}, got {mode!r}")
    manifest = open_manifest(manifest, retry=retry)
    if mode == "off":
        return VerificationReport(split=split, backend=backend, mode=mode, num_checked=0,
                                  dataset_id=manifest.dataset_id)
    bad = []
    holder: dict[str, str] = {}  # record id -> the good shard that holds it
    shards = split_shards(manifest, split, backend)
    for url in dict.fromkeys(s.url for s in shards):
        require_support(url)
    remembered = VerificationCache.for_manifest(manifest.location, cache)
    started = time.perf_counter()
    from_cache = 0
    served_before, fetched_before = (downloads.served, downloads.fetched) if downloads is not None else (0, 0)
    try:
        for shard in shards:
            check = check_shard(shard, backend, retry=retry, cache=remembered, downloads=downloads)
            from_cache += check.from_cache
            reason = check.reason
            if reason is None:
                again = [i for i in check.record_ids if i in holder]
                if again:
                    reason = (f"duplicate record ids: {again[0]!r} is also in {holder[again[0]]} "
                              f"({len(again)} such ids)")
            if reason is None:
                holder.update(dict.fromkeys(check.record_ids, shard.path))
                continue
            if mode == "strict":
                raise ShardVerificationError(
                    f"{shard.url}: bad shard ({reason}); split {split!r} of {manifest.location}. Rebuild the "
                    "dataset, or leave the shard out with tolerant verification (training: data.verify=tolerant).")
            logger.warning("bad shard %s: %s (%d motions skipped)", shard.path, reason, shard.num_motions)
            bad.append(BadShard(path=shard.path, reason=reason, num_motions=shard.num_motions))
    finally:
        if remembered is not None:
            remembered.save(known_urls=_all_listed_urls(manifest))
    cache_served, downloaded = ((downloads.served - served_before, downloads.fetched - fetched_before)
                                if downloads is not None else (0, 0))
    logger.info("verified %d %s shards of split %r in %.2f s (%d unchanged since an earlier check, not read again%s%s)",
                len(shards), backend, split, time.perf_counter() - started, from_cache,
                f"; cache {remembered.path}" if remembered is not None else "; no cache",
                f"; shard cache {downloads.folder}: {cache_served} read from it, {downloaded} downloaded"
                if downloads is not None else "")
    unlisted = unlisted_files(manifest, split)
    if unlisted and mode == "strict":
        raise ShardVerificationError(
            f"{manifest.location}: split {split!r}: its folder holds {len(unlisted)} file(s) the manifest does not "
            f"list ({_first_few(unlisted)}): data it does not account for (a shard whose entry was removed?). Remove "
            "them or rebuild the dataset (tolerant verification reports them and goes on).")
    problems = manifest.consistency_problems(split, (backend,))
    if problems and mode == "strict":
        raise ShardVerificationError(
            f"{manifest.location}: inconsistent manifest: {'; '.join(problems)}. Its shards verify, so the "
            "totals are what is wrong: rebuild the dataset (or verify in tolerant mode, which trusts the "
            "verified shard counts).")
    if manifest.dataset_id_problem:
        if mode == "strict":
            raise ShardVerificationError(
                f"{manifest.location}: {manifest.dataset_id_problem}. Rebuild the dataset (tolerant verification goes "
                f"on, recording the derived id {manifest.dataset_id[:16]}…).")
        problems.append(manifest.dataset_id_problem)
    report = VerificationReport(split=split, backend=backend, mode=mode, num_checked=len(shards), bad=tuple(bad),
                                manifest_problems=tuple(problems), num_from_cache=from_cache,
                                dataset_id=manifest.dataset_id, unlisted_files=tuple(unlisted or ()),
                                unlisted_files_checked=unlisted is not None, num_cache_served=cache_served,
                                num_downloaded=downloaded)
    if bad:
        logger.warning("%d of %d %s shards of split %r are bad; %d motions will be skipped every epoch",
                       len(bad), len(shards), backend, split, report.samples_lost)
    if unlisted:
        logger.warning("%s: split %r: %d file(s) in its folder are not listed by the manifest and are not read: %s",
                       manifest.location, split, len(unlisted), ", ".join(unlisted))
    for problem in problems:
        logger.warning("%s: inconsistent manifest (tolerant: going on with the verified shard counts): %s",
                       manifest.location, problem)
    return report


def unlisted_files(manifest: Manifest, split: str) -> list[str] | None:
    """Entries of the folders holding the split's files (tar and Parquet) that no split of the manifest lists, as
    paths relative to the manifest's folder (a folder with a trailing '/'), sorted; None when the split's files are
    not local (listing an object store or HTTP folder is often not allowed, and HTTP has no listing). Not checked:
    the manifest's own folder (it holds the manifest and what else the user keeps there), and folders outside it
    (``allow_external_shards``)."""
    if local_path(manifest.location) is None:
        return None
    base = os.path.dirname(os.path.abspath(local_path(manifest.location)))
    listed: set[str] = set()
    folders: set[str] = set()
    splits = manifest.data.get("splits") or {}
    for name, entry in splits.items():
        for item in _listed_entries(entry):
            path = item.get("path")
            if shard_path_problem(path) is not None:
                continue  # outside the manifest's folder (allowed as external): not ours to list
            file = os.path.normpath(os.path.join(base, path))
            listed.add(file)
            if name == split and os.path.dirname(file) != base:
                folders.add(os.path.dirname(file))
    found = []
    for folder in sorted(folders):
        try:
            names = sorted(os.listdir(folder))
        except OSError:  # a missing folder: its shards are reported missing
            continue
        for name in names:
            file = os.path.join(folder, name)
            if file not in listed:
                relative = os.path.relpath(file, base).replace(os.sep, "/")
                found.append(relative + "/" if os.path.isdir(file) and not os.path.islink(file) else relative)
    return found


def _listed_entries(split_entry: Any) -> list[Mapping[str, Any]]:
    """The file entries (both backends) of one split of a manifest, skipping malformed ones."""
    if not isinstance(split_entry, Mapping):
        return []
    return [item for key in _MANIFEST_LIST_KEY.values() for item in (split_entry.get(key) or [])
            if isinstance(item, Mapping)]


def _first_few(items: Sequence[str], shown: int = 5) -> str:
    return ", ".join(items[:shown]) + (f" and {len(items) - shown} more" if len(items) > shown else "")


def _all_listed_urls(manifest: Manifest) -> set[str]:
    """Every file any split of the manifest lists (both backends): the cache keeps entries for these only."""
    urls = set()
    for entry in (manifest.data.get("splits") or {}).values():
        for item in _listed_entries(entry):
            if "path" in item:
                with contextlib.suppress(ManifestError):  # a refused location is never read, so never cached
                    urls.add(manifest.shard_location(str(item["path"])))
    return urls


# ----------------------------------------------------------------------------------------------------------
# Reading: shard → (position, raw record) for the wanted positions
# ----------------------------------------------------------------------------------------------------------


class DataResumeError(ValueError):
    """A saved data position cannot be continued: the epoch plan depends on ``key`` (a state entry such as
    ``batch_size`` or ``world_size``, or ``excluded_shards``), which was ``saved`` when the state was saved and is
    ``now`` now. The trainer names the setting behind it (``pipeline.checkpoint.ResumeSettingError``)."""

    def __init__(self, message: str, *, key: str, saved: Any, now: Any) -> None:
        super().__init__(message)
        self.key, self.saved, self.now = key, saved, now


class ShardReadError(DataError, RuntimeError):
    """A shard that cannot be read or does not match its manifest entry, discovered while training."""


class ShardChangedError(ShardReadError):
    """A remote shard read for use is not the file its manifest entry describes (another size or sha256): it changed
    since it was verified. Raised once its bytes are all read and hashed, before any of its records is parsed, so
    nothing of it has been used."""


SPOOL_IN_MEMORY_BYTES = 64 << 20
"""A remote shard being checked is held in memory up to this size, beyond it in a temporary file ($TMPDIR)."""


@contextlib.contextmanager
def checked_remote_copy(shard: ShardInfo) -> Iterator[BinaryIO]:
    """A remote shard's bytes, read once front to back and hashed as they arrive, held in a local spool and checked
    against the manifest's size and sha256 before the spool is handed out: the records parsed from it are exactly
    the bytes hashed, and a shard changed since verification (a server that keeps its ETag or Last-Modified through
    an in-place rewrite, an object replaced between two epochs) raises :class:`ShardChangedError` before any of them
    is used. Transient errors of the download propagate (:func:`read_shard` retries the shard from its start)."""
    with open_binary(shard.url) as stream, tempfile.SpooledTemporaryFile(max_size=SPOOL_IN_MEMORY_BYTES) as spool:
        reader = _HashingReader(stream)
        while block := reader.read(READ_BUFFER):
            spool.write(block)
        if reader.size != shard.bytes or reader.sha256 != shard.sha256:
            raise ShardChangedError(
                f"{shard.url}: changed since it was verified: the bytes read now are {reader.size} bytes with sha256 "
                f"{reader.sha256[:16]}…, the manifest says {shard.bytes} bytes with sha256 {shard.sha256[:16]}…; "
                "none of its records was used. Restore the shard or rebuild the dataset (training: "
                "data.verify=tolerant leaves its records out)")
        spool.seek(0)
        yield spool


def _open_cache_entry(shard: ShardInfo, downloads: ShardDownloadCache) -> BinaryIO:
    """The shard's entry in the local shard cache, open for reading: the one there (size-checked), else downloaded
    now and verified (size and sha256) before it becomes the entry. Bytes that are not the manifest's raise
    :class:`ShardChangedError` naming the URL, and nothing is kept; transient errors of the download propagate."""
    file = downloads.open_entry(shard.url, shard.bytes, shard.sha256)
    if file is not None:
        return file
    with open_binary(shard.url) as stream:
        try:
            return downloads.store(shard.url, shard.bytes, shard.sha256, stream)
        except DownloadMismatch as exc:
            raise ShardChangedError(f"{exc}; none of its records was used. Restore the shard or rebuild the dataset "
                                    "(training: data.verify=tolerant leaves its records out)") from exc


@contextlib.contextmanager
def cached_remote_copy(shard: ShardInfo, downloads: ShardDownloadCache) -> Iterator[BinaryIO]:
    """A remote shard read from the local shard cache (``data.cache_dir``; :func:`_open_cache_entry`)."""
    with _open_cache_entry(shard, downloads) as file:
        yield file


def _open_for_reading(shard: ShardInfo, check_remote_bytes: bool, downloads: ShardDownloadCache | None = None
                      ) -> contextlib.AbstractContextManager[BinaryIO]:
    """A local shard as it is (checked before the run: its stat fingerprint or its hash); a remote one from the
    local shard cache when there is one (verified when it was downloaded, size-checked on every open:
    :func:`cached_remote_copy`), else checked while it is read, when ``check_remote_bytes``
    (:func:`checked_remote_copy`)."""
    if local_path(shard.url) is None:
        if downloads is not None:
            return cached_remote_copy(shard, downloads)
        if check_remote_bytes:
            return checked_remote_copy(shard)
    return open_binary(shard.url)


def read_tar_shard(shard: ShardInfo, wanted: np.ndarray, check_remote_bytes: bool = True,
                   downloads: ShardDownloadCache | None = None) -> Iterator[tuple[int, dict]]:
    """Yield ``(position, raw webdataset sample)`` for the wanted positions of one tar shard, in order.
    After the last wanted record the rest is counted without being kept: a shard that holds fewer or more
    records than the manifest says is an error (in whichever verification mode, even ``off``). With
    ``check_remote_bytes`` a remote shard is hashed as it is read, before any record is parsed
    (:func:`checked_remote_copy`); with ``downloads`` it is read from the local shard cache
    (:func:`cached_remote_copy`)."""
    positions = np.flatnonzero(wanted)
    if positions.size == 0:
        return
    count = 0
    try:
        with _open_for_reading(shard, check_remote_bytes, downloads) as stream:
            for position, raw in enumerate(_tar_records(stream, shard.url)):
                count = position + 1
                if position < shard.num_motions and wanted[position]:
                    yield position, raw
    except _TAR_ERRORS as exc:
        raise ShardReadError(f"{shard.url}: cannot read shard: {type(exc).__name__}: {exc}") from exc
    if count != shard.num_motions:
        raise ShardReadError(f"{shard.url}: holds {count} records where the manifest says {shard.num_motions} "
                             "(truncated or replaced shard, or a wrong count in the manifest?)")


def read_parquet_part(shard: ShardInfo, wanted: np.ndarray, check_remote_bytes: bool = True,
                      downloads: ShardDownloadCache | None = None) -> Iterator[tuple[int, ParquetRow]]:
    """Yield ``(position, ParquetRow)`` for the wanted rows, reading only row groups that hold one. With
    ``check_remote_bytes`` a remote part is read whole and hashed first (:func:`checked_remote_copy`), and its row
    groups are read from that copy; with ``downloads`` from the local shard cache (:func:`cached_remote_copy`)."""
    import pyarrow.parquet as pq

    with contextlib.ExitStack() as opened:
        remote = local_path(shard.url) is None
        source = None
        if remote and downloads is not None:
            source = opened.enter_context(cached_remote_copy(shard, downloads))
        elif remote and check_remote_bytes:
            source = opened.enter_context(checked_remote_copy(shard))
        try:
            if source is None:
                source = open_seekable(shard.url)
                if not isinstance(source, str):
                    opened.enter_context(source)
            part = opened.enter_context(pq.ParquetFile(source))
        except (OSError, ValueError) as exc:
            raise ShardReadError(f"{shard.url}: cannot read Parquet part: {type(exc).__name__}: {exc}") from exc
        if part.metadata.num_rows != shard.num_motions:
            raise ShardReadError(f"{shard.url}: holds {part.metadata.num_rows} rows where the manifest says "
                                 f"{shard.num_motions}")
        start = 0
        for group in range(part.num_row_groups):
            rows = part.metadata.row_group(group).num_rows
            selected = np.flatnonzero(wanted[start:start + rows])
            if selected.size:
                try:
                    table = part.read_row_group(group)
                except (OSError, ValueError) as exc:
                    raise ShardReadError(f"{shard.url}: cannot read row group {group}: {exc}") from exc
                for row in selected:
                    yield start + int(row), ParquetRow(table=table.slice(int(row), 1), source=shard.url)
            start += rows


_READERS: dict[str, Callable[[ShardInfo, np.ndarray, bool, ShardDownloadCache | None],
                              Iterator[tuple[int, Any]]]] = {
    "webdataset": read_tar_shard,
    "parquet": read_parquet_part,
}
# Readers that can start a re-read at the first wanted position (Parquet reads only the row groups it needs); a
# tar is re-read from its start anyway (it is counted to its end), so it is given the whole mask again.
_RESTART_WITH_REMAINING = {"webdataset": False, "parquet": True}


def read_shard(shard: ShardInfo, wanted: np.ndarray, backend: str = "webdataset",
               retry: RetryPolicy | None = None, *, check_remote_bytes: bool = True,
               tolerate_bad_data: bool = False, downloads: ShardDownloadCache | None = None
               ) -> Iterator[tuple[int, Any]]:
    """Stage 5's reader: ``(position, raw record)`` for the wanted positions of one shard, in order, riding out
    transient errors (connection reset, timeout, HTTP 5xx/429).

    A read that fails with a transient error is retried at the shard level: the shard is opened again after a
    back-off and read from its start, and the records already yielded (positions up to the last one yielded)
    are passed over, so no record is duplicated or dropped and the order is the one an uninterrupted read
    gives: the exact-resume guarantee holds, and batches are bit-identical to an uninterrupted run. At most
    ``retry.retries`` consecutive failed attempts are made (the count starts again once an attempt has yielded a
    record), each logged as a warning; then :class:`ShardReadError` naming the URL. A permanent error (missing
    / 404, permission / 403, a damaged shard, a wrong record count) is raised at once, as a
    :class:`ShardReadError` naming the URL.

    ``check_remote_bytes``: a remote shard (a URL) is read whole and hashed before any of its records is parsed
    (:func:`checked_remote_copy`), so a shard that changed since verification while keeping its size, ETag and
    Last-Modified is never used: :class:`ShardChangedError`, or with ``tolerate_bad_data`` a
    :class:`SkippedRecord` in place of each of its wanted records (:func:`left_out_records`), counted and logged
    as tolerant mode's other skipped records are, with the batch boundaries where the plan put them.

    ``downloads``: a remote shard is read from the local shard cache (``data.cache_dir``;
    :mod:`pipeline.data.download_cache`), downloaded into it first when it is not there; a download that is not the
    manifest's bytes is handled as a changed shard (above), and a transient error during it is retried as here."""
    read, policy = _READERS[backend], retry or DEFAULT_RETRY
    last = -1  # the last position yielded
    failures = 0
    while True:
        mask = wanted
        if last >= 0 and _RESTART_WITH_REMAINING[backend]:
            mask = wanted.copy()
            mask[:last + 1] = False
        records = read(shard, mask, check_remote_bytes, downloads)
        try:
            with contextlib.closing(records):  # closes the file when the consumer stops early, too
                for position, raw in records:
                    if position <= last:
                        continue
                    yield position, raw
                    last, failures = position, 0
            return
        except ShardChangedError as exc:
            if not tolerate_bad_data:
                raise
            logger.warning("tolerant mode: %s", exc)
            remaining = wanted.copy()
            remaining[:last + 1] = False
            yield from left_out_records(shard, remaining, "changed since it was verified (its bytes are not the "
                                                          "manifest's sha256): its records are left out")
            return
        except ImportError:
            raise
        except Exception as exc:
            if not is_transient(exc):
                if isinstance(exc, ShardReadError):
                    raise
                raise ShardReadError(f"{shard.url}: cannot read shard: {type(exc).__name__}: {exc}") from exc
            if failures >= policy.retries:
                raise ShardReadError(f"{shard.url}: cannot read shard: still failing after {policy.retries} "
                                     f"retries: {type(exc).__name__}: {exc}") from exc
            failures += 1
            wait_before_retry(shard.url, "reading the shard" + (f" (resuming after record {last})" if last >= 0
                                                                 else ""), exc, failures, policy)
_DECODERS = {"webdataset": DecodeTarRecord, "parquet": DecodeParquetRow}


def left_out_records(shard: ShardInfo, wanted: np.ndarray, reason: str) -> Iterator[tuple[int, SkippedRecord]]:
    """A shard whose records are not used (excluded since the epoch was planned, or found changed while read in
    tolerant mode): a :class:`SkippedRecord` in place of each wanted record, so the epoch's batch boundaries stay
    where the plan put them."""
    skipped = SkippedRecord(f"{shard.url}: {reason}")  # one reason per shard: logged once, counted per record
    for position in np.flatnonzero(wanted):
        yield int(position), skipped


def ordered_records(shards: Sequence[ShardInfo], emission: np.ndarray,
                    read: Callable[[ShardInfo, np.ndarray], Iterator[tuple[int, Any]]],
                    left_out: Mapping[str, str] | None = None) -> Iterator[Any]:
    """Stage 5: raw records of a slot in ``emission`` order (positions in the concatenated shards).

    Shards are read sequentially; a record is held until its turn, so at most about a shuffle buffer's
    worth of raw records is in memory. Positions not in ``emission`` (consumed before a resume, or past
    the epoch's batch count) are never decoded, and shards with none of them are never opened. Shards in
    ``left_out`` (path -> why) are not opened either: their records come out as skipped records."""
    left_out = left_out or {}
    total = sum(s.num_motions for s in shards)
    wanted = np.zeros(total, dtype=bool)
    wanted[emission] = True
    pending: dict[int, Any] = {}
    next_out = 0
    base = 0
    for shard in shards:
        shard_wanted = wanted[base:base + shard.num_motions]
        if shard_wanted.any():
            records = (left_out_records(shard, shard_wanted, left_out[shard.path]) if shard.path in left_out
                       else read(shard, shard_wanted))
            for position, raw in records:
                pending[base + position] = raw
                while next_out < len(emission) and int(emission[next_out]) in pending:
                    yield pending.pop(int(emission[next_out]))
                    next_out += 1
        base += shard.num_motions
    if next_out != len(emission):
        raise ShardReadError(f"slot stream ended after {next_out} of {len(emission)} records: shards "
                             f"{[s.path for s in shards]} hold fewer records than the manifest says")


@dataclass
class VerifiedSplit:
    """A split checked by :func:`verify_shards`, and the report. Readers of whole splits (the evaluator's
    ground truth, tools) read through it, so they read only shards that verification passed, and can say
    in their outputs what was verified (``report.as_dict()``)."""

    manifest: Manifest
    split: str
    backend: str
    report: VerificationReport
    records_skipped: int = 0
    """Records the last :meth:`iter_motions` left out (tolerant mode only)."""
    retry: RetryPolicy = DEFAULT_RETRY
    """How reads ride out transient errors (:func:`read_shard`)."""
    downloads: ShardDownloadCache | None = None
    """The local shard cache remote shards are read through (:func:`read_shard`), or None."""

    @property
    def shards(self) -> list[ShardInfo]:
        bad = set(self.report.bad_paths)
        return [s for s in split_shards(self.manifest, self.split, self.backend) if s.path not in bad]

    def iter_motions(self) -> Iterator[MotionRecord]:
        """Every record of the good shards once, in manifest order, decoded and not cropped. In tolerant mode
        a record that fails to decode or validate is skipped, counted and logged. A remote shard is hashed again
        as it is read (unless verification is off): one that changed since it was verified raises
        :class:`ShardChangedError` (tolerant: its records are skipped) before any of its records is read."""
        decode = _DECODERS[self.backend](self.manifest.record_spec)
        tolerant = self.report.mode == "tolerant"
        if tolerant:
            decode = SkipBadRecords(decode)
        self.records_skipped = 0
        for shard in self.shards:
            for _, raw in read_shard(shard, np.ones(shard.num_motions, dtype=bool), self.backend, self.retry,
                                     check_remote_bytes=self.report.mode != "off", tolerate_bad_data=tolerant,
                                     downloads=self.downloads):
                record = decode(raw)
                if isinstance(record, SkippedRecord):
                    self.records_skipped += 1
                    logger.warning("tolerant mode: skipped a record: %s", record.reason)
                    continue
                yield record


def verified_split(manifest: Manifest | str | os.PathLike, split: str, backend: str = "webdataset",
                   mode: str = "strict", *, retry: RetryPolicy | None = None,
                   cache: str | os.PathLike | bool | None = None,
                   downloads: ShardDownloadCache | None = None) -> VerifiedSplit:
    """Verify a split (:func:`verify_shards`, ``mode``, ``cache``, ``downloads``) and return it for reading."""
    retry = retry or DEFAULT_RETRY
    manifest = open_manifest(manifest, retry=retry)
    report = verify_shards(manifest, split, mode=mode, backend=backend, retry=retry, cache=cache, downloads=downloads)
    return VerifiedSplit(manifest, split, backend, report, retry=retry, downloads=downloads)


def iter_motions(manifest: Manifest | str | os.PathLike, split: str, backend: str = "webdataset", *,
                 verify: str = "strict", retry: RetryPolicy | None = None) -> Iterator[MotionRecord]:
    """Every record of a split once, in manifest order, decoded and not cropped (for evaluators/tools); the
    split is verified first (``verify``: strict by default, so a tampered shard is refused before any record
    of the split is read)."""
    return verified_split(manifest, split, backend, mode=verify, retry=retry).iter_motions()


# ----------------------------------------------------------------------------------------------------------
# Options and the per-rank stream that runs in DataLoader workers
# ----------------------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class LoaderOptions:
    """How the stream is cut, shuffled and batched. Everything here except ``backend``, ``tolerate_bad_data``,
    ``check_remote_bytes``, ``prefetch_factor``, ``pin_memory``, ``multiprocessing_context``, ``retries`` and
    ``retry_backoff_s`` is part of the resume state and must not change on resume."""

    batch_size: int
    """Samples per batch on each rank."""
    num_workers: int = 0
    """DataLoader worker processes per rank (0: read in the main process)."""
    seed: int = 0
    """Seeds the shard shuffle, shuffle buffers, caption picks and crops."""
    window: int = 196
    """Frames per padded motion (MFM/MDM ``max_motion_length`` for HumanML3D)."""
    unit_length: int = 4
    """Crop lengths are multiples of this (MDM ``unit_length``); 1 disables the rounding."""
    shorten_prob: float = 1.0 / 3.0
    """Probability of removing one more unit (MDM's 'double' coin)."""
    shuffle: bool = True
    """Shuffle shards and samples; captions and crops stay random either way."""
    shuffle_buffer: int = 512
    """Shuffle buffer size per reader (samples)."""
    caption_policy: str = "random"
    """Which caption a visit uses: 'random' (training) or 'first' (debugging); see stages.PickCaption."""
    batching: str = "fixed"
    """One of BATCHINGS. 'fixed': every batch padded to ``window``. 'length_aware': clips of similar length batched
    together (by the manifest's lengths, within sort windows) and each batch padded to its longest clip rounded up to
    ``pad_multiple`` (see the module docstring); same samples, batch counts and resume as 'fixed'."""
    pad_multiple: int = 16
    """length_aware: batch widths are multiples of this (at most ``window``); 1: exactly the longest clip."""
    sort_window_batches: int = 8
    """length_aware: how many batches' worth of consecutive (shuffled) samples are sorted by length together."""
    backend: str = "webdataset"
    """'webdataset' (tar shards, local or any URL) or 'parquet' (the same records, Parquet parts)."""
    tolerate_bad_data: bool = False
    """Tolerant mode (training's ``data.verify=tolerant``): a record that fails to decode or validate is left out
    of its batch (counted, logged) instead of stopping the stream, and a resume whose excluded shards changed
    finishes the checkpoint's epoch with its plan (see the module docstring). False: both raise."""
    check_remote_bytes: bool = True
    """Hash every remote shard (a URL) as it is read and compare it with the manifest's sha256 before any of its
    records is used (:func:`checked_remote_copy`): a shard changed since it was verified stops the stream
    (:class:`ShardChangedError`) or, with ``tolerate_bad_data``, has its records skipped. Training passes
    ``data.verify != "off"``. Local shards are checked before the run only."""
    prefetch_factor: int = 2
    pin_memory: bool = False
    multiprocessing_context: str | None = None
    retries: int = DEFAULT_RETRY.retries
    """Retries of a shard read after a transient error (training's ``data.retries``; see :func:`read_shard`)."""
    retry_backoff_s: float = DEFAULT_RETRY.backoff_s
    """Seconds before the first retry, doubled for each further one (training's ``data.retry_backoff_s``)."""
    cache_dir: str | None = None
    """The local shard cache (training's ``data.cache_dir``; :mod:`pipeline.data.download_cache`): remote shards are
    downloaded there once, verified, and read from there every later epoch and run. None: off. Local shards are
    never copied."""
    cache_max_bytes: int = 0
    """The cache's size cap (least recently used entries go first); 0: no cap."""

    def __post_init__(self):
        if self.batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {self.batch_size}")
        if self.num_workers < 0:
            raise ValueError(f"num_workers must be >= 0, got {self.num_workers}")
        if self.caption_policy not in CAPTION_POLICIES:
            raise ValueError(f"caption_policy must be one of {CAPTION_POLICIES}, got {self.caption_policy!r}")
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {self.backend!r}")
        if self.window < 1 or self.unit_length < 1 or not 0.0 <= self.shorten_prob <= 1.0:
            raise ValueError(f"bad crop options: window={self.window}, unit_length={self.unit_length}, "
                             f"shorten_prob={self.shorten_prob}")
        if self.shuffle_buffer < 0:
            raise ValueError(f"shuffle_buffer must be >= 0, got {self.shuffle_buffer}")
        if self.batching not in BATCHINGS:
            raise ValueError(f"batching must be one of {BATCHINGS}, got {self.batching!r}")
        if self.pad_multiple < 1 or self.sort_window_batches < 1:
            raise ValueError(f"pad_multiple and sort_window_batches must be >= 1, got {self.pad_multiple} and "
                             f"{self.sort_window_batches}")
        RetryPolicy(retries=self.retries, backoff_s=float(self.retry_backoff_s))  # validates both
        if self.cache_max_bytes < 0:
            raise ValueError(f"cache_max_bytes must be >= 0 (0: no cap), got {self.cache_max_bytes}")

    def download_cache(self) -> ShardDownloadCache | None:
        """A handle on the local shard cache (its own counters), or None when ``cache_dir`` is None."""
        return None if self.cache_dir is None else ShardDownloadCache(self.cache_dir, self.cache_max_bytes)

    @property
    def retry_policy(self) -> RetryPolicy:
        return RetryPolicy(retries=self.retries, backoff_s=float(self.retry_backoff_s))

    @property
    def readers_per_rank(self) -> int:
        return max(1, self.num_workers)

    @property
    def batch_pad_multiple(self) -> int | None:
        """What :class:`~pipeline.data.stages.Collate` pads a batch to: None = the window (fixed batching)."""
        return self.pad_multiple if self.batching == "length_aware" else None


@dataclass(frozen=True)
class CarriedEpoch:
    """The epoch a tolerant resume landed in when the excluded shards had changed since the checkpoint. It
    keeps the plan it was started with (``shards``: usable under the exclusions of then), so that the batches
    still due are the ones that were due; the shards of that plan excluded now are ``left_out`` (path ->
    why): their records are skipped, their files never opened. Shards readmitted since wait for the next
    epoch, because the plan of then does not hold them."""

    epoch: int
    excluded_shards: tuple[str, ...]
    shards: tuple[ShardInfo, ...]
    left_out: Mapping[str, str]


@dataclass(frozen=True, eq=False)
class _StreamSpec:
    """Everything a reader process needs (picklable, so spawn contexts work too)."""

    shards: tuple[ShardInfo, ...]  # usable under the current exclusions: every epoch's plan but a carried one
    record_spec: RecordSpec
    mean: np.ndarray
    std: np.ndarray
    action_classes: tuple[str, ...]
    options: LoaderOptions
    rank: int
    world_size: int
    carried: CarriedEpoch | None = None
    _plans: dict = field(default_factory=dict, compare=False, repr=False)

    def shards_for(self, epoch: int) -> tuple[ShardInfo, ...]:
        """The shard list the epoch's plan indexes into."""
        return self.carried.shards if self.carried is not None and self.carried.epoch == epoch else self.shards

    def left_out(self, epoch: int) -> Mapping[str, str]:
        return self.carried.left_out if self.carried is not None and self.carried.epoch == epoch else {}

    def plan(self, epoch: int) -> EpochPlan:
        if epoch not in self._plans:
            if len(self._plans) > 8:
                self._plans.clear()
            self._plans[epoch] = plan_epoch([s.num_motions for s in self.shards_for(epoch)], epoch=epoch,
                                            seed=self.options.seed, world_size=self.world_size,
                                            readers_per_rank=self.options.readers_per_rank,
                                            batch_size=self.options.batch_size, shuffle=self.options.shuffle)
        return self._plans[epoch]

    def checked_plan(self, epoch: int) -> EpochPlan:
        plan = self.plan(epoch)
        if plan.batches_per_reader == 0:
            raise ValueError(
                f"epoch {epoch}: the smallest reader slot has {min(plan.slot_samples)} samples, fewer than "
                f"batch_size {plan.batch_size}, so every rank would get no batch. Use a smaller batch size, "
                f"fewer workers or ranks, or more data ({len(self.shards_for(epoch))} shards, {plan.num_slots} "
                "readers).")
        return plan


def batches_before(position: int, reader: int, readers: int) -> int:
    """How many of the rank's first ``position`` batches came from ``reader`` (batch k is reader k % readers)."""
    return max(0, (position - reader + readers - 1) // readers)


_DATA_ERROR_KEY = "_data_error"
"""The key of the item a DataLoader worker yields in place of a batch when it met bad data (the DataError)."""
_SHARD_CACHE_KEY = "_shard_cache"
"""The key of a batch's (shards read from the local shard cache, shards downloaded into it) since the reader's
previous batch: how the counts of DataLoader workers reach the loader (``MotionLoader.shards_from_cache``)."""


class _RankStream(IterableDataset):
    """One rank's batches, forever, starting at (epoch, batch). In DataLoader worker ``w`` it plays reader
    ``(w + start_batch) % readers``, so the DataLoader's round-robin resumes on the right reader."""

    def __init__(self, spec: _StreamSpec, start_epoch: int, start_batch: int):
        self.spec, self.start_epoch, self.start_batch = spec, start_epoch, start_batch

    def __iter__(self) -> Iterator[dict]:
        info = get_worker_info()
        readers = self.spec.options.readers_per_rank
        worker = 0 if info is None else info.id
        if info is not None and info.num_workers != readers:
            raise RuntimeError(f"stream built for {readers} workers runs under {info.num_workers}")
        reader = (worker + self.start_batch) % readers
        skip = batches_before(self.start_batch, reader, readers)
        downloads = self.spec.options.download_cache()
        try:
            for epoch in itertools.count(self.start_epoch):
                yield from self.reader_epoch(epoch, reader, skip, downloads)
                skip = 0
        except DataError as err:
            if info is None:
                raise
            # In a DataLoader worker: hand the error on whole, in the batch's place (MotionLoader._checked raises
            # it in the rank's process). Raised here, the DataLoader would raise a new error there whose message
            # is this worker's traceback, not the one line naming the file and the reason.
            yield {_DATA_ERROR_KEY: err}

    def reader_epoch(self, epoch: int, reader: int, skip_batches: int,
                     downloads: ShardDownloadCache | None = None) -> Iterator[dict]:
        spec, opts = self.spec, self.spec.options
        plan = spec.checked_plan(epoch)
        slot = plan.slot(spec.rank, reader)
        epoch_shards = spec.shards_for(epoch)
        shards = [epoch_shards[i] for i in plan.slot_shards[slot]]
        order = slot_sample_order(plan.slot_samples[slot], seed=opts.seed, epoch=epoch, slot=slot,
                                  shuffle=opts.shuffle, buffer_size=opts.shuffle_buffer)
        batch_size = opts.batch_size
        emission = order[:plan.batches_per_reader * batch_size]
        if opts.batching == "length_aware":
            emission = self.length_batches(emission, shards, epoch, slot)
        emission = emission[skip_batches * batch_size:]
        sample_stages: list[Callable[[Any], Any]] = [
            _DECODERS[opts.backend](spec.record_spec),
            PickCaption(opts.seed, epoch, opts.caption_policy),
            CropToWindow(opts.window, opts.unit_length, opts.shorten_prob, opts.seed, epoch),
            Normalize(spec.mean, spec.std),
        ]
        if opts.tolerate_bad_data:
            sample_stages = [SkipBadRecords(stage) for stage in sample_stages]
        pipeline = wds.DataPipeline(
            functools.partial(ordered_records, shards, emission,
                              functools.partial(read_shard, backend=opts.backend, retry=opts.retry_policy,
                                                check_remote_bytes=opts.check_remote_bytes,
                                                tolerate_bad_data=opts.tolerate_bad_data, downloads=downloads),
                              spec.left_out(epoch)),
            *[wds.map(stage) for stage in sample_stages],
            wds.batched(batch_size, collation_fn=Collate(opts.window, spec.action_classes, spec.record_spec,
                                                         opts.batch_pad_multiple),
                        partial=False),
        )
        counted = (downloads.served, downloads.fetched) if downloads is not None else (0, 0)
        for local, batch in enumerate(pipeline, start=skip_batches):
            batch["_position"] = (epoch, local * plan.readers_per_rank + reader)
            if downloads is not None:
                now = (downloads.served, downloads.fetched)
                batch[_SHARD_CACHE_KEY] = (now[0] - counted[0], now[1] - counted[1])
                counted = now
            yield batch

    def length_batches(self, emission: np.ndarray, shards: Sequence[ShardInfo], epoch: int, slot: int) -> np.ndarray:
        """The slot's epoch emission regrouped into length-aware batches (:func:`length_grouped_order`), from the
        manifest's lengths capped at the window (what a clip is cropped to at most); the batch order inside each
        sort window is drawn from (seed, epoch, slot) when shuffling."""
        opts = self.spec.options
        lengths = np.minimum(np.concatenate([np.asarray(s.lengths, np.int64) for s in shards]), opts.window)
        rng = (np.random.default_rng(np.random.SeedSequence([opts.seed, epoch, slot, _TAG_LENGTH_BATCHES]))
               if opts.shuffle else None)
        return length_grouped_order(emission, lengths, opts.batch_size, opts.sort_window_batches, rng)


# ----------------------------------------------------------------------------------------------------------
# The loader the trainer uses
# ----------------------------------------------------------------------------------------------------------

_PLAN_STATE_KEYS = ("split", "dataset_id", "world_size", "num_workers", "batch_size", "seed", "shuffle",
                    "shuffle_buffer", "window", "unit_length", "shorten_prob", "caption_policy", "batching")
_LENGTH_AWARE_STATE_KEYS = ("pad_multiple", "sort_window_batches")
"""Plan keys that only length-aware batching reads (a fixed-window resume ignores them)."""
_STATE_DEFAULTS = {"batching": "fixed"}
"""What a state saved before a key existed meant by its absence."""


class MotionLoader:
    """Batches of one rank, exactly once per epoch across ranks and workers, resumable bit-exactly.

    ``iter_batches()`` yields forever (epochs roll over); ``iter_epoch()`` yields the rest of the current
    epoch: every planned batch, on every rank, including (tolerant mode) empty batches whose every record was
    skipped (``ids == []``, zero rows). ``epoch`` and ``batches_in_epoch`` say where the next batch comes from;
    ``state_dict()`` saves that. Do not pass this loader through ``accelerator.prepare()`` (it is already
    sharded; see the module docstring); move batches to the device yourself.

    Args:
        manifest: a :class:`Manifest`, or the path/URL of ``manifest.json`` (or of its directory).
        split: "train", "val", ...
        options: :class:`LoaderOptions`.
        rank, world_size: this process among the data-parallel ranks.
        exclude_shards: manifest paths of shards to leave out (``VerificationReport.bad_paths``); must be
            the same list on every rank. The loader does not verify shards itself: its callers run
            :func:`verify_shards` first (the trainer on rank 0, evaluator training on every rank).
    """

    def __init__(self, manifest: Manifest | str | os.PathLike, split: str, options: LoaderOptions, *,
                 rank: int = 0, world_size: int = 1, exclude_shards: Iterable[str] = ()):
        if world_size < 1 or not 0 <= rank < world_size:
            raise ValueError(f"rank {rank} is not in a world of size {world_size}")
        self.manifest = open_manifest(manifest, retry=options.retry_policy)
        self.split, self.options, self.rank, self.world_size = split, options, rank, world_size
        self._split_shards = tuple(split_shards(self.manifest, split, options.backend))
        for url in dict.fromkeys(s.url for s in self._split_shards):
            require_support(url)  # a missing cloud package fails here, naming the extra, not in a worker
        self.excluded_shards = tuple(sorted(set(exclude_shards)))
        if options.batching == "length_aware":
            problem = split_lengths_problem(self.manifest.split(split), self._split_shards)
            if problem is not None:
                raise ManifestError(
                    f"{self.manifest.location}: data.batching=length_aware needs every record's length in split "
                    f"{split!r} of the manifest (its 'lengths' list, one per record in shard order), but {problem}; "
                    "rebuild the dataset with preprocess/build_shards.py, whose manifests list them, or train with "
                    "data.batching=fixed")
        self._spec = _StreamSpec(shards=self._usable_shards(self.excluded_shards, "exclude_shards"),
                                 record_spec=self.manifest.record_spec, mean=self.manifest.mean,
                                 std=self.manifest.std, action_classes=self.manifest.action_classes,
                                 options=options, rank=rank, world_size=world_size)
        self.epoch = 0
        self.batches_in_epoch = 0
        self.records_skipped = 0  # records left out of their batches (tolerant mode); saved with the position
        self.empty_batches = 0  # batches whose every record was left out, yielded empty (tolerant mode); saved too
        # Remote shards this rank's readers read from the local shard cache / downloaded into it (data.cache_dir),
        # in this process's life (not saved: a count of work done, not a position).
        self.shards_from_cache = 0
        self.shards_fetched = 0
        self._skip_reasons_logged: set[str] = set()
        self._generation = 0
        self._plan_logged = False
        self._log_plan(self._spec.checked_plan(0))

    def _usable_shards(self, excluded: Sequence[str], what: str) -> tuple[ShardInfo, ...]:
        """The shards an epoch plan deals out when ``excluded`` are left out (empty shards never are dealt)."""
        unknown = set(excluded) - {s.path for s in self._split_shards}
        if unknown:
            raise ValueError(f"{what} names shards that split {self.split!r} of {self.manifest.location} "
                             f"does not list for backend {self.options.backend!r}: {sorted(unknown)}")
        usable = tuple(s for s in self._split_shards if s.path not in set(excluded) and s.num_motions > 0)
        readers = self.world_size * self.options.readers_per_rank
        if len(usable) < readers:
            raise ValueError(
                f"split {self.split!r} has {len(usable)} usable shards but world_size {self.world_size} × "
                f"{self.options.readers_per_rank} reader(s) per rank (num_workers={self.options.num_workers}) = "
                f"{readers} readers each need at least one; write smaller shards or use fewer workers")
        return usable

    # -- plan ------------------------------------------------------------------------------------------

    @property
    def shards(self) -> tuple[ShardInfo, ...]:
        """The shards new epochs are planned with (a carried epoch keeps its own list: see ``CarriedEpoch``)."""
        return self._spec.shards

    def plan(self, epoch: int | None = None) -> EpochPlan:
        return self._spec.plan(self.epoch if epoch is None else epoch)

    def batches_per_epoch(self, epoch: int | None = None) -> int:
        """Batches this rank (and every other rank) yields in the epoch."""
        return self._spec.checked_plan(self.epoch if epoch is None else epoch).batches_per_rank

    def empty_batch(self) -> dict[str, Any]:
        """A batch of this stream with no sample (every key, the trailing sizes of a real batch, zero rows): what
        the trainer steps through in place of a batch it could not read, to stay in step with the other ranks."""
        return Collate(self.options.window, self._spec.action_classes, self._spec.record_spec).empty_batch()

    def samples_dropped(self, epoch: int | None = None) -> int:
        """Samples of the split (all ranks) not used in the epoch so that all readers yield equal batches."""
        return self.plan(epoch).samples_dropped

    def _log_plan(self, plan: EpochPlan) -> None:
        # Once at INFO (the first epoch); later epochs at DEBUG: a small dataset turns over every few steps.
        level = logging.INFO if plan.epoch == 0 or not self._plan_logged else logging.DEBUG
        self._plan_logged = True
        logger.log(level, "data %s epoch %d: %d batches per rank, %d of %d samples used, %d dropped (rotates "
                    "across epochs), %d shards over %d readers", self.split, plan.epoch, plan.batches_per_rank,
                    plan.samples_used, plan.samples_in_epoch, plan.samples_dropped,
                    len(self._spec.shards_for(plan.epoch)), plan.num_slots)

    # -- state -----------------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Position and everything that fixes the epoch plan. Identical on every rank, except the counts of
        tolerant mode, ``records_skipped`` and ``empty_batches`` (an empty batch still takes its position)."""
        opts = self.options
        carried = self._spec.carried
        return {"version": STATE_VERSION, "epoch": self.epoch, "batches_in_epoch": self.batches_in_epoch,
                "split": self.split, "dataset_id": self.manifest.dataset_id, "world_size": self.world_size,
                "num_workers": opts.num_workers, "batch_size": opts.batch_size, "seed": opts.seed,
                "shuffle": opts.shuffle, "shuffle_buffer": opts.shuffle_buffer, "window": opts.window,
                "unit_length": opts.unit_length, "shorten_prob": opts.shorten_prob,
                "caption_policy": opts.caption_policy, "batching": opts.batching,
                "pad_multiple": opts.pad_multiple, "sort_window_batches": opts.sort_window_batches,
                "excluded_shards": list(self.excluded_shards),
                # The exclusions the current epoch was planned with, while it differs from excluded_shards.
                "carried_epoch": ({"epoch": carried.epoch, "excluded_shards": list(carried.excluded_shards)}
                                  if carried is not None and carried.epoch == self.epoch else None),
                "records_skipped": self.records_skipped, "empty_batches": self.empty_batches}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Continue from a saved position. Refuses (:class:`DataResumeError`) anything that would change the epoch
        plan (world size, worker count, batch size, seed, ...): the remaining batches would not be the ones that
        were due.

        Excluded shards that changed since the state was saved (a shard went bad after the checkpoint, or a
        bad one was repaired): with ``tolerate_bad_data`` the saved epoch is finished with the plan it started
        with, leaving out the records of shards excluded now, and later epochs are planned with the current
        exclusions (:class:`CarriedEpoch`; logged as a warning); without it, refused."""
        if state.get("version") != STATE_VERSION:
            raise ValueError(f"data loader state version {state.get('version')!r}, this loader reads {STATE_VERSION}")
        current = self.state_dict()
        keys = _PLAN_STATE_KEYS + (_LENGTH_AWARE_STATE_KEYS if self.options.batching == "length_aware" else ())
        for key in keys:
            saved, now = state.get(key, _STATE_DEFAULTS.get(key)), current[key]
            if saved != now:
                raise DataResumeError(f"cannot resume the data stream: {key} was {saved!r} when the state was "
                                      f"saved and is {now!r} now; the epoch plan would differ. Resume with the "
                                      f"same {key}.", key=key, saved=saved, now=now)
        epoch, position = int(state["epoch"]), int(state["batches_in_epoch"])
        carried_state = state.get("carried_epoch")
        planned_with = sorted(carried_state["excluded_shards"] if carried_state and carried_state["epoch"] == epoch
                              else state.get("excluded_shards") or [])
        spec = replace(self._spec, carried=None, _plans={})
        if planned_with != list(self.excluded_shards) and position > 0:
            spec = replace(spec, carried=self._carried_epoch(epoch, position, planned_with))
        if epoch < 0 or not 0 <= position < spec.checked_plan(max(epoch, 0)).batches_per_rank:
            raise ValueError(f"data loader state position (epoch {epoch}, batch {position}) is outside the epoch "
                             f"({spec.checked_plan(max(epoch, 0)).batches_per_rank} batches)")
        self._spec = spec
        self.epoch, self.batches_in_epoch = epoch, position
        self.records_skipped = int(state.get("records_skipped", 0))
        self.empty_batches = int(state.get("empty_batches", 0))
        self._generation += 1  # iterators created before this point are stale

    def _carried_epoch(self, epoch: int, position: int, planned_with: Sequence[str]) -> CarriedEpoch:
        """The rule for a resume into the middle of an epoch planned with other exclusions than now's."""
        now = list(self.excluded_shards)
        if not self.options.tolerate_bad_data:
            raise DataResumeError(
                f"cannot resume the data stream: epoch {epoch} (resumed at batch {position}) was planned with "
                f"excluded shards {planned_with}, and verification now excludes {now} (a shard went bad, or a bad "
                "one was repaired, since the checkpoint). Only tolerant mode changes an epoch's data. Restore "
                "the shard(s) so that they verify as they did, or resume with data.verify=tolerant, which "
                f"finishes epoch {epoch} with its plan without the newly excluded shard(s) and plans later epochs "
                "without them.", key="excluded_shards", saved=list(planned_with), now=now)
        newly = sorted(set(now) - set(planned_with))
        readmitted = sorted(set(planned_with) - set(now))
        reason = (f"shard excluded since the checkpoint (tolerant mode: epoch {epoch} finishes without it)")
        carried = CarriedEpoch(epoch=epoch, excluded_shards=tuple(planned_with),
                               shards=self._usable_shards(planned_with, "the saved state's excluded_shards"),
                               left_out={path: reason for path in newly})
        level = logging.WARNING if self.rank == 0 else logging.DEBUG
        logger.log(level,
                   "RESUMING WITH CHANGED SHARDS (tolerant mode): epoch %d was planned with excluded shards %s, "
                   "verification now excludes %s. Rule: epoch %d is finished from batch %d with the plan it "
                   "started with; the records still due from the newly excluded shard(s) %s are left out of their "
                   "batches and counted as skipped records; readmitted shard(s) %s wait for epoch %d; every "
                   "later epoch is planned with the shards excluded now.",
                   epoch, planned_with, now, epoch, position, newly, readmitted, epoch + 1)
        return carried

    # -- iteration -------------------------------------------------------------------------------------

    def iter_batches(self) -> Iterator[dict[str, Any]]:
        """Batches forever, from the current position; ``epoch``/``batches_in_epoch`` advance as they are
        yielded (so ``state_dict()`` taken after consuming a batch resumes at the next one). Creating a new
        iterator or loading a state makes older iterators raise."""
        return self._positioned_batches()

    def iter_epoch(self) -> Iterator[dict[str, Any]]:
        """The remaining batches of the current epoch, then stop (workers are shut down)."""
        return _take(self._positioned_batches(), self.batches_per_epoch() - self.batches_in_epoch)

    def _positioned_batches(self) -> Iterator[dict[str, Any]]:
        """Every batch position from the current one, including (empty) batches whose every record was skipped."""
        self._generation += 1
        stream = _RankStream(self._spec, self.epoch, self.batches_in_epoch)
        if self.options.num_workers == 0:
            source: Iterable[dict] = stream
        else:
            source = DataLoader(stream, batch_size=None, collate_fn=_as_is, num_workers=self.options.num_workers,
                                prefetch_factor=self.options.prefetch_factor, pin_memory=self.options.pin_memory,
                                multiprocessing_context=self.options.multiprocessing_context)
        return self._checked(iter(source), self._generation)

    def _checked(self, source: Iterator[dict], generation: int) -> Iterator[dict[str, Any]]:
        try:
            for batch in source:
                if generation != self._generation:
                    raise RuntimeError("this batch iterator is stale: the loader's state was loaded or another "
                                       "iterator was created since; call iter_batches() again")
                if _DATA_ERROR_KEY in batch:  # a worker met bad data (see _RankStream.__iter__)
                    raise batch[_DATA_ERROR_KEY]
                position = tuple(batch.pop("_position"))  # robust to list conversion by collate/pin_memory
                if position != (self.epoch, self.batches_in_epoch):
                    raise RuntimeError(f"data stream out of order: got batch {position}, expected "
                                       f"{(self.epoch, self.batches_in_epoch)}")
                skipped = batch.pop(SKIPPED_RECORDS_KEY, None)
                served, fetched = batch.pop(_SHARD_CACHE_KEY, (0, 0))
                self.shards_from_cache += int(served)
                self.shards_fetched += int(fetched)
                self._advance()
                if skipped:
                    self._count_skipped(position, skipped, len(batch["ids"]))
                yield batch
        finally:
            # The stream ended (closed, exhausted, or by an error such as a worker's bad record): drop the source
            # now, and with it a DataLoader's worker processes. A traceback holding this frame (a stored DataError)
            # would otherwise keep them alive until it is collected.
            del source

    def _count_skipped(self, position: tuple[int, ...], reasons: Sequence[str], kept: int) -> None:
        """Count the records tolerant mode left out of a batch; each distinct reason is logged once as a
        warning (a shard left out for the rest of an epoch would otherwise log one line per batch). A batch left
        with no record is counted in ``empty_batches`` and logged as a warning every time."""
        self.records_skipped += len(reasons)
        for reason, count in Counter(reasons).items():
            level = logging.DEBUG if reason in self._skip_reasons_logged else logging.WARNING
            self._skip_reasons_logged.add(reason)
            logger.log(level, "tolerant mode: %d record(s) left out of batch %s (%d skipped in this run so "
                       "far): %s", count, position, self.records_skipped, reason)
        if kept == 0:
            self.empty_batches += 1
            logger.warning("tolerant mode: every record of batch %s was skipped: it is yielded as an empty batch "
                           "(no sample; trained with zero weight, in step with the other ranks; %d empty batch(es) "
                           "so far)", position, self.empty_batches)

    def _advance(self) -> None:
        self.batches_in_epoch += 1
        if self.batches_in_epoch == self.batches_per_epoch(self.epoch):
            if self.options.cache_dir is not None:
                logger.info("data %s epoch %d done: shard cache %s: %d remote shard(s) read from it, %d downloaded "
                            "into it so far (rank %d)", self.split, self.epoch, self.options.cache_dir,
                            self.shards_from_cache, self.shards_fetched, self.rank)
            self.epoch += 1
            self.batches_in_epoch = 0
            self._log_plan(self._spec.checked_plan(self.epoch))


def _as_is(batch: dict) -> dict:
    """DataLoader collate for already-collated batches (its default would turn tuples into lists)."""
    return batch


def _take(batches: Iterator[dict], count: int) -> Iterator[dict]:
    """The first ``count`` items, then close the source (which releases its DataLoader workers)."""
    try:
        for _ in range(count):
            yield next(batches)
    finally:
        batches.close()
