"""FlowMDM composition and extrapolation from a trained flow checkpoint: the engine behind
``launch/sample.py --compose`` / ``--extrapolate``.

A :class:`pipeline.generation.sampling.SampleRequest` with ``compose_file`` (FlowMDM's ``{"text": [...], "lengths": [...]}``)
or ``extrapolate`` (one text, or action, repeated over segments) is generated as ONE sequence of Σ lengths frames
per sample by :func:`mfm.composition.compose` / :func:`mfm.composition.extrapolate`, and written as::

    results.json                 the segments (text, length, start/end frame), boundaries, switch, nfe, files, and
                                 the plausibility figures of each whole sequence (transitions included)
    sample_000/features.npy      (Σ L, D) float32 features of the whole sequence, un-normalised
    sample_000/joints.npy        (Σ L, J, 3) float32 joint positions
    sample_000/motion.mp4|.gif   one video of the whole sequence; the caption changes at every segment start
    sample_000/motion.bvh        BVH of the whole sequence (as pipeline/generation/sampling.py)
    sample_000/trajectory.png    on request: x̂1 estimates along the ODE trajectory

``num_samples`` > 1 gives sample_001, ... (noise seeds as pipeline/generation/sampling.py). Lengths are NOT capped at the
training window: making sequences longer than any training sample is the point of composition.

What a model can do:

* several distinct texts need per-frame conditions: ``model.conditioning=pccat`` (with ``model.positional=bpe``,
  FlowMDM's blended positional encodings, for smooth transitions); other models fail with a message saying so;
* one repeated text (extrapolation, also chosen when every text of the file is the same) works with any flow model.
  A ``'bpe'`` model runs absolute mode (positions restart per segment, attention inside it) for flow times before
  ``switch`` and relative mode after; an ``'absolute'`` model samples the whole sequence as one long motion with
  ordinary positions (it must fit its positional table, ``max_len``);
* bpe models compute attention blockwise (``attention_chunk``, default the model's attention horizon once the
  sequence is longer than it), so memory grows linearly with the length; the result is the same as dense attention;
* diffusion checkpoints do not compose here (mfm.composition integrates the flow ODE).

Integration: a fixed-step solver with at most ``mfm.composition.DEFAULT_MAX_NFE`` (50) evaluations; a guided
evaluation is one batched pass and counts once.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from mfm.composition import (
    HUMANML3D_SWITCH,
    SWITCH_TOLERANCE,
    Composition,
    check_composition_budget,
    compose,
    extrapolate,
    read_prompt_file,
    resolve_switch,
    segment_boundaries,
)
from mfm.model import ModelConfig
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
    prepare_out_dir,
    results_header,
    write_json_atomically,
)
from pipeline.generation.request import SampleRequest, SamplingError

logger = logging.getLogger(__name__)

NEEDED_CONFIG = "model.positional=bpe model.conditioning=pccat"


def composition_segments(request: SampleRequest, fps: float) -> list[tuple[str, int]]:
    """[(text or action name, frames), ...] of the request: its prompt file, or its one prompt over the lengths."""
    if request.compose_file is not None:
        try:
            return read_prompt_file(request.compose_file)
        except ValueError as err:
            raise SamplingError(str(err)) from err
    prompt = (list(request.texts) or list(request.actions))[0]
    values = list(request.lengths) or [s * fps for s in request.seconds]
    frames = [int(round(v)) for v in values] * (request.num_segments or 1)
    if min(frames) < 1:
        raise SamplingError(f"segment lengths must be at least one frame, got {frames}")
    return [(prompt, length) for length in frames]


def distinct_prompts(segments: Sequence[tuple[str, int]]) -> list[str]:
    """The segments' prompts, each once, in order of first appearance."""
    return list(dict.fromkeys(text for text, _ in segments))


