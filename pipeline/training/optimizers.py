"""The model's optimizer (``optim.optimizer``): AdamW, or Muon on the Transformer blocks' weight matrices with AdamW
on every other parameter.

Muon (Jordan et al. 2024, "Muon: an optimizer for hidden layers"; torch.optim.Muon) replaces each 2-D weight's
momentum by its nearest semi-orthogonal matrix (five Newton–Schulz iterations) before the update, so every direction
of the matrix moves at the same rate whatever its gradient's scale. It is meant for hidden layers only: the input
and output projections, embeddings, biases and norms keep AdamW, as in Jordan's and Moonshot's recipes. None of
MFM, FLAME or FlowMDM uses it (they train with AdamW); it is ours, for the CPU budget of the synthetic preset, where
the counts are learnt late (docs/generator-study.md, "Muon on the blocks' matrices").
"""

from __future__ import annotations

from typing import Any, Iterable

import torch

from pipeline.config import OptimConfig

MUON_SCOPE = "layers."
"""The parameters Muon trains: the 2-D weights of the Transformer's blocks (attention, cross-attention, feed-forward
and, with adaLN, its modulation), all under ``MotionFlowTransformer.layers``."""


def muon_parameter_names(model: torch.nn.Module) -> list[str]:
    """The names of ``model``'s parameters that Muon trains (2-D weights under :data:`MUON_SCOPE`); every other
    parameter is AdamW's."""
    return [name for name, p in model.named_parameters() if p.requires_grad and name.startswith(MUON_SCOPE)
            and p.ndim == 2]


class MuonWithAdamW(torch.optim.Optimizer):
    """torch.optim.Muon on some parameters and torch.optim.AdamW on the rest, as one optimizer: one list of
    parameter groups, so one learning-rate scheduler, one ``zero_grad`` and one ``step``.

    Each group keeps its own base learning rate (``lr`` for AdamW's, ``muon_lr`` for Muon's), which the scheduler
    scales by the same factor. AdamW's group comes first, so the rate a run logs (the scheduler's first) is
    ``lr``'s, as in an AdamW run. The state dict holds both optimizers' states under ``muon`` and ``adamw``; loading
    one written by plain AdamW is refused by the trainer before it gets here.
    """

    def __init__(self, muon_params: Iterable[torch.nn.Parameter], adamw_params: Iterable[torch.nn.Parameter], *,
                 lr: float, betas: tuple[float, float], weight_decay: float, muon_lr: float, muon_momentum: float,
                 fused: bool | None = None) -> None:
        muon_params, adamw_params = list(muon_params), list(adamw_params)
        if not muon_params or not adamw_params:
            raise ValueError("MuonWithAdamW needs parameters for both Muon and AdamW")
        # Keller Jordan's scaling (adjust_lr_fn "original", torch's default): the step of a fan_out × fan_in matrix
        # is muon_lr · sqrt(max(1, fan_out / fan_in)) times an orthogonal matrix, which with muon_lr 0.02 moves
        # a weight about as far per step as AdamW at 1e-3 does early in training.
        self.muon = torch.optim.Muon(muon_params, lr=muon_lr, weight_decay=weight_decay, momentum=muon_momentum,
                                     nesterov=True, adjust_lr_fn="original")
        self.adamw = torch.optim.AdamW(adamw_params, lr=lr, betas=betas, weight_decay=weight_decay, fused=fused)
        super().__init__(adamw_params + muon_params, {"lr": lr})
        self._link_groups()

    def _link_groups(self) -> None:
        """Make this optimizer's groups the two optimizers' own group dicts, so what the scheduler writes (``lr``)
        is what they read. Called again after loading a state: ``Optimizer.load_state_dict`` replaces the dicts."""
        self.param_groups[:] = self.adamw.param_groups + self.muon.param_groups

    @torch.no_grad()
    def step(self, closure: Any = None) -> None:
        if closure is not None:
            raise ValueError("MuonWithAdamW.step takes no closure")
        self.adamw.step()
        self.muon.step()

    def state_dict(self) -> dict[str, Any]:
        return {"adamw": self.adamw.state_dict(), "muon": self.muon.state_dict()}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        if set(state_dict) != {"muon", "adamw"}:
            raise ValueError("MuonWithAdamW.load_state_dict needs the state of a Muon run (keys 'muon' and 'adamw'), "
                             f"got keys {sorted(state_dict)}")
        self.adamw.load_state_dict(state_dict["adamw"])
        self.muon.load_state_dict(state_dict["muon"])
        self._link_groups()


def build_optimizer(model: torch.nn.Module, cfg: OptimConfig, fused: bool) -> torch.optim.Optimizer:
    """``model``'s optimizer by ``cfg.optimizer``: AdamW over every parameter, or :class:`MuonWithAdamW`.
    ``fused``: fused AdamW (CUDA, or ``train.step_sync=deferred``, which Muon does not take)."""
    if cfg.optimizer == "adamw":
        return torch.optim.AdamW(model.parameters(), lr=cfg.lr, betas=cfg.betas, weight_decay=cfg.weight_decay,
                                 fused=fused or None)
    by_muon = set(muon_parameter_names(model))
    named = list(model.named_parameters())
    return MuonWithAdamW([p for n, p in named if n in by_muon], [p for n, p in named if n not in by_muon],
                         lr=cfg.lr, betas=cfg.betas, weight_decay=cfg.weight_decay, muon_lr=cfg.muon_lr,
                         muon_momentum=cfg.muon_momentum, fused=fused or None)
