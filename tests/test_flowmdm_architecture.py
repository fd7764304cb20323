"""FlowMDM's architecture options (mfm.model: head_dim, attention_bias, attention/ff/residual dropout, layer_dropout,
absolute_positions, wrapper_projections) and the configs/flowmdm.yaml preset."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from torch import nn

from mfm.model import (
    ModelConfig,
    MotionFlowTransformer,
    ScaledSinusoidalEmbedding,
    concatenated_sinusoid,
    count_parameters,
    draw_block_drop_mask,
    segment_runs,
    sinusoidal_embedding,
)
from pipeline.config import (
    DataConfig,
    TrainConfig,
    from_dict,
    load_config,
    to_dict,
    to_yaml,
)

D, FEATURES, COND, TOKEN_DIM, LAYERS = 32, 7, 5, 6, 2
NEW_DEFAULTS = dict(head_dim=0, attention_bias=True, attention_dropout=None, ff_dropout=None, residual_dropout=None,
                    layer_dropout=0.0, absolute_positions="sinusoidal", wrapper_projections=False)
FLOWMDM_OPTIONS = dict(head_dim=16, attention_bias=False, attention_dropout=0.0, ff_dropout=0.0, residual_dropout=0.0,
                       layer_dropout=0.1, absolute_positions="scaled_sinusoidal", wrapper_projections=True,
                       norm_first=True, positional="bpe", conditioning="pccat")
VARIANTS = [
    dict(),
    dict(norm_first=True),
    dict(positional="bpe", conditioning="pccat"),
    dict(positional="bpe", conditioning="prefix", norm_first=True),
    dict(conditioning="cross_attention", length_token=True),
]


def tiny_config(**overrides) -> ModelConfig:
    values = dict(feature_dim=FEATURES, latent_dim=D, ff_dim=64, num_layers=LAYERS, num_heads=4, cond_dim=COND,
                  max_len=128, max_frames=64, dropout=0.0, token_dim=TOKEN_DIM, attention_horizon=4)
    values.update(overrides)
    return ModelConfig(**values)


def tiny_model(seed: int = 0, **overrides) -> MotionFlowTransformer:
    torch.manual_seed(seed)
    return MotionFlowTransformer(tiny_config(**overrides)).eval()


def batch_inputs(config: ModelConfig, batch: int = 3, frames: int = 12, seed: int = 1) -> tuple[tuple, dict]:
    """(x, t, cond, lengths) and the keyword inputs the variant needs (two segments for bpe, tokens for FLAME)."""
    generator = torch.Generator().manual_seed(seed)
    x = torch.randn(batch, frames, FEATURES, generator=generator)
    t, cond = torch.rand(batch, generator=generator), torch.randn(batch, COND, generator=generator)
    lengths = torch.tensor([frames, frames - 3, 5][:batch])
    kwargs: dict = {}
    if config.conditioning == "cross_attention":
        kwargs = dict(text_tokens=torch.randn(batch, 4, TOKEN_DIM, generator=generator),
                      text_token_len=torch.tensor([4, 2, 1][:batch]))
    if config.positional == "bpe":
        kwargs["segments"] = (torch.arange(frames) >= frames // 2).long().expand(batch, frames)
    return (x, t, cond, lengths), kwargs


def train_output(model: MotionFlowTransformer, args: tuple, kwargs: dict, seed: int = 5) -> torch.Tensor:
    """A training-mode forward pass with fixed draws (the generator's and the global RNG's, for dropout)."""
    model.train()
    torch.manual_seed(7)
    return model(*args, generator=torch.Generator().manual_seed(seed), **kwargs)


def without_layers(model: MotionFlowTransformer) -> MotionFlowTransformer:
    """The same model with no Transformer layers: what remains is the input/position/output path."""
    model.layers = nn.ModuleList()
    return model


# ---------------------------------------------------------------------------------------------- defaults


def test_defaults_are_mdm_and_add_nothing():
    config = ModelConfig()
    assert {name: getattr(config, name) for name in NEW_DEFAULTS} == NEW_DEFAULTS
    assert config.head_size == 128 and config.attention_dim == 512 and config.rotary_dims == 64
    assert count_parameters(MotionFlowTransformer(config)) == 17_880_327  # MFM's MDM_Flow, as before


@pytest.mark.parametrize("variant", VARIANTS, ids=lambda v: "-".join(map(str, v.values())) or "default")
def test_options_at_their_defaults_are_bit_identical(variant):
    """A model built with every new option explicitly at its default (or each dropout explicitly equal to
    ``dropout``) has the same weights and the same outputs, in eval and in training (same dropout draws)."""
    base = tiny_model(dropout=0.1, **variant)
    explicit = tiny_model(dropout=0.1, **NEW_DEFAULTS, **variant)
    same_dropouts = tiny_model(dropout=0.1, attention_dropout=0.1, ff_dropout=0.1, residual_dropout=0.1, **variant)
    args, kwargs = batch_inputs(base.config)
    reference_state = base.state_dict()
    for other in (explicit, same_dropouts):
        assert other.state_dict().keys() == reference_state.keys()
        assert all(torch.equal(other.state_dict()[k], v) for k, v in reference_state.items())
        with torch.no_grad():
            assert torch.equal(other.eval()(*args, **kwargs), base.eval()(*args, **kwargs))
            assert torch.equal(train_output(other, args, kwargs), train_output(base, args, kwargs))


def test_old_checkpoint_without_the_keys_loads_with_defaults(tmp_path):
    """A checkpoint whose saved configs predate the options (no such keys) loads into today's architecture."""
    from pipeline import checkpoint as ckpt
    from pipeline.generation.inference import load_trained_model

    config = tiny_config(positional="bpe", conditioning="pccat")
    model = MotionFlowTransformer(config)
    old_model = {k: v for k, v in dataclasses.asdict(config).items() if k not in NEW_DEFAULTS}
    train_config = to_dict(TrainConfig(model=config, data=DataConfig(window=32)))
    train_config["model"] = dict(old_model)
    folder = ckpt.save_checkpoint(
        tmp_path / "checkpoints", 3, model_state=model.state_dict(), ema_state=None, optimizer_state={},
        scheduler_state=None, rng_states=[{}], data_states=[None], config=train_config, manifest={},
        extra={"samples_seen": 0, "skipped_steps": 0, "model_config": old_model})
    assert from_dict(TrainConfig, train_config).model == config
    loaded = load_trained_model(folder)
    assert loaded.model_config == config
    args, kwargs = batch_inputs(config)
    with torch.no_grad():
        assert torch.equal(loaded.model(*args, **kwargs), model.eval()(*args, **kwargs))


