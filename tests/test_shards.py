"""The clip → record stage, the shard writers, the manifest and the two-pass build (preprocess/)."""

from __future__ import annotations

import hashlib
import io
import json
import re
import tarfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import webdataset as wds

from mfm.features import FeatureStats, joints_to_features
from mfm.layout import FeatureLayout
from mfm.skeleton import HUMANML3D
from preprocess.clip import Caption, Clip, SkippedInput
from preprocess.processing import (
    Record,
    RecordCaption,
    captions_to_frames,
    process_clip,
    split_into_windows,
)
from preprocess.shards import (
    BadInputError,
    BuildConfig,
    DatasetExistsError,
    ManifestError,
    OutputFolderError,
    SplitShardWriter,
    TextFeatures,
    build_dataset,
    derive_dataset_id,
    load_manifest,
    parquet_schema,
)

FPS = HUMANML3D.fps


def make_joints(frames: int, seed: int = 0, fps: float = FPS) -> np.ndarray:
    """A plausible (frames, 22, 3) clip: the target skeleton's rest pose walking forward along +Z with a
    per-joint wobble, so every feature group varies."""
    rng = np.random.default_rng(seed)
    offsets, parents = HUMANML3D.target_offsets(), HUMANML3D.parents
    rest = np.zeros((HUMANML3D.num_joints, 3))
    for j in range(1, HUMANML3D.num_joints):
        rest[j] = rest[parents[j]] + offsets[j]
    rest[:, 1] -= rest[:, 1].min()
    t = np.arange(frames)[:, None, None] / fps
    wobble = 0.03 * np.sin(2 * np.pi * (t * rng.uniform(0.5, 2.0, (1, 22, 3)) + rng.uniform(0, 1, (1, 22, 3))))
    joints = rest[None] + wobble
    joints[..., 2] += rng.uniform(0.5, 1.5) * t[..., 0]
    return joints.astype(np.float32)


def make_clip(cid: str, frames: int = 81, *, split: str = "train", seed: int = 0, fps: float = FPS,
              captions: list[Caption] | None = None, action: str | None = "walk", joints=None) -> Clip:
    return Clip(
        id=cid,
        joints=make_joints(frames, seed, fps) if joints is None else joints,
        fps=fps,
        skeleton="humanml3d",
        captions=[Caption(f"a person walks, take {seed % 3}")] if captions is None else captions,
        split=split,
        source="listsource",
        action=action,
        path=f"/data/listsource/{cid}.npy",
    )


class ListSource:
    """A source over a fixed dict of items: a Clip, a SkippedInput, or an exception that ``load`` raises.
    Module level and plain data, so it pickles into worker processes."""

    name = "listsource"
    skeleton = "humanml3d"

    def __init__(self, items: dict) -> None:
        self.items = items

    def list_items(self) -> list[str]:
        return sorted(self.items)

    def load(self, item: str):
        value = self.items[item]
        if isinstance(value, Exception):
            raise value
        return value


def good_items(n: int = 9) -> dict:
    splits = ["train", "train", "train", "val", "test"]
    return {
        f"m{i:03d}": make_clip(f"m{i:03d}", frames=60 + 7 * i, split=splits[i % 5], seed=i,
                               action=["walk", "run", None][i % 3],
                               captions=[Caption(f"a person walks, take {i % 3}", ("a/DET", "person/NOUN")),
                                         Caption("someone moves forward", start=0.5, end=3.0)]
                               + [Caption("  ")] * (i == 0))
        for i in range(n)
    }


def bad_items() -> dict:
    nan = make_joints(81, 1)
    nan[10, 3, 1] = np.nan
    inf = make_joints(81, 2)
    inf[20, 0, 0] = np.inf
    return {
        "b_nan": make_clip("b_nan", joints=nan),
        "b_inf": make_clip("b_inf", joints=inf),
        "b_joints": make_clip("b_joints", joints=make_joints(81)[:, :21]),
        "b_ndim": make_clip("b_ndim", joints=make_joints(81).reshape(81, -1)),
        "b_empty": make_clip("b_empty", joints=make_joints(81)[:0]),
        "b_short": make_clip("b_short", frames=30),
        "b_long": make_clip("b_long", frames=260),
        "b_nocap": make_clip("b_nocap", captions=[]),
        "b_emptycap": make_clip("b_emptycap", captions=[Caption(""), Caption("   ")]),
        "b_unreadable": SkippedInput("b_unreadable", "/data/listsource/b_unreadable.npy", "unreadable", "truncated file"),
        "b_raises": OSError("disk read error"),
    }


