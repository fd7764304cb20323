"""Train the MFM flow-matching Transformer.

    accelerate launch launch/train.py                         # embedded default: DeepMimic clips, CPU-sized model
    accelerate launch launch/train.py --config humanml3d data.manifest=data/hml/manifest.json
    python launch/train.py --config tiny train.max_steps=20 model.num_layers=2

Settings: a preset from configs/ (``--config NAME`` or a YAML path; default ``default``) then ``key.sub=value``
overrides, type-checked against pipeline/config.py. The run folder (train.out_dir: new, empty, or a run's) gets
config.yaml, metrics.jsonl and checkpoints/step-XXXXXXXX/ (resume=auto continues from the newest one that
verifies). Exit code: 0 when train.max_steps is reached, 128 + N after a clean stop on signal N (143 SIGTERM,
130 SIGINT), 2 for settings refused before training and for bad data (a shard or record that contradicts the
manifest, a manifest whose dataset id is not the one its shard list derives, found before or during training: every rank stops at the same step, before its update), each one line on
stderr, 1 when a checkpoint could not be saved (e.g. a full disk: the run stops there) or for other errors.
"""

from __future__ import annotations

import argparse
import logging
import shlex
import sys
from pathlib import Path

from pipeline.checkpoint import CheckpointError, ResumeConflictError
from pipeline.config import (
    ConfigError,
    TrainConfig,
    available_presets,
    describe_config,
    load_config,
)
from pipeline.data.stages import DataError
from pipeline.distributed import Dist, MixedPrecisionError, ends_rank_processes
from pipeline.training.trainer import CheckpointSaveError, Trainer
from preprocess.shards import BuildConfig, ManifestError, OutputFolderError, build_dataset, default_out_dir

EMBEDDED_MANIFEST = default_out_dir("deepmimic", "minilm") / "manifest.json"


def ensure_embedded_dataset(manifest: str, dist: Dist) -> None:
    """Build the embedded default dataset (DeepMimic + MiniLM) the first time it is asked for; rank 0 builds,
    the others wait. Any other missing manifest is the user's to build: the trainer reports it."""
    if Path(manifest) != EMBEDDED_MANIFEST or EMBEDDED_MANIFEST.exists():
        return
    with dist.main_process_first():
        if dist.is_main and not EMBEDDED_MANIFEST.exists():
            dist.print0(f"building the embedded default dataset into {EMBEDDED_MANIFEST.parent} (once, ~1 min)")
            build_dataset(BuildConfig(out=EMBEDDED_MANIFEST.parent))


@ends_rank_processes
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="default",
                        help=f"preset name ({', '.join(available_presets(TrainConfig))}) or YAML path")
    parser.add_argument("--out", help="the run folder (the same as train.out_dir=...)")
    parser.add_argument("--print-config", action="store_true", help="print every key with its value, default and "
                        "meaning, then exit")
    parser.add_argument("overrides", nargs="*", metavar="key.sub=value", help="config overrides")
    args = parser.parse_intermixed_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        overrides = [*args.overrides, *([f"train.out_dir={args.out}"] if args.out else [])]
        cfg = load_config(TrainConfig, args.config, overrides)
        if args.print_config:
            print("\n".join(describe_config(cfg)))
            return 0
        with Dist(mixed_precision=cfg.train.mixed_precision, loss_scaling=True) as dist:
            ensure_embedded_dataset(cfg.data.manifest, dist)
            return Trainer(cfg, dist).fit()
    except ResumeConflictError as exc:
        given = sys.argv[1:] if argv is None else argv
        again = shlex.join(["python", "launch/train.py", *given, exc.continue_override])
        return fail(f"{exc}. The command that continues: {again}", 2)
    except (ConfigError, ManifestError, CheckpointError, FileNotFoundError, MixedPrecisionError,
            OutputFolderError, DataError) as exc:
        # refused before training (incl. strict verification: a bad shard, a manifest that is not its
        # dataset's), or bad data met while training; the message names the file and the reason
        return fail(str(exc), 2)
    except CheckpointSaveError as exc:
        return fail(str(exc), 1)


def fail(message: str, code: int) -> int:
    """One line on stderr instead of a traceback, for errors the user fixes by changing the command."""
    print(f"error: {message}", file=sys.stderr)
    return code


if __name__ == "__main__":
    sys.exit(main())
