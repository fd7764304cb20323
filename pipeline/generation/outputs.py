"""What sampling, editing and composition write, shared by pipeline/generation/sampling.py and pipeline/generation/composing.py: the
output folder's rules, each sample's files (:class:`SampleWriter`), results.json's common header, MDM's
results.npy layout and which index.html is ours (pipeline/generation/browse.py writes it).

Per sample: sample_NNN/{features.npy, joints.npy, motion.mp4|gif, motion.bvh, keep_mask.npy (edits),
trajectory.png (on request)}, each described in results.json (paths relative to the output folder), with the
sample's plausibility figures; index.html is written last.
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mfm import metrics
from mfm.export import plot_x1_trajectory, render_motion, write_bvh, write_mdm_results
from mfm.export.bvh import JOINT_CHANNELS, ROOT_CHANNELS
from mfm.export.render import Captions
from mfm.features import features_to_joints, rigid_joints
from mfm.layout import FeatureLayout
from mfm.skeleton import Skeleton
from pipeline.generation.inference import TrainedModel
from pipeline.generation.integration import Integrator
from pipeline.generation.request import JOINT_DECODES, SampleRequest, SamplingError

logger = logging.getLogger(__name__)

RESULTS_FILE = "results.json"

BROWSE_PAGE = "index.html"  # pipeline/generation/browse.py's page of the outputs, written last
# What marks a page as ours (pipeline/generation/browse.py writes it into every page; :func:`is_our_page` looks for
# it): here, with the output folder's other rules, so the page writer sits above this module and not beside it.
PAGE_GENERATOR = "motion-flow-matching pipeline/generation/browse.py"  # in every page's <meta name="generator">
_EARLIER_PAGE_FOOTER = "written by pipeline/generation/browse.py"  # what pages from before the tag say (lower case)

RESULTS_VERSION = 1

SAMPLE_DIR = "sample_{:03d}"

TIME_CONVENTIONS = {"flow": "flow time t, 1 = data", "diffusion": "diffusion t_model = step / train steps, 0 = data"}

_SAMPLE_DIR_PATTERN = re.compile(r"^sample_\d{3,}$")

MDM_RESULTS_FILES = ("results.npy", "results.txt", "results_len.txt")

def frame_ranges(flags: np.ndarray) -> list[list[int]]:
    """Half-open [start, stop) runs of True in a 1-D bool array."""
    padded = np.concatenate(([False], flags.astype(bool), [False]))
    edges = np.flatnonzero(padded[1:] != padded[:-1])
    return [[int(a), int(b)] for a, b in zip(edges[::2], edges[1::2])]

def edited_joints(keep: np.ndarray, layout: FeatureLayout) -> np.ndarray:
    """(T, J) bool: a joint is edited (generated) on a frame where any of its feature dims is not kept."""
    return np.stack([~keep[:, layout.joint_dims(j)].all(axis=1) for j in range(layout.num_joints)], axis=1)

class SampleWriter:
    """Writes one sample's files and describes each of them for results.json (paths relative to out_dir)."""

    def __init__(self, request: SampleRequest, trained: TrainedModel, out_dir: Path) -> None:
        self.request = request
        self.trained = trained
        self.out_dir = out_dir
        self.skeleton = trained.skeleton
        self.layout = FeatureLayout(self.skeleton)

    def _entry(self, path: Path, kind: str, **info: Any) -> dict[str, Any]:
        return {"path": path.relative_to(self.out_dir).as_posix(), "kind": kind, **info}

    def write(self, index: int, features: np.ndarray, title: Captions, keep: np.ndarray | None = None,
              x1_hat: np.ndarray | None = None, x1_hat_times: np.ndarray | None = None) -> dict[str, Any]:
        """Sample ``index``'s files from its un-normalised features (L, D); ``title``: a caption, or
        ``[(start_frame, caption), ...]`` for captions that change over the motion (composition). Returns the
        sample's results.json fields ``files`` and ``plausibility`` (:func:`plausibility_record`)."""
        folder = self.out_dir / SAMPLE_DIR.format(index)
        folder.mkdir(parents=True, exist_ok=True)
        ric = features_to_joints(features, self.skeleton)
        rigid = rigid_joints(ric, self.skeleton)  # fixed bone lengths: the only joints a rig (the BVH) can play
        joints = (rigid if self.request.decode == "rigid" else ric).astype(np.float32)
        files = []
        np.save(folder / "features.npy", features)
        files.append(self._entry(folder / "features.npy", "features", shape=list(features.shape),
                                 normalized=False, dtype="float32"))
        np.save(folder / "joints.npy", joints)
        files.append(self._entry(folder / "joints.npy", "joints", shape=list(joints.shape), unit=self.skeleton.unit,
                                 recovered_with=JOINT_DECODES[self.request.decode], dtype="float32"))
        if keep is not None:
            np.save(folder / "keep_mask.npy", keep)
            files.append(self._entry(folder / "keep_mask.npy", "keep_mask", shape=list(keep.shape),
                                     meaning="True = kept from the source motion"))
        if self.request.video:
            edited = None if keep is None else edited_joints(keep, self.layout)
            video = render_motion(folder / "motion", joints, self.skeleton, self.trained.fps, title=title,
                                  edited=edited, fmt=self.request.video_format)
            captions = {} if isinstance(title, str) or title is None else {"captions": [list(c) for c in title]}
            files.append(self._entry(video, "video", format=video.suffix.lstrip("."), fps=self.trained.fps,
                                     colors="kept blue, edited red" if keep is not None else "one colour per chain",
                                     **captions))
        if self.request.bvh:
            bvh = write_bvh(folder / "motion.bvh", rigid, self.skeleton, self.trained.fps)
            files.append(self._entry(bvh, "bvh", skeleton=self.skeleton.name, unit="m", up="Y",
                                     recovered_with=JOINT_DECODES["rigid"],
                                     root_channels=list(ROOT_CHANNELS), joint_channels=list(JOINT_CHANNELS),
                                     rotation_order="R = Ry @ Rx @ Rz (Blender Euler ZXY)", fps=self.trained.fps))
        if x1_hat is not None:
            plot_title = title if isinstance(title, str) or title is None else " / ".join(text for _, text in title)
            png = plot_x1_trajectory(folder / "trajectory.png", x1_hat, x1_hat_times, self.skeleton,
                                     mean=self.trained.mean.cpu(), std=self.trained.std.cpu(), title=plot_title)
            # Flow: t of each x̂1 estimate (1 = data); diffusion: the denoiser's t_model (0 = data).
            files.append(self._entry(png, "trajectory_plot", times=[round(float(t), 6) for t in x1_hat_times],
                                     time_convention=TIME_CONVENTIONS[self.trained.objective]))
        return {"files": files, "plausibility": plausibility_record(joints, self.skeleton)}

