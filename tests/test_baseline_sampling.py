"""The FLAME row run as FLAME's authors ran it (issue 25): every training step, the x0 clamp and the EMA weights
(``sampling.baseline_*`` options), and FLAME's editing procedure's reference translation for every diffusion edit
(``tasks.edit_reference_translation``); results record them and the units' keys carry them.

Tiny in-memory models (no training): what is checked is that each setting reaches the sampler and what it does to
the output, not the quality of the samples.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from mfm.diffusion import diffusion_from_preset
from mfm.editing import edit_mask
from mfm.layout import FeatureLayout
from mfm.model import ModelConfig, MotionFlowTransformer, valid_frame_mask
from mfm.skeleton import HUMANML3D
from pipeline.evaluation.config import SamplingConfig, SamplingPoint, load_eval_config
from pipeline.evaluation.job import CheckpointScorer, baseline_record, checkpoint_settings
from pipeline.evaluation.replications import check_weights, generate, points_for
from pipeline.evaluation.spaces import EvaluationError
from pipeline.generation.inference import TrainedModel
from pipeline.generation.integration import resolve_integrator
from pipeline.generation.request import SampleRequest, SamplingError, load_sample_request
from pipeline.generation.sampling import PromptConditions, SampleSpec, SourceMotion, _edit_record, generate_batch

pytestmark = pytest.mark.usefixtures("single_thread")

LAYOUT = FeatureLayout(HUMANML3D)
ROT = LAYOUT.slices["rot6d"]


def tiny_model(objective: str = "diffusion", preset: str | None = "flame", weights: str = "ema",
               guided_features: str = "all") -> TrainedModel:
    """An untrained tiny HumanML3D-layout model; unit normalisation, so raw = normalised features."""
    config = ModelConfig(feature_dim=LAYOUT.dim, latent_dim=16, ff_dim=32, num_layers=1, num_heads=2, cond_dim=4,
                         max_len=64, output_dim=2 * LAYOUT.dim if preset == "flame" else None,
                         guided_features=guided_features)
    torch.manual_seed(0)
    model = MotionFlowTransformer(config).eval()
    data = {"normalization": {"mean": [0.0] * LAYOUT.dim, "std": [1.0] * LAYOUT.dim},
            "feature_spec": {"skeleton": "humanml3d", "fps": 20}}
    diffusion = diffusion_from_preset(preset) if objective == "diffusion" else None
    return TrainedModel(model, config, Path(f"{preset}-step-1"), 1, weights, data, torch.device("cpu"), 64,
                        objective, preset if objective == "diffusion" else None, diffusion)


def sample(trained: TrainedModel, sampling: SamplingConfig, point: SamplingPoint, **edit) -> torch.Tensor:
    lengths = torch.tensor([10, 7])
    cond = torch.randn(2, 4, generator=torch.Generator().manual_seed(1))
    raw, _ = generate(trained, cond, {}, lengths, [1, 2], point, sampling, **edit)
    return raw


def test_flame_row_runs_all_its_training_steps_unless_the_sweep_is_asked_to_vary_them():
    flame = tiny_model()
    sweep = [SamplingPoint("ddpm", 10, 2.5), SamplingPoint("ddpm", 50, 2.5), SamplingPoint("euler", 10, 2.5)]
    # FLAME's diffusion_module.py: 61-65 samples every one of its 1,000 steps, at its guidance 8.0
    assert points_for(flame, sweep, SamplingConfig()) == (SamplingPoint("ddpm", 1000, 8.0),)
    assert points_for(flame, sweep, SamplingConfig(baseline_steps=False)) == (
        SamplingPoint("ddpm", 10, 8.0), SamplingPoint("ddpm", 50, 8.0))
    assert points_for(flame, sweep, SamplingConfig(baseline_defaults=False)) == tuple(sweep[:2])
    flowmdm = tiny_model(preset="flowmdm")  # no settings of its authors': the sweep as given
    assert points_for(flowmdm, sweep, SamplingConfig()) == tuple(sweep[:2])


def test_flame_row_clamps_its_x0_estimates_as_flame_on_the_6d_rotations():
    flame, point = tiny_model(), SamplingPoint("ddpm", 3, 8.0)
    clamped = sample(flame, SamplingConfig(), point)
    free = sample(flame, SamplingConfig(baseline_clip_denoised=False), point)
    assert float(clamped[..., ROT].abs().max()) <= 1.0 + 1e-5  # raw 6D components in [-1, 1], smoothing included
    assert float(free[..., ROT].abs().max()) > 1.5  # the untrained model's estimates leave the range unclamped
    assert float(clamped[..., : ROT.start].abs().max()) > 1.5  # the other channels are not clamped


def test_diffusion_edits_copy_the_reference_root_after_the_smoothing_and_mfm_edits_do_not():
    lengths = torch.tensor([10, 7])
    valid = valid_frame_mask(lengths, 10).unsqueeze(-1)
    known = torch.randn(2, 10, LAYOUT.dim, generator=torch.Generator().manual_seed(2)) * valid
    keep = edit_mask("upper_body", lengths, 10, LAYOUT)
    point = SamplingPoint("ddpm", 3, 8.0)
    for diffusion in (tiny_model(), tiny_model(preset="flowmdm")):  # FLAME's procedure: smoothed (FLAME) or not
        copied = sample(diffusion, SamplingConfig(), point, known=known, keep=keep, reference_translation=True)
        # FLAME's edit_motion.py: 79-82 smooths, then 93-94 overwrites the translation: the source's root exactly
        torch.testing.assert_close(copied[..., :4] * valid, known[..., :4], rtol=0, atol=1e-6)
        raw = sample(diffusion, SamplingConfig(), point, known=known, keep=keep, reference_translation=False)
        assert float((raw[..., :4] - known[..., :4]).abs().max()) > 1e-2
        torch.testing.assert_close(copied[..., 4:], raw[..., 4:], rtol=0, atol=0)  # only the root dims change
    flow = tiny_model(objective="flow", preset=None)  # the MFM row keeps its own procedure: no copy
    edited = sample(flow, SamplingConfig(), SamplingPoint("euler", 3, 1.0), known=known, keep=keep,
                    reference_translation=True)
    assert float((edited[..., :4] - known[..., :4]).abs().max()) > 1e-2
    assert load_eval_config("fast").tasks.edit_reference_translation  # on by default


def test_flame_row_is_not_silently_scored_with_raw_weights():
    without_ema = tiny_model(weights="model")
    with pytest.raises(EvaluationError, match="no EMA weights.*sampling.use_ema=false"):
        check_weights(without_ema, SamplingConfig())
    check_weights(without_ema, SamplingConfig(use_ema=False))  # asked for: scored, recorded as checkpoint.weights
    check_weights(without_ema, SamplingConfig(baseline_defaults=False))
    check_weights(tiny_model(), SamplingConfig())
    check_weights(tiny_model(objective="flow", preset=None, weights="model"), SamplingConfig())  # ours: fallback


def test_results_record_the_flame_settings_and_units_are_keyed_by_them():
    flame = tiny_model()
    record = baseline_record(flame, SamplingConfig())
    assert record["smoothing_sigma"] == 1.0
    own = record["baseline_defaults"]
    assert (own["preset"], own["guidance"], own["every_training_step"], own["clip_denoised"],
            own["ema_weights"]) == ("flame", 8.0, True, True, True)
    assert "6D rotation" in own["clip_denoised_range"] and "sample_util.py: 90" in own["source"]
    off = baseline_record(flame, SamplingConfig(baseline_steps=False, baseline_clip_denoised=False))
    assert (off["baseline_defaults"]["every_training_step"], off["baseline_defaults"]["clip_denoised"]) == (False,
                                                                                                           False)
    assert "clip_denoised_range" not in off["baseline_defaults"]
    assert baseline_record(flame, SamplingConfig(baseline_defaults=False))["baseline_defaults"] is None

    ids, point = {"checkpoint": "c", "evaluator": "e", "gt": "g"}, SamplingPoint("ddpm", 1000, 8.0)

    def key(trained, *overrides):
        cfg = load_eval_config("fast", overrides=list(overrides))
        return CheckpointScorer(cfg, None).unit_for(Path("s"), ids, point, checkpoint_settings(trained, cfg)).key

    keys = [key(flame), key(flame, "sampling.baseline_steps=false"), key(flame, "sampling.baseline_clip_denoised=false"),
            key(flame, "tasks.edit_reference_translation=false"), key(tiny_model(preset="flowmdm")),
            key(tiny_model(preset="flowmdm"), "tasks.edit_reference_translation=false")]
    assert len(set(keys)) == len(keys)
    # flow checkpoints read none of these: their keys are what they were before the settings existed
    flow = tiny_model(objective="flow", preset=None)
    plain = CheckpointScorer(load_eval_config("fast"), None).unit_for(Path("s"), ids, point).key
    assert checkpoint_settings(flow, load_eval_config("fast")) == {}
    assert key(flow) == key(flow, "tasks.edit_reference_translation=false", "sampling.baseline_steps=false") == plain


def test_an_explicit_output_smoothing_is_what_every_checkpoint_samples_with_and_results_record_and_keys_carry():
    """sampling.output_smoothing: one σ for every checkpoint (0 = the network's raw output) in place of each one's
    own (model.output_smoothing; FLAME's σ = 1); unset, the keys stay what they were."""
    from mfm.diffusion_sampling import smooth_over_time

    flow, point = tiny_model(objective="flow", preset=None), SamplingPoint("euler", 2, 2.5)
    raw = sample(flow, SamplingConfig(output_smoothing=0.0), point)
    smoothed = sample(flow, SamplingConfig(output_smoothing=1.0), point)
    lengths = torch.tensor([10, 7])
    expected = smooth_over_time(raw, lengths, 1.0) * valid_frame_mask(lengths, raw.shape[1]).unsqueeze(-1)
    torch.testing.assert_close(smoothed, expected)
    assert float((smoothed - raw).abs().max()) > 1e-3
    assert baseline_record(flow, SamplingConfig(output_smoothing=0.7))["smoothing_sigma"] == 0.7
    assert baseline_record(tiny_model(), SamplingConfig(output_smoothing=0.0))["smoothing_sigma"] == 0.0  # FLAME
    ids = {"checkpoint": "c", "evaluator": "e", "gt": "g"}

    def key(*overrides):
        return CheckpointScorer(load_eval_config("fast", overrides=list(overrides)), None).unit_for(
            Path("s"), ids, point).key

    assert key() == key("sampling.output_smoothing=null") != key("sampling.output_smoothing=0.7")


def test_smoothing_that_keeps_the_bones_reaches_the_evaluator_its_records_and_its_keys():
    """sampling.output_smoothing_keeps_bones (unset: each checkpoint's model.output_smoothing_keeps_bones, False
    here): the smoothed motion with every bone given back its length before the filter."""
    from mfm.diffusion_sampling import BoneKeeping, smooth_over_time
    from mfm.features import restore_bone_lengths

    flow, point = tiny_model(objective="flow", preset=None), SamplingPoint("euler", 2, 2.5)
    lengths = torch.tensor([10, 7])
    raw = sample(flow, SamplingConfig(output_smoothing=0.0), point)
    plain = sample(flow, SamplingConfig(output_smoothing=1.0), point)
    kept = sample(flow, SamplingConfig(output_smoothing=1.0, output_smoothing_keeps_bones=True), point)
    valid = valid_frame_mask(lengths, raw.shape[1]).unsqueeze(-1)
    expected = restore_bone_lengths(smooth_over_time(raw, lengths, 1.0), raw, flow.skeleton) * valid
    torch.testing.assert_close(kept, expected, atol=1e-5, rtol=1e-5)
    assert float((kept - plain).abs().max()) > 1e-3
    assert baseline_record(flow, SamplingConfig())["smoothing_keeps_bones"] is False
    assert baseline_record(flow, SamplingConfig(output_smoothing_keeps_bones=True))["smoothing_keeps_bones"] is True
    ids = {"checkpoint": "c", "evaluator": "e", "gt": "g"}

    def key(*overrides):
        return CheckpointScorer(load_eval_config("fast", overrides=list(overrides)), None).unit_for(
            Path("s"), ids, point).key

    assert key() == key("sampling.output_smoothing_keeps_bones=null") != key(
        "sampling.output_smoothing_keeps_bones=true") != key("sampling.output_smoothing_keeps_bones=smoothed")
    smoothed = sample(flow, SamplingConfig(output_smoothing=1.0, output_smoothing_keeps_bones="smoothed"), point)
    expected = smooth_over_time(raw, lengths, 1.0, BoneKeeping(flow.skeleton, flow.mean, flow.std, "smoothed"))
    torch.testing.assert_close(smoothed, expected * valid, atol=1e-5, rtol=1e-5)
    assert baseline_record(flow, SamplingConfig(output_smoothing_keeps_bones="smoothed"))[
        "smoothing_keeps_bones"] == "smoothed"
    with pytest.raises(ValueError, match="output_smoothing_keeps_bones"):
        SamplingConfig(output_smoothing_keeps_bones="maybe")


def test_pose_guidance_is_each_flow_checkpoints_own_unless_the_sweep_sets_it_and_results_record_it():
    """model.guided_features='pose' reaches the evaluator's sampler: the root-motion channels integrate the
    conditional field (guidance 2.5 then differs from 'all' there, and the run is exactly 'all' at guidance 1);
    sampling.guided_features overrides it for every flow checkpoint, results record what ran, and an explicit
    setting goes into the unit key (unset: keys as before)."""
    pose, point = tiny_model(objective="flow", preset=None, guided_features="pose"), SamplingPoint("euler", 3, 2.5)
    own = sample(pose, SamplingConfig(output_smoothing=0.0), point)
    every = sample(pose, SamplingConfig(output_smoothing=0.0, guided_features="all"), point)
    assert float((own - every).abs().max()) > 1e-3
    plain = SamplingPoint("euler", 3, 1.0)
    torch.testing.assert_close(sample(pose, SamplingConfig(output_smoothing=0.0), plain),
                               sample(pose, SamplingConfig(output_smoothing=0.0, guided_features="all"), plain))
    flow = tiny_model(objective="flow", preset=None)
    torch.testing.assert_close(sample(flow, SamplingConfig(output_smoothing=0.0, guided_features="pose"), point), own)
    assert baseline_record(pose, SamplingConfig())["guided_features"] == "pose"
    assert baseline_record(pose, SamplingConfig(guided_features="all"))["guided_features"] == "all"
    assert baseline_record(tiny_model(), SamplingConfig(guided_features="pose"))["guided_features"] == "all"  # FLAME
    ids = {"checkpoint": "c", "evaluator": "e", "gt": "g"}

    def key(*overrides):
        return CheckpointScorer(load_eval_config("fast", overrides=list(overrides)), None).unit_for(
            Path("s"), ids, point).key

    assert key() == key("sampling.guided_features=null") != key("sampling.guided_features=pose")
    with pytest.raises(ValueError, match="guided_features"):
        SamplingConfig(guided_features="root")


# ---------------------------------------------------------------------------------------------------------------
# launch/sample.py (and MotionPipeline, contact sheets: pipeline/generation) runs FLAME's checkpoints FLAME's way too


def sample_request(**keys) -> SampleRequest:
    return SampleRequest(checkpoint="unused", out_dir="", **{"texts": ("a", "b"), **keys})


def sampled(trained: TrainedModel, request: SampleRequest, source: SourceMotion | None = None) -> torch.Tensor:
    """The sampler's batch for the two motions :func:`sample` draws (same lengths, conditions and seeds)."""
    specs = [SampleSpec(0, 0, 10, 1), SampleSpec(1, 1, 7, 2)]
    conditions = PromptConditions(torch.randn(2, 4, generator=torch.Generator().manual_seed(1)), {})
    return generate_batch(request, trained, resolve_integrator(request, trained), specs, conditions, source,
                          {}).features


def test_sample_py_samples_a_flame_checkpoint_as_the_evaluator_does_x0_clamp_included():
    flame = tiny_model()
    # FLAME's settings: guidance 8.0, σ = 1, the clamp on the 6D rotations; three steps to keep the test short
    ours = sampled(flame, sample_request(steps=3))
    scored = sample(flame, SamplingConfig(baseline_steps=False), SamplingPoint("ddpm", 3, 8.0))
    torch.testing.assert_close(ours, scored, rtol=0, atol=1e-6)
    assert float(ours[..., ROT].abs().max()) <= 1.0 + 1e-5
    free = sampled(flame, sample_request(steps=3, baseline_clip_denoised=False))
    torch.testing.assert_close(free, sample(flame, SamplingConfig(baseline_steps=False, baseline_clip_denoised=False),
                                            SamplingPoint("ddpm", 3, 8.0)), rtol=0, atol=1e-6)
    assert float(free[..., ROT].abs().max()) > 1.5
    # baseline_defaults=false: our defaults (the model's guidance 2.5, no smoothing, no clamp), as the evaluator's
    plain = sampled(flame, sample_request(steps=3, baseline_defaults=False))
    torch.testing.assert_close(plain, sample(flame, SamplingConfig(baseline_defaults=False),
                                             SamplingPoint("ddpm", 3, 2.5)), rtol=0, atol=1e-6)


def test_sample_py_records_flames_settings_as_run_and_each_override():
    flame = tiny_model()
    default = sample_request()
    integrator = resolve_integrator(default, flame)
    assert integrator.steps == 1000 and integrator.clip_denoised is not None  # every training step, clamped
    record = default.baseline_record(flame)
    assert (record["preset"], record["guidance"], record["smoothing_sigma"], record["every_training_step"],
            record["clip_denoised"], record["ema_weights"], record["overridden"]) == ("flame", 8.0, 1.0, True, True,
                                                                                    True, [])
    assert "6D rotation" in record["clip_denoised_range"] and "sample_util.py: 90" in record["source"]
    assert sample_request(steps=1000).baseline_record(flame)["overridden"] == []  # all its steps: FLAME's count

    every = sample_request(steps=5, guidance=2.5, smoothing=0.0, baseline_clip_denoised=False, weights="model")
    record = every.baseline_record(flame)
    assert (record["every_training_step"], record["clip_denoised"], record["ema_weights"]) == (False, False, False)
    assert "clip_denoised_range" not in record
    assert record["overridden"] == ["guidance", "smoothing_sigma", "every_training_step", "clip_denoised",
                                    "ema_weights"]
    integrator = resolve_integrator(every, flame)
    assert (integrator.steps, integrator.clip_denoised) == (5, None)
    assert (every.guidance_for(flame), every.smoothing_for(flame)) == (2.5, 0.0)

    ours = sample_request(baseline_defaults=False)
    assert ours.baseline_record(flame) is None and resolve_integrator(ours, flame).clip_denoised is None
    assert (ours.guidance_for(flame), ours.smoothing_for(flame)) == (2.5, 0.0)  # the model's own
    assert resolve_integrator(ours, flame).steps == 1000  # our diffusion default: every step as well
    flowmdm = tiny_model(preset="flowmdm")  # no authors' settings of its own
    assert default.baseline_record(flowmdm) is None and resolve_integrator(default, flowmdm).clip_denoised is None
    assert load_sample_request(None, ["checkpoint=c", "out_dir=o"], {}).baseline_defaults  # on by default


def test_sample_py_refuses_to_sample_a_flame_checkpoint_without_ema_as_if_it_were_its_ema():
    without_ema = tiny_model(weights="model")  # a run that kept no EMA: loading fell back to the raw weights
    with pytest.raises(SamplingError, match="no EMA weights.*--model-weights model"):
        resolve_integrator(sample_request(), without_ema)
    asked = sample_request(weights="model")
    resolve_integrator(asked, without_ema)
    assert asked.baseline_record(without_ema)["overridden"] == ["ema_weights"]
    resolve_integrator(sample_request(baseline_defaults=False), without_ema)
    resolve_integrator(sample_request(), tiny_model(preset="flowmdm", weights="model"))  # ours: the fallback stays


def test_sample_py_diffusion_edits_copy_the_source_root_after_the_smoothing_unless_turned_off():
    flame = tiny_model()
    source = SourceMotion(Path("source.npy"), "features",
                          torch.randn(10, LAYOUT.dim, generator=torch.Generator().manual_seed(2)))
    edit = {"edit": "upper-body", "source_motion": "source.npy", "steps": 3}
    copied = sampled(flame, sample_request(**edit), source)
    not_copied = sampled(flame, sample_request(**edit, edit_reference_translation=False), source)
    lengths = torch.tensor([10, 7])
    valid = valid_frame_mask(lengths, 10).unsqueeze(-1)
    # FLAME's edit_motion.py: 79-82 smooths (σ = 1), then 93-94 sets the reference translation: the source's root
    torch.testing.assert_close(copied[..., :4], source.features[:, :4].expand(2, -1, -1) * valid, rtol=0, atol=0)
    assert float((not_copied[..., :4] - copied[..., :4]).abs().max()) > 1e-2  # smoothed without the copy
    torch.testing.assert_close(copied[..., 4:], not_copied[..., 4:], rtol=0, atol=0)  # only the root dims
    # ... exactly what the evaluator makes of the same edit (its tasks.edit_reference_translation)
    known = source.features.expand(2, -1, -1) * valid
    keep = edit_mask("upper_body", lengths, 10, LAYOUT)
    scored = sample(flame, SamplingConfig(baseline_steps=False), SamplingPoint("ddpm", 3, 8.0), known=known, keep=keep,
                    reference_translation=True, restore_known=True)
    torch.testing.assert_close(copied, scored, rtol=0, atol=1e-6)

    keep_np = keep[0].numpy()
    record = _edit_record(sample_request(**edit), resolve_integrator(sample_request(**edit), flame), source, {},
                          keep_np)
    assert record["reference_translation"] is True
    off = sample_request(**edit, edit_reference_translation=False)
    assert _edit_record(off, resolve_integrator(off, flame), source, {}, keep_np)["reference_translation"] is False
    flow = tiny_model(objective="flow", preset=None)  # MFM's procedure never copies: nothing to record
    flow_edit = sample_request(edit="upper-body", source_motion="source.npy")
    assert _edit_record(flow_edit, resolve_integrator(flow_edit, flow), source, {}, keep_np)[
        "reference_translation"] is None


def test_motion_pipeline_samples_a_flame_checkpoint_flames_way_unless_told_otherwise():
    from pipeline.generation.pretrained import MotionPipeline

    flame = tiny_model()
    pipe = MotionPipeline(flame)
    clamped = pipe(lengths=10, steps=3).features[0]  # unit normalisation: raw = normalised features
    free = pipe(lengths=10, steps=3, clip_denoised=False).features[0]
    assert abs(clamped[:, ROT]).max() <= 1.0 + 1e-5 and abs(free[:, ROT]).max() > 1.5
    plain = pipe(lengths=10, steps=3, baseline_defaults=False).features[0]
    assert abs(plain[:, ROT]).max() > 1.5
    with pytest.raises(SamplingError, match="no EMA weights"):  # asked for the EMA the run did not keep
        MotionPipeline(tiny_model(weights="model"), weights="ema")(lengths=10, steps=3)
    MotionPipeline(tiny_model(weights="model"))(lengths=10, steps=3)  # the weights it holds, as given
