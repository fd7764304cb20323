"""Where along the sampled path a caption's root motion goes wrong: the clip mean of the root's rates in the network's
estimate x̂1 at every Euler step, for captions that fix them ("jumps up in place": 0 m/s; "turns around": 180°).
One JSON line per (caption, length): the forward speed (m/s, the facing frame's Z velocity) and the total heading
change (degrees, positive: to the left) of x̂1 at each step's time, the mean over the seeds, and the same of the sampled motion.

    python benchmarks/root_mean_probe.py --checkpoint runs/synthetic [--text ... --lengths 173 --seeds 0,1,2,3]

The conditional field (guidance 1), integrated with the Euler steps of the model's sampler: the root's channels
follow it under ``model.guided_features=pose``. With a 10-step Euler sampler and an x̂1 network the sample is the
last step's x̂1. docs/generator-study.md ("The root's clip mean") reads these lines: the preset at training seed 2
starts "jumps up in place 3 times" at +0.09 m/s (x̂1 at t = 0, the caption's mean as the network learnt it) and
overcorrects to -0.09 m/s by t = 0.5, where it meets states no training path of that caption has.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from mfm.solvers import sample
from pipeline.generation.inference import load_trained_model
from pipeline.generation.sampling import PromptConditions, conditioned_model

CAPTIONS = ("a person jumps up in place 3 times.", "a person jumps up in place twice.", "a person jumps forward 3 times.",
            "a person turns around to the left.")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--text", action="append", help="caption (repeatable; default: four of the synthetic set's)")
    p.add_argument("--lengths", default="173", help="frames, comma-separated")
    p.add_argument("--seeds", default="0,1,2,3", help="comma-separated")
    p.add_argument("--steps", type=int, help="Euler steps (default: the model's sampling_steps)")
    args = p.parse_args(argv)

    trained = load_trained_model(args.checkpoint)
    if trained.objective != "flow":
        raise SystemExit(f"{args.checkpoint} is a {trained.objective} model: this probe needs a velocity field")
    steps = args.steps or trained.model_config.sampling_steps
    fps = trained.fps
    texts = args.text or list(CAPTIONS)
    seeds = [int(s) for s in args.seeds.split(",")]
    conditions = PromptConditions(*trained.condition_inputs(texts=texts))
    model = conditioned_model(trained, conditions)  # the solvers' call signature, as launch/sample.py drives it
    for frames in (int(n) for n in args.lengths.split(",")):
        lengths = torch.full((len(texts),), frames)
        forward, heading = np.zeros((len(seeds), steps + 1, len(texts))), np.zeros((len(seeds), steps + 1, len(texts)))
        for s, seed in enumerate(seeds):
            noise = torch.randn(len(texts), frames, trained.model_config.feature_dim,
                                generator=torch.Generator().manual_seed(seed))
            with torch.no_grad():
                solved = sample(model, conditions.cond, lengths, num_frames=frames, steps=steps, guidance=1.0,
                                noise=noise, return_trajectory=True)
            raw = trained.denormalize(torch.cat([solved.x1_hat, solved.x1[None]]))  # every step's x̂1, the sample
            forward[s] = (raw[..., 2].mean(dim=2) * fps).numpy()
            # The features' rate is half the heading's (HumanML3D's root quaternion is (cos a, 0, sin a, 0));
            # negative a turns left, and the caption checks count a left turn positive.
            heading[s] = -2 * np.degrees(raw[..., 0].sum(dim=2).numpy())
        for k, text in enumerate(texts):
            print(json.dumps({
                "checkpoint": str(trained.checkpoint), "step": trained.step, "text": text, "frames": frames,
                "times": [round(i / steps, 3) for i in range(steps)] + ["sample"],
                "forward_m_per_s": [round(float(v), 3) for v in forward[:, :, k].mean(axis=0)],
                "heading_change_deg": [round(float(v), 1) for v in heading[:, :, k].mean(axis=0)],
                "sample_forward_m_per_s_by_seed": [round(float(v), 3) for v in forward[:, -1, k]],
            }))


if __name__ == "__main__":
    main()
