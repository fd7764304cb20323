"""Self-conditioning (ModelConfig.self_condition_prob, Chen et al. 2022): the model's estimate input, the training
pass that feeds it the network's own x̂1, and the sampler's wrapper that feeds it the previous evaluation's."""

import dataclasses
import logging
import shutil

import pytest
import torch

from mfm.composition import BoundInputs, bind_inputs
from mfm.flow import (
    FlowMatchingObjective,
    flow_matching_loss,
    interpolate,
    masked_mse,
    sample_noise,
    sample_time,
    self_condition_estimate,
    target_velocity,
)
from mfm.model import ModelConfig, MotionFlowTransformer, valid_frame_mask
from mfm.path import data_from_velocity, velocity_from_data
from mfm.solvers import guided_velocity, solve

CONFIG = ModelConfig(feature_dim=263, latent_dim=16, ff_dim=32, num_layers=1, num_heads=2, cond_dim=4, dropout=0.0,
                     cond_drop_prob=0.0, prediction="data")


def model_with(seed: int = 0, **overrides) -> MotionFlowTransformer:
    torch.manual_seed(seed)
    return MotionFlowTransformer(dataclasses.replace(CONFIG, **overrides)).eval()


def used_estimate(model: MotionFlowTransformer) -> MotionFlowTransformer:
    """``model`` with a non-zero estimate projection, so that its output depends on the estimate."""
    with torch.no_grad():
        model.self_condition_proj.weight.normal_(0, 0.3, generator=torch.Generator().manual_seed(1))
    return model


def train_tiny(manifest, out, *overrides: str) -> dict:
    """``launch/train.py --config tiny`` on ``manifest`` into ``out``, logging every step and keeping every
    checkpoint; its metrics.jsonl records by step."""
    from test_trainer import metrics_by_step, train_entry

    assert train_entry.main(["--config", "tiny", f"data.manifest={manifest}", f"train.out_dir={out}",
                             "train.log_every=1", "train.keep_last=0", *overrides]) == 0
    return metrics_by_step(out)


class Recording:
    """A model stand-in that records each call's inputs and returns a fixed function of x."""

    def __init__(self, config: ModelConfig | None = None) -> None:
        self.config = config or dataclasses.replace(CONFIG, self_condition_prob=0.5)
        self.calls: list[dict] = []

    def __call__(self, x, t, cond, lengths=None, *, cond_mask=None, generator=None, self_condition=None, **kwargs):
        self.calls.append(dict(x=x.clone(), t=torch.as_tensor(t).clone(), cond_mask=cond_mask,
                               self_condition=None if self_condition is None else self_condition.clone(), **kwargs))
        return 0.5 * x + 0.1


def test_data_from_velocity_inverts_velocity_from_data():
    x_t, x1_hat = torch.randn(3, 7, 5), torch.randn(3, 7, 5)
    t = torch.tensor([0.0, 0.5, 0.99])  # 0.99: beyond the floor of the noise scale, still exact
    assert torch.allclose(data_from_velocity(velocity_from_data(x1_hat, x_t, t), x_t, t), x1_hat, atol=1e-5)
    assert torch.allclose(data_from_velocity(velocity_from_data(x1_hat, x_t, torch.tensor(0.3)), x_t,
                                             torch.tensor(0.3)), x1_hat, atol=1e-5)


def test_the_estimate_input_starts_at_zero_and_leaves_the_other_weights_as_they_were():
    plain, conditioned = model_with(0), model_with(0, self_condition_prob=0.5)
    x, t, cond, lengths = torch.randn(2, 9, 263), torch.tensor([0.2, 0.7]), torch.randn(2, 4), torch.tensor([9, 5])
    expected = plain(x, t, cond, lengths)
    assert torch.equal(conditioned(x, t, cond, lengths), expected)  # same initialisation, the projection is zero
    assert torch.equal(conditioned(x, t, cond, lengths, self_condition=torch.randn_like(x)), expected)
    used_estimate(conditioned)
    estimate = torch.randn_like(x)
    assert not torch.allclose(conditioned(x, t, cond, lengths, self_condition=estimate), expected)
    assert torch.equal(conditioned(x, t, cond, lengths),
                       conditioned(x, t, cond, lengths, self_condition=torch.zeros_like(x)))  # None = zeros
    changed = estimate.clone()
    changed[1, 5:] += 10.0  # padded frames of motion 1: never reach a valid frame
    assert torch.allclose(conditioned(x, t, cond, lengths, self_condition=estimate),
                          conditioned(x, t, cond, lengths, self_condition=changed), atol=1e-6)


