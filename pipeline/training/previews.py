"""Samples while training (``train.preview_every``): rank 0 generates the same few prompts with the EMA weights
every so many steps and shows them as a contact sheet, with their plausibility figures.

What a preview leaves as it was, so a run is bit-identical with previews on or off:

* the weights: the EMA weights are loaded into a private copy of the bare model (one more set of weights in memory,
  eval mode, gradients off); the training model and its EMA are only read;
* the random streams: the noise of sample ``i`` comes from a CPU generator of its own seeded with
  ``SeedSequence([train.seed, tag, i])`` (the same noise at every preview, so sheets differ only by the weights),
  lengths for given prompts from another; the global Python / NumPy / torch / CUDA RNGs are captured and restored
  around every preview anyway (a text encoder's construction draws from the global torch RNG);
* the data stream: the preview captions are read once, on rank 0, with a reader of their own (no shuffling, no
  workers), never through the training loader;
* the collectives: only rank 0 previews, outside any collective; the other ranks go on to the next step's
  all-reduce, where they wait for rank 0 (a preview is a few seconds), so every rank runs the same collectives.

Sampling: flow models integrate with euler, the model's ``sampling_steps`` steps (the samplers' default: 10, a
few-step student's 2); diffusion models use
ddim with :data:`DIFFUSION_STEPS` respaced steps (the full 1,000-step chain would cost a hundred times a flow
preview). Guidance is the model's ``sampling_guidance`` (a FLAME-preset model: its own 8.0), pose-only when the
model guides the pose alone; the output smoothing is the model's ``output_smoothing`` (FLAME: σ = 1). The joints are
recovered from the ric block (``mfm.features.features_to_joints``) as ``launch/sample.py`` does by default.

A preview that fails (an encoder that cannot be built, a full disk) is logged once and previews stop for the rest of
the run: nothing here may stop training.
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mfm.composition import bind_inputs
from mfm.diffusion import GaussianDiffusion
from mfm.diffusion_sampling import BASELINE_SAMPLING, BoneKeeping, sample_diffusion, smooth_over_time
from mfm.export import render_contact_sheet
from mfm.features import features_to_joints
from mfm.guidance import guided_feature_mask
from mfm.metrics import padded_motions, plausibility
from mfm.model import ModelConfig
from mfm.shortcut import sampler_step_size
from mfm.skeleton import Skeleton, get_skeleton
from mfm.solvers import sample, sample_lengths, seeded_generators, step_grid
from pipeline import checkpoint as ckpt
from pipeline.config import TrainConfig
from pipeline.data.stream import Manifest, backend_for_format, iter_motions
from pipeline.training.reporting import PREVIEW_PREFIX

logger = logging.getLogger(__name__)

PREVIEW_SUBDIR = "previews"
FLOW_SOLVER = "euler"
DIFFUSION_SAMPLER, DIFFUSION_STEPS = "ddim", 50
_SEED_TAG = 0x70726576  # "prev": keeps the preview noise apart from every other stream seeded from train.seed


def preview_path(out_dir: Path, step: int) -> Path:
    return Path(out_dir) / PREVIEW_SUBDIR / f"{ckpt.step_dir_name(step)}.png"


@dataclasses.dataclass(frozen=True)
class PreviewPrompts:
    """The prompts of every preview, encoded once: titles, model conditions (P, E) or action ids (P,), the extra
    per-prompt model inputs (cross_attention: text_tokens, text_token_len) and the lengths in frames."""

    titles: list[str]
    cond: torch.Tensor
    extras: dict[str, torch.Tensor]
    lengths: list[int]


@dataclasses.dataclass(frozen=True)
class Preview:
    step: int
    png: Path
    figures: dict[str, float]  # the samples' plausibility medians (figures undefined for every sample left out)
    seconds: float

    def record(self) -> dict[str, Any]:
        """The metrics.jsonl entries of this preview."""
        return {**{PREVIEW_PREFIX + name: value for name, value in self.figures.items()},
                f"{PREVIEW_PREFIX}time_s": round(self.seconds, 4)}


class PreviewSampler:
    """Rank 0's previews of one run. Build it on rank 0 only; :meth:`run` returns None once previews are off."""

    def __init__(self, cfg: TrainConfig, manifest: Manifest, model_config: ModelConfig, model: torch.nn.Module,
                 ema_state: Callable[[], Mapping[str, torch.Tensor]], device: torch.device, out_dir: Path,
                 diffusion: GaussianDiffusion | None) -> None:
        self.cfg, self.manifest, self.model_config = cfg, manifest, model_config
        self.ema_state, self.device, self.out_dir, self.diffusion = ema_state, device, Path(out_dir), diffusion
        self._template = model  # copied at the first preview: no second set of weights before it is needed
        self._model: torch.nn.Module | None = None
        self._prompts: PreviewPrompts | None = None
        self.enabled = True
        spec = manifest.data["feature_spec"]
        self.skeleton: Skeleton = get_skeleton(spec["skeleton"])
        self.fps = float(spec["fps"])
        baseline = BASELINE_SAMPLING.get(cfg.train.diffusion) if diffusion is not None else None
        self.guidance = baseline.guidance if baseline else float(model_config.sampling_guidance)
        self.smoothing = baseline.smoothing_sigma if baseline else float(model_config.output_smoothing)

    def run(self, step: int) -> Preview | None:
        """Generate, draw and measure this step's preview; None when previews are off (after a failure)."""
        if not self.enabled:
            return None
        start = time.perf_counter()
        rng = ckpt.capture_rng_state()
        try:
            preview = self._run(step, start)
        except Exception as err:  # noqa: BLE001 - a preview is never worth a failed run
            logger.warning("previews off for the rest of this run: the preview at step %d failed: %s: %s", step,
                           type(err).__name__, err)
            self.enabled = False
            return None
        finally:
            ckpt.restore_rng_state(rng)
        logger.info("preview of step %d: %s (%.1f s)", step, preview.png, preview.seconds)
        return preview

    def _run(self, step: int, start: float) -> Preview:
        if self._prompts is None:
            self._prompts = self._read_prompts()
            self._model = copy.deepcopy(self._template).requires_grad_(False).eval()
            self._template = None
        prompts, model = self._prompts, self._model
        model.load_state_dict(self.ema_state())
        with torch.no_grad():
            motions = self._generate(model, prompts)
        joints, lengths = padded_motions(motions, np.float32)
        figures = plausibility(joints, self.skeleton, lengths).summary()
        png = preview_path(self.out_dir, step)
        png.parent.mkdir(parents=True, exist_ok=True)
        tmp = png.with_name(f".{png.stem}.tmp.png")
        sampler = (f"{DIFFUSION_SAMPLER} {DIFFUSION_STEPS}" if self.diffusion is not None
                   else f"{FLOW_SOLVER} {self.model_config.sampling_steps}")
        render_contact_sheet(tmp, motions, prompts.titles, self.skeleton, fps=self.fps,
                             title=f"{self.out_dir.name} step {step}: EMA weights, {sampler} steps, guidance "
                                   f"{self.guidance:g}, seed {self.cfg.train.seed}")
        tmp.replace(png)
        defined = {name: value for name, value in figures.items() if value is not None}
        return Preview(step, png, defined, time.perf_counter() - start)

    def _generate(self, model: torch.nn.Module, prompts: PreviewPrompts) -> list[np.ndarray]:
        """The prompts' motions as (L_i, J, 3) joint arrays, in prompt order (one batch)."""
        config, device = self.model_config, self.device
        lengths = torch.tensor(prompts.lengths, dtype=torch.long)
        num_frames = int(lengths.max())
        generators = seeded_generators([_noise_seed(self.cfg.train.seed, i) for i in range(len(prompts.titles))])
        cond = prompts.cond.to(device)
        extras = {name: value.to(device) for name, value in prompts.extras.items()}
        # a shortcut model at its sampling steps' level, as launch/sample.py gives it (its guidance is 1 there)
        step_size = sampler_step_size(config.shortcut_levels, FLOW_SOLVER, config.sampling_steps)
        call = bind_inputs(model, extras, step_size=step_size)
        if self.diffusion is not None:
            result = sample_diffusion(call, self.diffusion, cond, lengths, num_frames=num_frames,
                                      feature_dim=config.feature_dim, sampler=DIFFUSION_SAMPLER, steps=DIFFUSION_STEPS,
                                      guidance=self.guidance, generator=generators)
        else:
            # As launch/sample.py draws it: each sample's noise from its own generator, over its own frames.
            conditional = guided_feature_mask(config.guided_features, self.skeleton)
            result = sample(call, cond, lengths, num_frames=num_frames, feature_dim=config.feature_dim,
                            solver=FLOW_SOLVER, steps=config.sampling_steps,
                            grid=step_grid(config.sampling_steps, config.sampling_times), guidance=self.guidance,
                            conditional_channels=None if conditional is None else conditional.to(device),
                            generator=generators)
        normalization = self.manifest.data["normalization"]
        mean = torch.as_tensor(np.asarray(normalization["mean"], dtype=np.float32))
        std = torch.as_tensor(np.asarray(normalization["std"], dtype=np.float32))
        keep_bones = BoneKeeping.for_setting(config.output_smoothing_keeps_bones, self.skeleton, mean, std)
        x1 = smooth_over_time(result.x1.float().cpu(), lengths, self.smoothing, keep_bones)
        features = (x1 * std + mean).numpy()
        return [features_to_joints(features[i, :n], self.skeleton) for i, n in enumerate(prompts.lengths)]

    def _read_prompts(self) -> PreviewPrompts:
        train = self.cfg.train
        if train.preview_prompts:
            return self._given_prompts(list(train.preview_prompts))
        return self._dataset_prompts(train.preview_count)

    def _dataset_prompts(self, count: int) -> PreviewPrompts:
        """The first caption of the split's first ``count`` motions, with the length of the span it describes."""
        split = "val" if "val" in (self.manifest.data.get("splits") or {}) else "train"
        records = list(itertools.islice(
            iter_motions(self.manifest, split, backend_for_format(self.cfg.data.format), verify=self.cfg.data.verify),
            count))
        if not records:
            raise ValueError(f"the {split!r} split of {self.manifest.location} has no motion to take captions from")
        limit = self._longest()
        lengths = [max(1, min(int(r.spans[0][1] - r.spans[0][0]), limit)) for r in records]
        extras: dict[str, torch.Tensor] = {}
        if self.model_config.is_action_model:
            classes = list(self.manifest.action_classes)
            titles = [r.action for r in records]
            cond = torch.tensor([classes.index(a) for a in titles], dtype=torch.long)
        else:
            titles = [r.captions[0] for r in records]
            cond = torch.as_tensor(np.stack([r.text_emb[0] for r in records]), dtype=torch.float32)
            if self.model_config.conditioning == "cross_attention":
                tokens = [r.text_tokens[0] for r in records]
                width = max(t.shape[0] for t in tokens)
                padded = np.zeros((len(tokens), width, tokens[0].shape[-1]), dtype=np.float32)
                for i, t in enumerate(tokens):
                    padded[i, : t.shape[0]] = t
                extras = {"text_tokens": torch.as_tensor(padded),
                          "text_token_len": torch.as_tensor([int(r.text_token_len[0]) for r in records])}
        return PreviewPrompts(titles, cond, extras, lengths)

    def _given_prompts(self, texts: list[str]) -> PreviewPrompts:
        """``train.preview_prompts`` encoded with the dataset's text encoder (action names for action models),
        lengths drawn from the training lengths by a generator of their own."""
        generator = torch.Generator().manual_seed(_noise_seed(self.cfg.train.seed, -1))
        lengths = sample_lengths(self.manifest.split("train")["lengths"], len(texts), generator,
                                 max_length=self._longest()).tolist()
        if self.model_config.is_action_model:
            classes = list(self.manifest.action_classes)
            unknown = [t for t in texts if t not in classes]
            if unknown:
                raise ValueError(f"train.preview_prompts names unknown action(s) {unknown}; known: {classes}")
            return PreviewPrompts(texts, torch.tensor([classes.index(t) for t in texts]), {}, lengths)
        from mfm.text import build_matching_text_encoder

        entry = self.manifest.data["text_encoder"]
        encoder = build_matching_text_encoder(entry, device=str(self.device))
        if self.model_config.conditioning == "cross_attention":
            encoding = encoder.encode(texts, token_features=True, max_tokens=int(entry["max_tokens"]))
            extras = {"text_tokens": torch.as_tensor(encoding.tokens),
                      "text_token_len": torch.as_tensor(encoding.token_lengths, dtype=torch.long)}
        else:
            encoding, extras = encoder.encode(texts), {}
        return PreviewPrompts(texts, torch.as_tensor(encoding.pooled, dtype=torch.float32), extras, lengths)

    def _longest(self) -> int:
        """The longest motion to preview: the training window (as launch/sample.py clamps)."""
        return min(int(self.cfg.data.window), int(self.model_config.max_frames))


def _noise_seed(seed: int, index: int) -> int:
    return int(np.random.SeedSequence([seed, _SEED_TAG, index + 1]).generate_state(1, np.uint64)[0] >> 1)
