"""The evaluation job (launch/evaluate.py): score committed checkpoints once each, from any number of jobs.

One *unit* of work is a checkpoint at one sampling point (solver, steps, guidance) with fixed settings::

    claim (store) -> load the model (EMA weights) -> the test split, verified and read once (spaces)
      -> R replications (replications), each: its ground-truth items (re-drawn captions and crops, or the
         fixed set) and their evaluator embeddings (cached on disk per evaluator and set) -> generate for those
         items with the sampling code -> embeddings / joints -> metrics
      -> mean ± 95 % CI -> result JSON + table rows (store) -> W&B under the training run, plots (plots)

Protocol (text-to-motion, Guo et al. / MDM / MFM): FID against the whole ground-truth set, R-precision top-1/2/3
among batches of 32, MM-Dist, Diversity (300 pairs), MultiModality (30 generations per text, 10 pairs, 100
texts), 20 replications (``full``) or 3 (``fast``), mean ± 1.96·std/√R, plus the ground-truth row. As the
reference's shuffled loader, every replication draws its own ground-truth items (``protocol.redraw_items``, the
default): each test motion's caption and crop, seeded by (protocol seed, replication); the replication generates
for those captions and lengths and scores against those clips (FID's μ and Σ, the ground-truth row, MultiModality
texts, edits, the FLAME-paper metrics), so the intervals of both rows include that spread (``protocol.intervals``).
``redraw_items=false`` keeps one fixed set for every replication (noise-only intervals). A test set too
small for a constant (32, 300, 100) uses a smaller value, recorded with a note under ``protocol``; never silently.
The ground-truth row's FID is that of a bootstrap resample of the replication's ground truth against the whole of
it: the sampling-noise floor (the reference's GT FID is likewise nonzero, its crops and captions being re-drawn). Also:
editing (prediction, in-between, upper body: FID, Diversity, and ADE/FDE on joints in metres, our definition: MFM's
Table 3 names them but its public code has no formula), the metrics FLAME's paper reports
(APE/AVE in TEMOS's definition, not FLAME's code's: mfm.metrics.ape_ave; mCLIP, MID, per-text joint variance), and
for action models FID / accuracy / Diversity /
MultiModality in the action classifier's feature space. NFE and generation seconds per motion are reported.
A diffusion baseline (FLAME) samples as its authors did unless ``sampling.baseline_*`` says otherwise: guidance 8.0,
σ = 1 output smoothing, every one of its 1,000 training steps, its x0 clamp carried to our features, its EMA weights
(a checkpoint without them is refused); every diffusion checkpoint's edits follow FLAME's procedure, the source's
root translation copied into the output (``tasks.edit_reference_translation``); results record them
(``sampling.baseline_defaults``, ``editing_settings.reference_translation``).
Plausibility (mfm.metrics.plausibility, on joints recovered from the features): bone-length range and relative
deviation, floor penetration, foot skating ratio / contact and skating foot speeds, mean jerk and its ratio to the
paired ground-truth clip's, as medians over the clips of a replication, for generated and edited motions (metric
names as the PlausibilityFigures fields) and for the ground truth (per ground-truth set, rank 0).
``--protocol mdm`` (configs/eval_mdm.yaml) runs the MDM/MFM reference loop instead, rule by rule (ProtocolConfig's
rules: 1,024 motions in whole batches, three independent ground-truth passes per replication so that the GT row's FID
is that of two draws, caption length 22 for the generated row, the sampler's 196-frame window seen by the evaluator,
MultiModality in the model's normalisation over 5 replications); results record the loop ('ours', 'mdm', 'mixed').
It samples at MFM's paper point (``protocol.sampling_point=paper``: 10 Euler steps) or its released code's
(``released``: 100 steps, 50 on KIT) instead of the sampling sweep; results record which (``sampling_point``).
With ``tasks.composition=true`` (a bpe + pccat model), FlowMDM's composition protocol adds one unit per sampling
point and ``composition.switch`` point (pipeline.evaluation.composition); ``tasks.text_to_motion=false`` runs only those.

Identity. A unit's key hashes the checkpoint id (its COMPLETE marker, which lists every file's sha256), the
evaluator id, the ground-truth identity (dataset id, split, crops; with the protocol's seed and redraw_items, every
replication's draw), the protocol, tasks and sampling point, and for a diffusion baseline its authors' sampling
settings as run (FLAME: steps, x0 clamp, smoothing; sampling.baseline_*) and its edits' translation copy
(``checkpoint_settings``); the
result and every table row carry the evaluator id and the dataset id, so numbers from different evaluators are
never mixed up. Re-running on the same checkpoint finds the result and skips it. The dataset id is the one derived
from the manifest's shard list when it is read (never the one written in it); a job whose test set (that id and the
split) differs from the run's earlier results is refused before anything is evaluated unless
``data.allow_other_test_set`` (:meth:`EvaluationJob._test_set_change`), and a table never takes a second test set.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections import defaultdict
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mfm.compilation import compiles
from mfm.solvers import noise_generator_device, step_grid
from pipeline import checkpoint as ckpt
from pipeline.config import ConfigError, parse_yaml, to_dict, wandb_mode
from pipeline.data.stream import (
    Manifest,
    ManifestError,
    backend_for_format,
    open_manifest,
)
from pipeline.distributed import Dist
from pipeline.evaluation.composition import (
    CompositionContext,
    composition_rows,
    composition_unit,
    evaluate_switch,
    prepare_composition,
)
from pipeline.evaluation.config import (
    OUR_RULES,
    SAMPLING_POINT_SOURCES,
    EvalConfig,
    SamplingPoint,
)
from pipeline.evaluation.replications import (
    CheckpointContext,
    GroundTruthDraws,
    PhaseTimer,
    PointRun,
    action_labels,
    baseline_sampling,
    check_weights,
    guided_features,
    output_smoothing,
    plan_protocol,
    points_for,
    sampling_precision,
    smoothing_keeps_bones,
)
from pipeline.evaluation.spaces import (
    CLASSIFIER_FILE,
    EVALUATOR_FILE,
    ClassifierSpace,
    ContrastiveSpace,
    EmbeddingSpace,
    EvaluationError,
    EvaluatorUnavailable,
    T2MSpace,
    digest,
    read_ground_truth_pool,
    resolve_evaluator_file,
)
from pipeline.evaluation.store import (
    ClaimHolder,
    EvalFolderError,
    ResultsStore,
    ScoredData,
    SeenCheckpoint,
    Unit,
    check_eval_folder,
    log_to_wandb,
)
from pipeline.generation.inference import (
    TrainedModel,
    load_trained_model,
    resolve_checkpoint,
)

logger = logging.getLogger(__name__)

RESULT_FORMAT = 1


class ChangedTestSetError(EvaluationError):
    """This job's test set (dataset id, split) is not the one the run's earlier results (or its evaluation folder's
    table) are on: refused before anything is evaluated (``data.allow_other_test_set``)."""


EXIT_ALL_DONE = 0
"""Every unit this job was given is evaluated (by this job or earlier by another)."""
EXIT_HELD_BY_OTHERS = 3
"""Some units were skipped because other live jobs hold their claims and had not finished them when this job
ended: run again later (distinct from 'all done', so a scheduler can tell nothing was lost)."""


# ---------------------------------------------------------------------------------------------------------------
# One checkpoint: context shared by its sampling points
# ---------------------------------------------------------------------------------------------------------------


def checkpoint_id(folder: Path) -> str:
    """sha256 of the COMPLETE marker, which lists every file's sha256: a re-saved checkpoint gets a new id (the id
    training lists in checkpoints/saved.jsonl)."""
    return ckpt.checkpoint_id(ckpt.read_marker(folder))


def solver_grid(steps: int, trained: TrainedModel) -> list[float] | None:
    """The fixed-step solver's time grid at ``steps`` steps as results record it: None for the uniform grid, else
    the model's own (``ModelConfig.sampling_times``, :func:`mfm.solvers.step_grid`)."""
    grid = step_grid(steps, trained.model_config.sampling_times)
    return None if grid is None else grid.tolist()


