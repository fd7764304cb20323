"""Make a few-step student of a trained flow-matching checkpoint: ``distill.method`` names the method (reflow,
shortcut).

    python launch/distill.py --teacher runs/default --out runs/student train.max_steps=2000
    accelerate launch launch/distill.py --teacher runs/default --out runs/student distill.pairs_per_caption=4
    python launch/distill.py --teacher runs/default --out runs/shortcut distill.method=shortcut

reflow (Liu et al. 2022; Luhman & Luhman 2021 at one step): the teacher integrates its guided ODE with its own
default sampler (euler, its model.sampling_steps, its guidance and guided_features, no output smoothing) from seeded
noise for every caption of its training split (pipeline/generation/pairs.py: the pair set in OUT/pairs/, made once,
shared out over the ranks); then the student, the teacher's architecture initialised from its EMA weights, trains
with the ordinary Trainer on the straight path from THAT noise to THAT motion (train.flow_noise=recorded), so Euler
with distill.student_steps (default 2) steps lands near the teacher's endpoint. It trains at uniform times along
the whole path; train.flow_time_sampling=grid (train.flow_time_grid_steps=2: t = 0 and 1/2, serving 1 and 2 steps;
rectified flow's k-step distillation) trains only the times its sampler visits: better bones and jerk at 1 step,
slightly lower FID and R@1 (docs/few-step.md, "Training at the sampler's times"). Guidance is distilled in: the student
samples with guidance 1 (one pass per step) and trains without condition dropout (model.sampling_guidance=1,
model.cond_drop_prob=0 in its config). Before training, the teacher solves distill.flow_map_probes pairs again from a
slightly perturbed noise: the median of how far its motion moves per unit change of the noise goes into the pair
set's manifest, the student's distill.teacher_flow_map_amplification and its model card, with a warning when it is
too rough for reflow to fit (docs/few-step.md, "A rough teacher").

shortcut (Frans et al. 2024, mfm/shortcut.py): no pair set. The student is the teacher's network with a step-size
input (model.shortcut_levels = distill.shortcut_levels, default 2: Euler in 1 or 2 steps), initialised from the
teacher's EMA weights (the step-size embedding starts at zero, so it starts as the teacher), and trains on the
teacher's own dataset: flow matching on most rows (the flow field, with the teacher's condition dropout), and on
train.shortcut_fraction of them self-consistency, one step of d against two of d/2 of its own, the finest level's
taken on its flow field guided at the teacher's scale (train.shortcut_guidance, model.guided_features), so the
guidance is built into its few steps: it samples them with guidance 1 (model.sampling_guidance=1).

Settings: the teacher's resolved training config, with the student's settings above (its optimizer too: a Muon
teacher's student fine-tunes with Muon, its optim.muon_lr scaled by the student's optim.lr over the teacher's unless
given; optim.optimizer=adamw is an override; a reflow student's bone term holds each bone to its median length over
the teacher's motion, train.flow_bone_target=clip_median, unless given), then ``key.sub=value`` overrides
(train.max_steps, optim.lr, distill.pairs_per_caption, ...). The ``distill`` section (method, teacher
checkpoint path, id and step, the teacher's sampler) is recorded in OUT/config.yaml and every checkpoint; set by this
command, it is not an override (nor are data.manifest, train.out_dir, train.init_from, train.flow_noise,
train.shortcut_guidance, model.shortcut_levels and model.sampling_steps: use distill.shortcut_levels and
distill.student_steps). Running the same command again reuses the pair set and resumes
training (train.resume=auto). Another student of the same pairs starts in a new folder holding only them
(``mkdir runs/B && ln -s ../A/pairs runs/B/pairs``, or a copy). The student is a checkpoint like any other:
launch/sample.py, MotionPipeline, the evaluator and launch/export.py take it, sampling it in distill.student_steps
steps unless --steps says otherwise.

Exit codes as launch/train.py: 0 at train.max_steps, 128 + N after a clean stop on signal N, 2 for settings, a
teacher or data refused (one line on stderr), 1 when a checkpoint could not be saved.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import shlex
import sys
from pathlib import Path
from typing import Any

from pipeline import checkpoint as ckpt
from pipeline.checkpoint import CheckpointError, ResumeConflictError
from pipeline.cli.train import fail
from pipeline.config import ConfigError, DistillConfig, TrainConfig, describe_config, load_config, parse_override
from pipeline.data.stages import DataError
from pipeline.distributed import Dist, MixedPrecisionError, ends_rank_processes
from pipeline.generation.inference import TrainedModel, load_trained_model
from pipeline.generation.pairs import FLOW_MAP_KEY, PairSetError, make_pairs, pairs_dir
from pipeline.training.run_folder import RUN_LOCK, RunFolderLock, check_run_folder, write_run_marker
from pipeline.training.trainer import CheckpointSaveError, Trainer
from preprocess.shards import MANIFEST_NAME, ManifestError, OutputFolderError

FIXED_BY_METHOD = ("data.manifest", "train.out_dir", "train.init_from", "train.flow_noise", "model.sampling_steps",
                   "model.shortcut_levels", "train.shortcut_guidance")
"""Keys the methods set: refused as overrides (the message says why)."""


def method_of(overrides: list[str]) -> str:
    """The ``distill.method`` the overrides name (default reflow)."""
    for text in overrides:
        path, value = parse_override(text)
        if ".".join(path) == "distill.method":
            return str(value)
    return DistillConfig.method


def student_config(teacher: TrainedModel, teacher_config: dict[str, Any], out: Path, overrides: list[str]
                   ) -> TrainConfig:
    """The student's resolved config: the teacher's training config, the student's settings (module docstring),
    the overrides, then the recorded teacher fields of the ``distill`` section."""
    given: set[str] = set()
    for text in overrides:
        key = ".".join(parse_override(text)[0])
        given.add(key)
        if key in FIXED_BY_METHOD or key.startswith("distill.teacher"):
            raise ConfigError(f"override {text!r}: {key} is set by launch/distill.py (the pair set, --out, the "
                              "teacher and its guidance; the student's steps are distill.student_steps, its levels "
                              "distill.shortcut_levels), not a setting here")
    base = {section: dict(values) for section, values in teacher_config.items() if section != "distill"}
    method = method_of(overrides)
    base["model"].update(sampling_guidance=1.0)
    base["train"].update(out_dir=str(out), init_from=str(teacher.checkpoint), resume="auto",
                         resume_discard_newer=False)
    if method == "reflow":
        base["data"].update(manifest=str(pairs_dir(out) / MANIFEST_NAME), unit_length=1)
        base["model"].update(cond_drop_prob=0.0)
        base["train"].update(flow_noise="recorded", val_every=0)
    else:  # shortcut: the teacher's data; condition dropout kept (the flow field's guidance builds the levels)
        base["train"].update(shortcut_guidance=float(teacher.model_config.sampling_guidance))
    cfg = load_config(TrainConfig, base, overrides)
    if "optim.muon_lr" not in given:
        cfg = with_muon_rate_following_lr(cfg, teacher_lr=float(teacher_config["optim"]["lr"]))
    if method == "reflow" and "train.flow_bone_target" not in given:
        cfg = with_bones_held_to_their_median(cfg)
    settings = cfg.distill or DistillConfig()
    teacher_model = teacher.model_config
    settings = dataclasses.replace(
        settings, teacher=str(teacher.checkpoint),
        teacher_checkpoint_id=ckpt.checkpoint_id(ckpt.read_marker(teacher.checkpoint)), teacher_step=teacher.step,
        teacher_solver="euler", teacher_steps=teacher_model.sampling_steps,
        teacher_guidance=float(teacher_model.sampling_guidance), teacher_guided_features=teacher_model.guided_features)
    return dataclasses.replace(cfg, distill=settings,
                               model=dataclasses.replace(cfg.model, sampling_steps=settings.student_steps,
                                                         shortcut_levels=(settings.shortcut_levels
                                                                          if settings.method == "shortcut" else 0)))


def with_muon_rate_following_lr(cfg: TrainConfig, teacher_lr: float) -> TrainConfig:
    """``cfg`` with Muon's rate scaled as its AdamW rate is (by the student's optim.lr over the teacher's): every
    student recipe (docs/few-step.md) fine-tunes at its own optim.lr, and the teacher's optim.muon_lr (a
    from-scratch rate, 0.02 in the synthetic preset) would otherwise move its matrices 3-30 times further than the
    rest. Not called when optim.muon_lr is given as an override."""
    if cfg.optim.optimizer != "muon":
        return cfg
    scaled = cfg.optim.muon_lr * (cfg.optim.lr / teacher_lr)
    return dataclasses.replace(cfg, optim=dataclasses.replace(cfg.optim, muon_lr=scaled))


def with_bones_held_to_their_median(cfg: TrainConfig) -> TrainConfig:
    """``cfg`` with the bone term (when on) holding each bone to its median length over the pair's motion
    (train.flow_bone_target=clip_median): a pair's motion is the teacher's raw output, whose bones vary from frame to
    frame, and a student held to each frame's length learns that variation; held to the median, the synthetic
    preset's 1- and 2-step students' bones came out steadier than their teacher's (docs/few-step.md, "Bones held to
    their median"). Not called when train.flow_bone_target is given as an override."""
    if cfg.train.flow_bone_weight == 0:
        return cfg
    return dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, flow_bone_target="clip_median"))


