"""The training loop: ``Trainer(cfg, dist).fit()``.

One object owns a run: the model (wrapped for the device by :mod:`pipeline.distributed`), its EMA, its optimizer
(AdamW, or Muon with AdamW: :mod:`pipeline.training.optimizers`) with linear warm-up, the self-sharded streaming
loader (never passed through ``accelerator.prepare``), and one versioned resume state saved atomically by
:mod:`pipeline.checkpoint`. ``fit`` reads top to bottom:

    resume → write run files → for each optimizer step: stop requested? → train_step → maybe_log (+ maybe_validate)
    → maybe_save

What rank 0 shows (metrics.jsonl, W&B, TensorBoard, loss.png at the end) is :mod:`pipeline.training.reporting`; the
validation loss every ``train.val_every`` steps (fixed val batches and draws, separate RNG streams, all-reduced
over ranks) is :mod:`pipeline.training.validation`; rank 0's samples every ``train.preview_every`` steps (EMA weights,
private RNG, no collective) are :mod:`pipeline.training.previews`.

Nothing is written into the run folder before the resume decision: rank 0 first checks train.out_dir
(:mod:`pipeline.training.run_folder`), takes its lock (one trainer per folder; a second start is refused, on every
rank, naming the holder; the lock is held until fit() returns or raises), removes unfinished checkpoint folders of
dead processes and resolves train.resume (auto skips, and sets aside, corrupt checkpoints; an explicit older one is
refused while newer ones exist). A save
that fails (a full disk) stops the run on every rank with :class:`CheckpointSaveError`; the same command continues
from the newest complete checkpoint once there is space.

Decisions that every rank must take together (skip a non-finite step, skip the update of a step with no sample,
stop on SIGTERM/SIGINT, stop on bad data that one rank met reading its batch) come from ONE all-reduce (SUM) of a
small flag vector per optimizer step, which also carries the loss and the sample count, so the logged loss is the
mean over all ranks at no extra cost; that and the ``.tolist()`` reading it are the only host syncs outside log
steps. With train.step_sync=deferred (auto on CUDA) not even that: the update is applied or skipped on the device,
and the host reads step k's flags while the GPU runs step k+1's forward and backward (:meth:`Trainer.settle`), and
at once at log, save, validation and preview steps.

Bad records (``data.verify=tolerant``). A record that fails to decode is left out of its batch, and a batch
whose every record was left out is an EMPTY batch, never passed over: every rank takes exactly one planned
batch per micro-step, so all ranks take the same number of steps, stay at the same data position and run the
same collectives. The step's loss is the mean over the samples it really holds, on all ranks: a micro-batch of
n samples weighs n (an empty one 0) and the sum is divided by the step's global sample count, which one extra
all-reduce (tolerant mode only; strict batches are always full) gives before the backward pass. An empty
micro-batch still runs forward and backward, on a zero stand-in with weight 0, so the gradient all-reduce
happens on every rank. A step with no sample on any rank makes no update (see :meth:`Trainer.train_step`).

fp16 (``train.mixed_precision=fp16`` or ``accelerate launch --mixed_precision fp16``): the loss is scaled
before each backward pass and the gradients unscaled once after the last (:mod:`pipeline.training.loss_scaling`), before
they are measured, clipped or applied. A step whose gradients overflow is a normal fp16 event, not bad data: each
rank's overflow flag travels in the same per-step flag all-reduce, so every rank skips that update alike (no
optimizer, scheduler or EMA step), the loss scale backs off on every rank, and the step is counted in
``scaler_skips``, never in ``skipped_steps`` nor against train.nonfinite / train.nonfinite_budget. A non-finite
LOSS (computed before scaling) is still the bad-data case, and wins when both happen (the scale is then left as it
was). The run stops only if overflows push the scale below train.fp16_min_scale. The logged loss, the EMA and the
validation loss never see the scale: the loss is read before scaling and the weights are fp32.

Exact resume: a run killed at any point and resumed with ``train.resume=auto`` continues bit-identically to an
uninterrupted one (weights, EMA, optimizer, scheduler, fp16 loss scale and growth tracker, Python/NumPy/torch
RNGs, the per-rank draw generator, the data position, counters), and metrics.jsonl holds every step once.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import logging
import math
import os
import random
import signal
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import nullcontext
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import torch
import yaml
from tqdm.auto import tqdm

from mfm.compilation import compiled_for_training, compiles  # train.compile's rule, shared with sampling's
from mfm.diffusion import diffusion_from_preset
from mfm.flow import FlowMatchingObjective, MotionGeometry, draw_self_condition_rows, feat_bias_channel_weight
from mfm.flops import TrainingFlops, device_peak, model_flops_utilisation
from mfm.guidance import guided_feature_mask
from mfm.layout import FeatureLayout
from mfm.model import (
    ModelConfig,
    MotionFlowTransformer,
    count_parameters,
    draw_block_drop_mask,
    draw_cond_drop_mask,
    draw_positional_mode,
)
from mfm.shortcut import ShortcutObjective
from mfm.skeleton import get_skeleton
from mfm.solvers import draw_noise, seeded_generators
from pipeline import checkpoint as ckpt
from pipeline.config import ConfigError, TrainConfig, to_dict
from pipeline.data.download_cache import ShardDownloadCache
from pipeline.data.locations import RetryPolicy
from pipeline.data.stages import DataError, batch_widths
from pipeline.data.stream import (
    DataResumeError,
    LoaderOptions,
    Manifest,
    MotionLoader,
    backend_for_format,
    open_manifest,
    verify_shards,
)
from pipeline.distributed import Dist
from pipeline.training.critic import CriticTraining
from pipeline.training.loss_scaling import LossScaler
from pipeline.training.optimizers import build_optimizer
from pipeline.training.previews import Preview, PreviewSampler
from pipeline.training.reporting import PREVIEW_IMAGE_TAG, MetricsSink, require_tensorboard
from pipeline.training.run_folder import (
    RunFolderError,
    RunFolderLock,
    check_run_folder,
    refuse_if_in_use,
    write_run_marker,
)
from pipeline.training.validation import Validator, build_validator, has_val_split
from preprocess.shards import PAIRS_KEY, ManifestError

logger = logging.getLogger(__name__)

EXIT_SIGNAL_BASE = 128  # a run stopped by signal N exits with 128 + N (143 SIGTERM, 130 SIGINT)

T = TypeVar("T")


class NonFiniteLossError(RuntimeError):
    """The loss or gradient norm was not finite on some rank and the policy (or its budget) says stop; or, with
    fp16, gradient overflows pushed the loss scale below train.fp16_min_scale."""


class CheckpointSaveError(RuntimeError):
    """A checkpoint could not be written (e.g. a full disk). The run stops there on every rank rather than train on
    without a way back: the message says what the save needed and where the run can resume from."""


# ---------------------------------------------------------------------------------------------------------------
# Small parts of a run
# ---------------------------------------------------------------------------------------------------------------

# The loader state entries a resume must keep (pipeline.data.stream._PLAN_STATE_KEYS), as the settings that set them.
DATA_STATE_SETTINGS = {
    "batch_size": "data.batch_size", "num_workers": "data.num_workers", "seed": "data.seed",
    "shuffle_buffer": "data.shuffle_buffer", "window": "data.window", "unit_length": "data.unit_length",
    "caption_policy": "data.caption_policy", "dataset_id": "data.manifest", "batching": "data.batching",
    "pad_multiple": "data.pad_multiple", "sort_window_batches": "data.sort_window_batches",
}


def resume_setting_error(path: Path | str, err: DataResumeError) -> ckpt.ResumeSettingError:
    """The loader's refusal of a saved data position, as the one-line error the launcher prints: which setting
    changed, its value in the checkpoint and now, and how to go on."""
    if err.key == "excluded_shards":  # the loader's message already names data.verify and how to go on
        return ckpt.ResumeSettingError(f"cannot resume from {path}: {err}", setting="data.verify", saved=err.saved,
                                       now=err.now)
    setting = DATA_STATE_SETTINGS.get(err.key, err.key)
    return ckpt.ResumeSettingError(
        f"cannot resume from {path}: {setting} was {err.saved!r} in the checkpoint and is {err.now!r} now, and the "
        f"data position (which samples come next) depends on it. Resume with {setting}={err.saved} (the "
        f"checkpoint's value), or start a new run in another train.out_dir to use {setting}={err.now}",
        setting=setting, saved=err.saved, now=err.now)


def model_config_for(manifest: Manifest, requested: ModelConfig, *, learned_variance: bool = False) -> ModelConfig:
    """The model config with the dataset-given sizes filled in: feature dim and text-embedding dim (pooled and
    token-level) from the manifest, for an action model (``num_actions > 0`` in the config) the number of action
    classes, and for a learned-variance diffusion objective (FLAME) twice the output channels."""
    spec = manifest.data["feature_spec"]
    text = manifest.data["text_encoder"]
    changes: dict[str, Any] = {"feature_dim": int(spec["dim"]), "cond_dim": int(text["dim"])}
    if requested.conditioning == "cross_attention":
        changes["token_dim"] = int(text["dim"])
        if requested.null_condition == "empty_caption":
            changes["null_tokens"] = int(text.get("max_tokens") or 0)
    if learned_variance:
        changes["output_dim"] = 2 * int(spec["dim"])
    if requested.num_actions > 0:
        if not manifest.action_classes:
            raise ValueError(f"model.num_actions > 0 asks for an action model, but {manifest.location} has no action classes")
        changes["num_actions"] = len(manifest.action_classes)
    return dataclasses.replace(requested, **changes)


def dataset_identity(manifest: Manifest) -> dict[str, Any]:
    """What a checkpoint records of its dataset (and what sampling needs of it: pipeline.generation.inference)."""
    return {"dataset_id": manifest.dataset_id, "location": str(manifest.location),
            "feature_spec": manifest.data["feature_spec"], "text_encoder": manifest.data["text_encoder"],
            "action_classes": list(manifest.action_classes), "normalization": manifest.data["normalization"],
            "train_lengths": list(manifest.split("train")["lengths"])}


def fill_null_condition(model: MotionFlowTransformer, manifest: Manifest) -> None:
    """FLAME's null condition (model.null_condition=empty_caption): the dataset's own text encoder applied to "",
    stored in the model before training (and so in every checkpoint). A CLIP dataset's encoder is rebuilt from the
    weights its build recorded."""
    from mfm.text import encode_empty_caption

    entry = manifest.data["text_encoder"]
    weights = manifest.data.get("builder", {}).get("options", {}).get("text_weights")
    try:
        empty = encode_empty_caption(entry, weights=weights)
    except (ValueError, OSError, RuntimeError) as err:
        raise ValueError(f"model.null_condition=empty_caption encodes the empty caption with the dataset's text "
                         f"encoder {entry.get('id')!r}, which could not be rebuilt: {err}") from err
    tokens = None if empty.tokens is None else torch.from_numpy(empty.tokens[0])
    token_len = None if empty.token_lengths is None else int(empty.token_lengths[0])
    model.set_null_condition(torch.from_numpy(empty.pooled[0]), tokens, token_len)


class EMA:
    """Exponential moving average of the weights (``optim.ema_*``), updated after every ``every``-th optimizer step:
    after steps k <= ``start`` a copy of the weights, later ``shadow ← decay·shadow + (1 − decay)·weights`` with the
    usual warm-up ``decay = min(decay, (1 + n) / (10 + n))`` (n: updates so far) unless ``warmup`` is off.

    FLAME (``diffusion_hml3d.yaml``: 8–10, ``diffusion_module.py``: 72–76 and 306–307): every 10 steps, a copy up to
    step 100, then decay 0.99 without a warm-up, i.e. ``EMA(model, 0.99, every=10, start=100, warmup=False)``.
    The schedule depends on the step and these settings only, so a resumed run (shadow and ``num_updates`` restored)
    goes on exactly as an uninterrupted one."""

    def __init__(self, model: torch.nn.Module, decay: float, *, every: int = 1, start: int = 0,
                 warmup: bool = True) -> None:
        self.decay = decay
        self.every = every
        self.start = start
        self.warmup = warmup
        self.num_updates = 0
        self.shadow = {name: p.detach().clone().float() for name, p in model.state_dict().items()}

    def after_step(self, model: torch.nn.Module, step: int, applied: torch.Tensor | None = None) -> bool:
        """Called after optimizer step ``step`` (1-based) updated ``model``'s weights: updates the EMA when due, and
        says whether it was due. ``applied``: a boolean device tensor, False when the step's update was skipped on
        the device (train.step_sync=deferred), which leaves the average as it was (its update count is the
        caller's to take back)."""
        if step % self.every:
            return False
        self.update(model, copy=step <= self.start, applied=applied)
        return True

    def next_decay(self) -> float:
        """Counts one more update and returns its decay (with the warm-up, if on)."""
        self.num_updates += 1
        return min(self.decay, (1 + self.num_updates) / (10 + self.num_updates)) if self.warmup else self.decay

    @torch.no_grad()
    def update(self, model: torch.nn.Module, *, copy: bool = False, applied: torch.Tensor | None = None) -> None:
        """One EMA update: the average (``copy=False``) or a copy of the weights; none where ``applied`` (a
        boolean device tensor, see :meth:`after_step`) is False."""
        decay = self.next_decay()
        averaged_shadows, averaged_values = [], []
        for name, value in model.state_dict().items():
            if value.dtype.is_floating_point and not copy:
                averaged_shadows.append(self.shadow[name])
                averaged_values.append(value.detach().float())
            elif applied is None:
                self.shadow[name].copy_(value)
            else:
                self.shadow[name].copy_(torch.where(applied, value, self.shadow[name]))
        if not averaged_shadows:
            return
        if applied is None:
            # One multi-tensor launch instead of one lerp per tensor: on a GPU the per-tensor loop's ~150 launches
            # cost the step more than the arithmetic (same result: the same lerp on every element).
            torch._foreach_lerp_(averaged_shadows, averaged_values, 1.0 - decay)
            return
        # The weight as a device tensor, 0 for a skipped update: shadow + w·(weights − shadow) in three multi-tensor
        # launches (a lerp with a tensor weight falls back to one launch per tensor on CUDA). It rounds unlike lerp's
        # fused multiply-add (the last bits of the average differ from every_step's) and costs a temporary copy of
        # the weights: on a CPU 29 ms against lerp's 3.8 ms at 17.8 M weights, where auto never defers.
        weight = applied.float() * (1.0 - decay)
        steps = torch._foreach_sub(averaged_values, averaged_shadows)
        torch._foreach_mul_(steps, weight)
        torch._foreach_add_(averaged_shadows, steps)

    @torch.no_grad()
    def copy_weights(self, model: torch.nn.Module) -> None:
        """The average becomes a copy of ``model``'s weights (train.init_from), its update count unchanged."""
        for name, value in model.state_dict().items():
            self.shadow[name].copy_(value)

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {name: t.detach().cpu() for name, t in self.shadow.items()}

    def load_state_dict(self, state: Mapping[str, torch.Tensor], num_updates: int) -> None:
        missing = set(self.shadow) ^ set(state)
        if missing:
            raise KeyError(f"EMA state does not match the model: differing keys {sorted(missing)[:5]}")
        for name, value in state.items():
            self.shadow[name].copy_(value)
        self.num_updates = num_updates


def lr_lambda(warmup_steps: int, schedule: str = "constant", total_steps: int = 0, min_ratio: float = 0.0,
              decay_fraction: float = 1.0):
    """LR multiplier per optimizer step: linear warm-up from ~0 to 1 over ``warmup_steps``, then constant (MFM: a
    constant 1e-4, no warm-up), a cosine from 1 down to ``min_ratio`` at ``total_steps``, or 'wsd': 1 until the
    last ``decay_fraction`` of the steps after warm-up, then linear down to ``min_ratio`` at ``total_steps``."""
    decay_steps = (total_steps - warmup_steps) * (decay_fraction if schedule == "wsd" else 1.0)

    def multiplier(step: int) -> float:
        if step < warmup_steps:
            return (step + 1) / warmup_steps
        if schedule == "constant" or total_steps <= warmup_steps:
            return 1.0
        progress = min(1.0, max(0.0, (step - (total_steps - decay_steps)) / decay_steps))
        if schedule == "wsd":
            return 1.0 - (1.0 - min_ratio) * progress
        return min_ratio + (1.0 - min_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress))

    return multiplier


