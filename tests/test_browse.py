"""pipeline/generation/browse.py: the index.html pages beside sampling and evaluation outputs (launch/browse.py).

Fast tests build the pages of hand-made output folders (results.json + joints.npy, results.jsonl + plots) and read
the HTML; the slow ones play a page in headless Chromium (it must animate, with no script error) and check that
sampling and evaluation runs write their page themselves."""

from __future__ import annotations

import fnmatch
import html
import json
import logging
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import tomllib
from conftest import load_launch_script
from PIL import Image

from mfm.export.stick import CHAIN_COLORS
from mfm.skeleton import HUMANML3D
from pipeline.generation import browse
from pipeline.generation.browse import (
    PAGE_FILE,
    write_eval_index,
    write_index,
    write_sample_index,
)

browse_entry = load_launch_script("browse")

CAPTIONS = ['a person walks <forward> & "waves"', "<script>alert('x')</script>", "someone jumps — twice</p>"]
FPS = 20.0
FIGURES = {"bone_length_range": 0.0123456, "bone_length_deviation": 0.004, "floor_penetration": 0.0,
           "foot_skating_ratio": 0.25, "contact_foot_speed": None, "skating_foot_speed": 0.5, "mean_jerk": 0.01,
           "pose_speed": 0.3, "root_speed": 1.0, "pose_spread": 0.07}


def walking_figure(frames: int, phase: float = 0.0) -> np.ndarray:
    """(frames, 22, 3) float32 metres: HumanML3D's rest pose on the floor walking forward at 1 m/s, arms and legs
    swinging once a second."""
    offsets, parents = HUMANML3D.target_offsets(), HUMANML3D.parents
    rest = np.zeros((HUMANML3D.num_joints, 3))
    for joint in range(1, HUMANML3D.num_joints):  # every parent comes before its children
        rest[joint] = rest[parents[joint]] + offsets[joint]
    rest[:, 1] -= rest[:, 1].min()
    t = np.arange(frames) / FPS
    joints = np.repeat(rest[None], frames, axis=0)
    joints[..., 2] += t[:, None]
    swing = 0.3 * np.sin(2 * np.pi * t + phase)[:, None]
    names = HUMANML3D.joint_names
    for side, sign in (("left", 1.0), ("right", -1.0)):
        arm = [names.index(f"{side}_{j}") for j in ("elbow", "wrist")]
        leg = [names.index(f"{side}_{j}") for j in ("knee", "ankle", "foot")]
        joints[:, arm, 2] += sign * swing
        joints[:, leg, 2] -= sign * swing
    return joints.astype(np.float32)


def fake_sampling_output(out: Path, captions=CAPTIONS, frames=(40, 33, 27), mode: str = "sample",
                         segments=None) -> dict:
    """What pipeline.generation.sampling writes, less the files the page does not read: results.json and joints.npy."""
    samples = []
    for index, (text, length) in enumerate(zip(captions, frames)):
        folder = out / f"sample_{index:03d}"
        folder.mkdir(parents=True)
        np.save(folder / "joints.npy", walking_figure(length, phase=index))
        samples.append({"index": index, "text": None if segments else text, "action": None, "length": length,
                        "seconds": round(length / FPS, 6), "noise_seed": index, "nfe": 10,
                        "files": [{"path": f"sample_{index:03d}/joints.npy", "kind": "joints",
                                   "shape": [length, 22, 3], "unit": "m"}],
                        "plausibility": dict(FIGURES)})
    results = {"version": 1, "checkpoint": "runs/x/checkpoints/step-00000004", "step": 4, "weights": "ema",
               "dataset_id": "d" * 64, "skeleton": "humanml3d", "fps": FPS, "mode": mode, "conditioning": "text",
               "objective": "flow", "sampler": "euler", "solver": "euler", "steps": 10, "guidance": 2.5,
               "smoothing_sigma": 0.0, "seed": 0, "device": "cpu",
               "plausibility_thresholds": {"unit": "m", "foot_contact_height_m": 0.05},
               "timing": {"generation_s": 0.1, "ms_per_motion": 33.3, "total_s": 0.2}, "samples": samples}
    if segments:
        results["segments"] = segments
    (out / "results.json").write_text(json.dumps(results, indent=1), encoding="utf-8")
    return results


