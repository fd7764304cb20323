"""Evaluate checkpoints: text-to-motion (or action-to-motion) metrics, editing and the FLAME-paper metrics (APE/AVE as
TEMOS defines them, mCLIP, MID), with 95 % CIs, and
plausibility figures (bone lengths, floor penetration, foot skating, jerk vs ground truth) beside the ground truth's.

    python launch/evaluate.py --checkpoint runs/default/checkpoints/step-00001500 --protocol fast
    python launch/evaluate.py --watch runs/default --once                      # every complete checkpoint, once
    python launch/evaluate.py --watch runs/default --steps 2,5,10,20,50 --solver euler,midpoint   # FID vs NFE
    accelerate launch --num_processes 2 launch/evaluate.py --checkpoint ...    # generation split across ranks
    python launch/evaluate.py --checkpoint runs/flow --checkpoint runs/diffusion --protocol fast \
        --solver euler,midpoint,dopri5,ddim,ddpm --steps 5,10,20,50,100,1000 --steps midpoint=5,10,25,50 \
        output.dir=eval-nfe              # MFM's FID vs NFE, flow vs diffusion: one sweep, one plot
    python launch/evaluate.py --checkpoint ... evaluator.kind=t2m evaluator.t2m_checkpoint_dir=DIR \
        evaluator.t2m_glove_dir=DIR                                              # the official T2M evaluator
    python launch/evaluate.py --checkpoint ... --protocol mdm evaluator.kind=t2m ...   # MDM/MFM's loop, quirks too
    python launch/evaluate.py --checkpoint runs/bpe --protocol fast tasks.composition=true \
        composition.switch=[relative,humanml3d,0.25,0.5,absolute]                # FlowMDM composition, bpe+pccat

Settings: configs/eval_{full,fast,mdm}.yaml (--protocol) or --config YAML, then ``key.sub=value`` overrides
(pipeline/evaluation/config.py EvalConfig). Diffusion baselines (train.objective=diffusion) take --solver ddpm|ddim and
--steps respaced from their training steps (e.g. 1000 or 50); a sweep listing both kinds runs each checkpoint's own
(flow: ODE solvers, diffusion: ddpm/ddim). ``--steps SOLVER=a,b`` gives one solver its own step counts; adaptive
solvers (dopri5) run once whatever the steps. The evaluator defaults to the one launch/train_evaluator.py trained on the
checkpoint's dataset. Results go to <run>/eval (output.dir=): one JSON per checkpoint and setting, results.jsonl /
results.parquet, plots/. Concurrent jobs (cron, Slurm, CronJob) never evaluate a unit twice (claim files). A claim
left by a killed job on this host (its pid is gone) is taken over at once; one from another host after
output.claim_timeout_s without a heartbeat. The last lines summarise the job: units skipped because another live job
holds them, and (--watch) checkpoints deleted by training (train.keep_last) before any evaluation, as
``pruned_before_evaluation: [steps]`` (training lists every save in <run>/checkpoints/saved.jsonl, so one saved and
pruned between two --once jobs is reported too). Keep checkpoints for the evaluator with train.keep_last=0 (or a
value that covers the time between evaluator runs), or run ``--watch`` alongside training.
Exit code: 0 all done (every unit evaluated, now or before), 3 some units skipped because other live jobs hold them
and have not finished them (run again later), 2 bad settings, a missing evaluator or checkpoint, test data that does
not verify or is not the test set of the run's earlier results (data.allow_other_test_set=true), 143 on SIGTERM
(claims released), 1 other errors. Pruned checkpoints are reported, not an error (they cannot be evaluated again).
The results folder must be new, empty or an evaluation folder of ours (mfm-eval.json, or one an earlier version
wrote); another tool's folder (its index.html, plots/) is refused with exit code 2 before anything is written.

Composition (``tasks.composition=true``, pipeline/evaluation/composition.py): FlowMDM's protocol on a bpe + pccat model,
one result per switch point (``composition.switch``: flow times, 'absolute' = 1.0 the absolute-only baseline,
'relative' = 0.0, 'humanml3d' = FlowMDM's 60 steps); ``composition.segments_per_sequence`` (32),
``composition.num_sequences`` (0: cover the test set), ``composition.scenario`` / ``composition.length_bins``,
``composition.transition_window`` (60 frames at 20 fps). ``tasks.text_to_motion=false`` skips the T2M units.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys

from pipeline.config import ConfigError, describe_config
from pipeline.distributed import Dist, ends_rank_processes
from pipeline.evaluation.config import (
    PROTOCOL_PRESETS,
    load_eval_config,
    sweep_overrides,
)
from pipeline.evaluation.job import (
    EvaluationJob,
    JobSummary,
    result_label,
    summary_line,
)
from pipeline.evaluation.spaces import EvaluationError, EvaluatorUnavailable
from pipeline.evaluation.store import EvalFolderError, MixedTestSetError


@ends_rank_processes
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    target = parser.add_mutually_exclusive_group()
    target.add_argument("--checkpoint", action="append", help="a step-XXXXXXXX folder (or a run folder: its newest "
                                                                "complete one); repeat it to sweep several in one job")
    target.add_argument("--watch", metavar="RUN_DIR", help="evaluate every complete checkpoint of a run, once each")
    parser.add_argument("--once", action="store_true", help="with --watch: one scan, then exit (cron / CronJob)")
    parser.add_argument("--protocol", choices=sorted(PROTOCOL_PRESETS), default="full",
                        help="full: 20 replications, fast: 3 (our loop); mdm: the MDM/MFM reference loop, rule by "
                             "rule (configs/eval_mdm.yaml, docs/protocol.md)")
    parser.add_argument("--config", help="a YAML preset instead of configs/eval_<protocol>.yaml")
    parser.add_argument("--solver", help="comma list, e.g. euler,midpoint")
    parser.add_argument("--steps", action="append", help="comma list, e.g. 5,10,20; again as SOLVER=5,10 for one "
                                                         "solver's own counts")
    parser.add_argument("--guidance", help="comma list, e.g. 1,2.5")
    parser.add_argument("--out", help="the results folder (the same as output.dir=...)")
    parser.add_argument("--print-config", action="store_true", help="print every key with its value, default and "
                        "meaning, then exit")
    parser.add_argument("overrides", nargs="*", metavar="key.sub=value", help="config overrides")
    args = parser.parse_intermixed_args(argv)
    if not (args.checkpoint or args.watch or args.print_config):
        parser.error("one of the arguments --checkpoint --watch is required")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        overrides = [*args.overrides, *([f"output.dir={args.out}"] if args.out else [])]
        cfg = load_eval_config(args.protocol, args.config,
                               sweep_overrides(args.solver, args.steps, args.guidance) + overrides)
    except (ConfigError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.print_config:
        print("\n".join(describe_config(cfg)))
        return 0
    # SIGTERM (Slurm preemption, a CronJob's deadline) unwinds like an exception: claims are released on the way out.
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))
    with Dist(mixed_precision="no") as dist:
        job = EvaluationJob(cfg, dist)
        try:
            if args.checkpoint:
                results = [result for folder in args.checkpoint for result in job.evaluate_checkpoint(folder)]
                for result in results:
                    dist.print0(f"{result_label(result)}: {summary_line(result)}")
                dist.print0(f"{len(results)} result(s) written")
                summary: JobSummary = job.summary(len(results))
            else:
                count = job.watch(args.watch, once=args.once)
                dist.print0(f"{count} unit(s) evaluated by this job")
                summary = job.summary(count)
        except (EvaluatorUnavailable, EvaluationError, EvalFolderError, MixedTestSetError, FileNotFoundError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        dist.print0("wall time per phase: " + ", ".join(f"{k} {v:.2f} s" for k, v in job.timings.items()))
        for line in summary.lines():
            dist.print0(line)
    return summary.exit_code


if __name__ == "__main__":
    sys.exit(main())
