"""The critic of train.critic_weight (mfm.critic, pipeline.training.critic): what it reads, its losses, and how
the trainer trains it beside the model. Its exact resume is tests/test_trainer.py's critic-deferred case; its
data parallelism tests/test_trainer_multirank.py's critic equivalence."""

from __future__ import annotations

import pytest
import torch
from test_trainer import base_overrides, build_dataset_once
from trainer_worker import global_batches

from mfm.critic import MotionCritic, critic_hinge_loss, frame_mean, generator_hinge_loss
from mfm.flow import flow_matching_loss
from mfm.model import valid_frame_mask
from pipeline import checkpoint as ckpt
from pipeline.config import ConfigError, TrainConfig, load_config
from pipeline.distributed import Dist
from pipeline.training.trainer import Trainer


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return build_dataset_once(tmp_path_factory)


def test_padding_never_reaches_a_valid_frames_logit():
    torch.manual_seed(0)
    critic = MotionCritic(12, cond_dim=5, channels=16).eval()
    motion, cond = torch.randn(2, 40, 12), torch.randn(2, 5)
    mask = valid_frame_mask(torch.tensor([25, 40]), 40)
    other = motion.clone()
    other[0, 25:] = 100 * torch.randn(15, 12)  # only padding changes
    logits, logits_other = critic(motion, cond, mask), critic(other, cond, mask)
    assert torch.equal(logits, logits_other)
    assert (logits[0, 25:] == 0).all() and (logits[0, :25] != 0).all()
    # a change inside the valid frames does reach the logits within the receptive field (31 frames)
    other[0, 10] += 1.0
    changed = (critic(other, cond, mask)[0] != logits[0]).nonzero().squeeze(1)
    assert changed.min() >= 10 - 15 and changed.max() <= 10 + 15 and len(changed) > 1


def test_the_caption_and_the_action_enter_the_judgement():
    torch.manual_seed(0)
    mask = torch.ones(1, 20, dtype=torch.bool)
    motion = torch.randn(1, 20, 12)
    text = MotionCritic(12, cond_dim=5, channels=16).eval()
    assert not torch.allclose(text(motion, torch.randn(1, 5), mask), text(motion, torch.randn(1, 5), mask))
    action = MotionCritic(12, num_actions=3, channels=16).eval()
    assert not torch.allclose(action(motion, torch.tensor([0]), mask), action(motion, torch.tensor([2]), mask))
    with pytest.raises(ValueError, match="exactly one"):
        MotionCritic(12, cond_dim=5, num_actions=3)


def test_spectral_norm_keeps_every_layer_near_unit_gain():
    torch.manual_seed(0)
    critic = MotionCritic(12, cond_dim=5, channels=16)
    for _ in range(30):  # power iterations run in training-mode forwards
        critic(torch.randn(2, 20, 12), torch.randn(2, 5), torch.ones(2, 20, dtype=torch.bool))
    critic.eval()
    weight = critic.blocks[0].weight.reshape(16, -1)
    assert torch.linalg.matrix_norm(weight, ord=2).item() == pytest.approx(1.0, abs=0.05)


def test_hinge_losses_per_valid_frame_then_per_motion():
    mask = valid_frame_mask(torch.tensor([2, 4]), 4)
    real = torch.tensor([[2.0, 0.0, 9.0, 9.0], [0.5, 0.5, 0.5, 0.5]])
    fake = torch.tensor([[-2.0, 0.0, 9.0, 9.0], [1.0, 1.0, 1.0, 1.0]])
    # real: motion 0 (0 + 1) / 2, motion 1 0.5; fake: motion 0 (0 + 1) / 2, motion 1 2
    assert critic_hinge_loss(real, fake, mask).item() == pytest.approx((0.5 + 0.5) / 2 + (0.5 + 2.0) / 2)
    assert generator_hinge_loss(fake, mask).item() == pytest.approx(-((-2.0 + 0.0) / 2 + 1.0) / 2)
    assert frame_mean(torch.ones(2, 4), mask).item() == 1.0


def test_the_estimate_at_time_zero_is_the_one_step_motion():
    torch.manual_seed(0)
    velocity = torch.randn(2, 6, 3)

    def model(x_t, t, cond, lengths, **kwargs):
        return velocity.clone().requires_grad_()

    x1, x0 = torch.randn(2, 6, 3), torch.randn(2, 6, 3)
    _, info = flow_matching_loss(model, x1, torch.zeros(2, 4), torch.tensor([6, 4]), t=torch.zeros(2), x0=x0,
                                 cond_mask=torch.ones(2, dtype=torch.bool), estimate=True, sigma_min=0.0)
    torch.testing.assert_close(info["x1_hat"], x0 + velocity)  # one Euler step from t = 0 to 1
    assert info["x1_hat"].requires_grad and info["frame_mask"].tolist()[1] == [True] * 4 + [False] * 2
    _, plain = flow_matching_loss(model, x1, torch.zeros(2, 4), torch.tensor([6, 4]), t=torch.zeros(2), x0=x0)
    assert "x1_hat" not in plain