def baseline_record(trained: TrainedModel, sampling: Any) -> dict[str, Any]:
    """What a result says about the output smoothing and whose sampling settings ran (a baseline's own, as run:
    guidance, smoothing, every training step, x0 clamp, EMA weights, and where the numbers come from; or ours)."""
    return {"smoothing_sigma": output_smoothing(trained, sampling),
            "smoothing_keeps_bones": smoothing_keeps_bones(trained, sampling),
            "baseline_defaults": trained.baseline_record(baseline_sampling(trained, sampling)),
            "guided_features": guided_features(trained, sampling)}


ADE_FDE_UNIT = "m"
"""Hashed into the keys of editing units of a skeleton not in metres (KIT): ADE/FDE are in metres since issue 25
(before, in the skeleton's millimetres), so results computed before are not taken as done."""


def checkpoint_settings(trained: TrainedModel, cfg: EvalConfig) -> dict[str, Any]:
    """The settings whose effect depends on the kind of checkpoint, as they run; only its units' keys carry them, so
    the others' keys stay as they were: a diffusion checkpoint's baseline sampling settings (FLAME's) and, when it
    edits, its edits' translation copy (``tasks.edit_reference_translation``); on a skeleton not in metres (KIT),
    when it edits, the unit of ADE/FDE. Empty for a flow checkpoint on a metre skeleton."""
    out: dict[str, Any] = {}
    if trained.objective == "diffusion":
        baseline = baseline_sampling(trained, cfg.sampling)
        if baseline is not None:  # the settings, not the text citing where they come from
            out["baseline"] = {k: v for k, v in baseline.record().items() if k != "source"}
        if cfg.tasks.editing:
            out["edit_reference_translation"] = cfg.tasks.edit_reference_translation
    if cfg.tasks.editing and trained.skeleton.unit != "m":
        out["ade_fde_unit"] = ADE_FDE_UNIT
    return out


def check_compatible(trained: TrainedModel, manifest: Manifest) -> None:
    """Refuse a checkpoint whose features or text conditions differ from the evaluation data's."""
    mine, theirs = trained.data["feature_spec"], manifest.data["feature_spec"]
    for key in ("representation", "skeleton", "dim", "fps"):
        if mine.get(key) != theirs.get(key):
            raise EvaluationError(f"{trained.checkpoint} was trained on {key}={mine.get(key)!r} features, the "
                                  f"evaluation data {manifest.location} has {theirs.get(key)!r}")
    if not trained.model_config.is_action_model:
        a, b = trained.data["text_encoder"], manifest.data["text_encoder"]
        if (a.get("id"), a.get("weights_sha256"), a.get("dim")) != (b.get("id"), b.get("weights_sha256"), b.get("dim")):
            raise EvaluationError(f"{trained.checkpoint} was conditioned on text encoder {a.get('id')} "
                                  f"({str(a.get('weights_sha256'))[:12]}), the evaluation data's captions were "
                                  f"encoded with {b.get('id')} ({str(b.get('weights_sha256'))[:12]})")
    if trained.dataset_id != manifest.dataset_id:
        logger.warning("%s was trained on dataset %s; evaluating on %s (%s)", trained.checkpoint,
                       trained.dataset_id[:16], manifest.dataset_id[:16], manifest.location)


