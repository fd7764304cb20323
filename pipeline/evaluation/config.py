"""Settings of the evaluation job (launch/evaluate.py): typed sections, presets configs/eval_{full,fast,mdm}.yaml,
dotted overrides, and the sweep flags ``--solver/--steps/--guidance`` (comma lists). See pipeline.evaluation.job.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

from mfm.composition import BABEL_SWITCH, HUMANML3D_SWITCH
from mfm.editing import EDIT_SETTINGS
from mfm.model import is_bone_keeping
from mfm.solvers import is_adaptive
from pipeline.config import ConfigError, coerce_fields, load_config, parse_yaml

PROTOCOL_PRESETS = {"full": "eval_full", "fast": "eval_fast", "mdm": "eval_mdm"}
"""``--protocol`` names and their presets: ``full`` / ``fast`` are our loop, ``mdm`` the reference loop
(configs/eval_mdm.yaml, docs/protocol.md)."""
EDIT_PRESETS = ("prediction", "inbetween", "interpolation", "upper_body")
"""mfm.editing presets the editing metrics may use."""
EDITS_PER_SINGLE_PASS = 5000
"""``tasks.editing_passes=single``'s edits per preset when ``tasks.editing_samples`` is null: the 5,000 generated
edits issue 26 gives for MFM's Table 3 (the paper's text was not at hand to check it; set editing_samples)."""


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise ConfigError(message)


@dataclasses.dataclass(frozen=True, kw_only=True)
class ProtocolConfig:
    """The metric protocol; ``full``, ``fast`` and ``mdm`` presets are configs/eval_full.yaml, eval_fast.yaml and
    eval_mdm.yaml."""

    name: str = "full"
    """Recorded in every result (``full``: 20 replications as published; ``fast``: 3, for training curves; ``mdm``:
    the reference loop, rule by rule). Which loop the rules make is recorded beside it (:attr:`loop`)."""
    replications: int = 20
    r_precision_batch: int = 32
    """Retrieval among this many (1 match + 31 others); a smaller test set uses its size (recorded)."""
    diversity_times: int = 300
    multimodality: bool = True
    """Generate ``mm_repeats`` motions for ``mm_num_texts`` texts per replication (MDM's ``mm_short``)."""
    mm_num_texts: int = 100
    mm_repeats: int = 30
    mm_times: int = 10
    num_samples: int = 0
    """Items generated per replication: 0 = the whole test set (T2M); 1000 = MDM's ``num_samples_limit``."""
    max_length: int = 196
    """Longest ground-truth clip in frames (the reference's ``max_motion_length``); longer ones are cropped."""
    unit_length: int = 4
    """Ground-truth clips are cropped to a multiple of this (the reference loader's rule)."""
    redraw_items: bool = True
    """Every replication draws its own ground-truth items, as the reference loader does on each pass: each test
    motion's caption picked at random and its clip randomly cropped (a multiple of ``unit_length``, one unit shorter
    with probability 1/3, at a random offset), seeded by (``seed``, replication); the replication's generated motions
    use those captions and lengths, its FID statistics and ground-truth row those clips. The 95 % intervals then
    include the spread of captions and crops. false: one fixed set (one seeded caption and crop per motion) for
    every replication, so the intervals hold only the generator's noise and the metrics' draws (the former
    default, kept for comparison)."""
    seed: int = 0
    # -- where the reference loop (MDM's eval_humanml.py as copied into MFM; ``--protocol mdm``) differs from ours.
    # Each rule's default is our loop; MDM_RULES lists the reference's values (docs/protocol.md cites the code).
    round_to_batches: bool = False
    """Round the generated motions up to whole ``r_precision_batch`` batches as the reference's generation loop
    (it stops only once it holds ``num_samples`` motions: 1000 -> 32 batches of 32 = 1,024 rows, all scored) and the
    MultiModality texts to the reference's ``mm_num_samples // batch + 1`` whole batches (100 -> 4 x 32 = 128).
    false: exactly ``num_samples`` and ``mm_num_texts``."""
    gt_draws: Literal["shared", "independent"] = "shared"
    """shared (ours): one draw of the items per replication gives the generated motions their captions and lengths,
    FID's statistics and the ground-truth row (scored on the generated items; its FID a bootstrap resample of them
    against the whole draw: the metric's noise floor). independent (the reference: a generation loader and two
    passes over the shuffled ground-truth loader): three independent draws per replication, seeded by (seed,
    replication, pass): the generated motions' captions and lengths; the ground-truth row (every test item, its
    FID, Diversity and R-precision); FID's statistics for both rows. Each ground-truth pass keeps all but
    ``N mod r_precision_batch`` random items (the reference's ``drop_last``). Needs ``redraw_items``."""
    generated_caption_length: Literal["sentence", "padded"] = "sentence"
    """Caption length the T2M text encoder gets for the generated row (its GRU stops there). sentence (ours, and
    the reference's ground truth): sos + the first 20 tokens + eos. padded (the reference's generated row, MDM
    issue #182, fixed in MDM but not in MFM): the length of the token list padded with unk/OTHER, 22 for every
    caption. Only the T2M evaluator reads caption lengths."""
    generated_padding: Literal["zero", "model"] = "zero"
    """What the evaluator sees past a generated motion's length (the T2M movement encoder convolves over every
    frame of its 196-frame window). zero (ours): generated like the ground truth, zero past the length (in the
    evaluator's normalisation). model (the reference): every motion (and MultiModality repetition) is sampled in a
    ``max_length``-frame window with noise on every frame and every frame integrated, and the evaluator gets the
    whole window as the sampler leaves it. Edits keep ours."""
    mm_normalisation: Literal["evaluator", "model"] = "evaluator"
    """MultiModality motions as the evaluator gets them. evaluator (ours; MDM since its fix): converted to the
    evaluator's normalisation like every other motion. model (the reference, MFM's copy): left in the generating
    model's normalisation (the evaluator's own normalisation is skipped)."""
    mm_replications: int = 0
    """MultiModality runs in the first this many replications (its interval over those); 0: every replication.
    The reference's MultiModality comes from its ``mm_short`` mode: 5 replications."""
    test_items: Literal["span", "caption"] = "span"
    """Which ground-truth items the test set makes (pipeline.evaluation.spaces). span (ours): one per distinct caption
    span of a motion, the captions sharing it pooled (each draw picks one), long spans cropped to ``max_length``.
    caption (the reference, MDM dataset.py: 271-298): the whole-clip captions of a motion pooled into one item, every
    sub-span caption line its own item (its own span's clip and length, its one caption as condition and as the
    R-precision / MultiModality text); motions (dataset.py: 254) and sub-spans (276-280) of 200 frames or more dropped
    and counted. A sub-span that covers the whole clip cannot be told from a whole-clip caption once preprocessing
    has mapped seconds to frames: it is pooled."""
    sampling_point: Literal["sweep", "paper", "released"] = "sweep"
    """Where the motions are sampled. sweep (ours): every point of ``sampling.solvers/steps/guidance`` (the sweep
    flags). paper: MFM's paper point, N = 10 Euler steps (guidance 2.5). released: MFM's released evaluation
    commands, Euler with ``ode_kwargs.step_size`` 0.01 (config_base.yaml: 41, README.md: 75: 100 steps) for
    HumanML3D and 0.02 (README.md: 65: 50 steps) for KIT, guidance_param 2.5; the step count follows the
    checkpoint's skeleton (SAMPLING_POINTS). A named point is the only point: with it the sampling lists must stay
    at their defaults. Results record it (``sampling.sampling_point`` and the table's ``sampling_point``)."""

    def __post_init__(self) -> None:
        coerce_fields(self)
        for name in ("replications", "r_precision_batch", "diversity_times", "mm_num_texts", "mm_repeats",
                     "mm_times", "max_length", "unit_length"):
            _require(getattr(self, name) >= 1, f"protocol.{name} must be >= 1, got {getattr(self, name)}")
        _require(self.mm_times <= self.mm_repeats,
                 f"protocol.mm_times ({self.mm_times}) must not exceed mm_repeats ({self.mm_repeats})")
        _require(self.num_samples >= 0, f"protocol.num_samples must be >= 0, got {self.num_samples}")
        _require(self.seed >= 0, f"protocol.seed must be >= 0, got {self.seed}")
        _require(self.mm_replications >= 0, f"protocol.mm_replications must be >= 0, got {self.mm_replications}")
        _require(self.gt_draws == "shared" or self.redraw_items,
                 "protocol.gt_draws=independent draws each pass anew: it needs protocol.redraw_items=true")

    def named_point(self, skeleton: str) -> SamplingPoint | None:
        """The sampling point ``sampling_point`` names for a checkpoint on ``skeleton`` (None: ``sweep``)."""
        if self.sampling_point == "sweep":
            return None
        points = SAMPLING_POINTS[self.sampling_point]
        if skeleton not in points:
            raise ConfigError(f"protocol.sampling_point={self.sampling_point}: MFM names no sampling point for "
                              f"skeleton {skeleton!r} (known: {sorted(points)}); use protocol.sampling_point=sweep "
                              "with sampling.steps")
        return points[skeleton]

    def rules(self) -> dict[str, Any]:
        """The loop's rules (the fields where the reference and ours differ) with their values."""
        return {name: getattr(self, name) for name in MDM_RULES}

    @property
    def loop(self) -> str:
        """Which evaluation loop the rules make: 'ours' (every rule at our default), 'mdm' (every rule as the
        reference's, MDM_RULES) or 'mixed'. Recorded in every result and table row."""
        rules = self.rules()
        if rules == OUR_RULES:  # OUR_RULES holds exactly MDM_RULES' names
            return "ours"
        return "mdm" if rules == MDM_RULES else "mixed"


MDM_RULES: dict[str, Any] = {"round_to_batches": True, "gt_draws": "independent",
                              "generated_caption_length": "padded", "generated_padding": "model",
                              "mm_normalisation": "model", "mm_replications": 5, "test_items": "caption"}
"""The reference loop's value of every rule of ProtocolConfig (MFM dongzhuoyao/motionfm 08eb88d, whose loop is MDM's
before its fixes of 2024-01 (caption lengths) and 2025-03 (MultiModality normalisation)); configs/eval_mdm.yaml."""
OUR_RULES: dict[str, Any] = {f.name: f.default for f in dataclasses.fields(ProtocolConfig) if f.name in MDM_RULES}
"""Our loop's value of every rule (the ProtocolConfig defaults)."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class SamplingConfig:
    """How motions are generated; every (solver, steps, guidance) combination is one unit (a sweep)."""

    solvers: tuple[str, ...] = ("euler",)
    """mfm.solvers names: euler, midpoint, heun, rk4 or a torchdiffeq method (dopri5, ...) for flow checkpoints;
    ddpm, ddim for diffusion checkpoints. A sweep may list both: each checkpoint runs the points of its objective."""
    steps: tuple[int, ...] = (10,)
    steps_per_solver: dict[str, tuple[int, ...]] = dataclasses.field(default_factory=dict)
    """Step counts for particular solvers instead of ``steps``, e.g. {midpoint: [5, 10, 25, 50]} (two evaluations
    per step: the NFE of euler's 10 to 100). Adaptive solvers (dopri5, ...) choose their own steps: one point each,
    named with the first of their step counts."""
    guidance: tuple[float, ...] = (2.5,)
    use_ema: bool = True
    """Sample the EMA of the weights (a checkpoint that kept none falls back to its raw weights, recorded as
    ``checkpoint.weights``, except for a baseline whose authors sample the EMA, FLAME: refused)."""
    baseline_defaults: bool = True
    """Diffusion checkpoints of a preset whose authors sampled it their own way run that way
    (mfm.diffusion_sampling.BASELINE_SAMPLING; FLAME: guidance 8.0 instead of ``guidance``, the output smoothed
    over time with σ = 1 frame, every training step and the x0 clamp below, its EMA weights). false: every
    checkpoint samples with ``guidance``, the sweep's steps, no smoothing and no clamp. Results record the settings
    that ran (``sampling.baseline_defaults``)."""
    baseline_steps: bool = True
    """With baseline_defaults: a baseline whose authors sample every training step (FLAME: all 1,000) runs every
    step whatever ``steps`` (its points with other step counts collapse into one); false: the sweep's steps,
    respaced (the FID-vs-NFE sweep of a diffusion baseline)."""
    baseline_clip_denoised: bool = True
    """With baseline_defaults: a baseline whose sampler clamps its x0 estimate (FLAME: [-1, 1] on its raw
    features) gets that clamp on ours: the 6D rotation channels bounded to [-1, 1] in raw units, the rest free
    (mfm.diffusion_sampling.rotation_6d_range). false: no clamp."""
    output_smoothing: float | None = None
    """Gaussian smoothing of every generated motion over time, σ in frames, for every checkpoint: 0 scores the
    network's raw output. None (default): each checkpoint's own (its ``model.output_smoothing``; a baseline's
    authors' σ with ``baseline_defaults``, FLAME's 1; else none). Results record the σ that ran
    (``smoothing_sigma``)."""
    output_smoothing_keeps_bones: bool | Literal["smoothed"] | None = None
    """After the output smoothing, every bone gets back a length it had before the filter, each frame's own (true)
    or its lengths smoothed over time with the same σ (smoothed) (ours, not FLAME's;
    mfm.model.ModelConfig.output_smoothing_keeps_bones), for every checkpoint. None (default): each checkpoint's
    own. Results record what ran (``smoothing_keeps_bones``); an explicit setting goes into the unit keys."""
    guided_features: str | None = None
    """Which channels classifier-free guidance mixes, for every flow checkpoint: 'all' or 'pose' (the root's motion
    left to the conditional output; mfm.model.ModelConfig.guided_features). None (default): each checkpoint's own
    ``model.guided_features``. Diffusion checkpoints always guide every channel. Results record what ran
    (``guided_features``)."""
    batch_size: int = 64
    """Motions generated per forward batch (per rank)."""
    precision: Literal["fp32", "bf16", "auto"] = "fp32"
    """The model passes' arithmetic in generation and editing (mfm.guidance): fp32 (default: the arithmetic of every
    earlier result, which keeps their keys); bf16: bf16 autocast on the CPU or a CUDA GPU with bf16, the ODE state,
    guidance mix and solver (or diffusion chain) staying fp32 (tests/test_sampling_precision.py bounds the
    difference); auto: bf16 on a CUDA GPU with native bf16, fp32 elsewhere. Results record the precision that ran
    (``sampling.precision``, table column ``precision``); a bf16 unit has a key of its own."""
    compile: bool | Literal["auto"] = False
    """torch.compile the generator's passes in generation and editing (mfm.compilation, the rule of training's
    ``train.compile``; built once per checkpoint): false (default: every earlier result's, which keeps their keys);
    auto: on a CUDA device only, with CUDA graphs (``mode="reduce-overhead"``); true: always (inductor's default
    mode off CUDA: minutes of compilation on a CPU). Results record what ran (``sampling.compiled``) and the setting
    (``sampling.compile_setting``); a compiled unit has a key of its own (compiled kernels may round differently)."""
    noise_device: Literal["cpu", "model"] = "cpu"
    """Where generation's, editing's and MultiModality's seeded noise is drawn (mfm.solvers.NOISE_DEVICES): cpu
    (default: every earlier result's, which keeps their keys; a seed gives the same motion on every device) or the
    model's device (on a GPU the CPU's draw is the sampler's largest fixed cost: 124 ms per 256 motions on an H200
    machine, docs/performance.md; on the GPU the motions differ from the CPU's for the same seeds, so such a unit has
    a key of its own). Results record it (``sampling.noise_device``). Composition keeps the CPU noise (one sequence
    per call: a small draw)."""
    rtol: float = 1e-5
    atol: float = 1e-5

    def __post_init__(self) -> None:
        coerce_fields(self)
        _require(bool(self.solvers) and bool(self.steps) and bool(self.guidance),
                 "sampling.solvers, sampling.steps and sampling.guidance must each list at least one value")
        _require(all(s >= 1 for s in self.steps), f"sampling.steps must be >= 1, got {self.steps}")
        for solver, steps in self.steps_per_solver.items():
            _require(solver in self.solvers, f"sampling.steps_per_solver names {solver!r}, which is not one of "
                                             f"sampling.solvers {list(self.solvers)}")
            _require(bool(steps) and all(s >= 1 for s in steps),
                     f"sampling.steps_per_solver.{solver} must list step counts >= 1, got {steps}")
        _require(self.batch_size >= 1, f"sampling.batch_size must be >= 1, got {self.batch_size}")
        _require(self.guided_features in (None, "all", "pose"),
                 f"sampling.guided_features must be all, pose or null (each checkpoint's own), got {self.guided_features!r}")
        _require(self.output_smoothing_keeps_bones is None or is_bone_keeping(self.output_smoothing_keeps_bones),
                 "sampling.output_smoothing_keeps_bones must be true, false, smoothed or null (each checkpoint's "
                 f"own), got {self.output_smoothing_keeps_bones!r}")
        _require(self.output_smoothing is None or self.output_smoothing >= 0,
                 f"sampling.output_smoothing must be >= 0 (or null: each checkpoint's own), got {self.output_smoothing}")

    def points(self) -> list[SamplingPoint]:
        points = []
        for solver in self.solvers:
            steps = self.steps_per_solver.get(solver, self.steps)
            if is_adaptive(solver):
                steps = steps[:1]  # the same integration whatever the step count: one unit, not duplicates
            points += [SamplingPoint(solver, n, float(g)) for n in steps for g in self.guidance]
        return points


@dataclasses.dataclass(frozen=True, kw_only=True)
class EvaluatorConfig:
    """Which network metrics are computed in."""

    kind: Literal["contrastive", "t2m"] = "contrastive"
    """contrastive: the project's own (launch/train_evaluator.py); t2m: the official evaluator of Guo et al."""
    path: str = "auto"
    """Contrastive evaluator weights (.safetensors); auto: runs/evaluators/<dataset id>/contrastive.safetensors."""
    action_classifier: str = "auto"
    """Action classifier for action-to-motion; auto: beside the evaluator if present; empty: none."""
    t2m_checkpoint_dir: str = ""
    """Folder holding {t2m,kit}/text_mot_match/model/finest.tar (T2M ``checkpoints/`` or MDM's repository root)."""
    t2m_glove_dir: str = ""
    """Folder holding our_vab_data.npy, our_vab_words.pkl, our_vab_idx.pkl."""
    t2m_norm_dir: str = ""
    """Folder holding {t2m,kit}_mean.npy / _std.npy (empty: look in t2m_checkpoint_dir)."""
    t2m_allow_pickle: bool = False


@dataclasses.dataclass(frozen=True, kw_only=True)
class TasksConfig:
    """Which metric families run besides text-to-motion (or action-to-motion for action models)."""

    text_to_motion: bool = True
    """The T2M protocol units (one per sampling point; with flame / editing below). false: composition only."""
    composition: bool = False
    """FlowMDM's composition protocol (section ``composition``; pipeline.evaluation.composition): bpe + pccat models."""
    flame: bool = True
    """The metrics FLAME's paper reports: APE/AVE (TEMOS's definition, mfm.metrics.ape_ave; FLAME's own
    eval_util.py differs: no floor or heading canonicalisation, bone vectors as the local error, the root from the
    SMPL translation), mCLIP, MID and per-text joint variance."""
    ape_floor: Literal["temos", "given"] = "temos"
    """APE/AVE: 'temos' re-estimates each clip's floor from its feet as TEMOS's Rifke transform, in millimetres as
    TEMOS (the lowest foot ends 0.69 mm under y = 0; since issue 25, before which the formula ran on metres and
    offset each clip by 0.1-0.4 m); 'given' keeps the heights as recovered (HumanML3D joints stand on y = 0
    already)."""
    mid_eps: float = 5e-4
    """Ridge added to MID's covariances (its authors' advice for small sets)."""
    editing: tuple[str, ...] = ("prediction", "inbetween", "upper_body")
    """MFM Table 3 tasks, mfm.editing presets; empty: none. Needs a fixed-step solver."""
    editing_replications: int = 0
    """0: as many as protocol.replications. With ``editing_passes=single``: 0 or 1 (the pass runs in one)."""
    editing_passes: Literal["per_replication", "single"] = "per_replication"
    """per_replication (default): each of the first ``editing_replications`` replications edits every item it
    generates for (its own ground-truth draw), and the editing figures are mean ± 95 % CI over those replications.
    single (MFM's Table 3 as issue 26 reads it: one pass over generated edits, not one per replication): one pass of
    ``editing_samples`` edits per preset, in the first replication, scored once (FID, Diversity, ADE/FDE and
    plausibility over all of them; no interval): the editing work of the whole protocol is that of one pass. Results
    record it (``editing_settings.passes``, ``edits_per_preset``; table column ``edit_passes``)."""
    editing_samples: int | None = None
    """With ``editing_passes=single``: edits per preset; null: EDITS_PER_SINGLE_PASS (5,000, the figure issue 26
    gives for MFM's Table 3). The first replication's items in a seeded random order, repeated while more edits are
    asked than there are items (each item then edited ⌊N/n⌋ or ⌈N/n⌉ times, every repetition from its own noise).
    per_replication mode edits each replication's items once: there it must stay null."""
    edit_settings: str = "paper"
    """Flow edits' steps, ς and guidance (mfm.editing.EDIT_SETTINGS): 'paper' (the MFM paper's §4.1: 30 Euler
    steps, ς = 0.2; guidance 1.0 as its edit.py) or 'reference-debug' (edit.py's debug presets: 100 steps, ς per
    task, interpolation one step). Edits integrate with these steps and guidance whatever the sampling point's (a
    diffusion model's replacement edits use the point's sampler, steps and guidance)."""
    edit_rewrite_until: dict[str, float] = dataclasses.field(default_factory=dict)
    """ς per preset overriding the settings' (e.g. {upper_body: 0.1}); empty: the settings' values."""
    edit_steps: int = 0
    """Euler steps of every flow edit; 0: the settings' (per preset)."""
    edit_guidance: float | None = None
    """Guidance scale of a flow edit; null: the settings'."""
    edit_restore_known: bool = False
    """Diffusion edits: copy the source into the kept part of the output after the last step. false (FLAME's kept
    joints, and what the flow edits do): the kept part is what the sampler made of it, so both methods are scored
    alike (the root translation aside: ``edit_reference_translation``)."""
    edit_reference_translation: bool = True
    """Diffusion edits (FLAME's replacement procedure): copy the source's root translation into the output after
    the smoothing, as FLAME's edit_motion.py (use_reference_translation: true): on our features the root dims
    (rotation velocity, linear velocity, height) wherever the edit keeps the root, every frame of an upper-body edit
    (mfm.diffusion_sampling.copy_reference_root). false: the chain's output. Flow edits (MFM's procedure) never
    copy. Results record it (``editing_settings.reference_translation``); only diffusion units' keys carry it."""

    def __post_init__(self) -> None:
        coerce_fields(self)
        unknown = [p for p in self.editing if p not in EDIT_PRESETS]
        _require(not unknown, f"tasks.editing: unknown preset(s) {unknown}; known: {list(EDIT_PRESETS)}")
        _require(self.editing_replications >= 0, "tasks.editing_replications must be >= 0")
        if self.editing_passes == "single":
            _require(self.editing_replications <= 1,
                     f"tasks.editing_passes=single edits in one replication: tasks.editing_replications must be 0 or "
                     f"1, got {self.editing_replications}")
            _require(self.editing_samples is None or self.editing_samples >= 1,
                     f"tasks.editing_samples must be >= 1 (or null: {EDITS_PER_SINGLE_PASS}), got "
                     f"{self.editing_samples}")
        else:
            _require(self.editing_samples is None,
                     "tasks.editing_samples sizes the single editing pass: set tasks.editing_passes=single, or leave "
                     "it null (per_replication edits each replication's items once)")
        _require(self.edit_settings in EDIT_SETTINGS,
                 f"tasks.edit_settings must be one of {list(EDIT_SETTINGS)}, got {self.edit_settings!r}")
        unknown = [p for p in self.edit_rewrite_until if p not in EDIT_PRESETS]
        _require(not unknown, f"tasks.edit_rewrite_until: unknown preset(s) {unknown}; known: {list(EDIT_PRESETS)}")
        _require(all(0.0 <= v <= 1.0 for v in self.edit_rewrite_until.values()),
                 f"tasks.edit_rewrite_until values must be in [0, 1], got {self.edit_rewrite_until}")
        _require(self.edit_steps >= 0, f"tasks.edit_steps must be >= 0 (0: the settings'), got {self.edit_steps}")
        _require(self.text_to_motion or self.composition,
                 "tasks.text_to_motion and tasks.composition are both false: nothing to evaluate")

    def single_pass_edits(self) -> int:
        """``editing_passes=single``: the edits per preset of the pass (``editing_samples`` or its default)."""
        return EDITS_PER_SINGLE_PASS if self.editing_samples is None else self.editing_samples

    def edit_setup(self) -> dict[str, Any]:
        """The flow edits' settings as run: name, steps (the settings' base count and ``steps_per_preset``, what
        each preset runs), ς per preset, guidance, and the overridden values."""
        settings = EDIT_SETTINGS[self.edit_settings]
        record = settings.record()
        record["rewrite_until"] = {p: self.edit_rewrite_until.get(p, settings.rewrite_time(p)) for p in EDIT_PRESETS}
        record["steps"] = self.edit_steps or settings.steps
        record["steps_per_preset"] = {p: self.edit_steps or settings.steps_for(p) for p in EDIT_PRESETS}
        record["guidance"] = settings.guidance if self.edit_guidance is None else self.edit_guidance
        record["overridden"] = ([f"rewrite_until.{p}" for p in self.edit_rewrite_until]
                                + (["steps"] if self.edit_steps else [])
                                + (["guidance"] if self.edit_guidance is not None else []))
        record["diffusion_restore_known"] = self.edit_restore_known
        return record


SWITCH_NAMES = {"absolute": 1.0, "relative": 0.0, "humanml3d": HUMANML3D_SWITCH, "babel": BABEL_SWITCH}
"""composition.switch names: 'absolute' = never switch (the absolute-only baseline, flow time 1.0), 'relative' =
relative from the start (0.0), FlowMDM's HumanML3D / Babel ``bpe_denoising_step`` (60 / 125) as flow times."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class CompositionConfig:
    """FlowMDM's composition evaluation (pipeline.evaluation.composition); runs with ``tasks.composition=true``."""

    switch: tuple[float | str, ...] = ("relative", "humanml3d", "absolute")
    """Flow times from which the bpe model runs in relative mode, one unit each; or names of SWITCH_NAMES.
    1.0 / 'absolute' is the absolute-only baseline (same model, same noise), 0.0 / 'relative' relative-only."""
    num_sequences: int = 0
    """Composed sequences per replication; 0: enough for every eligible test item to appear at least once."""
    segments_per_sequence: int = 32
    """FlowMDM: 32 (text, length) segments per sequence (one R-precision batch); fewer eligible test items: that many
    (recorded)."""
    scenario: str = "all"
    """'all' (every test item) or a key of ``length_bins``: only items whose length lies in that bin."""
    length_bins: dict[str, tuple[int, int]] = dataclasses.field(default_factory=dict)
    """Scenario name -> [min, max] segment length in frames (inclusive), e.g. {short: [70, 110]}."""
    transition_window: int = 60
    """Frames centred on every boundary for the transition metrics. FlowMDM: 60 at 20 fps (HumanML3D), 30 at 30 fps
    (Babel); set it for other frame rates (it is recorded with its length in seconds)."""
    gt_transitions: Literal["crops", "concatenated"] = "crops"
    """Reference windows of the transition FID / Diversity: 'crops' = one seeded window-long crop of every test clip
    at least that long (FlowMDM's HumanML3D 'gt_transitions' loader); 'concatenated' = the GT clips of consecutive
    segments of the composition set joined and cropped around their boundary (a hard cut)."""
    gt_jerk: float | None = None
    """AUJ's reference jerk; None: the average jerk of this dataset's test clips (cached, recorded). FlowMDM's
    constants: 0.033031363 (HumanML3D), 0.016383045 (Babel)."""
    replications: int = 0
    """0: protocol.replications (FlowMDM: 3 fast, 10 final)."""
    seed: int = 0
    """Draws the composition set and the sequences' noise (the same noise for every switch point)."""

    def __post_init__(self) -> None:
        coerce_fields(self)
        _require(bool(self.switch), "composition.switch must list at least one switch point")
        self.switch_times()  # validates
        _require(self.num_sequences >= 0, f"composition.num_sequences must be >= 0, got {self.num_sequences}")
        _require(self.segments_per_sequence >= 2,
                 f"composition.segments_per_sequence must be >= 2 (transitions need two segments), got "
                 f"{self.segments_per_sequence}")
        _require(self.transition_window >= 4,
                 f"composition.transition_window must be >= 4 frames (jerk needs 4), got {self.transition_window}")
        _require(self.replications >= 0, f"composition.replications must be >= 0, got {self.replications}")
        _require(self.seed >= 0, f"composition.seed must be >= 0, got {self.seed}")
        _require(self.scenario == "all" or self.scenario in self.length_bins,
                 f"composition.scenario={self.scenario!r} is neither 'all' nor a key of composition.length_bins "
                 f"({sorted(self.length_bins)}); define it, e.g. "
                 f"composition.length_bins={{{self.scenario}: [70, 110]}}")
        for name, (low, high) in self.length_bins.items():
            _require(1 <= low <= high, f"composition.length_bins.{name} must be [min, max] with 1 <= min <= max, "
                                       f"got [{low}, {high}]")
        _require(self.gt_jerk is None or (math.isfinite(self.gt_jerk) and self.gt_jerk >= 0),
                 f"composition.gt_jerk must be a non-negative number or null, got {self.gt_jerk}")

    def switch_times(self) -> tuple[float, ...]:
        """The switch points as flow times in [0, 1], in the given order, each once (1.0 = absolute-only)."""
        times: list[float] = []
        for value in self.switch:
            if isinstance(value, str):
                _require(value.lower() in SWITCH_NAMES,
                         f"composition.switch: unknown name {value!r}; use a flow time in [0, 1] or one of "
                         f"{sorted(SWITCH_NAMES)}")
                value = SWITCH_NAMES[value.lower()]
            _require(0.0 <= value <= 1.0, f"composition.switch: flow times lie in [0, 1], got {value}")
            if value not in times:
                times.append(float(value))
        return tuple(times)

    def length_range(self) -> tuple[int, int] | None:
        """The scenario's [min, max] segment lengths, None for 'all'."""
        return None if self.scenario == "all" else tuple(self.length_bins[self.scenario])


@dataclasses.dataclass(frozen=True, kw_only=True)
class EvalDataConfig:
    manifest: str = ""
    """Dataset manifest; empty: the one the checkpoint was trained on (its recorded location; for a few-step student
    trained on a teacher's pair set, the teacher's dataset the pair set was made from)."""
    split: str = "test"
    format: Literal["tar", "parquet"] = "tar"
    allow_external_shards: bool = False
    """Read shards the manifest lists outside its own folder or URL (absolute paths, other URLs, '..'): refused by
    default, as in training (``pipeline.config.DataConfig.allow_external_shards``)."""
    allow_other_test_set: bool = False
    """A run's results are on one test set (dataset id and split; the id is derived from the manifest's shard list
    when it is read). false: a job whose test set differs from the one the run's earlier results used (in its
    evaluation folder, or in the run's default <run>/eval when output.dir is elsewhere) is refused before anything
    is evaluated: the data changed (rebuilt, edited, another manifest) and the numbers would not compare. true:
    evaluate anyway, into an output.dir whose table is empty or on this test set (one table never holds two)."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class OutputConfig:
    dir: str = ""
    """Evaluation folder; empty: <run_dir>/eval."""
    claim_timeout_s: float = 3600.0
    """A claim without a heartbeat for this long belongs to a dead job and may be taken over. A claim from this host
    whose pid is gone is taken over at once, whatever its age: this timeout is for jobs on other hosts."""
    poll_s: float = 300.0
    """--watch without --once: seconds between scans of the run folder."""
    order: Literal["newest", "oldest"] = "newest"
    wandb: Literal["auto", "offline", "online", "disabled"] = "auto"
    """auto: the environment's WANDB_MODE when set, else the training run's mode (config.yaml train.wandb; its auto
    is offline). An explicit offline/online/disabled wins over WANDB_MODE (pipeline.config.wandb_mode)."""
    plots: bool = True

    def __post_init__(self) -> None:
        coerce_fields(self)
        _require(self.claim_timeout_s > 0, "output.claim_timeout_s must be > 0")
        _require(self.poll_s > 0, "output.poll_s must be > 0")


@dataclasses.dataclass(frozen=True, kw_only=True)
class EvalConfig:
    """Everything the evaluation job needs; every field that changes the numbers is part of a result's key."""

    protocol: ProtocolConfig = dataclasses.field(default_factory=ProtocolConfig)
    sampling: SamplingConfig = dataclasses.field(default_factory=SamplingConfig)
    evaluator: EvaluatorConfig = dataclasses.field(default_factory=EvaluatorConfig)
    tasks: TasksConfig = dataclasses.field(default_factory=TasksConfig)
    composition: CompositionConfig = dataclasses.field(default_factory=CompositionConfig)
    data: EvalDataConfig = dataclasses.field(default_factory=EvalDataConfig)
    output: OutputConfig = dataclasses.field(default_factory=OutputConfig)

    def __post_init__(self) -> None:
        named = self.protocol.sampling_point
        if named == "sweep":
            return
        defaults = SamplingConfig()
        swept = [f"sampling.{name}={list(value) if isinstance(value, tuple) else value}"
                 for name in ("solvers", "steps", "steps_per_solver", "guidance")
                 if (value := getattr(self.sampling, name)) != getattr(defaults, name)]
        _require(not swept, f"protocol.sampling_point={named} fixes the sampling point "
                            f"({SAMPLING_POINT_SOURCES[named]}), so {', '.join(swept)} would be ignored: leave the "
                            "sampling lists (and --solver/--steps/--guidance) out, or set "
                            "protocol.sampling_point=sweep to evaluate them")

    def sampling_points(self, skeleton: str) -> list[SamplingPoint]:
        """The points to evaluate for a checkpoint on ``skeleton``: the protocol's named point (paper / released,
        whose steps follow the dataset) or, with ``protocol.sampling_point=sweep``, the sampling sweep."""
        point = self.protocol.named_point(skeleton)
        return self.sampling.points() if point is None else [point]


def load_eval_config(protocol: str = "full", preset: str | Path | None = None,
                     overrides: Sequence[str] = ()) -> EvalConfig:
    """Defaults <- the protocol's preset (configs/eval_{full,fast,mdm}.yaml), or ``preset`` instead of it, <- dotted
    overrides."""
    if preset is None:
        if protocol not in PROTOCOL_PRESETS:
            raise ConfigError(f"--protocol must be one of {sorted(PROTOCOL_PRESETS)}, got {protocol!r}")
        preset = PROTOCOL_PRESETS[protocol]
    return load_config(EvalConfig, preset, overrides)


def _comma_list(text: str, flag: str) -> list:
    return [parse_yaml(v.strip(), source=flag) for v in text.split(",") if v.strip()]


def sweep_overrides(solvers: str | None, steps: str | Sequence[str] | None, guidance: str | None) -> list[str]:
    """``--solver euler,midpoint --steps 5,10 --guidance 2.5`` as config overrides (comma lists). ``--steps`` may
    be given again as ``SOLVER=5,10,25`` for one solver's own step counts (``sampling.steps_per_solver``)."""
    out = []
    for key, text in (("solvers", solvers), ("guidance", guidance)):
        if text:
            out.append(f"sampling.{key}={json.dumps(_comma_list(text, f'--{key}'))}")
    per_solver = {}
    for text in [steps] if isinstance(steps, str) else (steps or []):
        solver, sep, counts = text.partition("=")
        if sep:
            per_solver[solver.strip()] = _comma_list(counts, "--steps")
        else:
            out.append(f"sampling.steps={json.dumps(_comma_list(text, '--steps'))}")
    if per_solver:
        out.append(f"sampling.steps_per_solver={json.dumps(per_solver)}")
    return out


@dataclasses.dataclass(frozen=True)
class SamplingPoint:
    solver: str
    steps: int
    guidance: float

    @property
    def name(self) -> str:
        return f"{self.solver}-{self.steps}steps-g{self.guidance:g}"


SAMPLING_POINTS: dict[str, dict[str, SamplingPoint]] = {
    "paper": {"humanml3d": SamplingPoint("euler", 10, 2.5), "kit": SamplingPoint("euler", 10, 2.5)},
    "released": {"humanml3d": SamplingPoint("euler", 100, 2.5), "kit": SamplingPoint("euler", 50, 2.5)},
}
"""MFM's two text-to-motion sampling points per skeleton (``protocol.sampling_point``). paper: the paper evaluates
text-to-motion at N = 10 Euler steps. released: dongzhuoyao/motionfm 08eb88d's evaluation commands, Euler
(torchdiffeq ``odeint`` with ``step_size``) at config_base.yaml: 41 ``step_size: 0.01`` = 100 steps for HumanML3D
(README.md: 75 passes no step size) and README.md: 65 ``ode_kwargs.step_size=0.02`` = 50 steps for KIT; both
commands pass ``guidance_param=2.5`` (the paper point uses the same scale)."""
SAMPLING_POINT_SOURCES = {
    "paper": "MFM paper: 10 Euler steps, guidance 2.5",
    "released": "MFM's released evaluation commands: Euler, 100 steps for HumanML3D (step_size 0.01), 50 for KIT "
                "(step_size 0.02), guidance 2.5",
}
