"""Shortcut models (mfm/shortcut.py; launch/distill.py distill.method=shortcut): the step-size input starts as the
flow model it is initialised from, the sampler's step sizes, the self-consistency target against a hand-computed
pair of half steps, that the objective learns a one-step map the flow field's one Euler step does not have, and the
student end to end: made by launch/distill.py from a tiny teacher, sampled by launch/sample.py and the evaluator at
1 and 2 evaluations with its refusals, and resumed bit-exactly after SIGKILL."""

from __future__ import annotations

import json
import subprocess
import sys
from concurrent.futures import Future
from functools import partial
from pathlib import Path

import pytest
import torch
import yaml
from conftest import REPO_ROOT, load_launch_script, selected_tests, start_two_at_a_time
from eval_worker import SMALL_PROTOCOL, random_contrastive_evaluator
from test_distill import teacher_run  # noqa: F401  (the session's tiny teacher, shared with test_distill.py)
from test_trainer import (
    assert_runs_identical,
    base_overrides,
    build_dataset_once,
    clean_env,
    kill_and_resume,
    output_of,
)

from mfm.composition import BoundInputs
from mfm.flow import FlowMatchingObjective
from mfm.guidance import classifier_free_guidance
from mfm.model import ModelConfig, MotionFlowTransformer
from mfm.shortcut import ShortcutObjective, sampler_step_size
from mfm.solvers import guided_velocity, solve
from pipeline import checkpoint as ckpt
from preprocess.processing import single_threaded_torch

distill_entry = load_launch_script("distill")
sample_entry = load_launch_script("sample")


def small_config(levels: int, **overrides) -> ModelConfig:
    return ModelConfig(feature_dim=8, latent_dim=32, ff_dim=64, num_layers=2, num_heads=2, dropout=0.0, cond_dim=4,
                       max_frames=16, shortcut_levels=levels, **overrides)


def test_a_shortcut_model_starts_as_the_flow_model_it_is_initialised_from():
    """Its step-size embedding's last layer starts at zero: with a flow model's weights it returns that model's
    velocity at every step size. A flow model refuses a step size."""
    torch.manual_seed(0)
    flow = MotionFlowTransformer(small_config(0)).eval()
    shortcut = MotionFlowTransformer(small_config(2)).eval()
    missing, unexpected = shortcut.load_state_dict(flow.state_dict(), strict=False)
    assert not unexpected and missing and all(k.startswith("step_size_embedding.") for k in missing)
    x, t, cond = torch.randn(3, 10, 8), torch.rand(3), torch.randn(3, 4)
    with torch.no_grad():
        expected = flow(x, t, cond)
        for d in (0.0, 0.5, 1.0, torch.tensor([1.0, 0.5, 0.0])):
            torch.testing.assert_close(shortcut(x, t, cond, step_size=d), expected, rtol=0, atol=0)
        torch.nn.init.normal_(shortcut.step_size_embedding.mlp[-1].weight)
        assert not torch.allclose(shortcut(x, t, cond, step_size=1.0), expected)
        torch.testing.assert_close(shortcut(x, t, cond, step_size=1.0), shortcut(x, t, cond, step_size=[1.0] * 3))
    with pytest.raises(ValueError, match="shortcut models only"):
        flow(x, t, cond, step_size=0.5)


def test_the_sampler_gives_each_step_count_its_trained_step_size():
    assert sampler_step_size(0, "euler", 2) is None
    assert [sampler_step_size(2, "euler", n) for n in (1, 2, 4, 10)] == [1.0, 0.5, 0.0, 0.0]
    assert sampler_step_size(3, "euler", 4) == 0.25
    assert sampler_step_size(2, "midpoint", 1) == 0.0  # other solvers integrate the flow field
    with pytest.raises(ValueError, match="1, 2, 4 steps .* or in 8 or more"):
        sampler_step_size(3, "euler", 3)


