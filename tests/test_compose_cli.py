"""launch/sample.py's FlowMDM composition / extrapolation and its diffusion checkpoints (FLAME / FlowMDM baselines),
end to end on CPU with tiny models trained once per session on test_trainer.py's synthetic dataset: a BPE + PCCAT
flow model, a 'prefix' flow model (test_sample_cli.py's), and diffusion models with the flowmdm and flame presets."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from test_sample_cli import (
    _train_once,
    files_described,
    files_on_disk,
    sample,
    sample_entry,
    text_run,
)
from test_trainer import build_dataset_once

import pipeline.generation.outputs as outputs_module
from mfm.composition import HUMANML3D_SWITCH, BoundInputs, compose, read_prompt_file
from mfm.diffusion_sampling import sample_diffusion, smooth_over_time
from mfm.export import read_bvh
from pipeline.generation.inference import load_trained_model
from pipeline.generation.integration import sample_seed
from preprocess.build_shards import main as build_shards

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("single_thread")]

__all__ = ["text_run"]  # the 'prefix' flow model fixture, shared with test_sample_cli.py

THREE_SEGMENTS = {"text": ["a person walks forward", "a person jumps", "a person turns around"],
                  "lengths": [30, 25, 40]}


@pytest.fixture(scope="session")
def bpe_run(tmp_path_factory) -> Path:
    return _train_once(tmp_path_factory, "compose-bpe-pccat-run", build_dataset_once(tmp_path_factory),
                       "model.positional=bpe", "model.conditioning=pccat")


@pytest.fixture(scope="session")
def diffusion_run(tmp_path_factory) -> Path:
    return _train_once(tmp_path_factory, "diffusion-flowmdm-run", build_dataset_once(tmp_path_factory),
                       "train.objective=diffusion")


@pytest.fixture(scope="session")
def flame_run(tmp_path_factory) -> Path:
    return _train_once(tmp_path_factory, "diffusion-flame-run", build_dataset_once(tmp_path_factory),
                       "train.objective=diffusion", "train.diffusion=flame")


@pytest.fixture(scope="session")
def flame_layout_run(tmp_path_factory) -> Path:
    """FLAME's exact model: cross-attention to token-level text features, a length token, the flame diffusion."""
    root = tmp_path_factory.getbasetemp() / "token-dataset"
    if not (root / "manifest.json").exists():
        building = root.with_name("token-dataset.building")
        shutil.rmtree(building, ignore_errors=True)
        # in this process, as build_dataset_once (tests/test_trainer.py) builds its dataset
        assert build_shards(["--source", "synthetic", "--num-clips", "30", "--shard-size", "10", "--token-features",
                             "--out", str(building), "--quiet"]) == 0
        os.rename(building, root)
    return _train_once(tmp_path_factory, "diffusion-flame-layout-run", root / "manifest.json",
                       "train.objective=diffusion", "train.diffusion=flame", "model.conditioning=cross_attention",
                       "model.length_token=true")


def prompt_file(tmp_path: Path, content: dict, name: str = "prompts.json") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(content))
    return path


def fails(run: Path, out: Path, capsys, *args: str) -> str:
    assert sample_entry.main(["--checkpoint", str(run), "--out", str(out), *args]) == 2
    assert not out.exists()  # refused before writing anything
    return capsys.readouterr().err


def features_file(out: Path, results: dict, index: int = 0) -> np.ndarray:
    (path,) = [f["path"] for f in results["samples"][index]["files"] if f["kind"] == "features"]
    return np.load(out / path)


# ---------------------------------------------------------------------------------------------------------------
# composition