def with_flow_map(cfg: TrainConfig, pair_manifest: Path) -> TrainConfig:
    """``cfg`` with the pair set's probed teacher flow-map amplification recorded in its distill section."""
    flow_map = json.loads(pair_manifest.read_text()).get(FLOW_MAP_KEY)
    median = None if flow_map is None else float(flow_map["amplification_median"])
    return dataclasses.replace(cfg, distill=dataclasses.replace(cfg.distill, teacher_flow_map_amplification=median))


def holds_only_a_pair_set(out: Path) -> bool:
    """``out`` holds a complete pair set at ``pairs/`` (made there, copied, or linked from another student's folder)
    and nothing else: a new student may start there and reuse the pairs (make_pairs checks they are its teacher's
    and settings')."""
    if not out.is_dir():
        return False
    entries = sorted(entry.name for entry in out.iterdir() if entry.name != RUN_LOCK)
    return entries == ["pairs"] and (pairs_dir(out) / MANIFEST_NAME).is_file()


def prepare_out_dir(out: Path, dist: Dist) -> None:
    """Rank 0: the folder is one a run may use (new, empty, a run of ours: a student being resumed, or a folder
    holding only a finished pair set for a new student to reuse), and from now on a run of ours (its marker), so the
    pair set may go inside it. Held under the run lock while checked."""
    if dist.is_main:
        if not holds_only_a_pair_set(out):
            check_run_folder(out)
        lock = RunFolderLock.acquire(out)
        try:
            write_run_marker(out, written_by="pipeline/cli/distill.py")
        finally:
            lock.release()
    dist.barrier()


