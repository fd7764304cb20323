"""Contact sheets: the drawing (mfm.export.contact_sheet) from hand-made joints, and launch/contact_sheet.py end to
end on the tiny text checkpoint test_sample_cli.py trains, generated and ground-truth rows."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import load_launch_script
from matplotlib.colors import to_rgb
from PIL import Image
from test_export import synthetic_clip
from test_sample_cli import text_run  # noqa: F401  (the session's tiny checkpoint, a fixture)

from mfm.export import render_contact_sheet
from mfm.export.contact_sheet import HEADER_PX, ROW_TITLE_PX, sheet_frames
from mfm.export.stick import SIDE_COLORS, bone_sides
from mfm.skeleton import HUMANML3D, KIT, get_skeleton
from pipeline.cli.contact_sheet import parse_args as parse_sheet_args
from pipeline.data.stream import open_manifest
from pipeline.generation.contact_sheet import (
    ContactSheetRequest,
    compare_with_clips,
    first_captions,
    mean_joint_error,
    run_contact_sheet,
)
from pipeline.generation.inference import load_trained_model
from pipeline.generation.request import SamplingError
from pipeline.generation.sampling import max_sample_length


def pixels(path) -> np.ndarray:
    with Image.open(path) as im:
        assert im.format == "PNG"
        return np.asarray(im.convert("RGB"), dtype=np.int32)


def near(image: np.ndarray, color: str, tolerance: float = 40.0) -> int:
    return int((np.linalg.norm(image - np.array(to_rgb(color)) * 255, axis=-1) < tolerance).sum())


def ink(image: np.ndarray) -> int:
    """Pixels clearly darker than the white background."""
    return int((image.sum(-1) < 600).sum())


def test_sheet_has_one_row_per_motion_of_the_expected_size(tmp_path):
    motions = [synthetic_clip(HUMANML3D, frames=n, seed=n) for n in (30, 12, 4)]
    motions[2] = motions[2][:3]  # shorter than a row: frames repeat
    out = render_contact_sheet(tmp_path / "sheet.png", motions, ["walks", "jumps", "a very long caption " * 20],
                               HUMANML3D, frames=4, panel_px=100, title="hand-made joints")
    image = pixels(out)
    row_px = ROW_TITLE_PX + 100
    assert image.shape == (HEADER_PX + 3 * row_px, 4 * 100, 3)
    for row in range(3):
        top = HEADER_PX + row * row_px
        assert ink(image[top:top + ROW_TITLE_PX]) > 20  # the caption
        for column in range(4):
            panel = image[top + ROW_TITLE_PX:top + row_px, column * 100:(column + 1) * 100]
            # Both sides of the body are drawn in their colours in every panel.
            assert near(panel, SIDE_COLORS["left"]) > 10 and near(panel, SIDE_COLORS["right"]) > 10
    assert sheet_frames(30, 4).tolist() == [0, 10, 19, 29] and sheet_frames(3, 4).tolist() == [0, 1, 1, 2]


def test_sheet_of_a_kit_motion_in_millimetres_and_bad_input(tmp_path):
    assert set(bone_sides(KIT)) == {"left", "right", "centre"}
    kit = synthetic_clip(KIT, frames=10, seed=2, metre=1000.0)
    out = render_contact_sheet(tmp_path / "kit.png", [kit], ["kit"], KIT, frames=3, panel_px=80)
    assert pixels(out).shape == (HEADER_PX + ROW_TITLE_PX + 80, 240, 3)
    with pytest.raises(ValueError, match="1 titles for 2 motions"):
        render_contact_sheet(tmp_path / "x.png", [kit, kit], ["one"], KIT)
    with pytest.raises(ValueError, match="frames must be"):
        render_contact_sheet(tmp_path / "x.png", [kit], ["one"], KIT, frames=0)
    with pytest.raises(ValueError, match="motion 0 must be"):
        render_contact_sheet(tmp_path / "x.png", [kit[..., :2]], ["one"], KIT)


sheet_entry = load_launch_script("contact_sheet")


@pytest.mark.slow
@pytest.mark.usefixtures("single_thread")
def test_cli_samples_one_row_per_prompt(text_run, tmp_path, capsys):  # noqa: F811
    prompts = tmp_path / "prompts.txt"
    prompts.write_text("someone jumps\n")
    out = tmp_path / "sheet.png"
    code = sheet_entry.main(["--checkpoint", str(text_run), "--text", "a person walks forward", "--prompts-file",
                             str(prompts), "--frames", "5", "--steps", "4", "--seconds", "1", "--out", str(out)])
    assert code == 0 and "2 row(s) of 5 frames (generated)" in capsys.readouterr().out
    assert pixels(out).shape == (HEADER_PX + 2 * (ROW_TITLE_PX + 160), 5 * 160, 3)
    assert sheet_entry.main(["--checkpoint", str(text_run), "--out", str(out)]) == 2
    assert "exactly one" in capsys.readouterr().err


def test_cli_reads_the_bone_keeping_switch_as_launch_sample_does(capsys):
    read = parse_sheet_args
    assert read(["--out", "x.png"]).smoothing_keeps_bones is None  # the model's own
    assert read(["--out", "x.png", "--smoothing-keeps-bones", "on"]).smoothing_keeps_bones is True
    assert read(["--out", "x.png", "--smoothing-keeps-bones", "FALSE"]).smoothing_keeps_bones is False
    assert read(["--out", "x.png", "--smoothing-keeps-bones", "smoothed"]).smoothing_keeps_bones == "smoothed"
    with pytest.raises(SystemExit):
        read(["--out", "x.png", "--smoothing-keeps-bones", "maybe"])
    assert "true, false or smoothed, got 'maybe'" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.usefixtures("single_thread")
def test_generated_and_ground_truth_sheets_of_the_manifest_captions_match_row_for_row(text_run, tmp_path):  # noqa: F811
    trained = load_trained_model(text_run)
    captions = first_captions(open_manifest(trained.data["location"]), "test")
    common = dict(checkpoint=text_run, captions_from_manifest="test", frames=3, steps=2)
    generated = run_contact_sheet(ContactSheetRequest(out=tmp_path / "generated.png", **common))
    truth = run_contact_sheet(ContactSheetRequest(out=tmp_path / "truth.png", ground_truth=True, decode="rigid",
                                                  **common))
    expected = [{"text": c.text, "frames": len(c.features)} for c in captions]
    limit = max_sample_length(trained)  # generated clips are clamped to the model's window (32 frames here)
    assert generated["mode"] == "generated" and truth["mode"] == "ground_truth"
    assert truth["rows"] == expected  # the clips' captioned spans
    assert generated["rows"] == [{**row, "frames": min(row["frames"], limit)} for row in expected]
    assert (generated["steps"], generated["guidance"], truth["decode"]) == (2, 2.5, "rigid")
    # The generated sheet is measured against the clips of its captions; the ground truth against itself is exact.
    against = generated["against_dataset_clips"]
    assert [row["id"] for row in against["rows"]] == [c.motion_id for c in captions]
    assert 0.0 <= against["caption_match"] <= 1.0 and against["median_error_to_own_clip_m"] > 0
    assert against["plausibility"]["bone_length_range"]["ground_truth"] < 1e-4
    assert set(against["plausibility"]["bone_length_range"]) == {"generated", "ground_truth"}
    assert "against_dataset_clips" not in truth
    assert pixels(tmp_path / "truth.png").shape == pixels(tmp_path / "generated.png").shape == \
        (HEADER_PX + len(captions) * (ROW_TITLE_PX + 160), 3 * 160, 3)
    # The ground-truth rows are the clips: with only a manifest (no checkpoint) the same sheet comes out.
    alone = run_contact_sheet(ContactSheetRequest(out=tmp_path / "alone.png", manifest=trained.data["location"],
                                                  captions_from_manifest="test", ground_truth=True, frames=3,
                                                  decode="rigid"))
    assert alone["rows"] == expected
    np.testing.assert_array_equal(pixels(tmp_path / "alone.png"), pixels(tmp_path / "truth.png"))
    first_two = run_contact_sheet(ContactSheetRequest(out=tmp_path / "two.png", manifest=trained.data["location"],
                                                      captions_from_manifest="test", ground_truth=True, frames=3,
                                                      decode="rigid", max_rows=2))
    assert first_two["rows"] == expected[:2]


def test_comparison_with_the_captions_clips_finds_each_samples_own_clip():
    skeleton = get_skeleton("humanml3d")
    rng = np.random.default_rng(0)
    clips = [rng.normal(size=(n, 22, 3)) for n in (12, 9, 15)]
    swapped = [clips[1][:9], clips[0][:9] + 0.01, clips[2]]  # rows 0 and 1 show each other's clip
    report = compare_with_clips(swapped, clips, skeleton, ["a", "b", "c"])
    assert [row["nearest_clip"] for row in report["rows"]] == ["b", "a", "c"]
    assert report["caption_match"] == pytest.approx(1 / 3)
    assert report["rows"][2]["error_to_own_clip_m"] == 0.0 and report["rows"][2]["jerk_ratio"] == pytest.approx(1.0)
    assert report["rows"][0]["error_to_own_clip_m"] == pytest.approx(mean_joint_error(clips[1][:9], clips[0]))


def test_bad_requests_say_what_is_wrong(tmp_path):
    with pytest.raises(SamplingError, match="exactly one"):
        ContactSheetRequest(out=tmp_path / "x.png", checkpoint="run", texts=["a"], captions_from_manifest="train")
    with pytest.raises(SamplingError, match="dataset's own captions"):
        ContactSheetRequest(out=tmp_path / "x.png", checkpoint="run", texts=["a"], ground_truth=True)
    with pytest.raises(SamplingError, match="needs a checkpoint"):
        ContactSheetRequest(out=tmp_path / "x.png", texts=["a"])
    with pytest.raises(SamplingError, match="max_rows"):
        ContactSheetRequest(out=tmp_path / "x.png", checkpoint="run", texts=["a"], max_rows=2)
    with pytest.raises(SamplingError, match="max_rows"):
        ContactSheetRequest(out=tmp_path / "x.png", checkpoint="run", captions_from_manifest="test", max_rows=0)
    with pytest.raises(SamplingError, match="decode"):
        ContactSheetRequest(out=tmp_path / "x.png", checkpoint="run", texts=["a"], decode="fk")
