"""BVH export (round trip through an independent parse + FK), stick-figure videos and the x̂1 plot."""

import json
import logging
import os
import re
import shutil
import subprocess

import numpy as np
import pytest
import torch
from matplotlib import rcParams
from matplotlib.colors import to_rgb
from PIL import Image

from mfm.export import (
    EDITED_COLOR,
    KEPT_COLOR,
    ffmpeg_available,
    plot_x1_trajectory,
    read_bvh,
    render_motion,
    write_bvh,
)
from mfm.export.bvh import _axis_rotation, _euler_yxz_degrees
from mfm.export.render import caption_per_frame, edited_per_frame
from mfm.features import features_to_joints_rigid
from mfm.skeleton import HUMANML3D, KIT

# ---------------------------------------------------------------------------------------------------
# helpers


def synthetic_clip(skeleton, frames: int, seed: int = 0, metre: float = 1.0) -> np.ndarray:
    """A clip with constant (random) bone lengths whose bones swing smoothly about their rest
    directions, so the angles between sibling bones change over time (nothing is rigid), and the root
    walks. Frame 3's first arm bone points exactly opposite its rest direction (a half-turn case)."""
    rng = np.random.default_rng(seed)
    j = skeleton.num_joints
    lengths = rng.uniform(0.05, 0.4, j) * metre
    t = np.arange(frames)[:, None, None] / skeleton.fps
    phase, speed = rng.uniform(0, 2 * np.pi, (1, j, 3)), rng.uniform(0.5, 3.0, (1, j, 3))
    directions = skeleton.raw_offsets[None] + 0.6 * np.sin(speed * t + phase)
    arm = skeleton.kinematic_chains[3][2]
    directions[3, arm] = -skeleton.raw_offsets[arm]
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    joints = np.zeros((frames, j, 3))
    joints[:, 0] = np.stack((0.8 * t[:, 0, 0], 0.9 + 0.05 * np.sin(3 * t[:, 0, 0]), 0.3 * np.sin(t[:, 0, 0])), -1) * metre
    for chain in skeleton.kinematic_chains:  # a chain's start is placed by an earlier chain
        for parent, child in zip(chain[:-1], chain[1:]):
            joints[:, child] = joints[:, parent] + lengths[child] * directions[:, child]
    return joints


def bvh_sections(path):
    """(hierarchy lines, frame count, frame time, motion rows) read as plain text."""
    lines = path.read_text().splitlines()
    motion_at = lines.index("MOTION")
    frames = int(lines[motion_at + 1].split(":")[1])
    frame_time = float(lines[motion_at + 2].split(":")[1])
    rows = [line.split() for line in lines[motion_at + 3 :]]
    return lines[:motion_at], frames, frame_time, rows


def check_bvh_text(path, skeleton, frames: int, fps: float) -> None:
    hierarchy, count, frame_time, rows = bvh_sections(path)
    assert hierarchy[0] == "HIERARCHY" and hierarchy[1] == "ROOT " + skeleton.joint_names[0]
    channels = [line.split() for line in hierarchy if line.strip().startswith("CHANNELS")]
    assert channels[0] == ["CHANNELS", "6", "Xposition", "Yposition", "Zposition", "Yrotation", "Xrotation", "Zrotation"]
    assert all(c == ["CHANNELS", "3", "Yrotation", "Xrotation", "Zrotation"] for c in channels[1:])
    declared = [line.split()[1] for line in hierarchy if line.strip().split()[0] in ("ROOT", "JOINT")]
    assert set(skeleton.joint_names) <= set(declared)
    assert sum(line.count("{") for line in hierarchy) == sum(line.count("}") for line in hierarchy)
    leaves = sum(1 for joint in range(skeleton.num_joints) if joint not in set(skeleton.parents.tolist()))
    assert sum(1 for line in hierarchy if line.strip() == "End Site") == leaves
    assert count == frames == len(rows)
    assert frame_time == pytest.approx(1.0 / fps, abs=1e-8)
    assert all(len(row) == 6 + 3 * (len(declared) - 1) for row in rows)


# ---------------------------------------------------------------------------------------------------
# BVH


