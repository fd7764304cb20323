"""Sample, edit or compose motions with a trained checkpoint (text- or action-conditioned, flow or diffusion);
outputs in pipeline/sampling.py and pipeline/composing.py.

    python launch/sample.py --checkpoint runs/tiny --text "a person walks forward" --num-samples 3 --out out/walk
    python launch/sample.py --checkpoint runs/a2m --action jump --seconds 4 --out out/jump
    python launch/sample.py --checkpoint runs/tiny --text "a person jumps" --edit inbetween \\
        --source-motion walk.npy --keep prefix=0.3 --keep suffix=0.7 --out out/edit
    python launch/sample.py --checkpoint runs/flame --text "a person waves" --solver ddim --steps 50 --out out/ddim
    python launch/sample.py --checkpoint runs/flowmdm --compose composition_humanml.json --out out/story
    python launch/sample.py --checkpoint runs/tiny --extrapolate --text "a person walks" --length 100 \\
        --num-segments 10 --out out/long

Flow edits use --edit-settings paper (MFM paper: 30 Euler steps, ς = 0.2, guidance 1.0) unless --steps, --guidance or
--rewrite-until override a value (results.json records the settings and what was overridden).

--checkpoint takes a step-XXXXXXXX folder or a run folder (its newest complete checkpoint; EMA weights unless
--model-weights model). Per sample: sample_NNN/{features.npy, joints.npy, motion.mp4|gif, motion.bvh,
keep_mask.npy (edits), trajectory.png (--plot-trajectory)}, all described in results.json. joints.npy is recovered
from the ric block, or with --decode rigid also fitted onto the skeleton's fixed bone lengths (the BVH always is).
Edits: --keep prefix=F / suffix=F (prediction, inbetween), every=K (interpolate), joints=A,B[,..] frames=S:E (joints).

Flow checkpoints take ODE solvers (default euler, 10 steps); diffusion checkpoints (train.objective=diffusion) take
--solver ddpm (default) or ddim, --steps respaced from the training steps (default all 1000); nfe = steps.

--compose FILE.json (FlowMDM's {"text": [...], "lengths": [...]}) makes ONE sequence of all segments per sample
(distinct texts need a model trained with model.positional=bpe model.conditioning=pccat); --extrapolate repeats one
text over segments (any flow model; chosen automatically when every text of the file is the same). --switch: flow
time in [0, 1] (e.g. 0.09), an integer number of leading absolute solver steps, or humanml3d (default) / babel.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make the project importable from a checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mfm.editing import DEFAULT_EDIT_SETTINGS, EDIT_SETTINGS
from pipeline.composing import parse_switch, run_composition
from pipeline.sampling import (
    EDIT_PRESETS,
    JOINT_DECODES,
    SampleRequest,
    SamplingError,
    read_prompts,
    run_sampling,
)


def key_value(text: str) -> tuple[str, str]:
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    return key, value


def switch_value(text: str) -> float | int:
    try:
        return parse_switch(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add = p.add_argument
    add("--checkpoint", required=True, help="checkpoint folder, or a run folder (newest complete checkpoint)")
    add("--out", required=True, help="output folder (must be empty unless --overwrite)")
    add("--text", action="append", default=[], help="prompt (repeatable)")
    add("--prompts", help="file with one prompt per line")
    add("--action", action="append", default=[], help="action class name, for action models (repeatable)")
    add("--length", action="append", type=int, default=[], help="frames: once for all prompts or once per prompt")
    add("--seconds", action="append", type=float, default=[], help="like --length, in seconds")
    add("--num-samples", type=int, default=1, help="samples per prompt (default 1)")
    add("--steps", type=int, help="solver steps (default 10, flow edits: the edit settings' 30; diffusion: every "
                                  "training step, respaced if given)")
    add("--solver", help="flow: euler (default), midpoint, heun, rk4 or a torchdiffeq method such as dopri5; "
                         "diffusion: ddpm (default) or ddim")
    add("--guidance", type=float, help="classifier-free guidance scale (default 2.5; flow edits: the edit "
                                       "settings' 1.0, as MFM's edit.py; FLAME-preset diffusion models: 8.0)")
    add("--smoothing", type=float, help="Gaussian smoothing of the output over time, σ in frames (default: the "
                                        "diffusion baseline's own, FLAME: 1; else none)")
    add("--seed", type=int, default=0)
    add("--batch-size", type=int, default=64)
    add("--edit", choices=sorted(EDIT_PRESETS), help="edit --source-motion instead of sampling from noise")
    add("--source-motion", help=".npy of un-normalised features (T, D) or joint positions (T, J, 3)")
    add("--keep", action="append", type=key_value, default=[], metavar="KEY=VALUE", help="edit mask option")
    add("--rewrite-until", type=float, help="edit: rewrite the kept part up to this time ς (default: the edit "
                                            "settings')")
    add("--edit-settings", choices=sorted(EDIT_SETTINGS), default=DEFAULT_EDIT_SETTINGS,
        help="flow edits: paper (default; N = 30 steps, ς = 0.2, guidance 1.0) or reference-debug (MFM edit.py's "
             "debug presets: 100 steps, ς per task)")
    add("--compose", metavar="FILE.json", help='FlowMDM prompt file {"text": [...], "lengths": [...]}: one sequence')
    add("--extrapolate", action="store_true", help="one text repeated over segments (--compose file or --text with "
                                                   "--length per segment / --num-segments)")
    add("--num-segments", type=int, help="--extrapolate without a file: repeat the one --length this many times")
    add("--switch", type=switch_value, help="bpe models: flow time of the absolute-to-relative switch, an int "
                                            "number of absolute steps, or humanml3d (default) / babel")
    add("--attention-chunk", type=int, help="bpe models: attention block size (default: the attention horizon for "
                                            "sequences longer than it; 0: dense)")
    add("--plot-trajectory", action="store_true", help="also plot the x̂1 estimates along the trajectory")
    add("--no-video", action="store_true")
    add("--video-format", choices=("auto", "mp4", "gif"), default="auto", help="auto: MP4 if ffmpeg is found")
    add("--no-bvh", action="store_true")
    add("--mdm-results", action="store_true", help="also write MDM's results.npy (for MDM's render_mesh.py / SMPL "
                                                   "fitting) beside results.json")
    add("--decode", choices=sorted(JOINT_DECODES), default="ric", help="joints.npy and video: ric positions as "
                                                                      "recovered (default) or rigid: fitted onto the "
                                                                      "skeleton's bone lengths (the BVH always is)")
    add("--device", default="auto", help="auto (cuda when available), cpu, cuda, cuda:1, ...")
    add("--model-weights", choices=("ema", "model"), default="ema")
    add("--text-weights", help="text encoder weights (CLIP datasets), checked against the checkpoint's hash")
    add("--overwrite", action="store_true", help="replace an earlier run's outputs in --out")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        texts = args.text + (read_prompts(args.prompts) if args.prompts else [])
        request = SampleRequest(
            checkpoint=args.checkpoint, out_dir=args.out, texts=texts, actions=args.action, lengths=args.length,
            seconds=args.seconds, num_samples=args.num_samples, steps=args.steps, solver=args.solver,
            guidance=args.guidance, smoothing=args.smoothing, seed=args.seed, batch_size=args.batch_size, weights=args.model_weights,
            device=args.device, text_weights=args.text_weights, edit=args.edit, source_motion=args.source_motion,
            keep=dict(args.keep), rewrite_until=args.rewrite_until, edit_settings=args.edit_settings,
            video=not args.no_video,
            video_format=args.video_format, bvh=not args.no_bvh, mdm_results=args.mdm_results, plot_trajectory=args.plot_trajectory,
            decode=args.decode, overwrite=args.overwrite, compose_file=args.compose, extrapolate=args.extrapolate,
            num_segments=args.num_segments, switch=args.switch, attention_chunk=args.attention_chunk,
        )
        results = run_composition(request) if request.composes else run_sampling(request)
    except (SamplingError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if request.composes:
        print(f"{len(results['samples'])} sequence(s) of {results['total_frames']} frames "
              f"({len(results['segments'])} segments) in {args.out}")
    else:
        print(f"{len(results['samples'])} sample(s) in {args.out} ({results['timing']['ms_per_motion']:.1f} ms/motion)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
