"""Fixtures shared by tests/test_evaluation*.py, and the torchrun entry of the multi-rank evaluation test.

    torchrun --standalone --nproc_per_node N tests/eval_worker.py CHECKPOINT EVALUATOR OUT_DIR

evaluates CHECKPOINT with a small fast protocol (every task: text-to-motion, MultiModality, FLAME, editing) and
writes the results under OUT_DIR (rank 0).
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

NUM_CLIPS = 80  # test split: 10 motions, so batches of 4 split unevenly over 2 ranks (4 + 4 + 2)
TINY_EVALUATOR = {"latent_dim": 32, "num_layers": 1, "num_heads": 2, "ff_dim": 64, "out_dim": 32,
                  "text_hidden_dim": 64, "dropout": 0.0}
SMALL_PROTOCOL = ["protocol.replications=2", "protocol.mm_num_texts=3", "protocol.mm_repeats=4",
                  "protocol.mm_times=2", "sampling.batch_size=4",
                  "tasks.editing=[prediction,upper_body]", "tasks.editing_replications=1", "output.wandb=disabled",
                  "output.plots=false"]


def build_synthetic_dataset(out: Path) -> Path:
    """The synthetic source with MiniLM captions (built once per folder; reused when the manifest exists)."""
    from preprocess.shards import BuildConfig, build_dataset

    manifest = out / "manifest.json"
    if not manifest.exists():
        build_dataset(BuildConfig(out=out, source="synthetic", source_options={"num_clips": NUM_CLIPS},
                                  formats=("tar",), progress=False))
    return manifest


def train_tiny_model(manifest: Path, run_dir: Path, *overrides: str, steps: int = 2) -> Path:
    """A few steps of the tiny preset in this process; returns the run folder (checkpoints at every step)."""
    from pipeline.config import TrainConfig, load_config
    from pipeline.distributed import Dist
    from pipeline.training.trainer import Trainer

    cfg = load_config(TrainConfig, "tiny", [f"data.manifest={manifest}", f"train.out_dir={run_dir}",
                                            f"train.max_steps={steps}", "train.save_every=1", "train.keep_last=0",
                                            "train.wandb=disabled", *overrides])
    with Dist(mixed_precision="no", cpu=True) as dist:
        assert Trainer(cfg, dist).fit() == 0
    return run_dir


def random_contrastive_evaluator(manifest: Path, path: Path) -> Path:
    """An untrained (seeded) evaluator saved for ``manifest``: enough to test the job's plumbing quickly."""
    from mfm.evaluators import (
        ContrastiveEvaluator,
        ContrastiveEvaluatorConfig,
        save_evaluator,
    )
    from pipeline.data.stream import open_manifest

    data = open_manifest(manifest)
    config = ContrastiveEvaluatorConfig(feature_dim=data.record_spec.feature_dim, text_dim=data.record_spec.text_dim,
                                        **TINY_EVALUATOR)
    torch.manual_seed(0)
    save_evaluator(path, ContrastiveEvaluator(config).eval(), config, data.dataset_id)
    return path


def main(checkpoint: str, evaluator: str, out_dir: str) -> int:
    from pipeline.distributed import Dist
    from pipeline.evaluation.config import load_eval_config
    from pipeline.evaluation.job import EvaluationJob

    torch.set_num_threads(1)  # the same kernels on every rank and in the 1-rank reference run
    overrides = [*SMALL_PROTOCOL, "sampling.steps=[2]", f"evaluator.path={evaluator}", f"output.dir={out_dir}"]
    cfg = load_eval_config("fast", overrides=overrides)
    with Dist(mixed_precision="no", cpu=True) as dist:
        results = EvaluationJob(cfg, dist).evaluate_checkpoint(checkpoint)
        assert (len(results) == 1) == dist.is_main, (dist.rank, len(results))
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
