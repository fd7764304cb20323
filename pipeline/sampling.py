"""Sample (or edit) motions from a trained checkpoint and write files people can use: the engine behind
``launch/sample.py``.

A :class:`SampleRequest` says what to generate; :func:`run_sampling` loads the checkpoint, generates every sample
in batches of ``batch_size`` and writes, into ``out_dir``::

    index.html                   the motions to browse: animated stick figures, captions, lengths, plausibility
                                 (pipeline/browse.py; self-contained, opens from disk)
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
part is re-noised onto the chain before every step; ``rewrite_until`` does not apply) with the same mask presets.

Composition (FlowMDM, one long sequence from several (text, length) segments) lives in pipeline/composing.py; it
shares this module's request, outputs and checkpoint loading.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import re
import shutil
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from mfm import metrics
from mfm.composition import BoundInputs
from mfm.diffusion import GaussianDiffusion
from mfm.diffusion_sampling import SAMPLERS, replacement_edit, sample_diffusion, smooth_over_time
from mfm.editing import (
    DEFAULT_EDIT_SETTINGS,
    EDIT_SETTINGS,
    EditSettings,
    edit,
    edit_mask,
    joint_frame_mask,
    motion_to_features,
)
from mfm.export import plot_x1_trajectory, render_motion, write_bvh, write_mdm_results
from mfm.export.bvh import JOINT_CHANNELS, ROOT_CHANNELS
from mfm.export.render import Captions
from mfm.features import features_to_joints, rigid_joints
from mfm.guidance import classifier_free_guidance
from mfm.layout import FeatureLayout
from mfm.model import valid_frame_mask
from mfm.skeleton import Skeleton
from mfm.solvers import (
    FIXED_STEP_SOLVERS,
    SolveResult,
    draw_noise,
    guided_velocity,
    sample_lengths,
    seeded_generators,
    solve,
    zero_padded_frames,
)
from pipeline.inference import TrainedModel, load_trained_model

logger = logging.getLogger(__name__)

RESULTS_FILE = "results.json"
BROWSE_PAGE = "index.html"  # pipeline/browse.py's page of the outputs, written last
RESULTS_VERSION = 1
SAMPLE_DIR = "sample_{:03d}"
TIME_CONVENTIONS = {"flow": "flow time t, 1 = data", "diffusion": "diffusion t_model = step / train steps, 0 = data"}
_SAMPLE_DIR_PATTERN = re.compile(r"^sample_\d{3,}$")

# Command-line preset name -> mfm.editing preset (None: the custom joints/frames mask built here).
EDIT_PRESETS: dict[str, str | None] = {
    "prediction": "prediction",
    "inbetween": "inbetween",
    "interpolate": "interpolation",
    "upper-body": "upper_body",
    "joints": None,
}
# ``--keep KEY=VALUE`` options each preset accepts, with their parsers.
KEEP_OPTIONS: dict[str, dict[str, type]] = {
    "prediction": {"prefix": float},
    "inbetween": {"prefix": float, "suffix": float},
    "interpolate": {"every": int},
    "upper-body": {},
    "joints": {"joints": str, "frames": str},
}


class SamplingError(ValueError):
    """A request that cannot be served (bad option combination, unknown name, unreadable source motion)."""


def known_solvers() -> list[str]:
    """Fixed-step solvers of mfm.solvers, then the torchdiffeq methods it hands on (e.g. dopri5)."""
    # torchdiffeq has no public list of its methods; mfm.solvers reads the same table.
    from torchdiffeq._impl.odeint import SOLVERS

    return sorted(FIXED_STEP_SOLVERS) + sorted(set(SOLVERS) - set(FIXED_STEP_SOLVERS))


DEFAULT_FLOW_SOLVER = "euler"
MDM_RESULTS_FILES = ("results.npy", "results.txt", "results_len.txt")
DEFAULT_FLOW_STEPS = 10
DEFAULT_GUIDANCE = 2.5  # MFM's sampling scale (its generate.py and evaluation)
DEFAULT_DIFFUSION_SAMPLER = "ddpm"  # FLAME's and FlowMDM's sampler; its default steps are the training steps
# How joints.npy (and the video) are decoded from the features, as results.json describes them.
JOINT_DECODES = {
    "ric": "features_to_joints (recover_from_ric)",
    "rigid": "features_to_joints_rigid (recover_from_ric fitted onto the skeleton's fixed bone lengths)",
}


def _positive_int(name: str, value: Any) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or value < 1:
        raise SamplingError(f"{name} must be a positive int, got {value!r}")


@dataclasses.dataclass
class SampleRequest:
    """Everything one sampling run needs; see the module docstring for the outputs."""

    checkpoint: str | Path  # a step-XXXXXXXX folder, or a run/checkpoints folder (newest complete checkpoint)
    out_dir: str | Path
    texts: Sequence[str] = ()
    actions: Sequence[str] = ()  # class names, for action models
    lengths: Sequence[int] = ()  # frames: one for all prompts or one per prompt; empty: see module docstring
    seconds: Sequence[float] = ()  # alternative to lengths (converted with the dataset's fps)
    num_samples: int = 1  # per prompt (without prompts: in total, unconditional); composition: sequences
    steps: int | None = None  # None: 10 for flow models, every training step (1000) for diffusion models
    solver: str | None = None  # None: "euler" (flow) or "ddpm" (diffusion); see the module docstring
    guidance: float | None = None  # None: DEFAULT_GUIDANCE, or the edit settings' scale for a flow edit
    seed: int = 0
    batch_size: int = 64
    weights: str = "ema"  # "ema" (falls back to the raw weights when the run kept none) or "model"
    device: str = "auto"  # "auto": cuda when available
    text_weights: str | None = None  # CLIP datasets: the text encoder weights file (checked by hash)
    edit: str | None = None  # a key of EDIT_PRESETS
    source_motion: str | Path | None = None
    keep: Mapping[str, str] = dataclasses.field(default_factory=dict)  # preset options (KEEP_OPTIONS)
    rewrite_until: float | None = None  # ς; None: the edit settings' value for the preset
    edit_settings: str = DEFAULT_EDIT_SETTINGS  # flow edits: steps, ς and guidance (mfm.editing.EDIT_SETTINGS)
    smoothing: float | None = None  # output smoothing σ in frames; None: the diffusion baseline's (FLAME: 1), else 0
    mdm_results: bool = False  # also write MDM's results.npy (+ results.txt, results_len.txt) for MDM's scripts
    video: bool = True
    video_format: str = "auto"  # "auto" (MP4 if ffmpeg is on PATH, else GIF), "mp4" or "gif"
    bvh: bool = True
    plot_trajectory: bool = False
    decode: str = "ric"  # joints.npy and the video: a key of JOINT_DECODES (the BVH is always rigid)
    overwrite: bool = False  # replace the outputs of an earlier run in out_dir
    progress: bool | None = None  # None: progress bars when stderr is a terminal
    # Composition (pipeline/composing.py): one sequence made of (text, frames) segments.
    compose_file: str | Path | None = None  # FlowMDM prompt file {"text": [...], "lengths": [...]}
    extrapolate: bool = False  # one text (or action) over every segment; also chosen when the file's texts agree
    num_segments: int | None = None  # extrapolation without a file: the one length repeated this many times
    switch: float | int | None = None  # bpe models: flow time or leading absolute steps; None: HUMANML3D_SWITCH
    attention_chunk: int | None = None  # bpe models: attention block size; None: auto; 0: dense attention

    def __post_init__(self) -> None:
        if self.texts and self.actions:
            raise SamplingError("give texts or actions, not both")
        if self.lengths and self.seconds:
            raise SamplingError("give lengths (frames) or seconds, not both")
        for name in ("num_samples", "batch_size"):
            _positive_int(name, getattr(self, name))
        if self.steps is not None:
            _positive_int("steps", self.steps)
        if self.smoothing is not None and not self.smoothing >= 0:
            raise SamplingError(f"smoothing must be a σ >= 0 (frames; 0: none), got {self.smoothing}")
        if self.weights not in ("ema", "model"):
            raise SamplingError(f"weights must be 'ema' or 'model', got {self.weights!r}")
        if self.solver is not None and self.solver not in known_solvers() + list(SAMPLERS):
            raise SamplingError(f"unknown solver {self.solver!r}; known: {known_solvers()} for flow models, "
                                f"{list(SAMPLERS)} for diffusion models")
        if self.video_format not in ("auto", "mp4", "gif"):
            raise SamplingError(f"video_format must be 'auto', 'mp4' or 'gif', got {self.video_format!r}")
        if self.decode not in JOINT_DECODES:
            raise SamplingError(f"decode must be one of {sorted(JOINT_DECODES)}, got {self.decode!r}")
        if self.composes:
            self._check_composition()
        elif self.num_segments is not None or self.switch is not None or self.attention_chunk is not None:
            raise SamplingError("num_segments, switch and attention_chunk only apply to a composition "
                                "(compose_file / extrapolate)")
        if self.edit is None:
            if self.source_motion is not None or self.keep or self.rewrite_until is not None:
                raise SamplingError("source motion, keep options and rewrite_until only apply to an edit")
            return
        if self.edit not in EDIT_PRESETS:
            raise SamplingError(f"unknown edit {self.edit!r}; known: {sorted(EDIT_PRESETS)}")
        if self.source_motion is None:
            raise SamplingError(f"edit {self.edit!r} needs a source motion (.npy features (T, D) or joints (T, J, 3))")
        if self.solver is not None and self.solver not in FIXED_STEP_SOLVERS and self.solver not in SAMPLERS:
            raise SamplingError(f"editing rewrites the trajectory between fixed steps: use a solver in "
                                f"{sorted(FIXED_STEP_SOLVERS)} (flow) or {list(SAMPLERS)} (diffusion), "
                                f"not {self.solver!r}")
        unknown = sorted(set(self.keep) - set(KEEP_OPTIONS[self.edit]))
        if unknown:
            raise SamplingError(f"edit {self.edit!r} takes keep options {sorted(KEEP_OPTIONS[self.edit]) or 'none'}, "
                                f"got {unknown}")
        if self.edit == "joints" and "joints" not in self.keep:
            raise SamplingError("edit 'joints' needs keep joints=NAME,NAME,... (the joints taken from the source)")
        if self.rewrite_until is not None and not 0.0 <= self.rewrite_until <= 1.0:
            raise SamplingError(f"rewrite_until must be in [0, 1], got {self.rewrite_until}")
        if self.edit_settings not in EDIT_SETTINGS:
            raise SamplingError(f"unknown edit settings {self.edit_settings!r}; known: {', '.join(EDIT_SETTINGS)}")

    @property
    def composes(self) -> bool:
        """A composition request (pipeline/composing.py) rather than independent samples or edits."""
        return self.compose_file is not None or self.extrapolate

    def _check_composition(self) -> None:
        if self.edit is not None:
            raise SamplingError("a composition cannot also be an edit")
        if self.compose_file is not None:
            if self.texts or self.actions or self.lengths or self.seconds or self.num_segments is not None:
                raise SamplingError(f"{self.compose_file}: the composition's texts and lengths come from the file; "
                                    "do not also give texts, actions, lengths, seconds or num_segments")
        else:
            if len(self.texts) + len(self.actions) != 1:
                raise SamplingError("extrapolation without a prompt file repeats one text (or action): give exactly "
                                    "one")
            if not (self.lengths or self.seconds):
                raise SamplingError("extrapolation without a prompt file needs the segment lengths (one per segment, "
                                    "or one with num_segments)")
            if self.num_segments is not None:
                _positive_int("num_segments", self.num_segments)
                if len(self.lengths) + len(self.seconds) != 1:
                    raise SamplingError("num_segments repeats one length: give exactly one length (or seconds)")
        if self.switch is not None:
            if isinstance(self.switch, bool) or not isinstance(self.switch, (int, float)):
                raise SamplingError(f"switch must be a flow time (float) or a step count (int), got {self.switch!r}")
        if self.attention_chunk is not None and (isinstance(self.attention_chunk, bool)
                                                 or not isinstance(self.attention_chunk, int)
                                                 or self.attention_chunk < 0):
            raise SamplingError(f"attention_chunk must be an int >= 0 (0: dense attention), got "
                                f"{self.attention_chunk!r}")

    @property
    def settings(self) -> EditSettings:
        """The flow edit's settings (``edit_settings``); explicit steps, guidance and ς override them."""
        return EDIT_SETTINGS[self.edit_settings]

    @property
    def rewrite_time(self) -> float:
        if self.rewrite_until is not None:
            return float(self.rewrite_until)
        return self.settings.rewrite_time(EDIT_PRESETS[self.edit] or "joints")

    def guidance_for(self, trained: TrainedModel) -> float:
        """The guidance scale: as given, else the edit settings' for a flow edit, else the diffusion baseline's own
        (FLAME: 8.0, mfm.diffusion_sampling.BASELINE_SAMPLING), else DEFAULT_GUIDANCE."""
        if self.guidance is not None:
            return float(self.guidance)
        if self.edit is not None and trained.objective == "flow":
            return self.settings.guidance
        baseline = trained.baseline_sampling
        return baseline.guidance if baseline is not None else DEFAULT_GUIDANCE

    def smoothing_for(self, trained: TrainedModel) -> float:
        """σ (frames) of the output's Gaussian smoothing over time: as given, else the diffusion baseline's own
        (FLAME: 1.0), else 0 (none)."""
        if self.smoothing is not None:
            return float(self.smoothing)
        baseline = trained.baseline_sampling
        return baseline.smoothing_sigma if baseline is not None else 0.0


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


