"""The one place that talks to accelerate and torch.distributed.

The trainer and evaluator see a :class:`Dist`: who am I (rank, world size, device), a few collectives, and the
thin accelerate hooks a training step needs (prepare, accumulate, backward, clip, autocast). One process on a CPU
is the same code path: every collective is then a local no-op that returns the value a 1-rank reduction would.

Launches that work (rank 0 decides, everyone is told):

* ``python launch/train.py`` or ``accelerate launch launch/train.py``: one process, CPU or one GPU.
* ``torchrun --standalone --nproc_per_node N launch/train.py``: N ranks; gloo on CPU, NCCL on GPUs.
* ``accelerate launch --config_file configs/accelerate/multi_gpu.yaml ...`` (or ``--multi_gpu``): N GPUs.
* Two CPU ranks through accelerate: ``ACCELERATE_USE_CPU=1 accelerate launch --multi_gpu --num_processes 2
  --num_machines 1 --mixed_precision no --dynamo_backend no ...`` (configs/accelerate/cpu_2ranks.yaml).

Launches that silently run fewer processes than asked are refused with :class:`LaunchError`: accelerate 1.15's
``accelerate launch --cpu --num_processes 2`` (and a ``MULTI_CPU`` config) start ONE process, and a plain
``Accelerator()`` under a multi-process launcher without a GPU starts independent single-process copies.
"""

from __future__ import annotations

import atexit
import contextlib
import functools
import logging
import os
import sys
import threading
from collections.abc import Callable, Mapping
from datetime import timedelta
from types import MethodType
from typing import Any, NoReturn, ParamSpec, TypeVar

import torch
import torch.distributed as torch_dist
from accelerate import Accelerator
from accelerate.state import AcceleratorState, GradientState
from accelerate.utils import (
    DistributedDataParallelKwargs,
    InitProcessGroupKwargs,
    convert_outputs_to_fp32,
)

logger = logging.getLogger(__name__)

T = TypeVar("T")

_MPI_WORLD_SIZE_VARS = ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE", "MV2_COMM_WORLD_SIZE")

CPU_TWO_RANK_RECIPE = (
    "ACCELERATE_USE_CPU=1 accelerate launch --multi_gpu --num_processes 2 --num_machines 1 "
    "--mixed_precision no --dynamo_backend no <script>  (or: torchrun --standalone --nproc_per_node 2 <script>)"
)


class LaunchError(RuntimeError):
    """The process was launched in a way that would silently train with the wrong number of ranks."""


def _flag(value: str | None) -> bool:
    return value is not None and value.strip().lower() in ("1", "true", "yes", "on")


def check_launch_environment(environ: Mapping[str, str]) -> None:
    """Refuse accelerate's silent single-process CPU launch before anything is initialised.

    ``accelerate launch --cpu --num_processes N`` (N > 1) and a ``MULTI_CPU`` config run the script once through
    the simple launcher: it exports ACCELERATE_USE_CPU and MASTER_ADDR (because N > 1) but no WORLD_SIZE/RANK,
    which every real multi-process launcher (torchrun, accelerate's multi-GPU launcher, mpirun) sets.
    """
    requested_multi_cpu = _flag(environ.get("ACCELERATE_USE_CPU")) and "MASTER_ADDR" in environ
    has_rank_info = "WORLD_SIZE" in environ or any(v in environ for v in _MPI_WORLD_SIZE_VARS)
    if requested_multi_cpu and not has_rank_info:
        raise LaunchError(
            "accelerate was asked for several CPU processes (ACCELERATE_USE_CPU and MASTER_ADDR are set) but started "
            "this script once, without WORLD_SIZE: accelerate 1.15's `--cpu --num_processes N` and MULTI_CPU configs "
            "run a single process. For N real CPU ranks use:\n  " + CPU_TWO_RANK_RECIPE + "\n"
            "For one process, drop --num_processes (and unset MASTER_ADDR)."
        )


def check_world_size(num_processes: int, environ: Mapping[str, str]) -> None:
    """Refuse a run whose process group is smaller than the launcher's WORLD_SIZE."""
    expected = environ.get("WORLD_SIZE")
    if expected is not None and int(expected) != num_processes:
        raise LaunchError(
            f"the launcher set WORLD_SIZE={expected} but accelerate initialised {num_processes} process(es): each "
            "rank would train alone on all of the data. On a CPU-only machine pass cpu=True / set "
            f"ACCELERATE_USE_CPU=1; for CPU ranks use:\n  {CPU_TWO_RANK_RECIPE}"
        )


