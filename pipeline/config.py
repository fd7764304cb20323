"""Typed training configuration: nested dataclasses, YAML presets, dotted overrides.

A run's configuration is resolved once, in this order, and then never changes:

    dataclass defaults  <-  preset YAML (configs/<name>.yaml or a file path)  <-  ``key.sub=value`` overrides

``load_config(TrainConfig, "tiny", ["optim.lr=3e-4", "train.max_steps=20"])`` does all three. Every value is
type-checked against the dataclass field it lands in (int, float, bool, str, Optional, Literal, list/tuple,
nested dataclasses); an unknown key fails naming the key and the valid ones. Each section validates its own
values in ``__post_init__``, so a config built directly in Python is checked the same way.

``to_dict(cfg)`` / ``from_dict(TrainConfig, d)`` round-trip exactly; the resolved dict is what checkpoints and
run folders store.

YAML is read with YAML 1.2 scalar rules: only ``true``/``false`` are booleans (so ``verify: off`` stays the
string ``"off"``) and ``1e-4`` is a float (PyYAML's 1.1 rules read it as a string).
"""

from __future__ import annotations

import copy
import dataclasses
import os
import re
import types
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, Literal, TypeVar, Union, get_args, get_origin, get_type_hints

import yaml

from mfm.model import ModelConfig
from mfm.shortcut import level_steps

def preset_dir() -> Path:
    """The folder of the YAML presets. An install carries them inside this package (pipeline/presets/, a copy of the
    repository's configs/ made by the wheel build: pyproject.toml's package-dir); a checkout, or an editable install
    of one, has no such folder and reads the repository's configs/, the folder users edit."""
    here = Path(__file__).resolve().parent
    installed = here / "presets"
    return installed if installed.is_dir() else here.parent / "configs"


CONFIG_DIR = preset_dir()
"""Where preset names resolve: ``"tiny"`` -> ``configs/tiny.yaml`` (installed: ``pipeline/presets/tiny.yaml``)."""

T = TypeVar("T")


class ConfigError(ValueError):
    """A config value, key, preset or override is invalid; the message names it."""


# ---------------------------------------------------------------------------------------------------------------
# Sections
# ---------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, kw_only=True)
class DataConfig:
    """The streaming dataset (see docs/dataset-format.md)."""

    manifest: str = "data/deepmimic-minilm/manifest.json"
    """Path or URL of the dataset's manifest.json; shard paths inside it are relative to its folder."""
    format: Literal["tar", "parquet"] = "tar"
    """Which copy of the records to stream: webdataset tar shards or Parquet parts."""
    window: int = 196
    """Frames per training sample: longer motions are randomly cropped, shorter ones padded and masked."""
    unit_length: int = 4
    """Crop lengths are multiples of this, one unit shorter with probability 1/3 (MDM/MFM); 1 disables it."""
    batch_size: int = 32
    """Samples per batch on each rank (global batch = batch_size x world_size x grad_accum)."""
    num_workers: int = 0
    """DataLoader worker processes per rank (0: load in the training process)."""
    shuffle_buffer: int = 256
    """Samples held in the in-stream shuffle buffer (0 or 1: no sample shuffling)."""
    seed: int = 0
    """Seed of the shard order, shuffle buffer, crops and caption choice (independent of train.seed)."""
    batching: Literal["fixed", "length_aware"] = "fixed"
    """fixed: every batch is padded to data.window frames. length_aware: clips of similar length share a batch
    (sort_window_batches batches' worth of shuffled clips sorted by the manifest's lengths, cut into batches whose
    order is shuffled) and each batch is padded only to its longest clip rounded up to data.pad_multiple (at most
    data.window): no compute on most of the padding. Same samples per epoch, batch counts per rank, exact resume and
    per-clip loss as fixed; needs a manifest that lists every record's length (the builder's do). The validation
    batches stay fixed windows."""
    pad_multiple: int = 16
    """length_aware: batch widths are rounded up to a multiple of this many frames (few distinct shapes for compiled
    models and kernel autotuners); 1: exactly the longest clip."""
    sort_window_batches: int = 8
    """length_aware: how many batches' worth of consecutive shuffled clips are sorted by length together (more:
    tighter batches, and a reader holds that many more raw records)."""
    verify: Literal["strict", "tolerant", "off"] = "strict"
    """strict: before training, check the manifest's split totals against its shard counts and lengths, and every
    shard's size, sha256, real record count and record ids (unique) against the manifest; fail naming the file and
    the reason; a resume whose excluded shards changed mid-epoch is refused. tolerant: the same checks, but bad
    shards are left out and counted in shard_report.json; during training a record that fails to decode (e.g.
    non-finite features) is left out of its batch, counted and logged, deterministically (exact resume holds); a
    resume after a shard went bad finishes the checkpoint's epoch with its plan without that shard's records and
    plans later epochs without it (logged as a warning). Both hash remote shards again as they stream, before any
    of their records is used: one changed since verification stops a strict run naming its URL (before the next
    step, so before the next checkpoint) and has its records skipped, counted, in tolerant mode. off: no checks
    before training nor while streaming."""
    allow_external_shards: bool = False
    """false: every shard path in the manifest must be a relative path under the manifest's own folder or URL; an
    absolute path, a URL (``file://``, another host or scheme) or a '..' segment is refused before anything is read
    (a manifest fetched from elsewhere could otherwise make the job read any local file). true: read such shards
    where they point (a ``pipe:`` command is refused either way)."""
    caption_policy: Literal["random", "first"] = "random"
    """Which of a motion's captions a visit uses: a random one (training) or always the first (debugging)."""
    retries: int = 3
    """Retries of a manifest or shard read after a transient error (connection reset, timeout, HTTP 5xx/429), each
    logged; a shard read resumes where it failed without repeating or dropping a record. Permanent errors (404,
    permission) are not retried. 0: fail at the first error."""
    retry_backoff_s: float = 1.0
    """Seconds before the first retry, doubled for each further one (at most 60 s)."""
    cache_dir: str | None = None
    """A folder for local copies of remote shards (http(s)://, s3://, gs://, ...; ``~`` is expanded): each is
    downloaded once, written under its manifest sha256 only when its size and sha256 match the manifest (else the
    error names the URL and nothing is kept), and read from there every later epoch and run (shared by manifests
    listing the same bytes, by DataLoader workers and by the ranks of a machine). Every open checks the copy's size (a
    truncated copy is downloaded again, with a warning); verification at start (data.verify strict/tolerant) hashes
    every copy it uses and downloads a damaged one again. null (default): no cache, remote shards are read over the
    network every epoch. Local shards are never copied."""
    cache_max_gb: float = 0.0
    """Size cap of data.cache_dir in gigabytes (10^9 bytes): after each download the least recently used copies are
    removed until the cache is under it (the copy just downloaded stays). 0: no cap."""

    @property
    def cache_max_bytes(self) -> int:
        """data.cache_max_gb in bytes (0: no cap)."""
        return int(self.cache_max_gb * 1e9)

    def __post_init__(self) -> None:
        coerce_fields(self)
        _require(bool(self.manifest.strip()), "data.manifest must not be empty")
        _require(self.window >= 1, f"data.window must be >= 1, got {self.window}")
        _require(1 <= self.unit_length <= self.window, f"data.unit_length must lie in [1, window], got {self.unit_length}")
        _require(self.batch_size >= 1, f"data.batch_size must be >= 1, got {self.batch_size}")
        _require(self.num_workers >= 0, f"data.num_workers must be >= 0, got {self.num_workers}")
        _require(self.shuffle_buffer >= 0, f"data.shuffle_buffer must be >= 0, got {self.shuffle_buffer}")
        _require(self.seed >= 0, f"data.seed must be >= 0, got {self.seed}")
        _require(self.pad_multiple >= 1, f"data.pad_multiple must be >= 1, got {self.pad_multiple}")
        _require(self.sort_window_batches >= 1, f"data.sort_window_batches must be >= 1, got {self.sort_window_batches}")
        _require(self.retries >= 0, f"data.retries must be >= 0, got {self.retries}")
        _require(0.0 <= self.retry_backoff_s < float("inf"),
                 f"data.retry_backoff_s must be a finite number >= 0, got {self.retry_backoff_s}")
        _require(self.cache_dir is None or bool(self.cache_dir.strip()),
                 "data.cache_dir must be a folder, or null for no shard cache; got an empty string")
        _require(self.cache_dir is None or not os.path.exists(os.path.expanduser(self.cache_dir))
                 or os.path.isdir(os.path.expanduser(self.cache_dir)),
                 f"data.cache_dir {self.cache_dir!r} exists and is not a folder")
        _require(0.0 <= self.cache_max_gb < float("inf"),
                 f"data.cache_max_gb must be a finite number >= 0 (0: no cap), got {self.cache_max_gb}")
        _require(self.cache_max_gb == 0.0 or self.cache_dir is not None,
                 f"data.cache_max_gb={self.cache_max_gb} caps a shard cache, but data.cache_dir is not set")