def test_the_self_consistency_target_is_two_half_steps_of_the_level_below():
    """A coarse row's target is the mean velocity of two conditional Euler steps of d/2 at step size d/2; the finest
    level's, two steps on the flow field (step size 0) guided at the objective's scale on its channels."""
    torch.manual_seed(1)
    model = MotionFlowTransformer(small_config(2, cond_drop_prob=0.1)).eval()
    torch.nn.init.normal_(model.step_size_embedding.mlp[-1].weight, std=0.5)  # the levels differ from the field
    channels = torch.zeros(8, dtype=torch.bool)
    channels[:3] = True
    objective = ShortcutObjective(flow=FlowMatchingObjective(), levels=2, guidance=2.5, conditional_channels=channels)
    x, cond, lengths = torch.randn(2, 10, 8), torch.randn(2, 4), torch.tensor([10, 7])
    t, d, level = torch.tensor([0.0, 0.5]), torch.tensor([1.0, 0.5]), torch.tensor([0, 1])
    target = objective.two_half_steps(model, x, t, d, level, cond, lengths, {})

    def two_steps(row: int, field) -> torch.Tensor:
        xr, tr, half = x[row:row + 1], t[row:row + 1], float(d[row]) / 2
        first = field(xr, tr)
        second = field(xr + half * first, tr + half)
        return (first + second) / 2

    keep = torch.zeros(1, dtype=torch.bool)
    with torch.no_grad():
        coarse = two_steps(0, lambda xr, tr: model(xr, tr, cond[:1], lengths[:1], cond_mask=keep, step_size=0.5))
        flow_field = BoundInputs(model, {}, step_size=0.0)
        fine = two_steps(1, classifier_free_guidance(flow_field, cond[1:], scale=2.5, lengths=lengths[1:],
                                                     conditional_channels=channels))
    torch.testing.assert_close(target[:1], coarse, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(target[1:], fine, rtol=1e-5, atol=1e-5)
    assert not torch.allclose(target[1:], two_steps(1, lambda xr, tr: model(xr, tr, cond[1:], lengths[1:],
                                                                             cond_mask=keep, step_size=0.0)))
    assert model.training is False  # the objective restores the mode it found


def test_self_consistency_learns_a_one_step_map_the_flow_fields_one_step_lacks():
    """Eight motions under one caption: the flow field's one Euler step lands on their mean, far from where its
    two-step path goes. Trained with the shortcut objective (one level), the model's one step of d = 1 lands nearer
    that two-step endpoint than the same model's one flow step. Trained on the flow loss alone it does not."""

    def train(with_self_consistency: bool) -> tuple[float, float]:
        torch.manual_seed(0)
        model = MotionFlowTransformer(small_config(1, cond_drop_prob=0.0))
        x1 = torch.randn(8, 12, 8, generator=torch.Generator().manual_seed(1))
        cond, lengths = torch.randn(1, 4).expand(8, 4).contiguous(), torch.full((8,), 12)
        objective = ShortcutObjective(flow=FlowMatchingObjective(), levels=1, bootstrap_fraction=0.5)
        optimizer = torch.optim.Adam(model.parameters(), lr=2e-3)
        generator = torch.Generator().manual_seed(0)
        for _ in range(250):
            if with_self_consistency:
                loss, _ = objective.loss(model, x1, cond, lengths, generator=generator)
            else:
                loss, _ = objective.flow.loss(model, x1, cond, lengths, generator=generator)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        model.eval()
        x0 = torch.randn(64, 12, 8, generator=torch.Generator().manual_seed(5))
        cond64 = cond[:1].expand(64, 4)
        with torch.no_grad():
            def endpoint(step_size: float, steps: int) -> torch.Tensor:
                velocity = guided_velocity(BoundInputs(model, {}, step_size=step_size), cond64, scale=1.0)
                return solve(velocity, x0, solver="euler", steps=steps).x1
            two = endpoint(0.0, 2)
            return (float((endpoint(1.0, 1) - two).square().mean()), float((endpoint(0.0, 1) - two).square().mean()))

    with single_threaded_torch():
        shortcut_error, flow_error = train(True)
        untrained_error, untrained_flow_error = train(False)
    # measured: 0.027 against 0.054; the flow loss alone: 0.119 against 0.120
    assert shortcut_error < 0.75 * flow_error, (shortcut_error, flow_error)
    assert untrained_error > 0.9 * untrained_flow_error, (untrained_error, untrained_flow_error)


# -- the student end to end ------------------------------------------------------------------------------------

SHORTCUT = ("distill.method=shortcut", "distill.shortcut_levels=2")


@pytest.fixture(scope="module")
def shortcut_run(tmp_path_factory, teacher_run) -> Path:  # noqa: F811
    run = tmp_path_factory.mktemp("shortcut") / "student"
    with single_threaded_torch():
        assert distill_entry.main(["--teacher", str(teacher_run), "--out", str(run), *SHORTCUT, "train.max_steps=6",
                                   "train.save_every=6", "train.log_every=6"]) == 0
    return run


@pytest.mark.slow
def test_the_shortcut_student_samples_in_its_levels_and_refuses_what_it_cannot(shortcut_run, teacher_run,  # noqa: F811
                                                                               tmp_path, tmp_path_factory):
    """launch/distill.py distill.method=shortcut: no pair set, the teacher's dataset, condition dropout kept, the
    teacher's guidance built in (train.shortcut_guidance) and guidance 1 to sample; launch/sample.py samples it in 2
    (default) and 1 evaluations and records the step size; 3 steps (untrained) and guidance 2.5 at a level are refused
    (exit 2); 4 steps (the flow field) take guidance; the evaluator scores it at 1 and 2 steps."""
    config = yaml.safe_load((shortcut_run / "config.yaml").read_text())
    teacher_config = yaml.safe_load((teacher_run / "config.yaml").read_text())
    assert not (shortcut_run / "pairs").exists()
    assert config["data"]["manifest"] == teacher_config["data"]["manifest"]
    assert (config["distill"]["method"], config["model"]["shortcut_levels"], config["model"]["sampling_steps"],
            config["model"]["sampling_guidance"]) == ("shortcut", 2, 2, 1.0)
    assert config["model"]["cond_drop_prob"] == teacher_config["model"]["cond_drop_prob"] > 0
    assert config["train"]["shortcut_guidance"] == teacher_config["model"]["sampling_guidance"]
    assert config["distill"]["teacher_checkpoint_id"] == ckpt.checkpoint_id(
        ckpt.read_marker(ckpt.resolve_checkpoint(teacher_run)))

    def sample(name: str, *args: str) -> int:
        return sample_entry.main(["--checkpoint", str(shortcut_run), "--out", str(tmp_path / name), "--text",
                                  "a person walks", "--length", "20", "--no-video", "--no-bvh", *args])

    assert sample("two") == 0
    results = json.loads((tmp_path / "two" / "results.json").read_text())
    assert (results["steps"], results["nfe_per_batch"], results["guidance"]) == (2, [2], 1.0)
    assert results["shortcut_step_size"] == 0.5
    assert sample("one", "--steps", "1") == 0
    assert json.loads((tmp_path / "one" / "results.json").read_text())["shortcut_step_size"] == 1.0
    assert sample("three", "--steps", "3") == 2 and not (tmp_path / "three").exists()
    assert sample("guided", "--guidance", "2.5") == 2 and not (tmp_path / "guided").exists()
    assert sample("field", "--steps", "4", "--guidance", "2.5") == 0
    assert json.loads((tmp_path / "field" / "results.json").read_text())["shortcut_step_size"] == 0.0
    # trajectory rewriting in its 2 evaluations (the known part rewritten at the first step), and at the edit
    # settings' 30 steps on its flow field
    source = str(tmp_path / "two" / "sample_000" / "features.npy")
    assert sample("edit", "--edit", "inbetween", "--source-motion", source, "--steps", "2", "--guidance", "1",
                  "--rewrite-until", "0.5") == 0
    edited = json.loads((tmp_path / "edit" / "results.json").read_text())
    assert (edited["nfe_per_batch"], edited["shortcut_step_size"]) == ([2], 0.5)
    assert sample("edit30", "--edit", "inbetween", "--source-motion", source) == 0
    assert json.loads((tmp_path / "edit30" / "results.json").read_text())["shortcut_step_size"] == 0.0

    from launch.evaluate import main as evaluate

    dataset = build_dataset_once(tmp_path_factory)
    evaluator = random_contrastive_evaluator(dataset, tmp_path / "evaluator.safetensors")
    assert evaluate(["--checkpoint", str(shortcut_run), "--protocol", "fast", *SMALL_PROTOCOL, "--steps", "1,2",
                     "--guidance", "1", "protocol.replications=1", "tasks.editing=[]", "protocol.multimodality=false",
                     f"evaluator.path={evaluator}", f"output.dir={tmp_path / 'eval'}"]) == 0
    rows = [json.loads(line) for line in (tmp_path / "eval" / "results.jsonl").read_text().splitlines()]
    assert sorted((r["steps"], r["nfe"]) for r in rows if r.get("row_kind") == "generated") == [(1, 1), (2, 2)]
    assert evaluate(["--checkpoint", str(shortcut_run), "--protocol", "fast", *SMALL_PROTOCOL, "--steps", "2",
                     "protocol.replications=1", "tasks.editing=[]", "protocol.multimodality=false",
                     f"evaluator.path={evaluator}", f"output.dir={tmp_path / 'guided-eval'}"]) == 2


@pytest.fixture(scope="module")
def shortcut_launches(teacher_run, tmp_path_factory, request) -> dict[str, tuple[Path, Future]]:  # noqa: F811
    """The launches of the two slow training tests below, started together (start_two_at_a_time), each when its
    test runs: a shortcut run killed and resumed beside an uninterrupted one (kill_and_resume), and a shortcut
    student under torchrun. Per launch its folder and its result; kill_and_resume's checks fail where it is read."""
    root = tmp_path_factory.mktemp("shortcut-launches")
    wanted = selected_tests(request)
    launches = {}
    if "test_shortcut_training_resumes_bit_exactly" in wanted:
        extra = (f"train.init_from={teacher_run}", "model.shortcut_levels=2", "train.shortcut_guidance=2.5",
                 "train.shortcut_fraction=0.5", "train.max_steps=6", "train.save_every=2", "train.keep_last=2")
        launches["resume"] = partial(kill_and_resume, build_dataset_once(tmp_path_factory), root / "resume",
                                     base_overrides, extra, 5, 4)
    if "test_a_shortcut_student_trains_on_two_ranks" in wanted:
        launches["two_ranks"] = partial(
            subprocess.run, [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                             str(REPO_ROOT / "launch" / "distill.py"), "--teacher", str(teacher_run), "--out",
                             str(root / "two_ranks"), *SHORTCUT, "train.max_steps=2", "train.save_every=2"],
            cwd=REPO_ROOT, env=clean_env(), capture_output=True, text=True, timeout=300)
    started = start_two_at_a_time(launches)
    return {name: (root / name, future) for name, future in started.items()}


@pytest.mark.slow
def test_shortcut_training_resumes_bit_exactly(shortcut_launches):
    """A shortcut run (initialised from the teacher, self-consistency rows with guided targets) SIGKILLed in the
    middle of step 5 and resumed from checkpoint 4 ends bit-identical to an uninterrupted one."""
    a_out, b_out = shortcut_launches["resume"][1].result()
    assert_runs_identical(a_out / "run", b_out / "run", 6)


def test_composition_gives_a_shortcut_model_its_step_size():
    """mfm.composition.compose (and so launch/sample.py --compose and the evaluator's composition, which pass
    ``TrainedModel.shortcut_step_size``) hands every evaluation the step size it is given."""
    from mfm.composition import compose

    seen = []

    class Recording(MotionFlowTransformer):
        def forward(self, *args, step_size=None, **kwargs):
            seen.append(step_size)
            return super().forward(*args, step_size=step_size, **kwargs)

    model = Recording(small_config(2)).eval()
    cond = torch.randn(4)
    with torch.no_grad():
        result = compose(model, [(cond, 6), (cond, 5)], steps=2, guidance=1.0, step_size=0.5)
    assert result.nfe == 2 and seen == [0.5, 0.5]


@pytest.mark.slow
@pytest.mark.multirank
def test_a_shortcut_student_trains_on_two_ranks(shortcut_launches):
    """The objective's one pass with gradients (after the targets' passes without) is what DDP expects: under
    torchrun with 2 gloo ranks the student trains and saves."""
    out, started = shortcut_launches["two_ranks"]
    proc = started.result()
    assert proc.returncode == 0, output_of(proc)
    assert ckpt.list_complete(ckpt.checkpoints_dir(out))[-1][0] == 2


def test_the_shortcut_objective_refuses_input_perturbation_and_carries_the_root_mean_term():
    """The flow rows' loss is the flow objective's velocity loss with its terms (the root-mean term included);
    input perturbation, which the self-consistency targets do not take, is refused with the setting named."""
    with pytest.raises(ValueError, match="input_perturbation"):
        ShortcutObjective(flow=FlowMatchingObjective(input_perturbation=0.1), levels=1)
    torch.manual_seed(0)
    model = MotionFlowTransformer(small_config(1, cond_drop_prob=0.0))
    x1, cond, lengths = torch.randn(4, 12, 8), torch.randn(4, 4), torch.tensor([12, 12, 9, 6])
    plain = ShortcutObjective(flow=FlowMatchingObjective(), levels=1, bootstrap_fraction=0.5)
    with_term = ShortcutObjective(flow=FlowMatchingObjective(root_mean_weight=5.0), levels=1, bootstrap_fraction=0.5)
    losses = [objective.loss(model, x1, cond, lengths, generator=torch.Generator().manual_seed(3))[0].item()
              for objective in (plain, with_term)]
    assert losses[1] > losses[0]
