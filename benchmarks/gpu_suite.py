"""Every speed figure of issue 13 in one command: one JSON line per figure, DIR/results.jsonl and DIR/results.md.

    python benchmarks/gpu_suite.py --out runs/gpu-suite                       # full size, on CUDA when present
    python benchmarks/gpu_suite.py --out /tmp/suite --smoke --device cpu      # tiny sizes, seconds on a CPU
    python benchmarks/gpu_suite.py --out /tmp/suite --device cpu --steps 2 --warmup 1 --batch-size 32 \\
        --sampling-batch 4 --repeats 3 --eval-items 16 --eval-tasks main     # full-size model, reduced, on a CPU

Full size is the HumanML3D preset (configs/humanml3d.yaml: 8 layers, width 512, FF 1024, 4 heads, 263-D features,
512-D text embeddings; batch 128 of 196-frame windows); ``--smoke`` is configs/tiny.yaml's model (2 layers, width
64), batch 4 of 24-frame windows, 2 timed steps. Figures (each a JSON object with ``figure``, ``value``, ``unit``):

* ``train_fp32`` / ``train_optimised``: the real training step (``pipeline.training.trainer.Trainer.train_step``: the
  flow-matching loss of ``mfm.flow``, backward, clipping, AdamW, EMA) on random batches, timed by
  ``benchmarks/bench_train.py``. fp32 = no autocast, eager. Optimised = bf16 autocast where the device has it,
  ``torch.compile`` (``--compile``, default on CUDA only) and fused AdamW (the trainer's choice on CUDA, for both
  steps). Samples/s from the median step time, MFU against the device's dense bf16 peak (:data:`mfm.flops.DENSE_BF16_PEAKS`),
  peak memory (``torch.cuda.max_memory_allocated`` on CUDA; the process's max RSS on CPU).
* ``equal_loss``: both steps' loss on the same batch, initial weights and flow draws (dropout off, so only the
  arithmetic differs); value = |optimised − fp32| / |fp32|.
* ``sampling_one`` / ``sampling_batch``: ``mfm.solvers.sample`` at 10 Euler steps with guidance 2.5 (CFG's two
  halves in one batched pass), ms per motion for one motion and per motion at batch 256 (smoke: 8), timed by
  ``benchmarks/bench_sampling.py`` (CUDA synchronised before each clock read; compiled with CUDA graphs under
  ``--compile``); fp32. ``sampling_one_optimised`` / ``sampling_batch_optimised``: the same with the model's passes
  under bf16 autocast where the optimised training step has it (the ODE state and solver fp32);
  ``sampling_difference``: the largest |optimised − fp32| of the large batch's motions from the same noise.
* ``data_loader``: ``pipeline.data.stream.MotionLoader`` streaming a throwaway synthetic dataset with HumanML3D shapes
  (built by the real shard builder, ``benchmarks/bench_data.py``), samples/s and batches/s with ``--workers``.
* ``data_wait``: the optimised step fed by that loader; value = share of the wall time spent waiting for batches.
* ``evaluator``: the evaluation job's replication (``benchmarks/bench_eval.py``: generation, evaluator embeddings,
  FID/diversity/R-precision, plus editing, FLAME and MultiModality at full size) on a synthetic test set of
  ``--eval-items`` motions (HumanML3D's 4,384); value = test motions per second of one replication, with the
  estimated wall time of the whole protocol (ground truth once + every replication) and the generator's passes per
  replication. fp32, editing in every replication. ``evaluator_optimised``: the same at the sampler's optimised
  precision with one single editing pass (``tasks.editing_passes=single``) and the seeded noise drawn on the model's
  device (``sampling.noise_device=model``; the CPU's own on a CPU), averaged over the protocol.
* ``suite_wall``: the suite's own wall time.

FLOPs per training sample: fwd + bwd = 3 x forward, the forward pass counted by :class:`mfm.flops.TrainingFlops`
(as the training log counts it). For the suite's architecture, MFM's, the count equals this closed form::

    3 * [ 2 * (L * (4*d^2 + 2*d*F)) * S        per-token matmuls of the L layers (qkv, out, two FF Linears)
        + 2 * (D*d + d*D_out) * T               input and output projections of the T frames
        + 2 * (2*d^2 + C*d)                     per-sample time MLP and text projection
        + L * 4 * S^2 * d ]                     attention scores and weighted values (QK^T and AV)

with S = T + 1 tokens (the time/text token and T = window frames, padding included: it is computed). Biases,
LayerNorms, activations and the optimizer are left out (a few percent). HumanML3D preset: 22.1 GFLOP per sample.
MFU = FLOPs per sample x samples/s / dense bf16 peak; null where the device has no tabulated peak (CPUs).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch

BENCHMARKS_DIR = Path(__file__).resolve().parent
for _path in (BENCHMARKS_DIR, BENCHMARKS_DIR.parent):  # the sibling bench_* modules, and the project from a checkout
    if str(_path) not in sys.path:
        sys.path.insert(0, str(_path))

import bench_data  # noqa: E402
import bench_eval  # noqa: E402
import bench_sampling  # noqa: E402
import bench_train  # noqa: E402

from mfm.flops import PeakLookup, TrainingFlops, dense_bf16_peak, model_flops_utilisation  # noqa: E402
from mfm.model import ModelConfig, count_parameters  # noqa: E402
from pipeline.config import TrainConfig, load_config  # noqa: E402
from pipeline.data.stream import LoaderOptions, open_manifest  # noqa: E402
from pipeline.distributed import Dist  # noqa: E402
from pipeline.evaluation.config import load_eval_config  # noqa: E402
from pipeline.training.trainer import Trainer, draw_for_batch, model_config_for  # noqa: E402

FIGURES = ("train_fp32", "train_optimised", "equal_loss", "sampling_one", "sampling_batch", "sampling_one_optimised",
           "sampling_batch_optimised", "sampling_difference", "data_loader", "data_wait", "evaluator",
           "evaluator_optimised")
"""The measured figures, in the order they run (plus ``suite_wall`` at the end)."""

TEXT_DIM = 512  # HumanML3D's pooled CLIP ViT-B/32 text embedding
EQUAL_LOSS_RTOL = 2e-2
"""Expected bound on |bf16 loss - fp32 loss| / |fp32 loss|. bf16 keeps 8 significant bits (about 2-3 decimal digits,
relative rounding error 2^-9 = 0.2 %); matmuls accumulate in fp32 and the model's LayerNorms and the loss run in
fp32, so the loss itself agrees to about 1e-3. 2e-2 leaves a margin and still catches a wrong step (a missed mask,
a dtype bug), which moves the loss by far more."""


# ---------------------------------------------------------------------------------------------------------------
# Sizes and options
# ---------------------------------------------------------------------------------------------------------------

EVAL_TASKS = ("all", "edits", "main")
"""The evaluator's work: all (editing, FLAME metrics, MultiModality), edits (all but MultiModality, whose 30
repetitions per text a CPU cannot afford at the full model size) or main (text-to-motion only)."""
"""Evaluator work per replication: 'all' = the protocol's editing tasks, FLAME and MultiModality too; 'main' = the
text-to-motion metrics only (generation, embeddings, FID/diversity/R-precision), for a CPU run of the full model."""


@dataclasses.dataclass(frozen=True)
class SuiteSize:
    """How big every figure is: the training preset and shapes, steps, sampling batch, loader and evaluator sizes."""

    name: str
    preset: str
    """configs/<preset>.yaml: the model, optimizer and data settings of both training steps."""
    batch_size: int
    window: int
    steps: int
    warmup: int
    sampling_batch: int
    sampling_repeats: int
    clips: int
    """Synthetic clips built for the loader (about 80 % land in the train split; the stream cycles epochs), in about
    32 shards: enough that each of 8 loader workers' shard slots holds a batch of 128 (1,024 clips held 96 per slot,
    and the loader refused, seen on an H200)."""
    loader_batches: int
    eval_items: int
    eval_batch_size: int
    eval_protocol: str
    eval_tasks: str


FULL = SuiteSize(name="full", preset="humanml3d", batch_size=128, window=196, steps=30, warmup=5, sampling_batch=256,
                 sampling_repeats=10, clips=2048, loader_batches=50, eval_items=4384, eval_batch_size=256,
                 eval_protocol="full", eval_tasks="all")
SMOKE = SuiteSize(name="smoke", preset="tiny", batch_size=4, window=24, steps=2, warmup=1, sampling_batch=8,
                  sampling_repeats=2, clips=48, loader_batches=4, eval_items=16, eval_batch_size=16,
                  eval_protocol="fast", eval_tasks="main")


@dataclasses.dataclass(frozen=True)
class SuiteOptions:
    """The resolved command line."""

    out: Path
    size: SuiteSize
    device: str
    compile: bool
    workers: int
    optimised_precision: str
    """'bf16' where autocast supports it on the device, else 'no' (the optimised step then runs fp32)."""
    argv: tuple[str, ...] = ()
    """The command line, recorded in the results."""


def optimised_precision(device: str) -> str:
    """bf16 autocast where the device supports it: a CUDA GPU with native bf16 (Ampere and later; an older GPU only
    emulates it, slower than fp32) or torch's CPU autocast (native on CPUs with AVX-512 BF16 or AMX)."""
    if device == "cuda":
        return "bf16" if torch.cuda.is_bf16_supported(including_emulation=False) else "no"
    return "bf16" if torch.amp.is_autocast_available("cpu") else "no"


