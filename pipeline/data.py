"""The training data stream: exactly once per epoch, equal batch counts on every rank, bit-exact resume.

Stages, in order (each a named function or class; the per-sample ones live in ``pipeline.stages``)::

    split_shards(manifest, split)              shard list from the manifest (paths resolved against its location)
    plan_epoch(...)                            per-epoch shuffle of the shards from (seed, epoch), then every
                                               shard assigned to one reader slot (rank × DataLoader worker)
    shuffle_buffer_order(...)                  the slot's sample order: a shuffle buffer seeded by
                                               (seed, epoch, slot), computed from counts before reading
    ordered_records(...)                       read the slot's shards (webdataset tar or Parquet) and emit raw
                                               records in that order, skipping already-consumed ones undecoded
    DecodeTarRecord | DecodeParquetRow         → MotionRecord (features, all captions, spans, text embeddings)
    PickCaption                                one caption, motion cut to its span
    CropToWindow                               MDM/MFM random crop (multiple of unit_length, ≤ window frames)
    Normalize                                  manifest Mean/Std
    Collate                                    padded batch + masks (keys: see ``pipeline.stages.Collate``)

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

Resume. ``state_dict()`` is ``{epoch, batches_in_epoch, seed, world_size, num_workers, ...}``; it is the same
on every rank. Every random draw is a function of (seed, epoch, slot) or (seed, epoch, sample id), never of
what has been consumed, so a resumed loader recomputes the slot orders, drops the first
``batches_in_epoch`` batches' worth of sample positions before reading, and produces bit-identical next
batches. Cost of the fast-forward: shards whose samples were all consumed are not opened; the (at most a
shuffle buffer's worth of) remaining shards are read from their start, but skipped records are not decoded;
Parquet reads only the row groups that hold needed rows. A changed world size, worker count, batch size,
seed or excluded-shard list is refused. With workers, the DataLoader takes batches from workers round-robin;
the workers are rotated on resume so that worker ``k`` of the new iterator plays the reader that owns the
next batch, and each batch carries its (epoch, index) stamp, which the loader checks.

Accelerate. Never pass this loader (or a DataLoader built from it) through ``accelerator.prepare()``: it is
already sharded by rank, and prepare() would shard it again and silently drop data (accelerate issue 3547).
The trainer moves batches to its device itself.
"""

from __future__ import annotations

import functools
import hashlib
import heapq
import itertools
import json
import logging
import os
import tarfile
from dataclasses import dataclass, field
from typing import Any, BinaryIO, Callable, Iterable, Iterator, Mapping, Sequence
from urllib.parse import urlparse

import numpy as np
import webdataset as wds
from torch.utils.data import DataLoader, IterableDataset, get_worker_info
from webdataset.gopen import gopen, gopen_schemes
from webdataset.tariterators import group_by_keys, tar_file_expander

from pipeline.stages import (
    Collate,
    CropToWindow,
    DecodeParquetRow,
    DecodeTarRecord,
    MotionRecord,
    Normalize,
    ParquetRow,
    CAPTION_POLICIES,
    PickCaption,
    RecordSpec,
    shuffle_buffer_order,
)
from preprocess.shards import FORMAT_VERSION, MANIFEST_NAME, ManifestError, load_manifest

logger = logging.getLogger(__name__)

BACKENDS = ("webdataset", "parquet")


def backend_for_format(fmt: str) -> str:
    """The loader backend that reads a config's ``format``: "tar" shards -> webdataset, "parquet" -> parquet."""
    if fmt not in ("tar", "parquet"):
        raise ValueError(f"data format must be 'tar' or 'parquet', got {fmt!r}")
    return "parquet" if fmt == "parquet" else "webdataset"
_MANIFEST_LIST_KEY = {"webdataset": "shards", "parquet": "parquet"}
_TAG_SHARD_SHUFFLE = 11
_TAG_SAMPLE_SHUFFLE = 12
STATE_VERSION = 1


# ----------------------------------------------------------------------------------------------------------
# Locations: local paths and URLs
# ----------------------------------------------------------------------------------------------------------


