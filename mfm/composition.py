"""Composition and extrapolation sampling (FlowMDM) with a flow-matching velocity model.

A list of (condition, length) segments is generated as ONE sequence of Σ length frames, batch size 1:

* per frame: the index of its segment (``segments``: absolute positions restart there and absolute-mode attention
  stays inside it) and, for a ``'pccat'`` model, the text embedding of its segment (``frame_cond``);
* the ODE is integrated with every evaluation at flow time ``t < switch`` in the model's absolute mode and every
  later one in relative mode. FlowMDM's ``bpe_denoising_step`` k (60 HumanML3D, 125 Babel) switches at t > 1000 − k:
  the first k − 1 of its 1000 reverse diffusion steps use absolute positions, relative ones from step 1000 − k on
  (``BPE_Schedule``: relative iff t ≤ 1000 − k); flow matching runs noise → data over
  t = 0 → 1, so the absolute part is the start of the interval. :func:`flow_time_of_diffusion_step` converts
  FlowMDM's step count into the flow time with the same signal-to-noise ratio (``HUMANML3D_SWITCH``,
  ``BABEL_SWITCH``); ``switch`` also takes a number of leading solver steps;
* classifier-free guidance runs both halves in one batched pass (:func:`mfm.solvers.guided_velocity` on the model
  with these per-frame inputs bound, :class:`BoundInputs`), integrated by :func:`mfm.solvers.solve` with a
  fixed-step solver within a budget of ``max_nfe`` (50) evaluations.

:func:`extrapolate` repeats one text over many segments (longer than any training sample); for a ``'bpe'`` model it
computes attention blockwise (``attention_chunk``), so memory grows linearly with the length.

Distinct texts per segment need a ``'pccat'`` model (the only conditioning with per-frame conditions); ``'prefix'``
and ``'cross_attention'`` models compose segments of one text. A model with ``positional='absolute'`` is sampled
over the whole sequence with ordinary full attention (the switch does not apply).

:func:`read_prompt_file` reads FlowMDM's JSON prompt files ``{"text": [...], "lengths": [...]}``; encoding the texts
(mfm.text) is the caller's job.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor, nn

from mfm.flow import SIGMA_MIN
from mfm.path import data_from_velocity
from mfm.solvers import FIXED_STEP_SOLVERS, SolveResult, guided_velocity, initial_noise, solve, step_grid

logger = logging.getLogger(__name__)

DDPM_COSINE_OFFSET = 0.008
"""``s`` of the cosine noise schedule (Nichol & Dhariwal) used by FlowMDM's 1000-step diffusion."""
MAX_BETA = 0.999
"""guided-diffusion clips the cosine schedule's betas at this value."""
SWITCH_TOLERANCE = 1e-6
"""An evaluation time within this of the switch counts as reached (solver times are float32 copies of the grid)."""
DEFAULT_MAX_NFE = 50


def _cosine_alphas_cumprod(num_steps: int) -> list[float]:
    """ᾱ_t of guided-diffusion's ``squaredcos_cap_v2`` schedule, t = 0 … num_steps − 1 (float64)."""

    def alpha_bar(s: float) -> float:
        return math.cos((s + DDPM_COSINE_OFFSET) / (1 + DDPM_COSINE_OFFSET) * math.pi / 2) ** 2

    cumulative, product = [], 1.0
    for i in range(num_steps):
        beta = min(1.0 - alpha_bar((i + 1) / num_steps) / alpha_bar(i / num_steps), MAX_BETA)
        product *= 1.0 - beta
        cumulative.append(product)
    return cumulative