class CheckpointScorer:
    """Builds a checkpoint's context (model, data, evaluator, ground truth; the latter two kept across checkpoints)
    and runs the replications of a sampling point."""

    def __init__(self, cfg: EvalConfig, dist: Dist) -> None:
        self.cfg, self.dist = cfg, dist
        self._spaces: dict[tuple, Any] = {}
        self._gt: dict[tuple, tuple] = {}

    # -- building blocks -------------------------------------------------------------------------------------

    def manifest_for(self, trained: TrainedModel) -> Manifest:
        location = self.cfg.data.manifest or trained.data.get("location", "")
        if not location:
            raise EvaluationError(f"{trained.checkpoint} records no dataset location: set data.manifest=")
        manifest = self._open_evaluation_data(location)
        source = manifest.pair_set_source
        if not self.cfg.data.manifest and source:
            # A few-step student (launch/distill.py) trained on its teacher's pair set, which has no test split: its
            # test data is the teacher's dataset's, where the pair set says it was read.
            logger.info("%s trained on the pair set %s: evaluating on its teacher's dataset %s", trained.checkpoint,
                        location, source)
            manifest = self._open_evaluation_data(source)
        return manifest

    def _open_evaluation_data(self, location: str) -> Manifest:
        try:
            return open_manifest(location, allow_external_shards=self.cfg.data.allow_external_shards)
        except FileNotFoundError as exc:
            raise EvaluationError(f"evaluation data {location} not found ({exc}); set data.manifest=") from exc
        except ManifestError as exc:
            raise EvaluationError(str(exc)) from exc

    def space_for(self, trained: TrainedModel, manifest: Manifest) -> EmbeddingSpace:
        """The metric space: the action classifier for action models, else the configured evaluator."""
        ev = self.cfg.evaluator
        key = (trained.model_config.is_action_model, manifest.dataset_id, trained.data["feature_spec"]["skeleton"])
        if key not in self._spaces:
            if trained.model_config.is_action_model:
                path = resolve_evaluator_file(ev.action_classifier or "auto", manifest, CLASSIFIER_FILE,
                                               required=True)
                space: Any = ClassifierSpace(path, manifest, self.dist.device)
            elif ev.kind == "t2m":
                space = T2MSpace(ev, trained.data["feature_spec"]["skeleton"], self.dist.device)
            else:
                path = resolve_evaluator_file(ev.path, manifest, EVALUATOR_FILE, required=True)
                space = ContrastiveSpace(path, manifest, self.dist.device)
            self._spaces[key] = space
        return self._spaces[key]

    def context(self, folder: Path, cache_dir: Path, timer: PhaseTimer) -> CheckpointContext:
        with timer.phase("load"):
            trained = load_trained_model(folder, use_ema=self.cfg.sampling.use_ema, device=self.dist.device)
            trained = trained.compiled_with(self.cfg.sampling.compile)  # once per checkpoint, for every replication
            try:  # protocol.sampling_point: a named point (its steps follow the skeleton) or the sweep
                wanted = self.cfg.sampling_points(trained.skeleton.name)
            except ConfigError as exc:
                raise EvaluationError(f"{trained.checkpoint}: {exc}") from exc
            points = points_for(trained, wanted, self.cfg.sampling)
            check_weights(trained, self.cfg.sampling)
            manifest = self.manifest_for(trained)
            check_compatible(trained, manifest)
            space = self.space_for(trained, manifest)
        p, data = self.cfg.protocol, self.cfg.data
        is_action = trained.model_config.is_action_model
        tokens = not is_action and trained.model_config.conditioning == "cross_attention"
        key = (manifest.dataset_id, data.split, space.evaluator_id, is_action, tokens)
        if key not in self._gt:
            with timer.phase("ground_truth"):
                pool = read_ground_truth_pool(manifest, data.split, max_length=p.max_length,
                                              unit_length=p.unit_length, seed=p.seed,
                                              backend=backend_for_format(data.format), require_action=is_action,
                                              token_features=tokens, test_items=p.test_items)
            self._gt[key] = GroundTruthDraws(pool, space, trained.skeleton, p.redraw_items,
                                             self.cfg.sampling.batch_size,
                                             padded_text=p.generated_caption_length == "padded")
        draws = self._gt[key]
        gt, emb, cached, gt_figures = draws.fixed, None, False, None
        if not p.redraw_items or self.cfg.tasks.composition:  # something scores against the fixed set
            with timer.phase("ground_truth"):
                fixed = draws.fixed_truth(self.dist, cache_dir)
            emb, cached, gt_figures = fixed.emb, fixed.from_cache, fixed.plausibility
        limit = _max_generation_length(trained)
        if int(gt.lengths.max()) > limit:
            raise EvaluationError(f"test clips reach {int(gt.lengths.max())} frames but {trained.checkpoint} "
                                  f"generates at most {limit}: set protocol.max_length={limit}")
        if p.generated_padding == "model" and p.max_length > limit:
            raise EvaluationError(f"protocol.generated_padding=model samples {p.max_length}-frame windows but "
                                  f"{trained.checkpoint} generates at most {limit} frames: set "
                                  f"protocol.max_length={limit} or protocol.generated_padding=zero")
        notes = []
        if int(gt.lengths.max()) > trained.window:
            notes.append(f"test clips reach {int(gt.lengths.max())} frames; the model trained on windows of "
                         f"{trained.window}")
            logger.warning("%s: %s", trained.checkpoint, notes[-1])
        notes += _rules_without_effect(self.cfg, space, is_action)
        labels, candidates = None, np.arange(len(gt))
        if is_action:
            labels, candidates = action_labels(trained, space, gt, p.seed)
        plan = plan_protocol(self.cfg, len(gt), len(candidates))
        return CheckpointContext(trained, checkpoint_id(folder), manifest, gt, space, emb, cached, plan, labels,
                                 candidates, points, tuple(notes), gt_figures, draws, cache_dir)

    def unit_for(self, folder: Path, ctx_ids: Mapping[str, str], point: SamplingPoint,
                 kind_settings: Mapping[str, Any] | None = None) -> Unit:
        """The unit of a text-to-motion point; ``kind_settings``: the settings only its kind of checkpoint runs
        (:func:`checkpoint_settings`), which its key then carries."""
        cfg = self.cfg
        # The task switches are not settings of a text-to-motion unit: turning composition on keeps its key; nor is
        # a setting only diffusion edits read (kind_settings carries it for them): flow units keep their keys.
        tasks = {k: v for k, v in to_dict(cfg.tasks).items()
                 if k not in ("text_to_motion", "composition", "edit_reference_translation")}
        # The editing passes at their default (one per replication, no single-pass size) score as before the
        # setting existed: earlier results keep their keys.
        if tasks.get("editing_passes") == "per_replication":
            tasks.pop("editing_passes")
        if tasks.get("editing_samples") is None:
            tasks.pop("editing_samples", None)
        settings = {"format": RESULT_FORMAT, "ids": dict(ctx_ids), "point": dataclasses.asdict(point),
                    "protocol": protocol_key(cfg.protocol), "tasks": tasks, "split": cfg.data.split,
                    "sampling": {"use_ema": cfg.sampling.use_ema, "rtol": cfg.sampling.rtol,
                                 "atol": cfg.sampling.atol}}
        # fp32, the arithmetic of every earlier result, keeps their keys; bf16 (asked, or auto on a bf16 GPU) adds it
        if cfg.sampling.precision != "fp32" and sampling_precision(cfg.sampling, self.dist.device) != "fp32":
            settings["sampling"]["precision"] = "bf16"
        # uncompiled, every earlier result's way, adds nothing; compiling (true, or auto on CUDA) adds it
        if cfg.sampling.compile is not False and compiles(cfg.sampling.compile, self.dist.device):
            settings["sampling"]["compile"] = True
        # CPU noise, every earlier result's, adds nothing; noise drawn on a device other than the CPU adds it
        if (cfg.sampling.noise_device != "cpu"
                and noise_generator_device(cfg.sampling.noise_device, self.dist.device).type != "cpu"):
            settings["sampling"]["noise_device"] = str(self.dist.device.type)
        setup = cfg.tasks.edit_setup()
        own_steps = {p: setup["steps_per_preset"][p] for p in cfg.tasks.editing
                     if setup["steps_per_preset"][p] != setup["steps"]}
        if cfg.sampling.output_smoothing is not None:  # unset: the checkpoint's own, as keys were before it existed
            settings["sampling"]["output_smoothing"] = cfg.sampling.output_smoothing
        if cfg.sampling.output_smoothing_keeps_bones is not None:  # unset: the checkpoint's own, keys as before
            settings["sampling"]["output_smoothing_keeps_bones"] = cfg.sampling.output_smoothing_keeps_bones
        if cfg.sampling.guided_features is not None:  # unset: the checkpoint's own, as keys were before it existed
            settings["sampling"]["guided_features"] = cfg.sampling.guided_features
        if own_steps:  # a preset with its own step count (reference-debug's interpolation: 1 since issue 25)
            settings["edit_steps_per_preset"] = own_steps
        if kind_settings:  # settings of its kind of checkpoint change its numbers (only its units' keys carry them)
            settings["checkpoint_kind"] = dict(kind_settings)
        if tasks.get("flame"):
            # Issue 25 changed APE/AVE (TEMOS's floor in millimetres, every skeleton in metres): results computed
            # before carry the metre-floor bias, so units with the FLAME-paper metrics get new keys and run again.
            settings["ape_ave"] = APE_AVE_REVISION
        return Unit(folder.name, point.name, digest(settings))

    # -- evaluating one unit -------------------------------------------------------------------------------------

    def work(self, folder: Path, ctx: CheckpointContext, comp: CompositionContext | None) -> list[Work]:
        """The checkpoint's units: text-to-motion per sampling point, then composition per point and switch."""
        ids = {"checkpoint": ctx.checkpoint_id, "evaluator": ctx.space.evaluator_id, "gt": ctx.gt.key}
        points = ctx.points
        for point in points:  # before any unit is claimed: a student guided at the protocol's 2.5 would score noise
            if (reason := ctx.trained.unguidable_reason(point.guidance)) is not None:
                raise EvaluationError(f"{reason} (--guidance 1)")
            try:  # a shortcut model: an untrained step count, or guidance over its built-in guidance
                ctx.trained.shortcut_step_size(point.solver, point.steps, point.guidance)
            except ValueError as err:
                raise EvaluationError(f"sampling point {point.name}: {err}") from None
        out = []
        if self.cfg.tasks.text_to_motion:
            kind = checkpoint_settings(ctx.trained, self.cfg)
            out += [Work(self.unit_for(folder, ids, point, kind), point) for point in points]
        if comp is not None:
            precision = sampling_precision(self.cfg.sampling, self.dist.device)
            out += [Work(composition_unit(folder.name, ids, point, switch, self.cfg, comp.cset, precision), point,
                         switch)
                    for point in points for switch in self.cfg.composition.switch_times()]
        return out

    def evaluate(self, ctx: CheckpointContext, comp: CompositionContext | None, work: Work, timer: PhaseTimer,
                 heartbeat: Callable[[], None] = lambda: None) -> dict[str, Any] | None:
        if work.switch is None:
            return self.evaluate_point(ctx, work.point, timer, heartbeat)
        return evaluate_switch(self.cfg, self.dist, ctx, comp, work.point, work.switch, timer, heartbeat)

    def evaluate_point(self, ctx: CheckpointContext, point: SamplingPoint, timer: PhaseTimer,
                       heartbeat: Callable[[], None] = lambda: None) -> dict[str, Any] | None:
        """All replications of one sampling point; the result dict on rank 0, None elsewhere."""
        run = PointRun(self.cfg, self.dist, ctx, point, timer)
        for replication in range(ctx.plan.replications):
            run.replicate(replication)
            if self.dist.is_main:
                heartbeat()
        return run.result() if self.dist.is_main else None


