"""Sample (or edit) motions from a trained checkpoint and write files people can use: the engine behind
``launch/sample.py``.

A :class:`SampleRequest` says what to generate; :func:`run_sampling` loads the checkpoint, generates every sample
in batches of ``batch_size`` and writes, into ``out_dir``::

    index.html                   the motions to browse: animated stick figures, captions, lengths, plausibility
                                 (pipeline/generation/browse.py; self-contained, opens from disk)
    results.json                 describes every file below (and nothing else) plus the settings and timings, and
                                 each sample's plausibility figures (mfm.metrics.plausibility of its joints:
                                 bone-length range / deviation, floor penetration, foot skating, mean jerk)
    sample_000/features.npy      (L, D) float32 features, un-normalised (the dataset's HumanML3D-style vector)
    sample_000/joints.npy        (L, J, 3) float32 joint positions, recovered from the ric block (recover_from_ric;
                                 ``decode='rigid'``: then fitted onto the skeleton's fixed bone lengths)
    sample_000/motion.mp4|.gif   stick figure, caption as title (GIF when ffmpeg is missing or asked for)
    sample_000/motion.bvh        BVH for Blender (mfm.export.bvh: metres, Y up, channels Yrotation Xrotation
                                 Zrotation i.e. R = Ry·Rx·Rz, Blender Euler order ZXY) of the rigid decode
                                 (mfm.features.rigid_joints), whatever ``decode`` says: a rig needs fixed bones
    sample_000/keep_mask.npy     edits only: (L, D) bool, True = taken from the source motion
    sample_000/trajectory.png    on request: x̂1 estimates along the ODE trajectory (MFM Figure 4 style)

Sample ``i`` is prompt ``i // num_samples``'s ``(i % num_samples)``-th repetition. Determinism: sample ``i``'s
initial noise comes from its own generator seeded with ``SeedSequence([seed, i])``, and sampled lengths from a
generator seeded with ``seed``; since the model masks padded frames out of attention, a sample does not depend on
the batch it lands in (up to floating-point summation order), so ``batch_size`` does not change results.

Lengths: ``lengths`` (frames) or ``seconds``, one value for every prompt or one per prompt; otherwise drawn from the
checkpoint's training length distribution (sampling) or the source motion's length (editing). They are clamped to
:func:`max_sample_length`.

Editing (MFM trajectory rewriting, mfm.editing): the source motion is a ``.npy`` of un-normalised features (T, D) or
joint positions (T, J, 3) on the checkpoint's skeleton (converted with joints_to_features: T - 1 frames); it is
normalised, cropped to each sample's length, and a preset mask says what is kept. Frames past the source's end are
never kept (there is nothing to keep); they are generated. Without a text/action the edit is unconditional.

Objectives: a flow checkpoint (``train.objective=flow``) integrates its velocity field with an ODE solver (euler,
midpoint, heun, rk4 or a torchdiffeq method; default euler, 10 steps). A diffusion checkpoint (``train.objective=
diffusion``, FLAME / FlowMDM presets) runs the reverse chain with ``solver`` ``'ddpm'`` (ancestral, the references'
sampler) or ``'ddim'`` (eta 0, deterministic), ``steps`` respaced from the training steps (default: all of them,
1000); an evaluation is one denoiser pass (a guided one batches both halves), so nfe = steps. Diffusion samplers draw
a batch's initial and per-step noise from one generator seeded with the batch's first sample's ``noise_seed``, so
unlike flow samples they depend on ``batch_size``. Editing a diffusion model is FLAME's replacement editing (the kept
part is re-noised onto the chain before every step; ``rewrite_until`` does not apply) with the same mask presets;
as FLAME's edit_motion.py, the source's root is copied into the output where the edit keeps it, after the smoothing
(``edit_reference_translation``). A checkpoint of a preset whose authors sampled it their own way (FLAME) samples
that way unless the request overrides a setting (``baseline_defaults``: guidance 8.0, σ = 1 smoothing, every training
step, the x0 clamp on the 6D rotations, EMA weights), as the evaluator does (pipeline.generation.inference
TrainedModel's x0_clamp, finish_output, check_baseline_weights serve both); results.json's ``baseline_defaults`` says
what ran and what was overridden.

Composition (FlowMDM, one long sequence from several (text, length) segments) lives in pipeline/generation/composing.py; it
shares this module's request, outputs and checkpoint loading.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from mfm.composition import BoundInputs, bind_inputs
from mfm.diffusion_sampling import replacement_edit, sample_diffusion
from mfm.editing import (
    edit,
    edit_mask,
    joint_frame_mask,
    motion_to_features,
)
from mfm.guidance import classifier_free_guidance
from mfm.layout import FeatureLayout
from mfm.model import valid_frame_mask
from mfm.solvers import (
    SolveResult,
    draw_noise,
    guided_velocity,
    sample,
    sample_lengths,
    seeded_generators,
)
from pipeline.generation.browse import write_index_page
from pipeline.generation.inference import TrainedModel
from pipeline.generation.integration import (
    Integrator,
    load_for_request,
    resolve_integrator,
    sample_seed,
    synchronize,
)
from pipeline.generation.outputs import (
    RESULTS_FILE,
    SampleWriter,
    frame_ranges,
    prepare_out_dir,
    results_header,
    write_json_atomically,
    write_mdm_layout,
)
from pipeline.generation.request import (
    EDIT_PRESETS,
    KEEP_OPTIONS,
    SampleRequest,
    SamplingError,
)

logger = logging.getLogger(__name__)

@dataclasses.dataclass(frozen=True)
class SampleSpec:
    index: int
    prompt: int | None  # index into the request's texts/actions; None: unconditional
    length: int
    seed: int

@dataclasses.dataclass
class SourceMotion:
    """A source motion in the model's (normalised) feature space."""

    path: Path
    kind: str  # "features" or "joints"
    features: torch.Tensor  # (T, D), normalised