def is_url(location: str) -> bool:
    """True for ``scheme://...`` (a one-letter scheme is a Windows drive, not a URL)."""
    return len(urlparse(str(location)).scheme) > 1


def resolve_location(manifest_location: str, relative: str) -> str:
    """A shard path from the manifest, resolved against the manifest's own location (path or URL)."""
    if is_url(relative) or os.path.isabs(relative):
        return relative
    if is_url(manifest_location):
        return manifest_location.rsplit("/", 1)[0] + "/" + relative
    return os.path.join(os.path.dirname(os.path.abspath(manifest_location)), relative)


def open_binary(location: str) -> BinaryIO:
    """Open a local path or URL for reading: webdataset's ``gopen`` for what it knows (file, pipe:, http(s),
    gs, hf, ais, ...), fsspec for any other scheme (s3://, az://, ...)."""
    scheme = urlparse(location).scheme
    if not is_url(location) or scheme in gopen_schemes or scheme == "file":
        return gopen(location, "rb")
    import fsspec  # only needed for schemes webdataset does not handle

    return fsspec.open(location, "rb").open()


def _open_seekable(location: str):
    """Parquet needs random access: a local path as is, anything else through fsspec."""
    scheme = urlparse(location).scheme
    if not is_url(location):
        return location
    if scheme == "file":
        return urlparse(location).path
    import fsspec

    return fsspec.open(location, "rb").open()


# ----------------------------------------------------------------------------------------------------------
# Manifest
# ----------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Manifest:
    """A dataset's ``manifest.json`` and where it was read from (shard paths are relative to it)."""

    data: Mapping[str, Any]
    location: str

    def split(self, name: str) -> Mapping[str, Any]:
        splits = self.data.get("splits", {})
        if name not in splits:
            raise ManifestError(f"{self.location}: no split {name!r} (has {sorted(splits)})")
        return splits[name]

    @property
    def dataset_id(self) -> str:
        return str(self.data.get("dataset_id", ""))

    @property
    def record_spec(self) -> RecordSpec:
        text = self.data["text_encoder"]
        return RecordSpec(
            feature_dim=int(self.data["feature_spec"]["dim"]),
            text_dim=int(text["dim"]),
            token_features=bool(text.get("token_features", False)),
            max_tokens=int(text.get("max_tokens", 0)),
        )

    @property
    def mean(self) -> np.ndarray:
        return np.asarray(self.data["normalization"]["mean"], np.float32)

    @property
    def std(self) -> np.ndarray:
        return np.asarray(self.data["normalization"]["std"], np.float32)

    @property
    def action_classes(self) -> tuple[str, ...]:
        return tuple(self.data.get("action_classes") or ())


def _check_remote_manifest(data: Any, location: str) -> None:
    """The fields the loader relies on, for a manifest read from a URL (``load_manifest`` checks local ones)."""
    if not isinstance(data, dict):
        raise ManifestError(f"{location}: a manifest must be a JSON object")
    if data.get("format_version") != FORMAT_VERSION:
        raise ManifestError(f"{location}: format_version {data.get('format_version')!r}, this code reads "
                            f"{FORMAT_VERSION}")
    missing = [key for key in ("feature_spec", "normalization", "text_encoder", "splits") if key not in data]
    if missing:
        raise ManifestError(f"{location}: missing keys {missing}")


def open_manifest(location: str | os.PathLike | Manifest) -> Manifest:
    """Read ``manifest.json`` from a local path (or its dataset folder) with the builder's
    ``load_manifest``, or from a URL. Files are not checked here: see :func:`verify_shards`."""
    if isinstance(location, Manifest):
        return location
    location = os.fspath(location)
    if not is_url(location):
        path = os.path.join(location, MANIFEST_NAME) if os.path.isdir(location) else location
        return Manifest(data=load_manifest(path, verify="none"), location=os.path.abspath(path))
    try:
        with open_binary(location) as stream:
            data = json.loads(stream.read())
    except (OSError, ValueError) as exc:
        raise ManifestError(f"{location}: cannot read manifest: {exc}") from exc
    _check_remote_manifest(data, location)
    return Manifest(data=data, location=location)