def test_bvh_round_trip_of_the_real_humanml3d_clip(reference_data, tmp_path):
    joints = np.load(reference_data / "humanml3d" / "new_joints_012314.npy")
    path = write_bvh(tmp_path / "clip.bvh", joints, HUMANML3D)
    check_bvh_text(path, HUMANML3D, len(joints), 20.0)
    parsed = read_bvh(path, HUMANML3D.joint_names)
    assert parsed.fps == pytest.approx(20.0)
    assert parsed.names == list(HUMANML3D.joint_names)
    assert np.abs(parsed.joints - joints).max() <= 1e-4  # metres


def test_bvh_round_trip_of_a_synthetic_kit_clip_in_millimetres(tmp_path):
    joints = synthetic_clip(KIT, frames=30, seed=1, metre=1000.0)
    path = write_bvh(tmp_path / "kit.bvh", torch.from_numpy(joints), KIT)  # torch input is accepted too
    check_bvh_text(path, KIT, 30, 12.5)
    parsed = read_bvh(path, KIT.joint_names)
    assert parsed.fps == pytest.approx(12.5)
    # The file is in metres: 1e-4 m = 0.1 mm.
    assert np.abs(parsed.joints * 1000.0 - joints).max() <= 0.1


def test_bvh_rest_offsets_are_the_clips_bone_lengths_along_the_rest_directions(tmp_path):
    joints = synthetic_clip(HUMANML3D, frames=5, seed=2)
    path = write_bvh(tmp_path / "clip.bvh", joints, HUMANML3D)
    hierarchy, *_ = bvh_sections(path)
    offsets, name = {}, None
    for line in hierarchy:
        words = line.split()
        if words[0] in ("ROOT", "JOINT"):
            name = words[1]
        elif words[0] == "OFFSET" and name is not None:
            offsets[name] = np.array(words[1:], dtype=float)
            name = None  # the next OFFSET without a joint line is an End Site's
    parents = HUMANML3D.parents
    for j in range(1, HUMANML3D.num_joints):
        length = np.linalg.norm(joints[0, j] - joints[0, parents[j]])
        np.testing.assert_allclose(offsets[HUMANML3D.joint_names[j]], HUMANML3D.raw_offsets[j] * length, atol=2e-6)
    # The branch joints that give each extra child of pelvis/spine3 its own rotation sit at the branch point.
    branch = {n: o for n, o in offsets.items() if "_to_" in n}
    assert set(branch) == {"pelvis_to_right_hip", "pelvis_to_left_hip", "spine3_to_right_collar", "spine3_to_left_collar"}
    assert all(np.all(o == 0) for o in branch.values())


def test_bvh_keeps_bone_directions_and_warns_when_bone_lengths_drift(tmp_path, caplog):
    joints = synthetic_clip(HUMANML3D, frames=20, seed=3)
    parents = HUMANML3D.parents
    bones = joints[:, 1:] - joints[:, parents[1:]]
    stretch = 1.0 + 0.1 * np.sin(np.arange(20))[:, None, None]  # raw network output: lengths drift by 10%
    drifting = joints.copy()
    for j in range(1, HUMANML3D.num_joints):  # parents come first in joint order for HumanML3D
        drifting[:, j] = drifting[:, parents[j]] + stretch[:, 0] * bones[:, j - 1]
    with caplog.at_level(logging.WARNING, logger="mfm.export.bvh"):
        path = write_bvh(tmp_path / "drift.bvh", drifting, HUMANML3D)
    assert any("bone lengths vary" in r.getMessage() for r in caplog.records)
    parsed = read_bvh(path, HUMANML3D.joint_names).joints
    got = parsed[:, 1:] - parsed[:, parents[1:]]
    want = drifting[:, 1:] - drifting[:, parents[1:]]
    cosine = (got * want).sum(-1) / np.linalg.norm(got, axis=-1) / np.linalg.norm(want, axis=-1)
    assert cosine.min() > 1 - 1e-9
    assert np.abs(parsed - drifting).max() > 1e-3  # it really could not reproduce the positions


def test_no_drift_warning_for_a_rigid_clip(tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="mfm.export.bvh"):
        write_bvh(tmp_path / "rigid.bvh", synthetic_clip(HUMANML3D, frames=8, seed=4), HUMANML3D, fps=30)
    assert not caplog.records