def cpu_model_name() -> str:
    """The processor's marketing name (Linux /proc/cpuinfo), else what ``platform`` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text(encoding="utf-8", errors="replace").splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def device_name(device: str) -> str:
    """What the results name the device by: the CUDA device's name (the peak table's key), or the CPU's model."""
    if device == "cuda":
        return torch.cuda.get_device_name(0)
    return f"cpu: {cpu_model_name()}, {os.cpu_count()} logical cores"


# ---------------------------------------------------------------------------------------------------------------
# Training figures
# ---------------------------------------------------------------------------------------------------------------


def training_config(options: SuiteOptions, manifest: Path, out_dir: Path, precision: str,
                    compiled: bool) -> TrainConfig:
    """The size's preset with the suite's shapes, data, precision and compile setting; nothing is written to disk."""
    size = options.size
    overrides = [f"data.manifest={manifest}", f"data.batch_size={size.batch_size}", f"data.window={size.window}",
                 f"data.num_workers={options.workers}", "data.format=tar", "optim.grad_accum=1",
                 f"train.out_dir={out_dir}", "train.wandb=disabled", f"train.mixed_precision={precision}",
                 f"train.compile={str(compiled).lower()}", "train.seed=0"]
    return load_config(TrainConfig, size.preset, overrides)


