"""optim.optimizer=muon: Muon on the Transformer blocks' matrices, AdamW on the rest (pipeline.training.optimizers)."""

from __future__ import annotations

import copy

import pytest
import torch
from test_trainer import base_overrides, build_dataset_once

from mfm.model import MotionFlowTransformer
from pipeline import checkpoint as ckpt
from pipeline.config import ConfigError, TrainConfig, load_config
from pipeline.data.stream import open_manifest
from pipeline.distributed import Dist
from pipeline.generation.pretrained import export_pretrained
from pipeline.training.optimizers import MuonWithAdamW, build_optimizer, muon_parameter_names
from pipeline.training.trainer import Trainer, lr_lambda, model_config_for, resolve_step_sync


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return build_dataset_once(tmp_path_factory)


def tiny_model(dataset) -> tuple[MotionFlowTransformer, TrainConfig]:
    cfg = load_config(TrainConfig, "tiny", base_overrides(dataset, dataset.parent / "unused", "optim.optimizer=muon"))
    torch.manual_seed(0)
    return MotionFlowTransformer(model_config_for(open_manifest(cfg.data.manifest), cfg.model)), cfg


def test_muon_takes_the_blocks_matrices_and_adamw_everything_else(dataset):
    model, cfg = tiny_model(dataset)
    by_muon = set(muon_parameter_names(model))
    names = dict(model.named_parameters())
    assert by_muon and all(n.startswith("layers.") and names[n].ndim == 2 for n in by_muon)
    for block in range(cfg.model.num_layers):  # attention and feed-forward of every block
        assert {f"layers.{block}.qkv.weight", f"layers.{block}.out_proj.weight", f"layers.{block}.linear1.weight",
                f"layers.{block}.linear2.weight"} <= by_muon
    left = set(names) - by_muon
    assert {"input_proj.weight", "output_proj.weight", "input_proj.bias", "cond_proj.weight"} <= left
    assert any(n.startswith("layers.") and n.endswith("norm1.weight") for n in left)
    assert not any(n.startswith("layers.") and names[n].ndim == 2 for n in left)
    optimizer = build_optimizer(model, cfg.optim, fused=False)
    assert isinstance(optimizer, MuonWithAdamW)
    assert [len(g["params"]) for g in optimizer.param_groups] == [len(left), len(by_muon)]
    assert [g["lr"] for g in optimizer.param_groups] == [cfg.optim.lr, cfg.optim.muon_lr]


def scheduled(params_muon, params_adamw, steps: int = 10):
    optimizer = MuonWithAdamW(params_muon, params_adamw, lr=1e-3, betas=(0.9, 0.99), weight_decay=0.01,
                              muon_lr=0.02, muon_momentum=0.95)
    return optimizer, torch.optim.lr_scheduler.LambdaLR(optimizer, lr_lambda(2, "cosine", steps, 0.0, 0.2))


def train(optimizer, scheduler, params, steps: int, seed: int) -> None:
    generator = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        loss = sum((p * torch.randn(p.shape, generator=generator)).sum() ** 2 for p in params)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        scheduler.step()


def test_one_optimizer_steps_as_torchs_muon_and_adamw_side_by_side():
    """The hybrid is torch.optim.Muon on its first parameters and torch.optim.AdamW on the others, each with its
    own base learning rate scaled by the one schedule: bit for bit the two optimizers run separately."""
    torch.manual_seed(0)
    matrices, vectors = [torch.nn.Parameter(torch.randn(6, 4))], [torch.nn.Parameter(torch.randn(4))]
    reference = [copy.deepcopy(p) for p in matrices + vectors]
    optimizer, scheduler = scheduled(matrices, vectors)
    train(optimizer, scheduler, matrices + vectors, steps=5, seed=1)

    muon = torch.optim.Muon(reference[:1], lr=0.02, weight_decay=0.01, momentum=0.95, nesterov=True,
                            adjust_lr_fn="original")
    adamw = torch.optim.AdamW(reference[1:], lr=1e-3, betas=(0.9, 0.99), weight_decay=0.01)
    schedules = [torch.optim.lr_scheduler.LambdaLR(o, lr_lambda(2, "cosine", 10, 0.0, 0.2)) for o in (muon, adamw)]
    generator = torch.Generator().manual_seed(1)
    for _ in range(5):
        loss = sum((p * torch.randn(p.shape, generator=generator)).sum() ** 2 for p in reference)
        muon.zero_grad(), adamw.zero_grad()
        loss.backward()
        muon.step(), adamw.step()
        for s in schedules:
            s.step()
    for ours, theirs in zip(matrices + vectors, reference):
        assert torch.equal(ours, theirs)


