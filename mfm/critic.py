"""A critic that judges a generated motion as a whole, for adversarial distillation of a few-step student.

Reflow's loss compares a student's motion with its teacher's pair by pair; what the pairs average away (the feet's
contacts, the detail a single step blurs) no pairwise loss sees. Adversarial distillation (Sauer et al. 2023,
"Adversarial Diffusion Distillation", ADD; Lin et al. 2024, SDXL-Lightning) adds a critic trained to tell the
teacher's motions from the student's, and a term that moves the student toward what the critic takes for the
teacher's. ADD's critic reads frozen image-encoder features; a motion has no such encoder here, so this critic reads
the normalised motion features themselves: a stack of dilated 1-D convolutions over time (receptive field 31 frames
with dilations 1, 2, 4, 8), spectral-normalised (Miyato et al. 2018, which keeps the critic Lipschitz and its
gradient to the student bounded), with a logit per frame and the caption entering by projection (Miyato & Koyama
2018, "cGANs with Projection Discriminator"): ``logit_t = w·h_t + <e(c), h_t>``. Its losses are hinge losses per
valid frame (ADD's). The architecture is ours, not a published motion critic (docs/few-step.md, "A critic in the
trainer").

Padded frames (beyond each motion's length) are zeroed at the input and after every block, so no frame of padding
reaches a valid frame's logit, and they are left out of every mean.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn.utils.parametrizations import spectral_norm

CRITIC_DILATIONS = (1, 2, 4, 8)


class MotionCritic(nn.Module):
    """Caption- (or action-) conditioned critic of normalised motion features (B, T, D) with per-frame logits.

    ``cond_dim`` > 0: the condition is a pooled caption embedding (B, cond_dim); ``num_actions`` > 0 instead: an
    action index (B,). ``channels`` wide, one residual block per entry of ``dilations`` (kernel ``kernel``)."""

    def __init__(self, feature_dim: int, *, cond_dim: int = 0, num_actions: int = 0, channels: int = 128,
                 kernel: int = 3, dilations: tuple[int, ...] = CRITIC_DILATIONS) -> None:
        super().__init__()
        if feature_dim <= 0 or channels <= 0 or kernel < 1 or kernel % 2 == 0 or not dilations:
            raise ValueError(f"MotionCritic needs feature_dim > 0, channels > 0, an odd kernel and at least one "
                             f"dilation, got {feature_dim}, {channels}, {kernel}, {dilations}")
        if (cond_dim > 0) == (num_actions > 0):
            raise ValueError(f"MotionCritic takes a caption embedding (cond_dim > 0) or an action (num_actions > 0), "
                             f"exactly one of them, got cond_dim={cond_dim}, num_actions={num_actions}")
        self.input = spectral_norm(nn.Conv1d(feature_dim, channels, 1))
        self.blocks = nn.ModuleList(
            spectral_norm(nn.Conv1d(channels, channels, kernel, dilation=d, padding=d * (kernel - 1) // 2))
            for d in dilations)
        self.activation = nn.LeakyReLU(0.2)
        self.logit = spectral_norm(nn.Conv1d(channels, 1, 1))
        self.condition = (spectral_norm(nn.Linear(cond_dim, channels, bias=False)) if cond_dim > 0
                          else spectral_norm(nn.Embedding(num_actions, channels)))

    def forward(self, motion: torch.Tensor, cond: torch.Tensor, frame_mask: torch.Tensor) -> torch.Tensor:
        """Per-frame logits (B, T) of ``motion`` (B, T, D) under ``cond``; ``frame_mask`` (B, T) bool marks the
        valid frames (the logits of the others are 0)."""
        keep = frame_mask.unsqueeze(1).to(motion.dtype)  # (B, 1, T)
        h = self.activation(self.input(motion.transpose(1, 2) * keep)) * keep
        for block in self.blocks:
            h = (h + self.activation(block(h))) * keep
        embedded = self.condition(cond)  # (B, C)
        logits = self.logit(h).squeeze(1) + torch.einsum("bct,bc->bt", h, embedded.to(h.dtype))
        return logits * keep.squeeze(1)


def frame_mean(per_frame: torch.Tensor, frame_mask: torch.Tensor) -> torch.Tensor:
    """Mean over each motion's valid frames, then over the motions (so that ranks with equal batch sizes average to
    the global batch's mean)."""
    mask = frame_mask.to(per_frame.dtype)
    return ((per_frame * mask).sum(dim=1) / mask.sum(dim=1).clamp_min(1.0)).mean()


def critic_hinge_loss(real_logits: torch.Tensor, fake_logits: torch.Tensor, frame_mask: torch.Tensor
                      ) -> torch.Tensor:
    """The critic's hinge loss (Lim & Ye 2017; ADD's): ``relu(1 − real) + relu(1 + fake)`` per valid frame."""
    return (frame_mean(torch.relu(1.0 - real_logits), frame_mask)
            + frame_mean(torch.relu(1.0 + fake_logits), frame_mask))


def generator_hinge_loss(fake_logits: torch.Tensor, frame_mask: torch.Tensor) -> torch.Tensor:
    """The student's adversarial loss: ``−logit`` per valid frame of its motion."""
    return -frame_mean(fake_logits, frame_mask)
