"""launch/sample.py end to end on CPU: tiny text and action checkpoints trained once per session on the small
synthetic dataset test_trainer.py builds, then sampling, editing and the files results.json describes."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import embedded_dataset_once, load_launch_script
from matplotlib import rcParams
from PIL import Image
from test_trainer import build_dataset_once, train_entry

from mfm import metrics
from mfm.export import read_bvh
from mfm.features import features_to_joints, features_to_joints_rigid, rigid_joints
from mfm.layout import FeatureLayout
from pipeline.generation.inference import load_trained_model
from pipeline.generation.outputs import edited_joints
from pipeline.generation.sampling import max_sample_length
from preprocess.processing import single_threaded_torch

# Tiny models on a shared CPU: a second intra-op thread only adds spin-waiting.
pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("single_thread")]


sample_entry = load_launch_script("sample")
PLAUSIBILITY_FIGURES = {"bone_length_range", "bone_length_deviation", "floor_penetration", "foot_skating_ratio",
                        "contact_foot_speed", "skating_foot_speed", "mean_jerk", "pose_speed", "root_speed", "pose_spread"}


def _train_once(tmp_path_factory, name: str, manifest: Path, *overrides: str) -> Path:
    """A tiny 4-step run on ``manifest``, trained once per session."""
    run = tmp_path_factory.getbasetemp() / name
    if not (run / "checkpoints").is_dir():
        with single_threaded_torch():
            code = train_entry.main(["--config", "tiny", f"data.manifest={manifest}", f"train.out_dir={run}",
                                     "train.max_steps=4", "train.save_every=4", *overrides])
        assert code == 0
    return run


@pytest.fixture(scope="session")
def text_run(tmp_path_factory) -> Path:
    return _train_once(tmp_path_factory, "sampling-text-run", build_dataset_once(tmp_path_factory))


@pytest.fixture(scope="session")
def action_run(tmp_path_factory) -> Path:
    # num_actions > 0 makes the trainer build an action model over the manifest's action classes.
    return _train_once(tmp_path_factory, "sampling-action-run", build_dataset_once(tmp_path_factory),
                       "model.num_actions=1")


def sample(run: Path, out: Path, *args: str) -> dict:
    code = sample_entry.main(["--checkpoint", str(run), "--out", str(out), *args])
    assert code == 0
    return json.loads((out / "results.json").read_text())


def files_on_disk(out: Path) -> set[str]:
    return {p.relative_to(out).as_posix() for p in out.rglob("*")
            if p.is_file() and p.relative_to(out).as_posix() not in ("results.json", "index.html")}


def files_described(results: dict) -> set[str]:
    return {f["path"] for s in results["samples"] for f in s["files"]}


def file_of(sample_record: dict, kind: str) -> str:
    (path,) = [f["path"] for f in sample_record["files"] if f["kind"] == kind]
    return path


def features_of(out: Path, results: dict) -> list[np.ndarray]:
    return [np.load(out / f["path"]) for s in results["samples"] for f in s["files"] if f["kind"] == "features"]


def test_text_request_writes_every_file_and_describes_exactly_those(text_run, tmp_path, monkeypatch):
    monkeypatch.setitem(rcParams, "animation.ffmpeg_path", "no-such-ffmpeg-binary")  # force the GIF fallback
    out = tmp_path / "out"
    results = sample(text_run, out, "--text", "a person walks forward", "--text", "someone jumps",
                     "--num-samples", "2", "--length", "20", "--length", "27", "--plot-trajectory", "--seed", "5")
    trained = load_trained_model(text_run)
    assert (results["checkpoint"], results["step"], results["weights"]) == (str(trained.checkpoint), 4, "ema")
    assert results["dataset_id"] == trained.dataset_id
    assert (results["solver"], results["steps"], results["nfe_per_batch"], results["guidance"], results["seed"]) == \
        ("euler", 10, [10], 2.5, 5)
    assert results["timing"]["ms_per_motion"] > 0
    assert [(s["text"], s["length"], s["seconds"]) for s in results["samples"]] == [
        ("a person walks forward", 20, 1.0), ("a person walks forward", 20, 1.0),
        ("someone jumps", 27, 1.35), ("someone jumps", 27, 1.35)]
    assert files_on_disk(out) == files_described(results)
    assert results["plausibility_thresholds"]["foot_contact_height_m"] == 0.05
    assert results["plausibility_thresholds"]["foot_joints"] == ["left_ankle", "left_foot", "right_ankle",
                                                                 "right_foot"]

    skeleton = trained.skeleton
    for s in results["samples"]:
        # Every figure is defined: these untrained motions touch the floor (contact_foot_speed would be None if not).
        assert set(s["plausibility"]) == PLAUSIBILITY_FIGURES and all(np.isfinite(list(s["plausibility"].values())))
        files = {f["kind"]: out / f["path"] for f in s["files"]}
        assert set(files) == {"features", "joints", "video", "bvh", "trajectory_plot"}
        features, joints = np.load(files["features"]), np.load(files["joints"])
        assert features.shape == (s["length"], 263) and joints.shape == (s["length"], 22, 3)
        np.testing.assert_allclose(joints, features_to_joints(features, skeleton), rtol=0, atol=1e-6)
        figures = metrics.plausibility(joints, skeleton)
        assert s["plausibility"]["mean_jerk"] == pytest.approx(figures.mean_jerk[0], abs=1e-6)
        assert s["plausibility"]["floor_penetration"] == pytest.approx(figures.floor_penetration[0], abs=1e-6)
        assert files["video"].suffix == ".gif"
        with Image.open(files["video"]) as gif:
            assert gif.n_frames == s["length"]
        with Image.open(files["trajectory_plot"]) as png:
            assert png.format == "PNG"
        # The network's ric output has drifting bone lengths: the BVH is the rigid decode, reproduced exactly.
        bvh = read_bvh(files["bvh"], skeleton.joint_names)
        assert bvh.joints.shape == joints.shape and bvh.fps == pytest.approx(trained.fps)
        np.testing.assert_allclose(bvh.joints, rigid_joints(joints, skeleton), atol=1e-5)
        assert "rigid" in [f for f in s["files"] if f["kind"] == "bvh"][0]["recovered_with"]


def test_rigid_decode_writes_joints_with_the_skeletons_bone_lengths(text_run, tmp_path):
    out = tmp_path / "rigid"
    results = sample(text_run, out, "--text", "a person walks", "--length", "20", "--decode", "rigid", "--no-video")
    (record,) = results["samples"]
    skeleton = load_trained_model(text_run).skeleton
    joints = np.load(out / file_of(record, "joints"))
    np.testing.assert_allclose(joints, features_to_joints_rigid(np.load(out / file_of(record, "features")), skeleton),
                               atol=1e-6)
    lengths = np.linalg.norm(joints[:, 1:] - joints[:, skeleton.parents[1:]], axis=-1)
    np.testing.assert_allclose(lengths, np.broadcast_to(skeleton.bone_lengths[1:], lengths.shape), atol=1e-5)
    assert "rigid" in [f for f in record["files"] if f["kind"] == "joints"][0]["recovered_with"]
    np.testing.assert_allclose(read_bvh(out / file_of(record, "bvh"), skeleton.joint_names).joints, joints, atol=1e-5)


def test_same_seed_same_motions_whatever_the_batching(text_run, tmp_path):
    prompts = tmp_path / "prompts.txt"
    prompts.write_text("# one prompt per line\na person walks\n\n")
    args = ["--prompts", str(prompts), "--num-samples", "3", "--no-video", "--no-bvh", "--seed", "11"]
    first = sample(text_run, tmp_path / "a", *args)
    reference = features_of(tmp_path / "a", first)  # read before the overwrite below replaces them
    again = sample(text_run, tmp_path / "a", *args, "--overwrite")
    one_by_one = sample(text_run, tmp_path / "c", *args, "--batch-size", "1")
    other_seed = sample(text_run, tmp_path / "d", *args[:-1], "12")
    raw_weights = sample(text_run, tmp_path / "e", *args, "--model-weights", "model")

    assert [s["text"] for s in first["samples"]] == ["a person walks"] * 3
    lengths = [s["length"] for s in first["samples"]]
    trained = load_trained_model(text_run)
    # Drawn from the training distribution, capped at the training window.
    assert all(length in {min(n, max_sample_length(trained)) for n in trained.train_lengths} for length in lengths)
    assert first["nfe_per_batch"] == [10] and one_by_one["nfe_per_batch"] == [10, 10, 10]
    assert (first["weights"], raw_weights["weights"]) == ("ema", "model")
    assert [f.shape[0] for f in reference] == lengths
    for a, b, c in zip(reference, features_of(tmp_path / "a", again), features_of(tmp_path / "c", one_by_one)):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_allclose(a, c, atol=1e-4)
    assert not np.array_equal(reference[0], features_of(tmp_path / "d", other_seed)[0])
    assert not np.array_equal(reference[0], features_of(tmp_path / "e", raw_weights)[0])


def test_precision_is_recorded_and_bf16_changes_only_the_networks_rounding(text_run, tmp_path, capsys):
    """--precision: auto (the default) is fp32 on the CPU; bf16 runs the model's passes under bf16 autocast, the
    same motions within the bound of tests/test_sampling_precision.py; results.json records both."""
    from test_sampling_precision import BF16_MAX_ABS

    args = ["--text", "a person walks", "--num-samples", "2", "--no-video", "--no-bvh", "--seed", "3"]
    default = sample(text_run, tmp_path / "auto", *args)
    fp32 = sample(text_run, tmp_path / "fp32", *args, "--precision", "fp32")
    bf16 = sample(text_run, tmp_path / "bf16", *args, "--precision", "bf16")
    assert (default["precision"], default["precision_setting"]) == ("fp32", "auto")
    assert (fp32["precision"], bf16["precision"], bf16["precision_setting"]) == ("fp32", "bf16", "bf16")
    for a, b, c in zip(features_of(tmp_path / "auto", default), features_of(tmp_path / "fp32", fp32),
                       features_of(tmp_path / "bf16", bf16)):
        np.testing.assert_array_equal(a, b)
        trained = load_trained_model(text_run)  # the bound is in normalised units: compare there
        difference = np.abs((c - b) / trained.std.cpu().numpy())
        assert 0 < difference.max() <= BF16_MAX_ABS
    capsys.readouterr()
    assert sample_entry.main(["--checkpoint", str(text_run), "--out", str(tmp_path / "x"), "--text", "x",
                              "precision=fp16"]) == 2
    assert capsys.readouterr().err == "error: SampleRequest: precision must be one of ['auto', 'fp32', 'bf16'], got 'fp16'\n"


def test_inbetween_edit_keeps_the_source_frames_and_records_the_mask(text_run, tmp_path):
    source_out = tmp_path / "source"
    source = sample(text_run, source_out, "--text", "a person walks", "--length", "30", "--no-video", "--no-bvh")
    source_file = source_out / file_of(source["samples"][0], "features")
    out = tmp_path / "edit"
    results = sample(text_run, out, "--text", "a person jumps", "--num-samples", "2", "--edit", "inbetween",
                     "--source-motion", str(source_file), "--keep", "prefix=0.2", "--rewrite-until", "1",
                     "--steps", "50", "--no-bvh", "--seed", "1")  # other noise than the source's
    assert files_on_disk(out) == files_described(results)
    assert results["guidance"] == 1.0  # the edit settings' scale (MFM's edit.py), not sampling's 2.5
    trained = load_trained_model(text_run)
    src = trained.normalize(torch.from_numpy(np.load(source_file))).numpy()
    for s in results["samples"]:
        record = s["edit"]
        assert record["preset"] == "inbetween" and record["rewrite_until"] == 1.0
        assert record["options"] == {"prefix": 0.2} and record["source_kind"] == "features"
        assert record["kept_frame_ranges"] == [[0, 6], [22, 30]] and record["kept_dim_ranges"] == [[0, 263]]
        files = {f["kind"]: out / f["path"] for f in s["files"]}
        keep = np.load(files["keep_mask"])
        expected = np.zeros((30, 263), dtype=bool)
        expected[:6] = expected[22:] = True
        np.testing.assert_array_equal(keep, expected)
        edited = trained.normalize(torch.from_numpy(np.load(files["features"]))).numpy()
        error = np.abs(edited - src)
        # With ς = 1 the known frames are on the noise→source line until the last step; only that step's drift
        # h·(v - (x1 - x0)) (h = 1/50) separates them from the source. The generated middle is free.
        assert error[keep].max() < 0.25
        assert error[keep].mean() < 0.1 * error[~keep].mean()


def test_upper_body_edit_from_joints_colours_the_generated_joints(text_run, tmp_path):
    source_out = tmp_path / "source"
    source = sample(text_run, source_out, "--text", "a person walks", "--length", "25", "--no-video", "--no-bvh")
    joints_file = source_out / file_of(source["samples"][0], "joints")
    out = tmp_path / "edit"
    results = sample(text_run, out, "--edit", "upper-body", "--source-motion", str(joints_file), "--no-bvh",
                     "--video-format", "gif")
    (record,) = [s["edit"] for s in results["samples"]]
    assert results["conditioning"] == "none" and results["guidance"] == 0.0
    assert record["source_kind"] == "joints" and record["source_frames"] == 24  # joints -> features drops a frame
    # MFM paper's edit settings by default: 30 Euler steps, rewriting until 0.2
    assert results["samples"][0]["length"] == 24 and record["rewrite_until"] == 0.2 and results["steps"] == 30
    assert record["settings"]["settings"] == "paper" and record["settings"]["overridden"] == []
    debug = sample(text_run, tmp_path / "debug", "--edit", "upper-body", "--source-motion", str(joints_file),
                   "--edit-settings", "reference-debug", "--steps", "12", "--no-bvh", "--no-video")
    (debug_record,) = [s["edit"] for s in debug["samples"]]
    assert debug_record["rewrite_until"] == 0.1 and debug["steps"] == 12  # edit.py's upper-body ς; --steps wins
    assert debug_record["settings"]["settings"] == "reference-debug"
    assert debug_record["settings"]["overridden"] == ["steps"]
    layout = FeatureLayout(load_trained_model(text_run).skeleton)
    keep = np.load(out / "sample_000" / "keep_mask.npy")
    np.testing.assert_array_equal(keep, np.broadcast_to(layout.lower_body_mask, keep.shape))
    generated = edited_joints(keep, layout)
    lower = set(layout.skeleton.lower_body_joints)
    assert all(generated[:, j].all() != (j in lower) for j in range(layout.num_joints))
    assert (out / "sample_000" / "motion.gif").is_file()


def test_action_model_samples_by_class_name_and_rejects_unknown_names(action_run, tmp_path, capsys):
    trained = load_trained_model(action_run)
    assert trained.model_config.is_action_model and "jump" in trained.action_classes
    results = sample(action_run, tmp_path / "ok", "--action", "jump", "--action", "walk", "--length", "16",
                     "--no-video", "--no-bvh")
    assert results["conditioning"] == "action"
    assert [(s["action"], s["text"], s["length"]) for s in results["samples"]] == [("jump", None, 16),
                                                                                   ("walk", None, 16)]
    code = sample_entry.main(["--checkpoint", str(action_run), "--out", str(tmp_path / "bad"), "--action", "moonwalk"])
    assert code == 2
    err = capsys.readouterr().err
    assert "moonwalk" in err and "jump" in err
    assert not (tmp_path / "bad" / "results.json").exists()
    code = sample_entry.main(["--checkpoint", str(action_run), "--out", str(tmp_path / "bad"), "--text", "a jump"])
    assert code == 2 and "action" in capsys.readouterr().err


def test_bad_requests_fail_with_a_clear_message(text_run, tmp_path, capsys):
    def fails(*args: str) -> str:
        assert sample_entry.main(["--checkpoint", str(text_run), "--out", str(tmp_path / "o"), *args]) == 2
        return capsys.readouterr().err

    assert "dopri5" in fails("--text", "x", "--solver", "rk45")
    assert "source motion" in fails("--text", "x", "--edit", "inbetween")
    assert "keep options" in fails("--text", "x", "--edit", "prediction", "--source-motion", "m.npy", "--keep", "every=2")
    assert "one per prompt" in fails("--text", "x", "--text", "y", "--length", "10", "--length", "12", "--length", "9")
    bad_source = tmp_path / "bad.npy"
    np.save(bad_source, np.zeros((10, 7), dtype=np.float32))
    assert "bad.npy" in fails("--text", "x", "--edit", "inbetween", "--source-motion", str(bad_source))
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / "notes.txt").write_text("mine")
    assert "not empty" in fails("--text", "x", "--no-video", "--no-bvh")
    assert sample_entry.main(["--checkpoint", str(tmp_path / "nothing"), "--out", str(tmp_path / "p"), "--text", "x"]) == 2
    assert "no checkpoint" in capsys.readouterr().err


def test_a_damaged_checkpoint_or_a_missing_device_is_one_line_and_exit_2(text_run, tmp_path, monkeypatch, capsys):
    """Issue 24, item 9: a damaged state.pt, --device cuda on a machine without a GPU and --device gpu0 were
    tracebacks and exit 1. Now one ``error:`` line naming the file or the device, exit 2, nothing written."""
    def refused(checkpoint: Path, *args: str) -> str:
        out = tmp_path / "out"
        assert sample_entry.main(["--checkpoint", str(checkpoint), "--out", str(out), "--text", "x", *args]) == 2
        err = capsys.readouterr().err
        errors = [line for line in err.splitlines() if line.startswith("error: ")]
        assert len(errors) == 1 and "Traceback" not in err and not out.exists(), err
        return errors[0]

    step = next((text_run / "checkpoints").glob("step-*"))
    damaged = tmp_path / "damaged"
    shutil.copytree(step, damaged)
    state = damaged / "state.pt"
    state.write_bytes(state.read_bytes()[:1000])  # cut short, as by a full disk or an interrupted copy
    assert f"{state}: 1000 bytes, the marker says" in refused(damaged)

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # this machine, with or without a GPU
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 0)
    assert "device 'cuda': no CUDA GPU is visible" in refused(text_run, "--device", "cuda")
    assert "device 'cuda:1': no CUDA GPU is visible" in refused(text_run, "--device", "cuda:1")
    assert "device 'gpu0': not a device this program samples on" in refused(text_run, "--device", "gpu0")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # one GPU: cuda:1 is not there
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert "device 'cuda:1': this machine has 1 visible CUDA GPU(s)" in refused(text_run, "--device", "cuda:1")


def test_embedded_deepmimic_action_demo(tmp_path_factory, tmp_path):
    """The real demo: an action model on the embedded DeepMimic dataset samples its clips' class names."""
    data = embedded_dataset_once(tmp_path_factory)
    manifest = json.loads((data / "manifest.json").read_text())
    assert {"cartwheel", "backflip", "walk"} <= set(manifest["action_classes"])
    run = _train_once(tmp_path_factory, "sampling-deepmimic-run", data / "manifest.json", "model.num_actions=1")
    results = sample(run, tmp_path / "out", "--action", "cartwheel", "--action", "backflip", "--seconds", "1.5",
                     "--no-video")
    assert results["dataset_id"] == manifest["dataset_id"]
    assert [(s["action"], s["length"]) for s in results["samples"]] == [("cartwheel", 30), ("backflip", 30)]
    for s in results["samples"]:
        bvh = read_bvh(tmp_path / "out" / file_of(s, "bvh"))
        assert bvh.joints.shape[0] == 30 and bvh.fps == pytest.approx(20.0)


