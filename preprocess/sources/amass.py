"""AMASS motion files (SMPL-H G ``.npz``) -> HumanML3D's 22 joints, as EricGuo5513/HumanML3D's
``raw_pose_processing`` computes them.

Each ``.npz`` holds ``poses`` (T, 156) axis-angle (root, 21 body joints, 30 hand joints), ``trans``
(T, 3), ``betas`` (16,), ``mocap_framerate`` and ``gender``. Joint positions need an SMPL-H body
model, which is licensed and cannot ship here: pass ``body_model=`` either one ``model.npz`` (used for
every clip) or a folder holding ``male/model.npz`` and ``female/model.npz`` (the ``body_models/smplh``
folder of HumanML3D's instructions: "Extended SMPL+H model used in AMASS", mano.is.tue.mpg.de). As in
HumanML3D, male clips use the male model and every other clip the female one. A body model is read as plain
numeric arrays; a pickled one (a ``.pkl``, or an ``.npz`` holding Python objects) is refused unless the option
``unpickle_body_model=true`` says the file is trusted: unpickling runs whatever code the file carries.

Joints, per frame (what human_body_prior's ``BodyModel(...).Jtr + trans`` gives for the body joints):
rest joints ``J = J_regressor @ (v_template + shapedirs . betas[:10])`` (the joints are linear in the
shape, so only ``J_regressor @ v_template`` and ``J_regressor @ shapedirs`` are kept), forward
kinematics with Rodrigues rotations along ``kintree_table``, plus ``trans``; the first 22 joints.
Axes: AMASS is Z up; HumanML3D applies ``joints @ [[1,0,0],[0,0,1],[0,1,0]]`` then negates x, i.e.
``(x, y, z) -> (-x, z, y)`` (Y up, still right-handed).

Captions (AMASS has none), option ``captions=``:

* HumanML3D's ``index.csv`` (columns ``source_path,start_frame,end_frame,new_name``): reproduces
  HumanML3D's clips. Items are the ``new_name`` ids; captions come from ``texts/<id>.txt`` and splits
  from ``train.txt``/``val.txt``/``test.txt`` (both looked up beside ``index.csv`` unless ``texts_dir``
  / ``split_dir`` say otherwise). As in raw_pose_processing the sequence is subsampled with stride
  ``int(mocap_framerate / 20)`` and called 20 fps (exact for the 60/100/120 fps captures; a 50 fps file
  gets stride 2 and plays 25 % slow, as in the published dataset), the per-dataset lead-ins are cut
  (Eyes_Japan_Dataset and MPI_HDM05 3 s, TotalCapture and MPI_Limits 1 s, Transitions_mocap 0.5 s),
  then ``[start_frame:end_frame]``. ``root`` is the ``amass_data`` folder with HumanML3D's folder
  names (``./pose_data/KIT/3/x_poses.npy`` is read from ``root/KIT/3/x_poses.npz``); the HumanAct12
  rows read HumanML3D's own ``pose_data/humanact12`` joint files from ``root/humanact12/...``.
  ``mirror=True`` adds HumanML3D's left/right mirrored copies (``M<id>``). Caption lines and split files
  are read as HumanML3D's (``humanml3d.py``): malformed caption lines are counted by reason, and an id a
  split file lists without an index row is skipped as ``missing_file`` (an ``M<id>`` only with
  ``mirror=True``; without it mirrored copies are not built, so not missing).
* A JSON file ``{"relative/path.npz": [caption, ...]}`` (a caption is a string, optionally in
  HumanML3D's ``text#tokens#from#to`` form, or ``{"text", "start", "end"}`` in seconds) or a CSV with
  columns ``path,text`` (and optionally ``start,end`` in seconds). Items are every ``.npz`` under
  ``root``; the clip keeps the capture's own frame rate (the processing stage resamples) and its split
  is a hash of its path (80/10/10). Files without captions are skipped as ``no_captions``. Spans follow
  HumanML3D's rules (an end of 0 means "to the end"); an entry with a malformed span, an empty text or another
  shape is dropped, logged and counted by reason in the clip's ``dropped_captions`` (``span_not_a_number``,
  ``span_negative``, ``span_end_not_after_start``, ``empty``, ``malformed_entry``), never fatal;
  ``caption_problems()`` lists them, and ``--strict`` stops at the first, naming the file and the entry.
"""

from __future__ import annotations

