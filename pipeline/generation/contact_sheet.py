"""Contact sheets of a checkpoint's samples, or of the dataset clips of the same captions: the engine behind
``launch/contact_sheet.py`` (the drawing is :func:`mfm.export.render_contact_sheet`).

Generated rows come from :func:`pipeline.generation.sampling.run_sampling` itself (into a temporary folder, without video or
BVH), so a sheet shows what ``launch/sample.py`` writes for the same prompts, lengths, solver, steps, guidance and
seed: row i is sample i of a request with one sample per prompt, its joints decoded as ``decode`` says.

Prompts are texts, or with ``captions_from_manifest=SPLIT`` the first caption of every motion of that split of the
dataset manifest (the one the checkpoint was trained on unless ``manifest`` is given). Those rows are generated with
the length of the part of the clip the caption describes (unless ``seconds`` are given; clamped to the model's
window like any sample), so the same request with ``ground_truth=True`` draws the clips themselves, decoded the same
way: the sheet to compare with, row for row. Such a generated sheet is also measured against those clips
(:func:`compare_with_clips`): the plausibility figures of the samples beside the clips', and whether each sample is
nearest to its own caption's clip; the command writes them beside the PNG (``.json``).
"""

from __future__ import annotations

import dataclasses
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mfm.caption_checks import caption_check_summary, stated_attributes
from mfm.export import render_contact_sheet
from mfm.features import features_to_joints, features_to_joints_rigid
from mfm.metrics import movement_spread, padded_motions, plausibility, plausibility_settings, plausibility_side_by_side
from mfm.skeleton import Skeleton, get_skeleton
from pipeline.data.stream import Manifest, iter_motions, open_manifest
from pipeline.generation.inference import load_trained_model, skeleton_from_spec
from pipeline.generation.request import JOINT_DECODES, SampleRequest, SamplingError
from pipeline.generation.sampling import run_sampling

DECODERS = {"ric": features_to_joints, "rigid": features_to_joints_rigid}  # the keys of JOINT_DECODES


@dataclasses.dataclass
class ContactSheetRequest:
    """One contact sheet: what to draw (see the module docstring) and, for generated rows, how to sample."""

    out: str | Path  # the PNG to write
    checkpoint: str | Path | None = None  # a step-XXXXXXXX or run folder; ground truth needs it only for the dataset
    texts: Sequence[str] = ()
    captions_from_manifest: str | None = None  # a split name: its motions' first captions are the prompts
    max_rows: int | None = None  # captions_from_manifest: only the split's first max_rows motions (None: all)
    manifest: str | Path | None = None  # the dataset for captions_from_manifest; default: the checkpoint's
    ground_truth: bool = False  # draw the dataset clips of the captions instead of sampling
    frames: int = 6  # panels per row
    seconds: Sequence[float] = ()  # one for every prompt or one per prompt; default: see the module docstring
    steps: int | None = None
    solver: str | None = None
    guidance: float | None = None  # None: the sampler's default (the model's sampling_guidance)
    seed: int = 0
    guided_features: str | None = None  # all or pose; None: the model's own (as launch/sample.py --guided-features)
    smoothing_keeps_bones: bool | str | None = None  # None: the model's own (as launch/sample.py --smoothing-keeps-bones)
    smoothing: float | None = None  # σ in frames of the output's Gaussian smoothing; None: the sampler's default
    decode: str = "ric"  # a key of pipeline.generation.sampling.JOINT_DECODES
    device: str = "auto"
    weights: str = "ema"
    text_weights: str | None = None

    def __post_init__(self) -> None:
        if bool(self.texts) == bool(self.captions_from_manifest):
            raise SamplingError("give texts or a manifest split to take captions from (exactly one of the two)")
        if self.ground_truth and not self.captions_from_manifest:
            raise SamplingError("ground truth exists for the dataset's own captions only: take them from a manifest "
                                "split")
        if self.checkpoint is None and not (self.ground_truth and self.manifest is not None):
            raise SamplingError("generating needs a checkpoint (ground truth: a checkpoint or a manifest)")
        if self.decode not in JOINT_DECODES:
            raise SamplingError(f"decode must be one of {sorted(JOINT_DECODES)}, got {self.decode!r}")
        if self.max_rows is not None and (not self.captions_from_manifest or not isinstance(self.max_rows, int)
                                          or self.max_rows < 1):
            raise SamplingError(f"max_rows must be a positive int and needs a manifest split, got {self.max_rows!r}")
        if not isinstance(self.frames, int) or self.frames < 1:
            raise SamplingError(f"frames must be a positive int, got {self.frames!r}")


