"""Classifier-free guidance as one batched model pass (shared by the flow-matching solvers and the diffusion
samplers): the conditional and unconditional halves run as a single forward of size 2B, the condition is encoded
once by the caller and never re-encoded, and scale 1 / 0 need only one half.

Precision (:data:`SAMPLING_PRECISIONS`): ``fp32`` runs the model as it is; ``bf16`` runs each forward pass under
``torch.autocast`` with bfloat16 on the input's device (CPU or CUDA) and hands back its output as fp32
(:class:`AutocastForward`), so the guidance mix, the ODE state and every solver or sampler update stay fp32: only
the network's matmuls and attention run in bf16. :func:`resolve_precision` turns a setting (``auto`` included) into
the precision a device runs.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from mfm.layout import FeatureLayout
from mfm.skeleton import Skeleton

SAMPLING_PRECISIONS = ("fp32", "bf16")
"""The arithmetic of a sampler's model passes: fp32, or bf16 autocast (the state and the solver stay fp32)."""
PRECISION_SETTINGS = ("auto", *SAMPLING_PRECISIONS)
"""What a user may ask for: ``auto`` = bf16 on a CUDA device that supports it, fp32 elsewhere (CPU included)."""


class AutocastForward:
    """``model`` with every forward pass under ``torch.autocast(dtype)`` on the input's device and its output
    converted to fp32: the caller's arithmetic (guidance mix, solver) never sees the low precision. Callable with
    the model's own signature."""

    def __init__(self, model: Callable[..., Tensor], dtype: torch.dtype = torch.bfloat16) -> None:
        self.model = model
        self.dtype = dtype

    def __call__(self, x: Tensor, t: Tensor, *args, **kwargs) -> Tensor:
        with torch.autocast(device_type=x.device.type, dtype=self.dtype):
            out = self.model(x, t, *args, **kwargs)
        return out.float()


def in_precision(model: Callable[..., Tensor], precision: str) -> Callable[..., Tensor]:
    """``model`` itself for ``fp32``; wrapped in :class:`AutocastForward` (bf16) for ``bf16``."""
    if precision == "fp32":
        return model
    if precision == "bf16":
        return AutocastForward(model, torch.bfloat16)
    raise ValueError(f"precision must be one of {list(SAMPLING_PRECISIONS)}, got {precision!r}")


def resolve_precision(setting: str, device: torch.device | str) -> str:
    """The precision ``setting`` means on ``device``: ``auto`` is bf16 on a CUDA device with native bf16 (Ampere and
    later) and fp32 anywhere else; ``fp32`` is fp32; ``bf16`` is bf16 where autocast supports it (CPU, and CUDA
    devices with bf16), else a ValueError saying why."""
    if setting not in PRECISION_SETTINGS:
        raise ValueError(f"precision must be one of {list(PRECISION_SETTINGS)}, got {setting!r}")
    device = torch.device(device)
    # native bf16 only: an older GPU emulates it, slower than fp32
    cuda_bf16 = (device.type == "cuda" and torch.cuda.is_available()
                 and torch.cuda.is_bf16_supported(including_emulation=False))
    if setting == "auto":
        return "bf16" if cuda_bf16 else "fp32"
    if setting == "bf16" and not (device.type == "cpu" or cuda_bf16):
        raise ValueError(f"precision bf16: autocast has no bf16 on device {str(device)!r} (it runs on cpu and on CUDA "
                         "GPUs with native bf16); use fp32 or auto")
    return setting


class PassLengths:
    """A batch's valid lengths as each model pass should get them: None when every motion fills the pass's window.

    A model given lengths builds a key-padding mask, and any attention mask keeps
    ``F.scaled_dot_product_attention`` off the flash kernels on a GPU. With lengths None the model attends over
    the whole window unmasked, which is the same arithmetic when no frame is padding: bit-identical on CPU
    (``tests/test_solvers.py -k window``), within a kernel's rounding on a GPU. One motion always fills its window,
    because the pipeline samples each batch in a window of its longest length. The shortest length is read to the
    host once, when the sampler is built, not at every pass (a CUDA-graphed pass must not wait on the device)."""

    def __init__(self, lengths: Tensor | None) -> None:
        self.lengths = lengths
        self.shortest = None if lengths is None else int(lengths.min())

    def for_window(self, num_frames: int) -> Tensor | None:
        """The lengths for a pass over ``num_frames`` frames: None when no motion is shorter than the window."""
        if self.shortest is None or self.shortest >= num_frames:
            return None
        return self.lengths


def classifier_free_guidance(
    model: Callable[..., Tensor],
    cond: Tensor,
    *,
    scale: float,
    lengths: Tensor | None = None,
    null_cond: Tensor | None = None,
    guided_channels: int | None = None,
    conditional_channels: Tensor | None = None,
    precision: str = "fp32",
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
    precision: the model passes' arithmetic (:data:`SAMPLING_PRECISIONS`); the output and the mix are fp32 either way.
    A pass whose window no motion is shorter than gets no lengths (:class:`PassLengths`): the unmasked kernels.
    """
    model = in_precision(model, precision)
    batch = cond.shape[0]
    uncond = cond if null_cond is None else null_cond.to(cond.device, cond.dtype).expand_as(cond)
    keep = torch.zeros(batch, dtype=torch.bool, device=cond.device)
    drop = torch.ones(batch, dtype=torch.bool, device=cond.device)

    if conditional_channels is not None:
        conditional_channels = conditional_channels.to(device=cond.device, dtype=torch.bool)
        if not bool(conditional_channels.any()):
            conditional_channels = None
    if scale == 1.0:
        single = PassLengths(lengths)
        return lambda x, t: model(x, t, cond, single.for_window(x.shape[1]), cond_mask=keep)
    if scale == 0.0:
        single = PassLengths(lengths)
        return lambda x, t: model(x, t, uncond, single.for_window(x.shape[1]), cond_mask=drop)

    both_cond = torch.cat([cond, uncond])
    both_mask = torch.cat([keep, drop])
    both_lengths = PassLengths(None if lengths is None else torch.cat([lengths, lengths]))

    def guided(x: Tensor, t: Tensor) -> Tensor:
        out_cond, out_uncond = model(torch.cat([x, x]), torch.cat([t, t]), both_cond,
                                     both_lengths.for_window(x.shape[1]), cond_mask=both_mask).chunk(2)
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
