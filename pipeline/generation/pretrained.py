"""Pretrained-model folders and a diffusers-shaped Python API on top of the sampling code.

    python launch/export.py runs/default --out exported/default        # a checkpoint -> an inference folder

    import torch
    from pipeline.generation.pretrained import MotionPipeline
    pipe = MotionPipeline.from_pretrained("exported/default", torch_dtype=torch.float32).to("cuda")
    out = pipe(prompt="a person walks in a circle", seconds=4.0, num_inference_steps=10, guidance_scale=2.5,
               generator=torch.Generator().manual_seed(0), output_type="np")
    out.joints[0].shape                   # (80, 22, 3): metres, y up, at out.fps
    out.save("samples/circle")             # what launch/sample.py writes: features, joints, MP4, BVH, results.json
    pipe.save_pretrained("exported/copy")  # an exported folder again

The project's own argument names work as well (``pipe(["..."], seconds=4.0, seed=0, steps=10, guidance=2.5,
num_samples=2)``): each conventional name is an alias of one of ours (:data:`ARGUMENT_ALIASES`) and both reach the
same code path; giving both names of one argument is a TypeError.

An exported folder holds ``model.safetensors`` (the EMA weights by default, nothing of the optimizer),
``normalization.safetensors`` (the training Mean/Std), ``config.json`` (the model config, objective and diffusion
preset, training window and step, the dataset identity: feature spec, text encoder id and weights hash, action
classes, training lengths; and what the model card says: the training data's splits, the recipe and the evaluator's
rows for this checkpoint; written last, so a folder without it is incomplete) and ``README.md``, a Hugging Face Hub
model card (YAML metadata, intended use and limitations, training data and recipe, metrics naming their evaluator and
protocol; no local path). Files are written with the umask's permissions (0644 under the usual 022).
``launch/sample.py --checkpoint`` takes an exported folder as it takes a checkpoint
(:func:`pipeline.generation.inference.load_trained_model` recognises it; the folder's reader,
:func:`~pipeline.generation.inference.load_pretrained`, lives there, below everything that loads a model, and is
importable from here as well); the evaluator scores checkpoints (its results are keyed by a checkpoint's COMPLETE
marker). :class:`MotionPipeline` generates through the same functions as
``launch/sample.py`` (:func:`pipeline.generation.sampling.generated_batches`), so the same seed gives the same motion.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import safetensors.torch
import torch
import yaml

from mfm.features import features_to_joints
from mfm.model import ModelConfig
from mfm.solvers import ROUGH_AMPLIFICATION, sample_lengths
from pipeline import checkpoint as ckpt
from pipeline.generation import integration, outputs, sampling
from pipeline.generation.inference import (  # the folder format and its reader live with the other loaders
    CONFIG_FILE,
    NORMALIZATION_FILE,
    PRETRAINED_FORMAT,
    PRETRAINED_VERSION,
    SAMPLING_DTYPES,
    WEIGHTS_FILE,
    PretrainedError,
    TrainedModel,
    is_pretrained_folder,
    load_pretrained,  # noqa: F401  (importable from here too, where it was defined before)
    load_trained_model,
)
from pipeline.generation.integration import resolve_device
from pipeline.generation.request import SampleRequest
from preprocess.shards import ManifestError, derive_dataset_id, load_manifest

logger = logging.getLogger(__name__)

CARD_FILE = "README.md"
CARD_METRICS = ("fid", "r_precision_top1", "r_precision_top3", "mm_dist", "diversity", "multimodality",
                "bone_length_range", "foot_skating_ratio", "jerk_ratio")
# What the card repeats of an evaluator row (pipeline.evaluation.job.table_rows): how it was measured, never where.
CARD_ROW_FIELDS = ("row_kind", "evaluator_kind", "evaluator_id", "protocol", "protocol_loop", "redraw_items", "split",
                   "num_items", "replications", "sampling_point", "solver", "steps", "guidance")
SAMPLER_FIELDS = ("sampling_point", "solver", "steps", "guidance")  # what a ground-truth row does not depend on
PROVENANCE_KEYS = ("source_checkpoint", "checkpoint_id", "training", "evaluation")
"""What config.json records of where the weights came from, and the model card is written from."""
LICENSE_ID = "mit"  # the project's LICENSE (MIT), as the Hub's lower-case SPDX id
LIBRARY_NAME = "motion-flow-matching"
EVALUATORS = {
    "contrastive": "this project's contrastive text-motion evaluator (`launch/train_evaluator.py`), trained on the "
                   "same dataset: numbers compare checkpoints of this project, not published results",
    "t2m": "the official T2M evaluator (Guo et al. 2022, the text-motion matching model MDM and MFM report with): "
           "comparable with published numbers under the `mdm` or `full` protocol",
}
PROTOCOLS = {
    "fast": "3 replications, for training curves",
    "full": "20 replications, as published (T2M's protocol)",
    "mdm": "MDM's evaluation loop, rule by rule",
}
ARGUMENT_ALIASES = {"prompt": "texts", "num_motions_per_prompt": "num_samples", "num_inference_steps": "steps",
                    "guidance_scale": "guidance", "generator": "seed"}
"""diffusers' argument name -> ours: the same argument (``generator``: see :meth:`MotionPipeline.__call__`)."""
OUTPUT_TYPES = {"np": "numpy", "numpy": "numpy", "pt": "torch", "torch": "torch"}


