"""Fixed windows against length-aware batches (``data.batching``): the share of computed frames that are padding,
and useful (non-padding) frames trained per second. One run prints one JSON line per measurement, ratios included.

    OMP_NUM_THREADS=2 python benchmarks/bench_padding.py --manifest data/synthetic-minilm/manifest.json

Padding, from the batch plan (what the loader computes before reading a record), over one epoch:

* ``padding_synthetic``: the real loader over the manifest's train split with the synthetic preset's data settings
  (window 196, batch 16, shuffle buffer 256; length-aware: ``--pad-multiple``, ``--sort-window``), reading and
  cropping every clip as training does: padding = 1 − real frames / (batch rows × batch width).
* ``padding_humanml3d_lengths``: ``--clips`` lengths drawn to HumanML3D's distribution as the issue states it
  (mean 7.1 s, 2–9.8 s at 20 fps: 40–196 frames; a Beta(2.62, 1.38) scaled to [40, 196], a stand-in with that mean
  and range, not the real histogram), cropped as training crops (``CropToWindow``: multiples of 4 frames, one unit
  shorter with probability 1/3), batched by the humanml3d preset's settings (batch 128, shuffle buffer 2048) with
  the loader's own functions (``shuffle_buffer_order``, ``length_grouped_order``, ``padded_width``); no data is
  read. Also for several sort windows (1 = each batch cut to its own longest clip, no regrouping).

Speed (``train_speed``): ``Trainer.train_step`` of the humanml3d preset's model (8 layers, 512 wide; the text
condition's width comes from ``--manifest``) with the preset's precision and compile setting (``auto``: bf16 and
torch.compile on a CUDA GPU, fp32 eager on a CPU): one sort window of clips of the HumanML3D-like lengths
(``--batch-size`` × ``--sort-window`` clips, random features), trained as fixed-window batches in their shuffled
order and as the length-aware batches of the same clips, after one untimed step of each; ``--passes`` N repeats
that N times and times the last. ``useful_frames_per_s``: real frames over the time the steps took, timed as
``--timing`` says:

* ``streamed`` (default): each kind's steps run back to back as one block (its batches built before), then
  drained (the last step's flags read, the GPU synchronised): the throughput of a run, where under
  ``train.step_sync=deferred`` (auto on CUDA) the host queues a step while the GPU runs the one before;
* ``per_step``: steps of the two kinds interleaved, each timed to its end (the GPU synchronised before and after:
  no overlap), as the 2026-11-27 H200 figures were taken.

    python benchmarks/bench_padding.py --only train_speed --manifest M --batch-size 128 --passes 2   # on a GPU
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pipeline.config import TrainConfig, load_config
from pipeline.data.stages import CropToWindow, length_grouped_order, padded_width, shuffle_buffer_order
from pipeline.data.stream import LoaderOptions, MotionLoader

HUMANML3D_FRAMES = (40, 196)
HUMANML3D_MEAN_FRAMES = 142  # 7.1 s at 20 fps
_BETA = (2.62, 1.38)  # mean 2.62 / 4 = 0.655 of the 156-frame range: 40 + 0.655 · 156 = 142 frames


def humanml3d_like_lengths(count: int, seed: int) -> np.ndarray:
    low, high = HUMANML3D_FRAMES
    rng = np.random.default_rng(seed)
    return np.round(low + (high - low) * rng.beta(*_BETA, size=count)).astype(np.int64)


def cropped(lengths: np.ndarray, window: int, seed: int) -> np.ndarray:
    """The lengths as training crops them (MDM's unit rounding and 'double' coin; data defaults)."""
    crop = CropToWindow(window, unit_length=4, shorten_prob=1.0 / 3.0, seed=seed, epoch=0)
    rng = np.random.default_rng(seed + 1)
    return np.array([crop.crop_length(int(n), rng) for n in lengths], np.int64)


def planned_batches(lengths: np.ndarray, crops: np.ndarray, *, batch_size: int, window: int, shuffle_buffer: int,
                    batching: str, pad_multiple: int, sort_window: int, seed: int) -> list[np.ndarray]:
    """The epoch's batches (item indices) of one reader, as the loader plans them from counts and lengths."""
    rng = np.random.default_rng(seed)
    order = shuffle_buffer_order(len(lengths), shuffle_buffer, rng)
    order = order[:len(order) // batch_size * batch_size]
    if batching == "length_aware":
        order = length_grouped_order(order, np.minimum(lengths, window), batch_size, sort_window, rng)
    return [order[i:i + batch_size] for i in range(0, len(order), batch_size)]


def padding_share(batches_crops: list[np.ndarray], window: int, pad_multiple: int | None) -> tuple[float, int, int]:
    real = sum(int(c.sum()) for c in batches_crops)
    computed = sum(len(c) * padded_width(c.tolist(), window, pad_multiple) for c in batches_crops)
    return 1.0 - real / computed, real, computed


def padding_humanml3d(args: argparse.Namespace) -> dict[str, Any]:
    cfg = load_config(TrainConfig, "humanml3d")
    window, batch, buffer = cfg.data.window, cfg.data.batch_size, cfg.data.shuffle_buffer
    lengths = humanml3d_like_lengths(args.clips, args.seed)
    crops = cropped(lengths, window, args.seed)
    shares = {}
    for batching, sort_window in [("fixed", 0)] + [("length_aware", k) for k in sorted({1, 2, 4, args.sort_window, 16})]:
        batches = planned_batches(lengths, crops, batch_size=batch, window=window, shuffle_buffer=buffer,
                                  batching=batching, pad_multiple=args.pad_multiple, sort_window=max(1, sort_window),
                                  seed=args.seed)
        share, real, computed = padding_share([crops[b] for b in batches], window,
                                              None if batching == "fixed" else args.pad_multiple)
        key = "fixed" if batching == "fixed" else f"length_aware_sort_window_{sort_window}"
        shares[key] = {"padding_share": round(share, 4), "real_frames": real, "computed_frames": computed}
    fixed, aware = shares["fixed"], shares[f"length_aware_sort_window_{args.sort_window}"]
    return {"bench": "padding_humanml3d_lengths", "clips": args.clips,
            "mean_length_s": round(float(lengths.mean()) / 20.0, 2), "mean_cropped_frames": round(float(crops.mean()), 1),
            "window": window, "batch_size": batch, "shuffle_buffer": buffer, "pad_multiple": args.pad_multiple,
            "sort_window": args.sort_window, "by_batching": shares,
            "computed_frames_ratio_fixed_to_length_aware": round(fixed["computed_frames"] / aware["computed_frames"], 3)}


def padding_synthetic(args: argparse.Namespace) -> dict[str, Any]:
    cfg = load_config(TrainConfig, "synthetic")
    out: dict[str, Any] = {"bench": "padding_synthetic", "manifest": args.manifest, "window": cfg.data.window,
                           "batch_size": cfg.data.batch_size, "shuffle_buffer": cfg.data.shuffle_buffer,
                           "pad_multiple": args.pad_multiple, "sort_window": args.sort_window}
    for batching in ("fixed", "length_aware"):
        options = LoaderOptions(batch_size=cfg.data.batch_size, seed=cfg.data.seed, window=cfg.data.window,
                                shuffle_buffer=cfg.data.shuffle_buffer, batching=batching,
                                pad_multiple=args.pad_multiple, sort_window_batches=args.sort_window)
        loader = MotionLoader(args.manifest, "train", options)
        real = computed = batches = 0
        start = time.perf_counter()
        for batch in loader.iter_epoch():
            real += int(batch["lengths"].sum())
            computed += batch["features"].shape[0] * batch["features"].shape[1]
            batches += 1
        out[batching] = {"padding_share": round(1 - real / computed, 4), "real_frames": real,
                         "computed_frames": computed, "batches": batches,
                         "epoch_read_s": round(time.perf_counter() - start, 1)}
    out["computed_frames_ratio_fixed_to_length_aware"] = round(
        out["fixed"]["computed_frames"] / out["length_aware"]["computed_frames"], 3)
    return out


def train_speed(args: argparse.Namespace) -> dict[str, Any]:
    from pipeline.distributed import Dist
    from pipeline.training.trainer import Trainer

    batch, sort_window = args.batch_size, args.sort_window
    lengths = humanml3d_like_lengths(batch * (sort_window + 2), args.seed + 7)
    crops = cropped(lengths, 196, args.seed + 7)
    order = np.random.default_rng(args.seed).permutation(len(lengths))
    warmup, timed = order[:2 * batch], order[2 * batch:]
    fixed_batches = [timed[i:i + batch] for i in range(0, len(timed), batch)]
    aware_order = length_grouped_order(timed, lengths, batch, sort_window, np.random.default_rng(args.seed))
    aware_batches = [aware_order[i:i + batch] for i in range(0, len(aware_order), batch)]
    with tempfile.TemporaryDirectory() as tmp:
        # data.batching=length_aware: the trainer compiles (on CUDA) as a length-aware run does, one graph per width;
        # the fixed windows' 196 is one of those widths
        cfg = load_config(TrainConfig, "humanml3d", [f"data.manifest={args.manifest}", f"train.out_dir={tmp}/run",
                                                    "train.wandb=disabled", "data.verify=off", "data.num_workers=0",
                                                    f"data.batch_size={batch}", "data.batching=length_aware",
                                                    f"data.pad_multiple={args.pad_multiple}"])
        with Dist(mixed_precision=cfg.train.mixed_precision) as dist:
            trainer = Trainer(cfg, dist)
            model_config = trainer.model_config
            generator = torch.Generator().manual_seed(0)

            def make(items: np.ndarray, pad_multiple: int | None) -> dict[str, Any]:
                n = torch.from_numpy(crops[items])
                width = padded_width(n.tolist(), 196, pad_multiple)
                return {"features": torch.randn(len(items), width, model_config.feature_dim, generator=generator),
                        "lengths": n, "text_emb": torch.randn(len(items), model_config.cond_dim, generator=generator),
                        "action": torch.zeros(len(items), dtype=torch.int64), "ids": [str(i) for i in items]}

            def drain() -> None:  # the queued step's flags read (deferred), the GPU's queue emptied
                trainer.settle()
                if dist.device.type == "cuda":
                    torch.cuda.synchronize(dist.device)

            def step(b: dict[str, Any]) -> float:
                drain()  # the optimizer and EMA launches of the step before end first
                start = time.perf_counter()
                trainer.train_step([b])
                trainer.step += 1
                drain()
                return time.perf_counter() - start

            def block(built: list[dict[str, Any]]) -> list[float]:
                """The batches back to back, drained at the end: the block's time spread evenly over its steps."""
                drain()
                start = time.perf_counter()
                for b in built:
                    trainer.train_step([b])
                    trainer.step += 1
                drain()
                return [(time.perf_counter() - start) / len(built)] * len(built)

            step(make(warmup[:batch], None))
            step(make(warmup[batch:], args.pad_multiple))
            plans = {"fixed": (fixed_batches, None), "length_aware": (aware_batches, args.pad_multiple)}
            # Every pass trains the same batches; the last pass's times are kept. On a GPU under torch.compile each
            # new batch width compiles its own graph on first sight, and --passes 2 keeps that out of the figures.
            for _ in range(args.passes):
                times: dict[str, list[float]] = {"fixed": [], "length_aware": []}
                widths: dict[str, list[int]] = {"fixed": [], "length_aware": []}
                if args.timing == "streamed":
                    for name, (plan, multiple) in plans.items():
                        built = [make(items, multiple) for items in plan]
                        widths[name] = [b["features"].shape[1] for b in built]
                        times[name] = block(built)
                    continue
                for fixed_items, aware_items in zip(fixed_batches, aware_batches):
                    for name, items, multiple in (("fixed", fixed_items, None),
                                                  ("length_aware", aware_items, args.pad_multiple)):
                        b = make(items, multiple)
                        widths[name].append(b["features"].shape[1])
                        times[name].append(step(b))
            useful = int(crops[timed].sum())
            result: dict[str, Any] = {
                "bench": "train_speed", "config": "humanml3d", "params_m": round(trainer.num_parameters / 1e6, 3),
                "cond_dim": model_config.cond_dim,
                "device": torch.cuda.get_device_name(dist.device) if dist.device.type == "cuda" else "cpu",
                "precision": dist.mixed_precision, "compile": cfg.train.compile, "threads": torch.get_num_threads(),
                "batch_size": batch, "steps_each": len(fixed_batches), "passes": args.passes,
                "timing": args.timing, "step_sync": "deferred" if trainer.defers_step_sync else "every_step",
                "pad_multiple": args.pad_multiple,
                "useful_frames": useful}
            for name in times:
                total = sum(times[name])
                computed = sum(batch * w for w in widths[name])
                result[name] = {"widths": widths[name], "step_s": [round(t, 2) for t in times[name]],
                                "total_s": round(total, 2), "padding_share": round(1 - useful / computed, 4),
                                "useful_frames_per_s": round(useful / total, 1)}
            result["useful_frames_per_s_ratio"] = round(result["length_aware"]["useful_frames_per_s"]
                                                        / result["fixed"]["useful_frames_per_s"], 3)
            return result


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--manifest", default="data/synthetic-minilm/manifest.json",
                        help="a built dataset: its train split for the synthetic padding figures, its sizes for the "
                             "speed figures")
    parser.add_argument("--clips", type=int, default=23384, help="clips of HumanML3D-like lengths (its train split)")
    parser.add_argument("--pad-multiple", type=int, default=16)
    parser.add_argument("--sort-window", type=int, default=8, help="data.sort_window_batches")
    parser.add_argument("--batch-size", type=int, default=16, help="batch of the speed figures")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--passes", type=int, default=1,
                        help="train_speed: passes over the same batches, the last one timed (2 on a GPU with compile)")
    parser.add_argument("--timing", choices=("streamed", "per_step"), default="streamed",
                        help="train_speed: each kind's steps back to back, drained at the end (a run's throughput), "
                             "or each step timed to its end")
    parser.add_argument("--only", default="padding_humanml3d,padding_synthetic,train_speed",
                        help="comma-separated subset of the measurements")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    measurements = {"padding_humanml3d": padding_humanml3d, "padding_synthetic": padding_synthetic,
                    "train_speed": train_speed}
    for name in args.only.split(","):
        print(json.dumps(measurements[name](args)), flush=True)


if __name__ == "__main__":
    main()
