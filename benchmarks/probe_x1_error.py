"""How well a trained flow model knows its training clips, along the path: the diagnostic that separated the two
causes of the embedded default's broken motion (docs/generator-study.md). One JSON line per time t.

    python benchmarks/probe_x1_error.py --checkpoint runs/default [--split train] [--times 0,0.25,0.5,0.75,0.9,0.97]

For every motion of the split, its first caption and the part of the clip it describes: draw x0 ~ N(0, I), put
x_t on the path, ask the model (conditional, no guidance) for v and form x̂1 = x_t + (1 − t)·v. Per t:

* ``x1_error``: mean squared error of x̂1 against the clip (normalised units; the clips' variance is ~1). A model
  that has learnt 15 captioned clips should be near 0 at every t: each caption names one clip.
* ``white_share``: the share of that error that changes from frame to frame, ``Σ(Δe)² / (2·Σe²)`` over time:
  1 for white noise (what a velocity network leaves when it cannot carry x0 through its width), near 0 for an
  error that is smooth in time.
* ``x1_jerk_ratio``: median over the clips of the jerk of x̂1's joints over the clip's own
  (:func:`mfm.metrics.mean_jerk`): where on the path the estimate shakes.
* at t = 0 also ``caption_spread`` (RMS distance of each caption's x̂1 to their mean, same noise for all, over
  the first frames all clips share) beside ``clip_spread`` (the same for the clips): a model that ignores its
  caption has a spread near 0.
Averaged over ``--draws`` noise draws (seeded).

A last line follows the sampled trajectory instead (conditional, ``--sample-steps`` Euler steps from one noise draw):
the x̂1 jerk ratio at every step and of the output. A sample whose x̂1 already shakes at t = 0 keeps that jitter:
the steps integrate it and the late ones mostly pass x_t through (docs/generator-study.md).
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from flow_probe import load_probe_clips
from mfm.features import features_to_joints
from mfm.metrics import mean_jerk  # benchmarks/, on sys.path when run as a script


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--split", default="train")
    p.add_argument("--times", default="0,0.25,0.5,0.75,0.9,0.97")
    p.add_argument("--draws", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--sample-steps", type=int, default=10)
    p.add_argument("--count", type=int, default=None, help="only the split's first N motions (default: all)")
    args = p.parse_args()

    probe = load_probe_clips(args.checkpoint, args.split, args.count)
    trained, captions, x1, lengths, mask, cond = (probe.trained, probe.captions, probe.x1, probe.lengths, probe.mask,
                                                  probe.cond)
    shared = int(lengths.min())
    generator = torch.Generator().manual_seed(args.seed)

    def joints(x: torch.Tensor) -> np.ndarray:
        return np.asarray(features_to_joints(trained.denormalize(x * mask).numpy(), trained.skeleton))

    clip_jerk = mean_jerk(joints(x1), lengths.numpy())

    def jerk_ratio(x: torch.Tensor) -> float:
        return float(np.nanmedian(mean_jerk(joints(x), lengths.numpy()) / clip_jerk))

    def x1_estimate(x: torch.Tensor, t: float) -> torch.Tensor:
        with torch.no_grad():
            velocity = trained.model(x, torch.full((len(captions),), t), cond, lengths, **probe.cond_inputs)
        return x + (1 - t) * velocity

    def spread(x: torch.Tensor) -> float:
        x = x[:, :shared]
        return float((x - x.mean(dim=0, keepdim=True)).square().mean().sqrt())

    for t in (float(v) for v in args.times.split(",")):
        errors, white, spreads, jerks = [], [], [], []
        for _ in range(args.draws):
            x0 = torch.randn(x1.shape[1:], generator=generator).expand_as(x1) * mask  # same noise for every caption
            x_t = t * x1 + (1 - (1 - 1e-4) * t) * x0
            x1_hat = x1_estimate(x_t, t)
            error = (x1_hat - x1) * mask
            errors.append(float(error.square().sum() / (mask.sum() * x1.shape[-1])))
            step = (error[:, 1:] - error[:, :-1]) * mask[:, 1:]
            white.append(float(step.square().sum() / (2 * error.square().sum())))
            spreads.append(spread(x1_hat))
            jerks.append(jerk_ratio(x1_hat))
        line = {"checkpoint": str(trained.checkpoint), "step": trained.step, "t": t,
                "x1_error": round(float(np.mean(errors)), 5), "white_share": round(float(np.mean(white)), 3),
                "x1_jerk_ratio": round(float(np.mean(jerks)), 2)}
        if t == 0.0:
            line.update(caption_spread=round(float(np.mean(spreads)), 3), clip_spread=round(spread(x1), 3))
        print(json.dumps(line))

    x = torch.randn(x1.shape, generator=generator) * mask
    by_t = {}
    for i in range(args.sample_steps):
        t = i / args.sample_steps
        x1_hat = x1_estimate(x, t)
        by_t[round(t, 3)] = round(jerk_ratio(x1_hat), 2)
        x = (x + (x1_hat - x) / (1 - t) / args.sample_steps) * mask  # an Euler step of v = (x̂1 − x) / (1 − t)
    print(json.dumps({"checkpoint": str(trained.checkpoint), "step": trained.step, "sampled_steps": args.sample_steps,
                      "x1_jerk_ratio_by_t": by_t, "output_jerk_ratio": round(jerk_ratio(x), 2)}))


if __name__ == "__main__":
    main()