# ---------------------------------------------------------------------------------------------------------------
# export


def export_pretrained(checkpoint: str | Path, out: str | Path, *, weights: str = "ema") -> Path:
    """Write the inference folder of ``checkpoint`` (a step folder or a run folder's newest) into ``out`` (new or
    empty); ``weights``: 'ema' (the raw weights when the run kept none) or 'model'."""
    if weights not in ("ema", "model"):
        raise PretrainedError(f"weights must be 'ema' or 'model', got {weights!r}")
    check_export_folder(out)
    trained = load_trained_model(checkpoint, use_ema=weights == "ema")
    return write_pretrained(trained, out, provenance(trained))


def check_export_folder(out: str | Path) -> Path:
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise PretrainedError(f"{out} exists and is not an empty folder: export into a new one")
    return out


def write_pretrained(trained: TrainedModel, out: str | Path, source: Mapping[str, Any]) -> Path:
    """Write ``trained`` (its weights in their current dtype) as an exported folder ``out`` (new or empty);
    ``source``: its :data:`PROVENANCE_KEYS` (:func:`provenance`)."""
    out = check_export_folder(out)
    out.mkdir(parents=True, exist_ok=True)
    state_dict = {k: v.detach().cpu().contiguous() for k, v in trained.model.state_dict().items()}
    write_file_atomically(out / WEIGHTS_FILE,
                          safetensors.torch.save(state_dict, metadata={"format": PRETRAINED_FORMAT}))
    write_file_atomically(out / NORMALIZATION_FILE, safetensors.torch.save(
        {"mean": trained.mean.cpu().contiguous(), "std": trained.std.cpu().contiguous()}))
    identity = {k: v for k, v in trained.data.items() if k != "normalization"}
    normalization = {k: v for k, v in trained.data["normalization"].items() if k not in ("mean", "std")}
    config = {
        "format": PRETRAINED_FORMAT,
        "version": PRETRAINED_VERSION,
        **{key: source.get(key) for key in PROVENANCE_KEYS},
        "step": trained.step,
        "weights": trained.weights,
        "torch_dtype": str(trained.dtype).removeprefix("torch."),
        "objective": trained.objective,
        "diffusion_preset": trained.diffusion_preset,
        "window": trained.window,
        "model_config": dataclasses.asdict(trained.model_config),
        "data": {**identity, "normalization": normalization},
    }
    write_file_atomically(out / CARD_FILE, model_card(config).encode("utf-8"))
    write_file_atomically(out / CONFIG_FILE, (json.dumps(config, indent=1) + "\n").encode("utf-8"))  # last: complete
    logger.info("exported %s (%s weights, step %d) to %s", trained.checkpoint, trained.weights, trained.step, out)
    return out


def write_file_atomically(path: Path, payload: bytes) -> None:
    """``payload`` into ``path`` through a temporary file and a rename. Created by ``open``, so with the umask's
    permissions (0644 under the usual 022): safetensors' own ``save_file`` leaves 0600, unreadable to a group that
    shares the folder."""
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "wb") as handle:
        handle.write(payload)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)


def provenance(trained: TrainedModel) -> dict[str, Any]:
    """Where ``trained``'s weights come from and what its model card says (:data:`PROVENANCE_KEYS`): read from the
    checkpoint (its training config, its dataset's manifest, its run's evaluator rows) or, for an exported folder,
    taken over from its config.json."""
    if is_pretrained_folder(trained.checkpoint):
        config = json.loads((Path(trained.checkpoint) / CONFIG_FILE).read_text())
        source = {key: config.get(key) for key in PROVENANCE_KEYS}
        if source["source_checkpoint"]:  # folders exported before the card dropped local paths
            source["source_checkpoint"] = portable_checkpoint_name(source["source_checkpoint"])
        return source
    _, _, state = ckpt.load_checkpoint(trained.checkpoint)
    checkpoint_id = ckpt.checkpoint_id(ckpt.read_marker(trained.checkpoint))
    return {
        "source_checkpoint": portable_checkpoint_name(trained.checkpoint),
        "checkpoint_id": checkpoint_id,
        "training": {"dataset": dataset_facts(trained), "recipe": recipe_facts(trained, state["config"])},
        "evaluation": evaluation_rows(trained.checkpoint, checkpoint_id),
    }