def test_three_segments_compose_into_one_sequence_with_changing_captions(bpe_run, tmp_path, monkeypatch):
    titles = []
    real_render = outputs_module.render_motion

    def recording_render(*args, **kwargs):
        titles.append(kwargs["title"])
        return real_render(*args, **kwargs)

    monkeypatch.setattr(outputs_module, "render_motion", recording_render)
    out = tmp_path / "out"
    results = sample(bpe_run, out, "--compose", str(prompt_file(tmp_path, THREE_SEGMENTS)), "--video-format", "gif",
                     "--seed", "3")
    assert (results["mode"], results["objective"], results["sampler"], results["positional"]) == \
        ("compose", "flow", "euler", "bpe")
    assert (results["total_frames"], results["nfe"], results["steps"], results["guidance"]) == (95, 10, 10, 2.5)
    assert [(s["text"], s["length"], s["start"], s["end"]) for s in results["segments"]] == [
        ("a person walks forward", 30, 0, 30), ("a person jumps", 25, 30, 55), ("a person turns around", 40, 55, 95)]
    assert results["boundaries"] == [[0, 30], [30, 55], [55, 95]]
    switch = results["switch"]
    assert switch["applies"] and switch["flow_time"] == pytest.approx(HUMANML3D_SWITCH, abs=1e-6)
    assert (switch["absolute_steps"], switch["relative_steps"]) == (1, 9)  # t = 0 < 0.084 only
    assert results["attention_chunk"] is None  # 95 frames: within the attention horizon, dense attention

    # ONE sample folder for the whole sequence, every file described, one video with the captions as they change.
    (record,) = results["samples"]
    assert files_on_disk(out) == files_described(results)
    assert {f["path"].split("/")[0] for f in record["files"]} == {"sample_000"}
    files = {f["kind"]: out / f["path"] for f in record["files"]}
    assert set(files) == {"features", "joints", "video", "bvh"}
    features, joints = np.load(files["features"]), np.load(files["joints"])
    assert features.shape == (95, 263) and joints.shape == (95, 22, 3) and record["length"] == 95
    with Image.open(files["video"]) as gif:
        assert gif.format == "GIF" and gif.n_frames == 95
    assert titles == [[(0, "a person walks forward"), (30, "a person jumps"), (55, "a person turns around")]]
    (video,) = [f for f in record["files"] if f["kind"] == "video"]
    assert video["captions"] == [[0, "a person walks forward"], [30, "a person jumps"], [55, "a person turns around"]]
    assert read_bvh(files["bvh"]).joints.shape[0] == 95

    # The sequence is mfm.composition.compose's, with this sample's noise seed (not three separate motions).
    trained = load_trained_model(bpe_run)
    cond = trained.conditions(texts=THREE_SEGMENTS["text"])
    expected = compose(trained.model, list(zip(cond, THREE_SEGMENTS["lengths"])), seed=sample_seed(3, 0), steps=10)
    assert record["noise_seed"] == sample_seed(3, 0)
    np.testing.assert_allclose(features, trained.denormalize(expected.motion).numpy(), rtol=0, atol=1e-4)


def test_the_real_flowmdm_composition_file_gives_one_long_sequence(bpe_run, reference_data, tmp_path):
    path = reference_data / "prompts" / "composition_humanml.json"
    segments = read_prompt_file(path)
    results = sample(bpe_run, tmp_path / "out", "--compose", str(path), "--steps", "4", "--no-video", "--no-bvh")
    total = sum(length for _, length in segments)
    assert len(segments) == 32 and total > 30 * 32  # far longer than the 32-frame window: nothing is clamped
    assert results["total_frames"] == total and results["prompt_file"] == str(path)
    assert [(s["text"], s["length"]) for s in results["segments"]] == segments
    assert results["boundaries"][-1] == [total - segments[-1][1], total]
    assert results["attention_chunk"] == 150  # the model's attention horizon: memory linear in the length
    assert results["nfe"] == 4 and results["mode"] == "compose"
    features = features_file(tmp_path / "out", results)
    assert features.shape == (total, 263) and np.isfinite(features).all()


