"""Model FLOPs and model FLOPs utilisation (MFU), for the training log (``pipeline.training``) and the speed suite
(``benchmarks/gpu_suite.py``).

MFU, as PaLM defines it: the model's FLOPs for the samples trained, per second, over the device's peak. The model's
FLOPs are one forward and one backward pass of the generator over each sample, 3 × the forward pass's (the backward
pass computes gradients for the inputs and for the weights, two forward passes' worth). Work a recipe adds on top
(a critic's passes, a student's own-path states, self-conditioning's first pass, a shortcut model's targets) is not
model FLOPs and is not counted, so MFU is the useful share, not the hardware's busy share.

The forward pass is counted, not modelled: :func:`forward_flops` runs it once per shape under torch's
``FlopCounterMode`` with the math attention kernel, so QKᵀ and AV count as the matmuls they are, and every variant
(cross-attention to caption tokens, grouped frames, adaptive norms, ...) is counted as it is built. For MFM's
architecture the count is the closed form ``docs/performance.md`` gives (22.06 GFLOP per 196-frame sample of the
HumanML3D preset; ``tests/test_flops.py`` holds the two equal). Padded frames are computed, so they are counted;
the training log gives their share beside it (``padding_frac``).

The peak is the device's dense bf16 tensor rate (:data:`DENSE_BF16_PEAKS`, no 2:4 sparsity), also for an fp32 step,
as ``../shared/docs/performance-anchors.md`` rates both, so the two compare directly. A CPU, or a GPU not in the
table, has no peak: MFU is then None, with the reason (:func:`dense_bf16_peak`).
"""

from __future__ import annotations

import dataclasses
import re

import torch
from torch.nn.attention import SDPBackend, sdpa_kernel
from torch.utils.flop_counter import FlopCounterMode

BACKWARD_FACTOR = 3.0
"""Forward + backward FLOPs over the forward pass's: the backward pass costs two forward passes."""


@dataclasses.dataclass(frozen=True)
class DevicePeak:
    """Dense bf16 tensor-core throughput of one GPU model (no 2:4 structured sparsity), TFLOP/s, and its source.

    ``pattern`` is searched case-insensitively in ``torch.cuda.get_device_name()``; the first matching row wins,
    so more specific rows come first. ``tflops`` None: a known device whose figure is not tabulated here."""

    name: str
    pattern: str
    tflops: float | None
    source: str


DENSE_BF16_PEAKS: tuple[DevicePeak, ...] = (
    DevicePeak("H100 PCIe", r"h100.*pcie", 756.0,
               "NVIDIA H100 Tensor Core GPU datasheet: BF16 Tensor Core 1,513 TFLOPS (PCIe) with sparsity; "
               "dense is half, 756"),
    DevicePeak("H100 NVL", r"h100.*nvl", None,
               "not tabulated here (an H100 NVL's dense bf16 rate differs from both SXM and PCIe): MFU not reported"),
    DevicePeak("H100 SXM", r"h100", 989.4,
               "NVIDIA H100 Tensor Core GPU datasheet: BF16 Tensor Core 1,979 TFLOPS (SXM) with sparsity; dense "
               "989.4 (H100 architecture whitepaper)"),
    DevicePeak("H200 NVL", r"h200.*nvl", None,
               "not tabulated here (the H200 NVL's dense bf16 rate is below the SXM's): MFU not reported"),
    DevicePeak("H200", r"h200", 989.4,
               "NVIDIA H200 Tensor Core GPU datasheet: BF16 Tensor Core 1,979 TFLOPS with sparsity (the H100 SXM's "
               "compute); dense 989.4"),
    DevicePeak("A100", r"a100", 312.0,
               "NVIDIA A100 Tensor Core GPU datasheet: BF16 Tensor Core 312 TFLOPS dense (624 with sparsity)"),
    DevicePeak("L4", r"\bl4\b", 121.0,
               "NVIDIA L4 Tensor Core GPU datasheet: BF16 Tensor Core 242 TFLOPS with sparsity; dense is half, 121"),
    DevicePeak("RTX 4090", r"rtx 4090", 165.2,
               "NVIDIA Ada Lovelace GPU architecture whitepaper, GeForce RTX 4090: peak BF16 Tensor TFLOPS with FP32 "
               "accumulate 165.2 dense (330.4 with sparsity)"),
)