# ---------------------------------------------------------------------------------------------------------------
# planning


def read_prompts(path: str | Path) -> list[str]:
    """One prompt per line; blank lines and lines starting with ``#`` are skipped."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise SamplingError(f"{path}: cannot read the prompts file ({err})") from err
    prompts = [line.strip() for line in lines if line.strip() and not line.lstrip().startswith("#")]
    if not prompts:
        raise SamplingError(f"{path}: the prompts file holds no prompt")
    return prompts


def max_sample_length(trained: TrainedModel) -> int:
    """Longest motion to ask for: the window the model was trained on (196 frames for HumanML3D, as MDM/MFM)."""
    return min(int(trained.window), int(trained.model_config.max_frames))


def sample_seed(seed: int, index: int) -> int:
    """The noise seed of sample ``index``: independent streams per (seed, index), unlike ``seed + index``."""
    return int(np.random.SeedSequence([seed, index]).generate_state(1)[0])


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


# ---------------------------------------------------------------------------------------------------------------
# editing inputs


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


# ---------------------------------------------------------------------------------------------------------------
# the checkpoint and how to integrate it


@dataclasses.dataclass(frozen=True)
class Integrator:
    """How a request integrates its checkpoint: an ODE solver (flow) or a diffusion sampler, with its steps."""

    objective: str  # "flow" or "diffusion"
    name: str  # the solver (flow) or sampler (diffusion: "ddpm" / "ddim")
    steps: int
    diffusion: GaussianDiffusion | None = None  # diffusion: the training process respaced to ``steps``

    def record(self, trained: TrainedModel) -> dict[str, Any]:
        """results.json's description of the objective and sampler."""
        info: dict[str, Any] = {"objective": self.objective, "sampler": self.name, "solver": self.name,
                                "steps": self.steps}
        if self.diffusion is not None:
            process = trained.diffusion
            info["diffusion"] = {"preset": trained.diffusion_preset, "train_steps": process.num_train_steps,
                                 "schedule": process.schedule, "prediction": process.prediction,
                                 "learn_sigma": process.learn_sigma,
                                 "model_steps": self.diffusion.timestep_map.tolist()}  # the training steps visited
            if self.name == "ddim":
                info["diffusion"]["eta"] = 0.0
        return info