def test_extrapolation_uses_chunked_attention_with_the_dense_result(bpe_run, tmp_path):
    args = ["--extrapolate", "--text", "a person walks", "--length", "40", "--num-segments", "6", "--no-video",
            "--no-bvh", "--seed", "2"]
    chunked = sample(bpe_run, tmp_path / "chunked", *args)
    assert (chunked["mode"], chunked["total_frames"], chunked["attention_chunk"]) == ("extrapolate", 240, 150)
    assert [(s["text"], s["length"], s["start"]) for s in chunked["segments"]] == \
        [("a person walks", 40, 40 * k) for k in range(6)]
    small_blocks = sample(bpe_run, tmp_path / "small", *args, "--attention-chunk", "64")
    dense = sample(bpe_run, tmp_path / "dense", *args, "--attention-chunk", "0")
    assert (small_blocks["attention_chunk"], dense["attention_chunk"]) == (64, None)
    reference = features_file(tmp_path / "dense", dense)
    assert reference.shape == (240, 263)
    np.testing.assert_allclose(features_file(tmp_path / "chunked", chunked), reference, rtol=0, atol=1e-3)
    np.testing.assert_allclose(features_file(tmp_path / "small", small_blocks), reference, rtol=0, atol=1e-3)

    # A FlowMDM file whose texts all agree is an extrapolation too (same segments, same sequence).
    same_text = prompt_file(tmp_path, {"text": ["a person walks"] * 6, "lengths": [40] * 6})
    from_file = sample(bpe_run, tmp_path / "file", "--compose", str(same_text), "--no-video", "--no-bvh", "--seed", "2")
    assert from_file["mode"] == "extrapolate"
    np.testing.assert_allclose(features_file(tmp_path / "file", from_file), features_file(tmp_path / "chunked", chunked),
                               rtol=0, atol=1e-5)


def test_switch_as_a_step_count_or_a_preset(bpe_run, tmp_path):
    base = ["--compose", str(prompt_file(tmp_path, THREE_SEGMENTS)), "--no-video", "--no-bvh"]
    three = sample(bpe_run, tmp_path / "three", *base, "--switch", "3")
    assert three["switch"] == {"applies": True, "requested": 3, "requested_as": "absolute solver steps",
                               "flow_time": 0.3, "absolute_steps": 3, "relative_steps": 7}
    babel = sample(bpe_run, tmp_path / "babel", *base, "--switch", "babel")
    assert babel["switch"]["absolute_steps"] == 2 and 0.1 < babel["switch"]["flow_time"] < 0.2
    default = sample(bpe_run, tmp_path / "default", *base)
    assert not np.array_equal(features_file(tmp_path / "three", three), features_file(tmp_path / "default", default))


def test_a_prefix_model_extrapolates_one_text_but_refuses_several(text_run, bpe_run, diffusion_run, tmp_path, capsys):
    results = sample(text_run, tmp_path / "ok", "--extrapolate", "--text", "a person walks", "--length", "40",
                     "--num-segments", "6", "--no-video", "--no-bvh")
    assert (results["mode"], results["positional"], results["total_frames"]) == ("extrapolate", "absolute", 240)
    assert results["switch"]["applies"] is False and results["attention_chunk"] is None
    assert features_file(tmp_path / "ok", results).shape == (240, 263)

    three = str(prompt_file(tmp_path, THREE_SEGMENTS))
    err = fails(text_run, tmp_path / "bad", capsys, "--compose", three)
    assert "3 different texts" in err and "model.positional=bpe model.conditioning=pccat" in err
    assert "conditioning=prefix" in err
    assert "one text" in fails(bpe_run, tmp_path / "bad", capsys, "--compose", three, "--extrapolate")
    assert "model.positional=bpe model.conditioning=pccat" in fails(diffusion_run, tmp_path / "bad", capsys,
                                                                  "--compose", three)
    assert "fixed-step solver" in fails(bpe_run, tmp_path / "bad", capsys, "--compose", three, "--solver", "dopri5")
    assert "at most 50" in fails(bpe_run, tmp_path / "bad", capsys, "--compose", three, "--solver", "rk4",
                                 "--steps", "13")
    assert "[0, 10]" in fails(bpe_run, tmp_path / "bad", capsys, "--compose", three, "--switch", "11")
    assert "exactly one" in fails(bpe_run, tmp_path / "bad", capsys, "--extrapolate", "--text", "a", "--text", "b",
                                  "--length", "40")
    broken = prompt_file(tmp_path, {"text": ["a", "b"], "lengths": [40]}, "broken.json")
    assert "broken.json" in fails(bpe_run, tmp_path / "bad", capsys, "--compose", str(broken))


