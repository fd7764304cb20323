"""Data sources: HumanML3D/KIT layouts (including bad input), AMASS with a fake body model, the real
DeepMimic clips, the synthetic generator, and the registry."""

from __future__ import annotations

import json
import math
import pickle
import sys
from pathlib import Path

import numpy as np
import pytest

from mfm.skeleton import HUMANML3D, KIT
from preprocess.clip import Caption, Clip, SkippedInput
from preprocess.sources import SOURCES, Source, build_source
from preprocess.sources.amass import (
    TRANS_MATRIX,
    AMASSSource,
    load_body_model,
    mirror_left_right,
    to_humanml3d_axes,
)
from preprocess.sources.humanml3d import hash_split, motion_id, parse_caption_line
from preprocess.sources.synthetic import ACTIONS, CORRUPTIONS, SyntheticSource

RNG = np.random.default_rng(0)


def bone_lengths(joints: np.ndarray, parents: np.ndarray) -> np.ndarray:
    return np.linalg.norm(joints[:, 1:] - joints[:, parents[1:]], axis=-1)


def facing(joints: np.ndarray) -> np.ndarray:
    """(T, 3) unit forward direction on the floor, as HumanML3D computes it (hips + shoulders)."""
    r_hip, l_hip, r_sh, l_sh = HUMANML3D.face_joints
    across = joints[:, r_hip] - joints[:, l_hip] + joints[:, r_sh] - joints[:, l_sh]
    forward = np.cross(np.array([0.0, 1.0, 0.0]), across)
    forward[:, 1] = 0
    return forward / np.linalg.norm(forward, axis=-1, keepdims=True)


def turned_degrees(joints: np.ndarray) -> float:
    """Total turn over the clip, degrees, positive = to the performer's left (counter-clockwise from above)."""
    f = facing(joints)
    return float(np.degrees(np.unwrap(np.arctan2(f[:, 0], f[:, 2]))[-1] - np.arctan2(f[0, 0], f[0, 2])))


# ----------------------------------------------------------------------------------------------------
# HumanML3D / KIT layout
# ----------------------------------------------------------------------------------------------------


def walking_joints(frames: int, num_joints: int, scale: float = 1.0) -> np.ndarray:
    base = RNG.normal(size=(1, num_joints, 3)) * 0.3 * scale
    drift = np.linspace(0, 1, frames)[:, None, None] * np.array([0.0, 0.0, 1.0]) * scale
    return (base + drift).astype(np.float32)


def write_layout(root: Path, joints: dict[str, np.ndarray | bytes], texts: dict[str, str], splits: dict[str, list[str]], folder: str = "new_joints") -> Path:
    (root / folder).mkdir(parents=True)
    (root / "texts").mkdir()
    for clip_id, data in joints.items():
        path = root / folder / f"{clip_id}.npy"
        if isinstance(data, bytes):
            path.write_bytes(data)
        else:
            np.save(path, data)
    for clip_id, text in texts.items():
        (root / "texts" / f"{clip_id}.txt").write_text(text, encoding="utf-8")
    for split, ids in splits.items():
        (root / f"{split}.txt").write_text("".join(f"{i}\n" for i in ids))
    return root


GOOD_TEXT = (
    "a person walks forward.#a/DET person/NOUN walk/VERB forward/ADV#0.0#0.0\n"
    "someone strolls ahead#someone/PRON stroll/VERB ahead/ADV#nan#nan\n"
    "then turns left#then/ADV turn/VERB left/ADV#1.5#3.0\n"
)


@pytest.fixture
def humanml3d_root(tmp_path: Path) -> Path:
    nan_clip = walking_joints(60, 22)
    nan_clip[10:12, 4] = np.nan
    inf_clip = walking_joints(60, 22)
    inf_clip[0, 0, 1] = np.inf
    joints = {
        "000001": walking_joints(80, 22),
        "000002": walking_joints(120, 22),
        "000003": walking_joints(5, 22),  # too short for training: the source still delivers it
        "000004": walking_joints(400, 22),  # too long: likewise
        "000005": nan_clip,
        "000006": inf_clip,
        "000007": walking_joints(60, 21),
        "000008": walking_joints(60, 22)[:, :, :2].copy(),
        "000009": b"this is not a numpy file",
        "000010": walking_joints(60, 22),  # no caption file
        "000011": walking_joints(60, 22),  # only empty captions
        "000012": walking_joints(60, 22),  # in no split file
        "M000001": walking_joints(80, 22),
    }
    texts = {i: GOOD_TEXT for i in joints if i not in ("000010", "000011")}
    texts["000011"] = "#\n   #x/X#0.0#0.0\n\n"
    splits = {"train": ["000001", "000003", "000004", "000005", "000006", "000007", "000008", "000009", "000010", "000011", "M000001"], "val": ["000002"], "test": []}
    return write_layout(tmp_path / "HumanML3D", joints, texts, splits)


def test_parse_caption_line() -> None:
    whole = parse_caption_line("a man kicks.#a/DET man/NOUN kick/VERB#0.0#0.0")
    assert whole == Caption("a man kicks.", ("a/DET", "man/NOUN", "kick/VERB"), 0.0, None)
    assert parse_caption_line("x#x/X#nan#nan") == Caption("x", ("x/X",), 0.0, None)
    assert parse_caption_line("x#x/X#1.5#3.25") == Caption("x", ("x/X",), 1.5, 3.25)
    assert parse_caption_line("x#x/X#1.0#0.0") == Caption("x", ("x/X",), 1.0, None)
    assert parse_caption_line("plain text only") == Caption("plain text only")
    assert parse_caption_line("#x/X#0#0") is None
    with pytest.raises(ValueError):
        parse_caption_line("x#x/X#3.0#1.0")


def test_humanml3d_good_clips(humanml3d_root: Path) -> None:
    source = build_source("humanml3d", str(humanml3d_root))
    items = source.list_items()
    assert items == sorted(items) and "000012" in items and len(items) == 13
    clip = source.load("000001")
    assert isinstance(clip, Clip)
    assert clip.joints.shape == (80, 22, 3) and clip.joints.dtype == np.float32
    assert (clip.fps, clip.skeleton, clip.source, clip.split) == (20.0, "humanml3d", "humanml3d", "train")
    np.testing.assert_array_equal(clip.joints, np.load(humanml3d_root / "new_joints" / "000001.npy"))
    assert [(c.text, c.start, c.end) for c in clip.captions] == [
        ("a person walks forward.", 0.0, None), ("someone strolls ahead", 0.0, None), ("then turns left", 1.5, 3.0)
    ]
    assert clip.captions[0].tokens[:2] == ("a/DET", "person/NOUN")
    assert source.load("000002").split == "val"
    assert source.load("000012").split == "train"  # in no split file: the default split
    assert build_source("humanml3d", str(humanml3d_root), default_split="test").load("000012").split == "test"
    assert build_source("humanml3d", str(humanml3d_root), splits="val").list_items() == ["000002"]
    assert build_source("humanml3d", str(humanml3d_root), splits=["val", "test"], default_split="test").list_items() == ["000002", "000012"]


