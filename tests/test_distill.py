"""launch/distill.py (reflow) on CPU: a tiny teacher trained once per session on test_trainer.py's synthetic dataset,
its pair set (the teacher's own samples, made once and reused), the recorded-noise loss, the student sampled in 1 and
2 function evaluations by launch/sample.py and MotionPipeline, the test that the method does something (the student's
one Euler step lands nearer the teacher's 10-step endpoint than the teacher's own one step), and exact resume."""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import sys
from concurrent.futures import Future
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from conftest import REPO_ROOT, load_launch_script, selected_tests, start_two_at_a_time
from eval_worker import SMALL_PROTOCOL, random_contrastive_evaluator
from test_trainer import (
    assert_runs_identical,
    base_overrides,
    build_dataset_once,
    clean_env,
    kill_and_resume,
    output_of,
    train_entry,
)

import pipeline.generation.pairs as pairs_module
from mfm.solvers import (
    FLOW_MAP_PERTURBATION,
    draw_noise,
    guided_velocity,
    seeded_generators,
    solve,
    zero_padded_frames,
)
from pipeline import checkpoint as ckpt
from pipeline.cli.distill import student_config
from pipeline.config import ConfigError, DistillConfig, TrainConfig, load_config
from pipeline.data.stream import iter_motions, open_manifest
from pipeline.distributed import Dist
from pipeline.generation.inference import load_trained_model
from pipeline.generation.integration import sample_seed
from pipeline.generation.pairs import (
    FLOW_MAP_KEY,
    PairSetError,
    PlannedPair,
    RecordWindow,
    make_pairs,
    probe_indices,
    report_flow_map,
)
from pipeline.generation.pretrained import CARD_FILE, MotionPipeline, export_pretrained
from pipeline.training.run_folder import RUN_MARKER
from pipeline.training.trainer import Trainer
from preprocess.processing import single_threaded_torch

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("single_thread")]

distill_entry = load_launch_script("distill")
sample_entry = load_launch_script("sample")

# The teacher has to have learnt something for its ODE paths to curve (150 steps of the tiny preset); the student
# gets as many at a higher rate, without dropout.
TEACHER_STEPS, STUDENT_STEPS = 150, 150
STUDENT_OVERRIDES = (f"train.max_steps={STUDENT_STEPS}", f"train.save_every={STUDENT_STEPS}",
                     f"train.log_every={STUDENT_STEPS}", "optim.lr=2e-3", "model.dropout=0")


@pytest.fixture(scope="session")
def teacher_run(tmp_path_factory) -> Path:
    run = tmp_path_factory.getbasetemp() / "distill-teacher"
    if not (run / "checkpoints").is_dir():
        with single_threaded_torch():
            code = train_entry.main(["--config", "tiny", f"data.manifest={build_dataset_once(tmp_path_factory)}",
                                     f"train.out_dir={run}", f"train.max_steps={TEACHER_STEPS}",
                                     f"train.save_every={TEACHER_STEPS}", f"train.log_every={TEACHER_STEPS}"])
        assert code == 0
    return run


@pytest.fixture(scope="session")
def student_run(tmp_path_factory, teacher_run) -> Path:
    run = tmp_path_factory.getbasetemp() / "distill-student"
    if not (run / "checkpoints").is_dir():
        with single_threaded_torch():
            assert distill_entry.main(["--teacher", str(teacher_run), "--out", str(run), *STUDENT_OVERRIDES]) == 0
    return run


def pair_records(run: Path):
    return list(iter_motions(open_manifest(run / "pairs" / "manifest.json"), "train"))


@torch.no_grad()
def solve_from_recorded_noise(trained, record, guidance: float, steps: int, grid=None) -> torch.Tensor:
    """(L, D) normalised: ``trained``'s Euler solution from the record's own noise, for its caption and length
    (on ``grid`` when given, else uniform)."""
    length = record.features.shape[0]
    lengths = torch.tensor([length])
    x0 = draw_noise((1, length, trained.model_config.feature_dim), seeded_generators([record.noise_seed]),
                    lengths=lengths)
    velocity = guided_velocity(trained.model, torch.from_numpy(record.text_emb[:1]), scale=guidance, lengths=lengths)
    return solve(zero_padded_frames(velocity, lengths), x0, solver="euler", steps=steps, grid=grid).x1[0]


def refuse_solving(*args, **kwargs):
    raise AssertionError("a complete pair set of the same teacher and settings was made again")


