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
                                            smaller, recorded) and classifier accuracy on val/test ground truth

Held-out items are built exactly as the evaluation job builds its ground truth (pipeline.evaluation.job).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

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


def _train(dist: Dist, module: nn.Module, loader: MotionLoader, optim: EvaluatorOptimConfig, name: str,
           loss_of) -> list[float]:
    """A small loop: AdamW, linear warm-up, clipping; returns the logged losses (rank-local means)."""
    optimizer = torch.optim.AdamW(module.parameters(), lr=optim.lr, weight_decay=optim.weight_decay)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, _schedule(optim.warmup_steps))
    module, optimizer = dist.prepare(module, optimizer)
    module.train()
    losses, window = [], []
    batches = loader.iter_batches()
    for step in range(1, optim.steps + 1):
        batch = next(batches)
        loss = loss_of(module, {k: v.to(dist.device) if torch.is_tensor(v) else v for k, v in batch.items()})
        optimizer.zero_grad(set_to_none=True)
        dist.backward(loss)
        if optim.grad_clip > 0:
            dist.clip_grad_norm_(module.parameters(), optim.grad_clip)
        optimizer.step()
        scheduler.step()
        window.append(float(loss.detach()))
        if step % optim.log_every == 0 or step == optim.steps:
            losses.append(float(np.mean(window)))
            dist.log0("%s step %d/%d: loss %.4f", name, step, optim.steps, losses[-1], log=logger)
            window = []
    batches.close()
    return losses


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
    losses = _train(dist, _ContrastiveObjective(model), loader(), cfg.optim, "contrastive", _contrastive_loss)
    classes = list(manifest.action_classes)
    want_classifier = cfg.action_classifier == "yes" or (cfg.action_classifier == "auto" and len(classes) >= 2)
    if cfg.action_classifier == "yes" and len(classes) < 2:
        raise EvaluationError(f"{manifest.location} lists {len(classes)} action class(es): no classifier to train")
    classifier, classifier_losses = None, []
    if want_classifier:
        torch.manual_seed(cfg.seed + 1)
        classifier = ActionClassifier(model_config, classes)
        classifier_losses = _train(dist, classifier, loader(), cfg.optim, "action classifier", _classifier_loss)
    model.to(dist.device).eval()
    report: dict[str, Any] = {
        "dataset_id": manifest.dataset_id, "manifest": manifest.location, "config": to_dict(cfg),
        "data_verified": verification.verified, "verification": verification.as_dict(),
        "model_config": model_config.to_dict(), "world_size": dist.world_size, "batch_size": batch_size,
        "losses": {"contrastive": losses, "action_classifier": classifier_losses},
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
