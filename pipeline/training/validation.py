"""The validation loss of a training run (``train.val_every``): the training objective's own loss, on fixed
batches of the manifest's ``val`` split, gradients off, in eval mode, from random streams of its own.

What makes the figure comparable from step to step, and the same on any number of ranks:

* the batches: the first ``train.val_batches`` batches of the val split, read once when the run starts through
  the training stream's own stages (caption pick, crop, normalisation, collation) at world size 1, without
  shuffling, in epoch 0 (so the same captions and crops every time). Global batch ``i`` is evaluated by rank
  ``i % world_size``; a rank may hold none. The loader yields full batches only: up to
  ``data.batch_size - 1`` motions of the split are never used (the batch size is cut to the split's size if
  the split is smaller than one batch);
* the draws (flow time or diffusion step, noise, dropped conditions, a BPE model's positional mode): global batch
  ``i`` draws from a generator of its own, seeded from ``(train.seed, i)``, whichever rank evaluates it;
* the mean: the loss is a per-motion mean within a batch; each batch weighs its motion count, and
  ``[sum, count]`` (float64) is all-reduced through :class:`pipeline.distributed.Dist`.

What it leaves as it was: the trainer's per-rank generator, the global Python / NumPy / torch RNGs (captured and
restored around every validation), the training data stream (the val loader is a loader of its own, without
worker processes), and the training weights and mode. ``train.val_weights=ema`` evaluates the EMA weights in a
copy of the model (one more set of weights in memory); ``model`` evaluates the raw weights in the training model
itself, switched to eval mode and back. The model's forward runs under the run's autocast (as the prepared
model's does in training) and never through the DDP wrapper, whose forward would be a collective that ranks
holding different numbers of batches could not match.
"""

from __future__ import annotations

import copy
import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import torch

from pipeline import checkpoint as ckpt
from pipeline.config import TrainConfig
from pipeline.data.stream import (
    LoaderOptions,
    Manifest,
    MotionLoader,
    backend_for_format,
    split_shards,
)
from pipeline.distributed import Dist
from preprocess.shards import ManifestError

logger = logging.getLogger(__name__)

VAL_SPLIT = "val"
_SEED_TAG = 0x76616C  # "val": keeps the validation draws apart from every other stream seeded from train.seed

LossFn = Callable[[Mapping[str, Any], torch.Generator, Callable[..., Any]], torch.Tensor]
"""``loss_fn(batch, generator, model)``: the trainer's loss of one batch with the draws from ``generator``."""


def batch_seed(seed: int, index: int) -> int:
    """The seed of global validation batch ``index``'s draws (the same on every rank and at every step)."""
    return int(np.random.SeedSequence([seed, _SEED_TAG, index]).generate_state(1, np.uint64)[0])


class _Autocast:
    """The bare model called under the run's autocast, outputs in fp32: what the prepared model does in training."""

    def __init__(self, model: torch.nn.Module, dist: Dist) -> None:
        self.model, self.dist = model, dist

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        with self.dist.autocast():
            out = self.model(*args, **kwargs)
        return out.float() if isinstance(out, torch.Tensor) and out.is_floating_point() else out