EXPECTED_REASONS = {
    "b_nan": "nan_frames", "b_inf": "nan_frames", "b_joints": "bad_shape", "b_ndim": "bad_shape", "b_empty": "bad_shape",
    "b_short": "too_short", "b_long": "too_long", "b_nocap": "no_captions", "b_emptycap": "no_captions",
    "b_unreadable": "unreadable", "b_raises": "unreadable",
}


@pytest.fixture(scope="module")
def encoder():
    from mfm.text import build_text_encoder

    return build_text_encoder("minilm")


# --- process_clip ---------------------------------------------------------------------------------------


def test_process_clip_features_and_caption_spans():
    clip = make_clip("c1", frames=101, captions=[
        Caption("whole clip"), Caption("  padded  ", ("p/ADJ",), start=1.0, end=4.0),
        Caption("hml3d zero tags", start=0.0, end=0.0), Caption("past the end", start=2.0, end=99.0),
        Caption("too short", start=1.0, end=2.0), Caption(""),
    ])
    record = process_clip(clip, HUMANML3D)
    assert isinstance(record, Record)
    assert record.features.dtype == np.float32 and record.features.shape == (100, 263)
    np.testing.assert_array_equal(record.features, joints_to_features(clip.joints, HUMANML3D, compat=True))
    spans = [(c.text, c.tokens, c.start_frame, c.end_frame) for c in record.captions]
    assert spans == [("whole clip", (), 0, 100), ("padded", ("p/ADJ",), 20, 80), ("hml3d zero tags", (), 0, 100),
                     ("past the end", (), 40, 100)]
    assert record.dropped_captions == {"span_too_short": 1, "empty": 1}
    assert (record.id, record.split, record.skeleton, record.fps, record.action) == ("c1", "train", "humanml3d", 20.0, "walk")


def test_process_clip_resamples_to_skeleton_fps():
    # 60 fps -> 20 fps: an integer ratio keeps every third frame exactly.
    clip = make_clip("c60", frames=241, fps=60.0)
    record = process_clip(clip, HUMANML3D)
    assert record.length == 80
    np.testing.assert_array_equal(record.features, joints_to_features(clip.joints[::3], HUMANML3D))


@pytest.mark.parametrize("item", [k for k in EXPECTED_REASONS if k not in ("b_unreadable", "b_raises")])
def test_process_clip_skip_reasons(item):
    clip = bad_items()[item]
    skipped = process_clip(clip, HUMANML3D)
    assert isinstance(skipped, SkippedInput)
    assert (skipped.id, skipped.path, skipped.reason) == (item, clip.path, EXPECTED_REASONS[item])
    assert skipped.detail


def test_process_clip_refuses_complex_joints():
    skipped = process_clip(make_clip("cx", joints=make_joints(81) * (1 + 0.5j)), HUMANML3D)
    assert isinstance(skipped, SkippedInput) and skipped.reason == "bad_shape" and "complex" in skipped.detail


def test_length_limits_are_inclusive_feature_frames():
    assert isinstance(process_clip(make_clip("a", frames=41), HUMANML3D, min_frames=40), Record)
    assert process_clip(make_clip("a", frames=40), HUMANML3D, min_frames=40).reason == "too_short"
    assert isinstance(process_clip(make_clip("a", frames=200), HUMANML3D, max_frames=199), Record)
    assert process_clip(make_clip("a", frames=201), HUMANML3D, max_frames=199).reason == "too_long"