def embedded_data(page: str) -> dict:
    match = re.search(r'<script type="application/json" id="motion-data">(.*?)</script>', page, re.DOTALL)
    assert match, "no embedded motion data"
    return json.loads(match.group(1))


def test_sample_page_embeds_every_motion_and_escapes_every_caption(tmp_path):
    out = tmp_path / "samples"
    results = fake_sampling_output(out)
    page = write_sample_index(out).read_text(encoding="utf-8")

    for caption in CAPTIONS:
        assert html.escape(caption) in page
    assert "<script>alert" not in page and "twice</p>" not in page  # no caption is markup anywhere, data included
    assert not re.search(r"https?://", page)  # self-contained: no network, no CDN
    assert page.count("<canvas") == len(CAPTIONS) and "requestAnimationFrame" in page

    data = embedded_data(page)
    assert data["fps"] == FPS and data["joints"] == 22
    parents = HUMANML3D.parents
    assert sorted(child for _, child in data["bones"]) == list(range(1, 22))
    assert all(parents[child] == parent for parent, child in data["bones"])
    for sample, motion in zip(results["samples"], data["motions"]):
        joints = np.load(out / sample["files"][0]["path"])
        assert motion["index"] == sample["index"] and motion["frames"] == sample["length"]
        np.testing.assert_array_equal(motion["joints"], np.rint(joints.astype(np.float64) * 1000).reshape(-1))
        assert motion["edited"] is None

    # Lengths and the plausibility figures, undefined ones as a dash.
    assert "40 frames · 2 s at 20 fps" in page and "33 frames · 1.65 s at 20 fps" in page
    assert "0.01235 m" in page and "0.5 m/s" in page and ">—</td>" in page


def test_composition_page_lists_the_segments_and_plays_the_whole_sequence(tmp_path):
    out = tmp_path / "story"
    segments = [{"index": 0, "text": "walk <left>", "length": 30, "start": 0, "end": 30},
                {"index": 1, "text": "then sit & rest", "length": 20, "start": 30, "end": 50}]
    fake_sampling_output(out, captions=["ignored"], frames=(50,), mode="compose", segments=segments)
    page = write_sample_index(out).read_text(encoding="utf-8")
    assert "walk &lt;left&gt;" in page and "then sit &amp; rest" in page
    assert 'data-start="30" data-end="50"' in page and "frames 30–49" in page
    assert embedded_data(page)["motions"][0]["frames"] == 50


def test_a_sample_without_joints_is_listed_without_a_player(tmp_path):
    out = tmp_path / "samples"
    fake_sampling_output(out)
    (out / "sample_001" / "joints.npy").unlink()
    page = write_sample_index(out).read_text(encoding="utf-8")
    assert page.count("<canvas") == 2 and "no player: no joints.npy" in page
    assert [m["index"] for m in embedded_data(page)["motions"]] == [0, 2]
    assert html.escape(CAPTIONS[1]) in page


def test_only_the_first_max_motions_get_a_player(tmp_path):
    out = tmp_path / "samples"
    fake_sampling_output(out)
    page = write_sample_index(out, max_motions=2).read_text(encoding="utf-8")
    assert page.count("<canvas") == 2 and "only the first 2 motions are embedded" in page
    assert [m["index"] for m in embedded_data(page)["motions"]] == [0, 1]
    assert browse_entry.main([str(out), "--max-motions", "0"]) == 0  # 0: all
    assert (out / PAGE_FILE).read_text(encoding="utf-8").count("<canvas") == 3