@dataclasses.dataclass(frozen=True, kw_only=True)
class OptimConfig:
    """The optimizer (AdamW, or Muon with AdamW), linear warm-up and schedule, gradient clipping and accumulation,
    and the EMA of the weights."""

    lr: float = 1e-4
    """Peak learning rate (reached after warmup_steps; then constant or decayed, see ``schedule``)."""
    schedule: Literal["constant", "cosine", "wsd"] = "constant"
    """After warm-up: 'constant' (MFM) or 'cosine' decay from lr to ``min_lr_ratio``·lr at train.max_steps (not MFM:
    a short run that must end fitted, like the CPU default, gains most in its last, low-lr steps), or 'wsd'
    (warmup-stable-decay: constant lr, then a linear decay to ``min_lr_ratio``·lr over the last ``decay_fraction``
    of the steps after warm-up; Hu et al. 2024, MiniCPM; Hägele et al. 2024. Not in MFM, FLAME or FlowMDM. It keeps
    the peak lr where cosine has already lowered it; on the synthetic preset that lost the counts, which are learnt
    while the cosine's lr is low: docs/generator-study.md, "... warmup-stable-decay")."""
    min_lr_ratio: float = 0.0
    """cosine and wsd: the final learning rate as a fraction of lr."""
    decay_fraction: float = 0.2
    """wsd: the share of the steps after warm-up spent in the final linear decay (1: linear decay from warm-up on)."""
    weight_decay: float = 0.0
    betas: tuple[float, float] = (0.9, 0.999)
    optimizer: Literal["adamw", "muon"] = "adamw"
    """'adamw' (MFM, FLAME, FlowMDM): AdamW on every parameter. 'muon' (ours, in none of the three): torch.optim.Muon
    (Jordan et al. 2024) on the Transformer blocks' 2-D weights, whose momentum it orthogonalises before each step,
    and AdamW (``lr``, ``betas``) on everything else: input and output projections, embeddings, biases, norms
    (pipeline.training.optimizers). Both take ``weight_decay`` and the same schedule. A step costs more (five
    Newton–Schulz iterations per matrix: 1.3x on the synthetic preset's 2-core CPU step) and learns more: the
    synthetic preset's loss at step 300 is AdamW's at step 750 (docs/generator-study.md, "Muon on the blocks'
    matrices"). Not with train.step_sync=deferred (Muon has no on-device skip)."""
    muon_lr: float = 0.02
    """optimizer=muon: the peak learning rate of Muon's matrices (Jordan's default; each step is muon_lr ·
    sqrt(max(1, fan_out/fan_in)) times an orthogonal matrix), scaled by the schedule as ``lr`` is."""
    muon_momentum: float = 0.95
    """optimizer=muon: Muon's Nesterov momentum (Jordan's default)."""
    warmup_steps: int = 0
    """Optimizer steps of linear warm-up from 0 to lr."""
    grad_clip: float = 1.0
    """Max global gradient norm; 0 disables clipping."""
    grad_accum: int = 1
    """Micro-batches accumulated per optimizer step."""
    ema_decay: float = 0.9999
    """EMA weight of the previous average at each EMA update."""
    ema_every: int = 1
    """Optimizer steps between EMA updates: the EMA is updated after optimizer steps k = ema_every, 2·ema_every, ...
    (k counts from 1, as FLAME's ``global_step % ema_update == 0``; a skipped step updates nothing)."""
    ema_start: int = 0
    """EMA updates after optimizer steps k <= ema_start copy the weights instead of averaging them (FLAME's
    ``ema_start``, diffusion_module.py: 72–76 ``global_step <= ema_start``); 0: every update averages."""
    ema_warmup: bool = True
    """Average with the warm-up decay ``min(ema_decay, (1 + n) / (10 + n))`` (n: EMA updates so far, copies
    included), so a short run's average is not dominated by its random initialisation; false: ``ema_decay`` from
    the first average on (FLAME, whose copy phase ``ema_start`` stands in for a warm-up)."""

    def __post_init__(self) -> None:
        coerce_fields(self)
        _require(self.lr > 0.0, f"optim.lr must be > 0, got {self.lr}")
        _require(self.weight_decay >= 0.0, f"optim.weight_decay must be >= 0, got {self.weight_decay}")
        _require(all(0.0 <= b < 1.0 for b in self.betas), f"optim.betas must lie in [0, 1), got {self.betas}")
        _require(self.muon_lr > 0.0, f"optim.muon_lr must be > 0, got {self.muon_lr}")
        _require(0.0 <= self.muon_momentum < 1.0, f"optim.muon_momentum must lie in [0, 1), got {self.muon_momentum}")
        _require(self.warmup_steps >= 0, f"optim.warmup_steps must be >= 0, got {self.warmup_steps}")
        _require(0.0 <= self.min_lr_ratio <= 1.0, f"optim.min_lr_ratio must lie in [0, 1], got {self.min_lr_ratio}")
        _require(0.0 < self.decay_fraction <= 1.0,
                 f"optim.decay_fraction must lie in (0, 1], got {self.decay_fraction}")
        _require(self.grad_clip >= 0.0, f"optim.grad_clip must be >= 0 (0 disables), got {self.grad_clip}")
        _require(self.grad_accum >= 1, f"optim.grad_accum must be >= 1, got {self.grad_accum}")
        _require(0.0 <= self.ema_decay < 1.0, f"optim.ema_decay must lie in [0, 1), got {self.ema_decay}")
        _require(self.ema_every >= 1, f"optim.ema_every must be >= 1, got {self.ema_every}")
        _require(self.ema_start >= 0, f"optim.ema_start must be >= 0 (0: no copy phase), got {self.ema_start}")