def test_pair_set_is_the_teachers_samples_made_once(student_run, teacher_run, tmp_path):
    """Pair i is launch/sample.py's sample i of its caption and length with --seed distill.seed (the teacher's
    default sampler, no smoothing); the manifest names the teacher; making the set again elsewhere gives the same
    bytes, also after an interruption left shards without a manifest; running in the same folder reuses a complete
    set, or refuses one made with other settings."""
    manifest = json.loads((student_run / "pairs" / "manifest.json").read_text())
    teacher_folder = ckpt.resolve_checkpoint(teacher_run)
    assert manifest["pairs"]["teacher_checkpoint_id"] == ckpt.checkpoint_id(ckpt.read_marker(teacher_folder))
    assert (manifest["pairs"]["teacher_step"], manifest["pairs"]["steps"], manifest["pairs"]["solver"]) == \
        (TEACHER_STEPS, 10, "euler")
    records = pair_records(student_run)
    assert [r.noise_seed for r in records] == [sample_seed(0, i) for i in range(len(records))]

    first = records[0]
    out = tmp_path / "sampled"
    assert sample_entry.main(["--checkpoint", str(teacher_run), "--out", str(out), "--text", first.captions[0],
                              "--length", str(first.features.shape[0]), "--seed", "0", "--no-video", "--no-bvh"]) == 0
    sampled = np.load(out / "sample_000" / "features.npy")
    np.testing.assert_allclose(sampled, first.features, rtol=0, atol=1e-4)

    teacher = load_trained_model(teacher_run)
    settings = load_config(TrainConfig, student_run / "config.yaml").distill
    with Dist() as dist:
        again = make_pairs(teacher, settings, tmp_path / "again", dist)
        assert json.loads(again.read_text())["dataset_id"] == manifest["dataset_id"]
        again.unlink()  # an interrupted making: shards, no manifest; made again from scratch, leftovers gone
        leftover = again.parent / "train" / "shard-00099.tar"
        leftover.write_bytes(b"partial")
        assert json.loads(make_pairs(teacher, settings, tmp_path / "again", dist).read_text())["dataset_id"] == \
            manifest["dataset_id"]
        assert not leftover.exists()

        original = pairs_module.solve_pairs
        pairs_module.solve_pairs = refuse_solving
        try:
            make_pairs(teacher, settings, student_run, dist)  # reused
            # one pair per caption: the grouped and the interleaved order are the same pairs
            make_pairs(teacher, dataclasses.replace(settings, pair_order="grouped"), student_run, dist)
            with pytest.raises(PairSetError, match="seed"):
                make_pairs(teacher, dataclasses.replace(settings, seed=1), student_run, dist)
        finally:
            pairs_module.solve_pairs = original


def test_interleaved_pairs_cycle_through_the_captions_in_every_shard(student_run, teacher_run, tmp_path):
    """distill.pair_order=interleaved (the default) numbers the pairs repeat by repeat, so the shards hold every
    caption once before any caption's second pair (a shuffle buffer then mixes the captions into each batch; grouped,
    a caption's pairs come together); pair i keeps noise seed sample_seed(seed, i). A set made before the option
    (no order in its manifest) is a grouped one: reused with pair_order=grouped, refused with interleaved."""
    teacher = load_trained_model(teacher_run)
    settings = dataclasses.replace(load_config(TrainConfig, student_run / "config.yaml").distill,
                                   pairs_per_caption=2, flow_map_probes=0, batch_size=64)
    source = pairs_module.teacher_source(teacher)
    captions = [(r.id, c) for r in iter_motions(source, "train") for c in range(len(r.captions))]
    plans = {order: pairs_module.plan_pairs(source, dataclasses.replace(settings, pair_order=order), 96)
             for order in ("interleaved", "grouped")}
    assert [(p.record_id, p.caption, p.repeat) for p in plans["interleaved"]] == \
        [(record, caption, repeat) for repeat in (0, 1) for record, caption in captions]
    assert [(p.record_id, p.caption, p.repeat) for p in plans["grouped"]] == \
        [(record, caption, repeat) for record, caption in captions for repeat in (0, 1)]

    with Dist() as dist:
        manifest_path = make_pairs(teacher, dataclasses.replace(settings, pair_order="interleaved"),
                                   tmp_path / "interleaved", dist)
    records = list(iter_motions(open_manifest(manifest_path), "train"))
    assert [r.id for r in records] == [p.pair_id for p in plans["interleaved"]]
    assert [r.noise_seed for r in records] == [sample_seed(settings.seed, i) for i in range(len(records))]
    assert len({r.id.rsplit("_p", 1)[0] for r in records[:len(captions)]}) == len(captions)
    manifest = json.loads(manifest_path.read_text())
    assert manifest["pairs"]["order"] == "interleaved"

    del manifest["pairs"]["order"]  # as a set made before the option recorded it
    manifest_path.write_text(json.dumps(manifest))
    with Dist() as dist:
        with pytest.raises(PairSetError, match="its pairs are grouped: distill.pair_order=grouped reuses them"):
            make_pairs(teacher, dataclasses.replace(settings, pair_order="interleaved"), tmp_path / "interleaved",
                       dist)
        original = pairs_module.solve_pairs
        pairs_module.solve_pairs = refuse_solving
        try:
            assert make_pairs(teacher, dataclasses.replace(settings, pair_order="grouped"), tmp_path / "interleaved",
                              dist) == manifest_path
        finally:
            pairs_module.solve_pairs = original