def _row(key: str, kind: str, fid: float, ci: float | None, step: int = 4, **extra) -> dict:
    return {"checkpoint": f"/x/runs/flow/checkpoints/step-{step:08d}", "checkpoint_name": f"step-{step:08d}",
            "step": step, "result_key": key, "row_key": f"{key}:{kind}", "row_kind": kind, "task": "text_to_motion",
            "solver": "euler", "steps": 10, "guidance": 2.5, "nfe": 10, "protocol": "fast", "replications": 3,
            "num_items": 64, "redraw_items": True, "evaluator_kind": "contrastive", "evaluator_id": "e" * 64,
            "dataset_id": "d" * 64, "fid": fid, "fid_ci": ci, "r_precision_top3": 0.5, "r_precision_top3_ci": 0.01,
            "mean_jerk": 0.02, "mean_jerk_ci": 0.001, **extra}


def fake_evaluation_output(out: Path) -> None:
    (out / "plots").mkdir(parents=True)
    Image.new("RGB", (40, 30), "white").save(out / "plots" / "metrics_vs_step.png")
    key = "a" * 64
    (out / "results" / "step-00000004").mkdir(parents=True)
    (out / "results" / "step-00000004" / f"euler-10steps-g2.5.{key[:12]}.json").write_text("{}")
    rows = [_row(key, "generated", 0.123456, 0.0056, edit_upper_body_fid=0.9, edit_upper_body_fid_ci=None),
            _row(key, "ground_truth", 0.01, 0.002),
            _row("b" * 64, "generated", 0.2, 0.01, step=8)]
    (out / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows) + "{torn", encoding="utf-8")


def test_evaluation_page_shows_the_table_with_intervals_and_the_plots(tmp_path):
    out = tmp_path / "eval"
    fake_evaluation_output(out)
    page = write_eval_index(out).read_text(encoding="utf-8")
    assert "0.1235 ± 0.0056" in page and "0.01 ± 0.002" in page  # generated and ground-truth rows, mean ± CI
    # Three tables (headline, plausibility, editing); the ground truth has no editing figures: no row there.
    assert page.count(">generated<") == 2 + 2 + 1 and page.count(">ground truth<") == 1 + 1
    assert "Headline metrics" in page and "Plausibility" in page and "Editing: upper_body" in page
    assert "flow · 4" in page and "flow · 8" in page
    assert '<img src="plots/metrics_vs_step.png"' in page
    assert f'href="results/step-00000004/euler-10steps-g2.5.{"a" * 12}.json"' in page
    assert not re.search(r"https?://", page)


def test_launch_browse_finds_the_kind_of_folder(tmp_path, capsys):
    fake_sampling_output(tmp_path / "samples")
    fake_evaluation_output(tmp_path / "run" / "eval")
    (tmp_path / "empty").mkdir()
    assert browse_entry.main([str(tmp_path / "samples"), str(tmp_path / "run")]) == 0
    assert (tmp_path / "samples" / PAGE_FILE).is_file() and (tmp_path / "run" / "eval" / PAGE_FILE).is_file()
    assert browse_entry.main([str(tmp_path / "empty")]) == 2
    assert "neither a sampling output" in capsys.readouterr().err
    assert write_index(tmp_path / "samples") == tmp_path / "samples" / PAGE_FILE


PAGE_FRONT_END = Path(__file__).resolve().parents[1] / "pipeline" / "generation" / "page"  # browse.PAGE_ASSETS


