"""Pretrained-model folders and a few-line Python API on top of the sampling code.

    python launch/export.py runs/default --out exported/default        # a checkpoint -> an inference folder

    from pipeline.generation.pretrained import MotionPipeline
    pipe = MotionPipeline.from_pretrained("exported/default")
    out = pipe(["a person walks in a circle"], seconds=4.0, seed=0)
    out.joints[0].shape                   # (80, 22, 3): metres, y up, at out.fps
    out.save("samples/circle")             # what launch/sample.py writes: features, joints, MP4, BVH, results.json

An exported folder holds ``model.safetensors`` (the EMA weights by default, nothing of the optimizer),
``normalization.safetensors`` (the training Mean/Std), ``config.json`` (the model config, objective and diffusion
preset, training window and step, and the dataset identity: feature spec, text encoder id and weights hash, action
classes, training lengths; written last, so a folder without it is incomplete) and ``README.md``, a model card (data,
steps, recipe, and the evaluator's metrics for this checkpoint when its run folder has any). ``launch/sample.py
--checkpoint`` takes an exported folder as it takes a checkpoint (:func:`pipeline.generation.inference.load_trained_model`
recognises it); the evaluator scores checkpoints (its results are keyed by a checkpoint's COMPLETE marker). :class:`MotionPipeline` generates through the same
functions as ``launch/sample.py`` (:func:`pipeline.generation.sampling.generated_batches`), so the same seed gives the same motion.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import safetensors.torch
import torch

from mfm.features import features_to_joints
from mfm.model import ModelConfig, MotionFlowTransformer
from pipeline import checkpoint as ckpt
from pipeline.generation.inference import (
    TrainedModel,
    load_trained_model,
    training_objective,
)

logger = logging.getLogger(__name__)

PRETRAINED_FORMAT = "mfm-pretrained"
PRETRAINED_VERSION = 1
CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"
NORMALIZATION_FILE = "normalization.safetensors"
CARD_FILE = "README.md"
CARD_METRICS = ("fid", "r_precision_top1", "r_precision_top3", "mm_dist", "diversity", "multimodality",
                "bone_length_range", "foot_skating_ratio", "jerk_ratio")


class PretrainedError(ValueError):
    """An export that cannot be written or an exported folder that cannot be read; names the folder and why."""


def is_pretrained_folder(path: str | Path) -> bool:
    config = Path(path) / CONFIG_FILE
    if not config.is_file():
        return False
    try:
        return json.loads(config.read_text()).get("format") == PRETRAINED_FORMAT
    except (OSError, ValueError):
        return False


# ---------------------------------------------------------------------------------------------------------------
# export


def export_pretrained(checkpoint: str | Path, out: str | Path, *, weights: str = "ema") -> Path:
    """Write the inference folder of ``checkpoint`` (a step folder or a run folder's newest) into ``out`` (new or
    empty); ``weights``: 'ema' (the raw weights when the run kept none) or 'model'."""
    if weights not in ("ema", "model"):
        raise PretrainedError(f"weights must be 'ema' or 'model', got {weights!r}")
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise PretrainedError(f"{out} exists and is not an empty folder: export into a new one")
    trained = load_trained_model(checkpoint, use_ema=weights == "ema")
    _, _, state = ckpt.load_checkpoint(trained.checkpoint)
    out.mkdir(parents=True, exist_ok=True)
    state_dict = {k: v.detach().cpu().contiguous() for k, v in trained.model.state_dict().items()}
    safetensors.torch.save_file(state_dict, str(out / WEIGHTS_FILE), metadata={"format": PRETRAINED_FORMAT})
    safetensors.torch.save_file({"mean": trained.mean.cpu().contiguous(), "std": trained.std.cpu().contiguous()},
                                str(out / NORMALIZATION_FILE))
    identity = {k: v for k, v in trained.data.items() if k != "normalization"}
    normalization = {k: v for k, v in trained.data["normalization"].items() if k not in ("mean", "std")}
    config = {
        "format": PRETRAINED_FORMAT,
        "version": PRETRAINED_VERSION,
        "source_checkpoint": str(trained.checkpoint.resolve()),
        "checkpoint_id": ckpt.checkpoint_id(ckpt.read_marker(trained.checkpoint)),
        "step": trained.step,
        "weights": trained.weights,
        "objective": trained.objective,
        "diffusion_preset": trained.diffusion_preset,
        "window": trained.window,
        "model_config": dataclasses.asdict(trained.model_config),
        "data": {**identity, "normalization": normalization},
    }
    (out / CARD_FILE).write_text(model_card(trained, config, state["config"]), encoding="utf-8")
    (out / CONFIG_FILE).write_text(json.dumps(config, indent=1) + "\n", encoding="utf-8")  # last: complete
    logger.info("exported %s (%s weights, step %d) to %s", trained.checkpoint, trained.weights, trained.step, out)
    return out


def model_card(trained: TrainedModel, config: dict[str, Any], train_config: dict[str, Any]) -> str:
    """README.md of an export: what it was trained on, how, and what the evaluator measured."""
    spec, text = trained.data["feature_spec"], trained.data["text_encoder"]
    model = trained.model_config
    conditioning = (f"{len(trained.action_classes)} action classes" if model.is_action_model else
                    f"text: {text['id']} ({text['dim']}-D, weights sha256 {str(text['weights_sha256'])[:16]})")
    optim, loop = train_config.get("optim", {}), train_config.get("train", {})
    lines = [
        f"# Motion model: step {trained.step} of `{config['source_checkpoint']}`",
        "",
        "Exported with `launch/export.py`; load with `MotionPipeline.from_pretrained(folder)` or pass the folder "
        "to `launch/sample.py --checkpoint`.",
        "",
        "## Data",
        f"- dataset id `{trained.dataset_id}` ({trained.data.get('location', '?')})",
        f"- features: {spec['representation']} {spec['dim']}-D on the {spec['skeleton']} skeleton at {spec['fps']:g} fps",
        f"- condition: {conditioning}",
        f"- normalisation: {trained.data['normalization'].get('rule', 'the training split')}",
        "",
        "## Model and recipe",
        f"- objective: {trained.objective}" + (f" ({trained.diffusion_preset} preset)" if trained.diffusion_preset
                                               else ""),
        f"- {model.num_layers} layers, width {model.latent_dim}, FF {model.ff_dim}, {model.num_heads} heads, "
        f"{model.conditioning} conditioning, {model.positional} positions, prediction {model.prediction}",
        f"- {trained.step} steps, batch {train_config.get('data', {}).get('batch_size', '?')} of "
        f"{trained.window}-frame windows, lr {optim.get('lr', '?')} ({optim.get('schedule', '?')}), "
        f"flow loss {loop.get('flow_loss', '?')}; weights: {trained.weights}",
        "",
        "## Evaluation",
        *evaluation_lines(trained.checkpoint, config["checkpoint_id"]),
        "",
    ]
    return "\n".join(lines)


def evaluation_lines(folder: Path, checkpoint_id: str) -> list[str]:
    """The evaluator's rows for this checkpoint (``<run>/eval/results.jsonl``), as a Markdown table."""
    table = ckpt.run_dir_of(folder) / "eval" / "results.jsonl"
    rows = []
    if table.is_file():
        for line in table.read_text().splitlines():
            row = json.loads(line)
            if row.get("checkpoint_id") == checkpoint_id:
                rows.append(row)
    if not rows:
        return [f"No evaluator results for this checkpoint (looked in {table}); run `launch/evaluate.py "
                f"--checkpoint {folder}`."]
    shown = [m for m in CARD_METRICS if any(m in r for r in rows)]
    out = ["| row | protocol | solver, steps | " + " | ".join(shown) + " |",
           "|---" * (3 + len(shown)) + "|"]
    for row in rows:
        cells = []
        for metric in shown:
            mean, ci = row.get(metric), row.get(f"{metric}_ci")
            cells.append("—" if mean is None else f"{mean:.3g}" + ("" if ci is None else f" ± {ci:.2g}"))
        out.append(f"| {row.get('row_kind')} | {row.get('protocol')} | {row.get('solver')}, {row.get('steps')} | "
                   + " | ".join(cells) + " |")
    return out


