"""A trained model ready to sample from: weights (EMA by default) + everything the checkpoint knows about its data.

A checkpoint carries the dataset's identity (id, feature spec, text encoder entry, action classes, normalisation,
training lengths), so sampling and evaluation need no access to the shards: features are produced in the
training normalisation and converted back with the checkpoint's Mean/Std, prompts are encoded with the same
text encoder (checked by weights hash), and joints are recovered on the dataset's skeleton.

The checkpoint's resolved training config says which objective trained it (``train.objective``): a ``'flow'``
model is a velocity field (ODE solvers, mfm.solvers), a ``'diffusion'`` model a denoiser whose
:class:`mfm.diffusion.GaussianDiffusion` is rebuilt from the saved preset (``train.diffusion``: ``'flowmdm'`` or
``'flame'``; DDPM/DDIM samplers, mfm.diffusion_sampling).

Every way of getting one is here, at the bottom of pipeline/generation/ (tests/test_layout.py): a checkpoint, a run
folder's newest complete checkpoint, or an exported folder (launch/export.py; :mod:`pipeline.generation.pretrained`
writes it, :func:`load_pretrained` reads it), so the modules that sample, write and export import this one and it
imports none of them.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Mapping, Sequence
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import safetensors
import safetensors.torch
import torch

from mfm.compilation import compiled_for_sampling, compiles
from mfm.diffusion import DenoisedRange, GaussianDiffusion, diffusion_from_preset
from mfm.diffusion_sampling import (
    BASELINE_SAMPLING,
    ROTATION_6D_RANGE_RECORD,
    BaselineSampling,
    BoneKeeping,
    copy_reference_root,
    rotation_6d_range,
    smooth_over_time,
)
from mfm.layout import FeatureLayout
from mfm.model import ModelConfig, MotionFlowTransformer
from mfm.shortcut import sampler_step_size
from mfm.skeleton import Skeleton, get_skeleton
from mfm.text import build_matching_text_encoder
from pipeline import checkpoint as ckpt
from pipeline.checkpoint import resolve_checkpoint  # noqa: F401 - where samplers and tools have imported it from

SAMPLING_DTYPES = (torch.float32, torch.bfloat16, torch.float16)
"""The weight dtypes a model can be sampled in (:meth:`TrainedModel.to`): float32, what training saves, or a half
type under autocast. Not float64: the model computes its time and position tables in float32 by design."""

logger = logging.getLogger(__name__)

# An exported folder (launch/export.py; written by pipeline.generation.pretrained, read here by load_pretrained).
PRETRAINED_FORMAT = "mfm-pretrained"
PRETRAINED_VERSION = 1
CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"
NORMALIZATION_FILE = "normalization.safetensors"


def skeleton_from_spec(feature_spec: Mapping[str, Any]) -> Skeleton:
    """The dataset's skeleton with the bone lengths its features were extracted with (FK, BVH export)."""
    skeleton = get_skeleton(feature_spec["skeleton"])
    lengths = feature_spec.get("bone_lengths")
    if lengths is not None:
        skeleton = dataclasses.replace(skeleton, bone_lengths=np.asarray(lengths, dtype=np.float64))
    return skeleton