def test_mdm_results_npy_holds_the_written_joints_in_mdms_order(text_run, tmp_path):
    from mfm.export import read_mdm_results

    out = tmp_path / "mdm"
    results = sample(text_run, out, "--text", "a person walks", "--text", "a person jumps", "--num-samples", "2",
                     "--length", "12", "--length", "16", "--no-video", "--no-bvh", "--mdm-results")
    assert results["mdm_results"]["path"] == "results.npy" and (out / "results.txt").is_file()
    mdm = read_mdm_results(out / "results.npy")
    assert (mdm.num_samples, mdm.num_repetitions, mdm.motion.shape) == (2, 2, (4, 22, 3, 16))
    for ours in results["samples"]:  # ours: prompt-major; MDM's: repetition-major
        prompt, repetition = divmod(ours["index"], 2)
        entry = mdm.index(prompt, repetition)
        joints = np.load(out / file_of(ours, "joints"))
        assert mdm.texts[entry] == ours["text"] and mdm.lengths[entry] == ours["length"]
        np.testing.assert_array_equal(mdm.motion[entry, :, :, :ours["length"]], joints.transpose(1, 2, 0))
    again = sample(text_run, out, "--text", "a person walks", "--length", "12", "--no-video", "--no-bvh",
                   "--overwrite")  # an overwrite without --mdm-results leaves no stale results.npy behind
    assert "mdm_results" not in again and not (out / "results.npy").exists()


