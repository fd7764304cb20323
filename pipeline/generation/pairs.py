"""Reflow's teacher pairs (``launch/distill.py``, method ``reflow``): the teacher's own noise → motion map, written as
a dataset of our format that the ordinary Trainer streams.

For every caption of the teacher's training split (``distill.pairs_per_caption`` times), the teacher integrates its
guided ODE from noise x0 at t = 0 to a motion x1 at t = 1 with its own default sampler: its solver (euler), its
``sampling_steps`` (10), its ``sampling_guidance`` and ``guided_features``. Pair ``i``'s noise is
``mfm.solvers.draw_noise`` of a generator seeded with ``sample_seed(distill.seed, i)`` over its length (as
``launch/sample.py``'s sample ``i`` with ``--seed distill.seed``), so a record stores only ``(caption, length, noise
seed, teacher x1)`` and the student's loss regenerates x0 exactly (``train.flow_noise=recorded``).

No output smoothing in the target: smoothing (``model.output_smoothing``) is applied to a sampler's output after the
ODE, and the student inherits the teacher's setting, so its samples are smoothed once anyway; a smoothed target would
be smoothed twice, and it would no longer be the end of the teacher's ODE path from that noise, which is what makes
the student's straight path land where the teacher's curved one does.

The pair set (``<out>/pairs/``): one ``train`` split of tar and Parquet shards (``preprocess.shards`` writers), each
record one caption with its span the whole motion, the source record's text embedding (and token features) for it,
its features the teacher's x1 un-normalised with the teacher's Mean/Std (the loader normalises them back), and its
``noise_seed``. ``manifest.json`` is written last and carries the ``pairs`` section (teacher checkpoint id and step,
sampler, seeds, source dataset); the normalisation, feature spec and text encoder are the teacher's dataset's.

Order (``distill.pair_order``): ``interleaved`` numbers the pairs repeat by repeat (every caption of the split once,
then every caption again, ...), so a shard's records span the captions; ``grouped`` puts a caption's pairs one after
another (the order before 2026-12-06, when a shard of the embedded default's 144 pairs per caption held one clip).

Ranks: every rank plans the same pair list from the manifest (indices, lengths and seeds only); rank ``r`` solves
pairs ``r, r + W, ...`` in chunks of :data:`CHUNK_BATCHES` batches of ``distill.batch_size`` (longest first within a
chunk, as the samplers batch), reading the chunk's records from one pass over the split (:class:`RecordWindow`), and
writes each chunk to ``.build-tmp/rank-r-chunk-k.pt``; rank 0 then streams the split again (once per repeat when
interleaved) and writes the shards in pair order, reading each rank's chunks one at a time, and the manifest. Memory
is one chunk's records and motions per rank (and one chunk per rank on rank 0 while it writes), not the dataset's,
so a HumanML3D-sized split with token features fits. Resume: a complete pair set whose ``pairs`` section is the one
asked for is reused as it is; one made with another teacher or settings is refused; an unfinished one (no manifest)
is removed and made again (generation itself restarts from its first pair).
"""

from __future__ import annotations

import logging
import math
import shutil
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mfm.guidance import guided_feature_mask
from mfm.solvers import (
    FLOW_MAP_PERTURBATION,
    ROUGH_AMPLIFICATION,
    draw_noise,
    flow_map_amplification,
    sample,
    seeded_generators,
    step_grid,
)
from pipeline import checkpoint as ckpt
from pipeline.config import DistillConfig
from pipeline.data.stages import MotionRecord
from pipeline.data.stream import Manifest, iter_motions, open_manifest
from pipeline.distributed import Dist
from pipeline.generation.inference import TrainedModel
from pipeline.generation.integration import sample_seed
from pipeline.generation.sampling import PromptConditions, conditioned_model, max_sample_length
from preprocess.processing import Record, RecordCaption
from preprocess.shards import (
    FORMAT_VERSION,
    MANIFEST_NAME,
    PAIRS_KEY,
    SplitShardWriter,
    TextFeatures,
    derive_dataset_id,
    load_manifest,
    parquet_schema,
    write_manifest,
)

