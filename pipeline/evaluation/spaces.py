"""What the evaluation job scores and in which space: the ground-truth items of a split, and the evaluators
(the project's contrastive evaluator, its action classifier, the official T2M evaluator) behind one interface.

Ground truth. One item per test motion and caption span (HumanML3D's sub-clips), as the reference loader: a caption
picked at random, the clip cropped to at most ``max_length`` frames and to a multiple of ``unit_length`` (random
offset). The split is verified and read once (:class:`GroundTruthPool`, in memory); sets are drawn from it:

* re-drawn per replication (``protocol.redraw_items``, the default): replication r's picks and crops come from
  ``(seed, r, motion id, span)`` and the crop is one unit shorter with probability 1/3, as the reference loader
  (MDM/T2M ``Text2MotionDatasetV2``) draws anew on every pass over the shuffled test set. The same items (ids, order)
  in every replication; their captions, lengths and clips differ.
* fixed: picks and crops drawn once from ``(seed, motion id, span)``, the same for every replication.
* further passes of a replication (``protocol.gt_draws=independent``, the ``mdm`` protocol): the same rule from
  ``(seed, r, pass, motion id, span)``, independent of the replication's own set.

Either way a set is the same for every checkpoint, job and rank, and its evaluator embeddings are cached per
evaluator and set (:attr:`GroundTruthSet.key`).

Which items (``protocol.test_items``): ``span`` (ours) one per distinct caption span of a motion, the captions
sharing it pooled; ``caption`` (the reference loader, ``Text2MotionDatasetV2.__init__``) the whole-clip captions
pooled into one item, but every sub-span caption line its own item with its own span and its one caption, and
motions of :data:`REFERENCE_SPAN_LIMIT` frames or more dropped (counted).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections import defaultdict
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor

from mfm.evaluators import (
    T2MEvaluator,
    T2MEvaluatorFilesMissing,
    load_evaluator,
    resolve_t2m_files,
    t2m_dataset_for_skeleton,
)
from mfm.integrity import sha256_file
from mfm.model import valid_frame_mask
from pipeline.data.stages import MotionRecord, stable_id_hash
from pipeline.data.stream import (
    Manifest,
    ManifestError,
    ShardVerificationError,
    open_manifest,
    verified_split,
)
from pipeline.evaluation.config import EvaluatorConfig

GT_FORMAT = 1
REDRAW_FORMAT = 1
"""Version of the per-replication draw (part of a re-drawn set's key)."""
REDRAW_SHORTEN_PROB = 1.0 / 3.0
"""The reference loader's 'double' coin: one unit shorter with this probability (``unit_length < 10``)."""
EVALUATOR_FILE = "contrastive.safetensors"
CLASSIFIER_FILE = "action_classifier.safetensors"
TEST_ITEMS = ("span", "caption")
"""``protocol.test_items``: one item per distinct caption span (ours), or per sub-span caption line (the reference)."""
REFERENCE_SPAN_LIMIT = 200
"""test_items=caption: the reference loader drops motions (dataset.py: 254) and sub-spans (276-280) of this many
frames or more; span (ours) crops them to ``max_length`` instead."""
_TAG_GT_PICK = 10
_TAG_GT_REDRAW = 12
_TAG_GT_PASS = 13


class EvaluationError(RuntimeError):
    """A checkpoint, dataset and evaluator that cannot be evaluated together; the message says why."""


class UnverifiedGroundTruth(EvaluationError):
    """The split to score against does not verify against its manifest (size, sha256, record count, ids): a
    score against it would carry the manifest's dataset id without being about that data."""


class EvaluatorUnavailable(FileNotFoundError):
    """The requested evaluator's files are missing; the message lists them and how to get them."""


def digest(obj: Any) -> str:
    """sha256 of a JSON-able object (sorted keys): identities of settings and items."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


# ---------------------------------------------------------------------------------------------------------------
# Ground truth
# ---------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class GroundTruthSet:
    """The evaluation items of one split: one caption and crop per (motion, span), fixed or drawn for one
    replication; raw features."""

    dataset_id: str
    split: str
    ids: tuple[str, ...]
    features: tuple[np.ndarray, ...]
    """(L_i, D) float32, un-normalised, already cropped."""
    lengths: np.ndarray
    captions: tuple[str, ...]
    caption_tokens: tuple[tuple[str, ...], ...]
    text_cond: np.ndarray
    """(N, E) float32 cached pooled embedding of each item's caption: the text model's condition."""
    actions: tuple[str | None, ...]
    dropped: Mapping[str, int]
    key: str
    """sha256 of (dataset id, split, construction settings; a re-drawn set's replication): identifies cached
    embeddings."""
    text_tokens: np.ndarray | None = None
    """(N, L, E) token features of each caption (cross-attention models), when asked for."""
    text_token_len: np.ndarray | None = None
    """(N,) valid tokens per caption."""
    verification: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    """What strict verification checked before the split was read (``VerificationReport.as_dict()``); results
    files carry it next to the dataset id."""
    replication: int | None = None
    """None: the fixed set; r: the set re-drawn for replication r (``protocol.redraw_items``)."""
    offsets: np.ndarray | None = None
    """(N,) crop start of each item within its caption span."""
    caption_index: np.ndarray | None = None
    """(N,) which of its motion's captions each item uses."""

    def __len__(self) -> int:
        return len(self.ids)

    def padded(self, indices: np.ndarray, device: torch.device | str = "cpu") -> tuple[Tensor, Tensor]:
        """Raw features of ``indices`` zero-padded to their longest, (B, T, D), and lengths (B,)."""
        lengths = self.lengths[indices]
        out = np.zeros((len(indices), int(lengths.max()), self.features[0].shape[1]), np.float32)
        for row, index in enumerate(indices):
            out[row, : lengths[row]] = self.features[index]
        return torch.from_numpy(out).to(device), torch.from_numpy(lengths.astype(np.int64)).to(device)


@dataclasses.dataclass(frozen=True, eq=False)
class _Motion:
    """A test motion as read, with its items: ((start, end), caption indices, caption line) in order of
    appearance. The caption line is None for an item pooling its span's captions; with ``test_items=caption`` a
    sub-span caption line's own item names it (its id and its draw's seed then include it)."""

    record: MotionRecord
    spans: tuple[tuple[tuple[int, int], tuple[int, ...], int | None], ...]
    named_spans: bool
    """The motion has several caption spans (dropped ones included): its item ids name theirs."""


@dataclasses.dataclass(frozen=True, eq=False)
class GroundTruthPool:
    """Every motion of a split, verified and read once and kept in memory: each ground-truth set of the split (the
    fixed one, or one per replication) is drawn from it without reading the shards again. The items, their ids and
    order are the same in every draw (one per motion and caption span at least one unit long; with
    ``test_items=caption`` one per sub-span caption line); only the caption picks and the crops differ. A set's clips
    are views into the pool's features (no copy per draw)."""

    dataset_id: str
    location: str
    split: str
    motions: tuple[_Motion, ...]
    dropped: Mapping[str, int]
    settings: Mapping[str, Any]
    """Construction settings (the fixed set's key hashes them)."""
    token_features: bool
    verification: Mapping[str, Any]

    @property
    def unit_length(self) -> int:
        return int(self.settings["unit_length"])

    @property
    def max_length(self) -> int:
        return int(self.settings["max_length"])

    def draw(self, replication: int | None = None, stream: int = 0) -> GroundTruthSet:
        """The fixed set (``replication=None``: one caption pick and crop per span from ``(seed, motion id, span)``,
        the same in every replication, job and checkpoint), or replication ``r``'s re-drawn set: per span a caption
        picked at random, the crop one unit shorter with probability 1/3 (the reference loader's 'double' coin,
        when ``unit_length < 10``; never shortened to zero) and a random offset, from ``(seed, r, motion id,
        span)``. Deterministic: every rank and every job draws the same items for the same seed and replication.

        ``stream`` > 0: another pass of replication ``r`` over the loader, independent of stream 0 (the replication's
        set) and of the other streams, seeded by ``(seed, r, stream, motion id, span)`` (``protocol.gt_draws``)."""
        if stream and replication is None:
            raise ValueError("only a re-drawn set (a replication) has further streams")
        seed, unit, max_length = int(self.settings["seed"]), self.unit_length, self.max_length
        fields: dict[str, list] = defaultdict(list)
        for motion in self.motions:
            record = motion.record
            for (start, end), captions, line in motion.spans:
                own = [] if line is None else [line]  # a caption line's own item: its own draw beside its span's
                span = end - start
                units = min(span, max_length) // unit
                if replication is None:
                    rng = np.random.default_rng(np.random.SeedSequence(
                        [seed, _TAG_GT_PICK, stable_id_hash(record.id), start, end, *own]))
                    c = captions[int(rng.integers(len(captions)))]
                else:
                    pass_seed = [_TAG_GT_REDRAW] if stream == 0 else [_TAG_GT_PASS, stream]
                    rng = np.random.default_rng(np.random.SeedSequence(
                        [seed, *pass_seed, replication, stable_id_hash(record.id), start, end, *own]))
                    c = captions[int(rng.integers(len(captions)))]
                    if unit < 10:  # the reference: coin2 = choice(['single', 'single', 'double'])
                        shorten = rng.random() < REDRAW_SHORTEN_PROB  # drawn always: a stable stream position
                        units -= int(shorten and units > 1)
                length = units * unit
                offset = start + int(rng.integers(0, span - length + 1))
                item_id = f"{record.id}#{start}-{end}" if motion.named_spans or own else record.id
                fields["ids"].append(item_id if line is None else f"{item_id}#{line}")
                fields["features"].append(np.ascontiguousarray(record.features[offset:offset + length], np.float32))
                fields["lengths"].append(length)
                fields["offsets"].append(offset - start)
                fields["caption_index"].append(c)
                fields["captions"].append(record.captions[c])
                fields["caption_tokens"].append(tuple(record.caption_tokens[c]))
                fields["text_cond"].append(record.text_emb[c])
                fields["actions"].append(record.action)
                if self.token_features:
                    fields["text_tokens"].append(record.text_tokens[c])
                    fields["text_token_len"].append(int(record.text_token_len[c]))
        settings = dict(self.settings)
        if replication is not None:  # the fixed set's key is the one it always had (its caches stay valid)
            settings["redraw"] = {"format": REDRAW_FORMAT, "replication": int(replication),
                                  "shorten_prob": REDRAW_SHORTEN_PROB if unit < 10 else 0.0}
            if stream:  # stream 0 keeps the key it always had
                settings["redraw"]["stream"] = int(stream)
        tokens = self.token_features
        return GroundTruthSet(
            dataset_id=self.dataset_id, split=self.split, ids=tuple(fields["ids"]),
            features=tuple(fields["features"]), lengths=np.asarray(fields["lengths"], np.int64),
            captions=tuple(fields["captions"]), caption_tokens=tuple(fields["caption_tokens"]),
            text_cond=np.stack(fields["text_cond"]).astype(np.float32), actions=tuple(fields["actions"]),
            dropped=dict(self.dropped), key=digest(settings),
            text_tokens=np.stack(fields["text_tokens"]).astype(np.float32) if tokens else None,
            text_token_len=np.asarray(fields["text_token_len"], np.int64) if tokens else None,
            verification=self.verification, replication=replication,
            offsets=np.asarray(fields["offsets"], np.int64),
            caption_index=np.asarray(fields["caption_index"], np.int64))


def read_ground_truth_pool(manifest: Manifest | str | Path, split: str = "test", *, max_length: int = 196,
                           unit_length: int = 4, seed: int = 0, backend: str = "webdataset",
                           require_action: bool = False, token_features: bool = False,
                           test_items: str = "span") -> GroundTruthPool:
    """Verify ``split`` strictly (the training reader's checks: a shard that does not match the manifest raises
    :class:`UnverifiedGroundTruth` naming the file and the reason, before any item is built), then read its motions
    into a :class:`GroundTruthPool`. ``token_features``: also keep each caption's token features (the manifest must
    store them). ``test_items``: span (ours) or caption (the reference's items; the module docstring)."""
    if test_items not in TEST_ITEMS:
        raise ValueError(f"test_items must be one of {TEST_ITEMS}, got {test_items!r}")
    manifest = open_manifest(manifest)
    if token_features and not manifest.record_spec.token_features:
        raise EvaluationError(f"{manifest.location}: the model needs caption token features, which this dataset "
                              "does not store (build it with --token-features)")
    try:
        source = verified_split(manifest, split, backend, mode="strict")
    except (ShardVerificationError, ManifestError) as exc:  # a bad shard, or one outside the manifest's folder
        raise UnverifiedGroundTruth(f"refusing to score against split {split!r} of {manifest.location}, which does "
                                    f"not match its manifest: {exc}") from exc
    motions: list[_Motion] = []
    dropped: dict[str, int] = defaultdict(int)
    for record in source.iter_motions():
        if require_action and not record.action:
            dropped["no_action_label"] += 1
            continue
        length = len(record.features)
        if test_items == "caption" and length >= REFERENCE_SPAN_LIMIT:
            dropped[f"motion_{REFERENCE_SPAN_LIMIT}_frames_or_longer"] += 1
            continue
        spans: dict[tuple[int, int], list[int]] = {}
        for c, (start, end) in enumerate(record.spans.tolist()):
            spans.setdefault((int(start), int(end)), []).append(c)
        items: list[tuple[tuple[int, int], tuple[int, ...], int | None]] = []
        for (start, end), captions in spans.items():
            # the reference pools whole-clip captions too; its sub-span limit (dataset.py: 276-280) never bites once the
            # motion is under it, as a sub-span lies within its motion
            if test_items == "span" or (start, end) == (0, length):
                items.append(((start, end), tuple(captions), None))
            else:
                items.extend(((start, end), (c,), c) for c in captions)
        usable = []
        for (start, end), captions, line in items:
            if min(end - start, max_length) // unit_length < 1:  # whatever the draw: the items never change
                dropped["shorter_than_unit_length"] += 1
                continue
            usable.append(((start, end), captions, line))
        if usable:
            motions.append(_Motion(record, tuple(usable), len(spans) > 1))
    if not motions:
        raise EvaluationError(f"{manifest.location}: split {split!r} has no usable evaluation item "
                              f"(dropped: {dict(dropped) or 'none'})")
    settings = {"format": GT_FORMAT, "dataset_id": manifest.dataset_id, "split": split,
                "max_length": max_length, "unit_length": unit_length, "seed": seed, "require_action": require_action}
    if test_items != "span":  # span sets keep the keys (and cached embeddings) they always had
        settings["test_items"] = test_items
    return GroundTruthPool(manifest.dataset_id, str(manifest.location), split, tuple(motions), dict(dropped),
                           settings, token_features, source.report.as_dict())


def build_ground_truth(manifest: Manifest | str | Path, split: str = "test", *, max_length: int = 196,
                       unit_length: int = 4, seed: int = 0, backend: str = "webdataset",
                       require_action: bool = False, token_features: bool = False,
                       replication: int | None = None, test_items: str = "span") -> GroundTruthSet:
    """The evaluation items of ``split`` (see the module docstring); deterministic in (manifest, settings,
    ``replication``): None = the fixed set, r = replication r's re-drawn set (:meth:`GroundTruthPool.draw`). The
    split is verified strictly first (:func:`read_ground_truth_pool`). Several draws of one split: read the pool
    once and draw from it."""
    return read_ground_truth_pool(manifest, split, max_length=max_length, unit_length=unit_length, seed=seed,
                                  backend=backend, require_action=require_action,
                                  token_features=token_features, test_items=test_items).draw(replication)


# ---------------------------------------------------------------------------------------------------------------
# Embedding spaces (evaluators)
# ---------------------------------------------------------------------------------------------------------------


class EmbeddingSpace(Protocol):
    """An evaluator seen by the job: raw motions (and the items' captions) -> embeddings."""

    kind: str
    evaluator_id: str
    has_text: bool

    def encode_motions(self, features_raw: Tensor, lengths: Tensor, *, keep_padding: bool = False,
                       normalized: bool = False) -> Tensor:
        """Embeddings of (B, T, D) motions. keep_padding: the frames past each length are given to the encoder as
        they are (else zero, in the evaluator's normalisation); normalized: the motions are already in the
        evaluator's input space (its normalisation is skipped)."""
        ...

    def encode_texts(self, gt: GroundTruthSet, indices: np.ndarray, lengths: str = "sentence") -> Tensor:
        """Embeddings of the items' captions; ``lengths``: the caption length rule (T2M only:
        mfm.evaluators.t2m.CAPTION_LENGTHS)."""
        ...

    def describe(self) -> dict[str, Any]: ...


class _NormalisingEncoder:
    """Runs a model trained on manifest-normalised features on raw features."""

    def __init__(self, mean: np.ndarray, std: np.ndarray, device: torch.device) -> None:
        self.mean = torch.as_tensor(mean, dtype=torch.float32, device=device)
        self.std = torch.as_tensor(std, dtype=torch.float32, device=device)
        self.device = device

    def normalise(self, features_raw: Tensor, lengths: Tensor, keep_padding: bool = False,
                  normalized: bool = False) -> tuple[Tensor, Tensor]:
        lengths = lengths.to(self.device)
        x = features_raw.to(self.device)
        if not normalized:
            x = (x - self.mean) / self.std
        if keep_padding:
            return x, lengths
        return x * valid_frame_mask(lengths, features_raw.shape[1]).unsqueeze(-1), lengths


class _SavedEvaluatorSpace(_NormalisingEncoder):
    """A model saved by launch/train_evaluator.py, checked to be the expected kind, trained on this dataset and
    sized for its features (and captions, when it has a text side)."""

    kind: str
    has_text: bool
    noun: str  # for the wrong-kind message

    def __init__(self, path: Path, manifest: Manifest, device: torch.device) -> None:
        loaded = load_evaluator(path, device)
        if loaded.kind != self.kind:
            raise EvaluationError(f"{path}: a {loaded.kind!r} model, not {self.noun}")
        _check_evaluator_dataset(path, loaded.manifest_dataset_id, manifest)
        _check_dims(path, loaded.config.feature_dim, loaded.config.text_dim if self.has_text else None, manifest)
        super().__init__(manifest.mean, manifest.std, device)
        self.model, self.path = loaded.model, path
        self.evaluator_id, self.manifest_dataset_id = loaded.evaluator_id, loaded.manifest_dataset_id


class ContrastiveSpace(_SavedEvaluatorSpace):
    """The project's motion-CLIP evaluator (mfm.evaluators.contrastive) on the manifest's normalisation."""

    kind = "contrastive"
    has_text = True
    noun = "a contrastive evaluator"

    @torch.no_grad()
    def encode_motions(self, features_raw: Tensor, lengths: Tensor, *, keep_padding: bool = False,
                       normalized: bool = False) -> Tensor:
        return self.model.encode_motions(*self.normalise(features_raw, lengths, keep_padding, normalized)).float()

    @torch.no_grad()
    def encode_texts(self, gt: GroundTruthSet, indices: np.ndarray, lengths: str = "sentence") -> Tensor:
        # A pooled caption embedding: no caption length to choose (``lengths`` does not apply).
        return self.model.encode_texts(torch.from_numpy(gt.text_cond[indices]).to(self.device)).float()

    def describe(self) -> dict[str, Any]:
        return {"kind": self.kind, "id": self.evaluator_id, "path": str(self.path),
                "manifest_dataset_id": self.manifest_dataset_id}


class ClassifierSpace(_SavedEvaluatorSpace):
    """The action classifier: its encoder features are the action-to-motion metric space; logits give accuracy."""

    kind = "action_classifier"
    has_text = False
    noun = "an action classifier"

    def __init__(self, path: Path, manifest: Manifest, device: torch.device) -> None:
        super().__init__(path, manifest, device)
        self.action_classes: list[str] = list(self.model.action_classes)

    @torch.no_grad()
    def encode_motions(self, features_raw: Tensor, lengths: Tensor, *, keep_padding: bool = False,
                       normalized: bool = False) -> Tensor:
        return self.model.features(*self.normalise(features_raw, lengths, keep_padding, normalized)).float()

    @torch.no_grad()
    def logits(self, features_raw: Tensor, lengths: Tensor) -> Tensor:
        return self.model(*self.normalise(features_raw, lengths)).float()

    def encode_texts(self, gt: GroundTruthSet, indices: np.ndarray, lengths: str = "sentence") -> Tensor:
        raise EvaluationError("the action classifier has no text tower")

    def describe(self) -> dict[str, Any]:
        return {"kind": self.kind, "id": self.evaluator_id, "path": str(self.path),
                "manifest_dataset_id": self.manifest_dataset_id, "action_classes": self.action_classes}


class T2MSpace:
    """The official T2M evaluator (mfm.evaluators.t2m): raw Guo features and POS-tagged caption tokens."""

    kind = "t2m"
    has_text = True

    def __init__(self, cfg: EvaluatorConfig, skeleton: str, device: torch.device) -> None:
        dataset = t2m_dataset_for_skeleton(skeleton)
        norm_dir = cfg.t2m_norm_dir or None
        try:
            files = resolve_t2m_files(cfg.t2m_checkpoint_dir or ".", cfg.t2m_glove_dir or ".", dataset, norm_dir)
        except T2MEvaluatorFilesMissing as exc:
            raise EvaluatorUnavailable(
                f"{exc}\nPoint the job at them with evaluator.t2m_checkpoint_dir=DIR evaluator.t2m_glove_dir=DIR "
                f"(and evaluator.t2m_norm_dir=DIR for {dataset}_mean.npy/{dataset}_std.npy), or use "
                "evaluator.kind=contrastive (launch/train_evaluator.py).") from exc
        self.model = T2MEvaluator.from_files(cfg.t2m_checkpoint_dir or ".", cfg.t2m_glove_dir or ".", dataset,
                                             device, norm_dir=norm_dir, allow_pickle=cfg.t2m_allow_pickle)
        self.evaluator_id = f"t2m-{dataset}-{sha256_file(files.checkpoint)}"
        self.files = files
        self.dataset = dataset

    def encode_motions(self, features_raw: Tensor, lengths: Tensor, *, keep_padding: bool = False,
                       normalized: bool = False) -> Tensor:
        return self.model.encode_motions(features_raw, lengths.cpu(), keep_padding=keep_padding,
                                         normalized=normalized).float()

    def encode_texts(self, gt: GroundTruthSet, indices: np.ndarray, lengths: str = "sentence") -> Tensor:
        tokens = [gt.caption_tokens[i] for i in indices]
        if any(len(t) == 0 for t in tokens):
            raise EvaluationError(
                f"the T2M evaluator reads captions as word/POS tokens, but item "
                f"{gt.ids[indices[[len(t) == 0 for t in tokens].index(True)]]!r} of {gt.dataset_id[:16]} has none "
                "(only the HumanML3D and KIT-ML sources carry them); use evaluator.kind=contrastive")
        return self.model.encode_texts(tokens, lengths).float()

    def describe(self) -> dict[str, Any]:
        return {"kind": self.kind, "id": self.evaluator_id, "dataset": self.dataset,
                "checkpoint": str(self.files.checkpoint), "epoch": self.model.checkpoint_epoch}


def _check_evaluator_dataset(path: Path, evaluator_dataset: str, manifest: Manifest) -> None:
    if evaluator_dataset != manifest.dataset_id:
        raise EvaluationError(
            f"{path} was trained on dataset {evaluator_dataset[:16]}, but the evaluation data is "
            f"{manifest.dataset_id[:16]} ({manifest.location}): its normalisation and embedding space belong to "
            "its own dataset. Train one on this dataset with launch/train_evaluator.py.")


def _check_dims(path: Path, feature_dim: int, text_dim: int | None, manifest: Manifest) -> None:
    spec = manifest.record_spec
    if feature_dim != spec.feature_dim or (text_dim is not None and text_dim != spec.text_dim):
        raise EvaluationError(f"{path}: built for features {feature_dim}-D / text {text_dim}-D, the dataset has "
                              f"{spec.feature_dim}-D / {spec.text_dim}-D")


def default_evaluator_dir(dataset_id: str) -> Path:
    """Where launch/train_evaluator.py saves, and evaluator.path=auto looks: runs/evaluators/<dataset id>."""
    return Path("runs") / "evaluators" / dataset_id[:16]


def resolve_evaluator_file(setting: str, manifest: Manifest, filename: str, *, required: bool) -> Path | None:
    if setting == "":
        return None
    path = default_evaluator_dir(manifest.dataset_id) / filename if setting == "auto" else Path(setting)
    if path.is_file() and path.with_suffix(".json").is_file():
        return path
    if not required and setting == "auto":
        return None
    raise EvaluatorUnavailable(
        f"no evaluator at {path} (weights + .json sidecar). Train one on this dataset first:\n"
        f"  python launch/train_evaluator.py data.manifest={manifest.location}\n"
        "then pass evaluator.path=<its contrastive.safetensors> (or leave evaluator.path=auto), "
        "or use the official one with evaluator.kind=t2m.")
