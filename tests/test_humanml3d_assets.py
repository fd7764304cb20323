"""HumanML3D as it is distributed: the published features (new_joint_vecs) read as they are, checked against
new_joints, and the official Mean/Std in the manifest, on the real clip 012314 (../shared/reference-data)."""

from __future__ import annotations

import hashlib
import io
import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import webdataset as wds
from test_features import PUBLISHED_TOLERANCE, kit_skeleton_and_clip

from mfm import features as F
from mfm.layout import FeatureLayout
from mfm.skeleton import HUMANML3D, KIT
from preprocess.build_shards import main
from preprocess.clip import Clip
from preprocess.processing import process_clip
from preprocess.shards import BadInputError, BuildConfig, build_dataset, load_manifest
from preprocess.sources import build_source

CLIP = "012314"
COPY = "000001"  # the same files under a second id, in the test split
# HumanML3D's caption format: caption#tokens#from#to (seconds). The last span runs past the clip's end
# (8.5 s = frame 170): it is clipped to the record's length, 170 read from the file, 169 recomputed.
CAPTIONS = (
    "a person serves a tennis ball.#a/DET person/NOUN serve/VERB a/DET tennis/NOUN ball/NOUN#0.0#0.0\n"
    "a man tosses a ball up and swings his arm.#a/DET man/NOUN toss/VERB a/DET ball/NOUN up/ADP and/CCONJ "
    "swing/VERB his/DET arm/NOUN#2.0#6.0\n"
    "the person finishes the serve.#the/DET person/NOUN finish/VERB the/DET serve/NOUN#5.0#8.5\n"
)


@pytest.fixture(scope="module")
def encoder():
    from mfm.text import build_text_encoder

    return build_text_encoder("minilm")


@pytest.fixture(scope="module")
def published(tmp_path_factory) -> dict[str, Path]:
    from conftest import REFERENCE_DATA

    folder = REFERENCE_DATA / "humanml3d"
    if not folder.is_dir():
        pytest.skip(f"reference data not found at {REFERENCE_DATA} (set MFM_SHARED_DIR or place shared/ beside the checkout)")
    return {"joints": folder / f"new_joints_{CLIP}.npy", "features": folder / f"new_joint_vecs_{CLIP}.npy",
            "mean": folder / "Mean.npy", "std": folder / "Std.npy"}


def write_humanml3d(root: Path, published: dict[str, Path], *, joints: bool = True, features: bool = True,
                    statistics: bool = True) -> Path:
    """HumanML3D's layout holding the real clip (train) and a copy of it (test)."""
    for folder, key, wanted in (("new_joints", "joints", joints), ("new_joint_vecs", "features", features)):
        if wanted:
            (root / folder).mkdir(parents=True)
            for clip_id in (CLIP, COPY):
                shutil.copyfile(published[key], root / folder / f"{clip_id}.npy")
    (root / "texts").mkdir(parents=True)
    for clip_id in (CLIP, COPY):
        (root / "texts" / f"{clip_id}.txt").write_text(CAPTIONS, encoding="utf-8")
    (root / "train.txt").write_text(f"{CLIP}\n")
    (root / "val.txt").write_text("")
    (root / "test.txt").write_text(f"{COPY}\n")
    if statistics:
        shutil.copyfile(published["mean"], root / "Mean.npy")
        shutil.copyfile(published["std"], root / "Std.npy")
    return root


def records(out: Path, manifest: dict, split: str = "train") -> list[dict]:
    """Every record of a split from the tar shards, checked equal to the Parquet rows."""
    urls = [str(out / s["path"]) for s in manifest["splits"][split]["shards"]]
    tar = [{"features": np.load(io.BytesIO(s["features.npy"])), "meta": json.loads(s["meta.json"]),
            "members": sorted(k for k in s if not k.startswith("__"))}
           for s in wds.WebDataset(urls, shardshuffle=False, empty_check=False)]
    rows = [row for part in manifest["splits"][split]["parquet"] for row in pq.read_table(out / part["path"]).to_pylist()]
    assert [r["id"] for r in rows] == [t["meta"]["id"] for t in tar]
    for t, row in zip(tar, rows):
        assert np.array(row["features"], np.float32).tobytes() == t["features"].tobytes()
        assert (row["span_start"], row["span_end"]) == ([c["start_frame"] for c in t["meta"]["captions"]],
                                                        [c["end_frame"] for c in t["meta"]["captions"]])
    return tar


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def both_builds(tmp_path_factory, published, encoder):
    """The same folder built from the feature files + official statistics (the defaults), and recomputed."""
    base = tmp_path_factory.mktemp("hml")
    root = write_humanml3d(base / "HumanML3D", published)
    config = BuildConfig(out=base / "files", source="humanml3d", root=str(root), progress=False)
    from_files = build_dataset(config, text_encoder=encoder)
    recompute = replace(config, out=base / "recomputed", source_options={"features": "recompute"},
                        normalization="recompute")
    recomputed = build_dataset(recompute, text_encoder=encoder)
    return root, (config.out, from_files), (recompute.out, recomputed)


