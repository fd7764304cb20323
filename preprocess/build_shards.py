"""Build a dataset (tar + Parquet shards, manifest.json) from a motion source. With no arguments: the
embedded default, DeepMimic clips + MiniLM captions, into data/deepmimic-minilm. See docs/dataset-format.md.

    python preprocess/build_shards.py --source synthetic --num-clips 2000 --out /tmp/syn --workers 2
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a script: import the project, not preprocess/ siblings as top-level modules
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from mfm.text import TEXT_ENCODERS
from preprocess.processing import DEFAULT_MAX_FRAMES, LONG_CLIP_POLICIES
from preprocess.shards import (
    DEFAULT_SHARD_SIZE,
    NORMALIZATION_MODES,
    SHARD_FORMATS,
    BadInputError,
    BuildConfig,
    build_dataset,
    default_out_dir,
)
from preprocess.sources import SOURCES


def _key_value(text: str) -> tuple[str, object]:
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    for parse in (int, float):
        try:
            return key, parse(value)
        except ValueError:
            pass
    return key, {"true": True, "false": False, "none": None}.get(value.lower(), value)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add = p.add_argument
    add("--source", choices=sorted(SOURCES), default="deepmimic", help="motion source (default: deepmimic, shipped with pybullet)")
    add("--root", help="source data folder (HumanML3D/KIT-ML/AMASS checkout; not needed for deepmimic, synthetic)")
    add("--out", type=Path, help="output folder (default: data/<source>-<text encoder> under the current folder)")
    add("--text-encoder", choices=sorted(TEXT_ENCODERS), default="minilm", help="caption encoder (default: minilm, offline)")
    add("--text-weights", help="encoder weights: a local file/folder, or 'openai' for CLIP via open_clip's cache")
    add("--text-option", type=_key_value, action="append", default=[], metavar="KEY=VALUE",
        help="text encoder builder option, e.g. context_length=22 for CLIP (repeatable)")
    add("--token-features", action="store_true", help="also store per-token text features (for cross-attention)")
    add("--max-tokens", type=int, default=32, help="tokens kept per caption with --token-features (default: 32)")
    add("--shard-size", type=int, help=f"motions per shard (default: {DEFAULT_SHARD_SIZE}; the embedded DeepMimic set: 5)")
    add("--format", default=",".join(SHARD_FORMATS), help="comma-separated subset of tar,parquet (default: both)")
    add("--workers", type=int, default=1, help="processes for loading + feature extraction (default: 1)")
    add("--min-frames", type=int, help="shortest motion/caption span kept, in feature frames "
        "(default: HumanML3D's, 40; 24 for KIT)")
    add("--max-frames", type=lambda v: None if v.lower() == "none" else int(v), default=DEFAULT_MAX_FRAMES,
        help=f"longest motion kept, inclusive (default: {DEFAULT_MAX_FRAMES}, HumanML3D's len < 200; 'none': no limit)")
    add("--long-clips", choices=LONG_CLIP_POLICIES, default="skip",
        help="motions over --max-frames: skip them (HumanML3D) or cut them into --max-frames windows")
    add("--compat", action=argparse.BooleanOptionalAction, default=True,
        help="reproduce HumanML3D's feature-extraction quirks (default) or use the fixed IK (--no-compat)")
    add("--normalization", choices=NORMALIZATION_MODES, default="auto",
        help="Mean/Std: the dataset's official files (HumanML3D's Mean.npy/Std.npy at --root), recomputed over the "
             "train split, or auto (default): official when the files are there. The manifest says which")
    add("--num-clips", type=int, help="synthetic: number of clips")
    add("--seed", type=int, help="synthetic: random seed")
    add("--body-model", help="amass: SMPL-H body model file (required for AMASS): a model.npz of numeric arrays; a "
        "pickled one (.pkl, or an .npz holding Python objects) is refused unless --source-option "
        "unpickle_body_model=true, because unpickling runs any code the file carries: pass it only for a file you "
        "trust")
    add("--source-option", type=_key_value, action="append", default=[], metavar="KEY=VALUE",
        help="any other source option (repeatable), e.g. humanml3d/kit: features=auto|file|recompute (auto: read "
             "new_joint_vecs/ when present), verify=all|none|FRACTION (check feature files against new_joints/)")
    add("--strict", action="store_true", help="stop at the first bad input, naming its file and the reason")
    add("--overwrite", action="store_true", help="replace a complete dataset built here that is already in --out "
        "(only the files its manifest.json names are deleted; a folder that is no build of ours is refused)")
    add("--quiet", action="store_true", help="no progress bars")
    return p.parse_args(argv)


def config_from_args(args: argparse.Namespace) -> BuildConfig:
    shortcuts = {"num_clips": args.num_clips, "seed": args.seed, "body_model": args.body_model}
    source_options = {k: v for k, v in shortcuts.items() if v is not None} | dict(args.source_option)
    return BuildConfig(
        out=args.out or default_out_dir(args.source, args.text_encoder), source=args.source, root=args.root,
        source_options=source_options, text_encoder=args.text_encoder, text_weights=args.text_weights,
        text_options=dict(args.text_option), token_features=args.token_features, max_tokens=args.max_tokens,
        shard_size=args.shard_size, formats=tuple(f.strip() for f in args.format.split(",") if f.strip()),
        min_frames=args.min_frames, max_frames=args.max_frames, long_clips=args.long_clips, compat=args.compat,
        normalization=args.normalization, workers=args.workers, strict=args.strict, overwrite=args.overwrite, progress=False if args.quiet else None,
    )


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    args = parse_args(argv)
    try:
        config = config_from_args(args)
        manifest = build_dataset(config)
    except BadInputError as error:  # --strict and a bad item of the data: one line naming it
        print(f"build_shards: error: {error}", file=sys.stderr)
        return 1
    except (OSError, ValueError, KeyError, RuntimeError) as error:  # settings refused (a missing root, an
        # unknown source or option, an existing dataset without --overwrite, an --out folder that is no build of
        # ours): one line, exit 2 as every entry point
        print(f"build_shards: error: {error}", file=sys.stderr)
        return 2
    splits = ", ".join(f"{name} {s['num_motions']}" for name, s in manifest["splits"].items())
    report = manifest["skip_report"]
    ignored = report.get("ignored_files", {}).get("count", 0)  # files of the source folder never read
    print(f"{config.out}: {splits} motions; {report['total']} skipped; {ignored} ignored files; "
          f"dataset_id {manifest['dataset_id'][:16]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