def test_humanml3d_bad_input_is_skipped_with_reasons(humanml3d_root: Path) -> None:
    source = build_source("humanml3d", str(humanml3d_root))
    expected = {
        "000005": "nan_frames", "000006": "nan_frames", "000007": "bad_shape", "000008": "bad_shape",
        "000009": "unreadable", "000010": "no_captions", "000011": "no_captions",
    }
    for item, reason in expected.items():
        result = source.load(item)
        assert isinstance(result, SkippedInput), item
        assert (result.id, result.reason) == (item, reason)
        assert result.path and result.detail
    # Length is the processing stage's business: short and long clips pass the source.
    assert source.load("000003").joints.shape[0] == 5
    assert source.load("000004").joints.shape[0] == 400


def test_humanml3d_raw_joints_folder_keeps_the_22_body_joints(tmp_path: Path) -> None:
    smplh = walking_joints(50, 52)
    root = write_layout(tmp_path / "h", {"000001": smplh, "000002": smplh.reshape(50, -1)}, {"000001": GOOD_TEXT, "000002": GOOD_TEXT}, {}, folder="joints")
    source = build_source("humanml3d", str(root))
    assert source.joints_dir.name == "joints"
    np.testing.assert_array_equal(source.load("000001").joints, smplh[:, :22])
    np.testing.assert_array_equal(source.load("000002").joints, smplh[:, :22])
    with pytest.raises(FileNotFoundError, match="new_joints"):
        build_source("humanml3d", str(root), joints_dir="new_joints")


def test_kit_layout_and_target_skeleton(tmp_path: Path) -> None:
    reference = walking_joints(40, 21, scale=1000.0)
    root = write_layout(
        tmp_path / "KIT-ML",
        {"03950": reference, "00001": walking_joints(30, 21, 1000.0), "00002": walking_joints(30, 22, 1000.0)},
        {"03950": GOOD_TEXT, "00001": GOOD_TEXT, "00002": GOOD_TEXT},
        {"train": ["03950", "00001"], "test": ["00002"]},
    )
    source = build_source("kit", str(root))
    clip = source.load("00001")
    assert (clip.skeleton, clip.fps, clip.source, clip.joints.shape) == ("kit", 12.5, "kit", (30, 21, 3))
    assert source.load("00002").reason == "bad_shape"  # 22 joints in a KIT folder
    target = source.target_skeleton()
    np.testing.assert_allclose(target.bone_lengths, KIT.with_bone_lengths_from(reference[0]).bone_lengths)


# The HumanML3D reader serves KIT too: each bad-input case runs on both.
LAYOUTS = [("humanml3d", 22, "000001"), ("kit", 21, "00001")]
MALFORMED_SPANS = (
    "not a number#t/X#abc#2.0\n"
    "end before start#t/X#5.0#2.0\n"
    "negative start#t/X#-1#2\n"
)


@pytest.mark.parametrize("name, num_joints, clip_id", LAYOUTS)
def test_malformed_caption_spans_are_counted_by_reason(tmp_path: Path, name: str, num_joints: int, clip_id: str) -> None:
    root = write_layout(tmp_path / name, {clip_id: walking_joints(60, num_joints)},
                        {clip_id: GOOD_TEXT + MALFORMED_SPANS + "   #x/X#0.0#0.0\n\n"}, {})
    clip = build_source(name, str(root)).load(clip_id)
    assert isinstance(clip, Clip) and len(clip.captions) == 3
    assert clip.dropped_captions == {"span_end_not_after_start": 1, "span_negative": 1, "span_not_a_number": 1,
                                     "empty": 1}  # a blank line is no caption; "#tokens" without text is


@pytest.mark.parametrize("name, num_joints, clip_id", LAYOUTS)
def test_clip_whose_only_caption_is_malformed_says_why(tmp_path: Path, name: str, num_joints: int, clip_id: str) -> None:
    root = write_layout(tmp_path / name, {clip_id: walking_joints(60, num_joints)}, {clip_id: "a man runs#t/X#5.0#2.0\n"}, {})
    skipped = build_source(name, str(root)).load(clip_id)
    assert isinstance(skipped, SkippedInput) and skipped.reason == "no_captions"
    assert skipped.path.endswith(f"texts/{clip_id}.txt")
    assert "span_end_not_after_start" in skipped.detail and "line 1" in skipped.detail and "empty" not in skipped.detail


@pytest.mark.parametrize("name, num_joints, clip_id", LAYOUTS)
def test_split_ids_without_a_joint_file_are_skipped_with_a_reason(tmp_path: Path, name: str, num_joints: int, clip_id: str) -> None:
    absent = "0" + clip_id[:-1] + "9"
    root = write_layout(tmp_path / name, {clip_id: walking_joints(60, num_joints)}, {clip_id: GOOD_TEXT},
                        {"train": [clip_id], "test": [absent, "../escape"]})
    source = build_source(name, str(root))
    assert source.list_items() == sorted([clip_id, absent, "../escape"])
    assert build_source(name, str(root), splits="train").list_items() == [clip_id]  # only the splits asked for
    skipped = source.load(absent)
    assert isinstance(skipped, SkippedInput) and (skipped.id, skipped.reason) == (absent, "missing_file")
    assert skipped.path == str(root / "new_joints" / f"{absent}.npy") and "test.txt" in skipped.detail
    escape = source.load("../escape")  # never read outside the joint folder
    assert isinstance(escape, SkippedInput) and escape.reason == "missing_file" and "not a file name" in escape.detail


