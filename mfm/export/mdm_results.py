"""MDM's ``results.npy``: generated joint positions in the file MDM's ``sample/generate.py`` saves, so that MDM's
own scripts run on our samples (``visualize/render_mesh.py`` fits SMPL to a sample with SMPLify and writes
meshes; it reads only ``results.npy`` beside the ``sampleXX_repYY.mp4`` path it is given, whose name it parses
and whose file it does not open).

The layout, as in GuyTevet/motion-diffusion-model ``sample/generate.py``::

    np.save("results.npy", {"motion": all_motions, "text": all_text, "lengths": all_lengths,
                            "num_samples": num_samples, "num_repetitions": num_repetitions})

* ``motion``: float32 ``(num_samples * num_repetitions, njoints, 3, max_frames)``: joint positions (HumanML3D's
  axes and units: metres, Y up; 22 joints for HumanML3D, 21 for KIT) with the frames LAST. MDM samples every
  motion at one length ``n_frames``; here a motion shorter than ``max_frames`` is padded by repeating its last
  frame (what MDM's own stick-figure videos show past a motion's length: a frozen pose).
* ``text``: a list of ``num_samples * num_repetitions`` strings, ``lengths``: int64 array of as many lengths (the
  real frames of each motion; render_mesh.py writes that many meshes).
* Order, repetition-major: entry ``rep * num_samples + sample`` is repetition ``rep`` of sample ``sample``
  (MDM appends one batch of all samples per repetition); ``text``/``lengths`` repeat once per repetition.
* ``num_samples``, ``num_repetitions``: Python ints.

``np.save`` pickles the dict (a 0-d object array), so reading needs ``allow_pickle=True``, as in MDM: read only
files you trust. MDM also writes ``results.txt`` (one text a line) and ``results_len.txt`` (one length a line);
:func:`write_mdm_results` writes them too unless asked not to.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ORDERS = ("repetition_major", "sample_major")
_KEYS = ("motion", "text", "lengths", "num_samples", "num_repetitions")


def _per_motion(values: Sequence, total: int, num_samples: int, num_repetitions: int, what: str) -> list:
    """``values`` for every motion in MDM's order: given once per sample (tiled per repetition) or per motion."""
    values = list(values)
    if len(values) == total:
        return values
    if len(values) == num_samples:
        return values * num_repetitions
    raise ValueError(f"{what}: expected {num_samples} values (one per sample) or {total} (one per motion), "
                     f"got {len(values)}")


def write_mdm_results(
    path: str | Path,
    joints_list: Sequence[np.ndarray],
    texts: Sequence[str],
    lengths: Sequence[int] | None = None,
    num_repetitions: int = 1,
    *,
    order: str = "repetition_major",
    max_frames: int | None = None,
    text_files: bool = True,
) -> Path:
    """Write ``joints_list`` as MDM's ``results.npy`` at ``path`` (a file name, or a folder to hold
    ``results.npy``) and return the file's path.

    ``joints_list``: ``num_samples * num_repetitions`` arrays (T_i, J, 3) (the same J for all), in ``order``:
    ``"repetition_major"`` (MDM's: index ``rep * num_samples + sample``) or ``"sample_major"`` (index
    ``sample * num_repetitions + rep``), reordered to MDM's on writing. ``texts`` and ``lengths``: one per sample
    (the same for every repetition) or one per motion in the same order as ``joints_list``; ``lengths`` None means
    every motion's own frame count; a length must be 1..T_i. ``max_frames``: the stored frame count (default: the
    longest motion); motions are padded to it with their last frame and may not have more than that many real
    frames. ``text_files``: also write MDM's ``results.txt`` and ``results_len.txt`` beside it.
    """
    if order not in ORDERS:
        raise ValueError(f"order must be one of {ORDERS}, got {order!r}")
    if isinstance(num_repetitions, bool) or int(num_repetitions) != num_repetitions or num_repetitions < 1:
        raise ValueError(f"num_repetitions must be a positive integer, got {num_repetitions!r}")
    num_repetitions = int(num_repetitions)
    motions = [np.asarray(j) for j in joints_list]
    total = len(motions)
    if total == 0 or total % num_repetitions:
        raise ValueError(f"{total} motions cannot be {num_repetitions} repetitions of the same samples")
    num_samples = total // num_repetitions
    for i, joints in enumerate(motions):
        if joints.ndim != 3 or joints.shape[2] != 3 or joints.shape[0] == 0:
            raise ValueError(f"motion {i}: expected joint positions (T>0, J, 3), got shape {joints.shape}")
        if joints.shape[1] != motions[0].shape[1]:
            raise ValueError(f"motion {i} has {joints.shape[1]} joints, motion 0 has {motions[0].shape[1]}")
        if not np.isfinite(joints).all():
            raise ValueError(f"motion {i} holds NaN/inf")
    text = [str(t) for t in _per_motion(texts, total, num_samples, num_repetitions, "texts")]
    frames = [len(j) for j in motions] if lengths is None else [
        int(n) for n in _per_motion(lengths, total, num_samples, num_repetitions, "lengths")]

    if order == "sample_major" and num_repetitions > 1:
        # input index sample * R + rep  ->  MDM index rep * S + sample
        permutation = [sample * num_repetitions + rep for rep in range(num_repetitions) for sample in range(num_samples)]
        motions = [motions[k] for k in permutation]
        if len(texts) == total:
            text = [text[k] for k in permutation]
        if lengths is None or len(lengths) == total:
            frames = [frames[k] for k in permutation]

    for i, (joints, n) in enumerate(zip(motions, frames)):
        if not 1 <= n <= len(joints):
            raise ValueError(f"motion {i}: length {n} outside 1..{len(joints)} (its frame count)")
    width = max(len(j) for j in motions) if max_frames is None else int(max_frames)
    if width < max(frames):
        raise ValueError(f"max_frames {width} is shorter than the longest length {max(frames)}")
    num_joints = motions[0].shape[1]
    motion = np.empty((total, num_joints, 3, width), dtype=np.float32)
    for i, joints in enumerate(motions):
        kept = joints[:width].astype(np.float32)
        padded = np.concatenate([kept, np.repeat(kept[-1:], width - len(kept), axis=0)]) if len(kept) < width else kept
        motion[i] = padded.transpose(1, 2, 0)  # (T, J, 3) -> (J, 3, T), as MDM's rot2xyz output

    path = Path(path)
    if path.is_dir() or path.suffix != ".npy":
        path = path / "results.npy"
    path.parent.mkdir(parents=True, exist_ok=True)
    results = {"motion": motion, "text": text, "lengths": np.asarray(frames, dtype=np.int64),
               "num_samples": num_samples, "num_repetitions": num_repetitions}
    np.save(path, results, allow_pickle=True)
    if text_files:
        path.with_suffix(".txt").write_text("\n".join(text), encoding="utf-8")
        path.with_name(path.stem + "_len.txt").write_text("\n".join(str(n) for n in frames), encoding="utf-8")
    return path