def test_the_estimate_input_is_refused_where_it_does_not_apply():
    x, t, cond = torch.randn(2, 9, 263), torch.tensor([0.2, 0.7]), torch.randn(2, 4)
    with pytest.raises(ValueError, match="self_condition is an input of self-conditioned models only"):
        model_with(0)(x, t, cond, self_condition=torch.zeros_like(x))
    with pytest.raises(ValueError, match="self_condition must have"):
        model_with(0, self_condition_prob=0.5)(x, t, cond, self_condition=torch.zeros(2, 8, 263))
    for bad in (-0.1, 1.5):
        with pytest.raises(ValueError, match="self_condition_prob must be in"):
            dataclasses.replace(CONFIG, self_condition_prob=bad)
    with pytest.raises(ValueError, match="shortcut"):
        dataclasses.replace(CONFIG, self_condition_prob=0.5, shortcut_levels=2)
    with pytest.raises(ValueError, match="self_condition_prob"):
        FlowMatchingObjective(self_condition_prob=2.0)


def test_the_training_estimate_is_the_chosen_rows_gradient_free_x1_and_zeros_elsewhere():
    model = used_estimate(model_with(0, self_condition_prob=0.5))
    x_t, t, cond = torch.randn(4, 9, 263), torch.tensor([0.1, 0.4, 0.6, 0.9]), torch.randn(4, 4)
    lengths, keep = torch.tensor([9, 6, 9, 3]), torch.tensor([False, True, False, False])
    chosen = torch.tensor([True, False, True, True])
    tokens = {"positional_mode": None}  # a non-tensor input passes through unchanged
    estimate = self_condition_estimate(model, x_t, t, cond, lengths, keep, chosen, tokens)
    assert not estimate.requires_grad
    assert torch.equal(estimate[1], torch.zeros(9, 263))
    rows = torch.tensor([0, 2, 3])
    alone = model(x_t[rows], t[rows], cond[rows], lengths[rows], cond_mask=keep[rows])
    assert torch.allclose(estimate[rows], data_from_velocity(alone, x_t[rows], t[rows]), atol=1e-6)
    assert torch.equal(self_condition_estimate(model, x_t, t, cond, lengths, keep, torch.zeros(4, dtype=torch.bool),
                                               {}), torch.zeros_like(x_t))
    with pytest.raises(ValueError, match="cond_mask"):
        self_condition_estimate(model, x_t, t, cond, lengths, None, chosen, {})
    # No row chosen: one row still runs (and is discarded), so every data-parallel rank makes the same model calls
    recording = Recording()
    self_condition_estimate(recording, x_t, t, cond, lengths, keep, torch.zeros(4, dtype=torch.bool),
                            {"text_tokens": torch.randn(4, 3, 8), "block_drop_mask": torch.zeros(1, 2, dtype=torch.bool)})
    assert len(recording.calls) == 1 and recording.calls[0]["x"].shape == (1, 9, 263)
    assert recording.calls[0]["text_tokens"].shape == (1, 3, 8)  # per-sample inputs sliced with the rows
    assert recording.calls[0]["block_drop_mask"].shape == (1, 2)  # per-pass inputs as they are