def test_the_page_is_its_template_filled_with_the_front_end_files(tmp_path):
    """Issue 27: the page's HTML shell, CSS and JavaScript are static files (pipeline/generation/page/), filled by
    a string.Template: each file is in the written page as it is on disk, every placeholder is filled, and a ``$``
    in a caption is text (escaped with the rest), not a placeholder."""
    out = tmp_path / "samples"
    captions = ["walks $title ${css} $$ <b>", "$script"]
    fake_sampling_output(out, captions=captions, frames=(20, 20))
    page = write_sample_index(out).read_text(encoding="utf-8")
    assert {p.name for p in PAGE_FRONT_END.iterdir()} == {"index.html", "page.css", "error-hook.js", "player.js"}
    for name, wrapped in (("page.css", "<style>\n{}</style>"), ("error-hook.js", "<script>\n{}</script>"),
                          ("player.js", "<script>\n{}</script>")):
        text = (PAGE_FRONT_END / name).read_text(encoding="utf-8")
        assert page.count(wrapped.format(text)) == 1, f"page/{name} is not in the page as it is on disk"
    template = (PAGE_FRONT_END / "index.html").read_text(encoding="utf-8")
    placeholders = set(re.findall(r"\$(\w+)", template))
    assert placeholders == {"generator", "title", "error_hook", "css", "body", "script"}
    assert page.startswith(template.split("$generator")[0] + browse.PAGE_GENERATOR)
    assert page.endswith(template.rsplit("$script", 1)[1])
    for caption in captions:
        assert html.escape(caption) in page
    with pytest.raises(FileNotFoundError, match=r"page/no-such\.css of pipeline/generation/ is missing.*package data"):
        browse.page_asset("no-such.css")


def test_the_front_end_files_ship_as_package_data_and_not_as_python_strings():
    """Issue 27: pyproject.toml's package data covers every file of pipeline/generation/page/ (a wheel without
    them writes no page), and browse.py builds only the data-dependent parts: no CSS rule, no script function."""
    root = Path(__file__).resolve().parents[1]
    assert PAGE_FRONT_END == Path(browse.__file__).parent / browse.PAGE_ASSETS
    globs = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["pipeline"]
    files = [p.relative_to(root / "pipeline").as_posix() for p in PAGE_FRONT_END.iterdir()]
    assert files and all(any(fnmatch.fnmatch(f, g) for g in globs) for f in files), (files, globs)
    source = Path(browse.__file__).read_text(encoding="utf-8")
    assert not re.search(r"function\s*\(|addEventListener|\{\s*[\w-]+\s*:\s*[^{}]+;\s*\}", source), \
        "browse.py holds CSS or JavaScript: put it in pipeline/generation/page/"


FOREIGN_PAGE = "<html><body>another tool's report</body></html>\n"


def test_a_page_we_did_not_write_is_never_overwritten(tmp_path):
    """Issue 24, finding 4: the evaluator's output folder overwrote a foreign index.html. A page is written only over
    a page of ours (our generator tag, or the footer of pages written before the tag)."""
    for out, fill, write in ((tmp_path / "eval", fake_evaluation_output, write_eval_index),
                             (tmp_path / "samples", fake_sampling_output, write_sample_index)):
        fill(out)
        (out / PAGE_FILE).write_text(FOREIGN_PAGE)
        with pytest.raises(browse.PageNotOursError, match=f"{out / PAGE_FILE} is there and was not written by"):
            write(out)
        assert (out / PAGE_FILE).read_text() == FOREIGN_PAGE
        (out / PAGE_FILE).unlink()
        ours = write(out).read_text(encoding="utf-8")
        assert f'<meta name="generator" content="{browse.PAGE_GENERATOR}">' in ours
        earlier = ours.replace(f'<meta name="generator" content="{browse.PAGE_GENERATOR}">\n', "")
        (out / PAGE_FILE).write_text(earlier)  # a page of an earlier version: no tag, our footer
        assert browse.is_our_page(out / PAGE_FILE) and write(out).read_text(encoding="utf-8") == ours


def test_sampling_overwrite_replaces_only_an_earlier_sampling_output_of_ours(tmp_path):
    """Issue 24, finding 4: --overwrite removed any index.html and sample_NNN folder by name. Now only a folder whose
    results.json we wrote is replaced, and never another tool's index.html in it."""
    from pipeline.generation.outputs import prepare_out_dir
    from pipeline.generation.request import SamplingError

    theirs = tmp_path / "theirs"
    (theirs / "sample_000").mkdir(parents=True)
    (theirs / "sample_000" / "photo.jpg").write_bytes(b"theirs")
    (theirs / PAGE_FILE).write_text(FOREIGN_PAGE)
    with pytest.raises(SamplingError, match="not an earlier sampling output"):
        prepare_out_dir(theirs, overwrite=True)
    assert (theirs / "sample_000" / "photo.jpg").read_bytes() == b"theirs"
    ours = tmp_path / "ours"
    fake_sampling_output(ours)
    (ours / PAGE_FILE).write_text(FOREIGN_PAGE)
    with pytest.raises(SamplingError, match=r"not sampling outputs of ours \(\['index.html'\]\)"):
        prepare_out_dir(ours, overwrite=True)
    assert (ours / PAGE_FILE).read_text() == FOREIGN_PAGE and (ours / "sample_000" / "joints.npy").is_file()
    (ours / PAGE_FILE).unlink()
    write_sample_index(ours)
    prepare_out_dir(ours, overwrite=True)
    assert list(ours.iterdir()) == []