def test_long_clip_windows():
    clip = make_clip("long", frames=451, captions=[Caption("all of it"), Caption("the start", start=0.0, end=3.0)])
    record = process_clip(clip, HUMANML3D, max_frames=196, long_clips="window")
    assert record.length == 450
    windows = split_into_windows(record, window=196, min_frames=40)
    # 450 = 196 + 196 + 58: the tail is long enough to keep.
    assert [w.id for w in windows] == ["long-w000", "long-w001", "long-w002"]
    assert [w.length for w in windows] == [196, 196, 58]
    np.testing.assert_array_equal(np.concatenate([w.features for w in windows]), record.features)
    assert [(c.text, c.start_frame, c.end_frame) for c in windows[0].captions] == [("all of it", 0, 196), ("the start", 0, 60)]
    assert [(c.text, c.start_frame, c.end_frame) for c in windows[2].captions] == [("all of it", 0, 58)]


# --- writers ----------------------------------------------------------------------------------------------


def hand_made_records(n: int, dim: int = 263, text_dim: int = 8, tokens: int = 0):
    rng = np.random.default_rng(7)
    out = []
    for i in range(n):
        captions = [RecordCaption(f"caption {i} {k} ünïcode", ("w/NOUN",) * k, k, 10 + i) for k in range(1 + i % 3)]
        record = Record(id=f"r{i:02d}", split="train", source="hand", skeleton="humanml3d", fps=20.0,
                        features=rng.standard_normal((10 + i, dim)).astype(np.float32), captions=captions,
                        action=None if i % 2 else "jump")
        c = len(captions)
        text = TextFeatures(
            pooled=rng.standard_normal((c, text_dim)).astype(np.float32),
            tokens=rng.standard_normal((c, tokens, text_dim)).astype(np.float32) if tokens else None,
            token_lengths=rng.integers(1, tokens + 1, c).astype(np.int32) if tokens else None,
        )
        out.append((record, text))
    return out


@pytest.mark.parametrize("tokens", [0, 5])
def test_writers_round_trip_bit_exact(tmp_path, tokens):
    items = hand_made_records(5, tokens=tokens)
    writer = SplitShardWriter(tmp_path, "train", shard_size=2, formats=("tar", "parquet"),
                              schema=parquet_schema(263, 8, token_features=bool(tokens)))
    for record, text in items:
        writer.write(record, text)
    shards = writer.close()
    assert [s.num_motions for s in shards["tar"]] == [2, 2, 1] == [s.num_motions for s in shards["parquet"]]
    assert [s.path for s in shards["tar"]] == [f"train/shard-0000{i}.tar" for i in range(3)]
    for info in shards["tar"] + shards["parquet"]:
        data = (tmp_path / info.path).read_bytes()
        assert (len(data), hashlib.sha256(data).hexdigest()) == (info.bytes, info.sha256)

    # tarfile: fixed headers, sorted members.
    with tarfile.open(tmp_path / "train/shard-00000.tar") as tar:
        members = tar.getmembers()
    suffixes = ["features.npy", "meta.json", "text_emb.npy"] + (["text_token_len.npy", "text_tokens.npy"] if tokens else [])
    assert [m.name for m in members] == [f"r{i:02d}.{s}" for i in range(2) for s in suffixes]
    assert {(m.mtime, m.uid, m.gid, m.uname, m.gname, m.mode) for m in members} == {(0, 0, 0, "", "", 0o444)}

    # webdataset: the reader the training pipeline uses.
    urls = [str(tmp_path / s.path) for s in shards["tar"]]
    samples = list(wds.WebDataset(urls, shardshuffle=False, empty_check=False))
    assert [s["__key__"] for s in samples] == [r.id for r, _ in items]
    for sample, (record, text) in zip(samples, items):
        features = np.load(io.BytesIO(sample["features.npy"]))
        assert features.dtype == np.float32 and features.tobytes() == record.features.tobytes()
        assert np.load(io.BytesIO(sample["text_emb.npy"])).tobytes() == text.pooled.tobytes()
        meta = json.loads(sample["meta.json"])
        assert meta["length"] == record.length and meta["action"] == record.action
        assert [(c["text"], tuple(c["tokens"]), c["start_frame"], c["end_frame"]) for c in meta["captions"]] == [
            (c.text, c.tokens, c.start_frame, c.end_frame) for c in record.captions]
        if tokens:
            assert np.load(io.BytesIO(sample["text_tokens.npy"])).tobytes() == text.tokens.tobytes()
            np.testing.assert_array_equal(np.load(io.BytesIO(sample["text_token_len.npy"])), text.token_lengths)

    # Parquet: same records, same order, bit-exact arrays.
    table = pa.concat_tables([pq.read_table(tmp_path / s.path) for s in shards["parquet"]])
    assert table.column("id").to_pylist() == [r.id for r, _ in items]
    for row, (record, text) in enumerate(items):
        features = np.asarray(table.column("features")[row].values.flatten(), dtype=np.float32).reshape(-1, 263)
        assert features.tobytes() == record.features.tobytes()
        emb = np.asarray(table.column("text_emb")[row].values.flatten(), dtype=np.float32).reshape(-1, 8)
        assert emb.tobytes() == text.pooled.tobytes()
        assert table.column("span_start")[row].as_py() == [c.start_frame for c in record.captions]
        assert table.column("caption_tokens")[row].as_py() == [list(c.tokens) for c in record.captions]
        assert table.column("action")[row].as_py() == record.action
        if tokens:
            tok = np.asarray(table.column("text_tokens")[row].values.flatten().flatten(), dtype=np.float32)
            assert tok.tobytes() == text.tokens.tobytes()