logger = logging.getLogger(__name__)

FLOW_MAP_KEY = "teacher_flow_map"
"""The pair set manifest's section with the teacher's flow-map amplification (:func:`probe_amplification`)."""

PAIRS_FOLDER = "pairs"
TMP_FOLDER = ".build-tmp"
MAX_SHARD_SIZE = 500
MIN_SHARDS = 16
"""At least this many shards when there are enough pairs: the loader needs a shard per reader (ranks × workers)."""
CHUNK_BATCHES = 16
"""Teacher batches per chunk: a rank holds one chunk's records and motions at a time (:func:`chunk_size`)."""
NOISE_RULE = ("x0 = mfm.solvers.draw_noise((1, length, D), seeded_generators([noise_seed]), lengths=[length]); "
              "features = the teacher's Euler solution from x0, un-normalised")


class PairSetError(ValueError):
    """The pair set cannot be made or reused (another teacher's pairs in the folder, a teacher that is not a flow
    model, a teacher whose dataset is not where it was): the message names the file and the reason."""


@dataclass(frozen=True)
class PlannedPair:
    """One teacher solution to make: pair ``index`` of caption ``caption`` of the split's record number
    ``record_index`` (id ``record_id``), ``length`` frames. No features or text: those are streamed from the
    dataset when the pair is solved and when it is written (:func:`stream_records`)."""

    index: int
    record_index: int
    record_id: str
    caption: int
    repeat: int
    length: int
    seed: int

    @property
    def pair_id(self) -> str:
        return f"{self.record_id}_c{self.caption}_p{self.repeat}"


def pairs_dir(out_dir: str | Path) -> Path:
    return Path(out_dir) / PAIRS_FOLDER


def pair_settings(teacher: TrainedModel, settings: DistillConfig, source: Manifest) -> dict[str, Any]:
    """The manifest's ``pairs`` section: what the pairs are a function of (a pair set is reused only when equal)."""
    return {
        "method": settings.method,
        "teacher_checkpoint_id": settings.teacher_checkpoint_id,
        "teacher_step": settings.teacher_step,
        "solver": settings.teacher_solver,
        "steps": settings.teacher_steps,
        "guidance": settings.teacher_guidance,
        "guided_features": settings.teacher_guided_features,
        "output_smoothing": 0.0,
        "pairs_per_caption": settings.pairs_per_caption,
        "order": settings.pair_order,
        "seed": settings.seed,
        "max_length": max_sample_length(teacher),
        "source_dataset_id": source.dataset_id,
        "source_split": "train",
        "noise": NOISE_RULE,
    }


def teacher_source(teacher: TrainedModel) -> Manifest:
    """The teacher's training dataset, where its checkpoint says it was read, with the id it was trained on."""
    location = teacher.data.get("location")
    if not location:
        raise PairSetError(f"{teacher.checkpoint}: the checkpoint records no dataset location to take captions from")
    manifest = open_manifest(location)
    if manifest.dataset_id != teacher.dataset_id:
        raise PairSetError(f"{location}: holds dataset {manifest.dataset_id}, but the teacher {teacher.checkpoint} was "
                           f"trained on {teacher.dataset_id}: rebuild or restore the teacher's dataset there")
    return manifest


def plan_pairs(source: Manifest, settings: DistillConfig, max_length: int, backend: str = "webdataset"
               ) -> list[PlannedPair]:
    """Every pair, in order, ``pairs_per_caption`` per caption: the split's captions (records in manifest order,
    their captions in order) once per repeat (``distill.pair_order=interleaved``), or each caption's repeats together
    (``grouped``). A caption's length is its span's, at most ``max_length`` (the frames the teacher samples: its
    window)."""
    captions = [(record_index, record.id, caption, min(int(end - start), max_length))
                for record_index, record in enumerate(iter_motions(source, "train", backend))
                for caption, (start, end) in enumerate(record.spans.tolist())]
    repeats = range(settings.pairs_per_caption)
    order = ([(caption, repeat) for caption in captions for repeat in repeats] if settings.pair_order == "grouped"
             else [(caption, repeat) for repeat in repeats for caption in captions])
    return [PlannedPair(index, record_index, record_id, caption, repeat, length, sample_seed(settings.seed, index))
            for index, ((record_index, record_id, caption, length), repeat) in enumerate(order)]