class StopSignal:
    """Remembers SIGTERM/SIGINT instead of dying mid-step; the loop checks it at step boundaries, all ranks agree
    through the step's flag all-reduce, and the run stops after writing one complete checkpoint.

    A second signal means "now": the previous handlers come back and the signal is delivered to them
    (KeyboardInterrupt for SIGINT, death for SIGTERM), e.g. when a data read hangs. DataLoader workers forked
    after :meth:`install` inherit the handler; there it ignores the signal (their rank process shuts them down).
    """

    SIGNALS = (signal.SIGTERM, signal.SIGINT)

    def __init__(self) -> None:
        self.signum = 0
        self._previous: dict[int, Any] = {}
        self._pid = os.getpid()

    def install(self) -> None:
        self._pid = os.getpid()
        for signum in self.SIGNALS:
            self._previous[signum] = signal.signal(signum, self._handle)

    def _handle(self, signum: int, frame: Any) -> None:
        if os.getpid() != self._pid:
            return
        if not self.signum:
            self.signum = signum
            logger.warning("received %s: stopping after this step with a checkpoint (send it again to stop at once)",
                           signal.Signals(signum).name)
            return
        previous = self._previous.get(signum, signal.SIG_DFL)
        self.restore()
        if callable(previous):
            previous(signum, frame)
        elif signum == signal.SIGINT:
            # SIGINT was ignored (a job started in the background by a non-interactive shell) or default before
            # install: the user still sent it twice, so stop now, through Python's unwinding.
            raise KeyboardInterrupt
        else:
            signal.signal(signum, signal.SIG_DFL)
            signal.raise_signal(signum)

    def flags(self) -> list[float]:
        """One slot per handled signal (1.0 if it was received): summed over ranks, any non-zero slot stops all."""
        return [float(self.signum == s) for s in self.SIGNALS]

    @classmethod
    def from_flags(cls, summed: list[float]) -> int:
        """The signal every rank stops for (SIGTERM first), from the rank-summed :meth:`flags`; 0 for none."""
        return next((int(s) for s, count in zip(cls.SIGNALS, summed) if count > 0), 0)

    def restore(self) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()