class MixedPrecisionError(ValueError):
    """``accelerate launch --mixed_precision`` and ``train.mixed_precision`` disagree, or ask for what is not
    supported; the message says which setting to change."""


def cpu_has_native_bf16() -> bool:
    """Whether this CPU multiplies bf16 in hardware (x86 AVX512_BF16 or AMX tiles): there bf16 autocast runs a
    Linear's forward and backward about 2x as fast as fp32 (1.5x a whole training step of the synthetic preset on
    2 Zen 4 cores); elsewhere oneDNN emulates it, slower than fp32."""
    probes = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
    return any(getattr(torch.cpu, name, lambda: False)() for name in probes)


def resolve_mixed_precision(setting: str, launcher: str | None = None, *, loss_scaling: bool = False) -> str:
    """The autocast this run uses, from the config's ``train.mixed_precision`` and the launcher's
    ``ACCELERATE_MIXED_PRECISION`` (``accelerate launch --mixed_precision``): ``"no"``, ``"bf16"`` or ``"fp16"``.

    ``accelerate launch`` sets ``no`` when nothing is given, so ``no`` from the launcher is not a choice and never
    overrides the config. A launcher's ``bf16`` or ``fp16`` is: with ``auto`` it is honoured, against an explicit
    different setting it is refused. ``auto`` otherwise: bf16 on a CUDA device that supports it, else no autocast
    (never fp16 on its own: its overflow steps are skipped, so it is asked for by name). fp16 needs dynamic loss
    scaling (:class:`pipeline.training.loss_scaling.LossScaler`), which only the generator's trainer does: a program without
    it (``loss_scaling=False``) refuses fp16 rather than train with gradients that underflow to zero.
    """
    if setting not in ("no", "bf16", "fp16", "auto"):
        raise MixedPrecisionError(f"train.mixed_precision must be 'no', 'bf16', 'fp16' or 'auto', got {setting!r}")
    if launcher not in (None, "no", "bf16", "fp16"):
        raise MixedPrecisionError(f"accelerate launch --mixed_precision {launcher}: expected no, bf16 or fp16")
    if launcher in ("bf16", "fp16") and setting not in ("auto", launcher):
        raise MixedPrecisionError(
            f"accelerate launch --mixed_precision {launcher} disagrees with train.mixed_precision={setting}: pass "
            f"train.mixed_precision={launcher} (or auto, which follows the launcher), or launch without "
            "--mixed_precision")
    if setting != "auto":
        resolved = setting
    elif launcher in ("bf16", "fp16"):
        resolved = launcher
    else:
        resolved = "bf16" if torch.cuda.is_available() and torch.cuda.is_bf16_supported() else "no"
    if resolved == "fp16" and not loss_scaling:
        asked = "accelerate launch --mixed_precision fp16" if launcher == "fp16" else "mixed_precision=fp16"
        raise MixedPrecisionError(
            f"{asked}: this program has no fp16 loss scaling (only the generator's training, launch/train.py, "
            "has); use bf16 (GPUs since Ampere) or no")
    return resolved