# ---------------------------------------------------------------------------------------------------------------
# load


def load_pretrained(folder: str | Path, *, device: str | torch.device = "cpu") -> TrainedModel:
    """An exported folder as a :class:`TrainedModel` (what sampling and evaluation use)."""
    folder = Path(folder)
    try:
        config = json.loads((folder / CONFIG_FILE).read_text())
    except (OSError, ValueError) as err:
        raise PretrainedError(f"{folder}: no readable {CONFIG_FILE} ({err}): not an exported model folder") from err
    if config.get("format") != PRETRAINED_FORMAT or config.get("version") != PRETRAINED_VERSION:
        raise PretrainedError(f"{folder / CONFIG_FILE}: format {config.get('format')!r} version "
                              f"{config.get('version')!r}; this code reads {PRETRAINED_FORMAT!r} {PRETRAINED_VERSION}")
    model_config = ModelConfig(**config["model_config"])
    model = MotionFlowTransformer(model_config)
    try:
        model.load_state_dict(safetensors.torch.load_file(str(folder / WEIGHTS_FILE), device="cpu"))
        stats = safetensors.torch.load_file(str(folder / NORMALIZATION_FILE), device="cpu")
    except (OSError, RuntimeError, safetensors.SafetensorError) as err:
        raise PretrainedError(f"{folder}: the weights or normalisation cannot be read ({err})") from err
    train = {"objective": config["objective"], "diffusion": config.get("diffusion_preset") or "flowmdm"}
    objective, preset, diffusion = training_objective({"train": train}, model_config, folder)
    data = dict(config["data"])
    data["normalization"] = {**data.get("normalization", {}), "mean": stats["mean"].tolist(),
                             "std": stats["std"].tolist()}
    device = torch.device(device)
    model.to(device).eval()
    return TrainedModel(model, model_config, folder, int(config["step"]), str(config["weights"]), data, device,
                        int(config["window"]), objective, preset, diffusion)


