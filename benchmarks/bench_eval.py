"""Wall time per phase of the evaluation job on a synthetic test set: one JSON line.

    python benchmarks/bench_eval.py --items 4384 --device cuda --batch-size 256         # HumanML3D-sized test set
    python benchmarks/bench_eval.py --items 64 --model-preset tiny --batch-size 32 --threads 1   # CPU smoke run
    python benchmarks/bench_eval.py --items 4384 --protocol full --replications 20 ...  # the whole published run

What runs: the job's own code (pipeline.evaluation.replications.PointRun and ground_truth_embeddings) on an in-memory
test set of ``--items`` motions (lengths uniform in [40, 196] frames, rounded down to multiples of 4, as the
HumanML3D test split), a model of ``--model-preset`` (configs/*.yaml, random weights: speed does not depend on
their values) and a randomly initialised contrastive evaluator of the default size. Phases (seconds, summed over
replications): ``ground_truth`` (evaluator embeddings and plausibility figures of the test set: done once per
test set), ``generation`` (sampling, ``--steps`` Euler steps with guidance), ``features`` (evaluator on generated
motions), ``joints`` (joint recovery + APE/AVE, joint variance, ADE/FDE), ``editing`` (trajectory-rewriting
generation), ``metrics`` (FID, R-precision, ... on rank 0). ``seconds_per_motion`` = generation seconds per
generated motion. ``--no-multimodality`` skips MultiModality's extra generations (a quicker smoke run).
``run_evaluation_bench(EvalBenchSettings(...))`` is the same measurement for other scripts (benchmarks/gpu_suite.py).

``--precision bf16`` samples and edits with the model's passes under bf16 autocast (``sampling.precision``);
``--noise-device model`` draws their seeded noise on the model's device (``sampling.noise_device``);
``--editing-passes single`` edits once, in the first replication, ``--editing-samples`` edits per preset
(``tasks.editing_passes``; default: the share of the test set MFM's 5,000 edits are of HumanML3D's 4,384 motions).
Per replication the record gives its wall time, phases and model passes (forward calls of the generator and the
motions they carried, per phase); ``protocol_estimate`` estimates the whole protocol: the ground truth once plus
``protocol.replications`` replications, those that edit (all with per_replication editing and the full protocol's
``tasks.editing_replications: 0``; the first with a single pass or the fast protocol's 1) like the measured ones
that edited, the others like the measured ones that did not. When the protocol has both kinds, ``--replications``
must be >= 2 so that both are measured (``--editing none``: every replication is alike).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import statistics
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from mfm.evaluators import ContrastiveEvaluator, ContrastiveEvaluatorConfig, save_evaluator  # noqa: E402
from mfm.model import MotionFlowTransformer  # noqa: E402
from mfm.solvers import NOISE_DEVICES  # noqa: E402
from pipeline.config import TrainConfig, load_config  # noqa: E402
from pipeline.data.stream import Manifest  # noqa: E402
from pipeline.distributed import Dist  # noqa: E402
from pipeline.evaluation.config import EDITS_PER_SINGLE_PASS, SamplingPoint, load_eval_config  # noqa: E402
from pipeline.evaluation.replications import (  # noqa: E402
    CheckpointContext, PhaseTimer, PointRun, ground_truth_embeddings, ground_truth_plausibility, plan_protocol)
from pipeline.evaluation.spaces import ContrastiveSpace, GroundTruthSet  # noqa: E402
from pipeline.generation.inference import TrainedModel  # noqa: E402

DIM, TEXT_DIM = 263, 384
EDITING_TASKS = ("prediction", "inbetween", "upper_body")
HUMANML3D_TEST_ITEMS = 4384


def single_pass_edits_for(items: int) -> int:
    """Edits per preset of a single editing pass on ``items`` test motions: the share MFM's 5,000 are of
    HumanML3D's 4,384 (5,000 at full size)."""
    return max(1, round(items * EDITS_PER_SINGLE_PASS / HUMANML3D_TEST_ITEMS))


