"""Turn a published MFM or MDM checkpoint into an ordinary checkpoint folder of ours.

The folder (``<out>/checkpoints/step-<N>``, N from the reference file name, e.g. ``model000475000.pt``) is written by
:func:`pipeline.checkpoint.save_checkpoint` like a training save — safetensors weights, the resolved config, a
COMPLETE marker — so sampling, editing and the evaluator load it unchanged. Its dataset identity carries what they
need, which a reference checkpoint does not hold itself:

* the feature spec of the dataset (HumanML3D 263-D on the 22-joint skeleton at 20 fps, KIT 251-D on 21 joints at
  12.5 fps), checked against the network's input width;
* the normalisation the reference model was trained with: the dataset's ``Mean.npy``/``Std.npy`` (``--mean``/``--std``,
  by default the reference repository's layout ``<reference_root>/dataset/HumanML3D/{Mean,Std}.npy``);
* the text encoder entry: CLIP ViT-B/32's unnormalised ``encode_text`` output with MDM's 22-token context (20 caption
  tokens), OpenAI's weights by hash unless other weights are named;
* the objective: flow matching for MFM (a velocity field); for MDM the ``'mdm'`` diffusion preset (x0 prediction,
  1,000 cosine steps, fixed small variance);
* where it came from: the source file, its sha256, the keys dropped (CLIP), and which forward-pass behaviour was
  chosen (the reference's by default: :data:`mfm.reference_weights.REFERENCE_BEHAVIOUR`).

Action-to-motion checkpoints (HumanAct12/UESTC, 25×6 SMPL rot6d features) map onto our network (shape inference
covers them) but have no feature spec here — decoding them needs the SMPL body model — so they are refused with
that reason.
"""

from __future__ import annotations

import dataclasses
import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mfm.integrity import sha256_file
from mfm.model import ModelConfig, MotionFlowTransformer
from mfm.reference_weights import (
    REFERENCE_BEHAVIOUR,
    REFERENCE_KINDS,
    convert_state_dict,
    infer_model_config,
    load_reference_state_dict,
    positional_table_gap,
)
from mfm.skeleton import get_skeleton
from mfm.text import MDM_CONTEXT_LENGTH, OPENAI_VIT_B_32_SHA256
from pipeline import checkpoint as ckpt
from pipeline.config import TrainConfig, to_dict
from pipeline.training.run_folder import check_run_folder, write_run_marker
from preprocess.shards import feature_spec

logger = logging.getLogger(__name__)

REFERENCE_WINDOW = 196
"""MDM/MFM train and sample HumanML3D and KIT motions of at most 196 frames."""


@dataclass(frozen=True)
class ReferenceDataset:
    skeleton: str
    folder: str  # the dataset's folder in the reference repositories (dataset/<folder>/Mean.npy)


REFERENCE_DATASETS = {
    "humanml3d": ReferenceDataset(skeleton="humanml3d", folder="HumanML3D"),
    "kit": ReferenceDataset(skeleton="kit", folder="KIT-ML"),
}


class ConversionError(ValueError):
    """The conversion cannot be done as asked; the message names the file or setting and the reason."""


@dataclass(frozen=True)
class ConversionRequest:
    kind: str
    """'mfm' or 'mdm' (mfm.reference_weights.REFERENCE_KINDS)."""
    source: Path
    """The reference checkpoint (.pt state dict, or .safetensors)."""
    dataset: str
    """'humanml3d' or 'kit'."""
    out: Path
    """The run folder to create (must be new or empty)."""
    mean: Path | None = None
    std: Path | None = None
    reference_root: Path = Path(".")
    """Where --mean/--std default to: <reference_root>/dataset/<HumanML3D|KIT-ML>/{Mean,Std}.npy."""
    clip_weights: str | None = None
    """A CLIP ViT-B/32 weights file the prompts will be encoded with (its sha256 is recorded); None = OpenAI's."""
    behaviour: str = "reference"
    """'reference' (reproduce the reference forward pass) or 'ours' (continuous time, masked padding)."""
    num_heads: int | None = None
    """None: the file's metadata, else MDM/MFM's 4."""