# --- features read from new_joint_vecs -------------------------------------------------------------------


def test_feature_files_are_stored_exactly_with_the_official_statistics(both_builds, published):
    root, (out, manifest), _ = both_builds
    assert load_manifest(out, verify="sha256") == manifest
    assert manifest["skip_report"]["total"] == 0  # both clips checked against new_joints, and agree
    (record,) = records(out, manifest, "train")
    expected = np.load(published["features"])
    assert record["features"].dtype == np.float32 and record["features"].tobytes() == expected.tobytes()
    assert record["meta"]["length"] == 170 and manifest["splits"]["train"]["lengths"] == [170]
    assert records(out, manifest, "test")[0]["features"].tobytes() == expected.tobytes()
    spans = [(c["start_frame"], c["end_frame"]) for c in record["meta"]["captions"]]
    assert spans == [(0, 170), (40, 120), (100, 170)]  # HumanML3D's int(seconds * 20) on the file's frames

    norm = manifest["normalization"]
    assert np.array(norm["mean"], np.float32).tobytes() == np.load(published["mean"]).tobytes()
    assert np.array(norm["std"], np.float32).tobytes() == np.load(published["std"]).tobytes()
    assert norm["source"] == "official" and norm["split"] is None and norm["num_frames"] is None
    assert norm["files"] == {"mean": {"path": "Mean.npy", "sha256": sha256(root / "Mean.npy")},
                             "std": {"path": "Std.npy", "sha256": sha256(root / "Std.npy")}}
    assert manifest["builder"]["options"]["normalization"] == "auto"
    assert "--normalization auto" in manifest["builder"]["command"]


def test_recomputed_features_match_the_files_to_the_golden_tolerance(both_builds, published):
    _, (files_out, from_files), (out, manifest) = both_builds
    assert manifest["skip_report"]["total"] == 0
    (record,) = records(out, manifest, "train")
    expected = np.load(published["features"])
    # new_joints has the 170 frames of the features (recover_from_ric of them): recomputed, 169.
    assert record["features"].shape == (169, 263) and record["meta"]["length"] == 169
    slices = FeatureLayout(HUMANML3D).slices
    # The golden tolerances of tests/test_features.py, measured with bone lengths taken from the clip; the
    # build uses the preset's (rounded to 0.1 mm), which moves the root height by 1.1e-6 m.
    tolerance = {**PUBLISHED_TOLERANCE, "root_height": 2e-6}
    for name, limit in tolerance.items():
        deviation = np.abs(record["features"][:, slices[name]].astype(np.float64) - expected[:169, slices[name]]).max()
        assert deviation <= limit, name
    spans = [(c["start_frame"], c["end_frame"]) for c in record["meta"]["captions"]]
    assert spans == [(0, 169), (40, 120), (100, 169)]  # clipped to the recomputed length

    # The record layout does not depend on where the features came from.
    (from_file,) = records(files_out, from_files, "train")
    assert record["members"] == from_file["members"]
    assert sorted(record["meta"]) == sorted(from_file["meta"])
    assert {k: v for k, v in record["meta"].items() if k not in ("length", "captions")} == \
        {k: v for k, v in from_file["meta"].items() if k not in ("length", "captions")}
    schema = pq.read_schema(out / manifest["splits"]["train"]["parquet"][0]["path"])
    assert schema.equals(pq.read_schema(files_out / from_files["splits"]["train"]["parquet"][0]["path"]))
    assert manifest["feature_spec"] == from_files["feature_spec"]

    norm = manifest["normalization"]
    assert norm["source"] == "recomputed" and norm["split"] == "train" and norm["num_frames"] == 169
    assert norm["rule"] == "std averaged within each feature group" and "files" not in norm