@pytest.mark.parametrize(
    ("overrides", "field"),
    [
        (dict(head_dim=-1), "head_dim"),
        (dict(head_dim=True), "head_dim"),
        (dict(latent_dim=30), "num_heads"),  # 30 channels over 4 heads needs head_dim
        (dict(layer_dropout=1.5), "layer_dropout"),
        (dict(attention_dropout=1.0), "attention_dropout"),
        (dict(ff_dropout=-0.1), "ff_dropout"),
        (dict(residual_dropout="0.1"), "residual_dropout"),
        (dict(absolute_positions="learned"), "absolute_positions"),
        (dict(attention_bias=1), "attention_bias"),
        (dict(wrapper_projections="yes"), "wrapper_projections"),
        (dict(positional="bpe", head_dim=8, rope_dims=10), "rope_dims"),  # rotated channels beyond the head
    ],
)
def test_config_rejects_bad_values(overrides, field):
    with pytest.raises(ValueError, match=field):
        tiny_config(**overrides)


# ---------------------------------------------------------------------------------------------- head dim, biases


def test_head_dim_is_decoupled_from_the_width():
    config = tiny_config(head_dim=16)  # 4 heads x 16 = 64 attention channels in a 32-wide model
    assert (config.head_size, config.attention_dim, config.rotary_dims) == (16, 64, 8)
    prefix = MotionFlowTransformer(config).layers[0]
    assert prefix.qkv.weight.shape == (3 * 64, D) and prefix.out_proj.weight.shape == (D, 64)
    pccat = MotionFlowTransformer(tiny_config(head_dim=16, conditioning="pccat")).layers[0]
    assert pccat.query_cond.weight.shape == (D, 2 * D)  # the condition merge stays in the model width
    assert pccat.q_proj.weight.shape == (64, D) and pccat.kv_proj.weight.shape == (2 * 64, D)
    assert pccat.out_proj.weight.shape == (D, 64)
    flame = MotionFlowTransformer(tiny_config(head_dim=16, conditioning="cross_attention")).layers[0]
    assert flame.cross_q.weight.shape == (64, D) and flame.cross_kv.weight.shape == (128, D)
    assert flame.cross_out.weight.shape == (D, 64)
    # The width need not be divisible by the heads once the head size is given.
    assert MotionFlowTransformer(tiny_config(latent_dim=30, head_dim=8)).layers[0].qkv.weight.shape == (96, 30)


