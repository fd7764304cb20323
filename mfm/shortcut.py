"""Shortcut models (Frans, Hafner, Levine & Abbeel 2024, "One Step Diffusion via Shortcut Models"): one network
that takes the sampler's step size d besides the time, trained so that one step of size d equals two of d/2.

A model with ``ModelConfig.shortcut_levels`` = K returns, for d = 2^-k (k < K), the average velocity over
[t, t + d]; d = 0 is its flow-matching field, trained as any flow model's on the data, and the finest shortcut
level 2^-(K−1) is built from two Euler steps of 2^-K on that field. :class:`ShortcutObjective` is the training
loss (the flow rows plus the self-consistency rows), :func:`sampler_step_size` the step size a sampler gives the
model.

As in the authors' code (``targets_shortcut.py``), a share of each batch (theirs 1/8) are self-consistency rows,
spread evenly over the levels, each at a time on its level's grid (t = i·d); the targets come from the model being
trained, without gradients and without dropout (their ``bootstrap_ema=0`` variant; their default takes the EMA
weights), and guidance is built into the levels (their
``bootstrap_cfg``): the finest level's two half steps are taken with the guided flow field, so every coarser level
inherits the guidance, and the model samples its few steps with guidance 1. Ours, not theirs: the guidance may mix
only the pose channels (``conditional_channels``, ``model.guided_features='pose'``), and the self-consistency rows
carry the flow loss's capped weighting over t and its jitter and bone-length terms (``mfm.flow``), as the flow rows
do, with the bones held to the clip's.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from mfm.composition import BoundInputs
from mfm.flow import FlowMatchingObjective, interpolate, sample_noise, sample_time, target_velocity, velocity_loss
from mfm.guidance import classifier_free_guidance
from mfm.model import ModelConfig, draw_cond_drop_mask, valid_frame_mask

PER_ROW_KWARGS = ("segments", "frame_cond", "text_tokens", "text_token_len", "positional_mode")
"""Model inputs with a leading batch dimension (the others, such as ``block_drop_mask``, hold for the batch)."""


def level_steps(levels: int) -> tuple[int, ...]:
    """The Euler step counts a shortcut model with ``levels`` levels takes in its trained step sizes: 1, 2, ...,
    2^(levels − 1)."""
    return tuple(2**k for k in range(levels))


def sampler_step_size(levels: int, solver: str, steps: int) -> float | None:
    """The step size d a sampler gives a model with ``levels`` shortcut levels: None for a flow model (levels 0);
    1/steps for Euler at a trained level's step count (1, 2, ..., 2^(levels − 1)); 0 (the flow field) for Euler at
    2^levels steps or more, and for every other solver. Euler at an untrained count in between is a ValueError."""
    if levels == 0:
        return None
    if solver != "euler" or steps >= 2**levels:
        return 0.0
    if steps not in level_steps(levels):
        raise ValueError(f"a shortcut model with {levels} levels samples Euler in "
                         f"{', '.join(map(str, level_steps(levels)))} steps (its trained step sizes) or in "
                         f"{2**levels} or more (its flow field), not {steps}")
    return 1.0 / steps


def rows_of(model_kwargs: Mapping[str, Any], rows: Tensor) -> dict[str, Any]:
    """``model_kwargs`` for the batch rows ``rows`` (per-row inputs indexed, the others as they are)."""
    return {name: (value[rows] if name in PER_ROW_KWARGS and value is not None else value)
            for name, value in model_kwargs.items()}


@dataclass(frozen=True)
class ShortcutObjective:
    """The shortcut model's training loss: ``flow``'s loss on the flow rows (d = 0) plus the self-consistency loss
    on the first ``round(B · bootstrap_fraction)`` rows (at least one), each row's share of the batch weighing it.

    levels: the model's ``shortcut_levels`` (K): self-consistency row i gets d = 2^-k, k = (i + a random first
        level) mod K.
    guidance / conditional_channels: the classifier-free guidance of the finest level's half steps on the flow
        field (the scale the model's few steps build in; 1 = none) and the channels that stay conditional
        (``mfm.solvers.guided_velocity``).
    """

    flow: FlowMatchingObjective
    levels: int
    bootstrap_fraction: float = 0.25
    guidance: float = 1.0
    conditional_channels: Tensor | None = None

    def __post_init__(self) -> None:
        if self.levels < 1:
            raise ValueError(f"ShortcutObjective.levels must be >= 1, got {self.levels!r}")
        if not 0.0 < self.bootstrap_fraction < 1.0:
            raise ValueError(f"ShortcutObjective.bootstrap_fraction must be in (0, 1), got {self.bootstrap_fraction!r}")
        if self.guidance < 0:
            raise ValueError(f"ShortcutObjective.guidance must be >= 0, got {self.guidance!r}")
        if self.flow.input_perturbation > 0:  # its self-consistency targets are the model's own steps from x_t
            raise ValueError("ShortcutObjective: the flow objective's input_perturbation is not supported with "
                             "shortcut levels (train.flow_input_perturbation=0 with model.shortcut_levels > 0)")

    def bootstrap_rows(self, batch: int) -> int:
        """How many of a batch's rows are self-consistency rows (the others are flow rows; a batch of one is all
        self-consistency)."""
        return min(batch, max(1, round(batch * self.bootstrap_fraction)))

    def loss(
        self,
        model: Callable[..., Tensor],
        x1: Tensor,
        cond: Tensor,
        lengths: Tensor,
        *,
        generator: torch.Generator | None = None,
        cond_mask: Tensor | None = None,
        t: Tensor | None = None,
        x0: Tensor | None = None,
        model_kwargs: Mapping[str, Any] | None = None,
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """The loss of one batch, from one model pass with gradients over all its rows (as a data-parallel wrapper
        expects: one forward, one backward) after the self-consistency targets' passes without. Draws from
        ``generator``, in this order: the flow rows' times and noise (as :func:`mfm.flow.flow_matching_loss`), the
        self-consistency rows' first level, grid times and noise, then, when ``cond_mask`` is None, the flow rows'
        dropped conditions (``model.config.cond_drop_prob``). ``t`` and ``x0`` (injected draws, (B,) and
        (B, T, D)) replace the flow rows' draws and give the self-consistency rows their noise; ``cond_mask``'s
        dropped conditions apply to the flow rows only: the self-consistency rows are conditional (their guided
        targets need the condition)."""
        flow, sigma_min = self.flow, self.flow.sigma_min
        batch, device = x1.shape[0], x1.device
        kwargs = dict(model_kwargs or {})
        lengths = lengths.to(device)
        n_boot = self.bootstrap_rows(batch)
        n_flow = batch - n_boot
        boot, flow_rows = slice(0, n_boot), slice(n_boot, batch)

        flow_t = sample_time(n_flow, generator, device) if t is None else t[flow_rows].to(device)
        flow_t = flow.training_times.warp(flow_t)
        flow_x0 = sample_noise(x1[flow_rows], generator) if x0 is None else x0[flow_rows].to(device)
        # Spread over the levels from a random first one, so that every level is trained at any batch size.
        draw_device = generator.device if generator is not None else device
        first = torch.randint(self.levels, (1,), generator=generator, device=draw_device).to(device)
        level = (torch.arange(n_boot, device=device) + first) % self.levels
        sections = (2 ** level).float()
        d = 1.0 / sections
        boot_t = torch.floor(sample_time(n_boot, generator, device) * sections) / sections  # on the level's grid
        boot_x0 = sample_noise(x1[boot], generator) if x0 is None else x0[boot].to(device)
        keep = torch.zeros(n_boot, dtype=torch.bool, device=device)
        if cond_mask is None:
            dropped = draw_cond_drop_mask(n_flow, _config_of(model).cond_drop_prob, generator, device)
        else:
            dropped = cond_mask[flow_rows].to(device)
        cond_mask = torch.cat([keep, dropped])

        times = torch.cat([boot_t, flow_t])
        x_t = interpolate(torch.cat([boot_x0, flow_x0]), x1, times, sigma_min)
        boot_target = self.two_half_steps(model, x_t[boot], boot_t, d, level, cond[boot], lengths[boot],
                                          rows_of(kwargs, torch.arange(n_boot, device=device)))
        step_size = torch.cat([d, torch.zeros(n_flow, device=device)])
        velocity = model(x_t, times, cond, lengths, cond_mask=cond_mask, step_size=step_size, **kwargs)

        frame_mask = valid_frame_mask(lengths, x1.shape[1])
        terms = dict(sigma_min=sigma_min, loss_space=flow.loss_space, temporal_weight=flow.temporal_weight,
                     bone_weight=flow.bone_weight, bone_target=flow.bone_target,
                     trajectory_weight=flow.trajectory_weight,
                     trajectory_min_t=flow.trajectory_min_t, trajectory_huber=flow.trajectory_huber,
                     foot_contact_weight=flow.foot_contact_weight, root_mean_weight=flow.root_mean_weight,
                     geometry=flow.geometry, terms_weighting=flow.terms_weighting,
                     velocity_weight_cap=flow.velocity_weight_cap,
                     channel_weight=flow.channel_weight_on(x1.device))
        boot_loss = velocity_loss(velocity[boot], boot_target, x1[boot], boot_t, frame_mask[boot], **terms)
        loss = boot_loss * (n_boot / batch)
        if n_flow:
            flow_loss = velocity_loss(velocity[flow_rows], target_velocity(flow_x0, x1[flow_rows], sigma_min),
                                      x1[flow_rows], flow_t, frame_mask[flow_rows], **terms)
            loss = loss + flow_loss * (n_flow / batch)
        return loss, {"loss": loss.detach(), "valid_frames": frame_mask.sum(),
                      "self_consistency_loss": boot_loss.detach()}

    @torch.no_grad()
    def two_half_steps(self, model: Callable[..., Tensor], x_t: Tensor, t: Tensor, d: Tensor, level: Tensor,
                       cond: Tensor, lengths: Tensor, model_kwargs: dict[str, Any]) -> Tensor:
        """The target average velocity over [t, t + d]: the mean of the model's velocities over two Euler steps of
        d/2. The finest level's half steps (d/2 = 2^-K) take the flow field (step size 0) with guidance; the
        others the level below, conditional."""
        finest = level == self.levels - 1
        model_kwargs = {name: value for name, value in model_kwargs.items() if name != "block_drop_mask"}  # eval: none
        half = torch.where(finest, torch.zeros_like(d), d / 2)
        step = (d / 2)[:, None, None]
        was_training = bool(getattr(model, "training", False))
        if was_training:
            model.eval()  # the targets without dropout, as the authors' (train=False)
        try:
            first = self._field(model, x_t, t, half, finest, cond, lengths, model_kwargs)
            second = self._field(model, x_t + step * first, t + d / 2, half, finest, cond, lengths, model_kwargs)
        finally:
            if was_training:
                model.train()
        return (first + second) / 2

    def _field(self, model: Callable[..., Tensor], x: Tensor, t: Tensor, step_size: Tensor, guided: Tensor,
               cond: Tensor, lengths: Tensor, model_kwargs: dict[str, Any]) -> Tensor:
        """The model's velocity at (x, t, step_size) with the condition; on rows where ``guided``, classifier-free
        guided at ``self.guidance`` (each row's model pass once: the guided rows' in the guided call only)."""
        if self.guidance == 1.0 or not bool(guided.any()):
            return _conditional(model, x, t, step_size, cond, lengths, model_kwargs)
        out = torch.empty_like(x)
        plain = (~guided).nonzero().squeeze(1)
        if plain.numel():
            out[plain] = _conditional(model, x[plain], t[plain], step_size[plain], cond[plain], lengths[plain],
                                      rows_of(model_kwargs, plain)).to(out.dtype)
        which = guided.nonzero().squeeze(1)
        # the rows' inputs, their step sizes among them, repeated for guidance's two halves
        bound = BoundInputs(model, {**rows_of(model_kwargs, which), "step_size": step_size[which]})
        guided_field = classifier_free_guidance(bound, cond[which], scale=self.guidance, lengths=lengths[which],
                                                conditional_channels=self.conditional_channels)
        out[which] = guided_field(x[which], t[which]).to(out.dtype)
        return out


def _conditional(model: Callable[..., Tensor], x: Tensor, t: Tensor, step_size: Tensor, cond: Tensor,
                 lengths: Tensor, model_kwargs: Mapping[str, Any]) -> Tensor:
    keep = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
    return model(x, t, cond, lengths, cond_mask=keep, step_size=step_size, **model_kwargs)


def _config_of(model: Any) -> ModelConfig:
    """The model's config through a data-parallel wrapper (``.module``)."""
    return model.config if hasattr(model, "config") else model.module.config