import csv
import json
import logging
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from mfm.rotations import axis_angle_to_matrix
from mfm.skeleton import HUMANML3D
from preprocess.clip import BAD_SHAPE, NO_CAPTIONS, UNREADABLE, Caption, Clip, SkippedInput, check_joints
from preprocess.sources.humanml3d import (
    EMPTY_CAPTION,
    SPAN_END_NOT_AFTER_START,
    SPAN_NEGATIVE,
    SPAN_NOT_A_NUMBER,
    SPLIT_NAMES,
    CaptionFile,
    CaptionSpanError,
    as_bool,
    as_name_list,
    check_splits,
    hash_split,
    load_caption_file,
    missing_listed_item,
    motion_id,
    parse_caption_line,
    read_split_files,
)

log = logging.getLogger(__name__)

NUM_BODY_JOINTS = HUMANML3D.num_joints  # 22: SMPL-H's body joints come first
NUM_BETAS = 10  # HumanML3D builds its body models with num_betas=10
HUMANML3D_FPS = 20
# raw_pose_processing: joints @ TRANS_MATRIX, then x negated.
TRANS_MATRIX = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
# Lead-ins raw_pose_processing cuts (in 20 fps frames) when the source path contains the name.
LEAD_IN_FRAMES = {
    "Eyes_Japan_Dataset": 3 * HUMANML3D_FPS,
    "MPI_HDM05": 3 * HUMANML3D_FPS,
    "TotalCapture": 1 * HUMANML3D_FPS,
    "MPI_Limits": 1 * HUMANML3D_FPS,
    "Transitions_mocap": int(0.5 * HUMANML3D_FPS),
}
INDEX_COLUMNS = ("source_path", "start_frame", "end_frame", "new_name")
# HumanML3D's swap_left_right for the 22 body joints.
RIGHT_CHAIN = (2, 5, 8, 11, 14, 17, 19, 21)
LEFT_CHAIN = (1, 4, 7, 10, 13, 16, 18, 20)
BODY_MODEL_HELP = (
    "AMASS joints need an SMPL-H body model: pass body_model=<path> to the 'Extended SMPL+H model used in "
    "AMASS' model.npz (male/model.npz from mano.is.tue.mpg.de, the file HumanML3D's raw_pose_processing "
    "uses), or to a folder holding male/model.npz and female/model.npz"
)


# ----------------------------------------------------------------------------------------------------
# Body model
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BodyJointModel:
    """The part of an SMPL-H model that body-joint positions depend on, for the first 22 joints:
    ``rest_joints`` (22, 3) = J_regressor @ v_template, ``joint_shapedirs`` (22, 3, B) =
    J_regressor @ shapedirs, ``parents`` (22,). A few KB, so it pickles cheaply to workers."""

    rest_joints: np.ndarray
    joint_shapedirs: np.ndarray
    parents: np.ndarray
    path: str

    def joints_at_rest(self, betas: np.ndarray) -> np.ndarray:
        b = np.zeros(self.joint_shapedirs.shape[-1])
        given = np.asarray(betas, dtype=np.float64).reshape(-1)[: b.size]
        b[: given.size] = given
        return self.rest_joints + self.joint_shapedirs @ b

    def forward(self, poses: np.ndarray, trans: np.ndarray, betas: np.ndarray) -> np.ndarray:
        """(T, 22, 3) joint positions in AMASS axes from axis-angle ``poses`` (T, >=66) and ``trans``."""
        rest = self.joints_at_rest(betas)
        frames = poses.shape[0]
        axis_angle = torch.from_numpy(np.ascontiguousarray(poses[:, : 3 * NUM_BODY_JOINTS], dtype=np.float64))
        local = axis_angle_to_matrix(axis_angle.reshape(frames, NUM_BODY_JOINTS, 3)).numpy()
        world_rot = np.empty_like(local)
        positions = np.empty((frames, NUM_BODY_JOINTS, 3))
        world_rot[:, 0] = local[:, 0]
        positions[:, 0] = rest[0]
        for joint in range(1, NUM_BODY_JOINTS):
            parent = self.parents[joint]
            world_rot[:, joint] = world_rot[:, parent] @ local[:, joint]
            positions[:, joint] = positions[:, parent] + world_rot[:, parent] @ (rest[joint] - rest[parent])
        return positions + np.asarray(trans, dtype=np.float64)[:, None, :]