@dataclasses.dataclass(frozen=True)
class Work:
    """A unit and what it evaluates: a sampling point, and a switch flow time for composition units."""

    unit: Unit
    point: SamplingPoint
    switch: float | None = None


APE_AVE_REVISION = "temos-floor-mm"
"""Hashed into the key of units that compute APE/AVE (``tasks.flame``): which definition their numbers have."""


def sampling_point_record(cfg: EvalConfig) -> dict[str, Any]:
    """What a result says about where it sampled: ``sampling_point`` (sweep, paper or released) and, for a named
    point, where its values come from."""
    named = cfg.protocol.sampling_point
    if named == "sweep":
        return {"sampling_point": named}
    return {"sampling_point": named, "sampling_point_source": SAMPLING_POINT_SOURCES[named]}


def protocol_key(protocol: Any) -> dict[str, Any]:
    """The protocol settings as hashed into a text-to-motion unit's key. ``redraw_items=false`` is left out: the
    fixed set scores exactly as before the setting existed, so results computed then keep their keys; so are the
    loop's rules (``mdm`` protocol) at our values, which score as before they existed, and ``sampling_point=sweep``
    (the point itself is in the key; a named point adds its name, which results record)."""
    out = to_dict(protocol)
    if not out.get("redraw_items", True):
        out.pop("redraw_items")
    if out.get("sampling_point") == "sweep":
        out.pop("sampling_point")
    for name, ours in OUR_RULES.items():
        if out.get(name) == ours:
            out.pop(name)
    return out


