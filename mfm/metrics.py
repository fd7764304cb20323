"""Evaluation metrics as pure functions over embeddings and joint positions (numpy/scipy; torch tensors accepted).

Definitions follow the reference implementations the field reports numbers with:

* Text-to-motion (EricGuo5513/text-to-motion ``final_evaluations.py``, copied into MDM/MFM/FlowMDM): FID, R-precision
  in batches of 32, MM-Dist ("Matching Score"), Diversity, MultiModality, 95% confidence intervals.
* Editing: ADE / FDE, mean over joints of the per-joint Euclidean error in metres: OUR definition. MFM's Table 3
  reports ADE/FDE, but its public code (dongzhuoyao/motionfm at 08eb88d) computes neither, so MFM's definition
  (joints or features, frames, units) cannot be reproduced; our numbers are not comparable with that table.
* Transitions (FlowMDM ``utils/metrics.py::evaluate_jerk``): per-frame jerk curve, Peak Jerk, Area Under the Jerk.
* Physical plausibility of joint positions, per clip: bone-length consistency, floor penetration, foot skating (GMD
  ``calculate_skating_ratio`` thresholds, as OmniControl), mean jerk and its ratio to the ground truth's.
* APE / AVE: TEMOS's definition (Mathux/TEMOS ``temos/model/metrics/compute.py`` ``ComputeMetrics`` over its
  Rifke transform), which FLAME's paper reports; FLAME's own code differs (kakaobrain/flame
  ``src/utils/eval_util.py``: 50–136, its call commented out at :37: no floor or heading canonicalisation, the
  local error over 21 parent→child bone vectors, the root from the SMPL translation), see :func:`ape_ave`.
* FLAME's other metrics: mCLIP score, Mutual Information Divergence (Kim et al. 2022, naver-ai/mid.metric
  ``_compute_pmi``), per-text joint variance.
* Action-to-motion: recogniser accuracy (FID/diversity/multimodality reuse the text-to-motion functions).

Randomised metrics take ``generator``: a ``numpy.random.Generator`` or an int seed (``None`` = fresh entropy), so a
replication is reproducible without touching numpy's global state (the reference code uses ``np.random``).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy import linalg
from scipy.spatial.distance import cdist

from mfm.skeleton import Skeleton

logger = logging.getLogger(__name__)

# T2M protocol constants (reference notes §5.3 / MDM eval_humanml.py).
R_PRECISION_BATCH_SIZE = 32
DIVERSITY_TIMES = 300
MULTIMODALITY_TIMES = 10
# "Average GT jerk of the dataset" constants hard-coded by FlowMDM (issue #5); recompute from your own ground truth
# with dataset_average_jerk when the data or the joint recovery differs.
FLOWMDM_GT_JERK = {"humanml3d": 0.033031363, "babel": 0.016383045}
# Largest imaginary part of sqrtm's diagonal tolerated as round-off (as the reference FID code).
FID_IMAGINARY_TOLERANCE = 1e-3

Generator = np.random.Generator | int | None


def _as_numpy(x: Any, name: str, dtype: type = np.float64) -> np.ndarray:
    """Arrays, lists and (CPU or GPU, grad or not) torch tensors → numpy ``dtype``."""
    if hasattr(x, "detach"):  # torch.Tensor without importing torch here
        x = x.detach().cpu().numpy()
    arr = np.asarray(x, dtype=dtype)
    if dtype is np.float64 and not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf")
    return arr


def _rng(generator: Generator) -> np.random.Generator:
    return generator if isinstance(generator, np.random.Generator) else np.random.default_rng(generator)


def _check_2d(x: np.ndarray, name: str) -> None:
    if x.ndim != 2:
        raise ValueError(f"{name} must be (N, E), got shape {x.shape}")


def _check_paired(a: np.ndarray, b: np.ndarray, names: tuple[str, str]) -> None:
    _check_2d(a, names[0])
    _check_2d(b, names[1])
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"{names[0]} and {names[1]} must pair row by row, got {a.shape[0]} and {b.shape[0]} rows")


def _check_joints(x: np.ndarray, name: str) -> None:
    if x.ndim != 4 or x.shape[-1] != 3:
        raise ValueError(f"{name} must be (N, T, J, 3) joint positions, got shape {x.shape}")


def _lengths_or_full(lengths: Any, n: int, t: int, name: str = "lengths", minimum: int = 1) -> np.ndarray:
    if lengths is None:
        return np.full(n, t, dtype=np.int64)
    out = _as_numpy(lengths, name, dtype=np.int64).reshape(-1)
    if out.shape[0] != n:
        raise ValueError(f"{name} must have one entry per sequence ({n}), got {out.shape[0]}")
    if np.any(out < minimum) or np.any(out > t):
        raise ValueError(f"{name} must lie in [{minimum}, {t}], got min {out.min()} max {out.max()}")
    return out


# ---------------------------------------------------------------------------------------------------------------
# Fréchet distance (T2M calculate_activation_statistics / calculate_frechet_distance)
# ---------------------------------------------------------------------------------------------------------------


def embedding_stats(emb: Any) -> tuple[np.ndarray, np.ndarray]:
    """Mean (E,) and covariance (E, E) of (N, E) embeddings, ``np.cov(rowvar=False)`` (ddof 1) as the reference."""
    emb = _as_numpy(emb, "emb")
    _check_2d(emb, "emb")
    if emb.shape[0] < 2:
        raise ValueError(f"emb needs at least 2 rows for a covariance, got {emb.shape[0]}")
    return emb.mean(axis=0), np.atleast_2d(np.cov(emb, rowvar=False))


def frechet_distance(mu1: Any, sigma1: Any, mu2: Any, sigma2: Any, eps: float = 1e-6) -> float:
    """Fréchet distance between N(mu1, sigma1) and N(mu2, sigma2) (T2M ``calculate_frechet_distance``):

    ``‖mu1 − mu2‖² + tr(sigma1 + sigma2 − 2·sqrtm(sigma1·sigma2))``.

    If ``sqrtm`` of the product is not finite (near-singular product), ``eps·I`` is added to both covariances and
    it is recomputed. Imaginary parts from round-off are dropped; an imaginary diagonal larger than 1e-3 raises.
    """
    mu1, mu2 = np.atleast_1d(_as_numpy(mu1, "mu1")), np.atleast_1d(_as_numpy(mu2, "mu2"))
    sigma1, sigma2 = np.atleast_2d(_as_numpy(sigma1, "sigma1")), np.atleast_2d(_as_numpy(sigma2, "sigma2"))
    if mu1.shape != mu2.shape:
        raise ValueError(f"means have different shapes: {mu1.shape} vs {mu2.shape}")
    if sigma1.shape != sigma2.shape or sigma1.shape != (mu1.shape[0], mu1.shape[0]):
        raise ValueError(f"covariances must both be ({mu1.shape[0]}, {mu1.shape[0]}), got {sigma1.shape}, {sigma2.shape}")

    diff = mu1 - mu2
    covmean = linalg.sqrtm(sigma1.dot(sigma2))
    if not np.isfinite(covmean).all():
        logger.warning("FID: singular covariance product; adding %g to the diagonal of both covariances", eps)
        offset = np.eye(sigma1.shape[0]) * eps
        covmean = linalg.sqrtm((sigma1 + offset).dot(sigma2 + offset))
    if np.iscomplexobj(covmean):
        if not np.allclose(np.diagonal(covmean).imag, 0, atol=FID_IMAGINARY_TOLERANCE):
            raise ValueError(f"FID: sqrtm has a large imaginary component {np.max(np.abs(covmean.imag)):.3g}")
        covmean = covmean.real
    return float(diff.dot(diff) + np.trace(sigma1) + np.trace(sigma2) - 2.0 * np.trace(covmean))


def fid(gen_emb: Any, gt_emb: Any) -> float:
    """FID between generated and ground-truth embeddings (each (N, E)); the GT statistics come from the whole set."""
    mu_gt, sigma_gt = embedding_stats(gt_emb)
    mu_gen, sigma_gen = embedding_stats(gen_emb)
    return frechet_distance(mu_gt, sigma_gt, mu_gen, sigma_gen)


# ---------------------------------------------------------------------------------------------------------------
# Text-motion matching (T2M calculate_R_precision / calculate_matching_score)
# ---------------------------------------------------------------------------------------------------------------


def r_precision(
    text_emb: Any,
    motion_emb: Any,
    *,
    batch_size: int = R_PRECISION_BATCH_SIZE,
    top_k: int = 3,
    generator: Generator | bool = False,
) -> tuple[float, ...]:
    """R-precision top-1..top-k as the T2M protocol: retrieval among ``batch_size`` = 32 (1 match + 31 others).

    Row i of ``text_emb`` pairs with row i of ``motion_emb``. The rows are cut into consecutive batches of
    ``batch_size``; in each batch the text×motion Euclidean distance matrix is argsorted per text (stable sort),
    and text i scores a hit@k when motion i is among its k nearest. Hits are summed over batches and divided by the
    number of samples used. An incomplete final batch is dropped (the reference GT loader has ``drop_last=True``;
    the MDM generated set is an exact multiple of 32), so retrieval is always among exactly ``batch_size``.

    ``generator=False`` (default) keeps the given order, as when the caller's loader already shuffled. Pass a
    ``numpy.random.Generator`` or an int seed to shuffle the pairs before batching (the reference shuffles its
    loader); ``None`` shuffles with fresh entropy.
    """
    text, motion = _as_numpy(text_emb, "text_emb"), _as_numpy(motion_emb, "motion_emb")
    _check_paired(text, motion, ("text_emb", "motion_emb"))
    if text.shape[1] != motion.shape[1]:
        raise ValueError(f"text and motion embeddings must share a dimension, got {text.shape[1]} and {motion.shape[1]}")
    if not 1 <= top_k <= batch_size:
        raise ValueError(f"top_k must be in [1, batch_size={batch_size}], got {top_k}")
    num_batches = text.shape[0] // batch_size
    if num_batches == 0:
        raise ValueError(f"R-precision needs at least batch_size={batch_size} pairs, got {text.shape[0]}")
    if generator is not False:
        order = _rng(generator).permutation(text.shape[0])
        text, motion = text[order], motion[order]

    hits = np.zeros(top_k, dtype=np.int64)
    for b in range(num_batches):
        rows = slice(b * batch_size, (b + 1) * batch_size)
        ranking = np.argsort(cdist(text[rows], motion[rows]), axis=1, kind="stable")
        # rank of the paired motion in each text's list (0 = nearest)
        rank = np.argmax(ranking == np.arange(batch_size)[:, None], axis=1)
        hits += np.array([(rank < k).sum() for k in range(1, top_k + 1)])
    return tuple(float(h) / (num_batches * batch_size) for h in hits)


def r_precision_distinct_captions(text_emb: np.ndarray, motion_emb: np.ndarray, captions: Sequence[str],
                                  batch_size: int, top_k: int = 3) -> tuple[float, ...]:
    """FlowMDM's R-precision (utils/metrics.py ``evaluate_matching_score``): consecutive complete batches of
    ``batch_size`` pairs; inside a batch only the first row of each distinct caption is ranked (among those rows:
    another motion of the same caption would count as a miss), and its hits are scaled by batch / distinct rows."""
    captions = np.asarray(captions, dtype=object)
    num_batches = len(text_emb) // batch_size
    if num_batches == 0:
        raise ValueError(f"R-precision needs at least batch_size={batch_size} pairs, got {len(text_emb)}")
    hits = np.zeros(top_k)
    for b in range(num_batches):
        rows = np.arange(b * batch_size, (b + 1) * batch_size)
        _, first = np.unique(captions[rows].astype(str), return_index=True)
        kept = rows[np.sort(first)]
        k = min(top_k, len(kept))
        distances = np.linalg.norm(text_emb[kept][:, None] - motion_emb[kept][None], axis=-1)
        rank = np.argmax(np.argsort(distances, axis=1, kind="stable") == np.arange(len(kept))[:, None], axis=1)
        counts = np.array([(rank < j).sum() for j in range(1, top_k + 1)], dtype=np.float64)
        counts[k:] = len(kept)  # fewer distinct rows than k: every row is within the top k
        hits += counts * batch_size / len(kept)
    return tuple(float(h) / (num_batches * batch_size) for h in hits)


def mm_dist(text_emb: Any, motion_emb: Any) -> float:
    """MM-Dist ("Matching Score"): mean Euclidean distance between paired text and motion embeddings, over all rows
    given (the reference averages over the samples of its full batches; pass the same rows to match it)."""
    text, motion = _as_numpy(text_emb, "text_emb"), _as_numpy(motion_emb, "motion_emb")
    _check_paired(text, motion, ("text_emb", "motion_emb"))
    return float(np.linalg.norm(text - motion, axis=1).mean())


# ---------------------------------------------------------------------------------------------------------------
# Diversity / MultiModality / confidence interval (T2M calculate_diversity / calculate_multimodality)
# ---------------------------------------------------------------------------------------------------------------


def diversity(emb: Any, times: int = DIVERSITY_TIMES, generator: Generator = None) -> float:
    """Diversity: draw ``times`` indices twice, each draw without replacement and independent of the other, and
    average the L2 distance between the paired embeddings (a pair may be the same row, as in the reference).

    Raises if there are fewer than ``times`` embeddings (the reference asserts N > times).
    """
    emb = _as_numpy(emb, "emb")
    _check_2d(emb, "emb")
    if emb.shape[0] < times:
        raise ValueError(f"diversity needs at least times={times} embeddings, got {emb.shape[0]}")
    rng = _rng(generator)
    first = rng.choice(emb.shape[0], times, replace=False)
    second = rng.choice(emb.shape[0], times, replace=False)
    return float(np.linalg.norm(emb[first] - emb[second], axis=1).mean())


def multimodality(emb: Any, times: int = MULTIMODALITY_TIMES, generator: Generator = None) -> float:
    """MultiModality of (num_texts, num_repeats, E) embeddings (``num_repeats`` generations per text): choose
    ``times`` pairs of repeats and average the L2 distance between the two generations of each pair, over pairs and
    texts. As the reference, the two index draws are each without replacement and shared by all texts.
    """
    emb = _as_numpy(emb, "emb")
    if emb.ndim != 3:
        raise ValueError(f"emb must be (num_texts, num_repeats, E), got shape {emb.shape}")
    if emb.shape[1] < times:
        raise ValueError(f"multimodality needs at least times={times} repeats per text, got {emb.shape[1]}")
    rng = _rng(generator)
    first = rng.choice(emb.shape[1], times, replace=False)
    second = rng.choice(emb.shape[1], times, replace=False)
    return float(np.linalg.norm(emb[:, first] - emb[:, second], axis=2).mean())


def confidence_interval(values: Any) -> tuple[Any, Any]:
    """Mean and 95% half-width ``1.96·std/√reps`` over replications (axis 0; numpy std, ddof 0, as the reference).
    Scalars for (reps,) input, arrays for (reps, ...) input (e.g. the 3 R-precision columns)."""
    v = _as_numpy(values, "values")
    if v.ndim == 0 or v.shape[0] == 0:
        raise ValueError(f"values must be (reps, ...) with reps >= 1, got shape {v.shape}")
    mean, half = v.mean(axis=0), 1.96 * v.std(axis=0) / np.sqrt(v.shape[0])
    if v.ndim == 1:
        return float(mean), float(half)
    return mean, half


# ---------------------------------------------------------------------------------------------------------------
# Editing: ADE / FDE (our definition: MFM's Table 3 has these names, its public code no formula)
# ---------------------------------------------------------------------------------------------------------------


def _per_joint_error(pred_joints: Any, gt_joints: Any, metres_per_unit: float = 1.0) -> np.ndarray:
    """(N, T, J) Euclidean error of each joint in metres, the inputs being in the unit ``metres_per_unit`` says."""
    pred, gt = _as_numpy(pred_joints, "pred_joints"), _as_numpy(gt_joints, "gt_joints")
    _check_joints(pred, "pred_joints")
    if pred.shape != gt.shape:
        raise ValueError(f"pred_joints {pred.shape} and gt_joints {gt.shape} must have the same shape")
    if isinstance(metres_per_unit, bool) or not metres_per_unit > 0:
        raise ValueError(f"metres_per_unit must be > 0, got {metres_per_unit!r}")
    return np.linalg.norm(pred - gt, axis=-1) * metres_per_unit  # (N, T, J)


def ade(pred_joints: Any, gt_joints: Any, lengths: Any = None, mask_frames: Any = None, *,
        metres_per_unit: float = 1.0) -> float:
    """Average Displacement Error in metres: per-joint Euclidean error averaged over joints and frames.

    Each sample is averaged over its frames ``< lengths[i]`` that are also True in ``mask_frames`` ((N, T) or
    (T,) bool, e.g. the edited frames), then samples are averaged with equal weight. Inputs (N, T, J, 3) in the
    unit ``metres_per_unit`` says (1 = metres; ``METRES_PER_UNIT[skeleton.unit]``: KIT's joints are millimetres).
    """
    err = _per_joint_error(pred_joints, gt_joints, metres_per_unit).mean(axis=-1)  # (N, T): mean over joints
    n, t = err.shape
    valid = np.arange(t)[None, :] < _lengths_or_full(lengths, n, t)[:, None]
    if mask_frames is not None:
        mask = _as_numpy(mask_frames, "mask_frames", dtype=bool)
        try:
            valid = valid & np.broadcast_to(mask, (n, t))
        except ValueError:
            raise ValueError(f"mask_frames of shape {mask.shape} does not broadcast to (N, T) = {(n, t)}") from None
    counts = valid.sum(axis=1)
    if np.any(counts == 0):
        raise ValueError(f"samples {np.flatnonzero(counts == 0).tolist()} have no frame to evaluate (mask ∩ length)")
    return float(((err * valid).sum(axis=1) / counts).mean())


def fde(pred_joints: Any, gt_joints: Any, lengths: Any = None, *, metres_per_unit: float = 1.0) -> float:
    """Final Displacement Error in metres: per-joint Euclidean error at each sample's last valid frame
    (``lengths[i] − 1``), averaged over joints and samples. Inputs (N, T, J, 3) in the unit ``metres_per_unit``
    says (as :func:`ade`)."""
    err = _per_joint_error(pred_joints, gt_joints, metres_per_unit).mean(axis=-1)  # (N, T)
    n, t = err.shape
    last = _lengths_or_full(lengths, n, t) - 1
    return float(err[np.arange(n), last].mean())


# ---------------------------------------------------------------------------------------------------------------
# Transitions: jerk, PJ, AUJ (FlowMDM utils/metrics.py evaluate_jerk + calculate_jerk)
# ---------------------------------------------------------------------------------------------------------------


def jerk_curve(joints: Any, lengths: Any = None) -> np.ndarray:
    """Per-frame jerk (N, L − 3) of (N, L, J, 3) joint positions (FlowMDM ``calculate_jerk``).

    Jerk = third finite difference of the positions (per frame, no fps scaling), L1 norm over xyz, max over joints.
    Entry k uses frames k..k+3, so entries ``k >= lengths[i] − 3`` (touching padding) are set to 0.
    """
    pos = _as_numpy(joints, "joints")
    _check_joints(pos, "joints")
    n, length = pos.shape[:2]
    if length < 4:
        raise ValueError(f"jerk needs at least 4 frames, got {length}")
    lens = _lengths_or_full(lengths, n, length)
    jerk = np.abs(np.diff(pos, n=3, axis=1)).sum(axis=-1).max(axis=-1)  # (N, L-3)
    jerk[np.arange(length - 3)[None, :] >= (lens - 3)[:, None]] = 0.0
    return jerk


def _mean_curve(curves: Any) -> np.ndarray:
    c = _as_numpy(curves, "curves")
    if c.ndim != 2 or c.shape[0] == 0:
        raise ValueError(f"curves must be (num_transitions, L - 3) jerk curves, got shape {c.shape}")
    return c.mean(axis=0)


def peak_jerk(curves: Any) -> float:
    """Peak Jerk: maximum over frames of the jerk curve averaged over all transitions."""
    return float(_mean_curve(curves).max())


def area_under_jerk(curves: Any, gt_jerk: float) -> float:
    """Area Under the Jerk: ``Σ_frames |mean_curve − gt_jerk|`` with the dataset's average GT jerk (a constant:
    FlowMDM issue #5 — GT jerk is homogeneous in time; see :data:`FLOWMDM_GT_JERK`, :func:`dataset_average_jerk`)."""
    return float(np.abs(_mean_curve(curves) - gt_jerk).sum())


def dataset_average_jerk(joints_list: Sequence[Any]) -> float:
    """Average ground-truth jerk of a dataset: the per-frame jerk of :func:`jerk_curve` averaged over every valid
    frame of every clip (clips (T_i, J, 3), any lengths ≥ 4). This is the constant AUJ is measured against."""
    total, count = 0.0, 0
    for i, clip in enumerate(joints_list):
        c = _as_numpy(clip, f"joints_list[{i}]")
        if c.ndim != 3 or c.shape[-1] != 3 or c.shape[0] < 4:
            raise ValueError(f"joints_list[{i}] must be (T >= 4, J, 3), got shape {c.shape}")
        curve = jerk_curve(c[None])[0]
        total += float(curve.sum())
        count += curve.shape[0]
    if count == 0:
        raise ValueError("joints_list is empty")
    return total / count


def boundaries_from_lengths(segment_lengths: Sequence[int]) -> np.ndarray:
    """Transition frames of a composition of consecutive segments: the first frame of every segment but the first
    (``cumsum(lengths)[:-1]``), as FlowMDM's ``mid += lengths[i]``."""
    lens = _as_numpy(segment_lengths, "segment_lengths", dtype=np.int64).reshape(-1)
    if np.any(lens < 1):
        raise ValueError(f"segment lengths must be positive, got {lens.tolist()}")
    return np.cumsum(lens)[:-1]


def transition_windows(x: Any, boundaries: Sequence[int], window: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """Crops of ``window`` frames centred on each boundary of a (T, ...) sequence (joints or features).

    The crop of boundary b covers frames [b − l, b + r) with ``l = window // 2``, ``r = window − l`` (FlowMDM's
    ``l_margin`` / ``r_margin``; 60 for HumanML3D, 30 for Babel). Returns ``(windows (B, window, ...),
    real (B, window) bool)``. The reference asserts every crop fits (its segments are ≥ 70 frames); here a crop that
    runs past either end of the sequence is clipped to it and padded by repeating the first / last real frame
    (so padded frames add no velocity), and ``real`` is False on the padded frames so callers can drop those
    windows or restrict statistics to real frames.
    """
    seq = np.asarray(x.detach().cpu().numpy() if hasattr(x, "detach") else x)
    if seq.ndim < 1 or seq.shape[0] == 0:
        raise ValueError(f"x must be a non-empty (T, ...) sequence, got shape {seq.shape}")
    if window < 1:
        raise ValueError(f"window must be positive, got {window}")
    t = seq.shape[0]
    bounds = _as_numpy(boundaries, "boundaries", dtype=np.int64).reshape(-1)
    if np.any(bounds < 0) or np.any(bounds > t):
        raise ValueError(f"boundaries must lie in [0, {t}], got {bounds.tolist()}")
    left = window // 2  # the window spans [boundary - left, boundary + window - left)
    frames = np.arange(window)[None, :] + (bounds - left)[:, None]  # (B, window) wanted frame indices
    real = (frames >= 0) & (frames < t)
    return seq[np.clip(frames, 0, t - 1)], real


# ---------------------------------------------------------------------------------------------------------------
# Physical plausibility: bone lengths, floor penetration, foot skating, jerk (per clip, then medians)
# ---------------------------------------------------------------------------------------------------------------

# GMD's foot-skating thresholds (Karunratanakul et al. 2023, ``calculate_skating_ratio``; OmniControl reuses them).
FOOT_CONTACT_HEIGHT = 0.05  # m: a foot joint lower than this touches the floor
FOOT_SKATING_SPEED = 0.5  # m/s in xz: a touching foot joint faster than this skates (2.5 cm/frame at 20 fps)
# A bone this short on average (two coincident joints) has no meaningful relative deviation: it is left out of it.
MIN_BONE_LENGTH = 1e-6  # m
METRES_PER_UNIT = {"m": 1.0, "mm": 1e-3}  # Skeleton.unit -> metres


def _clips(joints: Any, name: str = "joints") -> np.ndarray:
    """(N, T, J, 3) positions from (N, T, J, 3) clips or one (T, J, 3) clip (a batch of one)."""
    pos = _as_numpy(joints, name)
    if pos.ndim == 3:
        pos = pos[None]
    _check_joints(pos, name)
    return pos


def _frame_mask(lens: np.ndarray, t: int) -> np.ndarray:
    """(N, T) True on each clip's frames ``< lengths[i]``."""
    return np.arange(t)[None, :] < lens[:, None]


def _masked_mean(values: np.ndarray, mask: np.ndarray, empty: float) -> np.ndarray:
    """Per clip (axis 0) mean of ``values`` where ``mask``; ``empty`` for a clip with nothing masked in."""
    axes = tuple(range(1, values.ndim))
    count = mask.sum(axis=axes)
    out = np.full(values.shape[0], empty, dtype=np.float64)
    np.divide(np.where(mask, values, 0.0).sum(axis=axes), count, out=out, where=count > 0)
    return out


def bone_lengths(joints: Any, parents: Sequence[int]) -> np.ndarray:
    """(N, T, J − 1) length of every bone per frame: bone k joins non-root joint ``k + 1`` (in joint order) to its
    parent (``Skeleton.parents``, −1 for the root). Inputs (N, T, J, 3) or (T, J, 3)."""
    pos = _clips(joints)
    par = np.asarray(parents, dtype=np.int64).reshape(-1)
    if par.shape[0] != pos.shape[2]:
        raise ValueError(f"parents lists {par.shape[0]} joints, joints have {pos.shape[2]}")
    children = np.flatnonzero(par >= 0)
    return np.linalg.norm(pos[:, :, children] - pos[:, :, par[children]], axis=-1)


def bone_length_consistency(joints: Any, parents: Sequence[int], lengths: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """Per clip, how much the bone lengths change over the clip's frames ``< lengths[i]`` (a rigid body keeps them):

    * range: the largest over bones of (longest − shortest length of the bone) [the joints' unit];
    * relative deviation: mean over bones and frames of ``|length − mean length of the bone| / mean length``; bones
      whose mean length is below :data:`MIN_BONE_LENGTH` are left out (NaN if every bone is).

    HumanML3D's ground truth is retargeted to one skeleton, so its joints give ~0 for both (its clip 012314: 2e-6 m);
    the ric block a network generates is free to stretch bones. Returns ``(range (N,), relative deviation (N,))``.
    """
    length = bone_lengths(joints, parents)  # (N, T, B)
    n, t, _ = length.shape
    lens = _lengths_or_full(lengths, n, t)
    valid = _frame_mask(lens, t)[..., None]  # (N, T, 1)
    spread = np.where(valid, length, -np.inf).max(axis=1) - np.where(valid, length, np.inf).min(axis=1)  # (N, B)
    mean = np.where(valid, length, 0.0).sum(axis=1) / lens[:, None]  # (N, B)
    measurable = mean >= MIN_BONE_LENGTH
    deviation = np.abs(length - mean[:, None]) / np.where(measurable, mean, 1.0)[:, None]
    return spread.max(axis=1), _masked_mean(deviation, valid & measurable[:, None], np.nan)


def floor_penetration(joints: Any, foot_joints: Sequence[int], lengths: Any = None) -> np.ndarray:
    """(N,) how far the lowest foot joint goes below the floor (y = 0, y up: HumanML3D puts the floor at 0),
    ``max(0, −min over frames < lengths[i] and foot joints of y)`` [input unit]."""
    pos = _clips(joints)
    n, t = pos.shape[:2]
    lowest_foot = pos[:, :, list(foot_joints), 1].min(axis=-1)  # (N, T)
    lowest = np.where(_frame_mask(_lengths_or_full(lengths, n, t), t), lowest_foot, np.inf).min(axis=1)
    return np.where(lowest < 0.0, -lowest, 0.0)  # not max(0, −lowest): that is −0.0 for a foot exactly on the floor


@dataclasses.dataclass(frozen=True)
class FootSkating:
    """Per-clip foot-skating figures of :func:`foot_skating`, each (N,)."""

    ratio: np.ndarray
    """Fraction of frame pairs in which some foot joint skates."""
    contact_speed: np.ndarray
    """Mean horizontal speed of the foot joints while they touch the floor [m/s]; NaN if they never do."""
    skating_speed: np.ndarray
    """Mean horizontal speed over the skating joint-frame pairs [m/s]; 0 if none skates."""


def foot_skating(joints: Any, foot_joints: Sequence[int], fps: float, lengths: Any = None, *,
                 contact_height: float = FOOT_CONTACT_HEIGHT, skating_speed: float = FOOT_SKATING_SPEED) -> FootSkating:
    """Foot skating as GMD's ``calculate_skating_ratio`` (y up, floor at 0, positions in metres):

    for every pair of consecutive frames (t, t + 1) inside a clip and every foot joint, the joint touches the floor
    when its height is below ``contact_height`` (0.05 m) in both frames, and its horizontal speed is
    ``‖xz[t + 1] − xz[t]‖ · fps``; a touching joint faster than ``skating_speed`` (0.5 m/s) skates. The ratio is
    (frame pairs where any foot joint skates) / (frame pairs, ``lengths[i] − 1``). Unlike GMD (toes only, a 5-frame
    moving average that must also exceed the speed, ratio over the padded length) every given foot joint counts, a
    single fast pair skates and padding is not counted. A clip of one frame has no pair: NaN for all three.
    """
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    pos = _clips(joints)
    n, t = pos.shape[:2]
    pairs = _lengths_or_full(lengths, n, t) - 1
    feet = pos[:, :, list(foot_joints)]  # (N, T, F, 3)
    speed = np.linalg.norm(np.diff(feet[..., [0, 2]], axis=1), axis=-1) * fps  # (N, T-1, F)
    low = feet[..., 1] < contact_height  # (N, T, F)
    in_clip = _frame_mask(pairs, t - 1)  # (N, T-1) frame pairs before each clip's end
    contact = low[:, :-1] & low[:, 1:] & in_clip[..., None]
    skating = contact & (speed > skating_speed)
    ratio = _masked_mean(skating.any(axis=-1).astype(np.float64), in_clip, np.nan)
    skating_mean = _masked_mean(speed, skating, 0.0)
    skating_mean[pairs == 0] = np.nan
    return FootSkating(ratio, _masked_mean(speed, contact, np.nan), skating_mean)


def mean_jerk(joints: Any, lengths: Any = None) -> np.ndarray:
    """(N,) mean jerk of each clip: :func:`jerk_curve` (FlowMDM's per-frame jerk: third finite difference, L1 over
    xyz, max over joints; per frame, no fps scaling) averaged over the clip's ``lengths[i] − 3`` entries that use
    no padding frame. NaN for a clip shorter than 4 frames."""
    pos = _clips(joints)
    n, t = pos.shape[:2]
    lens = _lengths_or_full(lengths, n, t)
    out = np.full(n, np.nan)
    if t < 4:
        return out
    entries = lens - 3
    np.divide(jerk_curve(pos, lens).sum(axis=1), entries, out=out, where=entries > 0)  # jerk_curve zeroes the rest
    return out


@dataclasses.dataclass(frozen=True)
class MotionAmount:
    """Per-clip figures of how much a clip moves (:func:`motion_amount`), each (N,), in m/s."""

    pose_speed: np.ndarray
    """Mean speed of the joints relative to the root: the body's own movement, translation left out."""
    root_speed: np.ndarray
    """Mean horizontal (xz) speed of the root: how fast the body travels."""
    pose_spread: np.ndarray
    """Mean over joints of the RMS distance of the root-relative joint from its mean position over the clip [m]:
    how far the body moves, which fast jitter around a still pose does not raise (``pose_speed`` does)."""


def motion_amount(joints: Any, fps: float, lengths: Any = None, root: int = 0) -> MotionAmount:
    """How much each clip moves, over its frame pairs (t, t + 1) inside ``lengths[i]``: ``pose_speed``, the mean
    over joints of ``‖Δ(p_j − p_root)‖ · fps``, and ``root_speed``, the mean of ``‖Δ root_xz‖ · fps``; and over its
    frames ``pose_spread``, the mean over joints of ``sqrt(mean_t ‖(p_j − p_root) − mean_t(p_j − p_root)‖²)``.

    Not a plausibility figure by itself (a clip standing still is plausible) but the one that shows a generator
    whose samples freeze into an average pose: frozen samples keep their bones, feet and jerk perfect, so only
    their speeds beside the ground truth's give them away. NaN for a clip of one frame.
    """
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    pos = _clips(joints)
    n, t = pos.shape[:2]
    lens = _lengths_or_full(lengths, n, t)
    in_clip = _frame_mask(lens - 1, t - 1)  # (N, T-1) frame pairs inside each clip
    local = pos - pos[:, :, root : root + 1]
    local_speed = np.linalg.norm(np.diff(local, axis=1), axis=-1).mean(axis=-1) * fps  # (N, T-1)
    root_speed = np.linalg.norm(np.diff(pos[:, :, root, [0, 2]], axis=1), axis=-1) * fps
    return MotionAmount(_masked_mean(local_speed, in_clip, np.nan), _masked_mean(root_speed, in_clip, np.nan),
                        _spread(local, lens))


def _spread(local: np.ndarray, lens: np.ndarray) -> np.ndarray:
    """(N,) mean over joints of the RMS distance of (N, T, J, 3) positions from their mean over each clip's frames."""
    frames = _frame_mask(lens, local.shape[1])[..., None, None]  # (N, T, 1, 1)
    count = frames.sum(axis=1)  # (N, 1, 1)
    centre = np.where(frames, local, 0.0).sum(axis=1, keepdims=True) / count[:, None]  # (N, 1, J, 3)
    square = np.where(frames, local - centre, 0.0) ** 2
    return np.sqrt(square.sum(axis=(1, 3)) / count[..., 0]).mean(axis=-1)


def movement_spread(joints: Any, lengths: Any = None, root: int = 0) -> np.ndarray:
    """(N,) how much each clip moves as issue-level judges count it: per joint, the RMS spread over frames of its
    position relative to the root's ground point (the root's x and z, height 0), averaged over joints [m].

    Unlike ``pose_spread`` (relative to the root itself) this counts the body rising and sinking — a jump's flight,
    a squat's dip — as movement, and a turn in place (the joints circle the ground point) too; travel does not count.
    """
    pos = _clips(joints)
    lens = _lengths_or_full(lengths, pos.shape[0], pos.shape[1])
    ground = pos[:, :, root : root + 1].copy()
    ground[..., 1] = 0.0
    return _spread(pos - ground, lens)


def _jerk_ratio(jerk: np.ndarray, reference: Any) -> np.ndarray:
    """``jerk / reference`` (reference (N,) or a scalar); NaN where the reference is not positive or undefined."""
    ref = np.asarray(reference, dtype=np.float64)
    if ref.ndim > 0 and ref.shape != jerk.shape:
        raise ValueError(f"{ref.size} reference jerks for {jerk.size} clips: give one per clip or one for all")
    ref = np.broadcast_to(ref, jerk.shape)
    out = np.full(jerk.shape, np.nan)
    np.divide(jerk, ref, out=out, where=np.nan_to_num(ref, nan=0.0) > 0)
    return out


def jerk_ratio(joints: Any, gt_joints: Any, lengths: Any = None, gt_lengths: Any = None) -> np.ndarray:
    """(N,) each clip's :func:`mean_jerk` divided by that of its ground-truth clip (row i pairs with row i; the two
    may differ in length). 1 for a clip against itself; above 1 for a clip shakier than its ground truth. NaN where
    either clip is shorter than 4 frames or the ground truth does not move (zero jerk)."""
    return _jerk_ratio(mean_jerk(joints, lengths), mean_jerk(gt_joints, gt_lengths))


@dataclasses.dataclass(frozen=True)
class PlausibilityFigures:
    """Per-clip plausibility figures of :func:`plausibility`, each an (N,) array in metres / seconds; NaN where a
    figure is undefined for a clip (too short, or ``contact_foot_speed`` of a clip that never touches the floor).
    :meth:`summary` gives the medians over clips."""

    bone_length_range: np.ndarray
    """Largest over bones of (longest − shortest) bone length [m] (:func:`bone_length_consistency`)."""
    bone_length_deviation: np.ndarray
    """Mean relative deviation of the bone lengths from their clip means (:func:`bone_length_consistency`)."""
    floor_penetration: np.ndarray
    """Depth of the lowest foot joint below the floor [m] (:func:`floor_penetration`)."""
    foot_skating_ratio: np.ndarray
    """Fraction of frame pairs in which a foot joint skates (:func:`foot_skating`)."""
    contact_foot_speed: np.ndarray
    """Mean horizontal foot-joint speed while touching the floor [m/s] (:func:`foot_skating`)."""
    skating_foot_speed: np.ndarray
    """Mean horizontal speed of the skating foot joints [m/s], 0 without skating (:func:`foot_skating`)."""
    mean_jerk: np.ndarray
    """Mean per-frame jerk [m per frame³] (:func:`mean_jerk`)."""
    pose_speed: np.ndarray
    """Mean speed of the joints relative to the root [m/s] (:func:`motion_amount`): near 0 for frozen samples."""
    root_speed: np.ndarray
    """Mean horizontal speed of the root [m/s] (:func:`motion_amount`)."""
    pose_spread: np.ndarray
    """Mean RMS distance of the root-relative joints from their mean positions [m] (:func:`motion_amount`)."""
    jerk_ratio: np.ndarray | None = None
    """``mean_jerk`` over a reference jerk (the paired ground-truth clip's, or a dataset average); None: no
    reference given."""

    def __len__(self) -> int:
        return len(self.mean_jerk)

    @property
    def names(self) -> tuple[str, ...]:
        """The figures this object holds (``jerk_ratio`` only with a reference)."""
        return tuple(f.name for f in dataclasses.fields(self) if getattr(self, f.name) is not None)

    def _map(self, fn) -> PlausibilityFigures:
        return PlausibilityFigures(**{f.name: None if (v := getattr(self, f.name)) is None else fn(v)
                                      for f in dataclasses.fields(self)})

    def select(self, indices: Any) -> PlausibilityFigures:
        """The figures of clips ``indices`` (any numpy index: reorders, repeats, masks)."""
        index = np.asarray(indices)
        return self._map(lambda v: v[index])

    @staticmethod
    def concatenate(parts: Sequence[PlausibilityFigures]) -> PlausibilityFigures:
        """Clips of every part, in order; ``jerk_ratio`` is kept only if every part has one."""
        if not parts:
            raise ValueError("nothing to concatenate")
        names = set.intersection(*(set(p.names) for p in parts))
        return PlausibilityFigures(**{name: np.concatenate([getattr(p, name) for p in parts]) for name in names})

    def with_jerk_reference(self, reference_jerk: Any) -> PlausibilityFigures:
        """A copy whose ``jerk_ratio`` is ``mean_jerk / reference_jerk``: one value per clip (its ground-truth clip's
        mean jerk) or one for all (e.g. a dataset's average jerk); NaN where the reference is not positive."""
        return dataclasses.replace(self, jerk_ratio=_jerk_ratio(self.mean_jerk, reference_jerk))

    def clip(self, index: int) -> dict[str, float | None]:
        """One clip's figures by name; None where undefined."""
        return {name: _number_or_none(getattr(self, name)[index]) for name in self.names}

    def summary(self) -> dict[str, float | None]:
        """The median over clips of every figure, ignoring clips where it is undefined; None if it is for all."""
        return {name: _median_or_none(getattr(self, name)) for name in self.names}


def _number_or_none(value: float) -> float | None:
    return None if np.isnan(value) else float(value)


def _median_or_none(values: np.ndarray) -> float | None:
    defined = values[~np.isnan(values)]
    return float(np.median(defined)) if defined.size else None


def padded_motions(motions: Sequence[np.ndarray], dtype: Any = np.float64) -> tuple[np.ndarray, list[int]]:
    """Motions of different lengths as one zero-padded (N, max T, ...) array of ``dtype``, with their lengths (what
    :func:`plausibility` and :func:`movement_spread` take)."""
    lengths = [len(m) for m in motions]
    padded = np.zeros((len(motions), max(lengths), *motions[0].shape[1:]), dtype=dtype)
    for i, m in enumerate(motions):
        padded[i, : len(m)] = m
    return padded, lengths


def plausibility(joints: Any, skeleton: Skeleton, lengths: Any = None, *, gt_joints: Any = None,
                 gt_lengths: Any = None, contact_height: float = FOOT_CONTACT_HEIGHT,
                 skating_speed: float = FOOT_SKATING_SPEED) -> PlausibilityFigures:
    """Every plausibility figure of (N, T, J, 3) or (T, J, 3) joint positions on ``skeleton`` (y up, floor at 0, as
    ``mfm.features.features_to_joints`` recovers them), in metres whatever ``skeleton.unit``: bones from
    ``skeleton.parents``, foot joints = ``skeleton.foot_left + foot_right`` (ankles and toes), fps =
    ``skeleton.fps``; thresholds as :func:`foot_skating`. With ``gt_joints`` (paired row by row, ``gt_lengths``)
    ``jerk_ratio`` is each clip's mean jerk over its ground-truth clip's."""
    scale = METRES_PER_UNIT[skeleton.unit]
    pos = _clips(joints) * scale
    if pos.shape[2] != skeleton.num_joints:
        raise ValueError(f"joints have {pos.shape[2]} joints, skeleton {skeleton.name!r} {skeleton.num_joints}")
    feet = skeleton.foot_left + skeleton.foot_right
    bone_range, bone_deviation = bone_length_consistency(pos, skeleton.parents, lengths)
    skating = foot_skating(pos, feet, skeleton.fps, lengths, contact_height=contact_height,
                           skating_speed=skating_speed)
    figures = PlausibilityFigures(
        bone_length_range=bone_range, bone_length_deviation=bone_deviation,
        floor_penetration=floor_penetration(pos, feet, lengths), foot_skating_ratio=skating.ratio,
        contact_foot_speed=skating.contact_speed, skating_foot_speed=skating.skating_speed,
        mean_jerk=mean_jerk(pos, lengths), **dataclasses.asdict(motion_amount(pos, skeleton.fps, lengths)))
    if gt_joints is None:
        return figures
    return figures.with_jerk_reference(mean_jerk(_clips(gt_joints, "gt_joints") * scale, gt_lengths))


def plausibility_settings(skeleton: Skeleton, *, contact_height: float = FOOT_CONTACT_HEIGHT,
                          skating_speed: float = FOOT_SKATING_SPEED) -> dict[str, Any]:
    """What :func:`plausibility` measures ``skeleton``'s clips with (the same keywords), for results files."""
    return {"unit": "m", "fps": skeleton.fps, "foot_joints": [skeleton.joint_names[j] for j in
                                                               skeleton.foot_left + skeleton.foot_right],
            "foot_contact_height_m": contact_height, "foot_skating_speed_m_per_s": skating_speed}


def plausibility_side_by_side(generated: PlausibilityFigures,
                              ground_truth: PlausibilityFigures) -> dict[str, dict[str, float | None]]:
    """``{figure: {"generated": median, "ground_truth": median}}`` for every figure both hold."""
    gen, gt = generated.summary(), ground_truth.summary()
    return {name: {"generated": gen[name], "ground_truth": gt[name]} for name in gen if name in gt}


# ---------------------------------------------------------------------------------------------------------------
# APE / AVE (TEMOS's definition, reported by FLAME's paper), FLAME's mCLIP, MID, joint variance
# ---------------------------------------------------------------------------------------------------------------


def _yaw_rotation(angle: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations about +y by ``angle``; applied as row vectors ``p @ R``."""
    c, s = np.cos(angle), np.sin(angle)
    z, o = np.zeros_like(angle), np.ones_like(angle)
    # p @ R gives x' = c·x − s·z, z' = s·x + c·z: a rotation by −angle, which maps heading `angle` to +z.
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def _heading(joints: np.ndarray, face_joints: tuple[int, int, int, int]) -> np.ndarray:
    """Per-frame facing angle about +y (0 = facing +z) from (r_hip, l_hip, r_shoulder, l_shoulder), (..., T)."""
    r_hip, l_hip, r_sh, l_sh = face_joints
    across = joints[..., r_hip, :] - joints[..., l_hip, :] + joints[..., r_sh, :] - joints[..., l_sh, :]
    forward_x, forward_z = across[..., 2], -across[..., 0]  # up × across, up = +y (HumanML3D's convention)
    return np.arctan2(forward_x, forward_z)


def _canonical_parts(joints: np.ndarray, root: int, face_joints: tuple[int, int, int, int] | None):
    """TEMOS-style decomposition of (N, T, J, 3) clips, each on its own: global joints, root, xz trajectory, local pose.

    Every clip is translated so the root's first-frame ground position is the origin and, with ``face_joints``,
    rotated about y so its first frame faces +z. Local pose = non-root joints with the root's xz removed (height
    kept), expressed in each frame's own heading frame when ``face_joints`` is given. Frame by frame (the first
    frame aside), so padding frames never reach a clip's valid ones.
    """
    g = joints - joints[:, :1, root : root + 1] * np.array([1.0, 0.0, 1.0])
    if face_joints is not None:
        first = _yaw_rotation(_heading(g[:, 0], face_joints))  # (N, 3, 3)
        g = g @ first[:, None]  # (T, J, 3) @ (3, 3) per clip
    root_pos = g[:, :, root]  # (N, T, 3)
    local = np.delete(g, root, axis=2) - (root_pos * np.array([1.0, 0.0, 1.0]))[:, :, None]
    if face_joints is not None:
        local = local @ _yaw_rotation(_heading(g, face_joints))  # (J, 3) @ (3, 3) per clip and frame
    return g, root_pos, root_pos[..., [0, 2]], local


TEMOS_FLOOR_SOFTNESS = 0.5
"""``softness`` of TEMOS's ``get_floor`` (temos/transforms/joints2jfeats/tools.py: 29–46)."""
TEMOS_FLOOR_MM_PER_UNIT = 1000.0
"""TEMOS's ``get_floor`` runs on joints in millimetres (its MMM/KIT joints; ``ComputeMetrics.transform`` divides
by 1000 only after the Rifke transform, temos/model/metrics/compute.py: 154–159): the softmin's ``log`` term is in
millimetres, so metres are scaled by this before it."""


def temos_floor_height(joints: np.ndarray, foot_joints: Sequence[int], *,
                       millimetres_per_unit: float = TEMOS_FLOOR_MM_PER_UNIT) -> float:
    """The floor height TEMOS's ``get_floor`` estimates for one clip (T, J, 3), y up, in the clip's unit: the lowest
    of the foot joints in each frame, then TEMOS's ``softmin`` over frames, ``min − log(softness + e^(min − max))``
    with softness 0.5, computed in millimetres as TEMOS does (``millimetres_per_unit``: 1000 for joints in metres,
    1 for joints in millimetres) and converted back.

    In millimetres e^(min − max) vanishes for any clip whose lowest foot moves by more than a few mm, so the floor
    is ``min + log 2`` mm: 0.69 mm above the lowest foot point (which then sits at −0.69 mm), whatever the clip.
    Applying the formula to metres (this function before issue 25) put the floor 0.1–0.4 m *under* the lowest foot,
    by an amount that depends on each clip's foot-height range (log(0.5 + e^(−range)) m), so generated and
    ground-truth clips got different offsets and APE_root / APE_mean_global were biased by 0.1–0.3 m.
    """
    clip = np.asarray(joints, dtype=np.float64)
    return float(temos_floor_heights(clip[None], foot_joints, millimetres_per_unit=millimetres_per_unit)[0])


def temos_floor_heights(joints: np.ndarray, foot_joints: Sequence[int], lengths: Any = None, *,
                        millimetres_per_unit: float = TEMOS_FLOOR_MM_PER_UNIT) -> np.ndarray:
    """:func:`temos_floor_height` of every clip of (N, T, J, 3) joints at once, over its frames ``< lengths[i]``:
    (N,) heights in the clips' unit."""
    if not millimetres_per_unit > 0:
        raise ValueError(f"millimetres_per_unit must be > 0, got {millimetres_per_unit}")
    n, t = joints.shape[:2]
    valid = _frame_mask(_lengths_or_full(lengths, n, t), t)
    heights = joints[:, :, list(foot_joints), 1].min(axis=2) * millimetres_per_unit  # (N, T)
    low = np.where(valid, heights, np.inf).min(axis=1)
    high = np.where(valid, heights, -np.inf).max(axis=1)
    return (low - np.log(TEMOS_FLOOR_SOFTNESS + np.exp(low - high))) / millimetres_per_unit


def ape_ave(
    pred_joints: Any,
    gt_joints: Any,
    lengths: Any = None,
    *,
    root: int = 0,
    face_joints: tuple[int, int, int, int] | None = None,
    floor_joints: Sequence[int] | None = None,
    metres_per_unit: float = 1.0,
) -> dict[str, float]:
    """Average Position Error and Average Variance Error as TEMOS defines them (``ComputeMetrics``,
    temos/model/metrics/compute.py), the definition FLAME's paper reports.

    FLAME's own code differs (kakaobrain/flame ``src/utils/eval_util.py``: 50–136 ``compute_ape_ave``, whose call is
    commented out at :37): no floor or heading canonicalisation, the local error over 21 parent→child bone vectors
    instead of root-relative joints, the root from the SMPL translation; it is not implemented here, so our APE/AVE
    are TEMOS's, not FLAME's code's.

    Both clips of a pair are put in canonical form independently (:func:`_canonical_parts`: root's first-frame xz
    at the origin; with ``face_joints`` = (r_hip, l_hip, r_shoulder, l_shoulder), e.g. ``Skeleton.face_joints``,
    first frame facing +z and the local pose in each frame's heading frame), then for each part

    * root: root joint xyz; traj: root xz; mean_local: non-root joints relative to the root's ground position;
      mean_global: all joints;
    * APE = Euclidean error, averaged over all valid frames of all sequences (frame-weighted, as TEMOS divides by
      Σ lengths) and, for the joint sets, over joints;
    * AVE = ‖σ²_pred − σ²_gt‖₂ over xyz, σ² = per-coordinate variance over the sequence's frames with the T − 1
      denominator, averaged over sequences and, for the joint sets, over joints.

    ``floor_joints`` (the skeleton's foot joints, as TEMOS's LM/LF/RM/RF): each clip's floor is re-estimated with
    :func:`temos_floor_height` (in millimetres, as TEMOS) and subtracted from its heights first, as TEMOS's Rifke
    transform does (rifke.py: 31); None keeps the heights as given (HumanML3D joints are floor-aligned already).
    Inputs (N, T, J, 3) in the unit ``metres_per_unit`` says (1 = metres; ``METRES_PER_UNIT[skeleton.unit]``, e.g.
    1e-3 for KIT's millimetres), converted to metres first: results are in metres (TEMOS's ``force_in_meter``);
    ``lengths`` (N,) valid frames (≥ 2). Keys: ``APE_root, APE_traj, APE_mean_local, APE_mean_global, AVE_root,
    AVE_traj, AVE_mean_local, AVE_mean_global``.

    All clips are computed at once (array operations over the batch, every clip masked to its own frames; no loop
    over clips): the same numbers as one clip at a time, up to summation order.
    """
    pred, gt = _as_numpy(pred_joints, "pred_joints"), _as_numpy(gt_joints, "gt_joints")
    _check_joints(pred, "pred_joints")
    if pred.shape != gt.shape:
        raise ValueError(f"pred_joints {pred.shape} and gt_joints {gt.shape} must have the same shape")
    if not metres_per_unit > 0:
        raise ValueError(f"metres_per_unit must be > 0, got {metres_per_unit}")
    if metres_per_unit != 1.0:
        pred, gt = pred * metres_per_unit, gt * metres_per_unit
    n, t, j = pred.shape[:3]
    if not 0 <= root < j:
        raise ValueError(f"root index {root} out of range for {j} joints")
    lens = _lengths_or_full(lengths, n, t, minimum=2)
    valid = _frame_mask(lens, t)  # (N, T)
    clips = [pred, gt]
    if floor_joints is not None:
        clips = [clip - temos_floor_heights(clip, floor_joints, lens)[:, None, None, None] * np.array([0.0, 1.0, 0.0])
                 for clip in clips]
    names = ("mean_global", "root", "traj", "mean_local")
    parts_pred = _canonical_parts(clips[0], root, face_joints)
    parts_gt = _canonical_parts(clips[1], root, face_joints)
    out = {}
    for name, p, g in zip(names, parts_pred, parts_gt):
        # (N, T, [joints,] D): the error per frame (mean over joints, if any), summed over each clip's frames
        mask = valid.reshape(n, t, *([1] * (p.ndim - 2)))
        error = np.linalg.norm(p - g, axis=-1)
        error = error.reshape(n, t, -1).mean(axis=-1)
        out[f"APE_{name}"] = float(np.where(valid, error, 0.0).sum() / lens.sum())
        spread = [_masked_variance(x, mask, lens) for x in (p, g)]  # (N, [joints,] D), T − 1 denominator
        ave = np.linalg.norm(spread[0] - spread[1], axis=-1).reshape(n, -1).mean(axis=-1)
        out[f"AVE_{name}"] = float(ave.mean())
    return {k: out[k] for k in (*(f"APE_{k}" for k in ("root", "traj", "mean_local", "mean_global")),
                                *(f"AVE_{k}" for k in ("root", "traj", "mean_local", "mean_global")))}


def _masked_variance(x: np.ndarray, mask: np.ndarray, lens: np.ndarray) -> np.ndarray:
    """Per clip (axis 0), the variance over frames (axis 1) where ``mask``, with the ``lens − 1`` denominator."""
    shape = (-1, *([1] * (x.ndim - 2)))
    count = lens.reshape(shape).astype(np.float64)
    mean = np.where(mask, x, 0.0).sum(axis=1) / count
    return (np.where(mask, x - mean[:, None], 0.0) ** 2).sum(axis=1) / (count - 1.0)


def mclip_score(text_emb: Any, motion_emb: Any) -> float:
    """mCLIP score: mean cosine similarity between paired text and motion embeddings (FLAME's CLIP score on its
    motion-CLIP evaluator)."""
    text, motion = _as_numpy(text_emb, "text_emb"), _as_numpy(motion_emb, "motion_emb")
    _check_paired(text, motion, ("text_emb", "motion_emb"))
    norms = np.linalg.norm(text, axis=1) * np.linalg.norm(motion, axis=1)
    if np.any(norms == 0):
        raise ValueError("mclip_score: zero-norm embedding has no direction")
    return float(((text * motion).sum(axis=1) / norms).mean())


def _logdet_spd(m: np.ndarray, name: str) -> float:
    sign, logdet = np.linalg.slogdet(m)
    if sign <= 0:
        raise ValueError(f"MID: covariance of {name} is singular; use more samples or eps > 0")
    return float(logdet)


def mutual_information_divergence(
    text_emb: Any,
    motion_emb: Any,
    gt_motion_emb: Any = None,
    *,
    eps: float = 0.0,
) -> float:
    """Mutual Information Divergence (Kim et al. 2022; naver-ai/mid.metric ``_compute_pmi``, reduction=True).

    Gaussians are fitted to the real pairs: x = ``gt_motion_emb`` (N, Ex), y = ``text_emb`` (N, Ey), z = [x; y],
    means μ and covariances Σ (denominator N − 1). MID is the expected point-wise mutual information of the
    generated pairs (x̂ = ``motion_emb`` (M ≤ N rows, paired with the first M texts), y) under those Gaussians:

        MID = I(X; Y) + ½ E[D²_x(x̂) + D²_y(y) − D²_z([x̂; y])],   I = ½ log(det Σx · det Σy / det Σz),
        D²_a(a) = (a − μ_a)ᵀ Σa⁻¹ (a − μ_a),

    computed as traces with the generated second moments taken about the real means. With ``gt_motion_emb=None``
    the generated pairs are their own reference, so MID is their Gaussian MI. ``eps`` adds eps·I to Σx, Σy, Σz
    (0 as the reference default; its authors suggest 5e-4 for small sets). Computed in float64.
    """
    y = _as_numpy(text_emb, "text_emb")
    x0 = _as_numpy(motion_emb, "motion_emb")
    x = x0 if gt_motion_emb is None else _as_numpy(gt_motion_emb, "gt_motion_emb")
    _check_paired(x, y, ("gt_motion_emb" if gt_motion_emb is not None else "motion_emb", "text_emb"))
    _check_2d(x0, "motion_emb")
    if x0.shape[1] != x.shape[1]:
        raise ValueError(f"generated and real motion embeddings differ in width: {x0.shape[1]} vs {x.shape[1]}")
    n, m = x.shape[0], x0.shape[0]
    if m > n:
        raise ValueError(f"motion_emb has {m} rows but only {n} texts to pair with")
    if m < 2:
        raise ValueError("MID needs at least 2 generated samples")
    dz = x.shape[1] + y.shape[1]
    if n <= dz and eps == 0:
        raise ValueError(f"MID needs more real pairs ({n}) than the joint dimension ({dz}) for a full-rank covariance")

    z = np.concatenate([x, y], axis=1)
    z0 = np.concatenate([x0, y[:m]], axis=1)
    mu_x, mu_y, mu_z = x.mean(0), y.mean(0), z.mean(0)

    def second_moment(a: np.ndarray, mu: np.ndarray) -> np.ndarray:
        d = a - mu
        return d.T @ d / (a.shape[0] - 1)

    def regularised(c: np.ndarray) -> np.ndarray:
        return c + eps * np.eye(c.shape[0])

    cov_x, cov_y, cov_z = (regularised(second_moment(a, mu)) for a, mu in ((x, mu_x), (y, mu_y), (z, mu_z)))
    mom_x0, mom_z0 = second_moment(x0, mu_x), second_moment(z0, mu_z)  # about the real means, as the reference

    mi = 0.5 * (_logdet_spd(cov_x, "motions") + _logdet_spd(cov_y, "texts") - _logdet_spd(cov_z, "pairs"))
    smd = 0.5 * (
        np.trace(np.linalg.solve(cov_x, mom_x0))
        + np.trace(np.linalg.solve(cov_y, second_moment(y, mu_y)))
        - np.trace(np.linalg.solve(cov_z, mom_z0))
    )
    return float(mi + smd)


def joint_variance(samples: Any) -> float:
    """Spread of the S generations of one text, (S, T, J, 3): for every frame and joint the mean squared distance of
    the samples' positions from their across-sample mean (= sum over xyz of the variances, ddof 0), averaged over
    frames and joints (m² for metric joints)."""
    s = _as_numpy(samples, "samples")
    _check_joints(s, "samples")
    if s.shape[0] < 2:
        raise ValueError(f"joint_variance needs at least 2 samples, got {s.shape[0]}")
    return float(s.var(axis=0).sum(axis=-1).mean())


# ---------------------------------------------------------------------------------------------------------------
# Action-to-motion
# ---------------------------------------------------------------------------------------------------------------


def action_accuracy(logits: Any, labels: Any) -> float:
    """Recogniser accuracy: fraction of samples whose argmax class over (N, C) ``logits`` equals ``labels`` (N,)."""
    lg = _as_numpy(logits, "logits")
    lb = _as_numpy(labels, "labels", dtype=np.int64).reshape(-1)
    if lg.ndim != 2 or lg.shape[0] != lb.shape[0] or lg.shape[0] == 0:
        raise ValueError(f"logits must be (N, C) with N = len(labels) > 0, got {lg.shape} and {lb.shape}")
    if np.any(lb < 0) or np.any(lb >= lg.shape[1]):
        raise ValueError(f"labels must lie in [0, {lg.shape[1]}), got min {lb.min()} max {lb.max()}")
    return float((lg.argmax(axis=1) == lb).mean())
