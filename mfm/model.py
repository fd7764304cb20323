"""The MFM velocity-field Transformer (MDM's ``trans_enc`` backbone, batch-first, padding-aware).

Token sequence seen by the encoder, batch-first ``(B, P + T, latent)``::

    [length token]?  [time ⊕ condition token]  [motion frame 1 … T]
    └─ FLAME option ┘ └─ MFM/MDM prefix token ┘

* Time ``t ∈ [0, 1]`` (noise at 0, data at 1) goes through a *continuous* sinusoidal embedding of ``t·1000`` and a
  Linear-SiLU-Linear MLP. MFM looks ``(t*1000).long()`` up in the positional table instead; the continuous form is
  identical at integer points but does not collapse an adaptive solver's nearby evaluation times onto one embedding
  (a piecewise-constant field in ``t`` makes dopri5's error estimate meaningless).
* The condition (pooled text embedding projected by a Linear, or a learned action embedding) is *added* to the time
  embedding, as in MFM/MDM. Classifier-free training zeroes the raw condition for ``cond_drop_prob`` of the samples;
  ``cond_mask`` forces the drop per sample so a sampler can batch its conditional and unconditional halves.
* Unlike MFM (which attends over the 196-frame zero padding), padded frames are masked out of attention with a
  boolean key-padding mask and their outputs are zeroed, so a clip's velocity does not depend on how it was padded.

The HumanML3D preset (263, 512, 1024, 8 layers, 4 heads, CLIP cond 512, post-norm) has exactly 17,880,327
parameters, the same as MFM's ``MDM_Flow`` without CLIP (17.88 M).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

ACTIVATIONS = {"gelu": F.gelu, "relu": F.relu, "silu": F.silu}

# MFM feeds the sinusoidal table with t*1000 (its diffusion-step scale); keep the scale so the embedding matches.
TIME_SCALE = 1000.0


@dataclass
class ModelConfig:
    """Architecture of :class:`MotionFlowTransformer`; defaults are MFM's HumanML3D text model."""

    feature_dim: int = 263
    """Per-frame motion feature size (263 HumanML3D, 251 KIT)."""
    latent_dim: int = 512
    """Transformer width."""
    ff_dim: int = 1024
    """Hidden size of the feed-forward block."""
    num_layers: int = 8
    num_heads: int = 4
    dropout: float = 0.1
    """Dropout on embeddings, attention probabilities and residual branches (as nn.TransformerEncoderLayer)."""
    activation: str = "gelu"
    """Feed-forward activation: one of ACTIVATIONS."""
    cond_dim: int = 512
    """Size of the pooled text embedding (dataset manifest ``text_encoder.dim``: 512 CLIP, 384 MiniLM).
    Unused by action models (``num_actions > 0``)."""
    num_actions: int = 0
    """0: text-conditioned model; > 0: action-class model with a learned embedding per class."""
    cond_drop_prob: float = 0.1
    """Probability of zeroing a sample's condition in training (classifier-free guidance)."""
    length_token: bool = False
    """FLAME option: prepend a learned embedding of the motion's valid length as an extra token."""
    max_frames: int = 196
    """Largest motion length the length token can embed (table of max_frames + 1 rows)."""
    max_len: int = 5000
    """Rows of the sinusoidal positional table: prefix tokens + frames must fit."""
    norm_first: bool = False
    """False: post-norm like MDM's nn.TransformerEncoder (parity); True: pre-norm with a final LayerNorm."""

    def __post_init__(self) -> None:
        positive = {
            "feature_dim": self.feature_dim,
            "latent_dim": self.latent_dim,
            "ff_dim": self.ff_dim,
            "num_layers": self.num_layers,
            "num_heads": self.num_heads,
            "max_len": self.max_len,
            "max_frames": self.max_frames,
        }
        for name, value in positive.items():
            if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
                raise ValueError(f"ModelConfig.{name} must be a positive int, got {value!r}")
        if self.latent_dim % self.num_heads != 0:
            raise ValueError(
                f"ModelConfig.latent_dim ({self.latent_dim}) must be divisible by num_heads ({self.num_heads})"
            )
        if self.latent_dim % 2 != 0:
            raise ValueError(f"ModelConfig.latent_dim must be even (sinusoidal embeddings), got {self.latent_dim}")
        if not isinstance(self.num_actions, int) or self.num_actions < 0:
            raise ValueError(f"ModelConfig.num_actions must be an int >= 0, got {self.num_actions!r}")
        if self.num_actions == 0 and (not isinstance(self.cond_dim, int) or self.cond_dim <= 0):
            raise ValueError(
                f"ModelConfig.cond_dim must be a positive int for a text model (num_actions=0), got {self.cond_dim!r}"
            )
        for name in ("dropout", "cond_drop_prob"):
            value = getattr(self, name)
            if not 0.0 <= value < 1.0:
                raise ValueError(f"ModelConfig.{name} must be in [0, 1), got {value!r}")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"ModelConfig.activation must be one of {sorted(ACTIVATIONS)}, got {self.activation!r}")
        if self.length_token and self.max_frames + self.num_prefix_tokens > self.max_len:
            raise ValueError(
                f"ModelConfig.max_frames ({self.max_frames}) + prefix tokens must fit in max_len ({self.max_len})"
            )

    @property
    def num_prefix_tokens(self) -> int:
        """Tokens before the motion frames: the time/condition token, plus the length token if enabled."""
        return 1 + int(self.length_token)

    @property
    def is_action_model(self) -> bool:
        return self.num_actions > 0