@pytest.mark.parametrize("name, num_joints, clip_id", LAYOUTS)
def test_ids_come_only_from_exact_joint_file_names(tmp_path: Path, name: str, num_joints: int, clip_id: str) -> None:
    joints = walking_joints(60, num_joints)
    root = write_layout(tmp_path / name, {clip_id: joints, f"M{clip_id}": joints, f"{clip_id}.bak": joints,
                                          f"{clip_id} copy": joints, f".{clip_id}": joints},
                        {clip_id: GOOD_TEXT, f"M{clip_id}": GOOD_TEXT}, {"train": [clip_id]})
    (root / "new_joints" / "notes.txt").write_text("stray")
    (root / "new_joints" / "old").mkdir()
    source = build_source(name, str(root))
    assert source.list_items() == [clip_id, f"M{clip_id}"]
    folder = root / "new_joints"
    assert source.ignored_files() == [str(folder / n) for n in
                                      sorted([f".{clip_id}.npy", f"{clip_id} copy.npy", f"{clip_id}.bak.npy", "notes.txt", "old"])]
    assert {source.load(i).id for i in source.list_items()} == {clip_id, f"M{clip_id}"}


@pytest.mark.parametrize("name, num_joints, clip_id", LAYOUTS)
def test_complex_joint_arrays_are_refused(tmp_path: Path, name: str, num_joints: int, clip_id: str) -> None:
    root = write_layout(tmp_path / name, {clip_id: walking_joints(60, num_joints) * (1 + 1j)}, {clip_id: GOOD_TEXT}, {})
    skipped = build_source(name, str(root)).load(clip_id)
    assert isinstance(skipped, SkippedInput) and skipped.reason == "bad_shape"
    assert skipped.path == str(root / "new_joints" / f"{clip_id}.npy") and "complex" in skipped.detail


# ----------------------------------------------------------------------------------------------------
# AMASS with a fake SMPL-H body model
# ----------------------------------------------------------------------------------------------------

SMPLH_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19] + [
    parent for hand in (20, 21) for _ in range(5) for parent in (hand, -2, -2)
]


def smplh_kintree() -> np.ndarray:
    parents = []
    for joint, parent in enumerate(SMPLH_PARENTS):
        parents.append(joint - 1 if parent == -2 else parent)  # finger segments chain to the previous one
    table = np.array([parents, list(range(52))], dtype=np.int64)
    table[0, 0] = 2**32 - 1  # as stored in the real files
    return table


def write_body_model(path: Path, offset: float = 0.0, vertices: int = 60) -> Path:
    rng = np.random.default_rng(1)
    regressor = rng.random((52, vertices))
    regressor /= regressor.sum(axis=1, keepdims=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(
        path,
        v_template=rng.normal(size=(vertices, 3)) + offset,
        shapedirs=rng.normal(size=(vertices, 3, 16)) * 0.01,
        J_regressor=regressor,
        kintree_table=smplh_kintree(),
        f=np.zeros((4, 3), dtype=np.int64),
    )
    return path


def expected_rest_joints(model_path: Path, betas: np.ndarray) -> np.ndarray:
    data = np.load(model_path)
    shaped = data["v_template"] + data["shapedirs"][:, :, :10] @ betas[:10]
    return (data["J_regressor"] @ shaped)[:22]


def write_motion(path: Path, poses: np.ndarray, trans: np.ndarray, fps: float = 60.0, gender: str = "male", betas: np.ndarray | None = None) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, poses=poses, trans=trans, betas=np.zeros(16) if betas is None else betas, mocap_framerate=np.array(fps), gender=np.array(gender))
    return path


def test_amass_needs_a_body_model(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"model\.npz.*mano\.is\.tue\.mpg\.de"):
        build_source("amass", str(tmp_path), captions=str(tmp_path / "c.json"))
    with pytest.raises(FileNotFoundError, match="not found"):
        build_source("amass", str(tmp_path), body_model=str(tmp_path / "missing.npz"), captions="x")
    bad = tmp_path / "bad.npz"
    np.savez(bad, v_template=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="missing"):
        load_body_model(bad)
    one_array = tmp_path / "model.npy"
    np.save(one_array, np.zeros(3))
    with pytest.raises(ValueError, match=r"model\.npy: a \.npy file holds one array, not a body model"):
        load_body_model(one_array)


def test_amass_reads_a_pickled_body_model_or_says_what_it_needs(tmp_path: Path) -> None:
    import pickle
    import sys
    import types

    npz = write_body_model(tmp_path / "model.npz")
    with np.load(npz) as data:
        arrays = {k: data[k] for k in data.files}
    as_pickle = tmp_path / "SMPLH_male.pkl"
    as_pickle.write_bytes(pickle.dumps(arrays))
    from_pickle, from_npz = load_body_model(as_pickle, unpickle=True), load_body_model(npz)
    np.testing.assert_array_equal(from_pickle.rest_joints, from_npz.rest_joints)
    np.testing.assert_array_equal(from_pickle.parents, from_npz.parents)
    # The MANO site's .pkl files hold chumpy objects: without that package, a clear message, not a TypeError
    fake = types.ModuleType("chumpy")

    class Ch:
        pass

    Ch.__module__, Ch.__qualname__ = "chumpy", "Ch"
    fake.Ch = Ch
    sys.modules["chumpy"] = fake
    try:
        needs_chumpy = pickle.dumps({**arrays, "v_template": Ch()})
    finally:
        del sys.modules["chumpy"]
    chumpy_file = tmp_path / "SMPLH_female.pkl"
    chumpy_file.write_bytes(needs_chumpy)
    with pytest.raises(ValueError, match=r"SMPLH_female\.pkl: this \.pkl body model needs the 'chumpy' package"):
        load_body_model(chumpy_file, unpickle=True)
    renamed = tmp_path / "renamed.npz"
    renamed.write_bytes(pickle.dumps(arrays))  # a pickle under an .npz name
    with pytest.raises(ValueError, match=r"renamed\.npz: not an SMPL-H model\.npz \(it holds a dict\)"):
        load_body_model(renamed, unpickle=True)


class _SparseLike:
    """Stands in for a pickled scipy sparse J_regressor (what some body-model conversions store)."""

    def __init__(self, dense: np.ndarray) -> None:
        self.dense = dense

    def toarray(self) -> np.ndarray:
        return self.dense


class _RunsCode:
    """A pickle payload that, unpickled, creates the file its constructor names: proof that code ran."""

    def __init__(self, proof: Path) -> None:
        self.proof = proof

    def __reduce__(self):
        return (Path.touch, (self.proof,))


