"""A generator people would accept, at test scale: a small model trained on three real motion-capture clips (the
embedded DeepMimic walk, cartwheel and jump, with their MiniLM captions) for a few hundred steps reproduces each
captioned clip when sampled with the default sampler (Euler, 10 steps, guidance 2.5), with rigid bones, feet on the
floor and ground-truth-like smoothness.

The same budget with the parametrisation the embedded default used to ship (a velocity network, unscaled unit-norm
text embeddings) is trained beside it and must fail the same thresholds: that is what shows the margins separate a
working generator from a broken one (issue 11's figures for it: 1 m bone variation, 0.26 m under the floor, 38×
the ground truth's jerk). The two trainings run side by side, one per core (~20 s on two cores, ~40 s on one).
"""

from __future__ import annotations

import json
import math
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
from conftest import embedded_dataset_once

from mfm.features import features_to_joints
from mfm.flow import flow_matching_loss
from mfm.metrics import plausibility
from mfm.model import ModelConfig, MotionFlowTransformer
from mfm.skeleton import get_skeleton
from mfm.solvers import sample

pytestmark = [pytest.mark.slow]

CLIPS = ("walk", "cartwheel", "jump")
STEPS = 500
DRAWS_PER_CLIP = 4  # (t, noise) draws of every clip in each batch

# What the working recipe must reach. Measured at this budget (one core): bone range 0.10-0.16 m, penetration
# 0.01-0.06 m, jerk 5-8x, error to the own clip 0.14-0.19 m (to the others >= 0.62 m); the old parametrisation:
# ~1.2 m, ~0.5 m, 40-70x, contact foot speed 6-8 m/s.
MAX_BONE_RANGE_M = 0.25
MAX_PENETRATION_M = 0.10
MAX_JERK_RATIO = 12.0
MAX_OWN_CLIP_ERROR_M = 0.25
MAX_CONTACT_FOOT_SPEED = 2.0  # m/s; the clips' own: 0.12-0.49 (this budget still slides: ~0.8-1.3)

RECIPES = {
    "working": {"prediction": "data", "cond_scaling": "rms"},
    "old": {"prediction": "velocity", "cond_scaling": "none"},  # what the embedded default shipped with (issue 11)
}
# The initial weights come from the global torch generator: seeding and drawing them is one step per training.
_INIT_LOCK = threading.Lock()


@pytest.fixture(scope="module")
def three_clips(tmp_path_factory):
    data = embedded_dataset_once(tmp_path_factory)
    manifest = json.loads((data / "manifest.json").read_text())
    rows = [row for path in sorted((data / "train").glob("part-*.parquet")) for row in pq.read_table(path).to_pylist()]
    rows = sorted((row for row in rows if row["id"] in CLIPS), key=lambda row: CLIPS.index(row["id"]))
    assert [row["id"] for row in rows] == list(CLIPS)
    mean, std = (torch.tensor(manifest["normalization"][key]) for key in ("mean", "std"))
    features = [torch.tensor(np.asarray(row["features"], np.float32)) for row in rows]
    lengths = torch.tensor([len(f) for f in features])
    x1 = torch.zeros(len(rows), int(lengths.max()), features[0].shape[1])
    for i, f in enumerate(features):
        x1[i, : len(f)] = (f - mean) / std
    cond = torch.tensor(np.stack([np.asarray(row["text_emb"][0], np.float32) for row in rows]))  # first captions
    return x1, lengths, cond, mean, std


def train_and_sample(three_clips, *, prediction: str, cond_scaling: str) -> list[np.ndarray]:
    """Train a 2-layer, 128-wide model on the three clips (AdamW 1e-3, cosine decay), then sample one motion per
    caption at its clip's length; returns their joints."""
    x1, lengths, cond, mean, std = three_clips
    config = ModelConfig(feature_dim=x1.shape[-1], latent_dim=128, ff_dim=256, num_layers=2, num_heads=4,
                         cond_dim=cond.shape[-1], dropout=0.0, norm_first=True, max_len=256,
                         prediction=prediction, cond_scaling=cond_scaling)
    with _INIT_LOCK:
        torch.manual_seed(0)
        model = MotionFlowTransformer(config)
    # From here on every draw comes from an explicit generator (no dropout), so two trainings can run at once.
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=0.0)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: 0.5 * (1 + math.cos(math.pi * s / STEPS)))
    generator = torch.Generator().manual_seed(0)
    batch = (x1.repeat(DRAWS_PER_CLIP, 1, 1), cond.repeat(DRAWS_PER_CLIP, 1), lengths.repeat(DRAWS_PER_CLIP))
    model.train()
    for _ in range(STEPS):
        loss, _ = flow_matching_loss(model, *batch, generator=generator)
        optimizer.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        optimizer.step()
        schedule.step()
    model.eval()
    with torch.no_grad():
        generated = sample(model, cond, lengths, num_frames=x1.shape[1], seed=0).x1
    skeleton = get_skeleton("humanml3d")
    return [features_to_joints(generated[i, :n] * std + mean, skeleton).numpy() for i, n in enumerate(lengths.tolist())]