class Dist:
    """This process's place in the run, collectives, and the accelerate hooks of a training step.

    Build one per process, before the model. ``cpu=None`` picks CPU (gloo between ranks) when no GPU is visible
    or ACCELERATE_USE_CPU is set. ``mixed_precision`` is the config's ``train.mixed_precision``, resolved with
    ``accelerate launch --mixed_precision`` by :func:`resolve_mixed_precision` (honoured, or refused when they
    disagree); ``loss_scaling=True`` says the caller scales its loss for fp16 (the trainer's
    :class:`pipeline.training.loss_scaling.LossScaler`), without it fp16 is refused.

    fp16 is done here, not by accelerate: accelerate's fp16 is CUDA-only (on a CPU it silently runs in fp32) and
    its prepared optimizer would step through its own GradScaler, deciding alone, per rank, whether a step is
    skipped. So accelerate is told ``no``, :meth:`prepare` wraps the model's forward in fp16 autocast (outputs in
    fp32, as accelerate does for bf16), :meth:`autocast` gives the same context, and the trainer owns the scaler.
    """

    def __init__(
        self,
        *,
        mixed_precision: str = "no",
        loss_scaling: bool = False,
        grad_accum: int = 1,
        cpu: bool | None = None,
        find_unused_parameters: bool = False,
        collective_timeout_s: float | None = None,
    ) -> None:
        environ = os.environ
        check_launch_environment(environ)
        if cpu is None:
            cpu = _flag(environ.get("ACCELERATE_USE_CPU")) or not torch.cuda.is_available()
        launcher_precision = environ.get("ACCELERATE_MIXED_PRECISION")
        self._mixed_precision = resolve_mixed_precision(mixed_precision, launcher_precision,
                                                        loss_scaling=loss_scaling)
        if launcher_precision == "no" and self._mixed_precision != "no":
            logger.info("accelerate's --mixed_precision no is also its default, so it does not turn %s off: "
                        "train.mixed_precision=no does", self._mixed_precision)
        handlers: list[Any] = [DistributedDataParallelKwargs(find_unused_parameters=find_unused_parameters)]
        if collective_timeout_s is not None:
            handlers.append(InitProcessGroupKwargs(timeout=timedelta(seconds=collective_timeout_s)))
        self._accelerator = Accelerator(
            cpu=cpu,
            # fp16 autocast and loss scaling are this module's and the trainer's (see the class docstring)
            mixed_precision="no" if self._mixed_precision == "fp16" else self._mixed_precision,
            gradient_accumulation_steps=grad_accum,
            kwargs_handlers=handlers,
            # The trainer steps its scheduler once per optimizer step; accelerate's default would step it
            # world_size times per call, silently shortening warm-up on N ranks.
            step_scheduler_with_optimizer=False,
        )
        check_world_size(self._accelerator.num_processes, environ)
        if self._mixed_precision == "bf16" and self.device.type == "cpu" and not cpu_has_native_bf16():
            logger.warning("bf16 autocast on a CPU without native bf16 dot products (AVX512_BF16 or AMX): its "
                           "matmuls are emulated and slower than fp32; train.mixed_precision=no is faster here")
        self._closed = False
        logger.debug(
            "rank %d/%d (local %d) on %s, mixed precision %s",
            self.rank,
            self.world_size,
            self.local_rank,
            self.device,
            self._mixed_precision,
        )

    # -- who am I --------------------------------------------------------------------------------------------

    @property
    def rank(self) -> int:
        return self._accelerator.process_index

    @property
    def world_size(self) -> int:
        return self._accelerator.num_processes

    @property
    def local_rank(self) -> int:
        return self._accelerator.local_process_index

    @property
    def device(self) -> torch.device:
        return self._accelerator.device

    @property
    def is_main(self) -> bool:
        """Global rank 0: the only process that writes checkpoints, logs and W&B."""
        return self._accelerator.is_main_process

    @property
    def is_local_main(self) -> bool:
        return self._accelerator.is_local_main_process

    @property
    def is_distributed(self) -> bool:
        return self.world_size > 1

    @property
    def mixed_precision(self) -> str:
        """The resolved setting: ``"no"``, ``"bf16"`` or ``"fp16"``."""
        return self._mixed_precision

    # -- training-step hooks (thin accelerate wrappers) -------------------------------------------------------

    def prepare(self, *objects: Any) -> Any:
        """Wrap model / optimizer / scheduler for the device, DDP and autocast (returns them in the same order).

        Never pass the training DataLoader: the streaming dataset shards itself by rank and worker, and
        accelerate would shard it again, silently dropping data (accelerate issue 3547).
        """
        for obj in objects:
            if isinstance(obj, torch.utils.data.DataLoader):
                raise TypeError(
                    "Dist.prepare() refuses DataLoaders: the streaming dataset shards itself by rank, and "
                    "accelerate.prepare() would shard it a second time and silently drop data"
                )
        if self._mixed_precision == "fp16":
            for obj in objects:
                if isinstance(obj, torch.nn.Module):
                    self._fp16_autocast_forward(obj)
        return self._accelerator.prepare(*objects)

    def _fp16_autocast_forward(self, model: torch.nn.Module) -> None:
        """Run ``model``'s forward under fp16 autocast with its outputs converted to fp32: what accelerate's
        prepare does for bf16 (the same wrapping, so :meth:`unwrap` keeps it and a deep copy of the module, e.g.
        the validation's EMA model, calls its own forward)."""
        model._original_forward = model.forward
        autocast = torch.autocast(device_type=self.device.type, dtype=torch.float16)
        forward = getattr(model.forward, "__func__", None)
        if forward is None:  # a forward that is not a bound method (e.g. torch.compile's)
            model.forward = convert_outputs_to_fp32(autocast(model.forward))
        else:
            model.forward = MethodType(convert_outputs_to_fp32(autocast(forward)), model)

    def accumulate(self, model: torch.nn.Module) -> contextlib.AbstractContextManager[None]:
        """Context for one micro-batch: gradients sync (and the prepared optimizer steps) every grad_accum calls."""
        return self._accelerator.accumulate(model)

    @property
    def sync_gradients(self) -> bool:
        """True inside the micro-batch that completes an optimizer step."""
        return self._accelerator.sync_gradients

    def no_sync(self, model: torch.nn.Module) -> contextlib.AbstractContextManager[None]:
        """Skip the DDP gradient all-reduce for this backward (manual accumulation)."""
        return self._accelerator.no_sync(model)

    def backward(self, loss: torch.Tensor) -> None:
        self._accelerator.backward(loss)

    def clip_grad_norm_(self, parameters: Any, max_norm: float) -> torch.Tensor:
        """Clip the global gradient norm; returns the norm before clipping (a device tensor, no host sync)."""
        return self._accelerator.clip_grad_norm_(parameters, max_norm)

    def autocast(self) -> contextlib.AbstractContextManager[None]:
        """Autocast for code outside the prepared model's forward (e.g. a loss), per the resolved precision."""
        if self._mixed_precision == "fp16":
            return torch.autocast(device_type=self.device.type, dtype=torch.float16)
        return self._accelerator.autocast()

    def unwrap(self, model: torch.nn.Module) -> torch.nn.Module:
        """The bare module under DDP / torch.compile wrappers: what gets saved (no ``_orig_mod.`` key prefix)."""
        return self._accelerator.unwrap_model(model, keep_torch_compile=False)

    def main_process_first(self) -> contextlib.AbstractContextManager[None]:
        """Rank 0 runs the block first (e.g. verifying shards), the others after it."""
        return self._accelerator.main_process_first()

    # -- collectives (every rank must call them, in the same order) -------------------------------------------

    def barrier(self) -> None:
        if self.is_distributed:
            self._accelerator.wait_for_everyone()

    def all_reduce_sum(self, tensor: torch.Tensor) -> torch.Tensor:
        return self._all_reduce(tensor, torch_dist.ReduceOp.SUM)

    def all_reduce_max(self, tensor: torch.Tensor) -> torch.Tensor:
        return self._all_reduce(tensor, torch_dist.ReduceOp.MAX)

    def all_reduce_min(self, tensor: torch.Tensor) -> torch.Tensor:
        return self._all_reduce(tensor, torch_dist.ReduceOp.MIN)

    def _all_reduce(self, tensor: torch.Tensor, op: torch_dist.ReduceOp) -> torch.Tensor:
        """A new tensor (same device and dtype as ``tensor``) holding the reduction; the input is untouched."""
        if not self.is_distributed:
            return tensor.detach().clone()
        # gloo has no bool reductions; int32 MAX/MIN/SUM give any/all/count.
        work_dtype = torch.int32 if tensor.dtype == torch.bool else tensor.dtype
        work = tensor.detach().to(device=self.device, dtype=work_dtype, copy=True)
        torch_dist.all_reduce(work, op=op)
        if tensor.dtype == torch.bool:
            work = work != 0
        return work.to(tensor.device)

    def any_across_ranks(self, flag: bool) -> bool:
        """True on every rank if ``flag`` is True on any rank (so all ranks take the same branch)."""
        return bool(self.all_reduce_max(torch.tensor(int(bool(flag)), device=self.device)).item())

    def all_across_ranks(self, flag: bool) -> bool:
        """True on every rank only if ``flag`` is True on every rank."""
        return bool(self.all_reduce_min(torch.tensor(int(bool(flag)), device=self.device)).item())

    def broadcast_object(self, obj: T, src: int = 0) -> T:
        """Rank ``src``'s (picklable) ``obj`` on every rank; the others' argument is ignored."""
        if not self.is_distributed:
            return obj
        box = [obj if self.rank == src else None]
        torch_dist.broadcast_object_list(box, src=src, device=self.device)
        return box[0]  # type: ignore[return-value]

    def all_gather_object(self, obj: T) -> list[T]:
        """Every rank's (picklable) ``obj``, indexed by rank, on every rank."""
        if not self.is_distributed:
            return [obj]
        gathered: list[Any] = [None] * self.world_size
        torch_dist.all_gather_object(gathered, obj)
        return gathered

    def gather_tensor(self, tensor: torch.Tensor) -> torch.Tensor:
        """Every rank's ``tensor`` concatenated along dim 0 in rank order, on every rank (on ``tensor``'s device).

        Ranks may hold different numbers of rows (an evaluation set that does not divide evenly): nothing is
        padded or duplicated in the result. Trailing dimensions and dtype must agree on all ranks.
        """
        if tensor.dim() == 0:
            raise ValueError("gather_tensor needs a tensor with a leading dimension, got a scalar")
        if not self.is_distributed:
            return tensor.detach().clone()
        # gloo cannot all_gather bool tensors: ship masks as uint8.
        work = tensor.detach().to(self.device, dtype=torch.uint8 if tensor.dtype == torch.bool else None)
        work = work.contiguous()
        layouts = self.all_gather_object((tuple(work.shape), str(work.dtype)))
        trailing = {(shape[1:], dtype) for shape, dtype in layouts}
        if len(trailing) != 1:  # every rank sees the same list, so every rank raises: no hang
            raise ValueError(f"gather_tensor: ranks disagree on trailing shape/dtype: {layouts}")
        rows = [shape[0] for shape, _ in layouts]
        padded = work.new_zeros((max(rows), *work.shape[1:]))
        padded[: work.shape[0]] = work
        buffers = [torch.empty_like(padded) for _ in range(self.world_size)]
        torch_dist.all_gather(buffers, padded)
        gathered = torch.cat([buf[:n] for buf, n in zip(buffers, rows, strict=True)])
        return gathered.to(tensor.device, dtype=tensor.dtype)

    # -- output on the main process only ------------------------------------------------------------------------

    def log0(self, msg: str, *args: Any, level: int = logging.INFO, log: logging.Logger | None = None) -> None:
        """Log on global rank 0 only (through ``log``, default this module's logger)."""
        if self.is_main:
            (log or logger).log(level, msg, *args)

    def print0(self, *args: Any, **kwargs: Any) -> None:
        """print() on global rank 0 only: for entry points' user-facing output; library code uses log0."""
        if self.is_main:
            print(*args, flush=True, **kwargs)

    # -- teardown -----------------------------------------------------------------------------------------------

    def close(self, *, wait_for_all: bool = True) -> None:
        """Destroy the process group and forget accelerate's process-wide state, so a new Dist can be built.

        ``wait_for_all``: first a barrier, so that no rank tears its process group down while another is still
        in its last steps (without it, 1 of 8 two-rank CPU runs of the accelerate end-to-end test ended with a rank
        aborting at teardown: "terminate called without an active exception"). Leaving with an exception skips
        it: the other ranks may never get there."""
        if self._closed:
            return
        self._closed = True
        if wait_for_all and self.world_size > 1:
            self.barrier()
        if self.world_size > 1:
            global _closed_a_multi_rank_group
            _closed_a_multi_rank_group = True
        self._accelerator.end_training()
        # accelerate keeps its state in process-wide singletons; a second Accelerator with other settings (a test,
        # or evaluation after training in one process) would otherwise raise or inherit the old settings.
        AcceleratorState._reset_state(reset_partial_state=True)
        GradientState._reset_state()

    def __enter__(self) -> Dist:
        return self

    def __exit__(self, exc_type: object, *exc_info: object) -> None:
        self.close(wait_for_all=exc_type is None)