def sinusoidal_embedding(positions: torch.Tensor, dim: int) -> torch.Tensor:
    """MDM's sinusoid for real-valued positions: ``[..., 2i] = sin(p·ω_i)``, ``[..., 2i+1] = cos(p·ω_i)``.

    ``ω_i = 10000^(-2i/dim)``. Evaluated in fp32 whatever the autocast state, because bf16 cannot hold
    ``p·ω`` for positions in the hundreds accurately enough for sin/cos.
    """
    positions = positions.float()
    half = torch.arange(0, dim, 2, device=positions.device, dtype=torch.float32)
    frequencies = torch.exp(half * (-math.log(10000.0) / dim))
    angles = positions.unsqueeze(-1) * frequencies
    # Interleave sin/cos exactly like MDM's PositionalEncoding table (pe[:, 0::2] = sin, pe[:, 1::2] = cos).
    return torch.stack((angles.sin(), angles.cos()), dim=-1).flatten(-2)


def valid_frame_mask(lengths: torch.Tensor, num_frames: int) -> torch.Tensor:
    """(B, num_frames) bool, True on the first ``lengths[b]`` frames of each sample."""
    frames = torch.arange(num_frames, device=lengths.device)
    return frames.unsqueeze(0) < lengths.unsqueeze(1)


def draw_cond_drop_mask(
    batch: int, prob: float, generator: torch.Generator | None = None, device: torch.device | None = None
) -> torch.Tensor:
    """(batch,) bool, True for the samples whose condition is dropped; each is dropped with probability ``prob``.

    Drawn on the generator's device (so a CPU generator works with a GPU model), then moved to ``device``.
    """
    draw_device = generator.device if generator is not None else device
    return (torch.rand(batch, generator=generator, device=draw_device) < prob).to(device)


