"""The replications of one (checkpoint, sampling point): generation split across ranks, evaluator embeddings,
joints, and the metrics of each replication with their mean ± 95 % CI.

Deterministic whatever the world size. Every replication's work is a fixed list of batches (items sorted by
length, independent of the number of ranks); rank ``r`` runs batches ``r, r + W, ...``; rows are gathered back into
item order (``Dist.gather_tensor``, uneven counts are fine) and per-batch statistics are combined in batch order.
Each motion's initial noise comes from its own seed ``(protocol seed, task, replication, item, repetition)``, and
each replication's ground-truth items (re-drawn captions and crops, ``protocol.redraw_items``) from seeds
``(protocol seed, replication, motion, span)``, never from a rank's own generator. So 1 and 2 ranks compute the
same numbers (tests/test_evaluation_multirank.py).

Ground truth per replication (:class:`GroundTruthDraws`): with ``protocol.redraw_items`` (the default) replication r
generates for its own draw of the items (their captions as conditions, their lengths), edits its clips, and scores
against them: FID's μ, Σ, the ground-truth row, R-precision texts, MultiModality texts, APE/AVE (TEMOS's) and MID,
plausibility references. Its evaluator embeddings cost one pass over the test set per replication (cached on disk
per set, so later sampling points and checkpoints read them).

Generation uses the sampling code: ``mfm.solvers.solve`` over ``guided_velocity`` with padded frames zeroed (what
``mfm.solvers.sample`` does, with per-motion noise), and ``mfm.editing.edit`` for the editing tasks.

The ``mdm`` protocol's rules (pipeline.evaluation.config.MDM_RULES) change four places here: :func:`plan_protocol` (whole
batches, MultiModality replications), :class:`GroundTruthPasses` (the ground-truth row and FID statistics from two
further passes), :func:`generate` with ``window`` and :meth:`PointRun.encode_generated` (what the evaluator sees past
a motion's length, MultiModality's normalisation), and the generated row's captions (``text_padded``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from collections import defaultdict
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from mfm import metrics, metrics_torch
from mfm.composition import bind_inputs
from mfm.diffusion_sampling import (
    SAMPLERS,
    BaselineSampling,
    replacement_edit,
    sample_diffusion,
)
from mfm.editing import edit, edit_mask
from mfm.features import features_to_joints
from mfm.guidance import classifier_free_guidance, guided_feature_mask, resolve_precision
from mfm.layout import FeatureLayout
from mfm.model import valid_frame_mask
from mfm.skeleton import Skeleton
from mfm.solvers import (
    FIXED_STEP_SOLVERS,
    draw_noise,
    guided_velocity,
    noise_generator_device,
    seeded_generators,
    solve,
    step_grid,
    zero_padded_frames,
)
from pipeline.data.stream import Manifest
from pipeline.distributed import Dist
from pipeline.evaluation.config import (
    EDIT_PRESETS,
    OUR_RULES,
    EvalConfig,
    SamplingConfig,
    SamplingPoint,
)
from pipeline.evaluation.spaces import (
    ClassifierSpace,
    EmbeddingSpace,
    EvaluationError,
    GroundTruthPool,
    GroundTruthSet,
)
from pipeline.generation.inference import TrainedModel

logger = logging.getLogger(__name__)

# Task tags keep the random streams of different uses independent (noise, subsets, shuffles, draws).
_TAG = {"main": 1, "mm": 2, "edit": 3, "subset": 4, "mm_texts": 5, "shuffle": 6, "diversity": 7,
        "multimodality": 8, "bootstrap": 9, "gt": 11, "gt_row": 12, "gt_stats": 13, "edit_items": 14}
GT_ROW_STREAM, GT_STATS_STREAM = 1, 2
"""``protocol.gt_draws=independent``: the ground-truth passes of a replication besides its own set (stream 0, which
the generated motions take their captions and lengths from): the ground-truth row's, and FID's statistics'."""


# ---------------------------------------------------------------------------------------------------------------
# Work plan: batches, seeds, gathering
# ---------------------------------------------------------------------------------------------------------------


def derive_seed(*parts: int) -> int:
    """A 64-bit seed from integer parts; independent streams for different tuples (unlike sums)."""
    return int(np.random.SeedSequence([int(p) for p in parts]).generate_state(1, np.uint64)[0] >> 1)


def rng_of(*parts: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(p) for p in parts]))


@dataclasses.dataclass(frozen=True)
class Batch:
    """Rows of one forward batch: which ground-truth item each row uses, and where its output goes."""

    index: int
    kind: str
    """'main', 'mm', 'gt' or 'edit:<preset>'."""
    items: np.ndarray
    slots: np.ndarray
    """Row position in the kind's output array."""
    repeats: np.ndarray
    """Repetition number of each row (MultiModality), else 0."""


def length_sorted_chunks(items: np.ndarray, lengths: np.ndarray, batch_size: int) -> list[np.ndarray]:
    """Positions into ``items`` sorted by length (stable) and cut into chunks: less padding per batch."""
    order = np.argsort(lengths[items], kind="stable")
    return [order[i:i + batch_size] for i in range(0, len(order), batch_size)]


def plan_rows(kind: str, items: np.ndarray, lengths: np.ndarray, batch_size: int, first_index: int,
              repeats: np.ndarray | None = None) -> list[Batch]:
    """One batch per length-sorted chunk; slot = position in ``items``; ``repeats``: each position's repetition
    number (an item listed more than once: a single editing pass), zeros by default."""
    repeats = np.zeros(len(items), np.int64) if repeats is None else repeats
    return [Batch(first_index + b, kind, items[chunk], chunk, repeats[chunk])
            for b, chunk in enumerate(length_sorted_chunks(items, lengths, batch_size))]