@dataclasses.dataclass(frozen=True, kw_only=True)
class TrainLoopConfig:
    """Length of the run, logging, checkpointing, resume, precision and failure policy."""

    max_steps: int = 10_000
    """Optimizer steps to train for (the run ends at this step, resumed or not)."""
    log_every: int = 50
    """Optimizer steps between log lines / logged scalars."""
    save_every: int = 1_000
    """Optimizer steps between checkpoints."""
    keep_last: int = 3
    """Complete checkpoints kept on disk (the newest is never deleted); 0 keeps all of them."""
    resume: str = "auto"
    """auto: newest complete checkpoint in out_dir whose files verify, else start fresh (a corrupt newer one is
    renamed step-N.corrupt-<time>, kept); never: always start fresh (fails if out_dir already holds checkpoints,
    rather than mixing runs); otherwise the path of a checkpoint folder, which must exist and be complete, and
    out_dir must hold no newer checkpoint (see resume_discard_newer)."""
    resume_discard_newer: bool = False
    """With resume=PATH: move out_dir's checkpoints newer than PATH aside (renamed step-N.discarded-<time>, not
    deleted) instead of refusing to start; without it the run refuses before step 1, not when it reaches them."""
    out_dir: str = "runs/default"
    """Run folder: resolved config, checkpoints/, logs. A new or empty folder, or an existing run folder; never
    the filesystem root, a file, or a non-empty folder that is not a run (checked before anything is written)."""
    mixed_precision: Literal["no", "bf16", "fp16", "auto"] = "auto"
    """auto: ``accelerate launch --mixed_precision bf16|fp16`` when given, else bf16 autocast on a GPU that supports
    it, full fp32 otherwise (never fp16 unasked). An explicit setting that the launcher's bf16/fp16 contradicts is
    refused (the launcher's "no" is also its default, so it never overrides). fp16: fp16 autocast (CPU or GPU) with
    dynamic loss scaling (torch.amp.GradScaler); a step whose scaled gradients overflow on any rank is skipped on
    every rank and the scale lowered, counted as scaler_skips, apart from the non-finite policy below."""
    fp16_init_scale: float = 65536.0
    """With fp16: the initial loss scale (GradScaler's init_scale; halved at each overflow, doubled after
    fp16_growth_interval steps without one)."""
    fp16_growth_interval: int = 2000
    """With fp16: consecutive updates without an overflow before the loss scale doubles."""
    fp16_min_scale: float = 1.0e-4
    """With fp16: the run stops (NonFiniteLossError) when overflow skips push the loss scale below this: the
    gradients overflow even barely scaled, which is divergence, not fp16's range (use bf16 or no)."""
    seed: int = 0
    """Seed of model initialisation (unless train.init_seed is set) and of the noise / time draws of training."""
    init_seed: int | None = None
    """Seed of the initial weights, and of everything else drawn from the global generators (a critic's weights,
    the DataLoader workers' base seed, the network's dropout); null: train.seed. The flow loss's draws (times,
    noise, condition dropout: the trainer's own generator) stay train.seed's, so two runs that differ in one of
    the two seeds separate what the initial weights decide from what the draws decide (docs/generator-study.md,
    "Initial weights or draws"). The data order is data.seed's in every case."""
    nonfinite: Literal["skip", "stop"] = "skip"
    """On a non-finite loss or gradient norm on any rank: skip the update on every rank, or stop the run. With
    fp16, non-finite gradients under a finite loss are a loss-scale overflow instead (see mixed_precision): they
    never count here."""
    nonfinite_budget: int = 10
    """With nonfinite=skip: consecutive skipped steps tolerated before the run stops."""
    step_sync: Literal["auto", "every_step", "deferred"] = "auto"
    """When the host reads a step's outcome (non-finite loss or gradient on some rank, no sample, bad data, a stop
    signal, the loss it logs). every_step: at the step's end, before its update is applied: one host sync per step,
    so on a GPU the host waits for the backward pass before it can queue the next step (the HumanML3D preset's
    batch-128 step kept an H200 busy half of the time, docs/performance.md). deferred: the update is applied or
    skipped on the device (fused AdamW's ``found_inf``, the EMA's weight times 0 or 1), and the host reads step
    k's flags once step k+1's forward and backward are queued, and at once at every log, save, validation and
    preview step and the last: between those it never waits for the GPU. The decisions are the same, on every
    rank alike; the host acts on them one step later: a stop signal ends the run after the next step (saved there),
    train.nonfinite=stop and bad data raise during the next step. Uses fused AdamW on every device; not with fp16,
    whose loss scale is decided on the host every step. auto: deferred on CUDA (without fp16), every_step elsewhere:
    a CPU has nothing to overlap, and every_step keeps the CPU presets' runs as they were, bit for bit."""
    wandb: Literal["auto", "offline", "online", "disabled"] = "auto"
    """Weights & Biases mode (offline needs no network; `wandb sync` uploads later). auto: the environment's
    WANDB_MODE when set, else offline. An explicit offline/online/disabled (here, in a preset or an override) wins
    over WANDB_MODE: disabled writes no W&B files whatever the environment says (see :func:`wandb_mode`)."""
    wandb_project: str = "mfm"
    tensorboard: bool = True
    """Write TensorBoard event files to ``<out_dir>/tensorboard/`` (rank 0 only): the scalars of metrics.jsonl,
    as ``train/<key>`` and ``val/<key>`` (``tensorboard --logdir <out_dir>``). Needs the ``tensorboard`` package
    (a dependency of this project); a run asked for it without the package is refused before training."""
    val_every: int = 500
    """Optimizer steps between validation losses (at every multiple of it); 0 = no validation. The loss of the
    training objective on the first ``val_batches`` batches of the manifest's ``val`` split, with fixed draws
    (comparable from step to step), logged as ``val_loss``. 500 = the default preset's checkpoint interval: 24
    points in its 12,000 steps, each costing about 0.6 of a training step there (2 batches, 50 ms on 2 CPU
    cores); at HumanML3D's sizes 16 forward passes, roughly 5 steps' time per 500 (1%)."""
    val_batches: int = 16
    """At most this many validation batches (``data.batch_size`` motions each, read once at the start: the
    same captions and crops every time); the ranks share them out and the mean over their motions is all-reduced,
    so any number of ranks gives the same figure."""
    val_weights: Literal["ema", "model"] = "ema"
    """Which weights the validation loss is of: the EMA (what sampling and evaluation use by default) or the raw
    training weights ('model', the weights of the train loss). Recorded with every val_loss line."""
    preview_every: int = 500
    """Optimizer steps between preview samples (at every multiple of it); 0 = none. Rank 0 generates the preview
    prompts with the EMA weights (a private copy of the model, eval mode, no gradients, noise from generators of
    its own: training's weights, RNG streams and data stream are left as they were, so a run is bit-identical with
    previews on or off) and writes ``<out_dir>/previews/step-XXXXXXXX.png`` (a contact sheet), the same image to
    TensorBoard (``preview/samples``) and W&B, and the samples' plausibility medians as ``preview/<figure>``
    scalars (also in metrics.jsonl as ``preview_<figure>``). Flow models: euler, 10 steps; diffusion models: ddim,
    50 steps; guidance and smoothing: the model's sampling defaults. 500: on the default preset (12,000 steps) 24
    sheets of 4 samples, about a second each on 2 CPU cores. A preview that fails is logged and previews stop for
    the run; training goes on."""
    preview_prompts: tuple[str, ...] = ()
    """The texts to preview (action models: action names); empty = the first caption of the first
    ``preview_count`` motions of the manifest's val split (train when it has none), at the length of the part of
    the clip that caption describes (given prompts: lengths drawn from the training lengths, the same every time)."""
    preview_count: int = 4
    """How many dataset captions to preview when ``preview_prompts`` is empty (ignored otherwise)."""
    compile: bool | Literal["auto"] = "auto"
    """torch.compile the model. auto: on a CUDA device, off elsewhere (on an H100 it took the HumanML3D preset's
    optimised step from 3.6x to 4.8x the reference's samples/s, docs/performance.md; on CPU it costs minutes of
    compilation for little). true / false: always / never."""
    compile_mode: Literal["default", "reduce-overhead", "max-autotune-no-cudagraphs"] = "default"
    """torch.compile's mode for training (with ``compile``): default; reduce-overhead (CUDA graphs of the forward and
    backward: less host time per step, where a small model's step waits on the host, docs/performance.md); or
    max-autotune-no-cudagraphs (longer compilation, tuned kernels). Length-aware batches compile one graph per batch
    width whatever the mode (``mfm.compilation.compiled_for_training``)."""
    objective: Literal["flow", "diffusion"] = "flow"
    """flow: MFM's conditional flow matching; diffusion: the DDPM baseline on the same backbone (FLAME/FlowMDM)."""
    flow_loss: Literal["velocity", "data"] = "velocity"
    """objective=flow: 'velocity' = MFM's velocity MSE; 'data' = the same error weighted into the motion's space
    (``mfm.flow.loss_space_weight``: the MSE of the x̂1 the velocity implies; not MFM's choice)."""
    flow_temporal_weight: float = 0.0
    """objective=flow: weight of ``mfm.flow.temporal_loss`` (the frame-to-frame change of the implied motion's
    error; MDM's velocity loss in feature space), added to the flow loss. 0 = MFM."""
    flow_bone_weight: float = 0.0
    """objective=flow: weight of ``mfm.flow.bone_length_loss`` (bone lengths of the implied motion against the
    clip's, m²), added to the flow loss. 0 = MFM."""
    flow_bone_target: Literal["frames", "clip_median"] = "frames"
    """objective=flow: what the bone term holds the implied motion's bones to (``mfm.flow.BONE_TARGETS``): 'frames' =
    each frame's bone lengths of the clip (as introduced); 'clip_median' = each bone's median length over the clip's
    frames. For mocap clips the two agree; for a reflow student (launch/distill.py) the "clip" is the teacher's raw
    output, whose bones vary from frame to frame, and 'frames' teaches the student that variation
    (docs/few-step.md, "Bones held to their median"). Ours, not MFM's."""
    flow_trajectory_weight: float = 0.0
    """objective=flow: weight of ``mfm.flow.trajectory_loss`` (the root's integrated path of the implied motion
    against the clip's: ground position m² plus heading rad²), added to the flow loss. 0 = MFM."""
    flow_foot_contact_weight: float = 0.0
    """objective=flow: weight of ``mfm.flow.foot_contact_loss`` (the squared error of the implied motion's foot
    displacements against the clip's, m² per frame, over the frames whose clip labels that foot in contact), added
    to the flow loss. In the spirit of MDM's foot-contact loss (``lambda_fc``); ours, 0 = MFM."""
    flow_root_mean_weight: float = 0.0
    """objective=flow: weight of ``mfm.flow.root_rate_mean_loss`` (the squared clip-mean error of the implied
    motion's root rates: heading rate and ground velocity, normalised units), added to the flow loss. Why: the clip
    mean of a root rate is what a caption fixes ("up in place", "turns around"), and the main MSE charges its error
    about a thousandth of the loss (docs/generator-study.md, "The root's clip mean"). Ours; 0 = MFM."""
    flow_input_perturbation: float = 0.0
    """objective=flow: γ of the input perturbation (Ning et al. 2023, "Input Perturbation Reduces Exposure Bias in
    Diffusion Models", γ 0.1 there; for DDPM, here on the flow path): the network's input is built from the noise
    ``x0 + γ·ξ`` (ξ a second draw) while its target stays the velocity of ``x0``. Why: a sampler's states leave the
    training paths by the network's own errors, and the synthetic preset's in-place jumps drift where they do
    (docs/generator-study.md, "The root's clip mean"). 0 = MFM."""
    flow_trajectory_start_step: int = 0
    """objective=flow: the trajectory term counts only in the updates after the first this many (0: in all). Why:
    from the first step its heavy-tailed gradient, clipped with the main loss's, slows the main loss; late in a
    run it straightens the root's path at little cost (docs/generator-study.md). The validation loss includes the
    term from then on, as the training loss does. Ours, not MFM's."""
    self_condition_start_step: int = 0
    """Self-conditioned models only (``model.self_condition_prob`` > 0): the estimate pass runs only in the updates
    after the first this many (0: in all); before, every row gets zeros, as a solve's first step does. Why: on the
    synthetic preset self-conditioning from the first step kept the in-place jumps in place but, in 2,100 CPU steps,
    the network learnt the counts less well at two training seeds of three; the counts are learnt early without it
    (docs/generator-study.md, "Self-conditioning"). Ours, not Chen et al.'s."""
    flow_trajectory_min_t: float = 0.0
    """objective=flow: the trajectory term counts only for the batch rows trained at a time t >= this (0: all; the
    batch mean still divides by every row). Why it was tried: near the noise end x̂1 can only be the caption's mean
    path, so most of the term there is the spread of the clips' paths, which no network removes; nearer the data the
    path is in x_t and the error is the network's. On the synthetic preset at 0.5 from scratch it kept the jumps in
    place but still cost the counts (docs/generator-study.md, "... only where the path is in x_t"). Ours, not MFM's."""
    flow_trajectory_huber: float = 0.0
    """objective=flow: when > 0 (metres), the trajectory term's per-frame squared path error becomes its
    pseudo-Huber (``mfm.flow.pseudo_huber``): the squared error below this distance, linear beyond, so no frame's
    gradient exceeds 2 × this. Why it was tried: the squared path error of a walk that is metres off early in
    training sends a heavy-tailed gradient that could crowd the main loss out of the clipped update. On the
    synthetic preset at 0.1 m (weight 0.1, from scratch) it still cost the counts and no longer cured the drift
    (docs/generator-study.md, "... with its tail bounded"). 0: squared error. Ours, not MFM's."""
    flow_terms_weighting: Literal["data", "loss"] = "data"
    """objective=flow: how the temporal, bone, trajectory and foot-contact terms are weighted over t
    (``mfm.flow.term_weight``): 'data' = the same at every t (as introduced); 'loss' = as the main loss weighs an x̂1
    error at that t (under the velocity loss 1/(1 − t)², so the terms keep their proportion to it where the
    sampler's last steps are). Not MFM's."""
    flow_velocity_weight_cap: float = 0.0
    """objective=flow, flow_loss=velocity: cap on the weight the velocity loss puts on an x̂1 error, 1/(1 − t)²
    (``mfm.flow.loss_space_weight``): the velocity loss where that is at most the cap, the cap times the data loss
    nearer the data end (9 = from t = 2/3). 0 = no cap (MFM). Not MFM's; in the spirit of Min-SNR-γ (Hang et al.
    2023). Also caps the terms under flow_terms_weighting=loss."""
    flow_feat_bias: float = 1.0
    """objective=flow: Guo et al.'s ``feat_bias`` as a loss weight (``mfm.flow.feat_bias_channel_weight``): the
    squared error of the root's channels (rotation velocity, linear velocity, height: features 0:4) and of the foot
    contacts (the last 4) times feat_bias², the weight text-to-motion's own generator (Comp_v6) trained with by
    dividing those groups' std by 5. 1 = every channel alike (MDM, MFM, FlowMDM). The temporal, bone and trajectory
    terms are not weighted."""
    flow_time_sampling: Literal["uniform", "logit_normal", "grid", "stratified"] = "uniform"
    """objective=flow: the density of the training times (``mfm.flow.warp_time``): 'uniform' = MFM; 'logit_normal' =
    sigmoid(N(flow_time_loc, flow_time_scale²)) (Esser et al. 2024; not MFM's choice); 'stratified' = uniform, but
    each micro-batch's B times one per stratum [k/B, (k+1)/B) (Kingma et al. 2021's low-discrepancy sampler, with
    a random permutation of the strata over the rows; ``mfm.flow.stratify_times``; not MFM's); 'grid' = the times
    0, 1/K, ..., (K−1)/K of Euler with K = flow_time_grid_steps steps, for a reflow student's pair set
    (launch/distill.py; rectified flow's k-step distillation, Liu et al. 2022), not for training from data."""
    flow_time_loc: float = 0.0
    """flow_time_sampling=logit_normal: the normal's mean (< 0 toward the noise, > 0 toward the data)."""
    flow_time_scale: float = 1.0
    """flow_time_sampling=logit_normal: the normal's standard deviation (> 0)."""
    flow_time_grid_steps: int = 2
    """flow_time_sampling=grid: K, the Euler steps whose times are trained (2: t = 0 and 1/2, which serve the 1-step
    and the 2-step sampler; a student's distill.student_steps must divide it). With ``model.sampling_times`` the
    times are those (K must be their number): e.g. ``model.sampling_times=[0,0.9]`` trains t = 0 and 0.9, the
    times the model's 2-step sampler then starts its steps at."""
    flow_grid_inputs: Literal["interpolated", "own_path"] = "interpolated"
    """flow_time_sampling=grid: a row at the grid time k/K is fed 'interpolated', the straight path's point between
    its noise and its pair's motion (rectified flow's k-step distillation, Liu et al. 2022), or 'own_path', the
    state the student's own first k Euler steps reach from that noise, without gradient, trained toward the same
    motion (backward distillation, Kohler et al. 2024, "Imagine Flash"): the later steps learn to mend what the
    earlier ones really leave. Costs K − 1 gradient-free passes per update. Ours for motion, not MFM's."""
    critic_weight: float = 0.0
    """objective=flow: weight of an adversarial term (adversarial distillation; Sauer et al. 2023, "Adversarial
    Diffusion Distillation"): a caption-conditioned critic (``mfm.critic.MotionCritic``) trains alongside the model
    with its own Adam, telling the batch's motions (a student's pair set: its teacher's motions) from the motion
    each row's trained pass leads to (x̂1: a one-step student's one-step motion), and the model's loss adds
    critic_weight × the critic's hinge loss of that motion. A fixed weight, not ADD's adaptive one (which needs a
    second backward through the output layer; the fixed weight did the same in the probes: docs/few-step.md,
    "A critic in the trainer"; 0.0022 there for a one-step student). The critic and its optimiser are part of the
    resume state. Ours for motion; 0 = off (MFM, reflow)."""
    critic_lr: float = 1e-4
    """The critic's Adam learning rate (constant; no warm-up)."""
    critic_betas: tuple[float, float] = (0.5, 0.9)
    """The critic's Adam betas (a low β1, as GAN critics are usually trained)."""
    critic_channels: int = 128
    """The critic's width (``mfm.critic.MotionCritic``: 4 dilated residual blocks, 3-frame kernels)."""
    flow_noise: Literal["independent", "recorded"] = "independent"
    """objective=flow: where each training pair's noise x0 comes from. 'independent' (MFM): fresh N(0, I) from the
    trainer's generator. 'recorded' (reflow, ``launch/distill.py``): the noise the teacher integrated to make the
    record, ``mfm.solvers.draw_noise`` of the record's ``noise_seed`` and length; needs a distillation pair set
    (its manifest's ``pairs`` section) whose clips are never cropped (data.unit_length=1 and every length <=
    data.window, checked before training)."""
    shortcut_fraction: float = 0.25
    """model.shortcut_levels > 0 (a shortcut model, ``mfm.shortcut``): the share of every batch's rows trained by
    self-consistency (the others by flow matching). Frans et al. 2024: 1/8 (their bootstrap_every 8)."""
    shortcut_guidance: float = 1.0
    """model.shortcut_levels > 0: the classifier-free guidance scale built into the shortcut levels (the finest
    level's half steps take the flow field guided at this scale, on model.guided_features' channels; the authors'
    bootstrap_cfg). launch/distill.py sets it to the teacher's sampling guidance. 1 = none."""
    init_from: str | None = None
    """A checkpoint folder (or a run folder: its newest complete checkpoint) whose weights (EMA, else the raw ones)
    start this run, and its EMA, instead of a random initialisation; the architecture must match. Read at a fresh
    start only: a resumed run (train.resume) continues from its own checkpoint and never reads it. null: random."""
    diffusion: Literal["flowmdm", "flame", "mdm"] = "flowmdm"
    """With objective=diffusion: flowmdm = 1000-step cosine, x0-prediction (mdm: the same process, the name
    converted MDM checkpoints carry); flame = cosine, eps-prediction with
    learned variance and the hybrid loss L_simple + lambda * L_vlb (the model then outputs 2 x feature_dim)."""

    def __post_init__(self) -> None:
        coerce_fields(self)
        _require(self.max_steps >= 1, f"train.max_steps must be >= 1, got {self.max_steps}")
        _require(self.flow_bone_weight >= 0, f"train.flow_bone_weight must be >= 0, got {self.flow_bone_weight}")
        _require(self.flow_bone_target == "frames" or self.flow_bone_weight > 0,
                 f"train.flow_bone_target={self.flow_bone_target} changes the bone term, which is off "
                 "(train.flow_bone_weight=0)")
        _require(self.flow_trajectory_weight >= 0,
                 f"train.flow_trajectory_weight must be >= 0, got {self.flow_trajectory_weight}")
        _require(self.flow_input_perturbation >= 0,
                 f"train.flow_input_perturbation must be >= 0, got {self.flow_input_perturbation}")
        _require(self.flow_root_mean_weight >= 0,
                 f"train.flow_root_mean_weight must be >= 0, got {self.flow_root_mean_weight}")
        _require(self.flow_foot_contact_weight >= 0,
                 f"train.flow_foot_contact_weight must be >= 0, got {self.flow_foot_contact_weight}")
        for name in ("flow_trajectory_start_step", "self_condition_start_step"):
            start = getattr(self, name)
            _require(0 <= start < self.max_steps,
                     f"train.{name} must be in [0, train.max_steps={self.max_steps}), got {start}")
        _require(0 <= self.flow_trajectory_min_t < 1,
                 f"train.flow_trajectory_min_t must be in [0, 1), got {self.flow_trajectory_min_t}")
        _require(self.flow_trajectory_huber >= 0,
                 f"train.flow_trajectory_huber must be >= 0, got {self.flow_trajectory_huber}")
        _require(self.flow_temporal_weight >= 0, f"train.flow_temporal_weight must be >= 0, got {self.flow_temporal_weight}")
        _require(self.flow_time_scale > 0, f"train.flow_time_scale must be > 0, got {self.flow_time_scale}")
        _require(self.flow_time_grid_steps >= 1,
                 f"train.flow_time_grid_steps must be >= 1, got {self.flow_time_grid_steps}")
        _require(self.flow_feat_bias > 0,
                 f"train.flow_feat_bias must be > 0 (1 = no weighting), got {self.flow_feat_bias}")
        _require(self.flow_velocity_weight_cap >= 0,
                 f"train.flow_velocity_weight_cap must be >= 0 (0 = no cap), got {self.flow_velocity_weight_cap}")
        _require(self.flow_velocity_weight_cap == 0 or self.flow_loss == "velocity",
                 f"train.flow_velocity_weight_cap applies to train.flow_loss=velocity, not {self.flow_loss!r}")
        _require(self.flow_time_sampling != "grid" or self.flow_noise == "recorded",
                 "train.flow_time_sampling=grid trains only the times a K-step sampler visits, so the network learns "
                 "no flow between them: it is for a reflow student's pair set (launch/distill.py, which sets "
                 "train.flow_noise=recorded), not for training from data")
        _require(self.flow_noise == "independent" or self.objective == "flow",
                 f"train.flow_noise={self.flow_noise} is a flow-matching setting; train.objective is {self.objective}")
        _require(self.critic_weight >= 0, f"train.critic_weight must be >= 0 (0: no critic), got {self.critic_weight}")
        _require(self.critic_lr > 0, f"train.critic_lr must be > 0, got {self.critic_lr}")
        _require(all(0.0 <= b < 1.0 for b in self.critic_betas),
                 f"train.critic_betas must lie in [0, 1), got {self.critic_betas}")
        _require(self.critic_channels >= 1, f"train.critic_channels must be >= 1, got {self.critic_channels}")
        _require(self.critic_weight == 0 or self.objective == "flow",
                 f"train.critic_weight > 0 judges the motion a flow model's velocity leads to: it needs "
                 f"train.objective=flow, got {self.objective}")
        _require(self.critic_weight == 0 or self.mixed_precision != "fp16",
                 "train.critic_weight > 0 does not go with train.mixed_precision=fp16: the critic's own update is not "
                 "loss-scaled (use bf16 or no)")
        _require(0 < self.shortcut_fraction < 1, f"train.shortcut_fraction must be in (0, 1), got {self.shortcut_fraction}")
        _require(self.shortcut_guidance >= 0, f"train.shortcut_guidance must be >= 0, got {self.shortcut_guidance}")
        _require(self.init_seed is None or self.init_seed >= 0,
                 f"train.init_seed must be >= 0, or null for train.seed, got {self.init_seed}")
        _require(self.init_from is None or bool(self.init_from.strip()),
                 "train.init_from must be a checkpoint folder, or null for a random initialisation")
        _require(self.log_every >= 1, f"train.log_every must be >= 1, got {self.log_every}")
        _require(self.save_every >= 1, f"train.save_every must be >= 1, got {self.save_every}")
        _require(self.keep_last >= 0, f"train.keep_last must be >= 0 (0 keeps all), got {self.keep_last}")
        _require(bool(self.resume.strip()), "train.resume must be 'auto', 'never' or a checkpoint path")
        _require(
            not self.resume_discard_newer or self.resume not in ("auto", "never"),
            f"train.resume_discard_newer=true goes with train.resume=PATH (a checkpoint folder), not "
            f"train.resume={self.resume}",
        )
        _require(bool(self.out_dir.strip()), "train.out_dir must not be empty")
        _require(self.seed >= 0, f"train.seed must be >= 0, got {self.seed}")
        _require(self.nonfinite_budget >= 0, f"train.nonfinite_budget must be >= 0, got {self.nonfinite_budget}")
        _require(not (self.step_sync == "deferred" and self.mixed_precision == "fp16"),
                 "train.step_sync=deferred does not go with train.mixed_precision=fp16: fp16's loss scale is decided on "
                 "the host every step (use bf16, or train.step_sync=every_step)")
        _require(self.fp16_init_scale > 0, f"train.fp16_init_scale must be > 0, got {self.fp16_init_scale}")
        _require(self.fp16_growth_interval >= 1,
                 f"train.fp16_growth_interval must be >= 1, got {self.fp16_growth_interval}")
        _require(0 < self.fp16_min_scale <= self.fp16_init_scale,
                 f"train.fp16_min_scale must lie in (0, train.fp16_init_scale={self.fp16_init_scale}], got "
                 f"{self.fp16_min_scale}")
        _require(self.val_every >= 0, f"train.val_every must be >= 0 (0 disables validation), got {self.val_every}")
        _require(self.val_batches >= 1, f"train.val_batches must be >= 1, got {self.val_batches}")
        _require(self.preview_every >= 0,
                 f"train.preview_every must be >= 0 (0 disables previews), got {self.preview_every}")
        _require(self.preview_count >= 1, f"train.preview_count must be >= 1, got {self.preview_count}")
        _require(all(isinstance(p, str) and p.strip() for p in self.preview_prompts),
                 f"train.preview_prompts must be non-empty strings, got {list(self.preview_prompts)}")