@dataclass(frozen=True)
class ShardInfo:
    """One shard (a tar or a Parquet part) as the manifest lists it."""

    path: str  # as written in the manifest, relative to it: the name used in reports and exclude lists
    url: str  # resolved location
    num_motions: int
    bytes: int
    sha256: str


def split_shards(manifest: Manifest, split: str, backend: str = "webdataset") -> list[ShardInfo]:
    """Stage 1: the shards of a split in manifest order."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    entries = manifest.split(split).get(_MANIFEST_LIST_KEY[backend]) or []
    if not entries:
        raise ManifestError(f"{manifest.location}: split {split!r} lists no {backend} files")
    return [ShardInfo(path=e["path"], url=resolve_location(manifest.location, e["path"]),
                      num_motions=int(e["num_motions"]), bytes=int(e["bytes"]), sha256=str(e["sha256"]))
            for e in entries]


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
# Shard verification (before training)
# ----------------------------------------------------------------------------------------------------------

VERIFY_MODES = ("strict", "tolerant", "off")


class ShardVerificationError(RuntimeError):
    """A shard is missing, truncated or corrupted (strict verification)."""


@dataclass(frozen=True)
class BadShard:
    path: str
    reason: str
    num_motions: int


@dataclass(frozen=True)
class VerificationReport:
    split: str
    backend: str
    mode: str
    num_checked: int
    bad: tuple[BadShard, ...] = ()

    @property
    def bad_paths(self) -> tuple[str, ...]:
        """Pass this to ``MotionLoader(exclude_shards=...)``; broadcast rank 0's copy to keep ranks equal."""
        return tuple(b.path for b in self.bad)

    @property
    def samples_lost(self) -> int:
        return sum(b.num_motions for b in self.bad)

    def as_dict(self) -> dict[str, Any]:
        return {"split": self.split, "backend": self.backend, "mode": self.mode, "num_checked": self.num_checked,
                "samples_lost": self.samples_lost,
                "bad": [{"path": b.path, "reason": b.reason, "num_motions": b.num_motions} for b in self.bad]}


def _hash_stream(stream: BinaryIO, chunk: int = 1 << 20) -> tuple[int, str]:
    digest, size = hashlib.sha256(), 0
    while block := stream.read(chunk):
        digest.update(block)
        size += len(block)
    return size, digest.hexdigest()


def check_shard(shard: ShardInfo) -> str | None:
    """Why this shard cannot be trusted (missing / truncated / size / sha256), or None if it matches."""
    if not is_url(shard.url):
        if not os.path.exists(shard.url):
            return "missing"
        size = os.path.getsize(shard.url)
        if size < shard.bytes:
            return f"truncated: {size} bytes, manifest says {shard.bytes}"
        if size != shard.bytes:
            return f"size mismatch: {size} bytes, manifest says {shard.bytes}"
    try:
        with open_binary(shard.url) as stream:
            size, sha = _hash_stream(stream)
    except (OSError, ValueError) as exc:
        return f"unreadable: {exc}"
    if size != shard.bytes:
        return f"{'truncated' if size < shard.bytes else 'size mismatch'}: {size} bytes, manifest says {shard.bytes}"
    if sha != shard.sha256:
        return f"corrupted: sha256 {sha[:16]}…, manifest says {shard.sha256[:16]}…"
    return None