def load_for_request(request: SampleRequest) -> TrainedModel:
    """The request's checkpoint on its device (a checkpoint that cannot be loaded is a SamplingError)."""
    try:
        return load_trained_model(request.checkpoint, use_ema=request.weights == "ema",
                                  device=resolve_device(request.device))
    except ValueError as err:
        raise SamplingError(str(err)) from err


def resolve_integrator(request: SampleRequest, trained: TrainedModel) -> Integrator:
    """The solver or sampler and steps for ``trained``'s objective; a mismatch is a clear SamplingError."""
    if trained.objective == "flow":
        solver = request.solver or DEFAULT_FLOW_SOLVER
        if solver in SAMPLERS:
            raise SamplingError(f"{trained.checkpoint} is a flow-matching model (train.objective=flow): {solver!r} is "
                                f"a diffusion sampler; use an ODE solver ({', '.join(known_solvers())})")
        default_steps = request.settings.steps if request.edit is not None else DEFAULT_FLOW_STEPS
        return Integrator("flow", solver, request.steps or default_steps)
    sampler = request.solver or DEFAULT_DIFFUSION_SAMPLER
    if sampler not in SAMPLERS:
        raise SamplingError(f"{trained.checkpoint} is a diffusion model (train.objective=diffusion, preset "
                            f"{trained.diffusion_preset!r}): sample it with solver 'ddpm' or 'ddim' (steps respaced "
                            f"from its {trained.diffusion.num_train_steps} training steps), not the ODE solver "
                            f"{sampler!r}")
    if request.edit is not None and request.rewrite_until is not None:
        raise SamplingError("rewrite_until is a flow-matching edit option: FLAME's replacement editing of a diffusion "
                            "model re-noises the kept part before every step")
    steps = request.steps or trained.diffusion.num_train_steps
    try:
        schedule = trained.diffusion.respaced(steps)
    except ValueError as err:
        raise SamplingError(f"cannot sample {trained.checkpoint} with {steps} steps of its "
                            f"{trained.diffusion.num_train_steps}: {err}") from err
    return Integrator("diffusion", sampler, steps, schedule)