def test_feature_file_that_disagrees_with_new_joints_is_skipped_naming_it(tmp_path, published, encoder):
    root = write_humanml3d(tmp_path / "HumanML3D", published)
    vecs = np.load(published["features"])
    ric = FeatureLayout(HUMANML3D).slices["ric"]
    vecs[:, ric] += np.random.default_rng(0).normal(0.0, 0.01, vecs[:, ric].shape).astype(np.float32)  # ~8 mm
    np.save(root / "new_joint_vecs" / f"{CLIP}.npy", vecs)
    config = BuildConfig(out=tmp_path / "ds", source="humanml3d", root=str(root), progress=False)
    manifest = build_dataset(config, text_encoder=encoder)
    (item,) = manifest["skip_report"]["items"]
    assert (item["id"], item["path"], item["reason"]) == (CLIP, f"new_joint_vecs/{CLIP}.npy", "feature_mismatch")
    assert f"new_joints/{CLIP}.npy" in item["detail"] and "ric: joints recovered from the root and ric groups" in item["detail"]
    assert "rot6d" not in item["detail"]  # only the perturbed group
    assert manifest["skip_report"]["by_reason"] == {"feature_mismatch": 1}
    assert list(manifest["splits"]) == ["test"]  # the copy agrees; the official Mean/Std need no train split

    with pytest.raises(BadInputError, match=rf"new_joint_vecs/{CLIP}\.npy: feature_mismatch .*new_joints/{CLIP}\.npy"):
        build_dataset(replace(config, out=tmp_path / "strict", strict=True), text_encoder=encoder)
    assert not (tmp_path / "strict" / "manifest.json").exists()
    unchecked = build_dataset(replace(config, out=tmp_path / "unchecked", source_options={"verify": "none"}),
                              text_encoder=encoder)
    assert unchecked["skip_report"]["total"] == 0  # not checked: the file's features as they are

    # Another clip's features (a swapped file) are off in every group, not just a little.
    np.save(root / "new_joint_vecs" / f"{CLIP}.npy", np.load(published["features"])[::-1].copy())
    swapped = build_dataset(replace(config, out=tmp_path / "swapped"), text_encoder=encoder)
    assert swapped["skip_report"]["items"][0]["reason"] == "feature_mismatch"
    assert "rot6d" in swapped["skip_report"]["items"][0]["detail"]


@pytest.mark.parametrize("group, noise", [("root_lin_vel", 0.005), ("ric", 0.01), ("rot6d", 0.02),
                                          ("local_vel", 0.005), ("contacts", None)])
def test_each_feature_group_is_checked_against_new_joints(tmp_path, published, group, noise):
    """A feature file that differs from new_joints in any one group is caught, and the group is named."""
    root = write_humanml3d(tmp_path / "h", published)
    clip = build_source("humanml3d", str(root)).load(CLIP)
    assert process_clip(clip, HUMANML3D).features.tobytes() == np.load(published["features"]).tobytes()
    block = clip.meta['features'][:, FeatureLayout(HUMANML3D).slices[group]]
    if noise is None:  # flip 20 % of the foot-contact labels
        flip = np.random.default_rng(1).random(block.shape) < 0.2
        block[flip] = 1.0 - block[flip]
    else:
        block += np.random.default_rng(1).normal(0.0, noise, block.shape).astype(np.float32)
    clip.meta['features'][:, FeatureLayout(HUMANML3D).slices[group]] = block
    skipped = process_clip(clip, HUMANML3D)
    assert skipped.reason == "feature_mismatch" and skipped.path == str(root / "new_joint_vecs" / f"{CLIP}.npy")
    named = {part.split(":")[0] for part in skipped.detail.split(": ", 1)[1].split("; ")}
    # root velocities feed the recovered root trajectory, so they show up in the recovered joints (ric, rot6d)
    assert named == ({"ric", "rot6d"} if group == "root_lin_vel" else {group}), skipped.detail


def test_raw_joints_beside_the_features_are_checked_by_recomputing(tmp_path):
    """raw_pose_processing's joints/ (T + 1 frames, 52 SMPL-H joints, not retargeted): the check recomputes the
    features from them (the features' own computation) and compares group means."""
    from test_features import synthetic_clip

    raw = synthetic_clip(HUMANML3D, HUMANML3D.bone_lengths * 1.08, 81, seed=4, turn_per_frame=0.1)
    features = F.joints_to_features(raw, HUMANML3D)
    smplh = np.concatenate([raw, np.zeros((81, 30, 3))], axis=1).astype(np.float32)
    root = tmp_path / "h"
    for folder, array in (("joints", smplh), ("new_joint_vecs", features)):
        (root / folder).mkdir(parents=True)
        np.save(root / folder / f"{CLIP}.npy", array)
    (root / "texts").mkdir()
    (root / "texts" / f"{CLIP}.txt").write_text(CAPTIONS)
    clip = build_source("humanml3d", str(root)).load(CLIP)
    assert clip.joints.shape == (81, 22, 3) and clip.meta['features'].shape == (80, 263)
    assert process_clip(clip, HUMANML3D).features.tobytes() == features.tobytes()
    clip.meta['features'][:, FeatureLayout(HUMANML3D).slices["rot6d"]] *= 0.9
    skipped = process_clip(clip, HUMANML3D)
    assert skipped.reason == "feature_mismatch" and "rot6d: mean |diff| from recomputed features" in skipped.detail
    assert f"joints/{CLIP}.npy" in skipped.detail