def verify_shards(manifest: Manifest | str | os.PathLike, split: str, mode: str = "strict",
                  backend: str = "webdataset") -> VerificationReport:
    """Check every shard of a split against the manifest's size and sha256, before training.

    ``strict`` raises :class:`ShardVerificationError` naming the first bad shard; ``tolerant`` checks them
    all and reports the bad ones (pass ``report.bad_paths`` as ``exclude_shards``; every rank must exclude
    the same list, so verify on every rank (deterministic) or broadcast rank 0's list); ``off`` checks
    nothing. Runtime read errors always raise: skipping data on one rank mid-epoch would unbalance ranks.
    """
    if mode not in VERIFY_MODES:
        raise ValueError(f"verify mode must be one of {VERIFY_MODES}, got {mode!r}")
    manifest = open_manifest(manifest)
    if mode == "off":
        return VerificationReport(split=split, backend=backend, mode=mode, num_checked=0)
    bad = []
    shards = split_shards(manifest, split, backend)
    for shard in shards:
        reason = check_shard(shard)
        if reason is None:
            continue
        if mode == "strict":
            raise ShardVerificationError(f"{shard.url}: bad shard ({reason}); split {split!r} of "
                                         f"{manifest.location}. Rebuild it, or verify in tolerant mode to skip it.")
        logger.warning("bad shard %s: %s (%d motions skipped)", shard.path, reason, shard.num_motions)
        bad.append(BadShard(path=shard.path, reason=reason, num_motions=shard.num_motions))
    report = VerificationReport(split=split, backend=backend, mode=mode, num_checked=len(shards), bad=tuple(bad))
    if bad:
        logger.warning("%d of %d %s shards of split %r are bad; %d motions will be skipped every epoch",
                       len(bad), len(shards), backend, split, report.samples_lost)
    return report


# ----------------------------------------------------------------------------------------------------------
# Reading: shard → (position, raw record) for the wanted positions
# ----------------------------------------------------------------------------------------------------------


class ShardReadError(RuntimeError):
    """A shard that cannot be read or does not match its manifest entry, discovered while training."""


def read_tar_shard(shard: ShardInfo, wanted: np.ndarray) -> Iterator[tuple[int, dict]]:
    """Yield ``(position, raw webdataset sample)`` for the wanted positions of one tar shard, in order.
    Stops after the last wanted record; a shard that ends early or holds extra records is an error."""
    positions = np.flatnonzero(wanted)
    if positions.size == 0:
        return
    last = int(positions[-1])
    count = 0
    try:
        with open_binary(shard.url) as stream:
            files = tar_file_expander([{"url": shard.url, "stream": stream}])
            for position, raw in enumerate(group_by_keys(files)):
                count = position + 1
                if position >= shard.num_motions:
                    break
                if wanted[position]:
                    yield position, raw
                if position == last:
                    return
    except (OSError, ValueError, EOFError, KeyError, tarfile.TarError) as exc:
        raise ShardReadError(f"{shard.url}: cannot read shard: {exc}") from exc
    found = f"more than {shard.num_motions}" if count > shard.num_motions else str(count)
    raise ShardReadError(f"{shard.url}: holds {found} records where the manifest says {shard.num_motions} "
                         "(truncated or replaced shard?)")


def read_parquet_part(shard: ShardInfo, wanted: np.ndarray) -> Iterator[tuple[int, ParquetRow]]:
    """Yield ``(position, ParquetRow)`` for the wanted rows, reading only row groups that hold one."""
    import pyarrow.parquet as pq

    try:
        part = pq.ParquetFile(_open_seekable(shard.url))
    except (OSError, ValueError) as exc:
        raise ShardReadError(f"{shard.url}: cannot read Parquet part: {exc}") from exc
    with part:
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


_READERS: dict[str, Callable[[ShardInfo, np.ndarray], Iterator[tuple[int, Any]]]] = {
    "webdataset": read_tar_shard,
    "parquet": read_parquet_part,
}
_DECODERS = {"webdataset": DecodeTarRecord, "parquet": DecodeParquetRow}


def ordered_records(shards: Sequence[ShardInfo], emission: np.ndarray,
                    read: Callable[[ShardInfo, np.ndarray], Iterator[tuple[int, Any]]]) -> Iterator[Any]:
    """Stage 5: raw records of a slot in ``emission`` order (positions in the concatenated shards).

    Shards are read sequentially; a record is held until its turn, so at most about a shuffle buffer's
    worth of raw records is in memory. Positions not in ``emission`` (consumed before a resume, or past
    the epoch's batch count) are never decoded, and shards with none of them are never opened."""
    total = sum(s.num_motions for s in shards)
    wanted = np.zeros(total, dtype=bool)
    wanted[emission] = True
    pending: dict[int, Any] = {}
    next_out = 0
    base = 0
    for shard in shards:
        shard_wanted = wanted[base:base + shard.num_motions]
        if shard_wanted.any():
            for position, raw in read(shard, shard_wanted):
                pending[base + position] = raw
                while next_out < len(emission) and int(emission[next_out]) in pending:
                    yield pending.pop(int(emission[next_out]))
                    next_out += 1
        base += shard.num_motions
    if next_out != len(emission):
        raise ShardReadError(f"slot stream ended after {next_out} of {len(emission)} records: shards "
                             f"{[s.path for s in shards]} hold fewer records than the manifest says")