def stream_records(source: Manifest, backend: str = "webdataset") -> Iterator[tuple[int, MotionRecord]]:
    """The training split's records with their positions, in manifest order (one pass; nothing kept)."""
    return enumerate(iter_motions(source, "train", backend))


class RecordWindow:
    """The records a run of pairs needs, read from passes over the split: asked for a run of pairs, it reads up to
    their last record and keeps only the records they use, so memory holds one chunk's records. A run that needs a
    record this pass has gone by starts a new pass (``open_records`` again): interleaved pairs come back to the
    split's first records once per repeat."""

    def __init__(self, open_records: Callable[[], Iterator[tuple[int, MotionRecord]]]) -> None:
        self._open = open_records
        self._records = open_records()
        self._last: tuple[int, MotionRecord] | None = None  # the newest record read: the next run may start on it
        self.passes = 1

    def take(self, pairs: Sequence[PlannedPair]) -> dict[int, MotionRecord]:
        """The records of ``pairs`` by position."""
        wanted = {p.record_index for p in pairs}
        if self._last is not None and min(wanted) < self._last[0]:
            self._records, self._last = self._open(), None
            self.passes += 1
        found: dict[int, MotionRecord] = {}
        if self._last is not None and self._last[0] in wanted:
            found[self._last[0]] = self._last[1]
        last = max(wanted)
        while len(found) < len(wanted):
            self._last = next(self._records, None)
            if self._last is None or self._last[0] > last:  # the split ended, or passed them: they are not in it
                raise PairSetError(f"records {sorted(wanted - set(found))} of the pairs are not in the split (it "
                                   "changed while the pairs were made)")
            position, record = self._last
            if position in wanted:
                found[position] = record
        return found


@torch.no_grad()
def solve_pairs(teacher: TrainedModel, pairs: Sequence[PlannedPair], records: Mapping[int, MotionRecord],
                settings: DistillConfig, noise: torch.Tensor | None = None) -> torch.Tensor:
    """The teacher's (B, T, D) normalised ODE solutions of ``pairs`` (one batch; ``records`` holds their records by
    position), zero past each length; from ``noise`` (B, T, D) instead of the pairs' seeded noise if given."""
    device = teacher.device
    lengths = torch.tensor([p.length for p in pairs], dtype=torch.long, device=device)
    rows = [(records[p.record_index], p.caption) for p in pairs]
    cond = torch.from_numpy(np.stack([record.text_emb[caption] for record, caption in rows])).to(device)
    extras: dict[str, torch.Tensor] = {}
    if teacher.model_config.conditioning == "cross_attention":
        extras = {"text_tokens": torch.from_numpy(np.stack([record.text_tokens[caption]
                                                            for record, caption in rows])).to(device),
                  "text_token_len": torch.tensor([int(record.text_token_len[caption]) for record, caption in rows],
                                                 dtype=torch.long, device=device)}
    model = conditioned_model(teacher, PromptConditions(cond, extras))
    result = sample(model, cond, lengths, num_frames=int(lengths.max()), feature_dim=teacher.model_config.feature_dim,
                    solver=settings.teacher_solver, steps=settings.teacher_steps,
                    grid=step_grid(settings.teacher_steps, teacher.model_config.sampling_times),
                    guidance=settings.teacher_guidance,
                    conditional_channels=guided_feature_mask(settings.teacher_guided_features, teacher.skeleton),
                    generator=seeded_generators([p.seed for p in pairs]), noise=noise)
    return result.x1.float()


