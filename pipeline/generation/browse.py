"""Pages people can browse: an ``index.html`` beside sampling / composition outputs and beside evaluation results.

* :func:`write_sample_index` (``launch/sample.py --out DIR``, also run at the end of every sampling and composition
  run): every motion of ``DIR/results.json`` as an animated stick figure on a ``<canvas>`` (the same orthographic
  camera, chain colours, floor grid and root trajectory as the videos of mfm.export.render; edits: kept joints
  blue, edited red), played at the dataset's fps with play/pause, a frame slider, loop and speed; beside it the
  caption (composition: the segments, the current one highlighted), the length in frames and seconds, the
  plausibility figures of results.json and links to the sample's files.
* :func:`write_eval_index` (an evaluation folder, ``<run>/eval`` or ``output.dir=``; also rewritten whenever the
  evaluation job writes a result): the results table ``results.jsonl`` as HTML tables, the generated and the
  ground-truth row of every result together, metrics as mean ± 95 % CI, grouped (headline, plausibility, editing,
  other), with links to the result JSON files; then every ``plots/*.png`` as an image.

The pages are self-contained files: no network, no CDN. A sample page embeds the joints as JSON (integer
millimetres) in a ``<script type="application/json">`` element, so it opens from ``file://`` (where Chromium does
not let a page fetch JSON); images and the sample files are relative links to the files beside the page. Captions
and every other text are HTML-escaped. ``launch/browse.py DIR`` (re)builds the page of an existing folder.

The front end is static files in pipeline/generation/page/ (package data): ``index.html``, the page's shell, a
:class:`string.Template` whose ``$generator``, ``$title``, ``$error_hook``, ``$css``, ``$body`` and ``$script``
:func:`page` fills; ``page.css``; ``error-hook.js`` (in every page's <head>); ``player.js`` (the sample page's
stick-figure players, reading the embedded ``motion-data``). Edit them there; this module builds only the
data-dependent parts (the embedded JSON, the cards, the header and the tables), escaping every text it puts in.
"""

from __future__ import annotations

import functools
import html
import importlib.resources
import json
import logging
import math
import os
import string
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mfm.export.stick import (
    CHAIN_COLORS,
    EDITED_COLOR,
    FLOOR_COLOR,
    KEPT_COLOR,
    TRAJECTORY_COLOR,
    UNIT_SCALE,
    Camera,
    bones,
    equal_scale_limits,
)
from mfm.layout import FeatureLayout
from mfm.skeleton import Skeleton, get_skeleton
from pipeline.checkpoint import run_dir_of
from pipeline.generation.outputs import (  # PAGE_GENERATOR, is_our_page: importable from here too
    BROWSE_PAGE,
    PAGE_GENERATOR,
    RESULTS_FILE,
    edited_joints,
    is_our_page,
)

logger = logging.getLogger(__name__)

PAGE_FILE = BROWSE_PAGE
SAMPLE_RESULTS = RESULTS_FILE
EVAL_TABLE = "results.jsonl"  # pipeline.evaluation.store.TABLE_JSONL
EVAL_RESULTS_DIR = "results"  # pipeline.evaluation.store.RESULTS_SUBDIR
EVAL_PLOTS_DIR = "plots"  # pipeline.evaluation.store.PLOTS_SUBDIR
GRID_SPACING_MM = 500  # mfm.export.render.GRID_SPACING_M
CANVAS_PX = 320
PAGE_ASSETS = "page"  # pipeline/generation/page/: the pages' HTML template, CSS and JavaScript (package data)
MAX_MOTIONS = 200  # motions embedded in a sample page (about 0.3 kB per frame each); the rest listed without a player

