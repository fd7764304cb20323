"""The project's own evaluator: a motion-CLIP (FLAME's mCLIP / TMR style) trained on the dataset's cached text
embeddings, plus an action classifier for action-to-motion accuracy.

Why a second evaluator: the official T2M evaluator only understands the 263/251-D Guo representation with its own
normalisation and GloVe tokens; this one works on any manifest (any skeleton, any cached text encoder). Its numbers
are comparable only between runs scored with the same ``evaluator_id`` (sha256 of the weights file) on the same
``manifest_dataset_id``, which is why both travel with the weights and should be copied into every result.

* :class:`MotionEncoder`: Linear -> sinusoidal positions -> pre-norm Transformer with a key-padding mask -> CLS token
  (or masked mean) -> LayerNorm -> projection. Input = features normalised with the manifest's normalisation.
* :class:`TextHead`: MLP on the cached pooled caption embedding (manifest ``text_encoder.dim``).
* Loss: symmetric InfoNCE over the cosine-similarity matrix (CLIP), optionally ignoring negatives whose captions are
  near-duplicates of the positive's (TMR's ``threshold_selfsim`` filtering).
* Files: ``NAME.safetensors`` (weights) + ``NAME.json`` (kind, config, evaluator_id, manifest_dataset_id, action
  classes), the JSON written last so its presence marks a complete save.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from safetensors.torch import load as load_safetensors_bytes
from safetensors.torch import save as save_safetensors_bytes
from torch import nn

from mfm.metrics import R_PRECISION_BATCH_SIZE, r_precision

FORMAT_VERSION = 1
POOLINGS = ("cls", "mean")


@dataclass
class ContrastiveEvaluatorConfig:
    """Architecture and loss of :class:`ContrastiveEvaluator` (and of :class:`ActionClassifier`'s motion encoder)."""

    feature_dim: int = 263
    """Per-frame motion feature size (manifest ``feature_spec.dim``)."""
    text_dim: int = 384
    """Size of the cached pooled text embedding (manifest ``text_encoder.dim``: 384 MiniLM, 512 CLIP)."""
    latent_dim: int = 256
    """Transformer width."""
    num_layers: int = 4
    num_heads: int = 4
    ff_dim: int = 1024
    dropout: float = 0.1
    attention_dropout: float | None = None
    """Dropout on the attention weights; None: ``dropout`` (torch's TransformerEncoderLayer default, the evaluators
    trained so far). 0 lets CPU attention take its fused kernel (PyTorch falls back to the unfused math path for
    attention dropout): about 1.6x faster training steps on CPU for the synthetic preset's evaluator; the residual
    and feed-forward dropout stay ``dropout``."""
    out_dim: int = 256
    """Joint embedding size (256 TMR-like, 512 FLAME-like)."""
    text_hidden_dim: int = 512
    """Hidden size of the text head MLP."""
    pooling: str = "cls"
    """'cls': a learned summary token; 'mean': masked mean of the frame outputs."""
    temperature: float = 0.07
    """InfoNCE temperature (CLIP's initial value; FLAME's mCLIP)."""
    selfsim_threshold: float | None = 0.8
    """TMR's caption self-similarity threshold on the (cos + 1) / 2 scale: a negative whose caption embedding has
    cosine > 2·0.8 − 1 = 0.6 with the positive's is left out of the loss. None: no filtering."""

    def __post_init__(self) -> None:
        for name in ("feature_dim", "text_dim", "latent_dim", "num_layers", "num_heads", "ff_dim", "out_dim",
                     "text_hidden_dim"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
                raise ValueError(f"ContrastiveEvaluatorConfig.{name} must be a positive int, got {value!r}")
        if self.latent_dim % self.num_heads or self.latent_dim % 2:
            raise ValueError(f"latent_dim {self.latent_dim} must be even and divisible by num_heads {self.num_heads}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout}")
        if self.attention_dropout is not None and not 0.0 <= self.attention_dropout < 1.0:
            raise ValueError(f"attention_dropout must be in [0, 1) or None, got {self.attention_dropout}")
        if self.pooling not in POOLINGS:
            raise ValueError(f"pooling must be one of {POOLINGS}, got {self.pooling!r}")
        if not self.temperature > 0:
            raise ValueError(f"temperature must be > 0, got {self.temperature}")
        if self.selfsim_threshold is not None and not 0.0 < self.selfsim_threshold <= 1.0:
            raise ValueError(f"selfsim_threshold must be in (0, 1] or None, got {self.selfsim_threshold}")

    @classmethod
    def from_manifest(cls, manifest: Mapping[str, Any], **overrides: Any) -> ContrastiveEvaluatorConfig:
        """Sizes from a dataset manifest (``feature_spec.dim``, ``text_encoder.dim``), other fields from overrides."""
        try:
            sizes = {"feature_dim": int(manifest["feature_spec"]["dim"]),
                     "text_dim": int(manifest["text_encoder"]["dim"])}
        except (KeyError, TypeError) as exc:
            raise ValueError(f"manifest lacks feature_spec.dim or text_encoder.dim: {exc!r}") from exc
        return cls(**{**sizes, **overrides})

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> ContrastiveEvaluatorConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown ContrastiveEvaluatorConfig keys: {unknown}")
        return cls(**data)


def sinusoidal_positions(num_frames: int, dim: int, device: torch.device) -> torch.Tensor:
    """(num_frames, dim) interleaved sin/cos table (Vaswani et al.), computed on the fly: no length limit."""
    position = torch.arange(num_frames, device=device, dtype=torch.float32)[:, None]
    frequencies = torch.exp(torch.arange(0, dim, 2, device=device, dtype=torch.float32) * (-math.log(10000.0) / dim))
    angles = position * frequencies
    return torch.stack((angles.sin(), angles.cos()), dim=-1).flatten(-2)


def padding_mask(lengths: torch.Tensor, num_frames: int) -> torch.Tensor:
    """(B, num_frames) bool, True on padded frames (nn.MultiheadAttention's key_padding_mask convention)."""
    return torch.arange(num_frames, device=lengths.device)[None, :] >= lengths[:, None]


class MotionEncoder(nn.Module):
    """Normalised features (B, T, D) with valid lengths (B,) -> (B, out_dim), independent of padding content."""

    def __init__(self, config: ContrastiveEvaluatorConfig) -> None:
        super().__init__()
        self.config = config
        self.input_proj = nn.Linear(config.feature_dim, config.latent_dim)
        self.cls_token = nn.Parameter(torch.randn(config.latent_dim) * 0.02) if config.pooling == "cls" else None
        layer = nn.TransformerEncoderLayer(config.latent_dim, config.num_heads, config.ff_dim, config.dropout,
                                           activation="gelu", batch_first=True, norm_first=True)
        if config.attention_dropout is not None:
            layer.self_attn.dropout = config.attention_dropout  # MultiheadAttention's dropout_p (a float)
        self.transformer = nn.TransformerEncoder(layer, config.num_layers, enable_nested_tensor=False)
        self.final_norm = nn.LayerNorm(config.latent_dim)
        self.projection = nn.Linear(config.latent_dim, config.out_dim)

    def forward(self, features_norm: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        if features_norm.ndim != 3 or features_norm.shape[-1] != self.config.feature_dim:
            raise ValueError(f"features must be (B, T, {self.config.feature_dim}), got {tuple(features_norm.shape)}")
        batch, num_frames, _ = features_norm.shape
        lengths = lengths.to(features_norm.device).long().reshape(-1)
        if lengths.shape[0] != batch or int(lengths.min()) < 1 or int(lengths.max()) > num_frames:
            raise ValueError(f"lengths must be ({batch},) in [1, {num_frames}], got {lengths.tolist()}")
        pad = padding_mask(lengths, num_frames)
        # Zero padded frames first: masked attention weights are 0, but 0 * NaN garbage would still be NaN.
        x = features_norm.masked_fill(pad[..., None], 0.0)
        x = self.input_proj(x) + sinusoidal_positions(num_frames, self.config.latent_dim, x.device).to(x.dtype)
        if self.cls_token is not None:
            x = torch.cat([self.cls_token.expand(batch, 1, -1).to(x.dtype), x], dim=1)
            pad = torch.cat([torch.zeros(batch, 1, dtype=torch.bool, device=pad.device), pad], dim=1)
        h = self.transformer(x, src_key_padding_mask=pad)
        if self.cls_token is not None:
            pooled = h[:, 0]
        else:
            valid = (~pad).unsqueeze(-1).to(h.dtype)
            pooled = (h * valid).sum(dim=1) / valid.sum(dim=1)
        return self.projection(self.final_norm(pooled))


class TextHead(nn.Module):
    """Cached pooled text embedding (B, text_dim) -> (B, out_dim)."""

    def __init__(self, config: ContrastiveEvaluatorConfig) -> None:
        super().__init__()
        self.config = config
        self.mlp = nn.Sequential(
            nn.Linear(config.text_dim, config.text_hidden_dim),
            nn.GELU(),
            nn.Dropout(config.dropout),
            nn.Linear(config.text_hidden_dim, config.out_dim),
        )

    def forward(self, text_emb: torch.Tensor) -> torch.Tensor:
        if text_emb.ndim != 2 or text_emb.shape[-1] != self.config.text_dim:
            raise ValueError(f"text embeddings must be (B, {self.config.text_dim}), got {tuple(text_emb.shape)}")
        return self.mlp(text_emb)


def duplicate_caption_mask(caption_emb: torch.Tensor, selfsim_threshold: float) -> torch.Tensor:
    """(B, B) bool, True off the diagonal where two captions are near-duplicates: TMR's filter,
    cosine(caption_i, caption_j) > 2·threshold − 1 (threshold on the (cos + 1) / 2 scale)."""
    unit = F.normalize(caption_emb.float(), dim=-1)
    similar = unit @ unit.T > 2.0 * selfsim_threshold - 1.0
    similar.fill_diagonal_(False)
    return similar


def infonce_loss(motion_emb: torch.Tensor, text_emb: torch.Tensor, temperature: float = 0.07, *,
                 ignore_negatives: torch.Tensor | None = None) -> torch.Tensor:
    """Symmetric InfoNCE: mean of the motion->text and text->motion cross-entropies over cosine similarity / τ.

    Row i of ``motion_emb`` pairs with row i of ``text_emb``. ``ignore_negatives`` (B, B) bool removes pairs from
    both softmaxes (its diagonal must be False), e.g. :func:`duplicate_caption_mask` so that "a person walks" is not
    pushed away from another walking clip.
    """
    if motion_emb.shape != text_emb.shape or motion_emb.ndim != 2:
        raise ValueError(f"motion and text embeddings must both be (B, E), got {tuple(motion_emb.shape)} "
                         f"and {tuple(text_emb.shape)}")
    logits = F.normalize(motion_emb, dim=-1) @ F.normalize(text_emb, dim=-1).T / temperature
    if ignore_negatives is not None:
        if ignore_negatives.shape != logits.shape or bool(ignore_negatives.diagonal().any()):
            raise ValueError(f"ignore_negatives must be a {tuple(logits.shape)} bool mask with a False diagonal")
        logits = logits.masked_fill(ignore_negatives.to(logits.device), float("-inf"))
    targets = torch.arange(logits.shape[0], device=logits.device)
    return 0.5 * (F.cross_entropy(logits, targets) + F.cross_entropy(logits.T, targets))


def retrieval_accuracy(motion_emb: torch.Tensor, text_emb: torch.Tensor, top_k: Sequence[int] = (1, 2, 3),
                       batch_size: int = R_PRECISION_BATCH_SIZE) -> dict[int, float]:
    """Text->motion R@k among consecutive batches of ``batch_size`` pairs (incomplete last batch dropped).

    Uses :func:`mfm.metrics.r_precision` on L2-normalised embeddings, where Euclidean ranking equals cosine ranking.
    Returns ``{k: accuracy}``.
    """
    ks = sorted(set(int(k) for k in top_k))
    if not ks or ks[0] < 1:
        raise ValueError(f"top_k must be positive ints, got {top_k}")
    text = F.normalize(text_emb.detach().float(), dim=-1).cpu()
    motion = F.normalize(motion_emb.detach().float(), dim=-1).cpu()
    scores = r_precision(text, motion, batch_size=batch_size, top_k=ks[-1])
    return {k: scores[k - 1] for k in ks}


class ContrastiveEvaluator(nn.Module):
    """Motion and text towers into one unit-norm embedding space."""

    kind = "contrastive"

    def __init__(self, config: ContrastiveEvaluatorConfig) -> None:
        super().__init__()
        self.config = config
        self.motion_encoder = MotionEncoder(config)
        self.text_head = TextHead(config)

    def encode_motions(self, features_norm: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """(B, T, D) manifest-normalised features, (B,) lengths -> (B, out_dim) unit-norm embeddings."""
        return F.normalize(self.motion_encoder(features_norm, lengths), dim=-1)

    def encode_texts(self, text_emb: torch.Tensor) -> torch.Tensor:
        """(B, text_dim) cached pooled caption embeddings -> (B, out_dim) unit-norm embeddings."""
        return F.normalize(self.text_head(text_emb), dim=-1)

    def training_loss(self, features_norm: torch.Tensor, lengths: torch.Tensor, text_emb: torch.Tensor) -> torch.Tensor:
        """InfoNCE of a batch of (motion, caption) pairs with the config's temperature and duplicate filtering."""
        threshold = self.config.selfsim_threshold
        duplicates = None if threshold is None else duplicate_caption_mask(text_emb, threshold)
        return infonce_loss(self.encode_motions(features_norm, lengths), self.encode_texts(text_emb),
                            self.config.temperature, ignore_negatives=duplicates)


class ActionClassifier(nn.Module):
    """Action recogniser for action-to-motion accuracy: :class:`MotionEncoder` + Linear over the classes.

    :meth:`features` (the encoder output) is the space action-to-motion FID/diversity are computed in.
    """

    kind = "action_classifier"

    def __init__(self, config: ContrastiveEvaluatorConfig, action_classes: Sequence[str]) -> None:
        super().__init__()
        if len(action_classes) < 2 or len(set(action_classes)) != len(action_classes):
            raise ValueError(f"action_classes must be >= 2 distinct names, got {list(action_classes)}")
        self.config = config
        self.action_classes = list(action_classes)
        self.motion_encoder = MotionEncoder(config)
        self.classifier = nn.Linear(config.out_dim, len(self.action_classes))

    def features(self, features_norm: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        return self.motion_encoder(features_norm, lengths)

    def forward(self, features_norm: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """Class logits (B, num_classes)."""
        return self.classifier(self.features(features_norm, lengths))


# ----------------------------------------------------------------------------------------------------------------------
# Saving / loading


@dataclass(frozen=True)
class LoadedEvaluator:
    model: ContrastiveEvaluator | ActionClassifier
    config: ContrastiveEvaluatorConfig
    evaluator_id: str
    """sha256 of the weights file: copy it into every result scored with this evaluator."""
    manifest_dataset_id: str
    """``dataset_id`` of the manifest whose data (and normalisation) trained the evaluator."""
    kind: str


def sidecar_path(weights_path: str | Path) -> Path:
    return Path(weights_path).with_suffix(".json")


def _check_weights_path(path: str | Path) -> Path:
    path = Path(path)
    if path.suffix != ".safetensors":
        raise ValueError(f"{path}: evaluator weights must be a .safetensors file (the sidecar is the same name .json)")
    return path


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def save_evaluator(path: str | Path, model: ContrastiveEvaluator | ActionClassifier,
                   config: ContrastiveEvaluatorConfig, manifest_dataset_id: str) -> str:
    """Write ``path`` (.safetensors) and its .json sidecar; return the evaluator_id (sha256 of the weights file)."""
    path = _check_weights_path(path)
    if config != model.config:
        raise ValueError("config does not match the model's config")
    if not manifest_dataset_id:
        raise ValueError("manifest_dataset_id is required: results must say which data trained the evaluator")
    tensors = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    weights = save_safetensors_bytes(tensors)
    evaluator_id = hashlib.sha256(weights).hexdigest()
    sidecar = {
        "format_version": FORMAT_VERSION,
        "kind": model.kind,
        "evaluator_id": evaluator_id,
        "weights_file": path.name,
        "manifest_dataset_id": manifest_dataset_id,
        "config": config.to_dict(),
    }
    if isinstance(model, ActionClassifier):
        sidecar["action_classes"] = model.action_classes
    path.parent.mkdir(parents=True, exist_ok=True)
    _atomic_write(path, weights)
    # Sidecar last: its presence marks a complete save.
    _atomic_write(sidecar_path(path), (json.dumps(sidecar, indent=2, sort_keys=True) + "\n").encode())
    return evaluator_id


def _read_sidecar(path: Path) -> dict:
    meta_path = sidecar_path(path)
    if not meta_path.is_file():
        raise FileNotFoundError(f"{meta_path}: evaluator sidecar missing (an incomplete save, or not an evaluator)")
    try:
        meta = json.loads(meta_path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{meta_path}: not valid JSON: {exc}") from exc
    if meta.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"{meta_path}: format_version {meta.get('format_version')!r}, expected {FORMAT_VERSION}")
    for key in ("kind", "evaluator_id", "manifest_dataset_id", "config"):
        if key not in meta:
            raise ValueError(f"{meta_path}: missing {key!r}")
    return meta


def load_evaluator(path: str | Path, device: str | torch.device = "cpu") -> LoadedEvaluator:
    """Load a model saved by :func:`save_evaluator`, in eval mode; the weights must hash to the recorded id."""
    path = _check_weights_path(path)
    meta = _read_sidecar(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: evaluator weights missing (sidecar {sidecar_path(path)} exists)")
    weights = path.read_bytes()
    evaluator_id = hashlib.sha256(weights).hexdigest()
    if evaluator_id != meta["evaluator_id"]:
        raise ValueError(f"{path}: sha256 {evaluator_id} does not match evaluator_id {meta['evaluator_id']} "
                         f"recorded in {sidecar_path(path)} (file modified or mismatched pair)")
    config = ContrastiveEvaluatorConfig.from_dict(meta["config"])
    if meta["kind"] == ContrastiveEvaluator.kind:
        model: ContrastiveEvaluator | ActionClassifier = ContrastiveEvaluator(config)
    elif meta["kind"] == ActionClassifier.kind:
        model = ActionClassifier(config, meta.get("action_classes") or [])
    else:
        raise ValueError(f"{sidecar_path(path)}: unknown evaluator kind {meta['kind']!r}")
    try:
        model.load_state_dict(load_safetensors_bytes(weights), strict=True)
    except RuntimeError as exc:
        raise ValueError(f"{path}: weights do not match the config in {sidecar_path(path)}: {exc}") from exc
    model.to(device).eval()
    return LoadedEvaluator(model, config, evaluator_id, meta["manifest_dataset_id"], meta["kind"])
