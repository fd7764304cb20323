"""Compiled sampling (issue 26): ``compile: auto | true | false`` of launch/sample.py, MotionPipeline and the
evaluator, one rule with training's ``train.compile`` (mfm.compilation). ``torch.compile`` is replaced by a
recording identity wrapper (tests/conftest.py ``compile_calls``): inductor takes minutes on a CPU, and what is tested
here is when the model is compiled, in which mode, how often, that the compiled model is the one sampled, and what
is recorded; not inductor itself."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_sample_cli import features_of, sample, sample_entry, text_run  # noqa: F401 (text_run: a fixture)

from mfm.compilation import compiled_for_sampling, compiles, sampling_compile_mode

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("single_thread")]

ARGS = ("--text", "a person walks", "--num-samples", "3", "--batch-size", "1", "--length", "20", "--seed", "3",
        "--no-video", "--no-bvh")


def test_one_rule_for_training_and_sampling_and_cuda_graphs_on_cuda(compile_calls):
    import benchmarks.bench_sampling as bench
    from pipeline.training import trainer

    assert trainer.compiles is compiles and bench.compiled_for_sampling is compiled_for_sampling  # no copies
    assert compiles("auto", torch.device("cuda")) and not compiles("auto", torch.device("cpu"))
    assert compiles(True, "cpu") and not compiles(False, "cuda:0")
    assert sampling_compile_mode(torch.device("cuda")) == "reduce-overhead" == sampling_compile_mode("cuda:1")
    assert sampling_compile_mode(torch.device("cpu")) == "default"
    held = torch.ones(3)  # a CUDA graph's output: memory its next replay writes over

    class GraphOutput(torch.nn.Module):
        def forward(self) -> torch.Tensor:
            return held

    graphed = compiled_for_sampling(GraphOutput(), torch.device("cuda"))
    assert [c.mode for c in compile_calls] == ["reduce-overhead"]
    out = graphed()
    assert torch.equal(out, held) and out.data_ptr() != held.data_ptr()  # the caller gets its own copy
    # The wrapper is in the wrapped model's mode (a fresh Module is in training mode: the samplers then warned that
    # dropout makes the network random, on every call on a GPU)
    assert graphed.training and not compiled_for_sampling(GraphOutput().eval(), "cuda").training
    assert not isinstance(compiled_for_sampling(torch.nn.Module(), "cpu"), type(graphed))  # no copy off CUDA
    for bad in ("maybe", "true", 1, None):
        with pytest.raises(ValueError, match="compile must be auto, true or false"):
            compiles(bad, "cpu")


def test_sample_compiles_once_per_run_when_asked_and_records_it(text_run, tmp_path, compile_calls, capsys):  # noqa: F811
    default = sample(text_run, tmp_path / "auto", *ARGS)
    assert compile_calls == [] and (default["compiled"], default["compile_setting"]) == (False, "auto")
    off = sample(text_run, tmp_path / "off", *ARGS, "--compile", "false")
    assert compile_calls == [] and (off["compiled"], off["compile_setting"]) == (False, False)
    on = sample(text_run, tmp_path / "on", *ARGS, "--compile", "true")
    (compiled,) = compile_calls  # once for the run's three batches
    assert compiled.mode == "default" and (on["compiled"], on["compile_setting"]) == (True, True)
    assert compiled.calls == sum(on["nfe_per_batch"]) and len(on["nfe_per_batch"]) == 3  # every pass went through it
    for a, b in zip(features_of(tmp_path / "off", off), features_of(tmp_path / "on", on)):
        np.testing.assert_array_equal(a, b)
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_code:  # argparse's usage error: exit 2
        sample_entry.main(["--checkpoint", str(text_run), "--out", str(tmp_path / "x"), "--text", "x",
                           "--compile", "maybe"])
    assert exit_code.value.code == 2
    assert "--compile: auto, true or false, got 'maybe'" in capsys.readouterr().err
    assert sample_entry.main(["--checkpoint", str(text_run), "--out", str(tmp_path / "x"), "--text", "x",
                              "compile=maybe"]) == 2
    assert capsys.readouterr().err == "error: SampleRequest: compile must be auto, true or false, got 'maybe'\n"


def test_motion_pipeline_compiles_once_and_again_after_to(text_run, compile_calls):  # noqa: F811
    from pipeline.generation.pretrained import MotionPipeline

    plain = MotionPipeline.from_pretrained(text_run, device="cpu")  # auto on a CPU: not compiled
    assert compile_calls == [] and not plain.trained.is_compiled
    pipe = MotionPipeline.from_pretrained(text_run, device="cpu", compile=True)
    first = pipe("a person walks", lengths=20, seed=3)
    second = pipe("a person jumps", lengths=24, seed=4)
    (compiled,) = compile_calls
    assert compiled.mode == "default" and compiled.calls == 20  # 10 Euler steps per call, one compiled model
    np.testing.assert_array_equal(first.features[0], plain("a person walks", lengths=20, seed=3).features[0])
    assert second.lengths == [24]
    pipe.to("cpu")  # a moved model is compiled again, for its device
    assert len(compile_calls) == 2 and pipe.trained.is_compiled
    with pytest.raises(ValueError, match="compile must be auto, true or false"):
        MotionPipeline.from_pretrained(text_run, device="cpu", compile="yes")