def test_a_pickled_body_model_is_refused_unless_the_user_opts_in(tmp_path: Path) -> None:
    """Issue 24, finding 6: an AMASS --body-model .npz with an object array was loaded with allow_pickle=True as a
    fallback, and its pickle ran code. Now nothing is unpickled without unpickle_body_model=true, and the refusal
    names the file, the risk and the opt-in."""
    import pickle

    npz = write_body_model(tmp_path / "model.npz")
    with np.load(npz) as data:
        arrays = {k: data[k] for k in data.files}
    proof = tmp_path / "code-ran"
    payload = np.empty((), dtype=object)
    payload[()] = _RunsCode(proof)
    attack = tmp_path / "attack" / "model.npz"
    attack.parent.mkdir()
    np.savez(attack, **{**arrays, "J_regressor": payload})  # an object array, as a pickled sparse J_regressor is
    as_pickle = tmp_path / "model.pkl"
    as_pickle.write_bytes(pickle.dumps({**arrays, "extra": _RunsCode(proof)}))
    renamed = tmp_path / "renamed.npz"
    renamed.write_bytes(pickle.dumps(_RunsCode(proof)))
    for path, what in ((attack, "holds pickled Python objects"), (as_pickle, "is a Python pickle"),
                       (renamed, "holds pickled Python objects")):
        with pytest.raises(ValueError, match=rf"{path.name}: .*{what}.*unpickling runs whatever code the file carries"
                                             r".*unpickle_body_model=true"):
            load_body_model(path)
        assert not proof.exists(), f"{path}: unpickled without the opt-in"
    captions = tmp_path / "c.json"
    captions.write_text("{}")
    (tmp_path / "amass").mkdir()
    with pytest.raises(ValueError, match="unpickle_body_model=true"):  # through the source, as build_shards does
        build_source("amass", str(tmp_path / "amass"), body_model=str(attack), captions=str(captions))
    assert not proof.exists()
    # The opt-in reads a trusted pickled model as before (here, a scipy-like sparse J_regressor).
    sparse = np.empty((), dtype=object)
    sparse[()] = _SparseLike(arrays["J_regressor"])
    trusted = tmp_path / "trusted.npz"
    np.savez(trusted, **{**arrays, "J_regressor": sparse})
    with pytest.raises(ValueError, match="unpickle_body_model=true"):
        load_body_model(trusted)
    opted_in = load_body_model(trusted, unpickle=True)
    np.testing.assert_allclose(opted_in.rest_joints, load_body_model(npz).rest_joints)
    source = build_source("amass", str(tmp_path / "amass"), body_model=str(trusted), captions=str(captions),
                          unpickle_body_model="true")
    np.testing.assert_allclose(source.body_models["male"].rest_joints, opted_in.rest_joints)


def test_amass_zero_pose_is_rest_joints_plus_trans_in_humanml3d_axes(tmp_path: Path) -> None:
    model = write_body_model(tmp_path / "smplh" / "male" / "model.npz")
    betas = RNG.normal(size=16)
    trans = np.array([[1.0, 2.0, 3.0], [0.5, -1.0, 0.25]])
    write_motion(tmp_path / "amass" / "CMU" / "01" / "01_01_poses.npz", np.zeros((2, 156)), trans, betas=betas)
    captions = tmp_path / "captions.json"
    captions.write_text(json.dumps({"CMU/01/01_01_poses.npz": ["a person stands still.", {"text": "then waves", "start": 0.5, "end": 1.0}]}))
    source = build_source("amass", str(tmp_path / "amass"), body_model=str(model), captions=str(captions))
    assert source.list_items() == ["CMU/01/01_01_poses.npz"]
    only = [s for s in ("train", "val", "test") if s != hash_split("CMU/01/01_01_poses.npz")]
    assert build_source("amass", str(tmp_path / "amass"), body_model=str(model), captions=str(captions), splits=only).list_items() == []
    clip = source.load("CMU/01/01_01_poses.npz")
    assert isinstance(clip, Clip)
    assert clip.id == "CMU__01__01_01_poses" == motion_id("CMU/01/01_01_poses.npz")
    assert (clip.fps, clip.skeleton, clip.joints.shape) == (60.0, "humanml3d", (2, 22, 3))
    assert clip.captions[1] == Caption("then waves", (), 0.5, 1.0)
    rest = expected_rest_joints(model, betas)
    for frame in range(2):
        amass_axes = rest + trans[frame]
        # raw_pose_processing: joints @ trans_matrix, then x negated: (x, y, z) -> (-x, z, y)
        expected = amass_axes @ TRANS_MATRIX * np.array([-1.0, 1.0, 1.0])
        np.testing.assert_allclose(clip.joints[frame], expected, atol=1e-5)
        np.testing.assert_allclose(clip.joints[frame], amass_axes[:, [0, 2, 1]] * np.array([-1.0, 1.0, 1.0]), atol=1e-5)
    # AMASS is Z up: moving up in AMASS is moving up (+y) in HumanML3D.
    np.testing.assert_allclose(to_humanml3d_axes(np.array([[0.0, 0.0, 1.0]])), [[0.0, 1.0, 0.0]])


def test_amass_forward_kinematics(tmp_path: Path) -> None:
    model_path = write_body_model(tmp_path / "model.npz")
    model = load_body_model(model_path)
    rest = model.joints_at_rest(np.zeros(16))
    parents = np.array(SMPLH_PARENTS[:22])
    # Root turned 90 degrees about AMASS's up axis (z): every joint turns about the pelvis.
    poses = np.zeros((1, 156))
    poses[0, 2] = math.pi / 2
    turned = model.forward(poses, np.zeros((1, 3)), np.zeros(16))[0]
    rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(turned, (rest - rest[0]) @ rz.T + rest[0], atol=1e-9)
    # A left-knee rotation moves only the left ankle and foot.
    poses = np.zeros((1, 156))
    poses[0, 3 * 4 : 3 * 4 + 3] = [0.7, 0.0, 0.0]
    bent = model.forward(poses, np.zeros((1, 3)), np.zeros(16))[0]
    moved = np.flatnonzero(np.abs(bent - rest).max(axis=1) > 1e-9)
    assert moved.tolist() == [7, 10]
    # Random poses keep every bone length.
    poses = RNG.normal(size=(5, 156))
    posed = model.forward(poses, RNG.normal(size=(5, 3)), np.zeros(16))
    np.testing.assert_allclose(bone_lengths(posed, parents), np.broadcast_to(bone_lengths(rest[None], parents), (5, 21)), atol=1e-9)