def test_read_bvh_applies_channels_in_the_listed_order(tmp_path):
    # Hand-computed: listed "Zrotation Xrotation" means R = Rz(90) @ Rx(90). Rx(90) turns the child
    # offset (0, 1, 0) onto +z, which Rz leaves alone: child at root + (0, 0, 1). The opposite order
    # would put it at root + (-1, 0, 0).
    text = """HIERARCHY
ROOT hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT tip
  {
    OFFSET 0 1 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 1 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.04
1 2 3 90 90 0 0 0 0
1 2 3 0 0 0 0 0 0
"""
    path = tmp_path / "tiny.bvh"
    path.write_text(text)
    parsed = read_bvh(path)
    assert parsed.names == ["hips", "tip"] and parsed.fps == pytest.approx(25.0)
    np.testing.assert_allclose(parsed.joints[0], [[1, 2, 3], [1, 2, 4]], atol=1e-12)
    np.testing.assert_allclose(parsed.joints[1], [[1, 2, 3], [1, 3, 3]], atol=1e-12)


def test_euler_decomposition_recomposes_including_the_singularity():
    rng = np.random.default_rng(5)
    angles = np.concatenate((rng.uniform(-180, 180, (50, 3)), [[30.0, 90.0, 40.0], [-70.0, -90.0, 10.0]]))
    angles[:50, 1] = rng.uniform(-89.9, 89.9, 50)
    r = _axis_rotation("y", angles[:, 0]) @ _axis_rotation("x", angles[:, 1]) @ _axis_rotation("z", angles[:, 2])
    back = _euler_yxz_degrees(r)
    recomposed = _axis_rotation("y", back[:, 0]) @ _axis_rotation("x", back[:, 1]) @ _axis_rotation("z", back[:, 2])
    np.testing.assert_allclose(recomposed, r, atol=1e-10)
    np.testing.assert_allclose(back[:50], angles[:50], atol=1e-8)  # unique away from the singularity


def test_read_bvh_reports_a_truncated_file_by_name(tmp_path):
    path = write_bvh(tmp_path / "clip.bvh", synthetic_clip(HUMANML3D, frames=4), HUMANML3D)
    text = path.read_text()
    path.write_text(text[: len(text) - 40])
    with pytest.raises(ValueError, match="clip.bvh"):
        read_bvh(path)
    with pytest.raises(ValueError, match="no joint"):
        read_bvh(write_bvh(tmp_path / "ok.bvh", synthetic_clip(HUMANML3D, frames=4), HUMANML3D), ["tail"])