# ---------------------------------------------------------------------------------------------------------------
# in a browser


def chromium() -> str:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        message = "Chromium is not installed (apt-get install -y chromium; .ci/run installs it)"
        if os.environ.get("MFM_REQUIRE_BROWSER"):
            pytest.fail(message)
        pytest.skip(message)
    return exe


def run_chromium(page: Path, profile: Path, budget_ms: int, *action: str) -> subprocess.CompletedProcess:
    """Headless Chromium on ``page`` for ``budget_ms`` of virtual time, offline (no background connections)."""
    cmd = [chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           f"--user-data-dir={profile}", "--enable-logging=stderr", "--v=0", f"--virtual-time-budget={budget_ms}",
           "--window-size=900,700", *action, page.as_uri()]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def console_errors(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if ":CONSOLE" in line and ("Uncaught" in line or "rror" in line)]


def bone_pixels(image: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels near one of the chain colours (the dark one aside: text is dark too)."""
    colours = [np.array([int(c[i:i + 2], 16) for i in (1, 3, 5)]) for c in CHAIN_COLORS if c != "#222222"]
    return np.any([np.abs(image - c).sum(axis=-1) < 60 for c in colours], axis=0)


@pytest.mark.slow
def test_the_page_plays_in_headless_chromium_without_script_errors(tmp_path):
    out = tmp_path / "samples"
    fake_sampling_output(out, captions=CAPTIONS[:1], frames=(40,))
    page = write_sample_index(out)

    shots = []
    for budget in (500, 1200):  # frames 10 and 24 of 40 at 20 fps
        shot = tmp_path / f"shot-{budget}.png"
        proc = run_chromium(page, tmp_path / f"profile-{budget}", budget, f"--screenshot={shot}")
        assert not console_errors(proc.stderr), console_errors(proc.stderr)
        shots.append(np.asarray(Image.open(shot).convert("RGB")).astype(np.int64))
    first, second = shots
    assert first.shape == second.shape
    changed = np.abs(first - second).sum(axis=-1) > 30
    moved = changed & (bone_pixels(first) | bone_pixels(second))
    assert moved.sum() > 50, "the stick figure did not move between the two screenshots"

    proc = run_chromium(page, tmp_path / "profile-dom", 300, "--dump-dom")
    root = re.search(r"<html[^>]*>", proc.stdout).group(0)
    assert 'data-ready="1"' in root and "data-error" not in root, root
    assert not console_errors(proc.stderr), console_errors(proc.stderr)

    # The controls: a figure's button pauses it, "Play all" restarts every one, the slider shows a frame (paused).
    clicks = out / "clicks.html"
    clicks.write_text(page.read_text(encoding="utf-8").replace("</body>", """<script>
window.addEventListener("load", function () {
  var card = document.querySelector("section.card"), button = card.querySelector("button.play");
  var all = document.getElementById("all"), scrub = card.querySelector("input.scrub"), seen = [];
  button.click(); seen.push(button.textContent);
  all.click(); seen.push(all.textContent, button.textContent);
  scrub.value = "7"; scrub.dispatchEvent(new Event("input")); seen.push(card.getAttribute("data-frame"), button.textContent);
  document.documentElement.setAttribute("data-seen", seen.join("|"));
});
</script></body>"""), encoding="utf-8")
    proc = run_chromium(clicks, tmp_path / "profile-clicks", 300, "--dump-dom")
    assert 'data-seen="Play|Pause all|Pause|7|Play"' in re.search(r"<html[^>]*>", proc.stdout).group(0)

    # The error hook works: a page whose data is broken says so in the DOM and on the console.
    broken = out / "broken.html"
    broken.write_text(page.read_text(encoding="utf-8").replace('id="motion-data">{', 'id="motion-data">{oops'),
                      encoding="utf-8")
    proc = run_chromium(broken, tmp_path / "profile-broken", 300, "--dump-dom")
    assert "data-error=" in re.search(r"<html[^>]*>", proc.stdout).group(0)
    assert console_errors(proc.stderr)


# ---------------------------------------------------------------------------------------------------------------
# written by the runs themselves


@pytest.fixture(scope="session")
def tiny_text_run(tmp_path_factory) -> Path:
    """The tiny text model of test_sample_cli.py (trained once per session, shared with those tests)."""
    from test_sample_cli import _train_once
    from test_trainer import build_dataset_once

    return _train_once(tmp_path_factory, "sampling-text-run", build_dataset_once(tmp_path_factory))


@pytest.mark.slow
@pytest.mark.usefixtures("single_thread")
def test_sampling_and_composition_write_their_page_and_its_failure_is_not_fatal(tiny_text_run, tmp_path,
                                                                               monkeypatch, caplog):
    from test_sample_cli import sample

    results = sample(tiny_text_run, tmp_path / "a", "--text", "a <person> walks", "--length", "20", "--no-video",
                     "--no-bvh")
    page = (tmp_path / "a" / PAGE_FILE).read_text(encoding="utf-8")
    assert "a &lt;person&gt; walks" in page
    joints = np.load(tmp_path / "a" / "sample_000" / "joints.npy").astype(np.float64)
    np.testing.assert_array_equal(embedded_data(page)["motions"][0]["joints"], np.rint(joints * 1000).reshape(-1))
    assert len(results["samples"]) == 1

    sample(tiny_text_run, tmp_path / "b", "--extrapolate", "--text", "a person walks", "--length", "10",
           "--num-segments", "2", "--no-video", "--no-bvh")
    assert "frames 10–19" in (tmp_path / "b" / PAGE_FILE).read_text(encoding="utf-8")

    def broken(out_dir):
        raise RuntimeError("disk full")

    monkeypatch.setattr(browse, "write_sample_index", broken)
    with caplog.at_level(logging.WARNING, logger="pipeline.generation.sampling"):
        sample(tiny_text_run, tmp_path / "c", "--text", "a person walks", "--length", "20", "--no-video",
               "--no-bvh")
    assert "index.html not written: disk full" in caplog.text and not (tmp_path / "c" / PAGE_FILE).exists()


@pytest.mark.slow
@pytest.mark.usefixtures("single_thread")
def test_the_evaluation_job_writes_its_page(tmp_path_factory, tmp_path):
    from eval_worker import (
        SMALL_PROTOCOL,
        build_synthetic_dataset,
        random_contrastive_evaluator,
        train_tiny_model,
    )

    from launch.evaluate import main as evaluate

    manifest = build_synthetic_dataset(tmp_path_factory.getbasetemp() / "eval-synthetic")  # as test_evaluation.py
    run = train_tiny_model(manifest, tmp_path / "run", steps=1)
    evaluator = random_contrastive_evaluator(manifest, tmp_path / "ev" / "contrastive.safetensors")
    out = tmp_path / "eval"
    assert evaluate(["--checkpoint", str(run / "checkpoints" / "step-00000001"), "--protocol", "fast",
                     *SMALL_PROTOCOL, "sampling.steps=[2]", "protocol.replications=1", "tasks.editing=[]",
                     "protocol.multimodality=false", f"evaluator.path={evaluator}", f"output.dir={out}"]) == 0
    page = (out / PAGE_FILE).read_text(encoding="utf-8")
    assert "euler 2 steps g2.5" in page and ">ground truth<" in page and " ± " in page