def probe_loss(trainer: Trainer) -> float:
    """The training step's loss on a fixed batch with fixed flow draws (t, noise, dropped conditions), at the
    trainer's initial weights (every Trainer built with the same seed starts from the same ones).

    Dropout is off for this one step (eval mode): dropout masks are drawn differently by fp32 and bf16 kernels, and
    the check is about the arithmetic. The step still updates the weights, like any step."""
    batch = bench_train.random_batches(trainer, count=1)[0]
    draws = draw_for_batch(batch, trainer.model_config.cond_drop_prob, torch.Generator().manual_seed(1))
    trainer.model.eval()
    try:
        *_, result = trainer.train_step([batch], draws=[draws]) + trainer.settle()
    finally:
        trainer.model.train()
    trainer.step += 1
    return result.loss


@dataclasses.dataclass
class TrainingRun:
    """What one Trainer measured: its probe loss, its step on random batches and, optionally, fed by the loader."""

    loss: float
    timing: dict[str, Any]
    model_config: ModelConfig
    flops_per_sample: float
    loader_timing: dict[str, Any] | None = None


def run_training(options: SuiteOptions, cfg: TrainConfig, *, with_loader: bool) -> TrainingRun:
    """Build a Trainer for ``cfg`` (its own Dist: accelerate's precision is process-wide state, so the fp32 and the
    optimised trainer cannot coexist), take the probe step, then time it (bench_train.measure)."""
    size = options.size
    with Dist(mixed_precision=cfg.train.mixed_precision, cpu=options.device == "cpu") as dist:
        trainer = Trainer(cfg, dist)
        loss = probe_loss(trainer)
        timing = bench_train.measure(trainer, "random", size.steps, size.warmup)
        loader_timing = bench_train.measure(trainer, "loader", size.steps, size.warmup) if with_loader else None
        flops = TrainingFlops(dist.unwrap(trainer.model)).per_sample(cfg.data.window)
        return TrainingRun(loss, timing, trainer.model_config, flops, loader_timing)