DISTILL_METHODS = ("reflow",)


@dataclasses.dataclass(frozen=True, kw_only=True)
class DistillConfig:
    """How a few-step student is made from its teacher (``launch/distill.py``; pipeline/training/distill.py). The
    ``teacher*`` fields are recorded by launch/distill.py from the teacher's checkpoint (not settings: given ones
    are refused), so the student's config.yaml, every checkpoint and an export's model card say where it came from."""

    method: Literal["reflow", "shortcut"] = "reflow"
    """reflow (Liu et al. 2022, rectified flow; Luhman & Luhman 2021 at one step): the teacher integrates its guided
    ODE from recorded noise, and the student learns the straight path between that noise and the teacher's motion.
    shortcut (Frans et al. 2024): the student, the teacher's network with a step-size input
    (model.shortcut_levels), trains on the teacher's dataset by flow matching plus self-consistency (one step of d
    = two of d/2), with the teacher's guidance built into its levels (train.shortcut_guidance); no pair set."""
    pairs_per_caption: int = 1
    """Teacher solutions per caption of the training split (each from its own noise seed)."""
    seed: int = 0
    """Seed of the pairs' noise: pair i's noise seed is ``SeedSequence([seed, i])`` (as launch/sample.py's)."""
    pair_order: Literal["interleaved", "grouped"] = "interleaved"
    """The order of the pairs (their indices, so their seeds, and the order the shards hold them in). interleaved:
    repeat by repeat, every caption of the split once per repeat, so any run of records in a shard spans the
    captions, and the loader's shuffle buffer (the teacher's data.shuffle_buffer, 64 on the embedded default) mixes
    them into every batch. grouped (the order of pair sets made before 2026-12-06): a caption's pairs_per_caption
    pairs one after another, so with many pairs per caption a shard holds one clip's pairs and the student trains
    on one clip for hundreds of steps at a time (docs/few-step.md, "Pairs in the order they were made"). The same
    when pairs_per_caption is 1."""
    batch_size: int = 64
    """Motions per teacher batch while making the pairs (does not change the pairs)."""
    student_steps: int = 2
    """The student's default sampler steps (its model.sampling_steps): 1 or 2 function evaluations."""
    flow_map_probes: int = 32
    """method=reflow: captions whose first pair the teacher solves again from a perturbed noise, to measure how far
    its motion moves per unit change of the noise (pipeline.generation.pairs.probe_amplification; 0: not measured).
    Recorded in the pair set's manifest and the student's config; a rough map gets a warning (docs/few-step.md,
    'A rough teacher'). Costs two extra teacher solves per probe. Not part of the pair set's identity: a reused set
    keeps the figure it was made with."""
    shortcut_levels: int = 2
    """method=shortcut: the student's model.shortcut_levels K (Euler at 1, 2, ..., 2^(K−1) steps; the flow field
    at 2^K or more). 2: steps 1 and 2, the finest built from the flow field at 4 steps (docs/few-step.md)."""
    teacher: str = ""
    """The teacher's checkpoint folder (recorded)."""
    teacher_checkpoint_id: str = ""
    """The teacher checkpoint's id (sha256 of its COMPLETE marker; recorded)."""
    teacher_step: int = 0
    """The teacher's training step (recorded)."""
    teacher_solver: str = "euler"
    """The ODE solver of the pairs (recorded: the teacher's default, euler)."""
    teacher_steps: int = 10
    """The solver steps of the pairs (recorded: the teacher's model.sampling_steps)."""
    teacher_guidance: float = 2.5
    """The guidance scale of the pairs (recorded: the teacher's model.sampling_guidance)."""
    teacher_guided_features: str = "all"
    """The channels guidance mixed in the pairs (recorded: the teacher's model.guided_features)."""
    teacher_flow_map_amplification: float | None = None
    """The median of the pair set's probed flow-map amplifications (recorded from its manifest; None: not measured,
    e.g. flow_map_probes=0, a pair set made before it was measured, or method=shortcut)."""

    def __post_init__(self) -> None:
        coerce_fields(self)
        _require(self.pairs_per_caption >= 1, f"distill.pairs_per_caption must be >= 1, got {self.pairs_per_caption}")
        _require(self.seed >= 0, f"distill.seed must be >= 0, got {self.seed}")
        _require(self.batch_size >= 1, f"distill.batch_size must be >= 1, got {self.batch_size}")
        _require(self.flow_map_probes >= 0, f"distill.flow_map_probes must be >= 0, got {self.flow_map_probes}")
        _require(self.student_steps >= 1, f"distill.student_steps must be >= 1, got {self.student_steps}")
        _require(1 <= self.shortcut_levels <= 10, f"distill.shortcut_levels must be in [1, 10], got {self.shortcut_levels}")
        _require(self.method != "shortcut" or self.student_steps in level_steps(self.shortcut_levels),
                 f"distill.student_steps={self.student_steps}: a shortcut student with distill.shortcut_levels="
                 f"{self.shortcut_levels} samples in {', '.join(map(str, level_steps(self.shortcut_levels)))} steps")
        _require(self.teacher_steps >= 1, f"distill.teacher_steps must be >= 1, got {self.teacher_steps}")


