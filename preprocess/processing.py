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

from mfm.features import features_to_joints, features_to_joints_fk, joints_to_features, resample_joints
from mfm.layout import FeatureLayout
from mfm.skeleton import Skeleton
from preprocess.clip import BAD_SHAPE, NAN_FRAMES, Caption, Clip, SkippedInput, check_joints

log = logging.getLogger(__name__)

# HumanML3D keeps a motion when 40 <= len(features) < 200 (KIT: 24 <= len < 200). Keeping 197-199 frames
# (the training window is 196) keeps the published test set intact; the loader crops to its window.
DEFAULT_MIN_FRAMES = 40
DEFAULT_MAX_FRAMES = 199
# HumanML3D's dataset code: ``min_motion_len = 40 if dataset_name == 't2m' else 24`` (about 2 s either way).
MIN_FRAMES_BY_SKELETON = {"humanml3d": 40, "kit": 24}
LONG_CLIP_POLICIES = ("skip", "window")

# A clip may bring its dataset's own features (HumanML3D's new_joint_vecs/<id>.npy, (T, D) at the skeleton's
# fps) in ``Clip.meta[FEATURES_KEY]``: the record then keeps them exactly. Its ``joints`` are then None, or the
# joints of ``Clip.meta[JOINTS_PATH_KEY]`` to check them against (``feature_file_disagreement``); a clip whose two
# files disagree, or whose joint file cannot be read for the check, is skipped as ``feature_mismatch``.
# ``Clip.path`` is the feature file.
FEATURES_KEY = "features"
JOINTS_PATH_KEY = "joints_path"
FEATURE_MISMATCH = "feature_mismatch"
# A caption dropped because its span is too large to be a frame number (seconds × fps overflows): ``#0.0#1e308``.
SPAN_OUT_OF_RANGE = "span_out_of_range"

# When a clip comes with both its dataset's feature file (new_joint_vecs, T frames) and its joint file, the
# two must agree (``feature_file_disagreement``); a clip that does not is skipped as ``feature_mismatch``
# naming both files. Two cases, by the joint file's length:
#
# * T frames: HumanML3D's/KIT's ``new_joints``, saved as recover_from_ric(features). Recomputing features
#   from them cannot reproduce the file: the forward direction is Gaussian-smoothed over the whole clip
#   (sigma 20 frames) and the joints lack the last raw frame, so the facing of the last ~80 frames moves;
#   on turning synthetic clips (tests/test_features.py's generator) the mean difference reached 39x the
#   limits below. The check therefore goes the other way, from the features to joints, where the two files
#   are the same data: joints recovered from the root + ric groups (recover_from_ric) and by forward
#   kinematics on the 6D rotations (recover_from_rot), every local velocity's length and height change
#   against the joints' frame differences, and the foot-contact labels recomputed from the joints. Measured
#   on the published clip 012314: 2.1e-7 m, 1.6e-6 m, 3.0e-7 m, 0 labels; on 12 synthetic clips (60-199
#   frames, turning up to 0.2 rad/frame) at most 2.4e-7 m, 2.4e-7 m, 3.7e-7 m, 0.
RECOVERED_JOINTS_TOLERANCE = {
    "ric": 1e-4,  # max |recover_from_ric(features) - joints|, m
    "rot6d": 1e-3,  # max |recover_from_rot(features) - joints|, m (the skeleton's bone lengths are rounded)
    "local_vel": 1e-4,  # max over joints/frames of | |v| - |dp| | and |v_y - dp_y|, m
    "contacts": 0.05,  # share of foot-contact labels that differ (velocities at the threshold may flip)
}
# * T + 1 frames: the joints the features were computed from (raw_pose_processing's ``joints/``): the features
#   are recomputed (compat=True: the published files were made with the reference's quirks) and must agree, per
#   feature group, in the MEAN absolute difference over the frames, in HumanML3D's units (m, rad/frame, 6D
#   components, contact labels). These are ~20x the differences between this code and the published features
#   (tests/test_features.py's golden test: means 4.5e-5, 8.6e-6, 9.3e-7, 1.5e-4, 1.0e-4, 6.9e-6, 0). The root
#   angular velocity is compared in absolute value: the reference flips its sign on the frame where the facing
#   crosses +-180 deg, this code does not (see mfm/features.py).
#
# Length tolerances (m) are multiplied by 1000 for a millimetre skeleton (KIT). A swapped, mirrored or
# differently extracted file is off by 1e-2..1.
FEATURE_AGREEMENT = {
    "root_rot_vel": 1e-3,
    "root_lin_vel": 2e-4,
    "root_height": 5e-3,
    "ric": 3e-3,
    "rot6d": 2e-3,
    "local_vel": 2e-4,
    "contacts": 0.05,
}
_LENGTH_GROUPS = ("root_lin_vel", "root_height", "ric", "local_vel")
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
    # Captions this record lost on the way, by reason ("empty", "span_too_short", "bad_span", "span_out_of_range", and
    # the source's own, e.g. "span_not_a_number" for a caption line it could not read): counted in the skip
    # report, never silently.
    dropped_captions: dict[str, int] = field(default_factory=dict)
    # A distillation pair's noise seed (pipeline/training/distill.py): the motion is the teacher's ODE solution from
    # mfm.solvers.draw_noise of this seed and the record's length. None for a dataset's own clips (not written).
    noise_seed: int | None = None

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


