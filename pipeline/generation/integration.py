"""How a request's checkpoint is integrated: the checkpoint loaded on the request's device, the ODE solver (flow)
or diffusion sampler with its steps (:class:`Integrator`), and each sample's noise seed; shared by sampling,
editing and composition."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import torch

from mfm.diffusion import DenoisedRange, GaussianDiffusion
from mfm.diffusion_sampling import SAMPLERS
from mfm.guidance import resolve_precision
from mfm.solvers import step_grid
from pipeline import checkpoint as ckpt
from pipeline.generation.inference import TrainedModel, load_trained_model
from pipeline.generation.request import (
    DEFAULT_DIFFUSION_SAMPLER,
    DEFAULT_FLOW_SOLVER,
    SampleRequest,
    SamplingError,
    known_solvers,
)


@dataclasses.dataclass(frozen=True)
class Integrator:
    """How a request integrates its checkpoint: an ODE solver (flow) or a diffusion sampler, with its steps, and the
    precision its model passes run in."""

    objective: str  # "flow" or "diffusion"
    name: str  # the solver (flow) or sampler (diffusion: "ddpm" / "ddim")
    steps: int
    diffusion: GaussianDiffusion | None = None  # diffusion: the training process respaced to ``steps``
    clip_denoised: DenoisedRange | None = None  # diffusion: the bounds of every step's x0 estimate (FLAME's clamp)
    precision: str = "fp32"  # the request's precision setting resolved on the model's device: "fp32" or "bf16"
    step_size: float | None = None  # a shortcut model's step size d (mfm.shortcut.sampler_step_size); None: a flow model
    grid: tuple[float, ...] | None = None  # flow: the model's own time grid at these steps (step_grid); None: uniform

    def record(self, trained: TrainedModel) -> dict[str, Any]:
        """results.json's description of the objective and sampler."""
        info: dict[str, Any] = {"objective": self.objective, "sampler": self.name, "solver": self.name,
                                "steps": self.steps, "precision": self.precision}
        if self.step_size is not None:
            info["shortcut_step_size"] = self.step_size
        if self.grid is not None:
            info["grid"] = list(self.grid)
        if self.diffusion is not None:
            process = trained.diffusion
            info["diffusion"] = {"preset": trained.diffusion_preset, "train_steps": process.num_train_steps,
                                 "schedule": process.schedule, "prediction": process.prediction,
                                 "learn_sigma": process.learn_sigma,
                                 "model_steps": self.diffusion.timestep_map.tolist()}  # the training steps visited
            if self.name == "ddim":
                info["diffusion"]["eta"] = 0.0
        return info

def load_for_request(request: SampleRequest) -> TrainedModel:
    """The request's checkpoint on its device (a checkpoint that cannot be loaded, e.g. a damaged state.pt, and a
    device this machine does not have are a SamplingError: one line naming the file or the device)."""
    device = resolve_device(request.device)
    try:
        return load_trained_model(request.checkpoint, use_ema=request.weights == "ema", device=device)
    except (ValueError, ckpt.CheckpointError) as err:
        raise SamplingError(str(err)) from err

def resolve_integrator(request: SampleRequest, trained: TrainedModel) -> Integrator:
    """The solver or sampler, steps and precision for ``trained``'s objective and device; a mismatch (or bf16 on a
    device without it) is a clear SamplingError."""
    try:
        precision = resolve_precision(request.precision, trained.device)
    except ValueError as err:
        raise SamplingError(str(err)) from err
    if trained.objective == "flow":
        solver = request.solver or DEFAULT_FLOW_SOLVER
        if solver in SAMPLERS:
            raise SamplingError(f"{trained.checkpoint} is a flow-matching model (train.objective=flow): {solver!r} is "
                                f"a diffusion sampler; use an ODE solver ({', '.join(known_solvers())})")
        # the model's own default (ModelConfig.sampling_steps: 10, a few-step student's 2); edits keep their settings'
        default_steps = request.settings_steps if request.edit is not None else trained.model_config.sampling_steps
        steps = request.steps or default_steps
        step_size = None
        if trained.model_config.shortcut_levels:  # a shortcut model: the step size of these steps, or why not
            try:
                step_size = trained.shortcut_step_size(solver, steps, request.guidance_for(trained))
            except ValueError as err:
                raise SamplingError(str(err)) from None
        grid = step_grid(steps, trained.model_config.sampling_times)  # a few-step student's own times, if any
        return Integrator("flow", solver, steps, precision=precision, step_size=step_size,
                          grid=None if grid is None else tuple(grid.tolist()))
    sampler = request.solver or DEFAULT_DIFFUSION_SAMPLER
    if sampler not in SAMPLERS:
        raise SamplingError(f"{trained.checkpoint} is a diffusion model (train.objective=diffusion, preset "
                            f"{trained.diffusion_preset!r}): sample it with solver 'ddpm' or 'ddim' (steps respaced "
                            f"from its {trained.diffusion.num_train_steps} training steps), not the ODE solver "
                            f"{sampler!r}")
    if request.edit is not None and request.rewrite_until is not None:
        raise SamplingError("rewrite_until is a flow-matching edit option: FLAME's replacement editing of a diffusion "
                            "model re-noises the kept part before every step")
    baseline = request.baseline_for(trained)  # the authors' settings as run (FLAME's), as the evaluator's
    try:
        trained.check_baseline_weights(baseline, "give --model-weights model (weights=model) to sample its raw "
                                                 "weights")
    except ValueError as err:
        raise SamplingError(str(err)) from None
    steps = request.steps or trained.diffusion.num_train_steps  # every training step unless asked for fewer
    try:
        schedule = trained.diffusion.respaced(steps)
    except ValueError as err:
        raise SamplingError(f"cannot sample {trained.checkpoint} with {steps} steps of its "
                            f"{trained.diffusion.num_train_steps}: {err}") from err
    return Integrator("diffusion", sampler, steps, schedule, clip_denoised=trained.x0_clamp(baseline),
                      precision=precision)

DEVICE_TYPES = ("cpu", "cuda", "mps")


def resolve_device(device: str) -> str:
    """The device to sample on: ``auto`` is cuda when a GPU is visible, else cpu; ``cpu``, ``cuda``, ``cuda:N`` and
    ``mps`` are used as given once this machine is seen to have them. Anything else, or a GPU that is not there,
    is a :class:`SamplingError` (torch would fail later, with a traceback, in its CUDA initialisation)."""
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    try:
        parsed = torch.device(device)
    except (RuntimeError, ValueError, TypeError):
        parsed = None
    if parsed is None or parsed.type not in DEVICE_TYPES:
        raise SamplingError(f"device {device!r}: not a device this program samples on (auto, cpu, cuda, cuda:N or "
                            "mps)")
    if parsed.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise SamplingError(f"device {device!r}: no CUDA GPU is visible on this machine; use --device cpu (or "
                                "auto, which picks cuda only when there is one)")
        if parsed.index is not None and parsed.index >= count:
            raise SamplingError(f"device {device!r}: this machine has {count} visible CUDA GPU(s), cuda:0 to "
                                f"cuda:{count - 1}")
    if parsed.type == "mps" and not torch.backends.mps.is_available():
        raise SamplingError(f"device {device!r}: Apple's MPS backend is not available on this machine; use --device "
                            "cpu")
    return device

def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)

def sample_seed(seed: int, index: int) -> int:
    """The noise seed of sample ``index``: independent streams per (seed, index), unlike ``seed + index``."""
    return int(np.random.SeedSequence([seed, index]).generate_state(1)[0])
