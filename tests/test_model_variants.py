"""The model's FlowMDM (BPE, PCCAT) and FLAME (cross-attention, learned-variance output) options."""

import dataclasses
import functools
import math

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from mfm.composition import BoundInputs
from mfm.flow import flow_matching_loss
from mfm.model import (
    BlendedAttention,
    DenseAttention,
    ModelConfig,
    MotionFlowTransformer,
    apply_rotary,
    count_parameters,
    draw_cond_drop_mask,
    draw_positional_mode,
    rotary_tables,
    segment_runs,
    valid_frame_mask,
)
from mfm.solvers import sample

HUMANML3D_PARAMETERS = 17_880_327
D, FEATURES, COND, TOKEN_DIM, LAYERS = 32, 7, 5, 6, 2
VARIANTS = [
    dict(positional=positional, conditioning=conditioning)
    for positional in ("absolute", "bpe")
    for conditioning in ("prefix", "pccat", "cross_attention")
] + [
    dict(positional="bpe", conditioning="cross_attention", length_token=True),  # FLAME layout + BPE
    dict(positional="absolute", conditioning="cross_attention", length_token=True),  # FLAME's exact layout
    dict(positional="bpe", conditioning="prefix", norm_first=True),
    dict(positional="absolute", conditioning="cross_attention", length_token=True, norm_first=True,
         adaptive_norm="adaln_zero"),  # DiT's adaLN-Zero on FLAME's layout
    dict(positional="absolute", conditioning="prefix", norm_first=True, adaptive_norm="adaln"),
]


def variant_id(variant: dict) -> str:
    return "-".join(f"{v}" if not isinstance(v, bool) else k for k, v in variant.items())


def tiny_config(**overrides) -> ModelConfig:
    values = dict(feature_dim=FEATURES, latent_dim=D, ff_dim=64, num_layers=LAYERS, num_heads=4, cond_dim=COND,
                  max_len=128, max_frames=64, dropout=0.0, token_dim=TOKEN_DIM)
    values.update(overrides)
    return ModelConfig(**values)


def tiny_model(seed: int = 0, **overrides) -> MotionFlowTransformer:
    torch.manual_seed(seed)
    model = MotionFlowTransformer(tiny_config(**overrides)).eval()
    if model.config.adaptive_norm != "none":
        randomize_modulations(model, seed)
    return model


def randomize_modulations(model: MotionFlowTransformer, seed: int = 0) -> None:
    """Give adaptive-norm modulations a trained model's non-zero weights: zero-initialised, the condition's path
    through them (and, for adaLN-Zero, every block behind a zero gate) would go untested."""
    generator = torch.Generator().manual_seed(seed + 100)
    with torch.no_grad():
        for name, parameter in model.named_parameters():
            if "modulation" in name:
                parameter.copy_(0.2 * torch.randn(parameter.shape, generator=generator))


def extra_inputs(model: MotionFlowTransformer, batch: int, seed: int = 0, num_tokens: int = 6) -> dict:
    """The inputs a variant needs beyond (x, t, cond, lengths): token features for cross-attention."""
    if model.config.conditioning != "cross_attention":
        return {}
    generator = torch.Generator().manual_seed(seed)
    lengths = torch.randint(1, num_tokens + 1, (batch,), generator=generator)
    tokens = torch.randn(batch, num_tokens, TOKEN_DIM, generator=generator)
    tokens = tokens * valid_frame_mask(lengths, num_tokens).unsqueeze(-1)  # zero-padded as in the shards
    return {"text_tokens": tokens, "text_token_len": lengths}


def inputs(batch: int, frames: int, seed: int = 0):
    generator = torch.Generator().manual_seed(seed)
    return (torch.randn(batch, frames, FEATURES, generator=generator), torch.rand(batch, generator=generator),
            torch.randn(batch, COND, generator=generator))


# ---------------------------------------------------------------------------------------------- defaults unchanged


def test_default_config_is_unchanged_and_options_are_off():
    config = ModelConfig()
    assert (config.positional, config.conditioning, config.output_dim) == ("absolute", "prefix", None)
    assert config.num_prefix_tokens == 1 and config.output_size == 263
    assert count_parameters(MotionFlowTransformer(config)) == HUMANML3D_PARAMETERS


def mdm_reference(model: MotionFlowTransformer, x, t, cond, lengths):
    """MDM's trans_enc forward written with nn.TransformerEncoderLayer and our weights (independent of mfm.model's
    attention and positional code)."""
    config = model.config
    d = config.latent_dim
    position = torch.arange(128).unsqueeze(1).float()
    div_term = torch.exp(torch.arange(0, d, 2).float() * (-math.log(10000.0) / d))
    table = torch.zeros(128, d)
    table[:, 0::2], table[:, 1::2] = torch.sin(position * div_term), torch.cos(position * div_term)
    tokens = torch.cat([(model.time_embedding(t) + model.cond_proj(cond)).unsqueeze(1), model.input_proj(x)], 1)
    tokens = tokens + table[: tokens.shape[1]]
    valid = valid_frame_mask(lengths, x.shape[1])
    padding = ~torch.cat([torch.ones(x.shape[0], 1, dtype=torch.bool), valid], 1)
    for ours in model.layers:
        layer = nn.TransformerEncoderLayer(d, config.num_heads, config.ff_dim, 0.0, "gelu", batch_first=True).eval()
        layer.self_attn.in_proj_weight.data.copy_(ours.qkv.weight)
        layer.self_attn.in_proj_bias.data.copy_(ours.qkv.bias)
        layer.self_attn.out_proj.load_state_dict(ours.out_proj.state_dict())
        for name in ("linear1", "linear2", "norm1", "norm2"):
            getattr(layer, name).load_state_dict(getattr(ours, name).state_dict())
        tokens = layer(tokens, src_key_padding_mask=padding)
    return model.output_proj(tokens[:, 1:]) * valid.unsqueeze(-1)