def training_figure(name: str, run: TrainingRun, cfg: TrainConfig, peak: PeakLookup, device: str) -> dict[str, Any]:
    """Samples/s from the median step time (warm-up excluded), with FLOPs, MFU and peak memory."""
    timing = run.timing
    step_s = timing["step_s_median"]
    samples_per_s = cfg.data.batch_size * cfg.optim.grad_accum / step_s
    flops = run.flops_per_sample
    mfu = model_flops_utilisation(flops * samples_per_s, peak.tflops)
    return {
        "figure": name, "value": round(samples_per_s, 2), "unit": "samples/s",
        "s_per_step": step_s, "s_per_step_p90": timing["step_s_p90"], "samples_per_s_mean": timing["samples_per_s"],
        "batch_size": cfg.data.batch_size, "window": cfg.data.window, "params_m": timing["params_m"],
        "precision": "bf16 autocast" if cfg.train.mixed_precision == "bf16" else "fp32",
        "compile": cfg.train.compile, "fused_adamw": device == "cuda",
        "gflop_per_sample": round(flops / 1e9, 4), "achieved_tflops": round(flops * samples_per_s / 1e12, 4),
        "mfu": None if mfu is None else round(mfu, 5), "mfu_note": None if mfu is not None else peak.source,
        "peak_mem_mb": timing["peak_mem_mb"], "peak_mem_kind": timing["peak_mem_kind"],
        "steps": timing["steps"], "warmup": timing["warmup"], "threads": timing["threads"],
    }


def equal_loss_figure(fp32_loss: float, optimised_loss: float, precision: str) -> dict[str, Any]:
    """Relative difference of the two probe losses (same batch, weights and draws)."""
    rel = abs(optimised_loss - fp32_loss) / max(abs(fp32_loss), 1e-12)
    return {"figure": "equal_loss", "value": rel, "unit": "relative difference",
            "loss_fp32": fp32_loss, "loss_optimised": optimised_loss,
            "optimised_precision": "bf16 autocast" if precision == "bf16" else "fp32",
            "tolerance": EQUAL_LOSS_RTOL if precision == "bf16" else 0.0,
            "within_tolerance": rel <= (EQUAL_LOSS_RTOL if precision == "bf16" else 0.0),
            "note": "same batch, initial weights and flow draws; dropout off for this step"}


def data_wait_figure(run: TrainingRun, workers: int) -> dict[str, Any]:
    """How much of the loader-fed step's wall time went to waiting for batches (issue 13's bar: well under 2 %)."""
    timing = run.loader_timing
    if timing is None:
        raise ValueError("the data-wait figure needs a training run fed by the loader (with_loader=True)")
    return {"figure": "data_wait", "value": timing["data_wait_frac"], "unit": "fraction of wall time",
            "num_workers": workers, "s_per_step": timing["step_s_median"],
            "samples_per_s_with_loader": timing["samples_per_s"], "steps": timing["steps"],
            "note": "the optimised step fed by pipeline.data.stream.MotionLoader; waiting for batches over the timed span"}


# ---------------------------------------------------------------------------------------------------------------
# Sampling, loader and evaluator figures
# ---------------------------------------------------------------------------------------------------------------


def sampler_precision(options: SuiteOptions) -> str:
    """The sampler's optimised precision: bf16 autocast where the optimised training step has it, else fp32."""
    return "bf16" if options.optimised_precision == "bf16" else "fp32"