def test_the_loss_trains_the_second_pass_on_the_estimate_and_draws_the_rows_after_the_noise():
    """p = 1: every row's trained pass sees the first pass's x̂1; the rows are drawn after t and x0 from the same
    generator; p = 0 draws nothing more (a run without the option keeps its random stream)."""
    model = used_estimate(model_with(0, self_condition_prob=1.0))
    x1, cond, lengths = torch.randn(3, 9, 263), torch.randn(3, 4), torch.tensor([9, 7, 4])
    keep = torch.zeros(3, dtype=torch.bool)
    drawn_here = torch.Generator().manual_seed(3)
    loss, _ = flow_matching_loss(model, x1, cond, lengths, generator=drawn_here, cond_mask=keep,
                                 self_condition_prob=1.0)
    replay = torch.Generator().manual_seed(3)
    t, x0 = sample_time(3, replay), sample_noise(x1, replay)
    torch.rand(3, generator=replay)  # the self-conditioned rows' draw
    assert torch.equal(drawn_here.get_state(), replay.get_state())
    x_t = interpolate(x0, x1, t)
    first = model(x_t, t, cond, lengths, cond_mask=keep)
    second = model(x_t, t, cond, lengths, cond_mask=keep, self_condition=data_from_velocity(first, x_t, t))
    expected = masked_mse(second, target_velocity(x0, x1), valid_frame_mask(lengths, 9))
    assert loss.item() == pytest.approx(expected.item(), rel=1e-5)
    assert loss.item() != pytest.approx(masked_mse(first, target_velocity(x0, x1),
                                                   valid_frame_mask(lengths, 9)).item(), rel=1e-4)
    without, with_zero = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    flow_matching_loss(model, x1, cond, lengths, generator=without, cond_mask=keep)
    flow_matching_loss(model, x1, cond, lengths, generator=with_zero, cond_mask=keep, self_condition_prob=0.0)
    assert torch.equal(without.get_state(), with_zero.get_state())
    # the gradient flows through the second pass only
    loss, _ = FlowMatchingObjective(self_condition_prob=1.0).loss(model, x1, cond, lengths, cond_mask=keep,
                                                                  generator=torch.Generator().manual_seed(3))
    loss.backward()
    assert model.self_condition_proj.weight.grad.abs().sum() > 0


def test_the_sampler_feeds_each_row_its_previous_estimate_and_starts_every_solve_from_zeros():
    recording = Recording()
    bound = bind_inputs(recording)  # no extras: still bound, for the estimate
    assert isinstance(bound, BoundInputs)
    cond, lengths = torch.randn(2, 4), torch.tensor([6, 6])
    velocity = guided_velocity(bound, cond, scale=2.5, lengths=lengths)  # one batched pass of both halves
    x0 = torch.randn(2, 6, 263)
    solve(velocity, x0, solver="euler", steps=3)
    assert [c["self_condition"] is None for c in recording.calls] == [True, False, False]
    for before, after in zip(recording.calls, recording.calls[1:]):
        times = before["t"].float().reshape(-1).expand(before["x"].shape[0])
        expected = data_from_velocity(0.5 * before["x"] + 0.1, before["x"], times)
        assert after["self_condition"].shape == (4, 6, 263)  # each half its own estimate
        assert torch.allclose(after["self_condition"], expected, atol=1e-6)
    solve(velocity, x0, solver="euler", steps=3)  # a new solve starts from no estimate
    assert recording.calls[3]["self_condition"] is None
    solve(velocity, x0, solver="heun", steps=2)  # times 0, 0.5, 0.5, 1: a stage at the same time keeps it
    heun = recording.calls[6:]
    assert [float(c["t"].max()) for c in heun] == [0.0, 0.5, 0.5, 1.0]
    assert heun[0]["self_condition"] is None and all(c["self_condition"] is not None for c in heun[1:])
    plain = Recording(dataclasses.replace(CONFIG))
    assert bind_inputs(plain) is plain
    bound_plain = BoundInputs(plain, {"text_token_len": torch.tensor([1, 1])})
    bound_plain(torch.randn(2, 6, 263), torch.tensor([0.1, 0.1]), cond)
    assert "self_condition" not in plain.calls[0] or plain.calls[0]["self_condition"] is None


def test_self_conditioning_is_a_flow_objective_option_that_build_objective_passes_on():
    from types import SimpleNamespace

    from pipeline.config import ConfigError, TrainConfig, load_config
    from pipeline.training.trainer import build_objective

    manifest = SimpleNamespace(data={"feature_spec": {"skeleton": "humanml3d"},
                                     "normalization": {"mean": [0.0] * 263, "std": [1.0] * 263}})
    objective = build_objective(load_config(TrainConfig, "tiny", ["model.self_condition_prob=0.5"]), manifest)
    assert objective.self_condition_prob == 0.5
    assert build_objective(load_config(TrainConfig, "tiny"), manifest).self_condition_prob == 0.0
    with pytest.raises(ConfigError, match="self_condition_prob"):
        load_config(TrainConfig, "tiny", ["model.self_condition_prob=0.5", "train.objective=diffusion"])
    with pytest.raises(ConfigError, match="needs model.self_condition_prob > 0"):
        load_config(TrainConfig, "tiny", ["train.self_condition_start_step=2"])
    with pytest.raises(ConfigError, match="self_condition_start_step must be in"):
        load_config(TrainConfig, "tiny", ["model.self_condition_prob=0.5", "train.self_condition_start_step=-1"])
    late = load_config(TrainConfig, "tiny", ["model.self_condition_prob=0.5", "train.self_condition_start_step=2"])
    assert build_objective(late, manifest, self_conditioning=False).self_condition_prob == 0.0


