"""Export a training checkpoint as an inference folder (weights, normalisation, config.json, a Hub model card).

    python launch/export.py runs/default --out exported/default            # the run's newest checkpoint, EMA
    python launch/export.py runs/default/checkpoints/step-00012000 --out exported/s12k --weights model

Then, in Python::

    import torch
    from pipeline.generation.pretrained import MotionPipeline
    pipe = MotionPipeline.from_pretrained("exported/default", torch_dtype=torch.float32).to("cuda")
    out = pipe(prompt="a person walks in a circle", seconds=4.0, generator=torch.Generator().manual_seed(0))
    out.save("samples/circle")

or ``python launch/sample.py --checkpoint exported/default --text ...``. Exit code 0 done, 2 refused (one line).
"""

from __future__ import annotations

import argparse
import logging
import sys

from pipeline.generation.pretrained import PretrainedError, export_pretrained


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", help="a checkpoint folder, or a run folder (its newest complete checkpoint)")
    parser.add_argument("--out", required=True, help="a new or empty folder for the export")
    parser.add_argument("--weights", choices=("ema", "model"), default="ema", help="EMA (default) or raw weights")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        out = export_pretrained(args.checkpoint, args.out, weights=args.weights)
    except (PretrainedError, FileNotFoundError, ValueError) as err:
        print(f"export: {err}", file=sys.stderr)
        return 2
    print(f"exported to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