def max_sample_length(trained: TrainedModel) -> int:
    """Longest motion to ask for: the window the model was trained on (196 frames for HumanML3D, as MDM/MFM)."""
    return min(int(trained.window), int(trained.model_config.max_frames))

def _prompt_count(request: SampleRequest) -> int:
    return len(request.texts) or len(request.actions)

def requested_lengths(request: SampleRequest, fps: float) -> list[int] | None:
    """Per-prompt lengths in frames from ``lengths``/``seconds`` (None when neither was given)."""
    values: list[float] = list(request.lengths) or [s * fps for s in request.seconds]
    if not values:
        return None
    prompts = max(_prompt_count(request), 1)
    if len(values) not in (1, prompts):
        raise SamplingError(f"give one length for all prompts or one per prompt ({prompts}), got {len(values)}")
    frames = [int(round(v)) for v in values]
    if min(frames) < 1:
        raise SamplingError(f"lengths must be at least one frame, got {frames}")
    return frames * prompts if len(frames) == 1 else frames

def plan_samples(request: SampleRequest, trained: TrainedModel, source: SourceMotion | None) -> list[SampleSpec]:
    """One SampleSpec per output motion, with its prompt, length (clamped) and noise seed."""
    prompts = _prompt_count(request)
    prompt_of = [p for p in range(prompts) for _ in range(request.num_samples)] or [None] * request.num_samples
    n = len(prompt_of)
    per_prompt = requested_lengths(request, trained.fps)
    if per_prompt is not None:
        lengths = [per_prompt[p or 0] for p in prompt_of]
    elif source is not None:
        lengths = [source.features.shape[0]] * n
    elif trained.train_lengths:
        generator = torch.Generator().manual_seed(request.seed)
        lengths = sample_lengths(trained.train_lengths, n, generator).tolist()
    else:
        raise SamplingError(f"{trained.checkpoint} records no training lengths: give lengths or seconds")
    limit = max_sample_length(trained)
    if max(lengths) > limit:
        logger.warning("clamping lengths above %d frames (the model's max_frames) to %d", limit, limit)
    return [SampleSpec(i, prompt_of[i], min(int(lengths[i]), limit), sample_seed(request.seed, i)) for i in range(n)]

def batches(specs: Sequence[SampleSpec], batch_size: int) -> Iterator[list[SampleSpec]]:
    """Chunks of ``batch_size``, longest samples together (less padding to compute)."""
    ordered = sorted(specs, key=lambda s: (-s.length, s.index))
    for start in range(0, len(ordered), batch_size):
        yield ordered[start:start + batch_size]