@dataclass(frozen=True)
class MDMResults:
    """The content of an MDM ``results.npy`` (see the module docstring)."""

    motion: np.ndarray  # (num_samples * num_repetitions, J, 3, max_frames)
    texts: list[str]
    lengths: np.ndarray  # (num_samples * num_repetitions,)
    num_samples: int
    num_repetitions: int

    def index(self, sample: int, repetition: int) -> int:
        """The entry of ``sample``'s repetition ``repetition`` (MDM: ``rep * num_samples + sample``)."""
        if not (0 <= sample < self.num_samples and 0 <= repetition < self.num_repetitions):
            raise IndexError(f"sample {sample}, repetition {repetition} outside {self.num_samples} x {self.num_repetitions}")
        return repetition * self.num_samples + sample

    def joints(self, sample: int, repetition: int = 0) -> np.ndarray:
        """(length, J, 3) joint positions of one motion, without the padding."""
        i = self.index(sample, repetition)
        return self.motion[i, :, :, : int(self.lengths[i])].transpose(2, 0, 1)

    def text(self, sample: int, repetition: int = 0) -> str:
        return self.texts[self.index(sample, repetition)]


def read_mdm_results(path: str | Path) -> MDMResults:
    """Read an MDM ``results.npy`` (ours or MDM's own; a folder means its ``results.npy``) and check its layout.
    Unpickles the file, as MDM does: read only files you trust."""
    path = Path(path)
    if path.is_dir():
        path = path / "results.npy"
    loaded = np.load(path, allow_pickle=True)
    data = loaded.item() if isinstance(loaded, np.ndarray) and loaded.dtype == object and loaded.ndim == 0 else loaded
    if not isinstance(data, dict):
        raise ValueError(f"{path}: not an MDM results file (expected a pickled dict, got {type(data).__name__})")
    missing = [key for key in _KEYS if key not in data]
    if missing:
        raise ValueError(f"{path}: not an MDM results file: missing {missing}")
    motion = np.asarray(data["motion"])
    num_samples, num_repetitions = int(data["num_samples"]), int(data["num_repetitions"])
    texts, lengths = list(data["text"]), np.asarray(data["lengths"])
    total = num_samples * num_repetitions
    if motion.ndim != 4 or motion.shape[2] != 3:
        raise ValueError(f"{path}: motion must be (N, njoints, 3, frames) joint positions, got {motion.shape}")
    if not (motion.shape[0] == len(texts) == len(lengths) == total):
        raise ValueError(f"{path}: {motion.shape[0]} motions, {len(texts)} texts, {len(lengths)} lengths; "
                         f"num_samples x num_repetitions = {total}")
    return MDMResults(motion=motion, texts=texts, lengths=lengths, num_samples=num_samples,
                      num_repetitions=num_repetitions)


__all__ = ["MDMResults", "read_mdm_results", "write_mdm_results"]