def probe_indices(pairs: Sequence[PlannedPair], count: int) -> set[int]:
    """The pairs :func:`probe_amplification` measures: the first pair (``repeat`` 0) of ``count`` captions spread
    evenly over the split (all captions if it has fewer)."""
    firsts = [p.index for p in pairs if p.repeat == 0]
    if count <= 0 or not firsts:
        return set()
    picks = np.unique(np.round(np.linspace(0, len(firsts) - 1, min(count, len(firsts)))).astype(int))
    return {firsts[i] for i in picks}


@torch.no_grad()
def probe_amplification(teacher: TrainedModel, pairs: Sequence[PlannedPair], records: Mapping[int, MotionRecord],
                        settings: DistillConfig) -> dict[int, float]:
    """By pair index: how far the teacher's solution of each pair moves per unit change of its noise
    (:func:`mfm.solvers.flow_map_amplification`, one batch). The direction is the next draw of the pair's own noise
    generator, so the figure is a function of the pair alone."""
    device, dim = teacher.device, teacher.model_config.feature_dim
    lengths = torch.tensor([p.length for p in pairs], dtype=torch.long)
    shape = (len(pairs), int(lengths.max()), dim)
    generators = seeded_generators([p.seed for p in pairs])
    x0 = draw_noise(shape, generators, lengths=lengths, device=device)
    direction = draw_noise(shape, generators, lengths=lengths, device=device)
    amplification = flow_map_amplification(lambda noise: solve_pairs(teacher, pairs, records, settings, noise),
                                           x0, direction, lengths.to(device))
    return {p.index: float(a) for p, a in zip(pairs, amplification.tolist())}


def flow_map_summary(amplification: Mapping[int, float]) -> dict[str, Any] | None:
    """The pair set manifest's ``teacher_flow_map`` section (None when nothing was probed)."""
    if not amplification:
        return None
    values = np.array(list(amplification.values()), dtype=np.float64)
    return {"probes": len(values), "perturbation_rms": FLOW_MAP_PERTURBATION,
            "amplification_median": float(np.median(values)), "amplification_max": float(values.max()),
            "by_pair": {str(k): float(v) for k, v in sorted(amplification.items())}}


def report_flow_map(summary: Mapping[str, Any] | None) -> None:
    """Log the teacher's flow-map amplification; a warning when reflow cannot fit it
    (:data:`mfm.solvers.ROUGH_AMPLIFICATION`)."""
    if summary is None:
        return
    median, most, probes = summary["amplification_median"], summary["amplification_max"], summary["probes"]
    if median > ROUGH_AMPLIFICATION:
        logger.warning(
            "the teacher's flow map is rough: a noise change moves its motion %.3g-fold (median of %d probes, "
            "max %.3g; above %g). Reflow's pairs are then not a smooth function of the noise, and a 1-2 step "
            "student learns their average: expect a high distillation loss and blurred motion (docs/few-step.md, "
            "'A rough teacher')", median, probes, most, ROUGH_AMPLIFICATION)
    else:
        logger.info("teacher flow-map amplification %.3g (median of %d probes, max %.3g)", median, probes, most)


def _existing(folder: Path, wanted: Mapping[str, Any]) -> bool:
    """True when ``folder`` holds a complete pair set made as ``wanted`` says; an unfinished one is removed."""
    if not (folder / MANIFEST_NAME).is_file():
        if folder.exists():
            logger.info("removing the unfinished pair set in %s (no manifest): making it again", folder)
            shutil.rmtree(folder)
        return False
    manifest = load_manifest(folder, verify="size")
    found = manifest.get(PAIRS_KEY)
    if found is not None:
        found = {"order": "grouped", **found}  # a set made before distill.pair_order holds its pairs grouped
        if found.get("pairs_per_caption") == wanted.get("pairs_per_caption") == 1:
            found["order"] = wanted["order"]  # one pair per caption: both orders are the same pairs
    if found != dict(wanted):
        differing = sorted(k for k in set(wanted) | set(found or {}) if (found or {}).get(k) != wanted.get(k))
        hint = (f"; its pairs are {found['order']}: distill.pair_order={found['order']} reuses them"
                if found and "order" in differing else "")
        raise PairSetError(f"{folder / MANIFEST_NAME}: a pair set made with other settings ({', '.join(differing)} "
                           f"differ): give another --out for this teacher or these settings{hint}")
    return True


