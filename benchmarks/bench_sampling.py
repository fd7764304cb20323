"""Sampling speed: milliseconds per generated motion, one JSON line per batch size.

    python benchmarks/bench_sampling.py                                  # HumanML3D preset, batch 1 and 256
    python benchmarks/bench_sampling.py --device cuda --compile          # torch.compile (CUDA graphs on GPU)
    python benchmarks/bench_sampling.py --batch-sizes 1,32 --repeats 3   # CPU-friendly
    python benchmarks/bench_sampling.py --checkpoint runs/tiny           # a trained model instead of a preset
    python benchmarks/bench_sampling.py --precision fp32,bf16            # each precision, then their difference

What is timed: ``mfm.solvers.sample`` (initial noise, ``--steps`` fixed steps of ``--solver``, classifier-free
guidance at ``--guidance`` as one batched pass of 2B per evaluation), full ``--frames`` windows (as MDM/MFM
evaluation), random text embeddings; the text encoder and any export are not included. Random weights are fine:
speed does not depend on their values. ``ms_per_motion`` = median wall time over ``--repeats`` timed runs (after
``--warmup`` untimed ones) / batch size.

``--compile``: ``torch.compile`` of the model; on CUDA with ``mode="reduce-overhead"``, which captures CUDA graphs
(a fixed-step solver calls the model with the same shapes every step, so the graph is replayed). The first
(warm-up) call compiles; its time is reported as ``compile_s``.

``--precision``: ``fp32`` and/or ``bf16`` (the model's passes under bf16 autocast, the ODE state and solver fp32:
``mfm.solvers.sample(precision=...)``); with both, a ``sampling_precision`` line per batch size gives the largest
and mean |bf16 − fp32| of the motions sampled from the same noise (normalised feature units) and the time ratio.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import time
from pathlib import Path

import torch

if __package__ in (None, ""):  # run as a script: make the project importable from a checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mfm.compilation import compiled_for_sampling  # benchmarks/gpu_suite.py takes it from here too
from mfm.guidance import SAMPLING_PRECISIONS
from mfm.model import ModelConfig, MotionFlowTransformer, count_parameters
from mfm.solvers import NOISE_DEVICES, sample

PRESETS = {
    "humanml3d": ModelConfig(),  # MFM's HumanML3D text model: 263-D, 8 layers x 512, 4 heads, CLIP 512
    "kit": ModelConfig(feature_dim=251),
    "tiny": ModelConfig(latent_dim=64, ff_dim=128, num_layers=2, cond_dim=384),
}


@dataclasses.dataclass(frozen=True)
class SamplingSettings:
    """What one sampling measurement runs: the solver call (as ``mfm.solvers.sample`` takes it) and how it is timed."""

    device: str
    frames: int = 196
    steps: int = 10
    solver: str = "euler"
    guidance: float = 2.5
    repeats: int = 5
    warmup: int = 1
    compile: bool = False
    precision: str = "fp32"
    """The model passes' arithmetic (mfm.guidance.SAMPLING_PRECISIONS)."""
    noise_device: str = "cpu"
    """Where the initial noise is drawn (mfm.solvers.NOISE_DEVICES): cpu, as by default, or the model's device."""

    @classmethod
    def from_args(cls, args: argparse.Namespace, precision: str = "fp32") -> SamplingSettings:
        return cls(device=args.device, frames=args.frames, steps=args.steps, solver=args.solver,
                   guidance=args.guidance, repeats=args.repeats, warmup=args.warmup, compile=args.compile,
                   precision=precision, noise_device=args.noise_device)


def preset_model(config: ModelConfig, device: str) -> MotionFlowTransformer:
    """A randomly initialised model of ``config`` for sampling (dropout off, eval mode, seed 0): speed does not
    depend on the weights' values."""
    torch.manual_seed(0)
    return MotionFlowTransformer(dataclasses.replace(config, dropout=0.0)).to(device).eval()


def build_model(args: argparse.Namespace) -> tuple[torch.nn.Module, ModelConfig, str]:
    if args.checkpoint:
        from pipeline.generation.inference import load_trained_model

        trained = load_trained_model(args.checkpoint, device=args.device)
        return trained.model, trained.model_config, str(trained.checkpoint)
    config = dataclasses.replace(PRESETS[args.preset], dropout=0.0)
    return preset_model(config, args.device), config, args.preset


def random_conditions(config: ModelConfig, batch: int, device: str) -> torch.Tensor:
    generator = torch.Generator().manual_seed(1)
    if config.is_action_model:
        return torch.randint(config.num_actions, (batch,), generator=generator).to(device)
    return torch.randn(batch, config.cond_dim, generator=generator).to(device)


def timed(fn, device: str) -> float:
    """Wall time of ``fn()``; on CUDA the device is synchronised before both clock reads, so queued kernels count."""
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    start = time.perf_counter()
    fn()
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    return time.perf_counter() - start


