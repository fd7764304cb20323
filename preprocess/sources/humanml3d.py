"""HumanML3D-layout datasets (HumanML3D itself; KIT-ML reuses the reader, see ``kit.py``), and the
HumanML3D conventions the other sources share: caption files, split files, motion ids and the checks
every joint array goes through.

Layout (EricGuo5513/HumanML3D)::

    ROOT/
      new_joint_vecs/<id>.npy (T, 263) float32: the published features (KIT: (T, 251))
      new_joints/<id>.npy     (T, 22, 3) float32, metres, Y up, 20 fps (the retargeted joints, saved as
                               recover_from_ric of the features, so also T frames; or
      joints/<id>.npy          raw_pose_processing's output, (T + 1, 52, 3) SMPL-H joints of which the first
                               22 are the body, exactly as motion_representation reads them)
      texts/<id>.txt          one caption a line: ``caption#tok1/POS tok2/POS ...#from#to``
      train.txt val.txt test.txt   ids, one a line
      Mean.npy Std.npy        the official normalisation (used by the build when present, see shards.py)

Features (option ``features``): ``auto`` (default) reads ``new_joint_vecs/<id>.npy`` as they are when that
folder exists, and computes them from the joint folder otherwise; ``file`` insists on the feature files;
``recompute`` always computes them from the joints. With feature files, ids come from ``new_joint_vecs/`` and
the joint folder is optional; when it is there, a share of the clips (option ``verify``: ``all``, ``none`` or
a fraction, picked by a hash of the id; default all) is checked against its joint file
(``preprocess.processing.feature_file_disagreement``: for ``new_joints``, joints recovered from the features
must match them to 0.1 mm, velocities and contacts too; for raw ``joints/``, features recomputed from them
must match), else the clip is skipped as ``feature_mismatch`` naming both files (``--strict``: an error). Features read from files have the file's
T frames; recomputed from ``new_joints/`` (T frames) they have T - 1 (the last frame needs a joint frame
the dataset does not ship); caption spans are mapped onto whichever length the record has.

``from``/``to`` are seconds into the clip. As in HumanML3D's own loader, ``0.0#0.0`` (or NaN) means the
whole clip and anything else a sub-clip ``[from, to)``; ``to = 0`` with ``from > 0`` (which HumanML3D's
loader turns into an empty clip) is read here as "from ``from`` to the end". A line whose span is not a
number, negative, or ends before it starts, a line with tags but no text, and a line of plain text without the
``#tokens#from#to`` tags (not a HumanML3D caption line: no tokens for the T2M evaluator, and HumanML3D's own loader
fails on it) is dropped and counted by reason (``Clip.dropped_captions``, then the skip report's
``dropped_captions``); so is a span too large to be a frame number (``#0.0#1e308``, counted by the processing stage).

Ids: a joint file is ``<id>.npy`` with the id in ``[A-Za-z0-9_-]`` (``000001.npy``, ``M000001.npy``), so the
file name alone is the id and two files can never share one. Anything else in the joint folder (a
``000001.bak.npy``, ``notes.txt``) is not read; ``ignored_files()`` lists it for the skip report.

Splits: an id listed in ``<split>.txt`` belongs to that split; an id in no split file (or every id, when
the folder has no split files) gets the ``default_split`` option ('train' unless told otherwise).
Only ids whose split is in the ``splits`` option are listed, and every id a split file lists is an item:
one without its joint file is skipped as ``missing_file``, never ignored.
"""

from __future__ import annotations

import hashlib
import logging
import math
import re
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mfm.skeleton import Skeleton, get_skeleton
from preprocess.clip import (
    MISSING_FILE,
    NO_CAPTIONS,
    UNREADABLE,
    Caption,
    Clip,
    SkippedInput,
    check_joints,
)
from preprocess.processing import FEATURE_MISMATCH, FEATURES_KEY, JOINTS_PATH_KEY, check_features, is_valid_key

log = logging.getLogger(__name__)

SPLIT_NAMES: tuple[str, ...] = ("train", "val", "test")


_INVALID_ID_CHARS = re.compile(r"[^A-Za-z0-9_-]")


# ----------------------------------------------------------------------------------------------------
# Conventions shared by every source
# ----------------------------------------------------------------------------------------------------


