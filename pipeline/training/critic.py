"""The critic of ``train.critic_weight > 0`` beside the trained model: its update, its part of the resume state.

:class:`mfm.critic.MotionCritic` is a module; training it next to a data-parallel model asks for what the model's
own wrapper gives the model and nothing gives the critic (docs/few-step.md, "A critic in the trainer"):

* Its gradients are averaged over the ranks by hand, one all-reduce of one flat vector per step
  (:meth:`CriticTraining.reduce_gradients`); it is not wrapped in DistributedDataParallel, whose hooks would fire on
  the student's backward as well.
* Its update is applied or skipped with the model's (:meth:`CriticTraining.step`): on a host decision
  (``train.step_sync=every_step``), or on the device through fused Adam's ``found_inf`` (``deferred``), as the
  model's AdamW is.
* The student's term goes through the critic frozen and in eval mode (no gradient into the critic, no power
  iteration of its spectral norms), from the loss's own forward pass (``x1_hat``: a second forward of a
  data-parallel model before its backward is refused).
* Its weights and Adam state are one entry of the checkpoint's state (:meth:`state_dict`), restored on resume.

The critic's power iterations run once per micro-batch, in its own update's forward, and depend on its weights
only: every rank keeps the same ``u`` and ``v``.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import Any

import torch

from mfm.critic import MotionCritic, critic_hinge_loss, generator_hinge_loss
from mfm.model import ModelConfig
from pipeline.config import TrainLoopConfig
from pipeline.distributed import Dist

CRITIC_STATE_VERSION = 1


class CriticTraining:
    """The critic, its Adam, and the running sums of its losses that the log lines report."""

    def __init__(self, cfg: TrainLoopConfig, model_config: ModelConfig, dist: Dist, *, fused: bool) -> None:
        if dist.mixed_precision == "fp16":
            raise ValueError("train.critic_weight > 0 does not go with fp16 mixed precision (this run's accelerate "
                             "setting): the critic's own update is not loss-scaled; use bf16 or no")
        self.weight = cfg.critic_weight
        self.dist = dist
        action = model_config.is_action_model
        self.critic = MotionCritic(model_config.feature_dim, cond_dim=0 if action else model_config.cond_dim,
                                   num_actions=model_config.num_actions if action else 0,
                                   channels=cfg.critic_channels).to(dist.device)
        self.optimizer = torch.optim.Adam(self.critic.parameters(), lr=cfg.critic_lr, betas=cfg.critic_betas,
                                          fused=fused or None)
        # this rank's sums since the last log line: critic loss, the student's term (unweighted), micro-batches
        self._sums = torch.zeros(3, device=dist.device)

    @contextmanager
    def _frozen(self) -> Iterator[None]:
        was_training = self.critic.training
        params = list(self.critic.parameters())
        self.critic.eval()
        for p in params:
            p.requires_grad_(False)
        try:
            yield
        finally:
            for p in params:
                p.requires_grad_(True)
            self.critic.train(was_training)

    def student_loss(self, x1_hat: torch.Tensor, cond: torch.Tensor, frame_mask: torch.Tensor) -> torch.Tensor:
        """``critic_weight`` × the hinge loss of the model's motion ``x1_hat`` (in the graph) under the critic as
        it stands: its gradient reaches the model only."""
        with self._frozen():
            term = generator_hinge_loss(self.critic(x1_hat.float(), cond, frame_mask), frame_mask)
        self._sums[1] += term.detach()
        return self.weight * term

    def accumulate(self, real: torch.Tensor, fake: torch.Tensor, cond: torch.Tensor, frame_mask: torch.Tensor,
                   scale: float | torch.Tensor) -> torch.Tensor:
        """One micro-batch of the critic's update: its hinge loss on the batch's motions (``real``) against the
        model's (``fake``, detached), real and fake in one forward pass, backward into its gradients weighted by
        ``scale`` (the micro-batch's share of the step, as the model's loss is weighted). Returns the loss."""
        self.critic.train()
        logits = self.critic(torch.cat([real.float(), fake.detach().float()]), torch.cat([cond, cond]),
                             torch.cat([frame_mask, frame_mask]))
        real_logits, fake_logits = logits.chunk(2)
        loss = critic_hinge_loss(real_logits, fake_logits, frame_mask)
        (loss * scale).backward()
        self._sums[0] += loss.detach()
        self._sums[2] += 1
        return loss.detach()

    def reduce_gradients(self) -> torch.Tensor:
        """Average the critic's gradients over the ranks (one all-reduce of a flat vector; a parameter without a
        gradient on this rank counts as zeros) and return their global norm (a device tensor; non-finite when any
        rank's were)."""
        params = list(self.critic.parameters())
        flat = torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1) for p in params])
        if self.dist.world_size == 1:  # nothing to average: the gradients stay where they are
            return torch.linalg.vector_norm(flat)
        flat = self.dist.all_reduce_sum(flat) / self.dist.world_size  # a new tensor: the views below own it
        offset = 0
        for p in params:
            p.grad = flat[offset:offset + p.numel()].view_as(p)
            offset += p.numel()
        return torch.linalg.vector_norm(flat)

    def step(self, skip: bool | torch.Tensor) -> None:
        """Apply the critic's update unless ``skip`` (a host bool, or a device tensor that fused Adam takes as
        ``found_inf``: no update, its step count kept), then clear its gradients."""
        if isinstance(skip, torch.Tensor):
            self.optimizer.found_inf = skip.float()
            try:
                self.optimizer.step()
            finally:
                del self.optimizer.found_inf
        elif not skip:
            self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    def discard_gradients(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)

    def window_sums(self) -> torch.Tensor:
        """This rank's (critic loss, student's term, micro-batches) since the last call, and a reset."""
        sums, self._sums = self._sums, torch.zeros_like(self._sums)
        return sums

    def state_dict(self) -> dict[str, Any]:
        return {"version": CRITIC_STATE_VERSION, "critic": {k: v.detach().cpu() for k, v in
                                                            self.critic.state_dict().items()},
                "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        if state.get("version") != CRITIC_STATE_VERSION:
            raise ValueError(f"critic state version {state.get('version')!r}; this code reads {CRITIC_STATE_VERSION}")
        self.critic.load_state_dict(state["critic"])
        self.optimizer.load_state_dict(state["optimizer"])