def iter_motions(manifest: Manifest | str | os.PathLike, split: str,
                 backend: str = "webdataset") -> Iterator[MotionRecord]:
    """Every record of a split once, in manifest order, decoded and not cropped (for evaluators/tools)."""
    manifest = open_manifest(manifest)
    decode = _DECODERS[backend](manifest.record_spec)
    for shard in split_shards(manifest, split, backend):
        for _, raw in _READERS[backend](shard, np.ones(shard.num_motions, dtype=bool)):
            yield decode(raw)


# ----------------------------------------------------------------------------------------------------------
# Options and the per-rank stream that runs in DataLoader workers
# ----------------------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class LoaderOptions:
    """How the stream is cut, shuffled and batched. Everything here except ``backend``, ``prefetch_factor``,
    ``pin_memory`` and ``multiprocessing_context`` is part of the resume state and must not change on resume."""

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
    backend: str = "webdataset"
    """'webdataset' (tar shards, local or any URL) or 'parquet' (the same records, Parquet parts)."""
    prefetch_factor: int = 2
    pin_memory: bool = False
    multiprocessing_context: str | None = None

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

    @property
    def readers_per_rank(self) -> int:
        return max(1, self.num_workers)


@dataclass(frozen=True, eq=False)
class _StreamSpec:
    """Everything a reader process needs (picklable, so spawn contexts work too)."""

    shards: tuple[ShardInfo, ...]
    record_spec: RecordSpec
    mean: np.ndarray
    std: np.ndarray
    action_classes: tuple[str, ...]
    options: LoaderOptions
    rank: int
    world_size: int
    _plans: dict = field(default_factory=dict, compare=False, repr=False)

    def plan(self, epoch: int) -> EpochPlan:
        if epoch not in self._plans:
            if len(self._plans) > 8:
                self._plans.clear()
            self._plans[epoch] = plan_epoch([s.num_motions for s in self.shards], epoch=epoch,
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
                f"fewer workers or ranks, or more data ({len(self.shards)} shards, {plan.num_slots} readers).")
        return plan