def motion_id(reference: str) -> str:
    """A shard key (``[A-Za-z0-9_-]`` only, see docs/dataset-format.md) for an item reference such as a
    relative path: folders joined with ``__``, the extension dropped, any other character replaced by
    ``_``."""
    stem = reference.replace("\\", "/")
    stem = stem[: -len(Path(stem).suffix)] if Path(stem).suffix else stem
    return _INVALID_ID_CHARS.sub("_", stem.strip("/").replace("/", "__"))


def as_name_list(value: str | Iterable[str] | None) -> tuple[str, ...]:
    """Options given on a command line arrive as ``"a,b"``; in code as a list. Both become a tuple."""
    if value is None:
        return ()
    if isinstance(value, str):
        return tuple(part.strip() for part in value.split(",") if part.strip())
    return tuple(value)


def as_bool(value: bool | str) -> bool:
    """A boolean option, also from a command line (``true``/``false``/``1``/``0``/``yes``/``no``)."""
    if isinstance(value, str):
        if value.strip().lower() in ("1", "true", "yes", "on"):
            return True
        if value.strip().lower() in ("0", "false", "no", "off"):
            return False
        raise ValueError(f"expected a boolean, got {value!r}")
    return bool(value)


def check_splits(splits: Sequence[str], what: str) -> tuple[str, ...]:
    unknown = sorted(set(splits) - set(SPLIT_NAMES))
    if unknown:
        raise ValueError(f"{what}: unknown split(s) {unknown}; known: {list(SPLIT_NAMES)}")
    return tuple(splits)


def hash_unit(key: str) -> float:
    """A number in [0, 1) that depends only on ``key`` (sha256, not Python's salted ``hash``)."""
    return int.from_bytes(hashlib.sha256(key.encode("utf-8")).digest()[:8], "big") / 2**64


def hash_split(key: str, val_fraction: float = 0.1, test_fraction: float = 0.1) -> str:
    """A split that depends only on ``key`` (sha256, not Python's salted ``hash``), so it is the same on
    every machine and run: roughly (1 - val - test) train, val, test."""
    u = hash_unit(key)
    if u < test_fraction:
        return "test"
    if u < test_fraction + val_fraction:
        return "val"
    return "train"


# ----------------------------------------------------------------------------------------------------
# Caption and split files
# ----------------------------------------------------------------------------------------------------


# Why a caption line is dropped (its key in the skip report's ``dropped_captions``).
EMPTY_CAPTION = "empty"  # tags without text (the processing stage counts empty texts under the same key)
SPAN_NOT_A_NUMBER = "span_not_a_number"  # ``#abc#2.0``, or infinite
SPAN_NEGATIVE = "span_negative"  # ``#-1#2``
SPAN_END_NOT_AFTER_START = "span_end_not_after_start"  # ``#5.0#2.0``
NO_TAGS = "no_tags"  # a caption file line of plain text, without ``#tokens#from#to``


class CaptionSpanError(ValueError):
    """A caption line whose ``#from#to`` span cannot be used; ``reason`` is one of the ``SPAN_*`` keys."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def _seconds(field: str) -> float:
    """A ``#from#to`` tag; NaN (HumanML3D writes ``nan`` for some) counts as 0 like its loader does."""
    try:
        value = float(field)
    except ValueError:
        raise CaptionSpanError(SPAN_NOT_A_NUMBER, f"span tag {field.strip()!r} is not a number") from None
    if math.isinf(value):
        raise CaptionSpanError(SPAN_NOT_A_NUMBER, f"span tag {field.strip()!r} is not a finite number")
    return 0.0 if math.isnan(value) else value


def parse_caption_line(line: str) -> Caption | None:
    """One ``caption#tokens#from#to`` line; None for an empty caption. A line without the tags (plain
    text) is a whole-clip caption without tokens. Raises :class:`CaptionSpanError` (a ValueError) on a
    malformed span."""
    fields = line.rstrip("\r\n").split("#")
    text = fields[0].strip()
    if not text:
        return None
    tokens = tuple(fields[1].split()) if len(fields) > 1 else ()
    start = _seconds(fields[2]) if len(fields) > 2 and fields[2].strip() else 0.0
    end_tag = _seconds(fields[3]) if len(fields) > 3 and fields[3].strip() else 0.0
    if start < 0 or end_tag < 0:
        raise CaptionSpanError(SPAN_NEGATIVE, f"negative span {start}..{end_tag} s")
    if end_tag == 0.0:
        return Caption(text=text, tokens=tokens, start=start, end=None)
    if end_tag <= start:
        raise CaptionSpanError(SPAN_END_NOT_AFTER_START, f"span end {end_tag} s is not after its start {start} s")
    return Caption(text=text, tokens=tokens, start=start, end=end_tag)