def judge(joints: list[np.ndarray], three_clips) -> dict[str, np.ndarray]:
    """Plausibility figures of each sample against its own clip's, and its mean joint error to every clip."""
    x1, lengths, _, mean, std = three_clips
    skeleton = get_skeleton("humanml3d")
    truth = [features_to_joints(x1[i, :n] * std + mean, skeleton).numpy() for i, n in enumerate(lengths.tolist())]
    figures = [plausibility(j, skeleton, gt_joints=g) for j, g in zip(joints, truth)]
    truth_figures = [plausibility(g, skeleton) for g in truth]
    errors = np.array([[np.linalg.norm(j[: min(len(j), len(g))] - g[: min(len(j), len(g))], axis=-1).mean()
                        for g in truth] for j in joints])  # same start, no alignment: the clips start at the origin
    return {
        "bone_range": np.array([f.bone_length_range[0] for f in figures]),
        "penetration": np.array([f.floor_penetration[0] for f in figures]),
        "jerk_ratio": np.array([f.jerk_ratio[0] for f in figures]),
        "contact_foot_speed": np.array([f.contact_foot_speed[0] for f in figures]),
        "truth_contact_foot_speed": np.array([f.contact_foot_speed[0] for f in truth_figures]),
        "errors": errors,
    }


@pytest.fixture(scope="module")
def figures_by_recipe(three_clips) -> dict[str, dict[str, np.ndarray]]:
    """Both recipes trained at once, each in a thread of its own: one intra-op thread each (tests/conftest.py),
    and the matrix work, nearly all of a step, runs outside the GIL, so the two use both cores. Each training's
    numbers are those of a training alone."""
    with ThreadPoolExecutor(max_workers=len(RECIPES)) as pool:
        joints = {name: pool.submit(train_and_sample, three_clips, **recipe) for name, recipe in RECIPES.items()}
        return {name: judge(future.result(), three_clips) for name, future in joints.items()}


def test_small_model_reproduces_its_captioned_clips(figures_by_recipe):
    figures = figures_by_recipe["working"]
    report = {k: np.round(v, 3).tolist() for k, v in figures.items()}
    errors = figures["errors"]
    # Each sample is its own caption's clip: nearest to it, by a wide margin, and close in absolute terms.
    assert (errors.argmin(axis=1) == np.arange(len(CLIPS))).all(), report
    assert np.diag(errors).max() < MAX_OWN_CLIP_ERROR_M, report
    assert (np.diag(errors) * 2 < np.where(np.eye(len(CLIPS), dtype=bool), np.inf, errors).min(axis=1)).all(), report
    # ... and physically plausible.
    assert figures["bone_range"].max() < MAX_BONE_RANGE_M, report
    assert figures["penetration"].max() < MAX_PENETRATION_M, report
    assert figures["jerk_ratio"].max() < MAX_JERK_RATIO, report
    assert np.nanmax(figures["contact_foot_speed"]) < MAX_CONTACT_FOOT_SPEED, report


def test_the_thresholds_reject_the_old_parametrisation(figures_by_recipe):
    """The recipe the embedded default shipped with (velocity network, unscaled MiniLM captions), same budget:
    the stretching, sinking, shaking motion of issue 11. It must fail every physical threshold above."""
    figures = figures_by_recipe["old"]
    report = {k: np.round(v, 3).tolist() for k, v in figures.items()}
    assert np.median(figures["bone_range"]) > 2 * MAX_BONE_RANGE_M, report
    assert np.median(figures["penetration"]) > MAX_PENETRATION_M, report
    assert np.median(figures["jerk_ratio"]) > 2 * MAX_JERK_RATIO, report
    assert np.nanmedian(figures["contact_foot_speed"]) > 2 * MAX_CONTACT_FOOT_SPEED, report
