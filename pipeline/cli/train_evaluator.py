"""Train the project's evaluator (contrastive motion/text embedding + action classifier) on a dataset's shards.

    python launch/train_evaluator.py data.manifest=data/deepmimic-minilm/manifest.json
    python launch/train_evaluator.py data.manifest=/data/hml/manifest.json optim.steps=20000 model.out_dim=512
    torchrun --standalone --nproc_per_node 2 launch/train_evaluator.py data.manifest=...

Settings: pipeline/evaluation/evaluator_training.py EvaluatorTrainConfig (``--config YAML`` then ``key.sub=value``). The
evaluator is saved with its data manifest id under runs/evaluators/<dataset id>/ (``out_dir=``), where
launch/evaluate.py finds it by default; report.json holds its held-out retrieval accuracy.
Exit code: 0 done, 2 bad settings.
"""

from __future__ import annotations

import argparse
import logging
import sys

from pipeline.config import ConfigError, describe_config, load_config
from pipeline.distributed import Dist, ends_rank_processes
from pipeline.evaluation.evaluator_training import EvaluatorTrainConfig, train_evaluator
from preprocess.shards import ManifestError


def format_report(report: dict) -> str:
    lines = [f"evaluator {report.get('evaluator_id', '?')[:16]} on dataset {report['dataset_id'][:16]}: "
             f"{report.get('evaluator_path', '')}"]
    for split, entry in report["held_out"].items():
        scores = ", ".join(f"R@{k} {entry[f'retrieval_top{k}']:.3f}" for k in (1, 2, 3) if f"retrieval_top{k}" in entry)
        batch = entry.get("retrieval_batch_size")
        accuracy = entry.get("action_accuracy")
        lines.append(f"  {split}: {entry['num_items']} items; retrieval among {batch}: {scores or 'n/a'}"
                     + ("" if accuracy is None else f"; action accuracy {accuracy:.3f}"))
    return "\n".join(lines)


@ends_rank_processes
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", help="a YAML file of settings (defaults: pipeline/evaluation/evaluator_training.py)")
    parser.add_argument("--out", help="the output folder (the same as out_dir=...)")
    parser.add_argument("--print-config", action="store_true", help="print every key with its value, default and "
                        "meaning, then exit")
    parser.add_argument("overrides", nargs="*", metavar="key.sub=value", help="config overrides")
    args = parser.parse_intermixed_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        overrides = [*args.overrides, *([f"out_dir={args.out}"] if args.out else [])]
        cfg = load_config(EvaluatorTrainConfig, args.config, overrides)
    except (ConfigError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.print_config:
        print("\n".join(describe_config(cfg)))
        return 0
    try:
        with Dist(mixed_precision=cfg.mixed_precision) as dist:
            report = train_evaluator(cfg, dist)
            dist.print0(format_report(report))
    except (ManifestError, FileNotFoundError) as exc:  # a missing or unreadable dataset: the settings' to fix
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
