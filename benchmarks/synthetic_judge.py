"""The judge of the synthetic preset's study (docs/generator-study.md, every run since its eleventh session): what a
checkpoint's motions show against the test split's clips and the captions' checks, as one JSON summary.

    python benchmarks/synthetic_judge.py --checkpoint runs/synthetic --out judge/   # about 4 minutes on 2 cores

* ``sheet``: the contact sheet of the first ``--rows`` test captions (first caption, the clip's length, the model's
  own sampler) at each of ``--seeds``, and the mean over the seeds of its figures against each sample's own clip:
  caption match, movement and jerk ratios, bone-length range and floor penetration (cm), foot skating, and the share
  of rows passing each caption check (count, place, turn angle, all), with ``all`` per seed. The sheets' PNG and
  JSON stay in ``--out``.
* ``in_place_rows``: the test rows whose caption says "in place", over the seeds, passing all their checks.
* ``jump_sweep``: "jumps up in place once / twice / 3 times" at each of ``--jump-lengths`` and seed, passing all
  checks (48 cells by default), and ``travel_m``: how far the root moved over the longest of them, "3 times", at
  each seed (the clips: 0 m; the check allows 0.3 m).
* ``length_sweep``: benchmarks/length_sweep.py's default captions and lengths at seeds 0-2, the share passing, and
  the heading change of its turns at its shortest and longest length.

``--steps`` and ``--guidance`` replace the checkpoint's own solver steps and guidance scale in all four;
``--model-weights model`` samples all four with the raw training weights instead of the EMA;
``--smoothing`` (σ in frames) and ``--smoothing-keeps-bones`` set the output smoothing and how it keeps the bones
in all four.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from length_sweep import main as length_sweep_main  # benchmarks/, on sys.path when run as a script
from length_sweep import sample_joints
from mfm.caption_checks import check_caption
from pipeline.generation.contact_sheet import ContactSheetRequest, run_contact_sheet
from pipeline.generation.request import bone_keeping_setting

IN_PLACE_JUMPS = ("a person jumps up in place once.", "a person jumps up in place twice.",
                  "a person jumps up in place 3 times.")
CHECKS = ("count", "place", "turn_angle", "all")


def sheet_figures(checkpoint: str, out: Path, rows: int, seeds: list[int], sampling: dict) -> dict:
    """``sampling``: the sampler settings every part of the judge shares (steps, guidance, weights,
    smoothing, smoothing_keeps_bones; None: the model's)."""
    sheets = []
    for seed in seeds:
        sheet = run_contact_sheet(ContactSheetRequest(out=out / f"sheet-s{seed}.png", checkpoint=checkpoint,
                                                      captions_from_manifest="test", max_rows=rows, seed=seed,
                                                      device="cpu", **sampling))
        (out / f"sheet-s{seed}.json").write_text(json.dumps(sheet, indent=1))
        sheets.append(sheet)
    against = [s["against_dataset_clips"] for s in sheets]

    def mean(read) -> float:
        return float(np.mean([read(a) for a in against]))

    def plausibility(key: str, scale: float = 1.0) -> float:
        return scale * mean(lambda a: a["plausibility"][key]["generated"])

    figures = {"caption_match": mean(lambda a: a["caption_match"]),
               "movement": mean(lambda a: a["median_movement_ratio"]),
               "jerk_ratio": plausibility("jerk_ratio"), "bones_cm": plausibility("bone_length_range", 100),
               "floor_cm": plausibility("floor_penetration", 100), "skating": plausibility("foot_skating_ratio")}
    for check in CHECKS:
        figures[check] = mean(lambda a: a["caption_checks"]["generated"][check]["share"])
    figures["all_per_seed"] = [a["caption_checks"]["generated"]["all"]["share"] for a in against]
    passed = total = 0
    for sheet, a in zip(sheets, against):
        for row, judged in zip(sheet["rows"], a["rows"]):
            checks = judged.get("caption_checks") or {}
            if "in place" in row["text"] and checks:
                total += 1
                passed += all(checks.values())
    return {"sheet": figures, "in_place_rows": {"passed": passed, "of": total}}


def jump_sweep(checkpoint: str, lengths: list[int], seeds: list[int], sampling: dict) -> dict:
    cells = [(text, n) for text in IN_PLACE_JUMPS for n in lengths]
    longest = (IN_PLACE_JUMPS[-1], max(lengths))
    passed, travel = 0, []
    for seed in seeds:
        motions = sample_joints(checkpoint, [t for t, _ in cells], [n for _, n in cells], seed,
                                {"device": "cpu", **sampling})
        for cell, joints in zip(cells, motions):
            passed += all(check_caption(joints, cell[0])["checks"].values())
            if cell == longest:
                moved = joints[-1, 0] - joints[0, 0]
                travel.append(round(float(np.hypot(moved[0], moved[2])), 3))
    return {"passed": passed, "of": len(cells) * len(seeds), "frames": max(lengths), "travel_m": travel}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--out", type=Path, required=True, help="folder for the sheets and summary.json")
    p.add_argument("--rows", type=int, default=64, help="test captions on each sheet (default 64)")
    p.add_argument("--seeds", default="0,1,2,3", help="sampling seeds, comma-separated")
    p.add_argument("--jump-lengths", default="77,111,162,173", help="frames of the jump sweep, comma-separated")
    p.add_argument("--sweep-lengths", default="40,60,90,130,196", help="frames of the length sweep")
    p.add_argument("--steps", type=int, help="solver steps (default: the model's)")
    p.add_argument("--guidance", type=float, help="guidance scale (default: the model's)")
    p.add_argument("--model-weights", choices=("ema", "model"), default="ema",
                   help="the checkpoint's EMA weights (default) or its raw training weights")
    p.add_argument("--smoothing", type=float, help="output smoothing σ in frames (default: the model's; as "
                                                   "launch/sample.py)")
    p.add_argument("--smoothing-keeps-bones", type=bone_keeping_setting, metavar="{true,false,smoothed}",
                   help="how the output smoothing keeps the bones (default: the model's; as launch/sample.py)")
    args = p.parse_args(argv)

    args.out.mkdir(parents=True, exist_ok=True)
    seeds = [int(s) for s in args.seeds.split(",")]
    sampling = {"steps": args.steps, "guidance": args.guidance, "weights": args.model_weights,
                "smoothing": args.smoothing, "smoothing_keeps_bones": args.smoothing_keeps_bones}
    summary = {"checkpoint": args.checkpoint, "seeds": seeds, "guidance": args.guidance,
               "model_weights": args.model_weights, "smoothing": args.smoothing,
               "smoothing_keeps_bones": args.smoothing_keeps_bones,
               **sheet_figures(args.checkpoint, args.out, args.rows, seeds, sampling),
               "jump_sweep": jump_sweep(args.checkpoint, [int(n) for n in args.jump_lengths.split(",")], seeds,
                                        sampling)}
    sweep_out = args.out / "length_sweep.json"
    sweep_args = ["--checkpoint", args.checkpoint, "--lengths", args.sweep_lengths, "--out", str(sweep_out),
                  "--model-weights", args.model_weights]
    length_sweep_main(sweep_args + (["--steps", str(args.steps)] if args.steps else [])
                      + (["--guidance", str(args.guidance)] if args.guidance is not None else [])
                      + (["--smoothing", str(args.smoothing)] if args.smoothing is not None else [])
                      + (["--smoothing-keeps-bones", str(args.smoothing_keeps_bones).lower()]
                         if args.smoothing_keeps_bones is not None else []))
    rows = json.loads(sweep_out.read_text())["rows"]
    shortest, longest = min(r["frames"] for r in rows), max(r["frames"] for r in rows)
    summary["length_sweep"] = {
        "passed": float(np.mean([r["passed"] for r in rows if r["passed"] is not None])),
        "turns_deg": {f"{r['text']} @{r['frames']}": round(float(np.mean([o["heading_change_deg"]
                                                                          for o in r["observed"]])), 1)
                      for r in rows if "turn" in r["text"] and r["frames"] in (shortest, longest)}}
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