def check_features(features: np.ndarray, dim: int) -> tuple[str, str] | None:
    """Why ``features`` cannot be a clip's (T, ``dim``) feature array, as ``(reason, detail)``; None if it can."""
    if features.ndim != 2 or features.shape[1] != dim or features.shape[0] == 0:
        return BAD_SHAPE, f"expected (T>0, {dim}) features, got shape {features.shape}"
    if np.issubdtype(features.dtype, np.complexfloating):
        return BAD_SHAPE, f"complex-valued array (dtype {features.dtype}): features must be real numbers"
    if not np.issubdtype(features.dtype, np.number):
        return BAD_SHAPE, f"expected numbers, got dtype {features.dtype}"
    finite = np.isfinite(features).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        return NAN_FRAMES, f"{bad.size} of {features.shape[0]} feature frames hold NaN/inf (first: frame {bad[0]})"
    return None


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
    if clip.meta.get(FEATURES_KEY) is not None:
        return _record_from_feature_file(clip, skeleton, min_frames=min_frames, max_frames=max_frames,
                                         long_clips=long_clips)
    if clip.joints is None:
        return skip("bad_shape", "the clip has neither joints nor features")
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
    framed = _length_and_captions(clip, skeleton, length, min_frames=min_frames, max_frames=max_frames,
                                  long_clips=long_clips)
    if isinstance(framed, SkippedInput):
        return framed
    captions, dropped = framed

    try:
        features = joints_to_features(joints, skeleton, compat=compat)
    except Exception as error:  # any failure inside the math is this clip's problem, reported per clip
        return skip("feature_error", f"{type(error).__name__}: {error}")
    features = np.ascontiguousarray(features, dtype=np.float32)
    if features.shape != (length, skeleton.feature_dim):
        return skip("feature_error", f"features have shape {features.shape}, expected ({length}, {skeleton.feature_dim})")
    if not np.isfinite(features).all():
        return skip("feature_error", "feature extraction produced NaN/inf (degenerate pose?)")
    return _record(clip, skeleton, features, captions, dropped)


def _length_and_captions(
    clip: Clip, skeleton: Skeleton, length: int, *, min_frames: int, max_frames: int | None, long_clips: str
) -> tuple[list[RecordCaption], dict[str, int]] | SkippedInput:
    """The length filters and the captions mapped onto ``length`` feature frames (with the source's own dropped
    lines counted), or why the clip is skipped: shared by computed features and a dataset's feature file."""

    def skip(reason: str, detail: str) -> SkippedInput:
        return SkippedInput(id=clip.id, path=clip.path, reason=reason, detail=detail)

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
    return captions, dropped