def check_model_can_compose(trained: TrainedModel, segments: Sequence[tuple[str, int]], where: str) -> None:
    """A clear SamplingError when ``trained`` cannot generate ``segments`` as one sequence."""
    config = trained.model_config
    if trained.objective != "flow":
        raise SamplingError(f"{trained.checkpoint} is a diffusion model (train.objective=diffusion): composition "
                            "integrates a flow-matching velocity field (mfm.composition); train with "
                            f"train.objective=flow {NEEDED_CONFIG}")
    texts = distinct_prompts(segments)
    if len(texts) > 1 and config.conditioning != "pccat":
        raise SamplingError(
            f"{where} asks for {len(texts)} different texts, but {trained.checkpoint} takes one condition per "
            f"sequence (model.positional={config.positional}, model.conditioning={config.conditioning}): composing "
            f"different texts needs a model trained with {NEEDED_CONFIG} (FlowMDM). This model can extrapolate one "
            "repeated text (--extrapolate).")
    total = sum(length for _, length in segments)
    if config.positional == "absolute" and total + config.num_prefix_tokens > config.max_len:
        raise SamplingError(
            f"{where}: {total} frames in all do not fit the positional table of {trained.checkpoint} "
            f"(model.positional=absolute, max_len={config.max_len}); shorten the sequence or use a model trained "
            f"with model.positional=bpe (positions restart at every segment)")
    longest = max(length for _, length in segments)
    if longest > trained.window:
        logger.warning("%s: segments up to %d frames, longer than the %d-frame training window of %s", where, longest,
                       trained.window, trained.checkpoint)
    if config.positional == "absolute":
        logger.warning("%s is not a bpe model: the %d-frame sequence is sampled as one motion with absolute positions",
                       trained.checkpoint, total)


def check_integration(request: SampleRequest, integrator: Integrator) -> None:
    """The solver, evaluation budget and switch compose() will accept, checked before any output is written."""
    try:
        check_composition_budget(integrator.name, integrator.steps)
    except ValueError as err:
        raise SamplingError(str(err)) from err
    try:
        resolve_switch(HUMANML3D_SWITCH if request.switch is None else request.switch, integrator.steps)
    except ValueError as err:
        raise SamplingError(str(err)) from err


def attention_chunk_for(request: SampleRequest, config: ModelConfig, total_frames: int) -> int | None:
    """Block size of the frames' attention: bpe models only; 0 = dense; default the attention horizon once the
    sequence is longer than it (dense attention's memory grows with the square of the length)."""
    if config.positional != "bpe":
        if request.attention_chunk:
            raise SamplingError(f"attention_chunk needs a model with model.positional=bpe, this one is "
                                f"{config.positional!r}")
        return None
    if request.attention_chunk is None:
        return config.attention_horizon if total_frames > config.attention_horizon else None
    return request.attention_chunk or None


def switch_record(request: SampleRequest, config: ModelConfig, composition: Composition) -> dict[str, Any]:
    """results.json's description of the positional schedule (bpe models: when relative mode starts)."""
    if config.positional != "bpe":
        return {"applies": False, "reason": "model.positional=absolute: one motion with absolute positions"}
    requested = HUMANML3D_SWITCH if request.switch is None else request.switch
    starts = composition.result.grid[:-1].tolist()  # each solver step's start time
    absolute_steps = sum(t < composition.switch_time - SWITCH_TOLERANCE for t in starts)
    return {
        "applies": True,
        "requested": requested,
        "requested_as": "absolute solver steps" if isinstance(requested, int) else "flow time",
        # The flow time from which evaluations run in relative mode (1.0: never, the whole ODE in absolute mode).
        "flow_time": 1.0 if math.isinf(composition.switch_time) else round(float(composition.switch_time), 6),
        "absolute_steps": int(absolute_steps),
        "relative_steps": len(starts) - int(absolute_steps),
    }


def segment_records(segments: Sequence[tuple[str, int]], fps: float, action_model: bool) -> list[dict[str, Any]]:
    key = "action" if action_model else "text"
    return [{"index": i, key: text, "length": length, "seconds": round(length / fps, 6), "start": start, "end": end}
            for i, ((text, length), (start, end)) in enumerate(zip(segments, segment_boundaries(
                [length for _, length in segments])))]


@dataclass
class EncodedSegments:
    """The segments' prompts encoded once: one condition per distinct prompt and, for a cross_attention model, the
    token features of its one text."""

    prompts: list[str]
    cond: torch.Tensor  # (P, E) pooled text embeddings or (P,) action ids
    tokens: dict[str, Any]  # compose()'s text_tokens (L, E) / text_token_len, or empty

    def condition(self, prompt: str) -> torch.Tensor:
        return self.cond[self.prompts.index(prompt)]


def encode_segments(request: SampleRequest, trained: TrainedModel,
                    segments: Sequence[tuple[str, int]]) -> EncodedSegments:
    prompts = distinct_prompts(segments)
    action_model = trained.model_config.is_action_model
    try:
        cond, extras = trained.condition_inputs(texts=[] if action_model else prompts,
                                                actions=prompts if action_model else [],
                                                text_weights=request.text_weights)
    except ValueError as err:
        raise SamplingError(str(err)) from err
    tokens: dict[str, Any] = {}
    if extras:  # cross_attention: one text (check_model_can_compose), its token features for the whole sequence
        tokens = {"text_tokens": extras["text_tokens"][0], "text_token_len": int(extras["text_token_len"][0])}
    return EncodedSegments(prompts, cond, tokens)