def _rules_without_effect(cfg: EvalConfig, space: Any, is_action: bool) -> list[str]:
    """Notes on the protocol's reference rules that the evaluator in use cannot show (they change what the T2M
    evaluator reads: caption lengths, the frames past a motion's length, its normalisation)."""
    p, notes = cfg.protocol, []
    if p.generated_caption_length == "padded" and (is_action or not isinstance(space, T2MSpace)):
        notes.append("protocol.generated_caption_length=padded has no effect: this evaluator reads no caption "
                     "lengths (only the T2M text encoder does)")
    if p.generated_padding == "model" and not isinstance(space, T2MSpace):
        notes.append("protocol.generated_padding=model: the motions are sampled in the reference's window, but "
                     f"this {space.kind} evaluator masks the frames past each length")
    return notes


def _max_generation_length(trained: TrainedModel) -> int:
    config = trained.model_config
    limit = config.max_len - config.num_prefix_tokens
    return min(limit, config.max_frames) if config.length_token else limit


# ---------------------------------------------------------------------------------------------------------------
# The job: one checkpoint, or watch a run
# ---------------------------------------------------------------------------------------------------------------



def table_rows(result: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The result's rows for the results table: the generated row and the ground-truth row, metrics flattened
    to ``<metric>`` (mean) and ``<metric>_ci``; editing as ``edit_<preset>_<metric>``. Column ``task`` says which
    protocol ('text_to_motion' or 'composition', whose rows add ``switch`` and the composition settings)."""
    base = {
        "checkpoint": result["checkpoint"]["path"], "checkpoint_name": result["checkpoint"]["name"],
        "step": result["checkpoint"]["step"], "checkpoint_id": result["checkpoint"]["id"],
        "evaluator_kind": result["evaluator"]["kind"], "evaluator_id": result["evaluator"]["id"],
        "dataset_id": result["data"]["dataset_id"], "checkpoint_dataset_id": result["checkpoint"]["dataset_id"],
        "split": result["data"]["split"], "protocol": result["protocol"]["name"],
        # Which evaluation loop the protocol's rules make: 'ours', 'mdm' (the reference loop) or 'mixed';
        # text-to-motion results written before the rules existed ran ours.
        "protocol_loop": result["protocol"].get("loop", "ours" if result.get("task") != "composition" else None),
        "replications": result["protocol"]["replications"], "num_items": result["protocol"]["num_items"],
        # Whether the intervals include re-drawn ground-truth items (results before the setting: a fixed set).
        "redraw_items": bool(result["protocol"].get("redraw_items", False)),
        # Which sampling point ran: the sweep's, or MFM's named 'paper' / 'released' one (protocol.sampling_point);
        # results written before the setting ran the sweep's.
        "sampling_point": result["sampling"].get("sampling_point", "sweep"),
        "solver": result["sampling"]["solver"], "steps": result["sampling"]["steps"],
        "guidance": result["sampling"]["guidance"], "nfe": result["nfe"],
        # the model passes' arithmetic; results written before the setting ran fp32
        "precision": result["sampling"].get("precision", "fp32"),
        "model_passes_per_motion": result["model_passes_per_motion"],
        "generation_seconds_per_motion": result["generation_seconds_per_motion"],
        "world_size": result["world_size"], "created": result["created"], "result_key": result["key"],
    }
    if result.get("task") == "composition":
        return composition_rows(result, base)
    base["task"] = "text_to_motion"
    generated = {**base, "row_kind": "generated", "row_key": f"{result['key']}:generated"}
    generated.update(_flatten(result["metrics"]))
    for preset, values in result["editing"].items():
        generated.update(_flatten(values, prefix=f"edit_{preset}_"))
    edits = result.get("editing_settings")
    if edits:  # which edit settings the edit_* columns were measured with
        generated.update(edit_method=edits["method"], edit_settings=edits.get("settings"),
                         edit_steps=edits["steps"], edit_guidance=edits["guidance"],
                         # one pass of N edits (tasks.editing_passes=single) or one per replication (results
                         # written before the setting)
                         edit_passes=edits.get("passes", "per_replication"),
                         edit_edits_per_preset=edits.get("edits_per_preset"))
        # what each preset integrated with when a preset has its own count (reference-debug's interpolation: 1)
        for preset, steps in (edits.get("steps_per_preset") or {}).items():
            generated[f"edit_{preset}_steps"] = steps
    truth = {**base, "row_kind": "ground_truth", "row_key": f"{result['key']}:ground_truth"}
    truth.update(_flatten(result["ground_truth"]))
    return [generated, truth]


def summary_line(result: Mapping[str, Any]) -> str:
    """A one-line human summary: the headline metrics with their intervals, NFE and phase times."""
    shown = [f"{name} {v['mean']:.4g}" + ("" if v["ci"] is None else f"±{v['ci']:.2g}")
             for name, v in result["metrics"].items()
             if name in ("fid", "r_precision_top1", "r_precision_top3", "mm_dist", "diversity", "multimodality",
                         "accuracy", "transition_fid", "peak_jerk", "auj")]
    phases = ", ".join(f"{k} {v:.1f}s" for k, v in result["timing_s"].items())
    return f"{'; '.join(shown)}; NFE {result['nfe']:g}; {phases}"


def result_label(result: Mapping[str, Any]) -> str:
    """``euler 10 steps`` (text-to-motion) or ``composition euler 10 steps switch 0.0844 (all)``."""
    sampling = result["sampling"]
    label = f"{sampling['solver']} {sampling['steps']} steps"
    if result.get("task") == "composition":
        return f"composition {label} switch {sampling['switch']:.4g} ({result['composition']['scenario']})"
    return label


def _flatten(summary: Mapping[str, Mapping[str, Any]], prefix: str = "") -> dict[str, float]:
    out = {}
    for name, value in summary.items():
        out[f"{prefix}{name}"] = value["mean"]
        out[f"{prefix}{name}_ci"] = value["ci"]
    return out


@dataclasses.dataclass(frozen=True)
class HeldUnit:
    """A unit this job skipped because another job's claim holds it."""

    unit: Unit
    holder: ClaimHolder | None

    def describe(self) -> str:
        who = self.holder.describe() if self.holder is not None else "a job that released it unfinished"
        return f"{self.unit.checkpoint_name} {self.unit.point_name} (held by {who})"


@dataclasses.dataclass(frozen=True)
class JobSummary:
    """What a job did and what it could not do, for its last lines and its exit status: a job that did nothing
    because other jobs hold the work, or whose checkpoints were deleted before evaluation, must say so."""

    evaluated: int
    held_by_other_jobs: tuple[str, ...] = ()
    """Units skipped because another live job holds them and had not finished them at the end of this job."""
    pruned_before_evaluation: tuple[int, ...] = ()
    """Steps of checkpoints that a watcher listed or training saved (checkpoints/saved.jsonl) but that were deleted
    (training's ``train.keep_last``) with no result."""

    @property
    def exit_code(self) -> int:
        return EXIT_HELD_BY_OTHERS if self.held_by_other_jobs else EXIT_ALL_DONE

    def lines(self) -> list[str]:
        out = [f"held by another job, not evaluated here (run again later): {held}"
               for held in self.held_by_other_jobs]
        if self.pruned_before_evaluation:
            out.append(f"pruned_before_evaluation: {list(self.pruned_before_evaluation)} (deleted by training before "
                       "any result; keep them with train.keep_last=0, or run the evaluator with --watch while "
                       "training)")
        status = "held_by_other_jobs" if self.held_by_other_jobs else "all_done"
        out.append(f"status: {status} (exit {self.exit_code})")
        return out


class EvaluationJob:
    """Claims units, evaluates them and writes results; the same object serves --checkpoint and --watch."""

    def __init__(self, cfg: EvalConfig, dist: Dist) -> None:
        self.cfg, self.dist = cfg, dist
        self.scorer = CheckpointScorer(cfg, dist)
        self.timings: dict[str, float] = defaultdict(float)
        """Wall seconds per phase over everything this job evaluated (rank 0's view)."""
        self._finished: set[str] = set()
        """Checkpoint ids whose every unit is done: a long-running watcher does not reload them (rank 0)."""
        self._held: dict[str, tuple[ResultsStore, HeldUnit]] = {}
        """Units skipped because another job held them, by unit key, with their store (rank 0)."""
        self._pruned: dict[SeenCheckpoint, None] = {}
        """Checkpoints listed once and deleted before any result, in the order found (rank 0)."""

    def store_for(self, folder: Path) -> ResultsStore:
        return self.store_for_run(ckpt.run_dir_of(folder))

    def store_for_run(self, run_dir: Path) -> ResultsStore:
        """The results store of a run (output.dir, default <run>/eval), its folder checked to be an evaluation folder
        of ours (EvalFolderError otherwise, before anything is written) and marked as one by the main rank."""
        root = Path(self.cfg.output.dir) if self.cfg.output.dir else run_dir / "eval"
        store = ResultsStore(root, self.cfg.output.claim_timeout_s)
        store.open_folder(write_marker=self.dist.is_main)
        return store

    def evaluate_checkpoint(self, folder: str | Path) -> list[dict[str, Any]]:
        """Every sampling point of one complete checkpoint not evaluated yet (by anyone); returns the results
        written by this job (rank 0; other ranks get an empty list)."""
        folder = resolve_checkpoint(folder)
        if not ckpt.is_complete(folder):
            raise EvaluationError(f"{folder} is not a complete checkpoint (no valid {ckpt.COMPLETE_MARKER} marker)")
        store = self.store_for(folder)
        timer = PhaseTimer(self.dist.device)
        ctx = self.scorer.context(folder, store.cache_dir, timer)
        changed = self.dist.broadcast_object(self._test_set_change(folder, store, ctx) if self.dist.is_main else None)
        if changed is not None:  # before any unit is claimed or generated, on every rank
            raise ChangedTestSetError(changed)
        comp = None
        if self.cfg.tasks.composition:
            comp = prepare_composition(self.cfg, self.dist, ctx, store.cache_dir, timer)
        setup = dict(timer.seconds)  # loading, ground truth: shared by the units below
        work = self.scorer.work(folder, ctx, comp)
        units = [w.unit for w in work]
        claimed = self.dist.broadcast_object(self._claim(store, units) if self.dist.is_main else None)
        written = []
        for item in work:
            unit, point = item.unit, item.point
            if unit.key not in claimed:
                continue
            try:
                before = dict(timer.seconds)
                result = self.scorer.evaluate(ctx, comp, item, timer, lambda: store.heartbeat(unit))
                if self.dist.is_main:
                    with timer.phase("write"):
                        phases = {k: v - before.get(k, 0.0) for k, v in timer.seconds.items()}
                        full = self._result(folder, ctx, point, unit, result, setup, phases)
                        store.write_result(unit, full, table_rows(full))
                        logger.info("%s %s: %s", folder.name, unit.point_name, summary_line(full))
                        self._publish(store, folder, full)
                    written.append(full)
            finally:
                if self.dist.is_main:
                    store.release(unit)
        for phase, seconds in timer.seconds.items():
            self.timings[phase] += seconds
        if self.dist.is_main and all(store.is_done(unit) for unit in units):
            self._finished.add(ctx.checkpoint_id)
        return written

    def _test_set_change(self, folder: Path, store: ResultsStore, ctx: CheckpointContext) -> str | None:
        """Why this checkpoint may not be scored on this job's test set, or None. The test set is the dataset id
        derived from the manifest now and the split. The evaluation folder's table holds one test set, always; with
        ``output.dir`` elsewhere, the run's default folder (<run>/eval) holds its earlier results, whose test set this
        job must keep unless ``data.allow_other_test_set``."""
        ours = ScoredData(ctx.manifest.dataset_id, ctx.gt.split)
        where = f"this job's test data is {ours.describe()} ({ctx.manifest.location})"
        here = store.scored_data()
        if here and here != [ours]:
            return (f"evaluation folder {store.root} holds results on {', '.join(d.describe() for d in here)} and "
                    f"{where}: one table never mixes test sets. If the test data changed on purpose, evaluate into "
                    "another folder: output.dir=... data.allow_other_test_set=true")
        if self.cfg.data.allow_other_test_set:
            return None
        run_dir = ckpt.run_dir_of(folder)
        default = run_dir / "eval"
        if default.resolve() == store.root.resolve():
            return None
        try:
            check_eval_folder(default)  # only read an evaluation folder of ours
        except EvalFolderError:
            return None
        earlier = ResultsStore(default).scored_data()
        if earlier and ours not in earlier:
            return (f"run {run_dir} was evaluated on {', '.join(d.describe() for d in earlier)} ({default}) and "
                    f"{where}: refusing to score it on another test set (the data was rebuilt, edited or is another "
                    "manifest, so the numbers would not compare); set data.allow_other_test_set=true to evaluate on "
                    "it anyway")
        return None

    def _claim(self, store: ResultsStore, units: Sequence[Unit]) -> list[str]:
        claimed = []
        for unit in units:
            if store.is_done(unit):
                store.append_rows(table_rows(store.read_result(unit)))  # repairs a crash before the table append
                logger.info("%s %s: already evaluated (%s)", unit.checkpoint_name, unit.point_name,
                            store.result_path(unit))
            elif store.try_claim(unit):
                claimed.append(unit.key)
                self._held.pop(unit.key, None)
            elif store.is_done(unit):
                logger.info("%s %s: evaluated by another job meanwhile", unit.checkpoint_name, unit.point_name)
            else:
                held = HeldUnit(unit, store.holder(unit))
                self._held[unit.key] = (store, held)
                logger.info("%s %s: skipped, held by another job (%s)", unit.checkpoint_name, unit.point_name,
                            held.describe())
        return claimed

    def summary(self, evaluated: int) -> JobSummary:
        """This job's summary (on every rank: call it on all of them). Units another job held are listed only if
        still not done now: one finished meanwhile is not a gap."""
        summary = None
        if self.dist.is_main:
            held = tuple(h.describe() for store, h in self._held.values() if not store.is_done(h.unit))
            summary = JobSummary(evaluated, held, tuple(sorted({c.step for c in self._pruned})))
        return self.dist.broadcast_object(summary)

    def pending(self, run_dir: Path) -> list[Path]:
        """Complete checkpoints of a run in the configured order (incomplete folders are ignored), less those this
        job already found fully evaluated. Each is recorded as seen, so that its loss can be reported later."""
        listed = [(step, path, _known_id(path)) for step, path in ckpt.list_complete(ckpt.checkpoints_dir(run_dir))]
        self.store_for_run(run_dir).record_seen([SeenCheckpoint(str(run_dir.resolve()), path.name, step, known)
                                                 for step, path, known in listed if known is not None])
        complete = [path for _, path, known in listed if known is not None and known not in self._finished]
        return complete[::-1] if self.cfg.output.order == "newest" else complete

    def check_pruned(self, run_dir: Path) -> list[SeenCheckpoint]:
        """Checkpoints of ``run_dir`` that are gone with no result written: training deleted them
        (``train.keep_last``) before any evaluator got to them. Known from what watchers listed
        (checkpoints_seen.jsonl) and from training's own listing of its saves (checkpoints/saved.jsonl), which also
        covers a checkpoint saved and pruned between two ``--watch --once`` jobs. One set aside by training
        (``.corrupt-``/``.discarded-``, kept) is not reported. Logged once per job, then in the summary; returns
        those found by this call for the first time."""
        store, run = self.store_for_run(run_dir), str(run_dir.resolve())
        root = ckpt.checkpoints_dir(run_dir)
        saved = [SeenCheckpoint(run, s.name, s.step, s.checkpoint_id) for s in ckpt.read_saved(root)]
        known = dict.fromkeys([seen for seen in store.seen() if seen.run == run] + saved)
        new = []
        for seen in sorted(known, key=lambda c: c.step):
            if seen in self._pruned or (root / seen.name).exists():
                continue
            if store.has_result_for(seen.name, seen.checkpoint_id) or _set_aside(root, seen):
                continue
            self._pruned[seen] = None
            new.append(seen)
            logger.warning("%s (step %d) is gone and was never evaluated: deleted before any evaluator got to it "
                           "(training prunes old checkpoints: train.keep_last=%s in %s); keep checkpoints for the "
                           "evaluator with train.keep_last=0 or a larger value, or run the evaluator with --watch "
                           "while training",
                           seen.name, seen.step, _training_keep_last(run_dir), run_dir / "config.yaml")
        return new

    def watch(self, run_dir: str | Path, once: bool = False, sleep: Callable[[float], None] = time.sleep) -> int:
        """Evaluate every complete checkpoint of ``run_dir`` once; with ``once`` exit after one scan, else
        rescan every ``output.poll_s`` seconds. Returns the number of units this job evaluated. Checkpoints
        deleted before any evaluation are reported after each scan (:meth:`check_pruned`, :meth:`summary`)."""
        run_dir = Path(run_dir)
        if not run_dir.is_dir():
            raise FileNotFoundError(f"--watch: no run folder at {run_dir}")
        self.store_for_run(run_dir)  # on every rank: a folder that is not ours is refused by all of them at once
        done = 0
        while True:
            folders = self.dist.broadcast_object([str(p) for p in self.pending(run_dir)] if self.dist.is_main else None)
            for folder in folders:
                try:
                    done += len(self.evaluate_checkpoint(folder))
                except (ckpt.CheckpointError, FileNotFoundError) as exc:
                    if isinstance(exc, EvaluatorUnavailable):
                        raise
                    logger.warning("skipping %s: %s (deleted or damaged while waiting?)", folder, exc)
            if self.dist.is_main:
                self.check_pruned(run_dir)
            if once:
                return done
            sleep(self.cfg.output.poll_s)

    def _result(self, folder: Path, ctx: CheckpointContext, point: SamplingPoint, unit: Unit,
                computed: Mapping[str, Any], setup: Mapping[str, float],
                phases: Mapping[str, float]) -> dict[str, Any]:
        trained, gt = ctx.trained, ctx.gt
        computed = dict(computed)
        sets = computed.pop("ground_truth_sets", [])
        return {
            "format": RESULT_FORMAT,
            "task": "text_to_motion",
            "key": unit.key,
            "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "checkpoint": {"path": str(folder.resolve()), "name": folder.name, "step": trained.step,
                           "id": ctx.checkpoint_id, "weights": trained.weights, "dataset_id": trained.dataset_id,
                           "model": "action-to-motion" if ctx.is_action else "text-to-motion",
                           "objective": trained.objective, "diffusion_preset": trained.diffusion_preset,
                           "conditioning": trained.model_config.conditioning, "window": trained.window},
            "evaluator": ctx.space.describe(),
            "data": {"manifest": ctx.manifest.location, "dataset_id": ctx.manifest.dataset_id, "split": gt.split,
                     "num_items": len(gt), "dropped": dict(gt.dropped), "gt_key": gt.key,
                     # Per replication: the set it scored against (re-drawn: its own key) and whether its
                     # embeddings came from the cache; gt_key above is the fixed set's (the items' identity).
                     "redraw_items": ctx.plan.redraw_items, "ground_truth_sets": sets,
                     "gt_embeddings_from_cache": bool(sets) and all(t["embeddings_from_cache"] for t in sets),
                     # The ground truth was read only after its shards verified (pipeline.data.stream.verify_shards).
                     "data_verified": bool(gt.verification.get("verified")), "verification": dict(gt.verification)},
            "protocol": {**ctx.plan.as_dict(), "config": to_dict(self.cfg.protocol)},
            "sampling": {**dataclasses.asdict(point), "use_ema": self.cfg.sampling.use_ema,
                         "batch_size": self.cfg.sampling.batch_size,
                         # the model passes' arithmetic as it ran, and the setting (auto resolves per device)
                         "precision": sampling_precision(self.cfg.sampling, self.dist.device),
                         "precision_setting": self.cfg.sampling.precision,
                         "compiled": trained.is_compiled, "compile_setting": self.cfg.sampling.compile,
                         # the solver's time grid: None = uniform, else the model's own (ModelConfig.sampling_times)
                         "grid": solver_grid(point.steps, trained),
                         # the seeded noise's setting, and where it was drawn (the CPU, or the model's device)
                         "noise_device": self.cfg.sampling.noise_device, "noise_drawn_on": noise_generator_device(
                             self.cfg.sampling.noise_device, self.dist.device).type,
                         **baseline_record(trained, self.cfg.sampling),
                         **sampling_point_record(self.cfg)},
            "tasks": to_dict(self.cfg.tasks),
            **computed,
            "world_size": self.dist.world_size,
            "timing_s": {k: round(v, 4) for k, v in phases.items() if v > 0},
            "setup_timing_s": {k: round(v, 4) for k, v in setup.items()},
        }

    def _publish(self, store: ResultsStore, folder: Path, result: Mapping[str, Any]) -> None:
        """W&B (under the training run) and the plots; failures are logged, never fatal."""
        run_dir = ckpt.run_dir_of(folder)
        trained_mode, project = _training_wandb(run_dir)
        mode = wandb_mode(self.cfg.output.wandb, fallback=wandb_mode(trained_mode))
        prefix = f"{result['sampling']['solver']}-{result['sampling']['steps']}-g{result['sampling']['guidance']:g}"
        if result.get("task") == "composition":
            prefix = f"compose-{prefix}-s{result['sampling']['switch']:.4g}-{result['composition']['scenario']}"
        scalars = {f"{prefix}/{k}": v for k, v in table_rows(result)[0].items()
                   if isinstance(v, float) and not k.endswith("_ci") and math.isfinite(v)}
        log_to_wandb(run_dir, mode, project, int(result["checkpoint"]["step"]), scalars,
                     {"protocol": result["protocol"]["name"], "evaluator_id": result["evaluator"]["id"]})
        if self.cfg.output.plots:
            from pipeline.evaluation.plots import plot_composition_switch, update_plots

            try:
                rows = store.table_rows()
                update_plots([r for r in rows if r.get("task", "text_to_motion") == "text_to_motion"],
                             store.plots_dir)
                plot_composition_switch(rows, store.plots_dir / "composition_switch.png")
            except Exception as exc:  # a plotting problem must not lose an evaluation
                logger.warning("plots not updated: %s", exc)
        try:  # index.html: the table and plots to browse (pipeline/generation/browse.py); a failure is logged, never fatal
            from pipeline.generation.browse import write_eval_index
            write_eval_index(store.root)
        except Exception as exc:
            logger.warning("index.html not written: %s", exc)