def test_default_forward_is_mdm_trans_enc():
    model = tiny_model()
    x, t, cond = inputs(3, 9)
    lengths = torch.tensor([9, 5, 2])
    with torch.no_grad():
        torch.testing.assert_close(model(x, t, cond, lengths), mdm_reference(model, x, t, cond, lengths),
                                   atol=1e-5, rtol=1e-5)


def test_parameter_cost_of_each_option():
    base = count_parameters(tiny_model())
    assert count_parameters(tiny_model(positional="bpe")) == base  # RoPE and masks have no parameters
    # PCCAT: one Linear(2d → d) per layer (FlowMDM's process_cond_input); q/k/v keep the fused projection's size.
    assert count_parameters(tiny_model(conditioning="pccat")) == base + LAYERS * (2 * D * D + D)
    # FLAME: per layer a cross-attention block (q, kv, out projections + LayerNorm), plus the token projection.
    cross = LAYERS * (4 * D * D + 4 * D + 2 * D) + TOKEN_DIM * D + D
    assert count_parameters(tiny_model(conditioning="cross_attention")) == base + cross
    assert count_parameters(tiny_model(output_dim=2 * FEATURES)) == base + FEATURES * D + FEATURES
    # adaLN: per layer Linear(d -> 2 or 3 per residual block x d), plus the final norm's Linear(d -> 2d).
    final = 2 * D * D + 2 * D
    pre_norm = count_parameters(tiny_model(norm_first=True))  # adds the final LayerNorm
    for adaptive_norm, per_block in (("adaln", 2), ("adaln_zero", 3)):
        assert count_parameters(tiny_model(norm_first=True, adaptive_norm=adaptive_norm)) == (
            pre_norm + LAYERS * 2 * per_block * (D * D + D) + final)
        assert count_parameters(tiny_model(norm_first=True, adaptive_norm=adaptive_norm,
                                           conditioning="cross_attention")) == (
            pre_norm + cross + LAYERS * 3 * per_block * (D * D + D) + final)


@pytest.mark.parametrize(
    "overrides, field",
    [
        (dict(positional="alibi"), "positional"),
        (dict(conditioning="adaln"), "conditioning"),
        (dict(output_dim=0), "output_dim"),
        (dict(positional="bpe", rope_dims=3), "rope_dims"),
        (dict(positional="bpe", rope_dims=10), "rope_dims"),  # head dim is 8
        (dict(attention_horizon=0), "attention_horizon"),
        (dict(bpe_train_relative_prob=1.5), "bpe_train_relative_prob"),
        (dict(conditioning="pccat", length_token=True), "length_token"),
        (dict(conditioning="pccat", num_actions=3), "conditioning"),
        (dict(token_dim=-1), "token_dim"),
    ],
)
def test_config_rejects_bad_option_values(overrides, field):
    with pytest.raises(ValueError, match=field):
        tiny_config(**overrides)


def test_forward_rejects_inputs_of_other_variants():
    x, t, cond = inputs(2, 6)
    plain = tiny_model()
    with pytest.raises(ValueError, match="positional='bpe'"):
        plain(x, t, cond, segments=torch.zeros(2, 6, dtype=torch.long))
    with pytest.raises(ValueError, match="positional='bpe'"):
        plain(x, t, cond, positional_mode=torch.ones(2, dtype=torch.bool))
    with pytest.raises(ValueError, match="pccat"):
        plain(x, t, cond, frame_cond=torch.randn(2, 6, COND))
    with pytest.raises(ValueError, match="cross_attention"):
        plain(x, t, cond, text_tokens=torch.randn(2, 3, TOKEN_DIM), text_token_len=torch.tensor([3, 1]))
    with pytest.raises(ValueError, match="needs text_tokens"):
        tiny_model(conditioning="cross_attention")(x, t, cond)
    bpe = tiny_model(positional="bpe")
    with pytest.raises(ValueError, match="segments must be"):
        bpe(x, t, cond, segments=torch.zeros(2, 5, dtype=torch.long))
    with pytest.raises(ValueError, match="positional_mode must be"):
        bpe(x, t, cond, positional_mode=torch.tensor([1, 0]))
    with pytest.raises(ValueError, match="attention_chunk"):
        bpe(x, t, cond, attention_chunk=0)
    with pytest.raises(ValueError, match="frame_cond must be"):
        tiny_model(conditioning="pccat")(x, t, cond, frame_cond=torch.randn(2, 5, COND))


def test_learned_variance_output_dim():
    model = tiny_model(output_dim=2 * FEATURES)
    x, t, cond = inputs(2, 6)
    with torch.no_grad():
        out = model(x, t, cond, torch.tensor([6, 3]))
    assert out.shape == (2, 6, 2 * FEATURES)
    assert torch.count_nonzero(out[1, 3:]) == 0


# ---------------------------------------------------------------------------------------------- rotary / BPE


def test_rotary_scores_depend_on_relative_position_only():
    generator = torch.Generator().manual_seed(0)
    q, k = torch.randn(2, 8, generator=generator), torch.randn(2, 8, generator=generator)
    positions = torch.tensor([3.0, 11.0])
    cos, sin = rotary_tables(positions, 4)
    shifted_cos, shifted_sin = rotary_tables(positions + 57.0, 4)
    score = (apply_rotary(q, cos, sin)[0] * apply_rotary(k, cos, sin)[1]).sum()
    shifted = (apply_rotary(q, shifted_cos, shifted_sin)[0] * apply_rotary(k, shifted_cos, shifted_sin)[1]).sum()
    torch.testing.assert_close(score, shifted, atol=1e-5, rtol=0)
    assert torch.equal(apply_rotary(q, cos, sin)[:, 4:], q[:, 4:])  # only the first rope_dims channels rotate
    assert not torch.allclose(apply_rotary(q, cos, sin)[:, :4], q[:, :4])