def portable_checkpoint_name(checkpoint: str | Path) -> str:
    """``<run name>/checkpoints/step-N``: the checkpoint named within its run, no folder of this machine."""
    folder = Path(checkpoint).resolve()
    run = ckpt.run_dir_of(folder)
    return (Path(run.name) / folder.relative_to(run)).as_posix()


def dataset_facts(trained: TrainedModel) -> dict[str, Any]:
    """The training data for the card: the dataset id, and from the manifest the checkpoint records (when it is
    still where training read it, with the same id) its source, folder name and split sizes."""
    facts: dict[str, Any] = {"dataset_id": trained.dataset_id, "name": None, "source": None, "splits": None}
    location = trained.data.get("location")
    if not location:
        return facts
    try:
        manifest = load_manifest(location, verify="none")
    except (ManifestError, OSError) as err:
        logger.warning("the model card lists no split sizes: the training manifest cannot be read (%s)", err)
        return facts
    if derive_dataset_id(manifest) != trained.dataset_id:
        logger.warning("the model card lists no split sizes: %s now holds another dataset than the checkpoint's",
                       location)
        return facts
    folder = Path(location) if Path(location).is_dir() else Path(location).parent
    facts["name"] = folder.name
    facts["source"] = (manifest.get("builder") or {}).get("options", {}).get("source")
    facts["splits"] = {name: {key: split.get(key) for key in ("num_motions", "num_captions", "num_frames")}
                       for name, split in manifest["splits"].items()}
    return facts


def recipe_facts(trained: TrainedModel, train_config: Mapping[str, Any]) -> dict[str, Any]:
    """How the checkpoint was trained, for the card (settings only: the training config's paths are left out)."""
    data, optim, loop = (train_config.get(key, {}) for key in ("data", "optim", "train"))
    return {
        "objective": trained.objective, "diffusion_preset": trained.diffusion_preset,
        "flow_loss": loop.get("flow_loss") if trained.objective == "flow" else None,
        "flow_time_sampling": loop.get("flow_time_sampling", "uniform") if trained.objective == "flow" else None,
        "flow_time_grid_steps": loop.get("flow_time_grid_steps"),
        "flow_grid_inputs": loop.get("flow_grid_inputs"),
        "critic_weight": loop.get("critic_weight", 0.0),  # train.critic_weight: an adversarial term (mfm.critic)
        "steps": trained.step, "batch_size": data.get("batch_size"), "window": trained.window,
        "optimizer": optim.get("optimizer", "adamw"), "muon_lr": optim.get("muon_lr"),
        "lr": optim.get("lr"), "schedule": optim.get("schedule"), "warmup_steps": optim.get("warmup_steps"),
        "weight_decay": optim.get("weight_decay"), "ema_decay": optim.get("ema_decay"),
        "mixed_precision": loop.get("mixed_precision"), "weights": trained.weights,
        "distill": train_config.get("distill"),  # a few-step student: its method and teacher (launch/distill.py)
    }


def evaluation_rows(folder: Path, checkpoint_id: str) -> list[dict[str, Any]]:
    """The evaluator's rows for this checkpoint (``<run>/eval/results.jsonl``, pipeline/evaluation/store.py): how
    each was measured (:data:`CARD_ROW_FIELDS`) and its :data:`CARD_METRICS` with their intervals. One row per
    setting, the last written (a re-evaluation under changed settings appends a new row); one ground-truth row per
    evaluator and protocol (it does not depend on the sampler), after that protocol's generated rows."""
    table = ckpt.run_dir_of(folder) / "eval" / "results.jsonl"
    if not table.is_file():
        return []
    latest: dict[tuple, dict[str, Any]] = {}
    for line in table.read_text().splitlines():
        row = json.loads(line) if line.strip() else {}
        if row.get("checkpoint_id") != checkpoint_id:
            continue
        kept = {k: row.get(k) for k in CARD_ROW_FIELDS}
        if kept["row_kind"] == "ground_truth":
            kept.update(dict.fromkeys(SAMPLER_FIELDS))
        kept.update({k: row[k] for m in CARD_METRICS for k in (m, f"{m}_ci") if row.get(k) is not None})
        setting = tuple(json.dumps(kept[k]) for k in CARD_ROW_FIELDS)
        latest.pop(setting, None)
        latest[setting] = kept
    return sorted(latest.values(), key=lambda r: (str(r["evaluator_id"]), str(r["protocol"]),
                                                  r["row_kind"] == "ground_truth"))


