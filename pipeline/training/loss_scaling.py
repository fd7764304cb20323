"""Dynamic loss scaling for fp16 training: ``torch.amp.GradScaler`` with its skip decision taken by all ranks.

fp16 has 5 exponent bits: small gradients underflow to zero unless the loss is multiplied by a large scale before
the backward pass (and the gradients divided by it again before they are used). The right scale is found at run
time: an overflow (an inf or NaN in the scaled gradients) means the scale was too large, so that step's update is
skipped and the scale halved; after ``growth_interval`` updates without one it doubles. That is GradScaler's job;
this wrapper changes who decides.

GradScaler decides per process: ``scaler.step(optimizer)`` skips the update if THIS rank found an inf. It has no
collective (only FSDP's ShardedGradScaler all-reduces its ``found_inf``). Under DDP the gradients are all-reduced
before they are unscaled, so an inf that arises in any rank's backward normally reaches every rank, but nothing
guarantees it (a gradient changed after the all-reduce, a parameter outside DDP's buckets), and one rank stepping
while another skips would make their weights diverge silently. So here the trainer takes the decision:

1. ``scale(loss)`` before each backward; after the last one, ``unscale_(optimizer)`` divides the gradients by
   the scale and returns this rank's overflow flag (a device tensor: no host sync);
2. the trainer all-reduces that flag in the one flag all-reduce it already makes per step (with its non-finite,
   signal and sample-count flags: no extra collective) and decides for every rank alike;
3. :meth:`LossScaler.update` applies that shared verdict: the scale backs off on every rank if any rank
   overflowed, else the update happened and the growth tracker advances; :meth:`LossScaler.keep` leaves scale and
   tracker as they are for a step that made no update for another reason (a non-finite loss, no sample).

The optimizer is stepped by the trainer itself (never ``scaler.step``), only when the verdict allows it.

A disabled scaler (precision no or bf16) is the identity: ``scale`` returns the loss, the overflow flag is 0 and
update/keep do nothing, so the trainer has one code path.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch


class LossScaler:
    """The trainer's loss scaler (see the module docstring). ``enabled`` only for fp16."""

    def __init__(self, device: torch.device, *, enabled: bool, init_scale: float = 2.0**16,
                 growth_interval: int = 2000) -> None:
        self.device = torch.device(device)
        self._scaler = torch.amp.GradScaler(self.device.type, init_scale=init_scale,
                                            growth_interval=growth_interval, enabled=enabled)
        self._unscaled = False

    @property
    def enabled(self) -> bool:
        return self._scaler.is_enabled()

    def scale(self, loss: torch.Tensor) -> torch.Tensor:
        """``loss`` times the current scale, to call backward on (``loss`` itself when disabled)."""
        return self._scaler.scale(loss)

    def unscale_(self, optimizer: torch.optim.Optimizer) -> torch.Tensor:
        """Divide ``optimizer``'s gradients by the scale, in place, once per step after the last backward; returns
        THIS rank's overflow flag: a 0-dim float32 tensor on the device, > 0 if any gradient is inf or NaN (always
        0 when disabled). The trainer shares it across ranks before it calls :meth:`update`."""
        if not self.enabled:
            return torch.zeros((), device=self.device)
        self._scaler.unscale_(optimizer)
        self._unscaled = True
        total = torch.zeros((), device=self.device)
        for flag in self._found_inf_tensors():
            total = total + flag.to(self.device, torch.float32)
        return total

    def update(self, overflow: bool) -> None:
        """End a step that the trainer decided on for every rank: ``overflow`` (on ANY rank: the update was skipped)
        backs the scale off and resets the growth tracker, otherwise (the update happened) the tracker advances and
        the scale grows after ``growth_interval`` such steps. The same verdict on every rank keeps their scalers
        identical."""
        if not self.enabled:
            return
        self._require_unscaled("update")
        # GradScaler.update reads the found_inf tensors unscale_ recorded; this rank's own may say 0 where another
        # rank overflowed: write the shared verdict into them (ShardedGradScaler all-reduces these same tensors in
        # place, with a collective of its own).
        flags = self._found_inf_tensors()
        for flag in flags:
            flag.fill_(1.0 if overflow else 0.0)
        if flags:
            self._scaler.update()
        else:  # no parameter had a gradient: nothing was unscaled, nothing can have overflowed
            self._scaler.update(new_scale=self._scaler.get_scale())
        self._unscaled = False

    def keep(self) -> None:
        """End a step that made no update for another reason than an overflow (a non-finite loss, no sample on any
        rank): scale and growth tracker stay as they were (the forward pass, not the loss scale, was the problem)."""
        if not self.enabled:
            return
        self._require_unscaled("keep")
        self._scaler.update(new_scale=self._scaler.get_scale())
        self._unscaled = False

    def get_scale(self) -> float:
        """The current scale (a host sync; 1.0 when disabled)."""
        return self._scaler.get_scale()

    def state_dict(self) -> dict[str, Any] | None:
        """``{"scale", "growth_tracker"}`` (plain Python values, for the checkpoint's state.pt), None when disabled.
        The factors and the growth interval are settings: they come from the config on resume."""
        if not self.enabled:
            return None
        state = self._scaler.state_dict()
        return {"scale": float(state["scale"]), "growth_tracker": int(state["_growth_tracker"])}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore :meth:`state_dict` (scale and growth tracker; the settings stay this run's)."""
        if not self.enabled:
            return
        current = self._scaler.state_dict()
        self._scaler.load_state_dict({**current, "scale": float(state["scale"]),
                                      "_growth_tracker": int(state["growth_tracker"])})

    def _found_inf_tensors(self) -> list[torch.Tensor]:
        # GradScaler's per-optimizer record of what unscale_ found (one tensor per device), the tensors its update()
        # sums; the same internals torch's FSDP ShardedGradScaler works on.
        return [flag for state in self._scaler._per_optimizer_states.values()
                for flag in state["found_inf_per_device"].values()]

    def _require_unscaled(self, what: str) -> None:
        if not self._unscaled:
            raise RuntimeError(f"LossScaler.{what}() before unscale_(): every step unscales its gradients once")