class Validator:
    """This rank's share of the fixed validation batches, and :meth:`run`, which every rank calls at once."""

    def __init__(self, batches: Sequence[tuple[int, Mapping[str, Any]]], *, dist: Dist, loss_fn: LossFn, seed: int,
                 weights: str, model: torch.nn.Module,
                 ema_state: Callable[[], Mapping[str, torch.Tensor]] | None = None) -> None:
        if weights not in ("ema", "model"):
            raise ValueError(f"weights must be 'ema' or 'model', got {weights!r}")
        if weights == "ema" and ema_state is None:
            raise ValueError("weights='ema' needs ema_state")
        self.batches = list(batches)
        self.dist, self.loss_fn, self.seed, self.weights = dist, loss_fn, seed, weights
        self.ema_state = ema_state
        # EMA: a copy of the bare model that only ever holds the EMA weights; raw: the training model itself.
        self.model = copy.deepcopy(model).requires_grad_(False) if weights == "ema" else model

    def run(self) -> dict[str, Any]:
        """The validation record of the current weights: ``val_loss`` (the mean over the validation motions of
        all ranks; None if not finite), ``val_samples``, ``val_weights``, ``val_time_s``. A collective: every rank
        calls it at the same step."""
        start = time.perf_counter()
        device = self.dist.device
        model = self.model
        if self.weights == "ema":
            model.load_state_dict(self.ema_state())
        was_training = model.training
        rng = ckpt.capture_rng_state()
        totals = torch.zeros(2, dtype=torch.float64, device=device)
        try:
            model.eval()
            call = _Autocast(model, self.dist)
            with torch.no_grad():
                for index, batch in self.batches:
                    count = len(batch["ids"])
                    if count == 0:  # tolerant mode: every record of the batch was left out
                        continue
                    generator = torch.Generator(device=device).manual_seed(batch_seed(self.seed, index))
                    loss = self.loss_fn(batch, generator, call)
                    totals[0] += loss.detach().double() * count
                    totals[1] += count
        finally:
            model.train(was_training)
            ckpt.restore_rng_state(rng)
        loss_sum, samples = self.dist.all_reduce_sum(totals).tolist()
        val_loss = loss_sum / samples if samples > 0 and math.isfinite(loss_sum) else None
        return {"val_loss": val_loss, "val_samples": int(samples), "val_weights": self.weights,
                "val_time_s": round(time.perf_counter() - start, 4)}


def has_val_split(manifest: Manifest) -> bool:
    return VAL_SPLIT in (manifest.data.get("splits") or {})


def build_validator(cfg: TrainConfig, manifest: Manifest, dist: Dist, *, exclude_shards: Sequence[str],
                    loss_fn: LossFn, model: torch.nn.Module,
                    ema_state: Callable[[], Mapping[str, torch.Tensor]] | None) -> Validator | None:
    """Read this rank's share of the validation batches (every rank reads the first ``train.val_batches``
    batches and keeps its own). None, with one logged line, when the manifest has no val split or it has no
    usable motion. ``exclude_shards``: the val shards verification left out (the same list on every rank)."""
    if not has_val_split(manifest):
        dist.log0("validation off: %s has no %r split (train.val_every=%d)", manifest.location, VAL_SPLIT,
                  cfg.train.val_every, level=logging.WARNING, log=logger)
        return None
    backend = backend_for_format(cfg.data.format)
    try:
        shards = [s for s in split_shards(manifest, VAL_SPLIT, backend) if s.path not in set(exclude_shards)]
    except ManifestError as err:
        dist.log0("validation off: %s", err, level=logging.WARNING, log=logger)
        return None
    motions = sum(s.num_motions for s in shards)
    if motions == 0:
        dist.log0("validation off: the %r split of %s has no usable motion", VAL_SPLIT, manifest.location,
                  level=logging.WARNING, log=logger)
        return None
    options = LoaderOptions(
        batch_size=min(cfg.data.batch_size, motions), num_workers=0, seed=cfg.data.seed, window=cfg.data.window,
        unit_length=cfg.data.unit_length, shuffle=False, shuffle_buffer=0, caption_policy=cfg.data.caption_policy,
        backend=backend, tolerate_bad_data=cfg.data.verify == "tolerant",
        check_remote_bytes=cfg.data.verify != "off", retries=cfg.data.retries,
        retry_backoff_s=cfg.data.retry_backoff_s, cache_dir=cfg.data.cache_dir,
        cache_max_bytes=cfg.data.cache_max_bytes)
    loader = MotionLoader(manifest, VAL_SPLIT, options, exclude_shards=exclude_shards)
    count = min(cfg.train.val_batches, loader.batches_per_epoch())
    mine = []
    batches = loader.iter_epoch()
    try:
        for index in range(count):
            batch = next(batches)
            if index % dist.world_size == dist.rank:
                mine.append((index, batch))
    finally:
        batches.close()
    dist.log0("validation every %d steps: %d batch(es) of %d motions of the %r split (%d motions), %s weights, "
              "%d rank(s)", cfg.train.val_every, count, options.batch_size, VAL_SPLIT, motions, cfg.train.val_weights,
              dist.world_size, log=logger)
    return Validator(mine, dist=dist, loss_fn=loss_fn, seed=cfg.train.seed, weights=cfg.train.val_weights,
                     model=model, ema_state=ema_state)
