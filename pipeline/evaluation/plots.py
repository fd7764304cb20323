"""Plots of the results table (pipeline.evaluation.store): metrics against training step, FID against NFE.

* ``metrics_vs_step.png``: one panel per metric, one line per sampling setting (solver, steps, guidance, evaluator,
  protocol), mean with its 95 % interval as error bars; the ground-truth value as a dashed line.
* ``fid_vs_nfe_<checkpoint>.png``: MFM Figure 1 for a sweep over steps/solvers: FID (mean ± CI) against the number
  of function evaluations per motion, one line per (solver, guidance). Written for every checkpoint evaluated at
  two or more NFE values.

Rows are plain dicts as stored in results.jsonl (``row_kind`` 'generated' or 'ground_truth').
"""

from __future__ import annotations

import logging
import os
from collections import defaultdict
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

logger = logging.getLogger(__name__)

STEP_METRICS = ("fid", "r_precision_top3", "mm_dist", "diversity", "multimodality", "accuracy")
COMPOSITION_METRICS = (("r_precision_top3", "segments: R@3"), ("fid", "segments: FID"), ("peak_jerk", "transitions: PJ"),
                ("auj", "transitions: AUJ"))


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")  # files only; no display on cluster nodes
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> None:
    """Write atomically: concurrent evaluation jobs redraw the same files."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)


def _protocol(row: Mapping[str, Any]) -> str:
    """The protocol's name, and 'fixed items' for a text-to-motion row scored against one fixed ground-truth set
    (``protocol.redraw_items=false``, or a result from before the setting): its intervals are narrower, so it is
    never drawn as the same series as a re-drawn one."""
    fixed = row.get("task", "text_to_motion") == "text_to_motion" and not row.get("redraw_items")
    return f"{row.get('protocol')}, fixed items" if fixed else str(row.get("protocol"))


def _setting(row: Mapping[str, Any]) -> tuple:
    return (row.get("solver"), row.get("steps"), row.get("guidance"), row.get("evaluator_id"), _protocol(row))


def _label(setting: tuple) -> str:
    solver, steps, guidance, evaluator_id, protocol = setting
    return f"{solver} {steps} steps, w={guidance:g} ({protocol}, eval {str(evaluator_id)[-8:]})"


def _latest(rows: Sequence[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """One row per (row_key): the last written (a result re-evaluated under new settings has a new key)."""
    return list({row["row_key"]: row for row in rows}.values())


def plot_metrics_vs_step(rows: Sequence[Mapping[str, Any]], path: Path,
                         metric_names: Sequence[str] = STEP_METRICS) -> Path | None:
    """Metrics against training step; None when no row has a step and a metric to plot."""
    generated = [r for r in _latest(rows) if r.get("row_kind") == "generated"]
    present = [m for m in metric_names if any(r.get(m) is not None for r in generated)]
    if not generated or not present:
        return None
    plt = _pyplot()
    fig, axes = plt.subplots(1, len(present), figsize=(4.2 * len(present), 3.6), squeeze=False)
    series: dict[tuple, list] = defaultdict(list)
    for row in generated:
        series[_setting(row)].append(row)
    truth = {(_setting(r), r.get("dataset_id")): r for r in _latest(rows) if r.get("row_kind") == "ground_truth"}
    for ax, metric in zip(axes[0], present):
        for setting, points in sorted(series.items(), key=lambda kv: str(kv[0])):
            points = sorted((p for p in points if p.get(metric) is not None), key=lambda p: p["step"])
            if points:
                ax.errorbar([p["step"] for p in points], [p[metric] for p in points],
                            yerr=[p.get(f"{metric}_ci") or 0.0 for p in points], marker="o", capsize=3,
                            label=_label(setting))
        gt_values = {r[metric] for (setting, _), r in truth.items() if setting in series and r.get(metric) is not None}
        for value in sorted(gt_values)[:1]:  # one reference line: the ground truth is the same for every setting
            ax.axhline(value, linestyle="--", color="gray", linewidth=1, label="ground truth")
        ax.set_xlabel("training step")
        ax.set_title(metric)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    _save(fig, path)
    return path


def plot_fid_vs_nfe(rows: Sequence[Mapping[str, Any]], path: Path, checkpoint_name: str | None = None) -> Path | None:
    """FID against NFE (MFM Figure 1): one line per (checkpoint, solver, guidance) for one checkpoint name, or for
    every checkpoint evaluated into this folder when ``checkpoint_name`` is None (e.g. a flow-matching run and a
    diffusion baseline swept together). None with fewer than two NFE values."""
    generated = [r for r in _latest(rows) if r.get("row_kind") == "generated" and r.get("fid") is not None
                 and (checkpoint_name is None or r.get("checkpoint_name") == checkpoint_name)]
    if len({r["nfe"] for r in generated}) < 2:
        return None
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 4.2))
    lines: dict[tuple, list] = defaultdict(list)
    for row in generated:
        run = Path(str(row["checkpoint"])).parent.parent.name  # <run>/checkpoints/step-N -> <run>
        lines[(run, row["checkpoint_name"], row["solver"], row["guidance"], _protocol(row))].append(row)
    for (run, name, solver, guidance, protocol), points in sorted(lines.items(), key=lambda kv: str(kv[0])):
        points.sort(key=lambda p: p["nfe"])
        prefix = "" if checkpoint_name is not None else f"{run}/{name}: "
        ax.errorbar([p["nfe"] for p in points], [p["fid"] for p in points],
                    yerr=[p.get("fid_ci") or 0.0 for p in points], marker="o", capsize=3,
                    label=f"{prefix}{solver}, w={guidance:g} ({protocol})")
    nfes = sorted({r["nfe"] for r in generated})
    ax.set_xscale("log", base=2)
    ax.set_xticks(nfes, [f"{n:.0f}" for n in nfes])  # an adaptive solver's NFE is a mean (267.4): whole numbers
    ax.minorticks_off()
    ax.set_xlabel("NFE (network evaluations per motion; ×2 model passes with guidance)")
    ax.set_ylabel("FID")
    title = "FID vs NFE" if checkpoint_name is None else f"FID vs NFE, {checkpoint_name} (step {generated[0]['step']})"
    ax.set_title(title)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    _save(fig, path)
    return path


def _series_key(row: Mapping[str, Any]) -> tuple:
    return (row.get("checkpoint_name"), row.get("solver"), row.get("steps"), row.get("guidance"),
            row.get("scenario"), row.get("protocol"), row.get("evaluator_id"), row.get("composition_set"))


def plot_composition_switch(rows: Sequence[Mapping[str, Any]], path: Path) -> Path | None:
    """Per-segment R@3 / FID and transition PJ / AUJ against the switch flow time (0 = relative-only, 1 =
    absolute-only), one line per checkpoint and setting, GT as dashed lines; a last panel puts segment FID against
    PJ (the trade-off). None without composition rows."""
    latest = {row["row_key"]: row for row in rows if row.get("task") == "composition"}.values()
    generated = [r for r in latest if r["row_kind"] == "generated"]
    if not generated:
        return None
    plt = _pyplot()
    truth = {_series_key(r): r for r in latest if r["row_kind"] == "ground_truth"}
    series: dict[tuple, list] = defaultdict(list)
    for row in generated:
        series[_series_key(row)].append(row)
    fig, axes = plt.subplots(1, len(COMPOSITION_METRICS) + 1, figsize=(4.2 * (len(COMPOSITION_METRICS) + 1), 3.8))
    for key, points in sorted(series.items(), key=lambda kv: str(kv[0])):
        points.sort(key=lambda r: r["switch"])
        label = f"{key[0]}: {key[1]} {key[2]} steps, w={key[3]:g} ({key[4]}, {key[5]})"
        for ax, (metric, title) in zip(axes, COMPOSITION_METRICS):
            shown = [p for p in points if p.get(metric) is not None]
            line = ax.errorbar([p["switch"] for p in shown], [p[metric] for p in shown],
                               yerr=[p.get(f"{metric}_ci") or 0.0 for p in shown], marker="o", capsize=3, label=label)
            if key in truth and truth[key].get(metric) is not None:
                ax.axhline(truth[key][metric], linestyle="--", linewidth=1, color=line[0].get_color())
            ax.set_title(title)
            ax.set_xlabel("switch (flow time; 0 relative-only, 1 absolute-only)")
            ax.grid(alpha=0.3)
        trade = axes[-1]
        trade.plot([p["peak_jerk"] for p in points], [p["fid"] for p in points], marker="o")
        for p in points:
            trade.annotate(f"{p['switch']:.3g}", (p["peak_jerk"], p["fid"]), fontsize=7, xytext=(3, 3),
                           textcoords="offset points")
    axes[-1].set_xlabel("transition peak jerk")
    axes[-1].set_ylabel("segment FID")
    axes[-1].set_title("trade-off (labels: switch)")
    axes[-1].grid(alpha=0.3)
    axes[0].legend(fontsize=6)
    _save(fig, path)
    return path


def update_plots(rows: Sequence[Mapping[str, Any]], plots_dir: Path) -> list[Path]:
    """Redraw every plot from the whole table; returns the files written."""
    written = []
    step_plot = plot_metrics_vs_step(rows, plots_dir / "metrics_vs_step.png")
    if step_plot is not None:
        written.append(step_plot)
    for name in sorted({r.get("checkpoint_name") for r in rows if r.get("checkpoint_name")}):
        nfe_plot = plot_fid_vs_nfe(rows, plots_dir / f"fid_vs_nfe_{name}.png", name)
        if nfe_plot is not None:
            written.append(nfe_plot)
    if len({r.get("checkpoint_id") for r in rows if r.get("row_kind") == "generated"}) > 1:
        combined = plot_fid_vs_nfe(rows, plots_dir / "fid_vs_nfe_all.png")
        if combined is not None:
            written.append(combined)
    logger.info("plots: %s", ", ".join(p.name for p in written) or "none yet")
    return written