def test_a_loaded_state_keeps_the_schedule_reaching_both_optimizers():
    """Optimizer.load_state_dict replaces an optimizer's group dicts; the hybrid links its groups to the new ones,
    so after a resume the scheduler still sets the learning rate both optimizers use (without that the rate froze
    at its value at the save), and the resumed run ends bit-identical to the uninterrupted one."""
    torch.manual_seed(0)
    start = [torch.nn.Parameter(torch.randn(5, 3)), torch.nn.Parameter(torch.randn(3))]
    whole = [copy.deepcopy(p) for p in start]
    optimizer, scheduler = scheduled(whole[:1], whole[1:])
    train(optimizer, scheduler, whole, steps=3, seed=2)
    saved = copy.deepcopy((optimizer.state_dict(), scheduler.state_dict(), [p.detach().clone() for p in whole]))
    train(optimizer, scheduler, whole, steps=4, seed=3)

    resumed = [torch.nn.Parameter(p.clone()) for p in saved[2]]
    optimizer2, scheduler2 = scheduled(resumed[:1], resumed[1:])
    optimizer2.load_state_dict(saved[0])
    scheduler2.load_state_dict(saved[1])
    train(optimizer2, scheduler2, resumed, steps=4, seed=3)
    assert optimizer2.muon.param_groups[0]["lr"] == optimizer.muon.param_groups[0]["lr"] != saved[0]["muon"][
        "param_groups"][0]["lr"]
    assert optimizer2.adamw.param_groups[0]["lr"] == optimizer.adamw.param_groups[0]["lr"]
    for a, b in zip(whole, resumed):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match="state of a Muon run"):
        optimizer2.load_state_dict(torch.optim.AdamW(resumed).state_dict())


def test_the_trainer_trains_with_muon_and_refuses_to_resume_across_optimizers(dataset, tmp_path):
    cfg = load_config(TrainConfig, "tiny", base_overrides(dataset, tmp_path / "run", "train.max_steps=2",
                                                          "optim.optimizer=muon"))
    with Dist(mixed_precision="no") as dist:
        trainer = Trainer(cfg, dist)
        before = {n: p.detach().clone() for n, p in trainer.model.named_parameters()}
        by_muon = set(muon_parameter_names(trainer.model))
        assert trainer.fit() == 0
        assert all(not torch.equal(before[n], p) for n, p in trainer.model.named_parameters() if n in by_muon)
        with_adamw = load_config(TrainConfig, "tiny", base_overrides(dataset, tmp_path / "run", "train.max_steps=3"))
        with pytest.raises(ckpt.ResumeSettingError, match="optim.optimizer=muon") as refused:
            Trainer(with_adamw, dist).fit()
    assert refused.value.setting == "optim.optimizer"
    _, _, state = ckpt.load_checkpoint(ckpt.checkpoints_dir(tmp_path / "run") / ckpt.step_dir_name(2))
    assert set(state["optimizer"]) == {"muon", "adamw"}
    card = (export_pretrained(tmp_path / "run", tmp_path / "model") / "README.md").read_text()
    assert f"Muon lr {cfg.optim.muon_lr} on the Transformer blocks' matrices" in card


@pytest.mark.parametrize("overrides, reason", [
    (["train.step_sync=deferred"], "does not go with train.step_sync=deferred"),
    (["optim.muon_lr=0"], "optim.muon_lr must be > 0"),
    (["optim.muon_momentum=1"], r"optim.muon_momentum must lie in \[0, 1\)"),
])
def test_settings_muon_cannot_train_with_are_refused(tmp_path, overrides, reason):
    with pytest.raises(ConfigError, match=reason):
        load_config(TrainConfig, "tiny", [f"train.out_dir={tmp_path}", "optim.optimizer=muon", *overrides])


def test_auto_step_sync_does_not_defer_with_muon():
    assert resolve_step_sync("auto", torch.device("cuda"), "bf16", "adamw")
    assert not resolve_step_sync("auto", torch.device("cuda"), "bf16", "muon")
