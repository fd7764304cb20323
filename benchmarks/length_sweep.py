"""Does a sample say what its caption says at every clip length? The diagnostic behind "A turn is a rate, not an
angle" (docs/generator-study.md): each caption is sampled at several lengths and seeds, and the caption checks
(``mfm.caption_checks``) read each sample's count, side and place, and a turn's heading change in degrees.

    python benchmarks/length_sweep.py --checkpoint runs/cap9 [--lengths 40,60,90,130,196] [--seeds 0,1,2] \
        [--text "a person turns around to the left."] [--out sweep.json]

A model that heard the caption's total ("turns around": 180° however long the clip) turns about as far at 40 frames
as at 196; one that learnt the turn as a rate turns in proportion to the length. One JSON line per caption and
length: what each seed's sample shows ("+66°", "left/2"), and the share of them passing every check. Sampling is
launch/sample.py's (the model's own sampler unless --steps/--guidance/--guided-features/--smoothing say otherwise).
The default captions are the synthetic set's (``--source synthetic``) whose checks depend on the length.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np

from mfm.caption_checks import check_caption
from pipeline.generation.request import SampleRequest, bone_keeping_setting
from pipeline.generation.sampling import run_sampling

DEFAULT_TEXTS = (
    "a person turns around to the left.",
    "a person turns 90 degrees to the left.",
    "a person squats down and stands up 3 times.",
    "a person kicks forward with the left leg twice.",
    "a person raises both arms above the head and lowers them twice.",
    "a person jumps up in place 3 times.",
)


def sample_joints(checkpoint: str, texts: list[str], lengths: list[int], seed: int,
                  options: dict) -> list[np.ndarray]:
    """One motion per (text, length), in that order, as (T, J, 3) joints."""
    with tempfile.TemporaryDirectory() as folder:
        result = run_sampling(SampleRequest(checkpoint=checkpoint, out_dir=folder, texts=tuple(texts),
                                            lengths=tuple(lengths), seed=seed, video=False, bvh=False,
                                            progress=False, **options))
        return [np.load(Path(folder) / f["path"]) for sample in result["samples"] for f in sample["files"]
                if f["kind"] == "joints"]


def shown(check: dict) -> str:
    observed = check["observed"]
    if "heading_change_deg" in observed:
        return f"{observed['heading_change_deg']:+.0f}°"
    return "/".join(str(observed[key]) for key in check["checks"])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--text", action="append", help="caption (repeatable; default: the synthetic set's six)")
    p.add_argument("--lengths", default="40,60,90,130,196", help="frames, comma-separated")
    p.add_argument("--seeds", default="0,1,2", help="comma-separated")
    p.add_argument("--steps", type=int)
    p.add_argument("--guidance", type=float)
    p.add_argument("--guided-features", choices=("all", "pose"))
    p.add_argument("--smoothing", type=float)
    p.add_argument("--smoothing-keeps-bones", type=bone_keeping_setting, metavar="{true,false,smoothed}")
    p.add_argument("--device", default="cpu")
    p.add_argument("--model-weights", choices=("ema", "model"), default="ema",
                   help="the checkpoint's EMA weights (default) or its raw ones")
    p.add_argument("--out", type=Path, help="write every row as JSON here")
    args = p.parse_args(argv)

    texts = args.text or list(DEFAULT_TEXTS)
    lengths = [int(n) for n in args.lengths.split(",")]
    seeds = [int(s) for s in args.seeds.split(",")]
    options = dict(steps=args.steps, guidance=args.guidance, guided_features=args.guided_features,
                   smoothing=args.smoothing, smoothing_keeps_bones=args.smoothing_keeps_bones, device=args.device,
                   weights=args.model_weights)
    cells = [(text, n) for text in texts for n in lengths]
    checks: dict[tuple[str, int], list[dict]] = {cell: [] for cell in cells}
    for seed in seeds:
        joints = sample_joints(args.checkpoint, [t for t, _ in cells], [n for _, n in cells], seed, options)
        for cell, motion in zip(cells, joints):
            checks[cell].append(check_caption(motion, cell[0]))

    rows = []
    for (text, n), results in checks.items():
        passed = [all(r["checks"].values()) for r in results if r["checks"]]
        rows.append({"text": text, "frames": n, "observed": [r["observed"] for r in results],
                     "passed": float(np.mean(passed)) if passed else None})
        print(json.dumps({"text": text, "frames": n, "shown": [shown(r) for r in results],
                          "passed": rows[-1]["passed"]}, ensure_ascii=False), flush=True)
    if args.out is not None:
        args.out.write_text(json.dumps({"checkpoint": str(args.checkpoint), "seeds": seeds, "options": options,
                                        "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
