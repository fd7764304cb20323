"""Wall time per phase of the evaluation job on a synthetic test set: one JSON line.

    python benchmarks/bench_eval.py --items 4384 --device cuda --batch-size 256         # HumanML3D-sized test set
    python benchmarks/bench_eval.py --items 64 --model-preset tiny --batch-size 32 --threads 1   # CPU smoke run
    python benchmarks/bench_eval.py --items 4384 --protocol full --replications 20 ...  # the whole published run

What runs: the job's own code (pipeline.eval_replications.PointRun and ground_truth_embeddings) on an in-memory
test set of ``--items`` motions (lengths uniform in [40, 196] frames, rounded down to multiples of 4, as the
HumanML3D test split), a model of ``--model-preset`` (configs/*.yaml, random weights: speed does not depend on
their values) and a randomly initialised contrastive evaluator of the default size. Phases (seconds, summed over
replications): ``ground_truth`` (evaluator embeddings of the test set: done once, then cached), ``generation``
(sampling, ``--steps`` Euler steps with guidance), ``features`` (evaluator on generated motions), ``joints``
(joint recovery + APE/AVE, joint variance, ADE/FDE), ``editing`` (trajectory-rewriting generation),
``metrics`` (FID, R-precision, ... on rank 0). ``seconds_per_motion`` = generation seconds per generated motion.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from mfm.evaluators import ContrastiveEvaluator, ContrastiveEvaluatorConfig, save_evaluator  # noqa: E402
from mfm.model import MotionFlowTransformer  # noqa: E402
from pipeline.config import TrainConfig, load_config  # noqa: E402
from pipeline.data import Manifest  # noqa: E402
from pipeline.distributed import Dist  # noqa: E402
from pipeline.eval_config import SamplingPoint, load_eval_config  # noqa: E402
from pipeline.eval_replications import (CheckpointContext, PhaseTimer, PointRun, ground_truth_embeddings,  # noqa: E402
                                        plan_protocol)
from pipeline.eval_spaces import ContrastiveSpace, GroundTruthSet  # noqa: E402
from pipeline.inference import TrainedModel  # noqa: E402

DIM, TEXT_DIM = 263, 384


def synthetic_ground_truth(items: int, seed: int) -> GroundTruthSet:
    rng = np.random.default_rng(seed)
    lengths = rng.integers(40, 197, items) // 4 * 4
    features = tuple((0.1 * rng.standard_normal((n, DIM))).astype(np.float32) for n in lengths)
    return GroundTruthSet(dataset_id="bench", split="test", ids=tuple(f"m{i:05d}" for i in range(items)),
                          features=features, lengths=lengths.astype(np.int64), captions=("a person walks",) * items,
                          caption_tokens=((),) * items, text_cond=rng.standard_normal((items, TEXT_DIM), np.float32),
                          actions=(None,) * items, dropped={}, key=f"bench-{items}-{seed}")


def bench_manifest() -> Manifest:
    return Manifest(data={"dataset_id": "bench", "feature_spec": {"dim": DIM, "skeleton": "humanml3d"},
                          "text_encoder": {"dim": TEXT_DIM}, "action_classes": [],
                          "normalization": {"mean": [0.0] * DIM, "std": [1.0] * DIM}}, location="<bench>")


def bench_model(preset: str, device: torch.device) -> TrainedModel:
    config = load_config(TrainConfig, preset, ["model.cond_dim=384"]).model
    torch.manual_seed(0)
    model = MotionFlowTransformer(config).to(device).eval()
    data = {"dataset_id": "bench", "feature_spec": {"skeleton": "humanml3d", "dim": DIM, "fps": 20.0},
            "normalization": {"mean": [0.0] * DIM, "std": [1.0] * DIM}, "action_classes": []}
    return TrainedModel(model=model, model_config=config, checkpoint=Path("<bench>"), step=0, weights="model",
                        data=data, device=device, window=196)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--items", type=int, default=4384, help="test-set size (HumanML3D test split: 4384)")
    parser.add_argument("--protocol", choices=("full", "fast"), default="fast")
    parser.add_argument("--replications", type=int, default=1)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--model-preset", default="humanml3d", help="configs/<preset>.yaml model section")
    parser.add_argument("--editing", default="prediction,inbetween,upper_body", help="comma list or 'none'")
    parser.add_argument("--no-flame", action="store_true")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    editing = [] if args.editing == "none" else args.editing.split(",")
    overrides = [f"protocol.replications={args.replications}", f"sampling.batch_size={args.batch_size}",
                 f"tasks.editing={json.dumps(editing)}", f"tasks.flame={str(not args.no_flame).lower()}"]
    cfg = load_eval_config(args.protocol, overrides=overrides)
    cpu = args.device == "cpu" or (args.device == "auto" and not torch.cuda.is_available())
    with Dist(mixed_precision="no", cpu=cpu) as dist, tempfile.TemporaryDirectory() as tmp:
        trained = bench_model(args.model_preset, dist.device)
        manifest = bench_manifest()
        evaluator_config = ContrastiveEvaluatorConfig(feature_dim=DIM, text_dim=TEXT_DIM)
        torch.manual_seed(0)
        save_evaluator(Path(tmp) / "ev.safetensors", ContrastiveEvaluator(evaluator_config), evaluator_config, "bench")
        space = ContrastiveSpace(Path(tmp) / "ev.safetensors", manifest, dist.device)
        gt = synthetic_ground_truth(args.items, 0)
        timer = PhaseTimer(dist.device)
        with timer.phase("ground_truth"):
            emb, _ = ground_truth_embeddings(gt, space, dist, Path(tmp), args.batch_size)
        plan = plan_protocol(cfg, len(gt), len(gt))
        ctx = CheckpointContext(trained, "bench", manifest, gt, space, emb, False, plan, None, np.arange(len(gt)))
        start = time.perf_counter()
        run = PointRun(cfg, dist, ctx, SamplingPoint("euler", args.steps, 2.5), timer)
        for replication in range(plan.replications):
            run.replicate(replication)
        total = time.perf_counter() - start
        if dist.is_main:
            result = run.result()
            record = {"bench": "evaluation", "device": str(dist.device), "world_size": dist.world_size,
                      "items": args.items, "replications": plan.replications, "steps": args.steps,
                      "batch_size": args.batch_size, "model_preset": args.model_preset, "editing": editing,
                      "flame": not args.no_flame, "mm_texts": plan.mm_num_texts, "mm_repeats": plan.mm_repeats,
                      "phases_s": {k: round(v, 3) for k, v in timer.seconds.items()},
                      "replications_wall_s": round(total, 3),
                      "seconds_per_motion": round(result["generation_seconds_per_motion"], 5),
                      "nfe": result["nfe"], "torch_threads": torch.get_num_threads()}
            print(json.dumps(record), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