# --- the build ------------------------------------------------------------------------------------------


def dataset_bytes(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def built(tmp_path_factory, encoder):
    """One build of good + bad items (shard size 2), and its config."""
    out = tmp_path_factory.mktemp("build") / "ds"
    config = BuildConfig(out=out, source="listsource", shard_size=2, progress=False)
    source = ListSource({**good_items(), **bad_items()})
    manifest = build_dataset(config, source=source, text_encoder=encoder)
    return out, manifest, source, config


def test_manifest_counts_checksums_and_normalisation(built):
    out, manifest, source, _ = built
    assert manifest == load_manifest(out, verify="sha256")
    good = good_items()
    for split in ("train", "val", "test"):
        ids = [k for k, clip in sorted(good.items()) if clip.split == split]
        entry = manifest["splits"][split]
        assert entry["num_motions"] == len(ids) == sum(s["num_motions"] for s in entry["shards"])
        assert [s["num_motions"] for s in entry["parquet"]] == [s["num_motions"] for s in entry["shards"]]
        assert entry["lengths"] == [len(good[i].joints) - 1 for i in ids]
        assert entry["num_frames"] == sum(entry["lengths"])
        assert entry["num_captions"] == 2 * len(ids)  # the second caption's span 0.5-3.0 s is 50 frames
        for shard in entry["shards"] + entry["parquet"]:
            data = (out / shard["path"]).read_bytes()
            assert shard["bytes"] == len(data) and shard["sha256"] == hashlib.sha256(data).hexdigest()
    assert list(manifest["splits"]) == ["train", "val", "test"]
    assert manifest["action_classes"] == ["run", "walk"]
    assert manifest["feature_spec"]["dim"] == 263 and manifest["feature_spec"]["groups"]["contacts"] == [259, 263]
    assert manifest["text_encoder"]["id"] == "minilm" and manifest["text_encoder"]["dim"] == 384
    assert manifest["text_encoder"]["num_distinct_captions"] == 4

    # Normalisation = FeatureStats over every frame of the train records, read back from the shards.
    stats = FeatureStats()
    urls = [str(out / s["path"]) for s in manifest["splits"]["train"]["shards"]]
    for sample in wds.WebDataset(urls, shardshuffle=False, empty_check=False):
        stats.update(np.load(io.BytesIO(sample["features.npy"])))
    mean, std = stats.mean_std(FeatureLayout(HUMANML3D))
    assert np.array(manifest["normalization"]["mean"], np.float32).tobytes() == mean.tobytes()
    assert np.array(manifest["normalization"]["std"], np.float32).tobytes() == std.tobytes()
    assert not (out / ".build-tmp").exists()


def test_skip_report_names_every_bad_item(built):
    _, manifest, _, _ = built
    report = manifest["skip_report"]
    assert report["total"] == len(EXPECTED_REASONS)
    assert {item["id"]: item["reason"] for item in report["items"]} == EXPECTED_REASONS
    assert [item["id"] for item in report["items"]] == sorted(EXPECTED_REASONS)  # list_items order
    assert report["by_reason"] == {"bad_shape": 3, "nan_frames": 2, "no_captions": 2, "too_long": 1,
                                   "too_short": 1, "unreadable": 2}
    by_id = {item["id"]: item for item in report["items"]}
    assert by_id["b_nan"]["path"] == "/data/listsource/b_nan.npy" and "frame 10" in by_id["b_nan"]["detail"]
    assert "disk read error" in by_id["b_raises"]["detail"]
    assert report["dropped_captions"] == {"empty": 1}  # from m000; skipped clips count in their detail


def test_text_embeddings_match_the_encoder(built, encoder):
    out, manifest, _, _ = built
    sample = next(iter(wds.WebDataset([str(out / manifest["splits"]["val"]["shards"][0]["path"])],
                                      shardshuffle=False, empty_check=False)))
    texts = [c["text"] for c in json.loads(sample["meta.json"])["captions"]]
    emb = np.load(io.BytesIO(sample["text_emb.npy"]))
    np.testing.assert_allclose(emb, encoder.encode(texts).pooled, atol=1e-5)


def test_two_builds_are_byte_identical_whatever_the_worker_count(built, tmp_path, encoder):
    out, manifest, source, config = built
    again = tmp_path / "again"
    from dataclasses import replace

    build_dataset(replace(config, out=again, workers=2), source=source, text_encoder=encoder)
    assert dataset_bytes(again) == dataset_bytes(out)


def test_strict_names_the_first_bad_file(tmp_path, encoder):
    source = ListSource({**good_items(3), **bad_items()})
    with pytest.raises(BadInputError, match=r"/data/listsource/b_empty\.npy: bad_shape \(expected \(T>0, 22, 3\)"):
        build_dataset(BuildConfig(out=tmp_path / "ds", strict=True, progress=False), source=source, text_encoder=encoder)
    assert not (tmp_path / "ds" / "manifest.json").exists()
    assert not (tmp_path / "ds" / ".build-tmp").exists()


def test_refuses_to_overwrite_and_overwrite_removes_stale_shards(tmp_path, encoder):
    out = tmp_path / "ds"
    config = BuildConfig(out=out, shard_size=1, progress=False)
    build_dataset(config, source=ListSource(good_items(6)), text_encoder=encoder)
    assert (out / "train" / "shard-00003.tar").exists()
    with pytest.raises(DatasetExistsError, match="--overwrite"):
        build_dataset(config, source=ListSource(good_items(3)), text_encoder=encoder)
    (out / "notes.txt").write_text("mine")
    from dataclasses import replace

    manifest = build_dataset(replace(config, overwrite=True), source=ListSource(good_items(3)), text_encoder=encoder)
    listed = {e["path"] for s in manifest["splits"].values() for e in s["shards"] + s["parquet"]}
    on_disk = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.suffix in (".tar", ".parquet")}
    assert on_disk == listed and len(listed) == 2 * 3
    assert (out / "notes.txt").read_text() == "mine"