def test_amass_humanml3d_index_mode(tmp_path: Path) -> None:
    body = tmp_path / "smplh"
    write_body_model(body / "male" / "model.npz")
    write_body_model(body / "female" / "model.npz", offset=0.5)
    frames = 600  # 10 s at 60 fps -> 200 frames at 20 fps, 3 s lead-in cut for MPI_HDM05
    poses = RNG.normal(size=(frames, 156)) * 0.2
    trans = np.cumsum(RNG.normal(size=(frames, 3)) * 0.01, axis=0)
    amass = tmp_path / "amass_data"
    write_motion(amass / "MPI_HDM05" / "bk" / "take_poses.npz", poses, trans, fps=60.0, gender="female")
    write_motion(amass / "KIT" / "3" / "walk_poses.npz", poses, trans, fps=60.0, gender="male")
    humanml = tmp_path / "HumanML3D"
    (humanml / "texts").mkdir(parents=True)
    (humanml / "index.csv").write_text(
        "source_path,start_frame,end_frame,new_name\n"
        "./pose_data/MPI_HDM05/bk/take_poses.npy,10,50,000000.npy\n"
        "./pose_data/KIT/3/walk_poses.npy,0,40,000001.npy\n"
        "./pose_data/KIT/3/missing_poses.npy,0,40,000002.npy\n"
    )
    for name in ("000000", "M000000", "000001", "000002"):
        (humanml / "texts" / f"{name}.txt").write_text(GOOD_TEXT)
    (humanml / "train.txt").write_text("000000\nM000000\n")
    (humanml / "test.txt").write_text("000001\n")
    source = build_source("amass", str(amass), body_model=str(body), captions=str(humanml / "index.csv"), mirror=True)
    assert source.list_items() == ["000000", "000001", "000002", "M000000", "M000001", "M000002"]
    assert build_source("amass", str(amass), body_model=str(body), captions=str(humanml / "index.csv"), splits="test").list_items() == ["000001"]

    clip = source.load("000000")
    assert (clip.fps, clip.split, clip.joints.shape) == (20.0, "train", (40, 22, 3))
    # Stride 3 (60 -> 20 fps), 60-frame lead-in cut, then [10:50]; the female model for a female clip.
    keep = np.arange(0, frames, 3)[60:][10:50]
    female = load_body_model(body / "female" / "model.npz")
    expected = to_humanml3d_axes(female.forward(poses[keep], trans[keep], np.zeros(16)))
    np.testing.assert_allclose(clip.joints, expected, atol=1e-5)
    np.testing.assert_allclose(source.load("M000000").joints, mirror_left_right(expected), atol=1e-5)
    kit = source.load("000001")
    assert kit.split == "test" and kit.joints.shape == (40, 22, 3)
    assert not np.allclose(kit.joints, to_humanml3d_axes(female.forward(poses[0:120:3], trans[0:120:3], np.zeros(16))))
    missing = source.load("000002")
    assert isinstance(missing, SkippedInput) and missing.reason == "unreadable" and "missing_poses.npz" in missing.path
    assert source.load("M000001").reason == "no_captions"


def test_amass_bad_files(tmp_path: Path) -> None:
    model = write_body_model(tmp_path / "model.npz")
    root = tmp_path / "amass"
    nan_poses = np.zeros((4, 156))
    nan_poses[2, 5] = np.nan
    write_motion(root / "a" / "nan_poses.npz", nan_poses, np.zeros((4, 3)))
    write_motion(root / "a" / "shape_poses.npz", np.zeros((4, 30)), np.zeros((4, 3)))
    (root / "a" / "broken_poses.npz").write_bytes(b"PK not really a zip")
    write_motion(root / "a" / "nocaption_poses.npz", np.zeros((4, 156)), np.zeros((4, 3)))
    captions = tmp_path / "captions.csv"
    captions.write_text("path,text\na/nan_poses.npz,x\na/shape_poses.npz,x\na/broken_poses.npz,x\na/nocaption_poses.npz,\n")
    source = AMASSSource(str(root), body_model=str(model), captions=str(captions))
    reasons = {item: source.load(item).reason for item in source.list_items()}
    assert reasons == {
        "a/broken_poses.npz": "unreadable", "a/nan_poses.npz": "nan_frames",
        "a/nocaption_poses.npz": "no_captions", "a/shape_poses.npz": "bad_shape",
    }


def test_amass_index_mode_bad_captions_missing_ids_and_complex_arrays(tmp_path: Path) -> None:
    """The HumanML3D faults where AMASS shares the code: caption files, split files, joint files."""
    model = write_body_model(tmp_path / "model.npz")
    amass = tmp_path / "amass_data"
    write_motion(amass / "KIT" / "3" / "walk_poses.npz", np.zeros((30, 156)), np.zeros((30, 3)))
    write_motion(amass / "KIT" / "3" / "complex_poses.npz", np.zeros((30, 156)) * (1 + 1j), np.zeros((30, 3)))
    (amass / "humanact12").mkdir()
    np.save(amass / "humanact12" / "P01.npy", walking_joints(30, 24) * (1 + 1j))
    humanml = tmp_path / "HumanML3D"
    (humanml / "texts").mkdir(parents=True)
    (humanml / "index.csv").write_text(
        "source_path,start_frame,end_frame,new_name\n"
        "./pose_data/KIT/3/walk_poses.npy,0,10,000000.npy\n"
        "./pose_data/KIT/3/walk_poses.npy,0,10,000001.npy\n"
        "./pose_data/KIT/3/complex_poses.npy,0,10,000002.npy\n"
        "./pose_data/humanact12/P01.npy,0,10,000003.npy\n"
    )
    (humanml / "texts" / "000000.txt").write_text(GOOD_TEXT + MALFORMED_SPANS)
    (humanml / "texts" / "000001.txt").write_text("a man runs#t/X#-1#2\n")
    for name in ("000002", "000003"):
        (humanml / "texts" / f"{name}.txt").write_text(GOOD_TEXT)
    # M000000 is not built without mirror=True: not missing. 000777 has no index row: missing.
    (humanml / "train.txt").write_text("000000\nM000000\n000001\n000002\n000003\n000777\n")
    source = build_source("amass", str(amass), body_model=str(model), captions=str(humanml / "index.csv"))
    assert source.list_items() == ["000000", "000001", "000002", "000003", "000777"]
    clip = source.load("000000")
    assert clip.dropped_captions == {"span_end_not_after_start": 1, "span_negative": 1, "span_not_a_number": 1}
    only_bad = source.load("000001")
    assert only_bad.reason == "no_captions" and "span_negative" in only_bad.detail and "empty" not in only_bad.detail
    missing = source.load("000777")
    assert (missing.id, missing.reason) == ("000777", "missing_file") and "index.csv" in missing.detail
    for item, file in (("000002", "complex_poses.npz"), ("000003", "P01.npy")):
        refused = source.load(item)
        assert (refused.id, refused.reason) == (item, "bad_shape") and "complex" in refused.detail
        assert refused.path.endswith(file)