def _known_id(folder: Path) -> str | None:
    """The checkpoint id, or None when the folder vanished meanwhile (pruned by training's keep_last)."""
    try:
        return checkpoint_id(folder)
    except (ckpt.CheckpointError, OSError):
        return None


def _set_aside(root: Path, seen: SeenCheckpoint) -> bool:
    """Whether training renamed the checkpoint aside (``step-N.corrupt-...``/``step-N.discarded-...``, kept for the
    user) rather than deleting it: not a checkpoint lost to pruning."""
    return any(_known_id(folder) == seen.checkpoint_id
               for label in ("corrupt", "discarded") for folder in root.glob(f"{seen.name}.{label}-*"))


def _training_keep_last(run_dir: Path) -> str:
    """The run's ``train.keep_last`` from its config.yaml, for the message about pruned checkpoints ('?' if
    unknown)."""
    config = run_dir / "config.yaml"
    try:
        data = parse_yaml(config.read_text(encoding="utf-8"), str(config))
    except (OSError, ConfigError):  # only a hint in a message: never fail the job over it
        return "?"
    train = data.get("train") if isinstance(data, dict) else None
    return str(train.get("keep_last", "?")) if isinstance(train, dict) else "?"


def _training_wandb(run_dir: Path) -> tuple[str, str]:
    """The training run's W&B mode and project (from its config.yaml), or ('disabled', 'mfm')."""
    config = run_dir / "config.yaml"
    if not config.is_file():
        return "disabled", "mfm"
    train = (parse_yaml(config.read_text(encoding="utf-8"), str(config)) or {}).get("train", {})
    return str(train.get("wandb", "disabled")), str(train.get("wandb_project", "mfm"))