def test_export_then_from_pretrained_generates_what_sampling_the_checkpoint_does(text_run, tmp_path, capsys):
    from pipeline.generation.pretrained import MotionPipeline

    export = load_launch_script("export").main
    exported = tmp_path / "exported"
    assert export([str(text_run), "--out", str(exported)]) == 0
    names = {p.name for p in exported.iterdir()}
    assert names == {"config.json", "model.safetensors", "normalization.safetensors", "README.md"}
    card = (exported / "README.md").read_text()
    assert "## Training data" in card and "dataset id" in card and "No evaluator results" in card
    assert export([str(text_run), "--out", str(exported)]) == 2  # never over an earlier export
    assert "not an empty folder" in capsys.readouterr().err

    pipe = MotionPipeline.from_pretrained(exported, device="cpu")
    out = pipe(["a person walks", "a person jumps"], lengths=[20, 24], num_samples=2, seed=3)
    assert len(out) == 4 and out.lengths == [20, 20, 24, 24] and out.texts[2] == "a person jumps"
    assert out.joints[2].shape == (24, 22, 3) and out.fps == load_trained_model(text_run).fps
    # The same request through the command line on the checkpoint itself gives the same motions.
    cli = sample(text_run, tmp_path / "cli", "--text", "a person walks", "--text", "a person jumps", "--length", "20",
                 "--length", "24", "--num-samples", "2", "--seed", "3", "--no-video", "--no-bvh")
    for index, features in enumerate(out.features):
        cli_features = np.load(tmp_path / "cli" / file_of(cli["samples"][index], "features"))
        np.testing.assert_allclose(features, cli_features, rtol=0, atol=1e-5)
    saved = out.save(tmp_path / "api", video=False, bvh=False, mdm_results=True)
    results = json.loads((saved / "results.json").read_text())
    assert [s["length"] for s in results["samples"]] == [20, 20, 24, 24] and (saved / "results.npy").is_file()
    np.testing.assert_allclose(np.load(saved / file_of(results["samples"][1], "joints")), out.joints[1], atol=1e-6)
    # launch/sample.py takes the exported folder as it takes a checkpoint
    from_export = sample(exported, tmp_path / "cli-export", "--text", "a person walks", "--length", "20",
                         "--seed", "3", "--no-video", "--no-bvh")
    exported_features = np.load(tmp_path / "cli-export" / file_of(from_export["samples"][0], "features"))
    np.testing.assert_allclose(exported_features, out.features[0], atol=1e-5)