@dataclasses.dataclass(frozen=True)
class DatasetCaption:
    motion_id: str
    text: str
    features: np.ndarray  # (L, D) un-normalised: the part of the motion the caption describes


def first_captions(manifest: Manifest, split: str) -> list[DatasetCaption]:
    """The first caption of every motion of ``split``, in manifest order, with the span of the motion it describes."""
    backend = "webdataset" if manifest.split(split).get("shards") else "parquet"  # whichever format was built
    captions = []
    for record in iter_motions(manifest, split, backend):
        start, end = (int(frame) for frame in record.spans[0])
        captions.append(DatasetCaption(record.id, record.captions[0], record.features[start:end]))
    return captions


def mean_joint_error(a: np.ndarray, b: np.ndarray) -> float:
    """Mean joint distance of two (T, J, 3) motions over their common frames. No alignment: recovered motions
    start with the root above the origin, facing +z."""
    frames = min(len(a), len(b))
    return float(np.linalg.norm(a[:frames] - b[:frames], axis=-1).mean())


def compare_with_clips(motions: Sequence[np.ndarray], clips: Sequence[np.ndarray], skeleton: Skeleton,
                       ids: Sequence[str], captions: Sequence[str] = ()) -> dict[str, Any]:
    """Samples of the dataset's captions against the clips the captions describe (row i ↔ clip i): medians of the
    plausibility figures, generated beside ground truth (jerk ratio: each sample over its own clip), and per row
    the mean joint error to its own clip, the clip it is nearest to (``caption_match``: the share of rows whose
    nearest clip is their own) and ``movement_ratio``, its :func:`mfm.metrics.movement_spread` over its own clip's (the median of the
    ratios is ``median_movement_ratio``: 1 = moves as much as its clip). With ``captions`` of the synthetic set on
    HumanML3D's skeleton, ``caption_checks`` says for samples and clips alike how many show what their caption
    states (side, count, in place, direction: :mod:`mfm.caption_checks`)."""
    generated = plausibility_figures(motions, skeleton)
    truth = plausibility_figures(clips, skeleton)
    truth = truth.with_jerk_reference(truth.mean_jerk)  # 1 (or undefined) by definition: the column's reference
    generated = generated.with_jerk_reference(truth.mean_jerk)
    errors = np.array([[mean_joint_error(m, c) for c in clips] for m in motions])
    nearest = errors.argmin(axis=1)
    movement = movement_spread(*padded_motions(motions)) / np.maximum(movement_spread(*padded_motions(clips)), 1e-9)
    rows = [{"id": ids[i], "error_to_own_clip_m": float(errors[i, i]), "nearest_clip": ids[int(nearest[i])],
             "movement_ratio": float(movement[i]), **generated.clip(i)} for i in range(len(motions))]
    report = {"plausibility": plausibility_side_by_side(generated, truth), "thresholds": plausibility_settings(skeleton),
              "caption_match": float(np.mean(nearest == np.arange(len(motions)))),
              "median_error_to_own_clip_m": float(np.median(np.diag(errors))),
              "median_movement_ratio": float(np.median(movement)), "rows": rows}
    if captions and skeleton.num_joints == 22 and any(stated_attributes(c) for c in captions):
        checked = {"generated": caption_check_summary(motions, captions),
                   "ground_truth": caption_check_summary(clips, captions)}
        report["caption_checks"] = {name: result["summary"] for name, result in checked.items()}
        for row, check in zip(rows, checked["generated"]["rows"]):
            row["caption_checks"] = check["checks"]
            row["caption_observed"] = check["observed"]
    return report


def plausibility_figures(motions: Sequence[np.ndarray], skeleton: Skeleton):
    """:func:`mfm.metrics.plausibility` of motions of different lengths (padded, with their lengths)."""
    padded, lengths = padded_motions(motions)
    return plausibility(padded, skeleton, lengths)