# ---------------------------------------------------------------------------------------------------------------
# diffusion checkpoints


@pytest.mark.parametrize("run_fixture, preset", [("diffusion_run", "flowmdm"), ("flame_run", "flame")])
def test_diffusion_checkpoints_sample_with_ddpm_and_ddim(run_fixture, preset, request, tmp_path):
    run = request.getfixturevalue(run_fixture)
    trained = load_trained_model(run)
    assert (trained.objective, trained.diffusion_preset) == ("diffusion", preset)
    assert trained.model_config.output_size == (2 if preset == "flame" else 1) * 263  # FLAME learns the variance

    ddpm = sample(run, tmp_path / "ddpm", "--text", "a person walks", "--text", "a person jumps", "--length", "20",
                  "--solver", "ddpm", "--steps", "5", "--no-video", "--no-bvh")
    # FLAME's checkpoints sample as its authors ran them: guidance 8.0, output smoothed over time with σ = 1, the x0
    # clamp on the 6D rotations (every training step unless --steps asks for fewer: recorded as overridden)
    guidance, sigma = (8.0, 1.0) if preset == "flame" else (2.5, 0.0)
    assert (ddpm["objective"], ddpm["sampler"], ddpm["steps"], ddpm["guidance"]) == ("diffusion", "ddpm", 5, guidance)
    assert ddpm["smoothing_sigma"] == sigma
    if preset == "flame":
        own = ddpm["baseline_defaults"]
        assert (own["preset"], own["every_training_step"], own["clip_denoised"], own["ema_weights"],
                own["overridden"]) == ("flame", False, True, True, ["every_training_step"])
    else:
        assert ddpm["baseline_defaults"] is None
    assert ddpm["nfe_per_batch"] == [5]  # one guided (batched) denoiser pass per step
    assert ddpm["diffusion"]["preset"] == preset and len(ddpm["diffusion"]["model_steps"]) == 5
    one_by_one = sample(run, tmp_path / "ddpm-b1", "--text", "a person walks", "--text", "a person jumps",
                        "--length", "20", "--solver", "ddpm", "--steps", "5", "--no-video", "--no-bvh",
                        "--batch-size", "1")
    assert one_by_one["nfe_per_batch"] == [5, 5]
    for index in range(2):
        features = features_file(tmp_path / "ddpm", ddpm, index)
        assert features.shape == (20, 263) and np.isfinite(features).all()
        # Every step's noise comes from the sample's own seed: the same motion whatever the batching.
        # Float noise scaled to the features: an untrained FLAME model's learned variance makes values of ~1e4.
        np.testing.assert_allclose(features, features_file(tmp_path / "ddpm-b1", one_by_one, index), rtol=0,
                                   atol=1e-5 * max(1.0, float(np.abs(features).max())))

    args = ["--text", "a person walks", "--length", "20", "--solver", "ddim", "--steps", "5", "--no-video", "--no-bvh"]
    ddim = sample(run, tmp_path / "ddim", *args)
    assert (ddim["sampler"], ddim["nfe_per_batch"], ddim["diffusion"]["eta"]) == ("ddim", [5], 0.0)
    features = features_file(tmp_path / "ddim", ddim)
    # The CLI runs mfm.diffusion_sampling.sample_diffusion with the sample's noise seed.
    cond = trained.conditions(texts=["a person walks"])
    generator = torch.Generator().manual_seed(ddim["samples"][0]["noise_seed"])
    expected = sample_diffusion(trained.model, trained.diffusion, cond, [20], num_frames=20, sampler="ddim", steps=5,
                                guidance=guidance, generator=generator,
                                clip_denoised=trained.x0_clamp(trained.baseline_sampling))
    smoothed = smooth_over_time(expected.x1, [20], sigma)
    scale = max(1.0, float(np.abs(features).max()))
    np.testing.assert_allclose(features, trained.denormalize(smoothed[0]).numpy(), rtol=0, atol=1e-4 * scale)
    if sigma:  # the smoothing is FLAME's scipy gaussian_filter1d over time
        from scipy.ndimage import gaussian_filter1d

        raw = trained.denormalize(expected.x1[0]).numpy()
        np.testing.assert_allclose(features, gaussian_filter1d(raw, sigma=1.0, axis=0), rtol=0, atol=1e-4 * scale)
        unsmoothed = sample(run, tmp_path / "raw", *args, "--smoothing", "0")
        assert unsmoothed["smoothing_sigma"] == 0.0
        np.testing.assert_allclose(features_file(tmp_path / "raw", unsmoothed), raw, rtol=0, atol=1e-4 * scale)
    other_seed = sample(run, tmp_path / "seed", *args, "--seed", "1")
    assert not np.array_equal(features, features_file(tmp_path / "seed", other_seed))


