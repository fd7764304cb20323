"""The clip → record stage: validate a source clip, resample it, extract features, map its captions to
feature frames, and run that over a whole source in worker processes.

A :class:`Record` is one motion as it goes into a shard. Everything here is deterministic: the same clip
gives the same record bytes whatever the worker count, and :func:`process_source` yields results in the
source's ``list_items`` order.
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import re
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from mfm.features import joints_to_features, resample_joints
from mfm.skeleton import Skeleton
from preprocess.clip import Caption, Clip, SkippedInput, check_joints

log = logging.getLogger(__name__)

# HumanML3D keeps a motion when 40 <= len(features) < 200 (KIT: 24 <= len < 200). Keeping 197-199 frames
# (the training window is 196) keeps the published test set intact; the loader crops to its window.
DEFAULT_MIN_FRAMES = 40
DEFAULT_MAX_FRAMES = 199
# HumanML3D's dataset code: ``min_motion_len = 40 if dataset_name == 't2m' else 24`` (about 2 s either way).
MIN_FRAMES_BY_SKELETON = {"humanml3d": 40, "kit": 24}
LONG_CLIP_POLICIES = ("skip", "window")
_KEY_PATTERN = re.compile(r"^[A-Za-z0-9_-]+$")


@dataclass(frozen=True)
class RecordCaption:
    """A caption mapped to feature frames: ``[start_frame, end_frame)`` inside ``[0, length]``."""

    text: str
    tokens: tuple[str, ...]
    start_frame: int
    end_frame: int


@dataclass
class Record:
    """One motion with all of its captions, as written to a shard (features not normalised)."""

    id: str
    split: str
    source: str
    skeleton: str
    fps: float
    features: np.ndarray  # float32 (T, D), T = joint frames - 1
    captions: list[RecordCaption]
    action: str | None = None
    path: str = ""
    # Captions this record lost on the way, by reason ("empty", "span_too_short", "bad_span", and the
    # source's own, e.g. "span_not_a_number" for a caption line it could not read): counted in the skip
    # report, never silently.
    dropped_captions: dict[str, int] = field(default_factory=dict)

    @property
    def length(self) -> int:
        return int(self.features.shape[0])


@dataclass(frozen=True)
class ProcessingSettings:
    """What :func:`process_clip` needs besides the clip; picklable, so it travels to worker processes."""

    min_frames: int = DEFAULT_MIN_FRAMES
    max_frames: int | None = DEFAULT_MAX_FRAMES  # inclusive; None keeps every length
    compat: bool = True
    long_clips: str = "skip"  # "skip": HumanML3D's filter; "window": cut into max_frames windows

    def __post_init__(self) -> None:
        if self.min_frames < 1:
            raise ValueError(f"min_frames must be >= 1, got {self.min_frames}")
        if self.max_frames is not None and self.max_frames < self.min_frames:
            raise ValueError(f"max_frames ({self.max_frames}) must be >= min_frames ({self.min_frames})")
        if self.long_clips not in LONG_CLIP_POLICIES:
            raise ValueError(f"long_clips must be one of {LONG_CLIP_POLICIES}, got {self.long_clips!r}")
        if self.long_clips == "window" and self.max_frames is None:
            raise ValueError("long_clips='window' needs max_frames (the window length)")


def default_min_frames(skeleton_name: str) -> int:
    return MIN_FRAMES_BY_SKELETON.get(skeleton_name, DEFAULT_MIN_FRAMES)


def is_valid_key(key: str) -> bool:
    """webdataset splits member names at the first dot, so a record id may only use ``[A-Za-z0-9_-]``."""
    return bool(_KEY_PATTERN.match(key))


def process_clip(
    clip: Clip,
    skeleton: Skeleton,
    *,
    min_frames: int = DEFAULT_MIN_FRAMES,
    max_frames: int | None = DEFAULT_MAX_FRAMES,
    compat: bool = True,
    long_clips: str = "skip",
) -> Record | SkippedInput:
    """Turn one clip into a record, or say why it cannot be one.

    Checks run cheapest first (shape, finiteness, length, captions) so that a rejected clip costs no
    feature extraction. Lengths are counted in feature frames at ``skeleton.fps``. With
    ``long_clips="window"`` a clip longer than ``max_frames`` is returned whole; cut it with
    :func:`split_into_windows`.
    """

    def skip(reason: str, detail: str) -> SkippedInput:
        return SkippedInput(id=clip.id, path=clip.path, reason=reason, detail=detail)

    if clip.skeleton != skeleton.name:
        raise ValueError(f"clip {clip.id!r} is for skeleton {clip.skeleton!r}, processing expects {skeleton.name!r}")
    joints = np.asarray(clip.joints)
    problem = check_joints(joints, skeleton.num_joints)
    if problem is not None:
        reason, detail = problem
        return skip(reason, f"{detail} ({skeleton.name} skeleton)")
    if not (math.isfinite(clip.fps) and clip.fps > 0):
        return skip("bad_fps", f"frame rate {clip.fps!r} is not a positive number")

    if not math.isclose(clip.fps, skeleton.fps, rel_tol=1e-9):
        joints = resample_joints(joints, clip.fps, skeleton.fps)
    length = len(joints) - 1  # features are per frame transition
    if length < min_frames:
        return skip("too_short", f"{length} feature frames at {skeleton.fps:g} fps < min_frames {min_frames}")
    if max_frames is not None and length > max_frames and long_clips == "skip":
        return skip("too_long", f"{length} feature frames at {skeleton.fps:g} fps > max_frames {max_frames}")

    captions, dropped = captions_to_frames(clip.captions, length=length, fps=skeleton.fps, min_frames=min_frames)
    for reason, count in clip.dropped_captions.items():  # lines the source could not read at all
        dropped[reason] = dropped.get(reason, 0) + count
    if not captions:
        why = ", ".join(f"{n} {reason}" for reason, n in sorted(dropped.items())) or "the clip has none"
        return skip("no_captions", f"no usable caption ({why})")

    try:
        features = joints_to_features(joints, skeleton, compat=compat)
    except Exception as error:  # any failure inside the math is this clip's problem, reported per clip
        return skip("feature_error", f"{type(error).__name__}: {error}")
    features = np.ascontiguousarray(features, dtype=np.float32)
    if features.shape != (length, skeleton.feature_dim):
        return skip("feature_error", f"features have shape {features.shape}, expected ({length}, {skeleton.feature_dim})")
    if not np.isfinite(features).all():
        return skip("feature_error", "feature extraction produced NaN/inf (degenerate pose?)")

    return Record(
        id=clip.id,
        split=clip.split,
        source=clip.source,
        skeleton=skeleton.name,
        fps=float(skeleton.fps),
        features=features,
        captions=captions,
        action=clip.action,
        path=clip.path,
        dropped_captions=dropped,
    )


def captions_to_frames(
    captions: list[Caption], *, length: int, fps: float, min_frames: int
) -> tuple[list[RecordCaption], dict[str, int]]:
    """Map caption spans from seconds to feature frames, as HumanML3D does (``int(seconds * fps)``, and
    ``#0.0#0.0`` meaning the whole clip), clipped to ``[0, length]``. Empty texts and spans shorter than
    ``min_frames`` are dropped and counted by reason."""
    kept: list[RecordCaption] = []
    dropped: dict[str, int] = {}

    def drop(reason: str) -> None:
        dropped[reason] = dropped.get(reason, 0) + 1

    for caption in captions:
        text = caption.text.strip()
        if not text:
            drop("empty")
            continue
        whole_clip = caption.end is None or (caption.start == 0.0 and caption.end == 0.0)
        if not (math.isfinite(caption.start) and (whole_clip or math.isfinite(caption.end))):
            drop("bad_span")
            continue
        start = max(0, min(length, int(caption.start * fps)))
        end = length if whole_clip else max(0, min(length, int(caption.end * fps)))
        if end < start:
            drop("bad_span")
            continue
        if end - start < min_frames:
            drop("span_too_short")
            continue
        kept.append(RecordCaption(text=text, tokens=tuple(caption.tokens), start_frame=start, end_frame=end))
    return kept, dropped


def split_into_windows(record: Record, *, window: int, min_frames: int) -> list[Record]:
    """Cut a long record into consecutive non-overlapping ``window``-frame records ``ID-w000``, ``ID-w001``...
    A trailing piece shorter than ``min_frames`` is dropped; each window keeps the captions whose span
    overlaps it by at least ``min_frames`` frames (spans re-based to the window); a window left without
    captions is dropped and counted under ``dropped_captions["window_without_captions"]`` of the first
    window returned."""
    if record.length <= window:
        return [record]
    pieces: list[Record] = []
    empty_windows = 0
    for index, start in enumerate(range(0, record.length, window)):
        end = min(start + window, record.length)
        if end - start < min_frames:
            break
        captions = [
            replace(c, start_frame=max(c.start_frame, start) - start, end_frame=min(c.end_frame, end) - start)
            for c in record.captions
            if min(c.end_frame, end) - max(c.start_frame, start) >= min_frames
        ]
        if not captions:
            empty_windows += 1
            continue
        pieces.append(
            replace(
                record,
                id=f"{record.id}-w{index:03d}",
                features=record.features[start:end],
                captions=captions,
                dropped_captions={},
            )
        )
    if pieces:
        counts = dict(record.dropped_captions)
        if empty_windows:
            counts["window_without_captions"] = empty_windows
        pieces[0].dropped_captions = counts
    return pieces


# --- running a whole source -------------------------------------------------------------------------

ItemResult = list[Record] | SkippedInput


@dataclass
class _WorkerState:
    source: object
    skeleton: Skeleton
    settings: ProcessingSettings


_WORKER: _WorkerState | None = None
# Never plain fork: the building process may already run threads (torch's OpenMP pool, tokenizers, tqdm's
# monitor), and a child forked while one of them holds a lock can block forever; this hung a CI run of the
# test suite. A fork server is a fresh interpreter that imports this module once and forks each worker from
# a single-threaded state (Python 3.14's default on Linux for the same reason); spawn where there is none.
_START_METHOD = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"


@contextmanager
def single_threaded_torch() -> Iterator[None]:
    """Feature extraction is many small tensor ops: torch's intra-op threads only add synchronisation
    (measured 10-20x slower on a busy 2-core machine), and one thread everywhere also makes the result
    independent of the worker count."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def _init_worker(source: object, skeleton: Skeleton, settings: ProcessingSettings) -> None:
    global _WORKER
    torch.set_num_threads(1)  # see single_threaded_torch
    _WORKER = _WorkerState(source, skeleton, settings)


def _process_item(item: str) -> ItemResult:
    assert _WORKER is not None, "_init_worker was not called in this process"
    return process_item(_WORKER.source, item, _WORKER.skeleton, _WORKER.settings)


def process_item(source, item: str, skeleton: Skeleton, settings: ProcessingSettings) -> ItemResult:
    """Load one source item and process it: a list of records (one, or several windows) or a skip."""
    try:
        loaded = source.load(item)
    except Exception as error:  # sources report bad files as SkippedInput; anything else is unreadable too
        return SkippedInput(id=str(item), path=str(item), reason="unreadable", detail=f"{type(error).__name__}: {error}")
    if isinstance(loaded, SkippedInput):
        return loaded
    result = process_clip(
        loaded,
        skeleton,
        min_frames=settings.min_frames,
        max_frames=settings.max_frames,
        compat=settings.compat,
        long_clips=settings.long_clips,
    )
    if isinstance(result, SkippedInput):
        return result
    if settings.long_clips == "window" and settings.max_frames is not None:
        pieces = split_into_windows(result, window=settings.max_frames, min_frames=settings.min_frames)
        if not pieces:
            return SkippedInput(
                id=loaded.id, path=loaded.path, reason="no_captions",
                detail=f"no {settings.max_frames}-frame window has a caption span of >= {settings.min_frames} frames",
            )
        return pieces
    return [result]


def process_source(
    source, items: list[str], skeleton: Skeleton, settings: ProcessingSettings, *, workers: int = 1
) -> Iterator[ItemResult]:
    """Process ``items`` of ``source`` and yield one result per item, in ``items`` order.

    ``workers > 1`` uses a process pool; results come back through ``imap``, which keeps order, so the
    output does not depend on the worker count. Closing the generator early terminates the pool.
    Workers come from a fork server where the platform has one and are spawned elsewhere (see
    ``_START_METHOD``); either way the source is pickled to them, which the source contract asks anyway.
    """
    if workers <= 1:
        with single_threaded_torch():
            for item in items:
                yield process_item(source, item, skeleton, settings)
        return
    # Small chunks keep the ordered stream flowing; larger ones cut pickling overhead on big sources.
    chunksize = max(1, min(16, len(items) // (workers * 8)))
    context = multiprocessing.get_context(_START_METHOD)
    if _START_METHOD == "forkserver":
        context.set_forkserver_preload([__name__])  # import torch and the features once, not per worker
    with context.Pool(workers, initializer=_init_worker, initargs=(source, skeleton, settings)) as pool:
        yield from pool.imap(_process_item, items, chunksize=chunksize)