AMASS_BAD_CAPTIONS = {
    "json": json.dumps({
        "a/walk_poses.npz": ["a person walks forward", {"text": "turns", "start": 5.0, "end": 2.0}, "runs#t/X#-1#2", "",
                             {"text": "  "}, 42, {"text": "jumps", "start": "abc"}, {"text": "waves", "start": 0.5, "end": 1.5}],
        "a/only_bad_poses.npz": [{"text": "kicks", "start": 3, "end": 1}],
    }),
    "csv": "path,text,start,end\n"
           "a/walk_poses.npz,a person walks forward,,\n"
           "a/walk_poses.npz,turns,5.0,2.0\n"
           "a/walk_poses.npz,runs,-1,2\n"
           "a/walk_poses.npz,,,\n"
           "a/walk_poses.npz,jumps,abc,\n"
           "a/walk_poses.npz,waves,0.5,1.5\n"
           "a/only_bad_poses.npz,kicks,3,1\n",
}


@pytest.mark.parametrize("kind", ["json", "csv"])
def test_amass_caption_map_bad_entries_are_counted_by_reason(tmp_path: Path, kind: str) -> None:
    """A malformed entry of a JSON/CSV caption map (bad span, empty text, another shape) no longer stops the build:
    it is dropped and counted by reason in its clip's dropped_captions, as HumanML3D's caption lines are; a clip
    left without captions says why; ``caption_problems()`` names the file and the entry of each (for --strict)."""
    model = write_body_model(tmp_path / "model.npz")
    root = tmp_path / "amass"
    for name in ("walk", "only_bad"):
        write_motion(root / "a" / f"{name}_poses.npz", np.zeros((4, 156)), np.zeros((4, 3)))
    captions = tmp_path / f"captions.{kind}"
    captions.write_text(AMASS_BAD_CAPTIONS[kind])
    source = AMASSSource(str(root), body_model=str(model), captions=str(captions))  # used to raise ValueError here
    clip = source.load("a/walk_poses.npz")
    assert isinstance(clip, Clip)
    assert clip.captions == [Caption("a person walks forward"), Caption("waves", (), 0.5, 1.5)]
    expected = {"span_end_not_after_start": 1, "span_negative": 1, "span_not_a_number": 1, "empty": 1}
    if kind == "json":
        expected |= {"empty": 2, "malformed_entry": 1}  # "" and {"text": "  "}; the number 42
    assert clip.dropped_captions == expected

    only_bad = source.load("a/only_bad_poses.npz")
    assert isinstance(only_bad, SkippedInput) and only_bad.reason == "no_captions"
    assert "1 span_end_not_after_start" in only_bad.detail and str(captions) in only_bad.detail

    problems = source.caption_problems()
    assert sum(expected.values()) + 1 == len(problems)
    first = problems[0]
    assert (first.id, first.path, first.reason) == ("a__walk_poses", str(captions), "span_end_not_after_start")
    where = "entry 'a/walk_poses.npz', caption 2" if kind == "json" else "line 3 ('a/walk_poses.npz')"
    assert first.detail == f"{where}: span end 2.0 s is not after its start 5.0 s"


# ----------------------------------------------------------------------------------------------------
# DeepMimic (real motion capture from pybullet)
# ----------------------------------------------------------------------------------------------------

DEEPMIMIC_CLIPS = {
    "backflip", "cartwheel", "crawl", "dance_a", "dance_b", "getup_facedown", "getup_faceup", "jump", "kick",
    "punch", "roll", "run", "spin", "spinkick", "walk",
}


@pytest.fixture(scope="module")
def deepmimic() -> dict[str, Clip]:
    source = build_source("deepmimic", None)
    clips = {item: source.load(item) for item in source.list_items()}
    assert all(isinstance(c, Clip) for c in clips.values()), {i: c for i, c in clips.items() if not isinstance(c, Clip)}
    return clips


def test_deepmimic_clips_load_as_humanml3d_skeleton(deepmimic: dict[str, Clip]) -> None:
    train = {c.action for c in deepmimic.values() if c.split == "train"}
    assert train == DEEPMIMIC_CLIPS and len([c for c in deepmimic.values() if c.split == "train"]) == 15
    assert {c.split for c in deepmimic.values()} == {"train", "val", "test"}
    for clip in deepmimic.values():
        assert clip.joints.shape[1:] == (22, 3) and clip.joints.dtype == np.float32
        assert clip.fps in (16.0, 24.0, 30.0, 60.0) and clip.skeleton == "humanml3d" and clip.source == "deepmimic"
        assert 2 <= len(clip.captions) <= 3 and all(c.text.endswith(".") for c in clip.captions)
        lengths = bone_lengths(clip.joints.astype(np.float64), HUMANML3D.parents)
        assert np.abs(lengths - lengths[0]).max() < 1e-4, clip.id
        if clip.meta["loop"]:
            assert (len(clip.joints) - 1) / clip.fps >= 2.5 - 1e-9, clip.id
    seconds = sum((len(c.joints) - 1) / c.fps for c in deepmimic.values() if c.split == "train")
    assert 40 < seconds < 50


def test_deepmimic_is_a_human_sized_figure_on_the_floor(deepmimic: dict[str, Clip]) -> None:
    for name in ("walk", "run", "jump", "kick", "punch", "backflip", "spin", "cartwheel"):
        first = deepmimic[name].joints[0].astype(np.float64)
        feet = first[[7, 8, 10, 11], 1]
        assert -0.05 < feet.min() < 0.1, name
        assert 1.25 < first[15, 1] - feet.min() < 1.6, name  # head joint; the head's top is ~0.17 m higher
        assert 0.75 < first[0, 1] < 0.95, name  # pelvis
    for name in ("crawl", "getup_facedown", "getup_faceup"):
        assert deepmimic[name].joints[0, 15, 1] < 0.5, name  # starts on the ground