def _preset_sampling_run(tmp_path_factory) -> Path:
    """A run whose preset sets the model's own sampling defaults: σ = 1 smoothing, guidance 1.5 of the pose."""
    return _train_once(tmp_path_factory, "sampling-smoothed-run", build_dataset_once(tmp_path_factory),
                       "model.output_smoothing=1.0", "model.sampling_guidance=1.5", "model.guided_features=pose")


def test_a_model_whose_preset_smooths_its_outputs_is_sampled_smoothed_unless_told_otherwise(tmp_path_factory,
                                                                                          tmp_path):
    from mfm.diffusion_sampling import smooth_over_time

    run = _preset_sampling_run(tmp_path_factory)
    assert load_trained_model(run).default_smoothing == 1.0
    args = ["--text", "a person walks", "--seconds", "3", "--no-video", "--no-bvh", "--seed", "3"]
    default = sample(run, tmp_path / "default", *args)
    raw = sample(run, tmp_path / "raw", *args, "--smoothing", "0")
    smoothed, unsmoothed = features_of(tmp_path / "default", default)[0], features_of(tmp_path / "raw", raw)[0]
    expected = smooth_over_time(torch.as_tensor(unsmoothed)[None].double(), [len(unsmoothed)], 1.0)[0].numpy()
    np.testing.assert_allclose(smoothed, expected, atol=1e-4)
    assert np.abs(np.diff(smoothed, 3, axis=0)).mean() < np.abs(np.diff(unsmoothed, 3, axis=0)).mean()