def load_source_motion(path: str | Path, trained: TrainedModel) -> SourceMotion:
    """A ``.npy`` of un-normalised features (T, D) or joints (T, J, 3) on the checkpoint's skeleton, normalised."""
    path = Path(path)
    try:
        motion = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as err:
        raise SamplingError(f"{path}: cannot read the source motion as a .npy array ({err})") from err
    if not np.issubdtype(motion.dtype, np.floating):
        raise SamplingError(f"{path}: the source motion must be a float array, got {motion.dtype}")
    kind = "features" if motion.ndim == 2 else "joints"
    try:
        features = motion_to_features(motion, trained.skeleton, mean=trained.mean.cpu(), std=trained.std.cpu())
    except ValueError as err:
        raise SamplingError(f"{path}: {err}") from err
    if features.shape[0] < 1:
        raise SamplingError(f"{path}: the source motion has no frames")
    return SourceMotion(path, kind, features.to(trained.device))

def _parse_frames(text: str, num_frames: int) -> slice | list[int]:
    """``a:b`` (a slice, either end optional) or ``i,j,k`` frame indices."""
    try:
        if ":" in text:
            start, _, stop = text.partition(":")
            return slice(int(start) if start else None, int(stop) if stop else None)
        return [int(f) for f in text.split(",") if f]
    except ValueError:
        raise SamplingError(f"keep frames={text!r}: use START:STOP or comma-separated frame indices") from None

def _parse_joints(text: str) -> list[int | str]:
    return [int(j) if j.strip().isdigit() else j.strip() for j in text.split(",") if j.strip()]

def preset_options(request: SampleRequest) -> dict[str, Any]:
    """The keep options converted to the preset's types (as recorded in results.json)."""
    types = KEEP_OPTIONS[request.edit]
    options: dict[str, Any] = {}
    for key, value in request.keep.items():
        if types[key] is str:
            options[key] = str(value)
            continue
        try:
            options[key] = types[key](value)
        except ValueError:
            raise SamplingError(f"keep {key}={value!r}: expected a {types[key].__name__}") from None
    return options

def keep_mask(request: SampleRequest, options: Mapping[str, Any], lengths: torch.Tensor, num_frames: int,
              layout: FeatureLayout, source_frames: int) -> torch.Tensor:
    """(B, T, D) bool keep mask of the request's preset, restricted to frames the source motion has."""
    batch = lengths.shape[0]
    try:
        if request.edit == "joints":
            frames = _parse_frames(options.get("frames", ":"), num_frames)
            mask = joint_frame_mask(num_frames, layout, frames, _parse_joints(options["joints"]))
            mask = mask.expand(batch, -1, -1)
        else:
            mask = edit_mask(EDIT_PRESETS[request.edit], lengths.cpu(), num_frames, layout, **options)
    except (ValueError, IndexError) as err:
        raise SamplingError(f"edit {request.edit!r} with keep {dict(options)}: {err}") from err
    available = torch.arange(num_frames) < source_frames
    return (mask & available.view(1, -1, 1)).contiguous()

@dataclasses.dataclass
class BatchResult:
    specs: list[SampleSpec]
    features: torch.Tensor  # (B, T, D) normalised, CPU
    nfe: int
    keep: torch.Tensor | None  # (B, T, D) bool, edits only
    x1_hat: torch.Tensor | None  # (K, B, T, D), on request
    x1_hat_times: torch.Tensor | None

@dataclasses.dataclass
class PromptConditions:
    """The encoded prompts: conditions (P, E) or (P,) and the per-prompt model inputs some models also need
    (cross_attention: ``text_tokens``, ``text_token_len``)."""

    cond: torch.Tensor
    extras: dict[str, torch.Tensor]

    def select(self, prompts: torch.Tensor) -> PromptConditions:
        index = prompts.to(self.cond.device)
        return PromptConditions(self.cond[index], {name: value[index] for name, value in self.extras.items()})