def test_deepmimic_forward_kinematics_matches_pybullet() -> None:
    pybullet = pytest.importorskip("pybullet")
    from preprocess.sources.deepmimic import (
        default_motions_dir,
        default_urdf_path,
        link_frames,
        parse_frames,
        read_humanoid_urdf,
    )

    model = read_humanoid_urdf(default_urdf_path())
    frames = np.asarray(json.loads((default_motions_dir() / "humanoid3d_cartwheel.txt").read_text())["Frames"])
    _, poses = parse_frames(frames)
    ours = link_frames(poses, model)
    client = pybullet.connect(pybullet.DIRECT)
    try:
        body = pybullet.loadURDF(str(default_urdf_path()), globalScaling=0.25, useFixedBase=True, physicsClientId=client)
        index = {pybullet.getJointInfo(body, i, physicsClientId=client)[12].decode(): i for i in range(pybullet.getNumJoints(body, physicsClientId=client))}
        for t in range(0, len(frames), 20):
            w, x, y, z = poses.root_quat[t]
            pybullet.resetBasePositionAndOrientation(body, poses.root_pos[t].tolist(), [x, y, z, w], physicsClientId=client)
            for name, rotation in poses.joint_rot.items():
                r = rotation[t]
                target = [r[1], r[2], r[3], r[0]] if r.size == 4 else [r[0]]
                pybullet.resetJointStateMultiDof(body, index[name], target, physicsClientId=client)
            for name, link in index.items():
                state = pybullet.getLinkState(body, link, computeForwardKinematics=True, physicsClientId=client)
                np.testing.assert_allclose(ours[name][0][t], state[4], atol=1e-5, err_msg=f"{name} frame {t}")
    finally:
        pybullet.disconnect(client)


def test_deepmimic_tiled_loops_have_no_seams(deepmimic: dict[str, Clip]) -> None:
    for name in ("walk", "run", "spinkick", "jump"):
        clip = deepmimic[name]
        assert clip.meta["loop_closed"] and clip.meta["cycles"] >= 2
        step = np.linalg.norm(np.diff(clip.joints.astype(np.float64), axis=0), axis=-1).max(axis=1)
        cycle = (len(clip.joints) - 1) // clip.meta["cycles"]
        seams = step[cycle - 1 : cycle + 1]
        assert seams.max() <= 1.1 * np.delete(step, [cycle - 1, cycle]).max(), name


def test_deepmimic_captions_match_the_motion(deepmimic: dict[str, Clip]) -> None:
    def peak(clip: str, joint: int) -> float:
        return float(deepmimic[clip].joints[:, joint, 1].max())

    assert peak("kick", 8) > 1.0 > 0.3 > peak("kick", 7)  # right ankle kicks, left stays down
    reach = {side: np.linalg.norm(deepmimic["punch"].joints[:, w] - deepmimic["punch"].joints[:, s], axis=-1).max() for side, (w, s) in {"left": (20, 16), "right": (21, 17)}.items()}
    assert reach["right"] > reach["left"] + 0.03
    assert peak("spinkick", 8) > peak("spinkick", 7) + 0.3
    cartwheel = deepmimic["cartwheel"].joints.astype(np.float64)
    left = np.cross(np.array([0.0, 1.0, 0.0]), facing(cartwheel[:1])[0])  # up x forward = left
    assert (cartwheel[-1, 0] - cartwheel[0, 0]) @ left > 1.5
    assert turned_degrees(deepmimic["dance_a"].joints[:98]) < -300  # one full turn to the right
    assert turned_degrees(deepmimic["spin"].joints) > 600  # two turns to the left
    walk = deepmimic["walk"].joints.astype(np.float64)
    assert (walk[-1, 0] - walk[0, 0]) @ facing(walk[:1])[0] > 2.0


# ----------------------------------------------------------------------------------------------------
# Synthetic
# ----------------------------------------------------------------------------------------------------


def test_synthetic_is_deterministic_and_extends() -> None:
    small, big = SyntheticSource(num_clips=5, seed=3), SyntheticSource(num_clips=40, seed=3)
    assert big.list_items()[:5] == small.list_items()
    for item in small.list_items():
        a, b = small.load(item), big.load(item)
        np.testing.assert_array_equal(a.joints, b.joints)
        assert (a.captions, a.action, a.split) == (b.captions, b.action, b.split)
    other = SyntheticSource(num_clips=5, seed=4).load("synth_000000")
    assert not np.array_equal(other.joints, small.load("synth_000000").joints)  # another seed, another clip


def test_synthetic_jump_forward_share_changes_only_which_jumps_travel() -> None:
    """jump_forward_share 0: every jump is "up in place"; every clip that is not a forward jump is the same as with
    the default share (the draw is still made); out-of-range shares are refused."""
    default, in_place = SyntheticSource(num_clips=60), SyntheticSource(num_clips=60, jump_forward_share=0)
    changed = 0
    for item in default.list_items():
        a, b = default.load(item), in_place.load(item)
        assert (a.action, a.split, len(a.joints)) == (b.action, b.split, len(b.joints))
        if a.action == "jump":
            assert all("up in place" in c.text for c in b.captions)
        if a.action == "jump" and "forward" in a.captions[0].text:
            changed += 1
            assert [c.text.replace("forward", "up in place") for c in a.captions] == [c.text for c in b.captions]
        else:
            np.testing.assert_array_equal(a.joints, b.joints)
            assert a.captions == b.captions
    assert changed > 0
    with pytest.raises(ValueError, match="jump_forward_share"):
        SyntheticSource(jump_forward_share=1.5)


def test_synthetic_clips_are_well_formed() -> None:
    source = build_source("synthetic", None, num_clips=200, seed=0)
    clips = [source.load(item) for item in source.list_items()]
    assert {c.action for c in clips} == set(ACTIONS)
    splits = [c.split for c in clips]
    assert 0.65 < splits.count("train") / len(splits) < 0.95 and "val" in splits and "test" in splits
    for clip in clips:
        assert isinstance(clip, Clip) and clip.joints.shape[1:] == (22, 3) and clip.fps == 20.0
        assert 41 <= len(clip.joints) <= 199  # HumanML3D's 40-198 feature frames (default lengths 2-9.9 s)
        assert clip.captions and all(c.text for c in clip.captions)
        np.testing.assert_allclose(bone_lengths(clip.joints.astype(np.float64), HUMANML3D.parents), np.broadcast_to(HUMANML3D.bone_lengths[1:], (len(clip.joints), 21)), atol=1e-5)
        feet = clip.joints[:, [7, 8, 10, 11], 1].min(axis=1)
        if clip.action != "jump":
            np.testing.assert_allclose(feet, 0.05, atol=1e-5)
        assert np.all(clip.joints[:, 15, 1] > clip.joints[:, 12, 1])  # head above neck