# ---------------------------------------------------------------------------------------------------------------
# generation


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


def conditioned_model(trained: TrainedModel, conditions: PromptConditions) -> torch.nn.Module | BoundInputs:
    """The model with the conditions' extra per-sample inputs bound (the solvers' and samplers' call signature)."""
    return BoundInputs(trained.model, conditions.extras) if conditions.extras else trained.model


def _known_motion(trained: TrainedModel, source: SourceMotion, lengths: torch.Tensor, num_frames: int) -> torch.Tensor:
    """(B, T, D) the source motion cropped/zero-padded to every sample's length."""
    known = torch.zeros(lengths.shape[0], num_frames, trained.model_config.feature_dim, device=trained.device)
    frames = min(num_frames, source.features.shape[0])
    known[:, :frames] = source.features[:frames]
    return known * valid_frame_mask(lengths, num_frames).unsqueeze(-1)


@torch.no_grad()
def generate_batch(request: SampleRequest, trained: TrainedModel, integrator: Integrator, specs: list[SampleSpec],
                   conditions: PromptConditions | None, source: SourceMotion | None,
                   options: Mapping[str, Any]) -> BatchResult:
    """Sample (or edit) one batch of motions."""
    device = trained.device
    lengths = torch.tensor([s.length for s in specs], dtype=torch.long, device=device)
    num_frames = int(lengths.max())
    dim = trained.model_config.feature_dim
    if conditions is None:
        batch_conditions, scale = placeholder_conditions(trained, len(specs)), 0.0
    else:
        batch_conditions = conditions.select(torch.tensor([s.prompt for s in specs]))
        scale = request.guidance_for(trained)
    model = conditioned_model(trained, batch_conditions)
    cond = batch_conditions.cond
    keep = None
    if source is not None:
        known = _known_motion(trained, source, lengths, num_frames)
        keep = keep_mask(request, options, lengths, num_frames, FeatureLayout(trained.skeleton),
                         source.features.shape[0]).to(device)
    if integrator.objective == "diffusion":
        # Each sample's initial and per-step noise from its own seed: the same sample at any --batch-size.
        generator = seeded_generators([s.seed for s in specs])
        if source is None:
            result: SolveResult = sample_diffusion(
                model, integrator.diffusion, cond, lengths, num_frames=num_frames, feature_dim=dim,
                sampler=integrator.name, guidance=scale, generator=generator,
                return_trajectory=request.plot_trajectory)
        else:
            denoise = classifier_free_guidance(model, cond, scale=scale, lengths=lengths, guided_channels=dim)
            result = replacement_edit(denoise, integrator.diffusion, known, keep, sampler=integrator.name,
                                      lengths=lengths, generator=generator, return_trajectory=request.plot_trajectory)
    else:
        velocity = guided_velocity(model, cond, scale=scale, lengths=lengths)
        x0 = draw_noise((len(specs), num_frames, dim), seeded_generators([s.seed for s in specs]), lengths=lengths,
                        device=device)
        if source is None:
            result = solve(zero_padded_frames(velocity, lengths), x0, solver=integrator.name, steps=integrator.steps,
                           return_trajectory=request.plot_trajectory)
        else:
            result = edit(velocity, known, keep, steps=integrator.steps, rewrite_until=request.rewrite_time,
                          solver=integrator.name, x0=x0, lengths=lengths, return_trajectory=request.plot_trajectory)
    x1 = smooth_over_time(result.x1.float(), lengths, request.smoothing_for(trained))
    return BatchResult(
        specs, x1.cpu(), result.nfe, None if keep is None else keep.cpu(),
        None if result.x1_hat is None else result.x1_hat.float().cpu(), result.x1_hat_times,
    )