def test_diffusion_replacement_edit_keeps_the_kept_part(flame_run, tmp_path, capsys):
    source = sample(flame_run, tmp_path / "source", "--text", "a person walks", "--length", "30", "--solver", "ddim",
                    "--steps", "5", "--no-video", "--no-bvh")
    source_file = tmp_path / "source" / "sample_000" / "features.npy"
    out = tmp_path / "edit"
    results = sample(flame_run, out, "--text", "a person jumps", "--edit", "inbetween", "--source-motion",
                     str(source_file), "--keep", "prefix=0.2", "--solver", "ddpm", "--steps", "5", "--no-video",
                     "--no-bvh", "--seed", "4", "--smoothing", "0")  # FLAME's smoothing would blur the kept part
    assert source["samples"][0]["length"] == 30
    (record,) = results["samples"]
    assert record["edit"]["method"] == "replacement (FLAME)" and record["edit"]["rewrite_until"] is None
    assert record["edit"]["kept_frame_ranges"] == [[0, 6], [22, 30]] and record["nfe"] == 5
    assert files_on_disk(out) == files_described(results)
    keep = np.load(out / "sample_000" / "keep_mask.npy")
    edited, original = np.load(out / "sample_000" / "features.npy"), np.load(source_file)
    np.testing.assert_allclose(edited[keep], original[keep], rtol=1e-5, atol=1e-4)
    assert np.abs(edited[~keep] - original[~keep]).mean() > 1e-2  # the middle is generated anew
    err = fails(flame_run, tmp_path / "bad", capsys, "--text", "x", "--edit", "inbetween", "--source-motion",
                str(source_file), "--rewrite-until", "0.5")
    assert "rewrite_until" in err and "replacement" in err


