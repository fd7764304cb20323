"""(Re)build the browsable ``index.html`` of an output folder; engine in pipeline/generation/browse.py. Sampling and evaluation
runs write it themselves; this is for folders written before, or after copying one elsewhere.

    python launch/browse.py out/walk          # launch/sample.py --out out/walk: animated stick figures, captions,
                                              # lengths and plausibility figures of every motion
    python launch/browse.py runs/default/eval # an evaluation folder (or the run folder: its eval/): the results
                                              # table (generated vs ground truth, mean ± CI) and plots/*.png

Open the page straight from disk (file://); it needs no server and no network.
"""

from __future__ import annotations

import argparse
import logging
import sys

from pipeline.generation.browse import MAX_MOTIONS, write_index


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("folders", nargs="+", metavar="DIR", help="sampling output, evaluation or run folder")
    p.add_argument("--max-motions", type=int, default=MAX_MOTIONS,
                   help=f"sample pages: embed the first N motions (default {MAX_MOTIONS}; 0: all); the others are "
                        "listed without a player")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    code = 0
    for folder in args.folders:
        try:
            path = write_index(folder, args.max_motions or None)
        except (OSError, ValueError, KeyError) as exc:
            print(f"error: {folder}: {exc}", file=sys.stderr)
            code = 2
            continue
        print(path.resolve().as_uri())
    return code


if __name__ == "__main__":
    sys.exit(main())