def test_synthetic_captions_match_the_motion() -> None:
    source = SyntheticSource(num_clips=160, seed=1, actions="wave,walk,turn,sidestep")
    seen = set()
    for item in source.list_items():
        clip = source.load(item)
        joints, text = clip.joints.astype(np.float64), clip.captions[0].text
        if clip.action == "wave":
            side = "right" if "right" in text else "left"
            wrist, other = (21, 20) if side == "right" else (20, 21)
            assert joints[:, wrist, 1].max() > joints[:, 15, 1].max() > joints[:, other, 1].max(), text
            top = int(joints[:, wrist, 1].argmax())
            left = np.cross(np.array([0.0, 1.0, 0.0]), facing(joints[top : top + 1])[0])
            sideways = (joints[top, wrist] - joints[top, 9]) @ left  # from the chest, towards the left
            assert sideways > 0.15 if side == "left" else sideways < -0.15, text
        elif clip.action == "walk" and "turning" not in text:
            travel = (joints[-1, 0] - joints[0, 0]) @ facing(joints[:1])[0]
            assert travel > 0.5 if "forward" in text else travel < -0.5, text
        elif clip.action == "turn":
            angle = turned_degrees(joints)
            target = (180 if "around" in text else 90) * (1 if "left" in text else -1)
            assert abs(angle - target) < 15, (text, angle)
        elif clip.action == "sidestep":
            left = np.cross(np.array([0.0, 1.0, 0.0]), facing(joints[:1])[0])
            assert ((joints[-1, 0] - joints[0, 0]) @ left > 0.3) == ("left" in text), text
        seen.add(clip.action)
    assert seen == {"wave", "walk", "turn", "sidestep"}


def test_synthetic_corruptions() -> None:
    source = SyntheticSource(num_clips=2, corrupt=list(CORRUPTIONS))
    results = {item: source.load(item) for item in source.list_items() if item.startswith("corrupt_")}
    reasons = {item: getattr(r, "reason", None) for item, r in results.items()}
    assert reasons == {
        "corrupt_nan": "nan_frames", "corrupt_inf": "nan_frames", "corrupt_bad_shape": "bad_shape",
        "corrupt_no_captions": "no_captions", "corrupt_short": None, "corrupt_long": None,
    }
    assert results["corrupt_short"].joints.shape[0] == 11 and results["corrupt_long"].joints.shape[0] == 301
    with pytest.raises(ValueError, match="unknown corruption"):
        SyntheticSource(corrupt="bogus")


# ----------------------------------------------------------------------------------------------------
# Registry
# ----------------------------------------------------------------------------------------------------


def test_registry(humanml3d_root: Path) -> None:
    assert set(SOURCES) == {"humanml3d", "kit", "amass", "deepmimic", "synthetic"}
    with pytest.raises(ValueError, match="unknown source"):
        build_source("bvh", None)
    with pytest.raises(ValueError, match="has no option"):
        build_source("synthetic", None, num_clip=3)
    with pytest.raises(ValueError, match="root"):
        build_source("humanml3d", None)
    for source in (build_source("humanml3d", str(humanml3d_root)), build_source("deepmimic", None), build_source("synthetic", None, num_clips="3", seed="2")):
        assert isinstance(source, Source) and source.name in SOURCES
        copy = pickle.loads(pickle.dumps(source))  # sources travel to worker processes
        item = source.list_items()[0]
        np.testing.assert_array_equal(copy.load(item).joints, source.load(item).joints)


def test_deepmimic_options_and_bad_files(tmp_path: Path) -> None:
    from preprocess.sources.deepmimic import (
        default_motions_dir,
        default_urdf_path,
        humanml3d_joints,
        parse_frames,
        read_humanoid_urdf,
    )

    assert len(build_source("deepmimic", None, held_out=False).list_items()) == 15
    untiled = build_source("deepmimic", None, min_seconds=0).load("walk")
    assert untiled.meta["cycles"] == 1 and len(untiled.joints) == 39  # the take as captured
    # The humanoid at rest (all rotations identity): sole of the foot box to the top of the head sphere.
    rest = np.zeros((1, 44))
    rest[0, [0, 4, 8, 12, 16, 21, 25, 30, 35, 39]] = [1 / 30, 1, 1, 1, 1, 1, 1, 1, 1, 1]
    _, poses = parse_frames(rest)
    joints = humanml3d_joints(poses, read_humanoid_urdf(default_urdf_path()))[0]
    sole = joints[7, 1] - 0.25 * 0.2  # foot box bottom is 0.2 URDF units below the ankle
    head_top = joints[12, 1] + 0.25 * (0.7 + 0.41)  # head sphere: centre 0.7 above the neck, radius 0.41
    assert 1.60 < head_top - sole < 1.64

    motions = tmp_path / "motions"
    motions.mkdir()
    walk = json.loads((default_motions_dir() / "humanoid3d_walk.txt").read_text())
    (motions / "humanoid3d_walk.txt").write_text(json.dumps(walk))
    (motions / "humanoid3d_moonwalk.txt").write_text(json.dumps(walk))
    (motions / "humanoid3d_broken.txt").write_text("{not json")
    (motions / "humanoid3d_short.txt").write_text(json.dumps({"Loop": "none", "Frames": [f[:43] for f in walk["Frames"]]}))
    nan = {"Loop": "none", "Frames": [list(f) for f in walk["Frames"]]}
    nan["Frames"][3][10] = float("nan")
    (motions / "humanoid3d_nan.txt").write_text(json.dumps(nan))
    source = build_source("deepmimic", str(motions), held_out=False)
    reasons = {item: getattr(source.load(item), "reason", None) for item in source.list_items()}
    assert reasons == {"broken": "unreadable", "moonwalk": "no_captions", "nan": "nan_frames", "short": "bad_shape", "walk": None}


def test_the_embedded_dataset_without_pybullet_says_how_to_get_it(monkeypatch) -> None:
    from preprocess.sources.deepmimic import default_motions_dir

    monkeypatch.setitem(sys.modules, "pybullet_data", None)  # as on a platform where pybullet did not install
    with pytest.raises(ModuleNotFoundError, match=r"pip install 'motion-flow-matching\[embedded\]'"):
        default_motions_dir()
