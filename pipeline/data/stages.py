"""The per-sample stages of the training stream, each a small callable that can be tested alone.

Order in the stream (see ``pipeline.data.stream`` for the shard-level stages that come before):

    raw record ─► DecodeTarRecord / DecodeParquetRow ─► PickCaption ─► CropToWindow ─► Normalize ─► Collate
                  (MotionRecord: all captions)          (one caption,   (MFM crop)     (manifest    (padded batch
                                                         its span)                      Mean/Std)     + masks)

Which samples go into which batch is decided before any record is read, from the manifest alone: the slot's shuffle
order (:func:`shuffle_buffer_order`) and, for length-aware batches, its regrouping by the manifest's clip lengths
(:func:`length_grouped_order`). How wide a batch is padded is decided by ``Collate`` from the cropped clips
themselves (:func:`padded_width`).

Tolerant mode wraps each per-sample stage in :class:`SkipBadRecords`: a record that fails to decode or validate
becomes a :class:`SkippedRecord` that flows on in its place until ``Collate`` drops it, so a batch is cut from
the same stream positions whether or not some of its records were bad. A batch whose every record was skipped
is still a batch: an empty one (zero rows, same keys), which the trainer steps through like any other, so every
rank takes exactly one planned batch per step.

Randomness. A stage that draws (caption pick, crop length and offset) seeds a fresh generator from
``(seed, epoch, sample id, stage)`` through :func:`sample_rng`. No generator state is carried from one
sample to the next, so replaying a stream from any point, on any number of ranks or workers, draws exactly
the same caption and crop for a given motion in a given epoch: that is what makes mid-epoch resume exact.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
from dataclasses import dataclass, replace
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch

SKIPPED_RECORDS_KEY = "skipped_records"
"""The batch key that lists why records were left out of the batch (tolerant mode); the loader pops it."""

# Stage tags keep the random streams of different stages independent of each other.
_TAG_CAPTION = 1
_TAG_CROP = 2


class DataError(Exception):
    """Bad data met while checking or reading a dataset: a shard or record that contradicts its manifest or the
    format. The message names the file and the reason, and the fix is the data's (rebuild or repair it, or leave it
    out with tolerant verification), so entry points print it as one ``error:`` line and exit with code 2.
    Subclasses keep the one-message constructor: the error is pickled to cross from a DataLoader worker or
    another rank."""


class RecordError(DataError, ValueError):
    """A record whose content contradicts the dataset format (shapes, spans, missing members)."""


def stable_id_hash(sample_id: str) -> int:
    """A 64-bit hash of a sample id that is the same in every process (Python's ``hash`` is salted)."""
    return int.from_bytes(hashlib.blake2b(sample_id.encode("utf-8"), digest_size=8).digest(), "little")


def sample_rng(seed: int, epoch: int, sample_id: str, tag: int) -> np.random.Generator:
    """The generator of one stage for one sample in one epoch: independent of rank, worker and order."""
    return np.random.default_rng(np.random.SeedSequence([seed, epoch, stable_id_hash(sample_id), tag]))


# ----------------------------------------------------------------------------------------------------------
# What flows between stages
# ----------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RecordSpec:
    """What a record must look like, from the manifest: checked by the decoders."""

    feature_dim: int
    text_dim: int
    token_features: bool = False
    max_tokens: int = 0
    noise_seeds: bool = False
    """A distillation pair set (pipeline/training/distill.py): every record carries its ``noise_seed``."""


@dataclass(frozen=True)
class MotionRecord:
    """One decoded record: a motion with all of its captions (features not normalised)."""

    id: str
    features: np.ndarray  # (T, D) float32
    text_emb: np.ndarray  # (C, E) float32
    captions: tuple[str, ...]
    caption_tokens: tuple[tuple[str, ...], ...]
    spans: np.ndarray  # (C, 2) int64: [start_frame, end_frame) per caption
    action: str | None
    source: str  # the shard it came from, for error messages
    text_tokens: np.ndarray | None = None  # (C, L, E) float32
    text_token_len: np.ndarray | None = None  # (C,) int32
    noise_seed: int | None = None  # distillation pairs: the seed of the noise the teacher integrated


@dataclass(frozen=True)
class TrainingSample:
    """One motion paired with one of its captions, on its way to a batch."""

    id: str
    features: np.ndarray  # (m, D) float32
    caption: str
    caption_tokens: tuple[str, ...]
    caption_index: int
    text_emb: np.ndarray  # (E,)
    action: str | None
    start_frame: int  # where ``features`` starts in the full motion
    text_tokens: np.ndarray | None = None  # (L, E)
    text_token_len: int | None = None
    noise_seed: int | None = None


@dataclass(frozen=True)
class SkippedRecord:
    """A record tolerant mode leaves out, in its place in the stream; ``reason`` names the file, the record and
    what is wrong with it. Keeping the place (rather than dropping the item) is what keeps batch boundaries, and
    with them the resume position and every later batch, where they would be without the bad record."""

    reason: str


class SkipBadRecords:
    """Tolerant mode around one per-sample stage: a :class:`RecordError` from the stage becomes a
    :class:`SkippedRecord`; a record skipped by an earlier stage passes through untouched. The outcome depends
    only on the record's bytes, so a resumed stream skips the same records at the same places."""

    def __init__(self, stage: Callable[[Any], Any]):
        self.stage = stage

    def __call__(self, item: Any) -> Any:
        if isinstance(item, SkippedRecord):
            return item
        try:
            return self.stage(item)
        except RecordError as exc:
            return SkippedRecord(str(exc))


# ----------------------------------------------------------------------------------------------------------
# Decode
# ----------------------------------------------------------------------------------------------------------


def _validate_record(rec: MotionRecord, spec: RecordSpec, length: int) -> MotionRecord:
    where = f"{rec.source}: record {rec.id!r}"
    feats, emb = rec.features, rec.text_emb
    if feats.ndim != 2 or feats.shape != (length, spec.feature_dim):
        raise RecordError(f"{where}: features shape {feats.shape}, expected ({length}, {spec.feature_dim})")
    num_captions = len(rec.captions)
    if num_captions == 0:
        raise RecordError(f"{where}: no captions")
    if emb.shape != (num_captions, spec.text_dim):
        raise RecordError(f"{where}: text_emb shape {emb.shape}, expected ({num_captions}, {spec.text_dim})")
    if len(rec.caption_tokens) != num_captions or rec.spans.shape != (num_captions, 2):
        raise RecordError(f"{where}: caption tokens/spans do not match the {num_captions} captions")
    starts, ends = rec.spans[:, 0], rec.spans[:, 1]
    if (starts < 0).any() or (ends > length).any() or (ends <= starts).any():
        raise RecordError(f"{where}: caption span outside [0, {length}] or empty: {rec.spans.tolist()}")
    if spec.token_features:
        if rec.text_tokens is None or rec.text_token_len is None:
            raise RecordError(f"{where}: the manifest declares token features but the record has none")
        expected = (num_captions, spec.max_tokens, spec.text_dim)
        if rec.text_tokens.shape != expected or rec.text_token_len.shape != (num_captions,):
            raise RecordError(f"{where}: text_tokens shape {rec.text_tokens.shape}, expected {expected}")
    if spec.noise_seeds and rec.noise_seed is None:
        raise RecordError(f"{where}: the manifest is a distillation pair set but the record has no noise_seed")
    if not np.isfinite(feats).all():
        raise RecordError(f"{where}: features contain NaN or inf")
    return rec


AST_RACE_MESSAGE = "AST constructor recursion depth mismatch"
"""CPython 3.11's AST constructor keeps one recursion counter for every thread (python/cpython#106905): when two
threads of a process parse at once (np.load reads a .npy header with ``ast.literal_eval``; a loader process also
runs fsspec's and the HTTP client's threads), a good header can fail with a SystemError saying this. It says
nothing about the data, so the read is tried again instead of dropping a sound record."""
AST_RACE_ATTEMPTS = 3


NPY_LAYOUTS: dict[bytes, tuple[np.dtype, tuple[int, ...], str]] = {}
"""A process's .npy headers seen so far → (dtype, shape, order) of their arrays. np.load parses every header with
``ast.literal_eval``, which was 80 % of a record's decode time on a CPU profile (docs/performance.md,
"The loader's .npy headers"); a dataset's records share a few hundred headers (one per clip length, one per
pooled/token shape), so each is parsed once and the arrays after it are copied straight from their bytes."""
NPY_LAYOUTS_MAX = 4096  # cleared when full: a bound, never reached by one dataset's shapes


def _npy_header(payload: bytes) -> bytes | None:
    """The magic, version, length and header dict of a .npy payload (the bytes its layout depends on), or None if
    it does not start like one (np.load then says what is wrong)."""
    if len(payload) < 10 or payload[:6] != b"\x93NUMPY":
        return None
    if payload[6] == 1:
        end = 10 + int.from_bytes(payload[8:10], "little")
    elif payload[6] in (2, 3) and len(payload) >= 12:
        end = 12 + int.from_bytes(payload[8:12], "little")
    else:
        return None
    return payload[:end] if end <= len(payload) else None


def _load_npy(raw: Mapping[str, Any], member: str, where: str) -> np.ndarray:
    if member not in raw:
        raise RecordError(f"{where}: missing member .{member}")
    payload = raw[member]
    header = _npy_header(payload)
    layout = NPY_LAYOUTS.get(header) if header is not None else None
    if layout is not None:
        dtype, shape, order = layout
        count = math.prod(shape)
        if len(payload) - len(header) == count * dtype.itemsize:  # else np.load below names the damage
            return np.frombuffer(payload, dtype=dtype, count=count, offset=len(header)).reshape(
                shape, order=order).copy(order=order)  # writable, as np.load's
    array = _parsed_npy(payload, member, where)
    if header is not None and array.dtype.kind in "biuf":
        if len(NPY_LAYOUTS) >= NPY_LAYOUTS_MAX:
            NPY_LAYOUTS.clear()
        order = "F" if array.ndim > 1 and array.flags.f_contiguous and not array.flags.c_contiguous else "C"
        NPY_LAYOUTS[header] = (array.dtype, array.shape, order)
    return array


def _parsed_npy(payload: bytes, member: str, where: str) -> np.ndarray:
    """np.load of a payload whose header is new to this process (or damaged), read again after CPython's AST race."""
    for attempt in range(1, AST_RACE_ATTEMPTS + 1):
        try:
            return np.load(io.BytesIO(payload), allow_pickle=False)
        except SystemError as exc:
            if AST_RACE_MESSAGE not in str(exc) or attempt == AST_RACE_ATTEMPTS:
                raise RecordError(f"{where}: cannot decode .{member}: {exc}") from exc
        except Exception as exc:  # np.load raises several types for a damaged payload
            raise RecordError(f"{where}: cannot decode .{member}: {exc}") from exc
    raise AssertionError("unreachable")  # the loop returns or raises


class DecodeTarRecord:
    """webdataset sample (``{"__key__", "features.npy": bytes, ...}``) → :class:`MotionRecord`."""

    def __init__(self, spec: RecordSpec):
        self.spec = spec

    def __call__(self, raw: Mapping[str, Any]) -> MotionRecord:
        key = raw.get("__key__", "?")
        where = f"{raw.get('__url__', '?')}: record {key!r}"
        if "meta.json" not in raw:
            raise RecordError(f"{where}: missing member .meta.json")
        try:
            meta = json.loads(raw["meta.json"])
        except ValueError as exc:
            raise RecordError(f"{where}: cannot parse .meta.json: {exc}") from exc
        if meta.get("id") != key:
            raise RecordError(f"{where}: meta.json id {meta.get('id')!r} differs from the tar key")
        captions = meta.get("captions") or []
        has_tokens = "text_tokens.npy" in raw
        rec = MotionRecord(
            id=key,
            features=_load_npy(raw, "features.npy", where).astype(np.float32, copy=False),
            text_emb=_load_npy(raw, "text_emb.npy", where).astype(np.float32, copy=False),
            captions=tuple(c["text"] for c in captions),
            caption_tokens=tuple(tuple(c.get("tokens") or ()) for c in captions),
            spans=np.array([[c["start_frame"], c["end_frame"]] for c in captions], dtype=np.int64).reshape(-1, 2),
            action=meta.get("action"),
            source=str(raw.get("__url__", "?")),
            text_tokens=_load_npy(raw, "text_tokens.npy", where).astype(np.float32, copy=False) if has_tokens else None,
            text_token_len=_load_npy(raw, "text_token_len.npy", where) if has_tokens else None,
            noise_seed=None if meta.get("noise_seed") is None else int(meta["noise_seed"]),
        )
        return _validate_record(rec, self.spec, int(meta["length"]))


@dataclass(frozen=True)
class ParquetRow:
    """One row of a Parquet part: a one-row slice of a row group (zero-copy) and the file it came from."""

    table: Any  # pyarrow.Table with one row
    source: str


def _flatten_cell(table, column: str, depth: int) -> np.ndarray:
    """The numbers of a ``depth``-times nested list cell of a one-row table. ``flatten()`` (unlike
    ``.values``) respects the slice offset of the row."""
    arr = table.column(column).combine_chunks()
    for _ in range(depth):
        arr = arr.flatten()
    return arr.to_numpy(zero_copy_only=False)


class DecodeParquetRow:
    """:class:`ParquetRow` → :class:`MotionRecord` (the same record the tar shard holds)."""

    def __init__(self, spec: RecordSpec):
        self.spec = spec

    def __call__(self, parquet_row: ParquetRow) -> MotionRecord:
        row, source = parquet_row.table, parquet_row.source
        cell = {name: row.column(name)[0].as_py() for name in ("id", "length", "action", "captions",
                                                                 "caption_tokens", "span_start", "span_end")}
        length, num_captions = int(cell["length"]), len(cell["captions"] or [])
        has_tokens = "text_tokens" in row.column_names and row.column("text_tokens")[0].is_valid
        rec = MotionRecord(
            id=cell["id"],
            features=_flatten_cell(row, "features", 2).astype(np.float32, copy=False).reshape(-1, self.spec.feature_dim),
            text_emb=_flatten_cell(row, "text_emb", 2).astype(np.float32, copy=False).reshape(-1, self.spec.text_dim),
            captions=tuple(cell["captions"] or ()),
            caption_tokens=tuple(tuple(t or ()) for t in (cell["caption_tokens"] or ())),
            spans=np.stack([np.asarray(cell["span_start"] or [], np.int64),
                            np.asarray(cell["span_end"] or [], np.int64)], axis=1).reshape(-1, 2),
            action=cell["action"],
            source=source,
            text_tokens=(_flatten_cell(row, "text_tokens", 3).astype(np.float32, copy=False)
                         .reshape(num_captions, -1, self.spec.text_dim) if has_tokens else None),
            text_token_len=(np.asarray(row.column("text_token_len")[0].as_py(), np.int32) if has_tokens else None),
            noise_seed=(int(row.column("noise_seed")[0].as_py()) if "noise_seed" in row.column_names else None),
        )
        return _validate_record(rec, self.spec, length)


# ----------------------------------------------------------------------------------------------------------
# Caption, crop, normalise
# ----------------------------------------------------------------------------------------------------------


CAPTION_POLICIES = ("random", "first")


class PickCaption:
    """Pick one caption and cut the motion to that caption's span (HumanML3D ``#from#to`` sub-clips): uniformly
    at random (``policy="random"``, training; a function of (seed, epoch, sample id) only) or always the first
    (``"first"``, for debugging)."""

    def __init__(self, seed: int, epoch: int, policy: str = "random"):
        if policy not in CAPTION_POLICIES:
            raise ValueError(f"caption policy must be one of {CAPTION_POLICIES}, got {policy!r}")
        self.seed, self.epoch, self.policy = seed, epoch, policy

    def __call__(self, rec: MotionRecord) -> TrainingSample:
        if self.policy == "first":
            c = 0
        else:
            c = int(sample_rng(self.seed, self.epoch, rec.id, _TAG_CAPTION).integers(len(rec.captions)))
        start, end = (int(v) for v in rec.spans[c])
        return TrainingSample(
            id=rec.id,
            features=rec.features[start:end],
            caption=rec.captions[c],
            caption_tokens=rec.caption_tokens[c],
            caption_index=c,
            text_emb=rec.text_emb[c],
            action=rec.action,
            start_frame=start,
            text_tokens=None if rec.text_tokens is None else rec.text_tokens[c],
            text_token_len=None if rec.text_token_len is None else int(rec.text_token_len[c]),
            noise_seed=rec.noise_seed,
        )


class CropToWindow:
    """Random crop to at most ``window`` frames, MDM/MFM style (``Text2MotionDatasetV2.__getitem__``).

    The crop length is ``m = min(len, window)`` rounded down to a multiple of ``unit_length``; with
    probability ``shorten_prob`` one more unit is removed (MDM's ``coin2 == 'double'``, 1/3 for
    ``unit_length < 10``); the start is uniform over ``[0, len - m]``. ``unit_length = 1`` disables the
    rounding. A span shorter than one unit is kept whole, and one unit is never shortened to zero.
    MDM filters motions to 40 <= len < 200 frames and never needs the ``window`` cut; here motions longer
    than the window (AMASS, long KIT clips) are cut to a random window of that size.
    """

    def __init__(self, window: int, unit_length: int, shorten_prob: float, seed: int, epoch: int):
        if window < 1 or unit_length < 1 or not 0.0 <= shorten_prob <= 1.0:
            raise ValueError(f"bad crop options: window={window}, unit_length={unit_length}, "
                             f"shorten_prob={shorten_prob}")
        self.window, self.unit_length, self.shorten_prob = window, unit_length, shorten_prob
        self.seed, self.epoch = seed, epoch

    def crop_length(self, length: int, rng: np.random.Generator) -> int:
        m = min(length, self.window)
        units = m // self.unit_length
        if self.unit_length == 1 or units == 0:
            return m
        # Draw even when the result cannot shorten, so the offset draw below is at the same stream position.
        shorten = rng.random() < self.shorten_prob
        return (units - 1 if shorten and units > 1 else units) * self.unit_length

    def __call__(self, sample: TrainingSample) -> TrainingSample:
        rng = sample_rng(self.seed, self.epoch, sample.id, _TAG_CROP)
        length = sample.features.shape[0]
        m = self.crop_length(length, rng)
        offset = int(rng.integers(0, length - m + 1))
        return replace(sample, features=sample.features[offset:offset + m], start_frame=sample.start_frame + offset)


class Normalize:
    """Z-normalise features with the manifest's Mean/Std (computed on the train split by the builder)."""

    def __init__(self, mean: np.ndarray, std: np.ndarray):
        mean, std = np.asarray(mean, np.float32), np.asarray(std, np.float32)
        if mean.shape != std.shape or mean.ndim != 1:
            raise ValueError(f"normalisation mean {mean.shape} and std {std.shape} must be equal 1-D shapes")
        if not (np.isfinite(std).all() and (std > 0).all()):
            raise ValueError("normalisation std must be finite and > 0 in every dimension")
        self.mean, self.std = mean, std

    def __call__(self, sample: TrainingSample) -> TrainingSample:
        return replace(sample, features=(sample.features - self.mean) / self.std)


# ----------------------------------------------------------------------------------------------------------
# Batch
# ----------------------------------------------------------------------------------------------------------


def padded_width(lengths: Sequence[int], window: int, pad_multiple: int | None) -> int:
    """How many frames a batch of clips of ``lengths`` (already cropped to at most ``window``) is padded to.

    ``pad_multiple`` None (``data.batching=fixed``): always ``window``. An int (``length_aware``): the longest clip
    rounded up to a multiple of it, never above ``window`` (196 with 16: the widths are 16, 32, ..., 192, 196), so a
    compiled model or a kernel autotuner sees few distinct shapes. An empty batch keeps ``window``."""
    if pad_multiple is None or len(lengths) == 0:
        return window
    longest = max(int(n) for n in lengths)
    return min(window, -(-longest // pad_multiple) * pad_multiple)


def batch_widths(window: int, pad_multiple: int) -> int:
    """How many distinct widths :func:`padded_width` gives length-aware batches: the multiples of ``pad_multiple``
    below ``window``, and ``window`` itself (196 with 16: 13)."""
    return -(-window // pad_multiple)


class Collate:
    """Samples → the batch dict the trainer consumes; motions zero-padded to ``W`` frames: ``window`` with
    ``pad_multiple`` None (fixed windows), else the batch's longest clip rounded up to a multiple of ``pad_multiple``
    and at most ``window`` (:func:`padded_width`; length-aware batches).

    Keys: ``features`` (B, W, D) float32, ``lengths`` (B,) int64, ``mask`` (B, W) bool (True on real frames),
    ``text_emb`` (B, E) float32, ``action`` (B,) int64 (index in the manifest's ``action_classes``, -1 when the
    motion has no label), ``caption_index`` (B,) int64, ``ids`` list[str], ``captions`` list[str],
    ``caption_tokens`` list[list[str]]; with token features also ``text_tokens`` (B, L, E) float32 and
    ``text_token_len`` (B,) int64; for a distillation pair set ``noise_seed`` (B,) int64. Records skipped in tolerant mode are not in the batch (so B may be smaller
    than the batch size): their reasons are under ``SKIPPED_RECORDS_KEY``. When every record was skipped the
    batch is EMPTY, not missing: every key is there with zero rows (``features`` (0, W, D), ``ids`` [], ...;
    the sizes come from ``record_spec``), so that the batch still takes its place in the stream and the trainer
    steps through it in lockstep with the other ranks (see ``pipeline.training.trainer.Trainer.train_step``).
    """

    def __init__(self, window: int, action_classes: Sequence[str], record_spec: RecordSpec | None = None,
                 pad_multiple: int | None = None):
        if pad_multiple is not None and pad_multiple < 1:
            raise ValueError(f"pad_multiple must be >= 1 (or None: pad to the window), got {pad_multiple}")
        self.window, self.pad_multiple = window, pad_multiple
        self.action_ids = {name: i for i, name in enumerate(action_classes)}
        self.record_spec = record_spec

    def action_id(self, sample: TrainingSample) -> int:
        if sample.action is None:
            return -1
        if sample.action not in self.action_ids:
            raise RecordError(f"record {sample.id!r}: action {sample.action!r} is not in the manifest's action_classes")
        return self.action_ids[sample.action]

    def __call__(self, items: Sequence[TrainingSample | SkippedRecord]) -> dict[str, Any]:
        samples = [s for s in items if not isinstance(s, SkippedRecord)]
        skipped = [s.reason for s in items if isinstance(s, SkippedRecord)]
        if not samples:
            return {**self.empty_batch(), SKIPPED_RECORDS_KEY: skipped}
        batch = self._collate(samples)
        if skipped:
            batch[SKIPPED_RECORDS_KEY] = skipped
        return batch

    def empty_batch(self) -> dict[str, Any]:
        """A batch with no sample: the keys and trailing sizes of a real one, zero rows."""
        spec = self.record_spec
        if spec is None:
            raise ValueError("Collate needs the record_spec to build an empty batch (every record was skipped)")
        batch: dict[str, Any] = {
            "features": torch.zeros((0, self.window, spec.feature_dim), dtype=torch.float32),
            "lengths": torch.zeros(0, dtype=torch.int64),
            "mask": torch.zeros((0, self.window), dtype=torch.bool),
            "text_emb": torch.zeros((0, spec.text_dim), dtype=torch.float32),
            "action": torch.zeros(0, dtype=torch.int64),
            "caption_index": torch.zeros(0, dtype=torch.int64),
            "ids": [],
            "captions": [],
            "caption_tokens": [],
        }
        if spec.token_features:
            batch["text_tokens"] = torch.zeros((0, spec.max_tokens, spec.text_dim), dtype=torch.float32)
            batch["text_token_len"] = torch.zeros(0, dtype=torch.int64)
        if spec.noise_seeds:
            batch["noise_seed"] = torch.zeros(0, dtype=torch.int64)
        return batch

    def _collate(self, samples: Sequence[TrainingSample]) -> dict[str, Any]:
        b, dim = len(samples), samples[0].features.shape[1]
        width = padded_width([s.features.shape[0] for s in samples], self.window, self.pad_multiple)
        features = np.zeros((b, width, dim), np.float32)
        lengths = np.zeros(b, np.int64)
        for i, s in enumerate(samples):
            n = s.features.shape[0]
            features[i, :n] = s.features
            lengths[i] = n
        lengths_t = torch.from_numpy(lengths)
        batch: dict[str, Any] = {
            "features": torch.from_numpy(features),
            "lengths": lengths_t,
            "mask": torch.arange(width)[None, :] < lengths_t[:, None],
            "text_emb": torch.from_numpy(np.stack([s.text_emb for s in samples]).astype(np.float32, copy=False)),
            "action": torch.tensor([self.action_id(s) for s in samples], dtype=torch.int64),
            "caption_index": torch.tensor([s.caption_index for s in samples], dtype=torch.int64),
            "ids": [s.id for s in samples],
            "captions": [s.caption for s in samples],
            "caption_tokens": [list(s.caption_tokens) for s in samples],
        }
        if samples[0].text_tokens is not None:
            batch["text_tokens"] = torch.from_numpy(np.stack([s.text_tokens for s in samples]).astype(np.float32, copy=False))
            batch["text_token_len"] = torch.tensor([s.text_token_len for s in samples], dtype=torch.int64)
        if samples[0].noise_seed is not None:  # distillation pairs (every record has one: checked at decode)
            batch["noise_seed"] = torch.tensor([s.noise_seed for s in samples], dtype=torch.int64)
        return batch


# ----------------------------------------------------------------------------------------------------------
# Shuffle buffer
# ----------------------------------------------------------------------------------------------------------


def shuffle_buffer_order(num_items: int, buffer_size: int, rng: np.random.Generator) -> np.ndarray:
    """The output order of a classic streaming shuffle buffer over items ``0..num_items-1``.

    Fill a buffer of ``buffer_size``; for every further item, emit a random buffered item and put the new
    one in its place; at the end emit the rest in random order. Computing the order up front (from item
    counts, without reading any data) is what lets a resumed stream skip already-consumed items without
    decoding them, and lets every rank know every other rank's stream length.
    """
    if buffer_size <= 1 or num_items <= 1:
        return np.arange(num_items, dtype=np.int64)
    fill = min(buffer_size, num_items)
    buffer = np.arange(fill, dtype=np.int64)
    picks = rng.integers(0, fill, size=num_items - fill)
    out = np.empty(num_items, dtype=np.int64)
    for step, (new_item, j) in enumerate(zip(range(fill, num_items), picks)):
        out[step] = buffer[j]
        buffer[j] = new_item
    out[num_items - fill:] = rng.permutation(buffer)
    return out


def length_grouped_order(order: np.ndarray, lengths: np.ndarray, batch_size: int, window_batches: int,
                         rng: np.random.Generator | None) -> np.ndarray:
    """``order`` (a slot's shuffled emission, a whole number of batches) regrouped into length-aware batches.

    The order is cut into sort windows of ``window_batches × batch_size`` consecutive items (the last window may hold
    fewer batches); each window is sorted by ``lengths[item]`` (stably: equal lengths keep their shuffled order),
    cut into batches of ``batch_size``, and its batches are put in a random order drawn from ``rng`` (None: shortest
    first). Each batch is then a run of ``batch_size`` consecutive items of the result. Every item of ``order``
    appears once, in the same window it was in, so the batch count and the set of items are those of ``order``:
    only which items share a batch, and the batch order inside a window, change. Like :func:`shuffle_buffer_order`
    it needs only counts and lengths, so a resumed stream and every other rank compute the same batches without
    reading a record.

    Why windows and not the whole epoch: the reader holds a record from the time it is read until its turn, so
    regrouping within a window keeps that at most a shuffle buffer plus one window of records; sorting the whole
    epoch would hold most of it, and would put the shortest clips of the epoch in the same batches every epoch."""
    order = np.asarray(order, dtype=np.int64)
    if batch_size < 1 or window_batches < 1:
        raise ValueError(f"batch_size and window_batches must be >= 1, got {batch_size} and {window_batches}")
    if len(order) % batch_size:
        raise ValueError(f"{len(order)} items are not a whole number of batches of {batch_size}")
    span = window_batches * batch_size
    out = np.empty_like(order)
    for start in range(0, len(order), span):
        window = order[start:start + span]
        ranked = window[np.argsort(np.asarray(lengths)[window], kind="stable")]
        batches = ranked.reshape(-1, batch_size)
        if rng is not None:
            batches = batches[rng.permutation(len(batches))]
        out[start:start + len(window)] = batches.reshape(-1)
    return out