def model_card(config: Mapping[str, Any]) -> str:
    """README.md of an exported folder, from its config.json: a Hugging Face Hub model card."""
    model = ModelConfig(**config["model_config"])
    data = config["data"]
    spec, text = data["feature_spec"], data["text_encoder"]
    training = config.get("training") or {}
    dataset, recipe = training.get("dataset") or {}, training.get("recipe") or {}
    rows = config.get("evaluation") or []
    task = "action-to-motion" if model.is_action_model else "text-to-motion"
    method = "flow-matching" if config["objective"] == "flow" else "diffusion"
    metadata = {
        "license": LICENSE_ID,
        "library_name": LIBRARY_NAME,
        "tags": [task, "motion-generation", method, "human-motion"],
        "datasets": [dataset["source"]] if dataset.get("source") else [],
        "metrics": [m for m in CARD_METRICS if any(m in r for r in rows)],
    }
    seconds = config["window"] / spec["fps"]
    conditioning = (f"{len(data.get('action_classes', []))} action classes ({', '.join(data.get('action_classes', []))})"
                    if model.is_action_model else
                    f"text encoded by `{text['id']}` ({text['dim']}-D, weights sha256 "
                    f"{str(text['weights_sha256'])[:16]}...)")
    prompt = 'actions=["walk"]' if model.is_action_model else 'prompt="a person walks forward"'
    lines = [
        "---", yaml.safe_dump(metadata, sort_keys=False).rstrip(), "---", "",
        f"# {task.capitalize()} {method} model (step {config['step']})",
        "",
        f"A `MotionFlowTransformer` trained with {'flow matching' if method == 'flow-matching' else 'diffusion'} to "
        f"generate human motion ({spec['representation']} {spec['dim']}-D features on the {spec['skeleton']} "
        f"skeleton at {spec['fps']:g} fps) from {conditioning}. Exported with `launch/export.py` from "
        f"`{config.get('source_checkpoint') or '?'}` ({config['weights']} weights).",
        "",
        "## Use",
        "",
        "```python",
        "import torch",
        "from pipeline.generation.pretrained import MotionPipeline",
        "",
        'pipe = MotionPipeline.from_pretrained("path/to/this/folder", torch_dtype=torch.float32).to("cpu")',
        f"out = pipe({prompt}, seconds=4.0, num_inference_steps={model.sampling_steps}, "
        f"guidance_scale={model.sampling_guidance:g}, "
        "generator=torch.Generator().manual_seed(0))",
        "out.joints[0].shape  # (frames, joints, 3) in metres, y up",
        "```",
        "",
        "or `python launch/sample.py --checkpoint path/to/this/folder "
        + ("--action walk" if model.is_action_model else '--text "a person walks forward"') + "`.",
        "",
        "## Intended use and limitations",
        "",
        f"- Intended for research on {task} generation: sampling, editing and evaluating motions of up to "
        f"{config['window']} frames ({seconds:g} s) on the {spec['skeleton']} skeleton, for prompts like the training "
        "data's.",
        f"- Longer motions are clamped to {config['window']} frames; prompts unlike the training captions (other "
        "languages, objects, scenes, several people) are outside what it has learnt.",
        "- Outputs are kinematic joint positions: no physics, contacts or collisions are enforced; check foot skating "
        "and floor penetration (`results.json` of `launch/sample.py` reports them) before using a motion.",
        "- The code's MIT licence covers the code and this card; weights trained on a dataset carry that dataset's "
        "terms too (HumanML3D and KIT-ML derive from AMASS / KIT, whose licences restrict use, e.g. to research).",
        "",
        "## Training data",
        "",
        f"- dataset id `{dataset.get('dataset_id') or data.get('dataset_id')}`"
        + (f", built from source `{dataset['source']}`" if dataset.get("source") else "")
        + (f" (folder `{dataset['name']}`)" if dataset.get("name") else ""),
        f"- features: {spec['representation']} {spec['dim']}-D, {spec['skeleton']} skeleton, {spec['fps']:g} fps; "
        f"condition: {conditioning}",
        f"- normalisation: {data.get('normalization', {}).get('rule', 'Mean/Std of the training split')}",
        *_split_lines(dataset.get("splits")),
        "",
        "## Training recipe",
        "",
        *_recipe_lines(config, model, recipe),
        "",
        "## Evaluation",
        "",
        *_evaluation_lines(rows),
        "",
    ]
    return "\n".join(lines)


def _split_lines(splits: Mapping[str, Mapping[str, Any]] | None) -> list[str]:
    if not splits:
        return ["- split sizes: not recorded (the training manifest was not readable at export)"]
    out = ["", "| split | motions | captions | frames |", "|---|---|---|---|"]
    out += [f"| {name} | {s.get('num_motions')} | {s.get('num_captions')} | {s.get('num_frames')} |"
            for name, s in splits.items()]
    return out