@dataclasses.dataclass(frozen=True)
class EvalBenchSettings:
    """One evaluation-job measurement (the command-line options of this script, as a value the GPU suite can pass).
    ``text_dim``: width of the synthetic text embeddings (384 MiniLM, 512 HumanML3D's CLIP)."""

    items: int = 4384
    protocol: str = "fast"
    replications: int = 1
    steps: int = 10
    batch_size: int = 256
    model_preset: str = "humanml3d"
    editing: tuple[str, ...] = EDITING_TASKS
    flame: bool = True
    multimodality: bool = True
    device: str = "auto"
    text_dim: int = TEXT_DIM
    precision: str = "fp32"
    """``sampling.precision``: fp32, bf16 or auto."""
    editing_passes: str = "per_replication"
    """``tasks.editing_passes``: per_replication or single."""
    editing_samples: int | None = None
    """Single mode's edits per preset; None: :func:`single_pass_edits_for` the test set."""
    noise_device: str = "cpu"
    """``sampling.noise_device``: cpu or model."""


class PassCountingTimer(PhaseTimer):
    """The job's phase timer that also counts the generator's forward passes per phase: calls, and the motions
    (rows) they carried (a guided pass carries both halves, 2B rows)."""

    def __init__(self, device: torch.device, model: torch.nn.Module) -> None:
        super().__init__(device)
        self.current: str | None = None
        self.calls: dict[str, int] = defaultdict(int)
        self.rows: dict[str, int] = defaultdict(int)
        model.register_forward_pre_hook(self._count)

    def _count(self, module: torch.nn.Module, args: tuple) -> None:
        self.calls[self.current or "other"] += 1
        self.rows[self.current or "other"] += int(args[0].shape[0])

    @contextlib.contextmanager
    def phase(self, name: str) -> Iterator[None]:
        outer, self.current = self.current, name
        try:
            with super().phase(name):
                yield
        finally:
            self.current = outer

    def snapshot(self) -> dict[str, dict[str, float]]:
        return {"seconds": dict(self.seconds), "calls": dict(self.calls), "rows": dict(self.rows)}


def replication_record(before: dict[str, dict[str, float]], after: dict[str, dict[str, float]], wall_s: float,
                       cpu_s: float, edits: bool) -> dict[str, Any]:
    """One replication's wall time, this process's CPU time (on a CPU shared with other jobs the figure that does
    not depend on their load), phase seconds and model passes (calls and rows, per phase and in all), and whether
    it ran the editing tasks."""
    def delta(kind: str) -> dict[str, float]:
        return {k: v - before[kind].get(k, 0) for k, v in after[kind].items() if v - before[kind].get(k, 0)}

    calls, rows = delta("calls"), delta("rows")
    return {"wall_s": round(wall_s, 3), "cpu_s": round(cpu_s, 3), "edits": edits,
            "phases_s": {k: round(v, 3) for k, v in delta("seconds").items()},
            "model_calls": dict(calls), "model_rows": dict(rows), "model_calls_total": sum(calls.values()),
            "model_rows_total": sum(rows.values())}


def protocol_estimate(replications: list[dict[str, Any]], protocol_replications: int, editing_replications: int,
                      ground_truth_s: float) -> dict[str, Any]:
    """The whole protocol from the measured replications: ``editing_replications`` of its replications like the
    mean of the measured ones that edited, the others like the mean of those that did not; the ground truth once."""
    kinds = {edits: [r for r in replications if r["edits"] == edits] for edits in (True, False)}
    counts = {True: editing_replications, False: protocol_replications - editing_replications}
    missing = [f"{'with' if edits else 'without'} editing" for edits, count in counts.items()
               if count and not kinds[edits]]
    if missing:
        raise ValueError(f"the protocol has replications {' and '.join(missing)} that none of the measured ones "
                         "stands for: measure more replications (--replications 2)")
    total = {key: sum(count * statistics.fmean(r[key] for r in kinds[edits])
                      for edits, count in counts.items() if count)
             for key in ("wall_s", "cpu_s", "model_calls_total", "model_rows_total")}
    return {"replications": protocol_replications, "editing_replications": editing_replications,
            "s": round(ground_truth_s + total["wall_s"], 2),
            "s_per_replication": round(total["wall_s"] / protocol_replications, 3),
            "cpu_s_per_replication": round(total["cpu_s"] / protocol_replications, 3),
            "model_calls_per_replication": round(total["model_calls_total"] / protocol_replications, 1),
            "model_rows_per_replication": round(total["model_rows_total"] / protocol_replications, 1)}


