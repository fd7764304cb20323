"""Classifier-free guidance as one batched model pass (shared by the flow-matching solvers and the diffusion
samplers): the conditional and unconditional halves run as a single forward of size 2B, the condition is encoded
once by the caller and never re-encoded, and scale 1 / 0 need only one half."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from mfm.layout import FeatureLayout
from mfm.skeleton import Skeleton


def classifier_free_guidance(
    model: Callable[..., Tensor],
    cond: Tensor,
    *,
    scale: float,
    lengths: Tensor | None = None,
    null_cond: Tensor | None = None,
    guided_channels: int | None = None,
    conditional_channels: Tensor | None = None,
) -> Callable[[Tensor, Tensor], Tensor]:
    """``(x, t) -> out``: ``out(∅) + scale·(out(c) − out(∅))`` from one batched model pass of size 2B.

    model: called as ``model(x, t, cond, lengths, cond_mask=...)`` (cond_mask True = drop the condition).
    scale: 1 → the conditional output alone (one pass of size B); 0 → the unconditional output alone.
    null_cond: what the unconditional half receives as ``cond`` (default ``cond``, dropped through cond_mask).
    guided_channels: mix only the first k output channels and take the others from the conditional half (FLAME /
        GLIDE: guide ε, keep the conditional learned variance). None: mix every channel
        (the flow-matching velocity, :func:`mfm.solvers.guided_velocity`).
    conditional_channels: (C,) bool mask of output channels that take the conditional output unguided (True)
        instead of the mix, e.g. :attr:`mfm.layout.FeatureLayout.root_motion_mask` for ``model.guided_features='pose'``
        (applied after ``guided_channels``). None or all False: no exception.
    """
    batch = cond.shape[0]
    uncond = cond if null_cond is None else null_cond.to(cond.device, cond.dtype).expand_as(cond)
    keep = torch.zeros(batch, dtype=torch.bool, device=cond.device)
    drop = torch.ones(batch, dtype=torch.bool, device=cond.device)

    if conditional_channels is not None:
        conditional_channels = conditional_channels.to(device=cond.device, dtype=torch.bool)
        if not bool(conditional_channels.any()):
            conditional_channels = None
    if scale == 1.0:
        return lambda x, t: model(x, t, cond, lengths, cond_mask=keep)
    if scale == 0.0:
        return lambda x, t: model(x, t, uncond, lengths, cond_mask=drop)

    both_cond = torch.cat([cond, uncond])
    both_mask = torch.cat([keep, drop])
    both_lengths = None if lengths is None else torch.cat([lengths, lengths])

    def guided(x: Tensor, t: Tensor) -> Tensor:
        out_cond, out_uncond = model(torch.cat([x, x]), torch.cat([t, t]), both_cond, both_lengths,
                                     cond_mask=both_mask).chunk(2)
        if guided_channels is None or guided_channels >= out_cond.shape[-1]:
            mixed = out_uncond + scale * (out_cond - out_uncond)
        else:
            k = guided_channels
            mixed = torch.cat([out_uncond[..., :k] + scale * (out_cond[..., :k] - out_uncond[..., :k]),
                               out_cond[..., k:]], dim=-1)
        if conditional_channels is None:
            return mixed
        if conditional_channels.shape != (out_cond.shape[-1],):
            raise ValueError(f"conditional_channels must be a ({out_cond.shape[-1]},) mask of the output channels, "
                             f"got shape {tuple(conditional_channels.shape)}")
        return torch.where(conditional_channels, out_cond, mixed)

    return guided


def guided_feature_mask(guided_features: str, skeleton: Skeleton) -> Tensor | None:
    """``conditional_channels`` for ``model.guided_features``: None for 'all' (every channel guided); for 'pose',
    the channels of ``skeleton``'s features that carry the root's motion (FeatureLayout.root_motion_mask)."""
    if guided_features == "all":
        return None
    if guided_features == "pose":
        return torch.from_numpy(FeatureLayout(skeleton).root_motion_mask)
    raise ValueError(f"guided_features must be 'all' or 'pose', got {guided_features!r}")