class FP32LayerNorm(nn.LayerNorm):
    """LayerNorm computed in fp32 and returned in the input dtype: bf16 mean/variance over 512 channels loses the
    small residual updates the post-norm stack depends on."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        weight = self.weight.float() if self.weight is not None else None
        bias = self.bias.float() if self.bias is not None else None
        return F.layer_norm(x.float(), self.normalized_shape, weight, bias, self.eps).to(x.dtype)


class EncoderLayer(nn.Module):
    """nn.TransformerEncoderLayer's computation, batch-first, with attention through
    ``F.scaled_dot_product_attention`` (fused kernels on GPU) and a boolean key-padding mask.

    Same parameters as ``nn.TransformerEncoderLayer(d, heads, ff, dropout)``, so counts and init match MDM.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        d = config.latent_dim
        self.num_heads = config.num_heads
        self.dropout = config.dropout
        self.norm_first = config.norm_first
        self.activation = ACTIVATIONS[config.activation]
        self.qkv = nn.Linear(d, 3 * d)
        self.out_proj = nn.Linear(d, d)
        self.linear1 = nn.Linear(d, config.ff_dim)
        self.linear2 = nn.Linear(config.ff_dim, d)
        self.norm1 = FP32LayerNorm(d)
        self.norm2 = FP32LayerNorm(d)
        # nn.MultiheadAttention's initialisation, for parity with MDM.
        nn.init.xavier_uniform_(self.qkv.weight)
        nn.init.zeros_(self.qkv.bias)
        nn.init.zeros_(self.out_proj.bias)

    def _attention(self, x: torch.Tensor, attn_mask: torch.Tensor | None) -> torch.Tensor:
        batch, seq, d = x.shape
        q, k, v = (
            self.qkv(x).view(batch, seq, 3, self.num_heads, d // self.num_heads).permute(2, 0, 3, 1, 4).unbind(0)
        )
        dropout_p = self.dropout if self.training else 0.0
        out = F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask, dropout_p=dropout_p)
        out = out.transpose(1, 2).reshape(batch, seq, d)
        return F.dropout(self.out_proj(out), self.dropout, self.training)

    def _feed_forward(self, x: torch.Tensor) -> torch.Tensor:
        hidden = F.dropout(self.activation(self.linear1(x)), self.dropout, self.training)
        return F.dropout(self.linear2(hidden), self.dropout, self.training)

    def forward(self, x: torch.Tensor, attn_mask: torch.Tensor | None = None) -> torch.Tensor:
        """x: (B, S, d); attn_mask: (B, 1, 1, S) bool, True = key may be attended, or None (attend to all)."""
        if self.norm_first:
            x = x + self._attention(self.norm1(x), attn_mask)
            return x + self._feed_forward(self.norm2(x))
        x = self.norm1(x + self._attention(x, attn_mask))
        return self.norm2(x + self._feed_forward(x))


class TimeEmbedding(nn.Module):
    """Continuous sinusoid of ``t·1000`` → Linear → SiLU → Linear (MDM's TimestepEmbedder, without rounding)."""

    def __init__(self, latent_dim: int) -> None:
        super().__init__()
        self.latent_dim = latent_dim
        self.mlp = nn.Sequential(nn.Linear(latent_dim, latent_dim), nn.SiLU(), nn.Linear(latent_dim, latent_dim))

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        return self.mlp(sinusoidal_embedding(t.float() * TIME_SCALE, self.latent_dim))


