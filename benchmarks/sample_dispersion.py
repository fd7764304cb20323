"""Where along the path a flow model loses its samples' motion: the diagnostic behind the synthetic set's frozen
samples (docs/generator-study.md, "The synthetic set"). One JSON line per experiment.

    python benchmarks/sample_dispersion.py --checkpoint runs/flow [--split test] [--count 40]

For the first ``--count`` motions of the split (first caption, the clip's length up to the model's window), the
conditional model without guidance is integrated with Euler steps, and every result is measured by its temporal
spread: per sample and feature the standard deviation over the clip's frames (normalised units), averaged. A still
pose has 0, the clips themselves give ``clip_spread``.

* ``from_noise``: integrated from pure noise over uniform grids of 10 and 50 steps and a 10-step grid crowded
  towards t = 0 (``t = s³``): if more or earlier steps do not raise the spread, the solver is not where it is lost.
* ``from_clip_at``: integrated from x_t = t·x1 + (1 − t)·x0 of the caption's own clip, started at t = 0.05 … 0.3
  (10 uniform steps over the rest): the spread the model keeps once the path already holds the clip's motion.
  The gap between starting at 0 and at 0.2 is what the model's field below t = 0.2 loses.
"""

from __future__ import annotations

import argparse
import json

import torch

from mfm.path import SIGMA_MIN
from flow_probe import load_probe_clips  # benchmarks/, on sys.path when run as a script


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--split", default="test")
    p.add_argument("--count", type=int, default=40)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()

    probe = load_probe_clips(args.checkpoint, args.split, args.count)
    trained, captions, x1, lengths, mask, cond = (probe.trained, probe.captions, probe.x1, probe.lengths, probe.mask,
                                                  probe.cond)
    generator = torch.Generator().manual_seed(args.seed)

    def temporal_spread(x: torch.Tensor) -> float:
        count = mask.sum(dim=1, keepdim=True)
        centred = (x - (x * mask).sum(dim=1, keepdim=True) / count) * mask
        return float((centred.square().sum(dim=1) / count[:, 0]).sqrt().mean())

    def integrate(x: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
        for t, t_next in zip(grid[:-1], grid[1:]):
            with torch.no_grad():
                velocity = trained.model(x, torch.full((len(captions),), float(t)), cond, lengths)
            x = (x + (t_next - t) * velocity) * mask
        return x

    def noise() -> torch.Tensor:
        return torch.randn(x1.shape, generator=generator) * mask

    base = {"checkpoint": str(trained.checkpoint), "step": trained.step, "clip_spread": round(temporal_spread(x1), 4)}
    grids = {"euler 10": torch.linspace(0, 1, 11), "euler 50": torch.linspace(0, 1, 51),
             "euler 10, t = s^3": torch.linspace(0, 1, 11) ** 3}
    for name, grid in grids.items():
        print(json.dumps({**base, "from_noise": name, "spread": round(temporal_spread(integrate(noise(), grid)), 4)}))
    for start in (0.05, 0.1, 0.2, 0.3):
        x_t = start * x1 + (1 - (1 - SIGMA_MIN) * start) * noise()
        out = integrate(x_t, torch.linspace(start, 1, 11))
        print(json.dumps({**base, "from_clip_at": start, "spread": round(temporal_spread(out), 4)}))


if __name__ == "__main__":
    main()