# Plausibility figures (mfm.metrics.PlausibilityFigures): unit and a one-line meaning, for the tables' tooltips.
FIGURES: dict[str, tuple[str, str]] = {
    "bone_length_range": ("m", "largest over bones of (longest − shortest) bone length"),
    "bone_length_deviation": ("", "mean relative deviation of the bone lengths from their clip means"),
    "floor_penetration": ("m", "depth of the lowest foot joint below the floor"),
    "foot_skating_ratio": ("", "fraction of frame pairs in which a foot joint skates"),
    "contact_foot_speed": ("m/s", "mean horizontal foot-joint speed while touching the floor (— never touches)"),
    "skating_foot_speed": ("m/s", "mean horizontal speed of the skating foot joints"),
    "mean_jerk": ("m/frame³", "mean per-frame jerk"),
    "jerk_ratio": ("", "mean jerk over the paired ground-truth clip's"),
    "pose_speed": ("m/s", "mean speed of the joints relative to the root (near 0: frozen)"),
    "root_speed": ("m/s", "mean horizontal speed of the root"),
    "pose_spread": ("m", "mean RMS distance of the root-relative joints from their mean positions"),
}
HEADLINE_METRICS = ("fid", "r_precision_top1", "r_precision_top2", "r_precision_top3", "mm_dist", "diversity",
                    "multimodality", "accuracy", "transition_fid", "peak_jerk", "auj")
EDIT_PRESETS = ("prediction", "inbetween", "interpolation", "upper_body")  # mfm.editing.EDIT_MASK_PRESETS
TASK_TITLES = {"text_to_motion": "Text-to-motion", "composition": "Composition (FlowMDM protocol)"}


# ---------------------------------------------------------------------------------------------------------------
# shared bits
# ---------------------------------------------------------------------------------------------------------------


def esc(value: Any) -> str:
    """HTML-escaped text (quotes too: safe in attributes)."""
    return html.escape("" if value is None else str(value), quote=True)


def script_json(payload: Any) -> str:
    """JSON to embed in a ``<script type="application/json">`` element: ``<``, ``>`` and ``&`` as \\u escapes, so
    no caption can close the element or open a comment; ``JSON.parse`` reads them back unchanged."""
    text = json.dumps(payload, separators=(",", ":"), ensure_ascii=False, allow_nan=False)
    return text.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")


def fmt_number(value: Any, digits: int = 4) -> str:
    if value is None:
        return "—"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return str(value)
    if isinstance(value, int):
        return str(value)
    if not math.isfinite(value):
        return "nan" if math.isnan(value) else ("∞" if value > 0 else "−∞")
    if value == 0:
        return "0"
    return f"{value:.{digits}g}"


class PageNotOursError(FileExistsError):
    """The page's file exists and was not written by this module: it is left as it is."""


def write_page(path: Path, text: str) -> Path:
    """Write atomically (concurrent evaluation jobs rewrite the same page). A file at ``path`` that is not a page of
    ours (:func:`is_our_page`; another tool's index.html) is never overwritten: PageNotOursError naming it."""
    if (path.exists() or path.is_symlink()) and not (path.is_file() and not path.is_symlink() and is_our_page(path)):
        raise PageNotOursError(f"{path} is there and was not written by this project (no generator tag or footer of "
                               "pipeline/generation/browse.py): it is left as it is; move it away to get the page")
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)
    return path


def page_asset(name: str) -> str:
    """The text of a front-end file of the pages (pipeline/generation/page/, shipped as package data)."""
    return _page_asset(name)


@functools.cache  # read once per process: the eval job rewrites its page after every result
def _page_asset(name: str) -> str:
    try:
        return (importlib.resources.files(__package__) / PAGE_ASSETS / name).read_text(encoding="utf-8")
    except FileNotFoundError as err:
        raise FileNotFoundError(f"{PAGE_ASSETS}/{name} of pipeline/generation/ is missing: this install lacks the "
                                f"pages' front-end files (package data of pyproject.toml) ({err})") from err


def page(title: str, body: str, script: str = "") -> str:
    """A whole page: page/index.html filled with the title, page/error-hook.js (registered first, in <head>: an
    error anywhere, a syntax error in the main script included, is shown on the page, put in the title and in
    <html data-error>, where a headless browser's DOM dump finds it), page/page.css, ``body`` and ``script``.
    Only the template's own ``$names`` are replaced: a ``$`` in a caption or the CSS/JS is left as it is."""
    return string.Template(page_asset("index.html")).substitute(
        generator=PAGE_GENERATOR, title=esc(title), error_hook=page_asset("error-hook.js"), css=page_asset("page.css"),
        body=body, script=script)