class MotionFlowTransformer(nn.Module):
    """Velocity field ``v(x_t, t, condition)`` over normalised motion features (B, T, D)."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        d = config.latent_dim
        self.input_proj = nn.Linear(config.feature_dim, d)
        self.time_embedding = TimeEmbedding(d)
        if config.is_action_model:
            # MDM's EmbedAction: an N(0, 1) table, zeroed (not replaced) when the condition is dropped.
            self.action_embedding = nn.Embedding(config.num_actions, d)
        else:
            self.cond_proj = nn.Linear(config.cond_dim, d)
        if config.length_token:
            self.length_embedding = nn.Embedding(config.max_frames + 1, d)
        # Not persistent: it is a pure function of (max_len, d), so checkpoints stay small and max_len can change.
        self.register_buffer(
            "positional_table", sinusoidal_embedding(torch.arange(config.max_len), d), persistent=False
        )
        self.layers = nn.ModuleList(EncoderLayer(config) for _ in range(config.num_layers))
        # Pre-norm leaves the residual stream un-normalised; post-norm (MDM) already ends in a LayerNorm.
        self.final_norm = FP32LayerNorm(d) if config.norm_first else nn.Identity()
        self.output_proj = nn.Linear(d, config.feature_dim)

    def forward(
        self,
        x: torch.Tensor,
        t: torch.Tensor,
        cond: torch.Tensor,
        lengths: torch.Tensor | None = None,
        *,
        cond_mask: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Velocity at ``x`` (B, T, D) and times ``t`` (B,) in [0, 1].

        cond: (B, cond_dim) float text embeddings, or (B,) long action ids for an action model.
        lengths: (B,) valid frames per sample; frames beyond are padding, hidden from attention and zeroed in the
            output. None: every frame is valid (and attention runs unmasked, the fastest kernel).
        cond_mask: (B,) bool, True = drop that sample's condition. Overrides the random training-time dropout, so
            one batched call can hold a sampler's conditional and unconditional halves.
        generator: RNG for the training-time condition dropout (global RNG if None).
        Returns the velocity (B, T, D) in ``x``'s dtype (fp32 under bf16 autocast, for the ODE solver).
        """
        batch, num_frames, _ = self._check_inputs(x, t, cond, lengths, cond_mask)
        if cond_mask is None and self.training and self.config.cond_drop_prob > 0:
            cond_mask = draw_cond_drop_mask(batch, self.config.cond_drop_prob, generator, x.device)

        if lengths is not None:
            lengths = lengths.to(x.device, non_blocking=True)
        frame_mask = None if lengths is None else valid_frame_mask(lengths, num_frames)

        prefix = [self._time_condition_token(t, cond, cond_mask)]
        if self.config.length_token:
            if lengths is None:
                lengths = torch.full((batch,), num_frames, dtype=torch.long, device=x.device)
            prefix.insert(0, self.length_embedding(lengths.long()))
        motion = self.input_proj(x)
        tokens = torch.cat([token.unsqueeze(1).to(motion.dtype) for token in prefix] + [motion], dim=1)
        # The fp32 table promotes the residual stream to fp32 under autocast; only the matmuls run in bf16.
        tokens = tokens + self.positional_table[: tokens.shape[1]]
        tokens = F.dropout(tokens, self.config.dropout, self.training)

        attn_mask = None
        if frame_mask is not None:
            prefix_valid = torch.ones(batch, len(prefix), dtype=torch.bool, device=x.device)
            attn_mask = torch.cat([prefix_valid, frame_mask], dim=1)[:, None, None, :]
        for layer in self.layers:
            tokens = layer(tokens, attn_mask)
        velocity = self.output_proj(self.final_norm(tokens[:, len(prefix) :]))
        if frame_mask is not None:
            velocity = velocity * frame_mask.unsqueeze(-1)
        return velocity.to(x.dtype)

    def _time_condition_token(
        self, t: torch.Tensor, cond: torch.Tensor, cond_mask: torch.Tensor | None
    ) -> torch.Tensor:
        """(B, latent): time embedding + condition embedding (MFM's single prefix token)."""
        keep = None if cond_mask is None else (~cond_mask).unsqueeze(1)
        if self.config.is_action_model:
            cond_embedding = self.action_embedding(cond)
            if keep is not None:
                cond_embedding = cond_embedding * keep
        else:
            # Zero the raw embedding before the projection, as MDM's mask_cond: the null condition is the bias.
            cond_embedding = self.cond_proj(cond if keep is None else cond * keep)
        return self.time_embedding(t) + cond_embedding

    def _check_inputs(
        self,
        x: torch.Tensor,
        t: torch.Tensor,
        cond: torch.Tensor,
        lengths: torch.Tensor | None,
        cond_mask: torch.Tensor | None,
    ) -> tuple[int, int, int]:
        """Shape/dtype checks only (no device sync); returns (B, T, D)."""
        config = self.config
        if x.dim() != 3 or x.shape[2] != config.feature_dim:
            raise ValueError(f"x must be (B, T, {config.feature_dim}), got {tuple(x.shape)}")
        batch, num_frames, dim = x.shape
        if num_frames + config.num_prefix_tokens > config.max_len:
            raise ValueError(
                f"{num_frames} frames + {config.num_prefix_tokens} prefix tokens exceed max_len={config.max_len}"
            )
        if config.length_token and num_frames > config.max_frames:
            raise ValueError(f"{num_frames} frames exceed the length token's max_frames={config.max_frames}")
        if t.shape != (batch,):
            raise ValueError(f"t must be ({batch},), got {tuple(t.shape)}")
        if config.is_action_model:
            if cond.shape != (batch,) or cond.is_floating_point():
                raise ValueError(f"an action model takes integer action ids of shape ({batch},), got "
                                 f"{tuple(cond.shape)} {cond.dtype}")
        elif cond.shape != (batch, config.cond_dim) or not cond.is_floating_point():
            raise ValueError(f"cond must be float ({batch}, {config.cond_dim}), got {tuple(cond.shape)} {cond.dtype}")
        if lengths is not None and lengths.shape != (batch,):
            raise ValueError(f"lengths must be ({batch},), got {tuple(lengths.shape)}")
        if cond_mask is not None and (cond_mask.shape != (batch,) or cond_mask.dtype != torch.bool):
            raise ValueError(f"cond_mask must be bool ({batch},), got {tuple(cond_mask.shape)} {cond_mask.dtype}")
        return batch, num_frames, dim


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
