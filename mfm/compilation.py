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


TRAINING_COMPILE_MODES = ("default", "reduce-overhead", "max-autotune-no-cudagraphs")
"""torch.compile modes a training run may ask for (``train.compile_mode``)."""


def compiled_for_training(model: torch.nn.Module, mode: str = "default", *,
                          batch_widths: int | None = None) -> torch.nn.Module:
    """``torch.compile`` of the training model in ``mode``.

    ``batch_widths``: how many distinct batch widths the run feeds (length-aware batches: one per multiple of
    ``data.pad_multiple`` up to the window), or None for one width (fixed windows). With several, each width gets
    its own static graph (``dynamic=False``) and dynamo's recompile limit is raised to hold them, in training and in
    eval mode (validation), plus the stand-in's: left to itself, torch.compile turns the width symbolic at the
    second width, and that graph's backward failed on an H200 (PyTorch 2.11: "shape '[1544, 512]' is invalid for
    input of size 8" in inductor's reduction over a symbolic size). Each width then compiles once, on first sight.
    """
    if mode not in TRAINING_COMPILE_MODES:
        raise ValueError(f"training compile mode must be one of {TRAINING_COMPILE_MODES}, got {mode!r}")
    if batch_widths is None:
        return torch.compile(model, mode=mode)
    if batch_widths < 1:
        raise ValueError(f"batch_widths must be >= 1, got {batch_widths!r}")
    import torch._dynamo.config as dynamo_config  # torch's own knob; there is no public API for the limit

    dynamo_config.recompile_limit = max(dynamo_config.recompile_limit, 2 * batch_widths + 4)
    return torch.compile(model, mode=mode, dynamic=False)


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