@dataclass(frozen=True)
class CaptionFile:
    """A caption file's usable captions, the lines dropped from it counted by reason, and the first
    dropped line (``"line N: why"``) for skip details. Blank lines are no captions and are not counted."""

    captions: list[Caption]
    dropped: dict[str, int]
    first_dropped: str = ""


def read_caption_file(path: Path) -> CaptionFile:
    """The captions of a HumanML3D ``texts/<id>.txt`` file; lines with a malformed span, and plain-text lines without
    the ``#tokens#from#to`` tags, are dropped, counted and logged (file:line). Raises OSError/UnicodeDecodeError if
    the file cannot be read."""
    captions: list[Caption] = []
    dropped: dict[str, int] = {}
    first = ""
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if not line.strip():
            continue
        if "#" not in line:
            reason, why = NO_TAGS, "plain text without the #tokens#from#to tags of a HumanML3D caption line"
            log.warning("%s:%d: caption dropped (%s): %s", path, number, reason, why)
        else:
            try:
                caption = parse_caption_line(line)
            except CaptionSpanError as err:
                reason, why = err.reason, str(err)
                log.warning("%s:%d: caption dropped (%s): %s", path, number, reason, why)
            else:
                if caption is not None:
                    captions.append(caption)
                    continue
                reason, why = EMPTY_CAPTION, "no caption text"
        dropped[reason] = dropped.get(reason, 0) + 1
        first = first or f"line {number}: {why}"
    return CaptionFile(captions, dropped, first)


def load_caption_file(path: Path, clip_id: str) -> CaptionFile | SkippedInput:
    """A clip's caption file, or why the clip has no caption: ``no_captions`` when the file is missing or no
    line is usable (the detail counts the dropped lines by reason and quotes the first), ``unreadable`` when
    it cannot be read. Every reader of HumanML3D's ``texts/`` goes through here."""
    if not path.is_file():
        return SkippedInput(clip_id, str(path), NO_CAPTIONS, "caption file missing")
    try:
        read = read_caption_file(path)
    except (OSError, UnicodeDecodeError) as err:
        return SkippedInput(clip_id, str(path), UNREADABLE, f"{type(err).__name__}: {err}")
    if read.captions:
        return read
    if not read.dropped:
        return SkippedInput(clip_id, str(path), NO_CAPTIONS, "the caption file has no caption line")
    counts = ", ".join(f"{n} {reason}" for reason, n in sorted(read.dropped.items()))
    return SkippedInput(clip_id, str(path), NO_CAPTIONS, f"no usable caption line ({counts}; {read.first_dropped})")


def missing_listed_item(item: str, split: str | None, path: Path, what: str) -> SkippedInput:
    """The skip for an id a split file lists whose data the dataset lacks (``what``: which file, or which
    index row, is absent). Such ids are items like any other, so the skip report counts them."""
    listed = f"listed in {split}.txt" if split else "asked for"
    return SkippedInput(item, str(path), MISSING_FILE, f"{listed}, but {what}")


def read_split_files(folder: Path) -> dict[str, str]:
    """``{id: split}`` from ``train.txt``/``val.txt``/``test.txt`` in ``folder`` (those that exist). An id
    listed twice keeps its first split in train, val, test order, with a warning."""
    membership: dict[str, str] = {}
    for split in SPLIT_NAMES:
        path = folder / f"{split}.txt"
        if not path.is_file():
            continue
        for line in path.read_text(encoding="utf-8").splitlines():
            item = line.strip()
            if not item:
                continue
            if item in membership and membership[item] != split:
                log.warning("%s: id %s is already in %s.txt; kept there", path, item, membership[item])
                continue
            membership[item] = split
    return membership


# ----------------------------------------------------------------------------------------------------
# The reader
# ----------------------------------------------------------------------------------------------------


FEATURE_MODES: tuple[str, ...] = ("auto", "file", "recompute")