def sampling_figures(options: SuiteOptions, model_config: ModelConfig) -> list[dict[str, Any]]:
    """10 Euler steps with CFG 2.5 for one motion, then per motion at the size's large batch: fp32
    (``sampling_one`` / ``sampling_batch``), at :func:`sampler_precision` (``*_optimised``), and the largest
    |optimised − fp32| of the large batch's motions from the same noise (``sampling_difference``)."""
    size = options.size
    model = bench_sampling.preset_model(model_config, options.device)
    parameters = count_parameters(model)
    if options.compile:
        model = bench_sampling.compiled_for_sampling(model, options.device)
    settings = bench_sampling.SamplingSettings(device=options.device, frames=size.window, steps=10, solver="euler",
                                               guidance=2.5, repeats=size.sampling_repeats, warmup=1,
                                               compile=options.compile)
    figures = []
    with torch.inference_mode():
        for suffix, precision in (("", "fp32"), ("_optimised", sampler_precision(options))):
            for name, batch in (("sampling_one", 1), ("sampling_batch", size.sampling_batch)):
                record = bench_sampling.measure_sampling(model, model_config, batch,
                                                         dataclasses.replace(settings, precision=precision))
                figures.append({"figure": name + suffix, "value": record["ms_per_motion"], "unit": "ms/motion",
                                "batch_size": batch, "median_batch_s": record["median_batch_s"],
                                "min_batch_s": record["min_batch_s"], "nfe": record["nfe"], "solver": "euler",
                                "guidance": 2.5, "frames": size.window, "repeats": record["repeats"],
                                "compile": options.compile, "precision": precision,
                                "compile_s": record.get("compile_s"), "parameters": parameters})
        difference = bench_sampling.precision_difference(
            model, model_config, size.sampling_batch,
            dataclasses.replace(settings, precision=sampler_precision(options)))
    figures.append({"figure": "sampling_difference", "value": difference["max_abs_difference"],
                    "unit": "max abs difference, optimised vs fp32 (normalised features)",
                    "mean_abs_difference": difference["mean_abs_difference"], "fp32_std": difference["fp32_std"],
                    "precision": sampler_precision(options), "batch_size": size.sampling_batch,
                    "state_dtype": difference["state_dtype"]})
    return figures


def loader_figure(options: SuiteOptions, manifest_path: Path, cfg: TrainConfig) -> dict[str, Any]:
    """The training split streamed with the training step's loader settings (bench_data.measure), alone: the
    loader's own ceiling, to set beside the step's rate."""
    manifest = open_manifest(manifest_path)
    loader_options = LoaderOptions(batch_size=cfg.data.batch_size, num_workers=options.workers, seed=cfg.data.seed,
                                   window=cfg.data.window, unit_length=cfg.data.unit_length,
                                   shuffle_buffer=cfg.data.shuffle_buffer, backend="webdataset")
    record = bench_data.measure(manifest, "train", loader_options, options.size.loader_batches, 0, 1)
    return {"figure": "data_loader", "value": record["samples_per_s"], "unit": "samples/s",
            "batches_per_s": record["batches_per_s"], "batch_size": record["batch_size"],
            "num_workers": record["num_workers"], "window": cfg.data.window, "batches": record["batches"],
            "first_batch_s": record["first_batch_s"], "backend": record["backend"],
            "feature_dim": manifest.data["feature_spec"]["dim"], "text_dim": manifest.data["text_encoder"]["dim"]}