@dataclasses.dataclass(frozen=True, kw_only=True)
class TrainConfig:
    """Everything a training run needs; saved resolved (``to_dict``) in every checkpoint and run folder."""

    data: DataConfig = dataclasses.field(default_factory=DataConfig)
    model: ModelConfig = dataclasses.field(default_factory=ModelConfig)
    optim: OptimConfig = dataclasses.field(default_factory=OptimConfig)
    train: TrainLoopConfig = dataclasses.field(default_factory=TrainLoopConfig)
    distill: DistillConfig | None = None
    """A few-step student's distillation (launch/distill.py writes it); null for an ordinary run."""

    def __post_init__(self) -> None:
        coerce_fields(self)
        _require(
            self.train.flow_noise == "independent" or self.data.unit_length == 1,
            f"train.flow_noise=recorded needs data.unit_length=1 (got {self.data.unit_length}): a crop would cut the "
            "teacher's motion away from the noise it was integrated from",
        )
        _require(
            self.train.objective == "flow" or self.model.prediction == "velocity",
            f"model.prediction={self.model.prediction!r} is a flow-matching parametrisation; the diffusion objective "
            "sets its own target (train.diffusion): use model.prediction=velocity",
        )
        _require(
            self.model.self_condition_prob == 0 or self.train.objective == "flow",
            "model.self_condition_prob > 0 (self-conditioning) trains with train.objective=flow",
        )
        _require(
            self.train.self_condition_start_step == 0 or self.model.self_condition_prob > 0,
            "train.self_condition_start_step > 0 starts self-conditioning late: it needs model.self_condition_prob > 0",
        )
        _require(
            self.train.critic_weight == 0 or self.model.shortcut_levels == 0,
            "train.critic_weight > 0 (a critic) trains with the flow-matching loss; a shortcut model's "
            "self-consistency rows have no motion to judge: use model.shortcut_levels=0",
        )
        _require(
            self.optim.optimizer != "muon" or self.train.step_sync != "deferred",
            "optim.optimizer=muon does not go with train.step_sync=deferred: a deferred step is skipped on the device "
            "through fused AdamW's found_inf, which Muon does not take (use train.step_sync=every_step or auto)",
        )
        _require(
            self.model.shortcut_levels == 0 or self.train.objective == "flow",
            "model.shortcut_levels > 0 (a shortcut model) trains with train.objective=flow",
        )
        _require(
            self.train.flow_time_sampling != "stratified" or self.model.shortcut_levels == 0,
            "train.flow_time_sampling=stratified spreads a flow-matching batch's times one per stratum; a shortcut "
            "model's batch splits its rows between two objectives: use uniform or logit_normal",
        )
        _require(
            self.train.flow_grid_inputs == "interpolated" or (
                self.train.objective == "flow" and self.train.flow_time_sampling == "grid"
                and self.model.self_condition_prob == 0 and self.model.shortcut_levels == 0
                and self.train.flow_input_perturbation == 0),
            "train.flow_grid_inputs=own_path feeds grid times the model's own Euler states: it needs "
            "train.objective=flow with train.flow_time_sampling=grid, and no self-conditioning, shortcut levels or "
            "input perturbation",
        )
        steps = self.distill.student_steps if self.distill is not None else 0
        times = self.model.sampling_times
        _require(
            times is None or self.train.flow_time_sampling != "grid" or (
                len(times) == self.train.flow_time_grid_steps and (not steps or steps in (1, len(times)))),
            f"model.sampling_times={list(times or ())} are the times train.flow_time_sampling=grid trains: "
            f"train.flow_time_grid_steps must be {len(times or ())} and distill.student_steps 1 or {len(times or ())}",
        )
        _require(
            not steps or self.train.flow_time_sampling != "grid" or times is not None
            or self.train.flow_time_grid_steps % steps == 0,
            f"train.flow_time_grid_steps={self.train.flow_time_grid_steps} does not hold the times of the student's "
            f"{steps}-step sampler (distill.student_steps): use a multiple of {steps}",
        )
        _require(
            self.train.objective == "flow" or self.model.guided_features == "all",
            f"model.guided_features={self.model.guided_features!r} guides a flow model's velocity channels; a "
            "diffusion model's guidance mixes every channel of its prediction (FLAME): use model.guided_features=all",
        )
        prefix = self.model.num_prefix_tokens
        _require(
            self.data.window + prefix <= self.model.max_len,
            f"data.window ({self.data.window}) + {prefix} prefix token(s) exceeds model.max_len ({self.model.max_len})",
        )
        _require(
            self.data.batching == "fixed" or not self.model.attend_padding,
            "data.batching=length_aware needs model.attend_padding=false: a model that attends to the padding "
            "(MFM/MDM's behaviour) gives a clip another output for every batch width, so the loss per clip would "
            "change with its batch mates",
        )
        if self.model.length_token:
            _require(
                self.data.window <= self.model.max_frames,
                f"data.window ({self.data.window}) exceeds model.max_frames ({self.model.max_frames}), "
                "the largest length the length token can embed",
            )