@pytest.mark.slow
@pytest.mark.usefixtures("single_thread")
def test_self_conditioned_training_resumes_exactly_and_samples(tmp_path_factory, tmp_path):
    """The self-conditioned rows come from the trainer's per-rank generator (saved in the checkpoint), so a run
    resumed half-way logs the same losses as one run straight through; they differ from a run without the option;
    the checkpoint samples through launch/sample.py."""
    from test_trainer import build_dataset_once

    from pipeline.generation.inference import load_trained_model

    manifest = build_dataset_once(tmp_path_factory)

    def run(out, steps, *extra):
        metrics = train_tiny(manifest, out, f"train.max_steps={steps}", "train.save_every=2", *extra)
        return {step: record["loss"] for step, record in metrics.items()}

    straight = run(tmp_path / "straight", 4, "model.self_condition_prob=0.5")
    run(tmp_path / "resumed", 2, "model.self_condition_prob=0.5")
    assert run(tmp_path / "resumed", 4, "model.self_condition_prob=0.5") == straight
    assert run(tmp_path / "plain", 4) != straight
    trained = load_trained_model(tmp_path / "straight")
    assert trained.model_config.self_condition_prob == 0.5
    assert trained.model.self_condition_proj.weight.abs().sum() > 0  # trained: the estimate reaches the network


@pytest.mark.slow
@pytest.mark.usefixtures("single_thread")
def test_a_late_start_leaves_the_run_before_it_unchanged(tmp_path_factory, tmp_path, caplog):
    """train.self_condition_start_step=2: the estimate projection has no bias, so until the estimate pass starts
    the self-conditioned model adds exactly zero and the run is the run without the option, bit for bit (losses,
    gradient norms, weights, EMA); from step 3 the estimate pass runs and the estimate's weights train. A run
    resumed at the start step (its optimizer has no state for the estimate's weights yet) logs the same losses."""
    from test_trainer import assert_identical, build_dataset_once

    from pipeline import checkpoint as ckpt

    manifest = build_dataset_once(tmp_path_factory)
    late_start = ["model.self_condition_prob=0.5", "train.self_condition_start_step=2"]

    def run(out, *extra):
        metrics = train_tiny(manifest, out, "train.max_steps=3", "train.save_every=1", *extra)
        return {step: (record["loss"], record["grad_norm"]) for step, record in metrics.items()}

    plain = run(tmp_path / "plain")
    late = run(tmp_path / "late", *late_start)
    assert [late[s] for s in (1, 2)] == [plain[s] for s in (1, 2)]
    resumed = tmp_path / "resumed"  # the late run with its last checkpoint lost: it resumes from step 2
    shutil.copytree(tmp_path / "late", resumed)
    shutil.rmtree(ckpt.checkpoints_dir(resumed) / ckpt.step_dir_name(3))
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="pipeline.distributed"):
        assert run(resumed, *late_start) == late
    assert "resumed from" in caplog.text and "at step 2" in caplog.text, caplog.text
    step_2 = ckpt.step_dir_name(2)
    plain_model, plain_ema, _ = ckpt.load_checkpoint(ckpt.checkpoints_dir(tmp_path / "plain") / step_2)
    late_model, late_ema, _ = ckpt.load_checkpoint(ckpt.checkpoints_dir(tmp_path / "late") / step_2)
    for name, estimate_weights in (("model", late_model), ("ema", late_ema)):
        assert not estimate_weights.pop("self_condition_proj.weight").any(), f"{name}: trained before its start"
    assert_identical(plain_model, late_model, "model")
    assert_identical(plain_ema, late_ema, "ema")
    assert late[3] != plain[3]
    late_model_3, _, _ = ckpt.load_checkpoint(ckpt.checkpoints_dir(tmp_path / "late") / ckpt.step_dir_name(3))
    assert late_model_3["self_condition_proj.weight"].abs().sum() > 0