def plausibility_record(joints: np.ndarray, skeleton: Skeleton) -> dict[str, float | None]:
    """A sample's plausibility figures (mfm.metrics.plausibility of the (L, J, 3) joints written to joints.npy;
    thresholds in results.json's ``plausibility_thresholds``), rounded; None where undefined (the contact foot
    speed of a motion whose feet never touch the floor). No ground truth here, so no jerk ratio."""
    figures = metrics.plausibility(joints, skeleton).clip(0)
    return {name: None if value is None else round(value, 6) for name, value in figures.items()}

def write_mdm_layout(out_dir: Path, samples: Sequence[Mapping[str, Any]], num_samples: int) -> dict[str, Any]:
    """MDM's ``results.npy`` (and its text files) of the written joints, so MDM's rendering and SMPL-fitting
    scripts read our samples: our sample i is prompt i // num_samples's repetition i % num_samples."""
    joints = [np.load(out_dir / next(f["path"] for f in s["files"] if f["kind"] == "joints")) for s in samples]
    texts = [s["text"] or s["action"] or "" for s in samples]
    path = write_mdm_results(out_dir / MDM_RESULTS_FILES[0], joints, texts, [s["length"] for s in samples],
                             num_repetitions=num_samples, order="sample_major")
    return {"path": path.name, "layout": "MDM sample/generate.py: motion (R·S, J, 3, F), index rep·S + sample, "
            "padded with the last frame", "num_samples": len(samples) // num_samples, "num_repetitions": num_samples}

def is_our_results_file(path: Path) -> bool:
    """Whether ``path`` is a results.json this module wrote (a JSON object with our ``version``, the checkpoint, the
    mode and the list of samples): what makes a folder an earlier sampling output of ours."""
    try:
        results = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return False
    return (isinstance(results, dict) and results.get("version") == RESULTS_VERSION and "checkpoint" in results
            and "mode" in results and isinstance(results.get("samples"), list))


def is_our_page(path: Path) -> bool:
    """Whether the file at ``path`` is a page pipeline/generation/browse.py wrote: it carries :data:`PAGE_GENERATOR`
    in its ``<meta name="generator">`` or, for pages written before that tag existed, the footer line naming that
    module (``written by pipeline/generation/browse.py``)."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return False
    return f'<meta name="generator" content="{PAGE_GENERATOR}">' in text or _EARLIER_PAGE_FOOTER in text.lower()


def prepare_out_dir(out_dir: Path, overwrite: bool) -> None:
    """Create ``out_dir``; refuse one with files unless ``overwrite``, which replaces an earlier sampling output of
    ours only (its results.json is ours: :func:`is_our_results_file`): it removes that run's results.json, MDM files,
    sample_NNN folders and index.html, the page only when it is ours. Anything else there (another tool's
    index.html included) refuses the overwrite before anything is removed."""
    out_dir.mkdir(parents=True, exist_ok=True)
    existing = [p for p in out_dir.iterdir()]
    if not existing:
        return
    if not overwrite:
        raise SamplingError(f"{out_dir} is not empty: choose a new output folder or pass overwrite")
    if not is_our_results_file(out_dir / RESULTS_FILE):
        raise SamplingError(f"{out_dir} is not an earlier sampling output (no {RESULTS_FILE} written by this project): "
                            "overwrite replaces only those; choose a new output folder")
    ours = [p for p in existing if not p.is_symlink() and (
        p.name in (RESULTS_FILE, *MDM_RESULTS_FILES) or (p.name == BROWSE_PAGE and is_our_page(p))
        or (p.is_dir() and _SAMPLE_DIR_PATTERN.match(p.name)))]
    others = sorted(p.name for p in set(existing) - set(ours))
    if others:
        raise SamplingError(f"{out_dir} holds files that are not sampling outputs of ours ({others[:5]}): "
                            "not overwriting")
    for path in ours:
        shutil.rmtree(path) if path.is_dir() else path.unlink()

def write_json_atomically(path: Path, payload: Mapping[str, Any]) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(payload, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, path)

def results_header(request: SampleRequest, trained: TrainedModel, integrator: Integrator, mode: str,
                   conditioned: bool) -> dict[str, Any]:
    """The part of results.json every mode shares: the checkpoint, the data it knows and how it was integrated."""
    return {
        "version": RESULTS_VERSION,
        "checkpoint": str(trained.checkpoint),
        "step": trained.step,
        "weights": trained.weights,
        "dataset_id": trained.dataset_id,
        "skeleton": trained.skeleton.name,
        "fps": trained.fps,
        "mode": mode,
        "conditioning": "text" if request.texts or request.compose_file else "action" if request.actions else "none",
        **integrator.record(trained),
        "precision_setting": request.precision,
        # whether the model passes ran torch.compile-d (CUDA graphs on CUDA), and the setting (auto: on CUDA only)
        "compiled": trained.is_compiled,
        "compile_setting": request.compile,
        "guidance": request.guidance_for(trained) if conditioned else 0.0,
        "guided_features": request.guided_features_for(trained),
        "smoothing_sigma": request.smoothing_for(trained),
        "smoothing_keeps_bones": request.smoothing_keeps_bones_for(trained),
        # A diffusion baseline's authors' settings as run (FLAME's) and which the request overrode; null: ours.
        "baseline_defaults": request.baseline_record(trained),
        "seed": request.seed,
        "device": str(trained.device),
        "plausibility_thresholds": metrics.plausibility_settings(trained.skeleton),
    }