def flow_time_of_diffusion_step(
    denoising_steps: int, num_diffusion_steps: int = 1000, *, sigma_min: float = SIGMA_MIN
) -> float:
    """Flow time at which FlowMDM's BPE schedule switches from absolute to relative mode.

    FlowMDM's ``BPE_Schedule`` runs its reverse steps t > T − k in absolute mode — the first k − 1 of them,
    t = T−1 … T−k+1 (k = ``denoising_steps``) — and the steps ``t <= T − k`` in relative mode. The returned flow time has the signal-to-noise ratio of ``x_{T−k}``
    (``√ᾱ / √(1 − ᾱ)`` on the cosine schedule) on MFM's path ``x_t = t·x1 + (1 − (1 − σ_min)·t)·x0``
    (``t / (1 − (1 − σ_min)·t)``), so the same noise level is the first one denoised in relative mode.
    0 steps → 0.0 (all relative); FlowMDM's −1 (all absolute) is ``switch=1.0``.
    """
    if not isinstance(num_diffusion_steps, int) or num_diffusion_steps < 1:
        raise ValueError(f"num_diffusion_steps must be a positive int, got {num_diffusion_steps!r}")
    if not isinstance(denoising_steps, int) or not 0 <= denoising_steps <= num_diffusion_steps:
        raise ValueError(f"denoising_steps must be an int in [0, {num_diffusion_steps}], got {denoising_steps!r}")
    if denoising_steps == 0:
        return 0.0
    alpha_bar = _cosine_alphas_cumprod(num_diffusion_steps)[num_diffusion_steps - denoising_steps]
    snr = math.sqrt(alpha_bar / (1.0 - alpha_bar))
    return snr / (1.0 + (1.0 - sigma_min) * snr)


HUMANML3D_SWITCH = flow_time_of_diffusion_step(60)
"""FlowMDM's HumanML3D ``--bpe_denoising_step 60`` as a flow time (≈ 0.09)."""
BABEL_SWITCH = flow_time_of_diffusion_step(125)
"""FlowMDM's Babel ``--bpe_denoising_step 125`` as a flow time (≈ 0.17)."""