UNPICKLE_OPTION = "unpickle_body_model"
UNPICKLE_RISK = (
    "unpickling runs whatever code the file carries, with your permissions, so it is never done by default. If the "
    f"file is your own copy of the licensed model from mano.is.tue.mpg.de, pass --source-option {UNPICKLE_OPTION}=true "
    "(only for a file from a source you trust), or convert it once to a plain model.npz of numeric arrays"
)


def load_body_model(path: str | Path, *, unpickle: bool = False) -> BodyJointModel:
    """Read an SMPL-H ``model.npz`` (v_template (V, 3), shapedirs (V, 3, >=10), J_regressor (52, V),
    kintree_table (2, 52)) of plain numeric arrays. Errors name the file and the key.

    Pickled models (a ``.pkl``, or an ``.npz`` whose J_regressor is a pickled scipy sparse matrix, as some
    conversions store it) are read only with ``unpickle=True`` (source option ``unpickle_body_model``): unpickling a
    file runs any code it carries, so without the opt-in such a file is refused with a ValueError naming the risk,
    before anything in it is unpickled."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"body model {path} not found. {BODY_MODEL_HELP}")
    arrays = _read_model_arrays(path, unpickle=unpickle)
    v_template = arrays["v_template"]
    shapedirs = arrays["shapedirs"]
    regressor = arrays["J_regressor"]
    kintree = arrays["kintree_table"]
    vertices = v_template.shape[0]
    if v_template.shape != (vertices, 3):
        raise ValueError(f"{path}: v_template must be (V, 3), got {v_template.shape}")
    if shapedirs.ndim != 3 or shapedirs.shape[:2] != (vertices, 3):
        raise ValueError(f"{path}: shapedirs must be ({vertices}, 3, B), got {shapedirs.shape}")
    if regressor.ndim != 2 or regressor.shape[1] != vertices or regressor.shape[0] < NUM_BODY_JOINTS:
        raise ValueError(f"{path}: J_regressor must be (>= {NUM_BODY_JOINTS}, {vertices}), got {regressor.shape}")
    if kintree.ndim != 2 or kintree.shape[0] != 2 or kintree.shape[1] < NUM_BODY_JOINTS:
        raise ValueError(f"{path}: kintree_table must be (2, >= {NUM_BODY_JOINTS}), got {kintree.shape}")
    parents = kintree[0, :NUM_BODY_JOINTS].astype(np.int64)
    parents[0] = -1  # stored as 2**32 - 1
    if any(not 0 <= parents[j] < j for j in range(1, NUM_BODY_JOINTS)):
        raise ValueError(f"{path}: kintree_table parents of the body joints are not ordered: {parents.tolist()}")
    body_regressor = regressor[:NUM_BODY_JOINTS].astype(np.float64)
    betas = min(NUM_BETAS, shapedirs.shape[2])
    return BodyJointModel(
        rest_joints=body_regressor @ v_template.astype(np.float64),
        joint_shapedirs=np.einsum("jv,vcb->jcb", body_regressor, shapedirs[:, :, :betas].astype(np.float64)),
        parents=parents,
        path=str(path),
    )


def _read_model_arrays(path: Path, *, unpickle: bool) -> dict[str, np.ndarray]:
    keys = ("v_template", "shapedirs", "J_regressor", "kintree_table")
    if path.suffix == ".npy":
        raise ValueError(f"{path}: a .npy file holds one array, not a body model. {BODY_MODEL_HELP}")
    if path.suffix == ".pkl":
        if not unpickle:
            raise ValueError(f"{path}: a .pkl body model is a Python pickle; {UNPICKLE_RISK}")
        return _read_pickled_model(path, keys)
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in keys if k not in data.files]
            if missing:
                raise ValueError(f"{path}: not an SMPL-H model.npz, missing {missing} (has {sorted(data.files)})")
            return {k: np.asarray(data[k]) for k in keys}
    except ValueError as err:
        if "allow_pickle" not in str(err):
            raise
    # Pickled content: an object array (some conversions store J_regressor as a pickled scipy sparse matrix) or a
    # pickle under an .npz name. Only on the user's explicit opt-in (see UNPICKLE_RISK).
    if not unpickle:
        raise ValueError(f"{path}: the body model holds pickled Python objects (not plain numeric arrays); "
                         f"{UNPICKLE_RISK}")
    loaded = np.load(path, allow_pickle=True)
    if not isinstance(loaded, np.lib.npyio.NpzFile):  # a pickle or .npy under another name
        raise ValueError(f"{path}: not an SMPL-H model.npz (it holds a {type(loaded).__name__}). {BODY_MODEL_HELP}")
    with loaded as data:
        missing = [k for k in keys if k not in data.files]
        if missing:
            raise ValueError(f"{path}: not an SMPL-H model.npz, missing {missing} (has {sorted(data.files)})")
        arrays = {k: np.asarray(data[k]) for k in keys}
    return _dense_arrays(arrays)


def _read_pickled_model(path: Path, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    """An SMPL/SMPL-H ``.pkl``, read only on the user's opt-in (``unpickle_body_model``: unpickling runs the code a
    file carries). The MANO site's ``SMPLH_*.pkl`` hold chumpy arrays: without the chumpy package they cannot be
    read, which is said plainly."""
    import pickle

    try:
        with open(path, "rb") as handle:
            data = pickle.load(handle, encoding="latin1")
    except ModuleNotFoundError as err:
        raise ValueError(f"{path}: this .pkl body model needs the {err.name!r} package to unpickle (the MANO site's "
                         f"SMPL-H .pkl files store chumpy arrays). Install it, or pass the AMASS 'Extended SMPL+H' "
                         f"model.npz instead. {BODY_MODEL_HELP}") from err
    except (pickle.UnpicklingError, EOFError, AttributeError) as err:
        raise ValueError(f"{path}: cannot be read as a pickled body model ({err}). {BODY_MODEL_HELP}") from err
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a pickled dict of model arrays, got {type(data).__name__}. "
                         f"{BODY_MODEL_HELP}")
    missing = [k for k in keys if k not in data]
    if missing:
        raise ValueError(f"{path}: not an SMPL-H model, missing {missing} (has {sorted(map(str, data))})")
    return _dense_arrays({k: data[k] for k in keys})


def _dense_arrays(arrays: dict) -> dict[str, np.ndarray]:
    """Plain float arrays: scipy sparse matrices (a pickled J_regressor) densified, chumpy-like objects read
    through ``np.asarray``."""
    arrays = {k: (v.toarray() if hasattr(v, "toarray") else v) for k, v in arrays.items()}
    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    for key, value in arrays.items():
        if value.dtype == object:
            value = value.item()
            arrays[key] = np.asarray(value.toarray() if hasattr(value, "toarray") else value, dtype=np.float64)
    return arrays


def to_humanml3d_axes(joints: np.ndarray) -> np.ndarray:
    """AMASS (Z up) -> HumanML3D (Y up): ``joints @ TRANS_MATRIX`` then x negated, as raw_pose_processing."""
    out = joints @ TRANS_MATRIX
    out[..., 0] *= -1
    return out


def mirror_left_right(joints: np.ndarray) -> np.ndarray:
    """HumanML3D's ``swap_left_right`` on (T, 22, 3): negate x and swap the left/right joints."""
    out = joints.copy()
    out[..., 0] *= -1
    out[:, RIGHT_CHAIN + LEFT_CHAIN] = out[:, LEFT_CHAIN + RIGHT_CHAIN]
    return out