def _dataset(request: ContactSheetRequest) -> Manifest:
    location = request.manifest
    if location is None:
        location = load_trained_model(request.checkpoint).data.get("location")
        if not location:
            raise SamplingError(f"{request.checkpoint} records no dataset location: give the manifest")
    manifest = _open_dataset(location)
    if request.manifest is None and manifest.pair_set_source:
        # a few-step student's recorded dataset is its teacher pair set: compare with the teacher's dataset's clips
        manifest = _open_dataset(manifest.pair_set_source)
    return manifest


def _open_dataset(location: str) -> Manifest:
    try:
        return open_manifest(location)
    except (OSError, ValueError) as err:  # ManifestError is a ValueError
        raise SamplingError(f"cannot read the dataset manifest {location}: {err}") from err


def run_contact_sheet(request: ContactSheetRequest) -> dict[str, Any]:
    """Draw the request's sheet into ``request.out``; returns what it shows (mode, rows, and for generated
    rows the sampling settings as results.json records them)."""
    split = request.captions_from_manifest
    captions = []
    if split:
        manifest = _dataset(request)
        try:
            captions = first_captions(manifest, split)
        except ValueError as err:
            raise SamplingError(str(err)) from err
        if not captions:
            raise SamplingError(f"{manifest.location}: split {split!r} holds no motions")
        captions = captions[: request.max_rows]
    if request.ground_truth:
        spec = manifest.data["feature_spec"]
        skeleton, fps = skeleton_from_spec(spec), float(spec["fps"])
        motions = [DECODERS[request.decode](c.features, skeleton) for c in captions]
        titles = [c.text for c in captions]
        header = f"ground truth: first caption of every {split} motion of {Path(manifest.location).parent.name}"
        info: dict[str, Any] = {"mode": "ground_truth", "manifest": manifest.location}
    else:
        titles = list(request.texts) or [c.text for c in captions]
        with tempfile.TemporaryDirectory(prefix="contact-sheet-") as folder:
            results = run_sampling(SampleRequest(
                checkpoint=request.checkpoint, out_dir=folder, texts=titles, seconds=request.seconds,
                lengths=[len(c.features) for c in captions] if not request.seconds else [],
                steps=request.steps, solver=request.solver, guidance=request.guidance, seed=request.seed,
                smoothing=request.smoothing, smoothing_keeps_bones=request.smoothing_keeps_bones,
                guided_features=request.guided_features,
                device=request.device, weights=request.weights, text_weights=request.text_weights,
                decode=request.decode, video=False, bvh=False, progress=False))
            motions = [np.load(Path(folder) / f["path"]) for s in results["samples"] for f in s["files"]
                       if f["kind"] == "joints"]
        skeleton, fps = get_skeleton(results["skeleton"]), float(results["fps"])
        run = Path(results["checkpoint"]).parents[1].name  # checkpoints live in RUN/checkpoints/step-XXXXXXXX
        header = (f"generated: {run} step {results['step']}, {results['solver']} {results['steps']} steps, "
                  f"guidance {results['guidance']:g}{' of the pose' if results['guided_features'] == 'pose' else ''}, "
                  f"seed {results['seed']}{', raw weights' if results['weights'] == 'model' else ''}")
        info = {"mode": "generated", **{key: results[key] for key in ("checkpoint", "step", "weights", "solver",
                                                                        "steps", "guidance", "guided_features",
                                                                        "seed", "smoothing_sigma",
                                                                        "smoothing_keeps_bones")}}
        if captions and not request.seconds:
            clips = [DECODERS[request.decode](c.features[: len(m)], skeleton) for c, m in zip(captions, motions)]
            info["against_dataset_clips"] = compare_with_clips(motions, clips, skeleton,
                                                               [c.motion_id for c in captions], titles)
    path = render_contact_sheet(request.out, motions, titles, skeleton, frames=request.frames, fps=fps, title=header)
    return {**info, "out": str(path), "decode": request.decode,
            "rows": [{"text": text, "frames": len(joints)} for text, joints in zip(titles, motions)]}