def wandb_mode(setting: str, fallback: str = "offline") -> str:
    """The W&B mode a job runs with, from its ``wandb`` setting (``train.wandb``, the evaluator's ``output.wandb``):
    an explicit ``offline``/``online``/``disabled`` as given, whatever the environment's ``WANDB_MODE`` says (so
    ``disabled`` starts no W&B run and writes no wandb folder); ``auto``, the environment's ``WANDB_MODE`` when set,
    else ``fallback``."""
    if setting != "auto":
        return setting
    return os.environ.get("WANDB_MODE") or fallback


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise ConfigError(message)


# ---------------------------------------------------------------------------------------------------------------
# Type checking and conversion
# ---------------------------------------------------------------------------------------------------------------


def coerce_fields(obj: Any) -> None:
    """Type-check every field of dataclass ``obj`` in place (lists become tuples where the type says so).

    Called first in each section's ``__post_init__`` so that direct construction is checked like YAML input.
    """
    hints = get_type_hints(type(obj))
    for field in dataclasses.fields(obj):
        value = getattr(obj, field.name)
        coerced = _coerce(value, hints[field.name], f"{type(obj).__name__}.{field.name}")
        if coerced is not value:
            object.__setattr__(obj, field.name, coerced)  # frozen dataclasses: still being initialised


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _coerce(value: Any, tp: Any, where: str) -> Any:
    """Return ``value`` checked against (and, where lossless, converted to) type ``tp``; ``where`` names it."""
    origin = get_origin(tp)
    if tp is Any:
        return value
    if origin is Literal:
        for choice in get_args(tp):
            if value == choice and type(value) is type(choice):
                return choice
        raise ConfigError(f"{where}: expected one of {list(get_args(tp))}, got {value!r}")
    if origin is Union or origin is types.UnionType:
        return _coerce_union(value, tp, where)
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if isinstance(value, Mapping):
            return _from_dict(tp, value, where)
        raise ConfigError(f"{where}: expected a mapping for section {tp.__name__}, got {value!r}")
    if tp in (list, tuple) or origin in (list, tuple):
        return _coerce_sequence(value, tp, where)
    if tp is dict or origin is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a mapping, got {value!r}")
        key_type, value_type = get_args(tp) or (Any, Any)
        return {
            _coerce(k, key_type, f"{where} key"): _coerce(v, value_type, f"{where}.{k}") for k, v in value.items()
        }
    return _coerce_scalar(value, tp, where)