def test_an_interrupted_build_is_named_by_its_marker_and_only_that_is_replaced(tmp_path, encoder, monkeypatch):
    """Issue 24, finding 3: a build names every path in build-in-progress.json before creating it, so a build that
    died before its manifest is recognised as ours and its files, and only those, are replaced by the next one."""
    import preprocess.shards as shards

    out = tmp_path / "ds"
    config = BuildConfig(out=out, shard_size=1, progress=False)

    def crash(*_args, **_kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(shards, "write_manifest", crash)
        with pytest.raises(KeyboardInterrupt):
            build_dataset(config, source=ListSource(good_items(6)), text_encoder=encoder)
    marker = json.loads((out / "build-in-progress.json").read_text())
    written = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.suffix in (".tar", ".parquet")}
    assert len(written) == 2 * 6 and written <= set(marker["paths"]) and not (out / "manifest.json").exists()
    (out / "train" / "notes.txt").write_text("mine")
    manifest = build_dataset(config, source=ListSource(good_items(3)), text_encoder=encoder)  # no --overwrite needed
    listed = {e["path"] for s in manifest["splits"].values() for e in s["shards"] + s["parquet"]}
    on_disk = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.suffix in (".tar", ".parquet")}
    assert on_disk == listed and len(listed) == 2 * 3
    assert (out / "train" / "notes.txt").read_text() == "mine" and not (out / "build-in-progress.json").exists()