def single_pass_items(num_items: int, edits: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``tasks.editing_passes=single``: the items of ``edits`` edits and each one's repetition number: the items in a
    seeded random order, repeated while more edits are asked than there are items (repetition k of an item draws
    its own noise), so every item is edited ⌊edits/n⌋ or ⌈edits/n⌉ times."""
    order = rng_of(seed, _TAG["edit_items"]).permutation(num_items)
    positions = np.arange(edits)
    return order[positions % num_items], positions // num_items


def plan_repeats(items: np.ndarray, lengths: np.ndarray, repeats: int, batch_size: int,
                 first_index: int) -> list[Batch]:
    """MultiModality: every text's ``repeats`` generations in one batch (several texts per batch when they fit),
    so per-text statistics never straddle ranks. Slot = text position × repeats + repetition."""
    per_batch = max(1, batch_size // repeats)
    batches = []
    for b, chunk in enumerate(length_sorted_chunks(items, lengths, per_batch)):
        text_slots = np.repeat(chunk, repeats)
        reps = np.tile(np.arange(repeats), len(chunk))
        batches.append(Batch(first_index + b, "mm", items[text_slots], text_slots * repeats + reps, reps))
    return batches


def my_batches(batches: Sequence[Batch], dist: Dist) -> list[Batch]:
    """Round-robin over the fixed global list: the same batches exist whatever the world size."""
    return [b for b in batches if b.index % dist.world_size == dist.rank]


def gather_rows(dist: Dist, parts: Sequence[tuple[np.ndarray, Tensor]], total: int, width: int) -> np.ndarray:
    """Rank-local (slots, rows) pieces -> the (total, width) array in slot order, identical on every rank."""
    if parts:
        slots = torch.from_numpy(np.concatenate([p[0] for p in parts]).astype(np.int64))
        rows = torch.cat([p[1].detach().float().cpu() for p in parts])
    else:
        slots, rows = torch.zeros(0, dtype=torch.int64), torch.zeros(0, width)
    slots, rows = dist.gather_tensor(slots.to(dist.device)).cpu(), dist.gather_tensor(rows.to(dist.device)).cpu()
    if sorted(slots.tolist()) != list(range(total)):
        raise RuntimeError(f"gathered {len(slots)} rows for {total} slots: a batch was lost or duplicated")
    out = np.empty((total, width), np.float32)
    out[slots.numpy()] = rows.numpy()
    return out


def gather_stats(dist: Dist, local: Sequence[tuple[int, str, dict]]) -> list[tuple[int, str, dict]]:
    """Per-batch statistics of every rank, in batch order (so sums are taken in the same order everywhere)."""
    return sorted((entry for part in dist.all_gather_object(list(local)) for entry in part), key=lambda e: e[0])


class PhaseTimer:
    """Wall time per named phase (accumulated); synchronises CUDA so times are not just launch times."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.seconds: dict[str, float] = defaultdict(float)

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    @contextlib.contextmanager
    def phase(self, name: str) -> Iterator[None]:
        self._sync()
        start = time.perf_counter()
        try:
            yield
        finally:
            self._sync()
            self.seconds[name] += time.perf_counter() - start


# ---------------------------------------------------------------------------------------------------------------
# Ground-truth embeddings (computed once per evaluator and set, cached on disk) and the sets of each replication
# ---------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class GroundTruthEmbeddings:
    motion: np.ndarray
    text: np.ndarray | None
    logits: np.ndarray | None
    text_padded: np.ndarray | None = None
    """The captions embedded with the 'padded' caption length rule (``protocol.generated_caption_length``)."""


def gt_cache_path(cache_dir: Path, space: EmbeddingSpace, gt: GroundTruthSet, padded_text: bool = False) -> Path:
    suffix = "-padtext" if padded_text else ""
    return cache_dir / f"gt-{space.evaluator_id[-16:]}-{gt.dataset_id[:12]}-{gt.split}-{gt.key[:12]}{suffix}.npz"


def ground_truth_embeddings(gt: GroundTruthSet, space: EmbeddingSpace, dist: Dist, cache_dir: Path,
                            batch_size: int, padded_text: bool = False) -> tuple[GroundTruthEmbeddings, bool]:
    """The evaluator's embeddings of every item (rank 0 gets them; other ranks get None) and whether they came
    from the cache. Missing: computed by all ranks, written by rank 0 (atomically). ``padded_text``: also the
    captions under the 'padded' caption length rule (cached in a file of their own)."""
    path = gt_cache_path(cache_dir, space, gt, padded_text)
    cached = dist.broadcast_object(path.is_file() if dist.is_main else None)
    if cached:
        return (_read_gt_cache(path, gt) if dist.is_main else None), True
    all_items = np.arange(len(gt))
    batches = plan_rows("gt", all_items, gt.lengths, batch_size, 0)
    parts: dict[str, list] = defaultdict(list)
    for batch in my_batches(batches, dist):
        features, lengths = gt.padded(batch.items, dist.device)
        parts["motion"].append((batch.slots, space.encode_motions(features, lengths)))
        if space.has_text:
            parts["text"].append((batch.slots, space.encode_texts(gt, batch.items)))
            if padded_text:
                parts["text_padded"].append((batch.slots, space.encode_texts(gt, batch.items, "padded")))
        if isinstance(space, ClassifierSpace):
            parts["logits"].append((batch.slots, space.logits(features, lengths)))
    widths = dist.all_gather_object({k: int(v[0][1].shape[1]) for k, v in parts.items() if v})
    width = {k: w for d in widths for k, w in d.items()}
    gathered = {k: gather_rows(dist, parts.get(k, []), len(gt), width[k]) for k in sorted(width)}
    result = GroundTruthEmbeddings(gathered["motion"], gathered.get("text"), gathered.get("logits"),
                                   gathered.get("text_padded"))
    if dist.is_main:
        cache_dir.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp.npz")
        arrays = {k: v for k, v in dataclasses.asdict(result).items() if v is not None}
        np.savez(tmp, ids=np.asarray(gt.ids), evaluator_id=np.asarray(space.evaluator_id), **arrays)
        tmp.replace(path)
        return result, False
    return None, False


def _read_gt_cache(path: Path, gt: GroundTruthSet) -> GroundTruthEmbeddings:
    with np.load(path) as data:
        if tuple(data["ids"].tolist()) != gt.ids:
            raise EvaluationError(f"{path}: cached ground truth lists other items; delete it to recompute")
        return GroundTruthEmbeddings(*(data[k] if k in data else None for k in ("motion", "text", "logits",
                                                                                 "text_padded")))


def ground_truth_plausibility(gt: GroundTruthSet, skeleton: Skeleton, batch_size: int,
                              device: torch.device | str = "cpu") -> metrics.PlausibilityFigures:
    """Plausibility figures of every item in item order, its joints recovered from its features (on ``device``) as
    the generated motions' are; no jerk ratio (each result row picks its reference). Cheap next to the embeddings:
    not cached on disk."""
    parts = []
    for start in range(0, len(gt), batch_size):
        features, lengths = gt.padded(np.arange(start, min(start + batch_size, len(gt))), device)
        parts.append(metrics_torch.plausibility(features_to_joints(features.double(), skeleton), skeleton, lengths))
    return metrics.PlausibilityFigures.concatenate(parts)


def plausibility_record(skeleton: Skeleton, jerk_reference: str) -> dict[str, Any]:
    """A result's description of its plausibility figures (metrics, ground_truth, editing sections)."""
    return {**metrics.plausibility_settings(skeleton), "jerk_ratio_reference": jerk_reference,
            "statistic": "median over the clips of a replication, then mean ± 95 % CI over replications",
            "ground_truth": "the same figures of the ground-truth clips the row uses (joints from their features)"}


@dataclasses.dataclass
class ReplicationTruth:
    """The ground truth one replication scores against: its items (every rank), their evaluator embeddings and
    plausibility figures (rank 0; None elsewhere)."""

    gt: GroundTruthSet
    emb: GroundTruthEmbeddings | None
    from_cache: bool
    plausibility: metrics.PlausibilityFigures | None

    def record(self) -> dict[str, Any]:
        return {"replication": self.gt.replication, "gt_key": self.gt.key, "embeddings_from_cache": self.from_cache}


@dataclasses.dataclass
class GroundTruthPasses:
    """``protocol.gt_draws=independent``: a replication's two further passes over the test set, each keeping the
    items of whole R-precision batches (the reference loader's ``drop_last``): the ground-truth row's and FID's
    statistics' (both rows are scored against the latter)."""

    row: ReplicationTruth
    row_items: np.ndarray
    stats: ReplicationTruth
    stats_items: np.ndarray

    def record(self) -> dict[str, Any]:
        return {"row_gt_key": self.row.gt.key, "row_items": len(self.row_items), "stats_gt_key": self.stats.gt.key,
                "stats_items": len(self.stats_items),
                "embeddings_from_cache": self.row.from_cache and self.stats.from_cache}


def drop_last_count(num_items: int, batch: int) -> int:
    """How many items one shuffled pass with ``drop_last`` scores: all but ``num_items mod batch`` (all of them
    when fewer than one batch)."""
    return num_items - num_items % batch if num_items >= batch else num_items


def whole_batches(num_items: int, batch: int, rng: np.random.Generator) -> np.ndarray:
    """The items one shuffled pass with ``drop_last`` scores (:func:`drop_last_count` random ones), in item
    order."""
    return np.sort(rng.permutation(num_items)[:drop_last_count(num_items, batch)])


class GroundTruthDraws:
    """The ground-truth sets of one split for the protocol: with ``protocol.redraw_items`` replication r scores
    against its own draw (:meth:`GroundTruthPool.draw`, seeds ``(protocol.seed, r, ...)``), else every replication
    against the fixed set. Sets are drawn from the in-memory pool on demand (cheap, identical on every rank); their
    embeddings are computed by all ranks once per set and cached on disk (:func:`ground_truth_embeddings`, keyed by
    the set's key), their plausibility figures kept in memory (rank 0). The fixed set is what composition uses."""

    def __init__(self, pool: GroundTruthPool, space: EmbeddingSpace, skeleton: Skeleton, redraw: bool,
                 batch_size: int, padded_text: bool = False) -> None:
        self.pool, self.space, self.skeleton, self.redraw, self.batch_size = pool, space, skeleton, redraw, batch_size
        self.padded_text = padded_text and space.has_text
        """The generated row's captions are also embedded with the 'padded' length rule (the sets they come from:
        the fixed one and each replication's stream 0)."""
        self.fixed = pool.draw(None)
        self._fixed_truth: ReplicationTruth | None = None
        self._figures: dict[tuple[int, int], metrics.PlausibilityFigures] = {}

    def fixed_truth(self, dist: Dist, cache_dir: Path) -> ReplicationTruth:
        """The fixed set with its embeddings and figures (computed on first use: call on every rank)."""
        if self._fixed_truth is None:
            self._fixed_truth = self._truth(self.fixed, dist, cache_dir, None, self.padded_text)
        return self._fixed_truth

    def truth(self, replication: int, dist: Dist, cache_dir: Path) -> ReplicationTruth:
        """Replication ``replication``'s ground truth (call on every rank: the embeddings may be computed)."""
        if not self.redraw:
            return self.fixed_truth(dist, cache_dir)
        return self.pass_truth(replication, 0, dist, cache_dir)

    def pass_truth(self, replication: int, stream: int, dist: Dist, cache_dir: Path) -> ReplicationTruth:
        """Pass ``stream`` of replication ``replication`` (0: the replication's own set; :meth:`GroundTruthPool.draw`)
        with its embeddings and (rank 0) plausibility figures; call on every rank."""
        gt = self.pool.draw(replication, stream)
        if gt.ids != self.fixed.ids:  # labels, MultiModality candidates, the plan: all index the items
            raise RuntimeError(f"replication {replication}'s ground truth lists other items than the fixed set")
        return self._truth(gt, dist, cache_dir, self._figures.get((replication, stream)),
                           self.padded_text and stream == 0, stream)

    def _truth(self, gt: GroundTruthSet, dist: Dist, cache_dir: Path, figures: metrics.PlausibilityFigures | None,
               padded_text: bool = False, stream: int = 0) -> ReplicationTruth:
        emb, cached = ground_truth_embeddings(gt, self.space, dist, cache_dir, self.batch_size, padded_text)
        if dist.is_main and figures is None:  # only rank 0 computes metrics
            figures = ground_truth_plausibility(gt, self.skeleton, self.batch_size, dist.device)
            if gt.replication is not None:
                self._figures[(gt.replication, stream)] = figures
        return ReplicationTruth(gt, emb, cached, figures if dist.is_main else None)


# ---------------------------------------------------------------------------------------------------------------
# Protocol sizes actually used
# ---------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ProtocolPlan:
    """The protocol's constants as applied to this test set; every reduction is listed in ``notes``."""

    name: str
    replications: int
    editing_replications: int
    num_items: int
    num_samples: int
    r_precision_batch: int
    diversity_times: int
    multimodality: bool
    mm_num_texts: int
    mm_repeats: int
    mm_times: int
    notes: tuple[str, ...]
    redraw_items: bool = False
    """Each replication scores against its own draw of the ground-truth items (captions, crops)."""
    intervals: str = ""
    """What the 95 % intervals over replications include."""
    loop: str = "ours"
    """'ours', 'mdm' (the reference loop: every rule as MDM_RULES) or 'mixed' (ProtocolConfig.loop)."""
    rules: Mapping[str, Any] = dataclasses.field(default_factory=lambda: dict(OUR_RULES))
    """The loop's rules as set (ProtocolConfig.rules); ``mm_replications`` there is the setting, here below the
    count applied."""
    mm_replications: int = 0
    """Replications that run MultiModality (the first ones); 0 when it is off."""
    gt_row_items: int = 0
    """gt_draws=independent: items each ground-truth pass scores (whole R-precision batches); else 0."""
    editing_passes: str = "per_replication"
    """``tasks.editing_passes``: 'per_replication' (each of the first ``editing_replications`` edits its items) or
    'single' (one pass of ``single_pass_edits`` edits per preset, in the first replication)."""
    single_pass_edits: int = 0
    """Edits per preset of the single pass; 0 in per_replication mode."""

    @property
    def independent_gt(self) -> bool:
        return self.rules.get("gt_draws") == "independent"

    def as_dict(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        out["notes"] = list(self.notes)
        out["rules"] = dict(self.rules)
        return out


def plan_protocol(cfg: EvalConfig, num_items: int, mm_candidates: int) -> ProtocolPlan:
    p, notes = cfg.protocol, []
    batch = p.r_precision_batch
    num_samples = num_items if p.num_samples == 0 else min(p.num_samples, num_items)
    if 0 < p.num_samples and p.num_samples > num_items:
        notes.append(f"num_samples {p.num_samples} > {num_items} test items: all items used")
    if p.round_to_batches and num_samples >= batch:
        # The reference generates until it holds num_samples_limit motions, a batch at a time (ceil); without a
        # limit, every whole batch of its drop_last loader (floor).
        whole = -(-num_samples // batch) if p.num_samples else num_samples // batch
        rounded = min(whole * batch, num_items // batch * batch)
        if rounded != num_samples:
            notes.append(f"{rounded} motions generated, not {p.num_samples or num_items}: whole batches of "
                         f"{batch} (protocol.round_to_batches, the reference's generation loop)")
        num_samples = rounded
    if num_samples < 2:
        raise EvaluationError(f"the test set has {num_samples} item(s); metrics need at least 2")
    rp = min(p.r_precision_batch, num_samples)
    if rp < p.r_precision_batch:
        notes.append(f"R-precision among {rp} (test set of {num_samples}), not {p.r_precision_batch}: "
                     "not comparable with published numbers")
    diversity_times = min(p.diversity_times, num_samples - 1)
    if diversity_times < p.diversity_times:
        notes.append(f"Diversity over {diversity_times} pairs (test set of {num_samples}), not {p.diversity_times}")
    wanted_texts = p.mm_num_texts
    if p.round_to_batches:  # the reference: mm_num_samples // batch_size + 1 whole generation batches
        wanted_texts = (p.mm_num_texts // batch + 1) * batch
        if p.multimodality:
            notes.append(f"MultiModality over {wanted_texts} texts, not {p.mm_num_texts}: "
                         f"{wanted_texts // batch} whole batches of {batch} (protocol.round_to_batches, the "
                         "reference's mm_num_samples // batch_size + 1)")
    mm_texts = min(wanted_texts, mm_candidates)
    if p.multimodality and mm_texts < wanted_texts:
        notes.append(f"MultiModality over {mm_texts} texts/classes (only {mm_candidates} available), "
                     f"not {wanted_texts}")
    mm_reps = min(p.mm_replications or p.replications, p.replications) if p.multimodality else 0
    if p.multimodality and mm_reps < p.replications:
        notes.append(f"MultiModality in the first {mm_reps} of {p.replications} replications "
                     "(protocol.mm_replications; the reference's mm_short mode); its interval over those")
    gt_row_items = 0
    if p.gt_draws == "independent":
        gt_row_items = drop_last_count(num_items, rp)
        if diversity_times > gt_row_items - 1:
            diversity_times = gt_row_items - 1
            notes.append(f"Diversity over {diversity_times} pairs: each ground-truth pass scores {gt_row_items} "
                         "items (whole batches)")
    edit_reps = cfg.tasks.editing_replications or p.replications
    single_edits = 0
    if cfg.tasks.editing_passes == "single":
        edit_reps, single_edits = 1, cfg.tasks.single_pass_edits()
        if cfg.tasks.editing:
            notes.append(f"editing: one pass of {single_edits} edits per preset in the first replication "
                         f"(tasks.editing_passes=single; {num_items} test items, each edited "
                         f"{single_edits // num_items} or {-(-single_edits // num_items)} time(s)); its figures have "
                         "no interval")
            if single_edits < diversity_times:
                notes.append(f"editing Diversity over {single_edits} pairs (the single pass's edits), not "
                             f"{diversity_times}")
    intervals = interval_sources(p.redraw_items, num_samples < num_items, p.multimodality,
                                 independent=p.gt_draws == "independent")
    return ProtocolPlan(p.name, p.replications, edit_reps, num_items, num_samples, rp, diversity_times,
                        p.multimodality, mm_texts, p.mm_repeats, p.mm_times, tuple(notes), p.redraw_items,
                        intervals, p.loop, p.rules(), mm_reps, gt_row_items, cfg.tasks.editing_passes,
                        single_edits)


def interval_sources(redraw: bool, subset: bool, multimodality: bool, independent: bool = False) -> str:
    """What varies between replications, hence what the 95 % intervals (1.96·std/√R) hold."""
    sources = ["the generator's noise"]
    if redraw and independent:
        sources.append("the ground-truth items re-drawn per replication in three independent passes (each test "
                       "motion's caption and crop: one for the generated motions' captions and lengths, one for the "
                       "ground-truth row, one for FID's statistics)")
    elif redraw:
        sources.append("the ground-truth items re-drawn per replication (each test motion's caption and crop; the "
                       "generated motions use the drawn captions and lengths, FID statistics and the ground-truth "
                       "row the drawn clips)")
    if subset:
        sources.append("the subset of items generated")
    sources.append("the metrics' own draws (R-precision batches, Diversity pairs"
                   + (", MultiModality texts and pairs)" if multimodality else ")"))
    fixed = "" if redraw else "; the ground-truth items are one fixed set (protocol.redraw_items=false)"
    return "intervals over replications include " + ", ".join(sources) + fixed


# ---------------------------------------------------------------------------------------------------------------
# Metrics of one replication (rank 0)
# ---------------------------------------------------------------------------------------------------------------


def retrieval_metrics(text: np.ndarray, motion: np.ndarray, batch_size: int,
                      shuffle: np.random.Generator) -> dict[str, float]:
    """R-precision top-1/2/3 and MM-Dist over the same shuffled pairs (complete batches only, as the reference)."""
    order = shuffle.permutation(len(text))
    text, motion = text[order], motion[order]
    top = metrics.r_precision(text, motion, batch_size=batch_size, top_k=3)
    used = len(text) // batch_size * batch_size
    return {"r_precision_top1": top[0], "r_precision_top2": top[1], "r_precision_top3": top[2],
            "mm_dist": metrics.mm_dist(text[:used], motion[:used])}


def summarise(per_replication: Sequence[Mapping[str, float | None]]) -> dict[str, dict[str, Any]]:
    """{metric: {mean, ci, values}} over replications (ci = 1.96·std/√R; None from a single replication, which
    has no spread to measure); metrics missing in any replication are dropped."""
    names = [k for k in per_replication[0] if all(r.get(k) is not None for r in per_replication)]
    out = {}
    for name in names:
        values = [float(r[name]) for r in per_replication]
        mean, half = metrics.confidence_interval(values)
        out[name] = {"mean": mean, "ci": half if len(values) > 1 else None, "values": values}
    return out


@dataclasses.dataclass
class CheckpointContext:
    trained: TrainedModel
    checkpoint_id: str
    manifest: Manifest
    gt: GroundTruthSet
    """The fixed set: the items every replication uses (each with its own captions and crops when they are
    re-drawn), their lengths' bound; composition's ground truth."""
    space: EmbeddingSpace
    gt_emb: GroundTruthEmbeddings | None
    """The fixed set's embeddings: rank 0 only, and only when something scores against the fixed set (redraw off,
    or composition)."""
    gt_from_cache: bool
    plan: ProtocolPlan
    labels: np.ndarray | None
    """Action models: each item's class index in the model's (= classifier's) classes."""
    mm_candidates: np.ndarray
    """Items MultiModality may pick (one per class for action models)."""
    points: tuple[SamplingPoint, ...] = ()
    """The sweep's sampling points this checkpoint runs (those of its objective, :func:`points_for`)."""
    notes: tuple[str, ...] = ()
    """Caveats about this checkpoint's evaluation, copied into every result."""
    gt_plausibility: metrics.PlausibilityFigures | None = None
    """The fixed set's plausibility figures (:func:`ground_truth_plausibility`); rank 0 only, as ``gt_emb``."""
    draws: GroundTruthDraws | None = None
    """The ground truth of each replication (:meth:`truth`)."""
    cache_dir: Path | None = None
    """Where ground-truth embeddings are cached."""

    @property
    def is_action(self) -> bool:
        return self.trained.model_config.is_action_model

    def truth(self, replication: int, dist: Dist) -> ReplicationTruth:
        """The ground truth replication ``replication`` scores against (call on every rank)."""
        if self.draws is None:  # a context built by hand around one set
            return ReplicationTruth(self.gt, self.gt_emb, self.gt_from_cache, self.gt_plausibility)
        return self.draws.truth(replication, dist, self.cache_dir)

    def passes(self, replication: int, dist: Dist, seed: int) -> GroundTruthPasses | None:
        """``protocol.gt_draws=independent``: the replication's ground-truth row pass and FID statistics pass
        (call on every rank); None otherwise."""
        if not self.plan.independent_gt:
            return None
        if self.draws is None:
            raise EvaluationError("protocol.gt_draws=independent needs the re-drawn ground truth (a full context)")
        batch = self.plan.r_precision_batch
        row = self.draws.pass_truth(replication, GT_ROW_STREAM, dist, self.cache_dir)
        stats = self.draws.pass_truth(replication, GT_STATS_STREAM, dist, self.cache_dir)
        return GroundTruthPasses(row, whole_batches(len(row.gt), batch, rng_of(seed, _TAG["gt_row"], replication)),
                                 stats, whole_batches(len(stats.gt), batch,
                                                      rng_of(seed, _TAG["gt_stats"], replication)))


def action_labels(trained: TrainedModel, space: EmbeddingSpace, gt: GroundTruthSet,
                  seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Each item's class index (the model's and the classifier's class lists must agree) and one item per class
    (a seeded pick) as MultiModality's 'texts'."""
    classes = trained.action_classes
    if isinstance(space, ClassifierSpace) and space.action_classes != classes:
        raise EvaluationError(f"the action classifier knows {space.action_classes}, the model {classes}")
    unknown = sorted({a for a in gt.actions if a not in classes})
    if unknown:
        raise EvaluationError(f"test actions {unknown} are not among the model's classes {classes}")
    labels = np.array([classes.index(a) for a in gt.actions], np.int64)
    rng = rng_of(seed, _TAG["mm_texts"])
    per_class = [int(rng.choice(np.flatnonzero(labels == c))) for c in range(len(classes)) if (labels == c).any()]
    return labels, np.asarray(per_class, np.int64)


# ---------------------------------------------------------------------------------------------------------------
# Generation and the replications of one sampling point
# ---------------------------------------------------------------------------------------------------------------


def check_point(trained: TrainedModel, point: SamplingPoint) -> None:
    """A flow model takes an ODE solver, a diffusion model a reverse sampler (ddpm/ddim) with respaced steps."""
    if trained.objective == "diffusion":
        if point.solver not in SAMPLERS:
            raise EvaluationError(f"{trained.checkpoint} is a diffusion model: sample it with "
                                  f"sampling.solvers={list(SAMPLERS)}, not {point.solver!r}")
        try:
            trained.diffusion.respaced(point.steps)
        except ValueError as exc:
            raise EvaluationError(f"{trained.checkpoint}: cannot respace its {trained.diffusion.num_train_steps} "
                                  f"diffusion steps to {point.steps}: {exc}") from exc
    elif point.solver in SAMPLERS:
        raise EvaluationError(f"{trained.checkpoint} is a flow-matching model: {point.solver!r} is a diffusion "
                              "sampler; use an ODE solver (euler, midpoint, heun, rk4, dopri5, ...)")


def points_for(trained: TrainedModel, points: Sequence[SamplingPoint],
               sampling: SamplingConfig | None = None) -> tuple[SamplingPoint, ...]:
    """The points of a sweep that fit ``trained``: ODE solvers for a flow model, ddpm/ddim for a diffusion model.
    One sweep may so list both kinds for flow and diffusion checkpoints (MFM's FID-vs-NFE comparison); the others
    are logged as skipped. None fitting, or a fitting one the model cannot run: :class:`EvaluationError`.
    A diffusion baseline run with its authors' settings (``sampling``, :func:`baseline_sampling`) runs at their
    guidance (FLAME: 8.0) and, with ``every_training_step``, every step of its training schedule (FLAME: 1,000);
    points that differ only there become one."""
    wanted = trained.objective == "diffusion"
    fitting = tuple(point for point in points if (point.solver in SAMPLERS) == wanted)
    baseline = baseline_sampling(trained, sampling)
    if baseline is not None:
        own = {"guidance": baseline.guidance}
        if baseline.every_training_step:
            own["steps"] = trained.diffusion.num_train_steps
        fitting = tuple(dict.fromkeys(dataclasses.replace(p, **own) for p in fitting))
    for point in fitting or points[:1]:
        check_point(trained, point)
    skipped = [point.name for point in points if point not in fitting]
    if skipped:
        logger.info("%s is a %s model: skipping the sweep's points for the other objective, or run at its "
                    "authors' settings instead: %s", trained.checkpoint, trained.objective, ", ".join(skipped))
    return fitting


def edit_points(point: SamplingPoint, edit_setup: Mapping[str, Any], objective: str) -> dict[str, SamplingPoint]:
    """The point each edit preset runs at: a diffusion model's replacement edits at the sampling point itself; flow
    edits with Euler at the edit settings' steps for that preset (``edit_setup['steps_per_preset']``:
    reference-debug's interpolation takes one step, as MFM's edit.py) and their guidance."""
    return {preset: point if objective == "diffusion" else dataclasses.replace(
        point, solver="euler", steps=int(steps), guidance=edit_setup["guidance"])
        for preset, steps in edit_setup["steps_per_preset"].items()}


def baseline_sampling(trained: TrainedModel, sampling: SamplingConfig | None) -> BaselineSampling | None:
    """The diffusion baseline's own sampling settings as this evaluation runs them: None without ``sampling``,
    with ``sampling.baseline_defaults=false`` or for a checkpoint without such settings; each of the authors'
    settings that its ``sampling.baseline_*`` option turns off reads False."""
    baseline = trained.baseline_sampling if sampling is not None and sampling.baseline_defaults else None
    if baseline is None:
        return None
    return baseline.as_run(every_training_step=sampling.baseline_steps, clip_denoised=sampling.baseline_clip_denoised)


def check_weights(trained: TrainedModel, sampling: SamplingConfig) -> None:
    """A baseline whose authors sample the EMA of the weights (FLAME) is not silently scored with its raw weights:
    with ``sampling.use_ema`` its checkpoint must hold EMA weights."""
    baseline = baseline_sampling(trained, sampling)
    try:
        trained.check_baseline_weights(None if baseline is None else baseline.as_run(ema_weights=sampling.use_ema),
                                       "set sampling.use_ema=false to score its raw weights")
    except ValueError as err:
        raise EvaluationError(str(err)) from None


def guided_features(trained: TrainedModel, sampling: SamplingConfig) -> str:
    """Which channels guidance mixes: ``sampling.guided_features`` when set, else the checkpoint's own
    (:meth:`TrainedModel.guided_features_with`)."""
    return trained.guided_features_with(sampling.guided_features)


def sampling_precision(sampling: SamplingConfig, device: torch.device | str) -> str:
    """``sampling.precision`` as it runs on ``device``: 'fp32' or 'bf16' (auto: bf16 on a CUDA GPU with native bf16);
    bf16 on a device whose autocast has none is an :class:`EvaluationError`."""
    try:
        return resolve_precision(sampling.precision, device)
    except ValueError as err:
        raise EvaluationError(f"sampling.{err}") from err


def output_smoothing(trained: TrainedModel, sampling: SamplingConfig) -> float:
    """σ (frames) of the output smoothing: ``sampling.output_smoothing`` when set; else the checkpoint's own
    sampling defaults' (a diffusion baseline's, or the model's ``model.output_smoothing``) with
    ``sampling.baseline_defaults``, 0 without."""
    if sampling.output_smoothing is not None:
        return sampling.output_smoothing
    return trained.default_smoothing if sampling.baseline_defaults else 0.0


def smoothing_keeps_bones(trained: TrainedModel, sampling: SamplingConfig) -> bool | str:
    """How the output smoothing gives the bones back their lengths: ``sampling.output_smoothing_keeps_bones``
    when set, else the checkpoint's own ``model.output_smoothing_keeps_bones``."""
    return trained.smoothing_keeps_bones_with(sampling.output_smoothing_keeps_bones)


@torch.no_grad()
def generate(trained: TrainedModel, cond: Tensor, extras: Mapping[str, Tensor], lengths: Tensor,
             seeds: Sequence[int], point: SamplingPoint, sampling: SamplingConfig, *, known: Tensor | None = None,
             keep: Tensor | None = None, rewrite_until: float = 1.0, restore_known: bool = False,
             reference_translation: bool = False, window: int | None = None,
             precision: str = "fp32") -> tuple[Tensor, int]:
    """Sample (or, with ``known``/``keep``, edit) one batch with the sampling code; raw (un-normalised) features,
    zero past each length, and the number of (guided) model evaluations. The batch is sampled in a window of its
    longest length (the items are length-sorted into batches), not the model's max_frames.

    ``precision`` (:func:`sampling_precision`): the model passes' arithmetic, fp32 or bf16 autocast; the state and
    the solver or chain stay fp32.

    ``window`` (``protocol.generated_padding=model``, sampling only): every motion is sampled in a window of
    ``max(window, longest length)`` frames, as the reference samples all 196 frames of every motion: its initial
    noise covers every frame, every frame is integrated (the velocity past the length is not zeroed), and the
    output keeps whatever the sampler leaves past the length (a model that masks padding, as ours, leaves its
    initial noise there; one that attends over it, ``attend_padding``, what it made of it; the diffusion sampler
    zero in the model's normalisation).

    Flow models: ``mfm.solvers.solve`` of the guided velocity (``mfm.editing.edit`` for edits), each motion's
    initial noise from its own seed. Diffusion models (FLAME / FlowMDM baselines): ``sample_diffusion`` /
    FLAME's ``replacement_edit`` on the schedule respaced to ``point.steps``, each motion's initial and per-step
    noise from its own seed's stream. So a motion's sample does not depend on the batch size or world size. A
    diffusion baseline run with its authors' settings (:func:`baseline_sampling`, FLAME) gets their x0 clamp
    (``TrainedModel.x0_clamp``, as launch/sample.py). ``reference_translation``
    (``tasks.edit_reference_translation``): a diffusion edit gets the source's root copied into the output after the
    smoothing, as FLAME's procedure (``TrainedModel.finish_output``, as launch/sample.py); flow edits ignore it.
    ``extras``: per-motion model inputs (cross-attention token features), bound with ``mfm.composition.bind_inputs``.
    """
    model = trained.sampling_model  # the module, or it compiled once per checkpoint (sampling.compile)
    model = bind_inputs(model, extras, step_size=trained.shortcut_step_size(point.solver, point.steps, point.guidance))
    num_frames, dim = int(lengths.max()), trained.model_config.feature_dim
    windowed = window is not None and keep is None
    if windowed:
        num_frames = max(int(window), num_frames)
    generators = seeded_generators(seeds, noise_generator_device(sampling.noise_device, trained.device))
    if trained.objective == "diffusion":
        schedule = trained.diffusion.respaced(point.steps)
        clamp = trained.x0_clamp(baseline_sampling(trained, sampling))  # FLAME's clip_denoised on our features
        if keep is None:
            result = sample_diffusion(model, schedule, cond, lengths, num_frames=num_frames, feature_dim=dim,
                                      sampler=point.solver, guidance=point.guidance, generator=generators,
                                      clip_denoised=clamp, precision=precision)
        else:
            denoise = classifier_free_guidance(model, cond, scale=point.guidance, lengths=lengths, guided_channels=dim,
                                               precision=precision)
            result = replacement_edit(denoise, schedule, known, keep, sampler=point.solver, lengths=lengths,
                                      generator=generators, restore_known=restore_known, clip_denoised=clamp)
    else:
        velocity = guided_velocity(model, cond, scale=point.guidance, lengths=lengths, precision=precision,
                                   conditional_channels=guided_feature_mask(guided_features(trained, sampling),
                                                                            trained.skeleton))
        x0 = draw_noise((len(seeds), num_frames, dim), generators, lengths=None if windowed else lengths,
                        device=trained.device)
        grid = step_grid(point.steps, trained.model_config.sampling_times)
        if keep is None:
            result = solve(velocity if windowed else zero_padded_frames(velocity, lengths), x0, solver=point.solver,
                           steps=point.steps, grid=grid, rtol=sampling.rtol, atol=sampling.atol)
        else:
            result = edit(velocity, known, keep, steps=point.steps, grid=grid, rewrite_until=rewrite_until,
                          solver=point.solver, x0=x0, lengths=lengths)
    x1 = trained.finish_output(result.x1.float(), lengths, output_smoothing(trained, sampling), known=known,
                               keep=keep, reference_translation=reference_translation,
                               keep_bones=smoothing_keeps_bones(trained, sampling))
    if windowed:
        return trained.denormalize(x1), result.nfe
    valid = valid_frame_mask(lengths, num_frames).unsqueeze(-1)
    return trained.denormalize(x1) * valid, result.nfe


class PointRun:
    """Replications of one (checkpoint, sampling point): per-rank generation, gathering, rank-0 metrics."""

    def __init__(self, cfg: EvalConfig, dist: Dist, ctx: CheckpointContext, point: SamplingPoint,
                 timer: PhaseTimer) -> None:
        self.cfg, self.dist, self.ctx, self.point, self.timer = cfg, dist, ctx, point, timer
        self.trained, self.gt, self.space, self.plan = ctx.trained, ctx.gt, ctx.space, ctx.plan
        self.truth: ReplicationTruth | None = None
        """The current replication's ground truth; ``self.gt`` is its set."""
        self.passes: GroundTruthPasses | None = None
        """The current replication's further ground-truth passes (``protocol.gt_draws=independent``)."""
        rules = cfg.protocol
        self.window = rules.max_length if rules.generated_padding == "model" else None
        """Sampling window of the generated motions and MultiModality repetitions (``generated_padding=model``)."""
        self.padded_captions = rules.generated_caption_length == "padded" and not ctx.is_action
        self.truths: list[dict[str, Any]] = []
        self.skeleton = ctx.trained.skeleton
        self.layout = FeatureLayout(self.skeleton)
        self.flame = cfg.tasks.flame and not ctx.is_action
        check_point(ctx.trained, point)
        self.precision = sampling_precision(cfg.sampling, ctx.trained.device)
        """The model passes' arithmetic as it runs here: 'fp32' or 'bf16' (``sampling.precision``)."""
        editable = ctx.trained.objective == "diffusion" or point.solver in FIXED_STEP_SOLVERS
        self.edit_presets: tuple[str, ...] = cfg.tasks.editing if editable else ()
        # Flow edits integrate with the edit settings' Euler steps and guidance (MFM paper: 30, 1.0), not the
        # sampling point's; a diffusion model's replacement edits run on the point's sampler and steps.
        self.edit_setup = cfg.tasks.edit_setup()
        self.edit_points = edit_points(point, self.edit_setup, ctx.trained.objective)
        self.notes: list[str] = list(ctx.notes)
        if cfg.tasks.editing and not self.edit_presets:
            self.notes.append(f"editing skipped: edits run at fixed-step sampling points only, not {point.solver}")
        self.generated: list[dict[str, float | None]] = []
        self.ground_truth: list[dict[str, float | None]] = []
        self.edited: dict[str, list[dict[str, float]]] = defaultdict(list)
        self.nfe: list[tuple[int, int]] = []  # (nfe, rows) per main batch
        self.gen_seconds: list[tuple[float, int]] = []
        self.width: int | None = None  # the evaluator's embedding width, known with the first ground truth

    # -- plan ------------------------------------------------------------------------------------------------

    def batches(self, replication: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[Batch]]:
        """The replication's items, MultiModality texts, edited items (empty when it edits nothing) and batches, on
        the lengths of its ground truth (set by :meth:`replicate` first)."""
        plan, lengths, size = self.plan, self.gt.lengths, self.cfg.sampling.batch_size
        seed = self.cfg.protocol.seed
        items = np.arange(plan.num_items)
        if plan.num_samples < plan.num_items:
            items = np.sort(rng_of(seed, _TAG["subset"], replication).choice(plan.num_items, plan.num_samples,
                                                                           replace=False))
        batches = plan_rows("main", items, lengths, size, 0)
        mm_items = np.zeros(0, np.int64)
        if plan.multimodality and replication < plan.mm_replications:
            candidates = self.ctx.mm_candidates
            mm_items = np.sort(rng_of(seed, _TAG["mm_texts"], replication).choice(candidates, plan.mm_num_texts,
                                                                                replace=False))
            batches += plan_repeats(mm_items, lengths, plan.mm_repeats, size, len(batches))
        edit_items, edit_repeats = np.zeros(0, np.int64), None
        if replication < plan.editing_replications and self.edit_presets:
            edit_items = items
            if plan.editing_passes == "single":
                edit_items, edit_repeats = single_pass_items(plan.num_items, plan.single_pass_edits, seed)
            for preset in self.edit_presets:
                batches += [dataclasses.replace(b, kind=f"edit:{preset}")
                            for b in plan_rows("edit", edit_items, lengths, size, len(batches), edit_repeats)]
        return items, mm_items, edit_items, batches

    # -- one replication ---------------------------------------------------------------------------------------

    def replicate(self, replication: int) -> None:
        with self.timer.phase("ground_truth"):  # a set and its embeddings per replication when items are re-drawn
            self.truth = self.ctx.truth(replication, self.dist)
            self.gt = self.truth.gt
            self.passes = self.ctx.passes(replication, self.dist, self.cfg.protocol.seed)
            if self.width is None:
                self.width = self.dist.broadcast_object(self.truth.emb.motion.shape[1] if self.dist.is_main else None)
        record = self.truth.record()
        if self.passes is not None:
            passes = self.passes.record()
            record.update(passes, embeddings_from_cache=record["embeddings_from_cache"]
                          and passes["embeddings_from_cache"])
        self.truths.append(record)
        items, mm_items, edit_items, batches = self.batches(replication)
        parts: dict[str, list] = defaultdict(list)
        stats: list[tuple[int, str, dict]] = []
        for batch in my_batches(batches, self.dist):
            stats.append((batch.index, batch.kind, self._run_batch(batch, replication, parts)))
        with self.timer.phase("gather"):
            width = self.width
            totals = {"main": len(items), "mm": len(mm_items) * self.plan.mm_repeats}
            kinds = sorted({b.kind for b in batches})
            rows = {k: gather_rows(self.dist, parts[k], totals.get(k, len(edit_items)), width) for k in kinds}
            logits = None
            if self.ctx.is_action:
                logits = gather_rows(self.dist, parts["logits"], len(items), len(self.trained.action_classes))
            all_stats = gather_stats(self.dist, stats)
        if self.dist.is_main:
            with self.timer.phase("metrics"):
                self._metrics(replication, items, mm_items, edit_items, rows, logits, all_stats)

    def _conditions(self, items: np.ndarray) -> tuple[Tensor, dict[str, Tensor]]:
        """The model's condition for each row (cached caption embedding or action id) and extra inputs."""
        device = self.trained.device
        if self.ctx.is_action:
            return torch.as_tensor(self.ctx.labels[items], device=device), {}
        extras = {}
        if self.gt.text_tokens is not None:
            extras = {"text_tokens": torch.from_numpy(self.gt.text_tokens[items]).to(device),
                      "text_token_len": torch.from_numpy(self.gt.text_token_len[items]).to(device)}
        return torch.from_numpy(self.gt.text_cond[items]).to(device), extras

    def _run_batch(self, batch: Batch, replication: int, parts: dict[str, list]) -> dict[str, Any]:
        device, kind = self.trained.device, batch.kind
        lengths = torch.as_tensor(self.gt.lengths[batch.items], device=device)
        tag = _TAG["edit"] * 1000 + EDIT_PRESETS.index(kind[5:]) if kind.startswith("edit:") else _TAG[kind]
        seeds = [derive_seed(self.cfg.protocol.seed, tag, replication, item, rep)
                 for item, rep in zip(batch.items.tolist(), batch.repeats.tolist())]
        cond, extras = self._conditions(batch.items)
        gt_raw = None
        phase = "editing" if kind.startswith("edit:") else "generation"
        before = self.timer.seconds[phase]
        with self.timer.phase(phase):  # synchronises CUDA on exit: the time is the batch's real time
            if kind.startswith("edit:"):
                preset = kind[5:]
                gt_raw, _ = self.gt.padded(batch.items, device)
                known = self.trained.normalize(gt_raw) * valid_frame_mask(lengths, gt_raw.shape[1]).unsqueeze(-1)
                keep = edit_mask(preset, lengths.cpu(), gt_raw.shape[1], self.layout).to(device)
                raw, nfe = generate(self.trained, cond, extras, lengths, seeds, self.edit_points[preset],
                                    self.cfg.sampling,
                                    known=known, keep=keep, rewrite_until=self.edit_setup["rewrite_until"][preset],
                                    restore_known=self.cfg.tasks.edit_restore_known,
                                    reference_translation=self.cfg.tasks.edit_reference_translation,
                                    precision=self.precision)
            else:
                raw, nfe = generate(self.trained, cond, extras, lengths, seeds, self.point, self.cfg.sampling,
                                    window=self.window, precision=self.precision)
        stats: dict[str, Any] = {"nfe": nfe, "rows": len(batch.items), "seconds": self.timer.seconds[phase] - before}
        with self.timer.phase("features"):
            parts[kind].append((batch.slots, self.encode_generated(kind, raw, lengths)))
            if kind == "main" and isinstance(self.space, ClassifierSpace):
                parts["logits"].append((batch.slots, self.space.logits(raw, lengths)))
        raw = raw[:, : int(lengths.max())]  # the frames the joint figures read (a sampling window is longer)
        if kind == "main" or kind.startswith("edit:") or (self.flame and kind == "mm"):
            with self.timer.phase("joints"):
                stats.update(self._joint_stats(batch, kind, raw, lengths, gt_raw))
        return stats

    def encode_generated(self, kind: str, raw: Tensor, lengths: Tensor) -> Tensor:
        """Evaluator embeddings of generated (or edited) motions under the protocol's rules: past each length the
        evaluator sees zero, or with ``generated_padding=model`` what the sampler left in the window (main and
        MultiModality motions); MultiModality motions are given in the model's normalisation with
        ``mm_normalisation=model``."""
        keep_padding = self.window is not None and kind in ("main", "mm")
        if kind == "mm" and self.cfg.protocol.mm_normalisation == "model":
            return self.space.encode_motions(self.trained.normalize(raw), lengths, keep_padding=keep_padding,
                                             normalized=True)
        return self.space.encode_motions(raw, lengths, keep_padding=keep_padding)

    def _joint_stats(self, batch: Batch, kind: str, raw: Tensor, lengths: Tensor,
                     gt_raw: Tensor | None) -> dict[str, Any]:
        # The joints stay on the generator's device and are scored there (mfm.metrics_torch, the numpy reference's
        # definitions, float64): only the per-clip figures and the batch's scalars come to the host.
        joints = features_to_joints(raw.double(), self.skeleton)
        if kind == "mm":  # one batch holds every repetition of its texts
            texts = torch.as_tensor(batch.slots // self.plan.mm_repeats, device=joints.device)
            ids, variances = metrics_torch.joint_variance_per_group(joints, texts, lengths)
            return {"joint_variance": list(zip(ids, variances))}
        # Per clip, with its slot: medians need every clip of the replication, and the jerk ratio its item.
        stats: dict[str, Any] = {"plausibility": (batch.slots,
                                                  metrics_torch.plausibility(joints, self.skeleton, lengths))}
        if kind == "main" and not self.flame:
            return stats
        if gt_raw is None:
            gt_raw, _ = self.gt.padded(batch.items, raw.device)
        gt_joints = features_to_joints(gt_raw.double(), self.skeleton)
        if kind == "main":
            feet = self.skeleton.foot_left + self.skeleton.foot_right
            # TEMOS's APE/AVE in metres (KIT joints are millimetres), its floor estimated in millimetres.
            ape = metrics_torch.ape_ave(joints, gt_joints, lengths, face_joints=self.skeleton.face_joints,
                                        floor_joints=feet if self.cfg.tasks.ape_floor == "temos" else None,
                                        metres_per_unit=metrics.METRES_PER_UNIT[self.skeleton.unit])
            return {**stats, "ape_ave": ape, "frames": int(lengths.sum())}
        keep = edit_mask(kind[5:], lengths.cpu(), raw.shape[1], self.layout)
        regenerated = ~keep.all(dim=-1)  # frames with at least one generated dim
        scale = metrics.METRES_PER_UNIT[self.skeleton.unit]  # ADE/FDE in metres (KIT joints are millimetres)
        return {**stats, "ade": metrics_torch.ade(joints, gt_joints, lengths, mask_frames=regenerated.to(joints.device),
                                                  metres_per_unit=scale),
                "fde": metrics_torch.fde(joints, gt_joints, lengths, metres_per_unit=scale)}

    # -- metrics (rank 0) ----------------------------------------------------------------------------------------

    def _metrics(self, replication: int, items: np.ndarray, mm_items: np.ndarray, edit_items: np.ndarray,
                 rows: Mapping[str, np.ndarray], logits: np.ndarray | None,
                 stats: Sequence[tuple[int, str, dict]]) -> None:
        seed, plan, gt_emb = self.cfg.protocol.seed, self.plan, self.truth.emb
        gt_all, gt_motion = gt_emb.motion, gt_emb.motion[items]

        def draws(tag: str) -> np.random.Generator:  # the same draws for the generated and the GT row
            return rng_of(seed, _TAG[tag], replication)

        # The ground-truth row: the generated items of the replication's set, its FID that of a bootstrap resample
        # against the whole set; or (gt_draws=independent, the reference) a pass of its own over the test set
        # against FID statistics from another pass, which the generated row's FID uses too.
        row_truth, row_items, passes = self.truth, items, self.passes
        if passes is not None:
            gt_all = passes.stats.emb.motion[passes.stats_items]
            row_truth, row_items = passes.row, passes.row_items
        row_emb = row_truth.emb
        row_motion = row_emb.motion[row_items]
        gen = self._spread(rows["main"], gt_all, draws)
        gen.update(self._plausibility(stats, "main", items))
        if passes is None:
            boot = draws("bootstrap").integers(0, len(gt_motion), len(gt_motion))
            truth = {"fid": metrics.fid(gt_motion[boot], gt_all), **self._spread(gt_motion, None, draws)}
        else:
            truth = {"fid": metrics.fid(row_motion, gt_all), **self._spread(row_motion, None, draws)}
        gt_figures = row_truth.plausibility.select(row_items)
        truth.update(gt_figures.with_jerk_reference(gt_figures.mean_jerk).summary())
        if self.ctx.is_action:
            labels = self.ctx.labels[items]
            gen["accuracy"] = metrics.action_accuracy(logits, labels)
            truth["accuracy"] = metrics.action_accuracy(row_emb.logits[row_items], self.ctx.labels[row_items])
        else:
            text, row_text = gt_emb.text[items], row_emb.text[row_items]
            # The captions of the generated row as the text encoder reads them (generated_caption_length)
            gen_text = gt_emb.text_padded[items] if self.padded_captions and gt_emb.text_padded is not None else text
            gen.update(retrieval_metrics(gen_text, rows["main"], plan.r_precision_batch, draws("shuffle")))
            truth.update(retrieval_metrics(row_text, row_motion, plan.r_precision_batch, draws("shuffle")))
            if self.flame:
                gen.update(self._flame(text, rows["main"], gt_motion, stats))
                truth["mclip"] = metrics.mclip_score(row_text, row_motion)
                truth["mid"] = metrics.mutual_information_divergence(row_text, row_motion, row_motion,
                                                                     eps=self.cfg.tasks.mid_eps)
        if "mm" in rows:
            mm = rows["mm"].reshape(len(mm_items), plan.mm_repeats, -1)
            gen["multimodality"] = metrics.multimodality(mm, plan.mm_times, draws("multimodality"))
            if self.flame:
                variances = [v for _, kind, s in stats if kind == "mm" for _, v in s["joint_variance"]]
                gen["joint_variance"] = float(np.mean(variances))
        self.generated.append(gen)
        self.ground_truth.append(truth)
        for preset in self.edit_presets if len(edit_items) else ():
            kind = f"edit:{preset}"
            edited = self._spread(rows[kind], gt_all, draws)
            per_batch = [(s["ade"], s["fde"], s["rows"]) for _, k, s in stats if k == kind]
            n = sum(r for *_, r in per_batch)
            edited["ade"] = sum(a * r for a, _, r in per_batch) / n
            edited["fde"] = sum(f * r for _, f, r in per_batch) / n
            edited.update(self._plausibility(stats, kind, edit_items))
            self.edited[preset].append(edited)
        main = [s for _, kind, s in stats if kind == "main"]
        self.nfe += [(s["nfe"], s["rows"]) for s in main]
        self.gen_seconds += [(s["seconds"], s["rows"]) for s in main]

    def _plausibility(self, stats: Sequence[tuple[int, str, dict]], kind: str,
                      items: np.ndarray) -> dict[str, float | None]:
        """Medians over the replication's clips of ``kind``; the jerk ratio of the clip in slot s is against the
        ground-truth clip of ``items[s]`` (the one it was generated for, or edited from)."""
        parts = [s["plausibility"] for _, k, s in stats if k == kind]
        slots = np.concatenate([part[0] for part in parts])
        figures = metrics.PlausibilityFigures.concatenate([part[1] for part in parts]).select(np.argsort(slots))
        return figures.with_jerk_reference(self.truth.plausibility.mean_jerk[items]).summary()

    def _spread(self, motion: np.ndarray, gt_all: np.ndarray | None,
                draws: Callable[[str], np.random.Generator]) -> dict[str, float]:
        """FID against the whole ground truth (unless ``gt_all`` is None) and Diversity. The GT row's FID is that
        of a bootstrap resample of the ground truth: the sampling-noise floor of the metric."""
        # a single editing pass smaller than the protocol's pairs: Diversity over as many pairs as it has (noted)
        times = min(self.plan.diversity_times, len(motion))
        out = {"diversity": metrics.diversity(motion, times, draws("diversity"))}
        if gt_all is not None:
            out["fid"] = metrics.fid(motion, gt_all)
        return out

    def _flame(self, text: np.ndarray, motion: np.ndarray, gt_motion: np.ndarray,
               stats: Sequence[tuple[int, str, dict]]) -> dict[str, float]:
        out = {"mclip": metrics.mclip_score(text, motion),
               "mid": metrics.mutual_information_divergence(text, motion, gt_motion, eps=self.cfg.tasks.mid_eps)}
        main = [s for _, kind, s in stats if kind == "main"]
        frames, count = sum(s["frames"] for s in main), sum(s["rows"] for s in main)
        for name in main[0]["ape_ave"]:  # APE is frame-weighted, AVE sequence-weighted (TEMOS)
            weight = "frames" if name.startswith("APE") else "rows"
            total = frames if weight == "frames" else count
            out[name] = sum(s["ape_ave"][name] * s[weight] for s in main) / total
        return out

    # -- result ------------------------------------------------------------------------------------------------

    def _editing_settings(self) -> dict[str, Any]:
        """How the edits ran: flow trajectory rewriting with the edit settings, or FLAME's replacement on the
        point's sampler; and whether the kept part, or the source's root translation, was copied into the
        output."""
        if self.trained.objective == "diffusion":
            return {"method": "replacement (FLAME)", "sampler": self.point.solver, "steps": self.point.steps,
                    "guidance": self.point.guidance, "restore_known": self.cfg.tasks.edit_restore_known,
                    "reference_translation": self.cfg.tasks.edit_reference_translation}
        setup = {k: v for k, v in self.edit_setup.items() if k != "diffusion_restore_known"}
        return {"method": "trajectory rewriting (MFM)", "solver": "euler", **setup,
                "rewrite_until": {p: setup["rewrite_until"][p] for p in self.edit_presets},
                "steps_per_preset": {p: setup["steps_per_preset"][p] for p in self.edit_presets}}

    def _editing_passes(self) -> dict[str, Any]:
        """How many edits the editing figures hold: one pass (``tasks.editing_passes=single``: its size, no interval)
        or one per replication (the edits of each, mean ± CI over them)."""
        plan = self.plan
        if plan.editing_passes == "single":
            return {"passes": "single", "replications": 1, "edits_per_preset": plan.single_pass_edits,
                    "statistic": "one pass: each figure over all its edits, no interval"}
        replications = min(plan.editing_replications, plan.replications)
        return {"passes": "per_replication", "replications": replications, "edits_per_preset": plan.num_samples,
                "statistic": "per replication, then mean ± 95 % CI over replications"}

    def result(self) -> dict[str, Any]:
        rows = sum(r for _, r in self.nfe)
        nfe = sum(n * r for n, r in self.nfe) / rows
        passes = 1 if self.point.guidance in (0.0, 1.0) else 2
        summary = summarise(self.generated)
        for name in ("multimodality", "joint_variance"):  # protocol.mm_replications: over the replications it ran
            ran = [{name: g[name]} for g in self.generated if g.get(name) is not None]
            if name not in summary and ran and len(ran) == self.plan.mm_replications:
                summary[name] = summarise(ran)[name]
        return {
            "metrics": summary,
            "ground_truth": summarise(self.ground_truth),
            "editing": {preset: summarise(values) for preset, values in self.edited.items()},
            "editing_settings": {**self._editing_settings(), **self._editing_passes()} if self.edited else None,
            "nfe": nfe,
            "model_passes_per_motion": nfe * passes,
            "generation_seconds_per_motion": sum(s for s, _ in self.gen_seconds) / rows,
            "plausibility": plausibility_record(self.skeleton, "the mean jerk of the ground-truth clip each motion "
                                                               "was generated for (editing: edited from)"),
            "notes": self.notes,
            "ground_truth_sets": list(self.truths),
        }