def make_pairs(teacher: TrainedModel, settings: DistillConfig, out_dir: str | Path, dist: Dist) -> Path:
    """Make (or reuse) the pair set in ``<out_dir>/pairs``; returns its manifest's path. A collective: every rank
    calls it; rank 0 decides whether to reuse and writes the shards and the manifest."""
    if teacher.objective != "flow":
        raise PairSetError(f"{teacher.checkpoint} is a diffusion model: reflow distils a flow-matching teacher's ODE")
    folder = pairs_dir(out_dir)
    source = teacher_source(teacher)
    wanted = pair_settings(teacher, settings, source)
    reuse = dist.broadcast_object(_existing(folder, wanted) if dist.is_main else None)
    if reuse:
        dist.log0("reusing the pair set in %s (same teacher and settings)", folder)
        if dist.is_main:
            report_flow_map(load_manifest(folder, verify="size").get(FLOW_MAP_KEY))
        return folder / MANIFEST_NAME
    pairs = plan_pairs(source, settings, wanted["max_length"])
    probes = probe_indices(pairs, settings.flow_map_probes)
    amplification: dict[int, float] = {}
    tmp = folder / TMP_FOLDER
    if dist.is_main:
        tmp.mkdir(parents=True, exist_ok=True)
    dist.barrier()
    mine = pairs[dist.rank::dist.world_size]
    size = chunk_size(settings)
    window = RecordWindow(partial(stream_records, source))
    for chunk_index, start in enumerate(range(0, len(mine), size)):
        chunk = mine[start:start + size]
        records = window.take(chunk)
        solved: dict[int, np.ndarray] = {}
        ordered = sorted(chunk, key=lambda p: (-p.length, p.index))  # longest first within the chunk
        for first in range(0, len(ordered), settings.batch_size):
            batch = ordered[first:first + settings.batch_size]
            motions = teacher.denormalize(solve_pairs(teacher, batch, records, settings)).cpu().numpy()
            for row, pair in enumerate(batch):
                solved[pair.index] = np.ascontiguousarray(motions[row, :pair.length], dtype=np.float32)
        probed = [p for p in chunk if p.index in probes]
        if probed:
            amplification.update(probe_amplification(teacher, probed, records, settings))
        torch.save(solved, chunk_path(tmp, dist.rank, chunk_index))
        dist.log0("teacher pairs: %d of %d on rank 0", start + len(chunk), len(mine))
    gathered = dist.all_gather_object(amplification)
    if dist.is_main:
        summary = flow_map_summary({k: v for part in gathered for k, v in part.items()})
        report_flow_map(summary)
        write_pair_set(folder, teacher, source, pairs, SolvedChunks(tmp, dist.world_size, size), wanted, summary)
        shutil.rmtree(tmp)
    dist.barrier()
    return folder / MANIFEST_NAME