def _coerce_union(value: Any, tp: Any, where: str) -> Any:
    arms = get_args(tp)
    if value is None:
        if type(None) in arms:
            return None
        raise ConfigError(f"{where}: expected {_type_name(tp)}, got None")
    # A value already of one arm's type keeps it (``int | float``: 1.0 stays a float, 3 an int).
    if type(value) in arms:
        return value
    for arm in arms:
        if arm is type(None):
            continue
        try:
            return _coerce(value, arm, where)
        except ConfigError:
            continue
    raise ConfigError(f"{where}: expected {_type_name(tp)}, got {value!r}")


def _coerce_sequence(value: Any, tp: Any, where: str) -> Any:
    if not isinstance(value, (list, tuple)):
        raise ConfigError(f"{where}: expected a list, got {value!r}")
    origin = get_origin(tp) or tp
    args = get_args(tp)
    if origin is list:
        item_type = args[0] if args else Any
        return [_coerce(v, item_type, f"{where}[{i}]") for i, v in enumerate(value)]
    if len(args) == 2 and args[1] is Ellipsis:  # tuple[X, ...]
        return tuple(_coerce(v, args[0], f"{where}[{i}]") for i, v in enumerate(value))
    if args:
        if len(value) != len(args):
            raise ConfigError(f"{where}: expected {len(args)} items, got {len(value)}: {value!r}")
        return tuple(_coerce(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args, strict=True)))
    return tuple(value)


def _coerce_scalar(value: Any, tp: Any, where: str) -> Any:
    # bool is a subclass of int: reject it explicitly so `num_layers: true` is an error, not 1.
    if tp is bool:
        if isinstance(value, bool):
            return value
    elif tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():  # 6.0e5 steps
            return int(value)
    elif tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
    elif tp is str:
        if isinstance(value, str):
            return value
        if isinstance(value, Path):
            return str(value)
    elif tp is Path:
        if isinstance(value, (str, Path)):
            return Path(value)
    else:
        raise ConfigError(f"{where}: unsupported field type {_type_name(tp)} in a config dataclass")
    raise ConfigError(f"{where}: expected {_type_name(tp)}, got {type(value).__name__} {value!r}")


# ---------------------------------------------------------------------------------------------------------------
# dict <-> dataclass
# ---------------------------------------------------------------------------------------------------------------


def to_dict(cfg: Any) -> dict[str, Any]:
    """Plain nested dict of a config dataclass (tuples as lists): YAML/JSON-safe, and ``from_dict`` inverts it."""
    if not dataclasses.is_dataclass(cfg) or isinstance(cfg, type):
        raise TypeError(f"to_dict expects a dataclass instance, got {type(cfg).__name__}")
    return {field.name: _plain(getattr(cfg, field.name)) for field in dataclasses.fields(cfg)}


def _plain(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return to_dict(value)
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, Path):
        return str(value)
    return value


def from_dict(cls: type[T], data: Mapping[str, Any]) -> T:
    """Build ``cls`` from a (possibly partial) nested dict; missing keys keep their defaults, unknown keys fail."""
    return _from_dict(cls, data, "")


def _from_dict(cls: type[T], data: Mapping[str, Any], where: str) -> T:
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where or cls.__name__}: expected a mapping, got {data!r}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(str(k) for k in data if k not in fields)
    if unknown:
        dotted = [_join(where, k) for k in unknown]
        scope = f" under {where!r}" if where else ""
        raise ConfigError(f"unknown config key(s) {dotted}; valid keys{scope}: {sorted(fields)}")
    hints = get_type_hints(cls)
    kwargs = {name: _coerce(value, hints[name], _join(where, name)) for name, value in data.items()}
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (ValueError, TypeError) as err:  # a section's own __post_init__ (e.g. ModelConfig) rejected a value
        raise ConfigError(f"{where or cls.__name__}: {err}") from err