def test_smoothing_that_keeps_the_bones_is_asked_for_and_recorded(tmp_path_factory, tmp_path):
    from mfm.diffusion_sampling import smooth_over_time
    from mfm.features import restore_bone_lengths

    run = _preset_sampling_run(tmp_path_factory)
    skeleton = load_trained_model(run).skeleton
    args = ["--text", "a person walks", "--seconds", "3", "--no-video", "--no-bvh", "--seed", "3"]
    default = sample(run, tmp_path / "default", *args)
    raw = sample(run, tmp_path / "raw", *args, "--smoothing", "0")
    kept = sample(run, tmp_path / "kept", *args, "--smoothing-keeps-bones", "true")
    assert default["smoothing_keeps_bones"] is False and kept["smoothing_keeps_bones"] is True  # the model's: off
    unsmoothed = torch.as_tensor(features_of(tmp_path / "raw", raw)[0]).double()
    smoothed = smooth_over_time(unsmoothed[None], [len(unsmoothed)], 1.0)[0]
    expected = restore_bone_lengths(smoothed, unsmoothed, skeleton).numpy()
    np.testing.assert_allclose(features_of(tmp_path / "kept", kept)[0], expected, atol=1e-4)
    assert not np.allclose(features_of(tmp_path / "default", default)[0], expected, atol=1e-4)