def test_the_pair_set_measures_the_teachers_flow_map(student_run, teacher_run, tmp_path):
    """The manifest holds the teacher's flow-map amplification at distill.flow_map_probes pairs spread over the
    split; one of them recomputed by hand (the pair's noise, then the next draw of its generator as the direction)
    agrees; the median is recorded in the student's config and model card."""
    manifest = json.loads((student_run / "pairs" / "manifest.json").read_text())
    flow_map = manifest[FLOW_MAP_KEY]
    records = pair_records(student_run)
    probed = sorted(int(k) for k in flow_map["by_pair"])
    assert flow_map["probes"] == len(probed) == min(DistillConfig.flow_map_probes, len(records))
    assert probed[0] == 0 and probed[-1] == len(records) - 1  # spread over the whole split
    values = list(flow_map["by_pair"].values())
    assert all(np.isfinite(v) and v > 0 for v in values)
    assert flow_map["amplification_median"] == pytest.approx(float(np.median(values)))

    teacher = load_trained_model(teacher_run)
    guidance = float(teacher.model_config.sampling_guidance)
    record = records[probed[len(probed) // 2]]
    length = record.features.shape[0]
    lengths = torch.tensor([length])
    generators = seeded_generators([record.noise_seed])
    shape = (1, length, teacher.model_config.feature_dim)
    x0, direction = draw_noise(shape, generators, lengths=lengths), draw_noise(shape, generators, lengths=lengths)
    velocity = zero_padded_frames(guided_velocity(teacher.model, torch.from_numpy(record.text_emb[:1]),
                                                  scale=guidance, lengths=lengths), lengths)
    with torch.no_grad():
        ends = [solve(velocity, x, solver="euler", steps=10).x1 for x in (x0, x0 + FLOW_MAP_PERTURBATION * direction)]
    by_hand = float((ends[1] - ends[0]).norm() / (FLOW_MAP_PERTURBATION * direction).norm())
    assert flow_map["by_pair"][str(probed[len(probed) // 2])] == pytest.approx(by_hand, rel=1e-2)

    recorded = yaml.safe_load((student_run / "config.yaml").read_text())["distill"]
    assert recorded["teacher_flow_map_amplification"] == pytest.approx(flow_map["amplification_median"])
    card = (export_pretrained(student_run, tmp_path / "export") / CARD_FILE).read_text()
    assert f"flow-map amplification" in card
    assert f"{flow_map['amplification_median']:.3g}" in card


def test_probes_spread_over_the_captions_and_a_rough_map_is_warned_of(caplog):
    pairs = [PlannedPair(i, i // 6, f"r{i // 6}", (i // 3) % 2, i % 3, 40, i) for i in range(60)]  # 20 captions x 3
    firsts = [p.index for p in pairs if p.repeat == 0]
    assert probe_indices(pairs, 100) == set(firsts)
    picked = sorted(probe_indices(pairs, 5))
    assert len(picked) == 5 and picked[0] == 0 and picked[-1] == firsts[-1] and set(picked) <= set(firsts)
    assert probe_indices(pairs, 0) == set()
    with caplog.at_level("INFO", logger="pipeline.generation.pairs"):
        report_flow_map({"probes": 5, "amplification_median": 1.3, "amplification_max": 2.0})
        assert [r.levelname for r in caplog.records] == ["INFO"]
        report_flow_map({"probes": 5, "amplification_median": 2.7e4, "amplification_max": 8e5})
        assert caplog.records[-1].levelname == "WARNING" and "rough" in caplog.records[-1].getMessage()


def test_pairs_made_in_chunks_straddling_records_are_the_same_pairs(student_run, teacher_run, tmp_path, monkeypatch):
    """A rank solves and holds one chunk of pairs at a time, streaming the records it needs: with chunks of one
    batch of 8 (a record's captions split across chunks) the pair set holds the same pairs, in the same order, with
    the same seeds, captions and text features, and (up to the summation order of other batch mates) motions."""
    monkeypatch.setattr(pairs_module, "CHUNK_BATCHES", 1)
    teacher = load_trained_model(teacher_run)
    settings = dataclasses.replace(load_config(TrainConfig, student_run / "config.yaml").distill, batch_size=8)
    with Dist() as dist:
        make_pairs(teacher, settings, tmp_path / "chunked", dist)
    one, chunked = pair_records(student_run), pair_records(tmp_path / "chunked")
    assert len(one) > 8 and [(r.id, r.noise_seed, r.captions) for r in chunked] == \
        [(r.id, r.noise_seed, r.captions) for r in one]
    for a, b in zip(one, chunked):
        np.testing.assert_array_equal(b.text_emb, a.text_emb)
        np.testing.assert_allclose(b.features, a.features, rtol=0, atol=1e-4)


def test_the_record_window_refuses_pairs_whose_records_the_split_lacks():
    """A pair set's records are streamed in order: a record the split skipped or ended before is refused with
    the missing positions named, whichever way it is missed; a run of pairs that needs a record the pass has gone by
    (interleaved pairs, back at the split's start) gets it from a new pass, and only then."""
    def pair(position: int) -> PlannedPair:
        return PlannedPair(position, position, f"r{position}", 0, 0, 10, 0)

    split = [(0, "a"), (1, "b"), (3, "d")]
    window = RecordWindow(lambda: iter(split))
    assert window.take([pair(0), pair(1)]) == {0: "a", 1: "b"}
    assert window.take([pair(1), pair(3)]) == {1: "b", 3: "d"} and window.passes == 1  # 1 is the record it holds
    assert window.take([pair(3), pair(0)]) == {0: "a", 3: "d"} and window.passes == 2
    with pytest.raises(PairSetError, match=r"records \[2\] of the pairs are not in the split"):
        window.take([pair(2)])  # the split passed it
    with pytest.raises(PairSetError, match=r"records \[1\] of the pairs are not in the split"):
        RecordWindow(lambda: iter([(0, "a")])).take([pair(0), pair(1)])  # the split ended before it


def test_recorded_noise_is_each_records_seed_and_length(student_run, teacher_run, tmp_path):
    """train.flow_noise=recorded: the loss's x0 is draw_noise of each record's seed over its length (zero after), and
    the teacher's Euler path from exactly that noise ends at the record's motion."""
    teacher = load_trained_model(teacher_run)
    cfg = load_config(TrainConfig, student_run / "config.yaml", [f"train.out_dir={tmp_path / 'run'}"])
    with Dist() as dist:
        trainer = Trainer(cfg, dist)
        batch = next(trainer.loader.iter_batches())
        captured = {}
        real = trainer.objective

        class Capture:
            def loss(self, model, x1, cond, lengths, **kwargs):
                captured.update(x0=kwargs.get("x0"), x1=x1, lengths=lengths)
                return real.loss(model, x1, cond, lengths, **kwargs)

        trainer.objective = Capture()
        trainer._micro_batch_loss(batch, None)
    x0, lengths = captured["x0"], captured["lengths"]
    assert x0 is not None and x0.shape == batch["features"].shape
    for row, (seed, length) in enumerate(zip(batch["noise_seed"].tolist(), lengths.tolist())):
        expected = draw_noise((1, length, x0.shape[-1]), seeded_generators([seed]), lengths=[length])[0]
        torch.testing.assert_close(x0[row, :length], expected, rtol=0, atol=0)
        assert not x0[row, length:].any()
    record = {r.id: r for r in pair_records(student_run)}[batch["ids"][0]]
    endpoint = solve_from_recorded_noise(teacher, record, teacher.default_guidance, 10)
    torch.testing.assert_close(endpoint, captured["x1"][0, :lengths[0]], rtol=0, atol=1e-4)


def test_student_samples_in_one_and_two_evaluations(student_run, teacher_run, tmp_path):
    """The student is a checkpoint like any other: launch/sample.py and MotionPipeline sample it in its 2 steps by
    default (guidance 1: one pass per step) or 1 when asked, results.json and the records say how many evaluations
    ran, and its config records the method and the teacher."""
    out = tmp_path / "two"
    assert sample_entry.main(["--checkpoint", str(student_run), "--out", str(out), "--text", "a person walks",
                              "--length", "20", "--no-video", "--no-bvh"]) == 0
    results = json.loads((out / "results.json").read_text())
    assert (results["steps"], results["nfe_per_batch"], results["guidance"]) == (2, [2], 1.0)
    assert [s["nfe"] for s in results["samples"]] == [2]
    out = tmp_path / "one"
    assert sample_entry.main(["--checkpoint", str(student_run), "--out", str(out), "--text", "a person walks",
                              "--length", "20", "--steps", "1", "--no-video", "--no-bvh"]) == 0
    assert json.loads((out / "results.json").read_text())["nfe_per_batch"] == [1]
    # trained without condition dropout, it has no unconditional field: guiding it is refused, not sampled
    assert sample_entry.main(["--checkpoint", str(student_run), "--out", str(tmp_path / "guided"), "--text",
                              "a person walks", "--length", "20", "--guidance", "2.5", "--no-video", "--no-bvh"]) == 2
    assert not (tmp_path / "guided" / "results.json").exists()

    pipe = MotionPipeline(load_trained_model(student_run))
    assert [r["nfe"] for r in pipe("a person jumps", seconds=1.0).records] == [2]
    motions = pipe("a person jumps", seconds=1.0, num_inference_steps=1)
    assert [r["nfe"] for r in motions.records] == [1] and np.isfinite(motions.joints[0]).all()

    config = yaml.safe_load((student_run / "config.yaml").read_text())
    teacher_folder = ckpt.resolve_checkpoint(teacher_run)
    assert config["distill"]["method"] == "reflow"
    assert config["distill"]["teacher_checkpoint_id"] == ckpt.checkpoint_id(ckpt.read_marker(teacher_folder))
    assert (config["distill"]["teacher_step"], config["distill"]["teacher_steps"]) == (TEACHER_STEPS, 10)
    assert (config["model"]["cond_drop_prob"], config["model"]["sampling_guidance"],
            config["model"]["sampling_steps"]) == (0.0, 1.0, 2)
    assert config["train"]["flow_noise"] == "recorded"


def test_student_one_step_lands_nearer_the_teachers_endpoint_than_the_teachers_one_step(student_run, teacher_run):
    """What the method is for: from a pair's own noise, the student's single Euler step (guidance 1) ends nearer the
    teacher's 10-step guided endpoint than the teacher's own single guided step does. A student trained on
    independent noise (the same pairs as data) learns the average motion per caption instead and fails this."""
    teacher, student = load_trained_model(teacher_run), load_trained_model(student_run)
    records = pair_records(student_run)[:32]
    student_error = teacher_error = 0.0
    for record in records:
        target = (torch.from_numpy(record.features) - teacher.mean) / teacher.std
        student_error += (solve_from_recorded_noise(student, record, 1.0, 1) - target).square().mean().item()
        teacher_error += (solve_from_recorded_noise(teacher, record, teacher.default_guidance, 1)
                          - target).square().mean().item()
    assert student_error < 0.9 * teacher_error, (student_error / len(records), teacher_error / len(records))


def distill_on_the_students_pairs(student_run: Path, teacher_run: Path, run: Path, *overrides: str) -> Path:
    """A student trained on ``student_run``'s pair set (linked, not made again) with ``overrides``."""
    if (run / "checkpoints").is_dir():
        return run
    run.mkdir(parents=True, exist_ok=True)
    (run / "pairs").symlink_to(student_run / "pairs", target_is_directory=True)
    shutil.copy(student_run / RUN_MARKER, run / RUN_MARKER)  # a run folder of ours, as the pairs' own run is
    with single_threaded_torch():
        assert distill_entry.main(["--teacher", str(teacher_run), "--out", str(run), *STUDENT_OVERRIDES,
                                   *overrides]) == 0
    return run


@pytest.fixture(scope="session")
def grid_student_run(tmp_path_factory, student_run, teacher_run) -> Path:
    return distill_on_the_students_pairs(student_run, teacher_run, tmp_path_factory.getbasetemp() / "grid-student",
                                         "train.flow_time_sampling=grid", "train.flow_time_grid_steps=2")


def endpoint_errors(teacher_run: Path, runs: list[Path], steps: int, pairs_of: Path) -> list[float]:
    """Each run's summed squared error, over the first 32 pairs of ``pairs_of``, between its ``steps``-step Euler
    solution (guidance 1) from the pair's own noise and the teacher's endpoint (normalised features)."""
    teacher = load_trained_model(teacher_run)
    records = pair_records(pairs_of)[:32]
    errors = []
    for student in (load_trained_model(run) for run in runs):
        errors.append(sum((solve_from_recorded_noise(student, record, 1.0, steps)
                           - (torch.from_numpy(record.features) - teacher.mean) / teacher.std
                           ).square().mean().item() for record in records))
    return errors


def test_grid_times_train_the_few_step_samplers_map_closer(student_run, teacher_run, grid_student_run, tmp_path):
    """Rectified flow's k-step distillation (train.flow_time_sampling=grid, K = 2): a student trained only at the
    times its 2-step sampler visits (t = 0 and 1/2) ends its 1- and 2-step solutions from the pairs' own noise nearer
    the teacher's endpoints than the student trained on the same pairs, as long, at uniform times (plain reflow, the
    default). Its config and model card record the grid; a grid that lacks the student's steps is refused."""
    run = grid_student_run
    recorded = yaml.safe_load((run / "config.yaml").read_text())["train"]
    assert (recorded["flow_time_sampling"], recorded["flow_time_grid_steps"]) == ("grid", 2)
    card = (export_pretrained(run, tmp_path / "export") / CARD_FILE).read_text()
    assert "trained only at the times its 2-step Euler sampler visits" in card
    for steps in (1, 2):
        errors = endpoint_errors(teacher_run, [student_run, run], steps, student_run)
        assert errors[1] < 0.8 * errors[0], (steps, errors)
    teacher = load_trained_model(teacher_run)
    with pytest.raises(ConfigError, match="student_steps"):
        student_config(teacher, yaml.safe_load((teacher_run / "config.yaml").read_text()), tmp_path / "s3",
                       ["train.flow_time_sampling=grid", "distill.student_steps=3"])


def test_a_student_keeps_its_teachers_optimizer_with_muons_rate_scaled_as_its_lr(teacher_run, tmp_path):
    """A teacher trained with Muon (optim.optimizer=muon, the synthetic preset's) gives a Muon student whose
    matrices' rate moves with the student's optim.lr as the rest's does (a Muon student of the synthetic preset beat
    the AdamW one at one step on every figure: docs/few-step.md); a given optim.muon_lr is kept, AdamW is one
    override away, and an AdamW teacher's student stays AdamW."""
    teacher = load_trained_model(teacher_run)
    config = yaml.safe_load((teacher_run / "config.yaml").read_text())
    assert student_config(teacher, config, tmp_path / "s", []).optim.optimizer == "adamw"
    config["optim"].update(optimizer="muon", lr=1e-3, muon_lr=0.02)
    student = student_config(teacher, config, tmp_path / "s", ["optim.lr=3e-4"]).optim
    assert (student.optimizer, student.lr) == ("muon", 3e-4) and student.muon_lr == pytest.approx(0.006)
    assert student_config(teacher, config, tmp_path / "s", []).optim.muon_lr == pytest.approx(0.02)
    assert student_config(teacher, config, tmp_path / "s", ["optim.lr=3e-4", "optim.muon_lr=0.01"]
                          ).optim.muon_lr == 0.01
    assert student_config(teacher, config, tmp_path / "s", ["optim.optimizer=adamw"]).optim.optimizer == "adamw"


def test_a_reflow_students_bone_term_holds_each_bone_to_its_median(teacher_run, tmp_path):
    """A reflow student's targets are the teacher's raw motions, whose bones vary from frame to frame: its bone term
    holds each bone to its median over the motion (train.flow_bone_target=clip_median) unless told otherwise; with
    the term off nothing changes (the config would refuse a target for a term that is off), and a shortcut student,
    which trains on the teacher's clips, keeps the teacher's target."""
    teacher = load_trained_model(teacher_run)
    config = yaml.safe_load((teacher_run / "config.yaml").read_text())
    assert config["train"]["flow_bone_weight"] == 0
    assert student_config(teacher, config, tmp_path / "s", []).train.flow_bone_target == "frames"
    config["train"]["flow_bone_weight"] = 30.0
    assert student_config(teacher, config, tmp_path / "s", []).train.flow_bone_target == "clip_median"
    assert student_config(teacher, config, tmp_path / "s", ["train.flow_bone_weight=0"]).train.flow_bone_target == (
        "frames")
    assert student_config(teacher, config, tmp_path / "s", ["train.flow_bone_target=frames"]
                          ).train.flow_bone_target == "frames"
    assert student_config(teacher, config, tmp_path / "s", ["distill.method=shortcut"]
                          ).train.flow_bone_target == "frames"
    # the output filter is the student's own sampling setting (the synthetic recipe samples at σ 0.9)
    assert student_config(teacher, config, tmp_path / "s", ["model.output_smoothing=0.9"]
                          ).model.output_smoothing == 0.9


def test_a_second_step_trained_from_the_first_steps_own_states_lands_nearer(student_run, teacher_run,
                                                                            grid_student_run, tmp_path_factory,
                                                                            tmp_path):
    """Backward distillation (train.flow_grid_inputs=own_path): the same grid, but the t = 1/2 rows start from the
    state the student's own first step reaches. Its 2-step solution from the pairs' own noise, the sampler it was
    trained for, ends nearer the teacher's endpoints than the grid student's trained from the straight path's
    states, on the same pairs as long; the option is recorded in its config and model card."""
    run = distill_on_the_students_pairs(student_run, teacher_run, tmp_path_factory.getbasetemp() / "own-student",
                                        "train.flow_time_sampling=grid", "train.flow_time_grid_steps=2",
                                        "train.flow_grid_inputs=own_path")
    assert yaml.safe_load((run / "config.yaml").read_text())["train"]["flow_grid_inputs"] == "own_path"
    card = (export_pretrained(run, tmp_path / "export") / CARD_FILE).read_text()
    assert "from the state its own earlier steps reach" in card
    errors = endpoint_errors(teacher_run, [grid_student_run, run], 2, student_run)
    assert errors[1] < 0.9 * errors[0], errors


@pytest.fixture(scope="session")
def late_student_run(tmp_path_factory, student_run, teacher_run) -> Path:
    """A 2-step student whose second step starts at 0.9, trained there from its first step's own states."""
    return distill_on_the_students_pairs(student_run, teacher_run, tmp_path_factory.getbasetemp() / "late-student",
                                         "train.flow_time_sampling=grid", "train.flow_grid_inputs=own_path",
                                         "model.sampling_times=[0,0.9]")


def test_a_student_at_its_own_sampling_times_is_trained_and_sampled_there(student_run, teacher_run,
                                                                           late_student_run, tmp_path):
    """model.sampling_times=[0,0.9] with the own-path grid: the student trains at t = 0 and 0.9, and its 2-step
    sampler starts its steps there: launch/sample.py gives the Euler solution on 0 -> 0.9 -> 1 from the pair's
    noise (not the uniform grid's), which ends nearer the teacher's endpoints than the same student on the
    uniform grid; its 1-step sampler is the uniform one; config, model card and results.json record the times."""
    run = late_student_run
    assert yaml.safe_load((run / "config.yaml").read_text())["model"]["sampling_times"] == [0, 0.9]
    card = (export_pretrained(run, tmp_path / "export") / CARD_FILE).read_text()
    assert "starts its Euler steps at the times 0, 0.9" in card
    student, first = load_trained_model(run), pair_records(student_run)[0]
    late, uniform = (solve_from_recorded_noise(student, first, 1.0, 2, grid) for grid in ([0, 0.9, 1], None))
    for steps, expected in ((2, late), (1, solve_from_recorded_noise(student, first, 1.0, 1))):
        out = tmp_path / f"sampled-{steps}"
        assert sample_entry.main(["--checkpoint", str(run), "--out", str(out), "--text", first.captions[0],
                                  "--length", str(first.features.shape[0]), "--seed", "0", "--steps", str(steps),
                                  "--no-video", "--no-bvh"]) == 0
        sampled = np.load(out / "sample_000" / "features.npy")
        np.testing.assert_allclose(sampled, student.denormalize(expected).numpy(), rtol=0, atol=1e-4)
        assert json.loads((out / "results.json").read_text()).get("grid") == ([0, 0.9, 1] if steps == 2 else None)
    assert (late - uniform).abs().max() > 1e-2
    teacher = load_trained_model(teacher_run)
    errors = []
    for grid in ([0, 0.9, 1], None):
        errors.append(sum((solve_from_recorded_noise(student, record, 1.0, 2, grid)
                           - (torch.from_numpy(record.features) - teacher.mean) / teacher.std).square().mean().item()
                          for record in pair_records(student_run)[:32]))
    assert errors[0] < 0.9 * errors[1], errors


def test_recorded_noise_needs_a_pair_set_used_whole(tmp_path_factory, tmp_path):
    """train.flow_noise=recorded is refused on a crop that would cut a pair from its noise, and on a dataset that
    is not a pair set; launch/distill.py refuses overrides of what the method sets (exit 2, one line)."""
    with pytest.raises(ConfigError, match="unit_length=1"):
        load_config(TrainConfig, "tiny", ["train.flow_noise=recorded"])
    with pytest.raises(ConfigError, match="flow-matching"):
        load_config(TrainConfig, "tiny", ["train.flow_noise=recorded", "data.unit_length=1", "train.objective=diffusion"])
    cfg = load_config(TrainConfig, "tiny", ["train.flow_noise=recorded", "data.unit_length=1",
                                             f"data.manifest={build_dataset_once(tmp_path_factory)}",
                                             f"train.out_dir={tmp_path / 'run'}"])
    with Dist() as dist, pytest.raises(ConfigError, match="not a distillation pair set"):
        Trainer(cfg, dist)
    assert DistillConfig().method == "reflow"


def test_refused_overrides_exit_2(teacher_run, tmp_path, capsys):
    code = distill_entry.main(["--teacher", str(teacher_run), "--out", str(tmp_path / "s"),
                               "train.flow_noise=independent"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err[-1].startswith("error: override 'train.flow_noise=independent'")
    assert not (tmp_path / "s").exists()


def test_a_new_student_starts_in_a_folder_holding_only_a_linked_pair_set(student_run, teacher_run, tmp_path,
                                                                         monkeypatch, capsys):
    """Several students of one pair set (the method comparisons of docs/few-step.md): a new folder holding only
    ``pairs``, a link to another student's finished set, is taken as a student's folder and its pairs are reused,
    not solved again; a folder holding anything beside them, or an unfinished set, is still refused."""
    monkeypatch.setattr(pairs_module, "solve_pairs", refuse_solving)
    args = ["--teacher", str(teacher_run), *STUDENT_OVERRIDES, "train.max_steps=2", "train.save_every=2",
            "train.log_every=1", "train.preview_every=0"]
    seeded = tmp_path / "seeded"
    seeded.mkdir()
    (seeded / "pairs").symlink_to(student_run / "pairs", target_is_directory=True)
    with single_threaded_torch():
        assert distill_entry.main(["--out", str(seeded), *args]) == 0
    assert (seeded / RUN_MARKER).is_file() and ckpt.resolve_checkpoint(seeded).name == "step-00000002"
    assert (seeded / "pairs").is_symlink()

    crowded = tmp_path / "crowded"
    crowded.mkdir()
    (crowded / "pairs").symlink_to(student_run / "pairs", target_is_directory=True)
    (crowded / "notes.txt").write_text("someone's files")
    unfinished = tmp_path / "unfinished"
    (unfinished / "pairs").mkdir(parents=True)
    for folder in (crowded, unfinished):
        capsys.readouterr()
        assert distill_entry.main(["--out", str(folder), *args]) == 2
        assert "is a non-empty folder that is not a run folder" in capsys.readouterr().err
        assert not (folder / RUN_MARKER).exists()


@pytest.fixture(scope="module")
def student_launches(student_run, teacher_run, tmp_path_factory, request) -> dict[str, Future]:
    """The launches of the two tests below, started together (start_two_at_a_time), each when its test runs: the
    student's run killed and resumed beside an uninterrupted one (kill_and_resume), and the distillation under
    torchrun. Per launch its result; kill_and_resume's checks fail where its result is read."""
    root = tmp_path_factory.mktemp("student-launches")
    wanted = selected_tests(request)
    launches = {}
    if "test_student_training_resumes_bit_exactly" in wanted:
        extra = ("data.unit_length=1", "train.flow_noise=recorded", f"train.init_from={teacher_run}",
                 "model.cond_drop_prob=0", "train.max_steps=6", "train.save_every=2", "train.keep_last=2",
                 "train.flow_time_sampling=grid", "train.flow_grid_inputs=own_path")
        launches["resume"] = partial(kill_and_resume, student_run / "pairs" / "manifest.json", root / "resume",
                                     base_overrides, extra, 5, 4)
    if "test_two_ranks_share_the_teachers_work" in wanted:
        launches["two_ranks"] = partial(
            subprocess.run, [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                             str(REPO_ROOT / "launch" / "distill.py"), "--teacher", str(teacher_run), "--out",
                             str(root / "two_ranks"), "train.max_steps=2", "train.save_every=2",
                             "distill.batch_size=7", "train.flow_time_sampling=grid",
                             "train.flow_grid_inputs=own_path"],
            cwd=REPO_ROOT, env=clean_env(), capture_output=True, text=True, timeout=300)
    started = start_two_at_a_time(launches)
    return {name: (root / name, future) for name, future in started.items()}


def test_student_training_resumes_bit_exactly(student_launches):
    """The student's run (recorded noise, initialised from the teacher, its second grid time trained from its own
    first step's states) SIGKILLed in the middle of step 5 and resumed from checkpoint 4 ends bit-identical to an
    uninterrupted one."""
    a_out, b_out = student_launches["resume"][1].result()
    assert_runs_identical(a_out / "run", b_out / "run", 6)


@pytest.mark.multirank
def test_two_ranks_share_the_teachers_work(student_run, student_launches):
    """Under torchrun with 2 ranks each rank solves every other pair and rank 0 writes them all: the same pairs, in
    the same order, with the same seeds and (up to the summation order of other batch mates) the same motions as
    one rank's; then the student trains on both ranks (with the own-path grid's extra gradient-free pass)."""
    out, started = student_launches["two_ranks"]
    proc = started.result()
    assert proc.returncode == 0, output_of(proc)
    one, two = pair_records(student_run), pair_records(out)
    assert [(r.id, r.noise_seed, r.captions) for r in two] == [(r.id, r.noise_seed, r.captions) for r in one]
    for a, b in zip(one, two):
        np.testing.assert_allclose(b.features, a.features, rtol=0, atol=1e-4)
    assert ckpt.list_complete(ckpt.checkpoints_dir(out))[-1][0] == 2


def evaluate_at_one_and_two_steps(run: Path, tmp_path: Path, tmp_path_factory) -> tuple[Path, Path, Path]:
    """The evaluator's fast protocol (small) on ``run`` at 1 and 2 steps, guidance 1, with a random evaluator:
    (dataset manifest, evaluator weights, output folder)."""
    from launch.evaluate import main as evaluate

    dataset = build_dataset_once(tmp_path_factory)
    evaluator = random_contrastive_evaluator(dataset, tmp_path / "evaluator.safetensors")
    out = tmp_path / "eval"
    assert evaluate(["--checkpoint", str(run), "--protocol", "fast", *SMALL_PROTOCOL, "--steps", "1,2",
                     "--guidance", "1", "protocol.replications=1", "tasks.editing=[]", "protocol.multimodality=false",
                     f"evaluator.path={evaluator}", f"output.dir={out}"]) == 0
    return dataset, evaluator, out


def test_the_evaluator_scores_a_student_on_its_teachers_test_split(student_run, tmp_path, tmp_path_factory):
    """The evaluator takes the student like any checkpoint: its recorded dataset is the pair set (no test split), so
    the default evaluation data is the teacher's dataset the pairs were made from; each row records its NFE."""
    from launch.evaluate import main as evaluate

    dataset, evaluator, out = evaluate_at_one_and_two_steps(student_run, tmp_path, tmp_path_factory)
    rows = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    generated = [r for r in rows if r.get("row_kind") == "generated"]
    assert sorted((r["steps"], r["nfe"]) for r in generated) == [(1, 1), (2, 2)]
    # the protocol's own guidance (2.5) would guide a model with no unconditional field: refused before any unit
    assert evaluate(["--checkpoint", str(student_run), "--protocol", "fast", *SMALL_PROTOCOL, "--steps", "2",
                     "protocol.replications=1", "tasks.editing=[]", "protocol.multimodality=false",
                     f"evaluator.path={evaluator}", f"output.dir={tmp_path / 'guided'}"]) == 2
    assert {r["dataset_id"] for r in generated} == {open_manifest(dataset).dataset_id}


def test_the_evaluator_steps_on_a_students_own_sampling_times(late_student_run, tmp_path, tmp_path_factory):
    """The evaluator's 2-step point of a student with model.sampling_times runs on 0 -> 0.9 -> 1 and its results
    say so; its 1-step point runs (and records) the uniform grid."""
    _, _, out = evaluate_at_one_and_two_steps(late_student_run, tmp_path, tmp_path_factory)
    results = [json.loads(path.read_text()) for path in sorted((out / "results").glob("step-*/euler-*.json"))]
    assert sorted((r["sampling"]["steps"], r["sampling"]["grid"], r["nfe"]) for r in results) == \
        [(1, None, 1), (2, [0.0, 0.9, 1.0], 2)]


def test_a_students_contact_sheet_compares_with_its_teachers_clips(student_run, tmp_path, tmp_path_factory):
    """--captions-from-manifest of a student takes its teacher's dataset (its own is the pair set), at its 2 steps."""
    from pipeline.generation.contact_sheet import ContactSheetRequest, first_captions, run_contact_sheet

    sheet = run_contact_sheet(ContactSheetRequest(out=tmp_path / "sheet.png", checkpoint=student_run,
                                                  captions_from_manifest="test", frames=2))
    captions = first_captions(open_manifest(build_dataset_once(tmp_path_factory)), "test")
    assert [row["text"] for row in sheet["rows"]] == [c.text for c in captions]
    assert (sheet["steps"], sheet["guidance"]) == (2, 1.0)
    assert [row["id"] for row in sheet["against_dataset_clips"]["rows"]] == [c.motion_id for c in captions]


def test_init_from_starts_the_weights_and_their_ema_from_the_checkpoints_ema(teacher_run, tmp_path, tmp_path_factory):
    """train.init_from on a fresh start: after one step at a negligible rate the weights and their EMA are the
    teacher's EMA weights; a checkpoint of another architecture is refused in one line (exit 2)."""
    _, teacher_ema, _ = ckpt.load_checkpoint(ckpt.resolve_checkpoint(teacher_run))
    run = tmp_path / "run"
    common = ["--config", "tiny", f"data.manifest={build_dataset_once(tmp_path_factory)}",
              f"train.init_from={teacher_run}", "train.max_steps=1", "train.save_every=1", "optim.lr=1e-12"]
    assert train_entry.main([*common, f"train.out_dir={run}"]) == 0
    model, ema, _ = ckpt.load_checkpoint(ckpt.resolve_checkpoint(run))
    for name, value in teacher_ema.items():
        torch.testing.assert_close(model[name], value, rtol=0, atol=1e-6)
        torch.testing.assert_close(ema[name], value, rtol=0, atol=1e-6)
    assert train_entry.main([*common, f"train.out_dir={tmp_path / 'wide'}", "model.latent_dim=32"]) == 2