def encode_prompts(request: SampleRequest, trained: TrainedModel) -> PromptConditions | None:
    """The request's texts or actions encoded for the model; None without prompts."""
    if not _prompt_count(request):
        return None
    try:
        cond, extras = trained.condition_inputs(texts=list(request.texts), actions=list(request.actions),
                                                text_weights=request.text_weights)
    except ValueError as err:
        raise SamplingError(str(err)) from err
    return PromptConditions(cond, extras)

def placeholder_conditions(trained: TrainedModel, batch: int) -> PromptConditions:
    """Conditions of the right shapes for unconditional sampling (guidance 0 drops them through cond_mask)."""
    config = trained.model_config
    device = trained.device
    if config.is_action_model:
        return PromptConditions(torch.zeros(batch, dtype=torch.long, device=device), {})
    extras = {}
    if config.conditioning == "cross_attention":
        extras = {"text_tokens": torch.zeros(batch, 1, config.text_token_dim, device=device),
                  "text_token_len": torch.ones(batch, dtype=torch.long, device=device)}
    return PromptConditions(torch.zeros(batch, config.cond_dim, device=device), extras)

def conditioned_model(trained: TrainedModel, conditions: PromptConditions, step_size: float | None = None
                      ) -> torch.nn.Module | BoundInputs:
    """The model with the conditions' extra per-sample inputs (and a shortcut model's step size) bound (the
    solvers' and samplers' call signature)."""
    return bind_inputs(trained.sampling_model, conditions.extras, step_size=step_size)  # in its weights' dtype


def _known_motion(trained: TrainedModel, source: SourceMotion, lengths: torch.Tensor, num_frames: int) -> torch.Tensor:
    """(B, T, D) the source motion cropped/zero-padded to every sample's length."""
    known = torch.zeros(lengths.shape[0], num_frames, trained.model_config.feature_dim, device=trained.device)
    frames = min(num_frames, source.features.shape[0])
    known[:, :frames] = source.features[:frames]
    return known * valid_frame_mask(lengths, num_frames).unsqueeze(-1)

@torch.no_grad()
def generate_batch(request: SampleRequest, trained: TrainedModel, integrator: Integrator, specs: list[SampleSpec],
                   conditions: PromptConditions | None, source: SourceMotion | None,
                   options: Mapping[str, Any],
                   noise_generators: Mapping[int, torch.Generator] | None = None) -> BatchResult:
    """Sample (or edit) one batch of motions, in a window of the batch's longest length (not the model's
    max_frames): :func:`batches` puts similar lengths together, and no pass computes frames no motion has.
    ``noise_generators``: sample index -> the generator its noise is drawn from (the Python API's ``generator=``);
    by default each sample's own, seeded with its ``seed``."""
    device = trained.device
    lengths = torch.tensor([s.length for s in specs], dtype=torch.long, device=device)
    num_frames = int(lengths.max())
    dim = trained.model_config.feature_dim
    if conditions is None:
        batch_conditions, scale = placeholder_conditions(trained, len(specs)), 0.0
    else:
        batch_conditions = conditions.select(torch.tensor([s.prompt for s in specs]))
        scale = request.guidance_for(trained)
    model = conditioned_model(trained, batch_conditions, integrator.step_size)
    cond = batch_conditions.cond
    known = keep = None
    if source is not None:
        known = _known_motion(trained, source, lengths, num_frames)
        keep = keep_mask(request, options, lengths, num_frames, FeatureLayout(trained.skeleton),
                         source.features.shape[0]).to(device)
    if integrator.objective == "diffusion":
        # Each sample's initial and per-step noise from its own seed: the same sample at any --batch-size.
        generator = _noise_generators(specs, noise_generators)
        if source is None:
            result: SolveResult = sample_diffusion(
                model, integrator.diffusion, cond, lengths, num_frames=num_frames, feature_dim=dim,
                sampler=integrator.name, guidance=scale, generator=generator,
                return_trajectory=request.plot_trajectory, clip_denoised=integrator.clip_denoised,
                precision=integrator.precision)
        else:
            denoise = classifier_free_guidance(model, cond, scale=scale, lengths=lengths, guided_channels=dim,
                                               precision=integrator.precision)
            result = replacement_edit(denoise, integrator.diffusion, known, keep, sampler=integrator.name,
                                      lengths=lengths, generator=generator, return_trajectory=request.plot_trajectory,
                                      clip_denoised=integrator.clip_denoised)
    elif source is None:
        result = sample(model, cond, lengths, num_frames=num_frames, feature_dim=dim, solver=integrator.name,
                        steps=integrator.steps, grid=integrator.grid,
                        guidance=scale,
                        conditional_channels=request.conditional_channels_for(trained),
                        generator=_noise_generators(specs, noise_generators),
                        return_trajectory=request.plot_trajectory, precision=integrator.precision)
    else:
        velocity = guided_velocity(model, cond, scale=scale, lengths=lengths,
                                   conditional_channels=request.conditional_channels_for(trained),
                                   precision=integrator.precision)
        x0 = draw_noise((len(specs), num_frames, dim), _noise_generators(specs, noise_generators), lengths=lengths,
                        device=device)
        result = edit(velocity, known, keep, steps=integrator.steps, rewrite_until=request.rewrite_time,
                      grid=integrator.grid,
                      solver=integrator.name, x0=x0, lengths=lengths, return_trajectory=request.plot_trajectory)
    # As the evaluator: smoothed, then a diffusion edit's source root copied (FLAME's use_reference_translation)
    x1 = trained.finish_output(result.x1.float(), lengths, request.smoothing_for(trained), known=known, keep=keep,
                               reference_translation=request.edit_reference_translation,
                               keep_bones=request.smoothing_keeps_bones_for(trained))
    return BatchResult(
        specs, x1.cpu(), result.nfe, None if keep is None else keep.cpu(),
        None if result.x1_hat is None else result.x1_hat.float().cpu(), result.x1_hat_times,
    )