def test_a_marker_or_manifest_that_is_not_ours_names_nothing_to_delete(tmp_path, encoder):
    """Issue 24, finding 3: only our own marker and manifest say what a build may delete; a file of that name from
    elsewhere (or one naming paths a build never writes) makes the folder foreign: refused, untouched."""
    for name, text in (("build-in-progress.json", json.dumps({"paths": ["train/shard-00000.tar"]})),
                       ("build-in-progress.json", json.dumps({"format": "mfm-dataset-build", "paths": ["../x"]})),
                       ("manifest.json", json.dumps({"splits": {"train": {"shards": [{"path": "../../etc/x"}]}}}))):
        out = tmp_path / f"case-{len(list(tmp_path.iterdir()))}"
        (out / "train").mkdir(parents=True)
        (out / "train" / "shard-00000.tar").write_bytes(b"theirs")
        (out / name).write_text(text)
        before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
        with pytest.raises(OutputFolderError, match=f"--out {out}: .*{name}.* is not a"):
            build_dataset(replace(BuildConfig(out=out, progress=False), overwrite=True),
                          source=ListSource(good_items(3)), text_encoder=encoder)
        assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


def test_load_manifest_rejects_bad_versions_and_files(built, tmp_path):
    out, manifest, _, _ = built
    copy = tmp_path / "copy"
    for rel, data in dataset_bytes(out).items():
        (copy / rel).parent.mkdir(parents=True, exist_ok=True)
        (copy / rel).write_bytes(data)
    with pytest.raises(ManifestError, match="no manifest"):
        load_manifest(tmp_path / "nowhere")
    shard = copy / manifest["splits"]["train"]["shards"][1]["path"]
    data = bytearray(shard.read_bytes())
    data[700] ^= 0xFF
    shard.write_bytes(bytes(data))
    load_manifest(copy, verify="size")  # same size: only the hash notices
    with pytest.raises(ManifestError, match=f"{shard.name}: sha256"):
        load_manifest(copy, verify="sha256")
    shard.write_bytes(bytes(data[:1000]))
    with pytest.raises(ManifestError, match=f"{shard.name}: 1000 bytes"):
        load_manifest(copy)
    (copy / "manifest.json").write_text(json.dumps({**manifest, "format_version": 99}))
    with pytest.raises(ManifestError, match="format_version 99"):
        load_manifest(copy, verify="none")


def test_load_manifest_derives_the_dataset_id_and_keeps_files_under_the_folder(built, tmp_path):
    """Issue 24, items 1 and 7, on the builder's side: the stored id must be the one derived from the shard list, and
    every listed file lies under the dataset folder (an absolute path is never opened)."""
    out, manifest, _, _ = built
    assert manifest["format_version"] == 2 and manifest["dataset_id"] == derive_dataset_id(manifest)
    copy = tmp_path / "copy"
    for rel, data in dataset_bytes(out).items():
        (copy / rel).parent.mkdir(parents=True, exist_ok=True)
        (copy / rel).write_bytes(data)
    edited = json.loads(json.dumps(manifest))
    edited["splits"]["train"]["shards"][0]["num_motions"] += 1
    (copy / "manifest.json").write_text(json.dumps(edited))
    load_manifest(copy, verify="none")  # structure only
    with pytest.raises(ManifestError, match=rf"manifest\.json: dataset_id {manifest['dataset_id'][:16]}… is not the "
                                            "id derived from its shard list"):
        load_manifest(copy)
    outside = tmp_path / "outside.tar"
    outside.write_bytes((copy / manifest["splits"]["train"]["shards"][0]["path"]).read_bytes())
    edited = json.loads(json.dumps(manifest))
    edited["splits"]["train"]["shards"][0]["path"] = str(outside)
    edited["dataset_id"] = derive_dataset_id(edited)
    (copy / "manifest.json").write_text(json.dumps(edited))
    with pytest.raises(ManifestError, match=rf"shard path '{re.escape(str(outside))}' is absolute"):
        load_manifest(copy, verify="sha256")