def batches_before(position: int, reader: int, readers: int) -> int:
    """How many of the rank's first ``position`` batches came from ``reader`` (batch k is reader k % readers)."""
    return max(0, (position - reader + readers - 1) // readers)


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
        for epoch in itertools.count(self.start_epoch):
            yield from self.reader_epoch(epoch, reader, skip)
            skip = 0

    def reader_epoch(self, epoch: int, reader: int, skip_batches: int) -> Iterator[dict]:
        spec, opts = self.spec, self.spec.options
        plan = spec.checked_plan(epoch)
        slot = plan.slot(spec.rank, reader)
        shards = [spec.shards[i] for i in plan.slot_shards[slot]]
        order = slot_sample_order(plan.slot_samples[slot], seed=opts.seed, epoch=epoch, slot=slot,
                                  shuffle=opts.shuffle, buffer_size=opts.shuffle_buffer)
        batch_size = opts.batch_size
        emission = order[skip_batches * batch_size: plan.batches_per_reader * batch_size]
        pipeline = wds.DataPipeline(
            functools.partial(ordered_records, shards, emission, _READERS[opts.backend]),
            wds.map(_DECODERS[opts.backend](spec.record_spec)),
            wds.map(PickCaption(opts.seed, epoch, opts.caption_policy)),
            wds.map(CropToWindow(opts.window, opts.unit_length, opts.shorten_prob, opts.seed, epoch)),
            wds.map(Normalize(spec.mean, spec.std)),
            wds.batched(batch_size, collation_fn=Collate(opts.window, spec.action_classes), partial=False),
        )
        for local, batch in enumerate(pipeline, start=skip_batches):
            batch["_position"] = (epoch, local * plan.readers_per_rank + reader)
            yield batch


# ----------------------------------------------------------------------------------------------------------
# The loader the trainer uses
# ----------------------------------------------------------------------------------------------------------

_PLAN_STATE_KEYS = ("split", "dataset_id", "world_size", "num_workers", "batch_size", "seed", "shuffle",
                    "shuffle_buffer", "window", "unit_length", "shorten_prob", "caption_policy", "excluded_shards")


class MotionLoader:
    """Batches of one rank, exactly once per epoch across ranks and workers, resumable bit-exactly.

    ``iter_batches()`` yields forever (epochs roll over); ``iter_epoch()`` yields the rest of the current
    epoch. ``epoch`` and ``batches_in_epoch`` say where the next batch comes from; ``state_dict()`` saves
    that. Do not pass this loader through ``accelerator.prepare()`` (it is already sharded; see the module
    docstring); move batches to the device yourself.

    Args:
        manifest: a :class:`Manifest`, or the path/URL of ``manifest.json`` (or of its directory).
        split: "train", "val", ...
        options: :class:`LoaderOptions`.
        rank, world_size: this process among the data-parallel ranks.
        exclude_shards: manifest paths of shards to leave out (``VerificationReport.bad_paths``); must be
            the same list on every rank.
    """

    def __init__(self, manifest: Manifest | str | os.PathLike, split: str, options: LoaderOptions, *,
                 rank: int = 0, world_size: int = 1, exclude_shards: Iterable[str] = ()):
        if world_size < 1 or not 0 <= rank < world_size:
            raise ValueError(f"rank {rank} is not in a world of size {world_size}")
        self.manifest = open_manifest(manifest)
        self.split, self.options, self.rank, self.world_size = split, options, rank, world_size
        shards = split_shards(self.manifest, split, options.backend)
        self.excluded_shards = tuple(sorted(set(exclude_shards)))
        unknown = set(self.excluded_shards) - {s.path for s in shards}
        if unknown:
            raise ValueError(f"exclude_shards names shards that split {split!r} of {self.manifest.location} "
                             f"does not list for backend {options.backend!r}: {sorted(unknown)}")
        usable = tuple(s for s in shards if s.path not in self.excluded_shards and s.num_motions > 0)
        readers = world_size * options.readers_per_rank
        if len(usable) < readers:
            raise ValueError(
                f"split {split!r} has {len(usable)} usable shards but world_size {world_size} × "
                f"{options.readers_per_rank} reader(s) per rank (num_workers={options.num_workers}) = {readers} "
                f"readers each need at least one; write smaller shards or use fewer workers")
        self._spec = _StreamSpec(shards=usable, record_spec=self.manifest.record_spec, mean=self.manifest.mean,
                                 std=self.manifest.std, action_classes=self.manifest.action_classes,
                                 options=options, rank=rank, world_size=world_size)
        self.epoch = 0
        self.batches_in_epoch = 0
        self._generation = 0
        self._plan_logged = False
        self._log_plan(self._spec.checked_plan(0))

    # -- plan ------------------------------------------------------------------------------------------

    @property
    def shards(self) -> tuple[ShardInfo, ...]:
        return self._spec.shards

    def plan(self, epoch: int | None = None) -> EpochPlan:
        return self._spec.plan(self.epoch if epoch is None else epoch)

    def batches_per_epoch(self, epoch: int | None = None) -> int:
        """Batches this rank (and every other rank) yields in the epoch."""
        return self._spec.checked_plan(self.epoch if epoch is None else epoch).batches_per_rank

    def samples_dropped(self, epoch: int | None = None) -> int:
        """Samples of the split (all ranks) not used in the epoch so that all readers yield equal batches."""
        return self.plan(epoch).samples_dropped

    def _log_plan(self, plan: EpochPlan) -> None:
        # Once at INFO (the first epoch); later epochs at DEBUG: a small dataset turns over every few steps.
        level = logging.INFO if plan.epoch == 0 or not self._plan_logged else logging.DEBUG
        self._plan_logged = True
        logger.log(level, "data %s epoch %d: %d batches per rank, %d of %d samples used, %d dropped (rotates "
                    "across epochs), %d shards over %d readers", self.split, plan.epoch, plan.batches_per_rank,
                    plan.samples_used, plan.samples_in_epoch, plan.samples_dropped, len(self.shards),
                    plan.num_slots)

    # -- state -----------------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Position and everything that fixes the epoch plan. Identical on every rank."""
        opts = self.options
        return {"version": STATE_VERSION, "epoch": self.epoch, "batches_in_epoch": self.batches_in_epoch,
                "split": self.split, "dataset_id": self.manifest.dataset_id, "world_size": self.world_size,
                "num_workers": opts.num_workers, "batch_size": opts.batch_size, "seed": opts.seed,
                "shuffle": opts.shuffle, "shuffle_buffer": opts.shuffle_buffer, "window": opts.window,
                "unit_length": opts.unit_length, "shorten_prob": opts.shorten_prob,
                "caption_policy": opts.caption_policy, "excluded_shards": list(self.excluded_shards)}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Continue from a saved position. Refuses anything that would change the epoch plan (world size,
        worker count, batch size, seed, ...): the remaining batches would not be the ones that were due."""
        if state.get("version") != STATE_VERSION:
            raise ValueError(f"data loader state version {state.get('version')!r}, this loader reads {STATE_VERSION}")
        current = self.state_dict()
        for key in _PLAN_STATE_KEYS:
            saved, now = state.get(key), current[key]
            if key == "excluded_shards":
                saved = list(saved or [])
            if saved != now:
                raise ValueError(f"cannot resume the data stream: {key} was {saved!r} when the state was saved "
                                 f"and is {now!r} now; the epoch plan would differ. Resume with the same "
                                 f"{key}, or start a new epoch from scratch without loading the data state.")
        epoch, position = int(state["epoch"]), int(state["batches_in_epoch"])
        if epoch < 0 or not 0 <= position < self.batches_per_epoch(epoch):
            raise ValueError(f"data loader state position (epoch {epoch}, batch {position}) is outside the epoch "
                             f"({self.batches_per_epoch(max(epoch, 0))} batches)")
        self.epoch, self.batches_in_epoch = epoch, position
        self._generation += 1  # iterators created before this point are stale

    # -- iteration -------------------------------------------------------------------------------------

    def iter_batches(self) -> Iterator[dict[str, Any]]:
        """Batches forever, from the current position; ``epoch``/``batches_in_epoch`` advance as they are
        yielded (so ``state_dict()`` taken after consuming a batch resumes at the next one). Creating a new
        iterator or loading a state makes older iterators raise."""
        self._generation += 1
        stream = _RankStream(self._spec, self.epoch, self.batches_in_epoch)
        if self.options.num_workers == 0:
            source: Iterable[dict] = stream
        else:
            source = DataLoader(stream, batch_size=None, collate_fn=_as_is, num_workers=self.options.num_workers,
                                prefetch_factor=self.options.prefetch_factor, pin_memory=self.options.pin_memory,
                                multiprocessing_context=self.options.multiprocessing_context)
        return self._checked(iter(source), self._generation)

    def iter_epoch(self) -> Iterator[dict[str, Any]]:
        """The remaining batches of the current epoch, then stop (workers are shut down)."""
        return _take(self.iter_batches(), self.batches_per_epoch() - self.batches_in_epoch)

    def _checked(self, source: Iterator[dict], generation: int) -> Iterator[dict[str, Any]]:
        for batch in source:
            if generation != self._generation:
                raise RuntimeError("this batch iterator is stale: the loader's state was loaded or another "
                                   "iterator was created since; call iter_batches() again")
            position = tuple(batch.pop("_position"))  # robust to list conversion by collate/pin_memory
            if position != (self.epoch, self.batches_in_epoch):
                raise RuntimeError(f"data stream out of order: got batch {position}, expected "
                                   f"{(self.epoch, self.batches_in_epoch)}")
            self._advance()
            yield batch

    def _advance(self) -> None:
        self.batches_in_epoch += 1
        if self.batches_in_epoch == self.batches_per_epoch(self.epoch):
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
