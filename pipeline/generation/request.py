"""What a sampling, editing or composition run is asked to do: :class:`SampleRequest`, a typed config.

A request is given as a YAML file (``--config FILE``), command-line flags (``--text``, ``--steps``, ... : the
:data:`FLAGS` table, each a shorthand for one key) and dotted overrides (``key=value``, e.g. ``steps=20
'texts=[a person walks]'``), applied in that order, validated as the training and evaluation configs are
(pipeline.config.load_config); ``--print-config`` lists every key with its value, default and meaning. The request
is run by :func:`pipeline.generation.sampling.run_sampling` (samples and edits) or :func:`pipeline.generation.composing.run_composition`
(composition, extrapolation); what they write is described in pipeline/generation/outputs.py.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from mfm.compilation import COMPILE_SETTINGS
from mfm.composition import BABEL_SWITCH, HUMANML3D_SWITCH
from mfm.diffusion_sampling import SAMPLERS, BaselineSampling
from mfm.editing import (
    DEFAULT_EDIT_SETTINGS,
    EDIT_SETTINGS,
    EditSettings,
)
from mfm.guidance import PRECISION_SETTINGS, guided_feature_mask
from mfm.model import is_bone_keeping
from mfm.solvers import (
    FIXED_STEP_SOLVERS,
)
from pipeline.config import field_docs, load_config
from pipeline.generation.inference import TrainedModel

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
    # torchdiffeq has no public list of its methods; mfm.solvers reads the same table. Imported when asked, as
    # mfm.solvers does: torchdiffeq brings scipy.integrate (about a second), which most imports of this module skip.
    from torchdiffeq._impl.odeint import SOLVERS

    return sorted(FIXED_STEP_SOLVERS) + sorted(set(SOLVERS) - set(FIXED_STEP_SOLVERS))

DEFAULT_FLOW_SOLVER = "euler"


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
    """Everything one sampling, editing or composition run needs (module docstring: how it is given)."""

    checkpoint: str | Path
    """A step-XXXXXXXX folder, a run folder (its newest complete checkpoint) or an exported folder."""
    out_dir: str | Path
    """Output folder (must be empty unless overwrite)."""
    texts: tuple[str, ...] = ()
    """Prompts (text models)."""
    prompts: str | None = None
    """A file with one prompt per line (blank and # lines skipped), appended to texts."""
    actions: tuple[str, ...] = ()
    """Action class names (action models)."""
    lengths: tuple[int, ...] = ()
    """Frames: one for every prompt or one per prompt; empty: drawn from the training lengths (edits: the source's)."""
    seconds: tuple[float, ...] = ()
    """Like lengths, in seconds (converted with the dataset's fps)."""
    num_samples: int = 1
    """Samples per prompt (without prompts: in total, unconditional); composition: sequences."""
    steps: int | None = None
    """Solver steps; null: the model's ``sampling_steps`` (flow: 10 unless its config says otherwise, e.g. a
    few-step student's 2), the edit settings' (flow edits: paper 30; reference-debug 100, interpolation
    1), every training step (diffusion)."""
    solver: str | None = None
    """Flow: euler (default), midpoint, heun, rk4 or a torchdiffeq method such as dopri5; diffusion: ddpm
    (default) or ddim."""
    guidance: float | None = None
    """Classifier-free guidance scale; null: a flow edit's settings' 1.0, a FLAME-preset model's 8.0, else the
    model's ``sampling_guidance`` (2.5 unless its preset says otherwise)."""
    guided_features: str | None = None
    """Flow models: which channels guidance mixes, all or pose (the root's motion follows the conditional field);
    null: the model's ``guided_features`` (all unless its preset says otherwise). Diffusion models: all."""
    smoothing: float | None = None
    """Gaussian smoothing of the output over time, σ in frames; null: the diffusion baseline's own (FLAME: 1), else
    the model's ``output_smoothing`` (none unless its preset says otherwise; not the baseline's with
    ``baseline_defaults=false``)."""
    smoothing_keeps_bones: bool | str | None = None
    """After the smoothing, give every bone back a length it had before the filter (it then smooths the bones'
    directions only; ours, not FLAME's): true, each frame's own; smoothed, its lengths smoothed over time with the
    same σ (mfm.model.ModelConfig.output_smoothing_keeps_bones); null: the model's ``output_smoothing_keeps_bones``
    (false unless its preset says otherwise). Nothing to keep without smoothing."""
    baseline_defaults: bool = True
    """Diffusion checkpoints of a preset whose authors sampled it their own way run that way unless a key below
    overrides one setting (mfm.diffusion_sampling.BASELINE_SAMPLING; FLAME: guidance 8.0, σ = 1 smoothing, every
    training step, the x0 clamp, EMA weights: a FLAME checkpoint that kept none is refused unless weights=model),
    as the evaluator's ``sampling.baseline_defaults``; false: every checkpoint samples with our defaults (the model's
    sampling_guidance and output_smoothing, no clamp). results.json records what ran (``baseline_defaults``)."""
    baseline_clip_denoised: bool = True
    """With baseline_defaults: a baseline whose sampler clamps its x0 estimate (FLAME) gets that clamp on our features
    (the 6D rotation channels bounded to [-1, 1] in raw units, mfm.diffusion_sampling.rotation_6d_range; the
    evaluator's ``sampling.baseline_clip_denoised``); false: no clamp."""
    edit_reference_translation: bool = True
    """Diffusion edits (FLAME's replacement procedure): copy the source's root (rotation and linear velocity, height)
    into the output where the edit keeps it, after the smoothing, as FLAME's edit_motion.py
    (use_reference_translation: true; the evaluator's ``tasks.edit_reference_translation``); false: the chain's
    output, smoothed. Flow edits (MFM's procedure) never copy."""
    seed: int = 0
    """Noise seed (sample i uses SeedSequence([seed, i]))."""
    batch_size: int = 64
    """Motions per batch (does not change flow samples)."""
    weights: str = "ema"
    """ema (falls back to the raw weights when the run kept none, except for a baseline whose authors sample the
    EMA, FLAME: refused) or model."""
    device: str = "auto"
    """auto (cuda when available), cpu, cuda, cuda:1, ..., mps; a device this machine does not have is refused
    before the checkpoint is loaded (pipeline.generation.integration.resolve_device)."""
    precision: str = "auto"
    """The model passes' arithmetic: fp32; bf16 (bf16 autocast on CPU or a CUDA GPU with bf16; the ODE state, the
    guidance mix and the solver stay fp32, so the motions differ from fp32 ones by the network's rounding only); auto
    (default): bf16 on a CUDA GPU with native bf16 (as training's ``train.mixed_precision=auto``), fp32 anywhere else,
    the CPU included. results.json records what ran (``precision``) and the setting (``precision_setting``)."""
    compile: bool | str = "auto"
    """torch.compile the model passes (mfm.compilation, the rule of training's ``train.compile``): auto (default) on
    a CUDA device only, with CUDA graphs (``mode="reduce-overhead"``: a fixed-step solver calls the model with the
    same shapes every step); true / false: always (elsewhere inductor's default mode, minutes of compilation on a CPU)
    / never. Built once per run, compiled on the first batch (and again for each new batch shape). Composition
    requests do not use it. results.json records what ran (``compiled``) and the setting (``compile_setting``)."""
    text_weights: str | None = None
    """CLIP datasets: the text encoder weights file, checked against the checkpoint's hash."""
    edit: str | None = None
    """Edit source_motion instead of sampling from noise: a key of EDIT_PRESETS."""
    source_motion: str | Path | None = None
    """Edits: .npy of un-normalised features (T, D) or joint positions (T, J, 3)."""
    keep: dict[str, Any] = dataclasses.field(default_factory=dict)
    """Edit mask options (KEEP_OPTIONS): prefix=F / suffix=F (prediction, inbetween), every=K (interpolate),
    joints=A,B[,..] frames=S:E (joints)."""
    rewrite_until: float | None = None
    """Flow edits: rewrite the kept part up to this time ς; null: the edit settings'."""
    edit_settings: str = DEFAULT_EDIT_SETTINGS
    """Flow edits: paper (the MFM paper's §4.1: N = 30 steps, ς = 0.2; guidance 1.0) or reference-debug (MFM
    edit.py's debug presets: 100 steps, interpolation 1)."""
    mdm_results: bool = False
    """Also write MDM's results.npy (+ results.txt, results_len.txt) for MDM's render/SMPL scripts."""
    video: bool = True
    """Write motion.mp4 / motion.gif per sample."""
    video_format: str = "auto"
    """auto (MP4 if ffmpeg is found, else GIF), mp4 or gif."""
    bvh: bool = True
    """Write motion.bvh per sample."""
    plot_trajectory: bool = False
    """Also plot the x̂1 estimates along the trajectory."""
    decode: str = "ric"
    """joints.npy and the video: ric (positions as recovered) or rigid (fitted onto the skeleton's bone lengths;
    the BVH always is)."""
    overwrite: bool = False
    """Replace an earlier run's outputs in out_dir."""
    progress: bool | None = None
    """Progress bars; null: when stderr is a terminal."""
    # Composition (pipeline/generation/composing.py): one sequence made of (text, frames) segments.
    compose_file: str | Path | None = None
    """FlowMDM prompt file {"text": [...], "lengths": [...]}: one sequence of all segments per sample."""
    extrapolate: bool = False
    """One text (or action) repeated over segments; also chosen when the file's texts agree."""
    num_segments: int | None = None
    """Extrapolation without a file: the one length repeated this many times."""
    switch: int | float | str | None = None
    """bpe models: the flow time of the absolute-to-relative switch (float), a number of leading absolute steps
    (int), or a name (humanml3d, babel); null: humanml3d."""
    attention_chunk: int | None = None
    """bpe models: attention block size; null: the attention horizon for sequences longer than it; 0: dense."""

    def __post_init__(self) -> None:
        if self.prompts is not None:  # read once: the request then holds the prompts themselves
            self.texts = (*self.texts, *read_prompts(self.prompts))
            self.prompts = None
        if isinstance(self.switch, str):
            try:
                self.switch = parse_switch(self.switch)
            except ValueError as err:
                raise SamplingError(str(err)) from None
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
        if self.smoothing_keeps_bones is not None and not is_bone_keeping(self.smoothing_keeps_bones):
            raise SamplingError(f"smoothing_keeps_bones must be true, false or smoothed, got {self.smoothing_keeps_bones!r}")
        if self.weights not in ("ema", "model"):
            raise SamplingError(f"weights must be 'ema' or 'model', got {self.weights!r}")
        if self.solver is not None and self.solver not in known_solvers() + list(SAMPLERS):
            raise SamplingError(f"unknown solver {self.solver!r}; known: {known_solvers()} for flow models, "
                                f"{list(SAMPLERS)} for diffusion models")
        if self.video_format not in ("auto", "mp4", "gif"):
            raise SamplingError(f"video_format must be 'auto', 'mp4' or 'gif', got {self.video_format!r}")
        if self.precision not in PRECISION_SETTINGS:
            raise SamplingError(f"precision must be one of {list(PRECISION_SETTINGS)}, got {self.precision!r}")
        if self.compile not in COMPILE_SETTINGS or not isinstance(self.compile, (bool, str)):
            raise SamplingError(f"compile must be auto, true or false, got {self.compile!r}")
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
        """A composition request (pipeline/generation/composing.py) rather than independent samples or edits."""
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

    @property
    def settings_steps(self) -> int:
        """The edit settings' Euler steps for this edit's preset (reference-debug's interpolation: 1, as MFM's
        edit.py); an explicit ``steps`` wins over it."""
        return self.settings.steps_for(EDIT_PRESETS[self.edit] or "joints")

    def guidance_for(self, trained: TrainedModel) -> float:
        """The guidance scale: as given, else the edit settings' for a flow edit, else the diffusion baseline's own
        (FLAME: 8.0, mfm.diffusion_sampling.BASELINE_SAMPLING; not with ``baseline_defaults=false``), else the
        model's ``sampling_guidance`` (MFM's 2.5 unless its preset says otherwise)."""
        if self.guidance is not None:
            scale = float(self.guidance)
        elif self.edit is not None and trained.objective == "flow":
            scale = self.settings.guidance
        else:
            scale = trained.guidance_with(self.baseline_for(trained))
        if (reason := trained.unguidable_reason(scale)) is not None:
            raise SamplingError(reason)
        return scale

    def guided_features_for(self, trained: TrainedModel) -> str:
        """Which channels guidance mixes: as given, else the model's (:meth:`TrainedModel.guided_features_with`)."""
        return trained.guided_features_with(self.guided_features)

    def conditional_channels_for(self, trained: TrainedModel) -> torch.Tensor | None:
        """:func:`mfm.guidance.guided_feature_mask` of :meth:`guided_features_for`."""
        return guided_feature_mask(self.guided_features_for(trained), trained.skeleton)

    def smoothing_for(self, trained: TrainedModel) -> float:
        """σ (frames) of the output's Gaussian smoothing over time: as given, else the checkpoint's default
        (a diffusion baseline's own, FLAME: 1.0; else the model's ``output_smoothing``, 0 = none)."""
        if self.smoothing is not None:
            return float(self.smoothing)
        return trained.smoothing_with(self.baseline_for(trained))

    def smoothing_keeps_bones_for(self, trained: TrainedModel) -> bool | str:
        """Whether the smoothing keeps the bones' lengths: as given, else the model's."""
        return trained.smoothing_keeps_bones_with(self.smoothing_keeps_bones)

    def baseline_for(self, trained: TrainedModel) -> BaselineSampling | None:
        """The authors' sampling settings of ``trained``'s diffusion preset as this request runs them (None: ours,
        for flow models, presets without such settings and ``baseline_defaults=false``): every training step
        unless ``steps`` asks for fewer, the x0 clamp unless ``baseline_clip_denoised=false``, the EMA weights
        unless ``weights=model``; guidance and smoothing stay the authors' (an explicit value wins, recorded in
        :meth:`baseline_record`)."""
        baseline = trained.baseline_sampling if self.baseline_defaults else None
        if baseline is None:
            return None
        return baseline.as_run(
            every_training_step=self.steps is None or self.steps == trained.diffusion.num_train_steps,
            clip_denoised=self.baseline_clip_denoised, ema_weights=self.weights == "ema")

    def baseline_record(self, trained: TrainedModel) -> dict[str, Any] | None:
        """results.json's ``baseline_defaults``: None when no authors' settings apply, else those settings as run
        (:meth:`TrainedModel.baseline_record`: preset, guidance, smoothing_sigma, every_training_step,
        clip_denoised, ema_weights, source) and ``overridden``: the ones this request ran with another value
        (``guidance``, ``smoothing``, ``steps``, ``baseline_clip_denoised``, ``weights``)."""
        baseline = self.baseline_for(trained)
        if baseline is None:
            return None
        own = trained.baseline_sampling
        ran = {"guidance": self.guidance_for(trained), "smoothing_sigma": self.smoothing_for(trained),
               "every_training_step": baseline.every_training_step, "clip_denoised": baseline.clip_denoised,
               "ema_weights": baseline.ema_weights}
        return {**trained.baseline_record(baseline),
                "overridden": [name for name, value in ran.items() if value != getattr(own, name)]}


SWITCH_PRESETS = {"humanml3d": HUMANML3D_SWITCH, "babel": BABEL_SWITCH}
"""FlowMDM's ``bpe_denoising_step`` per dataset (60 HumanML3D, 125 Babel) as flow times."""


def parse_switch(text: str) -> float | int:
    """``--switch``: a preset name (humanml3d, babel), an int (leading absolute solver steps) or a float flow time."""
    name = text.strip().lower()
    if name in SWITCH_PRESETS:
        return SWITCH_PRESETS[name]
    try:
        return int(name)
    except ValueError:
        pass
    try:
        return float(name)
    except ValueError:
        raise ValueError(f"switch must be {' or '.join(SWITCH_PRESETS)}, an int step count or a float flow time, "
                         f"got {text!r}") from None


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


# ---------------------------------------------------------------------------------------------------------------
# the command line: the flags users already type, each a shorthand for one request key


@dataclasses.dataclass(frozen=True)
class Flag:
    """``--name`` on the command line, setting request key ``key``; ``kind``: 'value' (one value), 'append'
    (repeatable, a list), 'true' / 'false' (a switch setting the key to True / False). Help: the key's doc."""

    name: str
    key: str
    kind: str = "value"
    type: Callable[[str], Any] = str
    choices: tuple[str, ...] | None = None
    metavar: str | None = None


def on_off(text: str) -> bool:
    """A switch's value (--smoothing-keeps-bones of launch/sample.py and launch/contact_sheet.py): true/on or
    false/off."""
    settings = {"true": True, "on": True, "false": False, "off": False}
    if text.lower() not in settings:
        raise argparse.ArgumentTypeError(f"true or false, got {text!r}")
    return settings[text.lower()]


def _switch_or(word: str, accepted: str) -> Callable[[str], bool | str]:
    """A switch's value (:func:`on_off`) that may also be ``word``; ``accepted`` lists the values in the error."""

    def parse(text: str) -> bool | str:
        if text.lower() == word:
            return word
        try:
            return on_off(text)
        except argparse.ArgumentTypeError:
            raise argparse.ArgumentTypeError(f"{accepted}, got {text!r}") from None

    return parse


bone_keeping_setting = _switch_or("smoothed", "true, false or smoothed")
"""--smoothing-keeps-bones's value (launch/sample.py, launch/contact_sheet.py, the study's benchmarks): true/on,
false/off or smoothed (mfm.model.BONE_KEEPING)."""
_compile_setting = _switch_or("auto", "auto, true or false")
"""``--compile``'s value as the request key holds it: auto, True or False."""


def _key_value(text: str) -> tuple[str, str]:
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    return key, value


FLAGS: tuple[Flag, ...] = (
    Flag("--checkpoint", "checkpoint"),
    Flag("--out", "out_dir"),
    Flag("--text", "texts", "append"),
    Flag("--prompts", "prompts"),
    Flag("--action", "actions", "append"),
    Flag("--length", "lengths", "append", int),
    Flag("--seconds", "seconds", "append", float),
    Flag("--num-samples", "num_samples", type=int),
    Flag("--steps", "steps", type=int),
    Flag("--solver", "solver"),
    Flag("--guidance", "guidance", type=float),
    Flag("--guided-features", "guided_features", choices=("all", "pose")),
    Flag("--smoothing", "smoothing", type=float),
    Flag("--smoothing-keeps-bones", "smoothing_keeps_bones", type=bone_keeping_setting,
         metavar="{true,false,smoothed}"),
    Flag("--no-baseline-defaults", "baseline_defaults", "false"),
    Flag("--no-clip-denoised", "baseline_clip_denoised", "false"),
    Flag("--no-reference-translation", "edit_reference_translation", "false"),
    Flag("--seed", "seed", type=int),
    Flag("--batch-size", "batch_size", type=int),
    Flag("--edit", "edit", choices=tuple(sorted(EDIT_PRESETS))),
    Flag("--source-motion", "source_motion"),
    Flag("--keep", "keep", "append", _key_value, metavar="KEY=VALUE"),
    Flag("--rewrite-until", "rewrite_until", type=float),
    Flag("--edit-settings", "edit_settings", choices=tuple(sorted(EDIT_SETTINGS))),
    Flag("--compose", "compose_file", metavar="FILE.json"),
    Flag("--extrapolate", "extrapolate", "true"),
    Flag("--num-segments", "num_segments", type=int),
    Flag("--switch", "switch"),
    Flag("--attention-chunk", "attention_chunk", type=int),
    Flag("--plot-trajectory", "plot_trajectory", "true"),
    Flag("--no-video", "video", "false"),
    Flag("--video-format", "video_format", choices=("auto", "mp4", "gif")),
    Flag("--no-bvh", "bvh", "false"),
    Flag("--mdm-results", "mdm_results", "true"),
    Flag("--decode", "decode", choices=tuple(sorted(JOINT_DECODES))),
    Flag("--device", "device"),
    Flag("--precision", "precision", choices=PRECISION_SETTINGS),
    Flag("--compile", "compile", type=_compile_setting, metavar="{auto,true,false}"),
    Flag("--model-weights", "weights", choices=("ema", "model")),
    Flag("--text-weights", "text_weights"),
    Flag("--overwrite", "overwrite", "true"),
)


def add_request_flags(parser: argparse.ArgumentParser) -> None:
    """Declare :data:`FLAGS` on ``parser`` (defaults None: an unset flag leaves the config's value)."""
    docs = field_docs(SampleRequest)
    for flag in FLAGS:
        help_text = docs.get(flag.key, "")
        if flag.kind in ("true", "false"):
            parser.add_argument(flag.name, dest=flag.key, action=f"store_{flag.kind}", default=None, help=help_text)
        else:
            parser.add_argument(flag.name, dest=flag.key, type=flag.type, choices=flag.choices, metavar=flag.metavar,
                                action="append" if flag.kind == "append" else "store", default=None,
                                help=help_text)


def flag_values(args: argparse.Namespace) -> dict[str, Any]:
    """The request keys the flags in ``args`` set (``--keep`` pairs become the keep mapping)."""
    values = {flag.key: getattr(args, flag.key) for flag in FLAGS if getattr(args, flag.key, None) is not None}
    if "keep" in values:
        values["keep"] = dict(values["keep"])
    return values


def load_sample_request(preset: str | Path | None = None, overrides: Sequence[str] = (),
                        values: Mapping[str, Any] | None = None) -> SampleRequest:
    """A validated request: ``preset`` (a YAML file), then ``values`` (the flags'), then ``key=value``
    overrides. A bad key or value is a ConfigError or SamplingError naming it."""
    return load_config(SampleRequest, preset, overrides, values=values or {})