def test_token_features_tar_only(tmp_path, encoder):
    out = tmp_path / "tok"
    config = BuildConfig(out=out, token_features=True, max_tokens=8, formats=("tar",), progress=False)
    manifest = build_dataset(config, source=ListSource(good_items(5)), text_encoder=encoder)
    assert manifest["text_encoder"]["token_features"] is True and manifest["text_encoder"]["max_tokens"] == 8
    assert "--token-features --max-tokens 8" in manifest["builder"]["command"]
    assert all(split["parquet"] == [] for split in manifest["splits"].values())
    assert not list(out.rglob("*.parquet"))
    for sample in wds.WebDataset([str(out / manifest["splits"]["train"]["shards"][0]["path"])],
                                 shardshuffle=False, empty_check=False):
        texts = [c["text"] for c in json.loads(sample["meta.json"])["captions"]]
        tokens = np.load(io.BytesIO(sample["text_tokens.npy"]))
        lengths = np.load(io.BytesIO(sample["text_token_len.npy"]))
        expected = encoder.encode(texts, token_features=True, max_tokens=8)
        assert tokens.shape == (len(texts), 8, 384) and lengths.dtype == np.int32
        np.testing.assert_array_equal(lengths, expected.token_lengths)
        np.testing.assert_allclose(tokens, expected.tokens, atol=1e-5)


# --- a HumanML3D folder with bad input, end to end ----------------------------------------------------------


def write_humanml3d_folder(root: Path) -> Path:
    """A tiny HumanML3D layout with every kind of bad input a real folder has been seen to hold."""
    good = "a person walks forward.#a/DET person/NOUN walk/VERB forward/ADV#0.0#0.0\n"
    files = {
        "000001": (make_joints(81, 1), good + "bad number#t/X#abc#2.0\nreversed#t/X#5.0#2.0\nnegative#t/X#-1#2\n"),
        "000002": (make_joints(81, 2), good),
        "000003": (make_joints(81, 3), "only a reversed span#t/X#5.0#2.0\n"),
        "000004": (make_joints(81, 4) * (1 + 1j), good),
    }
    (root / "new_joints").mkdir(parents=True)
    (root / "texts").mkdir()
    for clip_id, (joints, text) in files.items():
        np.save(root / "new_joints" / f"{clip_id}.npy", joints)
        (root / "texts" / f"{clip_id}.txt").write_text(text)
    np.save(root / "new_joints" / "000001.bak.npy", make_joints(81, 9))  # a stray backup: not id 000001
    (root / "texts" / "000001.bak.txt").write_text(files["000001"][1])
    (root / "train.txt").write_text("000001\n000003\n000004\n000404\n")  # 000404 has no joint file
    (root / "val.txt").write_text("000002\n")
    return root