def _record(clip: Clip, skeleton: Skeleton, features: np.ndarray, captions: list[RecordCaption],
            dropped: dict[str, int]) -> Record:
    return Record(
        id=clip.id,
        split=clip.split,
        source=clip.source,
        skeleton=skeleton.name,
        fps=float(skeleton.fps),
        features=np.ascontiguousarray(features, dtype=np.float32),
        captions=captions,
        action=clip.action,
        path=clip.path,
        dropped_captions=dropped,
    )


def _record_from_feature_file(
    clip: Clip, skeleton: Skeleton, *, min_frames: int, max_frames: int | None, long_clips: str
) -> Record | SkippedInput:
    """:func:`process_clip` for a clip that brings its dataset's features: they become the record as they
    are (float32), after the same checks, filters and caption mapping as computed features; with joints
    beside them, the two files must first agree (:func:`feature_file_disagreement`)."""

    def skip(reason: str, detail: str) -> SkippedInput:
        return SkippedInput(id=clip.id, path=clip.path, reason=reason, detail=detail)

    features = np.asarray(clip.meta[FEATURES_KEY])
    problem = check_features(features, skeleton.feature_dim)
    if problem is not None:
        reason, detail = problem
        return skip(reason, f"{detail} ({skeleton.name} skeleton)")
    if not (math.isfinite(clip.fps) and math.isclose(clip.fps, skeleton.fps, rel_tol=1e-9)):
        return skip("bad_fps", f"feature file at {clip.fps!r} fps, the {skeleton.name} skeleton's is {skeleton.fps:g}: "
                               "features cannot be resampled (recompute them from the joints)")
    framed = _length_and_captions(clip, skeleton, len(features), min_frames=min_frames, max_frames=max_frames,
                                  long_clips=long_clips)
    if isinstance(framed, SkippedInput):
        return framed
    captions, dropped = framed

    if clip.joints is not None:
        disagreement = feature_file_disagreement(features, clip.joints, skeleton)
        if disagreement:
            return skip(FEATURE_MISMATCH, f"disagrees with the joint file {clip.meta.get(JOINTS_PATH_KEY) or '(in memory)'}: "
                                          f"{disagreement}")
    return _record(clip, skeleton, features, captions, dropped)


def feature_file_disagreement(features: np.ndarray, joints: np.ndarray, skeleton: Skeleton) -> str:
    """Empty when ``features`` (a dataset's feature file, T frames) agree with ``joints``: a joint file of T
    frames saved as recover_from_ric of the features (HumanML3D's ``new_joints``), checked against joints
    recovered from the features (:data:`RECOVERED_JOINTS_TOLERANCE`), or one of T + 1 raw frames, checked
    against features recomputed from it (:data:`FEATURE_AGREEMENT`). Else what disagrees, group by group."""
    joints = np.asarray(joints)
    problem = check_joints(joints, skeleton.num_joints)
    if problem is not None:
        return f"the joint file cannot be used ({problem[0]}: {problem[1]})"
    if len(joints) not in (len(features), len(features) + 1) or len(joints) < 2:
        return (f"{len(features)} feature frames, but the joint file has {len(joints)} frames "
                f"(expected {len(features)} for new_joints, or {len(features) + 1} for the joints they were computed from)")
    scale = 1000.0 if skeleton.unit == "mm" else 1.0
    ours = np.asarray(features, dtype=np.float64)
    positions = np.asarray(joints, dtype=np.float64)
    if len(joints) == len(features):
        return _recovered_joints_disagreement(ours, positions, skeleton, scale)
    try:
        recomputed = np.asarray(joints_to_features(positions, skeleton, compat=True), dtype=np.float64)
    except Exception as error:  # a degenerate pose: the files cannot be shown to agree
        return f"feature extraction from the joints failed ({type(error).__name__}: {error})"
    problems = []
    for name, group in FeatureLayout(skeleton).slices.items():
        a, b = ours[:, group], recomputed[:, group]
        if name == "root_rot_vel":
            a, b = np.abs(a), np.abs(b)
        deviation = float(np.abs(a - b).mean())
        tolerance = FEATURE_AGREEMENT[name] * (scale if name in _LENGTH_GROUPS else 1.0)
        if not deviation <= tolerance:  # NaN disagrees too
            unit = f" {skeleton.unit}" if name in _LENGTH_GROUPS else ""
            problems.append(f"{name}: mean |diff| from recomputed features {deviation:.3g}{unit} > {tolerance:g}{unit}")
    return "; ".join(problems)