def _noise_generators(specs: Sequence[SampleSpec],
                      given: Mapping[int, torch.Generator] | None) -> list[torch.Generator]:
    """One generator per sample of the batch: the given one, or a new one seeded with the sample's seed."""
    if given is not None:
        return [given[s.index] for s in specs]
    return seeded_generators([s.seed for s in specs])

def caption(request: SampleRequest, spec: SampleSpec) -> str:
    if spec.prompt is None:
        words = "unconditional"
    else:
        words = (request.texts or request.actions)[spec.prompt]
    return words if request.edit is None else f"{words} [{request.edit} edit]"

def _edit_record(request: SampleRequest, integrator: Integrator, source: SourceMotion, options: Mapping[str, Any],
                 keep: np.ndarray) -> dict[str, Any]:
    diffusion = integrator.objective == "diffusion"
    return {
        "preset": request.edit,
        "method": "replacement (FLAME)" if diffusion else "trajectory rewriting (MFM)",
        "source_motion": str(source.path),
        "source_kind": source.kind,
        "source_frames": int(source.features.shape[0]),
        "options": dict(options),
        "rewrite_until": None if diffusion else request.rewrite_time,
        # Diffusion edits: FLAME's copy of the source's root after the smoothing (edit_reference_translation).
        "reference_translation": request.edit_reference_translation if diffusion else None,
        # Flow edits: the named settings and what this edit overrode (steps, guidance and ς given explicitly).
        "settings": None if diffusion else {
            **request.settings.record(),
            "overridden": [name for name, value in (("steps", request.steps), ("guidance", request.guidance),
                                                   ("rewrite_until", request.rewrite_until)) if value is not None]},
        "kept_frame_ranges": frame_ranges(keep.any(axis=1)),
        "kept_dim_ranges": frame_ranges(keep.any(axis=0)),
        "kept_fraction": round(float(keep.mean()), 6),
    }

def sample_record(request: SampleRequest, trained: TrainedModel, integrator: Integrator, spec: SampleSpec,
                  chunk: Sequence[SampleSpec], nfe: int) -> dict[str, Any]:
    """What results.json says about one sample besides its files."""
    return {
        "index": spec.index,
        "text": request.texts[spec.prompt] if request.texts and spec.prompt is not None else None,
        "action": request.actions[spec.prompt] if request.actions and spec.prompt is not None else None,
        "length": spec.length,
        "seconds": round(spec.length / trained.fps, 6),
        # Diffusion samplers seed one generator per batch (module docstring).
        "noise_seed": chunk[0].seed if integrator.objective == "diffusion" else spec.seed,
        "nfe": nfe,
    }