# ----------------------------------------------------------------------------------------------------
# Caption sources
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class IndexRow:
    source_path: str
    start_frame: int
    end_frame: int


def read_index_csv(path: Path) -> dict[str, IndexRow]:
    """HumanML3D's ``index.csv``: ``{new_name without .npy: IndexRow}``."""
    rows = {}
    with path.open(newline="", encoding="utf-8") as handle:
        for number, row in enumerate(csv.DictReader(handle), start=2):
            try:
                name = Path(row["new_name"].strip()).stem
                rows[name] = IndexRow(row["source_path"].strip(), int(row["start_frame"]), int(row["end_frame"]))
            except (KeyError, ValueError, AttributeError) as err:
                raise ValueError(f"{path}:{number}: bad index row {row}: {err}") from None
    return rows


class CaptionEntryError(ValueError):
    """A caption-map entry that is neither a string nor ``{"text", "start", "end"}``; ``reason`` is its
    ``dropped_captions`` key (:data:`MALFORMED_ENTRY`)."""

    reason = "malformed_entry"


MALFORMED_ENTRY = CaptionEntryError.reason


def _span_seconds(start: object, end: object) -> tuple[float, float | None]:
    """A ``start``/``end`` pair in seconds (JSON numbers or CSV cells; absent or empty: 0 and "to the end"), read by
    HumanML3D's rules as :func:`parse_caption_line` reads ``#from#to``: NaN counts as 0, an end of 0 means "to the
    end". Raises :class:`CaptionSpanError` (not a number, negative, end not after start)."""

    def seconds(value: object) -> float:
        if value is None or (isinstance(value, str) and not value.strip()):
            return 0.0
        try:
            if isinstance(value, bool):
                raise TypeError
            number = float(value)
        except (TypeError, ValueError):
            raise CaptionSpanError(SPAN_NOT_A_NUMBER, f"span value {value!r} is not a number") from None
        if math.isinf(number):
            raise CaptionSpanError(SPAN_NOT_A_NUMBER, f"span value {value!r} is not a finite number")
        return 0.0 if math.isnan(number) else number

    first, last = seconds(start), seconds(end)
    if first < 0 or last < 0:
        raise CaptionSpanError(SPAN_NEGATIVE, f"negative span {first}..{last} s")
    if last == 0.0:
        return first, None
    if last <= first:
        raise CaptionSpanError(SPAN_END_NOT_AFTER_START, f"span end {last} s is not after its start {first} s")
    return first, last