def as_fraction(value: float | int | str) -> float:
    """The ``verify`` option: ``all`` (1), ``none`` (0) or a fraction in [0, 1]."""
    if isinstance(value, str):
        named = {"all": 1.0, "none": 0.0}.get(value.strip().lower())
        if named is not None:
            return named
        try:
            value = float(value)
        except ValueError:
            raise ValueError(f"expected 'all', 'none' or a fraction in [0, 1], got {value!r}") from None
    if isinstance(value, bool) or not (0.0 <= float(value) <= 1.0):
        raise ValueError(f"expected 'all', 'none' or a fraction in [0, 1], got {value!r}")
    return float(value)


class HumanML3DLayoutSource:
    """Feature files, joint files, caption files and split files in HumanML3D's layout (see the module
    docstring).

    Options: ``features`` ('auto', 'file' or 'recompute', see the module docstring), ``verify`` (the share
    of clips whose feature file is checked against their joint file: 'all' (default), 'none' or a fraction),
    ``joints_dir`` ('new_joints' or 'joints'; default: whichever exists, new_joints first), ``splits``
    (which splits to list, default all three), ``default_split`` (the split of an id in no split file,
    default 'train'). Subclasses set the dataset constants below.
    """

    name: str = "humanml3d"
    skeleton: str = "humanml3d"
    fps: float = 20.0
    num_joints: int = 22
    # Joint counts accepted in the joint files; more than ``num_joints`` means "the body joints come
    # first" (raw_pose_processing saves all 52 SMPL-H joints and motion_representation keeps [:22]).
    accepted_joint_counts: tuple[int, ...] = (22, 52)
    joints_dir_names: tuple[str, ...] = ("new_joints", "joints")
    features_dir_name: str = "new_joint_vecs"
    # The official normalisation files at the root (``normalization_files``).
    normalization_file_names: tuple[str, str] = ("Mean.npy", "Std.npy")
    # Clips whose frame 0 defines the target skeleton when the skeleton has no built-in bone lengths.
    reference_clip_ids: tuple[str, ...] = ()

    def __init__(
        self,
        root: str | Path | None,
        *,
        features: str = "auto",
        verify: float | str = "all",
        joints_dir: str | None = None,
        splits: str | Sequence[str] = SPLIT_NAMES,
        default_split: str = "train",
    ) -> None:
        if root is None:
            raise ValueError(f"source {self.name!r} needs a root folder (--root) in HumanML3D's layout")
        self.root = Path(root)
        if not self.root.is_dir():
            raise FileNotFoundError(f"{self.name}: root folder {self.root} does not exist")
        if features not in FEATURE_MODES:
            raise ValueError(f"{self.name} option features: expected one of {list(FEATURE_MODES)}, got {features!r}")
        try:
            self.verify_fraction = as_fraction(verify)
        except ValueError as err:
            raise ValueError(f"{self.name} option verify: {err}") from None
        self.features_dir = self.root / self.features_dir_name
        if features == "file" and not self.features_dir.is_dir():
            raise FileNotFoundError(f"{self.name}: features=file, but there is no feature folder {self.features_dir} "
                                    f"(HumanML3D's {self.features_dir_name}/<id>.npy)")
        # Features from the dataset's own files ('auto' when the folder is there), else computed from joints.
        self.reads_feature_files = features == "file" or (features == "auto" and self.features_dir.is_dir())
        self.joints_dir = self._find_joints_dir(joints_dir, required=not self.reads_feature_files or joints_dir is not None)
        self.texts_dir = self.root / "texts"
        self.splits = check_splits(as_name_list(splits), f"{self.name} option splits")
        (self.default_split,) = check_splits((default_split,), f"{self.name} option default_split")
        # Read once here (cheap) rather than per item: workers receive it with the pickled source.
        self.split_of = read_split_files(self.root)
        if self.reads_feature_files:
            checked = "no joint folder to check them against" if self.joints_dir is None else (
                f"checking {self.verify_fraction:.0%} of them against {self.joints_dir.name}/")
            log.info("%s: features read from %s/ (%s)", self.name, self.features_dir_name, checked)

    def _find_joints_dir(self, requested: str | None, *, required: bool = True) -> Path | None:
        candidates = (requested,) if requested else self.joints_dir_names
        for candidate in candidates:
            if (self.root / candidate).is_dir():
                return self.root / candidate
        if not required:
            return None
        raise FileNotFoundError(
            f"{self.name}: no joint folder {' or '.join(candidates)} under {self.root} "
            f"(expected HumanML3D's layout: <root>/new_joints/<id>.npy or <root>/{self.features_dir_name}/<id>.npy, "
            f"<root>/texts/<id>.txt)"
        )

    @property
    def item_dir(self) -> Path:
        """The folder whose ``<id>.npy`` files are the items: the feature folder when features are read from
        files, else the joint folder."""
        return self.features_dir if self.reads_feature_files else self.joints_dir

    # -- protocol ------------------------------------------------------------------------------------

    def list_items(self) -> list[str]:
        """The ids of the item files (feature or joint files) in the asked splits, and every id those split
        files list (an absent file is the item's skip, ``missing_file``)."""
        ids = {i for i in self._scan_item_folder()[0] if self.split_of.get(i, self.default_split) in self.splits}
        listed = {i for i, split in self.split_of.items() if split in self.splits}
        return sorted(ids | listed)

    def ignored_files(self) -> list[str]:
        """Entries of the item folder that are not ``<id>.npy`` files, so never read (for the skip report)."""
        return [str(path) for path in self._scan_item_folder()[1]]

    def normalization_files(self) -> tuple[Path, Path]:
        """Where the dataset's official Mean/Std would be (``ROOT/Mean.npy``, ``ROOT/Std.npy``); the build
        uses them when present (``--normalization auto``)."""
        mean, std = self.normalization_file_names
        return self.root / mean, self.root / std

    def load(self, item: str) -> Clip | SkippedInput:
        path = self.item_dir / f"{item}.npy"
        clip_id = motion_id(item)
        if not is_valid_key(item):
            split = self.split_of.get(item)
            return missing_listed_item(item, split, self.root / f"{split}.txt" if split else path,
                                       f"{item!r} is not a file name of the layout (<id>.npy, id in [A-Za-z0-9_-])")
        if not path.is_file():
            what = "feature" if self.reads_feature_files else "joint"
            return missing_listed_item(item, self.split_of.get(item), path,
                                       f"there is no {what} file {self.item_dir.name}/{item}.npy")
        try:
            raw = np.load(path, allow_pickle=False)
        except Exception as err:  # any failure to read is a skip, never a crash of the worker
            return SkippedInput(clip_id, str(path), UNREADABLE, f"{type(err).__name__}: {err}")
        if self.reads_feature_files:
            features = raw
            problem = check_features(features, get_skeleton(self.skeleton).feature_dim)
            joints = None
        else:
            features = None
            joints = self._body_joints(raw)
            problem = check_joints(joints, self.num_joints)
        if problem is not None:
            return SkippedInput(clip_id, str(path), *problem)

        captions = load_caption_file(self.texts_dir / f"{item}.txt", clip_id)
        if isinstance(captions, SkippedInput):
            return captions

        joints_path = ""
        if self.reads_feature_files and self._checks(item):
            checked = self._joints_to_check(item, clip_id, path)
            if isinstance(checked, SkippedInput):
                return checked
            if checked is not None:
                joints_path, joints = checked

        return Clip(
            id=clip_id,
            joints=None if joints is None else joints.astype(np.float32, copy=False),
            fps=self.fps,
            skeleton=self.skeleton,
            captions=captions.captions,
            split=self.split_of.get(item, self.default_split),
            source=self.name,
            path=str(path),
            dropped_captions=dict(captions.dropped),
            meta={} if features is None else {FEATURES_KEY: features.astype(np.float32, copy=False),
                                              JOINTS_PATH_KEY: joints_path},
        )

    def target_skeleton(self) -> Skeleton:
        """The skeleton every clip is retargeted to: the built-in one when it has bone lengths, else
        measured on frame 0 of the first reference clip present (``reference_clip_ids``), falling back to
        the first listed clip. Files in ``new_joints/`` are already retargeted, so any of them gives the
        target lengths; without a joint folder, the joints recovered from a feature file do."""
        skeleton = get_skeleton(self.skeleton)
        if skeleton.bone_lengths is not None:
            return skeleton
        folder = self.joints_dir if self.joints_dir is not None else self.features_dir
        present = [i for i in self.reference_clip_ids if (folder / f"{i}.npy").is_file()]
        on_disk = [i for i in sorted(self._scan(folder)[0]) if self.split_of.get(i, self.default_split) in self.splits]
        for item in present + on_disk[:1]:
            first = self._first_frame(folder / f"{item}.npy", skeleton)
            if first is not None:
                log.info("%s: target skeleton measured on %s", self.name, folder / f"{item}.npy")
                return skeleton.with_bone_lengths_from(first)
        raise FileNotFoundError(
            f"{self.name}: no readable clip in {folder} to measure the target skeleton on "
            f"(the reference code uses {self.reference_clip_ids or 'a reference clip'})"
        )

    # -- helpers ---------------------------------------------------------------------------------------

    def _checks(self, item: str) -> bool:
        """Whether clip ``item``'s feature file is checked against its joint file (a fixed share of ids,
        picked by a hash of the id: the same clips whatever the worker count or the order)."""
        if self.joints_dir is None or self.verify_fraction <= 0.0:
            return False
        return self.verify_fraction >= 1.0 or hash_unit(f"verify:{item}") < self.verify_fraction

    def _joints_to_check(self, item: str, clip_id: str, features_path: Path) -> tuple[str, np.ndarray] | SkippedInput | None:
        """``(path, joints)`` of the joint file to check the features of ``item`` against; None when the clip
        has no joint file (nothing to check); a ``feature_mismatch`` skip when it cannot be read."""
        assert self.joints_dir is not None
        path = self.joints_dir / f"{item}.npy"
        if not path.is_file():
            return None
        try:
            joints = self._body_joints(np.load(path, allow_pickle=False))
        except Exception as err:
            return SkippedInput(clip_id, str(features_path), FEATURE_MISMATCH,
                                f"cannot be checked against {path}: {type(err).__name__}: {err}")
        problem = check_joints(joints, self.num_joints)
        if problem is not None:
            return SkippedInput(clip_id, str(features_path), FEATURE_MISMATCH,
                                f"cannot be checked against {path} ({problem[0]}: {problem[1]})")
        return str(path), joints

    def _first_frame(self, path: Path, skeleton: Skeleton) -> np.ndarray | None:
        """Frame 0 of a clip's joints read from a joint file, or recovered from a feature file; None if the
        file cannot be used."""
        try:
            raw = np.load(path, allow_pickle=False)
        except Exception:
            return None
        if path.parent == self.features_dir and self.joints_dir is None:
            if check_features(raw, skeleton.feature_dim) is not None:
                return None
            from mfm.features import features_to_joints

            return np.asarray(features_to_joints(raw[:1].astype(np.float64), skeleton))[0]
        joints = self._body_joints(raw)
        return None if check_joints(joints, self.num_joints) is not None else joints[0]

    def _scan_item_folder(self) -> tuple[list[str], list[Path]]:
        return self._scan(self.item_dir)

    @staticmethod
    def _scan(folder: Path) -> tuple[list[str], list[Path]]:
        """``(ids, ignored)``: the sorted ids of the ``<id>.npy`` files in ``folder``, and every other entry
        there (``000001.bak.npy``, ``.000001.npy``, ``notes.txt``, a subfolder)."""
        ids: list[str] = []
        ignored: list[Path] = []
        with os.scandir(folder) as entries:
            for entry in entries:
                stem = entry.name.removesuffix(".npy")
                if stem != entry.name and is_valid_key(stem) and entry.is_file():
                    ids.append(stem)
                else:
                    ignored.append(folder / entry.name)
        return sorted(ids), sorted(ignored)

    def _body_joints(self, raw: np.ndarray) -> np.ndarray:
        """(T, J, 3) from what was stored: flat (T, 3J) rows are reshaped (the reference code reshapes its
        example clip the same way); extra trailing joints beyond an accepted count are dropped."""
        joints = raw
        if joints.ndim == 2 and joints.shape[1] % 3 == 0:
            joints = joints.reshape(joints.shape[0], -1, 3)
        if joints.ndim == 3 and joints.shape[1] != self.num_joints and joints.shape[1] in self.accepted_joint_counts:
            joints = joints[:, : self.num_joints]
        return joints


class HumanML3DSource(HumanML3DLayoutSource):
    """HumanML3D (22 SMPL joints, metres, 20 fps). See the module docstring for the layout and options."""