def write_pair_set(folder: Path, teacher: TrainedModel, source: Manifest, pairs: Sequence[PlannedPair],
                   solved: Mapping[int, np.ndarray], settings: Mapping[str, Any],
                   flow_map: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The shards (in pair order) and, last, the manifest of the pair set; the records' captions and text features
    streamed from ``source`` again, the motions read from ``solved`` one at a time. ``flow_map``: the teacher's
    probed amplification (:func:`flow_map_summary`), kept beside the pairs' settings, not part of their identity."""
    text = source.data["text_encoder"]
    tokens = bool(text.get("token_features", False))
    spec = source.data["feature_spec"]
    schema = parquet_schema(int(spec["dim"]), int(text["dim"]), tokens, noise_seeds=True)
    shard_size = max(1, min(MAX_SHARD_SIZE, math.ceil(len(pairs) / MIN_SHARDS)))
    writer = SplitShardWriter(folder, "train", shard_size=shard_size, formats=("tar", "parquet"), schema=schema)
    window = RecordWindow(partial(stream_records, source))
    for pair in pairs:
        record = window.take([pair])[pair.record_index]
        motion = solved[pair.index]
        caption = RecordCaption(record.captions[pair.caption], tuple(record.caption_tokens[pair.caption]), 0,
                                pair.length)
        writer.write(
            Record(id=pair.pair_id, split="train", source="reflow", skeleton=spec["skeleton"], fps=float(spec["fps"]),
                   features=motion, captions=[caption], action=record.action, noise_seed=pair.seed),
            TextFeatures(record.text_emb[pair.caption:pair.caption + 1],
                         None if not tokens else record.text_tokens[pair.caption:pair.caption + 1],
                         None if not tokens else record.text_token_len[pair.caption:pair.caption + 1]))
    shards = writer.close()
    manifest = {
        "format_version": FORMAT_VERSION,
        "dataset_id": "",
        "builder": {"command": "python launch/distill.py", "version": source.data["builder"].get("version"),
                    "options": {"teacher": ckpt.run_dir_of(teacher.checkpoint).name, **settings,
                                # where the teacher's dataset was read (the evaluator's default test data for a
                                # student); not part of the pairs' identity, so a moved dataset keeps its pairs
                                "source_manifest": str(source.location)}},
        "feature_spec": spec,
        "normalization": teacher.data["normalization"],
        "text_encoder": text,
        "action_classes": list(source.action_classes),
        "splits": {"train": {
            "num_motions": len(pairs), "num_captions": len(pairs), "num_frames": sum(p.length for p in pairs),
            "lengths": [p.length for p in pairs],
            "shards": [s.to_json() for s in shards["tar"]], "parquet": [s.to_json() for s in shards["parquet"]]}},
        "skip_report": {"total": 0, "by_reason": {}, "items": [], "dropped_captions": {},
                        "ignored_files": {"count": 0, "paths": []}},
        PAIRS_KEY: dict(settings),
    }
    if flow_map is not None:
        manifest[FLOW_MAP_KEY] = dict(flow_map)
    manifest["dataset_id"] = derive_dataset_id(manifest)
    write_manifest(folder, manifest)
    logger.info("wrote %d teacher pairs to %s", len(pairs), folder)
    return manifest


def chunk_size(settings: DistillConfig) -> int:
    """Pairs a rank solves (and holds) at a time: :data:`CHUNK_BATCHES` teacher batches."""
    return settings.batch_size * CHUNK_BATCHES


def chunk_path(tmp: Path, rank: int, chunk: int) -> Path:
    return tmp / f"rank-{rank}-chunk-{chunk:06d}.pt"


class SolvedChunks(Mapping[int, np.ndarray]):
    """The ranks' solved motions by pair index, read from their chunk files as the writer asks for them in pair
    order (pair i is rank i mod W's, in its chunk (i div W) div ``size``): one chunk per rank in memory."""

    def __init__(self, tmp: Path, world_size: int, size: int) -> None:
        self.tmp, self.world_size, self.size = tmp, world_size, size
        self._held: dict[int, tuple[int, dict[int, np.ndarray]]] = {}

    def __getitem__(self, index: int) -> np.ndarray:
        rank, chunk = index % self.world_size, (index // self.world_size) // self.size
        if self._held.get(rank, (None,))[0] != chunk:
            self._held[rank] = (chunk, torch.load(chunk_path(self.tmp, rank, chunk), weights_only=False))
        return self._held[rank][1][index]

    def __iter__(self) -> Iterator[int]:
        raise TypeError("SolvedChunks is read by pair index only")

    def __len__(self) -> int:
        raise TypeError("SolvedChunks is read by pair index only")
