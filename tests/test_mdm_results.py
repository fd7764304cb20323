"""mfm.export.mdm_results: MDM's results.npy (sample/generate.py's layout), written and read back."""

from __future__ import annotations

import numpy as np
import pytest

from mfm.export import read_mdm_results, write_mdm_results


def motion(frames: int, tag: float, joints: int = 22) -> np.ndarray:
    """(frames, joints, 3) whose every value says which motion and frame it is."""
    t = np.arange(frames, dtype=np.float32)[:, None, None]
    j = np.arange(joints, dtype=np.float32)[None, :, None]
    return (tag * 1000 + t + j / 100 + np.array([0.0, 0.1, 0.2], np.float32)).astype(np.float32)


def test_round_trip_in_mdms_layout_and_order(tmp_path):
    texts = ["a person walks", "a person jumps", "a person waves"]
    lengths = [40, 57, 23]
    reps = 2
    # repetition-major, as MDM: entry rep * num_samples + sample
    joints = [motion(lengths[s], tag=10 * rep + s) for rep in range(reps) for s in range(3)]
    path = write_mdm_results(tmp_path / "out", joints, texts, lengths, reps)
    assert path == tmp_path / "out" / "results.npy"

    # Exactly what MDM's generate.py saves and visualize/vis_utils.py (npy2obj) reads.
    raw = np.load(path, allow_pickle=True)[None][0]
    assert sorted(raw) == ["lengths", "motion", "num_repetitions", "num_samples", "text"]
    assert raw["motion"].shape == (6, 22, 3, 57) and raw["motion"].dtype == np.float32
    assert raw["num_samples"] == 3 and raw["num_repetitions"] == 2
    assert type(raw["num_samples"]) is int and type(raw["num_repetitions"]) is int
    assert raw["text"] == texts * 2 and isinstance(raw["text"], list)
    assert raw["lengths"].dtype == np.int64 and raw["lengths"].tolist() == lengths * 2
    absl_idx = 1 * raw["num_samples"] + 2  # npy2obj: rep_idx * num_samples + sample_idx
    np.testing.assert_array_equal(raw["motion"][absl_idx].transpose(2, 0, 1)[: raw["lengths"][absl_idx]], motion(23, 12))
    # padded with the last frame, as MDM's videos freeze a motion past its length
    padded = raw["motion"][absl_idx].transpose(2, 0, 1)[23:]
    np.testing.assert_array_equal(padded, np.broadcast_to(motion(23, 12)[-1], (57 - 23, 22, 3)))
    assert (tmp_path / "out" / "results.txt").read_text() == "\n".join(texts * 2)
    assert (tmp_path / "out" / "results_len.txt").read_text() == "\n".join(str(n) for n in lengths * 2)

    results = read_mdm_results(tmp_path / "out")
    for rep in range(reps):
        for s in range(3):
            np.testing.assert_array_equal(results.joints(s, rep), motion(lengths[s], 10 * rep + s))
            assert results.text(s, rep) == texts[s] and results.lengths[results.index(s, rep)] == lengths[s]
    with pytest.raises(IndexError):
        results.index(3, 0)


def test_sample_major_input_lengths_from_the_arrays_and_max_frames(tmp_path):
    texts = ["kick", "spin"]
    reps = 3
    # sample-major input: entry sample * R + rep; each repetition its own length (from the arrays)
    frames = {(s, rep): 30 + 5 * s + rep for s in range(2) for rep in range(reps)}
    joints = [motion(frames[s, rep], tag=10 * rep + s, joints=21) for s in range(2) for rep in range(reps)]
    per_motion_texts = [f"{texts[s]} #{rep}" for s in range(2) for rep in range(reps)]
    path = write_mdm_results(tmp_path / "r.npy", joints, per_motion_texts, None, reps, order="sample_major",
                             max_frames=196, text_files=False)
    assert path == tmp_path / "r.npy" and not (tmp_path / "r.txt").exists()
    results = read_mdm_results(path)
    assert results.motion.shape == (6, 21, 3, 196) and (results.num_samples, results.num_repetitions) == (2, 3)
    assert results.texts == [f"{texts[s]} #{rep}" for rep in range(reps) for s in range(2)]  # MDM's order
    assert results.lengths.tolist() == [frames[s, rep] for rep in range(reps) for s in range(2)]
    for s in range(2):
        for rep in range(reps):
            np.testing.assert_array_equal(results.joints(s, rep), motion(frames[s, rep], 10 * rep + s, joints=21))


def test_bad_input_is_refused(tmp_path):
    joints = [motion(40, 0), motion(40, 1)]
    with pytest.raises(ValueError, match="3 motions cannot be 2 repetitions"):
        write_mdm_results(tmp_path, joints + [motion(40, 2)], ["a"], None, 2)
    with pytest.raises(ValueError, match="texts: expected 1 values"):
        write_mdm_results(tmp_path, joints, ["a", "b", "c"], None, 2)
    with pytest.raises(ValueError, match="length 41 outside 1..40"):
        write_mdm_results(tmp_path, joints, ["a", "b"], [40, 41], 1)
    with pytest.raises(ValueError, match="max_frames 30"):
        write_mdm_results(tmp_path, joints, ["a", "b"], None, 1, max_frames=30)
    with pytest.raises(ValueError, match="motion 1 has 21 joints"):
        write_mdm_results(tmp_path, [motion(40, 0), motion(40, 1, joints=21)], ["a", "b"], None, 1)
    with pytest.raises(ValueError, match="expected joint positions"):
        write_mdm_results(tmp_path, [np.zeros((40, 22))], ["a"], None, 1)
    np.save(tmp_path / "other.npy", {"motion": np.zeros((1, 22, 3, 5))}, allow_pickle=True)
    with pytest.raises(ValueError, match="missing"):
        read_mdm_results(tmp_path / "other.npy")