# ---------------------------------------------------------------------------------------------------------------
# samples
# ---------------------------------------------------------------------------------------------------------------


def _sample_caption(results: Mapping[str, Any], sample: Mapping[str, Any]) -> str:
    """As pipeline.generation.sampling.caption: the text or action, 'unconditional', and the edit preset."""
    words = sample.get("text") or sample.get("action") or "unconditional"
    edit = sample.get("edit")
    return f"{words} [{edit.get('preset')} edit]" if isinstance(edit, Mapping) and edit.get("preset") else words


def _segments(results: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Composition: [{text, start, end}] of results.json's segments; [] for independent samples."""
    out = []
    for seg in results.get("segments") or []:
        text = seg.get("text") or seg.get("action") or ""
        out.append({"text": str(text), "start": int(seg.get("start", 0)), "end": int(seg.get("end", 0))})
    return out


def _file_of(sample: Mapping[str, Any], kind: str) -> str | None:
    return next((f["path"] for f in sample.get("files", []) if f.get("kind") == kind), None)


def _edited_flags(out_dir: Path, sample: Mapping[str, Any], skeleton: Skeleton, frames: int) -> str | None:
    """Edits: '0'/'1' per (frame, joint), 1 = generated (as the video's red), from the sample's keep_mask.npy."""
    path = _file_of(sample, "keep_mask")
    if path is None or not (out_dir / path).is_file():
        return None
    keep = np.load(out_dir / path)
    edited = edited_joints(keep, FeatureLayout(skeleton))[:frames]
    if edited.shape != (frames, skeleton.num_joints):
        return None
    return "".join("1" if flag else "0" for flag in edited.reshape(-1))


def motion_view(joints_mm: np.ndarray, camera: Camera) -> dict[str, Any]:
    """What the player needs besides the joints, as mfm.export.render.render_motion frames a video: the floor
    height, the view's image-plane limits around the root (the camera follows it) and the floor grid's extent."""
    floor = float(joints_mm[..., 1].min())
    root = joints_mm[:, 0].copy()
    root[:, 1] = floor
    height = float((joints_mm[..., 1] - floor).max())
    spread = float(np.linalg.norm((joints_mm - root[:, None])[..., [0, 2]], axis=-1).max())
    radius = 1.1 * max(spread, 0.35 * height, 300.0)
    box = np.array([[x, y, z] for x in (-radius, radius) for y in (0.0, 1.1 * height) for z in (-radius, radius)])
    lo, hi = equal_scale_limits(camera.project(box), aspect=1.0)
    ground_lo = root[:, [0, 2]].min(axis=0) - radius
    ground_hi = root[:, [0, 2]].max(axis=0) + radius
    return {"floor": round(floor), "view": [round(float(v), 1) for v in (*lo, *hi)],
            "grid": [round(float(v)) for v in (*ground_lo, *ground_hi)]}


def sample_page_data(out_dir: Path, results: Mapping[str, Any], skeleton: Skeleton, camera: Camera | None = None,
                     max_motions: int | None = MAX_MOTIONS) -> tuple[dict[str, Any], dict[int, str]]:
    """The JSON the page embeds (skeleton, camera, the joints of the first ``max_motions`` motions in integer mm)
    and, per sample index, why it has no player (joints missing or unreadable, or past ``max_motions``)."""
    camera = Camera() if camera is None else camera  # the videos' view (mfm.export.render)
    to_mm = 1000.0 / UNIT_SCALE[skeleton.unit]
    bone_list = bones(skeleton)
    basis = camera.basis()
    motions, missing = [], {}
    for sample in results.get("samples", []):
        index = int(sample.get("index", len(motions)))
        if max_motions is not None and len(motions) >= max_motions:
            missing[index] = (f"only the first {max_motions} motions are embedded (launch/browse.py --max-motions N "
                              "embeds more)")
            continue
        path = _file_of(sample, "joints")
        if path is None or not (out_dir / path).is_file():
            missing[index] = "no joints.npy"
            continue
        try:
            joints = np.load(out_dir / path).astype(np.float64) * to_mm
        except (OSError, ValueError) as exc:
            missing[index] = f"joints unreadable ({exc})"
            continue
        if joints.ndim != 3 or joints.shape[1:] != (skeleton.num_joints, 3) or len(joints) < 1:
            missing[index] = f"joints of shape {joints.shape}, not (L, {skeleton.num_joints}, 3)"
            continue
        if not np.isfinite(joints).all():
            missing[index] = "joints contain NaN or inf"
            continue
        motions.append({
            "index": index,
            "frames": len(joints),
            "joints": np.rint(joints).astype(np.int64).reshape(-1).tolist(),
            "edited": _edited_flags(out_dir, sample, skeleton, len(joints)),
            **motion_view(joints, camera),
        })
    data = {
        "fps": float(results.get("fps") or skeleton.fps),
        "skeleton": skeleton.name,
        "joints": skeleton.num_joints,
        "bones": [[a, b] for a, b, _ in bone_list],
        "boneColors": [CHAIN_COLORS[chain % len(CHAIN_COLORS)] for _, _, chain in bone_list],
        "keptColor": KEPT_COLOR, "editedColor": EDITED_COLOR, "floorColor": FLOOR_COLOR,
        "trajectoryColor": TRAJECTORY_COLOR,
        "camera": {"right": [round(float(v), 6) for v in basis[0]], "up": [round(float(v), 6) for v in basis[1]],
                   "look": [round(float(v), 6) for v in camera.look()]},
        "gridSpacing": GRID_SPACING_MM,
        "motions": motions,
    }
    return data, missing


def _figures_table(figures: Mapping[str, Any]) -> str:
    rows = []
    for name, value in figures.items():
        unit, meaning = FIGURES.get(name, ("", ""))
        shown = fmt_number(value) + (f" {unit}" if unit and value is not None else "")
        rows.append(f"<tr title=\"{esc(meaning)}\"><td>{esc(name.replace('_', ' '))}</td>"
                    f"<td class=\"num\">{esc(shown)}</td></tr>")
    return f"<table class=\"figures\">{''.join(rows)}</table>" if rows else ""


def _sample_header(out_dir: Path, results: Mapping[str, Any]) -> str:
    mode = results.get("mode", "sample")
    samples = results.get("samples", [])
    timing = results.get("timing", {})
    per = timing.get("ms_per_motion", timing.get("ms_per_sequence"))
    what = "sequence" if "ms_per_sequence" in timing else "motion"
    lines = [
        ("mode", mode), ("motions", len(samples)), ("checkpoint", results.get("checkpoint")),
        ("step", results.get("step")), ("weights", results.get("weights")),
        ("objective", results.get("objective")), ("solver", results.get("solver")),
        ("steps", results.get("steps")), ("guidance", results.get("guidance")),
        ("smoothing σ", results.get("smoothing_sigma")), ("seed", results.get("seed")),
        ("skeleton", results.get("skeleton")), ("fps", results.get("fps")), ("device", results.get("device")),
        (f"ms per {what}", per),
    ]
    if mode in ("compose", "extrapolate"):
        lines += [("positional", results.get("positional")), ("total frames", results.get("total_frames")),
                  ("switch", _switch_text(results.get("switch")))]
    meta = " · ".join(f"{esc(k)} <b>{esc(fmt_number(v) if isinstance(v, float) else v)}</b>"
                      for k, v in lines if v is not None)
    return (f"<header><h1>{esc(mode.capitalize())} outputs: {esc(out_dir.resolve().name)}</h1>"
            f"<p class=\"meta\">{meta}</p>"
            "<div class=\"controls\"><button id=\"all\" type=\"button\">Pause all</button>"
            "<label><input id=\"loop\" type=\"checkbox\" checked> loop</label>"
            "<label>speed <select id=\"speed\"><option value=\"0.25\">¼×</option><option value=\"0.5\">½×</option>"
            "<option value=\"1\" selected>1×</option><option value=\"2\">2×</option></select></label>"
            "<span class=\"meta\">click a figure to pause it; drag its slider to scrub</span></div></header>")


def _switch_text(switch: Any) -> str | None:
    """pipeline.generation.composing.switch_record in a few words."""
    if not isinstance(switch, Mapping):
        return None if switch is None else str(switch)
    if not switch.get("applies"):
        return "n/a (absolute positions)"
    return (f"flow time {fmt_number(switch.get('flow_time'))} ({switch.get('absolute_steps')} absolute + "
            f"{switch.get('relative_steps')} relative steps)")


def _sample_card(results: Mapping[str, Any], sample: Mapping[str, Any], fps: float, segments: Sequence[Mapping],
                 missing: str | None) -> str:
    index = int(sample.get("index", 0))
    length = int(sample.get("length", 0))
    seconds = sample.get("seconds", length / fps if fps else None)
    if segments:
        items = "".join(f"<li data-start=\"{s['start']}\" data-end=\"{s['end']}\">{esc(s['text'])} "
                        f"<span class=\"span\">frames {s['start']}–{s['end'] - 1}</span></li>" for s in segments)
        title = (f"<p class=\"caption\">{len(segments)} segments <span class=\"index\">#{index:03d}</span></p>"
                 f"<ol class=\"segments\">{items}</ol>")
    else:
        title = (f"<p class=\"caption\">{esc(_sample_caption(results, sample))} "
                 f"<span class=\"index\">#{index:03d}</span></p>")
    if missing is None:
        player = (f"<canvas width=\"{CANVAS_PX}\" height=\"{CANVAS_PX}\" aria-label=\"stick figure\"></canvas>"
                  f"<div class=\"bar\"><button class=\"play\" type=\"button\">Pause</button>"
                  f"<input class=\"scrub\" type=\"range\" min=\"0\" max=\"{max(length - 1, 0)}\" value=\"0\">"
                  f"<span class=\"frame\">1/{length}</span></div>")
    else:
        player = f"<p class=\"note\">no player: {esc(missing)}</p>"
    seconds_text = f" · {fmt_number(seconds)} s at {fmt_number(fps)} fps" if seconds is not None else ""
    extra = ""
    edit = sample.get("edit")
    if isinstance(edit, Mapping):
        extra = (f"<p class=\"length\">edit {esc(edit.get('preset'))} ({esc(edit.get('method'))}), kept fraction "
                 f"{esc(fmt_number(edit.get('kept_fraction')))}: kept joints blue, generated red</p>")
    files = " · ".join(f"<a href=\"{esc(f['path'])}\">{esc(Path(f['path']).name)}</a>"
                       for f in sample.get("files", []) if f.get("path"))
    return (f"<section class=\"card\" id=\"sample-{index:03d}\" data-index=\"{index}\">{player}{title}"
            f"<p class=\"length\">{length} frames{esc(seconds_text)}</p>{extra}"
            f"{_figures_table(sample.get('plausibility') or {})}"
            f"<p class=\"files\">{files}</p></section>")


def write_index_page(out_dir: Path) -> None:
    """index.html to browse the written motions (:func:`write_sample_index`), written last; a failure is logged, never
    fatal: the motions and results.json are already complete."""
    try:
        write_sample_index(out_dir)
    except Exception as exc:
        logger.warning("index.html not written: %s", exc)


def write_sample_index(out_dir: str | Path, max_motions: int | None = MAX_MOTIONS) -> Path:
    """``out_dir/index.html`` for a sampling or composition output folder (its results.json and joints.npy
    files), players for the first ``max_motions`` motions (None: all); returns the page's path."""
    out_dir = Path(out_dir)
    results = json.loads((out_dir / SAMPLE_RESULTS).read_text(encoding="utf-8"))
    skeleton = get_skeleton(str(results.get("skeleton")))
    data, missing = sample_page_data(out_dir, results, skeleton, max_motions=max_motions)
    fps = data["fps"]
    segments = _segments(results)
    cards = "".join(_sample_card(results, s, fps, segments, missing.get(int(s.get("index", 0))))
                    for s in results.get("samples", []))
    thresholds = results.get("plausibility_thresholds") or {}
    notes = ", ".join(f"{esc(k)} {esc(v)}" for k, v in thresholds.items())
    body = (f"{_sample_header(out_dir, results)}<main class=\"grid\">{cards}</main>"
            f"<footer>Plausibility figures: mfm.metrics.plausibility of each joints.npy ({notes}); hover a figure "
            f"for its meaning. Joints shown in mm, orthographic camera following the root, floor grid "
            f"{GRID_SPACING_MM / 1000:g} m, the root's path in grey. Written by pipeline/generation/browse.py; rebuild with "
            f"<code>python launch/browse.py {esc(out_dir)}</code>.</footer>")
    script = (f"<script type=\"application/json\" id=\"motion-data\">{script_json(data)}</script>\n"
              f"<script>\n{page_asset('player.js')}</script>")
    title = f"{results.get('mode', 'sample')}: {out_dir.resolve().name}"
    path = write_page(out_dir / PAGE_FILE, page(title, body, script))
    logger.info("wrote %s (%d motions, %.0f kB)", path, len(data["motions"]), path.stat().st_size / 1024)
    return path


# ---------------------------------------------------------------------------------------------------------------
# evaluation
# ---------------------------------------------------------------------------------------------------------------


def read_table(path: Path) -> list[dict[str, Any]]:
    """results.jsonl's rows (a torn or foreign line is skipped)."""
    rows = []
    if not path.is_file():
        return rows
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(row, dict):
            rows.append(row)
    return rows


def metric_names(rows: Iterable[Mapping[str, Any]]) -> list[str]:
    """Every column that has a ``_ci`` partner (mean ± CI metrics), in first-seen order."""
    names: dict[str, None] = {}
    for row in rows:
        for key in row:
            if not key.endswith("_ci") and f"{key}_ci" in row:
                names.setdefault(key, None)
    return list(names)


def metric_groups(names: Sequence[str]) -> list[tuple[str, list[str]]]:
    """(title, metrics): headline, plausibility, FLAME/other, then one group per edit preset."""
    headline = [m for m in HEADLINE_METRICS if m in names]
    plausible = [m for m in FIGURES if m in names]
    edits: dict[str, list[str]] = {}
    other = []
    for name in names:
        if name in headline or name in plausible:
            continue
        if name.startswith("edit_"):
            rest = name[len("edit_"):]
            preset = next((p for p in EDIT_PRESETS if rest.startswith(p + "_")), rest.split("_", 1)[0])
            edits.setdefault(preset, []).append(name)
        else:
            other.append(name)
    groups = [("Headline metrics", headline), ("Plausibility (medians over clips)", plausible),
              ("Other metrics", other)]
    groups += [(f"Editing: {preset}", sorted(cols, key=lambda c: (_edit_rank(c), c))) for preset, cols in edits.items()]
    return [(title, cols) for title, cols in groups if cols]


def _edit_rank(column: str) -> int:
    for rank, suffix in enumerate(("_fid", "_diversity", "_ade", "_fde")):
        if column.endswith(suffix):
            return rank
    return 9


def _mean_ci(row: Mapping[str, Any], name: str) -> str:
    mean, ci = row.get(name), row.get(f"{name}_ci")
    if mean is None:
        return ""
    return fmt_number(mean) if ci is None else f"{fmt_number(mean)} ± {fmt_number(ci, 2)}"


def _checkpoint_label(row: Mapping[str, Any]) -> str:
    """``run · step`` (``<run>/checkpoints/step-N``): one evaluation folder may hold several runs."""
    path = Path(str(row.get("checkpoint") or row.get("checkpoint_name") or "?"))
    run = run_dir_of(path).name
    return f"{run} · {row.get('step')}" if run else str(row.get("step"))


def _sort_key(row: Mapping[str, Any]) -> tuple:
    return (str(row.get("evaluator_id")), str(row.get("protocol")), _checkpoint_label(row).rsplit(" · ", 1)[0],
            row.get("step") or 0, str(row.get("solver")),
            row.get("steps") or 0, row.get("guidance") or 0, row.get("switch") or 0, str(row.get("scenario")),
            str(row.get("result_key")), 0 if row.get("row_kind") == "generated" else 1)


def _result_links(root: Path) -> dict[str, str]:
    """result key prefix (12 hex) -> the result JSON's path relative to ``root``."""
    out = {}
    for path in sorted((root / EVAL_RESULTS_DIR).glob("*/*.json")):
        out[path.stem.rsplit(".", 1)[-1]] = path.relative_to(root).as_posix()
    return out


def _setting(row: Mapping[str, Any]) -> str:
    text = f"{row.get('solver')} {row.get('steps')} steps g{fmt_number(row.get('guidance'))}"
    if row.get("task") == "composition":
        text += f" switch {fmt_number(row.get('switch'))} ({row.get('scenario')})"
    return text


def _eval_table(rows: Sequence[Mapping[str, Any]], columns: Sequence[str], links: Mapping[str, str]) -> str:
    head = ("<tr><th>checkpoint</th><th>setting</th><th>row</th><th>NFE</th><th>evaluator</th><th>protocol</th>"
            + "".join(f"<th title=\"{esc(FIGURES.get(c, ('', ''))[1])}\">{esc(c)}</th>" for c in columns) + "</tr>")
    body, previous = [], None
    for row in rows:
        if all(row.get(c) is None for c in columns):
            continue  # e.g. the ground-truth row of an editing group
        key = str(row.get("result_key"))
        first = key != previous
        previous = key
        gt = row.get("row_kind") == "ground_truth"
        link = links.get(key[:12])
        setting = esc(_setting(row))
        if link:
            setting = f"<a href=\"{esc(link)}\">{setting}</a>"
        evaluator = f"{row.get('evaluator_kind')} {str(row.get('evaluator_id'))[:8]}"
        protocol = f"{row.get('protocol')} R={row.get('replications')} n={row.get('num_items')}"
        if row.get("task", "text_to_motion") == "text_to_motion" and not row.get("redraw_items"):
            protocol += " fixed items"
        cells = "".join(f"<td class=\"num\">{esc(_mean_ci(row, c))}</td>" for c in columns)
        classes = " ".join(c for c, on in (("gt", gt), ("first", first)) if on)
        body.append(f"<tr class=\"{classes}\"><td class=\"id\">{esc(_checkpoint_label(row))}</td>"
                    f"<td class=\"id\">{setting}</td><td class=\"id\">{'ground truth' if gt else 'generated'}</td>"
                    f"<td class=\"num\">{'' if gt else esc(fmt_number(row.get('nfe')))}</td>"
                    f"<td class=\"id\">{esc(evaluator)}</td><td class=\"id\">{esc(protocol)}</td>{cells}</tr>")
    return f"<div class=\"tablewrap\"><table>{head}{''.join(body)}</table></div>"


def write_eval_index(out_dir: str | Path) -> Path:
    """``out_dir/index.html`` for an evaluation folder (results.jsonl, results/, plots/); returns its path. A table
    whose rows are on more than one test set (dataset id, split; the evaluator refuses to write one, an earlier
    version did not) is refused with a ValueError: one page never shows them side by side."""
    root = Path(out_dir)
    rows = sorted(read_table(root / EVAL_TABLE), key=_sort_key)
    test_sets = sorted({(str(r.get("dataset_id")), str(r.get("split"))) for r in rows})
    if len(test_sets) > 1:
        shown = ", ".join(f"{dataset[:16]} (split {split!r})" for dataset, split in test_sets)
        raise ValueError(f"{root / EVAL_TABLE}: results on {len(test_sets)} test sets ({shown}): one page never mixes "
                         "test sets; keep each test set's results in its own evaluation folder")
    links = _result_links(root)
    sections = []
    for task in dict.fromkeys(str(row.get("task", "text_to_motion")) for row in rows):
        task_rows = [r for r in rows if str(r.get("task", "text_to_motion")) == task]
        units = len({r.get("result_key") for r in task_rows})
        parts = [f"<h2>{esc(TASK_TITLES.get(task, task))}: {units} result(s)</h2>"]
        for title, columns in metric_groups(metric_names(task_rows)):
            parts.append(f"<h3 class=\"note\">{esc(title)}</h3>{_eval_table(task_rows, columns, links)}")
        sections.append("".join(parts))
    if not rows:
        sections.append(f"<p class=\"note\">No results yet ({esc(EVAL_TABLE)} is missing or empty).</p>")
    plots = sorted((root / EVAL_PLOTS_DIR).glob("*.png"))
    if plots:
        figures = "".join(f"<figure><a href=\"{esc(p.relative_to(root).as_posix())}\"><img src=\""
                          f"{esc(p.relative_to(root).as_posix())}\" alt=\"{esc(p.stem)}\" loading=\"lazy\"></a>"
                          f"<figcaption>{esc(p.name)}</figcaption></figure>" for p in plots)
        sections.append(f"<h2>Plots</h2><div class=\"plots\">{figures}</div>")
    datasets = sorted({str(r.get("dataset_id"))[:12] for r in rows if r.get("dataset_id")})
    checkpoints = sorted({_checkpoint_label(r) for r in rows})
    meta = (f"{len({r.get('result_key') for r in rows})} result(s) · checkpoints <b>{esc(', '.join(checkpoints))}</b>"
            f" · dataset <b>{esc(', '.join(datasets))}</b>")
    body = (f"<header><h1>Evaluation: {esc(root.resolve().name)}</h1><p class=\"meta\">{meta}</p>"
            "<p class=\"meta\">Every result has a generated row and, shaded below it, the ground-truth row it was "
            "scored against; values are mean ± 95 % CI over the replications (R). The setting links to the "
            "result JSON.</p></header>"
            f"{''.join(sections)}<footer>From {esc(EVAL_TABLE)} and {esc(EVAL_PLOTS_DIR)}/; written by "
            f"pipeline/generation/browse.py; rebuild with <code>python launch/browse.py {esc(root)}</code>.</footer>")
    path = write_page(root / PAGE_FILE, page(f"evaluation: {root.resolve().name}", body))
    logger.info("wrote %s (%d rows, %d plots)", path, len(rows), len(plots))
    return path


# ---------------------------------------------------------------------------------------------------------------
# either
# ---------------------------------------------------------------------------------------------------------------


def folder_kind(folder: Path) -> str | None:
    """'samples' (results.json with samples), 'evaluation' (results.jsonl, results/ or plots/), or None."""
    results = folder / SAMPLE_RESULTS
    if results.is_file():
        try:
            if "samples" in json.loads(results.read_text(encoding="utf-8")):
                return "samples"
        except (OSError, json.JSONDecodeError):
            pass
    if (folder / EVAL_TABLE).is_file() or (folder / EVAL_RESULTS_DIR).is_dir() or (folder / EVAL_PLOTS_DIR).is_dir():
        return "evaluation"
    return None


def write_index(folder: str | Path, max_motions: int | None = MAX_MOTIONS) -> Path:
    """The page of a sampling/composition output folder or an evaluation folder (a run folder: its ``eval/``)."""
    folder = Path(folder)
    kind = folder_kind(folder)
    if kind is None and folder_kind(folder / "eval") == "evaluation":
        folder, kind = folder / "eval", "evaluation"
    if kind == "samples":
        return write_sample_index(folder, max_motions)
    if kind == "evaluation":
        return write_eval_index(folder)
    raise FileNotFoundError(f"{folder}: neither a sampling output (results.json with samples) nor an evaluation "
                            f"folder (results.jsonl, results/ or plots/)")