# ---------------------------------------------------------------------------------------------------------------
# the few-line API


@dataclasses.dataclass
class GeneratedMotions:
    """What :class:`MotionPipeline` made: per motion its prompt, un-normalised features (L, D) and joints (L, J, 3)
    in metres; ``save`` writes them as ``launch/sample.py`` does."""

    texts: list[str | None]
    actions: list[str | None]
    lengths: list[int]
    features: list[np.ndarray]
    joints: list[np.ndarray]
    fps: float
    records: list[dict[str, Any]]
    _request: Any
    _trained: TrainedModel
    _integrator: Any

    def __len__(self) -> int:
        return len(self.features)

    def save(self, out_dir: str | Path, *, video: bool = True, bvh: bool = True, mdm_results: bool = False,
             overwrite: bool = False) -> Path:
        """Write every motion (sample_NNN/ with features.npy, joints.npy, motion.mp4|gif, motion.bvh) and
        results.json into ``out_dir``; ``mdm_results`` also MDM's results.npy."""
        from pipeline.generation import outputs

        out_dir = Path(out_dir)
        request = dataclasses.replace(self._request, out_dir=str(out_dir), video=video, bvh=bvh,
                                      mdm_results=mdm_results, overwrite=overwrite)
        outputs.prepare_out_dir(out_dir, overwrite)
        writer = outputs.SampleWriter(request, self._trained, out_dir)
        samples = []
        for record, features in zip(self.records, self.features):
            title = record["text"] or record["action"] or "unconditional"
            samples.append({**record, **writer.write(record["index"], features, title)})
        results = {**outputs.results_header(request, self._trained, self._integrator, "sample",
                                             bool(request.texts or request.actions)),
                   "api": "pipeline.generation.pretrained.MotionPipeline", "samples": samples}
        if mdm_results:
            results["mdm_results"] = outputs.write_mdm_layout(out_dir, samples, request.num_samples)
        outputs.write_json_atomically(out_dir / outputs.RESULTS_FILE, results)
        return out_dir