def evaluator_figures(options: SuiteOptions) -> list[dict[str, Any]]:
    """The evaluation job (bench_eval.run_evaluation_bench) as it was and as issue 26 runs it, in one run:
    ``evaluator``, fp32 with the editing tasks in every replication (one replication measured); and
    ``evaluator_optimised``, the generator's passes at the sampler's precision (:func:`sampler_precision`) with one
    single editing pass (``tasks.editing_passes=single``; two replications measured, the first with the pass).
    Each: the time and the generator's passes per replication averaged over the protocol's replications, and the
    protocol's estimated wall time (the ground truth once + every replication)."""
    size = options.size
    editing = size.eval_tasks in ("all", "edits")
    # Where the protocol has replications with and without the editing tasks (the single pass; the fast protocol's
    # editing_replications 1 of 3), a replication of each kind is measured.
    some_edit = load_eval_config(size.eval_protocol).tasks.editing_replications > 0
    base = bench_eval.EvalBenchSettings(
        items=size.eval_items, protocol=size.eval_protocol, replications=2 if editing and some_edit else 1, steps=10,
        batch_size=size.eval_batch_size, model_preset=size.preset,
        editing=bench_eval.EDITING_TASKS if editing else (), flame=editing, multimodality=size.eval_tasks == "all",
        device=options.device, text_dim=TEXT_DIM)
    runs = (("evaluator", base),
            ("evaluator_optimised", dataclasses.replace(base, precision=sampler_precision(options),
                                                        noise_device="model", **(
                {"replications": 2, "editing_passes": "single"} if editing else {}))))
    figures = []
    for name, settings in runs:
        record = bench_eval.run_evaluation_bench(settings)
        if record is None:  # not rank 0: the suite runs as one process, so this does not happen
            raise RuntimeError("the evaluator bench returned no record")
        estimate = record["protocol_estimate"]
        phases = record["phases_s"]
        metric_s = phases.get("features", 0.0) + phases.get("metrics", 0.0)
        figures.append({
            "figure": name, "value": round(size.eval_items / estimate["s_per_replication"], 3),
            "unit": "test motions/s", "items": size.eval_items, "protocol": size.eval_protocol,
            "tasks": size.eval_tasks, "precision": record["precision"], "editing_passes": record["editing_passes"],
            "single_pass_edits": record["single_pass_edits"], "replication_s": estimate["s_per_replication"],
            "replication_cpu_s": estimate["cpu_s_per_replication"],
            "model_calls_per_replication": estimate["model_calls_per_replication"],
            "model_rows_per_replication": estimate["model_rows_per_replication"],
            "full_protocol_s_estimate": estimate["s"], "protocol_replications": estimate["replications"],
            "measured_replications": [r["wall_s"] for r in record["per_replication"]],
            "metric_motions_per_s": round(size.eval_items * settings.replications / metric_s, 2) if metric_s else None,
            "generation_ms_per_motion": round(1000 * record["seconds_per_motion"], 3),
            "phases_s": phases, "batch_size": size.eval_batch_size, "model_preset": size.preset})
    return figures


# ---------------------------------------------------------------------------------------------------------------
# The run and its reports
# ---------------------------------------------------------------------------------------------------------------


def environment_record(options: SuiteOptions, peak: PeakLookup) -> dict[str, Any]:
    """The header of both reports: what ran where (a figure means nothing without its device and versions)."""
    return {"figure": "environment", "device": options.device, "device_name": device_name(options.device),
            "torch": torch.__version__, "cuda": torch.version.cuda if options.device == "cuda" else None,
            "torch_cuda_build": torch.version.cuda, "python": platform.python_version(),
            "threads": torch.get_num_threads(), "dense_bf16_peak_tflops": peak.tflops, "peak_source": peak.source,
            "size": options.size.name, "preset": options.size.preset, "compile": options.compile,
            "workers": options.workers, "optimised_precision": options.optimised_precision,
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "argv": list(options.argv)}


