"""The currency between data sources and the shard writer."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Caption:
    """One description of a clip. ``start``/``end`` are seconds into the clip (HumanML3D's ``#from#to``);
    ``end = None`` means "to the end of the clip". ``tokens`` are HumanML3D's ``word/POS`` tokens when the
    source has them (used by the official T2M evaluator), else empty."""

    text: str
    tokens: tuple[str, ...] = ()
    start: float = 0.0
    end: float | None = None


@dataclass
class Clip:
    """A joint sequence as a source delivers it, before feature extraction.

    ``joints`` is (T, J, 3) in the skeleton's own units (metres for HumanML3D-style sources, millimetres
    for KIT), Y up, at ``fps``. Sources do not resample: the feature stage does, to the skeleton's fps.
    """

    id: str
    joints: np.ndarray
    fps: float
    skeleton: str  # a name from mfm.skeleton.SKELETONS
    captions: list[Caption]
    split: str  # "train" | "val" | "test"
    source: str  # "humanml3d" | "kit" | "amass" | "deepmimic" | "synthetic" | ...
    action: str | None = None  # class label for action-to-motion (DeepMimic, synthetic)
    path: str = ""  # the file it was read from, for error messages
    meta: dict = field(default_factory=dict)
    # Captions the source could not read (a malformed span, no text), by reason: the processing stage adds
    # them to the record's ``dropped_captions``, so the skip report counts them.
    dropped_captions: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class SkippedInput:
    """A source item that could not become a Clip (unreadable file, wrong shape, ...). Sources yield these
    instead of raising so that the skip report counts them; ``--strict`` turns the first into an error."""

    id: str
    path: str
    reason: str  # a short machine-readable category, e.g. "unreadable", "bad_shape", "no_captions"
    detail: str = ""


# Skip reasons a source may report (the processing stage adds bad_fps/too_short/too_long/feature_error).
UNREADABLE = "unreadable"
BAD_SHAPE = "bad_shape"
NAN_FRAMES = "nan_frames"
NO_CAPTIONS = "no_captions"
MISSING_FILE = "missing_file"  # an item the dataset lists (a split file, an index) whose data file is absent


def check_joints(joints: np.ndarray, num_joints: int) -> tuple[str, str] | None:
    """Why ``joints`` cannot be a clip of a ``num_joints`` skeleton, as ``(reason, detail)``; None if it can.
    Sources call it on what they read; the processing stage again on every clip (any source, any caller)."""
    if joints.ndim != 3 or joints.shape[1:] != (num_joints, 3) or joints.shape[0] == 0:
        return BAD_SHAPE, f"expected (T>0, {num_joints}, 3) joint positions, got shape {joints.shape}"
    if np.issubdtype(joints.dtype, np.complexfloating):
        return BAD_SHAPE, f"complex-valued array (dtype {joints.dtype}): joint positions must be real numbers"
    if not np.issubdtype(joints.dtype, np.number):
        return BAD_SHAPE, f"expected numbers, got dtype {joints.dtype}"
    finite = np.isfinite(joints).all(axis=(1, 2))
    if not finite.all():
        bad = np.flatnonzero(~finite)
        return NAN_FRAMES, f"{bad.size} of {joints.shape[0]} frames hold NaN/inf (first: frame {bad[0]})"
    return None