def test_decoupled_heads_attend_with_their_own_size():
    """One layer's attention equals multi-head attention written out with 4 heads of 16 channels, scale 16^-0.5."""
    layer = tiny_model(head_dim=16, attention_bias=False).layers[0]
    x = torch.randn(2, 9, D)
    q, k, v = layer.qkv(x).split(64, dim=-1)
    heads = [t.view(2, 9, 4, 16).transpose(1, 2) for t in (q, k, v)]
    weights = torch.softmax(heads[0] @ heads[1].transpose(-1, -2) / math.sqrt(16), dim=-1)
    expected = layer.out_proj((weights @ heads[2]).transpose(1, 2).reshape(2, 9, 64))
    with torch.no_grad():
        torch.testing.assert_close(layer._attention(x, _dense(), None), expected, atol=1e-6, rtol=1e-5)


def _dense():
    from mfm.model import DenseAttention

    return DenseAttention(None)


@pytest.mark.parametrize("conditioning", ["prefix", "pccat", "cross_attention"])
def test_bias_free_attention_projections(conditioning):
    layer = tiny_model(attention_bias=False, conditioning=conditioning).layers[0]
    names = {"prefix": ["qkv", "out_proj"], "pccat": ["q_proj", "kv_proj", "out_proj"],
             "cross_attention": ["qkv", "out_proj", "cross_q", "cross_kv", "cross_out"]}[conditioning]
    assert all(getattr(layer, name).bias is None for name in names)
    assert layer.linear1.bias is not None and layer.linear2.bias is not None  # the feed-forward keeps its biases
    if conditioning == "pccat":
        assert layer.query_cond.bias is not None  # FlowMDM's PCCAT Linear is a plain nn.Linear