def run_suite(options: SuiteOptions, emit: Callable[[dict[str, Any]], None]) -> list[dict[str, Any]]:
    """Measure every figure in :data:`FIGURES` order, passing each record to ``emit`` as soon as it exists."""
    start = time.perf_counter()
    peak = dense_bf16_peak(options.device, device_name(options.device))
    records: list[dict[str, Any]] = []

    def add(record: dict[str, Any]) -> None:
        records.append(record)
        emit(record)

    add(environment_record(options, peak))
    size = options.size
    with tempfile.TemporaryDirectory(prefix="gpu-suite-") as tmp:
        manifest = bench_data.build_synthetic(size.clips, Path(tmp) / "ds", text_dim=TEXT_DIM, formats=("tar",))
        fp32_cfg = training_config(options, manifest, Path(tmp) / "fp32", "no", compiled=False)
        fp32 = run_training(options, fp32_cfg, with_loader=False)
        add(training_figure("train_fp32", fp32, fp32_cfg, peak, options.device))
        opt_cfg = training_config(options, manifest, Path(tmp) / "optimised", options.optimised_precision,
                                  compiled=options.compile)
        optimised = run_training(options, opt_cfg, with_loader=True)
        add(training_figure("train_optimised", optimised, opt_cfg, peak, options.device))
        add(equal_loss_figure(fp32.loss, optimised.loss, options.optimised_precision))
        for record in sampling_figures(options, model_config_for(open_manifest(manifest), fp32_cfg.model)):
            add(record)
        add(loader_figure(options, manifest, opt_cfg))
        add(data_wait_figure(optimised, options.workers))
    for record in evaluator_figures(options):
        add(record)
    add({"figure": "suite_wall", "value": round(time.perf_counter() - start, 2), "unit": "s"})
    return records


def format_number(value: Any) -> str:
    """A table cell: thousands separators, about three significant digits for small numbers, n/a for None."""
    if value is None:
        return "n/a"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return str(value)
    if isinstance(value, int):
        return f"{value:,}"
    if value != 0 and abs(value) < 0.01:
        return f"{value:.3g}"
    return f"{value:,.3f}".rstrip("0").rstrip(".") if abs(value) < 100 else f"{value:,.1f}"


DETAILS: dict[str, tuple[str, ...]] = {
    "train_fp32": ("s_per_step", "mfu", "achieved_tflops", "gflop_per_sample", "peak_mem_mb", "precision", "compile",
                   "batch_size", "window"),
    "equal_loss": ("loss_fp32", "loss_optimised", "optimised_precision", "tolerance", "within_tolerance"),
    "sampling_one": ("batch_size", "median_batch_s", "nfe", "guidance", "frames", "compile", "precision"),
    "data_loader": ("batches_per_s", "batch_size", "num_workers", "first_batch_s"),
    "data_wait": ("num_workers", "s_per_step", "samples_per_s_with_loader"),
    "sampling_difference": ("mean_abs_difference", "fp32_std", "precision", "batch_size", "state_dtype"),
    "evaluator": ("items", "protocol", "tasks", "precision", "editing_passes", "replication_s", "replication_cpu_s",
                  "model_calls_per_replication", "model_rows_per_replication", "full_protocol_s_estimate",
                  "metric_motions_per_s", "generation_ms_per_motion"),
}
DETAILS["train_optimised"] = DETAILS["train_fp32"]
DETAILS["sampling_batch"] = DETAILS["sampling_one_optimised"] = DETAILS["sampling_one"]
DETAILS["sampling_batch_optimised"] = DETAILS["sampling_one"]
DETAILS["evaluator_optimised"] = DETAILS["evaluator"]


def details(record: dict[str, Any]) -> str:
    """The record's secondary fields worth a glance, ``key value`` pairs; MFU as a percentage."""
    parts = []
    for key in DETAILS.get(record["figure"], ()):
        value = record.get(key)
        if key == "mfu":
            parts.append("MFU n/a" if value is None else f"MFU {100 * value:.2f} %")
        else:
            parts.append(f"{key} {format_number(value)}")
    return ", ".join(parts)


def markdown_report(records: Sequence[dict[str, Any]]) -> str:
    """results.md: the environment, the dense bf16 peak with its source, each training figure's MFU, the table."""
    env = records[0]
    peak = env["dense_bf16_peak_tflops"]
    cuda = f"CUDA {env['cuda'] or 'not used'} (torch built for CUDA {env['torch_cuda_build'] or 'none'})"
    run = (f"size {env['size']} (configs/{env['preset']}.yaml), compile {env['compile']}, loader workers "
           f"{env['workers']}, optimised precision {env['optimised_precision']}, started {env['started']}")
    lines = ["# GPU suite results", "",
             f"- device: {env['device_name']} ({env['device']}, {env['threads']} torch threads)",
             f"- torch {env['torch']}, {cuda}, Python {env['python']}",
             f"- dense bf16 peak: {'n/a' if peak is None else f'{peak} TFLOP/s'} ({env['peak_source']})",
             f"- {run}"]
    for record in records:
        if record["figure"] in ("train_fp32", "train_optimised"):
            mfu = "n/a" if record["mfu"] is None else f"{100 * record['mfu']:.2f} %"
            lines.append(f"- MFU of {record['figure']}: {mfu} ({format_number(record['achieved_tflops'])} TFLOP/s "
                         f"achieved, {format_number(record['gflop_per_sample'])} GFLOP per sample)")
    lines += ["", "| figure | value | unit | details |", "|---|---|---|---|"]
    for record in records[1:]:
        lines.append(f"| {record['figure']} | {format_number(record['value'])} | {record['unit']} | "
                     f"{details(record)} |")
    return "\n".join(lines) + "\n"