def _join(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else str(key)


# ---------------------------------------------------------------------------------------------------------------
# YAML presets and overrides
# ---------------------------------------------------------------------------------------------------------------


class _Yaml12Loader(yaml.SafeLoader):
    """SafeLoader with YAML 1.2 booleans and floats (see the module docstring)."""


_BOOL_TAG = "tag:yaml.org,2002:bool"
_FLOAT_TAG = "tag:yaml.org,2002:float"
_Yaml12Loader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag not in (_BOOL_TAG, _FLOAT_TAG)]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_Yaml12Loader.add_implicit_resolver(_BOOL_TAG, re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF"))
# Appended after the int resolver, so plain integers still resolve to int first.
_Yaml12Loader.add_implicit_resolver(
    _FLOAT_TAG,
    re.compile(
        r"^(?:[-+]?(?:(?:[0-9]+\.[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?|[0-9]+[eE][-+]?[0-9]+)"
        r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"
    ),
    list("-+0123456789."),
)


def parse_yaml(text: str, source: str = "<string>") -> Any:
    """Parse YAML text with the config's scalar rules; errors name ``source``."""
    try:
        return yaml.load(text, Loader=_Yaml12Loader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as err:
        raise ConfigError(f"{source}: invalid YAML: {err}") from err


def available_presets(cls: type | None = None) -> list[str]:
    """Preset names in configs/ (``tiny``, ``default``, ...); with ``cls``, only those that load as ``cls`` (the
    training presets for TrainConfig, not the evaluation protocols), so a ``--help`` lists what runs."""
    names = sorted(p.stem for p in CONFIG_DIR.glob("*.yaml"))
    if cls is None:
        return names
    fitting = []
    for name in names:
        try:
            load_config(cls, name)
        except (ConfigError, FileNotFoundError):
            continue
        fitting.append(name)
    return fitting


def field_docs(cls: type) -> dict[str, str]:
    """The first line of the string literal under each field of dataclass ``cls`` (the attribute docstrings this
    project writes), read from the class source; {} when the source is not available."""
    import ast
    import inspect
    import textwrap

    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except (OSError, TypeError, SyntaxError):
        return {}
    body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
    docs: dict[str, str] = {}
    for field, after in zip(body, body[1:]):
        if (isinstance(field, ast.AnnAssign) and isinstance(field.target, ast.Name) and isinstance(after, ast.Expr)
                and isinstance(after.value, ast.Constant) and isinstance(after.value.value, str)):
            docs[field.target.id] = " ".join(after.value.value.split())
    return docs


def describe_config(cfg: Any, prefix: str = "") -> list[str]:
    """Every key of a resolved config, one line each: ``key = value  (default: d)  # doc``, nested sections dotted;
    what ``--print-config`` prints."""
    lines: list[str] = []
    docs = field_docs(type(cfg))
    defaults = _defaults_of(type(cfg))
    for field in dataclasses.fields(cfg):
        value = getattr(cfg, field.name)
        key = f"{prefix}{field.name}"
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            lines.append(f"[{key}]" + (f"  # {docs[field.name]}" if field.name in docs else ""))
            lines += describe_config(value, f"{key}.")
            continue
        default = defaults.get(field.name, dataclasses.MISSING)
        line = f"{key} = {_inline_yaml(value)}"
        if default is not dataclasses.MISSING and _plain(default) != _plain(value):
            line += f"  (default: {_inline_yaml(default)})"
        if field.name in docs:
            line += f"  # {docs[field.name]}"
        lines.append(line)
    return lines


def _inline_yaml(value: Any) -> str:
    """A value as it would be written in a preset or an override, on one line."""
    return yaml.safe_dump(_plain(value), default_flow_style=True, width=10**6).strip().removesuffix("...").strip()


def _defaults_of(cls: type) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for field in dataclasses.fields(cls):
        if field.default is not dataclasses.MISSING:
            out[field.name] = field.default
        elif field.default_factory is not dataclasses.MISSING:
            out[field.name] = field.default_factory()
    return out


def resolve_preset(preset: str | Path) -> Path:
    """A preset name (``"tiny"`` -> configs/tiny.yaml) or a YAML file path, checked to exist."""
    path = Path(preset)
    looks_like_path = isinstance(preset, Path) or path.suffix in (".yaml", ".yml") or len(path.parts) > 1
    if looks_like_path:
        if not path.is_file():
            raise FileNotFoundError(f"config file {path} does not exist")
        return path
    candidate = CONFIG_DIR / f"{preset}.yaml"
    if not candidate.is_file():
        raise FileNotFoundError(
            f"no config preset named {preset!r} ({candidate} does not exist); available: {available_presets()}"
        )
    return candidate


def read_preset(preset: str | Path) -> dict[str, Any]:
    """The raw (unvalidated) nested dict of a preset; an empty file is an empty dict."""
    path = resolve_preset(preset)
    data = parse_yaml(path.read_text(encoding="utf-8"), source=str(path))
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: the top level must be a mapping of sections, got {type(data).__name__}")
    return data


def parse_override(text: str) -> tuple[list[str], Any]:
    """``"optim.lr=3e-4"`` -> ``(["optim", "lr"], 0.0003)``; the value is parsed as YAML (``key=`` gives None)."""
    key, sep, raw = text.partition("=")
    keys = key.strip().split(".")
    if not sep or not all(k.strip() for k in keys):
        raise ConfigError(f"override {text!r} is not of the form section.key=value")
    return [k.strip() for k in keys], parse_yaml(raw, source=f"override {text!r}")


def _check_key_path(cls: type, keys: list[str], override: str) -> None:
    """Fail naming the override if ``keys`` does not lead to a field of ``cls``'s tree."""
    section: Any = cls
    for depth, key in enumerate(keys):
        where = ".".join(keys[:depth])
        if not (isinstance(section, type) and dataclasses.is_dataclass(section)):
            raise ConfigError(f"override {override!r}: {where!r} is a value, not a section")
        hints = get_type_hints(section)
        names = [f.name for f in dataclasses.fields(section) if f.init]
        if key not in names:
            scope = f"under {where!r}" if where else "at the top level"
            raise ConfigError(
                f"override {override!r}: unknown config key {'.'.join(keys[: depth + 1])!r}; "
                f"valid keys {scope}: {names}"
            )
        section = _dataclass_in(hints[key])


def _dataclass_in(tp: Any) -> Any:
    """The dataclass inside ``tp`` (also inside Optional[...]), else ``tp`` itself."""
    if get_origin(tp) in (Union, types.UnionType):
        for arm in get_args(tp):
            if dataclasses.is_dataclass(arm):
                return arm
    return tp


def _set_nested(data: dict[str, Any], keys: list[str], value: Any) -> None:
    node = data
    for key in keys[:-1]:
        child = node.get(key)
        if not isinstance(child, dict):
            child = {}
            node[key] = child
        node = child
    node[keys[-1]] = value


def load_config(cls: type[T], preset: str | Path | Mapping[str, Any] | None = None, overrides: Iterable[str] = (),
                values: Mapping[str, Any] | None = None) -> T:
    """Resolve a config: ``cls`` defaults, then the preset (name in configs/, YAML path, or an already-read nested
    dict such as a checkpoint's resolved config), then ``values`` (dotted
    key -> value, already typed: what a command line's flags set), then the overrides.

    Raises ConfigError (a ValueError) naming the offending key, override or file, and FileNotFoundError for a
    preset that does not exist.
    """
    if isinstance(preset, Mapping):
        data: dict[str, Any] = copy.deepcopy(dict(preset))
    else:
        data = {} if preset is None else read_preset(preset)
    for key, value in (values or {}).items():
        keys = key.split(".")
        _check_key_path(cls, keys, f"{key}={value!r}")
        _set_nested(data, keys, value)
    for text in overrides:
        keys, value = parse_override(text)
        _check_key_path(cls, keys, text)
        _set_nested(data, keys, value)
    return _from_dict(cls, data, "")


def to_yaml(cfg: Any) -> str:
    """The resolved config as YAML (loads back with ``load_config(type(cfg), path)``)."""
    return yaml.safe_dump(to_dict(cfg), sort_keys=False)