def test_flame_settings_are_switched_off_one_by_one_from_the_command_line_and_recorded(flame_run, tmp_path, capsys):
    """launch/sample.py applies FLAME's sampling settings to a FLAME checkpoint unless a flag turns one off
    (--no-clip-denoised, --no-baseline-defaults, --model-weights model, --steps, --guidance, --smoothing), and
    its diffusion edits copy the source's root unless --no-reference-translation; results.json records each."""
    # (FLAME's every training step without --steps: test_baseline_sampling.py, 1,000 steps being slow here)
    args = ["--text", "a person walks", "--length", "20", "--solver", "ddim", "--no-video", "--no-bvh", "--steps", "5"]
    free = sample(flame_run, tmp_path / "free", *args, "--no-clip-denoised", "--model-weights", "model",
                  "--guidance", "3", "--smoothing", "0")
    own = free["baseline_defaults"]
    assert (free["weights"], own["clip_denoised"], own["ema_weights"]) == ("model", False, False)
    assert own["overridden"] == ["guidance", "smoothing_sigma", "every_training_step", "clip_denoised",
                                 "ema_weights"]
    ours = sample(flame_run, tmp_path / "ours", *args, "--no-baseline-defaults")
    assert ours["baseline_defaults"] is None and (ours["guidance"], ours["smoothing_sigma"]) == (2.5, 0.0)
    # (what each setting does to the motions: test_baseline_sampling.py)

    source = tmp_path / "ours" / "sample_000" / "features.npy"
    edit = [*args, "--edit", "upper-body", "--source-motion", str(source)]
    copied = sample(flame_run, tmp_path / "copied", *edit)
    kept = sample(flame_run, tmp_path / "kept", *edit, "--no-reference-translation")
    assert copied["samples"][0]["edit"]["reference_translation"] is True
    assert kept["samples"][0]["edit"]["reference_translation"] is False
    root = np.load(source)[:, :4]
    # FLAME's edit_motion.py: the reference translation after the smoothing, so the source's root exactly
    np.testing.assert_allclose(features_file(tmp_path / "copied", copied)[:, :4], root, rtol=1e-6, atol=1e-5)
    assert np.abs(features_file(tmp_path / "kept", kept)[:, :4] - root).max() > 1e-3  # smoothed


def test_objectives_reject_each_others_samplers(text_run, diffusion_run, tmp_path, capsys):
    err = fails(text_run, tmp_path / "bad", capsys, "--text", "x", "--solver", "ddpm")
    assert "train.objective=flow" in err and "diffusion sampler" in err and "euler" in err
    err = fails(diffusion_run, tmp_path / "bad", capsys, "--text", "x", "--solver", "euler")
    assert "train.objective=diffusion" in err and "'ddpm' or 'ddim'" in err
    err = fails(diffusion_run, tmp_path / "bad", capsys, "--text", "x", "--solver", "ddim", "--steps", "1001")
    assert "1001 steps" in err


def test_flame_layout_samples_with_its_token_features(flame_layout_run, tmp_path):
    trained = load_trained_model(flame_layout_run)
    assert (trained.model_config.conditioning, trained.model_config.length_token) == ("cross_attention", True)
    results = sample(flame_layout_run, tmp_path / "out", "--text", "a person walks", "--length", "20", "--solver",
                     "ddim", "--steps", "5", "--guidance", "2.5", "--smoothing", "0", "--no-video", "--no-bvh")
    assert results["nfe_per_batch"] == [5] and results["diffusion"]["preset"] == "flame"
    walk = features_file(tmp_path / "out", results)
    assert walk.shape == (20, 263)
    # The text's token features reach the cross-attention (the encoder's, at the dataset's max_tokens).
    cond, extras = trained.condition_inputs(texts=["a person walks"])
    assert extras["text_tokens"].shape[1] == trained.data["text_encoder"]["max_tokens"]
    generator = torch.Generator().manual_seed(results["samples"][0]["noise_seed"])
    expected = sample_diffusion(BoundInputs(trained.model, extras), trained.diffusion, cond, [20], num_frames=20,
                                sampler="ddim", steps=5, guidance=2.5, generator=generator,
                                clip_denoised=trained.x0_clamp(trained.baseline_sampling))  # FLAME's clamp
    np.testing.assert_allclose(walk, trained.denormalize(expected.x1[0]).numpy(), rtol=0, atol=1e-4)
    unconditional = sample(flame_layout_run, tmp_path / "none", "--length", "20", "--solver", "ddim", "--steps", "5",
                           "--no-video", "--no-bvh")
    assert unconditional["conditioning"] == "none" and unconditional["guidance"] == 0.0
