"""HumanML3D-layout datasets (HumanML3D itself; KIT-ML reuses the reader, see ``kit.py``), and the
HumanML3D conventions the other sources share: caption files, split files, motion ids and the checks
every joint array goes through.

Layout (EricGuo5513/HumanML3D)::

    ROOT/
      new_joints/<id>.npy     (T, 22, 3) float32, metres, Y up, 20 fps (the retargeted joints; or
      joints/<id>.npy          raw_pose_processing's output, (T, 52, 3) SMPL-H joints of which the first
                               22 are the body, exactly as motion_representation reads them)
      texts/<id>.txt          one caption a line: ``caption#tok1/POS tok2/POS ...#from#to``
      train.txt val.txt test.txt   ids, one a line

``from``/``to`` are seconds into the clip. As in HumanML3D's own loader, ``0.0#0.0`` (or NaN) means the
whole clip and anything else a sub-clip ``[from, to)``; ``to = 0`` with ``from > 0`` (which HumanML3D's
loader turns into an empty clip) is read here as "from ``from`` to the end". A line whose span is not a
number, negative, or ends before it starts, and a line with tags but no text, is dropped and counted by
reason (``Clip.dropped_captions``, then the skip report's ``dropped_captions``).

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
from preprocess.processing import is_valid_key

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


def hash_split(key: str, val_fraction: float = 0.1, test_fraction: float = 0.1) -> str:
    """A split that depends only on ``key`` (sha256, not Python's salted ``hash``), so it is the same on
    every machine and run: roughly (1 - val - test) train, val, test."""
    u = int.from_bytes(hashlib.sha256(key.encode("utf-8")).digest()[:8], "big") / 2**64
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
    """The captions of a HumanML3D ``texts/<id>.txt`` file; lines with a malformed span are dropped, counted
    and logged (file:line). Raises OSError/UnicodeDecodeError if the file cannot be read."""
    captions: list[Caption] = []
    dropped: dict[str, int] = {}
    first = ""
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if not line.strip():
            continue
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


class HumanML3DLayoutSource:
    """Joint files + caption files + split files in HumanML3D's layout (see the module docstring).

    Options: ``joints_dir`` ('new_joints' or 'joints'; default: whichever exists, new_joints first),
    ``splits`` (which splits to list, default all three), ``default_split`` (the split of an id in no
    split file, default 'train'). Subclasses set the dataset constants below.
    """

    name: str = "humanml3d"
    skeleton: str = "humanml3d"
    fps: float = 20.0
    num_joints: int = 22
    # Joint counts accepted in the joint files; more than ``num_joints`` means "the body joints come
    # first" (raw_pose_processing saves all 52 SMPL-H joints and motion_representation keeps [:22]).
    accepted_joint_counts: tuple[int, ...] = (22, 52)
    joints_dir_names: tuple[str, ...] = ("new_joints", "joints")
    # Clips whose frame 0 defines the target skeleton when the skeleton has no built-in bone lengths.
    reference_clip_ids: tuple[str, ...] = ()

    def __init__(
        self,
        root: str | Path | None,
        *,
        joints_dir: str | None = None,
        splits: str | Sequence[str] = SPLIT_NAMES,
        default_split: str = "train",
    ) -> None:
        if root is None:
            raise ValueError(f"source {self.name!r} needs a root folder (--root) in HumanML3D's layout")
        self.root = Path(root)
        if not self.root.is_dir():
            raise FileNotFoundError(f"{self.name}: root folder {self.root} does not exist")
        self.joints_dir = self._find_joints_dir(joints_dir)
        self.texts_dir = self.root / "texts"
        self.splits = check_splits(as_name_list(splits), f"{self.name} option splits")
        (self.default_split,) = check_splits((default_split,), f"{self.name} option default_split")
        # Read once here (cheap) rather than per item: workers receive it with the pickled source.
        self.split_of = read_split_files(self.root)

    def _find_joints_dir(self, requested: str | None) -> Path:
        candidates = (requested,) if requested else self.joints_dir_names
        for candidate in candidates:
            if (self.root / candidate).is_dir():
                return self.root / candidate
        raise FileNotFoundError(
            f"{self.name}: no joint folder {' or '.join(candidates)} under {self.root} "
            f"(expected HumanML3D's layout: <root>/new_joints/<id>.npy, <root>/texts/<id>.txt)"
        )

    # -- protocol ------------------------------------------------------------------------------------

    def list_items(self) -> list[str]:
        """The ids of the joint files in the asked splits, and every id those split files list (an absent
        joint file is the item's skip, ``missing_file``)."""
        ids = {i for i in self._scan_joint_folder()[0] if self.split_of.get(i, self.default_split) in self.splits}
        listed = {i for i, split in self.split_of.items() if split in self.splits}
        return sorted(ids | listed)

    def ignored_files(self) -> list[str]:
        """Entries of the joint folder that are not ``<id>.npy`` files, so never read (for the skip report)."""
        return [str(path) for path in self._scan_joint_folder()[1]]

    def load(self, item: str) -> Clip | SkippedInput:
        path = self.joints_dir / f"{item}.npy"
        clip_id = motion_id(item)
        if not is_valid_key(item):
            split = self.split_of.get(item)
            return missing_listed_item(item, split, self.root / f"{split}.txt" if split else path,
                                       f"{item!r} is not a file name of the layout (<id>.npy, id in [A-Za-z0-9_-])")
        if not path.is_file():
            return missing_listed_item(item, self.split_of.get(item), path,
                                       f"there is no joint file {self.joints_dir.name}/{item}.npy")
        try:
            raw = np.load(path, allow_pickle=False)
        except Exception as err:  # any failure to read is a skip, never a crash of the worker
            return SkippedInput(clip_id, str(path), UNREADABLE, f"{type(err).__name__}: {err}")
        joints = self._body_joints(raw)
        problem = check_joints(joints, self.num_joints)
        if problem is not None:
            return SkippedInput(clip_id, str(path), *problem)

        captions = load_caption_file(self.texts_dir / f"{item}.txt", clip_id)
        if isinstance(captions, SkippedInput):
            return captions

        return Clip(
            id=clip_id,
            joints=joints.astype(np.float32, copy=False),
            fps=self.fps,
            skeleton=self.skeleton,
            captions=captions.captions,
            split=self.split_of.get(item, self.default_split),
            source=self.name,
            path=str(path),
            dropped_captions=dict(captions.dropped),
        )

    def target_skeleton(self) -> Skeleton:
        """The skeleton every clip is retargeted to: the built-in one when it has bone lengths, else
        measured on frame 0 of the first reference clip present (``reference_clip_ids``), falling back to
        the first listed clip. Files in ``new_joints/`` are already retargeted, so any of them gives the
        target lengths."""
        skeleton = get_skeleton(self.skeleton)
        if skeleton.bone_lengths is not None:
            return skeleton
        present = [i for i in self.reference_clip_ids if (self.joints_dir / f"{i}.npy").is_file()]
        on_disk = [i for i in self.list_items() if is_valid_key(i) and (self.joints_dir / f"{i}.npy").is_file()]
        for item in present + on_disk[:1]:
            loaded = self.load(item)
            if isinstance(loaded, Clip):
                log.info("%s: target skeleton measured on %s", self.name, loaded.path)
                return skeleton.with_bone_lengths_from(loaded.joints[0])
        raise FileNotFoundError(
            f"{self.name}: no readable clip in {self.joints_dir} to measure the target skeleton on "
            f"(the reference code uses {self.reference_clip_ids or 'a reference clip'})"
        )

    # -- helpers ---------------------------------------------------------------------------------------

    def _scan_joint_folder(self) -> tuple[list[str], list[Path]]:
        """``(ids, ignored)``: the sorted ids of the ``<id>.npy`` files in the joint folder, and every other
        entry there (``000001.bak.npy``, ``.000001.npy``, ``notes.txt``, a subfolder)."""
        ids: list[str] = []
        ignored: list[Path] = []
        with os.scandir(self.joints_dir) as entries:
            for entry in entries:
                stem = entry.name.removesuffix(".npy")
                if stem != entry.name and is_valid_key(stem) and entry.is_file():
                    ids.append(stem)
                else:
                    ignored.append(self.joints_dir / entry.name)
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