def _caption_from_json(value: object) -> Caption | None:
    """A caption of a JSON caption map; None for an empty text. Raises :class:`CaptionSpanError` for a bad span and
    :class:`CaptionEntryError` for an entry of another shape."""
    if isinstance(value, str):
        return parse_caption_line(value)
    if isinstance(value, dict) and isinstance(value.get("text"), str):
        text = value["text"].strip()
        if not text:
            return None
        start, end = _span_seconds(value.get("start"), value.get("end"))
        return Caption(text=text, start=start, end=end)
    raise CaptionEntryError(f"a caption must be a string or {{'text', 'start', 'end'}}, got {value!r}")


def read_caption_map(path: Path) -> tuple[dict[str, CaptionFile], list[SkippedInput]]:
    """``{relative .npz path: its captions}`` from a JSON or CSV caption file (see the module docstring), and the
    caption entries dropped from it, in file order, as SkippedInput (id: the clip's id, path: the caption file,
    reason: the ``dropped_captions`` key, detail: which entry and why) for ``--strict``, which stops at the first.
    A dropped entry (malformed span, empty text, an entry of another shape) is logged and counted by reason in its
    path's ``CaptionFile.dropped``, as HumanML3D's caption lines are; a file of the wrong structure (not an object
    of lists, a CSV without path,text) is an error."""
    captions: dict[str, list[Caption]] = {}
    dropped: dict[str, dict[str, int]] = {}
    first_dropped: dict[str, str] = {}
    problems: list[SkippedInput] = []

    def drop(key: str, reason: str, where: str, why: str) -> None:
        counts = dropped.setdefault(key, {})
        counts[reason] = counts.get(reason, 0) + 1
        first_dropped.setdefault(key, f"{where}: {why}")
        problems.append(SkippedInput(motion_id(key), str(path), reason, f"{where}: {why}"))
        log.warning("%s %s: caption dropped (%s): %s", path, where, reason, why)

    if path.suffix.lower() == ".json":
        document = json.loads(path.read_text(encoding="utf-8"))
        if not isinstance(document, dict):
            raise ValueError(f"{path}: expected an object {{relative path: [captions]}}")
        for raw, values in document.items():
            if not isinstance(values, list):
                raise ValueError(f"{path}: captions of {raw!r} must be a list")
            key = _normal_relpath(raw)
            kept = captions.setdefault(key, [])
            for number, value in enumerate(values, start=1):
                where = f"entry {raw!r}, caption {number}"
                try:
                    caption = _caption_from_json(value)
                except (CaptionSpanError, CaptionEntryError) as err:
                    drop(key, err.reason, where, str(err))
                    continue
                if caption is None:
                    drop(key, EMPTY_CAPTION, where, "no caption text")
                    continue
                kept.append(caption)
    else:
        with path.open(newline="", encoding="utf-8") as handle:
            reader = csv.DictReader(handle)
            if not reader.fieldnames or not {"path", "text"} <= set(reader.fieldnames):
                raise ValueError(f"{path}: a caption CSV needs columns path,text (optionally start,end); got {reader.fieldnames}")
            for number, row in enumerate(reader, start=2):
                raw = (row["path"] or "").strip()
                key = _normal_relpath(raw)
                kept = captions.setdefault(key, [])
                where = f"line {number} ({raw!r})"
                text = (row["text"] or "").strip()
                if not text:
                    drop(key, EMPTY_CAPTION, where, "no caption text")
                    continue
                try:
                    start, end = _span_seconds(row.get("start"), row.get("end"))
                except CaptionSpanError as err:
                    drop(key, err.reason, where, str(err))
                    continue
                kept.append(Caption(text=text, start=start, end=end))
    table = {key: CaptionFile(kept, dropped.get(key, {}), first_dropped.get(key, "")) for key, kept in captions.items()}
    return table, problems


