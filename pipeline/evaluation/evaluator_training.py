"""Train the project's own evaluator on a dataset's shards: a contrastive motion/text embedding (InfoNCE over the
cached caption embeddings) and, when the dataset has action labels, an action classifier.

    python launch/train_evaluator.py data.manifest=data/deepmimic-minilm/manifest.json

Data: the training stream of pipeline.data.stream (MotionLoader: random caption, MDM crop to ``data.window`` frames,
manifest normalisation), the same as the motion model sees. Distributed: one process, or several ranks under
torchrun / accelerate (DDP; each rank's InfoNCE uses its own batch's negatives).

Outputs (``out_dir``, default runs/evaluators/<dataset id>, where launch/evaluate.py looks by default)::

    contrastive.safetensors + .json         the evaluator; the sidecar records evaluator_id and the dataset id
    action_classifier.safetensors + .json   when the manifest lists action classes
    report.json                             held-out retrieval R@1/2/3 (batches of 32, or the split's size when
                                            smaller, recorded) and classifier accuracy on val/test ground truth;
                                            ``timing``: seconds per step and data-wait share of each loop

Progress: rank 0 shows a tqdm bar per loop (loss, s/step, share of time waiting for data) and logs every
``optim.log_every`` steps and a closing line with the loop's time. Where the time goes (synthetic preset's evaluator,
2 layers x 128, batch 32 x 196 frames, one CPU thread): the model's forward and backward passes, about 90 % of a
step; most of the rest is reading the batch, which :class:`ReadAhead` now does on a background thread during the
previous step (the same batches, so the same weights). Attention dropout sends CPU attention down PyTorch's unfused
path: ``model.attention_dropout=0`` makes a step about 1.6x faster (other weights, see the README).

Held-out items are built exactly as the evaluation job builds its ground truth (pipeline.evaluation.job).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import queue
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from tqdm.auto import tqdm

from mfm.evaluators import (
    ActionClassifier,
    ContrastiveEvaluator,
    ContrastiveEvaluatorConfig,
    save_evaluator,
)
from mfm.evaluators.contrastive import retrieval_accuracy
from mfm.metrics import R_PRECISION_BATCH_SIZE, action_accuracy
from pipeline.config import ConfigError, coerce_fields, to_dict
from pipeline.data.stream import (
    LoaderOptions,
    Manifest,
    MotionLoader,
    backend_for_format,
    open_manifest,
    verify_shards,
)
from pipeline.distributed import Dist
from pipeline.evaluation.spaces import (
    CLASSIFIER_FILE,
    EVALUATOR_FILE,
    EvaluationError,
    GroundTruthSet,
    UnverifiedGroundTruth,
    build_ground_truth,
    default_evaluator_dir,
)
from pipeline.evaluation.store import atomic_write_text

logger = logging.getLogger(__name__)

REPORT_FILE = "report.json"


@dataclasses.dataclass(frozen=True, kw_only=True)
class EvaluatorDataConfig:
    manifest: str = "data/deepmimic-minilm/manifest.json"
    format: Literal["tar", "parquet"] = "tar"
    split: str = "train"
    eval_splits: tuple[str, ...] = ("val", "test")
    """Held-out splits the retrieval accuracy is reported on (those the manifest has)."""
    window: int = 196
    unit_length: int = 4
    batch_size: int = 64
    num_workers: int = 0
    shuffle_buffer: int = 256
    seed: int = 0
    allow_external_shards: bool = False
    """Read shards the manifest lists outside its own folder or URL (absolute paths, other URLs, '..'): refused by
    default, as in training (``pipeline.config.DataConfig.allow_external_shards``)."""

    def __post_init__(self) -> None:
        coerce_fields(self)
        if self.batch_size < 2:
            raise ConfigError(f"data.batch_size must be >= 2 (InfoNCE needs negatives), got {self.batch_size}")


@dataclasses.dataclass(frozen=True, kw_only=True)
class EvaluatorOptimConfig:
    steps: int = 3000
    lr: float = 1e-4
    weight_decay: float = 1e-4
    warmup_steps: int = 100
    grad_clip: float = 1.0
    log_every: int = 100

    def __post_init__(self) -> None:
        coerce_fields(self)
        if self.steps < 1 or self.lr <= 0 or self.log_every < 1 or self.warmup_steps < 0:
            raise ConfigError(f"bad optim settings: {self}")


@dataclasses.dataclass(frozen=True, kw_only=True)
class EvaluatorTrainConfig:
    data: EvaluatorDataConfig = dataclasses.field(default_factory=EvaluatorDataConfig)
    model: ContrastiveEvaluatorConfig = dataclasses.field(default_factory=ContrastiveEvaluatorConfig)
    """Architecture and loss; feature_dim and text_dim are taken from the manifest."""
    optim: EvaluatorOptimConfig = dataclasses.field(default_factory=EvaluatorOptimConfig)
    action_classifier: Literal["auto", "yes", "no"] = "auto"
    """auto: train one when the manifest lists at least two action classes."""
    out_dir: str = ""
    """Empty: runs/evaluators/<dataset id> (where evaluator.path=auto finds it)."""
    seed: int = 0
    mixed_precision: Literal["no", "bf16", "auto"] = "no"


class _ContrastiveObjective(nn.Module):
    """forward = the InfoNCE loss, so that DDP's gradient hooks see the evaluator's forward."""

    def __init__(self, model: ContrastiveEvaluator) -> None:
        super().__init__()
        self.model = model

    def forward(self, features: torch.Tensor, lengths: torch.Tensor, text_emb: torch.Tensor) -> torch.Tensor:
        return self.model.training_loss(features, lengths, text_emb)


def model_config_for(cfg: EvaluatorTrainConfig, manifest: Manifest) -> ContrastiveEvaluatorConfig:
    spec = manifest.record_spec
    return dataclasses.replace(cfg.model, feature_dim=spec.feature_dim, text_dim=spec.text_dim)


def _schedule(warmup: int):
    return lambda step: min(1.0, (step + 1) / warmup) if warmup > 0 else 1.0


class TrainingTimes:
    """Where a training loop's time went: steps, seconds waiting for batches, seconds in all (report.json)."""

    def __init__(self) -> None:
        self.steps, self.data_wait_s, self.total_s = 0, 0.0, 0.0

    def as_dict(self) -> dict[str, float]:
        return {"steps": self.steps, "s_per_step": round(self.total_s / max(self.steps, 1), 4),
                "data_wait_frac": round(self.data_wait_s / max(self.total_s, 1e-9), 4)}


