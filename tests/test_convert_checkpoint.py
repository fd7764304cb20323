"""Published MFM/MDM checkpoints in our pipeline: the converted model is the reference function.

Golden data: ../shared/reference-data/mfm-reference-forward (the reference ``MDM_Flow``'s own state dict in a
small configuration, and its outputs on fixed inputs with and without the text condition).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import REFERENCE_DATA, load_launch_script

from mfm.model import MotionFlowTransformer
from mfm.reference_weights import (
    ReferenceCheckpointError,
    convert_state_dict,
    from_reference_layout,
    infer_model_config,
    load_reference_state_dict,
    reference_layout,
)

GOLDEN = REFERENCE_DATA / "mfm-reference-forward"
HUMANML3D = REFERENCE_DATA / "humanml3d"
needs_golden = pytest.mark.skipif(not (GOLDEN / "io.npz").exists(),
                                  reason=f"golden reference forward pass not found at {GOLDEN}")


def golden_model(behaviour: str) -> MotionFlowTransformer:
    state, metadata, _ = load_reference_state_dict(GOLDEN / "weights.safetensors")
    config = infer_model_config(state, behaviour=behaviour, kind="mfm", num_heads=int(metadata["num_heads"]))
    model = MotionFlowTransformer(config)
    model.load_state_dict(convert_state_dict(state, config))
    return model.eval()


def golden_io() -> dict[str, torch.Tensor]:
    io = np.load(GOLDEN / "io.npz")
    return {"x": from_reference_layout(torch.from_numpy(io["x"])), "t": torch.from_numpy(io["t"]),
            "cond": torch.from_numpy(io["text_emb"]),
            "out_cond": from_reference_layout(torch.from_numpy(io["out_cond"])),
            "out_uncond": from_reference_layout(torch.from_numpy(io["out_uncond"]))}


@needs_golden
def test_the_converted_golden_model_reproduces_the_reference_outputs():
    model, io = golden_model("reference"), golden_io()
    dropped = torch.ones(3, dtype=torch.bool)
    with torch.no_grad():
        out_cond = model(io["x"], io["t"], io["cond"])
        out_uncond = model(io["x"], io["t"], io["cond"], cond_mask=dropped)
    assert (out_cond - io["out_cond"]).abs().max() < 1e-5
    assert (out_uncond - io["out_uncond"]).abs().max() < 1e-5
    assert (io["out_cond"] - io["out_uncond"]).abs().max() > 1e-4  # the condition matters: the check can fail
    assert reference_layout(out_cond).shape == (3, 263, 1, 40)


@needs_golden
def test_our_behaviour_differs_from_the_reference_only_by_time_rounding():
    ours, reference, io = golden_model("ours"), golden_model("reference"), golden_io()
    with torch.no_grad():
        # On the grid (the golden times): the same function, up to the reference's table being computed on its
        # device (float32 rounding, < 1e-5 in these rows).
        assert (ours(io["x"], io["t"], io["cond"]) - io["out_cond"]).abs().max() < 1e-4
        # Off the grid the reference floors t to 1/1000; ours does not: at most one grid step of time apart.
        t = torch.tensor([0.4375, 0.0009, 0.99951])
        floored = torch.tensor([0.437, 0.0, 0.999])
        gap = ours.time_embedding.positions(t) - reference.time_embedding.positions(t)
        assert ((gap >= 0) & (gap < 1)).all() and gap.max() > 0.4
        assert torch.equal(reference(io["x"], t, io["cond"]), reference(io["x"], floored, io["cond"]))
        assert (ours(io["x"], t, io["cond"]) - reference(io["x"], t, io["cond"])).abs().max() > 1e-4


@needs_golden
def test_padding_is_masked_in_our_behaviour_and_attended_in_the_reference_behaviour():
    io = golden_io()
    x, t, cond = io["x"], io["t"], io["cond"]
    lengths = torch.tensor([40, 25, 31])
    padded = x.clone()
    for b, n in enumerate(lengths.tolist()):
        padded[b, n:] = 7.0  # what lies beyond a clip's length must not matter to ours
    with torch.no_grad():
        ours = golden_model("ours")
        masked = ours(padded, t, cond, lengths)
        for b, n in enumerate(lengths.tolist()):
            alone = ours(x[b:b + 1, :n], t[b:b + 1], cond[b:b + 1])
            assert (masked[b, :n] - alone[0]).abs().max() < 1e-5
            assert not masked[b, n:].any()
        reference = golden_model("reference")
        attended = reference(padded, t, cond, lengths)
        unmasked = reference(padded, t, cond)  # the reference runs without a key-padding mask
        assert torch.equal(attended, unmasked)  # padded frames' outputs are left as computed, too
        for b, n in enumerate(lengths.tolist()):
            if n < 40:  # the padding changes the valid frames, as in the reference
                assert (attended[b, :n] - reference(x[b:b + 1, :n], t[b:b + 1], cond[b:b + 1])[0]).abs().max() > 1e-4


# ------------------------------------------------------------------------------------------- shape inference


def reference_key_set(feats: int, latent: int, ff: int, layers: int, *, clip_dim: int = 512,
                      num_actions: int = 0) -> dict[str, torch.Tensor]:
    """Zero tensors with the names and shapes of MDM's ``trans_enc`` state dict (model/mdm.py). (Not uninitialised
    memory: that may hold NaN bit patterns, which the converter refuses.)"""
    shapes = {
        "sequence_pos_encoder.pe": (5000, 1, latent),
        "embed_timestep.sequence_pos_encoder.pe": (5000, 1, latent),
        "embed_timestep.time_embed.0.weight": (latent, latent), "embed_timestep.time_embed.0.bias": (latent,),
        "embed_timestep.time_embed.2.weight": (latent, latent), "embed_timestep.time_embed.2.bias": (latent,),
        "input_process.poseEmbedding.weight": (latent, feats), "input_process.poseEmbedding.bias": (latent,),
        "output_process.poseFinal.weight": (feats, latent), "output_process.poseFinal.bias": (feats,),
    }
    if num_actions:
        shapes["embed_action.action_embedding"] = (num_actions, latent)
    else:
        shapes.update({"embed_text.weight": (latent, clip_dim), "embed_text.bias": (latent,)})
    for i in range(layers):
        p = f"seqTransEncoder.layers.{i}."
        shapes.update({p + "self_attn.in_proj_weight": (3 * latent, latent), p + "self_attn.in_proj_bias": (3 * latent,),
                       p + "self_attn.out_proj.weight": (latent, latent), p + "self_attn.out_proj.bias": (latent,),
                       p + "linear1.weight": (ff, latent), p + "linear1.bias": (ff,),
                       p + "linear2.weight": (latent, ff), p + "linear2.bias": (latent,),
                       p + "norm1.weight": (latent,), p + "norm1.bias": (latent,),
                       p + "norm2.weight": (latent,), p + "norm2.bias": (latent,)})
    state = {k: torch.zeros(shape) for k, shape in shapes.items()}
    from mfm.model import sinusoidal_embedding

    table = sinusoidal_embedding(torch.arange(5000), latent).unsqueeze(1)
    state["sequence_pos_encoder.pe"] = state["embed_timestep.sequence_pos_encoder.pe"] = table
    return state


@pytest.mark.parametrize("name, feats, num_actions, cond_dim", [
    ("humanml3d", 263, 0, 512), ("kit", 251, 0, 512), ("humanact12", 150, 12, 512)])
def test_full_size_key_sets_convert_to_the_published_configs(name, feats, num_actions, cond_dim):
    state = reference_key_set(feats, 512, 1024, 8, num_actions=num_actions)
    config = infer_model_config(state, kind="mdm")
    assert (config.feature_dim, config.latent_dim, config.ff_dim, config.num_layers, config.num_heads) == \
        (feats, 512, 1024, 8, 4)
    assert config.num_actions == num_actions and config.is_action_model == bool(num_actions)
    assert config.cond_dim == cond_dim and not config.norm_first and config.activation == "gelu"
    assert (config.time_grid, config.attend_padding, config.positional_table) == ("nearest", True, "stored")
    converted = convert_state_dict(state, config)
    with torch.device("meta"):
        expected = MotionFlowTransformer(config).state_dict()
    assert set(converted) == set(expected)
    if name == "humanml3d":  # MFM's 17.88 M parameters without CLIP
        assert sum(v.numel() for k, v in converted.items() if k != "positional_table") == 17_880_327


def test_truncated_renamed_or_foreign_key_sets_are_refused_naming_the_keys():
    state = reference_key_set(263, 64, 128, 3)
    truncated = {k: v for k, v in state.items() if k != "seqTransEncoder.layers.1.linear2.weight"}
    with pytest.raises(ReferenceCheckpointError, match=r"missing 1 key\(s\): seqTransEncoder\.layers\.1\.linear2\.weight"):
        infer_model_config(truncated)
    renamed = dict(state)
    renamed["seqTransEncoder.layers.2.norm_1.weight"] = renamed.pop("seqTransEncoder.layers.2.norm1.weight")
    with pytest.raises(ReferenceCheckpointError, match=r"layers\.2\.norm1\.weight.*unexpected 1 key\(s\): "
                                                       r"seqTransEncoder\.layers\.2\.norm_1\.weight"):
        infer_model_config(renamed)
    unconditional = {k: v for k, v in state.items() if not k.startswith("embed_text")}
    with pytest.raises(ReferenceCheckpointError, match="neither embed_text nor embed_action"):
        infer_model_config(unconditional)
    decoder = {k.replace("seqTransEncoder", "seqTransDecoder"): v for k, v in state.items()}
    with pytest.raises(ReferenceCheckpointError, match="not an MDM 'trans_enc' model"):
        infer_model_config(decoder)
    wrong_width = dict(state)
    wrong_width["seqTransEncoder.layers.0.linear2.weight"] = torch.empty(64, 100)
    with pytest.raises(ReferenceCheckpointError, match=r"linear2\.weight \(64, 100\) \(expected \(64, 128\)\)"):
        infer_model_config(wrong_width)
    other_table = dict(state)
    other_table["sequence_pos_encoder.pe"] = torch.zeros(5000, 1, 64)
    with pytest.raises(ReferenceCheckpointError, match="differs from MDM's sinusoid table"):
        infer_model_config(other_table)


def test_non_finite_weights_are_refused_naming_the_tensor(tmp_path, capsys):
    """Issue 24, item 9: a reference state dict with a NaN or inf weight converted, and every motion sampled from
    it was NaN. Now it is refused, naming the tensor(s), before anything is written: one line, exit 2. A NaN in the
    stored positional table, which the table check's comparisons let through, too."""
    state = reference_key_set(263, 64, 128, 2)
    state["seqTransEncoder.layers.1.linear1.weight"][3, 5] = float("nan")
    state["output_process.poseFinal.bias"][0] = float("inf")
    source = tmp_path / "model000100000.pt"
    torch.save(state, source)
    with pytest.raises(ReferenceCheckpointError, match=r"non-finite.*seqTransEncoder\.layers\.1\.linear1\.weight "
                                                       r"\(1 of 8192 values\)"):
        infer_model_config(state)
    out = tmp_path / "converted"
    assert convert("--from", "mfm", str(source), "--dataset", "humanml3d", "--out", str(out)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(source) in err[0], err
    assert "output_process.poseFinal.bias" in err[0] and "seqTransEncoder.layers.1.linear1.weight" in err[0]
    assert not out.exists()
    table = reference_key_set(263, 64, 128, 2)
    table["sequence_pos_encoder.pe"][7, 0, 3] = float("nan")
    with pytest.raises(ReferenceCheckpointError, match=r"non-finite.*sequence_pos_encoder\.pe"):
        infer_model_config(table)


def test_files_are_read_without_pickle_code(tmp_path):
    state = reference_key_set(263, 64, 128, 2)
    wrapped = tmp_path / "model000123000.pt"
    clip = {"clip_model.token_embedding.weight": torch.zeros(4, 2)}
    torch.save({"model": {f"module.{k}": v for k, v in {**state, **clip}.items()}}, wrapped)
    loaded, _, dropped = load_reference_state_dict(wrapped)
    assert set(loaded) == set(state) and dropped == ["clip_model.token_embedding.weight"]
    needs_code = tmp_path / "with_args.pt"
    torch.save({"model": state, "args": argparse.Namespace(latent_dim=64)}, needs_code)
    with pytest.raises(ReferenceCheckpointError, match="with_args.pt: refusing a checkpoint that needs pickle code"):
        load_reference_state_dict(needs_code)
    not_a_state = tmp_path / "list.pt"
    torch.save([1, 2], not_a_state)
    with pytest.raises(ReferenceCheckpointError, match="list.pt: expected a state dict of tensors"):
        load_reference_state_dict(not_a_state)
    garbage = tmp_path / "garbage.safetensors"
    garbage.write_bytes(b"nothing")
    with pytest.raises(ReferenceCheckpointError, match="garbage.safetensors: not a readable safetensors"):
        load_reference_state_dict(garbage)


# ------------------------------------------------------------------------------------------- end to end


@pytest.fixture(scope="module")
def clip_weights(tmp_path_factory) -> Path:
    """A seeded random CLIP ViT-B/32 text tower saved as a local weights file (fp16, like OpenAI's): the real
    file-loading path, with meaningless embeddings."""
    from mfm.text import _random_clip_text_tower

    path = tmp_path_factory.mktemp("clip") / "ViT-B-32-random-text.pt"
    torch.save({k: v.half() for k, v in _random_clip_text_tower(quick_gelu=True).state_dict().items()}, path)
    return path


def convert(*args: str) -> int:
    return load_launch_script("convert_checkpoint").main(list(args))


def golden_conversion(out: Path, clip_weights: Path, kind: str = "mfm") -> list[str]:
    return ["--from", kind, str(GOLDEN / "weights.safetensors"), "--dataset", "humanml3d",
            "--mean", str(HUMANML3D / "Mean.npy"), "--std", str(HUMANML3D / "Std.npy"),
            "--clip-weights", str(clip_weights), "--out", str(out)]


@needs_golden
def test_conversion_writes_a_complete_checkpoint_and_refuses_bad_requests(tmp_path, clip_weights, capsys):
    from pipeline.generation.inference import load_trained_model

    out = tmp_path / "mfm-golden"
    assert convert(*golden_conversion(out, clip_weights)) == 0
    trained = load_trained_model(out)
    source = json.loads(json.dumps(trained.data["converted_from"]))
    assert source["kind"] == "mfm" and len(source["sha256"]) == 64 and source["behaviour"] == "reference"
    assert trained.objective == "flow" and trained.window == 196
    assert trained.data["text_encoder"]["options"] == {"context_length": 22, "quick_gelu": True}
    np.testing.assert_allclose(trained.mean.numpy(), np.load(HUMANML3D / "Mean.npy"), rtol=1e-6)
    io = golden_io()
    with torch.no_grad():
        assert (trained.model(io["x"], io["t"], io["cond"]) - io["out_cond"]).abs().max() < 1e-5

    assert convert(*golden_conversion(out, clip_weights)) == 2  # the folder is taken
    assert "already holds files" in capsys.readouterr().err
    assert convert(*golden_conversion(tmp_path / "kit", clip_weights)[:-4], "--dataset", "kit",
                   "--out", str(tmp_path / "kit")) == 2
    assert "263-D features, but --dataset kit has 251-D" in capsys.readouterr().err
    assert convert("--from", "mfm", str(GOLDEN / "weights.safetensors"), "--dataset", "humanml3d",
                   "--reference-root", str(tmp_path), "--out", str(tmp_path / "no-stats")) == 2
    assert "dataset/HumanML3D/Mean.npy: no such file" in capsys.readouterr().err
    assert not (tmp_path / "no-stats").exists()


@pytest.mark.slow
@needs_golden
def test_a_converted_checkpoint_samples_edits_and_is_evaluated(tmp_path, clip_weights):
    from eval_worker import SMALL_PROTOCOL, random_contrastive_evaluator

    from launch.evaluate import main as evaluate
    from preprocess.shards import BuildConfig, build_dataset

    def sample(*args: str) -> int:
        return load_launch_script("sample").main(list(args))

    flow, mdm = tmp_path / "mfm", tmp_path / "mdm"
    assert convert(*golden_conversion(flow, clip_weights)) == 0
    assert convert(*golden_conversion(mdm, clip_weights, kind="mdm")) == 0
    common = ["--text-weights", str(clip_weights), "--no-video", "--no-bvh"]

    assert sample("--checkpoint", str(flow), "--text", "a person walks forward.", "--seconds", "2",
                  "--num-samples", "2", "--out", str(tmp_path / "t2m"), *common) == 0
    features = np.load(tmp_path / "t2m" / "sample_000" / "features.npy")
    assert features.shape == (40, 263) and np.isfinite(features).all()
    assert np.load(tmp_path / "t2m" / "sample_000" / "joints.npy").shape == (40, 22, 3)

    source = HUMANML3D / "new_joint_vecs_012314.npy"
    assert sample("--checkpoint", str(flow), "--text", "a person jumps.", "--edit", "prediction",
                  "--source-motion", str(source), "--keep", "prefix=0.3", "--out", str(tmp_path / "edit"),
                  *common) == 0
    edit = json.loads((tmp_path / "edit" / "results.json").read_text())
    assert edit["mode"] == "edit" and edit["samples"][0]["edit"]["kept_frame_ranges"] == [[0, 51]]
    assert np.load(tmp_path / "edit" / "sample_000" / "features.npy").shape == (170, 263)

    assert sample("--checkpoint", str(mdm), "--text", "a person waves.", "--length", "30", "--solver", "ddim",
                  "--steps", "4", "--out", str(tmp_path / "ddim"), *common) == 0
    assert np.isfinite(np.load(tmp_path / "ddim" / "sample_000" / "features.npy")).all()

    prompts = REFERENCE_DATA / "prompts" / "composition_humanml.json"
    assert sample("--checkpoint", str(flow), "--compose", str(prompts), "--out", str(tmp_path / "compose"),
                  *common) == 2  # distinct texts need bpe + pccat: refused with the reason

    data = tmp_path / "embedded-clip"
    build_dataset(BuildConfig(out=data, source="deepmimic", text_encoder="clip-vit-b-32",
                              text_weights=str(clip_weights), text_options={"context_length": 22}, progress=False))
    evaluator = random_contrastive_evaluator(data / "manifest.json", tmp_path / "evaluator.safetensors")
    assert evaluate(["--checkpoint", str(flow), "--protocol", "fast", f"data.manifest={data / 'manifest.json'}",
                     f"evaluator.path={evaluator}", "sampling.steps=[2]", f"output.dir={tmp_path / 'eval'}",
                     *SMALL_PROTOCOL]) == 0
    results = [json.loads(line) for line in (tmp_path / "eval" / "results.jsonl").read_text().splitlines()]
    scored = [r for r in results if r["checkpoint_dataset_id"].startswith("humanml3d:mfm-reference:")]
    assert scored and all(np.isfinite(r["fid"]) and np.isfinite(r["r_precision_top1"]) for r in scored)
    assert any("edit_prediction_ade" in r for r in scored)


def test_a_kit_state_dict_converts_with_the_kit_feature_spec_and_its_step(tmp_path):
    from mfm.text import OPENAI_VIT_B_32_SHA256
    from pipeline.generation.inference import load_trained_model

    state = reference_key_set(251, 64, 128, 2)
    for key, value in state.items():
        if "pe" not in key.split(".")[-1]:
            value.normal_(0, 0.02)
    source = tmp_path / "model000200000.pt"
    torch.save(state, source)
    stats = tmp_path / "motionfm" / "dataset" / "KIT-ML"
    stats.mkdir(parents=True)
    np.save(stats / "Mean.npy", np.zeros(251, np.float32))
    np.save(stats / "Std.npy", np.ones(251, np.float32))
    assert convert("--from", "mdm", str(source), "--dataset", "kit", "--reference-root", str(tmp_path / "motionfm"),
                   "--out", str(tmp_path / "kit")) == 0
    trained = load_trained_model(tmp_path / "kit")
    assert trained.step == 200_000 and trained.checkpoint.name == "step-00200000"
    spec = trained.data["feature_spec"]
    assert (spec["skeleton"], spec["dim"], spec["num_joints"], spec["fps"]) == ("kit", 251, 21, 12.5)
    assert trained.objective == "diffusion" and trained.diffusion_preset == "mdm"
    assert trained.model_config.time_grid == "nearest"
    assert trained.data["text_encoder"]["weights_sha256"] == OPENAI_VIT_B_32_SHA256
    assert trained.data["normalization"]["files"]["std"]["path"].endswith("KIT-ML/Std.npy")
    with torch.no_grad():  # the diffusion code passes step/1000: the reference's integer step is recovered
        steps = torch.arange(1000)
        assert torch.equal(trained.model.time_embedding.positions(trained.diffusion.model_time(steps)).long(), steps)