@torch.no_grad()
def generate_composition(request: SampleRequest, trained: TrainedModel, integrator: Integrator,
                         segments: Sequence[tuple[str, int]], encoded: EncodedSegments, attention_chunk: int | None,
                         seed: int) -> Composition:
    """One sequence of ``segments`` from the noise of ``seed``: extrapolation when they share one prompt."""
    settings = dict(solver=integrator.name, steps=integrator.steps, guidance=request.guidance_for(trained),
                    switch=HUMANML3D_SWITCH if request.switch is None else request.switch, seed=seed,
                    attention_chunk=attention_chunk, return_trajectory=request.plot_trajectory,
                    conditional_channels=request.conditional_channels_for(trained), precision=integrator.precision,
                    step_size=integrator.step_size, **encoded.tokens)
    lengths = [length for _, length in segments]
    try:
        if len(encoded.prompts) == 1:
            return extrapolate(trained.model, encoded.cond[0], lengths, **settings)
        return compose(trained.model, [(encoded.condition(text), length) for text, length in segments], **settings)
    except ValueError as err:
        raise SamplingError(f"cannot compose with {trained.checkpoint}: {err}") from err


def run_composition(request: SampleRequest) -> dict[str, Any]:
    """Generate ``request.num_samples`` composed sequences, write their files and ``results.json``."""
    if not request.composes:
        raise SamplingError("not a composition request: give compose_file or extrapolate")
    out_dir = Path(request.out_dir)
    trained = load_for_request(request)
    segments = composition_segments(request, trained.fps)
    where = str(request.compose_file) if request.compose_file is not None else "the extrapolation"
    distinct = distinct_prompts(segments)
    if request.extrapolate and len(distinct) > 1:
        raise SamplingError(f"{where}: extrapolation repeats one text, but the file holds {len(distinct)} different "
                            "ones; compose them without extrapolate")
    extrapolating = len(distinct) == 1
    check_model_can_compose(trained, segments, where)
    integrator = resolve_integrator(request, trained)
    check_integration(request, integrator)
    encoded = encode_segments(request, trained, segments)
    config = trained.model_config
    total = sum(length for _, length in segments)
    chunk = attention_chunk_for(request, config, total)
    prepare_out_dir(out_dir, request.overwrite)
    writer = SampleWriter(request, trained, out_dir)
    boundaries = segment_boundaries([length for _, length in segments])
    title = [(start, text) for (text, _), (start, _) in zip(segments, boundaries)]
    disable = None if request.progress is None else not request.progress

    started = time.perf_counter()
    generation_s = 0.0
    samples: list[dict[str, Any]] = []
    composition = None
    for index in tqdm(range(request.num_samples), desc="composing", unit="sequence", disable=disable):
        seed = sample_seed(request.seed, index)
        synchronize(trained.device)
        tick = time.perf_counter()
        composition = generate_composition(request, trained, integrator, segments, encoded, chunk, seed)
        synchronize(trained.device)
        generation_s += time.perf_counter() - tick
        features = trained.denormalize(composition.motion).float().cpu().numpy()
        x1_hat = None if composition.result.x1_hat is None else composition.result.x1_hat[:, 0].float().cpu().numpy()
        times = None if composition.result.x1_hat_times is None else composition.result.x1_hat_times.numpy()
        written = writer.write(index, np.ascontiguousarray(features, dtype=np.float32), title, None, x1_hat, times)
        samples.append({"index": index, "length": total, "seconds": round(total / trained.fps, 6),
                        "noise_seed": seed, "nfe": composition.nfe, **written})
    total_s = time.perf_counter() - started

    results = {
        **results_header(request, trained, integrator, "extrapolate" if extrapolating else "compose", True),
        "prompt_file": None if request.compose_file is None else str(request.compose_file),
        "positional": config.positional,
        "model_conditioning": config.conditioning,
        "switch": switch_record(request, config, composition),
        "attention_chunk": chunk,
        "nfe": composition.nfe,
        "total_frames": total,
        "segments": segment_records(segments, trained.fps, config.is_action_model),
        "boundaries": [list(b) for b in boundaries],
        "timing": {
            "generation_s": round(generation_s, 6),
            "ms_per_sequence": round(1000.0 * generation_s / request.num_samples, 3),
            "total_s": round(total_s, 6),
        },
        "samples": samples,
    }
    write_json_atomically(out_dir / RESULTS_FILE, results)
    logger.info("wrote %d composed sequence(s) of %d frames (%d segments) to %s", request.num_samples, total,
                len(segments), out_dir)
    write_index_page(out_dir)
    return results