def _train(dist: Dist, module: nn.Module, loader: MotionLoader, optim: EvaluatorOptimConfig, name: str,
           loss_of, times: TrainingTimes | None = None) -> list[float]:
    """A small loop: AdamW, linear warm-up, clipping; returns the logged losses (rank-local means). Rank 0 shows a
    progress bar (loss, seconds per step, share of the time spent waiting for data) and logs every ``log_every``
    steps. The next batch is read on a background thread while this one trains (:class:`ReadAhead`): the same
    batches in the same order, the data time hidden behind the model's."""
    optimizer = torch.optim.AdamW(module.parameters(), lr=optim.lr, weight_decay=optim.weight_decay)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, _schedule(optim.warmup_steps))
    module, optimizer = dist.prepare(module, optimizer)
    module.train()
    times = times if times is not None else TrainingTimes()
    losses, window = [], []
    batches = ReadAhead(loader.iter_batches())
    progress = tqdm(total=optim.steps, desc=name, disable=not dist.is_main, dynamic_ncols=True)
    started = time.perf_counter()
    try:
        for step in range(1, optim.steps + 1):
            waited = time.perf_counter()
            batch = next(batches)
            times.data_wait_s += time.perf_counter() - waited
            loss = loss_of(module, {k: v.to(dist.device) if torch.is_tensor(v) else v for k, v in batch.items()})
            optimizer.zero_grad(set_to_none=True)
            dist.backward(loss)
            if optim.grad_clip > 0:
                dist.clip_grad_norm_(module.parameters(), optim.grad_clip)
            optimizer.step()
            scheduler.step()
            window.append(float(loss.detach()))
            times.steps += 1
            times.total_s = time.perf_counter() - started
            progress.update(1)
            if step % optim.log_every == 0 or step == optim.steps:
                losses.append(float(np.mean(window)))
                progress.set_postfix(loss=f"{losses[-1]:.4f}", s_per_step=f"{times.total_s / times.steps:.3f}",
                                     wait=f"{times.data_wait_s / max(times.total_s, 1e-9):.0%}")
                dist.log0("%s step %d/%d: loss %.4f", name, step, optim.steps, losses[-1], log=logger)
                window = []
    finally:
        progress.close()
        batches.close()
    dist.log0("%s: %d steps in %.1f s (%.3f s/step, %.0f%% waiting for data)", name, times.steps, times.total_s,
              times.total_s / max(times.steps, 1), 100 * times.data_wait_s / max(times.total_s, 1e-9), log=logger)
    return losses


