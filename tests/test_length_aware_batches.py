"""Length-aware batches (``data.batching=length_aware``): batches of clips of similar length, each padded to its
longest clip rounded up to ``data.pad_multiple``. What must hold, as for fixed windows: every sample once per epoch
at 1 and 2 ranks, equal batch counts on every rank, bit-exact resume mid-epoch, and the same loss per clip as in a
fixed-window batch with the same draws. The 2-rank gloo run is in tests/test_data_multirank.py."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from test_data import (
    DIM,
    TEXT_DIM,
    UNEVEN,
    assert_batches_equal,
    motion_id,
    opts,
    position_after,
    read_in_resumed_segments,
    take,
    write_fixture_dataset,
)

from mfm.flow import FlowMatchingObjective
from mfm.model import ModelConfig, MotionFlowTransformer
from pipeline.config import ConfigError, TrainConfig, load_config
from mfm.compilation import compiled_for_training
from pipeline.data.stages import Collate, TrainingSample, batch_widths, length_grouped_order, padded_width
from pipeline.data.stream import DataResumeError, MotionLoader, split_shards
from pipeline.training.trainer import resume_setting_error
from preprocess.shards import ManifestError, derive_dataset_id

WINDOW = 48  # the fixture's clips are 20-56 frames: a few are cropped, most are padded
LENGTH_AWARE = dict(batching="length_aware", pad_multiple=8, sort_window_batches=3, window=WINDOW)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return write_fixture_dataset(tmp_path_factory.mktemp("data"))


@pytest.fixture(scope="module")
def all_ids() -> set[str]:
    return {motion_id(n) for n in range(sum(UNEVEN))}


def epoch_per_rank(manifest, world_size: int, **kw) -> list[list[dict]]:
    loaders = [MotionLoader(manifest, "train", opts(**kw), rank=r, world_size=world_size) for r in range(world_size)]
    return [list(loader.iter_epoch()) for loader in loaders]


# ----------------------------------------------------------------------------------------------------------
# The two pieces alone: the regrouping and the width
# ----------------------------------------------------------------------------------------------------------


def test_length_grouped_order_regroups_within_windows_only():
    rng = np.random.default_rng(0)
    order = rng.permutation(60)
    lengths = rng.integers(10, 200, size=60)
    out = length_grouped_order(order, lengths, batch_size=4, window_batches=3, rng=np.random.default_rng(1))
    assert sorted(out.tolist()) == list(range(60))
    for start in range(0, 60, 12):  # each window keeps its items, as sorted batches of consecutive items
        assert set(out[start:start + 12]) == set(order[start:start + 12])
        ranked = sorted(lengths[order[start:start + 12]])
        batches = [sorted(lengths[out[b:b + 4]]) for b in range(start, start + 12, 4)]
        assert sorted(batches) == [ranked[0:4], ranked[4:8], ranked[8:12]]
    again = length_grouped_order(order, lengths, batch_size=4, window_batches=3, rng=np.random.default_rng(1))
    assert np.array_equal(out, again)
    shortest_first = length_grouped_order(order, lengths, batch_size=4, window_batches=5, rng=None)
    assert list(lengths[shortest_first]) == [n for start in (0, 20, 40) for n in sorted(lengths[order[start:start + 20]])]
    with pytest.raises(ValueError, match="whole number of batches"):
        length_grouped_order(order[:7], lengths, batch_size=4, window_batches=3, rng=None)


def test_padded_width_and_collate_pad_to_the_longest_clip_rounded_up():
    assert padded_width([5, 17, 9], window=196, pad_multiple=None) == 196
    assert padded_width([5, 17, 9], window=196, pad_multiple=16) == 32
    assert padded_width([16], window=196, pad_multiple=16) == 16
    assert padded_width([193], window=196, pad_multiple=16) == 196  # never above the window
    assert padded_width([17], window=196, pad_multiple=1) == 17

    def sample(n: int, sample_id: str) -> TrainingSample:
        return TrainingSample(id=sample_id, features=np.ones((n, DIM), np.float32), caption="c", caption_tokens=(),
                              caption_index=0, text_emb=np.zeros(TEXT_DIM, np.float32), action=None, start_frame=0)

    batch = Collate(window=48, action_classes=(), pad_multiple=8)([sample(5, "a"), sample(11, "b")])
    assert batch["features"].shape == (2, 16, DIM) and batch["mask"].shape == (2, 16)
    assert batch["mask"].sum(dim=1).tolist() == batch["lengths"].tolist() == [5, 11]
    fixed = Collate(window=48, action_classes=())([sample(5, "a"), sample(11, "b")])
    assert fixed["features"].shape == (2, 48, DIM)
    assert torch.equal(fixed["features"][:, :16], batch["features"]) and not fixed["features"][:, 16:].any()


# ----------------------------------------------------------------------------------------------------------
# The loader: same samples and batch counts as fixed windows, narrower batches, exact resume
# ----------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("num_workers", [0, 2])
@pytest.mark.parametrize("world_size", [1, 2])
def test_same_samples_and_batch_counts_as_fixed_windows_and_narrower_batches(dataset, all_ids, world_size,
                                                                            num_workers):
    kw = dict(num_workers=num_workers, batch_size=3)
    aware = epoch_per_rank(dataset, world_size, **kw, **LENGTH_AWARE)
    fixed = epoch_per_rank(dataset, world_size, **kw, window=WINDOW)
    plan = MotionLoader(dataset, "train", opts(**kw), world_size=world_size).plan(0)
    assert [len(batches) for batches in aware] == [len(batches) for batches in fixed] == \
        [plan.batches_per_rank] * world_size
    ids = [i for batches in aware for b in batches for i in b["ids"]]
    assert len(ids) == len(set(ids)), "a sample was seen twice in one epoch"
    assert set(ids) == {i for batches in fixed for b in batches for i in b["ids"]}
    assert len(ids) == len(all_ids) - plan.samples_dropped
    widths = [b["features"].shape[1] for batches in aware for b in batches]
    for b in (b for batches in aware for b in batches):
        assert b["features"].shape[1] == padded_width(b["lengths"].tolist(), WINDOW, 8)
        assert b["mask"].sum().item() == b["lengths"].sum().item()
    frames = sum(b["lengths"].sum().item() for batches in fixed for b in batches)
    aware_computed = sum(b["features"].shape[0] * b["features"].shape[1] for batches in aware for b in batches)
    fixed_computed = sum(b["features"].shape[0] * WINDOW for batches in fixed for b in batches)
    assert len(set(widths)) > 1 and aware_computed < 0.9 * fixed_computed
    assert aware_computed >= frames


@pytest.mark.parametrize("world_size", [1, 2])
def test_every_sample_exactly_once_when_nothing_is_dropped(tmp_path, world_size):
    manifest = write_fixture_dataset(tmp_path / "even", shard_sizes=(8, 8, 8, 8))
    per_rank = epoch_per_rank(manifest, world_size, batch_size=4, **LENGTH_AWARE)
    assert len({len(batches) for batches in per_rank}) == 1
    ids = sorted(i for batches in per_rank for b in batches for i in b["ids"])
    assert ids == sorted(motion_id(n) for n in range(32))


@pytest.mark.parametrize("num_workers", [0, 2])
def test_resume_mid_epoch_is_bit_exact(dataset, num_workers):
    kw = dict(num_workers=num_workers, **LENGTH_AWARE)

    def make_loader() -> MotionLoader:
        return MotionLoader(dataset, "train", opts(**kw), rank=1, world_size=2)

    probe = make_loader()
    first = probe.batches_per_epoch(0)
    total = first + 3
    expected = take(make_loader().iter_batches(), total)
    assert len({b["features"].shape[1] for b in expected}) > 1
    got, _ = read_in_resumed_segments(make_loader, [1, 4, first, total], probe)
    assert_batches_equal(got, expected)


def test_resume_refuses_a_changed_batching_and_reads_old_states_as_fixed(dataset):
    fixed = MotionLoader(dataset, "train", opts(window=WINDOW))
    take(fixed.iter_batches(), 2)
    state = fixed.state_dict()
    aware = MotionLoader(dataset, "train", opts(**LENGTH_AWARE))
    with pytest.raises(DataResumeError, match="batching") as caught:
        aware.load_state_dict(state)
    assert (caught.value.saved, caught.value.now) == ("fixed", "length_aware")
    refusal = str(resume_setting_error("runs/x/checkpoints/step-00000002", caught.value))
    assert "data.batching was 'fixed' in the checkpoint and is 'length_aware' now" in refusal
    # A state saved before data.batching existed has no such key: it was a fixed-window stream.
    old = {k: v for k, v in state.items() if k not in ("batching", "pad_multiple", "sort_window_batches")}
    resumed = MotionLoader(dataset, "train", opts(window=WINDOW))
    resumed.load_state_dict(old)
    assert (resumed.epoch, resumed.batches_in_epoch) == position_after(fixed, 2)

    aware_state = MotionLoader(dataset, "train", opts(**LENGTH_AWARE)).state_dict()
    with pytest.raises(DataResumeError, match="pad_multiple"):
        MotionLoader(dataset, "train", opts(**{**LENGTH_AWARE, "pad_multiple": 16})).load_state_dict(aware_state)
    # fixed windows never read pad_multiple: changing it does not stop a fixed-window resume
    MotionLoader(dataset, "train", opts(window=WINDOW, pad_multiple=4)).load_state_dict(state)


@pytest.mark.parametrize("lengths", [None, "short"])
def test_a_manifest_without_matching_lengths_is_refused_naming_it(tmp_path, lengths):
    manifest = write_fixture_dataset(tmp_path / "data")
    data = json.loads(manifest.read_text())
    entry = data["splits"]["train"]
    if lengths is None:
        del entry["lengths"]
        del entry["num_frames"]
    else:
        entry["lengths"] = entry["lengths"][:-1]
    data["dataset_id"] = derive_dataset_id(data)
    manifest.write_text(json.dumps(data))
    with pytest.raises(ManifestError, match="length_aware") as caught:
        MotionLoader(manifest, "train", opts(**LENGTH_AWARE))
    assert str(manifest) in str(caught.value) and "rebuild" in str(caught.value)
    assert all(s.lengths is None for s in split_shards(MotionLoader(manifest, "train", opts()).manifest, "train"))
    assert next(MotionLoader(manifest, "train", opts()).iter_batches())["ids"]  # fixed windows need no lengths


def test_config_option_is_validated():
    cfg = load_config(TrainConfig, "tiny", ["data.batching=length_aware", "data.pad_multiple=8"])
    assert (cfg.data.batching, cfg.data.pad_multiple, cfg.data.sort_window_batches) == ("length_aware", 8, 8)
    assert load_config(TrainConfig, "tiny").data.batching == "fixed"
    for bad in (["data.batching=sorted"], ["data.pad_multiple=0"], ["data.sort_window_batches=0"]):
        with pytest.raises(ConfigError):
            load_config(TrainConfig, "tiny", bad)
    with pytest.raises(ConfigError, match="attend_padding"):
        load_config(TrainConfig, "tiny", ["data.batching=length_aware", "model.attend_padding=true"])


# ----------------------------------------------------------------------------------------------------------
# The loss of a clip does not depend on the width of its batch
# ----------------------------------------------------------------------------------------------------------

MODEL_VARIANTS = {
    "mfm": dict(),
    "progress_length_token_data": dict(progress_positions=True, length_token=True, prediction="data"),
    "frames_per_token_2": dict(progress_positions=True, length_token=True, prediction="data", frames_per_token=2),
    "bpe_pccat": dict(positional="bpe", conditioning="pccat", attention_horizon=12),
    "cross_attention": dict(conditioning="cross_attention", length_token=True, prediction="preconditioned"),
}


def per_clip_losses(model, objective, features, lengths, cond, t, x0, model_kwargs) -> torch.Tensor:
    """The objective's loss of every clip alone (each row of the batch, at the batch's width)."""
    losses = []
    for i in range(features.shape[0]):
        row = slice(i, i + 1)
        kwargs = {k: v[row] for k, v in model_kwargs.items()}
        loss, _ = objective.loss(model, features[row], cond[row], lengths[row], t=t[row], x0=x0[row],
                                 cond_mask=torch.zeros(1, dtype=torch.bool), model_kwargs=kwargs)
        losses.append(loss)
    return torch.stack(losses)


@pytest.mark.parametrize("variant", list(MODEL_VARIANTS) + ["attend_padding"])
def test_per_clip_loss_equals_the_fixed_window_loss(tmp_path, variant):
    token_features = variant == "cross_attention"
    # Normalised to about [-2, 2] (the fixture's raw features reach 5e4), so that the loss is sensitive to the model
    manifest = write_fixture_dataset(tmp_path / "data", token_features=token_features,
                                     mean=np.full(DIM, 26000.0), std=np.full(DIM, 15000.0))
    options = dict(LENGTH_AWARE, batch_size=6, window=64)
    batches = take(MotionLoader(manifest, "train", opts(**options)).iter_batches(), 4)
    batch = min(batches, key=lambda b: b["features"].shape[1])
    features, lengths = batch["features"], batch["lengths"]
    b, width = features.shape[:2]
    assert width < 64
    fixed = torch.zeros(b, 64, DIM)  # the same clips as a fixed-window batch pads them
    fixed[:, :width] = features

    settings = MODEL_VARIANTS.get(variant, dict(attend_padding=True))
    torch.manual_seed(0)
    model = MotionFlowTransformer(ModelConfig(feature_dim=DIM, latent_dim=32, ff_dim=64, num_layers=2, num_heads=4,
                                              cond_dim=TEXT_DIM, max_frames=64, dropout=0.0, **settings)).eval()
    objective = FlowMatchingObjective(temporal_weight=0.5)
    generator = torch.Generator().manual_seed(1)
    t = torch.rand(b, generator=generator)
    x0 = torch.randn(b, 64, DIM, generator=generator)
    model_kwargs = {}
    if token_features:
        model_kwargs = {"text_tokens": batch["text_tokens"], "text_token_len": batch["text_token_len"]}
    cond = batch["text_emb"]
    with torch.no_grad():
        cut = per_clip_losses(model, objective, features, lengths, cond, t, x0[:, :width], model_kwargs)
        padded = per_clip_losses(model, objective, fixed, lengths, cond, t, x0, model_kwargs)
        cut_batch, _ = objective.loss(model, features, cond, lengths, t=t, x0=x0[:, :width],
                                      cond_mask=torch.zeros(b, dtype=torch.bool), model_kwargs=model_kwargs)
    assert torch.all(torch.isfinite(cut)) and cut.std() > 0
    if variant == "attend_padding":  # MFM's attention over the padding: why the config refuses this combination
        assert (cut - padded).abs().max() > 1e-3
        return
    torch.testing.assert_close(cut, padded, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(cut_batch, padded.mean(), rtol=1e-5, atol=1e-5)


def test_the_padding_benchmark_plans_batches_as_the_loader_does(capsys):
    """benchmarks/bench_padding.py's analytic part (no timing), kept from rotting: its batch plan holds every planned
    clip once and the length-aware plan computes fewer frames than fixed windows."""
    import importlib.util

    from conftest import REPO_ROOT

    spec = importlib.util.spec_from_file_location("bench_padding", REPO_ROOT / "benchmarks" / "bench_padding.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    lengths = bench.humanml3d_like_lengths(1000, seed=0)
    assert lengths.min() >= 40 and lengths.max() <= 196 and abs(lengths.mean() - bench.HUMANML3D_MEAN_FRAMES) < 5
    plans = {batching: bench.planned_batches(lengths, lengths, batch_size=32, window=196, shuffle_buffer=64,
                                             batching=batching, pad_multiple=16, sort_window=4, seed=0)
             for batching in ("fixed", "length_aware")}
    planned = sorted(np.concatenate(plans["fixed"]).tolist())
    assert planned == sorted(np.concatenate(plans["length_aware"]).tolist()) and len(set(planned)) == 992
    fixed = bench.padding_share([lengths[b] for b in plans["fixed"]], 196, None)
    aware = bench.padding_share([lengths[b] for b in plans["length_aware"]], 196, 16)
    assert fixed[1] == aware[1] and aware[2] < fixed[2] and 0 < aware[0] < fixed[0]
    bench.main(["--only", "padding_humanml3d", "--clips", "2000"])
    record = json.loads(capsys.readouterr().out)
    assert record["computed_frames_ratio_fixed_to_length_aware"] > 1.1


# ----------------------------------------------------------------------------------------------------------
# Compiled training: one static graph per batch width (a dynamic-width graph failed on an H200)
# ----------------------------------------------------------------------------------------------------------


def test_batch_widths_counts_every_width_a_length_aware_batch_can_have():
    for window, multiple in ((196, 16), (192, 16), (48, 8), (196, 1), (20, 32)):
        widths = {padded_width([n], window, multiple) for n in range(1, window + 1)}
        assert batch_widths(window, multiple) == len(widths), (window, multiple)


@pytest.fixture
def dynamo_config():
    """torch._dynamo's config with the recompile limit at torch's default, restored afterwards (its own patch: a
    monkeypatch undo deletes the key from torch's config module)."""
    import torch._dynamo.config as config

    with config.patch(recompile_limit=8):
        yield config


def test_compiled_for_training_gives_length_aware_runs_static_graphs_and_room_for_every_width(compile_calls,
                                                                                            dynamo_config):
    model = torch.nn.Linear(2, 2)
    compiled_for_training(model)
    assert (compile_calls[-1].mode, compile_calls[-1].options) == ("default", {})  # fixed windows: as before
    assert dynamo_config.recompile_limit == 8
    compiled_for_training(model, "reduce-overhead", batch_widths=13)
    assert compile_calls[-1].mode == "reduce-overhead" and compile_calls[-1].options == {"dynamic": False}
    assert dynamo_config.recompile_limit == 2 * 13 + 4  # each width in train and eval mode, and the stand-in
    compiled_for_training(model, batch_widths=2)
    assert dynamo_config.recompile_limit == 30  # raised, never lowered
    with pytest.raises(ValueError, match="compile mode"):
        compiled_for_training(model, "max-autotune")
    with pytest.raises(ValueError, match="batch_widths"):
        compiled_for_training(model, batch_widths=0)


@pytest.mark.parametrize("batching", ["fixed", "length_aware"])
def test_the_trainer_compiles_in_the_configured_mode_one_graph_per_width_when_length_aware(
        batching, compile_calls, tmp_path_factory, dynamo_config):
    from test_trainer import build_dataset_once

    from pipeline.distributed import Dist
    from pipeline.training.trainer import Trainer

    manifest = build_dataset_once(tmp_path_factory)
    cfg = load_config(TrainConfig, "tiny", [
        f"data.manifest={manifest}", f"train.out_dir={tmp_path_factory.mktemp('run')}", "train.wandb=disabled",
        "train.compile=true", "train.compile_mode=max-autotune-no-cudagraphs", f"data.batching={batching}",
        "data.window=40", "data.pad_multiple=8"])
    with Dist(cpu=True) as dist:
        Trainer(cfg, dist)
    (compiled,) = compile_calls
    assert compiled.mode == "max-autotune-no-cudagraphs"
    if batching == "fixed":
        assert compiled.options == {} and dynamo_config.recompile_limit == 8
    else:
        assert compiled.options == {"dynamic": False} and dynamo_config.recompile_limit == 2 * 5 + 4  # 8, ..., 40
    with pytest.raises(ConfigError, match="train.compile_mode"):
        load_config(TrainConfig, "tiny", ["train.compile_mode=fast"])
