"""ODE solvers for flow-matching sampling, classifier-free guidance and seeded generation.

Time runs from ``t = 0`` (Gaussian noise) to ``t = 1`` (data); a velocity field ``v(x, t)`` is integrated forward.

* Fixed-step explicit Runge-Kutta solvers over any increasing time grid in [0, 1] (default: ``steps`` uniform steps):
  ``euler`` (MFM's default; the paper reports 10 steps suffice), ``midpoint``, ``heun`` and ``rk4``. One step costs
  1, 2, 2 and 4 velocity evaluations, so a solve costs N, 2N, 2N and 4N evaluations (Heun keeps its corrector on the
  last step too, unlike EDM's 2N - 1 variant).
* Every other name is handed to ``torchdiffeq.odeint`` (``dopri5`` = MFM's adaptive option, also ``dopri8``,
  ``bosh3``, ``adaptive_heun``, ``explicit_adams``, ...) with ``rtol``/``atol``; its evaluations are counted by
  wrapping the velocity function, so :attr:`SolveResult.nfe` is always the number of calls actually made.
* ``x̂1`` estimates (MFM Fig. 4): at the start of every fixed step, ``x̂1 = x_t + (1 - t)·v(x_t, t)`` from the step's
  first (already needed) evaluation, i.e. one estimate per step and no extra evaluations. torchdiffeq methods record
  one estimate per evaluation, including the trial stages and rejected steps of adaptive methods.

A velocity function is any ``VelocityFn`` ``(x (B, T, D), t (B,)) -> v (B, T, D)``; the solvers never depend on the
model class. :func:`guided_velocity` turns a model with MFM's forward signature
``model(x, t, cond, lengths, *, cond_mask)`` into one, doing classifier-free guidance in a single batched pass.

Padding: :func:`sample` zeroes the padded frames of the initial noise and of every velocity
(:func:`zero_padded_frames`), so padded frames of the state are exactly zero at every time and never drift.

Precision: ``precision='bf16'`` (:func:`guided_velocity`, :func:`sample`) runs the model's passes under bf16 autocast
(mfm.guidance.AutocastForward); the velocity comes back as fp32 and the state, the guidance mix and every solver
update stay fp32, so only the network's own rounding changes.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from mfm.guidance import PassLengths, classifier_free_guidance
from mfm.model import valid_frame_mask

logger = logging.getLogger(__name__)

VelocityFn = Callable[[Tensor, Tensor], Tensor]
"""``(x (B, T, D), t (B,)) -> velocity (B, T, D)``."""

StepHook = Callable[[Tensor, float, int], Tensor]
"""``(state, t, step_index) -> state``, applied before each fixed step (trajectory rewriting uses it)."""


@dataclass(frozen=True)
class ButcherTableau:
    """An explicit Runge-Kutta method: stage ``i`` is evaluated at ``(x + h·Σ_j a[i][j]·k_j, t + c[i]·h)`` and the
    step is ``x + h·Σ_i b[i]·k_i``."""

    a: tuple[tuple[float, ...], ...]
    b: tuple[float, ...]
    c: tuple[float, ...]

    def __post_init__(self) -> None:
        if not (len(self.a) == len(self.b) == len(self.c)) or any(len(row) != i for i, row in enumerate(self.a)):
            raise ValueError("explicit tableau: a must be strictly lower-triangular with one row per stage")
        if self.c[0] != 0.0:
            raise ValueError("explicit tableau: the first stage must be at the step start (c[0] = 0)")

    @property
    def num_stages(self) -> int:
        return len(self.b)


FIXED_STEP_SOLVERS: dict[str, ButcherTableau] = {
    "euler": ButcherTableau(a=((),), b=(1.0,), c=(0.0,)),
    "midpoint": ButcherTableau(a=((), (0.5,)), b=(0.0, 1.0), c=(0.0, 0.5)),
    "heun": ButcherTableau(a=((), (1.0,)), b=(0.5, 0.5), c=(0.0, 1.0)),
    "rk4": ButcherTableau(
        a=((), (0.5,), (0.0, 0.5), (0.0, 0.0, 1.0)),
        b=(1.0 / 6.0, 1.0 / 3.0, 1.0 / 3.0, 1.0 / 6.0),
        c=(0.0, 0.5, 0.5, 1.0),
    ),
}


@dataclass
class SolveResult:
    """Outcome of one solve.

    x1: final state at the last grid time (B, T, D).
    nfe: number of velocity-function evaluations made (a guided evaluation is one batched model pass).
    x1_hat: (K, B, T, D) estimates ``x + (1 - t)·v`` if a trajectory was requested, else None.
    x1_hat_times: (K,) float64 times of those estimates, else None.
    grid: float64 time grid (fixed-step: the N + 1 step boundaries; torchdiffeq: the times passed to odeint).
    """

    x1: Tensor
    nfe: int
    x1_hat: Tensor | None
    x1_hat_times: Tensor | None
    grid: Tensor


def uniform_grid(steps: int) -> Tensor:
    """``steps + 1`` float64 times ``i / steps``: exactly the values ``i / steps`` Python computes."""
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 1:
        raise ValueError(f"steps must be a positive int, got {steps!r}")
    return torch.arange(steps + 1, dtype=torch.float64) / steps


def step_grid(steps: int, sampling_times: Sequence[float] | None) -> Tensor | None:
    """The grid of a ``steps``-step fixed solve for a model with ``ModelConfig.sampling_times``: those start times
    and 1 when there are ``steps`` of them, else None (the solvers' uniform grid)."""
    if sampling_times is None or len(sampling_times) != steps:
        return None
    return check_grid([*sampling_times, 1.0])


def check_grid(grid: Sequence[float] | Tensor) -> Tensor:
    """A validated float64 copy of ``grid``: 1-D, at least two points, strictly increasing, within [0, 1]."""
    times = torch.as_tensor(grid, dtype=torch.float64).detach().cpu().clone()
    if times.dim() != 1 or times.numel() < 2:
        raise ValueError(f"time grid must be 1-D with at least 2 points, got shape {tuple(times.shape)}")
    if not torch.isfinite(times).all() or times[0] < 0.0 or times[-1] > 1.0:
        raise ValueError(f"time grid must lie in [0, 1] (noise at 0, data at 1), got {times.tolist()}")
    if not (times[1:] > times[:-1]).all():
        raise ValueError(f"time grid must be strictly increasing, got {times.tolist()}")
    return times


def _time_batch(t: float | Tensor, x: Tensor) -> Tensor:
    """The scalar time as the (B,) tensor a velocity function expects, in ``x``'s dtype and device."""
    return torch.full((x.shape[0],), float(t), dtype=x.dtype, device=x.device)


class _CountedVelocity:
    """Counts calls of a velocity function; optionally records ``x + (1 - t)·v`` at every call."""

    def __init__(self, velocity_fn: VelocityFn, record_every_call: bool = False) -> None:
        self.velocity_fn = velocity_fn
        self.calls = 0
        self.record_every_call = record_every_call
        self.estimates: list[Tensor] = []
        self.estimate_times: list[float] = []

    def __call__(self, x: Tensor, t: Tensor) -> Tensor:
        self.calls += 1
        v = self.velocity_fn(x, t)
        if v.shape != x.shape:
            raise ValueError(f"velocity function returned shape {tuple(v.shape)} for a state of {tuple(x.shape)}")
        if self.record_every_call:
            self.record(x, float(t[0]), v)
        return v

    def record(self, x: Tensor, t: float, v: Tensor) -> None:
        self.estimates.append(x + (1.0 - t) * v)
        self.estimate_times.append(t)

    def trajectory(self) -> tuple[Tensor | None, Tensor | None]:
        if not self.estimates:
            return None, None
        return torch.stack(self.estimates), torch.tensor(self.estimate_times, dtype=torch.float64)


def solve(
    velocity_fn: VelocityFn,
    x0: Tensor,
    *,
    solver: str = "euler",
    steps: int = 10,
    grid: Sequence[float] | Tensor | None = None,
    rtol: float = 1e-5,
    atol: float = 1e-5,
    options: dict | None = None,
    return_trajectory: bool = False,
    before_step: StepHook | None = None,
) -> SolveResult:
    """Integrate ``dx/dt = velocity_fn(x, t)`` from ``x0`` over ``grid`` (default ``uniform_grid(steps)``).

    solver: a name in FIXED_STEP_SOLVERS, or any torchdiffeq method (then ``rtol``, ``atol`` and ``options`` go to
        ``torchdiffeq.odeint``; adaptive methods integrate from ``grid[0]`` to ``grid[-1]``, fixed-grid torchdiffeq
        methods step on ``grid`` unless ``options`` says otherwise). ``rtol=atol=1e-5`` is MFM's dopri5 setting.
    before_step: fixed-step solvers only; maps the state before each step (see mfm.editing).
    """
    times = uniform_grid(steps) if grid is None else check_grid(grid)
    if x0.dim() < 1:
        raise ValueError("x0 must have a leading batch dimension")
    if solver in FIXED_STEP_SOLVERS:
        return _solve_fixed_step(velocity_fn, x0, times, FIXED_STEP_SOLVERS[solver], return_trajectory, before_step)
    if before_step is not None:
        raise ValueError(f"before_step needs a fixed-step solver {sorted(FIXED_STEP_SOLVERS)}, got {solver!r}")
    return _solve_torchdiffeq(velocity_fn, x0, times, solver, rtol, atol, options, return_trajectory)


def _solve_fixed_step(
    velocity_fn: VelocityFn,
    x0: Tensor,
    times: Tensor,
    tableau: ButcherTableau,
    return_trajectory: bool,
    before_step: StepHook | None,
) -> SolveResult:
    counted = _CountedVelocity(velocity_fn)
    x = x0
    boundaries = times.tolist()
    for index, (t, t_next) in enumerate(zip(boundaries[:-1], boundaries[1:])):
        if before_step is not None:
            x = before_step(x, t, index)
        h = t_next - t
        stages: list[Tensor] = []
        for a_row, c in zip(tableau.a, tableau.c):
            stage_x = x
            for a, k in zip(a_row, stages):
                if a != 0.0:
                    stage_x = stage_x + (h * a) * k
            # c = 1 lands exactly on the next grid time rather than on t + (t_next - t) with its rounding.
            stage_t = t_next if c == 1.0 else t + c * h
            stages.append(counted(stage_x, _time_batch(stage_t, x)))
        if return_trajectory:
            counted.record(x, t, stages[0])
        increment = None
        for b, k in zip(tableau.b, stages):
            if b != 0.0:
                increment = b * k if increment is None else increment + b * k
        x = x + h * increment
    x1_hat, x1_hat_times = counted.trajectory()
    return SolveResult(x1=x, nfe=counted.calls, x1_hat=x1_hat, x1_hat_times=x1_hat_times, grid=times)


def is_adaptive(method: str) -> bool:
    """A torchdiffeq adaptive-step method (dopri5, ...): its step count is not a setting. False for our fixed-step
    solvers, torchdiffeq's fixed-grid ones and unknown names."""
    if method in FIXED_STEP_SOLVERS:
        return False
    from torchdiffeq._impl.odeint import SOLVERS  # torchdiffeq's only list of its methods

    return method in SOLVERS and not is_torchdiffeq_fixed_grid(method)


def is_torchdiffeq_fixed_grid(method: str) -> bool:
    # torchdiffeq exposes no public "is fixed grid" flag; its solver classes are the only source of truth.
    from torchdiffeq._impl.odeint import SOLVERS
    from torchdiffeq._impl.solvers import FixedGridODESolver

    return issubclass(SOLVERS[method], FixedGridODESolver)


def _solve_torchdiffeq(
    velocity_fn: VelocityFn,
    x0: Tensor,
    times: Tensor,
    method: str,
    rtol: float,
    atol: float,
    options: dict | None,
    return_trajectory: bool,
) -> SolveResult:
    from torchdiffeq import odeint
    from torchdiffeq._impl.odeint import SOLVERS

    if method not in SOLVERS:
        raise ValueError(
            f"unknown solver {method!r}: use one of {sorted(FIXED_STEP_SOLVERS)} or a torchdiffeq method "
            f"{sorted(SOLVERS)}"
        )
    counted = _CountedVelocity(velocity_fn, record_every_call=return_trajectory)
    # Adaptive methods only need the end points (asking for every grid time would keep N + 1 states in memory);
    # torchdiffeq's fixed-grid methods take the output times as their step grid when no step_size is given.
    if options is None and is_torchdiffeq_fixed_grid(method):
        output_times = times
    else:
        output_times = times[[0, -1]]
    states = odeint(
        lambda t, x: counted(x, _time_batch(t, x)),
        x0,
        output_times.to(x0.device),
        rtol=rtol,
        atol=atol,
        method=method,
        options=options,
    )
    x1_hat, x1_hat_times = counted.trajectory()
    return SolveResult(x1=states[-1], nfe=counted.calls, x1_hat=x1_hat, x1_hat_times=x1_hat_times, grid=output_times)


def zero_padded_frames(velocity_fn: VelocityFn, lengths: Tensor | None) -> VelocityFn:
    """``velocity_fn`` with the velocity of frames ``>= lengths[b]`` set to zero (identity if lengths is None; a
    pass whose window no motion is shorter than is left as it is: it has no padded frame)."""
    if lengths is None:
        return velocity_fn
    pass_lengths = PassLengths(lengths)

    def masked(x: Tensor, t: Tensor) -> Tensor:
        window_lengths = pass_lengths.for_window(x.shape[1])
        if window_lengths is None:
            return velocity_fn(x, t)
        valid = valid_frame_mask(window_lengths.to(x.device), x.shape[1])
        return velocity_fn(x, t) * valid.unsqueeze(-1).to(x.dtype)

    return masked


def guided_velocity(
    model: Callable[..., Tensor],
    cond: Tensor,
    *,
    scale: float = 2.5,
    lengths: Tensor | None = None,
    null_cond: Tensor | None = None,
    conditional_channels: Tensor | None = None,
    precision: str = "fp32",
) -> VelocityFn:
    """Classifier-free guided velocity ``v = v(∅) + scale·(v(c) - v(∅))`` of ``model``.

    model: called as ``model(x, t, cond, lengths, cond_mask=...)`` (mfm.model.MotionFlowTransformer).
    cond: (B, E) float condition embeddings or (B,) long action ids, encoded once by the caller.
    scale: 1 → the conditional field, one pass of size B; 0 → the unconditional field, one pass of size B (the
        way to sample or edit without a condition: ``cond`` is then only a placeholder of the right shape, e.g.
        zeros); otherwise one batched pass of size 2B, conditional half with ``cond_mask`` False, unconditional
        half with ``cond_mask`` True.
    conditional_channels: (D,) bool mask of feature channels whose velocity is the conditional one, unguided
        (``model.guided_features='pose'``: :attr:`mfm.layout.FeatureLayout.root_motion_mask`).
    null_cond: what the unconditional half receives as ``cond`` (default: ``cond`` itself, which the model drops
        because of ``cond_mask``); for models whose null condition is an explicit input. Broadcast to cond's shape.
    precision: ``fp32`` or ``bf16`` (the model's passes under bf16 autocast; the velocity is fp32 either way).
    """
    return classifier_free_guidance(model, cond, scale=scale, lengths=lengths, null_cond=null_cond,
                                    conditional_channels=conditional_channels, precision=precision)


def initial_noise(
    shape: Sequence[int],
    *,
    seed: int = 0,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """Standard normal noise drawn from ``generator`` (default: a new CPU generator seeded with ``seed``).

    Drawn on the generator's device and then moved, so a CPU generator gives the same noise on every device. The
    move is queued (``non_blocking``): a blocking copy to a GPU would first wait for all the work queued there.
    """
    if generator is None:
        generator = torch.Generator().manual_seed(seed)
    noise = torch.randn(tuple(shape), generator=generator, device=generator.device, dtype=torch.float32)
    return noise.to(device=device, dtype=dtype, non_blocking=True)


NoiseGenerators = torch.Generator | Sequence[torch.Generator]
"""One generator for a whole batch, or one per motion (see :func:`draw_noise`)."""


NOISE_DEVICES = ("cpu", "model")
"""Where seeded noise is drawn. cpu (default): CPU generators, so a seed gives the same motion on every device.
model: generators on the model's device; on a GPU that saves the CPU's draw (124 ms for 256 × 196 × 263 normals on
an H200 machine's CPU, against 0.04 ms on the GPU: more than half of a 10-step batch's time), but a seed's motion
then differs between devices (CUDA's Philox stream is not the CPU's)."""


def noise_generator_device(noise_device: str, model_device: torch.device | str) -> torch.device:
    """The device whose generators draw the noise for ``noise_device`` (:data:`NOISE_DEVICES`)."""
    if noise_device not in NOISE_DEVICES:
        raise ValueError(f"noise_device must be one of {NOISE_DEVICES}, got {noise_device!r}")
    return torch.device("cpu") if noise_device == "cpu" else torch.device(model_device)


def seeded_generators(seeds: Sequence[int], device: torch.device | str = "cpu") -> list[torch.Generator]:
    """One generator per motion on ``device`` (default the CPU: the same noise on every device; see
    :data:`NOISE_DEVICES`), seeded with that motion's seed."""
    return [torch.Generator(device=device).manual_seed(int(seed)) for seed in seeds]


def draw_noise(
    shape: Sequence[int],
    generator: NoiseGenerators,
    *,
    lengths: Tensor | Sequence[int] | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """Standard normal (B, T, ...) noise from one generator, or from one generator per motion.

    One generator: the whole block in one draw (:func:`initial_noise`). One per motion: row b draws only its
    ``lengths[b]`` valid frames (all T without ``lengths``) from its own generator and is zero after them, so a
    motion's noise depends on its seed and length alone, not on which other motions share its batch or how long
    the longest of them is: a seed gives the same motion at any batch size.
    """
    if isinstance(generator, torch.Generator):
        return initial_noise(shape, generator=generator, device=device, dtype=dtype)
    shape = tuple(shape)
    if len(generator) != shape[0]:
        raise ValueError(f"{len(generator)} generators for a batch of {shape[0]}")
    if lengths is None:
        rows = [shape[1]] * shape[0]
    else:
        rows = [int(n) for n in (lengths.tolist() if isinstance(lengths, Tensor) else lengths)]
    noise = torch.zeros(shape, dtype=torch.float32, device=generator[0].device if generator else None)
    for row, (row_generator, length) in enumerate(zip(generator, rows)):
        noise[row, :length] = initial_noise((length, *shape[2:]), generator=row_generator)
    return noise.to(device=device, dtype=dtype, non_blocking=True)  # queued, as initial_noise's


def model_device(model: Callable[..., Tensor], fallback: Tensor) -> torch.device:
    if isinstance(model, nn.Module):
        parameter = next(model.parameters(), None)
        if parameter is not None:
            return parameter.device
    return fallback.device


def model_feature_dim(model: Callable[..., Tensor], feature_dim: int | None) -> int:
    if feature_dim is not None:
        return feature_dim
    config = getattr(model, "config", None)
    if config is None or not hasattr(config, "feature_dim"):
        raise ValueError("pass feature_dim: the model has no config.feature_dim to read it from")
    return int(config.feature_dim)


def check_lengths(lengths: Sequence[int] | Tensor, num_frames: int) -> Tensor:
    """(B,) long tensor of valid lengths, each in [1, num_frames]."""
    lengths = torch.as_tensor(lengths).detach()
    if lengths.dim() != 1 or lengths.numel() == 0 or lengths.is_floating_point():
        raise ValueError(f"lengths must be a non-empty 1-D integer sequence, got {tuple(lengths.shape)} {lengths.dtype}")
    lengths = lengths.long()
    if int(lengths.min()) < 1 or int(lengths.max()) > num_frames:
        raise ValueError(f"lengths must be in [1, {num_frames}] (num_frames), got {lengths.tolist()}")
    return lengths


@torch.no_grad()
def sampling_inputs(model: nn.Module, cond: Tensor, lengths: Tensor | Sequence[int],
                    num_frames: int) -> tuple[torch.device, Tensor, Tensor]:
    """Checked ``(device, cond, lengths)`` on the model's device, shared by the ODE and diffusion samplers
    (warns when the model is in training mode: dropout would make the network random)."""
    if getattr(model, "training", False):
        logger.warning("sampling from a model in training mode: dropout makes the network random")
    device = model_device(model, cond)
    lengths = check_lengths(lengths, num_frames).to(device)
    cond = cond.to(device)
    if cond.shape[0] != lengths.shape[0]:
        raise ValueError(f"cond has batch {cond.shape[0]} but {lengths.shape[0]} lengths were given")
    return device, cond, lengths


def sample(
    model: Callable[..., Tensor],
    cond: Tensor,
    lengths: Sequence[int] | Tensor,
    *,
    num_frames: int,
    feature_dim: int | None = None,
    solver: str = "euler",
    steps: int = 10,
    grid: Sequence[float] | Tensor | None = None,
    guidance: float = 2.5,
    null_cond: Tensor | None = None,
    conditional_channels: Tensor | None = None,
    seed: int = 0,
    generator: NoiseGenerators | None = None,
    return_trajectory: bool = False,
    rtol: float = 1e-5,
    atol: float = 1e-5,
    options: dict | None = None,
    precision: str = "fp32",
    noise_device: str = "cpu",
    noise: Tensor | None = None,
) -> SolveResult:
    """Generate B = len(lengths) motions (B, num_frames, D) of normalised features by integrating the guided field.
    ``conditional_channels``: feature channels left unguided (:func:`guided_velocity`).
    ``noise``: the (B, num_frames, D) initial noise to integrate from instead of drawing it (its padded frames are
    zeroed); ``seed``, ``generator`` and ``noise_device`` are then unused.

    The initial noise comes from ``generator`` or, by default, a generator seeded with ``seed`` on the CPU
    (``noise_device='cpu'``: the same seed, batch (cond, lengths) and device give identical results, and the noise
    is the same on every device) or on the model's device (``'model'``: faster on a GPU; :data:`NOISE_DEVICES`).
    A list of generators, one per motion
    (:func:`seeded_generators`), draws each motion's noise over its own length (:func:`draw_noise`), so a motion
    does not depend on its batch: how launch/sample.py, reflow's pairs and training previews draw it. Frames
    ``>= lengths[b]`` are zero in the output.
    The model should be in eval mode (dropout on makes the field random). feature_dim defaults to
    ``model.config.feature_dim``. ``num_frames``: the batch's window; the pipeline's samplers pass its longest
    length, so no pass computes frames that no motion of the batch has. ``precision``: see :func:`guided_velocity`.
    """
    device, cond, lengths = sampling_inputs(model, cond, lengths, num_frames)
    shape = (lengths.shape[0], num_frames, model_feature_dim(model, feature_dim))
    valid = valid_frame_mask(lengths, num_frames).unsqueeze(-1)
    if noise is not None:
        if tuple(noise.shape) != shape:
            raise ValueError(f"noise must be {shape} (batch, num_frames, feature_dim), got {tuple(noise.shape)}")
        x0 = noise.to(device=device, dtype=torch.float32) * valid
    else:
        if generator is None:
            generator = torch.Generator(device=noise_generator_device(noise_device, device)).manual_seed(seed)
        x0 = draw_noise(shape, generator, lengths=lengths, device=device) * valid
    velocity = zero_padded_frames(
        guided_velocity(model, cond, scale=guidance, lengths=lengths, null_cond=null_cond,
                        conditional_channels=conditional_channels, precision=precision),
        lengths,
    )
    return solve(
        velocity, x0, solver=solver, steps=steps, grid=grid, rtol=rtol, atol=atol, options=options,
        return_trajectory=return_trajectory,
    )


FLOW_MAP_PERTURBATION = 1e-3
"""RMS per noise element of :func:`flow_map_amplification`'s perturbation: well above float32 rounding of a solve
(about 1e-7 relative) and well below the noise's own scale (1)."""

ROUGH_AMPLIFICATION = 10.0
"""Median flow-map amplification above which launch/distill.py warns that reflow cannot fit the teacher (and an
exported student's model card says so). Measured (docs/few-step.md, 'A rough teacher'): the embedded default's
teacher 0.099, whose 2-step students come near its 10-step figures, and the synthetic preset's 0.32; a PCCAT-only
teacher of the embedded default 3.91; its BPE + PCCAT teacher 167, whose student's loss stalls 20x higher."""


def flow_map_amplification(solve_from: Callable[[Tensor], Tensor], x0: Tensor, direction: Tensor,
                           lengths: Tensor, *, perturbation: float = FLOW_MAP_PERTURBATION) -> Tensor:
    """How far a sampler's motion moves per unit change of its initial noise: per motion,
    ``||Φ(x0 + δ) − Φ(x0)|| / ||δ||`` over its valid frames, where ``Φ = solve_from`` maps a (B, T, D) noise batch to
    its (B, T, D) endpoints and ``δ = perturbation · direction`` (a finite difference along one direction; zero on
    padded frames). Returns (B,) float.

    Why it matters: reflow (docs/few-step.md) trains a student to jump from a noise straight to the teacher's motion
    from it, so the teacher's map must be a function a network can fit. About 1 or less: nearby noises give nearby
    motions. Thousands: a change far below anything a network resolves moves the motion, so the pairs are, to the
    student, an arbitrary assignment of motions to noises, and a 1-2 step student learns their average.
    ``solve_from`` is called twice with the same batch shape, so each unperturbed row is computed exactly as its
    perturbed twin (on a rough map even the float rounding that other batch mates cause shows)."""
    if perturbation <= 0:
        raise ValueError(f"perturbation must be > 0, got {perturbation}")
    if x0.shape != direction.shape or x0.dim() != 3:
        raise ValueError(f"x0 and direction must both be (B, T, D), got {tuple(x0.shape)} and {tuple(direction.shape)}")
    valid = valid_frame_mask(lengths.to(x0.device), x0.shape[1]).unsqueeze(-1).to(x0.dtype)
    delta = perturbation * direction * valid
    moved = (solve_from(x0 + delta) - solve_from(x0)) * valid
    return (moved.flatten(1).norm(dim=1) / delta.flatten(1).norm(dim=1).clamp_min(1e-30)).float()


def sample_lengths(
    lengths_distribution: Sequence[int],
    n: int,
    generator: torch.Generator | None = None,
    *,
    max_length: int | None = None,
) -> Tensor:
    """``n`` lengths drawn with replacement from the empirical training distribution (the manifest's per-split
    ``lengths``), optionally clipped to ``max_length`` (the model's frame window). Global RNG if no generator."""
    pool = torch.as_tensor(list(lengths_distribution), dtype=torch.long)
    if pool.dim() != 1 or pool.numel() == 0:
        raise ValueError("lengths_distribution must be a non-empty list of motion lengths")
    if int(pool.min()) < 1:
        raise ValueError(f"lengths_distribution holds a length < 1: {int(pool.min())}")
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    device = generator.device if generator is not None else None
    picks = torch.randint(pool.numel(), (n,), generator=generator, device=device).cpu()
    lengths = pool[picks]
    if max_length is not None:
        lengths = lengths.clamp(max=max_length)
    return lengths