@dataclasses.dataclass
class TrainedModel:
    model: MotionFlowTransformer  # eval mode, on ``device``
    model_config: ModelConfig
    checkpoint: Path
    step: int
    weights: str  # "ema" or "model"
    data: dict[str, Any]  # the checkpoint's dataset identity (see Trainer.save)
    device: torch.device
    window: int  # frames per training sample: the longest motion the model has learnt
    objective: str = "flow"  # the training objective: "flow" (velocity field) or "diffusion" (denoiser)
    diffusion_preset: str | None = None  # diffusion models: "flowmdm", "flame" or "mdm" (mfm.diffusion.DIFFUSION_PRESETS)
    diffusion: GaussianDiffusion | None = None  # diffusion models: the process they were trained on
    # sampling_model compiled (compiled_with): built once, reused by every batch; None: samplers call the module
    compiled_model: torch.nn.Module | None = None

    @cached_property
    def mean(self) -> torch.Tensor:
        return torch.as_tensor(np.asarray(self.data["normalization"]["mean"], dtype=np.float32), device=self.device)

    @cached_property
    def std(self) -> torch.Tensor:
        return torch.as_tensor(np.asarray(self.data["normalization"]["std"], dtype=np.float32), device=self.device)

    @property
    def skeleton(self) -> Skeleton:
        return skeleton_from_spec(self.data["feature_spec"])

    @property
    def fps(self) -> float:
        return float(self.data["feature_spec"]["fps"])

    @property
    def action_classes(self) -> list[str]:
        return list(self.data.get("action_classes", []))

    @property
    def train_lengths(self) -> list[int]:
        return list(self.data.get("train_lengths", []))

    @property
    def dataset_id(self) -> str:
        return self.data["dataset_id"]

    @property
    def baseline_sampling(self) -> BaselineSampling | None:
        """How the authors of this model's diffusion preset sampled it (FLAME: guidance 8.0, σ = 1 smoothing);
        None for flow models and presets without such settings."""
        if self.objective != "diffusion":
            return None
        return BASELINE_SAMPLING.get(self.diffusion_preset or "")

    @property
    def default_smoothing(self) -> float:
        """σ (frames) of the output smoothing samplers apply unless told otherwise: a diffusion baseline's own
        (FLAME: 1), else the model's ``output_smoothing`` (0 unless its preset says otherwise)."""
        return self.smoothing_with(self.baseline_sampling)

    def guided_features_with(self, override: str | None) -> str:
        """Which channels guidance mixes: ``override`` when set (a sample request's or the evaluator's), else the
        model's ``guided_features``; 'all' for diffusion checkpoints (their guidance mixes every channel)."""
        if self.objective == "diffusion":
            return "all"
        return override or self.model_config.guided_features

    def smoothing_keeps_bones_with(self, override: bool | str | None) -> bool | str:
        """How the output smoothing gives the bones back their lengths (mfm.model.BONE_KEEPING): ``override`` when
        set (a sample request's or the evaluator's), else the model's ``output_smoothing_keeps_bones``."""
        return self.model_config.output_smoothing_keeps_bones if override is None else override

    @property
    def default_guidance(self) -> float:
        """The classifier-free guidance scale samplers use unless told otherwise: a diffusion baseline's own
        (FLAME: 8.0), else the model's ``sampling_guidance`` (MFM's 2.5 unless its preset says otherwise)."""
        return self.guidance_with(self.baseline_sampling)

    def smoothing_with(self, baseline: BaselineSampling | None) -> float:
        """σ (frames) of the output smoothing with ``baseline`` (the authors' settings as a run applies them, None:
        ours): the baseline's, else the model's ``output_smoothing``."""
        return baseline.smoothing_sigma if baseline is not None else float(self.model_config.output_smoothing)

    def unguidable_reason(self, scale: float) -> str | None:
        """Why classifier-free guidance at ``scale`` is undefined for this model, or None. A model trained without
        condition dropout (``model.cond_drop_prob`` 0: a few-step student, whose teacher's guidance is distilled into
        its conditional field) never learnt the unconditional field guidance extrapolates from, so any scale but 1
        would sample from an untrained input."""
        if float(scale) == 1.0 or self.model_config.cond_drop_prob > 0:
            return None
        return (f"{self.checkpoint} was trained without condition dropout (model.cond_drop_prob 0), so it has no "
                f"unconditional field to guide from: guidance {float(scale):g} is undefined; sample it with "
                f"guidance 1 (its default, model.sampling_guidance {self.model_config.sampling_guidance:g})")

    def shortcut_step_size(self, solver: str, steps: int, guidance: float) -> float | None:
        """The step size d this model is given when ``solver`` takes ``steps`` steps
        (:func:`mfm.shortcut.sampler_step_size`: None for a flow model). A ValueError for an untrained step count,
        and for guidance other than 1 at a shortcut level: its few steps have the guidance of its training
        (``train.shortcut_guidance``, the teacher's) built in, so guiding them again would guide twice."""
        levels = self.model_config.shortcut_levels
        step_size = sampler_step_size(levels, solver, steps)
        if step_size and float(guidance) != 1.0:
            raise ValueError(f"{self.checkpoint} is a shortcut model: its {steps}-step level has its training's "
                             f"guidance built in, so guidance {float(guidance):g} would guide it twice; sample it "
                             f"with guidance 1 (its default), or in {2 ** levels} or more steps (its flow field, "
                             "which takes guidance)")
        return step_size

    def guidance_with(self, baseline: BaselineSampling | None) -> float:
        """The guidance scale with ``baseline`` (None: ours): the baseline's, else the model's
        ``sampling_guidance``."""
        return baseline.guidance if baseline is not None else float(self.model_config.sampling_guidance)

    @property
    def dtype(self) -> torch.dtype:
        """The dtype of the model's weights (float32 unless :meth:`to` changed it)."""
        return next(self.model.parameters()).dtype

    @property
    def sampling_model(self) -> torch.nn.Module:
        """What samplers call: the model itself in float32, else wrapped by :class:`RunInWeightDtype` (autocast);
        that compiled once when :meth:`compiled_with` compiled it."""
        if self.compiled_model is not None:
            return self.compiled_model
        return self.model if self.dtype == torch.float32 else RunInWeightDtype(self.model)

    @property
    def is_compiled(self) -> bool:
        """Whether samplers call a ``torch.compile``-d model (:meth:`compiled_with`)."""
        return self.compiled_model is not None

    def compiled_with(self, setting: bool | str) -> TrainedModel:
        """This model with its :attr:`sampling_model` compiled when the compile ``setting`` (auto / True / False,
        :func:`mfm.compilation.compiles`: auto on CUDA only) says so on this device, else this model as is. The
        compiled model (:func:`mfm.compilation.compiled_for_sampling`: CUDA graphs on CUDA) is built here, once, and
        compiles on its first call; call this after :meth:`to`, which drops it."""
        if not compiles(setting, self.device):
            return self
        uncompiled = dataclasses.replace(self, compiled_model=None).sampling_model
        return dataclasses.replace(self, compiled_model=compiled_for_sampling(uncompiled, self.device))

    def to(self, device: str | torch.device | None = None, dtype: torch.dtype | None = None) -> TrainedModel:
        """This model on ``device`` and/or in weight ``dtype`` (one of :data:`SAMPLING_DTYPES`). The module is moved
        in place (as ``nn.Module.to`` does); the returned TrainedModel records the new device, and its Mean/Std
        follow it (they stay float32: features are un-normalised in float32 whatever the weights are); it is not
        compiled (:meth:`compiled_with` again)."""
        if dtype is not None and dtype not in SAMPLING_DTYPES:
            raise ValueError(f"dtype {dtype}: a model samples in one of {', '.join(map(str, SAMPLING_DTYPES))}")
        target = self.device if device is None else torch.device(device)
        self.model.to(device=target, dtype=dtype)
        # a new instance: the cached Mean/Std are made on ``target``; a compiled model is of the old device/dtype
        return dataclasses.replace(self, device=target, compiled_model=None)

    def x0_clamp(self, baseline: BaselineSampling | None) -> DenoisedRange | None:
        """The bounds of every step's x0 estimate with ``baseline`` (None: ours, no clamp): when its authors'
        sampler clamps (FLAME's ``clip_denoised``), that clamp carried to this checkpoint's features
        (:func:`mfm.diffusion_sampling.rotation_6d_range`), on its device; the evaluator and the sampler both
        take it from here."""
        if baseline is None or not baseline.clip_denoised:
            return None
        bounds = rotation_6d_range(FeatureLayout(self.skeleton), self.mean, self.std)
        return DenoisedRange(*(bound.to(self.device) for bound in bounds))

    def baseline_record(self, baseline: BaselineSampling | None) -> dict[str, Any] | None:
        """What results say about the authors' sampling settings as run: None (ours), else the preset, every
        setting (:meth:`BaselineSampling.record`, with where it comes from) and the clamp's channels."""
        if baseline is None:
            return None
        record = {"preset": self.diffusion_preset, **baseline.record()}
        if baseline.clip_denoised:
            record["clip_denoised_range"] = ROTATION_6D_RANGE_RECORD
        return record

    def check_baseline_weights(self, baseline: BaselineSampling | None, remedy: str) -> None:
        """A baseline whose authors sample the EMA of the weights (FLAME; ``baseline`` as the run applies it) is not
        silently sampled with its raw weights: a ValueError ending in ``remedy`` when this checkpoint kept no
        EMA (loading falls back to the raw weights then)."""
        if baseline is not None and baseline.ema_weights and self.weights != "ema":
            raise ValueError(f"{self.checkpoint} holds no EMA weights, which its authors' sampling "
                             f"({self.diffusion_preset}) uses: {remedy}")

    def finish_output(self, x: torch.Tensor, lengths: torch.Tensor, smoothing_sigma: float, *,
                      known: torch.Tensor | None = None, keep: torch.Tensor | None = None,
                      reference_translation: bool = False, keep_bones: bool | str | None = None) -> torch.Tensor:
        """The sampler's output ``x`` (B, T, D, normalised) as it is written or scored: smoothed over time with
        σ = ``smoothing_sigma`` (0: as is), then, for a diffusion edit (``keep`` of ``known``) with
        ``reference_translation``, the source's root copied where the edit keeps it, after the smoothing as
        FLAME's edit_motion.py: 79–82 then 93–94 (:func:`mfm.diffusion_sampling.copy_reference_root`). Flow edits
        (MFM's procedure) never copy. Shared by the evaluator and the sampler."""
        x = smooth_over_time(x, lengths, smoothing_sigma, BoneKeeping.for_setting(
            self.smoothing_keeps_bones_with(keep_bones), self.skeleton, self.mean, self.std))
        if keep is not None and reference_translation and self.objective == "diffusion":
            x = copy_reference_root(x, known.to(x.dtype), keep, FeatureLayout(self.skeleton))
        return x

    def normalize(self, features: torch.Tensor) -> torch.Tensor:
        return (features - self.mean) / self.std

    def denormalize(self, features: torch.Tensor) -> torch.Tensor:
        return features * self.std + self.mean

    def text_encoder(self, weights: str | None = None):
        """The dataset's text encoder (verified by weights hash); CLIP needs its weights file passed again."""
        return build_matching_text_encoder(self.data["text_encoder"], weights=weights, device=str(self.device))

    def conditions(
        self, *, texts: Sequence[str] = (), actions: Sequence[str] = (), text_weights: str | None = None
    ) -> torch.Tensor:
        """Model conditions for the request: pooled text embeddings (N, E) or action ids (N,)."""
        return self.condition_inputs(texts=texts, actions=actions, text_weights=text_weights)[0]

    def condition_inputs(
        self, *, texts: Sequence[str] = (), actions: Sequence[str] = (), text_weights: str | None = None
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """:meth:`conditions` plus the per-prompt keyword inputs the model also needs: for a cross_attention model
        ``text_tokens`` (N, L, E) and ``text_token_len`` (N,), encoded as the dataset's token features; else none."""
        if self.model_config.is_action_model:
            if texts:
                raise ValueError("this is an action-to-motion model: ask with action names, not texts")
            unknown = [a for a in actions if a not in self.action_classes]
            if unknown:
                raise ValueError(f"unknown action(s) {unknown}; this model knows {self.action_classes}")
            ids = torch.tensor([self.action_classes.index(a) for a in actions], dtype=torch.long, device=self.device)
            return ids, {}
        if actions:
            raise ValueError("this is a text-to-motion model: ask with texts, not action names")
        if self.model_config.conditioning != "cross_attention":
            encoding = self.text_encoder(text_weights).encode(list(texts))
            return torch.as_tensor(encoding.pooled, device=self.device), {}
        entry = self.data["text_encoder"]
        if not entry.get("token_features") or int(entry.get("max_tokens", 0)) < 1:
            raise ValueError(f"{self.checkpoint}: a cross_attention model needs the dataset's token features, but "
                             "its text encoder entry records none (max_tokens)")
        encoding = self.text_encoder(text_weights).encode(list(texts), token_features=True,
                                                          max_tokens=int(entry["max_tokens"]))
        extras = {"text_tokens": torch.as_tensor(encoding.tokens, device=self.device),
                  "text_token_len": torch.as_tensor(encoding.token_lengths, dtype=torch.long, device=self.device)}
        return torch.as_tensor(encoding.pooled, device=self.device), extras


class RunInWeightDtype(torch.nn.Module):
    """A model with bfloat16 or float16 weights, callable as the samplers call the model (``model(x, t, cond,
    lengths, **inputs)``) with their float32 state: it runs under autocast (its matmuls in the weights' dtype, its
    float32 parts, layer norms and time/position tables, in float32) and returns the state's dtype, so the solver or
    sampler integrates as in float32."""

    def __init__(self, model: MotionFlowTransformer) -> None:
        super().__init__()
        self.model = model
        self.train(model.training)

    @property
    def config(self) -> ModelConfig:
        return self.model.config

    def forward(self, x: torch.Tensor, t: torch.Tensor, cond: torch.Tensor, lengths: torch.Tensor | None = None,
                **inputs: Any) -> torch.Tensor:
        with torch.autocast(device_type=x.device.type, dtype=next(self.model.parameters()).dtype):
            out = self.model(x, t, cond, lengths, **inputs)
        return out.to(x.dtype)


def load_trained_model(path: str | Path, *, use_ema: bool = True, device: str | torch.device = "cpu") -> TrainedModel:
    """Load a checkpoint (or a run folder's newest complete one, or an exported folder: :func:`load_pretrained`) for
    sampling/evaluation, EMA weights by default.

    The model is built with the saved (resolved) model config, output width included; a diffusion checkpoint
    also gets its GaussianDiffusion (``TrainedModel.diffusion``) from the saved ``train.diffusion`` preset.
    """
    if is_pretrained_folder(path):  # an exported folder (launch/export.py): one set of weights, no optimizer
        return load_pretrained(path, device=device)
    folder = resolve_checkpoint(path)
    model_state, ema_state, state = ckpt.load_checkpoint(folder)
    extra = state["extra"]
    model_config = ModelConfig(**extra["model_config"])
    objective, preset, diffusion = training_objective(state["config"], model_config, folder)
    model = MotionFlowTransformer(model_config)
    weights = "ema" if use_ema and ema_state is not None else "model"
    model.load_state_dict(ema_state if weights == "ema" else model_state)
    device = torch.device(device)
    model.to(device).eval()
    logger.info("loaded %s weights of %s (step %d)", weights, folder, state["step"])
    window = int(state["config"]["data"]["window"])
    return TrainedModel(model, model_config, folder, int(state["step"]), weights, dict(state["manifest"]), device,
                        window, objective, preset, diffusion)


# ---------------------------------------------------------------------------------------------------------------
# exported folders (pipeline.generation.pretrained writes them)


class PretrainedError(ValueError):
    """An export that cannot be written or an exported folder that cannot be read; names the folder and why."""


def is_pretrained_folder(path: str | Path) -> bool:
    config = Path(path) / CONFIG_FILE
    if not config.is_file():
        return False
    try:
        return json.loads(config.read_text()).get("format") == PRETRAINED_FORMAT
    except (OSError, ValueError):
        return False


def load_pretrained(folder: str | Path, *, device: str | torch.device = "cpu") -> TrainedModel:
    """An exported folder as a :class:`TrainedModel` (what sampling and evaluation use)."""
    folder = Path(folder)
    try:
        config = json.loads((folder / CONFIG_FILE).read_text())
    except (OSError, ValueError) as err:
        raise PretrainedError(f"{folder}: no readable {CONFIG_FILE} ({err}): not an exported model folder") from err
    if config.get("format") != PRETRAINED_FORMAT or config.get("version") != PRETRAINED_VERSION:
        raise PretrainedError(f"{folder / CONFIG_FILE}: format {config.get('format')!r} version "
                              f"{config.get('version')!r}; this code reads {PRETRAINED_FORMAT!r} {PRETRAINED_VERSION}")
    model_config = ModelConfig(**config["model_config"])
    model = MotionFlowTransformer(model_config)
    try:
        model.load_state_dict(safetensors.torch.load_file(str(folder / WEIGHTS_FILE), device="cpu"))
        stats = safetensors.torch.load_file(str(folder / NORMALIZATION_FILE), device="cpu")
    except (OSError, RuntimeError, safetensors.SafetensorError) as err:
        raise PretrainedError(f"{folder}: the weights or normalisation cannot be read ({err})") from err
    train = {"objective": config["objective"], "diffusion": config.get("diffusion_preset") or "flowmdm"}
    objective, preset, diffusion = training_objective({"train": train}, model_config, folder)
    data = dict(config["data"])
    data["normalization"] = {**data.get("normalization", {}), "mean": stats["mean"].tolist(),
                             "std": stats["std"].tolist()}
    device = torch.device(device)
    model.to(device).eval()
    return TrainedModel(model, model_config, folder, int(config["step"]), str(config["weights"]), data, device,
                        int(config["window"]), objective, preset, diffusion)


def training_objective(
    config: Mapping[str, Any], model_config: ModelConfig, folder: Path
) -> tuple[str, str | None, GaussianDiffusion | None]:
    """(objective, diffusion preset, GaussianDiffusion) a checkpoint was trained with, from its saved config.

    Checkpoints written before the objective switch existed record none: they are flow models.
    """
    train = config.get("train", {})
    objective = train.get("objective", "flow")
    if objective == "flow":
        return objective, None, None
    if objective != "diffusion":
        raise ValueError(f"{folder}: unknown train.objective {objective!r} in the checkpoint's config")
    preset = train.get("diffusion", "flowmdm")
    try:
        diffusion = diffusion_from_preset(preset)
    except ValueError as err:
        raise ValueError(f"{folder}: {err}") from err
    expected = diffusion.output_channels_factor * model_config.feature_dim
    if model_config.output_size != expected:
        raise ValueError(f"{folder}: the {preset!r} diffusion preset needs a denoiser with {expected} output channels "
                         f"(learn_sigma={diffusion.learn_sigma}), but the saved model has {model_config.output_size}")
    return objective, preset, diffusion