def _normal_relpath(path: str) -> str:
    """Caption-file keys compare with ``root``-relative POSIX paths: ``./a\\b.npz`` -> ``a/b.npz``."""
    return path.strip().replace("\\", "/").removeprefix("./").lstrip("/")


def _is_index_csv(path: Path) -> bool:
    if path.suffix.lower() != ".csv":
        return False
    with path.open(newline="", encoding="utf-8") as handle:
        header = next(csv.reader(handle), [])
    return set(INDEX_COLUMNS) <= {h.strip() for h in header}


# ----------------------------------------------------------------------------------------------------
# The source
# ----------------------------------------------------------------------------------------------------


class AMASSSource:
    """AMASS SMPL-H ``.npz`` files -> HumanML3D-skeleton clips (see the module docstring).

    Options: ``body_model`` (required), ``captions`` (required: index.csv, JSON or CSV), ``texts_dir``
    and ``split_dir`` (index mode; default beside index.csv), ``mirror`` (index mode, default False),
    ``splits`` (which to list), ``default_split`` (index mode: split of an id in no split file),
    ``unpickle_body_model`` (default False: a pickled body model, ``.pkl`` or an ``.npz`` holding Python objects, is
    refused, because unpickling runs the code the file carries; True reads it, for a file you trust).
    """

    name = "amass"
    skeleton = "humanml3d"

    def __init__(
        self,
        root: str | Path | None,
        *,
        body_model: str | Path | None = None,
        captions: str | Path | None = None,
        texts_dir: str | Path | None = None,
        split_dir: str | Path | None = None,
        mirror: bool | str = False,
        splits: str | list[str] | tuple[str, ...] = SPLIT_NAMES,
        default_split: str = "train",
        unpickle_body_model: bool | str = False,
    ) -> None:
        if body_model is None:
            raise ValueError(f"amass: no body model given. {BODY_MODEL_HELP}")
        if root is None:
            raise ValueError("amass: needs a root folder (--root): the AMASS amass_data folder")
        self.root = Path(root)
        if not self.root.is_dir():
            raise FileNotFoundError(f"amass: root folder {self.root} does not exist")
        self.unpickle_body_model = as_bool(unpickle_body_model)
        self.body_models = self._load_body_models(Path(body_model))
        if captions is None:
            raise ValueError(
                "amass: AMASS has no captions: pass captions=<HumanML3D index.csv> (with its texts/ folder) or a "
                "JSON/CSV file mapping each .npz path (relative to the root) to its captions"
            )
        self.captions_path = Path(captions)
        if not self.captions_path.is_file():
            raise FileNotFoundError(f"amass: caption file {self.captions_path} not found")
        self.splits = check_splits(as_name_list(splits), "amass option splits")
        (self.default_split,) = check_splits((default_split,), "amass option default_split")
        self.mirror = as_bool(mirror)
        self.index: dict[str, IndexRow] | None = None
        self.caption_map: dict[str, CaptionFile] = {}
        self._caption_problems: list[SkippedInput] = []
        self.split_of: dict[str, str] = {}
        if _is_index_csv(self.captions_path):
            self.index = read_index_csv(self.captions_path)
            self.texts_dir = Path(texts_dir) if texts_dir else self.captions_path.parent / "texts"
            self.split_of = read_split_files(Path(split_dir) if split_dir else self.captions_path.parent)
            if not self.texts_dir.is_dir():
                raise FileNotFoundError(f"amass: caption folder {self.texts_dir} (HumanML3D's texts/) not found")
        else:
            if self.mirror:
                raise ValueError("amass: mirror=True needs HumanML3D's index.csv (its M<id> captions swap left and right)")
            self.caption_map, self._caption_problems = read_caption_map(self.captions_path)

    def _load_body_models(self, path: Path) -> dict[str, BodyJointModel]:
        """``{"male": model, "female": model}``; one file serves both."""
        if path.is_dir():
            needed = {gender: path / gender / "model.npz" for gender in ("male", "female")}
            missing = [str(p) for p in needed.values() if not p.is_file()]
            if missing:
                raise FileNotFoundError(f"amass: body model folder {path} lacks {missing}. {BODY_MODEL_HELP}")
            return {gender: load_body_model(p, unpickle=self.unpickle_body_model) for gender, p in needed.items()}
        model = load_body_model(path, unpickle=self.unpickle_body_model)
        return {"male": model, "female": model}

    # -- protocol ------------------------------------------------------------------------------------

    def list_items(self) -> list[str]:
        if self.index is not None:
            ids = sorted(self.index)
            if self.mirror:
                ids = sorted(ids + [f"M{i}" for i in ids])
            chosen = {i for i in ids if self.split_of.get(i, self.default_split) in self.splits}
            # Every id the asked split files list is an item (one without an index row is a missing_file skip),
            # except the mirrored copies that mirror=False deliberately leaves out.
            listed = {i for i, split in self.split_of.items() if split in self.splits and not self._unmirrored(i)}
            return sorted(chosen | listed)
        paths = sorted(p.relative_to(self.root).as_posix() for p in self.root.rglob("*.npz"))
        unmatched = sorted(set(self.caption_map) - set(paths))
        if unmatched:
            log.warning(
                "amass: %d captioned paths in %s have no .npz under %s (e.g. %s)",
                len(unmatched), self.captions_path, self.root, unmatched[:3],
            )
        return [p for p in paths if hash_split(p) in self.splits]

    def caption_problems(self) -> list[SkippedInput]:
        """The entries of a JSON/CSV caption file that were dropped (a malformed span, an empty text, another
        shape), in file order: each is counted in its clip's ``dropped_captions``; ``--strict`` stops at the first,
        naming the file and the entry. Index mode reads HumanML3D's caption files clip by clip: none here."""
        return list(self._caption_problems)

    def load(self, item: str) -> Clip | SkippedInput:
        if self.index is not None:
            return self._load_indexed(item)
        return self._load_captioned_file(item)

    # -- index.csv mode ------------------------------------------------------------------------------

    def _unmirrored(self, item: str) -> bool:
        """An ``M<id>`` mirrored copy of an indexed id, not built because mirror=False."""
        return not self.mirror and item.startswith("M") and item[1:] in self.index

    def _load_indexed(self, item: str) -> Clip | SkippedInput:
        mirrored = self.mirror and item.startswith("M") and item[1:] in self.index
        if not mirrored and item not in self.index:
            return missing_listed_item(item, self.split_of.get(item), self.captions_path,
                                       f"{self.captions_path.name} has no row for {item}.npy")
        row = self.index[item[1:] if mirrored else item]
        captions = load_caption_file(self.texts_dir / f"{item}.txt", item)
        if isinstance(captions, SkippedInput):
            return captions
        relative = row.source_path.replace("\\", "/").removeprefix("./").removeprefix("pose_data/")
        if "humanact12" in relative:
            # HumanML3D ships these as joints already in its axes at 20 fps: used uncut, as it does.
            path = self.root / relative
            joints = _read_joint_file(path)
        else:
            path = self.root / (relative[: -len(".npy")] + ".npz" if relative.endswith(".npy") else relative)
            joints = self._indexed_amass_joints(path, row)
        if isinstance(joints, SkippedInput):
            return replace(joints, id=item)
        if mirrored:
            joints = mirror_left_right(joints)
        split = self.split_of.get(item, self.default_split)
        return self._clip(item, joints, float(HUMANML3D_FPS), path, captions.captions, split, captions.dropped)

    def _indexed_amass_joints(self, path: Path, row: IndexRow) -> np.ndarray | SkippedInput:
        motion = _read_motion(path)
        if isinstance(motion, SkippedInput):
            return motion
        poses, trans, betas, fps, gender = motion
        stride = max(1, int(fps / HUMANML3D_FPS))
        lead_in = sum(frames for name, frames in LEAD_IN_FRAMES.items() if name in row.source_path)
        keep = np.arange(0, poses.shape[0], stride)[lead_in:][row.start_frame : row.end_frame]
        if keep.size == 0:
            return SkippedInput("", str(path), BAD_SHAPE, f"index rows {row.start_frame}:{row.end_frame} select no frame")
        model = self.body_models["male" if gender == "male" else "female"]
        return to_humanml3d_axes(model.forward(poses[keep], trans[keep], betas))

    # -- JSON/CSV caption mode -----------------------------------------------------------------------

    def _load_captioned_file(self, item: str) -> Clip | SkippedInput:
        path = self.root / item
        clip_id = motion_id(item)
        entry = self.caption_map.get(item)
        if entry is None:
            return SkippedInput(clip_id, str(path), NO_CAPTIONS, f"no entry in {self.captions_path}")
        if not entry.captions:
            counts = ", ".join(f"{n} {reason}" for reason, n in sorted(entry.dropped.items()))
            why = f" ({counts}; {entry.first_dropped})" if counts else ": its entry lists none"
            return SkippedInput(clip_id, str(path), NO_CAPTIONS, f"no usable caption in {self.captions_path}{why}")
        motion = _read_motion(path)
        if isinstance(motion, SkippedInput):
            return replace(motion, id=clip_id)
        poses, trans, betas, fps, gender = motion
        model = self.body_models["male" if gender == "male" else "female"]
        joints = to_humanml3d_axes(model.forward(poses, trans, betas))
        return self._clip(clip_id, joints, fps, path, entry.captions, hash_split(item), entry.dropped)

    # -- shared --------------------------------------------------------------------------------------

    def _clip(
        self, clip_id: str, joints: np.ndarray, fps: float, path: Path, captions: list[Caption], split: str,
        dropped_captions: dict[str, int] | None = None,
    ) -> Clip | SkippedInput:
        problem = check_joints(joints, NUM_BODY_JOINTS)
        if problem is not None:
            return SkippedInput(clip_id, str(path), *problem)
        return Clip(
            id=clip_id,
            joints=joints.astype(np.float32),
            fps=fps,
            skeleton=self.skeleton,
            captions=captions,
            split=split,
            source=self.name,
            path=str(path),
            dropped_captions=dict(dropped_captions or {}),
        )