@ends_rank_processes
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--teacher", required=True, help="the teacher: a step-XXXXXXXX folder or a run folder (its "
                        "newest complete checkpoint)")
    parser.add_argument("--out", required=True, help="the student's run folder (pairs/ goes inside it)")
    parser.add_argument("--print-config", action="store_true", help="print the student's every key, then exit")
    parser.add_argument("overrides", nargs="*", metavar="key.sub=value", help="config overrides")
    args = parser.parse_intermixed_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    out = Path(args.out)
    try:
        folder = ckpt.resolve_checkpoint(args.teacher)
        _, _, state = ckpt.load_checkpoint(folder)
        teacher = load_trained_model(folder)
        cfg = student_config(teacher, state["config"], out, args.overrides)
        if args.print_config:
            print("\n".join(describe_config(cfg)))
            return 0
        with Dist(mixed_precision=cfg.train.mixed_precision, loss_scaling=True) as dist:
            teacher = teacher.to(dist.device)
            prepare_out_dir(out, dist)
            if cfg.distill.method == "reflow":
                cfg = with_flow_map(cfg, make_pairs(teacher, cfg.distill, out, dist))
            return Trainer(cfg, dist).fit()
    except ResumeConflictError as exc:
        given = sys.argv[1:] if argv is None else argv
        again = shlex.join(["python", "launch/distill.py", *given, exc.continue_override])
        return fail(f"{exc}. The command that continues: {again}", 2)
    except (ConfigError, ManifestError, CheckpointError, FileNotFoundError, MixedPrecisionError, OutputFolderError,
            DataError, PairSetError) as exc:
        return fail(str(exc), 2)
    except CheckpointSaveError as exc:
        return fail(str(exc), 1)


if __name__ == "__main__":
    sys.exit(main())