def read_prompt_file(path: str | Path) -> list[tuple[str, int]]:
    """FlowMDM's composition / extrapolation JSON ``{"text": [...], "lengths": [...]}`` → [(text, frames), ...]."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: cannot read a FlowMDM prompt file: {err}") from err
    if not isinstance(data, dict) or "text" not in data or "lengths" not in data:
        raise ValueError(f'{path}: expected an object with "text" and "lengths" lists')
    texts, lengths = data["text"], data["lengths"]
    if not isinstance(texts, list) or not isinstance(lengths, list):
        raise ValueError(f'{path}: "text" and "lengths" must be lists')
    if len(texts) != len(lengths) or not texts:
        raise ValueError(f'{path}: "text" ({len(texts)}) and "lengths" ({len(lengths)}) must be non-empty and of '
                         "equal size")
    for index, (text, length) in enumerate(zip(texts, lengths)):
        if not isinstance(text, str) or not text.strip():
            raise ValueError(f"{path}: segment {index}: text must be a non-empty string, got {text!r}")
        if not isinstance(length, int) or isinstance(length, bool) or length < 1:
            raise ValueError(f"{path}: segment {index}: length must be a positive int, got {length!r}")
    return list(zip(texts, lengths))


def segment_index(lengths: Sequence[int]) -> Tensor:
    """(Σ lengths,) long: the segment number of every frame of the composed sequence."""
    return torch.repeat_interleave(torch.arange(len(lengths)), torch.as_tensor(list(lengths), dtype=torch.long))


def segment_boundaries(lengths: Sequence[int]) -> list[tuple[int, int]]:
    """[start, end) frames of every segment of the composed sequence."""
    bounds, start = [], 0
    for length in lengths:
        bounds.append((start, start + int(length)))
        start += int(length)
    return bounds


def resolve_switch(switch: float | int, steps: int, grid: Tensor | None = None) -> float:
    """Flow time from which evaluations run in relative mode.

    float in [0, 1]: that time (1.0 = never, i.e. all absolute; 0.0 = all relative). int k in [0, steps]: the
    first k of ``steps`` steps run in absolute mode (k = steps: all), uniform steps or those of ``grid``.
    """
    if isinstance(switch, bool):
        raise ValueError(f"switch must be a flow time (float) or a step count (int), got {switch!r}")
    if isinstance(switch, int):
        if not 0 <= switch <= steps:
            raise ValueError(f"switch as a step count must be in [0, {steps}] (steps), got {switch}")
        if switch == steps:
            return math.inf
        return switch / steps if grid is None else float(grid[switch])
    switch = float(switch)
    if not 0.0 <= switch <= 1.0:
        raise ValueError(f"switch as a flow time must be in [0, 1], got {switch}")
    return math.inf if switch == 1.0 else switch


class BoundInputs:
    """A velocity model with per-sample extra inputs bound, callable with the solvers' model signature
    ``(x, t, cond, lengths, *, cond_mask)`` (so :func:`mfm.solvers.guided_velocity` and :func:`mfm.solvers.sample`
    can drive it).

    extras: keyword inputs of the model (``segments``, ``frame_cond``, ``text_tokens``, ``text_token_len``) with a
        leading batch of B; a call with k·B samples (guidance's conditional and unconditional halves) repeats them
        k times.
    switch_time: if given, ``positional_mode`` is set per evaluation: relative iff ``t >= switch_time``.
    attention_chunk: passed to the model as is.
    step_size: a shortcut model's step size d (``mfm.shortcut.sampler_step_size``), passed to every call; None for a
        flow model.

    A self-conditioned model (``config.self_condition_prob`` > 0) gets, as ``self_condition``, the x̂1 that its
    previous call implied for the same rows (:func:`mfm.path.data_from_velocity`): along one solve that is the
    previous evaluation's estimate (a Runge-Kutta stage's included), each half of a guided pass its own. A call at
    a time earlier than the previous one (a new solve, or an adaptive solver's retried step) or with another batch
    shape starts again from zeros, as the first step of a solve does. So one object must not drive two solves at
    once.
    """

    def __init__(
        self,
        model: nn.Module,
        extras: dict[str, Tensor] | None = None,
        *,
        switch_time: float | None = None,
        attention_chunk: int | None = None,
        step_size: float | None = None,
    ) -> None:
        self.model = model
        self.step_size = step_size
        self.extras = dict(extras or {})
        batches = {value.shape[0] for value in self.extras.values()}
        if len(batches) > 1:
            sizes = {name: value.shape[0] for name, value in self.extras.items()}
            raise ValueError(f"bound inputs disagree on the batch size: {sizes}")
        self.batch = batches.pop() if batches else None
        self.switch_time = switch_time
        self.attention_chunk = attention_chunk
        self.self_conditioning = self_conditioned(model)
        self._estimate: Tensor | None = None  # the previous call's x̂1 (self-conditioning)
        self._estimate_time = -math.inf

    @property
    def config(self):
        return self.model.config

    @property
    def training(self) -> bool:
        return self.model.training

    def parameters(self):
        return self.model.parameters()

    def __call__(
        self, x: Tensor, t: Tensor, cond: Tensor, lengths: Tensor | None = None, *, cond_mask: Tensor | None = None
    ) -> Tensor:
        kwargs: dict[str, object] = {}
        if self.extras:
            if x.shape[0] % self.batch != 0:
                raise ValueError(f"a batch of {x.shape[0]} is not a multiple of the bound inputs' batch {self.batch}")
            repeats = x.shape[0] // self.batch
            for name, value in self.extras.items():
                value = value.to(x.device)
                kwargs[name] = value if repeats == 1 else value.repeat(repeats, *([1] * (value.dim() - 1)))
        if self.switch_time is not None:
            kwargs["positional_mode"] = t >= self.switch_time - SWITCH_TOLERANCE
        if self.attention_chunk is not None:
            kwargs["attention_chunk"] = self.attention_chunk
        if self.step_size is not None:
            kwargs["step_size"] = self.step_size
        if not self.self_conditioning:
            return self.model(x, t, cond, lengths, cond_mask=cond_mask, **kwargs)
        time = float(torch.as_tensor(t).max())
        previous = self._estimate
        if previous is not None and (previous.shape != x.shape or time < self._estimate_time):
            previous = None  # a new solve (or a retried step): start from no estimate, as training's zero rows
        velocity = self.model(x, t, cond, lengths, cond_mask=cond_mask, self_condition=previous, **kwargs)
        times = torch.as_tensor(t, device=x.device).float().reshape(-1).expand(x.shape[0])
        self._estimate = data_from_velocity(velocity.float(), x.float(), times).to(x.dtype)
        self._estimate_time = time
        return velocity


def self_conditioned(model: nn.Module) -> bool:
    """Whether ``model`` takes an estimate of the motion as an input (``config.self_condition_prob`` > 0)."""
    return float(getattr(getattr(model, "config", None), "self_condition_prob", 0.0)) > 0


def bind_inputs(model: nn.Module, extras: Mapping[str, Tensor] | None = None, *,
                step_size: float | None = None) -> nn.Module | BoundInputs:
    """``model`` with per-sample ``extras`` and a shortcut model's ``step_size`` bound (:class:`BoundInputs`), or
    ``model`` itself when there is nothing to bind."""
    if not extras and step_size is None and not self_conditioned(model):
        return model
    return BoundInputs(model, dict(extras or {}), step_size=step_size)


@dataclass
class Composition:
    """A composed sequence.

    motion: (Σ lengths, output features) normalised features of the whole sequence.
    boundaries: [start, end) frames of every segment, in order.
    switch_time: flow time from which the model ran in relative mode (inf: never; absolute-positional models: nan).
    result: the raw solve (``x1`` (1, Σ lengths, D), ``nfe``, ``x1_hat`` if requested, grid).
    """

    motion: Tensor
    boundaries: list[tuple[int, int]]
    switch_time: float
    result: SolveResult

    @property
    def nfe(self) -> int:
        return self.result.nfe

    def segment(self, index: int) -> Tensor:
        start, end = self.boundaries[index]
        return self.motion[start:end]


def check_composition_budget(solver: str, steps: int, max_nfe: int = DEFAULT_MAX_NFE) -> int:
    """The number of evaluations ``solver`` with ``steps`` makes; ValueError unless it can compose: the
    positional mode switches at a fixed time, so a fixed-step solver, within the ``max_nfe`` budget."""
    if solver not in FIXED_STEP_SOLVERS:
        raise ValueError(f"composition switches positional modes at a fixed time: use a fixed-step solver "
                         f"{sorted(FIXED_STEP_SOLVERS)}, not {solver!r}")
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 1:
        raise ValueError(f"steps must be a positive int, got {steps!r}")
    nfe = steps * FIXED_STEP_SOLVERS[solver].num_stages
    if nfe > max_nfe:
        raise ValueError(f"{solver} with {steps} steps makes {nfe} model evaluations; composition allows at most "
                         f"{max_nfe} (max_nfe={max_nfe})")
    return nfe


def model_device(model: nn.Module) -> torch.device:
    parameter = next(model.parameters(), None)
    return parameter.device if parameter is not None else torch.device("cpu")


def _stack_conditions(segments: Sequence[tuple[Tensor, int]]) -> tuple[Tensor, list[int]]:
    if len(segments) == 0:
        raise ValueError("compose needs at least one (condition, length) segment")
    conds, lengths = [], []
    for index, segment in enumerate(segments):
        if len(segment) != 2:
            raise ValueError(f"segment {index} must be a (condition, length) pair, got {len(segment)} items")
        cond, length = segment
        if not isinstance(length, int) or isinstance(length, bool) or length < 1:
            raise ValueError(f"segment {index}: length must be a positive int, got {length!r}")
        conds.append(torch.as_tensor(cond))
        lengths.append(length)
    shapes = {tuple(c.shape) for c in conds}
    if len(shapes) != 1:
        raise ValueError(f"segment conditions must all have one shape, got {sorted(shapes)}")
    return torch.stack(conds), lengths


@torch.no_grad()
def compose(
    model: nn.Module,
    segments: Sequence[tuple[Tensor, int]],
    *,
    solver: str = "euler",
    steps: int = 20,
    guidance: float = 2.5,
    switch: float | int = HUMANML3D_SWITCH,
    seed: int = 0,
    generator: torch.Generator | None = None,
    null_cond: Tensor | None = None,
    conditional_channels: Tensor | None = None,
    text_tokens: Tensor | None = None,
    text_token_len: int | None = None,
    attention_chunk: int | None = None,
    return_trajectory: bool = False,
    max_nfe: int = DEFAULT_MAX_NFE,
    precision: str = "fp32",
    step_size: float | None = None,
) -> Composition:
    """Sample ``segments`` = [(condition, frames), ...] as one sequence (FlowMDM composition).

    model: a :class:`mfm.model.MotionFlowTransformer` (eval mode). condition: (cond_dim,) pooled text embedding
        (an action id for a prefix action model); distinct conditions need ``conditioning='pccat'``.
    solver / steps: a fixed-step solver of mfm.solvers (the positional mode switches at a fixed time, which an
        adaptive solver's error control would fight); ``steps × stages <= max_nfe``.
    guidance: classifier-free guidance scale (one batched pass per evaluation); ``conditional_channels``: feature
        channels left unguided (:func:`mfm.solvers.guided_velocity`).
    switch: flow time from which evaluations use relative mode, or a number of leading absolute steps
        (:func:`resolve_switch`); bpe models only.
    seed / generator: initial noise (1, Σ frames, D) as :func:`mfm.solvers.initial_noise`, so one segment with
        ``switch`` all-absolute reproduces :func:`mfm.solvers.sample` for the same seed.
    text_tokens (L, token_dim) / text_token_len: the text's token features, for a cross_attention model.
    attention_chunk: blockwise attention for bpe models (see MotionFlowTransformer.forward).
    precision: ``fp32`` or ``bf16`` (the model's passes under bf16 autocast; :func:`mfm.solvers.guided_velocity`).
    step_size: a shortcut model's step size for ``solver`` and ``steps`` (:func:`mfm.shortcut.sampler_step_size`);
        None for a flow model. The positional mode of a shortcut step is the one at its start time.
    """
    config = model.config
    if getattr(model, "training", False):
        logger.warning("composing with a model in training mode: dropout makes the velocity field random")
    check_composition_budget(solver, steps, max_nfe)
    device = model_device(model)
    conds, lengths = _stack_conditions(segments)
    conds = conds.to(device)
    bpe = config.positional == "bpe"
    grid = step_grid(steps, config.sampling_times)  # a few-step student's own times
    switch_time = resolve_switch(switch, steps, grid)

    extras: dict[str, Tensor] = {}
    if config.conditioning == "pccat":
        extras["frame_cond"] = conds.repeat_interleave(torch.as_tensor(lengths, device=device), dim=0).unsqueeze(0)
    elif not all(torch.equal(conds[0], c) for c in conds[1:]):
        raise ValueError(
            f"segments with different conditions need a model with conditioning='pccat' (per-frame conditions); "
            f"this model uses {config.conditioning!r}, which takes one condition per sequence"
        )
    if config.conditioning == "cross_attention":
        if text_tokens is None or text_token_len is None:
            raise ValueError("a cross_attention model needs the text's text_tokens (L, E) and text_token_len")
        extras["text_tokens"] = torch.as_tensor(text_tokens).to(device).unsqueeze(0)
        extras["text_token_len"] = torch.tensor([int(text_token_len)], device=device)
    elif text_tokens is not None or text_token_len is not None:
        raise ValueError(f"text_tokens are for a cross_attention model; this model uses {config.conditioning!r}")
    if bpe:
        extras["segments"] = segment_index(lengths).to(device).unsqueeze(0)
    elif attention_chunk is not None:
        raise ValueError("attention_chunk needs a model with positional='bpe'")

    bound = BoundInputs(
        model, extras, switch_time=switch_time if bpe else None, attention_chunk=attention_chunk, step_size=step_size
    )
    total = sum(lengths)
    x0 = initial_noise((1, total, config.feature_dim), seed=seed, generator=generator, device=device)
    velocity = guided_velocity(bound, conds[:1], scale=guidance, null_cond=null_cond,
                               conditional_channels=conditional_channels, precision=precision)
    result = solve(velocity, x0, solver=solver, steps=steps, grid=grid, return_trajectory=return_trajectory)
    return Composition(
        motion=result.x1[0],
        boundaries=segment_boundaries(lengths),
        switch_time=switch_time if bpe else math.nan,
        result=result,
    )


def extrapolate(
    model: nn.Module,
    cond: Tensor,
    lengths: Sequence[int],
    *,
    attention_chunk: int | None | str = "auto",
    **kwargs,
) -> Composition:
    """One condition repeated over ``len(lengths)`` consecutive segments (FlowMDM's extrapolation), as :func:`compose`.

    attention_chunk: "auto" = the model's attention horizon for a bpe model (blockwise attention, memory linear in
        the total length), None = dense attention; or an explicit block size.
    """
    if attention_chunk == "auto":
        attention_chunk = model.config.attention_horizon if model.config.positional == "bpe" else None
    return compose(model, [(cond, length) for length in lengths], attention_chunk=attention_chunk, **kwargs)
