"""How far the rigid decode (``mfm.features.features_to_joints_rigid``) moves joints from the ric positions it
fits, on the real clip 012314 (../shared/reference-data, or $MFM_SHARED_DIR): one JSON line per noise level.

    python benchmarks/bench_rigid.py [--sigmas 0,0.05,0.1,0.2] [--seed 0]

Noise: features + sigma * Std * N(0, 1), Std the dataset's normalisation (so sigma is in the units the model
works in), one draw per sigma from ``SeedSequence([seed, k])``. Per level: the distance between rigid and ric
joints (mean / max over joints and frames, mm), how much the ric bones' lengths vary over the clip (largest
max - min of one bone, mm) and the rigid bones' largest deviation from the skeleton's lengths; for comparison,
the same distance for two other fixed-length decodes: keeping every ric bone's direction (errors add up along
each chain) and ``features_to_joints_fk`` (forward kinematics of the 6D rotation block).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from mfm.features import features_to_joints, features_to_joints_fk, features_to_joints_rigid
from mfm.skeleton import HUMANML3D

REPO_ROOT = Path(__file__).resolve().parents[1]
REFERENCE = Path(os.environ.get("MFM_SHARED_DIR", REPO_ROOT.parent / "shared")) / "reference-data" / "humanml3d"


def bone_lengths(joints: np.ndarray) -> np.ndarray:
    """(T, J, 3) -> (T, J-1) lengths of the bones ending at joints 1..J-1."""
    parents = HUMANML3D.parents[1:]
    return np.linalg.norm(joints[:, 1:] - joints[:, parents], axis=-1)


def keep_observed_directions(joints: np.ndarray) -> np.ndarray:
    """The baseline: every bone keeps its observed direction at the skeleton's length, summed from the root."""
    bones = joints[:, 1:] - joints[:, HUMANML3D.parents[1:]]
    bones *= HUMANML3D.bone_lengths[1:, None] / np.linalg.norm(bones, axis=-1, keepdims=True)
    out = joints.copy()
    for j in range(1, HUMANML3D.num_joints):  # parents come before their children in HumanML3D's numbering
        out[:, j] = out[:, HUMANML3D.parents[j]] + bones[:, j - 1]
    return out


def distance_mm(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    d = np.linalg.norm(a - b, axis=-1) * 1000.0
    return {"mean_mm": round(float(d.mean()), 4), "max_mm": round(float(d.max()), 4)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sigmas", default="0,0.05,0.1,0.2")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if not REFERENCE.is_dir():
        sys.exit(f"reference data not found at {REFERENCE} (set MFM_SHARED_DIR)")
    features = np.load(REFERENCE / "new_joint_vecs_012314.npy").astype(np.float64)
    std = np.load(REFERENCE / "Std.npy").astype(np.float64)
    for k, sigma in enumerate(float(s) for s in args.sigmas.split(",")):
        noise = np.random.default_rng(np.random.SeedSequence([args.seed, k])).standard_normal(features.shape)
        noisy = features + sigma * std * noise
        ric = features_to_joints(noisy, HUMANML3D)
        rigid = features_to_joints_rigid(noisy, HUMANML3D)
        ric_lengths = bone_lengths(ric)
        print(json.dumps({
            "clip": "012314", "frames": len(features), "sigma": sigma,
            "rigid_vs_ric": distance_mm(rigid, ric),
            "ric_bone_length_range_mm": round(float((ric_lengths.max(0) - ric_lengths.min(0)).max() * 1000.0), 2),
            "rigid_bone_length_error_m": float(np.abs(bone_lengths(rigid) - HUMANML3D.bone_lengths[1:]).max()),
            "observed_directions_vs_ric": distance_mm(keep_observed_directions(ric), ric),
            "rot6d_fk_vs_ric": distance_mm(features_to_joints_fk(noisy, HUMANML3D), ric),
        }))


if __name__ == "__main__":
    main()