# ---------------------------------------------------------------------------------------------------------------
# outputs


def _ranges(flags: np.ndarray) -> list[list[int]]:
    """Half-open [start, stop) runs of True in a 1-D bool array."""
    padded = np.concatenate(([False], flags.astype(bool), [False]))
    edges = np.flatnonzero(padded[1:] != padded[:-1])
    return [[int(a), int(b)] for a, b in zip(edges[::2], edges[1::2])]


def edited_joints(keep: np.ndarray, layout: FeatureLayout) -> np.ndarray:
    """(T, J) bool: a joint is edited (generated) on a frame where any of its feature dims is not kept."""
    return np.stack([~keep[:, layout.joint_dims(j)].all(axis=1) for j in range(layout.num_joints)], axis=1)


def caption(request: SampleRequest, spec: SampleSpec) -> str:
    if spec.prompt is None:
        words = "unconditional"
    else:
        words = (request.texts or request.actions)[spec.prompt]
    return words if request.edit is None else f"{words} [{request.edit} edit]"


class SampleWriter:
    """Writes one sample's files and describes each of them for results.json (paths relative to out_dir)."""

    def __init__(self, request: SampleRequest, trained: TrainedModel, out_dir: Path) -> None:
        self.request = request
        self.trained = trained
        self.out_dir = out_dir
        self.skeleton = trained.skeleton
        self.layout = FeatureLayout(self.skeleton)

    def _entry(self, path: Path, kind: str, **info: Any) -> dict[str, Any]:
        return {"path": path.relative_to(self.out_dir).as_posix(), "kind": kind, **info}

    def write(self, index: int, features: np.ndarray, title: Captions, keep: np.ndarray | None = None,
              x1_hat: np.ndarray | None = None, x1_hat_times: np.ndarray | None = None) -> dict[str, Any]:
        """Sample ``index``'s files from its un-normalised features (L, D); ``title``: a caption, or
        ``[(start_frame, caption), ...]`` for captions that change over the motion (composition). Returns the
        sample's results.json fields ``files`` and ``plausibility`` (:func:`plausibility_record`)."""
        folder = self.out_dir / SAMPLE_DIR.format(index)
        folder.mkdir(parents=True, exist_ok=True)
        ric = features_to_joints(features, self.skeleton)
        rigid = rigid_joints(ric, self.skeleton)  # fixed bone lengths: the only joints a rig (the BVH) can play
        joints = (rigid if self.request.decode == "rigid" else ric).astype(np.float32)
        files = []
        np.save(folder / "features.npy", features)
        files.append(self._entry(folder / "features.npy", "features", shape=list(features.shape),
                                 normalized=False, dtype="float32"))
        np.save(folder / "joints.npy", joints)
        files.append(self._entry(folder / "joints.npy", "joints", shape=list(joints.shape), unit=self.skeleton.unit,
                                 recovered_with=JOINT_DECODES[self.request.decode], dtype="float32"))
        if keep is not None:
            np.save(folder / "keep_mask.npy", keep)
            files.append(self._entry(folder / "keep_mask.npy", "keep_mask", shape=list(keep.shape),
                                     meaning="True = kept from the source motion"))
        if self.request.video:
            edited = None if keep is None else edited_joints(keep, self.layout)
            video = render_motion(folder / "motion", joints, self.skeleton, self.trained.fps, title=title,
                                  edited=edited, fmt=self.request.video_format)
            captions = {} if isinstance(title, str) or title is None else {"captions": [list(c) for c in title]}
            files.append(self._entry(video, "video", format=video.suffix.lstrip("."), fps=self.trained.fps,
                                     colors="kept blue, edited red" if keep is not None else "one colour per chain",
                                     **captions))
        if self.request.bvh:
            bvh = write_bvh(folder / "motion.bvh", rigid, self.skeleton, self.trained.fps)
            files.append(self._entry(bvh, "bvh", skeleton=self.skeleton.name, unit="m", up="Y",
                                     recovered_with=JOINT_DECODES["rigid"],
                                     root_channels=list(ROOT_CHANNELS), joint_channels=list(JOINT_CHANNELS),
                                     rotation_order="R = Ry @ Rx @ Rz (Blender Euler ZXY)", fps=self.trained.fps))
        if x1_hat is not None:
            plot_title = title if isinstance(title, str) or title is None else " / ".join(text for _, text in title)
            png = plot_x1_trajectory(folder / "trajectory.png", x1_hat, x1_hat_times, self.skeleton,
                                     mean=self.trained.mean.cpu(), std=self.trained.std.cpu(), title=plot_title)
            # Flow: t of each x̂1 estimate (1 = data); diffusion: the denoiser's t_model (0 = data).
            files.append(self._entry(png, "trajectory_plot", times=[round(float(t), 6) for t in x1_hat_times],
                                     time_convention=TIME_CONVENTIONS[self.trained.objective]))
        return {"files": files, "plausibility": plausibility_record(joints, self.skeleton)}


