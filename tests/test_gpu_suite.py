"""benchmarks/gpu_suite.py: the one command behind every speed figure of issue 13, kept from rotting on CPU.

The suite runs here at its ``--smoke`` size on the CPU, in-process (about 5 s on 2 cores); its GPU figures are
measured on a GPU machine. The equal-loss check is also tested on its own with the real HumanML3D-sized model, fp32
against bf16 autocast on the CPU (the FLOP count behind MFU: tests/test_flops.py).
"""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import math
import sys
from pathlib import Path

import pytest
import torch

from conftest import load_benchmark

REPO_ROOT = Path(__file__).resolve().parents[1]


def load_suite():
    """benchmarks/gpu_suite.py as a module (benchmarks/ is a folder of scripts, not a package)."""
    if "gpu_suite" in sys.modules:
        return sys.modules["gpu_suite"]
    spec = importlib.util.spec_from_file_location("gpu_suite", REPO_ROOT / "benchmarks" / "gpu_suite.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["gpu_suite"] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory) -> Path:
    """One ``--smoke --device cpu`` run of the suite; its output folder."""
    out = tmp_path_factory.mktemp("gpu-suite")
    assert load_suite().main(["--smoke", "--device", "cpu", "--out", str(out)]) == 0
    return out


def read_records(out: Path) -> dict[str, dict]:
    records = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    return {record["figure"]: record for record in records}


def test_smoke_run_reports_every_figure_finite(smoke_run):
    suite = load_suite()
    records = read_records(smoke_run)
    assert records["environment"]["device"] == "cpu" and records["environment"]["size"] == "smoke"
    for name in (*suite.FIGURES, "suite_wall"):
        assert name in records, f"figure {name} missing from results.jsonl"
        value = records[name]["value"]
        assert isinstance(value, (int, float)) and math.isfinite(value) and value >= 0, (name, value)
        assert records[name]["unit"]
    for name in ("train_fp32", "train_optimised", "data_loader", "evaluator", "sampling_one", "sampling_batch"):
        assert records[name]["value"] > 0, name
    for name in ("train_fp32", "train_optimised"):  # no dense bf16 peak for a CPU: MFU null, with the reason
        assert records[name]["mfu"] is None and "CPU" in records[name]["mfu_note"]
        assert records[name]["gflop_per_sample"] > 0
    assert records["sampling_batch"]["batch_size"] == 8 and records["sampling_one"]["nfe"] == 10
    # issue 26: the sampler and the evaluator at the optimised precision beside fp32, in the same run
    optimised = "bf16" if records["environment"]["optimised_precision"] == "bf16" else "fp32"
    assert records["sampling_batch_optimised"]["precision"] == records["evaluator_optimised"]["precision"] == optimised
    assert records["sampling_one"]["precision"] == records["evaluator"]["precision"] == "fp32"
    assert records["sampling_difference"]["state_dtype"] == "float32"
    if optimised == "bf16":
        from test_sampling_precision import BF16_MAX_ABS

        assert 0 < records["sampling_difference"]["value"] <= BF16_MAX_ABS
    for name in ("evaluator", "evaluator_optimised"):  # smoke: text-to-motion only, 10 guided passes per batch
        assert records[name]["model_calls_per_replication"] == 10 and records[name]["editing_passes"] == \
            "per_replication"


def test_smoke_run_writes_a_markdown_table_naming_the_device(smoke_run):
    suite = load_suite()
    env = read_records(smoke_run)["environment"]
    text = (smoke_run / "results.md").read_text()
    assert env["device_name"] in text and env["device_name"].startswith("cpu")
    assert f"torch {torch.__version__}" in text and "dense bf16 peak: n/a" in text
    assert "MFU of train_fp32: n/a" in text and "MFU of train_optimised: n/a" in text
    for name in suite.FIGURES:
        assert f"| {name} |" in text


def test_smoke_run_equal_loss_is_small(smoke_run):
    record = read_records(smoke_run)["equal_loss"]
    if record["optimised_precision"] == "fp32":  # no CPU autocast in this torch: the same computation twice
        assert record["value"] == 0.0
    else:
        assert record["value"] < load_suite().EQUAL_LOSS_RTOL
    assert record["within_tolerance"]


def test_equal_loss_fp32_vs_bf16_autocast_on_cpu(tmp_path):
    """The HumanML3D preset's model (8 post-norm layers of 512), probe step at fp32, fp32 again and bf16 autocast.

    Two fp32 trainers must agree exactly (same seed, batch and draws: the check compares like with like). bf16 must
    differ (autocast really ran) by less than EQUAL_LOSS_RTOL = 2e-2: bf16 keeps about 3 significant digits, with
    fp32 accumulation, LayerNorms and loss; measured about 3e-5 on this machine."""
    suite = load_suite()
    if not torch.amp.is_autocast_available("cpu"):
        pytest.skip("this torch has no CPU autocast")
    from pipeline.distributed import Dist
    from pipeline.training.trainer import Trainer

    manifest = suite.bench_data.build_synthetic(16, tmp_path / "ds", text_dim=suite.TEXT_DIM, formats=("tar",))
    size = dataclasses.replace(suite.SMOKE, name="test", preset="humanml3d", batch_size=2, window=48)
    options = suite.SuiteOptions(out=tmp_path, size=size, device="cpu", compile=False, workers=0,
                                 optimised_precision="bf16")
    losses = []
    for i, precision in enumerate(("no", "no", "bf16")):
        cfg = suite.training_config(options, manifest, tmp_path / f"run{i}", precision, compiled=False)
        with Dist(mixed_precision=precision, cpu=True) as dist:
            trainer = Trainer(cfg, dist)
            assert trainer.model_config.num_layers == 8 and trainer.model_config.cond_dim == 512
            losses.append(suite.probe_loss(trainer))
    fp32, fp32_again, bf16 = losses
    assert math.isfinite(fp32) and fp32 == fp32_again
    figure = suite.equal_loss_figure(fp32, bf16, "bf16")
    assert 0.0 < figure["value"] < suite.EQUAL_LOSS_RTOL and figure["within_tolerance"]


def test_evaluator_bench_counts_the_generators_passes_and_estimates_a_single_editing_pass_once():
    """bench_eval before/after issue 26 at a tiny size: per replication the generator's forward calls per phase;
    with tasks.editing_passes=single the editing calls happen in the first replication only, and the protocol's
    estimate counts them once where per_replication counts them in every replication."""
    bench_eval = load_suite().bench_eval
    base = bench_eval.EvalBenchSettings(items=8, protocol="full", replications=1, steps=2, batch_size=8,
                                        model_preset="tiny", editing=("prediction",), flame=False,
                                        multimodality=False, device="cpu")
    before = bench_eval.run_evaluation_bench(base)
    after = bench_eval.run_evaluation_bench(dataclasses.replace(base, replications=2, editing_passes="single",
                                                                editing_samples=8, precision="bf16"))
    edit_steps = 30  # the paper's edit settings: 30 Euler steps at guidance 1 (one pass of B per step)
    assert before["per_replication"][0]["model_calls"] == {"generation": 2, "editing": edit_steps}
    assert [r["model_calls"] for r in after["per_replication"]] == [{"generation": 2, "editing": edit_steps},
                                                                    {"generation": 2}]
    assert after["per_replication"][0]["model_rows"] == {"generation": 2 * 16, "editing": edit_steps * 8}
    assert (after["precision"], after["editing_passes"], after["single_pass_edits"]) == ("bf16", "single", 8)
    replications = before["protocol_estimate"]["replications"]  # the full protocol's 20
    assert before["protocol_estimate"]["model_calls_per_replication"] == 2 + edit_steps
    assert after["protocol_estimate"]["model_calls_per_replication"] == pytest.approx(
        (replications * 2 + edit_steps) / replications, abs=0.1)
    with pytest.raises(ValueError, match="with and without the editing tasks"):
        bench_eval.run_evaluation_bench(dataclasses.replace(base, editing_passes="single"))


def test_train_step_profiler_times_both_step_syncs_and_writes_its_tables(tmp_path, capsys):
    """benchmarks/profile_train_step.py at the tiny preset on CPU (kept from rotting: its H200 figures are in
    docs/performance.md): one record per batch size, the step streamed with both train.step_sync modes, the
    profile's table written."""
    module = load_benchmark("profile_train_step")
    module.main(["--synthetic", "40", "--config", "tiny", "--batch-sizes", "4", "--window", "24", "--steps", "2",
                 "--warmup", "1", "--profile-steps", "1", "--out", str(tmp_path)])
    (record,) = [json.loads(line) for line in (tmp_path / "results.jsonl").read_text().splitlines()]
    assert record["batch_size"] == 4 and record["step_ms"] > 0
    assert record["streamed_ms_deferred"] > 0 and record["streamed_ms_every_step"] > 0
    assert record["device_busy"] is None  # a CPU has no device kernels to sum
    assert "aten::" in (tmp_path / "profile_b4.txt").read_text()


@pytest.mark.parametrize("counts", [["--profile-steps", "0"], ["--steps", "1"]])
def test_train_step_profiler_refuses_counts_its_figures_divide_by(tmp_path, capsys, counts):
    """--profile-steps 0 used to run every timed step and then fail dividing by it; now refused before any work."""
    module = load_benchmark("profile_train_step")
    with pytest.raises(SystemExit) as exit_info:
        module.main(["--synthetic", "40", "--config", "tiny", *counts, "--out", str(tmp_path / "out")])
    assert exit_info.value.code == 2
    assert "--profile-steps must be at least 1" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