@pytest.mark.parametrize("case, message", [
    ("mean_shape", r"Mean\.npy: the mean must have shape \(263,\) \(the feature dim\), got \(262,\)"),
    ("std_zero", r"Std\.npy: standard deviations must be positive; 1 are not \(first: dim 7"),
    ("std_missing", r"Std\.npy: no such file; .*Mean\.npy is there"),
    ("official_absent", r"--normalization official: .*Mean\.npy: no such file"),
])
def test_bad_official_statistics_are_clear_errors_naming_the_file(tmp_path, published, encoder, case, message):
    root = write_humanml3d(tmp_path / "HumanML3D", published, statistics=case != "official_absent")
    mode = "auto"
    if case == "mean_shape":
        np.save(root / "Mean.npy", np.load(published["mean"])[:-1])
    elif case == "std_zero":
        std = np.load(published["std"])
        std[7] = 0.0
        np.save(root / "Std.npy", std)
    elif case == "std_missing":
        (root / "Std.npy").unlink()
    else:
        mode = "official"
    config = BuildConfig(out=tmp_path / "ds", source="humanml3d", root=str(root), normalization=mode, progress=False)
    with pytest.raises(ValueError, match=message):
        build_dataset(config, text_encoder=encoder)
    assert not (tmp_path / "ds").exists()  # checked before anything is written


def test_cli_options_and_error(tmp_path, published, capsys):
    root = write_humanml3d(tmp_path / "HumanML3D", published)
    np.save(root / "Mean.npy", np.zeros((263, 1), np.float32))
    base = ["--source", "humanml3d", "--root", str(root), "--quiet"]
    assert main([*base, "--out", str(tmp_path / "bad")]) == 2  # a refused setting, as every entry point
    assert f"build_shards: error: {root / 'Mean.npy'}: the mean must have shape (263,)" in capsys.readouterr().err
    assert main([*base, "--out", str(tmp_path / "ds"), "--normalization", "recompute",
                 "--source-option", "features=recompute"]) == 0
    manifest = load_manifest(tmp_path / "ds")
    assert manifest["normalization"]["source"] == "recomputed" and manifest["splits"]["train"]["lengths"] == [169]
    assert "--source-option features=recompute" in manifest["builder"]["command"]
    assert "--normalization recompute" in manifest["builder"]["command"]
    assert main([*base, "--out", str(tmp_path / "nc"), "--no-compat"]) == 2
    assert "features=recompute" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert "--normalization {auto,official,recompute}" in text and "features=auto|file|recompute" in text


# --- the source on its own --------------------------------------------------------------------------------


def test_source_modes(tmp_path, published):
    root = write_humanml3d(tmp_path / "h", published)
    auto = build_source("humanml3d", str(root))
    assert auto.reads_feature_files and auto.item_dir.name == "new_joint_vecs"
    clip = auto.load(CLIP)
    assert isinstance(clip, Clip) and clip.meta['features'].shape == (170, 263) and clip.path.endswith(f"new_joint_vecs/{CLIP}.npy")
    assert clip.joints.shape == (170, 22, 3) and clip.meta['joints_path'].endswith(f"new_joints/{CLIP}.npy")  # verify=all
    assert build_source("humanml3d", str(root), verify="none").load(CLIP).joints is None
    recompute = build_source("humanml3d", str(root), features="recompute")
    assert not recompute.reads_feature_files and recompute.load(CLIP).meta == {}

    # A fraction checks a fixed share of the ids, picked by their hash (the same in every process and run).
    many = build_source("humanml3d", str(root), verify=0.5)
    picked = [many._checks(f"{i:06d}") for i in range(400)]
    assert 150 < sum(picked) < 250 and picked == [build_source("humanml3d", str(root), verify="0.5")._checks(f"{i:06d}")
                                                  for i in range(400)]

    only_vecs = write_humanml3d(tmp_path / "v", published, joints=False)  # the files everyone has
    source = build_source("humanml3d", str(only_vecs))
    assert source.joints_dir is None and source.list_items() == [COPY, CLIP]
    clip = source.load(CLIP)
    assert clip.joints is None and clip.meta['features'].tobytes() == np.load(published["features"]).tobytes()
    (only_vecs / "new_joint_vecs" / "012314.bak.npy").write_bytes(b"")
    assert source.ignored_files() == [str(only_vecs / "new_joint_vecs" / "012314.bak.npy")]
    with pytest.raises(FileNotFoundError, match="new_joints"):
        build_source("humanml3d", str(only_vecs), features="recompute")

    only_joints = write_humanml3d(tmp_path / "j", published, features=False)
    assert not build_source("humanml3d", str(only_joints)).reads_feature_files  # auto falls back to joints
    with pytest.raises(FileNotFoundError, match="features=file.*new_joint_vecs"):
        build_source("humanml3d", str(only_joints), features="file")
    with pytest.raises(ValueError, match="option features"):
        build_source("humanml3d", str(root), features="yes")
    with pytest.raises(ValueError, match="option verify"):
        build_source("humanml3d", str(root), verify=2)