def plausibility_record(joints: np.ndarray, skeleton: Skeleton) -> dict[str, float | None]:
    """A sample's plausibility figures (mfm.metrics.plausibility of the (L, J, 3) joints written to joints.npy;
    thresholds in results.json's ``plausibility_thresholds``), rounded; None where undefined (the contact foot
    speed of a motion whose feet never touch the floor). No ground truth here, so no jerk ratio."""
    figures = metrics.plausibility(joints, skeleton).clip(0)
    return {name: None if value is None else round(value, 6) for name, value in figures.items()}


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
        # Flow edits: the named settings and what this edit overrode (steps, guidance and ς given explicitly).
        "settings": None if diffusion else {
            **request.settings.record(),
            "overridden": [name for name, value in (("steps", request.steps), ("guidance", request.guidance),
                                                   ("rewrite_until", request.rewrite_until)) if value is not None]},
        "kept_frame_ranges": _ranges(keep.any(axis=1)),
        "kept_dim_ranges": _ranges(keep.any(axis=0)),
        "kept_fraction": round(float(keep.mean()), 6),
    }


def write_mdm_layout(out_dir: Path, samples: Sequence[Mapping[str, Any]], num_samples: int) -> dict[str, Any]:
    """MDM's ``results.npy`` (and its text files) of the written joints, so MDM's rendering and SMPL-fitting
    scripts read our samples: our sample i is prompt i // num_samples's repetition i % num_samples."""
    joints = [np.load(out_dir / next(f["path"] for f in s["files"] if f["kind"] == "joints")) for s in samples]
    texts = [s["text"] or s["action"] or "" for s in samples]
    path = write_mdm_results(out_dir / MDM_RESULTS_FILES[0], joints, texts, [s["length"] for s in samples],
                             num_repetitions=num_samples, order="sample_major")
    return {"path": path.name, "layout": "MDM sample/generate.py: motion (R·S, J, 3, F), index rep·S + sample, "
            "padded with the last frame", "num_samples": len(samples) // num_samples, "num_repetitions": num_samples}


def prepare_out_dir(out_dir: Path, overwrite: bool) -> None:
    """Create ``out_dir``; refuse one with files unless ``overwrite``, which removes an earlier run's outputs
    (results.json, index.html and sample_NNN folders) only."""
    out_dir.mkdir(parents=True, exist_ok=True)
    existing = [p for p in out_dir.iterdir()]
    if not existing:
        return
    if not overwrite:
        raise SamplingError(f"{out_dir} is not empty: choose a new output folder or pass overwrite")
    ours = [p for p in existing if p.name in (RESULTS_FILE, *MDM_RESULTS_FILES, BROWSE_PAGE)
            or (p.is_dir() and _SAMPLE_DIR_PATTERN.match(p.name))]
    others = sorted(p.name for p in set(existing) - set(ours))
    if others:
        raise SamplingError(f"{out_dir} holds files that are not sampling outputs ({others[:5]}): not overwriting")
    for path in ours:
        shutil.rmtree(path) if path.is_dir() else path.unlink()


def write_json_atomically(path: Path, payload: Mapping[str, Any]) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(payload, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, path)


def resolve_device(device: str) -> str:
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return device


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def results_header(request: SampleRequest, trained: TrainedModel, integrator: Integrator, mode: str,
                   conditioned: bool) -> dict[str, Any]:
    """The part of results.json every mode shares: the checkpoint, the data it knows and how it was integrated."""
    return {
        "version": RESULTS_VERSION,
        "checkpoint": str(trained.checkpoint),
        "step": trained.step,
        "weights": trained.weights,
        "dataset_id": trained.dataset_id,
        "skeleton": trained.skeleton.name,
        "fps": trained.fps,
        "mode": mode,
        "conditioning": "text" if request.texts or request.compose_file else "action" if request.actions else "none",
        **integrator.record(trained),
        "guidance": request.guidance_for(trained) if conditioned else 0.0,
        "smoothing_sigma": request.smoothing_for(trained),
        "seed": request.seed,
        "device": str(trained.device),
        "plausibility_thresholds": metrics.plausibility_settings(trained.skeleton),
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
                      options: Mapping[str, Any]) -> Iterator[tuple[list[SampleSpec], BatchResult, np.ndarray, float]]:
    """Generate ``specs`` batch by batch: ``(specs of the batch, its BatchResult, its un-normalised features
    (B, T, D) as numpy, generation seconds)``. Shared by the command line (which writes each batch as it comes) and
    the Python API (:class:`pipeline.pretrained.MotionPipeline`)."""
    for chunk in batches(specs, request.batch_size):
        synchronize(trained.device)
        tick = time.perf_counter()
        batch = generate_batch(request, trained, integrator, chunk, conditions, source, options)
        synchronize(trained.device)
        seconds = time.perf_counter() - tick
        features = trained.denormalize(batch.features.to(trained.device)).cpu().numpy()
        yield chunk, batch, features, seconds


def run_sampling(request: SampleRequest) -> dict[str, Any]:
    """Generate every sample of ``request``, write the files and ``results.json``; returns the results dict.
    Composition requests go to :func:`pipeline.composing.run_composition`."""
    if request.composes:
        raise SamplingError("a composition request is run by pipeline.composing.run_composition")
    out_dir = Path(request.out_dir)
    trained = load_for_request(request)
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
    try:  # index.html to browse the motions (pipeline/browse.py): a failure is logged, never fatal
        from pipeline.browse import write_sample_index
        write_sample_index(out_dir)
    except Exception as exc:
        logger.warning("index.html not written: %s", exc)
    return results