def seed_everything(seed: int) -> None:
    """Seed Python's, NumPy's (legacy global) and torch's RNGs (all devices): the states a checkpoint captures
    then start from the same point in every run with this seed, not from the OS entropy of each process."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


@dataclasses.dataclass
class Draws:
    """Injected random numbers of one flow-matching micro-batch (tests slice a global batch's draws across ranks):
    flow time, initial noise, which conditions are dropped and, for a BPE model, which samples use relative
    positions. Normal training draws them from the trainer's per-rank generator instead."""

    t: torch.Tensor  # (B,)
    x0: torch.Tensor  # (B, T, D)
    cond_mask: torch.Tensor  # (B,) bool
    positional_mode: torch.Tensor | None = None  # (B,) bool, True = relative (BPE models only)
    self_condition_rows: torch.Tensor | None = None  # (B,) bool, True = fed the estimate (self-conditioned models)

    def to(self, device: torch.device) -> "Draws":
        mode = None if self.positional_mode is None else self.positional_mode.to(device)
        rows = None if self.self_condition_rows is None else self.self_condition_rows.to(device)
        return Draws(self.t.to(device), self.x0.to(device), self.cond_mask.to(device), mode, rows)


def draw_for_batch(batch: Mapping[str, Any], cond_drop_prob: float, generator: torch.Generator,
                   self_condition_prob: float = 0.0) -> Draws:
    """Flow-matching draws for ``batch`` from ``generator`` (t, x0, cond_mask, and the self-conditioned rows when
    ``self_condition_prob`` > 0), for injecting with train_step."""
    features = batch["features"]
    b = features.shape[0]
    device = generator.device
    t = torch.rand(b, generator=generator, device=device)
    x0 = torch.randn(features.shape, generator=generator, device=device)
    cond_mask = draw_cond_drop_mask(b, cond_drop_prob, generator, device)
    rows = draw_self_condition_rows(b, self_condition_prob, generator, device) if self_condition_prob > 0 else None
    return Draws(t, x0, cond_mask, self_condition_rows=rows)


def recorded_noise(seeds: torch.Tensor, lengths: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """``train.flow_noise=recorded``: each record's noise x0 as the teacher drew it, ``mfm.solvers.draw_noise`` from a
    generator seeded with its ``noise_seed`` over its ``lengths`` valid frames (zero beyond), shaped like ``like``
    (B, T, D). A function of the record alone, so exact resume and any world size hold as for drawn noise."""
    return draw_noise(tuple(like.shape), seeded_generators(seeds.tolist()), lengths=lengths.cpu(),
                      device=like.device, dtype=like.dtype)


def check_noise_source(cfg: TrainConfig, manifest: Manifest) -> None:
    """train.flow_noise=recorded needs a distillation pair set whose training clips are used whole: every record
    carries its noise seed (the manifest's ``pairs`` section says so) and none is longer than data.window (a crop
    would separate the motion from its noise; data.unit_length=1 is checked with the config)."""
    if cfg.train.flow_noise != "recorded":
        return
    if PAIRS_KEY not in manifest.data:
        raise ConfigError(f"train.flow_noise=recorded trains on the noise each record was made from, but "
                          f"{manifest.location} is not a distillation pair set (no {PAIRS_KEY!r} section; make one "
                          "with launch/distill.py)")
    longest = max(manifest.split("train")["lengths"], default=0)
    if longest > cfg.data.window:
        raise ConfigError(f"train.flow_noise=recorded: {manifest.location} holds a {longest}-frame pair, longer than "
                          f"data.window={cfg.data.window}: the crop would cut it away from its noise; give "
                          f"data.window={longest}")


def load_initial_weights(model: torch.nn.Module, checkpoint: str) -> None:
    """train.init_from: ``model`` takes the weights of ``checkpoint`` (a step folder, or a run folder's newest complete
    one): its EMA, else its raw weights. A checkpoint of another architecture is a ConfigError naming it."""
    try:
        folder = ckpt.resolve_checkpoint(checkpoint)
    except FileNotFoundError as err:
        raise ConfigError(f"train.init_from: {err}") from None
    model_state, ema_state, _ = ckpt.load_checkpoint(folder)
    try:
        # A shortcut model may start from a flow model: its step-size embedding (zero at the start) is not there.
        missing, unexpected = model.load_state_dict(ema_state if ema_state is not None else model_state, strict=False)
        missing = [key for key in missing if not key.startswith("step_size_embedding.")]
        if missing or unexpected:
            raise RuntimeError(f"Error(s) in loading state_dict:\n\tmissing keys {missing[:3]}, unexpected keys "
                               f"{unexpected[:3]}")
    except RuntimeError as err:
        first = str(err).strip().splitlines()
        raise ConfigError(f"train.init_from={folder}: its weights do not fit this run's model "
                          f"({first[1].strip() if len(first) > 1 else first[0]}); give the teacher's model settings"
                          ) from None


def build_objective(cfg: TrainConfig, manifest: Manifest, *, trajectory_term: bool = True,
                    self_conditioning: bool = True):
    """The training objective the config names (both have the same ``loss(...)`` call). ``trajectory_term=False``:
    the flow objective without train.flow_trajectory_weight's term (before train.flow_trajectory_start_step);
    ``self_conditioning=False``: without the estimate pass of model.self_condition_prob (before
    train.self_condition_start_step)."""
    if cfg.train.objective == "flow":
        geometry = None
        skeleton = get_skeleton(manifest.data["feature_spec"]["skeleton"])
        trajectory_weight = cfg.train.flow_trajectory_weight if trajectory_term else 0.0
        if cfg.train.flow_bone_weight > 0 or trajectory_weight > 0 or cfg.train.flow_foot_contact_weight > 0:
            normalization = manifest.data["normalization"]
            geometry = MotionGeometry.from_dataset(normalization["mean"], normalization["std"], skeleton)
        channel_weight = (None if cfg.train.flow_feat_bias == 1.0
                          else feat_bias_channel_weight(FeatureLayout(skeleton), cfg.train.flow_feat_bias))
        flow = FlowMatchingObjective(loss_space=cfg.train.flow_loss, temporal_weight=cfg.train.flow_temporal_weight,
                                     bone_weight=cfg.train.flow_bone_weight,
                                     bone_target=cfg.train.flow_bone_target,
                                     trajectory_weight=trajectory_weight,
                                     trajectory_min_t=cfg.train.flow_trajectory_min_t,
                                     trajectory_huber=cfg.train.flow_trajectory_huber,
                                     foot_contact_weight=cfg.train.flow_foot_contact_weight,
                                     root_mean_weight=cfg.train.flow_root_mean_weight,
                                     input_perturbation=cfg.train.flow_input_perturbation,
                                     self_condition_prob=cfg.model.self_condition_prob if self_conditioning else 0.0,
                                     geometry=geometry,
                                     time_sampling=cfg.train.flow_time_sampling, time_loc=cfg.train.flow_time_loc,
                                     time_scale=cfg.train.flow_time_scale,
                                     time_grid_steps=cfg.train.flow_time_grid_steps,
                                     grid_inputs=cfg.train.flow_grid_inputs,
                                     time_grid_times=(cfg.model.sampling_times
                                                      if cfg.train.flow_time_sampling == "grid" else None),
                                     terms_weighting=cfg.train.flow_terms_weighting,
                                     velocity_weight_cap=cfg.train.flow_velocity_weight_cap,
                                     channel_weight=channel_weight)
        if cfg.model.shortcut_levels == 0:
            return flow
        return ShortcutObjective(flow=flow, levels=cfg.model.shortcut_levels,
                                 bootstrap_fraction=cfg.train.shortcut_fraction, guidance=cfg.train.shortcut_guidance,
                                 conditional_channels=guided_feature_mask(cfg.model.guided_features, skeleton))
    return diffusion_from_preset(cfg.train.diffusion)


# ---------------------------------------------------------------------------------------------------------------
# The trainer
# ---------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class StepResult:
    """A step's outcome as the host read it (:meth:`Trainer.train_step`, :meth:`Trainer.settle`)."""
    step: int  # 1-based: the step's number (Trainer.step after it)
    loss: float  # mean loss over the step's samples on all ranks (NaN when some rank's was not finite)
    grad_norm: torch.Tensor  # global gradient norm before clipping (device tensor: read it on log steps only)
    skipped: bool  # the update was skipped on every rank (non-finite loss or gradient norm on some rank)
    stop_signal: int  # the signal number some rank received before this step's end (0: none)
    empty: bool = False  # no rank had a sample (tolerant mode: every record skipped): no update, loss meaningless
    overflow: bool = False  # fp16: the scaled gradients overflowed on some rank: update skipped, scale lowered


def resolve_step_sync(setting: str, device: torch.device, mixed_precision: str, optimizer: str = "adamw") -> bool:
    """Whether train.step_sync defers the host's reading of each step's flags (see the option): auto defers on
    CUDA without fp16 with AdamW (optim.optimizer=muon has no on-device skip). A deferred run under fp16 (the
    launcher's ``--mixed_precision fp16``) is refused."""
    if setting == "auto":
        return device.type == "cuda" and mixed_precision != "fp16" and optimizer == "adamw"
    if setting == "deferred" and mixed_precision == "fp16":
        raise ConfigError("train.step_sync=deferred does not go with fp16 (here from the launcher): fp16's loss scale "
                          "is decided on the host every step; use bf16, or train.step_sync=every_step")
    return setting == "deferred"


def to_device(values: list[float], device: torch.device) -> torch.Tensor:
    """A float32 tensor of host values on ``device``, copied without making the host wait for the device's queue
    (a pageable host tensor's ``.to(cuda)`` waits for all queued work: the sync train.step_sync=deferred avoids)."""
    host = torch.tensor(values, dtype=torch.float32)
    if device.type != "cuda":
        return host.to(device)
    return host.pin_memory().to(device, non_blocking=True)


class PendingStep:
    """A step whose update was queued with its skip decided on the device (train.step_sync=deferred): its
    all-reduced flags travel to the host while the host queues the next step; :meth:`read` waits for them."""

    def __init__(self, step: int, flags: torch.Tensor, grad_norm: torch.Tensor, ema_updated: bool) -> None:
        self.step, self.grad_norm, self.ema_updated = step, grad_norm, ema_updated
        if flags.device.type == "cuda":
            self._host = torch.empty(flags.shape, dtype=flags.dtype, pin_memory=True)
            self._host.copy_(flags, non_blocking=True)
            self._copied: torch.cuda.Event | None = torch.cuda.Event()
            self._copied.record()
        else:
            self._host, self._copied = flags.detach().clone(), None

    def read(self) -> list[float]:
        if self._copied is not None:
            self._copied.synchronize()
        return self._host.tolist()


class Trainer:
    """A training run. Build with the resolved config and this process's :class:`Dist`; call :meth:`fit`."""

    def __init__(self, cfg: TrainConfig, dist: Dist) -> None:
        self.cfg = cfg
        self.dist = dist
        self.out_dir = Path(cfg.train.out_dir)
        self.ckpt_root = ckpt.checkpoints_dir(self.out_dir)
        # Refuse an unusable train.out_dir (or train.tensorboard without its package) before the slow part
        # (verifying every shard); fit() checks the folder again.
        self._decided_by_main(self._check_before_start)

        self.retry = RetryPolicy(cfg.data.retries, cfg.data.retry_backoff_s)  # transient errors of remote data
        self.manifest = open_manifest(cfg.data.manifest, retry=self.retry,
                                      allow_external_shards=cfg.data.allow_external_shards)
        bad_shards, self.shard_report = self._verified_bad_shards("train")
        check_noise_source(cfg, self.manifest)
        self.objective = build_objective(cfg, self.manifest)
        # train.flow_trajectory_start_step / train.self_condition_start_step: the same objective without the term
        # or the estimate pass for the first updates (self.objective from when both have started). Neither draws
        # before it starts, so the run up to then is the run without it.
        self.objectives_before_start = {
            phase: build_objective(cfg, self.manifest, trajectory_term=phase[0], self_conditioning=phase[1])
            for phase in {self._objective_phase(step) for step in self._phase_starts()} if not all(phase)}
        self.model_config = model_config_for(
            self.manifest, cfg.model, learned_variance=getattr(self.objective, "learn_sigma", False))

        # identical initial weights on every rank
        seed_everything(cfg.train.seed if cfg.train.init_seed is None else cfg.train.init_seed)
        model = MotionFlowTransformer(self.model_config)
        if self.model_config.null_condition == "empty_caption":
            fill_null_condition(model, self.manifest)
        self.num_parameters = count_parameters(model)
        self.ema = EMA(model, cfg.optim.ema_decay, every=cfg.optim.ema_every, start=cfg.optim.ema_start,
                       warmup=cfg.optim.ema_warmup)
        # train.step_sync=deferred needs fused AdamW (it takes the skip as found_inf, on the device) on every device
        self.defers_step_sync = resolve_step_sync(cfg.train.step_sync, dist.device, dist.mixed_precision,
                                                  cfg.optim.optimizer)
        self._pending: PendingStep | None = None  # deferred: the step whose flags the host has not read yet
        fused = dist.device.type == "cuda" or self.defers_step_sync
        optimizer = build_optimizer(model, cfg.optim, fused)
        # train.critic_weight > 0: the critic beside the model (pipeline.training.critic), made after the model so
        # the model's initial weights are those of the run without it
        self.critic = (CriticTraining(cfg.train, self.model_config, dist, fused=fused)
                       if cfg.train.critic_weight > 0 else None)
        scheduler = torch.optim.lr_scheduler.LambdaLR(
            optimizer,
            lr_lambda(cfg.optim.warmup_steps, cfg.optim.schedule, cfg.train.max_steps, cfg.optim.min_lr_ratio,
                      cfg.optim.decay_fraction),
        )
        if compiles(cfg.train.compile, dist.device):
            model = compiled_for_training(model, cfg.train.compile_mode, batch_widths=(
                batch_widths(cfg.data.window, cfg.data.pad_multiple) if cfg.data.batching == "length_aware" else None))
        self.model, self.optimizer, self.scheduler = dist.prepare(model, optimizer, scheduler)
        self.training_flops = TrainingFlops(dist.unwrap(self.model))  # the log's model FLOPs and MFU
        self.device_peak = device_peak(dist.device)
        self.ema.shadow = {k: v.to(dist.device) for k, v in self.ema.shadow.items()}
        # fp16's dynamic loss scale (the identity for no/bf16); its state is part of the resume state
        self.loss_scaler = LossScaler(dist.device, enabled=dist.mixed_precision == "fp16",
                                      init_scale=cfg.train.fp16_init_scale,
                                      growth_interval=cfg.train.fp16_growth_interval)

        self.loader = MotionLoader(
            self.manifest,
            "train",
            LoaderOptions(
                batch_size=cfg.data.batch_size,
                num_workers=cfg.data.num_workers,
                seed=cfg.data.seed,
                window=cfg.data.window,
                unit_length=cfg.data.unit_length,
                shuffle_buffer=cfg.data.shuffle_buffer,
                caption_policy=cfg.data.caption_policy,
                batching=cfg.data.batching,
                pad_multiple=cfg.data.pad_multiple,
                sort_window_batches=cfg.data.sort_window_batches,
                backend=backend_for_format(cfg.data.format),
                # tolerant: skip (count, log) records that fail to decode, and on a resume whose excluded shards
                # changed finish the checkpoint's epoch with its plan (pipeline.data.stream, "Tolerant mode at run time")
                tolerate_bad_data=cfg.data.verify == "tolerant",
                # remote shards are hashed again as they stream: one changed since verification is never trained on
                check_remote_bytes=cfg.data.verify != "off",
                retries=cfg.data.retries,
                retry_backoff_s=cfg.data.retry_backoff_s,
                # remote shards downloaded once into data.cache_dir (verified), read from there every later epoch
                cache_dir=cfg.data.cache_dir,
                cache_max_bytes=cfg.data.cache_max_bytes,
                # page-locked batches (workers > 0): their copy to a GPU is queued, the host does not wait for it
                pin_memory=dist.device.type == "cuda",
            ),
            rank=dist.rank,
            world_size=dist.world_size,
            exclude_shards=bad_shards,
        )
        # Per-rank stream of loss draws (t, noise, dropped conditions); its state is part of the resume state.
        self.generator = torch.Generator(device=dist.device).manual_seed(cfg.train.seed * 1_000_003 + dist.rank)
        self.step = 0
        self.samples_seen = 0
        self.skipped_steps = 0
        self.consecutive_skips = 0
        self.empty_steps = 0  # steps with no sample on any rank (tolerant mode): stepped through, no update
        self.scaler_skips = 0  # fp16: steps whose update was skipped for a gradient overflow (not bad data)
        self.stop_signal = StopSignal()
        self._run_lock: RunFolderLock | None = None  # rank 0's hold of train.out_dir, from resume() to fit()'s end
        self._data_error: DataError | None = None  # bad data this rank met reading the current step's batches
        self._last_saved_step = -1
        self._validator: Validator | None = None  # built by the first validate() (train.val_every)
        self._validator_built = False
        self._previews = self._build_previews()  # rank 0 with train.preview_every > 0; None elsewhere

    # -- setup ------------------------------------------------------------------------------------------------

    def _check_before_start(self) -> None:
        check_run_folder(self.out_dir)
        refuse_if_in_use(self.out_dir)  # a second trainer on the folder: refused now, not after verifying the data
        require_tensorboard(self.cfg.train.tensorboard)

    def _verified_bad_shards(self, split: str) -> tuple[tuple[str, ...], dict[str, Any]]:
        """Rank 0 checks every shard of ``split`` against the manifest (strict: raises naming the shard, before
        any training); the list of bad shards it found is broadcast so every rank drops the same ones. Returns
        that list and the report (for shard_report.json)."""
        mode = self.cfg.data.verify
        backend = backend_for_format(self.cfg.data.format)
        downloads = (ShardDownloadCache(self.cfg.data.cache_dir, self.cfg.data.cache_max_bytes)
                     if self.cfg.data.cache_dir is not None else None)
        report = self._decided_by_main(
            lambda: verify_shards(self.manifest, split, mode=mode, backend=backend, retry=self.retry,
                                  downloads=downloads))
        bad = tuple(report.bad_paths)
        if bad:
            self.dist.log0(
                "tolerant shard verification: skipping %d bad shard(s) of the %s split (%d samples): %s",
                len(bad), split, report.samples_lost, ", ".join(bad), level=logging.WARNING,
            )
        return bad, report.as_dict()

    # -- one optimizer step -----------------------------------------------------------------------------------

    def _condition(self, batch: Mapping[str, Any]) -> torch.Tensor:
        if self.model_config.is_action_model:
            return batch["action"].to(self.dist.device, non_blocking=True)
        return batch["text_emb"].to(self.dist.device, non_blocking=True)

    def _micro_batch_loss(self, batch: Mapping[str, Any], draws: Draws | None,
                          generator: torch.Generator | None = None, model: Callable[..., Any] | None = None,
                          critic_inputs: list[tuple[torch.Tensor, ...]] | None = None) -> torch.Tensor:
        """The objective's loss on one micro-batch. Draw order from the per-rank generator (replayed exactly on
        resume; ``generator`` replaces it): dropped conditions, the BPE positional mode (BPE models), the skipped
        blocks (model.layer_dropout > 0, in training mode), then the objective's own draws. ``model`` replaces the prepared training model (validation).
        ``critic_inputs`` (a list, with train.critic_weight > 0): the loss adds the critic's term on the motion the
        pass leads to, and the list receives (batch motions, that motion detached, conditions, frame mask) for the
        critic's own update (:meth:`train_step`). Draws nothing more."""
        device, config = self.dist.device, self.model_config
        generator = self.generator if generator is None else generator
        features = batch["features"].to(device, non_blocking=True)
        lengths = batch["lengths"].to(device, non_blocking=True)
        model_kwargs: dict[str, Any] = {}
        if config.conditioning == "cross_attention":
            if "text_tokens" not in batch:
                raise ValueError("model.conditioning=cross_attention needs token features: build the dataset with "
                                 "--token-features")
            model_kwargs["text_tokens"] = batch["text_tokens"].to(device, non_blocking=True)
            model_kwargs["text_token_len"] = batch["text_token_len"].to(device, non_blocking=True)
        overrides: dict[str, torch.Tensor] = {}
        if draws is None:
            cond_mask = draw_cond_drop_mask(features.shape[0], config.cond_drop_prob, generator, device)
            if config.positional == "bpe":
                model_kwargs["positional_mode"] = draw_positional_mode(
                    features.shape[0], config.bpe_train_relative_prob, generator).to(device)
            if config.layer_dropout > 0 and (self.model if model is None else model).training:
                # From this generator, not the global RNG: replayed exactly on resume like the other draws.
                model_kwargs["block_drop_mask"] = draw_block_drop_mask(
                    config.num_layers, config.blocks_per_layer, config.layer_dropout, generator, device)
            if self.cfg.train.flow_noise == "recorded":  # reflow: the noise the teacher integrated, from its seed
                # the host's lengths: the device's would be read back, making the host wait
                overrides["x0"] = recorded_noise(batch["noise_seed"], batch["lengths"], features)
        else:
            draws = draws.to(device)
            cond_mask, overrides = draws.cond_mask, {"t": draws.t, "x0": draws.x0}
            if draws.self_condition_rows is not None:
                overrides["self_condition_rows"] = draws.self_condition_rows
            if draws.positional_mode is not None:
                model_kwargs["positional_mode"] = draws.positional_mode
        phase = self._objective_phase(self.step)  # self.step: the updates before this one
        objective = self.objective if all(phase) else self.objectives_before_start[phase]
        judged = self.critic is not None and critic_inputs is not None
        if judged:
            overrides["estimate"] = True
        cond = self._condition(batch)
        loss, info = objective.loss(self.model if model is None else model, features, cond,
                                    lengths, generator=generator,
                                    cond_mask=cond_mask, model_kwargs=model_kwargs, **overrides)
        if judged:
            loss = loss + self.critic.student_loss(info["x1_hat"], cond, info["frame_mask"])
            critic_inputs.append((features, info["x1_hat"].detach(), cond, info["frame_mask"]))
        return loss

    def _phase_starts(self) -> list[int]:
        """The steps at which the objective changes (0 first)."""
        if self.cfg.train.objective != "flow":
            return [0]
        return [0, self.cfg.train.flow_trajectory_start_step, self.cfg.train.self_condition_start_step]

    def _objective_phase(self, step: int) -> tuple[bool, bool]:
        """(trajectory term on, estimate pass on) for the update after ``step`` updates."""
        if self.cfg.train.objective != "flow":
            return (True, True)
        return (step >= self.cfg.train.flow_trajectory_start_step, step >= self.cfg.train.self_condition_start_step)

    def _stand_in(self, empty: Mapping[str, Any]) -> dict[str, Any]:
        """What an empty micro-batch runs through the model (with weight 0) so that its rank takes part in the
        gradient all-reduce: ``data.batch_size`` zero motions of full length with the empty batch's trailing
        sizes (the usual shapes, so a compiled model is not recompiled), action 0, one text token each."""
        rows = self.cfg.data.batch_size
        window = empty["features"].shape[1]
        batch: dict[str, Any] = {
            "features": empty["features"].new_zeros((rows, *empty["features"].shape[1:])),
            "lengths": torch.full((rows,), window, dtype=torch.int64),
            "text_emb": empty["text_emb"].new_zeros((rows, *empty["text_emb"].shape[1:])),
            "action": torch.zeros(rows, dtype=torch.int64),
            "ids": [],
        }
        if "noise_seed" in empty:
            batch["noise_seed"] = torch.zeros(rows, dtype=torch.int64)
        if "text_tokens" in empty:
            batch["text_tokens"] = empty["text_tokens"].new_zeros((rows, *empty["text_tokens"].shape[1:]))
            batch["text_token_len"] = torch.ones(rows, dtype=torch.int64)
        return batch

    def _stand_in_loss(self, empty: Mapping[str, Any]) -> torch.Tensor:
        """The loss of :meth:`_stand_in`, drawn from a fixed generator with the global RNGs forked: an empty
        micro-batch takes no draw from this rank's streams, so they do not depend on where records went bad
        (and a resumed run replays them exactly all the same)."""
        device = self.dist.device
        generator = torch.Generator(device=device).manual_seed(0)
        with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
            return self._micro_batch_loss(self._stand_in(empty), None, generator)

    def _micro_batch_weights(self, counts: list[int]) -> list[float | torch.Tensor]:
        """Weight of each micro-batch's (per-sample mean) loss, such that the rank-averaged gradient is the mean
        over the step's samples on all ranks: ``n_i · accum · world_size / N`` for a micro-batch of ``n_i`` of
        the step's ``N`` samples (0 for an empty one; exactly 1 for full batches). Only tolerant mode can have
        short or empty batches; there ``N`` comes from one all-reduce (a device tensor: no host sync)."""
        if not self.loader.options.tolerate_bad_data:
            return [1.0] * len(counts)
        device = self.dist.device
        scale = len(counts) * self.dist.world_size
        total = self.dist.all_reduce_sum(to_device([float(sum(counts))], device)[0]).clamp_min(1.0)
        return [torch.full((), float(n * scale), device=device) / total if n else 0.0 for n in counts]

    def train_step(self, micro_batches: list[Mapping[str, Any]], draws: list[Draws] | None = None
                   ) -> list[StepResult]:
        """Forward/backward over the micro-batches (gradient accumulation), clip, and one optimizer + EMA update —
        unless the loss or gradient norm is non-finite on ANY rank, in which case every rank skips the update.
        ``draws`` replaces the generator's draws (tests slice a global batch's draws across ranks).

        Empty micro-batches (tolerant mode: every record of the batch was skipped) are stepped through, never
        passed over: the loss is the mean over the step's samples on all ranks (each micro-batch weighted by its
        sample count, :meth:`_micro_batch_weights`), an empty one weighs 0 and still runs forward and backward on
        a stand-in (:meth:`_stand_in_loss`, no draw from this rank's generator), so the gradient all-reduce and
        every other collective happen on every rank, and no 0/0 arises. If the step holds no sample on ANY rank
        (at one rank without accumulation: every empty batch), there is nothing to learn from:
        every rank skips the update as for a non-finite step (no optimizer, scheduler or EMA step: the LR
        schedule counts updates), but the step counts (``Trainer.step`` advances: train.max_steps counts the
        planned batches consumed) and is counted in ``empty_steps``, not in ``skipped_steps``; the non-finite
        policy and budget ignore it. Every part of this is a function of the data, so exact resume holds.

        fp16: each backward runs on the scaled loss; the gradients are unscaled once, before the norm and the
        clipping. Non-finite gradients under a finite loss on ANY rank are an overflow (``StepResult.overflow``):
        every rank skips the update and lowers the scale alike (the flag is in the step's one all-reduce). Order
        of precedence: a non-finite loss (``skipped``), then no sample (``empty``), then an overflow.

        Returns the outcomes the host read during this call: with train.step_sync=every_step, [this step's]; with
        deferred, [the previous step's] (or [] at the first step or after :meth:`settle`): this step's update is
        queued with its skip decided on the device, and :meth:`settle` or the next call reads it
        (:meth:`_queue_update`)."""
        model, device = self.model, self.dist.device
        accum = len(micro_batches)
        weights = self._micro_batch_weights([len(batch["ids"]) for batch in micro_batches])
        loss_sum = torch.zeros((), device=device)
        for i, batch in enumerate(micro_batches):
            sync = i == accum - 1
            critic_inputs: list[tuple[torch.Tensor, ...]] | None = [] if self.critic is not None else None
            with nullcontext() if sync else self.dist.no_sync(model):
                if batch["ids"]:
                    loss = self._micro_batch_loss(batch, None if draws is None else draws[i],
                                                  critic_inputs=critic_inputs)
                else:
                    loss = self._stand_in_loss(batch)
                weighted = loss if isinstance(weights[i], float) and weights[i] == 1.0 else loss * weights[i]
                self.dist.backward(self.loss_scaler.scale(weighted / accum))
            if critic_inputs:  # the critic's gradients for this micro-batch, weighted as the model's loss is
                self.critic.accumulate(*critic_inputs[0], scale=weights[i] / accum)
            loss_sum += weighted.detach()  # unscaled: what is logged and checked
        loss_mean = loss_sum / accum
        # fp16: the gradients back to their true size before they are measured, clipped or applied, and this
        # rank's overflow flag (0 without fp16)
        found_inf = self.loss_scaler.unscale_(self.optimizer)
        if not self._objective_phase(self.step)[1] and self.model_config.self_condition_prob > 0:
            # Before train.self_condition_start_step the estimate's input is zeros, so its weights' gradient is
            # exactly zero; dropping it keeps the norm's and AdamW's arithmetic that of the run without the option
            # (a zero in the norm's sum still changes its rounding), bit for bit.
            self.dist.unwrap(model).self_condition_proj.weight.grad = None
        if self.cfg.optim.grad_clip > 0:
            grad_norm = self.dist.clip_grad_norm_(model.parameters(), self.cfg.optim.grad_clip)
        else:
            grad_norm = torch.linalg.vector_norm(
                torch.stack([p.grad.detach().norm() for p in model.parameters() if p.grad is not None])
            )
        loss_nonfinite = ~torch.isfinite(loss_mean)
        grad_nonfinite = ~torch.isfinite(grad_norm)
        if self.critic is not None:  # averaged over the ranks here; a non-finite critic skips both updates
            grad_nonfinite = grad_nonfinite | ~torch.isfinite(self.critic.reduce_gradients())
        if self.loss_scaler.enabled:
            # fp16: non-finite gradients under a finite loss are the scaled gradients overflowing (the scaler's
            # business); only a non-finite loss is the bad-data case
            nonfinite, overflow = loss_nonfinite, (found_inf > 0) | grad_nonfinite
        else:
            nonfinite, overflow = loss_nonfinite | grad_nonfinite, found_inf > 0  # found_inf is 0 here
        samples = sum(len(batch["ids"]) for batch in micro_batches)
        host_flags = to_device([*self.stop_signal.flags(), float(samples), float(self._data_error is not None)],
                               device)
        flags = self.dist.all_reduce_sum(torch.cat([nonfinite.float().view(1), overflow.float().view(1),
                                                    loss_mean.float().view(1), host_flags]))
        if self.defers_step_sync:
            return self._queue_update(flags, grad_norm)
        # The one host sync per step: every rank reads the same sums, so every rank decides alike.
        nonfinite_ranks, overflow_ranks, loss_sum, *signal_counts, total_samples, data_error_ranks = flags.tolist()
        if data_error_ranks > 0:  # before any update: the run stops here on every rank
            self.optimizer.zero_grad(set_to_none=True)
            if self.critic is not None:
                self.critic.discard_gradients()
            raise self._data_error_of_some_rank()
        skip = nonfinite_ranks > 0
        empty = total_samples == 0
        overflowed = overflow_ranks > 0 and not (skip or empty)
        if self.critic is not None:
            self.critic.step(skip or empty or overflowed)
        if skip or empty or overflowed:
            self.optimizer.zero_grad(set_to_none=True)
            if overflowed:
                self.loss_scaler.update(overflow=True)  # backs off on every rank
            else:
                self.loss_scaler.keep()
        else:
            self.optimizer.step()
            self.loss_scaler.update(overflow=False)
            self.scheduler.step()
            self.optimizer.zero_grad(set_to_none=True)
            self.ema.after_step(self.dist.unwrap(model), self.step + 1)  # self.step: the steps before this one
        loss = loss_sum / self.dist.world_size
        return [StepResult(self.step + 1, loss, grad_norm, skip, StopSignal.from_flags(signal_counts),
                           empty=empty and not skip, overflow=overflowed)]

    # -- train.step_sync=deferred: the update decided on the device, its flags read one step later --------------

    def _queue_update(self, flags: torch.Tensor, grad_norm: torch.Tensor) -> list[StepResult]:
        """Apply this step's update unless its all-reduced ``flags`` say otherwise, without the host reading them:
        the skip is a device tensor that fused AdamW takes as ``found_inf`` (no update, its step count kept) and the
        EMA as a weight of 0. First, with this step's forward and backward queued (the GPU busy on them), the host
        reads the previous step's flags (:meth:`settle`): its scheduler step must precede this update's learning
        rate. This step's flags are copied to the host without waiting; :meth:`settle` reads them."""
        earlier = self.settle()
        nonfinite_ranks, total_samples, data_error_ranks = flags[0], flags[-2], flags[-1]  # train_step's layout
        skip = (nonfinite_ranks > 0) | (total_samples == 0) | (data_error_ranks > 0)
        optimizer = getattr(self.optimizer, "optimizer", self.optimizer)  # under accelerate's wrapper
        optimizer.found_inf = skip.float()
        try:
            self.optimizer.step()
        finally:
            del optimizer.found_inf
        self.optimizer.zero_grad(set_to_none=True)
        if self.critic is not None:
            self.critic.step(skip)
        applied = ~skip
        ema_updated = self.ema.after_step(self.dist.unwrap(self.model), self.step + 1, applied=applied)
        self._pending = PendingStep(self.step + 1, flags, grad_norm, ema_updated)
        return earlier

    def settle(self) -> list[StepResult]:
        """Read the queued step's flags (waiting for its all-reduce) and act on them as every_step does at the
        step's end: the scheduler steps after an applied update, the EMA's update count is taken back after a
        skipped one, bad data on some rank raises. Returns [its result], or [] with none queued."""
        pending, self._pending = self._pending, None
        if pending is None:
            return []
        nonfinite_ranks, _, loss_sum, *signal_counts, total_samples, data_error_ranks = pending.read()
        if data_error_ranks > 0:  # its update was not applied; the run stops here on every rank
            self.optimizer.zero_grad(set_to_none=True)
            raise self._data_error_of_some_rank()
        skip = nonfinite_ranks > 0
        empty = total_samples == 0
        if skip or empty:
            if pending.ema_updated:
                self.ema.num_updates -= 1  # as if it had not been called: the warm-up counts applied updates
        else:
            self.scheduler.step()
        return [StepResult(pending.step, loss_sum / self.dist.world_size, pending.grad_norm, skip,
                           StopSignal.from_flags(signal_counts), empty=empty and not skip)]

    def _next_micro_batches(self, window: "WindowStats", batches: Iterator[dict[str, Any]]) -> list[dict[str, Any]]:
        """The step's micro-batches. Bad data met reading them (a record that fails to decode in strict mode, a
        shard that does not hold what the manifest says) must not end this rank alone, while the others wait for it
        in the step's collectives: the rank keeps the error and steps through empty batches (a stand-in with weight
        0, as for tolerant mode's empty batches), its flag travels in the step's one all-reduce, and every rank
        stops there before the update (:meth:`train_step`). With train.step_sync=deferred the flag is read during the
        next step, whose batches this rank does not read (its stream ended with the error): stand-ins again."""
        if self._data_error is None:
            try:
                return window.timed_next(batches, self.cfg.optim.grad_accum)
            except DataError as err:
                self._data_error = err
        return [self.loader.empty_batch() for _ in range(self.cfg.optim.grad_accum)]

    def _data_error_of_some_rank(self) -> DataError:
        """The bad-data error every rank stops with, once the step's flags say some rank met one: this rank's own,
        else the lowest such rank's (one more collective, on this path only), so every rank's entry point prints
        the same line naming the file and the reason."""
        errors = self.dist.all_gather_object(self._data_error)
        return self._data_error or next(err for err in errors if err is not None)

    def _handle_nonfinite(self, result: StepResult) -> None:
        if result.overflow:  # fp16: a normal event, counted apart; the non-finite policy and budget untouched
            self._handle_overflow()
            return
        if result.empty:  # neither a non-finite step nor a normal one: counted apart, the budget untouched
            self.empty_steps += 1
            self.dist.log0("step %d: no rank had a sample (tolerant mode: every record of its batches was skipped); "
                           "stepped through without an update (%d such step(s) so far)", result.step, self.empty_steps,
                           level=logging.WARNING)
            return
        if not result.skipped:
            self.consecutive_skips = 0
            return
        self.skipped_steps += 1
        self.consecutive_skips += 1
        policy, budget = self.cfg.train.nonfinite, self.cfg.train.nonfinite_budget
        message = f"non-finite loss or gradient norm at step {result.step} on at least one rank"
        if policy == "stop":
            raise NonFiniteLossError(f"{message}; train.nonfinite=stop: stopping before the optimizer update")
        if self.consecutive_skips > budget:
            raise NonFiniteLossError(
                f"{message}; {self.consecutive_skips} consecutive skipped steps exceed train.nonfinite_budget={budget}"
            )
        self.dist.log0("%s: update skipped on every rank (%d in a row)", message, self.consecutive_skips, level=logging.WARNING)

    def _handle_overflow(self) -> None:
        """Count an fp16 overflow step; stop the run (on every rank: all hold the same scale) once the scale has
        fallen below train.fp16_min_scale."""
        self.scaler_skips += 1
        scale = self.loss_scaler.get_scale()  # a host sync, on overflow steps only
        floor = self.cfg.train.fp16_min_scale
        if scale < floor:
            raise NonFiniteLossError(
                f"fp16 gradient overflow at step {self.step}: the loss scale fell to {scale:g}, below "
                f"train.fp16_min_scale={floor:g} ({self.scaler_skips} overflow step(s) skipped): the gradients "
                "overflow even barely scaled, so the model diverged or fp16's range is too small for it. Use "
                "train.mixed_precision=bf16 or no, or resume from an earlier checkpoint with a lower optim.lr")
        self.dist.log0("step %d: fp16 gradient overflow on at least one rank: update skipped on every rank, loss "
                       "scale lowered to %g (%d overflow skip(s) so far)", self.step, scale, self.scaler_skips)

    # -- state ------------------------------------------------------------------------------------------------

    def save(self) -> Path | None:
        """Write one complete checkpoint of the current step (rank 0 writes; every rank contributes its RNG)."""
        if self._pending is not None:  # its scheduler step and EMA count are not known yet: the loop settles first
            raise RuntimeError(f"step {self._pending.step}'s flags are unread (train.step_sync=deferred): settle() "
                               "before saving")
        rank_state = {"rng": ckpt.capture_rng_state(), "generator": self.generator.get_state().cpu()}
        rank_states = self.dist.all_gather_object(rank_state)
        data_states = self.dist.all_gather_object(self.loader.state_dict())
        path = None
        failure = None
        if self.dist.is_main:
            try:
                path = self._save_on_main(rank_states, data_states)
            except OSError as err:
                failure = self._save_failure(err)
        # Every rank learns whether the save worked (and waits for it), so all stop together if it did not.
        failure = self.dist.broadcast_object(failure)
        if failure is not None:
            raise CheckpointSaveError(failure)
        self._last_saved_step = self.step
        return path

    def _save_failure(self, err: OSError) -> str:
        """The stop message after a failed save: what failed (for a full disk: space needed and free, from
        save_checkpoint, which has removed its partial folder) and where a restart continues from."""
        newest = ckpt.find_latest_complete(self.ckpt_root)
        restart = (f"train.resume=auto continues from {newest.name}" if newest is not None
                   else "there is no complete checkpoint yet: it starts over")
        what = err.strerror if isinstance(err, ckpt.CheckpointWriteError) else f"checkpoint not saved ({err})"
        fix = "Free space" if err.errno in (errno.ENOSPC, errno.EDQUOT) else "Fix that"
        return f"the run stopped at step {self.step}: {what}. {fix} and run the same command again ({restart})"

    def _save_on_main(self, rank_states: list[Any], data_states: list[Any]) -> Path:
        """Rank 0's part of :meth:`save`: write the checkpoint, list it in checkpoints/saved.jsonl, then apply
        train.keep_last."""
        path = ckpt.save_checkpoint(
            self.ckpt_root,
            self.step,
            model_state={k: v.detach().cpu() for k, v in self.dist.unwrap(self.model).state_dict().items()},
            ema_state=self.ema.state_dict(),
            optimizer_state=self.optimizer.state_dict(),
            scheduler_state=self.scheduler.state_dict(),
            scaler_state=self.loss_scaler.state_dict(),
            rng_states=rank_states,
            data_states=data_states,
            config=to_dict(self.cfg),
            manifest=dataset_identity(self.manifest),
            auxiliary_state={} if self.critic is None else {"critic": self.critic.state_dict()},
            extra={"samples_seen": self.samples_seen, "skipped_steps": self.skipped_steps,
                   "consecutive_skips": self.consecutive_skips, "empty_steps": self.empty_steps,
                   "scaler_skips": self.scaler_skips, "mixed_precision": self.dist.mixed_precision,
                   "ema_updates": self.ema.num_updates,
                   "model_config": dataclasses.asdict(self.model_config)},
        )
        ckpt.record_saved(self.ckpt_root, path)  # complete and in place: listed before keep_last may prune it
        ckpt.prune_checkpoints(self.ckpt_root, self.cfg.train.keep_last)
        return path

    def initialise_from(self, checkpoint: str) -> None:
        """train.init_from, on a fresh start (every rank, after :meth:`resume` found nothing to resume): the weights
        and their EMA become ``checkpoint``'s (:func:`load_initial_weights`), before the first step."""
        model = self.dist.unwrap(self.model)
        load_initial_weights(model, checkpoint)
        self.ema.copy_weights(model)
        self.dist.log0("initialised the weights (and their EMA) from %s", checkpoint)

    def resume(self) -> Path | None:
        """Restore the checkpoint train.resume names, chosen by rank 0 (:meth:`_open_run_folder`) and broadcast to
        all ranks; a refusal there is raised on every rank."""
        path = self._decided_by_main(self._open_run_folder)
        if path is None:
            return None
        model_state, ema_state, state = ckpt.load_checkpoint(path)
        if state["step"] > self.cfg.train.max_steps:
            # Training on would do nothing, and the run files written after this point (config.yaml with the
            # smaller max_steps, a new TensorBoard file, loss.png) would say otherwise: refused, nothing written.
            raise ckpt.ResumeSettingError(
                f"cannot resume from {path}: the run is already at step {state['step']} > "
                f"train.max_steps={self.cfg.train.max_steps}: nothing to train, and nothing of the run was "
                f"written. Give train.max_steps > {state['step']} to train on, or use another train.out_dir for a "
                "new run",
                setting="train.max_steps", saved=state["step"], now=self.cfg.train.max_steps)
        if state["world_size"] != self.dist.world_size:
            raise ckpt.ResumeSettingError(
                f"cannot resume from {path}: it was written by {state['world_size']} rank(s) and this run has "
                f"{self.dist.world_size}; exact resume needs the same world size (the data order and RNG streams are "
                f"per rank). Launch {state['world_size']} process(es), or start a new run in another train.out_dir",
                setting="world_size", saved=state["world_size"], now=self.dist.world_size)
        if state["manifest"]["dataset_id"] != self.manifest.dataset_id:
            raise ckpt.ResumeSettingError(
                f"cannot resume from {path}: it was trained on dataset {state['manifest']['dataset_id']} "
                f"({state['manifest'].get('location')}) and data.manifest={self.cfg.data.manifest} is dataset "
                f"{self.manifest.dataset_id}. Resume with the checkpoint's data.manifest, or start a new run in "
                "another train.out_dir",
                setting="data.manifest", saved=state["manifest"]["dataset_id"], now=self.manifest.dataset_id)
        saved_critic = state.get("auxiliary", {}).get("critic")
        if (saved_critic is None) != (self.critic is None):
            saved_weight = state["config"].get("train", {}).get("critic_weight", 0.0)
            raise ckpt.ResumeSettingError(
                f"cannot resume from {path}: it was written {'without' if saved_critic is None else 'with'} a "
                f"critic (train.critic_weight={saved_weight}) and this run has train.critic_weight="
                f"{self.cfg.train.critic_weight}; an exact resume needs the critic's state as it was. Resume with "
                f"train.critic_weight={saved_weight}, or start a new run in another train.out_dir (train.init_from "
                "takes the weights)", setting="train.critic_weight", saved=saved_weight,
                now=self.cfg.train.critic_weight)
        saved_optimizer = state["config"].get("optim", {}).get("optimizer", "adamw")
        if saved_optimizer != self.cfg.optim.optimizer:
            raise ckpt.ResumeSettingError(
                f"cannot resume from {path}: it was trained with optim.optimizer={saved_optimizer} and this run has "
                f"optim.optimizer={self.cfg.optim.optimizer}; an exact resume needs the optimizer's state as it was. "
                f"Resume with optim.optimizer={saved_optimizer}, or start a new run in another train.out_dir "
                "(train.init_from takes the weights)", setting="optim.optimizer", saved=saved_optimizer,
                now=self.cfg.optim.optimizer)
        try:  # checked before any weights are loaded: a refusal leaves this process as it was
            self.loader.load_state_dict(state["data"][self.dist.rank])
        except DataResumeError as err:
            raise resume_setting_error(path, err) from None
        self.dist.unwrap(self.model).load_state_dict(model_state)
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        if self.critic is not None:
            self.critic.load_state_dict(saved_critic)
        extra = state["extra"]
        self.ema.load_state_dict({k: v.to(self.dist.device) for k, v in ema_state.items()}, extra["ema_updates"])
        own = state["rng"][self.dist.rank]
        ckpt.restore_rng_state(own["rng"])
        self.generator.set_state(own["generator"])
        self.step = state["step"]
        self.samples_seen = extra["samples_seen"]
        self.skipped_steps = extra["skipped_steps"]
        self.consecutive_skips = extra.get("consecutive_skips", 0)
        self.empty_steps = extra.get("empty_steps", 0)
        self.scaler_skips = extra.get("scaler_skips", 0)
        self._restore_loss_scale(path, state.get("scaler"), extra.get("mixed_precision"))
        self._last_saved_step = self.step
        self.dist.log0("resumed from %s at step %d", path, self.step)
        return Path(path)

    def _restore_loss_scale(self, path: Path | str, saved: Mapping[str, Any] | None, saved_precision: str | None
                            ) -> None:
        """fp16 resumes with the checkpoint's loss scale and growth tracker. A checkpoint without them (written
        without fp16, or before loss scaling existed) starts from train.fp16_init_scale; a no/bf16 run ignores
        them."""
        if self.loss_scaler.enabled and saved is not None:
            self.loss_scaler.load_state_dict(saved)
        elif self.loss_scaler.enabled:
            written = (f"written with precision {saved_precision}" if saved_precision
                       else "written before fp16 loss scaling existed")
            self.dist.log0("%s holds no fp16 loss scale (%s): the loss scale starts at train.fp16_init_scale=%g",
                           path, written, self.cfg.train.fp16_init_scale)
        elif saved is not None:
            self.dist.log0("%s was written with fp16: its loss scale is not used by this %s run", path,
                           self.dist.mixed_precision)

    def _decided_by_main(self, decide: Callable[[], T]) -> T:
        """Take a start-up decision on rank 0 only (it may touch the run folder, or verify every shard) and hand the
        answer to every rank. If rank 0 refuses, every rank raises (the refusal itself when it is one of the
        user-facing kinds: a bad run folder, checkpoint, manifest or shard), so no rank waits forever in a
        collective."""
        answer: T | None = None
        refusal: Exception | None = None
        if self.dist.is_main:
            try:
                answer = decide()
            except Exception as err:  # noqa: BLE001 - raised again below, on every rank
                refusal = err
        shared = refusal
        if refusal is not None and not isinstance(refusal, (RunFolderError, ckpt.CheckpointError, OSError, DataError,
                                                            ManifestError)):
            shared = RuntimeError(f"rank 0 could not start the run: {type(refusal).__name__}: {refusal}")
        answer, shared = self.dist.broadcast_object((answer, shared))
        if refusal is not None:
            raise refusal
        if shared is not None:
            raise shared
        return answer

    def _open_run_folder(self) -> Path | None:
        """Rank 0's start-up decisions, before anything is written: the run folder is one this run may use, no other
        trainer holds it (its lock, held from here to the end of fit()), the unfinished checkpoint folders of dead
        writers are removed (they may hold the space the run needs), and train.resume is resolved (resume=auto sets
        corrupt checkpoints aside; an explicit older one is refused while newer checkpoints exist, unless
        train.resume_discard_newer)."""
        check_run_folder(self.out_dir)
        self._run_lock = RunFolderLock.acquire(self.out_dir)
        ckpt.remove_stale_tmp(self.ckpt_root)
        train = self.cfg.train
        return ckpt.resolve_resume(train.resume, self.ckpt_root, discard_newer=train.resume_discard_newer)

    # -- the loop ---------------------------------------------------------------------------------------------

    def fit(self) -> int:
        """Train to ``train.max_steps``; returns the process exit code (0, or 128 + signal after a clean stop). Rank 0
        holds the run folder's lock from the start of resume() until this returns or raises."""
        try:
            return self._fit()
        finally:
            if self._run_lock is not None:
                self._run_lock.release()
                self._run_lock = None

    def _fit(self) -> int:
        cfg = self.cfg
        resumed = self.resume()  # decided (and possibly refused) before anything in the run folder is written
        if resumed is None and cfg.train.init_from is not None:  # a fresh start; a resume never reads it
            self.initialise_from(cfg.train.init_from)
        if self._validation_ahead():
            self.validate(read_only=True)  # read the val batches now: a bad val shard is refused before step 1
        self._write_run_files()
        logger_sink = MetricsSink(self.out_dir, cfg, self.dist, self.model_config, self.num_parameters, self.step)
        self.stop_signal.install()
        # Creating the DataLoader iterator (num_workers > 0) draws the workers' base seed from the global torch
        # RNG; fork it, or a resumed run's dropout stream would be one draw ahead of the uninterrupted run's.
        with torch.random.fork_rng(devices=[]):
            batches = self.loader.iter_batches()
        window = WindowStats()
        progress = tqdm(total=cfg.train.max_steps, initial=self.step, disable=not self.dist.is_main,
                        desc="train", dynamic_ncols=True)
        try:
            while self.step < cfg.train.max_steps:
                micro_batches = self._next_micro_batches(window, batches)
                window.add_work(*self._work_of(micro_batches))
                outcomes = self.train_step(micro_batches)  # deferred: the previous step's, read during this one
                self.step += 1
                self.samples_seen += cfg.data.batch_size * cfg.optim.grad_accum * self.dist.world_size
                progress.update(1)
                log_step = self.step % cfg.train.log_every == 0 or self.step == cfg.train.max_steps
                stopping = any(outcome.stop_signal for outcome in outcomes)
                if stopping or log_step or self._saves_validates_or_previews():
                    outcomes += self.settle()  # deferred: this step's flags now (every_step: none pending)
                for outcome in outcomes:
                    self._handle_nonfinite(outcome)
                    window.add(outcome, cfg.data.batch_size * cfg.optim.grad_accum)
                result = outcomes[-1] if outcomes else None
                record = self._log_record(window, result) if log_step else None
                validation = self._validate_if_due(window)
                preview = self._preview_if_due(window)
                if record is not None or validation is not None or preview is not None:
                    logger_sink.log({**(record or {"step": self.step}), **(validation or {}),
                                     **(preview.record() if preview else {})}, progress)
                if preview is not None:
                    logger_sink.log_image(self.step, PREVIEW_IMAGE_TAG, preview.png)
                if self.step % cfg.train.save_every == 0 or self.step == cfg.train.max_steps:
                    self.save()
                signum = next((outcome.stop_signal for outcome in outcomes if outcome.stop_signal), 0)
                if signum:
                    return self._stop_on_signal(signum)
            return 0
        finally:
            # Ends the batch stream now, and with it the DataLoader's worker processes, however training ended: a
            # run stopped by an error would otherwise keep them until that error's traceback is collected.
            batches.close()
            progress.close()
            logger_sink.close()
            self.stop_signal.restore()
            if self.loss_scaler.enabled:
                self.dist.log0("precision fp16: loss scale %g at step %d; %d step(s) skipped for a gradient overflow "
                               "(scaler_skips), %d for a non-finite loss (skipped_steps)", self.loss_scaler.get_scale(),
                               self.step, self.scaler_skips, self.skipped_steps)

    # -- validation -------------------------------------------------------------------------------------------

    def _validation_ahead(self) -> bool:
        """Whether this run reaches a multiple of train.val_every after its current step."""
        every = self.cfg.train.val_every
        return every > 0 and self.step // every < self.cfg.train.max_steps // every

    def _saves_validates_or_previews(self) -> bool:
        """Whether this step ends in a checkpoint, a validation or a preview: train.step_sync=deferred reads the
        step's flags first. By the settings alone (previews run on rank 0 only), so every rank reads at the same
        steps."""
        train, step = self.cfg.train, self.step
        return (step % train.save_every == 0 or step == train.max_steps
                or any(every > 0 and step % every == 0 for every in (train.val_every, train.preview_every)))

    def _validate_if_due(self, window: "WindowStats") -> dict[str, Any] | None:
        """At a multiple of train.val_every: the validation record; its time is left out of the throughput."""
        every = self.cfg.train.val_every
        if every <= 0 or self.step % every:
            return None
        start = time.perf_counter()
        record = self.validate()
        window.started += time.perf_counter() - start
        return record

    def validate(self, read_only: bool = False) -> dict[str, Any] | None:
        """The validation loss of the current weights (:mod:`pipeline.training.validation`) as the record
        ``{val_loss, val_samples, val_weights, val_time_s}``; None when the manifest has no usable val split. A
        collective: every rank calls it at the same step. The first call reads the validation batches (rank 0
        verifies the val shards first, as data.verify says); ``read_only`` stops there."""
        if not self._validator_built:
            state = ckpt.capture_rng_state()  # reading the batches must leave every training stream as it was
            try:
                self._validator = self._build_validator()
            finally:
                ckpt.restore_rng_state(state)
            self._validator_built = True
        if read_only or self._validator is None:
            return None
        return self._validator.run()

    def _build_validator(self) -> Validator | None:
        bad: tuple[str, ...] = ()
        if has_val_split(self.manifest):
            bad, _ = self._verified_bad_shards("val")
        return build_validator(
            self.cfg, self.manifest, self.dist, exclude_shards=bad,
            loss_fn=lambda batch, generator, model: self._micro_batch_loss(batch, None, generator, model),
            model=self.dist.unwrap(self.model), ema_state=lambda: self.ema.shadow)

    # -- previews (train.preview_every) -----------------------------------------------------------------------

    def _build_previews(self) -> PreviewSampler | None:
        if not self.dist.is_main or self.cfg.train.preview_every <= 0:
            return None
        diffusion = self.objective if self.cfg.train.objective == "diffusion" else None
        return PreviewSampler(self.cfg, self.manifest, self.model_config, self.dist.unwrap(self.model),
                              lambda: self.ema.shadow, self.dist.device, self.out_dir, diffusion)

    def _preview_if_due(self, window: "WindowStats") -> Preview | None:
        """At a multiple of train.preview_every, on rank 0: the preview of the EMA weights
        (:mod:`pipeline.training.previews`; no collective, nothing of training touched); its time is left out of
        the throughput. None elsewhere."""
        every = self.cfg.train.preview_every
        if self._previews is None or self.step % every:
            return None
        start = time.perf_counter()
        preview = self._previews.run(self.step)
        window.started += time.perf_counter() - start
        return preview

    def _stop_on_signal(self, signum: int) -> int:
        """Some rank saw SIGTERM/SIGINT before this step ended: every rank learnt it from the same all-reduce, so
        all are here after the same completed step. Write one checkpoint (unless this step was just saved) and
        return 128 + N."""
        if self._last_saved_step != self.step:
            self.save()
        self.dist.log0("stopped by signal %d at step %d after writing a checkpoint", signum, self.step)
        return EXIT_SIGNAL_BASE + signum

    def _log_record(self, window: "WindowStats", result: StepResult) -> dict[str, Any]:
        """One metrics.jsonl line. Called on every rank at a log step (it sums the ranks' skipped records)."""
        stats = window.flush()
        grad_norm = float(result.grad_norm)
        # Tolerant mode's records left out of their batches, and batches left empty, so far (this run and the runs
        # it resumes), then this window's model FLOPs and frames (mfm.flops); all ranks.
        counters = torch.tensor([self.loader.records_skipped, self.loader.empty_batches,
                                 self.loader.shards_from_cache, self.loader.shards_fetched,
                                 stats["model_flops"], stats["frames_valid"], stats["frames_computed"]],
                                dtype=torch.float64, device=self.dist.device)
        if self.critic is not None:  # the critic's sums since the last log line ride along
            counters = torch.cat([counters, self.critic.window_sums().to(torch.float64)])
        (records_skipped, empty_batches, from_cache, fetched, flops, frames_valid, frames_computed,
         *critic_sums) = self.dist.all_reduce_sum(counters).tolist()
        model_flops_per_s = flops / stats["elapsed_s"]
        return {
            "step": self.step,
            "loss": stats["loss"],  # None (JSON null) when every step of the window was skipped
            "grad_norm": grad_norm if math.isfinite(grad_norm) else None,
            "lr": self.scheduler.get_last_lr()[0],
            "samples_per_s": stats["samples_per_s"] * self.dist.world_size,
            "data_wait_frac": stats["data_wait_frac"],
            # model FLOPs (one forward and backward of the generator per sample, padding included: it is computed)
            # per second, all ranks, and MFU against each device's dense bf16 peak (None without one, e.g. a CPU)
            "model_tflops": model_flops_per_s / 1e12,
            "mfu": model_flops_utilisation(model_flops_per_s / self.dist.world_size, self.device_peak.tflops),
            "padding_frac": 1.0 - frames_valid / frames_computed if frames_computed else None,
            "epoch": self.loader.epoch,
            "samples_seen": self.samples_seen,
            "skipped_steps": self.skipped_steps,
            "records_skipped": int(records_skipped),
            "empty_batches": int(empty_batches),  # batches (all ranks) whose every record was skipped
            "empty_steps": self.empty_steps,  # steps with no sample on any rank: no update
            # data.cache_dir only: remote shard reads (all ranks, this run) served by the local cache / downloaded
            **({"shards_from_cache": int(from_cache), "shards_fetched": int(fetched)}
               if self.cfg.data.cache_dir is not None else {}),
            **self._loss_scale_record(),
            **self._critic_record(critic_sums),
        }

    def _work_of(self, micro_batches: list[Mapping[str, Any]]) -> tuple[float, int, int]:
        """A step's model FLOPs (mfm.flops, counted once per batch width and caption length), valid frames and
        computed frames (rows × width), on this rank, from the batches' host tensors (no device sync)."""
        flops, valid, computed = 0.0, 0, 0
        for batch in micro_batches:
            rows, width = batch["features"].shape[:2]
            if rows == 0:  # a stand-in for a batch this rank could not read
                continue
            text_tokens = batch["text_tokens"].shape[1] if self.model_config.conditioning == "cross_attention" else 0
            flops += rows * self.training_flops.per_sample(width, text_tokens)
            valid += int(batch["lengths"].sum())
            computed += rows * width
        return flops, valid, computed

    def _critic_record(self, sums: list[float]) -> dict[str, Any]:
        """train.critic_weight > 0 only: the critic's hinge loss and the model's adversarial term (unweighted;
        ``loss`` holds it times train.critic_weight), means over the window's micro-batches on all ranks (None when
        there were none, or when a skipped step's non-finite value is among them)."""
        if self.critic is None:
            return {}
        critic_loss, term, count = sums

        def mean(total: float) -> float | None:
            return total / count if count and math.isfinite(total) else None

        return {"critic_loss": mean(critic_loss), "adversarial_loss": mean(term)}

    def _loss_scale_record(self) -> dict[str, Any]:
        """fp16 only: the loss scale after this step and the overflow steps skipped so far (this run and the runs
        it resumes); apart from skipped_steps, which counts non-finite losses."""
        if not self.loss_scaler.enabled:
            return {}
        return {"loss_scale": self.loss_scaler.get_scale(), "scaler_skips": self.scaler_skips}

    def _write_run_files(self) -> None:
        """The run marker first (mfm-run.json, unless there: from then on the folder is a run of ours, also for a run
        of an earlier version resumed here), then config.yaml (the resolved config) and shard_report.json (what
        verification found and skipped); written only once the resume was accepted, so a refused resume leaves the
        run's files as they were."""
        if self.dist.is_main:
            write_run_marker(self.out_dir, written_by="pipeline/training/trainer.py")
            (self.out_dir / "config.yaml").write_text(yaml.safe_dump(to_dict(self.cfg), sort_keys=False))
            (self.out_dir / "shard_report.json").write_text(json.dumps(self.shard_report, indent=1) + "\n")
        self.dist.barrier()


class WindowStats:
    """Loss, throughput and data-wait fraction since the last log line."""

    def __init__(self) -> None:
        self._reset()

    def _reset(self) -> None:
        self.loss_sum = 0.0
        self.loss_steps = 0
        self.samples = 0
        self.data_wait = 0.0
        self.model_flops = 0.0
        self.frames_valid = 0
        self.frames_computed = 0
        self.started = time.perf_counter()

    def add_work(self, model_flops: float, frames_valid: int, frames_computed: int) -> None:
        self.model_flops += model_flops
        self.frames_valid += frames_valid
        self.frames_computed += frames_computed

    def timed_next(self, batches: Iterator[dict[str, Any]], count: int) -> list[dict[str, Any]]:
        start = time.perf_counter()
        out = [next(batches) for _ in range(count)]
        self.data_wait += time.perf_counter() - start
        return out

    def add(self, result: StepResult, samples: int) -> None:
        # A skipped (non-finite) or empty step has no loss to average: it is counted in skipped_steps/empty_steps.
        if not (result.skipped or result.empty):
            self.loss_sum += result.loss
            self.loss_steps += 1
        self.samples += samples

    def flush(self) -> dict[str, float | None]:
        elapsed = max(time.perf_counter() - self.started, 1e-9)
        out = {
            "loss": self.loss_sum / self.loss_steps if self.loss_steps else None,
            "samples_per_s": self.samples / elapsed,
            "data_wait_frac": self.data_wait / elapsed,
            "elapsed_s": elapsed,
            "model_flops": self.model_flops,
            "frames_valid": self.frames_valid,
            "frames_computed": self.frames_computed,
        }
        self._reset()
        return out