@pytest.mark.parametrize("conditioning", ["prefix", "pccat", "cross_attention"])
def test_relative_mode_attention_is_translation_invariant(conditioning):
    """Shifting every frame position by a constant leaves the layer outputs unchanged (relative mode)."""
    model = tiny_model(positional="bpe", conditioning=conditioning, attention_horizon=6)
    layer, aux, frames, batch = model.layers[0], model.config.num_prefix_tokens, 15, 2
    generator = torch.Generator().manual_seed(1)
    tokens = torch.randn(batch, aux + frames, D, generator=generator)
    kwargs = {}
    if conditioning == "pccat":
        kwargs["condition"] = torch.randn(batch, aux + frames, D, generator=generator)
    if conditioning == "cross_attention":
        kwargs["memory"] = torch.randn(batch, 4, D, generator=generator)

    def plan(positions):
        return BlendedAttention(num_aux=aux, runs=torch.zeros(batch, frames, dtype=torch.long),
                                relative=torch.ones(batch, dtype=torch.bool), horizon=6, rotary_dims=4,
                                positions=positions)

    frames_at = torch.arange(frames, dtype=torch.float32)
    with torch.no_grad():
        reference = layer(tokens, plan(frames_at), **kwargs)
        shifted = layer(tokens, plan(frames_at + 113.0), **kwargs)
        stretched = layer(tokens, plan(frames_at * 2.0), **kwargs)
    torch.testing.assert_close(shifted, reference, atol=1e-4, rtol=1e-4)
    assert not torch.allclose(stretched[:, aux:], reference[:, aux:], atol=1e-3)  # positions do matter


@pytest.mark.parametrize("conditioning", ["prefix", "pccat", "cross_attention"])
def test_absolute_mode_attention_stays_inside_each_segment(conditioning):
    model = tiny_model(positional="bpe", conditioning=conditioning, num_layers=3)
    batch, first, second = 2, 6, 5
    x, t, cond = inputs(batch, first + second)
    segments = torch.tensor([0] * first + [1] * second).expand(batch, -1)
    extras = extra_inputs(model, batch)
    frame_cond = torch.randn(batch, first + second, COND)
    if conditioning == "pccat":
        extras["frame_cond"] = frame_cond
    absolute = torch.zeros(batch, dtype=torch.bool)
    changed = x.clone()
    changed[:, first:] = torch.randn(batch, second, FEATURES)
    changed_extras = dict(extras)
    if conditioning == "pccat":
        changed_extras["frame_cond"] = torch.cat([frame_cond[:, :first], torch.randn(batch, second, COND)], 1)
    with torch.no_grad():
        out = model(x, t, cond, segments=segments, positional_mode=absolute, **extras)
        out_changed = model(changed, t, cond, segments=segments, positional_mode=absolute, **changed_extras)
        relative = torch.ones(batch, dtype=torch.bool)
        rel = model(x, t, cond, segments=segments, positional_mode=relative, **extras)
        rel_changed = model(changed, t, cond, segments=segments, positional_mode=relative, **changed_extras)
        # Positions restart: the second segment computes exactly what it computes as a sequence of its own.
        alone_extras = dict(extras)
        if conditioning == "pccat":
            alone_extras["frame_cond"] = frame_cond[:, first:]
        alone = model(x[:, first:], t, cond, positional_mode=absolute, **alone_extras)
    torch.testing.assert_close(out_changed[:, :first], out[:, :first], atol=1e-6, rtol=0)
    assert not torch.allclose(out_changed[:, first:], out[:, first:])
    torch.testing.assert_close(alone, out[:, first:], atol=1e-5, rtol=1e-5)
    assert not torch.allclose(rel_changed[:, :first], rel[:, :first])  # relative mode crosses the boundary


@pytest.mark.parametrize("conditioning", ["prefix", "pccat"])
@pytest.mark.parametrize("num_layers", [1, 2])
@pytest.mark.parametrize("mode, horizon_in_absolute", [("relative", True), ("absolute", True), ("absolute", False)])
def test_attention_horizon_is_respected(conditioning, num_layers, mode, horizon_in_absolute):
    horizon, frames, poked = 3, 24, 11
    model = tiny_model(positional="bpe", conditioning=conditioning, attention_horizon=horizon, num_layers=num_layers,
                       horizon_in_absolute=horizon_in_absolute)
    x, t, cond = inputs(1, frames)
    poked_x = x.clone()
    poked_x[0, poked] += 3.0
    relative = torch.tensor([mode == "relative"])
    with torch.no_grad():
        delta = (model(poked_x, t, cond, positional_mode=relative) - model(x, t, cond, positional_mode=relative))
    moved = delta[0].abs().amax(dim=-1) > 1e-6
    reach = num_layers * horizon  # one layer sees ±H; stacking layers widens the receptive field by H each
    # FlowMDM's window mask limits both modes; without it absolute mode sees the whole (single) segment
    expected = (torch.arange(frames) - poked).abs() <= reach if horizon_in_absolute or mode == "relative" \
        else torch.ones(frames, dtype=torch.bool)
    assert torch.equal(moved, expected), (moved.nonzero().flatten().tolist(), reach)


