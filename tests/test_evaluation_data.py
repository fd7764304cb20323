"""The evaluation job scores only verified ground truth (issue 12, item 2): its results file says what was verified,
and a test shard changed after the build (same byte size, only the sha256 differs) stops the job with one line that
names the file and the reason, instead of a score under the manifest's dataset id.

Data: the synthetic source with MiniLM captions shared with tests/test_evaluation.py, copied so it can be tampered
with; a tiny model trained for two steps; an untrained (seeded) evaluator, enough for the job's plumbing.
"""

from __future__ import annotations

import io
import json
import shutil
import tarfile
from pathlib import Path

import numpy as np
from eval_worker import (
    SMALL_PROTOCOL,
    build_synthetic_dataset,
    random_contrastive_evaluator,
    train_tiny_model,
)


def evaluate(*args: str) -> int:
    from launch.evaluate import main

    return main(list(args))


def scale_features_in_place(shard: Path, factor: float) -> None:
    """Multiply the first record's features by ``factor`` inside the tar: same size, different bytes."""
    with tarfile.open(shard) as tar:
        member = next(m for m in tar.getmembers() if m.name.endswith(".features.npy"))
        features = np.load(io.BytesIO(tar.extractfile(member).read()))
    payload = io.BytesIO()
    np.save(payload, features * factor, allow_pickle=False)
    assert len(payload.getvalue()) == member.size
    with open(shard, "r+b") as handle:
        handle.seek(member.offset_data)
        handle.write(payload.getvalue())


def test_results_record_verified_ground_truth_and_a_tampered_test_shard_is_refused(tmp_path_factory, tmp_path,
                                                                                   capsys):
    shared = build_synthetic_dataset(tmp_path_factory.getbasetemp() / "eval-synthetic")
    shutil.copytree(shared.parent, tmp_path / "data")
    manifest = tmp_path / "data" / "manifest.json"
    run = train_tiny_model(manifest, tmp_path / "run")
    evaluator = random_contrastive_evaluator(manifest, tmp_path / "evaluator.safetensors")
    args = ["--checkpoint", str(run / "checkpoints" / "step-00000002"), "--protocol", "fast", "--steps", "1",
            *SMALL_PROTOCOL, "tasks.editing=[]", "tasks.flame=false", f"evaluator.path={evaluator}"]

    assert evaluate(*args, f"output.dir={tmp_path / 'eval'}") == 0
    [result_file] = (tmp_path / "eval" / "results" / "step-00000002").glob("*.json")
    data = json.loads(result_file.read_text())["data"]
    assert data["data_verified"] is True and data["dataset_id"] == json.loads(manifest.read_text())["dataset_id"]
    verification = data["verification"]
    assert verification["split"] == "test" and verification["mode"] == "strict" and verification["bad"] == []
    assert {"size", "sha256", "record_count", "unique_ids"} <= set(verification["checks"])
    test_shards = json.loads(manifest.read_text())["splits"]["test"]["shards"]
    assert verification["num_checked"] == len(test_shards)

    tampered = test_shards[0]["path"]
    scale_features_in_place(manifest.parent / tampered, 50.0)
    capsys.readouterr()
    assert evaluate(*args, f"output.dir={tmp_path / 'eval-tampered'}") == 2
    error = capsys.readouterr().err
    assert f"{tampered}: bad shard (corrupted: sha256" in error and "refusing to score against split 'test'" in error
    assert not list((tmp_path / "eval-tampered").glob("results/*/*.json"))