@dataclasses.dataclass(frozen=True)
class PeakLookup:
    """The device's dense bf16 peak (None when unknown) and why: the table row's source, or the reason for none."""

    tflops: float | None
    source: str


def dense_bf16_peak(device_type: str, device_name: str) -> PeakLookup:
    """Look the device up in :data:`DENSE_BF16_PEAKS`. CPUs get none: their bf16 rate depends on the core count,
    clock and ISA (AVX-512 BF16, AMX) of the exact part and no single figure is published for this use."""
    if device_type != "cuda":
        return PeakLookup(None, "CPU: no dense bf16 peak is tabulated (it depends on the part's cores, clock and "
                                "AVX-512/AMX units), so MFU is reported as null")
    for row in DENSE_BF16_PEAKS:
        if re.search(row.pattern, device_name, flags=re.IGNORECASE):
            return PeakLookup(row.tflops, f"{row.name}: {row.source}")
    return PeakLookup(None, f"{device_name!r} is not in the dense bf16 peak table: MFU not reported")


def device_peak(device: torch.device | str) -> PeakLookup:
    """:func:`dense_bf16_peak` of a torch device (a CUDA device by its name)."""
    device = torch.device(device)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else device.type
    return dense_bf16_peak(device.type, name)


@torch.no_grad()
def forward_flops(model: torch.nn.Module, frames: int, *, text_tokens: int = 0) -> int:
    """FLOPs of one forward pass of ``model`` (an :class:`mfm.model.MotionFlowTransformer`, unwrapped) over one
    sample of ``frames`` valid frames and, for a cross-attention model, ``text_tokens`` caption tokens, counted by
    ``FlopCounterMode`` with math attention, in eval mode (every block runs, nothing is drawn). The model's mode, its
    weights and every random generator are left as they were."""
    config = model.config
    if config.conditioning == "cross_attention" and text_tokens < 1:
        raise ValueError("a cross-attention model's FLOPs depend on the caption's tokens: give text_tokens >= 1")
    parameter = next(model.parameters())
    device, dtype = parameter.device, parameter.dtype
    x = torch.zeros(1, frames, config.feature_dim, device=device, dtype=dtype)
    cond = (torch.zeros(1, dtype=torch.long, device=device) if config.is_action_model
            else torch.zeros(1, config.cond_dim, device=device, dtype=dtype))
    inputs = {}
    if config.conditioning == "cross_attention":
        inputs = {"text_tokens": torch.zeros(1, text_tokens, config.text_token_dim, device=device, dtype=dtype),
                  "text_token_len": torch.full((1,), text_tokens, dtype=torch.long, device=device)}
    was_training = model.training
    model.eval()
    try:
        with sdpa_kernel(SDPBackend.MATH), FlopCounterMode(display=False) as counter:
            model(x, torch.full((1,), 0.5, device=device), cond, torch.full((1,), frames, device=device), **inputs)
    finally:
        model.train(was_training)
    return int(counter.get_total_flops())


class TrainingFlops:
    """Model FLOPs of training ``model`` on one sample (:data:`BACKWARD_FACTOR` × :func:`forward_flops`), counted
    once per (frames, caption tokens) and kept: a length-aware run meets a dozen widths."""

    def __init__(self, model: torch.nn.Module) -> None:
        self.model = model
        self._per_sample: dict[tuple[int, int], float] = {}

    def per_sample(self, frames: int, text_tokens: int = 0) -> float:
        key = (int(frames), int(text_tokens))
        if key not in self._per_sample:
            self._per_sample[key] = BACKWARD_FACTOR * forward_flops(self.model, key[0], text_tokens=key[1])
        return self._per_sample[key]


def model_flops_utilisation(flops_per_s: float, peak_tflops: float | None) -> float | None:
    """Achieved model FLOP/s of one device over its dense bf16 peak; None without a peak."""
    if peak_tflops is None:
        return None
    return flops_per_s / (peak_tflops * 1e12)