def _read_motion(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, str] | SkippedInput:
    """``(poses, trans, betas, fps, gender)`` of an AMASS ``.npz``, or why it cannot be used."""
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: np.asarray(data[key]) for key in ("poses", "trans")}
            if "betas" in data.files:
                arrays["betas"] = np.asarray(data["betas"])
            complex_keys = [f"{key} ({value.dtype})" for key, value in arrays.items() if np.iscomplexobj(value)]
            if complex_keys:  # a cast to float64 would silently drop the imaginary part
                return SkippedInput("", str(path), BAD_SHAPE,
                                    f"complex-valued {', '.join(complex_keys)}: AMASS motion must be real numbers")
            poses = arrays["poses"].astype(np.float64)
            trans = arrays["trans"].astype(np.float64)
            betas = arrays["betas"].astype(np.float64) if "betas" in arrays else np.zeros(NUM_BETAS)
            rate_key = "mocap_framerate" if "mocap_framerate" in data.files else "mocap_frame_rate"
            fps = float(data[rate_key])
            gender = _decode_gender(data["gender"]) if "gender" in data.files else "neutral"
    except Exception as err:  # any failure to read is a skip, never a crash of the worker
        return SkippedInput("", str(path), UNREADABLE, f"{type(err).__name__}: {err}")
    if poses.ndim != 2 or poses.shape[1] < 3 * NUM_BODY_JOINTS or trans.shape != (poses.shape[0], 3):
        return SkippedInput("", str(path), BAD_SHAPE, f"poses {poses.shape} / trans {trans.shape}: expected (T, >=66) / (T, 3)")
    if not (math.isfinite(fps) and fps > 0):
        return SkippedInput("", str(path), BAD_SHAPE, f"mocap frame rate {fps!r} is not a positive number")
    return poses, trans, betas, fps, gender


def _decode_gender(value: np.ndarray) -> str:
    item = np.asarray(value).reshape(-1)[0] if np.asarray(value).size else ""
    text = item.decode("utf-8") if isinstance(item, bytes) else str(item)
    return text.strip().lower()


def _read_joint_file(path: Path) -> np.ndarray | SkippedInput:
    try:
        joints = np.load(path, allow_pickle=False)
    except Exception as err:
        return SkippedInput("", str(path), UNREADABLE, f"{type(err).__name__}: {err}")
    if joints.ndim == 3 and joints.shape[1] >= NUM_BODY_JOINTS:
        joints = joints[:, :NUM_BODY_JOINTS]
    return joints