class ReadAhead:
    """An iterator read one item ahead on a background thread (the loader's randomness is its own, seeded per
    epoch and sample, so which thread reads changes nothing); ``close`` stops it and closes the source. An
    exception of the source is raised by the ``next`` that would have returned its item."""

    _END = object()

    def __init__(self, source: Iterator[Any]) -> None:
        self._source = source
        self._queue: queue.Queue = queue.Queue(maxsize=1)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, name="evaluator-read-ahead", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        try:
            for item in self._source:
                if not self._put((item, None)):
                    return
            self._put((self._END, None))
        except BaseException as err:  # noqa: BLE001 - handed to the consumer, raised there
            self._put((None, err))

    def _put(self, entry: tuple[Any, BaseException | None]) -> bool:
        while not self._stop.is_set():
            try:
                self._queue.put(entry, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def __iter__(self) -> ReadAhead:
        return self

    def __next__(self) -> Any:
        item, err = self._queue.get()
        if err is not None:
            raise err
        if item is self._END:
            raise StopIteration
        return item

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        close = getattr(self._source, "close", None)
        if close is not None:
            close()


def _contrastive_loss(module: nn.Module, batch: dict) -> torch.Tensor:
    return module(batch["features"], batch["lengths"], batch["text_emb"])


def _classifier_loss(module: nn.Module, batch: dict) -> torch.Tensor:
    labelled = batch["action"] >= 0
    logits = module(batch["features"], batch["lengths"])
    # Unlabelled motions still run through the model so every rank's DDP graph is the same; they weigh 0.
    per_sample = F.cross_entropy(logits, batch["action"].clamp(min=0), reduction="none")
    return (per_sample * labelled).sum() / labelled.sum().clamp(min=1)


@torch.no_grad()
def _held_out_embeddings(model: ContrastiveEvaluator, gt: GroundTruthSet, manifest: Manifest,
                         device: torch.device, batch_size: int = 64) -> tuple[torch.Tensor, torch.Tensor]:
    mean = torch.as_tensor(manifest.mean, device=device)
    std = torch.as_tensor(manifest.std, device=device)
    motions, texts = [], []
    for start in range(0, len(gt), batch_size):
        index = np.arange(start, min(start + batch_size, len(gt)))
        features, lengths = gt.padded(index, device)
        valid = (torch.arange(features.shape[1], device=device)[None, :] < lengths[:, None]).unsqueeze(-1)
        motions.append(model.encode_motions((features - mean) / std * valid, lengths))
        texts.append(model.encode_texts(torch.from_numpy(gt.text_cond[index]).to(device)))
    return torch.cat(motions), torch.cat(texts)


@torch.no_grad()
def _held_out_accuracy(classifier: ActionClassifier, gt: GroundTruthSet, manifest: Manifest,
                       device: torch.device, batch_size: int = 64) -> float | None:
    labelled = np.array([a in classifier.action_classes for a in gt.actions])
    if not labelled.any():
        return None
    mean, std = torch.as_tensor(manifest.mean, device=device), torch.as_tensor(manifest.std, device=device)
    items = np.flatnonzero(labelled)
    logits = []
    for start in range(0, len(items), batch_size):
        features, lengths = gt.padded(items[start:start + batch_size], device)
        valid = (torch.arange(features.shape[1], device=device)[None, :] < lengths[:, None]).unsqueeze(-1)
        logits.append(classifier((features - mean) / std * valid, lengths))
    labels = [classifier.action_classes.index(gt.actions[i]) for i in items]
    return action_accuracy(torch.cat(logits), labels)


def held_out_report(model: ContrastiveEvaluator, classifier: ActionClassifier | None, manifest: Manifest,
                    splits: tuple[str, ...], device: torch.device) -> dict[str, Any]:
    """Retrieval R@1/2/3 (text -> motion among batches of 32, or the whole split when smaller) and classifier
    accuracy on each held-out split's ground-truth items."""
    report: dict[str, Any] = {}
    model.eval()
    for split in splits:
        if split not in manifest.data.get("splits", {}):
            continue
        try:
            gt = build_ground_truth(manifest, split)
        except UnverifiedGroundTruth:
            raise  # tampered or damaged held-out data is an error, not a split to leave out of the report
        except EvaluationError as exc:
            logger.warning("no held-out report for %s: %s", split, exc)
            continue
        entry: dict[str, Any] = {"num_items": len(gt), "data_verified": bool(gt.verification.get("verified"))}
        batch = min(R_PRECISION_BATCH_SIZE, len(gt))
        if batch >= 2:
            motion, text = _held_out_embeddings(model, gt, manifest, device)
            accuracy = retrieval_accuracy(motion, text, top_k=(1, 2, 3) if batch >= 3 else (1,), batch_size=batch)
            entry.update({"retrieval_batch_size": batch, "chance_top1": 1.0 / batch,
                          **{f"retrieval_top{k}": v for k, v in accuracy.items()}})
        if classifier is not None:
            classifier.eval()
            entry["action_accuracy"] = _held_out_accuracy(classifier, gt, manifest, device)
        report[split] = entry
    return report


def _fitting_batch_size(data: EvaluatorDataConfig, manifest: Manifest, world_size: int) -> int:
    """``data.batch_size``, or less when the split is too small for one batch per reader (the embedded DeepMimic
    dataset has 15 training motions): said in the log, recorded in the report."""
    readers = world_size * max(1, data.num_workers)
    available = int(manifest.split(data.split)["num_motions"]) // readers
    if available < 2:
        raise EvaluationError(f"{manifest.location}: split {data.split!r} is too small for contrastive training "
                              f"on {readers} reader(s)")
    if available < data.batch_size:
        logger.warning("data.batch_size %d > %d motions per reader in split %r: using %d", data.batch_size,
                       available, data.split, available)
    return min(data.batch_size, available)


def train_evaluator(cfg: EvaluatorTrainConfig, dist: Dist) -> dict[str, Any]:
    """Train, save (rank 0) and return the report (every rank)."""
    start = time.perf_counter()
    manifest = open_manifest(cfg.data.manifest, allow_external_shards=cfg.data.allow_external_shards)
    model_config = model_config_for(cfg, manifest)
    out_dir = Path(cfg.out_dir) if cfg.out_dir else default_evaluator_dir(manifest.dataset_id)
    # The training reader's strict checks, on every rank (deterministic, so every rank reaches the same verdict);
    # a bad shard raises ShardVerificationError naming the file before any step.
    verification = verify_shards(manifest, cfg.data.split, mode="strict", backend=backend_for_format(cfg.data.format))
    batch_size = _fitting_batch_size(cfg.data, manifest, dist.world_size)
    options = LoaderOptions(batch_size=batch_size, num_workers=cfg.data.num_workers, seed=cfg.data.seed,
                            window=cfg.data.window, unit_length=cfg.data.unit_length,
                            shuffle_buffer=cfg.data.shuffle_buffer,
                            backend=backend_for_format(cfg.data.format))

    def loader() -> MotionLoader:
        return MotionLoader(manifest, cfg.data.split, options, rank=dist.rank, world_size=dist.world_size)

    torch.manual_seed(cfg.seed)
    model = ContrastiveEvaluator(model_config)
    times = {"contrastive": TrainingTimes()}
    losses = _train(dist, _ContrastiveObjective(model), loader(), cfg.optim, "contrastive", _contrastive_loss,
                    times["contrastive"])
    classes = list(manifest.action_classes)
    want_classifier = cfg.action_classifier == "yes" or (cfg.action_classifier == "auto" and len(classes) >= 2)
    if cfg.action_classifier == "yes" and len(classes) < 2:
        raise EvaluationError(f"{manifest.location} lists {len(classes)} action class(es): no classifier to train")
    classifier, classifier_losses = None, []
    if want_classifier:
        torch.manual_seed(cfg.seed + 1)
        classifier = ActionClassifier(model_config, classes)
        times["action_classifier"] = TrainingTimes()
        classifier_losses = _train(dist, classifier, loader(), cfg.optim, "action classifier", _classifier_loss,
                                   times["action_classifier"])
    model.to(dist.device).eval()
    report: dict[str, Any] = {
        "dataset_id": manifest.dataset_id, "manifest": manifest.location, "config": to_dict(cfg),
        "data_verified": verification.verified, "verification": verification.as_dict(),
        "model_config": model_config.to_dict(), "world_size": dist.world_size, "batch_size": batch_size,
        "losses": {"contrastive": losses, "action_classifier": classifier_losses},
        "timing": {name: t.as_dict() for name, t in times.items()},
        "held_out": held_out_report(model, classifier, manifest, cfg.data.eval_splits, dist.device),
    }
    if dist.is_main:
        report["evaluator_id"] = save_evaluator(out_dir / EVALUATOR_FILE, model, model_config, manifest.dataset_id)
        report["evaluator_path"] = str(out_dir / EVALUATOR_FILE)
        if classifier is not None:
            report["action_classifier_id"] = save_evaluator(out_dir / CLASSIFIER_FILE, classifier, model_config,
                                                            manifest.dataset_id)
            report["action_classifier_path"] = str(out_dir / CLASSIFIER_FILE)
        report["wall_s"] = time.perf_counter() - start
        atomic_write_text(out_dir / REPORT_FILE, json.dumps(report, indent=1) + "\n")
    dist.barrier()
    return dist.broadcast_object(report)