def _recipe_lines(config: Mapping[str, Any], model: ModelConfig, recipe: Mapping[str, Any]) -> list[str]:
    objective = config["objective"] + (f" ({config['diffusion_preset']} preset)" if config.get("diffusion_preset")
                                       else f", {recipe['flow_loss']} loss" if recipe.get("flow_loss") else "")
    lines = [
        f"- objective: {objective}",
        f"- model: {model.num_layers} layers, width {model.latent_dim}, feed-forward {model.ff_dim}, "
        f"{model.num_heads} heads, {model.conditioning} conditioning, {model.positional} positions, prediction "
        f"{model.prediction}; condition dropout {model.cond_drop_prob:g} (classifier-free guidance, sampled at "
        f"{model.sampling_guidance:g})",
    ]
    if not recipe:
        return lines + ["- optimisation: not recorded in this folder"]
    distill = recipe.get("distill")
    if distill:
        lines.append(
            f"- a few-step student ({distill.get('method')}, `launch/distill.py`) of the teacher "
            f"`{'/'.join(Path(str(distill.get('teacher'))).parts[-3:])}` at step {distill.get('teacher_step')} (checkpoint id "
            f"`{str(distill.get('teacher_checkpoint_id'))[:16]}...`), trained on the teacher's "
            f"{distill.get('teacher_solver')} {distill.get('teacher_steps')}-step solutions at guidance "
            f"{distill.get('teacher_guidance'):g} ({distill.get('teacher_guided_features')} channels); samples in "
            f"{model.sampling_steps} step(s) at guidance {model.sampling_guidance:g}")
        if model.sampling_times is not None:
            lines.append(f"- its {len(model.sampling_times)}-step sampler starts its Euler steps at the times "
                         f"{', '.join(f'{t:g}' for t in model.sampling_times)} (`model.sampling_times`), not on the "
                         "uniform grid")
        amplification = distill.get("teacher_flow_map_amplification")
        if amplification is not None:
            lines.append(f"- the teacher's flow-map amplification (how far its motion moves per unit change of the "
                         f"noise, median over probed pairs; reflow fits a map near 1): {amplification:.3g}"
                         + (" (rough: a reflow student learns an average of the teacher's motions; docs/few-step.md, "
                            "'A rough teacher')" if amplification > ROUGH_AMPLIFICATION else ""))
        if recipe.get("flow_time_sampling") == "grid":
            grid = int(recipe.get("flow_time_grid_steps") or 0)
            lines.append(f"- trained only at the times its {grid}-step Euler sampler visits (0, 1/{grid}, ...: "
                         "`train.flow_time_sampling=grid`); at step counts whose times are not among them it runs "
                         "at times it was not distilled at")
            if recipe.get("flow_grid_inputs") == "own_path":
                lines.append("- each later step trained from the state its own earlier steps reach, not from the "
                             "straight path's (`train.flow_grid_inputs=own_path`, backward distillation)")
    if recipe.get("critic_weight"):
        lines.append(f"- trained with a critic on the motion its training pass leads to, the critic's judgement "
                     f"weighted {recipe['critic_weight']:g} in the loss (adversarial distillation, "
                     "`train.critic_weight`; docs/few-step.md, 'A critic in the trainer')")
    rate = (f"AdamW lr {recipe.get('lr')} and Muon lr {recipe.get('muon_lr')} on the Transformer blocks' matrices "
            "(`optim.optimizer=muon`)" if recipe.get("optimizer") == "muon" else f"lr {recipe.get('lr')}")
    return lines + [
        f"- {recipe.get('steps')} steps, batch {recipe.get('batch_size')} of {recipe.get('window')}-frame windows, "
        f"{rate} ({recipe.get('schedule')}, {recipe.get('warmup_steps')} warm-up steps), weight decay "
        f"{recipe.get('weight_decay')}, EMA decay {recipe.get('ema_decay')}, mixed precision "
        f"{recipe.get('mixed_precision')}; exported weights: {recipe.get('weights')}",
    ]


