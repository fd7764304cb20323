"""End to end: the build_shards CLI on the synthetic source and on the embedded default (DeepMimic + MiniLM)."""

from __future__ import annotations

import hashlib
import io
import json
import os
import subprocess
import sys
from concurrent.futures import Future
from functools import partial
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import webdataset as wds
from conftest import start_two_at_a_time

from mfm.features import FeatureStats
from mfm.layout import FeatureLayout
from mfm.skeleton import HUMANML3D
from preprocess.build_shards import main
from preprocess.shards import load_manifest

REPO_ROOT = Path(__file__).resolve().parents[1]
SCRIPT = REPO_ROOT / "preprocess" / "build_shards.py"
pytestmark = pytest.mark.slow


def run_cli(args: list[str], cwd: Path, *, module: bool = False,
            env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    entry = ["-m", "preprocess.build_shards"] if module else [str(SCRIPT)]
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1", **(env or {})}
    return subprocess.run([sys.executable, *entry, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


def files_of(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def read_tar_records(root: Path, entries: list[dict]) -> list[dict]:
    return list(wds.WebDataset([str(root / e["path"]) for e in entries], shardshuffle=False, empty_check=False))


SYNTHETIC = ["--source", "synthetic", "--num-clips", "40", "--seed", "3", "--shard-size", "8", "--quiet",
             "--source-option", "corrupt=nan,bad_shape,short,long,no_captions"]


# The CLI launches of this file: arguments and run_cli options. Each runs in a current folder of its own.
LAUNCHES = {
    "synthetic": ([*SYNTHETIC, "--out", "syn", "--workers", "2"], {}),
    "wandb_offline": (["--source", "synthetic", "--num-clips", "6", "--shard-size", "8", "--quiet", "--out", "syn"],
                      {"env": {"WANDB_MODE": "offline"}}),
    "module_help": (["--help"], {"module": True}),
    "no_arguments": ([], {}),  # the embedded default: DeepMimic + MiniLM into data/deepmimic-minilm
}


@pytest.fixture(scope="module")
def launches(tmp_path_factory) -> dict[str, tuple[Path, Future]]:
    """Every launch of LAUNCHES, started together (start_two_at_a_time: most of a launch is a single-threaded Python
    start, torch and the text encoder). Per launch its current folder and its result."""
    root = tmp_path_factory.mktemp("cli")
    for name in LAUNCHES:
        (root / name).mkdir()
    started = start_two_at_a_time({name: partial(run_cli, args, root / name, **options)
                                   for name, (args, options) in LAUNCHES.items()})
    return {name: (root / name, started[name]) for name in LAUNCHES}


@pytest.fixture(scope="module")
def synthetic_build(launches):
    cwd, launch = launches["synthetic"]
    result = launch.result()
    assert result.returncode == 0, result.stderr
    return cwd / "syn", result


def test_stdout_starts_with_the_summary_under_wandb_offline(launches):
    """WANDB_MODE=offline (common among W&B users) makes transformers print "[INFO] Running in WANDB offline mode"
    to stdout when the text encoder loads: that chatter goes to stderr, stdout's first line is the summary."""
    result = launches["wandb_offline"][1].result()
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("syn: train"), result.stdout[:500]
    assert "Running in WANDB offline mode" not in result.stdout
    assert "Running in WANDB offline mode" in result.stderr  # the test is not vacuous: the chatter happened


def test_synthetic_cli_artifacts(synthetic_build):
    out, result = synthetic_build
    manifest = load_manifest(out, verify="sha256")
    assert result.stdout.startswith("syn: train")  # the summary line

    report = manifest["skip_report"]
    assert report["by_reason"] == {"bad_shape": 1, "nan_frames": 1, "no_captions": 1, "too_long": 1, "too_short": 1}
    assert [i["id"] for i in report["items"]] == ["corrupt_bad_shape", "corrupt_long", "corrupt_nan",
                                                  "corrupt_no_captions", "corrupt_short"]
    splits = manifest["splits"]
    assert sum(s["num_motions"] for s in splits.values()) == 40  # every generated clip is 2-10 s: all kept
    assert set(splits) <= {"train", "val", "test"} and "train" in splits
    assert manifest["builder"]["command"].startswith("python -m preprocess.build_shards --source synthetic")
    assert "--out" not in manifest["builder"]["command"] and "--workers" not in manifest["builder"]["command"]
    assert manifest["builder"]["options"]["source_options"] == {
        "corrupt": "nan,bad_shape,short,long,no_captions", "num_clips": 40, "seed": 3}
    # The id covers the splits section (docs/dataset-format.md): which files, in which split, with their counts.
    covered = json.dumps({"format_version": 2, "splits": splits}, sort_keys=True, separators=(",", ":"))
    assert manifest["format_version"] == 2 and manifest["dataset_id"] == hashlib.sha256(covered.encode()).hexdigest()

    stats = FeatureStats()
    action_classes = set()
    for name, split in splits.items():
        assert [e["num_motions"] for e in split["shards"]][:-1] == [8] * (len(split["shards"]) - 1)
        samples = read_tar_records(out, split["shards"])
        table = pa.concat_tables([pq.read_table(out / e["path"]) for e in split["parquet"]])
        assert [s["__key__"] for s in samples] == table.column("id").to_pylist()
        assert [s["__key__"] for s in samples] == sorted(s["__key__"] for s in samples)  # list_items order
        lengths = []
        for row, sample in enumerate(samples):
            meta = json.loads(sample["meta.json"])
            features = np.load(io.BytesIO(sample["features.npy"]))
            assert features.shape == (meta["length"], 263) and meta["split"] == name
            assert 40 <= meta["length"] <= 199 and meta["captions"]
            parquet_features = np.asarray(table.column("features")[row].values.flatten(), np.float32)
            assert parquet_features.tobytes() == features.tobytes()
            emb = np.load(io.BytesIO(sample["text_emb.npy"]))
            assert emb.shape == (len(meta["captions"]), 384)
            np.testing.assert_allclose(np.linalg.norm(emb, axis=1), 1.0, atol=1e-5)  # MiniLM is L2-normalised
            lengths.append(meta["length"])
            action_classes.add(meta["action"])
            if name == "train":
                stats.update(features)
        assert split["lengths"] == lengths and split["num_frames"] == sum(lengths)
    assert manifest["action_classes"] == sorted(action_classes)
    mean, std = stats.mean_std(FeatureLayout(HUMANML3D))
    assert manifest["normalization"]["mean"] == mean.tolist() and manifest["normalization"]["std"] == std.tolist()


def test_rebuild_in_process_with_one_worker_is_byte_identical(synthetic_build, tmp_path):
    out, _ = synthetic_build
    assert main([*SYNTHETIC, "--out", str(tmp_path / "again"), "--workers", "1"]) == 0
    assert files_of(tmp_path / "again") == files_of(out)


def test_strict_names_the_first_bad_file(tmp_path, capsys):
    assert main([*SYNTHETIC, "--out", str(tmp_path / "strict"), "--strict"]) != 0
    # corrupt_bad_shape is the first bad item in list order
    assert "synthetic:3:corrupt_bad_shape: bad_shape" in capsys.readouterr().err
    assert not (tmp_path / "strict" / "manifest.json").exists()


def test_module_entry_point(launches):
    result = launches["module_help"][1].result()
    assert result.returncode == 0 and "--source-option" in result.stdout, result.stderr


def test_help_explains_every_option(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    for option in ("--source", "--root", "--out", "--text-encoder", "--text-weights", "--token-features",
                   "--max-tokens", "--shard-size", "--format", "--workers", "--min-frames", "--max-frames",
                   "--long-clips", "--strict", "--overwrite", "--compat", "--no-compat", "--num-clips", "--seed",
                   "--body-model", "--source-option"):
        assert option in text


def test_default_build_without_arguments(launches, monkeypatch, capsys):
    cwd, launch = launches["no_arguments"]
    result = launch.result()
    assert result.returncode == 0, result.stderr
    out = cwd / "data" / "deepmimic-minilm"
    manifest = load_manifest(out, verify="sha256")
    assert manifest["builder"]["options"]["source"] == "deepmimic"
    assert manifest["builder"]["options"]["min_frames"] == 24  # DeepMimic's floor: keeps the 1.5 s kick take
    assert manifest["text_encoder"]["id"] == "minilm" and manifest["text_encoder"]["dim"] == 384
    assert manifest["feature_spec"]["skeleton"] == "humanml3d" and manifest["feature_spec"]["fps"] == 20.0
    assert list(manifest["splits"]) == ["train", "val", "test"]
    # Every one of DeepMimic's 15 humanoid clips is in the dataset, each its own action class.
    assert manifest["skip_report"]["total"] == 0, manifest["skip_report"]
    assert len(manifest["action_classes"]) == 15 and {"backflip", "kick"} <= set(manifest["action_classes"])
    train = read_tar_records(out, manifest["splits"]["train"]["shards"])
    assert sorted(json.loads(s["meta.json"])["action"] for s in train) == manifest["action_classes"]
    assert all(np.isfinite(manifest["normalization"]["std"])) and min(manifest["normalization"]["std"]) > 0

    before = files_of(out)
    monkeypatch.chdir(cwd)
    assert main([]) != 0  # a complete dataset is never overwritten silently
    assert "--overwrite" in capsys.readouterr().err
    assert files_of(out) == before


def test_summary_line_counts_the_ignored_files(tmp_path, capsys):
    """The skip report lists the files of the source folder that were never read (a ``000001.bak.npy``); the
    summary line says how many, beside the skipped count."""
    from test_shards import write_humanml3d_folder

    root = write_humanml3d_folder(tmp_path / "HumanML3D")
    assert main(["--source", "humanml3d", "--root", str(root), "--out", str(tmp_path / "ds"), "--quiet"]) == 0
    manifest = load_manifest(tmp_path / "ds")
    assert manifest["skip_report"]["ignored_files"]["count"] == 1
    summary = capsys.readouterr().out.strip().splitlines()[-1]
    assert f"; {manifest['skip_report']['total']} skipped; 1 ignored files;" in summary


def test_amass_caption_map_entries_are_counted_unless_strict(tmp_path, capsys):
    """A malformed entry of an AMASS JSON caption map is counted by reason in the skip report (the build goes on);
    with --strict the build stops before writing anything, naming the caption file and the entry."""
    from test_sources import write_body_model, write_motion

    model = write_body_model(tmp_path / "model.npz")
    frames = 180  # 3 s at 60 fps: long enough for the default min_frames
    poses = np.random.default_rng(0).normal(size=(frames, 156)) * 0.05
    trans = np.cumsum(np.tile([0.0, 0.01, 0.0], (frames, 1)), axis=0)
    for name in ("walk", "wave"):
        write_motion(tmp_path / "amass" / "a" / f"{name}_poses.npz", poses, trans, fps=60.0)
    captions = tmp_path / "captions.json"
    captions.write_text(json.dumps({
        "a/walk_poses.npz": ["a person walks", {"text": "turns", "start": 5.0, "end": 2.0}, "", 42],
        "a/wave_poses.npz": ["waves#t/X#-1#2"],
    }))
    args = ["--source", "amass", "--root", str(tmp_path / "amass"), "--body-model", str(model),
            "--source-option", f"captions={captions}", "--quiet"]

    assert main([*args, "--out", str(tmp_path / "ds")]) == 0  # used to stop at the first bad entry
    report = load_manifest(tmp_path / "ds")["skip_report"]
    assert report["dropped_captions"] == {"empty": 1, "malformed_entry": 1, "span_end_not_after_start": 1}
    (only_bad,) = report["items"]
    assert (only_bad["id"], only_bad["reason"]) == ("a__wave_poses", "no_captions")
    assert "1 span_negative; entry 'a/wave_poses.npz', caption 1" in only_bad["detail"]

    capsys.readouterr()
    assert main([*args, "--out", str(tmp_path / "strict"), "--strict"]) == 1
    assert (f"build_shards: error: {captions}: span_end_not_after_start (entry 'a/walk_poses.npz', caption 2: span "
            "end 2.0 s is not after its start 5.0 s)") in capsys.readouterr().err
    assert not (tmp_path / "strict").exists()


def snapshot_of(root: Path) -> dict[str, tuple[bytes | None, int]]:
    """Every path under ``root`` with its bytes (None for a folder) and mtime: what "untouched" compares."""
    return {p.relative_to(root).as_posix(): (p.read_bytes() if p.is_file() else None, p.stat().st_mtime_ns)
            for p in sorted(root.rglob("*"))}


@pytest.mark.parametrize("overwrite", [False, True])
def test_a_folder_of_another_tools_shards_is_refused_untouched(tmp_path, capsys, overwrite):
    """Issue 24, finding 3: --out on a folder holding another tool's train/shard-0000{0..9}.tar (no manifest.json)
    deleted or overwrote all ten. Now: one line naming the folder and why, exit 2, every file as it was."""
    out = tmp_path / "theirs"
    (out / "train").mkdir(parents=True)
    for index in range(10):
        (out / "train" / f"shard-{index:05d}.tar").write_bytes(f"another tool's shard {index}".encode())
    before = snapshot_of(out)
    capsys.readouterr()
    assert main([*SYNTHETIC, "--out", str(out), *(["--overwrite"] if overwrite else [])]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith(f"build_shards: error: --out {out} is a non-empty folder that is not a dataset built here")
    assert "it holds train" in err[0]
    assert snapshot_of(out) == before


def test_overwrite_never_deletes_a_shard_our_manifest_does_not_name(tmp_path, capsys):
    """Issue 24, finding 3: --overwrite of one of our datasets deleted every shard-named file of its folders, ours
    or not. A file our manifest does not name, that the new build could overwrite, is refused; nothing is touched."""
    out = tmp_path / "ours"
    args = ["--source", "synthetic", "--num-clips", "12", "--seed", "1", "--shard-size", "4", "--quiet",
            "--format", "tar", "--out", str(out)]
    assert main(args) == 0
    foreign = out / "train" / "shard-00009.tar"
    foreign.write_bytes(b"not ours")
    before = snapshot_of(out)
    capsys.readouterr()
    assert main([*args, "--overwrite"]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert f"--out {out} holds train/shard-00009.tar, which the build could overwrite and no build of ours" in line
    assert snapshot_of(out) == before
    foreign.unlink()
    (out / "notes.txt").write_text("mine")
    assert main([*args, "--overwrite"]) == 0  # our own dataset: replaced, the user's notes kept
    assert (out / "notes.txt").read_text() == "mine" and not (out / "build-in-progress.json").exists()
    load_manifest(out, verify="sha256")