class MotionPipeline:
    """Generate motions from an exported folder (or any checkpoint) in a few lines; see the module docstring."""

    def __init__(self, trained: TrainedModel, *, text_weights: str | None = None) -> None:
        self.trained = trained
        self.text_weights = text_weights

    @classmethod
    def from_pretrained(cls, folder: str | Path, *, device: str = "auto", weights: str = "ema",
                        text_weights: str | None = None) -> MotionPipeline:
        """``folder``: an exported folder, a checkpoint or a run folder. ``text_weights``: CLIP datasets' weights
        file (checked against the recorded hash)."""
        from pipeline.generation.integration import resolve_device

        trained = load_trained_model(folder, use_ema=weights == "ema", device=resolve_device(device))
        return cls(trained, text_weights=text_weights)

    @property
    def fps(self) -> float:
        return self.trained.fps

    def __call__(self, texts: str | Sequence[str] = (), *, actions: Sequence[str] = (),
                 seconds: float | Sequence[float] | None = None, lengths: int | Sequence[int] | None = None,
                 num_samples: int = 1, seed: int = 0, steps: int | None = None, solver: str | None = None,
                 guidance: float | None = None, batch_size: int = 64, precision: str = "auto") -> GeneratedMotions:
        """Motions for ``texts`` (or ``actions``), ``num_samples`` each, ``seconds`` or ``lengths`` long (one value
        or one per prompt; default: drawn from the training lengths). ``precision``: fp32, bf16 or auto (bf16 on a
        CUDA GPU with bf16, else fp32; SampleRequest.precision). The same arguments give the same motions as
        ``launch/sample.py``."""
        from pipeline.generation import integration, sampling
        from pipeline.generation.request import SampleRequest

        texts = [texts] if isinstance(texts, str) else list(texts)
        request = SampleRequest(
            checkpoint=str(self.trained.checkpoint), out_dir="", texts=texts, actions=list(actions),
            seconds=_as_list(seconds), lengths=_as_list(lengths), num_samples=num_samples, seed=seed, steps=steps,
            solver=solver, guidance=guidance, batch_size=batch_size, text_weights=self.text_weights,
            precision=precision)
        trained = self.trained
        integrator = integration.resolve_integrator(request, trained)
        conditions = sampling.encode_prompts(request, trained)
        specs = sampling.plan_samples(request, trained, None)
        records: dict[int, dict[str, Any]] = {}
        features: dict[int, np.ndarray] = {}
        for chunk, batch, batch_features, _ in sampling.generated_batches(request, trained, integrator, specs,
                                                                          conditions, None, {}):
            for row, spec in enumerate(chunk):
                records[spec.index] = sampling.sample_record(request, trained, integrator, spec, chunk, batch.nfe)
                features[spec.index] = np.ascontiguousarray(batch_features[row, :spec.length], dtype=np.float32)
        order = sorted(records)
        motion_features = [features[i] for i in order]
        return GeneratedMotions(
            texts=[records[i]["text"] for i in order], actions=[records[i]["action"] for i in order],
            lengths=[records[i]["length"] for i in order], features=motion_features,
            joints=[features_to_joints(f, trained.skeleton).astype(np.float32) for f in motion_features],
            fps=trained.fps, records=[records[i] for i in order], _request=request, _trained=trained,
            _integrator=integrator)


def _as_list(value: float | int | Sequence | None) -> list:
    if value is None:
        return []
    return list(value) if isinstance(value, (list, tuple)) else [value]
