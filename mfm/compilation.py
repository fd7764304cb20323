"""When and how the model is ``torch.compile``-d: one rule for training (``train.compile``) and sampling
(``compile`` of a sample request, ``sampling.compile`` of the evaluator, ``MotionPipeline(compile=)``).

``auto`` compiles on a CUDA device only: there it pays (docs/performance.md), on CPU inductor spends minutes
compiling for little. For sampling, CUDA gets ``mode="reduce-overhead"`` (CUDA graphs: a fixed-step solver calls the
model with the same shapes every step, so the launch overhead of the one-motion path disappears after the first
call); elsewhere the default mode.
"""

from __future__ import annotations

import torch

COMPILE_SETTINGS = ("auto", True, False)
"""What a compile setting may be: auto (on CUDA only), True (always), False (never)."""


def compiles(setting: bool | str, device: torch.device | str) -> bool:
    """Whether the compile ``setting`` compiles the model on ``device`` (auto: on CUDA only)."""
    if setting not in COMPILE_SETTINGS or not isinstance(setting, (bool, str)):
        raise ValueError(f"compile must be auto, true or false, got {setting!r}")
    return torch.device(device).type == "cuda" if setting == "auto" else bool(setting)


def sampling_compile_mode(device: torch.device | str) -> str:
    """``torch.compile``'s mode for sampling on ``device``: reduce-overhead (CUDA graphs) on CUDA, else default."""
    return "reduce-overhead" if torch.device(device).type == "cuda" else "default"


class OwnOutputs(torch.nn.Module):
    """A CUDA-graphed model whose every output is copied out of the graph's memory: a replay overwrites the previous
    replay's outputs, and a multi-stage solver (midpoint, RK4), an unguided pass (scale 0 or 1) or an edit may still
    hold them. One copy of a (B, T, D) output per pass."""

    def __init__(self, graphed: torch.nn.Module) -> None:
        super().__init__()
        self.graphed = graphed
        # A new Module starts in training mode; the wrapper takes the wrapped model's, or every sampler call warns
        # "sampling from a model in training mode" (seen on an H200 in benchmarks/gpu_suite.py).
        self.train(graphed.training)

    def forward(self, *args, **kwargs) -> torch.Tensor:
        return self.graphed(*args, **kwargs).clone()


def compiled_for_sampling(model: torch.nn.Module, device: torch.device | str) -> torch.nn.Module:
    """``torch.compile`` of ``model`` in :func:`sampling_compile_mode` (on CUDA, :class:`OwnOutputs`); the first call
    compiles (lazily), so build it once and reuse it across batches."""
    mode = sampling_compile_mode(device)
    compiled = torch.compile(model, mode=mode)
    return OwnOutputs(compiled) if mode == "reduce-overhead" else compiled