def generated_batches(request: SampleRequest, trained: TrainedModel, integrator: Integrator,
                      specs: Sequence[SampleSpec], conditions: PromptConditions | None, source: SourceMotion | None,
                      options: Mapping[str, Any], noise_generators: Mapping[int, torch.Generator] | None = None,
                      ) -> Iterator[tuple[list[SampleSpec], BatchResult, np.ndarray, float]]:
    """Generate ``specs`` batch by batch: ``(specs of the batch, its BatchResult, its un-normalised features
    (B, T, D) as numpy, generation seconds)``. Shared by the command line (which writes each batch as it comes) and
    the Python API (:class:`pipeline.generation.pretrained.MotionPipeline`)."""
    for chunk in batches(specs, request.batch_size):
        synchronize(trained.device)
        tick = time.perf_counter()
        batch = generate_batch(request, trained, integrator, chunk, conditions, source, options, noise_generators)
        synchronize(trained.device)
        seconds = time.perf_counter() - tick
        features = trained.denormalize(batch.features.to(trained.device)).cpu().numpy()
        yield chunk, batch, features, seconds

def run_sampling(request: SampleRequest) -> dict[str, Any]:
    """Generate every sample of ``request``, write the files and ``results.json``; returns the results dict.
    Composition requests go to :func:`pipeline.generation.composing.run_composition`."""
    if request.composes:
        raise SamplingError("a composition request is run by pipeline.generation.composing.run_composition")
    out_dir = Path(request.out_dir)
    trained = load_for_request(request).compiled_with(request.compile)  # compiled once, used by every batch
    integrator = resolve_integrator(request, trained)
    source = None if request.source_motion is None else load_source_motion(request.source_motion, trained)
    options = preset_options(request) if request.edit else {}
    conditions = encode_prompts(request, trained)
    specs = plan_samples(request, trained, source)
    prepare_out_dir(out_dir, request.overwrite)
    writer = SampleWriter(request, trained, out_dir)
    disable = None if request.progress is None else not request.progress

    started = time.perf_counter()
    generation_s = 0.0
    samples: dict[int, dict[str, Any]] = {}
    nfe_per_batch: list[int] = []
    with tqdm(total=len(specs), desc="sampling", unit="motion", disable=disable) as bar:
        for chunk, batch, features, seconds in generated_batches(request, trained, integrator, specs, conditions,
                                                                 source, options):
            generation_s += seconds
            nfe_per_batch.append(batch.nfe)
            for row, spec in enumerate(chunk):
                keep = None if batch.keep is None else batch.keep[row, :spec.length].numpy()
                x1_hat = None if batch.x1_hat is None else batch.x1_hat[:, row, :spec.length].numpy()
                times = None if batch.x1_hat_times is None else batch.x1_hat_times.numpy()
                sample_features = np.ascontiguousarray(features[row, :spec.length], dtype=np.float32)
                written = writer.write(spec.index, sample_features, caption(request, spec), keep, x1_hat, times)
                samples[spec.index] = {
                    **sample_record(request, trained, integrator, spec, chunk, batch.nfe),
                    **written,
                    **({"edit": _edit_record(request, integrator, source, options, keep)} if keep is not None else {}),
                }
            bar.update(len(chunk))
    total_s = time.perf_counter() - started

    results = {
        **results_header(request, trained, integrator, "edit" if request.edit else "sample", conditions is not None),
        "nfe_per_batch": nfe_per_batch,
        "batch_size": request.batch_size,
        "timing": {
            "generation_s": round(generation_s, 6),
            "ms_per_motion": round(1000.0 * generation_s / len(specs), 3),
            "total_s": round(total_s, 6),
        },
        "samples": [samples[i] for i in sorted(samples)],
    }
    if request.mdm_results:
        results["mdm_results"] = write_mdm_layout(out_dir, results["samples"], request.num_samples)
    write_json_atomically(out_dir / RESULTS_FILE, results)
    logger.info("wrote %d sample(s) to %s (%.1f ms per motion)", len(specs), out_dir,
                results["timing"]["ms_per_motion"])
    write_index_page(out_dir)
    return results
