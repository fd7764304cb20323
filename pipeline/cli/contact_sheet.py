"""One PNG with one row per prompt: the caption, then evenly spaced frames of the motion sampled for it (the same
sampling as launch/sample.py), or of the dataset clip of that caption (--ground-truth); engine in
pipeline/generation/contact_sheet.py, drawing in mfm/export/contact_sheet.py.

    python launch/contact_sheet.py --checkpoint runs/default --text "a person does a cartwheel." \\
        --text "someone walks forward." --out sheet.png
    python launch/contact_sheet.py --checkpoint runs/default --captions-from-manifest train --out generated.png
    python launch/contact_sheet.py --checkpoint runs/default --captions-from-manifest train --ground-truth \\
        --out ground_truth.png

--captions-from-manifest SPLIT takes the first caption of every motion of that split of the checkpoint's dataset
(a few-step student's: its teacher's; --manifest for another) and generates each with its clip's length, so the
generated and --ground-truth sheets compare row for row.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from pipeline.generation.contact_sheet import ContactSheetRequest, run_contact_sheet
from pipeline.generation.request import JOINT_DECODES, SamplingError, bone_keeping_setting, read_prompts


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add = p.add_argument
    add("--checkpoint", help="checkpoint or run folder (newest complete checkpoint); optional with --ground-truth "
                             "--manifest")
    add("--out", required=True, help="the PNG to write")
    add("--text", action="append", default=[], help="prompt (repeatable)")
    add("--prompts-file", help="file with one prompt per line")
    add("--captions-from-manifest", metavar="SPLIT", help="first caption of every motion of this dataset split")
    add("--max-rows", type=int, help="with --captions-from-manifest: only the split's first N motions")
    add("--manifest", help="dataset manifest for --captions-from-manifest (default: the checkpoint's)")
    add("--ground-truth", action="store_true", help="draw the dataset clips of the captions instead of sampling")
    add("--frames", type=int, default=6, help="frames per row (default 6)")
    add("--seconds", action="append", type=float, default=[], help="motion length: once for all or once per prompt")
    add("--steps", type=int, help="solver steps (as launch/sample.py)")
    add("--solver", help="ODE solver or diffusion sampler (as launch/sample.py)")
    add("--guidance", type=float, help="classifier-free guidance scale (default: the model's, as launch/sample.py)")
    add("--seed", type=int, default=0)
    add("--guided-features", choices=("all", "pose"), help="channels guidance mixes (as launch/sample.py)")
    add("--smoothing", type=float, help="Gaussian smoothing of the output over time, σ in frames (as launch/sample.py)")
    add("--smoothing-keeps-bones", type=bone_keeping_setting, metavar="{true,false,smoothed}",
        help="after the smoothing, every bone gets back its length, each frame's own (true) or its lengths smoothed "
             "over time (smoothed) (default: the model's; as launch/sample.py)")
    add("--decode", choices=sorted(JOINT_DECODES), default="ric", help="joints as recovered from the ric block "
                                                                      "(default) or fitted onto fixed bone lengths")
    add("--device", default="auto", help="auto (cuda when available), cpu, cuda, ...")
    add("--model-weights", choices=("ema", "model"), default="ema")
    add("--text-weights", help="text encoder weights (CLIP datasets)")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        texts = args.text + (read_prompts(args.prompts_file) if args.prompts_file else [])
        sheet = run_contact_sheet(ContactSheetRequest(
            out=args.out, checkpoint=args.checkpoint, texts=texts, captions_from_manifest=args.captions_from_manifest,
            max_rows=args.max_rows, manifest=args.manifest, ground_truth=args.ground_truth, frames=args.frames,
            seconds=args.seconds,
            steps=args.steps, solver=args.solver, guidance=args.guidance, seed=args.seed, smoothing=args.smoothing,
            guided_features=args.guided_features,
            smoothing_keeps_bones=args.smoothing_keeps_bones,
            decode=args.decode,
            device=args.device, weights=args.model_weights, text_weights=args.text_weights))
    except (SamplingError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"{len(sheet['rows'])} row(s) of {args.frames} frames ({sheet['mode']}) in {sheet['out']}")
    report = Path(sheet["out"]).with_suffix(".json")
    report.write_text(json.dumps(sheet, indent=1))
    if "against_dataset_clips" in sheet:
        figures = sheet["against_dataset_clips"]
        print(f"caption match {figures['caption_match']:.2f}; medians, generated | ground truth:")
        for name, pair in figures["plausibility"].items():
            print(f"  {name:<22} " + " | ".join("—" if v is None else f"{v:.3f}" for v in pair.values()))
        print(f"  {'movement_ratio':<22} {figures['median_movement_ratio']:.3f} (median of each sample's over its clip's)")
        for name, checks in figures.get("caption_checks", {}).get("generated", {}).items():
            truth = figures["caption_checks"]["ground_truth"][name]["share"]
            print(f"  caption check {name:<12} {checks['share']:.2f} | {truth:.2f} of {checks['checked']}")
    print(f"figures in {report}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
