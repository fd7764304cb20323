"""How a request's checkpoint is integrated: the checkpoint loaded on the request's device, the ODE solver (flow)
or diffusion sampler with its steps (:class:`Integrator`), and each sample's noise seed; shared by sampling,
editing and composition."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import torch

from mfm.diffusion import GaussianDiffusion
from mfm.diffusion_sampling import SAMPLERS
from pipeline.generation.inference import TrainedModel, load_trained_model
from pipeline.generation.request import (
    DEFAULT_DIFFUSION_SAMPLER,
    DEFAULT_FLOW_SOLVER,
    DEFAULT_FLOW_STEPS,
    SampleRequest,
    SamplingError,
    known_solvers,
)


@dataclasses.dataclass(frozen=True)
class Integrator:
    """How a request integrates its checkpoint: an ODE solver (flow) or a diffusion sampler, with its steps."""

    objective: str  # "flow" or "diffusion"
    name: str  # the solver (flow) or sampler (diffusion: "ddpm" / "ddim")
    steps: int
    diffusion: GaussianDiffusion | None = None  # diffusion: the training process respaced to ``steps``

    def record(self, trained: TrainedModel) -> dict[str, Any]:
        """results.json's description of the objective and sampler."""
        info: dict[str, Any] = {"objective": self.objective, "sampler": self.name, "solver": self.name,
                                "steps": self.steps}
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
    """The request's checkpoint on its device (a checkpoint that cannot be loaded is a SamplingError)."""
    try:
        return load_trained_model(request.checkpoint, use_ema=request.weights == "ema",
                                  device=resolve_device(request.device))
    except ValueError as err:
        raise SamplingError(str(err)) from err

def resolve_integrator(request: SampleRequest, trained: TrainedModel) -> Integrator:
    """The solver or sampler and steps for ``trained``'s objective; a mismatch is a clear SamplingError."""
    if trained.objective == "flow":
        solver = request.solver or DEFAULT_FLOW_SOLVER
        if solver in SAMPLERS:
            raise SamplingError(f"{trained.checkpoint} is a flow-matching model (train.objective=flow): {solver!r} is "
                                f"a diffusion sampler; use an ODE solver ({', '.join(known_solvers())})")
        default_steps = request.settings_steps if request.edit is not None else DEFAULT_FLOW_STEPS
        return Integrator("flow", solver, request.steps or default_steps)
    sampler = request.solver or DEFAULT_DIFFUSION_SAMPLER
    if sampler not in SAMPLERS:
        raise SamplingError(f"{trained.checkpoint} is a diffusion model (train.objective=diffusion, preset "
                            f"{trained.diffusion_preset!r}): sample it with solver 'ddpm' or 'ddim' (steps respaced "
                            f"from its {trained.diffusion.num_train_steps} training steps), not the ODE solver "
                            f"{sampler!r}")
    if request.edit is not None and request.rewrite_until is not None:
        raise SamplingError("rewrite_until is a flow-matching edit option: FLAME's replacement editing of a diffusion "
                            "model re-noises the kept part before every step")
    steps = request.steps or trained.diffusion.num_train_steps
    try:
        schedule = trained.diffusion.respaced(steps)
    except ValueError as err:
        raise SamplingError(f"cannot sample {trained.checkpoint} with {steps} steps of its "
                            f"{trained.diffusion.num_train_steps}: {err}") from err
    return Integrator("diffusion", sampler, steps, schedule)

def resolve_device(device: str) -> str:
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return device

def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)

def sample_seed(seed: int, index: int) -> int:
    """The noise seed of sample ``index``: independent streams per (seed, index), unlike ``seed + index``."""
    return int(np.random.SeedSequence([seed, index]).generate_state(1)[0])