def test_bad_feature_files_are_skipped_with_reasons(tmp_path, published):
    root = write_humanml3d(tmp_path / "h", published)
    folder = root / "new_joint_vecs"
    np.save(folder / "000002.npy", np.zeros((80, 251), np.float32))  # KIT's layout in a HumanML3D folder
    nan = np.load(published["features"])
    nan[3, 5] = np.nan
    np.save(folder / "000003.npy", nan)
    (folder / "000004.npy").write_bytes(b"not numpy")
    (root / "new_joints" / "000005.npy").write_bytes(b"not numpy")  # a good feature file, a broken joint file
    shutil.copyfile(published["features"], folder / "000005.npy")
    np.save(root / "new_joints" / "000006.npy", np.load(published["joints"])[:100])  # the wrong length
    shutil.copyfile(published["features"], folder / "000006.npy")
    for i in ("000002", "000003", "000004", "000005", "000006"):
        (root / "texts" / f"{i}.txt").write_text(CAPTIONS)
    (root / "test.txt").write_text(f"{COPY}\n000404\n")
    source = build_source("humanml3d", str(root))
    assert [source.load(i).reason for i in ("000002", "000003", "000004", "000005")] == [
        "bad_shape", "nan_frames", "unreadable", "feature_mismatch"]
    assert "(T>0, 263)" in source.load("000002").detail and "new_joints/000005.npy" in source.load("000005").detail
    missing = source.load("000404")
    assert missing.reason == "missing_file" and missing.path.endswith("new_joint_vecs/000404.npy")
    assert "feature file" in missing.detail
    wrong_length = process_clip(source.load("000006"), HUMANML3D)
    assert wrong_length.reason == "feature_mismatch" and "100 frames" in wrong_length.detail


def test_kit_feature_files_251_in_millimetres(tmp_path):
    """KIT's layout: (T, 251) feature files in mm. The target skeleton is measured on the reference clip
    03950 (its joints, or without a joint folder the joints recovered from its features), and the check
    scales its length tolerances to millimetres."""
    skeleton, clip = kit_skeleton_and_clip(frames=60)
    features = F.joints_to_features(clip, skeleton)
    new_joints = F.features_to_joints(features, skeleton).astype(np.float32)  # how HumanML3D saved new_joints
    root = tmp_path / "KIT-ML"
    for folder, array in (("new_joint_vecs", features), ("new_joints", new_joints)):
        (root / folder).mkdir(parents=True)
        for clip_id in ("03950", "00001"):
            np.save(root / folder / f"{clip_id}.npy", array)
    (root / "texts").mkdir()
    for clip_id in ("03950", "00001"):
        (root / "texts" / f"{clip_id}.txt").write_text(CAPTIONS)
    source = build_source("kit", str(root))
    target = source.target_skeleton()
    np.testing.assert_allclose(target.bone_lengths, skeleton.bone_lengths, rtol=1e-4)
    loaded = source.load("00001")
    assert loaded.meta['features'].shape == (59, 251) and loaded.joints.shape == (59, 21, 3)
    record = process_clip(loaded, target, min_frames=24)
    assert record.features.tobytes() == features.tobytes()  # agrees: kept as it is
    loaded.meta['features'][:, FeatureLayout(KIT).slices["ric"]] += 20.0  # 2 cm in mm units
    assert process_clip(loaded, target, min_frames=24).reason == "feature_mismatch"

    shutil.rmtree(root / "new_joints")
    without_joints = build_source("kit", str(root))
    np.testing.assert_allclose(without_joints.target_skeleton().bone_lengths, skeleton.bone_lengths, rtol=1e-4)
    assert without_joints.load("00001").joints is None