def critic_trainer(dataset, tmp_path, *extra: str) -> tuple[Trainer, TrainConfig]:
    cfg = load_config(TrainConfig, "tiny", base_overrides(dataset, tmp_path / "run", "model.dropout=0.0",
                                                          "train.critic_weight=0.05", *extra))
    return Trainer(cfg, Dist(mixed_precision="no")), cfg


def test_the_adversarial_term_reaches_the_model_and_the_critic_learns_apart(dataset, tmp_path):
    trainer, cfg = critic_trainer(dataset, tmp_path)
    (batch, draws), = global_batches(cfg, 1, cfg.data.batch_size)
    critic = trainer.critic.critic
    inputs: list = []
    judged = trainer._micro_batch_loss(batch, draws, critic_inputs=inputs)
    plain = trainer._micro_batch_loss(batch, draws)
    features, x1_hat, cond, mask = inputs[0]
    critic.eval()
    with torch.no_grad():
        expected = 0.05 * generator_hinge_loss(critic(x1_hat, cond, mask), mask)
    torch.testing.assert_close(judged - plain, expected)
    judged.backward()
    assert all(p.grad is None for p in critic.parameters()), "the model's loss must not train the critic"
    before = {k: v.clone() for k, v in critic.state_dict().items()}
    trainer.model.zero_grad(set_to_none=True)
    trainer.train_step([batch], [draws])
    after = critic.state_dict()
    assert any(not torch.equal(before[k], after[k]) for k in before if k.endswith("original"))
    assert all(p.grad is None for p in critic.parameters())
    assert int(next(iter(trainer.critic.optimizer.state.values()))["step"]) == 1


@pytest.mark.parametrize("step_sync", ["every_step", "deferred"])
def test_a_skipped_step_leaves_the_critic_as_it_was(dataset, tmp_path, step_sync):
    trainer, cfg = critic_trainer(dataset, tmp_path, f"train.step_sync={step_sync}")
    (batch, draws), = global_batches(cfg, 1, cfg.data.batch_size)
    batch["features"] = batch["features"].clone()
    batch["features"][0, 0, 0] = float("nan")
    before = {k: v.clone() for k, v in trainer.critic.critic.state_dict().items() if k.endswith("original")}
    results = trainer.train_step([batch], [draws]) + trainer.settle()
    assert results[-1].skipped
    after = trainer.critic.critic.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)
    assert all(p.grad is None for p in trainer.critic.critic.parameters())
    steps = [int(s["step"]) for s in trainer.critic.optimizer.state.values()]
    assert steps in ([], [0] * len(steps)), "a skipped step must not count as a critic update"


def test_a_resume_that_adds_or_drops_the_critic_is_refused(dataset, tmp_path):
    cfg = load_config(TrainConfig, "tiny", base_overrides(dataset, tmp_path / "run", "train.max_steps=1"))
    with Dist(mixed_precision="no") as dist:
        assert Trainer(cfg, dist).fit() == 0
        with_critic = load_config(TrainConfig, "tiny", base_overrides(
            dataset, tmp_path / "run", "train.max_steps=2", "train.critic_weight=0.05"))
        with pytest.raises(ckpt.ResumeSettingError, match="written without a critic") as refused:
            Trainer(with_critic, dist).fit()
    assert refused.value.setting == "train.critic_weight"


def test_a_run_trained_with_a_critic_says_so_on_its_model_card(dataset, tmp_path):
    from pipeline.generation.pretrained import export_pretrained

    cfg = load_config(TrainConfig, "tiny", base_overrides(dataset, tmp_path / "run", "train.max_steps=2",
                                                          "train.critic_weight=0.05"))
    with Dist(mixed_precision="no") as dist:
        assert Trainer(cfg, dist).fit() == 0
    card = (export_pretrained(tmp_path / "run", tmp_path / "model") / "README.md").read_text()
    assert "trained with a critic" in card and "weighted 0.05" in card


@pytest.mark.parametrize("overrides, reason", [
    (["train.mixed_precision=fp16"], "not loss-scaled"),
    (["train.objective=diffusion"], "needs train.objective=flow"),
    (["model.shortcut_levels=2"], "self-consistency rows"),
    (["train.critic_lr=0"], "critic_lr must be > 0"),
])
def test_settings_a_critic_cannot_train_with_are_refused(tmp_path, overrides, reason):
    with pytest.raises(ConfigError, match=reason):
        load_config(TrainConfig, "tiny", [f"train.out_dir={tmp_path}", "train.critic_weight=0.05", *overrides])