@pytest.mark.parametrize("conditioning", ["prefix", "pccat", "cross_attention"])
def test_chunked_attention_equals_dense_masked_attention(conditioning):
    model = tiny_model(positional="bpe", conditioning=conditioning, attention_horizon=5)
    batch, frames = 3, 70
    x, t, cond = inputs(batch, frames, seed=2)
    lengths = torch.tensor([70, 55, 23])
    # Different segmentations per sample, runs of 7 to 30 frames.
    cuts = [[0] * 30 + [1] * 25 + [2] * 15, [5] * 7 + [3] * 20 + [5] * 43, [0] * 12 + [1] * 58]
    segments = torch.tensor(cuts)
    modes = torch.tensor([True, False, True])
    extras = extra_inputs(model, batch)
    if conditioning == "pccat":
        extras["frame_cond"] = torch.randn(batch, frames, COND)
    with torch.no_grad():
        dense = model(x, t, cond, lengths, segments=segments, positional_mode=modes, **extras)
        for chunk in (1, 8, 64, 500):
            chunked = model(x, t, cond, lengths, segments=segments, positional_mode=modes, attention_chunk=chunk,
                            **extras)
            torch.testing.assert_close(chunked, dense, atol=2e-5, rtol=1e-5)


def test_chunked_attention_memory_is_linear_in_length(monkeypatch):
    """Shape argument: no attention call of the chunked path scores more than chunk × (chunk + 2·window + aux)
    pairs whatever the length, and the number of calls grows linearly; the dense path scores T² pairs."""
    horizon, chunk, segment = 8, 16, 20
    model = tiny_model(positional="bpe", attention_horizon=horizon, max_len=64)
    sizes: list[tuple[int, int]] = []
    original = torch.nn.functional.scaled_dot_product_attention

    def spy(q, k, v, attn_mask=None, **kwargs):
        sizes.append((q.shape[-2], k.shape[-2]))
        if attn_mask is not None:
            assert attn_mask.numel() <= q.shape[0] * q.shape[-2] * k.shape[-2]  # masks are per block too
        return original(q, k, v, attn_mask=attn_mask, **kwargs)

    monkeypatch.setattr(torch.nn.functional, "scaled_dot_product_attention", spy)
    largest, calls = {}, {}
    for frames in (200, 400):
        x, t, cond = inputs(1, frames)
        segments = torch.arange(frames).div(segment, rounding_mode="floor").unsqueeze(0)  # > max_len in total
        sizes.clear()
        with torch.no_grad():
            model(x, t, cond, segments=segments, positional_mode=torch.tensor([True]), attention_chunk=chunk)
        largest[frames] = max(q * k for q, k in sizes)
        calls[frames] = len(sizes)
    window = max(horizon, segment - 1)
    assert largest[200] == largest[400] <= chunk * (chunk + 2 * window + 1)
    per_layer = {frames: calls[frames] // LAYERS for frames in calls}
    assert per_layer == {f: 1 + math.ceil(f / chunk) for f in (200, 400)}  # aux block + query blocks
    sizes.clear()
    with torch.no_grad():
        model(*inputs(1, 60), positional_mode=torch.tensor([True]))
    assert max(q * k for q, k in sizes) == 61 * 61  # dense: every token pair


def test_segment_runs_restart_positions():
    segments = torch.tensor([[4, 4, 4, 1, 1, 4, 4], [0, 0, 0, 0, 0, 0, 0]])
    runs, offsets = segment_runs(segments, 2, 7, torch.device("cpu"))
    assert runs.tolist() == [[0, 0, 0, 1, 1, 2, 2], [0] * 7]
    assert offsets.tolist() == [[0, 1, 2, 0, 1, 0, 1], list(range(7))]


def test_bpe_training_draws_half_relative_from_the_generator():
    batch = 4000
    model = tiny_model(positional="bpe", cond_drop_prob=0.1)
    x, t, cond = inputs(batch, 3)
    generator = torch.Generator().manual_seed(7)
    cond_mask = draw_cond_drop_mask(batch, 0.1, generator)
    modes = draw_positional_mode(batch, 0.5, generator)  # drawn right after the dropout, same generator
    assert abs(modes.float().mean().item() - 0.5) < 0.03  # ~4 standard deviations
    with torch.no_grad():
        expected = model(x, t, cond, cond_mask=cond_mask, positional_mode=modes)
        absolute = model(x, t, cond, cond_mask=cond_mask)  # eval default: absolute mode
        model.train()
        trained = model(x, t, cond, generator=torch.Generator().manual_seed(7))
    torch.testing.assert_close(trained, expected, atol=1e-6, rtol=0)
    torch.testing.assert_close(absolute[~modes], expected[~modes], atol=1e-6, rtol=0)
    assert not torch.allclose(absolute[modes], expected[modes])


# ---------------------------------------------------------------------------------------------- PCCAT


def test_pccat_keys_and_values_do_not_depend_on_conditions():
    model = tiny_model(conditioning="pccat", positional="bpe")
    x, t, cond = inputs(2, 10)
    captured: dict[str, list] = {"kv_in": [], "kv_out": [], "q_out": []}
    layer = model.layers[0]

    def record_kv(module, args, output):  # a forward hook must return None, or it replaces the output
        captured["kv_in"].append(args[0])
        captured["kv_out"].append(output)

    def record_q(module, args, output):
        captured["q_out"].append(output)

    hooks = [layer.kv_proj.register_forward_hook(record_kv), layer.q_proj.register_forward_hook(record_q)]
    other_frames = torch.randn(2, 10, COND)
    with torch.no_grad():
        first = model(x, t, cond)
        second = model(x, t, cond, frame_cond=other_frames)
    for hook in hooks:
        hook.remove()
    assert captured["kv_in"][0].shape[-1] == D  # poses only: nothing concatenated
    torch.testing.assert_close(captured["kv_out"][0], captured["kv_out"][1], atol=0, rtol=0)
    assert not torch.allclose(captured["q_out"][0], captured["q_out"][1])  # the condition enters the queries
    assert not torch.allclose(first, second)
    # Any layer: for the same pose stream, different conditions change the output only through the queries.
    hidden, cond_a, cond_b = torch.randn(2, 10, D), torch.randn(2, 10, D), torch.randn(2, 10, D)
    deep = model.layers[1]
    outputs = []
    hook = deep.kv_proj.register_forward_hook(lambda module, args, output: outputs.append(output))  # returns None
    with torch.no_grad():
        a = deep(hidden, condition=cond_a)
        b = deep(hidden, condition=cond_b)
    hook.remove()
    torch.testing.assert_close(outputs[0], outputs[1], atol=0, rtol=0)
    assert not torch.allclose(a, b)


def test_pccat_frame_conditions_default_to_the_pooled_condition_and_drop_with_cond_mask():
    model = tiny_model(conditioning="pccat")
    x, t, cond = inputs(3, 8)
    drop = torch.tensor([True, False, False])
    with torch.no_grad():
        default = model(x, t, cond)
        broadcast = model(x, t, cond, frame_cond=cond.unsqueeze(1).expand(-1, 8, -1))
        dropped = model(x, t, cond, cond_mask=drop, frame_cond=torch.randn(3, 8, COND))
        zero = model(x, t, cond, frame_cond=torch.zeros(3, 8, COND))
    torch.testing.assert_close(default, broadcast)
    torch.testing.assert_close(dropped[drop], zero[drop], atol=1e-6, rtol=0)


# ---------------------------------------------------------------------------------------------- FLAME


def test_cross_attention_uses_valid_token_features_only():
    model = tiny_model(conditioning="cross_attention")
    x, t, cond = inputs(2, 7)
    tokens = torch.randn(2, 6, TOKEN_DIM)
    token_len = torch.tensor([4, 2])
    garbage = tokens.clone()
    garbage[0, 4:] = 100 * torch.randn(2, TOKEN_DIM)
    garbage[1, 2:] = 100 * torch.randn(4, TOKEN_DIM)
    other_valid = tokens.clone()
    other_valid[1, 1] += 1.0
    drop = torch.tensor([False, True])
    with torch.no_grad():
        out = model(x, t, cond, text_tokens=tokens, text_token_len=token_len)
        padded_changed = model(x, t, cond, text_tokens=garbage, text_token_len=token_len)
        valid_changed = model(x, t, cond, text_tokens=other_valid, text_token_len=token_len)
        dropped = model(x, t, cond, cond_mask=drop, text_tokens=tokens, text_token_len=token_len)
        dropped_other = model(x, t, cond, cond_mask=drop, text_tokens=other_valid, text_token_len=token_len)
        no_tokens = model(x, t, cond, text_tokens=tokens, text_token_len=torch.tensor([0, 0]))
    torch.testing.assert_close(padded_changed, out, atol=1e-6, rtol=0)
    torch.testing.assert_close(valid_changed[0], out[0], atol=1e-6, rtol=0)
    assert not torch.allclose(valid_changed[1], out[1])
    torch.testing.assert_close(dropped_other, dropped, atol=1e-6, rtol=0)  # a dropped text hides its tokens
    assert torch.isfinite(no_tokens).all()  # the auxiliary tokens keep every memory row non-empty


@pytest.mark.parametrize("norm_first", [False, True])
def test_cross_attention_layer_matches_torch_transformer_decoder_layer(norm_first):
    model = tiny_model(conditioning="cross_attention", norm_first=norm_first)
    ours = model.layers[0]
    reference = nn.TransformerDecoderLayer(D, 4, 64, dropout=0.0, activation="gelu", batch_first=True,
                                           norm_first=norm_first).eval()
    with torch.no_grad():
        reference.self_attn.in_proj_weight.copy_(ours.qkv.weight)
        reference.self_attn.in_proj_bias.copy_(ours.qkv.bias)
        reference.self_attn.out_proj.load_state_dict(ours.out_proj.state_dict())
        reference.multihead_attn.in_proj_weight.copy_(torch.cat([ours.cross_q.weight, ours.cross_kv.weight]))
        reference.multihead_attn.in_proj_bias.copy_(torch.cat([ours.cross_q.bias, ours.cross_kv.bias]))
        reference.multihead_attn.out_proj.load_state_dict(ours.cross_out.state_dict())
        for theirs, mine in (("norm1", "norm1"), ("norm2", "norm_cross"), ("norm3", "norm2"),
                             ("linear1", "linear1"), ("linear2", "linear2")):
            getattr(reference, theirs).load_state_dict(getattr(ours, mine).state_dict())
    tgt, memory = torch.randn(3, 9, D), torch.randn(3, 5, D)
    valid = valid_frame_mask(torch.tensor([9, 6, 2]), 9)
    memory_valid = valid_frame_mask(torch.tensor([5, 3, 1]), 5)
    with torch.no_grad():
        expected = reference(tgt, memory, tgt_key_padding_mask=~valid, memory_key_padding_mask=~memory_valid)
        got = ours(tgt, valid[:, None, None, :], memory=memory, memory_mask=memory_valid[:, None, None, :])
    torch.testing.assert_close(got[valid], expected[valid], atol=1e-5, rtol=1e-5)


# ---------------------------------------------------------------------------------------------- every variant


@pytest.mark.parametrize("variant", VARIANTS, ids=variant_id)
def test_every_variant_trains_and_samples(variant):
    model = tiny_model(seed=1, attention_horizon=4, **variant)
    batch, frames = 4, 12
    generator = torch.Generator().manual_seed(3)
    x1 = torch.randn(batch, frames, FEATURES, generator=generator).cumsum(1) * 0.3  # smooth-ish toy motions
    cond = torch.randn(batch, COND, generator=generator)
    lengths = torch.tensor([12, 9, 7, 12])
    extras = extra_inputs(model, batch)
    bound = functools.partial(model, **extras)
    fixed = dict(t=torch.rand(batch, generator=generator), x0=torch.randn(x1.shape, generator=generator),
                 cond_mask=torch.zeros(batch, dtype=torch.bool))

    def eval_loss() -> float:
        model.eval()
        with torch.no_grad():
            return flow_matching_loss(bound, x1, cond, lengths, **fixed)[0].item()

    before = eval_loss()
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    train_generator = torch.Generator().manual_seed(0)
    model.train()
    for _ in range(25):
        loss, _ = flow_matching_loss(bound, x1, cond, lengths, generator=train_generator)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    after = eval_loss()
    assert after < 0.8 * before, (before, after)

    model.eval()
    result = sample(BoundInputs(model, extras), cond, lengths, num_frames=frames, steps=3, guidance=2.0, seed=0)
    assert result.x1.shape == (batch, frames, FEATURES) and result.nfe == 3
    assert torch.isfinite(result.x1).all()
    assert torch.count_nonzero(result.x1[1, 9:]) == 0


@pytest.mark.parametrize("variant", VARIANTS, ids=variant_id)
def test_padding_does_not_change_valid_frames_in_any_variant(variant):
    model = tiny_model(attention_horizon=3, **variant)
    lengths = torch.tensor([10, 7, 4])
    x, t, cond = inputs(3, 10)
    extras = extra_inputs(model, 3)
    if model.config.conditioning == "pccat":
        extras["frame_cond"] = torch.randn(3, 10, COND)
    if model.config.positional == "bpe":
        extras["segments"] = torch.tensor([0] * 3 + [1] * 7).expand(3, -1)
        extras["positional_mode"] = torch.tensor([True, False, True])
    garbage = x.clone()
    garbage[1, 7:], garbage[2, 4:] = 1e3, -1e3
    with torch.no_grad():
        padded = model(x, t, cond, lengths, **extras)
        torch.testing.assert_close(model(garbage, t, cond, lengths, **extras), padded, atol=1e-5, rtol=0)
        for b, length in enumerate(lengths.tolist()):
            alone = {name: value[b : b + 1, :length] if name in ("frame_cond", "segments") else value[b : b + 1]
                     for name, value in extras.items()}
            out = model(x[b : b + 1, :length], t[b : b + 1], cond[b : b + 1], **alone)
            torch.testing.assert_close(padded[b, :length], out[0], atol=1e-5, rtol=1e-5)
            assert torch.count_nonzero(padded[b, length:]) == 0


@pytest.mark.parametrize("variant", VARIANTS, ids=variant_id)
def test_every_parameter_of_every_variant_gets_a_gradient(variant):
    """DDP without find_unused_parameters needs every parameter in the graph."""
    model = tiny_model(cond_drop_prob=0.0, **variant).train()
    x, t, cond = inputs(2, 6)
    model(x, t, cond, torch.tensor([6, 4]), generator=torch.Generator().manual_seed(0),
          **extra_inputs(model, 2)).square().sum().backward()
    missing = [name for name, p in model.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert not missing


@pytest.mark.parametrize("variant", VARIANTS[3:6], ids=variant_id)
def test_bf16_autocast_variants_are_finite_and_close_to_fp32(variant):
    model = tiny_model(latent_dim=64, ff_dim=128, **variant)
    batch, frames = 3, 30
    x, t, cond = inputs(batch, frames)
    lengths = torch.tensor([30, 20, 9])
    kwargs = extra_inputs(model, batch)
    kwargs.update(segments=torch.arange(frames).div(10, rounding_mode="floor").expand(batch, -1),
                  positional_mode=torch.tensor([True, False, True]))
    with torch.no_grad():
        reference = model(x, t, cond, lengths, **kwargs)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            low = model(x, t, cond, lengths, **kwargs)
            low_chunked = model(x, t, cond, lengths, attention_chunk=8, **kwargs)
    assert low.dtype == torch.float32 and torch.isfinite(low).all() and torch.isfinite(low_chunked).all()
    assert (low - reference).norm() / reference.norm() < 0.03
    assert (low_chunked - reference).norm() / reference.norm() < 0.03


# ---------------------------------------------------------------------------------------------- FLAME's null condition


@pytest.mark.parametrize("conditioning", ["prefix", "pccat", "cross_attention"])
def test_empty_caption_null_condition_is_the_encoding_of_the_empty_caption(conditioning):
    """FLAME drops a caption by encoding "" instead: a dropped sample must equal the same sample conditioned on the
    stored empty-caption encoding, and the buffers must travel with the weights."""
    num_tokens = 6
    model = tiny_model(conditioning=conditioning, null_condition="empty_caption", null_tokens=num_tokens,
                       cond_drop_prob=0.25)
    generator = torch.Generator().manual_seed(3)
    empty_pooled = torch.randn(COND, generator=generator)
    empty_tokens = torch.zeros(num_tokens, TOKEN_DIM)
    empty_tokens[:2] = torch.randn(2, TOKEN_DIM, generator=generator)  # "" is SOS/EOS: two valid tokens
    model.set_null_condition(empty_pooled, empty_tokens if conditioning == "cross_attention" else None,
                             2 if conditioning == "cross_attention" else None)
    x, t, cond = inputs(3, 10)
    extras = extra_inputs(model, 3, num_tokens=num_tokens)
    dropped = torch.tensor([True, False, True])
    with torch.no_grad():
        out = model(x, t, cond, cond_mask=dropped, **extras)
        as_empty = dict(extras)
        empty_cond = torch.where(dropped[:, None], empty_pooled, cond)
        if conditioning == "cross_attention":
            as_empty["text_tokens"] = torch.where(dropped[:, None, None], empty_tokens, extras["text_tokens"])
            as_empty["text_token_len"] = torch.where(dropped, torch.tensor(2), extras["text_token_len"])
        expected = model(x, t, empty_cond, **as_empty)
        torch.testing.assert_close(out, expected)
        zeroed = tiny_model(conditioning=conditioning, null_condition="zero", cond_drop_prob=0.25)
        zeroed.load_state_dict({k: v for k, v in model.state_dict().items() if not k.startswith("null_text")})
        assert not torch.allclose(zeroed(x, t, cond, cond_mask=dropped, **extras)[0], out[0])  # not MDM's zeros
        assert torch.equal(zeroed(x, t, cond, cond_mask=dropped, **extras)[1], out[1])  # kept samples alike
    reloaded = tiny_model(seed=5, conditioning=conditioning, null_condition="empty_caption", null_tokens=num_tokens)
    reloaded.load_state_dict(model.state_dict())  # the empty caption's encoding is saved with the weights
    assert torch.equal(reloaded.null_text, empty_pooled)
    with pytest.raises(ValueError, match="needs ModelConfig.null_condition='empty_caption'"):
        zeroed.set_null_condition(empty_pooled)
    with pytest.raises(ValueError, match="null_condition must be one of"):
        tiny_config(null_condition="learned")


def test_a_sinusoidal_length_token_embeds_every_length_and_nearby_lengths_alike():
    torch.manual_seed(0)
    config = ModelConfig(feature_dim=8, latent_dim=32, ff_dim=64, num_layers=1, num_heads=2, cond_dim=4,
                         length_token=True, length_embedding="sinusoidal", max_frames=64)
    model = MotionFlowTransformer(config).eval()
    tokens = model.length_embedding(torch.tensor([40, 41, 60]))
    assert (tokens[0] - tokens[1]).norm() < (tokens[0] - tokens[2]).norm()
    x = torch.randn(2, 50, 8)
    out = model(x, torch.rand(2), torch.randn(2, 4), torch.tensor([50, 37]))
    assert out.shape == (2, 50, 8) and torch.isfinite(out).all()
    with pytest.raises(ValueError, match="length_embedding"):
        ModelConfig(length_token=True, length_embedding="table")


def test_progress_positions_tell_frames_where_they_lie_in_their_motion_whatever_the_padding():
    torch.manual_seed(0)
    config = ModelConfig(feature_dim=8, latent_dim=32, ff_dim=64, num_layers=2, num_heads=2, cond_dim=4,
                         progress_positions=True, dropout=0.0, prediction="data")
    model = MotionFlowTransformer(config).eval()
    x, t, cond = torch.randn(1, 30, 8), torch.rand(1), torch.randn(1, 4)
    alone = model(x, t, cond, torch.tensor([30]))
    padded = model(torch.cat([x, torch.randn(1, 12, 8)], dim=1), t, cond, torch.tensor([30]))
    assert torch.allclose(alone, padded[:, :30], atol=1e-5)
    # The same frames as the first 30 of a longer motion lie elsewhere in it: a different output.
    longer = model(torch.cat([x, torch.randn(1, 12, 8)], dim=1), t, cond, torch.tensor([42]))
    assert not torch.allclose(alone, longer[:, :30], atol=1e-3)
    plain = MotionFlowTransformer(dataclasses.replace(config, progress_positions=False)).eval()
    plain.load_state_dict(model.state_dict())
    assert not torch.allclose(plain(x, t, cond, torch.tensor([30])), alone, atol=1e-4)
    with pytest.raises(ValueError, match="progress_positions"):
        ModelConfig(progress_positions=True, positional="bpe")


def test_frames_per_token_groups_consecutive_frames_into_one_token():
    config = tiny_config(conditioning="cross_attention", length_token=True, progress_positions=True,
                         prediction="data", frames_per_token=3)
    torch.manual_seed(0)
    model = MotionFlowTransformer(config).eval()
    assert model.input_proj.in_features == 3 * FEATURES and model.output_proj.out_features == 3 * FEATURES
    frames = torch.arange(2 * 7 * FEATURES, dtype=torch.float32).reshape(2, 7, FEATURES)
    grouped = model._group_frames(frames, valid_frame_mask(torch.tensor([7, 5]), 7))
    assert grouped.shape == (2, 3, 3 * FEATURES)
    assert torch.equal(grouped[0, 1], frames[0, 3:6].reshape(-1))
    # Frame 6 shares its token with the padding beyond it (zeros); sample 1's frames 5-6 are padding, zeroed.
    assert torch.equal(grouped[0, 2], torch.cat([frames[0, 6], torch.zeros(2 * FEATURES)]))
    assert torch.equal(grouped[1, 1], torch.cat([frames[1, 3:5].reshape(-1), torch.zeros(FEATURES)]))

    # The layers see ceil(T / 3) frame tokens after the auxiliary ones.
    seen = []
    model.layers[0].register_forward_hook(lambda module, args, out: seen.append(args[0].shape[1]))
    x, t, cond = torch.randn(2, 20, FEATURES), torch.rand(2), torch.randn(2, COND)
    lengths = torch.tensor([20, 13])
    out = model(x, t, cond, lengths, **extra_inputs(model, 2))
    assert out.shape == (2, 20, FEATURES) and seen == [7 + config.num_prefix_tokens]
    assert torch.all(out[1, 13:] == 0) and torch.isfinite(out).all()

    # Padding never reaches a valid frame, even inside a valid frame's token: other padding content, more padding.
    repadded = x.clone()
    repadded[1, 13:] = 100.0
    extra = extra_inputs(model, 2)
    same = model(repadded, t, cond, lengths, **extra)
    longer = model(torch.cat([repadded, torch.randn(2, 4, FEATURES)], dim=1), t, cond, lengths, **extra)
    reference = model(x, t, cond, lengths, **extra)
    assert torch.allclose(same[1, :13], reference[1, :13], atol=1e-5)
    assert torch.allclose(longer[:, :20], reference, atol=1e-5)
    # Frame 12 is valid: changing it changes the outputs of its own token's frames.
    moved = x.clone()
    moved[1, 12] += 1.0
    assert not torch.allclose(model(moved, t, cond, lengths, **extra)[1, 12], reference[1, 12], atol=1e-4)

    for bad in (dict(frames_per_token=0), dict(frames_per_token=2, positional="bpe"),
                dict(frames_per_token=2, conditioning="pccat"), dict(frames_per_token=2, attend_padding=True)):
        with pytest.raises(ValueError, match="frames_per_token"):
            tiny_config(**bad)


# ---------------------------------------------------------------------------------------------- adaptive norm (DiT)


def test_adaptive_norm_starts_as_the_plain_network_or_with_identity_blocks():
    plain = tiny_model(norm_first=True, conditioning="cross_attention", length_token=True)
    x, t, cond = inputs(2, 9)
    lengths = torch.tensor([9, 6])
    extras = extra_inputs(plain, 2)
    torch.manual_seed(0)
    adaln = MotionFlowTransformer(tiny_config(norm_first=True, conditioning="cross_attention", length_token=True,
                                              adaptive_norm="adaln")).eval()
    # Built without drawing from the RNG: same seed, same weights for everything the plain network has.
    shared = adaln.state_dict()
    assert all(torch.equal(value, shared[name]) for name, value in plain.state_dict().items())
    assert {name for name in shared if name not in plain.state_dict()} == (
        {f"layers.{i}.modulation.{p}" for i in range(LAYERS) for p in ("weight", "bias")}
        | {"final_modulation.weight", "final_modulation.bias"})
    with torch.no_grad():
        assert torch.equal(adaln(x, t, cond, lengths, **extras), plain(x, t, cond, lengths, **extras))

    torch.manual_seed(0)
    zero = MotionFlowTransformer(tiny_config(norm_first=True, conditioning="cross_attention", length_token=True,
                                             adaptive_norm="adaln_zero")).eval()
    seen = []
    for layer in zero.layers:
        layer.register_forward_hook(lambda module, args, out: seen.append(torch.equal(args[0], out)))
    with torch.no_grad():
        zero(x, t, cond, lengths, **extras)
    assert seen == [True] * LAYERS  # every gate is 0: each layer passes its tokens through


def test_adaln_zero_layer_modulates_each_block_with_shift_scale_and_gate():
    model = tiny_model(norm_first=True, adaptive_norm="adaln_zero")
    layer = model.layers[0]
    h, c = torch.randn(2, 5, D), torch.randn(2, D)
    mods = layer.modulation(F.silu(c)).view(2, 2, 3, 1, D)  # (blocks: attention, ff) x (shift, scale, gate)
    with torch.no_grad():
        attention = DenseAttention(None)
        shift, scale, gate = mods[:, 0].unbind(1)
        h1 = h + gate * layer._attention(layer.norm1(h) * (1 + scale) + shift, attention, None)
        shift, scale, gate = mods[:, 1].unbind(1)
        expected = h1 + gate * layer._feed_forward(layer.norm2(h1) * (1 + scale) + shift)
        torch.testing.assert_close(layer(h, None, norm_condition=c), expected)
        # Another condition, the same tokens: the block's output changes (the condition reaches every token).
        assert not torch.allclose(layer(h, None, norm_condition=c + 1), expected, atol=1e-4)
    with pytest.raises(ValueError, match="norm_condition"):
        layer(h, None)
    with pytest.raises(ValueError, match="norm_condition"):
        tiny_model(norm_first=True).layers[0](h, None, norm_condition=c)


@pytest.mark.parametrize("adaptive_norm", ["adaln", "adaln_zero"])
def test_adaptive_norm_condition_is_time_plus_the_pooled_condition_and_drops_with_it(adaptive_norm):
    model = tiny_model(norm_first=True, adaptive_norm=adaptive_norm, length_token=True)
    x, t, cond = inputs(2, 8)
    lengths = torch.tensor([8, 5])
    seen = []
    model.layers[0].register_forward_hook(
        lambda module, args, kwargs, out: seen.append(kwargs["norm_condition"]), with_kwargs=True)
    dropped = torch.tensor([True, False])
    with torch.no_grad():
        out = model(x, t, cond, lengths, cond_mask=dropped)
        # A dropped caption modulates as the null condition (the zeroed embedding's projection), as its prefix token.
        zeroed = cond.clone()
        zeroed[0] = 0
        torch.testing.assert_close(out, model(x, t, zeroed, lengths))
        time = model.time_embedding(t)
        expected = model.length_embedding(lengths) + time + model.cond_proj(model._scaled_text(zeroed))
    torch.testing.assert_close(seen[0], expected)


@pytest.mark.parametrize("overrides", [
    dict(adaptive_norm="film"),
    dict(adaptive_norm="adaln"),  # post-norm (norm_first=False)
    dict(adaptive_norm="adaln", norm_first=True, positional="bpe"),
    dict(adaptive_norm="adaln_zero", norm_first=True, conditioning="pccat"),
])
def test_adaptive_norm_is_refused_where_it_does_not_apply(overrides):
    with pytest.raises(ValueError, match="adaptive_norm"):
        tiny_config(**overrides)