# -- ending a rank's process ------------------------------------------------------------------------------------

_closed_a_multi_rank_group = False  # set by Dist.close: this process was one rank of several

P = ParamSpec("P")


def ends_rank_processes(main: Callable[P, int]) -> Callable[P, int]:
    """Decorate an entry point's ``main`` (which returns an exit code and builds its ``Dist`` inside): when the
    process was one rank of several, it ends right there with that code, through ``exit_without_native_teardown``.
    A single process (every in-process test, a one-rank run) returns the code as before.

    Why: DistributedDataParallel keeps its process group, and gloo's worker and socket threads, alive past
    ``destroy_process_group`` (torch 2.14: ``tests/test_rank_exit.py`` shows it), so they are torn down during
    interpreter finalization and the C++ static destructors, while those threads still run. Rarely, a rank then
    aborts there with "terminate called without an active exception" and the launcher reports the whole job
    failed: CI on 2026-12-05, a two-rank fp16 test whose training, checkpoint and final barrier had all completed
    (170 local runs of that test, 90 of them three at a time on 2 cores, did not reproduce it)."""

    @functools.wraps(main)
    def run(*args: P.args, **kwargs: P.kwargs) -> int:
        code = main(*args, **kwargs)
        if _closed_a_multi_rank_group:
            exit_without_native_teardown(code)
        return code

    return run


def exit_without_native_teardown(code: int) -> NoReturn:
    """End the process as a normal exit would up to its atexit handlers (non-daemon threads joined; logging,
    tensorboard writers, temporary folders closed by their handlers; stdout and stderr flushed), then
    ``os._exit(code)``: without interpreter finalization or C++ static destructors, where the process group's
    leaked threads would be torn down (``ends_rank_processes``)."""
    for thread in threading.enumerate():
        if thread is not threading.main_thread() and not thread.daemon:
            thread.join()
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):  # a closed or broken pipe must not change the exit code
            stream.flush()
    os._exit(code)