def test_head_dim_runs_with_bpe_and_pccat_masks():
    """Decoupled heads with blended positions (mixed modes, two segments, padding) and PCCAT per-frame conditions:
    finite, padding-independent, and blockwise attention gives the dense result."""
    model = tiny_model(head_dim=16, positional="bpe", conditioning="pccat", attention_bias=False,
                       absolute_positions="scaled_sinusoidal", wrapper_projections=True, norm_first=True)
    frames = 14
    (x, t, cond, lengths), kwargs = batch_inputs(model.config, frames=frames)
    frame_cond = torch.randn(3, frames, COND)
    mode = torch.tensor([True, False, True])
    with torch.no_grad():
        dense = model(x, t, cond, lengths, frame_cond=frame_cond, positional_mode=mode, **kwargs)
        chunked = model(x, t, cond, lengths, frame_cond=frame_cond, positional_mode=mode, attention_chunk=4,
                        **kwargs)
        garbage = x.clone()
        garbage[1, lengths[1]:] = 1e3
        padded = model(garbage, t, cond, lengths, frame_cond=frame_cond, positional_mode=mode, **kwargs)
    assert dense.shape == (3, frames, FEATURES) and torch.isfinite(dense).all()
    torch.testing.assert_close(chunked, dense, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(padded, dense, atol=1e-5, rtol=1e-5)
    assert not torch.equal(dense[0], dense[1])  # relative and absolute samples differ


# ---------------------------------------------------------------------------------------------- layer dropout


@pytest.mark.parametrize("variant", VARIANTS, ids=lambda v: "-".join(map(str, v.values())) or "default")
def test_layer_dropout_one_skips_every_layer(variant):
    """p = 1 in training: the output is the model's input path alone (positions, conditions, output head)."""
    model = tiny_model(layer_dropout=1.0, **variant)
    args, kwargs = batch_inputs(model.config)
    mode = {"positional_mode": torch.tensor([True, False, False])} if model.config.positional == "bpe" else {}
    cond_mask = torch.tensor([False, True, False])
    skipped = train_output(model, args, {**kwargs, **mode, "cond_mask": cond_mask})
    expected = train_output(without_layers(model), args, {**kwargs, **mode, "cond_mask": cond_mask})
    assert torch.equal(skipped, expected)


@pytest.mark.parametrize("variant", VARIANTS[:3], ids=["default", "norm_first", "bpe-pccat"])
def test_layer_dropout_zero_and_eval_mode_change_nothing(variant):
    plain = tiny_model(dropout=0.1, **variant)
    zero = tiny_model(dropout=0.1, layer_dropout=0.0, **variant)
    half = tiny_model(dropout=0.1, layer_dropout=0.5, **variant)
    args, kwargs = batch_inputs(plain.config)
    assert torch.equal(train_output(zero, args, kwargs), train_output(plain, args, kwargs))
    with torch.no_grad():  # eval mode: no block is ever skipped
        assert torch.equal(half.eval()(*args, **kwargs), plain.eval()(*args, **kwargs))


def test_block_drop_mask_skips_exactly_the_named_blocks():
    model = tiny_model(num_layers=3, norm_first=True)
    args, _ = batch_inputs(model.config)
    keep_all = torch.zeros(3, 2, dtype=torch.bool)
    first_layer = keep_all.clone()
    first_layer[0] = True  # both blocks of layer 0: the model without its first layer
    with torch.no_grad():
        assert torch.equal(model(*args, block_drop_mask=keep_all), model(*args))
        dropped = model(*args, block_drop_mask=first_layer)
        shallow = tiny_model(num_layers=3, norm_first=True)
        shallow.layers = shallow.layers[1:]
        assert torch.equal(dropped, shallow(*args))
        # Only layer 1's feed-forward: layer 1 then adds its attention and nothing else.
        ff_only = keep_all.clone()
        ff_only[1, 1] = True
        layer1 = model.layers[1]
        layer1.forward = lambda x, attention, **kw: x + layer1._attention(layer1.norm1(x), attention, None)
        manual = model(*args)
        del layer1.forward  # back to the class's forward
        assert torch.equal(model(*args, block_drop_mask=ff_only), manual)
    with pytest.raises(ValueError, match="block_drop_mask"):
        model(*args, block_drop_mask=torch.zeros(3, 3, dtype=torch.bool))
    with pytest.raises(ValueError, match="block_drop_mask"):
        model(*args, block_drop_mask=torch.zeros(3, 2))


def test_layer_dropout_draws_whole_blocks_per_batch_from_the_generator():
    mask = draw_block_drop_mask(400, 2, 0.3, torch.Generator().manual_seed(0))
    assert mask.shape == (400, 2) and mask.dtype == torch.bool and abs(mask.float().mean().item() - 0.3) < 0.04
    assert MotionFlowTransformer(tiny_config(conditioning="cross_attention")).config.blocks_per_layer == 3
    model = tiny_model(layer_dropout=0.5, num_layers=4)
    args, _ = batch_inputs(model.config)
    kwargs = {"cond_mask": torch.zeros(3, dtype=torch.bool)}  # the block draw is then the generator's first
    outputs = [train_output(model, args, kwargs, seed=s) for s in (0, 0, 1, 2, 3)]
    assert torch.equal(outputs[0], outputs[1])  # the skipped blocks come from the generator
    assert any(not torch.equal(outputs[0], other) for other in outputs[2:])
    # One draw for the whole batch: a sample's output does not depend on which batch it is in (dropout is 0).
    alone = train_output(model, tuple(a[:1] for a in args), {"cond_mask": torch.zeros(1, dtype=torch.bool)}, seed=0)
    torch.testing.assert_close(alone, outputs[0][:1], atol=1e-6, rtol=1e-5)


def test_every_parameter_stays_in_the_graph_when_blocks_are_skipped():
    """DDP without find_unused_parameters: a skipped block's parameters still receive a (zero) gradient."""
    model = tiny_model(layer_dropout=1.0, cond_drop_prob=0.0, **{k: v for k, v in FLOWMDM_OPTIONS.items()
                                                                 if k != "layer_dropout"})
    args, kwargs = batch_inputs(model.config)
    train_output(model, args, kwargs).square().sum().backward()
    assert all(p.grad is not None for p in model.parameters())
    assert all(not p.grad.any() for p in model.layers.parameters())


# ---------------------------------------------------------------------------------------------- positions


def test_scaled_sinusoid_is_cat_sin_cos_times_a_learned_scale():
    dim = 12
    embedding = ScaledSinusoidalEmbedding(dim)
    assert embedding.scale.shape == (1,) and embedding.scale.item() == pytest.approx(dim**-0.5)
    positions = torch.tensor([0.0, 1.0, 7.0, 150.0, 999.0])
    frequencies = 10000.0 ** -(torch.arange(dim // 2).float() / (dim // 2))  # x-transformers' inv_freq
    angles = positions[:, None] * frequencies
    expected = torch.cat((angles.sin(), angles.cos()), dim=-1) * dim**-0.5
    torch.testing.assert_close(embedding(positions), expected, atol=1e-6, rtol=1e-6)
    with torch.no_grad():
        embedding.scale.fill_(2.0)
    torch.testing.assert_close(embedding(positions), 2.0 * concatenated_sinusoid(positions, dim))
    # The same frequencies as MDM's interleaved table, laid out in two halves.
    table = sinusoidal_embedding(positions, dim)
    torch.testing.assert_close(concatenated_sinusoid(positions, dim), torch.cat((table[:, 0::2], table[:, 1::2]), -1),
                               atol=1e-4, rtol=1e-5)


@pytest.mark.parametrize("variant", [dict(), dict(positional="bpe", conditioning="pccat"),
                                     dict(positional="bpe", conditioning="prefix")], ids=["absolute", "bpe-pccat",
                                                                                          "bpe-prefix"])
def test_scaled_positions_are_what_the_model_adds(variant):
    """Without layers the output is output_proj(final_norm(tokens + s·cat(sin, cos)(position))): positions 0 … S−1
    over the whole sequence (absolute), restarting at every segment in bpe's absolute mode, none in relative mode."""
    model = without_layers(tiny_model(absolute_positions="scaled_sinusoidal", norm_first=True, **variant))
    with torch.no_grad():
        model.absolute_embedding.scale.fill_(1.7)
    config = model.config
    (x, t, cond, _), kwargs = batch_inputs(config)
    mode = torch.tensor([False, True, False])
    if config.positional == "bpe":
        kwargs["positional_mode"] = mode
    with torch.no_grad():
        out = model(x, t, cond, **kwargs)
        time = model.time_embedding(t)
        aux = [] if config.conditioning == "pccat" else [time + model.cond_proj(cond)]
        tokens = torch.cat([a.unsqueeze(1) for a in aux] + [model.input_proj(x)], dim=1)
        frames, prefix = x.shape[1], len(aux)
        if config.positional == "bpe":
            _, offsets = segment_runs(kwargs["segments"], 3, frames, x.device)
            positions = torch.cat([torch.arange(prefix).expand(3, prefix), prefix + offsets], dim=1)
            added = 1.7 * concatenated_sinusoid(positions, D) * (~mode)[:, None, None]
        else:
            added = 1.7 * concatenated_sinusoid(torch.arange(prefix + frames), D)
        expected = model.output_proj(model.final_norm(tokens + added)[:, prefix:])
    torch.testing.assert_close(out, expected, atol=1e-6, rtol=1e-5)


def test_position_scale_is_learned():
    model = tiny_model(**FLOWMDM_OPTIONS)
    assert "absolute_embedding.scale" in dict(model.named_parameters())
    assert model.absolute_embedding.scale.item() == pytest.approx(D**-0.5)
    args, kwargs = batch_inputs(model.config)
    kwargs["positional_mode"] = torch.tensor([False, False, True])  # absolute samples carry the positions
    train_output(model, args, {**kwargs, "block_drop_mask": torch.zeros(LAYERS, 2, dtype=torch.bool)}
                 ).square().sum().backward()
    assert model.absolute_embedding.scale.grad is not None and model.absolute_embedding.scale.grad.abs().item() > 0


def test_wrapper_projections_sit_either_side_of_the_encoder():
    model = without_layers(tiny_model(wrapper_projections=True, norm_first=True, conditioning="pccat"))
    assert model.project_in.weight.shape == (D, D) and model.project_out.weight.shape == (D, D)
    (x, t, cond, _), _ = batch_inputs(model.config)
    with torch.no_grad():
        positions = model.positional_table[: x.shape[1]]
        expected = model.output_proj(model.project_out(model.final_norm(model.project_in(model.input_proj(x))
                                                                        + positions)))
        torch.testing.assert_close(model(x, t, cond), expected, atol=1e-6, rtol=1e-5)
    plain = tiny_model(norm_first=True, conditioning="pccat")
    assert count_parameters(tiny_model(wrapper_projections=True, norm_first=True, conditioning="pccat")) == (
        count_parameters(plain) + 2 * (D * D + D))


# ---------------------------------------------------------------------------------------------- the preset


def flowmdm_reference_parameters(width=512, heads=4, head_dim=64, ff=1024, layers=8, features=263, clip=512) -> int:
    """FlowMDM's HumanML3D model without CLIP, from the reference's layer shapes (model/FlowMDM.py, x-transformers):
    per layer the PCCAT Linear(2d, d), bias-free to_q/to_k/to_v (d -> h·64) and to_out, a 2-layer GELU
    feed-forward and 2 pre-norms; a final norm; project_in / project_out; the position scale; InputProcess,
    OutputProcess, embed_text and the timestep MLP."""
    def linear(i, o, bias=True):
        return i * o + (o if bias else 0)

    attention = heads * head_dim
    layer = (linear(2 * width, width) + 3 * linear(width, attention, False) + linear(attention, width, False)
             + linear(width, ff) + linear(ff, width) + 2 * 2 * width)
    return (layers * layer + 2 * width + 2 * linear(width, width) + 1 + linear(features, width)
            + linear(width, features) + linear(clip, width) + 2 * linear(width, width))


def test_preset_loads_validates_and_is_flowmdm_sized(tmp_path):
    cfg = load_config(TrainConfig, "flowmdm")
    model = cfg.model
    assert (model.latent_dim, model.num_layers, model.num_heads, model.head_dim, model.ff_dim) == (512, 8, 4, 64, 1024)
    assert (model.positional, model.conditioning, model.attention_horizon, model.rotary_dims) == ("bpe", "pccat", 150,
                                                                                                  32)
    assert (model.norm_first, model.attention_bias, model.absolute_positions, model.wrapper_projections) == (
        True, False, "scaled_sinusoidal", True)
    assert (model.dropout, model.layer_dropout) == (0.1, 0.1)
    assert model.dropout_of("attention") == model.dropout_of("ff") == model.dropout_of("residual") == 0.0
    assert (cfg.data.batch_size, cfg.optim.lr, cfg.train.objective) == (64, 1e-4, "flow")
    assert from_dict(TrainConfig, to_dict(cfg)) == cfg
    (tmp_path / "resolved.yaml").write_text(to_yaml(cfg))
    assert load_config(TrainConfig, tmp_path / "resolved.yaml") == cfg
    assert count_parameters(MotionFlowTransformer(model)) == flowmdm_reference_parameters() == 18_394_376


TINY_FLOWMDM = ["model.latent_dim=32", "model.ff_dim=64", "model.num_layers=2", "model.head_dim=16",
                "model.rope_dims=8", "model.attention_horizon=10", "data.window=32", "data.batch_size=4",
                "data.num_workers=0", "data.shuffle_buffer=8", "train.mixed_precision=no", "train.wandb=disabled",
                "train.tensorboard=false", "optim.ema_decay=0.9"]


@pytest.mark.slow
@pytest.mark.usefixtures("single_thread")
def test_preset_trains_and_its_checkpoint_keeps_the_options(tmp_path_factory, tmp_path):
    from test_trainer import build_dataset_once, train_entry

    from pipeline.generation.inference import load_trained_model

    manifest = build_dataset_once(tmp_path_factory)
    run = tmp_path / "run"
    overrides = [f"data.manifest={manifest}", f"train.out_dir={run}", "train.max_steps=1", "train.save_every=1",
                 "train.log_every=1", *TINY_FLOWMDM]
    assert train_entry.main(["--config", "flowmdm", *overrides]) == 0
    expected = load_config(TrainConfig, "flowmdm", overrides).model
    loaded = load_trained_model(run, use_ema=False)
    config = loaded.model_config
    for name in ("head_dim", "attention_bias", "attention_dropout", "ff_dropout", "residual_dropout", "layer_dropout",
                 "absolute_positions", "wrapper_projections", "norm_first", "positional", "conditioning"):
        assert getattr(config, name) == getattr(expected, name), name
    assert config.attention_dim == 64 and config.latent_dim == 32
    state = loaded.model.state_dict()
    assert "absolute_embedding.scale" in state and "project_in.weight" in state
    assert state["layers.0.q_proj.weight"].shape == (64, 32) and "layers.0.q_proj.bias" not in state
    # The scale trained (it started at 32^-0.5), and the loaded model samples.
    assert state["absolute_embedding.scale"].item() != pytest.approx(32**-0.5, abs=1e-9)
    x = torch.randn(2, 20, config.feature_dim)
    with torch.no_grad():
        out = loaded.model(x, torch.rand(2), torch.randn(2, config.cond_dim), torch.tensor([20, 11]))
    assert torch.isfinite(out).all()


@pytest.mark.slow
@pytest.mark.usefixtures("single_thread")
def test_layer_dropout_draws_replay_exactly_on_resume(tmp_path_factory, tmp_path):
    """The skipped blocks come from the trainer's per-rank generator (saved in the checkpoint), so a run resumed
    half-way logs the same losses as one run straight through; with layer dropout on, the losses differ from a run
    without it (the draws reach the model)."""
    from test_trainer import build_dataset_once, metrics_by_step, train_entry

    manifest = build_dataset_once(tmp_path_factory)

    def run(out, steps, *extra):
        overrides = [f"data.manifest={manifest}", f"train.out_dir={out}", f"train.max_steps={steps}",
                     "train.save_every=2", "train.log_every=1", "train.keep_last=0", *TINY_FLOWMDM, *extra]
        assert train_entry.main(["--config", "flowmdm", *overrides]) == 0
        return {step: record["loss"] for step, record in metrics_by_step(out).items()}

    straight = run(tmp_path / "straight", 4, "model.layer_dropout=0.5")
    run(tmp_path / "resumed", 2, "model.layer_dropout=0.5")
    resumed = run(tmp_path / "resumed", 4, "model.layer_dropout=0.5")
    assert resumed == straight
    assert run(tmp_path / "none", 4, "model.layer_dropout=0") != straight