def synthetic_ground_truth(items: int, seed: int, text_dim: int = TEXT_DIM) -> GroundTruthSet:
    rng = np.random.default_rng(seed)
    lengths = rng.integers(40, 197, items) // 4 * 4
    features = tuple((0.1 * rng.standard_normal((n, DIM))).astype(np.float32) for n in lengths)
    return GroundTruthSet(dataset_id="bench", split="test", ids=tuple(f"m{i:05d}" for i in range(items)),
                          features=features, lengths=lengths.astype(np.int64), captions=("a person walks",) * items,
                          caption_tokens=((),) * items, text_cond=rng.standard_normal((items, text_dim), np.float32),
                          actions=(None,) * items, dropped={}, key=f"bench-{items}-{seed}")


def bench_manifest(text_dim: int = TEXT_DIM) -> Manifest:
    return Manifest(data={"dataset_id": "bench", "feature_spec": {"dim": DIM, "skeleton": "humanml3d"},
                          "text_encoder": {"dim": text_dim}, "action_classes": [],
                          "normalization": {"mean": [0.0] * DIM, "std": [1.0] * DIM}}, location="<bench>")


def bench_model(preset: str, device: torch.device, text_dim: int = TEXT_DIM) -> TrainedModel:
    config = load_config(TrainConfig, preset, [f"model.cond_dim={text_dim}"]).model
    torch.manual_seed(0)
    model = MotionFlowTransformer(config).to(device).eval()
    data = {"dataset_id": "bench", "feature_spec": {"skeleton": "humanml3d", "dim": DIM, "fps": 20.0},
            "normalization": {"mean": [0.0] * DIM, "std": [1.0] * DIM}, "action_classes": []}
    return TrainedModel(model=model, model_config=config, checkpoint=Path("<bench>"), step=0, weights="model",
                        data=data, device=device, window=196)


