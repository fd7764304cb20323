"""Shards and manifest: the webdataset tar and Parquet writers, the caption-embedding stage, the
manifest (written last) with its skip report, and :func:`build_dataset`, the two-pass build.

Two passes, so that no more than one record's features is ever held in memory:

1. Worker processes load and process clips (``preprocess.processing``); the parent receives records in
   ``list_items`` order, appends their features to a temporary spill file, accumulates the train split's
   normalisation statistics and collects the distinct caption strings. Only captions and small per-record
   metadata stay in memory.
2. Every distinct caption is encoded once, in sorted order and fixed batches (so the embeddings do not
   depend on the worker count); token features, when asked for, go to a memory-mapped temporary file.
   Then each split's records are streamed from the spill, joined with their embeddings and written to
   numbered tar and Parquet shards. ``manifest.json`` is written last (temp file + ``os.replace``):
   its presence marks a complete dataset.

The output folder (:func:`check_output_dir`, :class:`BuildMarker`): a build writes only into a new or empty folder or
one of its own earlier builds. Before it writes anything else it puts ``build-in-progress.json`` into the folder, and
it names there every path before creating it; the marker is removed once ``manifest.json`` is in place. So an
interrupted build is recognised by its marker and a complete one by its manifest, and a rebuild (``--overwrite``, or
after an interruption) deletes exactly the files one of them names, nothing else. A non-empty folder with neither,
and a shard-named file neither names (which the build could overwrite), are refused before anything is touched.

Everything written is deterministic: fixed tar headers (mtime/uid/gid 0, sorted members), fixed Parquet
options, and a manifest without timestamps or machine-specific paths.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import math
import os
import re
import shlex
import shutil
import tarfile
import time
from collections import Counter
from collections.abc import Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from tqdm import tqdm

from mfm.features import FeatureStats
from mfm.layout import FeatureLayout
from mfm.integrity import sha256_file
from mfm.skeleton import Skeleton, get_skeleton
from preprocess.clip import SkippedInput
from preprocess.processing import (
    DEFAULT_MAX_FRAMES,
    DEFAULT_MIN_FRAMES,
    default_min_frames,
    ProcessingSettings,
    Record,
    is_valid_key,
    process_source,
)

log = logging.getLogger(__name__)

FORMAT_VERSION = 2
"""The manifest format this code writes. 2: ``dataset_id`` covers the whole ``splits`` section
(:func:`derive_dataset_id`)."""
READABLE_FORMAT_VERSIONS = (1, 2)
"""Manifest formats this code reads. A format-1 manifest keeps its id, checked by the rule it was built with (the
files' sha256s only): rebuilding it gives a format-2 manifest with another id."""
MANIFEST_NAME = "manifest.json"
PAIRS_KEY = "pairs"
"""The manifest section of a distillation pair set (pipeline/training/distill.py: teacher, sampler, noise rule); its
records carry a ``noise_seed``."""
SPLIT_ORDER = ("train", "val", "test")
SHARD_FORMATS = ("tar", "parquet")
SKIP_REASONS = ("unreadable", "missing_file", "bad_shape", "bad_fps", "nan_frames", "too_short", "too_long",
                "no_captions", "no_body_model", "feature_error", "feature_mismatch", "duplicate_id")
NORMALIZATION_MODES = ("auto", "official", "recompute")
RECOMPUTED_RULE = "std averaged within each feature group"
DEFAULT_SHARD_SIZE = 500
TAR_PATTERN = "shard-{:05d}.tar"
PARQUET_PATTERN = "part-{:05d}.parquet"
_TMP_DIR_NAME = ".build-tmp"
BUILD_MARKER_NAME = "build-in-progress.json"  # the marker of a build under way (see the module docstring)
BUILD_MARKER_FORMAT = "mfm-dataset-build"
_SHARD_FILE_PATTERNS = (re.compile(r"^shard-\d{5}\.tar$"), re.compile(r"^part-\d{5}\.parquet$"))
_SHOWN_ENTRIES = 5
_PARQUET_ROW_GROUP = 64  # bounds the writer's buffer: 64 HumanML3D motions are ~10 MB of features
_TEXT_CHUNK = 1024  # captions per encode() call: bounds memory and drives the progress bar


class BadInputError(RuntimeError):
    """``--strict``: a source item could not become a record."""

    def __init__(self, skipped: SkippedInput) -> None:
        self.skipped = skipped
        super().__init__(f"{skipped.path or skipped.id}: {skipped.reason}" + (f" ({skipped.detail})" if skipped.detail else ""))


class DatasetExistsError(FileExistsError):
    """The output folder already holds a complete dataset and overwriting was not asked for."""


class OutputFolderError(FileExistsError):
    """The output folder holds files that are not of a build of ours (or that a build would overwrite): refused
    before anything in it is touched; the message names the folder, what is there and what to do."""


class ManifestError(ValueError):
    """A manifest that is missing, unreadable, of another format version, or inconsistent with its files."""


# --- record encoding -------------------------------------------------------------------------------


@dataclass(frozen=True)
class TextFeatures:
    """Text features of one record's captions, in caption order."""

    pooled: np.ndarray  # (C, E) float32
    tokens: np.ndarray | None = None  # (C, L, E) float32, zero past token_lengths
    token_lengths: np.ndarray | None = None  # (C,) int32


def record_meta(record: Record) -> dict[str, Any]:
    """The ``KEY.meta.json`` content of a record (``noise_seed`` only for a distillation pair)."""
    meta = {
        "id": record.id,
        "length": record.length,
        "fps": record.fps,
        "skeleton": record.skeleton,
        "source": record.source,
        "split": record.split,
        "action": record.action,
        "captions": [
            {"text": c.text, "tokens": list(c.tokens), "start_frame": c.start_frame, "end_frame": c.end_frame}
            for c in record.captions
        ],
    }
    if record.noise_seed is not None:
        meta["noise_seed"] = int(record.noise_seed)
    return meta


def npy_bytes(array: np.ndarray) -> bytes:
    """An array as ``.npy`` bytes (format 1.0, little-endian, C order: the same bytes every time)."""
    buffer = io.BytesIO()
    np.lib.format.write_array(buffer, np.ascontiguousarray(array), allow_pickle=False)
    return buffer.getvalue()


def tar_members(record: Record, text: TextFeatures) -> dict[str, bytes]:
    """Member suffix → bytes for one record (``KEY.<suffix>`` in the tar)."""
    members = {
        "features.npy": npy_bytes(record.features.astype("<f4", copy=False)),
        "meta.json": json.dumps(record_meta(record), ensure_ascii=False, sort_keys=True).encode("utf-8"),
        "text_emb.npy": npy_bytes(text.pooled.astype("<f4", copy=False)),
    }
    if text.tokens is not None:
        members["text_tokens.npy"] = npy_bytes(text.tokens.astype("<f4", copy=False))
        members["text_token_len.npy"] = npy_bytes(text.token_lengths.astype("<i4", copy=False))
    return members


# --- shard writers -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class ShardInfo:
    path: str  # relative to the dataset folder, "/"-separated
    num_motions: int
    bytes: int
    sha256: str

    def to_json(self) -> dict[str, Any]:
        return {"path": self.path, "num_motions": self.num_motions, "bytes": self.bytes, "sha256": self.sha256}


class TarShardWriter:
    """One webdataset shard. tarfile directly rather than ``wds.TarWriter`` so that every header field
    (mtime, uid/gid, owner names, mode, format) is fixed here and the bytes never depend on the clock."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._tar = tarfile.open(path, mode="w", format=tarfile.PAX_FORMAT)

    def write(self, record: Record, text: TextFeatures) -> None:
        for suffix, data in sorted(tar_members(record, text).items()):
            info = tarfile.TarInfo(f"{record.id}.{suffix}")
            info.size, info.mtime, info.mode = len(data), 0, 0o444
            info.uid = info.gid = 0
            info.uname = info.gname = ""
            self._tar.addfile(info, io.BytesIO(data))

    def close(self) -> None:
        self._tar.close()


def parquet_schema(feature_dim: int, text_dim: int, token_features: bool, noise_seeds: bool = False) -> pa.Schema:
    """The Parquet columns of a record; ``noise_seeds``: distillation pairs' ``noise_seed`` column too."""
    frames = pa.list_(pa.list_(pa.float32(), feature_dim))
    embeddings = pa.list_(pa.list_(pa.float32(), text_dim))
    fields = [
        pa.field("id", pa.string(), nullable=False),
        pa.field("split", pa.string(), nullable=False),
        pa.field("source", pa.string(), nullable=False),
        pa.field("skeleton", pa.string(), nullable=False),
        pa.field("action", pa.string()),
        pa.field("fps", pa.float32(), nullable=False),
        pa.field("length", pa.int32(), nullable=False),
        pa.field("features", frames, nullable=False),
        pa.field("captions", pa.list_(pa.string()), nullable=False),
        pa.field("caption_tokens", pa.list_(pa.list_(pa.string())), nullable=False),
        pa.field("span_start", pa.list_(pa.int32()), nullable=False),
        pa.field("span_end", pa.list_(pa.int32()), nullable=False),
        pa.field("text_emb", embeddings, nullable=False),
    ]
    if token_features:
        fields += [
            pa.field("text_tokens", pa.list_(embeddings), nullable=False),
            pa.field("text_token_len", pa.list_(pa.int32()), nullable=False),
        ]
    if noise_seeds:
        fields.append(pa.field("noise_seed", pa.int64(), nullable=False))
    return pa.schema(fields, metadata={"mfm_format_version": str(FORMAT_VERSION)})


def _list_of_rows(arrays: Sequence[np.ndarray], width: int) -> pa.Array:
    """list<fixed_size_list<float32>[width]> from 2-D float32 arrays (one list per array)."""
    offsets = np.concatenate([[0], np.cumsum([len(a) for a in arrays])]).astype(np.int32)
    flat = np.concatenate([np.asarray(a, dtype="<f4").reshape(-1) for a in arrays]) if arrays else np.zeros(0, "<f4")
    rows = pa.FixedSizeListArray.from_arrays(pa.array(flat, type=pa.float32()), width)
    return pa.ListArray.from_arrays(pa.array(offsets, type=pa.int32()), rows)


def records_table(batch: Sequence[tuple[Record, TextFeatures]], schema: pa.Schema) -> pa.Table:
    """A Parquet table of records with the columns of :func:`parquet_schema`."""
    records = [r for r, _ in batch]
    texts = [t for _, t in batch]
    feature_dim = schema.field("features").type.value_type.list_size
    text_dim = schema.field("text_emb").type.value_type.list_size
    columns: dict[str, pa.Array] = {
        "id": pa.array([r.id for r in records], pa.string()),
        "split": pa.array([r.split for r in records], pa.string()),
        "source": pa.array([r.source for r in records], pa.string()),
        "skeleton": pa.array([r.skeleton for r in records], pa.string()),
        "action": pa.array([r.action for r in records], pa.string()),
        "fps": pa.array([r.fps for r in records], pa.float32()),
        "length": pa.array([r.length for r in records], pa.int32()),
        "features": _list_of_rows([r.features for r in records], feature_dim),
        "captions": pa.array([[c.text for c in r.captions] for r in records], pa.list_(pa.string())),
        "caption_tokens": pa.array([[list(c.tokens) for c in r.captions] for r in records],
                                   pa.list_(pa.list_(pa.string()))),
        "span_start": pa.array([[c.start_frame for c in r.captions] for r in records], pa.list_(pa.int32())),
        "span_end": pa.array([[c.end_frame for c in r.captions] for r in records], pa.list_(pa.int32())),
        "text_emb": _list_of_rows([t.pooled for t in texts], text_dim),
    }
    if "text_tokens" in schema.names:
        per_caption = [caption for t in texts for caption in t.tokens]
        caption_offsets = np.concatenate([[0], np.cumsum([len(t.tokens) for t in texts])]).astype(np.int32)
        columns["text_tokens"] = pa.ListArray.from_arrays(
            pa.array(caption_offsets, pa.int32()), _list_of_rows(per_caption, text_dim))
        columns["text_token_len"] = pa.array([t.token_lengths.tolist() for t in texts], pa.list_(pa.int32()))
    if "noise_seed" in schema.names:
        columns["noise_seed"] = pa.array([int(r.noise_seed) for r in records], pa.int64())
    return pa.Table.from_pydict(columns, schema=schema)


class ParquetShardWriter:
    """One Parquet file holding the same records as the matching tar shard, in the same order.
    zstd level 3, row groups of ``_PARQUET_ROW_GROUP`` records; pyarrow writes no timestamps."""

    def __init__(self, path: Path, schema: pa.Schema) -> None:
        self.path = path
        self._schema = schema
        self._writer = pq.ParquetWriter(path, schema, compression="zstd", compression_level=3)
        self._buffer: list[tuple[Record, TextFeatures]] = []

    def write(self, record: Record, text: TextFeatures) -> None:
        self._buffer.append((record, text))
        if len(self._buffer) >= _PARQUET_ROW_GROUP:
            self._flush()

    def _flush(self) -> None:
        if self._buffer:
            self._writer.write_table(records_table(self._buffer, self._schema), row_group_size=len(self._buffer))
            self._buffer = []

    def close(self) -> None:
        self._flush()
        self._writer.close()


class SplitShardWriter:
    """Writes one split's records into numbered shards of ``shard_size`` motions, in every asked format,
    and describes the finished shards (path, motions, bytes, sha256). With a build ``marker``, every folder and
    file is named in it before it is created (and a file already there that it does not name is refused)."""

    def __init__(self, root: Path, split: str, *, shard_size: int, formats: Sequence[str], schema: pa.Schema,
                 marker: BuildMarker | None = None) -> None:
        if shard_size < 1:
            raise ValueError(f"shard_size must be >= 1, got {shard_size}")
        self._root, self._split, self._shard_size = root, split, shard_size
        self._formats, self._schema = tuple(formats), schema
        self._marker = marker
        self._writers: dict[str, TarShardWriter | ParquetShardWriter] = {}
        self._in_shard = 0
        self._index = 0
        self.shards: dict[str, list[ShardInfo]] = {fmt: [] for fmt in self._formats}
        if marker is not None:
            marker.claim_folder(split)
        else:
            (root / split).mkdir(parents=True, exist_ok=True)

    def _shard_path(self, pattern: str) -> Path:
        name = pattern.format(self._index)
        if self._marker is not None:
            return self._marker.claim_file(f"{self._split}/{name}")
        return self._root / self._split / name

    def _open(self) -> None:
        if "tar" in self._formats:
            self._writers["tar"] = TarShardWriter(self._shard_path(TAR_PATTERN))
        if "parquet" in self._formats:
            self._writers["parquet"] = ParquetShardWriter(self._shard_path(PARQUET_PATTERN), self._schema)

    def _close_shard(self) -> None:
        for fmt, writer in self._writers.items():
            writer.close()
            self.shards[fmt].append(ShardInfo(
                path=writer.path.relative_to(self._root).as_posix(),
                num_motions=self._in_shard,
                bytes=writer.path.stat().st_size,
                sha256=sha256_file(writer.path),
            ))
        self._writers = {}
        self._in_shard = 0
        self._index += 1

    def write(self, record: Record, text: TextFeatures) -> None:
        if not self._writers:
            self._open()
        for writer in self._writers.values():
            writer.write(record, text)
        self._in_shard += 1
        if self._in_shard == self._shard_size:
            self._close_shard()

    def close(self) -> dict[str, list[ShardInfo]]:
        if self._writers:
            self._close_shard()
        return self.shards


# --- pass 1 spill and pass 2 embeddings -------------------------------------------------------------


@dataclass(frozen=True)
class SpilledRecord:
    """A record whose features wait in the spill file: ``header`` is the record minus its features."""

    header: Record
    row: int  # first feature row in the spill
    length: int


class FeatureSpill:
    """Append-only float32 file of feature rows (pass 1), memory-mapped for reading back (pass 2)."""

    def __init__(self, path: Path, dim: int) -> None:
        self.path, self.dim = path, dim
        self._file = open(path, "wb")
        self._rows = 0
        self._view: np.ndarray | None = None

    def add(self, record: Record) -> SpilledRecord:
        if record.features.shape[1:] != (self.dim,):
            raise ValueError(f"{record.path or record.id}: features have shape {record.features.shape}, "
                             f"expected (T, {self.dim})")
        self._file.write(np.ascontiguousarray(record.features, dtype="<f4").tobytes())
        spilled = SpilledRecord(replace(record, features=np.zeros((0, self.dim), np.float32)), self._rows, record.length)
        self._rows += record.length
        return spilled

    def finish(self) -> None:
        self._file.close()
        if self._rows:
            self._view = np.memmap(self.path, dtype="<f4", mode="r", shape=(self._rows, self.dim))

    def restore(self, spilled: SpilledRecord) -> Record:
        assert self._view is not None, "finish() the spill before reading it"
        features = np.array(self._view[spilled.row:spilled.row + spilled.length])
        return replace(spilled.header, features=features)

    def close(self) -> None:
        if not self._file.closed:
            self._file.close()
        self._view = None  # drops the mapping so the file can be removed


@dataclass
class CaptionEmbeddings:
    """Every distinct caption's text features; row ``index[text]``."""

    index: dict[str, int]
    pooled: np.ndarray  # (N, E)
    tokens: np.ndarray | None  # (N, L, E), a memmap when token features are stored
    token_lengths: np.ndarray | None  # (N,)

    def for_record(self, record: Record) -> TextFeatures:
        rows = np.array([self.index[c.text] for c in record.captions], dtype=np.int64)
        if self.tokens is None:
            return TextFeatures(pooled=self.pooled[rows])
        return TextFeatures(pooled=self.pooled[rows], tokens=np.asarray(self.tokens[rows]),
                            token_lengths=self.token_lengths[rows])


def encode_captions(
    encoder, texts: Iterable[str], *, token_features: bool, max_tokens: int, batch_size: int,
    work_dir: Path, progress: bool | None = None,
) -> CaptionEmbeddings:
    """Encode each distinct caption once, in sorted order (fixed batches: reproducible embeddings)."""
    ordered = sorted(set(texts))
    n, dim = len(ordered), int(encoder.dim)
    pooled = np.zeros((n, dim), np.float32)
    tokens = token_lengths = None
    if token_features:
        tokens = np.lib.format.open_memmap(work_dir / "text_tokens.npy", mode="w+", dtype="<f4",
                                           shape=(n, max_tokens, dim))
        token_lengths = np.zeros(n, np.int32)
    with tqdm(total=n, desc="text", unit="caption", disable=_tqdm_disable(progress)) as bar:
        for start in range(0, n, _TEXT_CHUNK):
            chunk = ordered[start:start + _TEXT_CHUNK]
            encoded = encoder.encode(chunk, token_features=token_features, max_tokens=max_tokens, batch_size=batch_size)
            if encoded.pooled.shape != (len(chunk), dim):
                raise ValueError(f"text encoder {encoder.id!r} returned pooled {encoded.pooled.shape}, "
                                 f"expected {(len(chunk), dim)}")
            pooled[start:start + len(chunk)] = encoded.pooled
            if token_features:
                if encoded.tokens is None or encoded.tokens.shape != (len(chunk), max_tokens, dim):
                    got = None if encoded.tokens is None else encoded.tokens.shape
                    raise ValueError(f"text encoder {encoder.id!r} returned tokens {got}, "
                                     f"expected {(len(chunk), max_tokens, dim)}")
                tokens[start:start + len(chunk)] = encoded.tokens
                token_lengths[start:start + len(chunk)] = encoded.token_lengths
            bar.update(len(chunk))
    return CaptionEmbeddings({text: i for i, text in enumerate(ordered)}, pooled, tokens, token_lengths)


# --- manifest ------------------------------------------------------------------------------------------


def feature_spec(skeleton: Skeleton, compat: bool) -> dict[str, Any]:
    layout = FeatureLayout(skeleton)
    return {
        "representation": "guo",
        "skeleton": skeleton.name,
        "dim": layout.dim,
        "num_joints": skeleton.num_joints,
        "fps": float(skeleton.fps),
        "unit": skeleton.unit,
        "compat": compat,
        "bone_lengths": skeleton.bone_lengths.tolist() if skeleton.bone_lengths is not None else None,
        "groups": {name: [s.start, s.stop] for name, s in layout.slices.items()},
    }


def derive_dataset_id(manifest: Mapping[str, Any]) -> str:
    """The dataset id of a manifest, derived from what it identifies; the builder writes it and every reader derives
    it again (:func:`dataset_id_problem`), so an edited manifest never passes under the id of the data it was built
    for.

    Format 2: sha256 of the canonical JSON (sorted keys, no spaces) of ``{"format_version": 2, "splits": ...}``, i.e.
    which files each split lists with their paths, sizes, sha256s and record counts, and each split's totals and clip
    lengths. Format 1 (kept for datasets built before): sha256 over the sorted sha256s of every listed file, joined by
    newlines; it does not cover which split lists a file, nor counts or lengths. Not covered by either: feature spec,
    normalisation and text encoder (checkpoints record and compare those themselves), and a manifest whose shards,
    hashes and id were all rewritten consistently (only comparing the id with an earlier result's shows that)."""
    version = manifest.get("format_version")
    splits = manifest.get("splits")
    if version == 1:
        listed = [entry for split in (splits.values() if isinstance(splits, Mapping) else ())
                  if isinstance(split, Mapping) for kind in ("shards", "parquet") for entry in split.get(kind) or ()]
        hashes = sorted(str(e.get("sha256")) if isinstance(e, Mapping) else json.dumps(e) for e in listed)
        return hashlib.sha256("\n".join(hashes).encode("utf-8")).hexdigest()
    covered = {"format_version": version, "splits": splits}
    text = json.dumps(covered, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(text.encode("ascii")).hexdigest()


def dataset_id_problem(manifest: Mapping[str, Any]) -> str | None:
    """Why the manifest's stored ``dataset_id`` cannot be trusted (it is not the one derived from its shard list:
    the manifest was edited after the build), or None when it matches."""
    stored = manifest.get("dataset_id")
    derived = derive_dataset_id(manifest)
    if stored == derived:
        return None
    shown = f"{stored[:16]}…" if isinstance(stored, str) and stored else repr(stored)
    return (f"dataset_id {shown} is not the id derived from its shard list ({derived[:16]}…): the manifest was "
            "edited after it was built")


def shard_path_problem(path: Any) -> str | None:
    """Why a manifest's shard path does not name a file under the manifest's own folder ("is absolute", "is a URL",
    "leaves the manifest's folder ('..')", "is not a relative path"), or None for a plain relative path. Both
    separators count: a server or filesystem may take a backslash for one."""
    if not isinstance(path, str) or not path:
        return "is not a relative path"
    if path.startswith(("/", "\\")) or os.path.isabs(path) or re.match(r"^[A-Za-z]:", path):
        return "is absolute"
    if re.match(r"^[A-Za-z][A-Za-z0-9+.-]+:", path):
        return "is a URL"
    if ".." in re.split(r"[/\\]", path):
        return "leaves the manifest's folder ('..')"
    return None


def manifest_json(manifest: Mapping[str, Any]) -> str:
    """Indented JSON with lists of numbers and strings kept on one line (lengths and Mean/Std lists stay
    readable), keys in insertion order; the same dict always gives the same text."""

    def dump(value: Any, indent: int) -> str:
        pad, inner = " " * indent, " " * (indent + 2)
        if isinstance(value, Mapping):
            if not value:
                return "{}"
            items = [f"{inner}{json.dumps(str(k))}: {dump(v, indent + 2)}" for k, v in value.items()]
            return "{\n" + ",\n".join(items) + "\n" + pad + "}"
        if isinstance(value, (list, tuple)):
            if all(not isinstance(v, (Mapping, list, tuple)) for v in value):
                return "[" + ", ".join(json.dumps(v, ensure_ascii=False) for v in value) + "]"
            return "[\n" + ",\n".join(inner + dump(v, indent + 2) for v in value) + "\n" + pad + "]"
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"manifest value {value} is not finite")
        return json.dumps(value, ensure_ascii=False)

    return dump(manifest, 0) + "\n"


def write_manifest(out: Path, manifest: Mapping[str, Any]) -> Path:
    """Write ``manifest.json`` atomically (temp file, fsync, ``os.replace``)."""
    path = out / MANIFEST_NAME
    tmp = out / (MANIFEST_NAME + ".tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(manifest_json(manifest))
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    return path


_REQUIRED_KEYS = ("format_version", "dataset_id", "builder", "feature_spec", "normalization", "text_encoder",
                  "action_classes", "splits", "skip_report")


def load_manifest(path: str | Path, *, verify: str = "size") -> dict[str, Any]:
    """Read and check a dataset's manifest. ``path``: the dataset folder or its ``manifest.json``.

    ``verify``: ``"none"``, ``"size"`` (the stored ``dataset_id`` is the one derived from the shard list, and every
    listed file is a relative path under the dataset folder and exists with its recorded size; the default, a stat per
    file) or ``"sha256"`` (also re-hash every file). Raises :class:`ManifestError` naming the file and the problem.
    """
    path = Path(path)
    file = path / MANIFEST_NAME if path.is_dir() else path
    if not file.is_file():
        raise ManifestError(f"{file}: no manifest (the dataset is missing, or its build did not finish)")
    try:
        manifest = json.loads(file.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ManifestError(f"{file}: unreadable manifest: {error}") from None
    if not isinstance(manifest, dict):
        raise ManifestError(f"{file}: a manifest must be a JSON object")
    version = manifest.get("format_version")
    if version not in READABLE_FORMAT_VERSIONS:
        raise ManifestError(f"{file}: format_version {version!r}, this code reads versions "
                            f"{', '.join(map(str, READABLE_FORMAT_VERSIONS))}; "
                            "rebuild the dataset with this version of preprocess/build_shards.py")
    missing = [k for k in _REQUIRED_KEYS if k not in manifest]
    if missing:
        raise ManifestError(f"{file}: missing keys {missing}")
    dim = manifest["feature_spec"].get("dim")
    for key in ("mean", "std"):
        if len(manifest["normalization"].get(key, ())) != dim:
            raise ManifestError(f"{file}: normalization.{key} must have feature_spec.dim = {dim} values")
    if verify not in ("none", "size", "sha256"):
        raise ValueError(f"verify must be 'none', 'size' or 'sha256', got {verify!r}")
    if verify != "none":
        problem = dataset_id_problem(manifest)
        if problem:
            raise ManifestError(f"{file}: {problem}; rebuild the dataset")
        verify_shards(manifest, file.parent, check_sha256=verify == "sha256")
    return manifest


def manifest_files(manifest: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Every data file entry (tar and Parquet) of every split."""
    return [entry for split in manifest["splits"].values() for kind in ("shards", "parquet")
            for entry in split.get(kind, [])]


def verify_shards(manifest: Mapping[str, Any], root: str | Path, *, check_sha256: bool = True) -> None:
    """Check that every file the manifest lists exists with its size (and sha256): ManifestError naming
    the first bad file otherwise."""
    root = Path(root)
    for entry in manifest_files(manifest):
        problem = shard_path_problem(entry.get("path"))
        if problem:
            raise ManifestError(f"{root / MANIFEST_NAME}: shard path {entry.get('path')!r} {problem}; a manifest lists "
                                "files under its own folder")
        file = root / entry["path"]
        if not file.is_file():
            raise ManifestError(f"{file}: listed in the manifest but missing")
        size = file.stat().st_size
        if size != entry["bytes"]:
            raise ManifestError(f"{file}: {size} bytes, the manifest says {entry['bytes']} (truncated or replaced?)")
        if check_sha256 and sha256_file(file) != entry["sha256"]:
            raise ManifestError(f"{file}: sha256 does not match the manifest (corrupted?)")


# --- the build -----------------------------------------------------------------------------------------


def default_out_dir(source: str, text_encoder: str) -> Path:
    """Where a build goes without ``--out``: ``data/<source>-<text encoder>`` under the current folder."""
    return Path("data") / f"{source}-{text_encoder}"


@dataclass(frozen=True)
class BuildConfig:
    """Everything a build needs. ``out``, ``workers``, ``overwrite``, ``strict`` and ``progress`` do not
    change the dataset's bytes, so the manifest records only :meth:`content_options`."""

    out: Path
    source: str = "deepmimic"
    root: str | None = None
    source_options: Mapping[str, Any] = field(default_factory=dict)
    text_encoder: str = "minilm"
    text_weights: str | None = None
    text_options: Mapping[str, Any] = field(default_factory=dict)
    token_features: bool = False
    max_tokens: int = 32
    text_batch_size: int = 64
    shard_size: int | None = None  # None: the source's default_shard_size if it has one, else DEFAULT_SHARD_SIZE
    formats: tuple[str, ...] = SHARD_FORMATS
    min_frames: int | None = None  # None: the skeleton's HumanML3D default (40, KIT 24)
    max_frames: int | None = DEFAULT_MAX_FRAMES
    long_clips: str = "skip"
    compat: bool = True
    # Mean/Std: "official" = the dataset's own files (source.normalization_files(), HumanML3D's Mean.npy/Std.npy),
    # "recompute" = over the train split's frames, "auto" = official when the files are there.
    normalization: str = "auto"
    workers: int = 1
    strict: bool = False
    overwrite: bool = False
    progress: bool | None = None  # None: a progress bar when stderr is a terminal

    def __post_init__(self) -> None:
        unknown = [f for f in self.formats if f not in SHARD_FORMATS]
        if unknown or not self.formats:
            raise ValueError(f"formats must be a non-empty subset of {SHARD_FORMATS}, got {self.formats}")
        if self.shard_size is not None and self.shard_size < 1:
            raise ValueError(f"shard_size must be >= 1, got {self.shard_size}")
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {self.workers}")
        if self.token_features and self.max_tokens < 1:
            raise ValueError(f"max_tokens must be >= 1, got {self.max_tokens}")
        if self.normalization not in NORMALIZATION_MODES:
            raise ValueError(f"normalization must be one of {NORMALIZATION_MODES}, got {self.normalization!r}")
        self.processing_settings()  # validates the length options

    def processing_settings(self) -> ProcessingSettings:
        min_frames = DEFAULT_MIN_FRAMES if self.min_frames is None else self.min_frames
        return ProcessingSettings(min_frames=min_frames, max_frames=self.max_frames, compat=self.compat,
                                  long_clips=self.long_clips)

    def content_options(self) -> dict[str, Any]:
        """The options that decide the dataset's content, as given (paths as the user passed them)."""
        return {
            "source": self.source,
            "root": self.root,
            "source_options": dict(sorted(self.source_options.items())),
            "text_encoder": self.text_encoder,
            "text_weights": self.text_weights,
            "text_options": dict(sorted(self.text_options.items())),
            "token_features": self.token_features,
            "max_tokens": self.max_tokens if self.token_features else 0,
            "text_batch_size": self.text_batch_size,
            "shard_size": self.shard_size,
            "formats": list(self.formats),
            "min_frames": self.min_frames,
            "max_frames": self.max_frames,
            "long_clips": self.long_clips,
            "compat": self.compat,
            "normalization": self.normalization,
        }

    def command(self) -> list[str]:
        """A normalised ``build_shards`` argument list that rebuilds this dataset (add ``--out``)."""
        args = ["--source", self.source]
        if self.root is not None:
            args += ["--root", self.root]
        for key, value in sorted(self.source_options.items()):
            args += ["--source-option", f"{key}={_option_text(value)}"]
        args += ["--text-encoder", self.text_encoder]
        if self.text_weights is not None:
            args += ["--text-weights", self.text_weights]
        for key, value in sorted(self.text_options.items()):
            args += ["--text-option", f"{key}={_option_text(value)}"]
        if self.token_features:
            args += ["--token-features", "--max-tokens", str(self.max_tokens)]
        args += ["--shard-size", str(self.shard_size), "--format", ",".join(self.formats),
                 "--min-frames", str(self.min_frames),
                 "--max-frames", "none" if self.max_frames is None else str(self.max_frames),
                 "--long-clips", self.long_clips, "--compat" if self.compat else "--no-compat",
                 "--normalization", self.normalization]
        return args


def _option_text(value: Any) -> str:
    return json.dumps(value) if isinstance(value, bool) or value is None else str(value)


def _tqdm_disable(progress: bool | None) -> bool | None:
    return None if progress is None else not progress


# --- the output folder ---------------------------------------------------------------------------------


def is_build_path(relative: str) -> bool:
    """Whether ``relative`` ("/"-separated, inside an output folder) is a path a build of ours writes: its work
    folder, the manifest's temporary file, a split folder or a shard in one. Only such paths are ever deleted,
    whatever a marker or a manifest lists."""
    parts = relative.split("/")
    if len(parts) == 1:
        return relative in (_TMP_DIR_NAME, MANIFEST_NAME + ".tmp") or is_valid_key(relative)
    return len(parts) == 2 and is_valid_key(parts[0]) and any(p.match(parts[1]) for p in _SHARD_FILE_PATTERNS)


class BuildMarker:
    """``build-in-progress.json``: the paths (relative, "/"-separated) a build of ours created, or is about to
    create, in its output folder. Saved (temp file + ``os.replace``) before each new path is created, so whatever
    the build leaves behind, an interruption included, is named; removed once the manifest is in place."""

    def __init__(self, out: Path, paths: Iterable[str] = ()) -> None:
        self.out = Path(out)
        self.paths: list[str] = list(dict.fromkeys(paths))

    @property
    def file(self) -> Path:
        return self.out / BUILD_MARKER_NAME

    @classmethod
    def read(cls, out: Path) -> BuildMarker | None:
        """The marker of ``out``; None when there is none. A file of that name that is not one of our markers (or
        names a path no build of ours writes) is an OutputFolderError: nothing of that folder is deleted."""
        file = Path(out) / BUILD_MARKER_NAME
        if not file.exists():
            return None
        try:
            data = json.loads(file.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            data = None
        paths = data.get("paths") if isinstance(data, dict) and data.get("format") == BUILD_MARKER_FORMAT else None
        if not (isinstance(paths, list) and all(isinstance(p, str) and is_build_path(p) for p in paths)):
            raise OutputFolderError(f"--out {out}: {BUILD_MARKER_NAME} is not a build marker of this project (or names "
                                    "files a build does not write), so nothing in the folder is touched: pass a new "
                                    "or empty folder")
        return cls(out, paths)

    def save(self) -> None:
        tmp = self.out / (BUILD_MARKER_NAME + ".tmp")
        payload = {"format": BUILD_MARKER_FORMAT, "version": FORMAT_VERSION, "paths": self.paths}
        with open(tmp, "w", encoding="utf-8") as handle:
            handle.write(json.dumps(payload, indent=1) + "\n")
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, self.file)

    def claim_file(self, relative: str) -> Path:
        """Name the file ``relative`` (saved before the caller creates it) and return its path. A file already
        there that the marker does not name is not ours: OutputFolderError, never overwritten."""
        target = self.out / relative
        if relative not in self.paths:
            if target.exists() or target.is_symlink():
                raise OutputFolderError(f"{target}: a file this build would write is already there and no build of "
                                        "ours wrote it; move it away or pass another --out")
            self.paths.append(relative)
            self.save()
        return target

    def claim_folder(self, relative: str) -> Path:
        """Create the folder ``relative`` if needed; named only when this build creates it (an existing folder is
        written into, never removed)."""
        target = self.out / relative
        if not target.is_dir():
            if relative not in self.paths:
                self.paths.append(relative)
                self.save()
            target.mkdir(parents=True)
        return target

    def remove(self) -> None:
        self.file.unlink(missing_ok=True)


def _manifest_paths(out: Path) -> list[str] | None:
    """The data files the manifest of ``out`` lists; None without a manifest. A manifest.json that is not ours
    (not a dataset manifest, or listing paths a build does not write) is an OutputFolderError."""
    file = out / MANIFEST_NAME
    if not file.exists():
        return None
    try:
        manifest = json.loads(file.read_text(encoding="utf-8"))
        paths = [entry["path"] for entry in manifest_files(manifest)]
        ours = isinstance(manifest.get("dataset_id"), str)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError, KeyError, TypeError):
        paths, ours = [], False
    if not (ours and all(isinstance(p, str) and "/" in p and is_build_path(p) for p in paths)):
        raise OutputFolderError(f"--out {out}: its {MANIFEST_NAME} is not a dataset manifest of this project, so "
                                "nothing in the folder is touched: pass a new or empty folder")
    return paths


def check_output_dir(out: Path, *, overwrite: bool) -> tuple[str, ...]:
    """Refuse an output folder a build must not write into, before anything is touched; else return the paths of
    an earlier build of ours there (its manifest's files with ``overwrite``, its marker's after an interruption),
    which the new build replaces.

    Refused: a file; a complete dataset without ``overwrite`` (DatasetExistsError); a non-empty folder that is no
    build of ours (neither our manifest nor our marker); and a folder holding a shard-named file, the work folder or
    the manifest's temporary file that neither names (the build could overwrite it): OutputFolderError, naming the
    folder and what is there."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputFolderError(f"--out {out} is a file, not a folder: pass a new or empty folder")
    if not out.is_dir():
        return ()
    entries = sorted(entry.name for entry in out.iterdir())
    if not entries:
        return ()
    marker = BuildMarker.read(out)
    listed = _manifest_paths(out)
    if listed is not None and not overwrite:
        raise DatasetExistsError(f"{out} already holds a complete dataset ({MANIFEST_NAME}); "
                                 "pass --overwrite to replace it")
    if marker is None and listed is None:
        raise OutputFolderError(
            f"--out {out} is a non-empty folder that is not a dataset built here (no {MANIFEST_NAME} or "
            f"{BUILD_MARKER_NAME} of ours; it holds {_first_few(entries)}): the build would mix its files with these or overwrite "
            f"them. Pass a new or empty folder, e.g. {out / 'dataset'}")
    named = list(dict.fromkeys([*(marker.paths if marker else []), *(listed or [])]))
    unnamed = [name for name in (_TMP_DIR_NAME, MANIFEST_NAME + ".tmp")
               if (out / name).exists() and name not in named]
    for folder in sorted(p for p in out.iterdir() if p.is_dir() and not p.is_symlink() and is_valid_key(p.name)):
        shard_named = [f"{folder.name}/{file.name}" for file in sorted(folder.iterdir())
                       if any(p.match(file.name) for p in _SHARD_FILE_PATTERNS)]
        unnamed += [path for path in shard_named if path not in named]
    if unnamed:
        raise OutputFolderError(
            f"--out {out} holds {_first_few(unnamed)}, which the build could overwrite and no build of ours wrote (neither its "
            f"{MANIFEST_NAME} nor its {BUILD_MARKER_NAME} names them): move them away or pass another --out")
    return tuple(named)


def _first_few(names: Sequence[str]) -> str:
    """``a, b, c, d, e and 3 more``: what a refusal says a folder holds."""
    more = len(names) - _SHOWN_ENTRIES
    return ", ".join(names[:_SHOWN_ENTRIES]) + (f" and {more} more" if more > 0 else "")


def prepare_output_dir(out: Path, *, overwrite: bool) -> BuildMarker:
    """Check ``out`` (:func:`check_output_dir`), put this build's marker in it, still naming the earlier build's
    paths so that an interruption here leaves them named, then remove the earlier manifest first (the folder stops
    counting as complete), then exactly the files and work folder that build wrote, and the folders it left empty.
    Nothing else in the folder is touched. Returns the marker, which names what the build writes from here on."""
    out = Path(out)
    earlier = check_output_dir(out, overwrite=overwrite)
    out.mkdir(parents=True, exist_ok=True)
    fresh = [_TMP_DIR_NAME, MANIFEST_NAME + ".tmp"]
    marker = BuildMarker(out, [*earlier, *fresh])
    marker.save()
    if earlier:
        (out / MANIFEST_NAME).unlink(missing_ok=True)  # ours: check_output_dir refuses any other
    for relative in earlier:
        if "/" in relative:  # a shard
            (out / relative).unlink(missing_ok=True)
    (out / (MANIFEST_NAME + ".tmp")).unlink(missing_ok=True)  # named by this marker (and refused unless ours)
    work_dir = out / _TMP_DIR_NAME
    if work_dir.is_symlink():
        work_dir.unlink()
    elif work_dir.exists():
        shutil.rmtree(work_dir)  # named by this marker (and refused unless ours)
    split_folders = dict.fromkeys(r.split("/")[0] for r in earlier if "/" in r or is_valid_key(r))
    for folder in split_folders:  # removed only when the earlier build's files were all that was in them
        path = out / folder
        if path.is_dir() and not path.is_symlink() and not any(path.iterdir()):
            path.rmdir()
    marker.paths = fresh
    marker.save()
    return marker


def resolve_skeleton(source) -> Skeleton:
    """The skeleton clips are retargeted to: ``source.target_skeleton()`` where the source offers one (KIT
    measures its bone lengths on a reference clip), else the preset the source's skeleton name picks."""
    if hasattr(source, "target_skeleton"):
        return source.target_skeleton()
    return source.skeleton if isinstance(source.skeleton, Skeleton) else get_skeleton(source.skeleton)


def _split_order(splits: Iterable[str]) -> list[str]:
    names = set(splits)
    return [s for s in SPLIT_ORDER if s in names] + sorted(names - set(SPLIT_ORDER))


def _report_path(path: str, root: str | None) -> str:
    """Skip-report paths relative to the source root, so the manifest does not depend on where it lives."""
    if not path or root is None:
        return path
    try:
        return Path(path).resolve().relative_to(Path(root).resolve()).as_posix()
    except ValueError:
        return path


@dataclass
class _FirstPass:
    spilled: dict[str, list[SpilledRecord]] = field(default_factory=dict)
    skipped: list[SkippedInput] = field(default_factory=list)
    dropped_captions: Counter = field(default_factory=Counter)
    ignored_files: list[str] = field(default_factory=list)  # what the source's folder holds but it never reads
    captions: set[str] = field(default_factory=set)
    actions: set[str] = field(default_factory=set)
    train_stats: FeatureStats = field(default_factory=FeatureStats)


def _first_pass(source, items: list[str], skeleton: Skeleton, config: BuildConfig, spill: FeatureSpill) -> _FirstPass:
    state = _FirstPass()
    seen: dict[str, str] = {}
    results = process_source(source, items, skeleton, config.processing_settings(), workers=config.workers)
    try:
        for result in tqdm(results, total=len(items), desc="features", unit="clip",
                           disable=_tqdm_disable(config.progress)):
            if isinstance(result, SkippedInput):
                if config.strict:
                    raise BadInputError(result)
                state.skipped.append(result)
                continue
            for record in result:
                _add_record(state, record, spill, seen, strict=config.strict, root=config.root)
    finally:
        results.close()  # stops the worker pool at once on an error
    return state


def _add_record(state: _FirstPass, record: Record, spill: FeatureSpill, seen: dict[str, str], *, strict: bool,
                root: str | None) -> None:
    where = record.path or record.id
    if not is_valid_key(record.id) or not is_valid_key(record.split):
        raise ValueError(f"{where}: id {record.id!r} / split {record.split!r} may only use [A-Za-z0-9_-]")
    if record.id in seen:  # two inputs claim one id: the first keeps it, the second is bad input
        first = _report_path(seen[record.id], root)
        skipped = SkippedInput(record.id, record.path, "duplicate_id", f"motion id {record.id!r} is taken by {first}")
        if strict:
            raise BadInputError(skipped)
        state.skipped.append(skipped)
        return
    seen[record.id] = where
    state.dropped_captions.update(record.dropped_captions)
    state.captions.update(c.text for c in record.captions)
    if record.action is not None:
        state.actions.add(record.action)
    if record.split == "train":
        state.train_stats.update(record.features)
    state.spilled.setdefault(record.split, []).append(spill.add(record))


def _skip_report(first: _FirstPass, root: str | None) -> dict[str, Any]:
    by_reason = Counter(s.reason for s in first.skipped)
    return {
        "total": len(first.skipped),
        "by_reason": dict(sorted(by_reason.items())),
        "items": [{"id": s.id, "path": _report_path(s.path, root), "reason": s.reason, "detail": s.detail}
                  for s in first.skipped],
        "dropped_captions": dict(sorted(first.dropped_captions.items())),
        "ignored_files": {"count": len(first.ignored_files),
                          "paths": [_report_path(p, root) for p in first.ignored_files]},
    }


def _builder_version() -> str:
    try:
        return metadata.version("motion-flow-matching")
    except metadata.PackageNotFoundError:
        return "unknown"


def read_statistics_file(path: Path, dim: int, what: str) -> np.ndarray:
    """A Mean or Std file: a ``.npy`` array of ``dim`` finite real numbers, as float32; a Std's must be
    positive. ValueError naming the file otherwise."""
    try:
        array = np.load(path, allow_pickle=False)
    except Exception as err:  # not a .npy, pickled, truncated...
        raise ValueError(f"{path}: cannot be read as a .npy array of the {what} ({type(err).__name__}: {err})") from None
    if not np.issubdtype(array.dtype, np.number) or np.issubdtype(array.dtype, np.complexfloating):
        raise ValueError(f"{path}: the {what} must be real numbers, got dtype {array.dtype}")
    if array.shape != (dim,):
        raise ValueError(f"{path}: the {what} must have shape ({dim},) (the feature dim), got {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{path}: the {what} holds NaN/inf")
    if what == "std" and not (array > 0).all():
        bad = np.flatnonzero(~(array > 0))
        raise ValueError(f"{path}: standard deviations must be positive; {bad.size} are not (first: dim {bad[0]} = "
                         f"{array[bad[0]]})")
    return array.astype(np.float32)


def official_normalization(source, skeleton: Skeleton, mode: str, *, root: str | None = None) -> dict[str, Any] | None:
    """The manifest's ``normalization`` from the dataset's own Mean/Std files (``source.normalization_files()``,
    HumanML3D's ``Mean.npy``/``Std.npy`` at its root), or None when the statistics are to be recomputed from the
    train split: ``mode`` "recompute", or "auto" without the files. "official" without them, a half-present
    pair (auto), or a file of the wrong shape, not finite, or with a Std <= 0 is a ValueError naming the file."""
    if mode not in NORMALIZATION_MODES:
        raise ValueError(f"normalization must be one of {NORMALIZATION_MODES}, got {mode!r}")
    if mode == "recompute":
        return None
    files = source.normalization_files() if hasattr(source, "normalization_files") else None
    if files is None:
        if mode == "official":
            raise ValueError(f"--normalization official: source {getattr(source, 'name', source)!r} has no official "
                             "normalisation files")
        return None
    paths = {"mean": Path(files[0]), "std": Path(files[1])}
    present = {name: path.is_file() for name, path in paths.items()}
    if not any(present.values()) and mode == "auto":
        return None
    missing = [str(path) for name, path in paths.items() if not present[name]]
    if missing:
        there = [str(path) for name, path in paths.items() if present[name]]
        raise ValueError(("--normalization official: " if mode == "official" else "")
                         + f"{missing[0]}: no such file; " + (f"{there[0]} is there, but " if there else "")
                         + "the official normalisation needs both Mean and Std "
                         "(--normalization recompute computes them over the train split)")
    values = {name: read_statistics_file(path, skeleton.feature_dim, name) for name, path in paths.items()}
    log.info("normalisation: the official statistics %s, %s", paths["mean"], paths["std"])
    return {
        "mean": values["mean"].tolist(),
        "std": values["std"].tolist(),
        "split": None,
        "num_frames": None,
        "rule": "the dataset's official statistics, used as they are",
        "source": "official",
        "files": {name: {"path": _report_path(str(path), root), "sha256": sha256_file(path)}
                  for name, path in paths.items()},
    }


def build_dataset(config: BuildConfig, *, source=None, text_encoder=None) -> dict[str, Any]:
    """Build the dataset ``config`` describes and return its manifest.

    ``source``/``text_encoder`` may be passed already built (tests, notebooks); otherwise they are built
    from the config. The text encoder is built before the long first pass, so missing weights fail fast.
    """
    out = Path(config.out)
    check_output_dir(out, overwrite=config.overwrite)  # before the slow setup: fail fast, touching nothing
    if source is None:
        from preprocess.sources import build_source

        source = build_source(config.source, config.root, **config.source_options)
    if text_encoder is None:
        from mfm.text import build_text_encoder

        text_encoder = build_text_encoder(config.text_encoder, weights=config.text_weights, **config.text_options)
    if text_encoder.id != config.text_encoder:
        raise ValueError(f"text encoder {text_encoder.id!r} given, but the config names {config.text_encoder!r}")
    skeleton = resolve_skeleton(source)
    if not config.compat and getattr(source, "reads_feature_files", False):
        raise ValueError(f"--no-compat asks for features computed with the fixed IK, but source {config.source!r} "
                         "reads the dataset's feature files (made with the reference's quirks): pass "
                         "--source-option features=recompute")
    official = official_normalization(source, skeleton, config.normalization, root=config.root)  # fails fast
    if config.min_frames is None:
        # A source may know its clips need another floor (DeepMimic's kick); else the skeleton's HumanML3D rule.
        config = replace(config, min_frames=getattr(source, "default_min_frames", default_min_frames(skeleton.name)))
    if config.shard_size is None:
        # A tiny source (DeepMimic: 15 train motions) needs small shards to feed several ranks x workers.
        config = replace(config, shard_size=getattr(source, "default_shard_size", DEFAULT_SHARD_SIZE))
    items = list(source.list_items())
    if config.strict and hasattr(source, "caption_problems"):  # entries of a caption file read up front (AMASS)
        problems = list(source.caption_problems())
        if problems:
            raise BadInputError(problems[0])
    ignored = list(source.ignored_files()) if hasattr(source, "ignored_files") else []
    if ignored:
        log.warning("%s: %d files not read (not of the layout's file-name pattern; listed in the skip report), "
                    "e.g. %s", config.source, len(ignored), ignored[0])
    marker = prepare_output_dir(out, overwrite=config.overwrite)
    work_dir = out / _TMP_DIR_NAME
    work_dir.mkdir()
    spill = FeatureSpill(work_dir / "features.f32", skeleton.feature_dim)
    try:
        with _timed("features", len(items), "clips"):
            first = _first_pass(source, items, skeleton, config, spill)
            first.ignored_files = ignored
            spill.finish()
        if official is None and first.train_stats.count == 0:
            raise ValueError(f"no motion of source {config.source!r} reached the train split "
                             f"({len(first.skipped)} of {len(items)} items skipped): no normalisation statistics")
        with _timed("text", len(first.captions), "captions"):
            embeddings = encode_captions(text_encoder, first.captions, token_features=config.token_features,
                                         max_tokens=config.max_tokens, batch_size=config.text_batch_size,
                                         work_dir=work_dir, progress=config.progress)
        with _timed("shards", sum(len(v) for v in first.spilled.values()), "motions"):
            schema = parquet_schema(skeleton.feature_dim, int(text_encoder.dim), config.token_features)
            splits = _write_splits(out, first, spill, embeddings, schema, config, marker)
        manifest = _assemble_manifest(config, skeleton, text_encoder, first, embeddings, splits, official)
    finally:
        spill.close()
        shutil.rmtree(work_dir, ignore_errors=True)
    write_manifest(out, manifest)
    marker.remove()  # the manifest marks the complete dataset from here on
    log.info("built %s: %d motions, %d skipped", out, sum(s["num_motions"] for s in splits.values()),
             manifest["skip_report"]["total"])
    return manifest


@contextmanager
def _timed(stage: str, count: int, unit: str) -> Iterator[None]:
    start = time.perf_counter()
    yield
    seconds = time.perf_counter() - start
    log.info("%s: %d %s in %.1f s (%.1f %s/s)", stage, count, unit, seconds, count / max(seconds, 1e-9), unit)


def _write_splits(out: Path, first: _FirstPass, spill: FeatureSpill, embeddings: CaptionEmbeddings,
                  schema: pa.Schema, config: BuildConfig, marker: BuildMarker | None = None) -> dict[str, Any]:
    """Pass 2: stream each split's records from the spill into its shards; the manifest's split entries."""
    splits: dict[str, Any] = {}
    total = sum(len(v) for v in first.spilled.values())
    with tqdm(total=total, desc="shards", unit="motion", disable=_tqdm_disable(config.progress)) as bar:
        for split in _split_order(first.spilled):
            records = first.spilled[split]
            writer = SplitShardWriter(out, split, shard_size=config.shard_size, formats=config.formats, schema=schema,
                                      marker=marker)
            for spilled in records:
                record = spill.restore(spilled)
                writer.write(record, embeddings.for_record(record))
                bar.update()
            shards = writer.close()
            splits[split] = {
                "num_motions": len(records),
                "num_captions": sum(len(r.header.captions) for r in records),
                "num_frames": sum(r.length for r in records),
                "lengths": [r.length for r in records],
                "shards": [s.to_json() for s in shards.get("tar", [])],
                "parquet": [s.to_json() for s in shards.get("parquet", [])],
            }
    return splits


def _assemble_manifest(config: BuildConfig, skeleton: Skeleton, text_encoder, first: _FirstPass,
                       embeddings: CaptionEmbeddings, splits: dict[str, Any],
                       official: dict[str, Any] | None = None) -> dict[str, Any]:
    if official is not None:
        normalization = official
    else:
        mean, std = first.train_stats.mean_std(FeatureLayout(skeleton))
        normalization = {"mean": mean.tolist(), "std": std.tolist(), "split": "train",
                         "num_frames": first.train_stats.count, "rule": RECOMPUTED_RULE, "source": "recomputed"}
    manifest = {
        "format_version": FORMAT_VERSION,
        "dataset_id": "",  # derived below, from the splits (its place in the file stays second)
        "builder": {
            "command": "python -m preprocess.build_shards " + shlex.join(config.command()),
            "version": _builder_version(),
            "options": config.content_options(),
        },
        "feature_spec": feature_spec(skeleton, config.compat),
        "normalization": normalization,
        "text_encoder": {"id": text_encoder.id, "dim": int(text_encoder.dim),
                         "weights_sha256": text_encoder.weights_sha256,
                         "options": dict(getattr(text_encoder, "options", {})),
                         "token_features": config.token_features,
                         "max_tokens": config.max_tokens if config.token_features else 0,
                         "num_distinct_captions": len(embeddings.index)},
        "action_classes": sorted(first.actions),
        "splits": splits,
        "skip_report": _skip_report(first, config.root),
    }
    manifest["dataset_id"] = derive_dataset_id(manifest)
    return manifest