def _recovered_joints_disagreement(features: np.ndarray, joints: np.ndarray, skeleton: Skeleton, scale: float) -> str:
    """:func:`feature_file_disagreement` for a joint file saved as recover_from_ric(features) (same length).
    Nothing here depends on the facing estimate, so the missing last raw frame does not matter: ~1 ms a clip."""
    slices = FeatureLayout(skeleton).slices
    unit = skeleton.unit
    problems = []

    def check(name: str, deviation: float, what: str) -> None:
        tolerance = RECOVERED_JOINTS_TOLERANCE[name] * (scale if name != "contacts" else 1.0)
        if not deviation <= tolerance:
            limit = f"{tolerance:.0%}" if name == "contacts" else f"{tolerance:g} {unit}"
            shown = f"{deviation:.1%}" if name == "contacts" else f"{deviation:.3g} {unit}"
            problems.append(f"{name}: {what} {shown} > {limit}")

    check("ric", float(np.abs(features_to_joints(features, skeleton) - joints).max()),
          "joints recovered from the root and ric groups differ by up to")
    check("rot6d", float(np.abs(features_to_joints_fk(features, skeleton, compat=True) - joints).max()),
          "joints from forward kinematics on the 6D rotations differ by up to")
    # Frame t's velocities are the steps t -> t + 1 rotated about Y: same lengths, same vertical parts.
    velocities = features[:-1, slices["local_vel"]].reshape(len(features) - 1, skeleton.num_joints, 3)
    steps = joints[1:] - joints[:-1]
    speed = np.abs(np.linalg.norm(velocities, axis=-1) - np.linalg.norm(steps, axis=-1)).max()
    height = np.abs(velocities[..., 1] - steps[..., 1]).max()
    check("local_vel", float(max(speed, height)), "joint velocities differ from the joints' frame steps by up to")
    # HumanML3D's rule (mfm.features): a foot joint touches when its squared step is under the threshold.
    feet = steps[:, list(skeleton.foot_left + skeleton.foot_right)]
    labels = ((feet * feet).sum(axis=-1) < skeleton.contact_threshold).astype(np.float64)
    check("contacts", float((features[:-1, slices["contacts"]] != labels).mean()),
          "foot-contact labels recomputed from the joints differ on")
    return "; ".join(problems)


def captions_to_frames(
    captions: list[Caption], *, length: int, fps: float, min_frames: int
) -> tuple[list[RecordCaption], dict[str, int]]:
    """Map caption spans from seconds to feature frames, as HumanML3D does (``int(seconds * fps)``, and
    ``#0.0#0.0`` meaning the whole clip), clipped to ``[0, length]``. Empty texts, spans shorter than
    ``min_frames`` and spans too large to be a frame number (``#0.0#1e308``: seconds × fps overflows to inf, which
    ``int`` cannot take) are dropped and counted by reason, so one bad caption never stops a build."""
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
        start_frame, end_frame = caption.start * fps, None if whole_clip else caption.end * fps
        if not (math.isfinite(start_frame) and (end_frame is None or math.isfinite(end_frame))):
            drop(SPAN_OUT_OF_RANGE)
            continue
        start = max(0, min(length, int(start_frame)))
        end = length if end_frame is None else max(0, min(length, int(end_frame)))
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