def write_results(out: Path, records: Sequence[dict[str, Any]]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records), encoding="utf-8")
    (out / "results.md").write_text(markdown_report(records), encoding="utf-8")


def parse_options(argv: Sequence[str] | None) -> SuiteOptions:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="folder for results.jsonl and results.md")
    parser.add_argument("--smoke", action="store_true", help="tiny model and shapes (a CPU test in seconds)")
    parser.add_argument("--device", choices=("cuda", "cpu"), default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--compile", action=argparse.BooleanOptionalAction, default=None,
                        help="torch.compile the optimised step and the sampler (default: on CUDA only)")
    parser.add_argument("--workers", type=int, help="loader workers (default 8 on CUDA, 0 on CPU and in --smoke)")
    parser.add_argument("--steps", type=int, help="timed training steps (default 30; smoke 2)")
    parser.add_argument("--warmup", type=int, help="untimed training steps first (default 5; smoke 1)")
    parser.add_argument("--batch-size", type=int, help="training batch (default 128; smoke 4)")
    parser.add_argument("--sampling-batch", type=int, help="the large sampling batch (default 256; smoke 8)")
    parser.add_argument("--repeats", type=int, help="timed sampling calls per batch size (default 10; smoke 2)")
    parser.add_argument("--eval-items", type=int, help="synthetic test-set size (default 4384; smoke 16)")
    parser.add_argument("--eval-tasks", choices=EVAL_TASKS, help="evaluator work: all, edits (no MultiModality) or "
                                                                 "main (default all; smoke main)")
    parser.add_argument("--threads", type=int, help="torch CPU intra-op threads (default: torch's)")
    args = parser.parse_args(argv)
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: no CUDA device is visible")
    size = SMOKE if args.smoke else FULL
    changes = {"steps": args.steps, "warmup": args.warmup, "batch_size": args.batch_size,
               "sampling_batch": args.sampling_batch, "sampling_repeats": args.repeats, "eval_items": args.eval_items,
               "eval_tasks": args.eval_tasks}
    size = dataclasses.replace(size, **{k: v for k, v in changes.items() if v is not None})
    if (size.steps < 1 or size.warmup < 0 or size.batch_size < 1 or size.sampling_batch < 1
            or size.sampling_repeats < 1 or size.eval_items < 2):
        parser.error("need --steps >= 1, --warmup >= 0, --batch-size >= 1, --sampling-batch >= 1, --repeats >= 1, "
                     "--eval-items >= 2")
    if args.threads:
        torch.set_num_threads(args.threads)
    workers = args.workers if args.workers is not None else (8 if args.device == "cuda" and not args.smoke else 0)
    compiled = args.compile if args.compile is not None else args.device == "cuda"
    return SuiteOptions(out=args.out, size=size, device=args.device, compile=compiled, workers=workers,
                        optimised_precision=optimised_precision(args.device),
                        argv=tuple(sys.argv[1:] if argv is None else argv))


def main(argv: Sequence[str] | None = None) -> int:
    options = parse_options(argv)
    records = run_suite(options, lambda record: print(json.dumps(record), flush=True))
    write_results(options.out, records)
    bad = [r["figure"] for r in records if isinstance(r.get("value"), float) and not math.isfinite(r["value"])]
    if bad:
        print(f"non-finite figures: {', '.join(bad)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