def test_a_model_whose_preset_sets_its_guidance_is_sampled_with_it_unless_told_otherwise(tmp_path_factory, tmp_path):
    """model.sampling_guidance is the scale launch/sample.py uses when --guidance is not given (and results.json
    says so); --guidance still wins; a model that sets none samples at MFM's 2.5."""
    run = _preset_sampling_run(tmp_path_factory)
    assert load_trained_model(run).default_guidance == 1.5
    args = ["--text", "a person walks", "--seconds", "3", "--no-video", "--no-bvh", "--seed", "3"]
    default = sample(run, tmp_path / "default", *args)
    explicit = sample(run, tmp_path / "explicit", *args, "--guidance", "1.5")
    mfm = sample(run, tmp_path / "mfm", *args, "--guidance", "2.5")
    assert default["guidance"] == explicit["guidance"] == 1.5 and mfm["guidance"] == 2.5
    assert default["guided_features"] == "pose"
    np.testing.assert_array_equal(features_of(tmp_path / "default", default)[0],
                                  features_of(tmp_path / "explicit", explicit)[0])
    assert not np.allclose(features_of(tmp_path / "default", default)[0], features_of(tmp_path / "mfm", mfm)[0])
    assert load_trained_model(_train_once(tmp_path_factory, "sampling-text-run",
                                          build_dataset_once(tmp_path_factory))).default_guidance == 2.5