def convert_checkpoint(request: ConversionRequest) -> Path:
    """Convert ``request.source`` and write the checkpoint folder; returns its path."""
    if request.kind not in REFERENCE_KINDS:
        raise ConversionError(f"unknown reference kind {request.kind!r}; known: {', '.join(REFERENCE_KINDS)}")
    if request.dataset not in REFERENCE_DATASETS:
        raise ConversionError(f"unknown dataset {request.dataset!r}; known: {', '.join(REFERENCE_DATASETS)}")
    check_run_folder(request.out)
    if request.out.is_dir() and any(request.out.iterdir()):
        raise ConversionError(f"--out {request.out} already holds files (an earlier conversion or run?): converted "
                              "checkpoints go into a new or empty folder")
    state, metadata, dropped = load_reference_state_dict(request.source)
    num_heads = request.num_heads or int(metadata.get("num_heads", 4))
    config = infer_model_config(state, behaviour=request.behaviour, kind=request.kind, num_heads=num_heads,
                                activation=metadata.get("activation", "gelu"), source=str(request.source))
    if config.is_action_model:
        raise ConversionError(
            f"{request.source}: an action-to-motion model ({config.num_actions} classes, {config.feature_dim}-D "
            "features, MDM's SMPL rot6d layout for HumanAct12/UESTC): its network maps onto ours, but this pipeline "
            "has no feature spec for SMPL rot6d motions (decoding them needs the SMPL body model), so it cannot "
            "sample or evaluate it")
    spec = feature_spec(get_skeleton(REFERENCE_DATASETS[request.dataset].skeleton), compat=True)
    if spec["dim"] != config.feature_dim:
        raise ConversionError(f"{request.source}: the network reads {config.feature_dim}-D features, but "
                              f"--dataset {request.dataset} has {spec['dim']}-D ones: wrong --dataset?")
    weights = convert_state_dict(state, config)
    model = MotionFlowTransformer(config)
    model.load_state_dict(weights)  # strict: proves every tensor found its place

    source_sha = sha256_file(request.source)
    identity = {
        "dataset_id": f"{request.dataset}:{request.kind}-reference:{source_sha[:16]}",
        "location": str(request.source),
        "feature_spec": spec,
        "text_encoder": reference_text_encoder(request.clip_weights, config.cond_dim, request.source),
        "action_classes": [],
        "normalization": reference_normalization(request, spec["dim"]),
        "train_lengths": [],
        "converted_from": {
            "kind": request.kind,
            "file": str(request.source),
            "sha256": source_sha,
            "dropped_keys": len(dropped),
            "behaviour": request.behaviour,
            "model_settings": {k: getattr(config, k) for k in REFERENCE_BEHAVIOUR[request.kind]},
            "positional_table_max_gap_first_1000_rows": positional_table_gap(state, 1000),
            "num_heads": num_heads,
            "num_heads_from": "file metadata" if request.num_heads is None and "num_heads" in metadata
            else ("--num-heads" if request.num_heads else "MDM/MFM's fixed 4"),
        },
    }
    step = reference_step(request.source)
    train_config = TrainConfig(model=config)
    config_dict = to_dict(train_config)
    config_dict["data"].update(manifest=str(request.source), window=REFERENCE_WINDOW)
    config_dict["train"].update(out_dir=str(request.out), objective="flow" if request.kind == "mfm" else "diffusion",
                                diffusion="mdm")
    write_run_marker(request.out, written_by="pipeline/training/convert.py")  # a run folder of ours, like a training's
    folder = ckpt.save_checkpoint(
        ckpt.checkpoints_dir(request.out), step,
        model_state=model.state_dict(), ema_state=None, optimizer_state={}, scheduler_state=None,
        rng_states=[{}], data_states=[None], config=config_dict, manifest=identity,
        extra={"samples_seen": 0, "skipped_steps": 0, "model_config": dataclasses.asdict(config),
               "converted_from": identity["converted_from"]},
    )
    ckpt.record_saved(ckpt.checkpoints_dir(request.out), folder)
    logger.info("converted %s (%s, %s) into %s: %s", request.source, request.kind, request.dataset, folder,
                describe(config))
    return folder


def describe(config: ModelConfig) -> str:
    cond = f"text {config.cond_dim}-D" if not config.is_action_model else f"{config.num_actions} actions"
    return (f"{config.num_layers} layers, width {config.latent_dim}, FF {config.ff_dim}, {config.num_heads} heads, "
            f"{config.feature_dim}-D features, {cond}; time_grid={config.time_grid}, "
            f"attend_padding={config.attend_padding}, positional_table={config.positional_table}")


def reference_step(source: Path) -> int:
    """The training step in a reference file name (MDM/MFM save ``model<9 digits>.pt``), else 0."""
    match = re.search(r"(\d+)(?!.*\d)", source.stem)
    return int(match.group(1)) if match else 0


def reference_text_encoder(clip_weights: str | None, cond_dim: int, source: Path) -> dict[str, Any]:
    """The text encoder entry of a converted text model: CLIP ViT-B/32, pooled ``encode_text`` unnormalised, MDM's
    22-token context, OpenAI's weights (by hash) unless ``clip_weights`` names a file."""
    if cond_dim != 512:
        raise ConversionError(f"{source}: the text projection reads {cond_dim}-D embeddings; MDM/MFM's CLIP "
                              "ViT-B/32 gives 512 (a T5 variant of MFM is not supported)")
    if clip_weights is None:
        sha = OPENAI_VIT_B_32_SHA256
    else:
        path = Path(clip_weights).expanduser()
        if not path.is_file():
            raise ConversionError(f"--clip-weights {clip_weights}: no such file")
        sha = sha256_file(path)
    return {"id": "clip-vit-b-32", "dim": 512, "weights_sha256": sha,
            "options": {"context_length": MDM_CONTEXT_LENGTH, "quick_gelu": True},
            "token_features": False, "max_tokens": 0}


def reference_normalization(request: ConversionRequest, dim: int) -> dict[str, Any]:
    """Mean/Std the reference model was trained with, read from the dataset's files and checked."""
    folder = request.reference_root / "dataset" / REFERENCE_DATASETS[request.dataset].folder
    files = {"mean": request.mean or folder / "Mean.npy", "std": request.std or folder / "Std.npy"}
    values = {}
    for name, path in files.items():
        if not Path(path).is_file():
            raise ConversionError(f"{path}: no such file; the model's normalisation ({name}) is needed: pass "
                                  f"--{name} or --reference-root (the folder holding dataset/{folder.name}/)")
        try:
            array = np.load(path, allow_pickle=False).astype(np.float64).reshape(-1)
        except (ValueError, OSError) as err:
            raise ConversionError(f"{path}: cannot be read as a .npy array ({err})") from err
        if array.shape != (dim,) or not np.isfinite(array).all():
            raise ConversionError(f"{path}: expected {dim} finite values for the {request.dataset} features, got "
                                  f"shape {array.shape}")
        values[name] = array
    if (values["std"] <= 0).any():
        raise ConversionError(f"{files['std']}: standard deviations must be positive")
    return {"mean": values["mean"].tolist(), "std": values["std"].tolist(), "split": "train", "num_frames": None,
            "rule": f"the reference model's own statistics ({request.dataset} Mean.npy/Std.npy)",
            "files": {name: {"path": str(path), "sha256": sha256_file(path)} for name, path in files.items()}}
