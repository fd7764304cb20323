"""Sample, edit or compose motions with a trained checkpoint (text- or action-conditioned, flow or diffusion);
outputs in pipeline/generation/outputs.py. The request is a typed config (pipeline/generation/request.py SampleRequest): ``--config
FILE.yaml``, then the flags below (each a shorthand for one key), then ``key=value`` overrides
(``steps=20 'texts=[a person walks]'``); ``--print-config`` lists every key.

    python launch/sample.py --checkpoint runs/tiny --text "a person walks forward" --num-samples 3 --out out/walk
    python launch/sample.py --checkpoint runs/a2m --action jump --seconds 4 --out out/jump
    python launch/sample.py --checkpoint runs/tiny --text "a person jumps" --edit inbetween \\
        --source-motion walk.npy --keep prefix=0.3 --keep suffix=0.7 --out out/edit
    python launch/sample.py --checkpoint runs/flame --text "a person waves" --solver ddim --steps 50 --out out/ddim
    python launch/sample.py --checkpoint runs/flowmdm --compose composition_humanml.json --out out/story
    python launch/sample.py --checkpoint runs/tiny --extrapolate --text "a person walks" --length 100 \\
        --num-segments 10 --out out/long

Flow edits use --edit-settings paper (MFM paper §4.1: 30 Euler steps, ς = 0.2; guidance 1.0) unless --steps,
--guidance or --rewrite-until override a value (results.json records the settings and what was overridden).

--checkpoint takes a step-XXXXXXXX folder or a run folder (its newest complete checkpoint; EMA weights unless
--model-weights model). Per sample: sample_NNN/{features.npy, joints.npy, motion.mp4|gif, motion.bvh,
keep_mask.npy (edits), trajectory.png (--plot-trajectory)}, all described in results.json. joints.npy is recovered
from the ric block, or with --decode rigid also fitted onto the skeleton's fixed bone lengths (the BVH always is).
Edits: --keep prefix=F / suffix=F (prediction, inbetween), every=K (interpolate), joints=A,B[,..] frames=S:E (joints).

Flow checkpoints take ODE solvers (default euler, 10 steps); diffusion checkpoints (train.objective=diffusion) take
--solver ddpm (default) or ddim, --steps respaced from the training steps (default all 1000); nfe = steps.
FLAME-preset checkpoints sample as FLAME's authors did (guidance 8.0, σ = 1 smoothing, every training step, the x0
clamp, EMA weights; their edits copy the source's root) unless --guidance, --smoothing, --steps, --no-clip-denoised,
--model-weights model, --no-reference-translation or --no-baseline-defaults (all of them) say otherwise;
results.json's baseline_defaults records what ran and what was overridden.

--compose FILE.json (FlowMDM's {"text": [...], "lengths": [...]}) makes ONE sequence of all segments per sample
(distinct texts need a model trained with model.positional=bpe model.conditioning=pccat); --extrapolate repeats one
text over segments (any flow model; chosen automatically when every text of the file is the same). --switch: flow
time in [0, 1] (e.g. 0.09), an integer number of leading absolute solver steps, or humanml3d (default) / babel.
"""

from __future__ import annotations

import argparse
import logging
import sys

from pipeline.config import ConfigError, describe_config
from pipeline.generation.composing import run_composition
from pipeline.generation.request import (
    SamplingError,
    add_request_flags,
    flag_values,
    load_sample_request,
)
from pipeline.generation.sampling import run_sampling


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", help="a YAML request (any SampleRequest keys); flags and overrides win")
    parser.add_argument("--print-config", action="store_true", help="print every key with its value, default and "
                        "meaning, then exit")
    add_request_flags(parser)
    parser.add_argument("overrides", nargs="*", metavar="key=value", help="request overrides (pipeline/generation/request.py)")
    args = parser.parse_intermixed_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        request = load_sample_request(args.config, args.overrides, flag_values(args))
        if args.print_config:
            print("\n".join(describe_config(request)))
            return 0
        results = run_composition(request) if request.composes else run_sampling(request)
    except (ConfigError, SamplingError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if request.composes:
        print(f"{len(results['samples'])} sequence(s) of {results['total_frames']} frames "
              f"({len(results['segments'])} segments) in {request.out_dir}")
    else:
        print(f"{len(results['samples'])} sample(s) in {request.out_dir} "
              f"({results['timing']['ms_per_motion']:.1f} ms/motion)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