def _evaluation_lines(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """The evaluator's rows as a Markdown table, each naming its evaluator and protocol, with a legend."""
    if not rows:
        return ["No evaluator results for this checkpoint in its run's `eval/results.jsonl` at export; evaluate the "
                "checkpoint with `launch/evaluate.py --checkpoint ...` and export again to list them."]
    shown = [m for m in CARD_METRICS if any(m in r for r in rows)]
    out = ["| evaluator | protocol | split, items × replications | solver, steps, guidance | row | "
           + " | ".join(shown) + " |", "|---" * (5 + len(shown)) + "|"]
    for row in rows:
        cells = []
        for metric in shown:
            mean, ci = row.get(metric), row.get(f"{metric}_ci")
            cells.append("—" if mean is None else f"{mean:.3g}" + ("" if ci is None else f" ± {ci:.2g}"))
        notes = [f"{row['protocol_loop']} loop"] if row.get("protocol_loop") else []
        notes += [] if row.get("redraw_items") else ["fixed items"]
        sampler = ("—" if row.get("row_kind") == "ground_truth" else
                   f"{row.get('solver')}, {row.get('steps')}, {row.get('guidance')}")
        out.append(f"| {row.get('evaluator_kind')} | {row.get('protocol')}" + (f" ({', '.join(notes)})" if notes else "")
                   + f" | {row.get('split')}, {row.get('num_items')} × {row.get('replications')} | {sampler} | "
                   f"{row.get('row_kind')} | " + " | ".join(cells) + " |")
    out += ["", "Mean ± 95 % interval over the replications; `ground_truth` rows score the test set itself."]
    for kind in dict.fromkeys(r.get("evaluator_kind") for r in rows):
        ids = sorted({str(r.get("evaluator_id"))[:16] for r in rows if r.get("evaluator_kind") == kind})
        out.append(f"- evaluator `{kind}`: {EVALUATORS.get(kind, 'recorded as is')} (id {', '.join(ids)})")
    for name in dict.fromkeys(r.get("protocol") for r in rows):
        out.append(f"- protocol `{name}`: {PROTOCOLS.get(name, 'recorded as is')}")
    return out


# ---------------------------------------------------------------------------------------------------------------
# the few-line API


@dataclasses.dataclass
class GeneratedMotions:
    """What :class:`MotionPipeline` made: per motion its prompt, un-normalised features (L, D) and joints (L, J, 3)
    in metres (numpy arrays, or CPU float32 tensors with ``output_type="pt"``); ``save`` writes them as
    ``launch/sample.py`` does."""

    texts: list[str | None]
    actions: list[str | None]
    lengths: list[int]
    features: list[np.ndarray] | list[torch.Tensor]
    joints: list[np.ndarray] | list[torch.Tensor]
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
        out_dir = Path(out_dir)
        request = dataclasses.replace(self._request, out_dir=str(out_dir), video=video, bvh=bvh,
                                      mdm_results=mdm_results, overwrite=overwrite)
        outputs.prepare_out_dir(out_dir, overwrite)
        writer = outputs.SampleWriter(request, self._trained, out_dir)
        samples = []
        for record, features in zip(self.records, self.features):
            title = record["text"] or record["action"] or "unconditional"
            samples.append({**record, **writer.write(record["index"], np.asarray(features), title)})
        results = {**outputs.results_header(request, self._trained, self._integrator, "sample",
                                             bool(request.texts or request.actions)),
                   "api": "pipeline.generation.pretrained.MotionPipeline", "samples": samples}
        if mdm_results:
            results["mdm_results"] = outputs.write_mdm_layout(out_dir, samples, request.num_samples)
        outputs.write_json_atomically(out_dir / outputs.RESULTS_FILE, results)
        return out_dir


class MotionPipeline:
    """Generate motions from an exported folder (or any checkpoint) in a few lines, with diffusers' names:
    :meth:`from_pretrained` (``torch_dtype=``), :meth:`to`, a call taking ``prompt=``, ``num_inference_steps=``,
    ``guidance_scale=``, ``generator=`` and ``output_type=``, and :meth:`save_pretrained`; see the module docstring."""

    def __init__(self, trained: TrainedModel, *, text_weights: str | None = None, weights: str | None = None,
                 compile: bool | str = "auto") -> None:
        """``weights``: the weights asked for, 'ema' or 'model' (a FLAME checkpoint asked for its EMA that kept none
        is refused when sampling, as launch/sample.py); None: those ``trained`` holds. ``compile``: torch.compile the
        model passes, auto (on a CUDA device only, with CUDA graphs), True or False (SampleRequest.compile); the
        compiled model is built here (and again after :meth:`to`) and reused by every call."""
        self.compile = compile
        self.trained = trained.compiled_with(compile)
        self.text_weights = text_weights
        self.weights = weights or trained.weights

    @classmethod
    def from_pretrained(cls, folder: str | Path, *, device: str | torch.device = "auto",
                        torch_dtype: torch.dtype | str | None = None, weights: str = "ema",
                        text_weights: str | None = None, compile: bool | str = "auto") -> MotionPipeline:
        """``folder``: an exported folder, a checkpoint or a run folder. ``device``: auto (cuda when there is one),
        cpu, cuda, cuda:N or mps. ``torch_dtype``: the weights' dtype (float32 by default, whatever the folder
        stores; bfloat16 or float16, see :meth:`to`). ``text_weights``: CLIP datasets' weights file
        (checked against the recorded hash). ``compile``: auto (on CUDA only, CUDA graphs), True or False
        (:class:`MotionPipeline`)."""
        trained = load_trained_model(folder, use_ema=weights == "ema", device=resolve_device(str(device)))
        if torch_dtype is not None:  # before compiling: the compiled model is of the weights' dtype
            trained = trained.to(dtype=_as_dtype(torch_dtype))
        return cls(trained, text_weights=text_weights, weights=weights, compile=compile)

    def to(self, *args: str | torch.device | torch.dtype, device: str | torch.device | None = None,
           dtype: torch.dtype | str | None = None) -> MotionPipeline:
        """Move the model to a device and/or weight dtype, like ``nn.Module.to``: ``pipe.to("cuda")``,
        ``pipe.to(torch.bfloat16)``, ``pipe.to("cuda", torch.float16)`` or by keyword; returns the pipeline.
        Sampling keeps its state (noise, ODE/diffusion steps, Mean/Std) in float32 and runs a bfloat16/float16
        model under autocast, so a half dtype changes motions by its rounding only. float64 is refused: the model
        computes its time and position tables in float32 by design."""
        for arg in args:
            if isinstance(arg, torch.dtype) or (isinstance(arg, str) and _dtype_named(arg) is not None):
                if dtype is not None:
                    raise TypeError("MotionPipeline.to() got two dtypes")
                dtype = arg
            elif isinstance(arg, (str, torch.device)):
                if device is not None:
                    raise TypeError("MotionPipeline.to() got two devices")
                device = arg
            else:
                raise TypeError(f"MotionPipeline.to() takes a device and/or a torch.dtype, got {arg!r}")
        target = None if device is None else resolve_device(str(device))
        self.trained = self.trained.to(target, _as_dtype(dtype)).compiled_with(self.compile)  # for the new device
        return self

    @property
    def device(self) -> torch.device:
        return self.trained.device

    @property
    def dtype(self) -> torch.dtype:
        return self.trained.dtype

    @property
    def fps(self) -> float:
        return self.trained.fps

    def save_pretrained(self, save_directory: str | Path) -> Path:
        """Write this pipeline's model as an exported folder (new or empty) that :meth:`from_pretrained` and
        ``launch/sample.py --checkpoint`` read: the weights in their current dtype, the normalisation, config.json
        and the model card (provenance, training data, recipe and metrics carried over from where it was loaded)."""
        return write_pretrained(self.trained, save_directory, provenance(self.trained))

    def __call__(self, texts: str | Sequence[str] | None = None, *, prompt: str | Sequence[str] | None = None,
                 actions: Sequence[str] = (), seconds: float | Sequence[float] | None = None,
                 lengths: int | Sequence[int] | None = None, num_samples: int | None = None,
                 num_motions_per_prompt: int | None = None, seed: int | None = None,
                 generator: torch.Generator | Sequence[torch.Generator] | None = None, steps: int | None = None,
                 num_inference_steps: int | None = None, solver: str | None = None, guidance: float | None = None,
                 guidance_scale: float | None = None, batch_size: int = 64,
                 output_type: str = "np", baseline_defaults: bool = True,
                 clip_denoised: bool = True, precision: str = "auto") -> GeneratedMotions:
        """Motions for ``texts`` (or ``actions``), ``num_samples`` each, ``seconds`` or ``lengths`` long (one value
        or one per prompt; default: drawn from the training lengths). The same arguments give the same motions as
        ``launch/sample.py``. A FLAME-preset diffusion checkpoint samples as FLAME's authors did unless
        ``baseline_defaults=False`` (or ``clip_denoised=False``: no x0 clamp; ``steps``: fewer than every training
        step), as SampleRequest's keys of those names. ``precision``: fp32, bf16 or auto (bf16 on a CUDA GPU with
        bf16, else fp32; SampleRequest.precision).

        Each diffusers name is an alias of ours (:data:`ARGUMENT_ALIASES`; giving both is a TypeError): ``prompt``
        = ``texts``, ``num_motions_per_prompt`` = ``num_samples`` (default 1), ``num_inference_steps`` = ``steps``
        (default: the solver's, 10 Euler steps for a flow model), ``guidance_scale`` = ``guidance`` (default: the
        model's own), ``generator`` instead of ``seed`` (default 0):

        - ``seed``: motion ``i``'s initial noise comes from ``torch.Generator().manual_seed(sample_seed(seed, i))``
          (SeedSequence([seed, i])) and unset lengths from ``torch.Generator().manual_seed(seed)``, so a motion does
          not depend on the batch it is generated in.
        - ``generator=torch.Generator``: one draw from it gives the seed (:func:`seed_from_generator`), then as
          ``seed``; so the same generator state gives the same motions, and the generator advances (a second call
          with it gives new motions, as in diffusers).
        - ``generator=[g_0, g_1, ...]``: one generator per motion (prompts × ``num_samples``, in order): motion ``i``
          draws its length (when neither ``lengths`` nor ``seconds`` is given) and then its noise (a diffusion
          sampler's per-step noise too) from ``g_i`` in the state passed, where ``seed`` would use its own seeded
          generator; ``[torch.Generator().manual_seed(sample_seed(s, i)) for i in range(n)]`` with the lengths given
          reproduces ``seed=s``.

        ``output_type``: "np"/"numpy" (default) for numpy arrays, "pt"/"torch" for CPU float32 tensors.
        """
        texts = _one_of("texts", texts, "prompt", prompt)
        num_samples = _one_of("num_samples", num_samples, "num_motions_per_prompt", num_motions_per_prompt)
        steps = _one_of("steps", steps, "num_inference_steps", num_inference_steps)
        guidance = _one_of("guidance", guidance, "guidance_scale", guidance_scale)
        _one_of("seed", seed, "generator", generator)
        if output_type not in OUTPUT_TYPES:
            raise ValueError(f"output_type {output_type!r}: use one of {', '.join(OUTPUT_TYPES)}")
        generators = None
        if isinstance(generator, torch.Generator):
            seed = seed_from_generator(generator)
        elif generator is not None:
            generators = list(generator)
            if not all(isinstance(g, torch.Generator) for g in generators):
                raise TypeError("generator must be a torch.Generator or a list of them, one per motion")
        texts = [] if texts is None else [texts] if isinstance(texts, str) else list(texts)
        request = SampleRequest(
            checkpoint=str(self.trained.checkpoint), out_dir="", texts=texts, actions=list(actions),
            seconds=_as_list(seconds), lengths=_as_list(lengths), num_samples=1 if num_samples is None else num_samples,
            seed=0 if seed is None else seed, steps=steps, solver=solver, guidance=guidance, batch_size=batch_size,
            text_weights=self.text_weights, weights=self.weights, baseline_defaults=baseline_defaults,
            baseline_clip_denoised=clip_denoised, precision=precision, compile=self.compile)
        trained = self.trained
        integrator = integration.resolve_integrator(request, trained)
        conditions = sampling.encode_prompts(request, trained)
        specs = sampling.plan_samples(request, trained, None)
        noise_generators = None
        if generators is not None:
            if len(generators) != len(specs):
                raise ValueError(f"{len(generators)} generators for {len(specs)} motions: give one per motion "
                                 "(prompts × num_motions_per_prompt) or a single torch.Generator")
            if not (request.lengths or request.seconds):
                limit = sampling.max_sample_length(trained)
                specs = [dataclasses.replace(spec, length=min(int(sample_lengths(trained.train_lengths, 1, g)[0]),
                                                              limit))
                         for spec, g in zip(specs, generators)]
            noise_generators = {spec.index: g for spec, g in zip(specs, generators)}
        records: dict[int, dict[str, Any]] = {}
        features: dict[int, np.ndarray] = {}
        for chunk, batch, batch_features, _ in sampling.generated_batches(request, trained, integrator, specs,
                                                                          conditions, None, {}, noise_generators):
            for row, spec in enumerate(chunk):
                record = sampling.sample_record(request, trained, integrator, spec, chunk, batch.nfe)
                if noise_generators is not None:  # drawn from the caller's generator: no seed says which noise
                    record["noise_seed"] = None
                records[spec.index] = record
                features[spec.index] = np.ascontiguousarray(batch_features[row, :spec.length], dtype=np.float32)
        order = sorted(records)
        motion_features = [features[i] for i in order]
        motion_joints = [features_to_joints(f, trained.skeleton).astype(np.float32) for f in motion_features]
        if OUTPUT_TYPES[output_type] == "torch":
            motion_features = [torch.from_numpy(f) for f in motion_features]
            motion_joints = [torch.from_numpy(j) for j in motion_joints]
        return GeneratedMotions(
            texts=[records[i]["text"] for i in order], actions=[records[i]["action"] for i in order],
            lengths=[records[i]["length"] for i in order], features=motion_features, joints=motion_joints,
            fps=trained.fps, records=[records[i] for i in order], _request=request, _trained=trained,
            _integrator=integrator)


def seed_from_generator(generator: torch.Generator) -> int:
    """The seed a single ``generator=`` stands for: one 63-bit draw from it (advancing it)."""
    return int(torch.randint(0, 2**63 - 1, (1,), generator=generator, device=generator.device)[0])


def _one_of(ours: str, our_value: Any, theirs: str, their_value: Any) -> Any:
    """The value of an argument that has two names (ours and diffusers'); None when neither was given."""
    if our_value is not None and their_value is not None:
        raise TypeError(f"MotionPipeline() got both {ours}= and {theirs}=, two names for one argument: pass one")
    return their_value if our_value is None else our_value


def _dtype_named(name: str) -> torch.dtype | None:
    dtype = getattr(torch, name.removeprefix("torch."), None)
    return dtype if isinstance(dtype, torch.dtype) else None


def _as_dtype(dtype: torch.dtype | str | None) -> torch.dtype | None:
    """A torch.dtype from itself or its name ("bfloat16", "torch.float16"); one :meth:`TrainedModel.to` takes."""
    if dtype is None or isinstance(dtype, torch.dtype):
        resolved = dtype
    elif isinstance(dtype, str):
        resolved = _dtype_named(dtype)
    else:
        resolved = None
    if resolved is None and dtype is not None or resolved is not None and resolved not in SAMPLING_DTYPES:
        raise ValueError(f"torch_dtype {dtype!r}: use one of {', '.join(str(d) for d in SAMPLING_DTYPES)} (the model "
                         "computes its time and position tables in float32, so float64 would not be float64)")
    return resolved


def _as_list(value: float | int | Sequence | None) -> list:
    if value is None:
        return []
    return list(value) if isinstance(value, (list, tuple)) else [value]