def test_write_bvh_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match=r"\(T, 22, 3\)"):
        write_bvh(tmp_path / "x.bvh", np.zeros((5, 21, 3)), HUMANML3D)
    joints = synthetic_clip(HUMANML3D, frames=4)
    joints[2, 5, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        write_bvh(tmp_path / "x.bvh", joints, HUMANML3D)
    collapsed = synthetic_clip(HUMANML3D, frames=4)
    collapsed[:, 4] = collapsed[:, 1]  # knee on the hip: the bone has no direction
    with pytest.raises(ValueError, match="left_knee"):
        write_bvh(tmp_path / "x.bvh", collapsed, HUMANML3D)


BLENDER_IMPORT_CHECK = """
import json, sys
import bpy
import numpy as np
from mathutils import Vector
bvh, joints_file, names_file = sys.argv[-3:]
names, joints = json.load(open(names_file)), np.load(joints_file)
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_anim.bvh(filepath=bvh, global_scale=1.0, axis_forward="-Z", axis_up="Y", update_scene_fps=True)
arm = next(o for o in bpy.context.scene.objects if o.type == "ARMATURE")
err = 0.0
for f in range(len(joints)):
    bpy.context.scene.frame_set(1 + f)
    for j, name in enumerate(names):
        want = Vector((joints[f, j, 0], -joints[f, j, 2], joints[f, j, 1]))  # Y up -> Blender's Z up
        err = max(err, ((arm.matrix_world @ arm.pose.bones[name].head) - want).length)
print("RESULT", json.dumps({"err": err, "fps": bpy.context.scene.render.fps / bpy.context.scene.render.fps_base}))
"""


def test_blender_imports_the_bvh_at_the_input_positions(reference_data, tmp_path):
    # Blender as a Python module (pip install bpy) needs its own interpreter version, so it runs apart.
    python = os.environ.get("MFM_BPY_PYTHON")
    if not python:
        pytest.skip("set MFM_BPY_PYTHON to a Python with the bpy module (pip install bpy) to check Blender's BVH import")
    joints = np.load(reference_data / "humanml3d" / "new_joints_012314.npy")[:60]
    path = write_bvh(tmp_path / "clip.bvh", joints, HUMANML3D)
    np.save(tmp_path / "joints.npy", joints)
    (tmp_path / "names.json").write_text(json.dumps(list(HUMANML3D.joint_names)))
    script = tmp_path / "check.py"
    script.write_text(BLENDER_IMPORT_CHECK)
    run = subprocess.run([python, str(script), str(path), str(tmp_path / "joints.npy"), str(tmp_path / "names.json")],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    result = json.loads(next(line for line in run.stdout.splitlines() if line.startswith("RESULT"))[len("RESULT "):])
    assert result["err"] <= 1e-4 and result["fps"] == pytest.approx(20.0)


# ---------------------------------------------------------------------------------------------------
# videos



def test_bvh_of_the_rigid_decode_of_noisy_features_reparses_to_it(reference_data, tmp_path, caplog):
    """Generated-like features (the real clip + 0.1 Std of noise): their ric bones stretch, the rigid decode's do
    not, so its BVH reproduces it exactly (what pipeline/generation/sampling.py writes)."""
    folder = reference_data / "humanml3d"
    features = np.load(folder / "new_joint_vecs_012314.npy")[:60]
    noisy = features + 0.1 * np.load(folder / "Std.npy") * np.random.default_rng(1).standard_normal(features.shape)
    rigid = features_to_joints_rigid(noisy.astype(np.float32), HUMANML3D)
    with caplog.at_level(logging.WARNING, logger="mfm.export.bvh"):
        path = write_bvh(tmp_path / "rigid.bvh", rigid, HUMANML3D)
    assert not caplog.records  # no drifting bone lengths to warn about
    parsed = read_bvh(path, HUMANML3D.joint_names).joints
    np.testing.assert_allclose(parsed, rigid, rtol=0, atol=1e-5)

def gif_frames(path) -> list[np.ndarray]:
    with Image.open(path) as im:
        assert im.format == "GIF"
        out = []
        for i in range(im.n_frames):
            im.seek(i)
            out.append(np.asarray(im.convert("RGB"), dtype=np.int32))
        return out


def pixels_near(frame: np.ndarray, color: str, tolerance: float = 40.0) -> int:
    target = np.array(to_rgb(color)) * 255
    return int((np.linalg.norm(frame - target, axis=-1) < tolerance).sum())


@pytest.fixture
def short_clip():
    return synthetic_clip(HUMANML3D, frames=12, seed=6)


def test_render_writes_a_gif_with_one_frame_per_pose(tmp_path, short_clip):
    # The MP4 target name is replaced by .gif when the GIF path is forced.
    out = render_motion(tmp_path / "clip.mp4", short_clip, HUMANML3D, fps=20, fmt="gif", size_px=96,
                        title=[(0, "a person walks"), (6, "then turns")])
    assert out == tmp_path / "clip.gif" and out.stat().st_size > 0
    frames = gif_frames(out)
    assert len(frames) == 12 and frames[0].shape == (96, 96, 3)
    with Image.open(out) as im:
        assert im.info["duration"] == 50  # ms per frame at 20 fps


def test_render_falls_back_to_gif_without_ffmpeg(tmp_path, short_clip, monkeypatch):
    monkeypatch.setitem(rcParams, "animation.ffmpeg_path", "no-such-ffmpeg-binary")
    assert not ffmpeg_available()
    out = render_motion(tmp_path / "clip.mp4", short_clip[:3], HUMANML3D, size_px=64)
    assert out.suffix == ".gif" and len(gif_frames(out)) == 3
    with pytest.raises(RuntimeError, match="ffmpeg"):
        render_motion(tmp_path / "clip.mp4", short_clip[:3], HUMANML3D, size_px=64, fmt="mp4")


def test_render_writes_an_mp4_when_ffmpeg_is_on_path(tmp_path, short_clip):
    if not ffmpeg_available():
        pytest.skip(f"ffmpeg ({rcParams['animation.ffmpeg_path']!r}) is not on PATH: only the GIF path can be tested here")
    out = render_motion(tmp_path / "clip", short_clip, HUMANML3D, size_px=96)
    assert out.suffix == ".mp4" and out.stat().st_size > 0
    assert out.read_bytes()[4:8] == b"ftyp"  # an ISO media file
    decoded = subprocess.run([shutil.which(rcParams["animation.ffmpeg_path"]), "-i", str(out), "-f", "null", "-"],
                             capture_output=True, text=True, timeout=60)
    assert re.findall(r"frame=\s*(\d+)", decoded.stderr)[-1] == str(len(short_clip))


def test_render_colours_kept_and_edited_parts(tmp_path, short_clip):
    upper_edited = np.ones(HUMANML3D.num_joints, dtype=bool)
    upper_edited[list(HUMANML3D.lower_body_joints)] = False
    out = render_motion(tmp_path / "mask", short_clip[:2], HUMANML3D, edited=upper_edited, fmt="gif", size_px=160)
    frame = gif_frames(out)[0]
    assert pixels_near(frame, KEPT_COLOR) > 30 and pixels_near(frame, EDITED_COLOR) > 30

    per_frame = np.array([False, True])  # frame 0 kept, frame 1 generated
    out = render_motion(tmp_path / "frames", short_clip[:2], HUMANML3D, edited=per_frame, fmt="gif", size_px=160)
    kept, generated = gif_frames(out)
    assert pixels_near(kept, KEPT_COLOR) > 30 and pixels_near(kept, EDITED_COLOR) == 0
    assert pixels_near(generated, EDITED_COLOR) > 30 and pixels_near(generated, KEPT_COLOR) == 0


def test_caption_segments_and_mask_shapes():
    assert caption_per_frame([(0, "a"), (2, "b")], 4) == ["a", "a", "b", "b"]
    assert caption_per_frame([(1, "late")], 3) == ["", "late", "late"]
    assert caption_per_frame("same", 2) == ["same", "same"]
    with pytest.raises(ValueError, match="increasing"):
        caption_per_frame([(2, "b"), (0, "a")], 4)
    with pytest.raises(ValueError, match="increasing"):
        caption_per_frame([(5, "a")], 4)
    assert edited_per_frame(np.array([True, False, False]), 3, 2).tolist() == [[True, True], [False, False], [False, False]]
    assert edited_per_frame(np.array([True, False]), 3, 2).tolist() == [[True, False]] * 3
    with pytest.raises(ValueError, match="ambiguous"):
        edited_per_frame(np.zeros(22, bool), 22, 22)
    with pytest.raises(ValueError, match="edited mask"):
        edited_per_frame(np.zeros(5, bool), 3, 2)


# ---------------------------------------------------------------------------------------------------
# x̂1 trajectory figure


def test_plot_x1_trajectory_from_normalised_features(reference_data, tmp_path):
    features = np.load(reference_data / "humanml3d" / "new_joint_vecs_012314.npy")[:40]
    mean = np.load(reference_data / "humanml3d" / "Mean.npy")
    std = np.load(reference_data / "humanml3d" / "Std.npy")
    clean = (features - mean) / std
    noise = np.random.default_rng(7).standard_normal(clean.shape)
    times = torch.linspace(0, 1, 11, dtype=torch.float64)
    estimates = torch.stack([(1 - t) * 0.3 * torch.from_numpy(noise) + t * torch.from_numpy(clean) for t in times])
    out = plot_x1_trajectory(tmp_path / "traj.png", estimates, times, HUMANML3D, mean=mean, std=std,
                             max_panels=4, panel_px=120, title="a person serves")
    with Image.open(out) as im:
        assert im.format == "PNG" and im.size == (4 * 120, 120 + 30)
        pixels = np.asarray(im.convert("RGB"), dtype=np.int32)
    assert (pixels.sum(-1) < 600).sum() > 100  # something is drawn on the white background


def test_plot_x1_trajectory_from_joints_and_bad_shapes(tmp_path):
    joints = np.stack([synthetic_clip(KIT, frames=10, seed=s, metre=1000.0) for s in range(3)])
    out = plot_x1_trajectory(tmp_path / "kit.png", joints, [0.0, 0.5, 1.0], KIT, frames=[0, 9], panel_px=100)
    with Image.open(out) as im:
        assert im.size == (300, 100)
    with pytest.raises(ValueError, match="pick one sample"):
        plot_x1_trajectory(tmp_path / "x.png", np.zeros((3, 2, 10, KIT.feature_dim)), [0, 0.5, 1], KIT)
    with pytest.raises(ValueError, match="times has 2"):
        plot_x1_trajectory(tmp_path / "x.png", joints, [0.0, 1.0], KIT)