def test_humanml3d_folder_build_counts_every_bad_input(tmp_path, encoder):
    root = write_humanml3d_folder(tmp_path / "HumanML3D")
    config = BuildConfig(out=tmp_path / "ds", source="humanml3d", root=str(root), progress=False)
    manifest = build_dataset(config, text_encoder=encoder)  # no abort on the backup's duplicate id
    assert {name: split["num_motions"] for name, split in manifest["splits"].items()} == {"train": 1, "val": 1}
    report = manifest["skip_report"]
    assert [(i["id"], i["path"], i["reason"]) for i in report["items"]] == [
        ("000003", "texts/000003.txt", "no_captions"),
        ("000004", "new_joints/000004.npy", "bad_shape"),
        ("000404", "new_joints/000404.npy", "missing_file"),
    ]
    details = {i["id"]: i["detail"] for i in report["items"]}
    assert "span_end_not_after_start" in details["000003"] and "complex" in details["000004"]
    assert "train.txt" in details["000404"]
    assert report["by_reason"] == {"bad_shape": 1, "missing_file": 1, "no_captions": 1} and report["total"] == 3
    assert report["dropped_captions"] == {"span_end_not_after_start": 1, "span_negative": 1, "span_not_a_number": 1}
    assert report["ignored_files"] == {"count": 1, "paths": ["new_joints/000001.bak.npy"]}
    assert load_manifest(config.out, verify="sha256") == manifest

    with pytest.raises(BadInputError, match=r"000003\.txt: no_captions"):
        build_dataset(replace(config, out=tmp_path / "strict", strict=True), text_encoder=encoder)


def test_an_overflowing_span_and_a_line_without_tags_are_counted_not_fatal(tmp_path, encoder):
    """Issue 24, finding 8: a HumanML3D caption span ``#0.0#1e308`` stopped the whole build with OverflowError and no
    manifest, and lines with no ``#`` fields were kept silently as whole-clip captions. Both are now dropped and
    counted by reason in the skip report; a clip left with no caption is skipped, naming them."""
    good = "a person walks forward.#a/DET person/NOUN walk/VERB forward/ADV#0.0#0.0\n"
    root = tmp_path / "HumanML3D"
    (root / "new_joints").mkdir(parents=True)
    (root / "texts").mkdir()
    texts = {"000001": good + "walks on forever#walk/VERB#0.0#1e308\nplain text, no tags\n",
             "000002": "walks on forever#walk/VERB#0.0#1e308\nanother plain line\n"}
    for index, (clip_id, text) in enumerate(texts.items()):
        np.save(root / "new_joints" / f"{clip_id}.npy", make_joints(81, index))
        (root / "texts" / f"{clip_id}.txt").write_text(text)
    config = BuildConfig(out=tmp_path / "ds", source="humanml3d", root=str(root), progress=False)
    manifest = build_dataset(config, text_encoder=encoder)  # used to raise OverflowError
    report = manifest["skip_report"]
    assert report["dropped_captions"] == {"no_tags": 1, "span_out_of_range": 1}
    (skipped,) = report["items"]
    assert (skipped["id"], skipped["reason"]) == ("000002", "no_captions")
    assert "1 no_tags" in skipped["detail"] and "1 span_out_of_range" in skipped["detail"]
    assert sum(split["num_motions"] for split in manifest["splits"].values()) == 1
    assert load_manifest(config.out) == manifest
    kept, dropped = captions_to_frames([Caption("x", start=1e308, end=None), Caption("y", start=0.0, end=1e308),
                                        Caption("z", start=1e300, end=1e301)], length=100, fps=20.0, min_frames=1)
    assert kept == [] and dropped == {"span_out_of_range": 2, "span_too_short": 1}  # 1e300 s is past the clip


def test_duplicate_ids_are_skipped_unless_strict(tmp_path, encoder):
    second = replace(make_clip("m001", seed=5), path="/data/listsource/copy/m001.npy")  # another clip called m001
    source = ListSource({**good_items(3), "m999": second})
    manifest = build_dataset(BuildConfig(out=tmp_path / "ds", progress=False), source=source, text_encoder=encoder)
    assert sum(s["num_motions"] for s in manifest["splits"].values()) == 3
    (item,) = manifest["skip_report"]["items"]
    assert (item["id"], item["path"], item["reason"]) == ("m001", "/data/listsource/copy/m001.npy", "duplicate_id")
    assert "/data/listsource/m001.npy" in item["detail"]  # names the first holder of the id
    with pytest.raises(BadInputError, match="duplicate_id"):
        build_dataset(BuildConfig(out=tmp_path / "strict", strict=True, progress=False), source=source, text_encoder=encoder)