def measure_sampling(model, config: ModelConfig, batch: int, settings: SamplingSettings) -> dict:
    """Median wall time of ``settings.repeats`` calls of ``mfm.solvers.sample`` for ``batch`` full-window motions
    with random conditions, after ``settings.warmup`` untimed calls (the first one compiles under ``compile``)."""
    nfe = []

    def run() -> None:
        nfe.append(sample_batch(model, config, batch, settings).nfe)

    warmups = [timed(run, settings.device) for _ in range(settings.warmup)]
    times = [timed(run, settings.device) for _ in range(settings.repeats)]
    median = statistics.median(times)
    guided = settings.guidance not in (0.0, 1.0)
    record = {
        "bench": "sampling", "batch_size": batch, "ms_per_motion": round(1000.0 * median / batch, 3),
        "median_batch_s": round(median, 4), "min_batch_s": round(min(times), 4), "repeats": settings.repeats,
        "warmup": settings.warmup, "nfe": nfe[-1], "model_passes_of_2B": nfe[-1] if guided else 0,
        "steps": settings.steps, "solver": settings.solver, "guidance": settings.guidance, "frames": settings.frames,
        "precision": settings.precision, "noise_device": settings.noise_device,
    }
    if settings.compile and warmups:
        record["compile_s"] = round(warmups[0], 3)
    return record


def sample_batch(model, config: ModelConfig, batch: int, settings: SamplingSettings):
    """One ``mfm.solvers.sample`` call of ``batch`` full-window motions with random conditions and noise seed 0."""
    cond = random_conditions(config, batch, settings.device)
    lengths = torch.full((batch,), settings.frames, dtype=torch.long)
    return sample(model, cond, lengths, num_frames=settings.frames, feature_dim=config.feature_dim,
                  solver=settings.solver, steps=settings.steps, guidance=settings.guidance, seed=0,
                  precision=settings.precision, noise_device=settings.noise_device)


def precision_difference(model, config: ModelConfig, batch: int, settings: SamplingSettings) -> dict:
    """|bf16 − fp32| of one batch sampled from the same noise and conditions (normalised feature units): its
    largest and mean value, and the fp32 motions' spread to read them against."""
    fp32 = sample_batch(model, config, batch, dataclasses.replace(settings, precision="fp32")).x1
    bf16 = sample_batch(model, config, batch, dataclasses.replace(settings, precision="bf16")).x1
    difference = (bf16 - fp32).abs()
    return {"bench": "sampling_precision", "batch_size": batch, "max_abs_difference": float(difference.max()),
            "mean_abs_difference": float(difference.mean()), "fp32_std": float(fp32.std()),
            "fp32_max_abs": float(fp32.abs().max()), "state_dtype": str(bf16.dtype).removeprefix("torch.")}


def measure(model, config: ModelConfig, batch: int, args: argparse.Namespace, precision: str = "fp32") -> dict:
    return measure_sampling(model, config, batch, SamplingSettings.from_args(args, precision))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", choices=sorted(PRESETS), default="humanml3d")
    parser.add_argument("--checkpoint", help="time a trained checkpoint (run folder or step folder) instead")
    parser.add_argument("--batch-sizes", default="1,256", help="comma-separated (default 1,256)")
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--solver", default="euler")
    parser.add_argument("--guidance", type=float, default=2.5)
    parser.add_argument("--frames", type=int, default=196)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--threads", type=int, help="CPU intra-op threads (default: torch's)")
    parser.add_argument("--compile", action="store_true", help="torch.compile the model (CUDA graphs on GPU)")
    parser.add_argument("--precision", default="fp32", help="comma list of fp32, bf16 (default fp32); with both, "
                                                           "also their difference")
    parser.add_argument("--noise-device", choices=NOISE_DEVICES, default="cpu",
                        help="draw the initial noise on the CPU (default, as the sampler does) or the model's device")
    args = parser.parse_args(argv)
    precisions = [p.strip() for p in args.precision.split(",") if p.strip()]
    if not precisions or any(p not in SAMPLING_PRECISIONS for p in precisions):
        parser.error(f"--precision: a comma list of {', '.join(SAMPLING_PRECISIONS)}, got {args.precision!r}")
    if args.compile and args.warmup < 1:
        parser.error("--compile needs --warmup >= 1 (the first call compiles)")
    if args.threads:
        torch.set_num_threads(args.threads)

    model, config, source = build_model(args)
    if args.compile:
        model = compiled_for_sampling(model, args.device)
    header = {"bench": "sampling_setup", "model": source, "parameters": count_parameters(model), "device": args.device,
              "device_name": torch.cuda.get_device_name(args.device) if args.device.startswith("cuda") else "cpu",
              "threads": torch.get_num_threads(), "compile": args.compile, "torch": torch.__version__}
    print(json.dumps(header), flush=True)
    with torch.inference_mode():
        for batch in (int(b) for b in args.batch_sizes.split(",")):
            timed_runs = {precision: measure(model, config, batch, args, precision) for precision in precisions}
            for record in timed_runs.values():
                print(json.dumps(record), flush=True)
            if len(timed_runs) == 2:
                difference = precision_difference(model, config, batch, SamplingSettings.from_args(args))
                difference["bf16_speedup"] = round(timed_runs["fp32"]["median_batch_s"]
                                                   / timed_runs["bf16"]["median_batch_s"], 3)
                print(json.dumps(difference), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
