"""The evaluation job: protocol bookkeeping, claims, results layout, the watcher, end-to-end runs on CPU.

Data: the synthetic source with real MiniLM captions (80 clips, test split of 10), a tiny model trained for two
steps in-process (checkpoints at steps 1 and 2), and a tiny evaluator trained by launch/train_evaluator.py.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
from conftest import embedded_dataset_once
from eval_worker import (
    SMALL_PROTOCOL,
    TINY_EVALUATOR,
    build_synthetic_dataset,
    random_contrastive_evaluator,
    train_tiny_model,
)

from mfm.model import valid_frame_mask
from pipeline.config import ConfigError
from pipeline.evaluation.config import SamplingPoint, load_eval_config, sweep_overrides
from pipeline.evaluation.replications import (
    edit_points,
    my_batches,
    plan_protocol,
    plan_repeats,
    plan_rows,
)
from pipeline.evaluation.spaces import build_ground_truth, read_ground_truth_pool
from pipeline.evaluation.store import ResultsStore, Unit, this_pid_namespace

REPO_ROOT = Path(__file__).resolve().parents[1]
EVALUATE = REPO_ROOT / "launch" / "evaluate.py"
PLAUSIBILITY = {"bone_length_range", "bone_length_deviation", "floor_penetration", "foot_skating_ratio",
                "contact_foot_speed", "skating_foot_speed", "mean_jerk", "jerk_ratio", "pose_speed", "root_speed", "pose_spread"}


# ---------------------------------------------------------------------------------------------------------------
# fixtures


@pytest.fixture(scope="session")
def manifest(tmp_path_factory) -> Path:
    return build_synthetic_dataset(tmp_path_factory.getbasetemp() / "eval-synthetic")


@pytest.fixture(scope="session")
def text_run(manifest, tmp_path_factory) -> Path:
    return train_tiny_model(manifest, tmp_path_factory.mktemp("text-run"))


@pytest.fixture(scope="session")
def trained_evaluator(manifest, tmp_path_factory) -> tuple[Path, dict]:
    from launch.train_evaluator import main

    out = tmp_path_factory.mktemp("evaluator")
    tiny = [f"model.{k}={v}" for k, v in TINY_EVALUATOR.items()]
    assert main([f"data.manifest={manifest}", f"out_dir={out}", "optim.steps=12", "optim.log_every=6",
                 "optim.lr=2e-3", "optim.warmup_steps=0", "data.batch_size=8", "data.window=64", *tiny]) == 0
    return out / "contrastive.safetensors", json.loads((out / "report.json").read_text())


def evaluate(*args: str) -> int:
    from launch.evaluate import main

    return main(list(args))


def _fake_ids(n: int) -> Unit:
    return Unit("step-00000001", "euler-10steps-g2.5", f"{n:064x}")


# ---------------------------------------------------------------------------------------------------------------
# settings and bookkeeping


def test_protocol_presets_and_sweep_flags():
    full, fast = load_eval_config("full"), load_eval_config("fast")
    assert (full.protocol.replications, fast.protocol.replications) == (20, 3)
    assert (full.protocol.r_precision_batch, full.protocol.diversity_times) == (32, 300)
    assert (full.protocol.mm_repeats, full.protocol.mm_times, full.protocol.mm_num_texts) == (30, 10, 100)
    swept = load_eval_config("fast", overrides=sweep_overrides("euler,midpoint", "5,10", "2.5"))
    assert [p.name for p in swept.sampling.points()] == ["euler-5steps-g2.5", "euler-10steps-g2.5",
                                                         "midpoint-5steps-g2.5", "midpoint-10steps-g2.5"]
    # Per-solver step counts; an adaptive solver runs once; flow and diffusion samplers may share a sweep.
    mixed = load_eval_config("fast", overrides=sweep_overrides(
        "euler,midpoint,dopri5,ddim", ["5,10,1000", "midpoint=5,25"], None))
    assert [p.name for p in mixed.sampling.points()] == [
        "euler-5steps-g2.5", "euler-10steps-g2.5", "euler-1000steps-g2.5", "midpoint-5steps-g2.5",
        "midpoint-25steps-g2.5", "dopri5-5steps-g2.5", "ddim-5steps-g2.5", "ddim-10steps-g2.5", "ddim-1000steps-g2.5"]
    with pytest.raises(ConfigError, match="steps_per_solver names 'heun'"):
        load_eval_config("fast", overrides=sweep_overrides("euler", ["5", "heun=2"], None))
    with pytest.raises(ConfigError, match="protocol"):
        load_eval_config("slow")
    with pytest.raises(ConfigError, match="unknown preset"):
        load_eval_config("fast", overrides=["tasks.editing=[teleport]"])
    debug = load_eval_config("fast", overrides=["tasks.edit_settings=reference-debug",
                                                "tasks.edit_rewrite_until={upper_body: 0.3}"]).tasks.edit_setup()
    assert (debug["settings"], debug["steps"], debug["guidance"]) == ("reference-debug", 100, 1.0)
    assert debug["rewrite_until"] == {"prediction": 0.5, "inbetween": 1.0, "interpolation": 1.0, "upper_body": 0.3}
    assert debug["overridden"] == ["rewrite_until.upper_body"]
    # edit.py's interpolate preset integrates one step (step_size 1), the others 100; tasks.edit_steps sets them all
    assert debug["steps_per_preset"] == {"prediction": 100, "inbetween": 100, "interpolation": 1, "upper_body": 100}
    point = SamplingPoint("midpoint", 10, 2.5)
    flow = edit_points(point, debug, "flow")
    assert flow["interpolation"] == SamplingPoint("euler", 1, 1.0)
    assert flow["upper_body"] == SamplingPoint("euler", 100, 1.0)
    assert set(edit_points(point, debug, "diffusion").values()) == {point}  # replacement edits: the point's own
    paper = load_eval_config("fast").tasks.edit_setup()
    assert set(paper["steps_per_preset"].values()) == {30} and "§4.1" in paper["source"]
    fixed = load_eval_config("fast", overrides=["tasks.edit_settings=reference-debug", "tasks.edit_steps=7"])
    assert set(fixed.tasks.edit_setup()["steps_per_preset"].values()) == {7}
    with pytest.raises(ConfigError, match="tasks.edit_settings"):
        load_eval_config("fast", overrides=["tasks.edit_settings=debug"])
    with pytest.raises(ConfigError, match="mm_times"):
        load_eval_config("fast", overrides=["protocol.mm_times=50"])


def test_units_computing_ape_ave_are_keyed_by_its_definition(monkeypatch):
    """Issue 25 moved APE/AVE (TEMOS's floor in millimetres): units with tasks.flame hash the definition, so results
    computed before are not taken as done; units without APE/AVE keep their keys."""
    from pipeline.evaluation import job

    point, ids, folder = SamplingPoint("euler", 10, 2.5), {"checkpoint": "c", "evaluator": "e", "gt": "g"}, Path("s")
    with_ape, without = load_eval_config("fast"), load_eval_config("fast", overrides=["tasks.flame=false"])
    keys = [job.CheckpointScorer(cfg, None).unit_for(folder, ids, point).key for cfg in (with_ape, without)]
    monkeypatch.setattr(job, "APE_AVE_REVISION", "another definition")
    again = [job.CheckpointScorer(cfg, None).unit_for(folder, ids, point).key for cfg in (with_ape, without)]
    assert again[0] != keys[0] and again[1] == keys[1]
    # reference-debug's interpolation runs one step (was 100): its units get a key of their own, the others keep theirs
    debug = ["tasks.flame=false", "tasks.edit_settings=reference-debug"]
    unit = lambda *o: job.CheckpointScorer(load_eval_config("fast", overrides=[*debug, *o]), None).unit_for(
        folder, ids, point).key
    assert unit("tasks.editing=[prediction]") == unit("tasks.editing=[prediction]")
    settings = []
    monkeypatch.setattr(job, "digest", lambda value: settings.append(value) or "k")
    unit("tasks.editing=[prediction,interpolation]"), unit("tasks.editing=[prediction]"), unit("tasks.edit_steps=7")
    assert [s.get("edit_steps_per_preset") for s in settings] == [{"interpolation": 1}, None, None]


def test_edit_ade_fde_are_reported_in_metres_for_kit_joints_in_millimetres():
    """ADE/FDE of an edit batch on KIT (joints in millimetres) come out in metres, as the tables say."""
    from mfm.layout import FeatureLayout
    from mfm.skeleton import KIT
    from pipeline.evaluation.replications import Batch, PointRun

    run = object.__new__(PointRun)  # only what _joint_stats reads
    run.skeleton, run.layout, run.flame = KIT, FeatureLayout(KIT), False
    lengths = torch.tensor([8, 8])
    gt_raw = torch.zeros(2, 8, KIT.feature_dim)
    raw = gt_raw.clone()
    raw[..., 3] = 21.0  # the root 21 mm higher on every frame, the other 20 joints where they were: 1 mm per joint
    batch = Batch(0, "edit:inbetween", np.arange(2), np.arange(2), np.zeros(2, np.int64))
    stats = run._joint_stats(batch, "edit:inbetween", raw, lengths, gt_raw)
    assert stats["ade"] == pytest.approx(1e-3) and stats["fde"] == pytest.approx(1e-3)  # 1 mm = 0.001 m
    # KIT editing units computed before (in millimetres) get new keys, so they run again; HumanML3D's keep theirs
    from types import SimpleNamespace

    from mfm.skeleton import HUMANML3D
    from pipeline.evaluation.job import checkpoint_settings

    cfg = load_eval_config("fast")
    assert checkpoint_settings(SimpleNamespace(objective="flow", skeleton=KIT), cfg) == {"ade_fde_unit": "m"}
    assert checkpoint_settings(SimpleNamespace(objective="flow", skeleton=HUMANML3D), cfg) == {}
    no_edits = load_eval_config("fast", overrides=["tasks.editing=[]"])
    assert checkpoint_settings(SimpleNamespace(objective="flow", skeleton=KIT), no_edits) == {}


def test_small_test_sets_reduce_the_protocol_explicitly():
    cfg = load_eval_config("full")
    plan = plan_protocol(cfg, num_items=13, mm_candidates=13)
    assert (plan.r_precision_batch, plan.diversity_times, plan.mm_num_texts) == (13, 12, 13)
    assert len(plan.notes) == 3 and "not comparable" in plan.notes[0]
    big = plan_protocol(cfg, num_items=4384, mm_candidates=4384)
    assert (big.r_precision_batch, big.diversity_times, big.mm_num_texts, big.notes) == (32, 300, 100, ())


@pytest.mark.parametrize("world_size", [1, 2, 3])
def test_every_slot_is_generated_exactly_once_whatever_the_world_size(world_size):
    lengths = np.random.default_rng(0).integers(40, 197, 23)
    items = np.arange(23)
    batches = plan_rows("main", items, lengths, 4, 0)
    batches += plan_repeats(np.array([3, 7, 11]), lengths, 5, 12, len(batches))

    class FakeDist:
        def __init__(self, rank):
            self.rank, self.world_size = rank, world_size

    mine = [my_batches(batches, FakeDist(r)) for r in range(world_size)]
    main = np.concatenate([b.slots for part in mine for b in part if b.kind == "main"])
    assert sorted(main.tolist()) == list(range(23))
    mm = [b for part in mine for b in part if b.kind == "mm"]
    assert sorted(np.concatenate([b.slots for b in mm]).tolist()) == list(range(15))
    for batch in mm:  # a text's repetitions never straddle batches (joint variance is per batch)
        assert all(np.sum(batch.slots // 5 == t) == 5 for t in np.unique(batch.slots // 5))
    # rows of a batch share similar lengths: sorted by length before chunking
    assert all(np.all(np.diff(lengths[b.items]) >= 0) for b in batches if b.kind == "main")


def test_claims_are_exclusive_until_released_done_or_stale(tmp_path):
    first, second = ResultsStore(tmp_path, claim_timeout_s=60), ResultsStore(tmp_path, claim_timeout_s=60)
    unit = _fake_ids(1)
    assert first.try_claim(unit) and not second.try_claim(unit)
    first.release(unit)
    assert second.try_claim(unit)
    # a claim whose holder stopped heartbeating is taken over; a refreshed one is not
    old = time.time() - 120
    os.utime(second.claim_path(unit), (old, old))
    second.heartbeat(unit)
    assert not first.try_claim(unit)
    os.utime(second.claim_path(unit), (old, old))
    assert first.try_claim(unit)
    row = {"row_key": "k:generated", "fid": 1.0}
    first.write_result(unit, {"key": unit.key}, [row])
    first.release(unit)
    assert first.is_done(unit) and not second.try_claim(unit)


# A stand-in for another evaluator job: it claims the units given as checkpoint|point|key, says so, then either
# dies at once without releasing them (kill -9) or stays alive holding them.
_CLAIMING_JOB = """
import os, signal, sys, time
from pipeline.evaluation.store import ResultsStore, Unit
store = ResultsStore(sys.argv[1])
assert all(store.try_claim(Unit(*spec.split("|"))) for spec in sys.argv[3:])
print("claimed", flush=True)
if sys.argv[2] == "die":
    os.kill(os.getpid(), signal.SIGKILL)
time.sleep(600)
"""


def _claiming_job(root: Path, units: list[Unit], then: str) -> subprocess.Popen:
    """Start a process that claims ``units`` in the store at ``root``; ``then`` is 'die' or 'live'. Returns once
    the claims exist (and, for 'die', once the process is gone and reaped: its pid is dead)."""
    specs = [f"{u.checkpoint_name}|{u.point_name}|{u.key}" for u in units]
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    proc = subprocess.Popen([sys.executable, "-c", _CLAIMING_JOB, str(root), then, *specs], cwd=REPO_ROOT, env=env,
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "claimed"
    if then == "die":
        assert proc.wait(timeout=30) == -signal.SIGKILL
    return proc


def test_a_dead_jobs_claim_on_this_host_is_stale_at_once_others_keep_the_heartbeat_rule(tmp_path, caplog):
    store = ResultsStore(tmp_path, claim_timeout_s=3600)
    dead, live, foreign = (Unit("step-00000001", f"euler-{n}steps-g2.5", f"{n:064x}") for n in (1, 2, 3))
    corpse = _claiming_job(tmp_path, [dead, foreign], "die")
    holder = _claiming_job(tmp_path, [live], "live")
    try:
        assert all(store.claim_path(u).is_file() for u in (dead, live, foreign))
        # The same dead pid, recorded as from another host: nothing can be told from here, so the age rule holds.
        claim = json.loads(store.claim_path(foreign).read_text())
        assert (claim["host"], claim["pid"]) == (socket.gethostname(), corpse.pid)
        store.claim_path(foreign).write_text(json.dumps({**claim, "host": f"not-{socket.gethostname()}"}))
        with caplog.at_level("WARNING", logger="pipeline.evaluation.store"):
            assert store.try_claim(dead)  # fresh claim, but its job is dead: taken over without waiting an hour
        assert f"pid {corpse.pid} on this host" in caplog.text and "taking over" in caplog.text
        assert claim.get("pid_ns") == this_pid_namespace()  # pids are compared within one pid namespace only
        assert json.loads(store.claim_path(dead).read_text())["pid"] == os.getpid()
        assert not store.try_claim(live) and not store.try_claim(foreign)
        held = store.holder(live)
        assert (held.host, held.pid) == (socket.gethostname(), holder.pid) and held.heartbeat_age_s < 60
        old = time.time() - 7200
        os.utime(store.claim_path(foreign), (old, old))
        assert store.try_claim(foreign)  # another host's claim: stale after claim_timeout_s without a heartbeat
    finally:
        holder.kill()
        holder.wait(timeout=30)
    assert store.try_claim(live)  # its holder is dead now


def _race(root: str, key: int, barrier, results) -> None:
    barrier.wait()
    results.put(ResultsStore(root).try_claim(_fake_ids(key)))


def test_concurrent_processes_claim_a_unit_once(tmp_path):
    context = multiprocessing.get_context("fork")
    barrier, results = context.Barrier(4), context.Queue()
    procs = [context.Process(target=_race, args=(str(tmp_path), 7, barrier, results)) for _ in range(4)]
    for p in procs:
        p.start()
    outcomes = [results.get(timeout=30) for _ in procs]
    for p in procs:
        p.join(timeout=30)
    assert sorted(outcomes) == [False, False, False, True]


def test_table_rows_are_appended_once_and_mirrored_to_parquet(tmp_path):
    store = ResultsStore(tmp_path)
    rows = [{"row_key": "a:generated", "fid": 1.5, "fid_ci": 0.1}, {"row_key": "a:ground_truth", "fid": 0.01}]
    store.append_rows(rows)
    store.append_rows(rows)  # a repair after a crash must not duplicate
    store.append_rows([{"row_key": "b:generated", "accuracy": 0.5}])
    assert [r["row_key"] for r in store.table_rows()] == ["a:generated", "a:ground_truth", "b:generated"]
    table = pq.read_table(store.table_parquet).to_pylist()
    assert [r["fid"] for r in table] == [1.5, 0.01, None] and table[2]["accuracy"] == 0.5


def _rows_on(dataset_id: str, split: str, key: str) -> list[dict]:
    return [{"row_key": f"{key}:{kind}", "dataset_id": dataset_id, "split": split, "fid": 1.0}
            for kind in ("generated", "ground_truth")]


def test_one_table_never_holds_two_test_sets(tmp_path):
    """Issue 24.1: results on two test sets (dataset id, split) in one table read as comparable; the table refuses
    the second, before its result file is written, and a page over a table an earlier version mixed is refused."""
    from pipeline.evaluation.store import MixedTestSetError
    from pipeline.generation.browse import write_eval_index

    store = ResultsStore(tmp_path / "eval")
    first, second, third = (Unit(f"step-{n:08d}", "euler-10steps-g2.5", f"{n:064x}") for n in (1, 2, 3))
    store.write_result(first, {"unit": 1}, _rows_on("a" * 64, "test", "1"))
    store.write_result(second, {"unit": 2}, _rows_on("a" * 64, "test", "2"))  # the same test set: fine
    for other, message in (({"dataset_id": "b" * 64}, f"refusing to add results on test set {'b' * 16} "),
                           ({"split": "val"}, "refusing to add results on test set aaaaaaaaaaaaaaaa (split 'val')")):
        rows = [{**row, **other} for row in _rows_on("a" * 64, "test", "3")]
        with pytest.raises(MixedTestSetError, match=re.escape(message) + ".*one table never mixes test sets"):
            store.write_result(third, {"unit": 3}, rows)
        with pytest.raises(MixedTestSetError):
            store.append_rows(rows)
        assert not store.is_done(third) and len(store.table_rows()) == 4
    assert [d.dataset_id for d in store.scored_data()] == ["a" * 64]

    mixed = tmp_path / "mixed"
    mixed.mkdir()
    (mixed / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in _rows_on("a" * 64, "test", "1")
                                                 + _rows_on("b" * 64, "test", "2")))
    with pytest.raises(ValueError, match=r"results\.jsonl: results on 2 test sets .*one page never mixes"):
        write_eval_index(mixed)
    with pytest.raises(MixedTestSetError, match="written before the table refused a second test set"):
        ResultsStore(mixed).append_rows(_rows_on("a" * 64, "test", "3"))


def _scale_first_record(manifest: Path, shard: str, *, resign_id: bool) -> None:
    """Scale the features of the first record of ``shard`` in place (same byte count) and re-sign the shard's
    sha256 in the manifest; ``resign_id``: the dataset id too (a fully consistent manifest)."""
    from test_trainer_bad_data import rewrite_record_features

    rewrite_record_features(manifest, shard, lambda features: features * 3.0, resign_id=resign_id)


def test_a_run_scored_on_one_test_set_refuses_another_unless_told(text_run, manifest, tmp_path, capsys):
    """Issue 24.1: a tampered test shard re-signed in the manifest shifted FID while results said data_verified: true
    under the original dataset id. Re-signed hash only: the ground truth is refused (the id is derived again).
    Re-signed id too: nothing in the data can tell, but the run's earlier results are on another test set, so the job
    refuses, unless data.allow_other_test_set=true, and even then never into the same table."""
    run = tmp_path / "run"
    shutil.copytree(text_run, run)
    checkpoint = run / "checkpoints" / "step-00000002"
    quick = [a for a in _quick_eval_args(random_contrastive_evaluator(manifest, tmp_path / "a.safetensors"), tmp_path)
             if not a.startswith("output.dir=")]
    assert evaluate("--checkpoint", str(checkpoint), *quick) == 0  # into the run's own <run>/eval
    scored_a = ResultsStore(run / "eval").scored_data()
    assert [d.dataset_id for d in scored_a] == [json.loads(manifest.read_text())["dataset_id"]]

    def tampered_copy(name: str, *, resign_id: bool) -> tuple[Path, list[str]]:
        """A copy of the data with one test record's features scaled and its shard's sha256 re-signed, and the
        arguments that evaluate on it (with an evaluator made for the id it is read as)."""
        copy = tmp_path / name / "manifest.json"
        shutil.copytree(manifest.parent, copy.parent)
        _scale_first_record(copy, json.loads(copy.read_text())["splits"]["test"]["shards"][0]["path"],
                            resign_id=resign_id)
        evaluator = random_contrastive_evaluator(copy, tmp_path / name / "evaluator.safetensors")
        return copy, [*(a for a in quick if not a.startswith("evaluator.path=")), f"evaluator.path={evaluator}",
                      f"data.manifest={copy}"]

    _, on_hash_only = tampered_copy("hash-only", resign_id=False)
    capsys.readouterr()
    assert evaluate("--checkpoint", str(checkpoint), *on_hash_only, f"output.dir={tmp_path / 'eval-b'}") == 2
    assert "is not the id derived from its shard list" in capsys.readouterr().err

    other, on_b = tampered_copy("resigned", resign_id=True)
    for extra, message in (([], "holds results on test set"), ([f"output.dir={tmp_path / 'eval-b'}"],
                                                               f"run {run} was evaluated on test set"),
                           (["data.allow_other_test_set=true"], "one table never mixes test sets")):
        assert evaluate("--checkpoint", str(checkpoint), *on_b, *extra) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], err
    assert not (tmp_path / "eval-b" / "results").exists() and ResultsStore(run / "eval").scored_data() == scored_a

    assert evaluate("--checkpoint", str(checkpoint), *on_b, f"output.dir={tmp_path / 'eval-b'}",
                    "data.allow_other_test_set=true") == 0
    (result,) = [json.loads(p.read_text()) for p in (tmp_path / "eval-b" / "results").rglob("*.json")]
    assert result["data"]["dataset_id"] == json.loads(other.read_text())["dataset_id"] != scored_a[0].dataset_id
    assert result["data"]["data_verified"] is True and result["checkpoint"]["dataset_id"] == scored_a[0].dataset_id


def test_ground_truth_items_are_fixed_unit_multiples(manifest):
    a = build_ground_truth(manifest, "test", max_length=64, unit_length=4, seed=3)
    b = build_ground_truth(manifest, "test", max_length=64, unit_length=4, seed=3)
    c = build_ground_truth(manifest, "test", max_length=64, unit_length=4, seed=4)
    assert len(a) == 10 and a.key == b.key != c.key
    assert np.all(a.lengths % 4 == 0) and a.lengths.max() <= 64
    assert all(f.shape[0] == n for f, n in zip(a.features, a.lengths))
    assert all(np.array_equal(x, y) for x, y in zip(a.features, b.features)) and a.captions == b.captions
    features, lengths = a.padded(np.array([0, 3]))
    assert features.shape[0] == 2 and int(lengths.max()) == features.shape[1]


def test_ground_truth_items_are_redrawn_per_replication_from_seeds(manifest):
    """protocol.redraw_items: replication r's set is drawn from (seed, r): the same items (ids, order) as the fixed
    set, other caption picks / crops; the same draw for the same seed and replication, whoever builds it."""
    pool = read_ground_truth_pool(manifest, "test", seed=0)
    fixed = pool.draw(None)
    assert fixed.key == build_ground_truth(manifest, "test", seed=0).key and fixed.replication is None
    draws = [pool.draw(r) for r in range(4)]
    assert all(d.ids == fixed.ids and d.replication == r for r, d in enumerate(draws))
    assert len({fixed.key, *(d.key for d in draws)}) == 5  # one cache entry per set
    for d in draws:  # reference crops: multiples of unit_length, at most the fixed set's (the coin only shortens)
        assert np.all(d.lengths % 4 == 0) and np.all(d.lengths >= 4) and np.all(d.lengths <= fixed.lengths)
        assert all(f.shape[0] == n for f, n in zip(d.features, d.lengths))
    def items(d):
        return d.caption_index.tolist(), d.offsets.tolist(), d.lengths.tolist()

    assert all(items(a) != items(b) for i, a in enumerate(draws) for b in draws[i + 1:])
    assert len({c for d in draws for c in d.caption_index.tolist()}) > 1  # captions do change
    assert any(not np.array_equal(d.lengths, fixed.lengths) for d in draws)  # so do lengths
    again = build_ground_truth(manifest, "test", seed=0, replication=2)  # another read, another process's view
    assert again.key == draws[2].key and items(again) == items(draws[2]) and again.captions == draws[2].captions
    assert all(np.array_equal(x, y) for x, y in zip(again.features, draws[2].features))
    assert np.array_equal(again.text_cond, draws[2].text_cond)
    other_seed = read_ground_truth_pool(manifest, "test", seed=1).draw(2)
    assert other_seed.key != draws[2].key and items(other_seed) != items(draws[2])


@pytest.fixture(scope="module")
def sub_span_manifest(tmp_path_factory) -> Path:
    """A test split whose captions have HumanML3D sub-spans (seconds at 20 fps; 121 joint frames = 120 features):
    ``two_spans`` a whole-clip caption and two caption lines with different sub-spans (frames 10-60, 60-110),
    ``shared_span`` a whole-clip caption and two caption lines sharing the sub-span 20-80, ``whole`` two whole-clip
    captions, ``long`` 210 frames (at least the reference's 200; built without the default 199-frame limit)."""
    from test_shards import ListSource, make_clip

    from mfm.text import build_text_encoder
    from preprocess.clip import Caption
    from preprocess.shards import BuildConfig, build_dataset

    clips = {
        "two_spans": make_clip("two_spans", 121, split="test", seed=1, captions=[
            Caption("walks the whole time"), Caption("starts walking", start=0.5, end=3.0),
            Caption("keeps walking", start=3.0, end=5.5)]),
        "shared_span": make_clip("shared_span", 101, split="test", seed=2, captions=[
            Caption("a walk"), Caption("walks in the middle", start=1.0, end=4.0),
            Caption("strides mid-clip", start=1.0, end=4.0)]),
        "whole": make_clip("whole", 81, split="test", seed=3, captions=[Caption("walks"), Caption("strolls")]),
        "long": make_clip("long", 211, split="test", seed=4, captions=[Caption("walks for long")]),
        "train": make_clip("train", 81, split="train", seed=5),
    }
    out = tmp_path_factory.mktemp("sub-spans") / "ds"
    build_dataset(BuildConfig(out=out, formats=("tar",), max_frames=None, progress=False), source=ListSource(clips),
                  text_encoder=build_text_encoder("minilm"))
    return out / "manifest.json"


def test_test_items_caption_makes_one_item_per_sub_span_caption_line(sub_span_manifest):
    """protocol.test_items: span (ours) pools the captions sharing a span into one item; caption (the reference,
    MDM dataset.py: 271-298) makes each sub-span caption line its own item (its own span, length and caption),
    keeps whole-clip captions pooled and drops motions of 200 frames or more. Each item's caption is the text its
    generated motion and its R-precision / MultiModality rows read."""
    span = read_ground_truth_pool(sub_span_manifest, "test", seed=0)
    caption = read_ground_truth_pool(sub_span_manifest, "test", seed=0, test_items="caption")
    assert read_ground_truth_pool(sub_span_manifest, "test", seed=0, test_items="span").draw().key == span.draw().key
    assert caption.draw().key != span.draw().key and caption.draw(1).key != span.draw(1).key

    def items(pool, replication=None):
        gt = pool.draw(replication)
        return {i: (n, c) for i, n, c in zip(gt.ids, gt.lengths.tolist(), gt.captions)}

    span_items = items(span)
    assert sorted(span_items) == ["long", "shared_span#0-100", "shared_span#20-80", "two_spans#0-120",
                                  "two_spans#10-60", "two_spans#60-110", "whole"]
    assert span_items["long"][0] == 196 and span_items["shared_span#20-80"][0] == 60  # cropped; pooled
    assert {span_items["shared_span#20-80"][1]} <= {"walks in the middle", "strides mid-clip"}
    assert span.dropped == {}

    expected = {"two_spans#0-120": (120, "walks the whole time"), "two_spans#10-60#1": (48, "starts walking"),
                "two_spans#60-110#2": (48, "keeps walking"), "shared_span#0-100": (100, "a walk"),
                "shared_span#20-80#1": (60, "walks in the middle"), "shared_span#20-80#2": (60, "strides mid-clip")}
    whole = {"walks", "strolls"}
    for replication in (None, 0, 1, 2):
        got = items(caption, replication)
        assert set(got) == {*expected, "whole"}
        assert {i: c for i, (_, c) in got.items() if i != "whole"} == {i: c for i, (_, c) in expected.items()}
        assert got["whole"][1] in whole  # whole-clip captions stay pooled, as in the reference
        for item_id, (length, _) in expected.items():  # the fixed set: the span's unit multiple; a re-draw may
            assert got[item_id][0] in (length, length - 4)  # take one unit off (the reference's coin)
        if replication is None:
            assert {i: n for i, (n, _) in got.items() if i != "whole"} == {i: n for i, (n, _) in expected.items()}
    assert caption.dropped == {"motion_200_frames_or_longer": 1}
    # the two lines sharing a span are drawn independently (their own seeds), not as one crop
    offsets = [dict(zip(d.ids, d.offsets.tolist())) for d in (caption.draw(r) for r in range(8))]
    assert any(o["shared_span#20-80#1"] != o["shared_span#20-80#2"] for o in offsets)


def test_test_items_is_a_rule_of_the_mdm_loop_recorded_and_keyed():
    """The mdm protocol makes the reference's items; our presets keep span and their keys; overriding the rule
    makes a mixed loop and another key."""
    from pipeline.evaluation.config import MDM_RULES, OUR_RULES
    from pipeline.evaluation.job import protocol_key

    fast, mdm = load_eval_config("fast").protocol, load_eval_config("mdm").protocol
    assert (fast.test_items, mdm.test_items) == ("span", "caption")
    assert MDM_RULES["test_items"] == "caption" and OUR_RULES["test_items"] == "span"
    assert "test_items" not in protocol_key(fast) and protocol_key(mdm)["test_items"] == "caption"
    assert mdm.rules()["test_items"] == "caption" and (fast.loop, mdm.loop) == ("ours", "mdm")
    spans = load_eval_config("mdm", overrides=["protocol.test_items=span"]).protocol
    assert spans.loop == "mixed" and protocol_key(spans) != protocol_key(mdm)
    captions = load_eval_config("fast", overrides=["protocol.test_items=caption"]).protocol
    assert captions.loop == "mixed" and protocol_key(captions) == {**protocol_key(fast), "test_items": "caption"}
    with pytest.raises(ConfigError, match="test_items"):
        load_eval_config("fast", overrides=["protocol.test_items=line"])


def _scored_context(checkpoint: Path, evaluator: Path, out: Path, *overrides: str):
    """An evaluation job's scorer and the context of ``checkpoint`` under the small protocol (one process)."""
    from pipeline.distributed import Dist
    from pipeline.evaluation.job import EvaluationJob
    from pipeline.evaluation.replications import PhaseTimer

    cfg = load_eval_config("fast", overrides=[*SMALL_PROTOCOL, "sampling.steps=[1]", f"evaluator.path={evaluator}",
                                              f"output.dir={out}", *overrides])
    dist = Dist(mixed_precision="no", cpu=True)
    job = EvaluationJob(cfg, dist)
    ctx = job.scorer.context(checkpoint, job.store_for(checkpoint).cache_dir, PhaseTimer(dist.device))
    return job, dist, ctx


def _items(gt) -> tuple:
    return gt.key, gt.captions, gt.lengths.tolist(), gt.offsets.tolist()


def test_each_replication_generates_edits_and_scores_its_own_draw(text_run, manifest, tmp_path, monkeypatch):
    """Default protocol: replication r generates for its own items (their captions as conditions, their lengths;
    MultiModality texts and edits too) and scores against them; the same items when the plan is built again; one
    fixed set for every replication with protocol.redraw_items=false."""
    import pipeline.evaluation.replications as replications
    from pipeline.evaluation.replications import PhaseTimer

    evaluator = random_contrastive_evaluator(manifest, tmp_path / "ev" / "contrastive.safetensors")
    checkpoint = text_run / "checkpoints" / "step-00000001"
    job, dist, ctx = _scored_context(checkpoint, evaluator, tmp_path / "a", "protocol.replications=3")
    assert ctx.plan.redraw_items and "re-drawn" in ctx.plan.intervals
    truths = [ctx.truth(r, dist) for r in range(3)]
    assert len({t.gt.key for t in truths} | {ctx.gt.key}) == 4 and all(t.gt.ids == ctx.gt.ids for t in truths)
    assert len({(t.gt.captions, tuple(t.gt.lengths)) for t in truths}) == 3  # different items per replication
    assert not any(t.from_cache for t in truths) and all(t.emb.motion.shape[0] == len(ctx.gt) for t in truths)
    # GT embeddings are those of the drawn clips and captions (FID's μ, Σ and the GT row change with the draw)
    assert not np.allclose(truths[0].emb.motion, truths[1].emb.motion)
    # The plan built again (another job, fresh cache): the same items; its embeddings equal those computed here
    _, dist2, again = _scored_context(checkpoint, evaluator, tmp_path / "b", "protocol.replications=3")
    for r, truth in enumerate(truths):
        twin = again.truth(r, dist2)
        assert _items(twin.gt) == _items(truth.gt) and np.array_equal(twin.emb.motion, truth.emb.motion)
    assert ctx.truth(1, dist).from_cache  # cached per set: the next point / checkpoint reads it
    # redraw_items=false: the fixed set in every replication, embedded once
    _, dist3, fixed = _scored_context(checkpoint, evaluator, tmp_path / "c", "protocol.redraw_items=false")
    assert not fixed.plan.redraw_items and "fixed set" in fixed.plan.intervals
    assert {fixed.truth(r, dist3).gt.key for r in range(3)} == {fixed.gt.key} and fixed.gt_emb is not None

    # What each replication generates: record the conditions and lengths handed to the sampler.
    calls: list[tuple[int, bool, np.ndarray, list[int]]] = []
    current = {"replication": -1}
    generate, replicate = replications.generate, replications.PointRun.replicate

    def recording_generate(trained, cond, extras, lengths, *args, known=None, **kwargs):
        calls.append((current["replication"], known is not None, cond.cpu().numpy(), lengths.tolist()))
        return generate(trained, cond, extras, lengths, *args, known=known, **kwargs)

    def recording_replicate(self, replication):
        current["replication"] = replication
        return replicate(self, replication)

    monkeypatch.setattr(replications, "generate", recording_generate)
    monkeypatch.setattr(replications.PointRun, "replicate", recording_replicate)
    result = job.scorer.evaluate_point(ctx, ctx.points[0], PhaseTimer(dist.device))
    assert [t["gt_key"] for t in result["ground_truth_sets"]] == [t.gt.key for t in truths]
    main_batches = -(-len(ctx.gt) // job.cfg.sampling.batch_size)
    for r, truth in enumerate(truths):
        gt = truth.gt
        mine = [c for c in calls if c[0] == r]
        pairs = {(round(float(row[0]), 6), n) for _, _, cond, lengths in mine for row, n in zip(cond, lengths)}
        drawn = {(round(float(gt.text_cond[i, 0]), 6), int(gt.lengths[i])) for i in range(len(gt))}
        assert pairs <= drawn, r  # every generation (main, MultiModality, edits) is for one of r's drawn items
        main_lengths = sorted(n for _, _, _, lengths in mine[:main_batches] for n in lengths)
        assert main_lengths == sorted(gt.lengths.tolist())
        assert any(edit for _, edit, _, _ in mine) == (r < job.cfg.tasks.editing_replications)
    assert calls and {c[0] for c in calls} == {0, 1, 2}


def _edit_rows_per_replication(job, dist, ctx, monkeypatch) -> tuple[dict, dict[int, list[int]]]:
    """Run every replication of ``ctx``'s first point; the result and, per replication, the noise seed of every
    edited row (the same item edited twice draws two seeds)."""
    from pipeline.evaluation import replications
    from pipeline.evaluation.replications import PhaseTimer

    edits: dict[int, list[int]] = {}
    current = {"replication": -1}
    generate, replicate = replications.generate, replications.PointRun.replicate

    def recording_generate(trained, cond, extras, lengths, seeds, *args, known=None, **kwargs):
        if known is not None:
            edits.setdefault(current["replication"], []).extend(seeds)
        return generate(trained, cond, extras, lengths, seeds, *args, known=known, **kwargs)

    def recording_replicate(self, replication):
        current["replication"] = replication
        return replicate(self, replication)

    monkeypatch.setattr(replications, "generate", recording_generate)
    monkeypatch.setattr(replications.PointRun, "replicate", recording_replicate)
    return job.scorer.evaluate_point(ctx, ctx.points[0], PhaseTimer(dist.device)), edits


def test_single_editing_pass_edits_once_and_per_replication_edits_every_replication(text_run, manifest, tmp_path,
                                                                                      monkeypatch):
    """tasks.editing_passes=single (MFM's Table 3 as issue 26 reads it): one pass of editing_samples edits per preset
    in the first replication, none in the others, each repetition of an item with its own noise; per_replication
    (the default) edits each replication's items in every replication it covers."""
    evaluator = random_contrastive_evaluator(manifest, tmp_path / "ev" / "contrastive.safetensors")
    checkpoint = text_run / "checkpoints" / "step-00000001"
    common = ["protocol.replications=3", "protocol.multimodality=false"]
    job, dist, ctx = _scored_context(checkpoint, evaluator, tmp_path / "single", *common,
                                     "tasks.editing_passes=single", "tasks.editing_samples=15")
    presets = len(job.cfg.tasks.editing)
    items = len(ctx.gt)
    assert (ctx.plan.editing_passes, ctx.plan.single_pass_edits, ctx.plan.editing_replications) == ("single", 15, 1)
    assert any("one pass of 15 edits" in note for note in ctx.plan.notes)
    single, edits = _edit_rows_per_replication(job, dist, ctx, monkeypatch)
    assert set(edits) == {0} and len(edits[0]) == 15 * presets  # once, in the first replication
    assert len(set(edits[0])) == 15 * presets  # every edit its own noise, repeated items included
    settings = single["editing_settings"]
    assert (settings["passes"], settings["edits_per_preset"], settings["replications"]) == ("single", 15, 1)
    for preset in job.cfg.tasks.editing:
        assert len(single["editing"][preset]["fid"]["values"]) == 1 and single["editing"][preset]["ade"]["ci"] is None

    job, dist, ctx = _scored_context(checkpoint, evaluator, tmp_path / "per", *common,
                                     "tasks.editing_replications=0")
    per, edits = _edit_rows_per_replication(job, dist, ctx, monkeypatch)
    assert set(edits) == {0, 1, 2} and all(len(rows) == items * presets for rows in edits.values())
    assert (per["editing_settings"]["passes"], per["editing_settings"]["edits_per_preset"]) == ("per_replication",
                                                                                                 items)
    assert all(len(per["editing"][p]["fid"]["values"]) == 3 for p in job.cfg.tasks.editing)


def test_editing_passes_and_precision_are_validated_and_keyed(monkeypatch):
    """The single pass and bf16 units get keys of their own; the defaults (per_replication, fp32, and auto on a CPU,
    which runs fp32) keep the keys results had before the settings existed (nothing of theirs is hashed)."""
    from types import SimpleNamespace

    from pipeline.evaluation import job

    point, ids, folder = SamplingPoint("euler", 10, 2.5), {"checkpoint": "c", "evaluator": "e", "gt": "g"}, Path("s")
    cpu = SimpleNamespace(device=torch.device("cpu"))

    def key(*overrides: str) -> str:
        return job.CheckpointScorer(load_eval_config("fast", overrides=list(overrides)), cpu).unit_for(
            folder, ids, point).key

    default = key()
    assert default == key("tasks.editing_passes=per_replication", "sampling.precision=fp32") == key(
        "sampling.precision=auto")
    assert len({default, key("tasks.editing_passes=single"), key("tasks.editing_passes=single",
                                                                  "tasks.editing_samples=20"),
                key("sampling.precision=bf16")}) == 4
    with pytest.raises(ConfigError, match="editing_replications must be 0 or 1"):
        load_eval_config("full", overrides=["tasks.editing_passes=single", "tasks.editing_replications=2"])
    with pytest.raises(ConfigError, match="editing_samples sizes the single editing pass"):
        load_eval_config("full", overrides=["tasks.editing_samples=100"])
    with pytest.raises(ConfigError, match="precision"):
        load_eval_config("full", overrides=["sampling.precision=fp16"])
    assert load_eval_config("full", overrides=["tasks.editing_passes=single"]).tasks.single_pass_edits() == 5000
    hashed = []
    monkeypatch.setattr(job, "digest", lambda value: hashed.append(value) or "k")
    key(), key("sampling.precision=auto"), key("tasks.editing_passes=single"), key("sampling.precision=bf16")
    assert not {"editing_passes", "editing_samples"} & set(hashed[0]["tasks"]) and "precision" not in hashed[0][
        "sampling"]
    assert hashed[1] == hashed[0] and hashed[2]["tasks"]["editing_passes"] == "single"
    assert hashed[3]["sampling"]["precision"] == "bf16"


def test_sampling_compile_and_noise_device_are_validated_and_keyed_only_when_they_change_the_motions(monkeypatch):
    """sampling.compile: false (default) and auto on a CPU (which does not compile) keep the keys results had before
    the setting existed; compiling (true, or auto on a CUDA device) has a key of its own."""
    from types import SimpleNamespace

    from pipeline.evaluation import job

    point, ids, folder = SamplingPoint("euler", 10, 2.5), {"checkpoint": "c", "evaluator": "e", "gt": "g"}, Path("s")
    hashed = []
    monkeypatch.setattr(job, "digest", lambda value: hashed.append(value) or str(len(hashed)))

    def key(device: str, *overrides: str) -> dict:
        dist = SimpleNamespace(device=torch.device(device))
        job.CheckpointScorer(load_eval_config("fast", overrides=list(overrides)), dist).unit_for(folder, ids, point)
        return hashed[-1]

    assert load_eval_config("fast").sampling.compile is False
    default = key("cpu")
    assert "compile" not in default["sampling"]
    assert key("cpu", "sampling.compile=false") == key("cpu", "sampling.compile=auto") == default
    assert key("cpu", "sampling.compile=true")["sampling"]["compile"] is True
    assert key("cuda", "sampling.compile=auto")["sampling"]["compile"] is True
    assert key("cuda", "sampling.compile=false") == default
    with pytest.raises(ConfigError, match="sampling.compile"):
        load_eval_config("fast", overrides=["sampling.compile=maybe"])
    # sampling.noise_device: cpu (default) and model on a CPU draw the same noise and keep the key; model on a GPU
    # draws other noise for the same seeds, so its unit has a key of its own
    assert load_eval_config("fast").sampling.noise_device == "cpu" and "noise_device" not in default["sampling"]
    assert key("cpu", "sampling.noise_device=model") == key("cuda", "sampling.noise_device=cpu") == default
    assert key("cuda", "sampling.noise_device=model")["sampling"]["noise_device"] == "cuda"
    with pytest.raises(ConfigError, match="sampling.noise_device"):
        load_eval_config("fast", overrides=["sampling.noise_device=gpu"])


def test_compiled_generation_compiles_once_per_checkpoint_and_is_recorded(text_run, manifest, tmp_path,
                                                                           compile_calls):
    evaluator = random_contrastive_evaluator(manifest, tmp_path / "ev" / "contrastive.safetensors")
    args = ["--checkpoint", str(text_run / "checkpoints" / "step-00000001"), "--protocol", "fast", *SMALL_PROTOCOL,
            "sampling.steps=[1]", "protocol.multimodality=false", f"evaluator.path={evaluator}"]
    assert evaluate(*args, f"output.dir={tmp_path / 'plain'}") == 0  # default: false
    assert compile_calls == []
    assert evaluate(*args, f"output.dir={tmp_path / 'compiled'}", "sampling.compile=true") == 0
    (compiled,) = compile_calls  # one model for every replication and editing pass
    assert compiled.mode == "default" and compiled.calls > 0
    (plain,) = (json.loads(p.read_text()) for p in (tmp_path / "plain" / "results" / "step-00000001").glob("*.json"))
    (result,) = (json.loads(p.read_text())
                 for p in (tmp_path / "compiled" / "results" / "step-00000001").glob("*.json"))
    assert (plain["sampling"]["compiled"], plain["sampling"]["compile_setting"]) == (False, False)
    assert (result["sampling"]["compiled"], result["sampling"]["compile_setting"]) == (True, True)
    assert result["key"] != plain["key"]
    assert result["metrics"]["fid"] == plain["metrics"]["fid"]  # the identity wrapper: the same motions


# ---------------------------------------------------------------------------------------------------------------
# end to end


def test_train_evaluator_reports_held_out_retrieval(trained_evaluator, manifest):
    path, report = trained_evaluator
    sidecar = json.loads(path.with_suffix(".json").read_text())
    assert sidecar["manifest_dataset_id"] == report["dataset_id"] == json.loads(manifest.read_text())["dataset_id"]
    assert report["evaluator_id"] == sidecar["evaluator_id"]
    test = report["held_out"]["test"]
    assert test["num_items"] == 10 and test["retrieval_batch_size"] == 10
    assert 0.0 <= test["retrieval_top1"] <= test["retrieval_top2"] <= test["retrieval_top3"] <= 1.0
    assert report["losses"]["contrastive"][-1] < report["losses"]["contrastive"][0]
    assert (path.parent / "action_classifier.safetensors").is_file() and "action_accuracy" in test


def test_single_editing_pass_and_bf16_are_recorded_in_results_json_and_the_table(text_run, manifest, tmp_path):
    evaluator = random_contrastive_evaluator(manifest, tmp_path / "ev" / "contrastive.safetensors")
    out = tmp_path / "eval"
    assert evaluate("--checkpoint", str(text_run / "checkpoints" / "step-00000001"), "--protocol", "fast",
                    *SMALL_PROTOCOL, "sampling.steps=[1]", "protocol.multimodality=false", f"evaluator.path={evaluator}",
                    f"output.dir={out}", "tasks.editing_passes=single", "tasks.editing_samples=5",
                    "sampling.precision=bf16", "sampling.noise_device=model") == 0
    (path,) = (out / "results" / "step-00000001").glob("*.json")
    result = json.loads(path.read_text())
    assert (result["tasks"]["editing_passes"], result["tasks"]["editing_samples"]) == ("single", 5)
    assert (result["editing_settings"]["passes"], result["editing_settings"]["edits_per_preset"]) == ("single", 5)
    assert (result["protocol"]["editing_passes"], result["protocol"]["single_pass_edits"]) == ("single", 5)
    # fewer edits than the protocol's Diversity pairs (9 on 10 test items): Diversity over the 5, noted
    assert "editing Diversity over 5 pairs (the single pass's edits), not 9" in result["protocol"]["notes"]
    assert (result["sampling"]["precision"], result["sampling"]["precision_setting"]) == ("bf16", "bf16")
    assert (result["sampling"]["noise_device"], result["sampling"]["noise_drawn_on"]) == ("model", "cpu")
    (generated, truth) = ResultsStore(out).table_rows()
    assert (generated["edit_passes"], generated["edit_edits_per_preset"], generated["precision"]) == ("single", 5,
                                                                                                     "bf16")
    assert truth["precision"] == "bf16" and np.isfinite(generated["edit_prediction_ade"])


def test_evaluate_checkpoint_with_a_steps_sweep(text_run, trained_evaluator, tmp_path, capsys):
    checkpoint = text_run / "checkpoints" / "step-00000002"
    out = tmp_path / "eval"
    args = ["--checkpoint", str(checkpoint), "--protocol", "fast", "--steps", "1,3", *SMALL_PROTOCOL,
            "output.plots=true", f"evaluator.path={trained_evaluator[0]}",
            f"output.dir={out}"]
    assert evaluate(*args) == 0
    printed = capsys.readouterr().out
    assert "2 result(s) written" in printed and "generation" in printed and "ground_truth" in printed

    results = sorted((out / "results" / "step-00000002").glob("*.json"))
    assert [p.name.rsplit(".", 2)[0] for p in results] == ["euler-1steps-g2.5", "euler-3steps-g2.5"]
    result = json.loads(results[0].read_text())
    evaluator_id = json.loads(trained_evaluator[0].with_suffix(".json").read_text())["evaluator_id"]
    assert result["evaluator"]["id"] == evaluator_id and result["evaluator"]["kind"] == "contrastive"
    assert result["data"]["dataset_id"] == result["checkpoint"]["dataset_id"] and result["checkpoint"]["step"] == 2
    assert result["protocol"]["name"] == "fast" and result["protocol"]["replications"] == 2
    assert result["protocol"]["r_precision_batch"] == 10 and result["protocol"]["notes"]
    assert (result["sampling"]["solver"], result["sampling"]["steps"], result["nfe"]) == ("euler", 1, 1)
    assert result["model_passes_per_motion"] == 2 and result["generation_seconds_per_motion"] > 0
    for name in ("fid", "r_precision_top1", "r_precision_top2", "r_precision_top3", "mm_dist", "diversity",
                 "multimodality", "mclip", "mid", "APE_root", "AVE_mean_local", "joint_variance"):
        metric = result["metrics"][name]
        assert len(metric["values"]) == 2 and np.isfinite(metric["mean"]) and metric["ci"] >= 0, name
    assert result["metrics"]["fid"]["mean"] > 0
    truth = result["ground_truth"]
    assert truth["r_precision_top3"]["mean"] >= truth["r_precision_top1"]["mean"] and "multimodality" not in truth
    for preset in ("prediction", "upper_body"):
        edited = result["editing"][preset]
        assert {"fid", "diversity", "ade", "fde"} <= set(edited) and edited["ade"]["ci"] is None  # 1 replication
    # Edits at the MFM paper's settings whatever the sampling point (1 or 3 steps, guidance 2.5)
    edits = result["editing_settings"]
    assert (edits["method"], edits["settings"], edits["solver"], edits["steps"], edits["guidance"]) == \
        ("trajectory rewriting (MFM)", "paper", "euler", 30, 1.0)
    assert edits["rewrite_until"] == {"prediction": 0.2, "upper_body": 0.2} and edits["overridden"] == []
    # Plausibility medians beside the ground truth's; contact_foot_speed may be undefined (feet off the floor).
    for section in (result["metrics"], result["ground_truth"], *result["editing"].values()):
        assert PLAUSIBILITY - {"contact_foot_speed"} <= set(section)
        assert all(np.isfinite(v["mean"]) for k, v in section.items() if k in PLAUSIBILITY)
    truth = result["ground_truth"]
    assert truth["jerk_ratio"]["mean"] == pytest.approx(1.0)  # each GT clip against itself
    assert truth["bone_length_range"]["mean"] < 1e-3 < result["metrics"]["bone_length_range"]["mean"]  # rigid GT
    assert result["plausibility"]["foot_contact_height_m"] == 0.05
    assert "ground-truth clip" in result["plausibility"]["jerk_ratio_reference"]
    assert {"generation", "features", "editing", "metrics"} <= set(result["timing_s"])

    rows = ResultsStore(out).table_rows()
    assert [(r["steps"], r["row_kind"]) for r in rows] == [(1, "generated"), (1, "ground_truth"),
                                                          (3, "generated"), (3, "ground_truth")]
    for row in rows:
        assert row["evaluator_id"] == evaluator_id and row["protocol"] == "fast" and row["solver"] == "euler"
        assert row["dataset_id"] == result["data"]["dataset_id"] and "fid_ci" in row and "r_precision_top3" in row
    assert "edit_upper_body_ade" in rows[0] and pq.read_table(out / "results.parquet").num_rows == 4
    assert (rows[0]["edit_settings"], rows[0]["edit_steps"], rows[0]["edit_guidance"]) == ("paper", 30, 1.0)
    assert rows[0]["edit_upper_body_steps"] == rows[0]["edit_prediction_steps"] == 30
    assert rows[0]["sampling_point"] == "sweep" and result["sampling"]["sampling_point"] == "sweep"
    assert {"foot_skating_ratio", "jerk_ratio", "edit_prediction_jerk_ratio"} <= set(rows[0])
    assert "foot_skating_ratio" in rows[1]
    assert (out / "plots" / "fid_vs_nfe_step-00000002.png").stat().st_size > 0
    assert (out / "plots" / "metrics_vs_step.png").is_file()

    before = {p: p.stat().st_mtime_ns for p in results}
    assert evaluate(*args) == 0  # everything is done: nothing re-evaluated, no new rows
    assert "0 result(s) written" in capsys.readouterr().out
    assert {p: p.stat().st_mtime_ns for p in results} == before and len(ResultsStore(out).table_rows()) == 4


def test_results_say_whether_intervals_include_item_redraws(text_run, manifest, tmp_path):
    """results.json: the protocol section records redraw_items and what the intervals include; the data section
    the set of each replication; the ground-truth row has intervals over the draws. redraw_items=false: the fixed
    set in every replication (and a GT row whose item-only metrics do not vary), under another key."""
    evaluator = random_contrastive_evaluator(manifest, tmp_path / "ev" / "contrastive.safetensors")
    args = ["--checkpoint", str(text_run / "checkpoints" / "step-00000002"), "--protocol", "fast", *SMALL_PROTOCOL,
            "sampling.steps=[1]", "protocol.replications=3", "tasks.editing=[]", f"evaluator.path={evaluator}"]
    results = {}
    for redraw in (True, False):
        out = tmp_path / f"eval-{redraw}"
        assert evaluate(*args, f"protocol.redraw_items={str(redraw).lower()}", f"output.dir={out}") == 0
        (path,) = (out / "results").rglob("*.json")
        results[redraw] = json.loads(path.read_text())
        rows = ResultsStore(out).table_rows()
        assert [r["redraw_items"] for r in rows] == [redraw, redraw] and "mclip_ci" in rows[1]
    redrawn, fixed = results[True], results[False]
    assert redrawn["key"] != fixed["key"]
    assert redrawn["protocol"]["redraw_items"] is True and redrawn["protocol"]["config"]["redraw_items"] is True
    assert "ground-truth items re-drawn per replication" in redrawn["protocol"]["intervals"]
    assert fixed["protocol"]["redraw_items"] is False and "fixed set" in fixed["protocol"]["intervals"]
    assert redrawn["data"]["redraw_items"] is True and fixed["data"]["redraw_items"] is False
    sets = redrawn["data"]["ground_truth_sets"]
    assert [s["replication"] for s in sets] == [0, 1, 2] and len({s["gt_key"] for s in sets}) == 3
    assert redrawn["data"]["gt_key"] not in {s["gt_key"] for s in sets}  # the fixed set is not scored
    assert {s["gt_key"] for s in fixed["data"]["ground_truth_sets"]} == {fixed["data"]["gt_key"]}
    assert redrawn["data"]["num_items"] == fixed["data"]["num_items"] == 10  # the whole test set each time
    assert "ground_truth" in redrawn["timing_s"]  # the per-replication sets' cost, in the unit's own time
    # The GT row: means with intervals over replications; metrics of the items alone vary only when re-drawn
    for name in ("mclip", "mean_jerk", "fid", "r_precision_top1"):
        assert len(redrawn["ground_truth"][name]["values"]) == 3 and redrawn["ground_truth"][name]["ci"] is not None
    for name in ("mclip", "mean_jerk"):
        assert redrawn["ground_truth"][name]["ci"] > 0, name
        assert len(set(fixed["ground_truth"][name]["values"])) == 1 and fixed["ground_truth"][name]["ci"] == 0
    assert redrawn["metrics"]["fid"]["ci"] > 0 and redrawn["ground_truth"]["jerk_ratio"]["mean"] == pytest.approx(1.0)


def test_watchers_evaluate_each_complete_checkpoint_once(text_run, manifest, tmp_path):
    evaluator = random_contrastive_evaluator(manifest, tmp_path / "ev" / "contrastive.safetensors")
    run = tmp_path / "run"
    shutil.copytree(text_run, run)
    (run / "checkpoints" / "step-00000009").mkdir()  # a save still in progress: no COMPLETE marker
    out = tmp_path / "eval"
    cmd = [sys.executable, str(EVALUATE), "--watch", str(run), "--once", "--protocol", "fast",
           *SMALL_PROTOCOL, "sampling.steps=[2]", "protocol.replications=1", "tasks.editing=[]", "protocol.multimodality=false",
           f"evaluator.path={evaluator}", f"output.dir={out}"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "WANDB_MODE": "disabled"}
    procs = [subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    outputs = [p.communicate(timeout=240) for p in procs]
    for proc, (stdout, stderr) in zip(procs, outputs):
        # 3: this job skipped a unit the other was still evaluating when it finished (said so in its summary)
        assert proc.returncode in (0, 3), stderr[-3000:]
        assert ("status: all_done (exit 0)" if proc.returncode == 0 else "held by another job") in stdout
    counts = [int(stdout.split(" unit(s) evaluated")[0].split()[-1]) for stdout, _ in outputs]
    assert sum(counts) == 2, counts  # two complete checkpoints, one setting: two units between both jobs

    results = sorted(p.relative_to(out / "results").as_posix() for p in (out / "results").rglob("*.json"))
    assert [r.split("/")[0] for r in results] == ["step-00000001", "step-00000002"]
    rows = ResultsStore(out).table_rows()
    assert sorted((r["checkpoint_name"], r["row_kind"]) for r in rows) == [
        ("step-00000001", "generated"), ("step-00000001", "ground_truth"),
        ("step-00000002", "generated"), ("step-00000002", "ground_truth")]
    assert not list((out / "claims").glob("*.claim"))  # every claim released
    assert len(list((out / "cache").glob("gt-*.npz"))) == 1  # ground truth embedded once, then cached


def test_official_evaluator_without_its_files_says_what_is_missing(text_run, tmp_path, capsys):
    code = evaluate("--checkpoint", str(text_run / "checkpoints" / "step-00000001"), "--protocol", "fast",
                    "evaluator.kind=t2m", f"evaluator.t2m_checkpoint_dir={tmp_path / 'checkpoints'}",
                    f"evaluator.t2m_glove_dir={tmp_path / 'glove'}", f"output.dir={tmp_path / 'eval'}")
    message = capsys.readouterr().err
    assert code == 2
    for name in ("t2m/text_mot_match/model/finest.tar", "our_vab_data.npy", "our_vab_words.pkl", "our_vab_idx.pkl",
                 "t2m_mean.npy", "evaluator.t2m_checkpoint_dir"):
        assert name in message, name
    assert not (tmp_path / "eval" / "results").exists()


def test_missing_own_evaluator_says_how_to_train_one(text_run, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # evaluator.path=auto looks under ./runs/evaluators/
    code = evaluate("--checkpoint", str(text_run / "checkpoints" / "step-00000001"), "--protocol", "fast",
                    f"output.dir={tmp_path / 'eval'}")
    assert code == 2 and "launch/train_evaluator.py" in capsys.readouterr().err


def test_action_model_is_scored_with_the_classifier(manifest, trained_evaluator, tmp_path):
    run = train_tiny_model(manifest, tmp_path / "action-run", "model.num_actions=1", steps=1)
    classifier = trained_evaluator[0].parent / "action_classifier.safetensors"
    out = tmp_path / "eval"
    assert evaluate("--checkpoint", str(run / "checkpoints" / "step-00000001"), "--protocol", "fast",
                    *SMALL_PROTOCOL, "sampling.steps=[2]", "protocol.mm_num_texts=100", f"evaluator.action_classifier={classifier}",
                    f"output.dir={out}") == 0
    result = json.loads(next((out / "results").rglob("*.json")).read_text())
    assert result["checkpoint"]["model"] == "action-to-motion" and result["evaluator"]["kind"] == "action_classifier"
    assert {"fid", "accuracy", "diversity", "multimodality"} <= set(result["metrics"])
    assert 0.0 <= result["metrics"]["accuracy"]["mean"] <= 1.0 and "accuracy" in result["ground_truth"]
    classes = {a for a in build_ground_truth(manifest, "test").actions}
    assert result["protocol"]["mm_num_texts"] == len(classes)  # one MultiModality "text" per test class


def test_an_evaluation_folder_is_ours_by_its_marker_or_refused_untouched(tmp_path):
    """Issue 24, finding 4: the evaluator's output folder overwrote a foreign index.html and plots/. A folder is an
    evaluation folder of ours by its marker (written first into a new or empty one) or, written before the marker,
    by holding only the evaluator's own names with its table or listing; any other is refused before any write."""
    from pipeline.evaluation.store import EVAL_MARKER, EvalFolderError, check_eval_folder

    theirs = tmp_path / "theirs"
    (theirs / "plots").mkdir(parents=True)
    (theirs / "plots" / "metrics_vs_step.png").write_bytes(b"their plot")
    (theirs / "index.html").write_text("<html>their report</html>")
    before = {p: p.read_bytes() for p in theirs.rglob("*") if p.is_file()}
    with pytest.raises(EvalFolderError, match=f"evaluation folder {theirs} is a non-empty folder that is not an "
                                              "evaluation folder of ours"):
        ResultsStore(theirs).open_folder(write_marker=True)
    assert {p: p.read_bytes() for p in theirs.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in theirs.iterdir()) == ["index.html", "plots"]

    new = tmp_path / "new" / "eval"
    ResultsStore(new).open_folder(write_marker=True)
    assert (new / EVAL_MARKER).is_file()
    (new / "index.html").write_text("anything")  # ours by the marker from here on
    check_eval_folder(new)
    earlier = tmp_path / "earlier" / "eval"  # an earlier version's folder: the evaluator's names only
    (earlier / "claims").mkdir(parents=True)
    (earlier / "results.jsonl").write_text("")
    (earlier / ".table.lock").write_text("")
    ResultsStore(earlier).open_folder(write_marker=True)
    assert (earlier / EVAL_MARKER).is_file()
    a_file = tmp_path / "a-file"
    a_file.write_text("")
    with pytest.raises(EvalFolderError, match="is a file"):
        check_eval_folder(a_file)


def test_evaluating_into_another_tools_folder_is_refused_in_one_line(text_run, tmp_path, capsys):
    theirs = tmp_path / "report"
    (theirs / "plots").mkdir(parents=True)
    (theirs / "plots" / "fid_vs_nfe_all.png").write_bytes(b"their plot")
    (theirs / "index.html").write_text("<html>their report</html>")
    before = {p: p.read_bytes() for p in theirs.rglob("*") if p.is_file()}
    checkpoint = text_run / "checkpoints" / "step-00000002"
    assert evaluate("--checkpoint", str(checkpoint), "--protocol", "fast", f"output.dir={theirs}") == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error: ")]
    assert len(err) == 1 and f"evaluation folder {theirs} is a non-empty folder" in err[0]
    assert {p: p.read_bytes() for p in theirs.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in theirs.rglob("*")) == ["fid_vs_nfe_all.png", "index.html", "plots"]


def test_an_incomplete_checkpoint_is_refused(tmp_path, capsys):
    unfinished = tmp_path / "run" / "checkpoints" / "step-00000005"
    unfinished.mkdir(parents=True)  # a save in progress: no COMPLETE marker
    assert evaluate("--checkpoint", str(unfinished), f"output.dir={tmp_path / 'eval'}") == 2
    assert "no complete checkpoint" in capsys.readouterr().err


def test_diffusion_baseline_is_scored_with_its_reverse_sampler(manifest, text_run, tmp_path, capsys):
    run = train_tiny_model(manifest, tmp_path / "diffusion-run", "train.objective=diffusion",
                           "train.diffusion=flame", steps=1)
    evaluator = random_contrastive_evaluator(manifest, tmp_path / "ev" / "contrastive.safetensors")
    checkpoint = str(run / "checkpoints" / "step-00000001")
    common = [*SMALL_PROTOCOL, "protocol.replications=1", f"evaluator.path={evaluator}",
              f"output.dir={tmp_path / 'e'}"]
    assert evaluate("--checkpoint", checkpoint, "--protocol", "fast", *common) == 2  # euler: not for diffusion
    assert "diffusion model" in capsys.readouterr().err
    # One sweep over a flow and a diffusion checkpoint (MFM's FID vs NFE): each runs its own objective's points.
    # Overrides on both sides of the options (argparse's intermixed parse; a plain parse_args refuses this).
    flow_checkpoint = str(text_run / "checkpoints" / "step-00000001")
    # sampling.baseline_steps=false: the sweep varies FLAME's step count (by default it runs all 1,000)
    assert evaluate("--checkpoint", flow_checkpoint, "--checkpoint", checkpoint, *common[:2], "--protocol", "fast",
                    "--solver", "euler,ddim", "--steps", "4", "--steps", "ddim=2,3", *common[2:],
                    "sampling.baseline_steps=false", "output.plots=true") == 0
    results = [json.loads(path.read_text()) for path in (tmp_path / "e" / "results").rglob("*.json")]
    runs = sorted((r["checkpoint"]["objective"], r["sampling"]["solver"], r["nfe"]) for r in results)
    assert runs == [("diffusion", "ddim", 2), ("diffusion", "ddim", 3), ("flow", "euler", 4)]
    for result in results:
        if result["checkpoint"]["objective"] == "diffusion":
            assert result["checkpoint"]["diffusion_preset"] == "flame"
        assert np.isfinite(result["metrics"]["fid"]["mean"]) and set(result["editing"]) == {"prediction", "upper_body"}
        if result["checkpoint"]["objective"] == "diffusion":  # FLAME's replacement on the point's sampler; its
            # root translation copied into the output as FLAME's edit_motion.py, the rest of the kept part not
            assert result["editing_settings"] == {"method": "replacement (FLAME)", "sampler": "ddim",
                                                  "steps": result["sampling"]["steps"], "guidance": 8.0,
                                                  "restore_known": False, "reference_translation": True,
                                                  "passes": "per_replication", "replications": 1,
                                                  "edits_per_preset": result["protocol"]["num_samples"],
                                                  "statistic": "per replication, then mean ± 95 % CI over "
                                                               "replications"}
            # sampled as FLAME's authors did: guidance 8.0 (not the sweep's 2.5), output smoothed with σ = 1
            assert (result["sampling"]["guidance"], result["sampling"]["smoothing_sigma"]) == (8.0, 1.0)
            own = result["sampling"]["baseline_defaults"]  # FLAME's settings as run (the sweep varied the steps)
            assert (own["preset"], own["every_training_step"], own["clip_denoised"], own["ema_weights"]) == (
                "flame", False, True, True)
            assert result["checkpoint"]["weights"] == "ema"
        else:
            assert (result["sampling"]["guidance"], result["sampling"]["smoothing_sigma"]) == (2.5, 0.0)
    assert (tmp_path / "e" / "plots" / "fid_vs_nfe_all.png").is_file()  # both runs in one plot

    # Both methods leave the kept part as their sampler made it (FLAME's rule for its joints); copying it back is an
    # option. (generate's reference_translation, FLAME's root copy, is off here: this compares the kept part alone.)
    from pipeline.evaluation.config import SamplingConfig, SamplingPoint
    from pipeline.evaluation.replications import generate
    from pipeline.generation.inference import load_trained_model

    lengths = torch.tensor([12, 9])
    known = torch.randn(2, 12, 263) * valid_frame_mask(lengths, 12).unsqueeze(-1)
    keep = torch.zeros(2, 12, 263, dtype=torch.bool)
    keep[:, :4] = True
    for path, point in ((flow_checkpoint, SamplingPoint("euler", 4, 2.5)), (checkpoint, SamplingPoint("ddim", 2, 2.5))):
        trained = load_trained_model(path)
        cond = torch.zeros(2, trained.model_config.cond_dim)
        for restore in (False, True):
            raw, _ = generate(trained, cond, {}, lengths, [1, 2], point, SamplingConfig(baseline_defaults=False),
                              known=known, keep=keep, restore_known=restore)  # no FLAME smoothing over the copy
            gap = (trained.normalize(raw) - known)[keep].abs().max()
            if restore and trained.objective == "diffusion":
                assert gap < 1e-5  # copied back
            else:
                assert gap > 1e-3, (path, restore)  # what the sampler made of it


def test_cross_attention_model_gets_the_captions_token_features(tmp_path_factory, tmp_path):
    from preprocess.shards import BuildConfig, build_dataset

    data = tmp_path_factory.getbasetemp() / "eval-synthetic-tokens"
    build_dataset(BuildConfig(out=data, source="synthetic", source_options={"num_clips": 40}, formats=("tar",),
                              progress=False, token_features=True, max_tokens=12))
    run = train_tiny_model(data / "manifest.json", tmp_path / "run", "model.conditioning=cross_attention", steps=1)
    evaluator = random_contrastive_evaluator(data / "manifest.json", tmp_path / "ev" / "contrastive.safetensors")
    assert evaluate("--checkpoint", str(run / "checkpoints" / "step-00000001"), "--protocol", "fast",
                    *SMALL_PROTOCOL, "sampling.steps=[1]", "protocol.replications=1", "protocol.multimodality=false",
                    "tasks.editing=[]", f"evaluator.path={evaluator}", f"output.dir={tmp_path / 'e'}") == 0
    result = json.loads(next((tmp_path / "e" / "results").rglob("*.json")).read_text())
    assert result["checkpoint"]["conditioning"] == "cross_attention"
    assert np.isfinite(result["metrics"]["fid"]["mean"])
    assert any("windows of" in note for note in result["notes"])  # test clips longer than the training window


@pytest.mark.slow
def test_embedded_default_end_to_end_with_the_fast_protocol(tmp_path_factory, tmp_path, capsys):
    """The real DeepMimic clips (the embedded default dataset): build, train a tiny model, train the evaluator,
    evaluate with the fast protocol through the entry point."""
    from launch.train_evaluator import main as train_evaluator
    data = embedded_dataset_once(tmp_path_factory)
    manifest = data / "manifest.json"
    run = train_tiny_model(manifest, tmp_path / "run", "data.window=96", "data.batch_size=5", steps=3)
    tiny = [f"model.{k}={v}" for k, v in TINY_EVALUATOR.items()]
    assert train_evaluator([f"data.manifest={manifest}", f"out_dir={tmp_path / 'evaluator'}", "optim.steps=6",
                            "optim.log_every=3", "optim.warmup_steps=0", "data.window=96", *tiny]) == 0
    report = json.loads((tmp_path / "evaluator" / "report.json").read_text())
    assert report["held_out"]["test"]["num_items"] == 11 and "action_accuracy" in report["held_out"]["test"]

    out = tmp_path / "eval"
    assert evaluate("--checkpoint", str(run), "--protocol", "fast", *SMALL_PROTOCOL,
                    f"evaluator.path={tmp_path / 'evaluator' / 'contrastive.safetensors'}", f"output.dir={out}") == 0
    assert "1 result(s) written" in capsys.readouterr().out
    (path,) = (out / "results" / "step-00000003").glob("*.json")
    result = json.loads(path.read_text())
    assert result["checkpoint"]["step"] == 3 and result["protocol"]["name"] == "fast"
    assert result["data"]["dataset_id"] == json.loads(manifest.read_text())["dataset_id"]
    for name in ("fid", "r_precision_top3", "mm_dist", "diversity", "mclip"):
        assert np.isfinite(result["metrics"][name]["mean"]), name
        assert np.isfinite(result["ground_truth"].get(name, {"mean": 0.0})["mean"]), name


# ---------------------------------------------------------------------------------------------------------------
# a killed, a live and a pruned-away job (issue 12, item 6)


def _quick_eval_args(evaluator: Path, out: Path) -> list[str]:
    return ["--protocol", "fast", *SMALL_PROTOCOL, "sampling.steps=[2]", "protocol.replications=1",
            "tasks.editing=[]", "protocol.multimodality=false", f"evaluator.path={evaluator}", f"output.dir={out}"]


def _units_of(checkpoint: Path, args: list[str]) -> list[Unit]:
    """The units an evaluation job with these arguments works on for ``checkpoint`` (their keys need the context:
    model, evaluator, ground truth; the ground-truth embeddings it caches are reused by the job under test)."""
    from pipeline.distributed import Dist
    from pipeline.evaluation.job import EvaluationJob
    from pipeline.evaluation.replications import PhaseTimer

    cfg = load_eval_config("fast", overrides=[a for a in args if not a.startswith("--") and a != "fast"])
    with Dist(mixed_precision="no", cpu=True) as dist:
        job = EvaluationJob(cfg, dist)
        store = job.store_for(checkpoint)
        ctx = job.scorer.context(checkpoint, store.cache_dir, PhaseTimer(dist.device))
        return [work.unit for work in job.scorer.work(checkpoint, ctx, None)]


def test_a_killed_evaluators_claim_is_taken_over_at_once_and_its_unit_evaluated(text_run, manifest, tmp_path,
                                                                                 caplog, capsys):
    evaluator = random_contrastive_evaluator(manifest, tmp_path / "ev" / "contrastive.safetensors")
    checkpoint, out = text_run / "checkpoints" / "step-00000001", tmp_path / "eval"
    args = _quick_eval_args(evaluator, out)
    units = _units_of(checkpoint, args)
    _claiming_job(out, units, "die")  # claimed, then kill -9: its claim files stay, fresh, with a dead pid
    assert all(ResultsStore(out).claim_path(u).is_file() for u in units)
    with caplog.at_level("WARNING", logger="pipeline.evaluation.store"):
        assert evaluate("--checkpoint", str(checkpoint), *args) == 0
    assert "taking over claim" in caplog.text and "is no longer running" in caplog.text
    printed = capsys.readouterr().out
    assert f"{len(units)} result(s) written" in printed and "status: all_done (exit 0)" in printed
    assert all(ResultsStore(out).is_done(u) for u in units) and not list((out / "claims").glob("*.claim"))


def test_units_held_by_a_live_job_are_reported_with_a_distinct_exit_status(text_run, manifest, tmp_path, capsys):
    from pipeline.evaluation.job import EXIT_HELD_BY_OTHERS

    evaluator = random_contrastive_evaluator(manifest, tmp_path / "ev" / "contrastive.safetensors")
    checkpoint, out = text_run / "checkpoints" / "step-00000002", tmp_path / "eval"
    args = _quick_eval_args(evaluator, out)
    units = _units_of(checkpoint, args)
    holder = _claiming_job(out, units, "live")  # another job, alive, evaluating this checkpoint right now
    try:
        code = evaluate("--checkpoint", str(checkpoint), *args)
    finally:
        holder.kill()
        holder.wait(timeout=30)
    printed = capsys.readouterr().out
    assert code == EXIT_HELD_BY_OTHERS == 3 and "0 result(s) written" in printed
    (line,) = [line for line in printed.splitlines() if line.startswith("held by another job")]
    assert f"step-00000002 {units[0].point_name}" in line and f"pid {holder.pid} on {socket.gethostname()}" in line
    assert "status: held_by_other_jobs (exit 3)" in printed
    assert not any(ResultsStore(out).is_done(u) for u in units)


def test_a_checkpoint_pruned_before_evaluation_is_reported(text_run, manifest, tmp_path, caplog, capsys):
    evaluator = random_contrastive_evaluator(manifest, tmp_path / "ev" / "contrastive.safetensors")
    run, out = tmp_path / "run", tmp_path / "eval"
    shutil.copytree(text_run, run)
    args = _quick_eval_args(evaluator, out)
    first = run / "checkpoints" / "step-00000001"
    holder = _claiming_job(out, _units_of(first, args), "live")  # another job is on step 1 ...
    try:
        assert evaluate("--watch", str(run), "--once", *args) == 3  # ... so this one evaluates step 2 only
    finally:
        holder.kill()  # ... and that job dies before finishing step 1,
        holder.wait(timeout=30)
    shutil.rmtree(first)  # which training deletes meanwhile (train.keep_last)
    capsys.readouterr()
    with caplog.at_level("WARNING", logger="pipeline.evaluation.job"):
        assert evaluate("--watch", str(run), "--once", *args) == 0  # nothing left to evaluate: all done, but ...
    printed = capsys.readouterr().out
    assert "0 unit(s) evaluated" in printed and "pruned_before_evaluation: [1]" in printed  # ... not silently
    assert "step-00000001 (step 1) is gone and was never evaluated" in caplog.text
    assert "train.keep_last=0" in caplog.text
    assert [r["checkpoint_name"] for r in ResultsStore(out).table_rows()] == ["step-00000002", "step-00000002"]


def test_a_checkpoint_saved_and_pruned_between_two_jobs_is_reported(text_run, manifest, tmp_path, caplog, capsys):
    """No evaluator job ever listed step 1: training saved and pruned it between two ``--watch --once`` jobs. Its
    line in checkpoints/saved.jsonl (no folder, no result) makes it ``pruned_before_evaluation``; a checkpoint
    training set aside (kept, renamed) is not reported, nor one that has a result."""
    from pipeline import checkpoint as ckpt
    from pipeline.evaluation.job import checkpoint_id

    evaluator = random_contrastive_evaluator(manifest, tmp_path / "ev" / "contrastive.safetensors")
    run, out = tmp_path / "run", tmp_path / "eval"
    shutil.copytree(text_run, run)
    root = run / "checkpoints"
    assert [(c.step, c.name) for c in ckpt.read_saved(root)] == [(1, "step-00000001"), (2, "step-00000002")]
    first_id = checkpoint_id(root / "step-00000001")
    shutil.rmtree(root / "step-00000001")  # pruned by train.keep_last before any evaluator job ran
    ckpt.move_aside(root / "step-00000002", "discarded")  # train.resume_discard_newer: kept under another name
    args = _quick_eval_args(evaluator, out)
    with caplog.at_level("WARNING", logger="pipeline.evaluation.job"):
        assert evaluate("--watch", str(run), "--once", *args) == 0
    printed = capsys.readouterr().out
    assert "0 unit(s) evaluated" in printed and "pruned_before_evaluation: [1]" in printed
    assert "step-00000001 (step 1) is gone and was never evaluated" in caplog.text
    assert not (out / "checkpoints_seen.jsonl").exists()  # known from training's listing alone

    result = out / "results" / "step-00000001" / "euler-2steps-g2.5.x.json"  # evaluated after all (another job)
    result.parent.mkdir(parents=True)
    result.write_text(json.dumps({"checkpoint": {"id": first_id}}))
    assert evaluate("--watch", str(run), "--once", *args) == 0
    assert "pruned_before_evaluation" not in capsys.readouterr().out


def test_a_folder_holding_only_the_marker_our_main_rank_is_writing_is_ours(tmp_path):
    """Every rank checks the folder while the main rank writes the marker: its temporary file must not make the other
    ranks refuse (they did, and the main rank then waited for them forever)."""
    from pipeline.evaluation.store import EVAL_MARKER, EvalFolderError, check_eval_folder

    (tmp_path / f".{EVAL_MARKER}.tmp-4242").write_text("{")
    check_eval_folder(tmp_path)
    (tmp_path / ".notes.txt.tmp-1").write_text("someone else's")
    with pytest.raises(EvalFolderError):
        check_eval_folder(tmp_path)
