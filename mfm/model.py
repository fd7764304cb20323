"""The MFM velocity-field Transformer (MDM's ``trans_enc`` backbone, batch-first, padding-aware), with FlowMDM's
blended positional encodings / pose-centric conditioning and FLAME's cross-attention decoder as options.

Token sequence seen by the encoder (default, ``conditioning='prefix'``), batch-first ``(B, P + T, latent)``::

    [length token]?  [time ⊕ condition token]  [motion frame 1 … T]
    └─ FLAME option ┘ └─ MFM/MDM prefix token ┘

* Time ``t ∈ [0, 1]`` (noise at 0, data at 1) goes through a *continuous* sinusoidal embedding of ``t·1000`` and a
  Linear-SiLU-Linear MLP. MFM looks ``(t*1000).long()`` up in the positional table instead; the continuous form is
  identical at integer points but does not collapse an adaptive solver's nearby evaluation times onto one embedding
  (a piecewise-constant field in ``t`` makes dopri5's error estimate meaningless). ``time_grid='floor'`` /
  ``'nearest'`` reproduce MFM's / MDM's lookup for converted checkpoints (:mod:`mfm.reference_weights`).
* The condition (pooled text embedding projected by a Linear, or a learned action embedding) is *added* to the time
  embedding, as in MFM/MDM. Classifier-free training zeroes the raw condition for ``cond_drop_prob`` of the samples;
  ``cond_mask`` forces the drop per sample so a sampler can batch its conditional and unconditional halves.
* Unlike MFM (which attends over the 196-frame zero padding), padded frames are masked out of attention with a
  boolean key-padding mask and their outputs are zeroed, so a clip's velocity does not depend on how it was padded
  (``attend_padding=True`` is MFM's behaviour, for converted checkpoints).

The HumanML3D preset (263, 512, 1024, 8 layers, 4 heads, CLIP cond 512, post-norm) has exactly 17,880,327
parameters, the same as MFM's ``MDM_Flow`` without CLIP (17.88 M). Every option below is off by default and adds
nothing to that model.

Conditioning (``ModelConfig.conditioning``):

* ``'prefix'``: MFM's single time ⊕ condition token (above).
* ``'pccat'``: FlowMDM's pose-centric cross-attention. No condition token; every frame ``i`` has its own condition
  ``c_i = time embedding + Linear(text embedding of the segment frame i belongs to)`` (``frame_cond``), and each layer
  forms its queries from ``Linear_{2d→d}([h_i ; c_i])`` while keys and values come from the pose stream ``h`` alone,
  so what a frame offers to the others never depends on its text — the property that lets FlowMDM compose segments
  with different texts smoothly.
* ``'cross_attention'``: FLAME's decoder. Self-attention over ``[length]? [time] [pooled text] [frames]`` plus, in
  every layer, cross-attention to the memory ``[length]? [time] [pooled text] [Linear(token-level text features)]``
  with the text's padding mask. FLAME's exact layout is ``conditioning='cross_attention', length_token=True``.

Positional encoding (``ModelConfig.positional``):

* ``'absolute'``: MDM's sinusoidal table added to the whole token sequence (default).
* ``'bpe'``: FlowMDM's blended positional encodings. Each sample runs in one of two modes (``positional_mode``,
  True = relative): *absolute* adds the sinusoidal positions restarting at every segment (``segments``) and confines
  the frames' attention to their own segment (block-diagonal); *relative* adds no position, rotates the first
  ``rope_dims`` channels of every head's frame queries/keys (RoPE) and lets frames attend to frames at most
  ``attention_horizon`` apart, across segments (the horizon limits absolute mode too, as FlowMDM's window mask:
  ``horizon_in_absolute``). Training draws the mode per sample (``bpe_train_relative_prob``);
  samplers pass it (see :mod:`mfm.composition`). The auxiliary tokens (length, time, condition) carry no position
  and attend only to each other, so in both modes they are a read-only memory for the frames: a segment in absolute
  mode cannot see another segment through them, and in relative mode nothing bypasses the horizon. In relative mode
  their keys' rotary channels are zeroed, so a frame scores them on position-free channels only (translation
  invariance). With ``attention_chunk`` the frame attention is computed blockwise over a band (memory linear in the
  number of frames, FlowMDM's ``--use_chunked_att``), giving the same result as the dense mask.

FlowMDM's backbone (the x-transformers ``Encoder`` of its ``model/FlowMDM.py``; ``configs/flowmdm.yaml``) differs
from MDM's beyond BPE and PCCAT; each difference is an option whose default is MDM/MFM's: attention heads of 64
channels whatever the width (``head_dim``), bias-free attention projections (``attention_bias``), pre-norm with a
final norm (``norm_first``), dropout on the embeddings only (``attention_dropout``, ``ff_dropout``,
``residual_dropout``), stochastic skipping of whole residual blocks in training (``layer_dropout``), learned-scale
concatenated sinusoidal positions (``absolute_positions``) and an extra Linear either side of the encoder
(``wrapper_projections``).

All attention runs through ``F.scaled_dot_product_attention`` with boolean masks (True = may attend), which is safe
under bf16 autocast; no softmax row is ever empty. In CPU training, bf16 attention runs in fp32
(:func:`scaled_dot_product_attention`: PyTorch's CPU bf16 flash-attention backward is the slower of the two).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mfm.path import preconditioning, velocity_from_data

ACTIVATIONS = {"gelu": F.gelu, "relu": F.relu, "silu": F.silu}
POSITIONAL_ENCODINGS = ("absolute", "bpe")
CONDITIONINGS = ("prefix", "pccat", "cross_attention")
LENGTH_EMBEDDINGS = ("learned", "sinusoidal")
PREDICTIONS = ("velocity", "data", "preconditioned")
TIME_GRIDS = ("continuous", "floor", "nearest")
NULL_CONDITIONS = ("zero", "empty_caption")
POSITIONAL_TABLES = ("computed", "stored")
CONDITION_SCALINGS = ("none", "rms")
ABSOLUTE_POSITIONS = ("sinusoidal", "scaled_sinusoidal")
GUIDED_FEATURES = ("all", "pose")
ADAPTIVE_NORMS = ("none", "adaln", "adaln_zero")
BONE_KEEPING = (False, True, "smoothed")
"""``ModelConfig.output_smoothing_keeps_bones`` and its overrides: after the output smoothing the bones keep no
length of their own (False: FLAME's plain filter), each frame's length before the filter (True), or each bone's
lengths before the filter, smoothed over time with the same σ ("smoothed")."""


def is_bone_keeping(value: object) -> bool:
    """Whether ``value`` is one of :data:`BONE_KEEPING` (a bool, not 0 or 1)."""
    return isinstance(value, bool) or value == "smoothed"


# MFM feeds the sinusoidal table with t*1000 (its diffusion-step scale); keep the scale so the embedding matches.
TIME_SCALE = 1000.0
ROPE_BASE = 10000.0
"""Base of the rotary frequencies (x-transformers' / RoFormer's default, used by FlowMDM)."""


def is_step_start_grid(times: object) -> bool:
    """Whether ``times`` can be ``ModelConfig.sampling_times``: a non-empty sequence of numbers, 0 first, strictly
    increasing, all below 1."""
    if not isinstance(times, (tuple, list)) or not times:
        return False
    if not all(isinstance(t, (int, float)) and not isinstance(t, bool) and math.isfinite(t) for t in times):
        return False
    return times[0] == 0 and all(a < b for a, b in zip(times, times[1:])) and times[-1] < 1


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
    """Dropout on embeddings, attention probabilities, the feed-forward hidden layer and residual branches (as
    nn.TransformerEncoderLayer); ``attention_dropout``, ``ff_dropout`` and ``residual_dropout`` set the last three
    apart."""
    activation: str = "gelu"
    """Feed-forward activation: one of ACTIVATIONS."""
    cond_dim: int = 512
    """Size of the pooled text embedding (dataset manifest ``text_encoder.dim``: 512 CLIP, 384 MiniLM).
    Unused by action models (``num_actions > 0``)."""
    num_actions: int = 0
    """0: text-conditioned model; > 0: action-class model with a learned embedding per class."""
    cond_drop_prob: float = 0.1
    """Probability of dropping a sample's condition in training (classifier-free guidance); FLAME: 0.25."""
    null_condition: str = "zero"
    """What a dropped text condition becomes (one of NULL_CONDITIONS). 'zero' (MDM/MFM's ``mask_cond``): the raw
    embedding is zeroed, so the null condition is the projection's bias. 'empty_caption' (FLAME, which replaces the
    caption by "" before encoding it): the text encoder's output for the empty caption, pooled (and token features
    for cross-attention), held by the model as buffers (``null_text``...) that the trainer fills from the dataset's
    encoder (:meth:`MotionFlowTransformer.set_null_condition`) and every checkpoint carries."""
    null_tokens: int = 0
    """null_condition='empty_caption' with cross-attention: rows of the empty caption's token features (the
    dataset's max_tokens; the trainer sets it)."""
    length_token: bool = False
    """FLAME option: prepend an embedding of the motion's valid length as an extra token (``length_embedding``)."""
    length_embedding: str = "learned"
    """How the length token embeds a length (one of LENGTH_EMBEDDINGS). 'learned' (FLAME): a table of max_frames + 1
    rows, one free vector per length, so a length no training crop had (our crops are multiples of
    data.unit_length) stays at its initialisation. 'sinusoidal' (ours, not FLAME's): the sinusoid of the length
    through Linear → SiLU → Linear, as the time embedding, so nearby lengths get nearby tokens."""
    max_frames: int = 196
    """Largest motion length the length token can embed (table of max_frames + 1 rows)."""
    max_len: int = 5000
    """Rows of the sinusoidal positional table: prefix tokens + frames (bpe: + the longest segment) must fit."""
    norm_first: bool = False
    """False: post-norm like MDM's nn.TransformerEncoder (parity); True: pre-norm with a final LayerNorm."""
    output_dim: int | None = None
    """Per-frame output size; None = feature_dim (a velocity). 2·feature_dim for FLAME's ε + learned variance."""
    positional: str = "absolute"
    """One of POSITIONAL_ENCODINGS: 'absolute' (MFM) or 'bpe' (FlowMDM's blended positional encodings)."""
    rope_dims: int | None = None
    """bpe: channels of each head rotated in relative mode (even); None = half the head dim (FlowMDM: 32 of 64)."""
    attention_horizon: int = 150
    """bpe relative mode: frames further apart than this do not attend to each other (FlowMDM: 150 HumanML3D,
    100 Babel)."""
    horizon_in_absolute: bool = True
    """bpe: the attention horizon also limits absolute mode (within a segment, frames further apart than
    ``attention_horizon`` do not attend), as FlowMDM, whose x-transformers window mask applies to every sample
    whatever its mode. False: absolute mode attends over the whole segment (our earlier behaviour)."""
    bpe_train_relative_prob: float = 0.5
    """bpe: probability that a training sample runs in relative mode (FlowMDM's ``bpe_training_ratio``)."""
    conditioning: str = "prefix"
    """One of CONDITIONINGS: 'prefix' (MFM), 'pccat' (FlowMDM), 'cross_attention' (FLAME)."""
    token_dim: int | None = None
    """cross_attention: size of the token-level text features (manifest ``text_encoder.dim``); None = cond_dim."""
    time_grid: str = "continuous"
    """How ``t`` reaches the time sinusoid (one of TIME_GRIDS). 'continuous' (ours): the sinusoid of ``t·1000``.
    'floor' (MFM's ``MDM_Flow``, for converted checkpoints): ``(t·1000).long()`` in float32, i.e. t rounded down
    to the 1/1000 grid before the table lookup. 'nearest' (MDM's integer diffusion steps, which our diffusion code
    passes as ``step/1000``): rounded to the nearest grid point, which recovers the integer step exactly. The
    three agree wherever ``t·1000`` is an integer in float32."""
    attend_padding: bool = False
    """False (ours): padded frames are masked out of attention, so a clip's output does not depend on how it was
    padded. True (MFM/MDM, for converted checkpoints): every frame is a key, padding included, as the reference
    ``nn.TransformerEncoder`` runs without a key-padding mask, and padded frames' outputs are left as computed
    (ours zeroes them), so under a sampler the padding evolves as in the reference and its content reaches the
    valid frames as there. Only with ``positional='absolute'`` and ``conditioning='prefix'``."""
    positional_table: str = "computed"
    """Where the sinusoid table comes from (one of POSITIONAL_TABLES). 'computed' (ours): computed on the CPU at
    construction and never saved. 'stored' (for converted checkpoints): a saved buffer holding the reference's own
    table, which MFM/MDM computed on their device and differs from ours by float32 rounding (up to 3e-5 in the
    first 1,000 rows of the 64-wide golden model, 2.4e-4 near row 5,000); with ``time_grid`` 'floor'/'nearest' the
    time embedding then looks its rows up as the reference does."""
    cond_scaling: str = "none"
    """How a text embedding is scaled before its projection (one of CONDITION_SCALINGS). 'none': as given (MFM/MDM,
    whose CLIP ``encode_text`` output has a norm near 10). 'rms': to unit root-mean-square per channel
    (``c·√cond_dim/‖c‖``; a dropped, all-zero condition stays zero). Sentence encoders such as all-MiniLM-L6-v2 emit
    unit-norm vectors, about √cond_dim ≈ 20× smaller per channel than that CLIP output: through a default-initialised
    Linear the condition is then a ~0.03 ripple on the time embedding, and since Adam moves a weight by about lr per
    step, the projection needs most of a short run to grow the gain that makes captions distinguishable. Not MFM's
    choice: our presets say where they use it."""
    prediction: str = "velocity"
    """What the network's output layer predicts (one of PREDICTIONS); ``forward`` returns a velocity either way.
    'velocity': MFM (the output is v itself). 'data': the output is the clean motion x1 and ``forward`` converts
    it with :func:`mfm.path.velocity_from_data`. A velocity target contains the noise x0 — white in all
    ``feature_dim`` channels — so a velocity network must carry its input through the Transformer almost
    unchanged; when ``latent_dim`` is not well above ``feature_dim`` (256 vs 263 in the CPU presets) it cannot,
    and the leftover noise shows as jitter, stretching bones and sliding feet. An x1 target is smooth and
    low-dimensional. 'preconditioned': EDM's skip for the flow path (:func:`mfm.path.preconditioning`): x1
    prediction near t = 0, the input passed through towards t = 1, so late in the path the network only corrects
    x_t instead of redrawing every detail of the motion through its width. Not MFM's choice: our presets say where
    they use either."""

    # -- FlowMDM's architecture (x-transformers); each default is MDM/MFM's, configs/flowmdm.yaml sets FlowMDM's --
    head_dim: int = 0
    """Channels per attention head; 0 = latent_dim / num_heads (MDM/MFM). FlowMDM inherits x-transformers'
    ``dim_head`` = 64 whatever the width, so its 4 heads over 512 channels attend in 4 × 64 = 256: queries, keys and
    values are ``num_heads · head_dim`` wide and the output projection maps them back to latent_dim."""
    attention_bias: bool = True
    """Biases on the attention's query, key, value and output projections (nn.MultiheadAttention, MDM/MFM). False:
    x-transformers' bias-free ``to_q/to_k/to_v/to_out`` (FlowMDM). PCCAT's query-conditioning Linear keeps its
    bias either way (FlowMDM's is a plain nn.Linear)."""
    attention_dropout: float | None = None
    """Dropout on the attention probabilities; None = ``dropout``. FlowMDM: 0 (x-transformers' ``attn_dropout``)."""
    ff_dropout: float | None = None
    """Dropout on the feed-forward hidden layer; None = ``dropout``. FlowMDM: 0 (x-transformers' ``ff_dropout``)."""
    residual_dropout: float | None = None
    """Dropout on each residual branch's output (attention, cross-attention, feed-forward); None = ``dropout``.
    FlowMDM: 0 (x-transformers has no dropout there)."""
    layer_dropout: float = 0.0
    """Training only: probability of skipping each residual block (attention, cross-attention, feed-forward) of
    every layer, drawn independently per block and once per batch, without rescaling; a skipped block passes its
    input through unchanged (post-norm: its LayerNorm is skipped too). x-transformers' ``layer_dropout``, which
    counts the attention and feed-forward blocks as separate layers; FlowMDM: 0.1. The skipped block is still
    computed and its result discarded, so every parameter stays in the autograd graph (DDP without
    ``find_unused_parameters``). Drawn from ``generator`` after the condition-dropout and BPE-mode draws, or
    given as ``block_drop_mask``."""
    absolute_positions: str = "sinusoidal"
    """The absolute positional embedding added to the tokens (one of ABSOLUTE_POSITIONS; positional='absolute',
    and bpe's absolute mode). 'sinusoidal' (MDM/MFM): the interleaved sin/cos table, unscaled. 'scaled_sinusoidal'
    (FlowMDM, x-transformers' ``ScaledSinusoidalEmbedding``): ``cat(sin(p·ω), cos(p·ω)) · s`` with the same
    frequencies ``ω_i = 10000^(-i/(latent_dim/2))`` and one learned scalar ``s`` initialised to
    ``latent_dim ** -0.5``. The time embedding keeps MDM's table either way (FlowMDM's does too)."""
    output_smoothing: float = 0.0
    """σ (frames) of the Gaussian smoothing over time that samplers apply to this model's outputs unless told
    otherwise (``launch/sample.py --smoothing``, the evaluator, the contact sheet, MotionPipeline); 0 = none (MFM).
    FLAME smooths its samples this way with σ = 1 (its diffusion preset's own setting,
    mfm.diffusion_sampling.BASELINE_SAMPLING, still wins for such checkpoints). Not used in training."""
    output_smoothing_keeps_bones: bool | Literal["smoothed"] = False
    """After the output smoothing, give every bone of the ric positions back a length it had before the filter,
    along its filtered direction (mfm.features.set_ric_bone_lengths): true, the length it had in that frame;
    "smoothed", its lengths over the frames smoothed with the same σ (the filter then acts on a bone's length as a
    number instead of along its arc). Ours, not FLAME's (false: its plain filter). A Gaussian filter shortens a
    limb that swings fast (the average of points on an arc lies inside it): σ 0.9 took a synthetic run's shin from
    43 to 27 cm. Each frame's own length puts back that frame's length jitter, and it adds up along a leg to the
    foot: on the synthetic preset the feet went lower and slid more than with the plain filter
    (docs/generator-study.md, "Bone lengths smoothed, not put back per frame"). Applies wherever the smoothing does
    (sampler, evaluator, contact sheet, training previews)."""
    sampling_guidance: float = 2.5
    """The classifier-free guidance scale samplers use for this model unless told otherwise (``launch/sample.py
    --guidance``, the contact sheet, MotionPipeline; the evaluator keeps its protocol's ``sampling.guidance``).
    2.5 is MFM's (and MDM's) scale. A scale above 1 extrapolates away from the unconditional field, which also
    pushes what the caption fixes exactly past the data: on the synthetic set a jump "up in place" drifts backwards
    at 0.3 m/s in flight and "forward" overshoots 1.5 m/s (docs/generator-study.md, "Guidance overshoots what the
    caption fixes"). A diffusion baseline's authors' scale (FLAME: 8.0) still wins for such checkpoints. Not used
    in training."""
    sampling_steps: int = 10
    """The ODE solver steps samplers use for this flow model unless told otherwise (``launch/sample.py --steps``,
    the contact sheet, MotionPipeline; edits keep their settings' steps, the evaluator its protocol's). 10 is MFM's
    Euler default; a few-step student (``launch/distill.py``) records 2. Not used in training."""
    sampling_times: tuple[float, ...] | None = None
    """The times at which samplers start their Euler steps when they take ``len(sampling_times)`` steps
    (:func:`mfm.solvers.step_grid`): ``(0, 0.9)`` integrates 0 → 0.9 → 1 instead of 0 → 1/2 → 1, so a few-step
    student's last step starts from a state nearer the motion; other step counts keep the uniform grid. A student
    trained with ``train.flow_time_sampling=grid`` is trained at these times. None: the uniform grid (MFM). Ours,
    not MFM's; chosen times for a distilled sampler's few steps are common practice (e.g. DMD2's 4-step times)."""
    shortcut_levels: int = 0
    """0: a flow model. K > 0: a shortcut model (Frans et al. 2024, "One Step Diffusion via Shortcut Models"): the
    network also takes the step size d of the sampler's step (``step_size``, embedded as the time is and added to
    the time embedding; its last layer starts at zero, so a model initialised from a flow model starts as that
    model) and returns the average velocity over [t, t + d]. Steps d = 1, 1/2, ..., 1/2^(K−1) are trained by
    self-consistency (two steps of d/2 make one of d); d = 0 is the flow-matching field, which the finest level
    is built from (``mfm.shortcut``). Euler at 1, 2, ..., 2^(K−1) steps uses those levels; more steps, or another
    solver, integrate the flow field (d = 0)."""
    guided_features: str = "all"
    """Which output channels classifier-free guidance mixes when samplers guide this model (one of
    GUIDED_FEATURES; ``launch/sample.py``, edits, the evaluator, the contact sheet, MotionPipeline). 'all' (MFM,
    MDM, FLAME): every channel. 'pose' (ours, in no reference model): the pose channels (ric positions, 6D
    rotations, foot contacts) are guided and the channels that carry the root's motion (its rotation and linear
    velocity, its height, and every joint's velocity: mfm.layout.FeatureLayout.root_motion_mask) take the
    conditional output unguided. Guidance extrapolates away from the unconditional field, and what a caption fixes
    exactly, such as a speed, overshoots: on the synthetic set a jump "up in place" drifts backwards at 0.3 m/s in
    flight and "forward" runs at 1.75 m/s instead of 1.5 (docs/generator-study.md, "Guidance overshoots what the
    caption fixes"). Not used in training."""
    progress_positions: bool = False
    """Ours, in no reference model: also add to every frame the sinusoid of how far into its motion it lies,
    ``1000 · i / (L − 1)`` for frame i of a motion of L valid frames (the time embedding's scaling), so a frame knows
    where it sits between the motion's start and end as well as its distance from the start. A caption describes a
    whole clip ("kicks twice", "squats three times"): where its events fall scales with the clip's length, which
    absolute positions and a length token leave the network to work out by division. positional='absolute' only."""
    frames_per_token: int = 1
    """Ours, in no reference model (MFM, MDM, FLAME and FlowMDM give every frame its own token): the Transformer
    sees each run of this many consecutive frames as one token, their features concatenated into
    ``Linear(p·feature_dim → latent)``, and splits its output back into frames with ``Linear(latent → p·output)``
    (a patch embedding over time, as DiT's over space). The sequence is p times shorter, so a step costs about 1/p
    of the linear layers and 1/p² of the attention: more network per CPU minute. Frames past a motion's length are
    zeroed before grouping, so padding never reaches a valid frame; a token with any valid frame is valid, and its
    progress position is the token's. positional='absolute', conditioning 'prefix' or 'cross_attention' only."""
    adaptive_norm: str = "none"
    """One of ADAPTIVE_NORMS. 'none' (MFM, MDM, FLAME, FlowMDM): the condition reaches the frames only through
    attention, to the auxiliary tokens (and, with cross-attention, the text's token features). 'adaln_zero' (DiT's
    adaLN-Zero, Peebles & Xie 2023; in none of the three reference models): the sum of the auxiliary tokens (time
    embedding + pooled caption or action, + length token) also modulates every residual block of every token, as
    ``h + gate · block(LayerNorm(h) · (1 + scale) + shift)``, with (shift, scale, gate) a zero-initialised
    ``Linear(SiLU(c))`` per layer, and the final norm by its own (shift, scale). At initialisation every gate is 0,
    so each block starts as the identity. 'adaln' (DiT's adaLN): the same without the gates,
    ``h + block(LayerNorm(h) · (1 + scale) + shift)``; zero-initialised, the network starts as the one without the
    option and the condition's path is learnt on top. The auxiliary tokens stay as they are. Pre-norm (norm_first),
    positional='absolute' and conditioning 'prefix' or 'cross_attention' only (one condition per sample: BPE
    composition and PCCAT give frames different texts)."""
    self_condition_prob: float = 0.0
    """Self-conditioning (Chen et al. 2022, "Analog Bits", 0.5 there; in none of the three reference models). > 0:
    the network also sees an earlier estimate of the motion, ``x̂1``, through a zero-initialised, bias-free
    ``Linear(p·feature_dim → latent)`` added to the frames' input projection (``forward(self_condition=...)``;
    None = zeros, the network without an estimate). Training (mfm.flow) feeds this share of the rows the network's
    own x̂1 from a first, gradient-free pass at the same x_t and zeros to the others; a sampler
    (:class:`mfm.composition.BoundInputs`, :func:`mfm.composition.bind_inputs`) feeds the x̂1 of its previous
    evaluation; the model called unbound gets zeros. Why: along a sampled path the
    network meets states shaped by its own earlier estimates, which no training path has (exposure bias); with
    the estimate as an input those states are ones it was trained on (docs/generator-study.md, "Self-conditioning").
    0: off (MFM). Flow objective only, not with shortcut levels."""
    wrapper_projections: bool = False
    """FlowMDM (x-transformers' ``ContinuousTransformerWrapper`` with ``dim_in = dim_out = latent_dim``): an extra
    Linear(latent, latent) after the input projection (before positions are added) and one after the final norm,
    before the output projection."""

    def __post_init__(self) -> None:
        positive = {
            "feature_dim": self.feature_dim,
            "latent_dim": self.latent_dim,
            "ff_dim": self.ff_dim,
            "num_layers": self.num_layers,
            "num_heads": self.num_heads,
            "max_len": self.max_len,
            "max_frames": self.max_frames,
            "attention_horizon": self.attention_horizon,
        }
        for name in ("output_dim", "rope_dims", "token_dim"):
            if getattr(self, name) is not None:
                positive[name] = getattr(self, name)
        for name, value in positive.items():
            if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
                raise ValueError(f"ModelConfig.{name} must be a positive int, got {value!r}")
        if not isinstance(self.head_dim, int) or isinstance(self.head_dim, bool) or self.head_dim < 0:
            raise ValueError(f"ModelConfig.head_dim must be an int >= 0 (0: latent_dim / num_heads), got "
                             f"{self.head_dim!r}")
        if self.head_dim == 0 and self.latent_dim % self.num_heads != 0:
            raise ValueError(
                f"ModelConfig.latent_dim ({self.latent_dim}) must be divisible by num_heads ({self.num_heads}), "
                "or head_dim set"
            )
        if self.latent_dim % 2 != 0:
            raise ValueError(f"ModelConfig.latent_dim must be even (sinusoidal embeddings), got {self.latent_dim}")
        if not isinstance(self.num_actions, int) or self.num_actions < 0:
            raise ValueError(f"ModelConfig.num_actions must be an int >= 0, got {self.num_actions!r}")
        if self.num_actions == 0 and (not isinstance(self.cond_dim, int) or self.cond_dim <= 0):
            raise ValueError(
                f"ModelConfig.cond_dim must be a positive int for a text model (num_actions=0), got {self.cond_dim!r}"
            )
        for name in ("dropout", "cond_drop_prob", "attention_dropout", "ff_dropout", "residual_dropout"):
            value = getattr(self, name)
            if value is None and name not in ("dropout", "cond_drop_prob"):
                continue
            if not isinstance(value, numbers.Real) or isinstance(value, bool) or not 0.0 <= value < 1.0:
                raise ValueError(f"ModelConfig.{name} must be in [0, 1), got {value!r}")
        if (not isinstance(self.layer_dropout, numbers.Real) or isinstance(self.layer_dropout, bool)
                or not 0.0 <= self.layer_dropout <= 1.0):
            raise ValueError(f"ModelConfig.layer_dropout must be in [0, 1], got {self.layer_dropout!r}")
        for name in ("attention_bias", "wrapper_projections"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"ModelConfig.{name} must be a bool, got {getattr(self, name)!r}")
        if self.absolute_positions not in ABSOLUTE_POSITIONS:
            raise ValueError(f"ModelConfig.absolute_positions must be one of {ABSOLUTE_POSITIONS}, got "
                             f"{self.absolute_positions!r}")
        if not 0.0 <= self.bpe_train_relative_prob <= 1.0:
            raise ValueError(
                f"ModelConfig.bpe_train_relative_prob must be in [0, 1], got {self.bpe_train_relative_prob!r}"
            )
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"ModelConfig.activation must be one of {sorted(ACTIVATIONS)}, got {self.activation!r}")
        if self.positional not in POSITIONAL_ENCODINGS:
            raise ValueError(f"ModelConfig.positional must be one of {POSITIONAL_ENCODINGS}, got {self.positional!r}")
        if self.cond_scaling not in CONDITION_SCALINGS:
            raise ValueError(
                f"ModelConfig.cond_scaling must be one of {CONDITION_SCALINGS}, got {self.cond_scaling!r}"
            )
        if self.positional_table not in POSITIONAL_TABLES:
            raise ValueError(f"ModelConfig.positional_table must be one of {POSITIONAL_TABLES}, got "
                             f"{self.positional_table!r}")
        if self.time_grid not in TIME_GRIDS:
            raise ValueError(f"ModelConfig.time_grid must be one of {TIME_GRIDS}, got {self.time_grid!r}")
        if self.attend_padding and (self.positional != "absolute" or self.conditioning != "prefix"):
            raise ValueError("ModelConfig.attend_padding is MFM/MDM's behaviour: it needs positional='absolute' and "
                             f"conditioning='prefix', got {self.positional!r} and {self.conditioning!r}")
        if self.prediction not in PREDICTIONS:
            raise ValueError(f"ModelConfig.prediction must be one of {PREDICTIONS}, got {self.prediction!r}")
        if self.prediction != "velocity" and self.output_size != self.feature_dim:
            raise ValueError(
                f"ModelConfig.prediction={self.prediction!r} predicts the motion: output_dim must be feature_dim "
                f"({self.feature_dim}), got {self.output_dim}"
            )
        if self.conditioning not in CONDITIONINGS:
            raise ValueError(f"ModelConfig.conditioning must be one of {CONDITIONINGS}, got {self.conditioning!r}")
        if self.conditioning != "prefix" and self.is_action_model:
            raise ValueError(
                f"ModelConfig.conditioning={self.conditioning!r} needs a text model; action models (num_actions > 0) "
                "use 'prefix'"
            )
        if self.null_condition not in NULL_CONDITIONS:
            raise ValueError(f"ModelConfig.null_condition must be one of {NULL_CONDITIONS}, got {self.null_condition!r}")
        if self.null_condition == "empty_caption" and self.is_action_model:
            raise ValueError("ModelConfig.null_condition='empty_caption' needs a text model (num_actions=0)")
        if not isinstance(self.null_tokens, int) or self.null_tokens < 0:
            raise ValueError(f"ModelConfig.null_tokens must be an int >= 0, got {self.null_tokens!r}")
        if not (isinstance(self.output_smoothing, (int, float)) and self.output_smoothing >= 0):
            raise ValueError(f"ModelConfig.output_smoothing must be a σ >= 0 (frames), got {self.output_smoothing!r}")
        if not is_bone_keeping(self.output_smoothing_keeps_bones):
            raise ValueError("ModelConfig.output_smoothing_keeps_bones must be true, false or smoothed, got "
                             f"{self.output_smoothing_keeps_bones!r}")
        if self.guided_features not in GUIDED_FEATURES:
            raise ValueError(f"ModelConfig.guided_features must be one of {GUIDED_FEATURES}, got {self.guided_features!r}")
        if not (isinstance(self.sampling_guidance, (int, float)) and math.isfinite(self.sampling_guidance)
                and self.sampling_guidance >= 0):
            raise ValueError(f"ModelConfig.sampling_guidance must be a finite scale >= 0, got {self.sampling_guidance!r}")
        if not isinstance(self.sampling_steps, int) or isinstance(self.sampling_steps, bool) or self.sampling_steps < 1:
            raise ValueError(f"ModelConfig.sampling_steps must be an int >= 1, got {self.sampling_steps!r}")
        if isinstance(self.sampling_times, list):  # as a checkpoint's JSON or YAML gives it back
            self.sampling_times = tuple(self.sampling_times)
        if self.sampling_times is not None and not is_step_start_grid(self.sampling_times):
            raise ValueError("ModelConfig.sampling_times must be null or the start times of a solve's steps: 0 first, "
                             f"strictly increasing, below 1, got {self.sampling_times!r}")
        if self.sampling_times is not None and self.shortcut_levels > 0:
            raise ValueError("ModelConfig.sampling_times is for a flow model's Euler steps; a shortcut model's steps "
                             "are its trained step sizes (shortcut_levels)")
        if not isinstance(self.shortcut_levels, int) or isinstance(self.shortcut_levels, bool) or not (
                0 <= self.shortcut_levels <= 10):
            raise ValueError(f"ModelConfig.shortcut_levels must be an int in [0, 10], got {self.shortcut_levels!r}")
        if (not isinstance(self.frames_per_token, int) or isinstance(self.frames_per_token, bool)
                or self.frames_per_token < 1):
            raise ValueError(f"ModelConfig.frames_per_token must be an int >= 1, got {self.frames_per_token!r}")
        if self.frames_per_token > 1 and (self.positional != "absolute" or self.conditioning == "pccat"
                                          or self.attend_padding):
            raise ValueError("ModelConfig.frames_per_token > 1 needs positional='absolute', conditioning 'prefix' or "
                             "'cross_attention' and attend_padding=False (BPE segments, PCCAT's per-frame texts and "
                             "attended padding are per frame)")
        if self.adaptive_norm not in ADAPTIVE_NORMS:
            raise ValueError(f"ModelConfig.adaptive_norm must be one of {ADAPTIVE_NORMS}, got {self.adaptive_norm!r}")
        if self.adaptive_norm != "none" and (not self.norm_first or self.positional != "absolute"
                                             or self.conditioning == "pccat"):
            raise ValueError("ModelConfig.adaptive_norm needs norm_first=True, positional='absolute' and conditioning "
                             "'prefix' or 'cross_attention' (it modulates pre-norm blocks with one condition per "
                             f"sample), got norm_first={self.norm_first}, {self.positional!r}, {self.conditioning!r}")
        if not (isinstance(self.self_condition_prob, (int, float)) and 0.0 <= self.self_condition_prob <= 1.0):
            raise ValueError(f"ModelConfig.self_condition_prob must be in [0, 1], got {self.self_condition_prob!r}")
        if self.self_condition_prob > 0 and self.shortcut_levels > 0:
            raise ValueError("ModelConfig.self_condition_prob > 0 is not supported with shortcut levels (the "
                             "shortcut objective's own passes feed no estimate)")
        if self.progress_positions and self.positional != "absolute":
            raise ValueError("ModelConfig.progress_positions needs positional='absolute'")
        if self.length_embedding not in LENGTH_EMBEDDINGS:
            raise ValueError(f"ModelConfig.length_embedding must be one of {LENGTH_EMBEDDINGS}, got "
                             f"{self.length_embedding!r}")
        if self.conditioning == "pccat" and self.length_token:
            raise ValueError(
                "ModelConfig.length_token is not available with conditioning='pccat' (FlowMDM has no auxiliary tokens)"
            )
        if self.positional == "bpe":
            rotary = self.rotary_dims
            if rotary <= 0 or rotary % 2 != 0 or rotary > self.head_size:
                raise ValueError(
                    f"ModelConfig.rope_dims must be even and in [2, head dim {self.head_size}], got {rotary}"
                )
        if self.length_token and self.max_frames + self.num_prefix_tokens > self.max_len:
            raise ValueError(
                f"ModelConfig.max_frames ({self.max_frames}) + prefix tokens must fit in max_len ({self.max_len})"
            )

    @property
    def num_prefix_tokens(self) -> int:
        """Auxiliary tokens before the motion frames: prefix = time/condition token (+ length token); pccat = none;
        cross_attention = time token + pooled-text token (+ length token)."""
        base = {"prefix": 1, "pccat": 0, "cross_attention": 2}[self.conditioning]
        return base + int(self.length_token)

    @property
    def is_action_model(self) -> bool:
        return self.num_actions > 0

    @property
    def head_size(self) -> int:
        """Channels per attention head: ``head_dim``, or latent_dim / num_heads when it is 0."""
        return self.head_dim if self.head_dim > 0 else self.latent_dim // self.num_heads

    @property
    def attention_dim(self) -> int:
        """Width of the attention's queries, keys and values: num_heads · head_size (latent_dim by default)."""
        return self.num_heads * self.head_size

    @property
    def rotary_dims(self) -> int:
        """Rotated channels per head in bpe relative mode (default: half the head dim, rounded down to even)."""
        return self.rope_dims if self.rope_dims is not None else 2 * (self.head_size // 4)

    @property
    def blocks_per_layer(self) -> int:
        """Residual blocks of each layer that layer dropout may skip: attention, [cross-attention,] feed-forward."""
        return 3 if self.conditioning == "cross_attention" else 2

    def dropout_of(self, name: str) -> float:
        """The dropout probability of ``'attention'``, ``'ff'`` or ``'residual'`` (its own setting, else
        ``dropout``)."""
        value = getattr(self, f"{name}_dropout")
        return self.dropout if value is None else value

    @property
    def output_size(self) -> int:
        return self.output_dim if self.output_dim is not None else self.feature_dim

    @property
    def text_token_dim(self) -> int:
        return self.token_dim if self.token_dim is not None else self.cond_dim


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


def concatenated_sinusoid(positions: torch.Tensor, dim: int) -> torch.Tensor:
    """x-transformers' sinusoid for real-valued positions: ``cat(sin(p·ω), cos(p·ω))`` over the last dim, with
    ``ω_i = 10000^(-i/(dim/2))`` for i < dim/2 (the frequencies of :func:`sinusoidal_embedding`, laid out in two
    halves instead of interleaved). fp32 whatever the autocast state."""
    half = dim // 2
    frequencies = 10000.0 ** -(torch.arange(half, device=positions.device, dtype=torch.float32) / half)
    angles = positions.float().unsqueeze(-1) * frequencies
    return torch.cat((angles.sin(), angles.cos()), dim=-1)


class ScaledSinusoidalEmbedding(nn.Module):
    """FlowMDM's absolute positions (x-transformers' ``ScaledSinusoidalEmbedding``): :func:`concatenated_sinusoid`
    times one learned scalar ``scale``, initialised to ``dim ** -0.5`` (ModelConfig.absolute_positions)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.dim = dim
        self.scale = nn.Parameter(torch.full((1,), dim**-0.5))

    def forward(self, positions: torch.Tensor) -> torch.Tensor:
        """(..., dim) fp32 embedding of the real positions (...)."""
        return concatenated_sinusoid(positions, self.dim) * self.scale.float()


def valid_frame_mask(lengths: torch.Tensor, num_frames: int) -> torch.Tensor:
    """(B, num_frames) bool, True on the first ``lengths[b]`` frames of each sample."""
    frames = torch.arange(num_frames, device=lengths.device)
    return frames.unsqueeze(0) < lengths.unsqueeze(1)


def _draw_bernoulli(
    batch: int, prob: float, generator: torch.Generator | None, device: torch.device | None
) -> torch.Tensor:
    # Drawn on the generator's device (a CPU generator works with a GPU model), then moved to ``device``.
    draw_device = generator.device if generator is not None else device
    return (torch.rand(batch, generator=generator, device=draw_device) < prob).to(device)


def draw_cond_drop_mask(
    batch: int, prob: float, generator: torch.Generator | None = None, device: torch.device | None = None
) -> torch.Tensor:
    """(batch,) bool, True for the samples whose condition is dropped; each is dropped with probability ``prob``.

    Drawn on the generator's device (so a CPU generator works with a GPU model), then moved to ``device``.
    """
    return _draw_bernoulli(batch, prob, generator, device)


def draw_positional_mode(
    batch: int, relative_prob: float, generator: torch.Generator | None = None, device: torch.device | None = None
) -> torch.Tensor:
    """(batch,) bool BPE modes, True = relative with probability ``relative_prob`` (FlowMDM: 0.5 per sample).

    The model draws it in training right after the condition-dropout draw, from the same generator; a trainer
    that draws ``cond_mask`` itself should draw this too and pass it as ``positional_mode``.
    """
    return _draw_bernoulli(batch, relative_prob, generator, device)


def draw_block_drop_mask(
    num_layers: int,
    blocks: int,
    prob: float,
    generator: torch.Generator | None = None,
    device: torch.device | None = None,
) -> torch.Tensor:
    """(num_layers, blocks) bool, True for the residual blocks skipped in this batch (ModelConfig.layer_dropout):
    each independently with probability ``prob``, one draw per batch as x-transformers. Drawn on the generator's
    device (a CPU generator works with a GPU model), then moved to ``device``."""
    draw_device = generator.device if generator is not None else device
    return (torch.rand(num_layers, blocks, generator=generator, device=draw_device) < prob).to(device)


def segment_runs(
    segments: torch.Tensor | None, batch: int, num_frames: int, device: torch.device
) -> tuple[Tensor, Tensor]:
    """Segment structure of (B, T) per-frame segment indices (None: one segment).

    A segment is a maximal run of equal values. Returns ``runs`` (B, T) long, the run number of each frame
    (0, 1, ... along the sequence) and ``offsets`` (B, T) long, each frame's index within its run (the absolute
    position that restarts at every segment).
    """
    frames = torch.arange(num_frames, device=device)
    if segments is None:
        return torch.zeros(batch, num_frames, dtype=torch.long, device=device), frames.expand(batch, num_frames)
    starts = torch.ones(batch, num_frames, dtype=torch.bool, device=device)
    starts[:, 1:] = segments[:, 1:] != segments[:, :-1]
    runs = starts.long().cumsum(dim=1) - 1
    run_start = torch.where(starts, frames, torch.zeros_like(frames)).cummax(dim=1).values
    return runs, frames - run_start


def rotary_tables(positions: torch.Tensor, dim: int) -> tuple[Tensor, Tensor]:
    """RoPE tables ``cos, sin`` of shape (..., dim) for real positions (...,), fp32.

    Half-split convention (x-transformers): channel ``k`` and ``k + dim/2`` form a pair rotated by ``p·ω_k`` with
    ``ω_k = ROPE_BASE^(-2k/dim)``.
    """
    frequencies = ROPE_BASE ** (-torch.arange(0, dim, 2, device=positions.device, dtype=torch.float32) / dim)
    angles = positions.float().unsqueeze(-1) * frequencies
    angles = torch.cat((angles, angles), dim=-1)
    return angles.cos(), angles.sin()


def apply_rotary(x: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """Rotate the first ``cos.shape[-1]`` channels of ``x`` (..., S, head_dim) by the (S, r) tables; the rest pass.

    ``⟨R(p)q, R(p')k⟩`` then depends on ``p − p'`` only. Computed in fp32, returned in ``x``'s dtype.
    """
    dim = cos.shape[-1]
    rotated, rest = x[..., :dim].float(), x[..., dim:]
    first, second = rotated.chunk(2, dim=-1)
    rotated = rotated * cos + torch.cat((-second, first), dim=-1) * sin
    return torch.cat((rotated.to(x.dtype), rest), dim=-1)


def scaled_dot_product_attention(q: Tensor, k: Tensor, v: Tensor, attn_mask: Tensor | None = None,
                                 dropout_p: float = 0.0) -> Tensor:
    """``F.scaled_dot_product_attention``, except that on a CPU, when a gradient will flow back, a bf16/fp16 query,
    key and value are attended in fp32 (outside autocast) and the result cast back. Why: PyTorch's CPU
    flash-attention backward is 2-5x slower in bf16 than in fp32 (torch 2.14 on a Xeon with AMX: 63 against 28 ms
    for 16 x 6 heads x 200 frames x 64 channels, 43 against 9 ms over 32 caption tokens), so in the synthetic
    preset's bf16 training step attention's backward took 38 % of the time (docs/performance.md). Its bf16 forward
    is the faster one (8.6 against 12.8 ms), so inference (sampling under bf16 autocast) keeps it; on CUDA the fused
    bf16 kernels are fast both ways and stay."""
    backward = torch.is_grad_enabled() and (q.requires_grad or k.requires_grad or v.requires_grad)
    if backward and q.device.type == "cpu" and q.dtype in (torch.bfloat16, torch.float16):
        with torch.autocast("cpu", enabled=False):
            out = F.scaled_dot_product_attention(q.float(), k.float(), v.float(), attn_mask=attn_mask,
                                                 dropout_p=dropout_p)
        return out.to(q.dtype)
    return F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask, dropout_p=dropout_p)


class DenseAttention:
    """Plain attention over the whole token sequence with an optional boolean mask (True = may attend), broadcast
    to (B, heads, S, S): MFM's key-padding mask (B, 1, 1, S) or None."""

    def __init__(self, mask: torch.Tensor | None) -> None:
        self.mask = mask

    def position(self, q: Tensor, k: Tensor) -> tuple[Tensor, Tensor]:
        return q, k

    def attend(self, q: Tensor, k: Tensor, v: Tensor, dropout_p: float) -> Tensor:
        return scaled_dot_product_attention(q, k, v, attn_mask=self.mask, dropout_p=dropout_p)


class BlendedAttention:
    """FlowMDM's blended positional attention for one forward pass (built once, shared by every layer).

    Token layout: ``num_aux`` auxiliary tokens, then T frames. Per sample (``relative`` (B,) bool):

    * relative: RoPE on the first ``rotary_dims`` channels of the frames' queries and keys at ``positions`` (T,);
      frame i may attend to frame j iff ``|i − j| <= horizon``; the auxiliary keys' rotary channels are zeroed.
    * absolute: no rotation; frame i may attend to frame j iff both lie in the same segment run (``runs``) and, with
      ``horizon_in_absolute`` (FlowMDM), ``|i − j| <= horizon``.

    In both modes frames attend to every auxiliary token, auxiliary tokens only to each other, padded frames
    (``frame_valid`` False) are never attended, and every frame may attend to itself (a padded query then has a
    non-empty softmax row; its output is discarded).

    chunk: None computes one dense (B, 1, S, S) mask; an int computes the frames' attention in query blocks of
    ``chunk`` frames against a key band of ``window`` frames either side (memory O(T·(chunk + 2·window)) instead
    of O(T²)); ``window`` must cover every allowed pair (relative: horizon; absolute: longest segment − 1).
    """

    def __init__(
        self,
        *,
        num_aux: int,
        runs: Tensor,
        relative: Tensor,
        horizon: int,
        rotary_dims: int,
        positions: Tensor,
        frame_valid: Tensor | None = None,
        chunk: int | None = None,
        window: int | None = None,
        horizon_in_absolute: bool = True,
    ) -> None:
        if chunk is not None and (window is None or window < 0):
            raise ValueError("chunked attention needs the key window (frames either side of a query block)")
        self.num_aux = num_aux
        self.runs = runs
        self.relative = relative
        self.horizon = horizon
        self.horizon_in_absolute = horizon_in_absolute
        self.rotary_dims = rotary_dims
        self.rotary = rotary_tables(positions, rotary_dims)
        self.frame_valid = frame_valid
        self.chunk = chunk
        self.window = window
        self.mask = self.dense_mask() if chunk is None else None

    @property
    def num_frames(self) -> int:
        return self.runs.shape[1]

    def frame_mask(self, q_lo: int, q_hi: int, k_lo: int, k_hi: int) -> Tensor:
        """(B, 1, q_hi − q_lo, k_hi − k_lo) bool: which frames of [k_lo, k_hi) the frames of [q_lo, q_hi) attend."""
        device = self.runs.device
        i = torch.arange(q_lo, q_hi, device=device).unsqueeze(1)
        j = torch.arange(k_lo, k_hi, device=device).unsqueeze(0)
        near = (i - j).abs() <= self.horizon
        same_segment = self.runs[:, q_lo:q_hi, None] == self.runs[:, None, k_lo:k_hi]
        allowed = torch.where(self.relative[:, None, None], near, same_segment & near if self.horizon_in_absolute
                              else same_segment)
        if self.frame_valid is not None:
            allowed = allowed & self.frame_valid[:, None, k_lo:k_hi]
        return (allowed | (i == j)).unsqueeze(1)

    def dense_mask(self) -> Tensor:
        """(B, 1, S, S) bool over auxiliary tokens + frames."""
        batch, frames, aux = self.runs.shape[0], self.num_frames, self.num_aux
        mask = self.frame_mask(0, frames, 0, frames)
        if aux == 0:
            return mask
        device = mask.device
        aux_rows = torch.cat(
            [torch.ones(batch, 1, aux, aux, dtype=torch.bool, device=device),
             torch.zeros(batch, 1, aux, frames, dtype=torch.bool, device=device)], dim=-1
        )
        frame_rows = torch.cat([torch.ones(batch, 1, frames, aux, dtype=torch.bool, device=device), mask], dim=-1)
        return torch.cat([aux_rows, frame_rows], dim=2)

    def position(self, q: Tensor, k: Tensor) -> tuple[Tensor, Tensor]:
        """Rotate the frames' queries/keys of relative samples; zero their auxiliary keys' rotary channels."""
        aux = self.num_aux
        cos, sin = self.rotary
        relative = self.relative[:, None, None, None]
        q_frames = torch.where(relative, apply_rotary(q[:, :, aux:], cos, sin), q[:, :, aux:])
        k_frames = torch.where(relative, apply_rotary(k[:, :, aux:], cos, sin), k[:, :, aux:])
        if aux == 0:
            return q_frames, k_frames
        k_aux = k[:, :, :aux]
        positionless = torch.cat((torch.zeros_like(k_aux[..., : self.rotary_dims]), k_aux[..., self.rotary_dims :]), -1)
        k_aux = torch.where(relative, positionless, k_aux)
        return torch.cat((q[:, :, :aux], q_frames), dim=2), torch.cat((k_aux, k_frames), dim=2)

    def attend(self, q: Tensor, k: Tensor, v: Tensor, dropout_p: float) -> Tensor:
        if self.chunk is None:
            return scaled_dot_product_attention(q, k, v, attn_mask=self.mask, dropout_p=dropout_p)
        return self._attend_chunked(q, k, v, dropout_p)

    def _attend_chunked(self, q: Tensor, k: Tensor, v: Tensor, dropout_p: float) -> Tensor:
        aux, frames, chunk, window = self.num_aux, self.num_frames, self.chunk, self.window
        batch = q.shape[0]
        k_aux, v_aux = k[:, :, :aux], v[:, :, :aux]
        outputs = []
        if aux:
            outputs.append(scaled_dot_product_attention(q[:, :, :aux], k_aux, v_aux, dropout_p=dropout_p))
        for q_lo in range(0, frames, chunk):
            q_hi = min(frames, q_lo + chunk)
            k_lo, k_hi = max(0, q_lo - window), min(frames, q_hi + window)
            mask = self.frame_mask(q_lo, q_hi, k_lo, k_hi)
            if aux:
                always = torch.ones(batch, 1, q_hi - q_lo, aux, dtype=torch.bool, device=mask.device)
                mask = torch.cat([always, mask], dim=-1)
            keys = torch.cat([k_aux, k[:, :, aux + k_lo : aux + k_hi]], dim=2)
            values = torch.cat([v_aux, v[:, :, aux + k_lo : aux + k_hi]], dim=2)
            outputs.append(
                scaled_dot_product_attention(
                    q[:, :, aux + q_lo : aux + q_hi], keys, values, attn_mask=mask, dropout_p=dropout_p
                )
            )
        return torch.cat(outputs, dim=2)


Attention = DenseAttention | BlendedAttention


class FP32LayerNorm(nn.LayerNorm):
    """LayerNorm computed in fp32 and returned in the input dtype: bf16 mean/variance over 512 channels loses the
    small residual updates the post-norm stack depends on."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        weight = self.weight.float() if self.weight is not None else None
        bias = self.bias.float() if self.bias is not None else None
        return F.layer_norm(x.float(), self.normalized_shape, weight, bias, self.eps).to(x.dtype)


def _init_split_projection(query: nn.Linear, key_value: nn.Linear) -> None:
    """nn.MultiheadAttention's init (xavier over the stacked (3d, d) in-projection, zero bias) for separate query
    and key/value Linears, so their scale matches the fused ``qkv`` of the default layer."""
    weight = torch.empty(query.out_features + key_value.out_features, query.in_features)
    nn.init.xavier_uniform_(weight)
    with torch.no_grad():
        query.weight.copy_(weight[: query.out_features])
        key_value.weight.copy_(weight[query.out_features :])
    for layer in (query, key_value):
        if layer.bias is not None:
            nn.init.zeros_(layer.bias)


def _zero_bias(layer: nn.Linear) -> None:
    if layer.bias is not None:
        nn.init.zeros_(layer.bias)


def zero_linear(in_features: int, out_features: int, bias: bool = True) -> nn.Linear:
    """A zero-initialised Linear, built without drawing from the global RNG: adding one to a model leaves every
    other parameter's initialisation (and so a training seed's run) as it was without it."""
    with torch.random.fork_rng(devices=[]):
        layer = nn.Linear(in_features, out_features, bias=bias)
    nn.init.zeros_(layer.weight)
    if bias:
        nn.init.zeros_(layer.bias)
    return layer


class EncoderLayer(nn.Module):
    """nn.TransformerEncoderLayer's computation, batch-first, with attention through
    ``F.scaled_dot_product_attention`` (fused kernels on GPU) and a boolean key-padding mask.

    Same parameters as ``nn.TransformerEncoderLayer(d, heads, ff, dropout)``, so counts and init match MDM.

    pose_centric (FlowMDM PCCAT): the query comes from ``query_cond([h ; condition])`` then ``q_proj``; keys and
    values from ``kv_proj(h)`` only. cross_attention (FLAME, nn.TransformerDecoderLayer's order): a cross-attention
    block to ``memory`` between self-attention and feed-forward, with its own LayerNorm ``norm_cross``.
    """

    def __init__(self, config: ModelConfig, *, pose_centric: bool = False, cross_attention: bool = False) -> None:
        super().__init__()
        d, inner, bias = config.latent_dim, config.attention_dim, config.attention_bias
        self.num_heads = config.num_heads
        self.attention_dropout = config.dropout_of("attention")
        self.ff_dropout = config.dropout_of("ff")
        self.residual_dropout = config.dropout_of("residual")
        self.norm_first = config.norm_first
        self.activation = ACTIVATIONS[config.activation]
        self.pose_centric = pose_centric
        self.has_cross_attention = cross_attention
        if pose_centric:
            self.query_cond = nn.Linear(2 * d, d)
            self.q_proj = nn.Linear(d, inner, bias=bias)
            self.kv_proj = nn.Linear(d, 2 * inner, bias=bias)
        else:
            self.qkv = nn.Linear(d, 3 * inner, bias=bias)
        self.out_proj = nn.Linear(inner, d, bias=bias)
        self.linear1 = nn.Linear(d, config.ff_dim)
        self.linear2 = nn.Linear(config.ff_dim, d)
        self.norm1 = FP32LayerNorm(d)
        self.norm2 = FP32LayerNorm(d)
        # nn.MultiheadAttention's initialisation, for parity with MDM.
        if pose_centric:
            _init_split_projection(self.q_proj, self.kv_proj)
        else:
            nn.init.xavier_uniform_(self.qkv.weight)
            _zero_bias(self.qkv)
        _zero_bias(self.out_proj)
        if cross_attention:
            self.cross_q = nn.Linear(d, inner, bias=bias)
            self.cross_kv = nn.Linear(d, 2 * inner, bias=bias)
            self.cross_out = nn.Linear(inner, d, bias=bias)
            self.norm_cross = FP32LayerNorm(d)
            _init_split_projection(self.cross_q, self.cross_kv)
            _zero_bias(self.cross_out)
        self.num_blocks = 3 if cross_attention else 2
        if config.adaptive_norm != "none":
            # DiT's adaLN(-Zero): (shift, scale[, gate]) per residual block from SiLU(c), zero-initialised.
            self.num_modulations = 3 if config.adaptive_norm == "adaln_zero" else 2
            self.modulation = zero_linear(d, self.num_modulations * self.num_blocks * d)

    def _split_heads(self, x: Tensor, parts: int) -> tuple[Tensor, ...]:
        """(B, S, parts·a) → ``parts`` tensors (B, heads, S, a/heads), a = ModelConfig.attention_dim."""
        batch, seq, width = x.shape
        head_dim = width // (parts * self.num_heads)
        return x.view(batch, seq, parts, self.num_heads, head_dim).permute(2, 0, 3, 1, 4).unbind(0)

    def _merge_heads(self, x: Tensor) -> Tensor:
        batch, _, seq, _ = x.shape
        return x.transpose(1, 2).reshape(batch, seq, -1)

    def _attention(self, x: Tensor, attention: Attention, condition: Tensor | None) -> Tensor:
        dropout_p = self.attention_dropout if self.training else 0.0
        if self.pose_centric:
            if condition is None:
                raise ValueError("a pose-centric (PCCAT) layer needs the per-token condition")
            (q,) = self._split_heads(self.q_proj(self.query_cond(torch.cat([x, condition.to(x.dtype)], dim=-1))), 1)
            k, v = self._split_heads(self.kv_proj(x), 2)
        else:
            q, k, v = self._split_heads(self.qkv(x), 3)
        q, k = attention.position(q, k)
        out = self._merge_heads(attention.attend(q, k, v, dropout_p))
        return F.dropout(self.out_proj(out), self.residual_dropout, self.training)

    def _cross_attention(self, x: Tensor, memory: Tensor, memory_mask: Tensor | None) -> Tensor:
        dropout_p = self.attention_dropout if self.training else 0.0
        (q,) = self._split_heads(self.cross_q(x), 1)
        k, v = self._split_heads(self.cross_kv(memory), 2)
        out = scaled_dot_product_attention(q, k, v, attn_mask=memory_mask, dropout_p=dropout_p)
        return F.dropout(self.cross_out(self._merge_heads(out)), self.residual_dropout, self.training)

    def _feed_forward(self, x: torch.Tensor) -> torch.Tensor:
        hidden = F.dropout(self.activation(self.linear1(x)), self.ff_dropout, self.training)
        return F.dropout(self.linear2(hidden), self.residual_dropout, self.training)

    def forward(
        self,
        x: torch.Tensor,
        attn_mask: torch.Tensor | Attention | None = None,
        *,
        condition: Tensor | None = None,
        memory: Tensor | None = None,
        memory_mask: Tensor | None = None,
        skip: Tensor | None = None,
        norm_condition: Tensor | None = None,
    ) -> torch.Tensor:
        """x: (B, S, d). attn_mask: (B, 1, 1, S) bool, True = key may be attended, or None (attend to all), or an
        attention plan (:class:`DenseAttention`, :class:`BlendedAttention`).
        condition: (B, S, d) per-token query condition (pose-centric layers). memory: (B, M, d) and memory_mask
        (B, 1, 1, M) bool (cross-attention layers).
        skip: (blocks,) bool, True = that residual block (attention, [cross-attention,] feed-forward) passes its
        input through unchanged (layer dropout); None = every block runs.
        norm_condition: (B, d) the per-sample condition c of adaptive-norm layers (ModelConfig.adaptive_norm)."""
        plans = (DenseAttention, BlendedAttention)
        attention = attn_mask if isinstance(attn_mask, plans) else DenseAttention(attn_mask)
        if self.has_cross_attention and memory is None:
            raise ValueError("a cross-attention layer needs the memory")
        adaptive = hasattr(self, "modulation")
        if adaptive != (norm_condition is not None):
            raise ValueError("an adaptive-norm layer needs norm_condition, and only such a layer takes it")
        # (B, blocks, 2 or 3, 1, d): each block's shift, scale (and gate), broadcast over the tokens.
        mods = None if not adaptive else self.modulation(F.silu(norm_condition)).view(
            -1, self.num_blocks, self.num_modulations, 1, norm_condition.shape[-1])

        def pre(index: int, normed: Tensor) -> Tensor:
            return normed if mods is None else normed * (1 + mods[:, index, 1]) + mods[:, index, 0]

        def post(index: int, out: Tensor) -> Tensor:
            return out if mods is None or self.num_modulations == 2 else mods[:, index, 2] * out
        if self.norm_first:
            blocks = [lambda h: h + post(0, self._attention(pre(0, self.norm1(h)), attention, condition))]
            if self.has_cross_attention:
                blocks.append(lambda h: h + post(1, self._cross_attention(pre(1, self.norm_cross(h)), memory,
                                                                          memory_mask)))
            last = self.num_blocks - 1
            blocks.append(lambda h: h + post(last, self._feed_forward(pre(last, self.norm2(h)))))
        else:
            blocks = [lambda h: self.norm1(h + self._attention(h, attention, condition))]
            if self.has_cross_attention:
                blocks.append(lambda h: self.norm_cross(h + self._cross_attention(h, memory, memory_mask)))
            blocks.append(lambda h: self.norm2(h + self._feed_forward(h)))
        if skip is not None and skip.shape != (len(blocks),):
            raise ValueError(f"skip must be ({len(blocks)},) bool, one per residual block, got {tuple(skip.shape)}")
        for index, block in enumerate(blocks):
            # A skipped block is still computed, so its parameters stay in the graph (DDP); its result is dropped.
            x = block(x) if skip is None else torch.where(skip[index], x, block(x))
        return x


class SinusoidalLengthEmbedding(nn.Module):
    """Sinusoid of the valid length (frames) → Linear → SiLU → Linear (ModelConfig.length_embedding='sinusoidal')."""

    def __init__(self, latent_dim: int) -> None:
        super().__init__()
        self.latent_dim = latent_dim
        self.mlp = nn.Sequential(nn.Linear(latent_dim, latent_dim), nn.SiLU(), nn.Linear(latent_dim, latent_dim))

    def forward(self, lengths: torch.Tensor) -> torch.Tensor:
        return self.mlp(sinusoidal_embedding(lengths, self.latent_dim))


class TimeEmbedding(nn.Module):
    """Sinusoid of ``t·1000`` → Linear → SiLU → Linear (MDM's TimestepEmbedder); continuous by default, on MFM's or
    MDM's integer grid with ``grid`` (ModelConfig.time_grid)."""

    def __init__(self, latent_dim: int, grid: str = "continuous") -> None:
        super().__init__()
        self.latent_dim = latent_dim
        self.grid = grid
        self.mlp = nn.Sequential(nn.Linear(latent_dim, latent_dim), nn.SiLU(), nn.Linear(latent_dim, latent_dim))

    def positions(self, t: torch.Tensor) -> torch.Tensor:
        """The sinusoid's argument for times ``t``: ``t·1000``, floored or rounded on the reference grids."""
        scaled = t.float() * TIME_SCALE  # float32 like the reference, so the floor lands where MFM's does
        if self.grid == "floor":
            return scaled.long().float()
        if self.grid == "nearest":
            return scaled.round()
        return scaled

    def forward(self, t: torch.Tensor, table: torch.Tensor | None = None) -> torch.Tensor:
        """``table``: a stored (rows, latent) sinusoid table to look grid positions up in (the reference's rows);
        None computes the sinusoid."""
        positions = self.positions(t)
        if table is not None and self.grid != "continuous":
            return self.mlp(table[positions.long()])
        return self.mlp(sinusoidal_embedding(positions, self.latent_dim))


class StepSizeEmbedding(TimeEmbedding):
    """The shortcut model's step size d (ModelConfig.shortcut_levels): embedded as the time is, ``d·1000`` through
    a sinusoid and an MLP, whose last layer starts at zero, so the model starts as the flow model it may be
    initialised from (d = 0 is that flow field)."""

    def __init__(self, latent_dim: int) -> None:
        super().__init__(latent_dim)
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)


class MotionFlowTransformer(nn.Module):
    """Velocity field ``v(x_t, t, condition)`` over normalised motion features (B, T, D)."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        d = config.latent_dim
        self.input_proj = nn.Linear(config.feature_dim * config.frames_per_token, d)
        if config.self_condition_prob > 0:
            # Zero-initialised: the network starts as the one without the input, and learns to use the estimate.
            # No bias: the estimate joins the input as more input weights (Chen et al. concatenate it to x_t), so
            # zeros (no estimate) add exactly nothing and get no gradient, and a run that starts the estimate pass
            # late (train.self_condition_start_step) is, until then, the run without the option, bit for bit.
            self.self_condition_proj = zero_linear(config.feature_dim * config.frames_per_token, d, bias=False)
        self.time_embedding = TimeEmbedding(d, config.time_grid)
        if config.shortcut_levels > 0:
            self.step_size_embedding = StepSizeEmbedding(d)
        if config.is_action_model:
            # MDM's EmbedAction: an N(0, 1) table, zeroed (not replaced) when the condition is dropped.
            self.action_embedding = nn.Embedding(config.num_actions, d)
        else:
            self.cond_proj = nn.Linear(config.cond_dim, d)
        if config.length_token:
            self.length_embedding = (nn.Embedding(config.max_frames + 1, d) if config.length_embedding == "learned"
                                     else SinusoidalLengthEmbedding(d))
        # Computed: not persistent, a pure function of (max_len, d), so checkpoints stay small and max_len can
        # change. Stored: a converted checkpoint's own table (ModelConfig.positional_table).
        self.register_buffer(
            "positional_table", sinusoidal_embedding(torch.arange(config.max_len), d),
            persistent=config.positional_table == "stored",
        )
        if config.absolute_positions == "scaled_sinusoidal":
            self.absolute_embedding = ScaledSinusoidalEmbedding(d)
        if config.wrapper_projections:
            self.project_in = nn.Linear(d, d)
        self.layers = nn.ModuleList(
            EncoderLayer(
                config,
                pose_centric=config.conditioning == "pccat",
                cross_attention=config.conditioning == "cross_attention",
            )
            for _ in range(config.num_layers)
        )
        # Pre-norm leaves the residual stream un-normalised; post-norm (MDM) already ends in a LayerNorm.
        self.final_norm = FP32LayerNorm(d) if config.norm_first else nn.Identity()
        if config.wrapper_projections:
            self.project_out = nn.Linear(d, d)
        self.output_proj = nn.Linear(d, config.output_size * config.frames_per_token)
        if config.adaptive_norm != "none":
            # DiT's final layer: the last norm's (shift, scale) from SiLU(c), zero-initialised.
            self.final_modulation = zero_linear(d, 2 * d)
        if config.conditioning == "cross_attention":
            # FLAME: Linear(768 → 768) of RoBERTa's last hidden states, the cross-attention memory.
            self.text_proj = nn.Linear(config.text_token_dim, d)
        if config.null_condition == "empty_caption":
            # Filled by set_null_condition from the dataset's text encoder; saved with the weights.
            self.register_buffer("null_text", torch.zeros(config.cond_dim))
            if config.conditioning == "cross_attention":
                self.register_buffer("null_text_tokens", torch.zeros(config.null_tokens, config.text_token_dim))
                self.register_buffer("null_text_token_len", torch.zeros((), dtype=torch.long))

    def set_null_condition(self, pooled: Tensor, tokens: Tensor | None = None, token_len: int | None = None) -> None:
        """Store the text encoder's output for the empty caption (null_condition='empty_caption'): ``pooled``
        (cond_dim,), and for cross-attention ``tokens`` (null_tokens, token_dim) with ``token_len`` valid rows."""
        if self.config.null_condition != "empty_caption":
            raise ValueError("set_null_condition needs ModelConfig.null_condition='empty_caption'")
        with torch.no_grad():
            self.null_text.copy_(torch.as_tensor(pooled).reshape(self.null_text.shape))
            if self.config.conditioning == "cross_attention":
                if tokens is None or token_len is None:
                    raise ValueError("a cross_attention model's null condition needs the empty caption's token "
                                     "features and their count")
                self.null_text_tokens.copy_(torch.as_tensor(tokens).reshape(self.null_text_tokens.shape))
                self.null_text_token_len.fill_(int(token_len))

    def forward(
        self,
        x: torch.Tensor,
        t: torch.Tensor,
        cond: torch.Tensor,
        lengths: torch.Tensor | None = None,
        *,
        cond_mask: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
        segments: torch.Tensor | None = None,
        frame_cond: torch.Tensor | None = None,
        text_tokens: torch.Tensor | None = None,
        text_token_len: torch.Tensor | None = None,
        positional_mode: torch.Tensor | None = None,
        attention_chunk: int | None = None,
        block_drop_mask: torch.Tensor | None = None,
        step_size: torch.Tensor | float | None = None,
        self_condition: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Velocity at ``x`` (B, T, D) and times ``t`` (B,) in [0, 1].

        cond: (B, cond_dim) float text embeddings, or (B,) long action ids for an action model.
        lengths: (B,) valid frames per sample (>= 1); frames beyond are padding, hidden from attention and zeroed in
            the output. None: every frame is valid (and attention runs unmasked, the fastest kernel).
        cond_mask: (B,) bool, True = drop that sample's condition (pooled, per-frame and token features alike).
            Overrides the random training-time dropout, so one batched call can hold a sampler's conditional and
            unconditional halves.
        generator: RNG for the training-time draws, in this order: condition dropout (unless ``cond_mask``), then
            the BPE mode (unless ``positional_mode``), then the skipped blocks (``layer_dropout`` > 0, unless
            ``block_drop_mask``). Global RNG if None.
        segments: bpe only; (B, T) integer segment index of every frame (a segment = a run of equal values);
            None = one segment. Absolute positions restart and absolute-mode attention stays inside each segment.
        frame_cond: pccat only; (B, T, cond_dim) text embedding of the segment each frame belongs to; None =
            ``cond`` for every frame.
        text_tokens, text_token_len: cross_attention only (required); (B, L, token_dim) token-level text features
            zero-padded beyond (B,) valid counts (the shards' ``text_tokens`` / ``text_token_len``).
        positional_mode: bpe only; (B,) bool, True = relative mode. None: drawn per sample in training
            (``bpe_train_relative_prob``), all absolute in eval.
        attention_chunk: bpe only; compute the frames' attention blockwise in query blocks of this many frames
            (memory linear in T, same result). None: one dense mask.
        block_drop_mask: (num_layers, blocks_per_layer) bool, True = that residual block is skipped (layer
            dropout, in any mode). None: drawn in training when ``layer_dropout`` > 0, no block skipped otherwise.
        step_size: shortcut models only (``shortcut_levels`` > 0): (B,) or one step size d in [0, 1]; the output is
            the average velocity over [t, t + d]. None = 0, the flow-matching field.
        self_condition: self-conditioned models only (``self_condition_prob`` > 0): (B, T, feature_dim) an earlier
            estimate x̂1 of the motion (normalised features); None = zeros (no estimate).
        Returns (B, T, output_size) in ``x``'s dtype (fp32 under bf16 autocast, for the ODE solver).
        """
        config = self.config
        batch, num_frames, _ = self._check_inputs(x, t, cond, lengths, cond_mask)
        self._check_variant_inputs(
            batch, num_frames, segments, frame_cond, text_tokens, text_token_len, positional_mode, attention_chunk
        )
        expected_blocks = (config.num_layers, config.blocks_per_layer)
        if block_drop_mask is not None and (block_drop_mask.shape != expected_blocks
                                            or block_drop_mask.dtype != torch.bool):
            raise ValueError(f"block_drop_mask must be bool {expected_blocks}, got {tuple(block_drop_mask.shape)} "
                             f"{block_drop_mask.dtype}")
        if cond_mask is None and self.training and config.cond_drop_prob > 0:
            cond_mask = draw_cond_drop_mask(batch, config.cond_drop_prob, generator, x.device)

        if lengths is not None:
            lengths = lengths.to(x.device, non_blocking=True)
        frame_mask = None if lengths is None else valid_frame_mask(lengths, num_frames)
        # Tokens: one per frames_per_token frames (one per frame by default).
        per_token = config.frames_per_token
        num_tokens = -(-num_frames // per_token)
        token_lengths = None if lengths is None else -(-lengths // per_token)
        token_mask = frame_mask if per_token == 1 or lengths is None else valid_frame_mask(token_lengths, num_tokens)
        if config.length_token and lengths is None:
            lengths = torch.full((batch,), num_frames, dtype=torch.long, device=x.device)

        time = self.time_embedding(t, self.positional_table if config.positional_table == "stored" else None)
        if config.shortcut_levels > 0:
            d = torch.as_tensor(0.0 if step_size is None else step_size, device=x.device, dtype=torch.float32)
            time = time + self.step_size_embedding(d.reshape(-1).expand(batch))
        elif step_size is not None:
            raise ValueError("step_size is an input of shortcut models only (ModelConfig.shortcut_levels > 0)")
        aux = self._auxiliary_tokens(time, cond, cond_mask, lengths)
        if config.prediction == "preconditioned":
            path_time = t.to(x.device).float().reshape(-1).expand(batch)
            c_in, c_skip, c_out = (c[:, None, None] for c in preconditioning(path_time))
            motion = self.input_proj(self._group_frames((x.float() * c_in).to(x.dtype), frame_mask))
        else:
            motion = self.input_proj(self._group_frames(x, frame_mask))
        if config.self_condition_prob > 0:
            if self_condition is None:
                self_condition = torch.zeros_like(x)
            elif self_condition.shape != x.shape:
                raise ValueError(f"self_condition must have x's shape {tuple(x.shape)}, got "
                                 f"{tuple(self_condition.shape)}")
            motion = motion + self.self_condition_proj(self._group_frames(self_condition.to(x.dtype), frame_mask))
        elif self_condition is not None:
            raise ValueError("self_condition is an input of self-conditioned models only "
                             "(ModelConfig.self_condition_prob > 0)")
        if config.wrapper_projections:
            motion = self.project_in(motion)
        tokens = torch.cat([token.unsqueeze(1).to(motion.dtype) for token in aux] + [motion], dim=1)
        if config.positional == "bpe":
            if positional_mode is None:
                positional_mode = (
                    draw_positional_mode(batch, config.bpe_train_relative_prob, generator, x.device)
                    if self.training
                    else torch.zeros(batch, dtype=torch.bool, device=x.device)
                )
            relative = positional_mode.to(x.device)
            runs, offsets = segment_runs(
                None if segments is None else segments.to(x.device), batch, num_frames, x.device
            )
            tokens = tokens + self._segment_positions(offsets, len(aux)) * (~relative).to(tokens.dtype)[:, None, None]
            attention: Attention = self._blended_attention(
                len(aux), runs, offsets, relative, frame_mask, attention_chunk
            )
        else:
            # The fp32 table promotes the residual stream to fp32 under autocast; only the matmuls run in bf16.
            tokens = tokens + self._sequence_positions(tokens.shape[1])
            if config.progress_positions:
                tokens = torch.cat([tokens[:, : len(aux)], tokens[:, len(aux) :] + self._progress_positions(
                    token_lengths, batch, num_tokens, x.device)], dim=1)
            key_mask = None
            if token_mask is not None and not config.attend_padding:
                aux_valid = torch.ones(batch, len(aux), dtype=torch.bool, device=x.device)
                key_mask = torch.cat([aux_valid, token_mask], dim=1)[:, None, None, :]
            attention = DenseAttention(key_mask)
        tokens = F.dropout(tokens, config.dropout, self.training)

        condition = None
        if config.conditioning == "pccat":
            condition = self._frame_conditions(time, cond, frame_cond, cond_mask, num_frames)
        memory = memory_mask = None
        if config.conditioning == "cross_attention":
            memory, memory_mask = self._text_memory(aux, text_tokens, text_token_len, cond_mask)

        if block_drop_mask is None and self.training and config.layer_dropout > 0:
            block_drop_mask = draw_block_drop_mask(config.num_layers, config.blocks_per_layer, config.layer_dropout,
                                                   generator, x.device)
        # adaLN's c: the sum of the auxiliary tokens, i.e. time + pooled condition (+ length), DiT's t + y.
        norm_condition = torch.stack(aux).sum(0) if config.adaptive_norm != "none" else None
        for index, layer in enumerate(self.layers):
            skip = None if block_drop_mask is None else block_drop_mask[index].to(x.device)
            tokens = layer(tokens, attention, condition=condition, memory=memory, memory_mask=memory_mask, skip=skip,
                           norm_condition=norm_condition)
        hidden = self.final_norm(tokens[:, len(aux) :])
        if norm_condition is not None:
            shift, scale = self.final_modulation(F.silu(norm_condition)).unsqueeze(1).chunk(2, dim=-1)
            hidden = hidden * (1 + scale) + shift
        if config.wrapper_projections:
            hidden = self.project_out(hidden)
        # The output head runs outside autocast: a bf16 product has an 8-bit mantissa, and its rounding (about
        # 0.4 % of each feature, different in every frame) would reach the motion as frame-to-frame jitter. It
        # is one d x features product, a small share of a step's work.
        with torch.autocast(device_type=hidden.device.type, enabled=False):
            velocity = self.output_proj(hidden.to(self.output_proj.weight.dtype))
        if per_token > 1:
            velocity = velocity.reshape(batch, num_tokens * per_token, -1)[:, :num_frames]
        if config.prediction == "data":
            velocity = velocity_from_data(velocity.float(), x.float(), t.to(x.device).float())
        elif config.prediction == "preconditioned":
            x1_hat = c_skip * x.float() + c_out * velocity.float()
            velocity = velocity_from_data(x1_hat, x.float(), t.to(x.device).float())
        if frame_mask is not None and not config.attend_padding:
            velocity = velocity * frame_mask.unsqueeze(-1)
        return velocity.to(x.dtype)

    def _group_frames(self, frames: Tensor, frame_mask: Tensor | None) -> Tensor:
        """(B, T, D) frames → (B, ⌈T/p⌉, p·D) tokens of p = frames_per_token consecutive frames. Padded frames are
        zeroed first: they share a token with the last valid frames, and their content must not reach them."""
        per_token = self.config.frames_per_token
        if per_token == 1:
            return frames
        if frame_mask is not None:
            frames = frames * frame_mask.unsqueeze(-1).to(frames.dtype)
        frames = F.pad(frames, (0, 0, 0, (-frames.shape[1]) % per_token))
        return frames.reshape(frames.shape[0], frames.shape[1] // per_token, per_token * frames.shape[2])

    # -- conditioning ------------------------------------------------------------------------------------------

    def _pooled_condition(self, cond: Tensor, cond_mask: Tensor | None) -> Tensor:
        """(B, latent) embedding of the pooled text (or action), zeroed before the projection when dropped."""
        keep = None if cond_mask is None else (~cond_mask).unsqueeze(1)
        if self.config.is_action_model:
            cond_embedding = self.action_embedding(cond)
            return cond_embedding if keep is None else cond_embedding * keep
        if self.config.null_condition == "empty_caption":
            return self.cond_proj(self._scaled_text(self._with_null_text(cond, cond_mask)))
        # Zero the raw embedding before the projection, as MDM's mask_cond: the null condition is the bias.
        cond = self._scaled_text(cond)
        return self.cond_proj(cond if keep is None else cond * keep)

    def _with_null_text(self, text: Tensor, cond_mask: Tensor | None) -> Tensor:
        """``text`` (B, ..., cond_dim) with the dropped samples' embedding replaced by the empty caption's."""
        if cond_mask is None:
            return text
        dropped = cond_mask.reshape(-1, *([1] * (text.dim() - 1)))
        return torch.where(dropped, self.null_text.to(text.dtype), text)

    def _scaled_text(self, text: Tensor) -> Tensor:
        """A text embedding (..., cond_dim) as the projection sees it (ModelConfig.cond_scaling)."""
        if self.config.cond_scaling == "none":
            return text
        rms = text.float().square().mean(dim=-1, keepdim=True).sqrt()
        return (text.float() / rms.clamp_min(1e-12)).to(text.dtype)

    def _auxiliary_tokens(
        self, time: Tensor, cond: Tensor, cond_mask: Tensor | None, lengths: Tensor | None
    ) -> list[Tensor]:
        """The (B, latent) tokens before the frames, in order (see ModelConfig.num_prefix_tokens)."""
        config = self.config
        tokens: list[Tensor] = []
        if config.length_token:
            tokens.append(self.length_embedding(lengths.long()))
        if config.conditioning == "prefix":
            tokens.append(time + self._pooled_condition(cond, cond_mask))  # MFM's time ⊕ condition token
        elif config.conditioning == "cross_attention":
            tokens += [time, self._pooled_condition(cond, cond_mask)]  # FLAME's TS and pooled-text tokens
        return tokens

    def _frame_conditions(
        self, time: Tensor, cond: Tensor, frame_cond: Tensor | None, cond_mask: Tensor | None, num_frames: int
    ) -> Tensor:
        """PCCAT's (B, T, latent) per-frame conditions: time embedding + projected text of each frame's segment."""
        if frame_cond is None:
            frame_cond = cond.unsqueeze(1).expand(-1, num_frames, -1)
        if self.config.null_condition == "empty_caption":
            frame_cond = self._with_null_text(frame_cond, cond_mask)
        elif cond_mask is not None:
            frame_cond = frame_cond * (~cond_mask)[:, None, None].to(frame_cond.dtype)
        return time.unsqueeze(1) + self.cond_proj(self._scaled_text(frame_cond))

    def _text_memory(
        self, aux: list[Tensor], text_tokens: Tensor, text_token_len: Tensor, cond_mask: Tensor | None
    ) -> tuple[Tensor, Tensor]:
        """FLAME's cross-attention memory [aux tokens, Linear(text tokens)] and its (B, 1, 1, M) key mask. A dropped
        condition hides every text token (only the auxiliary tokens, with the null pooled text, remain), or with
        null_condition='empty_caption' (FLAME's own rule) attends to the empty caption's token features."""
        num_tokens = text_tokens.shape[1]
        text_token_len = text_token_len.to(text_tokens.device)
        empty_caption = self.config.null_condition == "empty_caption"
        if empty_caption and cond_mask is not None:
            # FLAME: a dropped caption is the encoding of "", its token features attended like any caption's.
            null = text_tokens.new_zeros(num_tokens, text_tokens.shape[2])
            rows = min(num_tokens, self.config.null_tokens)
            null[:rows] = self.null_text_tokens[:rows].to(text_tokens.dtype)
            text_tokens = torch.where(cond_mask[:, None, None], null, text_tokens)
            null_len = self.null_text_token_len.clamp(max=num_tokens).to(text_token_len.dtype)
            text_token_len = torch.where(cond_mask, null_len, text_token_len)
        projected = self.text_proj(text_tokens)
        memory = torch.cat([torch.stack(aux, dim=1).to(projected.dtype), projected], dim=1)
        token_valid = torch.arange(num_tokens, device=projected.device) < text_token_len.to(projected.device)[:, None]
        if cond_mask is not None and not empty_caption:
            token_valid = token_valid & ~cond_mask[:, None]
        aux_valid = torch.ones(projected.shape[0], len(aux), dtype=torch.bool, device=projected.device)
        return memory, torch.cat([aux_valid, token_valid], dim=1)[:, None, None, :]

    # -- blended positional encodings -------------------------------------------------------------------------

    def _progress_positions(self, lengths: Tensor | None, batch: int, num_frames: int, device: torch.device) -> Tensor:
        """(B, T, latent) sinusoid of each frame's progress through its motion (ModelConfig.progress_positions);
        padded frames get the last frame's."""
        frames = torch.arange(num_frames, device=device, dtype=torch.float32)
        last = (torch.full((batch,), num_frames, device=device) if lengths is None else lengths).float() - 1
        progress = (frames[None] / last.clamp_min(1)[:, None]).clamp(max=1.0)
        return sinusoidal_embedding(progress * TIME_SCALE, self.config.latent_dim)

    def _sequence_positions(self, length: int) -> Tensor:
        """(length, latent) absolute embedding of positions 0 … length−1 (ModelConfig.absolute_positions)."""
        if self.config.absolute_positions == "scaled_sinusoidal":
            return self.absolute_embedding(torch.arange(length, device=self.positional_table.device))
        return self.positional_table[:length]

    def _segment_positions(self, offsets: Tensor, num_aux: int) -> Tensor:
        """(B, P + T, latent) absolute positions: the auxiliary tokens at 0 … P−1, each frame at P + its index in
        its segment (one segment = MFM's table exactly)."""
        batch = offsets.shape[0]
        if self.config.absolute_positions == "scaled_sinusoidal":
            aux = torch.arange(num_aux, device=offsets.device).unsqueeze(0).expand(batch, -1)
            return self.absolute_embedding(torch.cat([aux, num_aux + offsets], dim=1))
        table = self.positional_table
        aux = table[:num_aux].unsqueeze(0).expand(batch, -1, -1)
        return torch.cat([aux, table[num_aux + offsets]], dim=1)

    def _blended_attention(
        self,
        num_aux: int,
        runs: Tensor,
        offsets: Tensor,
        relative: Tensor,
        frame_mask: Tensor | None,
        chunk: int | None,
    ) -> BlendedAttention:
        config = self.config
        window = None
        if chunk is not None:
            # The band must hold every allowed pair: the horizon (relative) and a whole segment (absolute).
            longest_segment = int(offsets.max()) + 1
            window = max(config.attention_horizon, longest_segment - 1)
        return BlendedAttention(
            num_aux=num_aux,
            runs=runs,
            relative=relative,
            horizon=config.attention_horizon,
            horizon_in_absolute=config.horizon_in_absolute,
            rotary_dims=config.rotary_dims,
            positions=torch.arange(runs.shape[1], device=runs.device),
            frame_valid=frame_mask,
            chunk=chunk,
            window=window,
        )

    # -- input checks -----------------------------------------------------------------------------------------

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
        # bpe positions restart at every segment: its own check bounds the longest segment instead.
        num_tokens = -(-num_frames // config.frames_per_token)
        if config.positional == "absolute" and num_tokens + config.num_prefix_tokens > config.max_len:
            raise ValueError(
                f"{num_frames} frames ({num_tokens} tokens) + {config.num_prefix_tokens} prefix tokens exceed "
                f"max_len={config.max_len}"
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

    def _check_variant_inputs(
        self,
        batch: int,
        num_frames: int,
        segments: Tensor | None,
        frame_cond: Tensor | None,
        text_tokens: Tensor | None,
        text_token_len: Tensor | None,
        positional_mode: Tensor | None,
        attention_chunk: int | None,
    ) -> None:
        """Checks of the options' inputs; syncs with the device only to bound a bpe model's longest segment when
        the whole sequence would not fit in the positional table."""
        config = self.config
        bpe_inputs = {"segments": segments, "positional_mode": positional_mode, "attention_chunk": attention_chunk}
        for name, value in bpe_inputs.items():
            if value is not None and config.positional != "bpe":
                raise ValueError(f"{name} needs ModelConfig.positional='bpe'; this model is {config.positional!r}")
        if frame_cond is not None and config.conditioning != "pccat":
            raise ValueError(f"frame_cond needs ModelConfig.conditioning='pccat'; this model is {config.conditioning!r}")
        given_tokens = text_tokens is not None or text_token_len is not None
        if config.conditioning == "cross_attention":
            if text_tokens is None or text_token_len is None:
                raise ValueError("a cross_attention model needs text_tokens (B, L, E) and text_token_len (B,)")
        elif given_tokens:
            raise ValueError(f"text_tokens need ModelConfig.conditioning='cross_attention'; this model is "
                             f"{config.conditioning!r}")
        if segments is not None and (segments.shape != (batch, num_frames) or segments.is_floating_point()
                                     or segments.dtype == torch.bool):
            raise ValueError(f"segments must be integer ({batch}, {num_frames}), got {tuple(segments.shape)} "
                             f"{segments.dtype}")
        if positional_mode is not None and (positional_mode.shape != (batch,) or positional_mode.dtype != torch.bool):
            raise ValueError(f"positional_mode must be bool ({batch},), got {tuple(positional_mode.shape)} "
                             f"{positional_mode.dtype}")
        if attention_chunk is not None and (
            not isinstance(attention_chunk, int) or isinstance(attention_chunk, bool) or attention_chunk <= 0
        ):
            raise ValueError(f"attention_chunk must be a positive int, got {attention_chunk!r}")
        if frame_cond is not None and (frame_cond.shape != (batch, num_frames, config.cond_dim)
                                       or not frame_cond.is_floating_point()):
            raise ValueError(f"frame_cond must be float ({batch}, {num_frames}, {config.cond_dim}), got "
                             f"{tuple(frame_cond.shape)} {frame_cond.dtype}")
        if text_tokens is not None:
            if (text_tokens.dim() != 3 or text_tokens.shape[0] != batch or text_tokens.shape[1] == 0
                    or text_tokens.shape[2] != config.text_token_dim or not text_tokens.is_floating_point()):
                raise ValueError(f"text_tokens must be float ({batch}, L >= 1, {config.text_token_dim}), got "
                                 f"{tuple(text_tokens.shape)} {text_tokens.dtype}")
            if text_token_len.shape != (batch,) or text_token_len.is_floating_point():
                raise ValueError(f"text_token_len must be integer ({batch},), got {tuple(text_token_len.shape)} "
                                 f"{text_token_len.dtype}")
        if config.positional == "bpe" and num_frames + config.num_prefix_tokens > config.max_len:
            longest = num_frames
            if segments is not None:
                longest = int(segment_runs(segments, batch, num_frames, segments.device)[1].max()) + 1
            if longest + config.num_prefix_tokens > config.max_len:
                raise ValueError(f"a segment of {longest} frames + {config.num_prefix_tokens} prefix tokens exceeds "
                                 f"max_len={config.max_len}")


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