def run_evaluation_bench(settings: EvalBenchSettings) -> dict[str, Any] | None:
    """Time the evaluation job's phases on a synthetic test set; the record on rank 0, None on other ranks.

    The ground-truth phase covers what the job does once per test set: the evaluator's embeddings and the
    plausibility figures of the clips (rank 0)."""
    overrides = [f"protocol.replications={settings.replications}", f"sampling.batch_size={settings.batch_size}",
                 f"tasks.editing={json.dumps(list(settings.editing))}", f"tasks.flame={str(settings.flame).lower()}",
                 f"protocol.multimodality={str(settings.multimodality).lower()}",
                 f"sampling.precision={settings.precision}", f"tasks.editing_passes={settings.editing_passes}",
                 f"sampling.noise_device={settings.noise_device}"]
    if settings.editing_passes == "single":
        edits = settings.editing_samples or single_pass_edits_for(settings.items)
        overrides += ["tasks.editing_replications=1", f"tasks.editing_samples={edits}"]
    protocol = load_eval_config(settings.protocol)  # the protocol's own replications and editing replications
    protocol_replications = protocol.protocol.replications
    editing_replications = 0 if not settings.editing else min(
        protocol_replications, 1 if settings.editing_passes == "single"
        else protocol.tasks.editing_replications or protocol_replications)
    cfg = load_eval_config(settings.protocol, overrides=overrides)
    cpu = settings.device == "cpu" or (settings.device == "auto" and not torch.cuda.is_available())
    with Dist(mixed_precision="no", cpu=cpu) as dist, tempfile.TemporaryDirectory() as tmp:
        trained = bench_model(settings.model_preset, dist.device, settings.text_dim)
        manifest = bench_manifest(settings.text_dim)
        evaluator_config = ContrastiveEvaluatorConfig(feature_dim=DIM, text_dim=settings.text_dim)
        torch.manual_seed(0)
        # the id a manifest reader derives from its (here empty) shard list, as a trained evaluator records it
        save_evaluator(Path(tmp) / "ev.safetensors", ContrastiveEvaluator(evaluator_config), evaluator_config,
                       manifest.dataset_id)
        space = ContrastiveSpace(Path(tmp) / "ev.safetensors", manifest, dist.device)
        gt = synthetic_ground_truth(settings.items, 0, settings.text_dim)
        timer = PassCountingTimer(dist.device, trained.model)
        with timer.phase("ground_truth"):
            emb, _ = ground_truth_embeddings(gt, space, dist, Path(tmp), settings.batch_size)
            gt_figures = (ground_truth_plausibility(gt, trained.skeleton, settings.batch_size)
                          if dist.is_main else None)
        plan = plan_protocol(cfg, len(gt), len(gt))
        measured = {bool(settings.editing) and r < plan.editing_replications for r in range(plan.replications)}
        needed = {edits for edits, count in ((True, editing_replications),
                                             (False, protocol_replications - editing_replications)) if count}
        if needed - measured:
            raise ValueError(f"the {settings.protocol} protocol has replications with and without the editing tasks: "
                             f"measure both (--replications 2; {plan.replications} measured)")
        ctx = CheckpointContext(trained, "bench", manifest, gt, space, emb, False, plan, None, np.arange(len(gt)),
                                gt_plausibility=gt_figures)
        ground_truth_s = timer.seconds["ground_truth"]  # once per test set; replications re-enter the phase
        start = time.perf_counter()
        run = PointRun(cfg, dist, ctx, SamplingPoint("euler", settings.steps, 2.5), timer)
        replications = []
        for replication in range(plan.replications):
            before, tick, cpu_tick = timer.snapshot(), time.perf_counter(), time.process_time()
            run.replicate(replication)
            edits = bool(run.edit_presets) and replication < plan.editing_replications
            replications.append(replication_record(before, timer.snapshot(), time.perf_counter() - tick,
                                                   time.process_time() - cpu_tick, edits))
        total = time.perf_counter() - start
        if not dist.is_main:
            return None
        result = run.result()
        estimate = protocol_estimate(replications, protocol_replications, editing_replications, ground_truth_s)
        return {"bench": "evaluation", "device": str(dist.device), "world_size": dist.world_size,
                "precision": run.precision, "noise_device": settings.noise_device,
                "editing_passes": plan.editing_passes,
                "single_pass_edits": plan.single_pass_edits, "per_replication": replications,
                "protocol_estimate": estimate,
                "items": settings.items, "protocol": settings.protocol, "replications": plan.replications,
                "steps": settings.steps, "batch_size": settings.batch_size, "model_preset": settings.model_preset,
                "text_dim": settings.text_dim, "editing": list(settings.editing), "flame": settings.flame,
                "multimodality": plan.multimodality, "mm_texts": plan.mm_num_texts, "mm_repeats": plan.mm_repeats,
                "phases_s": {k: round(v, 3) for k, v in timer.seconds.items()},
                "replications_wall_s": round(total, 3),
                "seconds_per_motion": round(result["generation_seconds_per_motion"], 5),
                "nfe": result["nfe"], "torch_threads": torch.get_num_threads()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--items", type=int, default=4384, help="test-set size (HumanML3D test split: 4384)")
    parser.add_argument("--protocol", choices=("full", "fast"), default="fast")
    parser.add_argument("--replications", type=int, default=1)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--model-preset", default="humanml3d", help="configs/<preset>.yaml model section")
    parser.add_argument("--editing", default=",".join(EDITING_TASKS), help="comma list or 'none'")
    parser.add_argument("--no-flame", action="store_true")
    parser.add_argument("--no-multimodality", action="store_true", help="skip MultiModality's extra generations")
    parser.add_argument("--text-dim", type=int, default=TEXT_DIM, help="text-embedding width (384 MiniLM, 512 CLIP)")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    parser.add_argument("--precision", choices=("fp32", "bf16", "auto"), default="fp32",
                        help="sampling.precision: the generator's passes in fp32 or under bf16 autocast")
    parser.add_argument("--editing-passes", choices=("per_replication", "single"), default="per_replication",
                        help="tasks.editing_passes")
    parser.add_argument("--editing-samples", type=int, help="single mode's edits per preset (default: "
                        f"items x {EDITS_PER_SINGLE_PASS} / {HUMANML3D_TEST_ITEMS})")
    parser.add_argument("--noise-device", choices=NOISE_DEVICES, default="cpu",
                        help="sampling.noise_device: seeded noise drawn on the CPU or on the model's device")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    settings = EvalBenchSettings(
        items=args.items, protocol=args.protocol, replications=args.replications, steps=args.steps,
        batch_size=args.batch_size, model_preset=args.model_preset,
        editing=() if args.editing == "none" else tuple(args.editing.split(",")), flame=not args.no_flame,
        multimodality=not args.no_multimodality, device=args.device, text_dim=args.text_dim,
        precision=args.precision, editing_passes=args.editing_passes, editing_samples=args.editing_samples,
        noise_device=args.noise_device)
    record = run_evaluation_bench(settings)
    if record is not None:
        print(json.dumps(record), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
