"""What the flow-model diagnostics (probe_x1_error.py, sample_dispersion.py) share: a trained flow model and the
dataset clips of a split's first captions, normalised as the model sees them, with their conditions."""

from __future__ import annotations

import dataclasses

import torch

from pipeline.generation.contact_sheet import DatasetCaption, first_captions
from pipeline.data.stream import open_manifest
from pipeline.generation.inference import TrainedModel, load_trained_model


@dataclasses.dataclass(frozen=True)
class ProbeClips:
    trained: TrainedModel
    captions: list[DatasetCaption]
    x1: torch.Tensor  # (N, T, D) normalised clips, zero beyond each length
    lengths: torch.Tensor  # (N,) frames, each clip cut to the model's window
    mask: torch.Tensor  # (N, T, 1) 1.0 on each clip's frames
    cond: torch.Tensor  # the captions' conditions
    cond_inputs: dict[str, torch.Tensor]  # the model's other condition inputs (cross_attention: the token features)


def load_probe_clips(checkpoint: str, split: str, count: int | None = None) -> ProbeClips:
    """The flow model of ``checkpoint`` and the clips of the first caption of the first ``count`` motions of
    ``split`` (all if None). Exits with a message for a diffusion checkpoint: the diagnostics need a velocity."""
    trained = load_trained_model(checkpoint)
    if trained.objective != "flow":
        raise SystemExit(f"{checkpoint} is a {trained.objective} model: this probe needs a velocity field")
    captions = first_captions(open_manifest(trained.data["location"]), split)[:count]
    lengths = torch.tensor([min(len(c.features), trained.window) for c in captions])
    frames = int(lengths.max())
    x1 = torch.zeros(len(captions), frames, trained.model_config.feature_dim)
    for i, c in enumerate(captions):
        x1[i, : lengths[i]] = trained.normalize(torch.as_tensor(c.features[: lengths[i]], dtype=torch.float32))
    mask = (torch.arange(frames)[None] < lengths[:, None]).float()[..., None]
    cond, cond_inputs = trained.condition_inputs(texts=[c.text for c in captions])
    return ProbeClips(trained, captions, x1, lengths, mask, cond, cond_inputs)
