import math

import pytest
import torch
from torch import nn
from torch.nn import functional as F

from mfm.model import (
    ModelConfig,
    MotionFlowTransformer,
    count_parameters,
    draw_cond_drop_mask,
    scaled_dot_product_attention,
    sinusoidal_embedding,
    valid_frame_mask,
)

# MFM's MDM_Flow (HumanML3D, text) without CLIP, counted layer by layer from nn.Linear / nn.TransformerEncoderLayer.
HUMANML3D_PARAMETERS = 17_880_327


def tiny_config(**overrides) -> ModelConfig:
    values = dict(feature_dim=7, latent_dim=32, ff_dim=64, num_layers=2, num_heads=4, cond_dim=5)
    values.update(max_len=128, max_frames=32)
    values.update(overrides)
    return ModelConfig(**values)


def tiny_model(seed: int = 0, **overrides) -> MotionFlowTransformer:
    torch.manual_seed(seed)
    return MotionFlowTransformer(tiny_config(**overrides))


def mdm_sinusoid_table(max_len: int, dim: int) -> torch.Tensor:
    """MDM's PositionalEncoding table, written out independently of mfm.model."""
    table = torch.zeros(max_len, dim)
    position = torch.arange(0, max_len, dtype=torch.float).unsqueeze(1)
    div_term = torch.exp(torch.arange(0, dim, 2).float() * (-math.log(10000.0) / dim))
    table[:, 0::2] = torch.sin(position * div_term)
    table[:, 1::2] = torch.cos(position * div_term)
    return table


# ---------------------------------------------------------------------------------------------- configuration


def test_humanml3d_preset_has_mfm_parameter_count():
    model = MotionFlowTransformer(ModelConfig(feature_dim=263, cond_dim=512))
    d, ff, layers, features = 512, 1024, 8, 263
    linear = lambda i, o: i * o + o  # noqa: E731
    per_layer = linear(d, 3 * d) + linear(d, d) + linear(d, ff) + linear(ff, d) + 2 * 2 * d
    expected = linear(features, d) + 2 * linear(d, d) + linear(512, d) + layers * per_layer + linear(d, features)
    assert expected == HUMANML3D_PARAMETERS
    assert count_parameters(model) == HUMANML3D_PARAMETERS
    assert round(count_parameters(model) / 1e6, 2) == 17.88  # the paper / reference figure


def test_pre_norm_adds_only_a_final_layer_norm():
    post = count_parameters(MotionFlowTransformer(tiny_config()))
    pre = count_parameters(MotionFlowTransformer(tiny_config(norm_first=True)))
    assert pre - post == 2 * 32


@pytest.mark.parametrize(
    "overrides, field",
    [
        (dict(latent_dim=30, num_heads=4), "latent_dim"),
        (dict(num_layers=0), "num_layers"),
        (dict(dropout=1.0), "dropout"),
        (dict(cond_drop_prob=-0.1), "cond_drop_prob"),
        (dict(activation="tanh"), "activation"),
        (dict(cond_dim=0), "cond_dim"),
        (dict(num_actions=-1), "num_actions"),
        (dict(length_token=True, max_frames=200, max_len=100), "max_frames"),
        (dict(prediction="epsilon"), "prediction"),
        (dict(prediction="data", output_dim=14), "output_dim"),
        (dict(cond_scaling="layernorm"), "cond_scaling"),
        (dict(output_smoothing=-0.5), "output_smoothing"),
        (dict(sampling_guidance=-1.0), "sampling_guidance"),
        (dict(guided_features="root"), "guided_features"),
        (dict(sampling_guidance=float("nan")), "sampling_guidance"),
    ],
)
def test_config_rejects_bad_values(overrides, field):
    with pytest.raises(ValueError, match=field):
        tiny_config(**overrides)


def test_forward_rejects_bad_shapes():
    model = tiny_model().eval()
    x, t, cond = torch.randn(2, 6, 7), torch.rand(2), torch.randn(2, 5)
    with pytest.raises(ValueError, match="x must be"):
        model(torch.randn(2, 6, 8), t, cond)
    with pytest.raises(ValueError, match="t must be"):
        model(x, torch.rand(3), cond)
    with pytest.raises(ValueError, match="cond must be"):
        model(x, t, torch.randn(2, 4))
    with pytest.raises(ValueError, match="cond_mask"):
        model(x, t, cond, cond_mask=torch.tensor([1, 0]))
    with pytest.raises(ValueError, match="max_len"):
        model(torch.randn(2, 128, 7), t, cond)


# ---------------------------------------------------------------------------------------------- encoder parity


@pytest.mark.parametrize("norm_first", [False, True])
def test_encoder_layer_matches_torch_transformer_encoder_layer(norm_first):
    """Our SDPA layer computes what MDM's nn.TransformerEncoderLayer computes, with the same parameters."""
    model = tiny_model(norm_first=norm_first).eval()
    ours = model.layers[0]
    reference = nn.TransformerEncoderLayer(
        32, 4, 64, dropout=0.1, activation="gelu", batch_first=True, norm_first=norm_first
    ).eval()
    with torch.no_grad():
        reference.self_attn.in_proj_weight.copy_(ours.qkv.weight)
        reference.self_attn.in_proj_bias.copy_(ours.qkv.bias)
        reference.self_attn.out_proj.load_state_dict(ours.out_proj.state_dict())
        for name in ("linear1", "linear2", "norm1", "norm2"):
            getattr(reference, name).load_state_dict(getattr(ours, name).state_dict())
    tokens = torch.randn(3, 9, 32)
    valid = valid_frame_mask(torch.tensor([9, 6, 2]), 9)
    with torch.no_grad():
        expected = reference(tokens, src_key_padding_mask=~valid)
        got = ours(tokens, valid[:, None, None, :])
    torch.testing.assert_close(got[valid], expected[valid], atol=1e-5, rtol=1e-5)


# ---------------------------------------------------------------------------------------------- padding


@pytest.mark.parametrize("overrides", [{}, {"norm_first": True}, {"length_token": True, "max_frames": 16}])
def test_padding_does_not_change_valid_frames(overrides):
    model = tiny_model(**overrides).eval()
    lengths = torch.tensor([10, 7, 4])
    x = torch.randn(3, 10, 7)
    t, cond = torch.rand(3), torch.randn(3, 5)
    with torch.no_grad():
        padded = model(x, t, cond, lengths)
        for b, length in enumerate(lengths.tolist()):
            alone = model(x[b : b + 1, :length], t[b : b + 1], cond[b : b + 1])
            torch.testing.assert_close(padded[b, :length], alone[0], atol=1e-5, rtol=0)
            assert torch.count_nonzero(padded[b, length:]) == 0


def test_garbage_in_padding_is_ignored():
    model = tiny_model().eval()
    lengths = torch.tensor([8, 3])
    x, t, cond = torch.randn(2, 8, 7), torch.rand(2), torch.randn(2, 5)
    noisy = x.clone()
    noisy[1, 3:] = 1e3 * torch.randn(5, 7)
    with torch.no_grad():
        torch.testing.assert_close(model(x, t, cond, lengths), model(noisy, t, cond, lengths), atol=1e-6, rtol=0)


# ---------------------------------------------------------------------------------------------- time embedding


def test_sinusoid_equals_mdm_table_at_integer_positions():
    table = mdm_sinusoid_table(1001, 32)
    torch.testing.assert_close(sinusoidal_embedding(torch.arange(1001), 32), table, atol=1e-5, rtol=0)


def test_time_embedding_matches_mfm_lookup_at_grid_points_and_is_continuous_between():
    model = tiny_model().eval()
    table = mdm_sinusoid_table(1001, 32)
    steps = torch.tensor([0, 1, 250, 999, 1000])
    with torch.no_grad():
        # MFM: time_embed(pe[(t * 1000).long()]) — identical where t*1000 is an integer.
        torch.testing.assert_close(
            model.time_embedding(steps / 1000.0), model.time_embedding.mlp(table[steps]), atol=2e-4, rtol=0
        )
        # Between grid points MFM's rounding would return the same embedding; ours moves, smoothly.
        t = torch.tensor([0.5, 0.5 + 1e-4, 0.5 + 2e-4])
        emb = model.time_embedding(t)
    first, second = (emb[1] - emb[0]).abs().max(), (emb[2] - emb[1]).abs().max()
    assert first > 0
    assert torch.isclose(first, second, rtol=0.1)  # locally linear in t, no jumps
    # The sinusoid moves at most |Δ(t*1000)| = 0.1 per channel (unit frequency at most): no jump.
    step = (sinusoidal_embedding(t[1:] * 1000, 32) - sinusoidal_embedding(t[:1] * 1000, 32)).abs().max()
    assert 0 < step <= 0.2 + 1e-4


def test_velocity_changes_with_sub_grid_time():
    model = tiny_model().eval()
    x, cond = torch.randn(1, 5, 7), torch.randn(1, 5)
    with torch.no_grad():
        a = model(x, torch.tensor([0.3]), cond)
        b = model(x, torch.tensor([0.3 + 3e-4]), cond)  # same (t*1000).long() bucket
    assert not torch.equal(a, b)


# ---------------------------------------------------------------------------------------------- conditioning


def test_cond_drop_mask_rate():
    generator = torch.Generator().manual_seed(1)
    mask = draw_cond_drop_mask(20_000, 0.1, generator)
    assert mask.dtype == torch.bool and mask.shape == (20_000,)
    assert abs(mask.float().mean().item() - 0.1) < 0.008  # ~4 standard deviations


def test_cond_mask_true_equals_zero_condition():
    model = tiny_model().eval()
    x, t, cond = torch.randn(4, 6, 7), torch.rand(4), torch.randn(4, 5)
    drop = torch.tensor([True, False, True, False])
    with torch.no_grad():
        dropped = model(x, t, cond, cond_mask=drop)
        zero = model(x, t, torch.zeros_like(cond))
        kept = model(x, t, cond)
    torch.testing.assert_close(dropped[drop], zero[drop], atol=1e-6, rtol=0)
    torch.testing.assert_close(dropped[~drop], kept[~drop], atol=1e-6, rtol=0)
    assert not torch.allclose(zero, kept)


def test_training_drops_condition_per_sample_from_the_generator():
    batch = 2000
    model = tiny_model(dropout=0.0, cond_drop_prob=0.1)
    x, t, cond = torch.randn(batch, 2, 7), torch.rand(batch), torch.randn(batch, 5)
    with torch.no_grad():
        model.eval()
        kept = model(x, t, cond)
        zero = model(x, t, torch.zeros_like(cond))
        model.train()
        trained = model(x, t, cond, generator=torch.Generator().manual_seed(3))
        overridden = model(x, t, cond, cond_mask=torch.zeros(batch, dtype=torch.bool))
    expected_drop = draw_cond_drop_mask(batch, 0.1, torch.Generator().manual_seed(3))
    torch.testing.assert_close(trained[expected_drop], zero[expected_drop], atol=1e-6, rtol=0)
    torch.testing.assert_close(trained[~expected_drop], kept[~expected_drop], atol=1e-6, rtol=0)
    assert 0.08 < expected_drop.float().mean().item() < 0.12
    torch.testing.assert_close(overridden, kept, atol=1e-6, rtol=0)  # an explicit cond_mask wins


def test_no_condition_dropout_in_eval_mode():
    model = tiny_model(cond_drop_prob=0.5).eval()
    x, t, cond = torch.randn(64, 3, 7), torch.rand(64), torch.randn(64, 5)
    with torch.no_grad():
        torch.testing.assert_close(
            model(x, t, cond, generator=torch.Generator().manual_seed(0)),
            model(x, t, cond, cond_mask=torch.zeros(64, dtype=torch.bool)),
        )


def test_data_prediction_returns_the_velocity_towards_its_output():
    """prediction='data': forward(x_t, t) = (x̂1 − (1 − σ)·x_t) / (1 − (1 − σ)·t), x̂1 being the network output."""
    torch.manual_seed(0)
    velocity_model = tiny_model(prediction="velocity").eval()
    data_model = tiny_model(prediction="data").eval()
    data_model.load_state_dict(velocity_model.state_dict())  # same network: its raw output is x̂1 for data_model
    x, cond = torch.randn(3, 6, 7), torch.randn(3, 5)
    t = torch.tensor([0.0, 0.5, 0.99])
    with torch.no_grad():
        x1_hat = velocity_model(x, t, cond)
        velocity = data_model(x, t, cond)
    sigma = 1e-4
    noise_scale = torch.clamp(1 - (1 - sigma) * t, min=0.05)[:, None, None]  # floored near t = 1
    torch.testing.assert_close(velocity, (x1_hat - (1 - sigma) * x) / noise_scale)
    # One Euler step from t over the rest of the path lands on x̂1 (up to σ, while the floor is not reached).
    torch.testing.assert_close(x[:2] + (1 - t[:2, None, None]) * velocity[:2], x1_hat[:2], atol=1e-3, rtol=0)


def test_preconditioned_prediction_is_data_prediction_at_the_start_and_a_skip_at_the_end():
    """prediction='preconditioned': x̂1 = c_skip·x_t + c_out·F(c_in·x_t) (mfm.path.preconditioning), F being the
    network of a velocity model with the same weights fed c_in·x_t."""
    torch.manual_seed(0)
    velocity_model = tiny_model(prediction="velocity").eval()
    model = tiny_model(prediction="preconditioned").eval()
    model.load_state_dict(velocity_model.state_dict())
    x, cond = torch.randn(3, 6, 7), torch.randn(3, 5)
    t = torch.tensor([0.0, 0.5, 0.9])
    sigma = 1e-4
    a = 1 - (1 - sigma) * t
    norm = (a.square() + t.square()).sqrt()[:, None, None]
    c_in, c_skip, c_out = 1 / norm, t[:, None, None] / norm.square(), a[:, None, None] / norm
    with torch.no_grad():
        network = velocity_model(x * c_in, t, cond)
        velocity = model(x, t, cond)
    x1_hat = c_skip * x + c_out * network
    torch.testing.assert_close(velocity, (x1_hat - (1 - sigma) * x) / a[:, None, None], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(c_skip[0], torch.zeros(1, 1))  # t = 0: x1 prediction (c_in = c_out = 1)
    # the target of F has unit variance at every t for unit-variance x0, x1: c_skip² (a² + t²) − 2 c_skip t + 1 = c_out²
    torch.testing.assert_close((c_skip.square() * norm.square() - 2 * c_skip * t[:, None, None] + 1), c_out.square())


def test_rms_condition_scaling_makes_the_condition_scale_free_and_keeps_the_null_condition():
    model = tiny_model(cond_scaling="rms").eval()
    x, t, cond = torch.randn(4, 6, 7), torch.rand(4), torch.randn(4, 5)
    drop = torch.tensor([True, False, True, False])
    with torch.no_grad():
        base = model(x, t, cond)
        torch.testing.assert_close(model(x, t, 0.01 * cond), base)  # a unit-norm encoder's small vectors
        torch.testing.assert_close(model(x, t, cond, cond_mask=drop)[drop], model(x, t, torch.zeros_like(cond))[drop])
        rms_scaled = cond * math.sqrt(5) / cond.norm(dim=-1, keepdim=True)
        torch.testing.assert_close(model.cond_proj(rms_scaled), model._pooled_condition(cond, None))
    unscaled = tiny_model(cond_scaling="none").eval()
    with torch.no_grad():
        assert not torch.allclose(unscaled(x, t, 0.01 * cond), unscaled(x, t, cond))


def test_action_model():
    model = tiny_model(num_actions=6).eval()
    assert not hasattr(model, "cond_proj")
    assert count_parameters(model) == count_parameters(tiny_model()) - (5 * 32 + 32) + 6 * 32
    x, t = torch.randn(1, 5, 7).expand(6, 5, 7), torch.full((6,), 0.4)
    actions = torch.arange(6)
    with torch.no_grad():
        out = model(x, t, actions)
        dropped = model(x, t, actions, cond_mask=torch.ones(6, dtype=torch.bool))
    assert out.shape == (6, 5, 7)
    assert all(not torch.allclose(out[0], out[k]) for k in range(1, 6))  # each class steers the field
    torch.testing.assert_close(dropped, dropped[:1].expand_as(dropped))  # dropped: the class no longer matters
    with pytest.raises(ValueError, match="action ids"):
        model(x, t, torch.randn(6, 5))


def test_length_token():
    plain, with_token = tiny_model(), tiny_model(length_token=True, max_frames=20)
    assert count_parameters(with_token) - count_parameters(plain) == 21 * 32
    with_token.eval()
    x, t, cond, lengths = torch.randn(2, 10, 7), torch.rand(2), torch.randn(2, 5), torch.tensor([10, 6])
    with torch.no_grad():
        before = with_token(x, t, cond, lengths)
        torch.testing.assert_close(with_token(x, t, cond), with_token(x, t, cond, torch.tensor([10, 10])))
        with_token.length_embedding.weight[6] += 1.0  # only sample 1 embeds length 6
        after = with_token(x, t, cond, lengths)
    torch.testing.assert_close(after[0], before[0])
    assert not torch.allclose(after[1, :6], before[1, :6])
    with pytest.raises(ValueError, match="max_frames"):
        with_token(torch.randn(1, 21, 7), t[:1], cond[:1])


# ---------------------------------------------------------------------------------------------- precision, grads


def test_bf16_autocast_is_finite_and_close_to_fp32():
    torch.manual_seed(0)
    model = MotionFlowTransformer(
        ModelConfig(feature_dim=263, latent_dim=128, ff_dim=256, num_layers=4, num_heads=4, cond_dim=512)
    ).eval()
    x, t, cond = torch.randn(3, 40, 263), torch.rand(3), torch.randn(3, 512)
    lengths = torch.tensor([40, 25, 9])
    with torch.no_grad():
        reference = model(x, t, cond, lengths)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            low = model(x, t, cond, lengths)
    assert low.dtype == torch.float32  # returned in x's dtype for the ODE solver
    assert torch.isfinite(low).all()
    relative = (low - reference).norm() / reference.norm()
    assert relative < 0.03, relative


def test_cpu_attention_under_bf16_autocast_runs_in_fp32_and_passes_gradients():
    """In CPU training the bf16 query/key/value are attended in fp32 (PyTorch's bf16 flash backward there is the
    slower): under autocast the result is the fp32 attention cast to bf16, exactly, not the bf16 kernel's, and the
    gradient reaches the bf16 inputs in bf16. Without a gradient (sampling) the bf16 kernel, the faster forward,
    runs; fp32 inputs go to PyTorch's kernel unchanged."""
    torch.manual_seed(0)
    q, k, v = (torch.randn(2, 3, 20, 16) for _ in range(3))
    mask = torch.ones(2, 1, 20, 20, dtype=torch.bool)
    mask[1, ..., 12:] = False
    low = [x.bfloat16().requires_grad_() for x in (q, k, v)]
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = scaled_dot_product_attention(*low, attn_mask=mask)
        bf16_kernel = F.scaled_dot_product_attention(*low, attn_mask=mask)
    fp32 = F.scaled_dot_product_attention(*(x.detach().float() for x in low), attn_mask=mask)
    assert out.dtype == torch.bfloat16
    assert torch.equal(out, fp32.bfloat16())
    assert not torch.equal(out, bf16_kernel)  # the test would not see a bf16 kernel otherwise
    out.float().square().sum().backward()
    assert all(x.grad is not None and x.grad.dtype == torch.bfloat16 and x.grad.abs().sum() > 0 for x in low)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        assert torch.equal(scaled_dot_product_attention(*low, attn_mask=mask), bf16_kernel)
    assert torch.equal(scaled_dot_product_attention(q, k, v, attn_mask=mask),
                       F.scaled_dot_product_attention(q, k, v, attn_mask=mask))


@pytest.mark.parametrize("overrides", [{}, {"length_token": True}, {"num_actions": 3}])
def test_every_parameter_gets_a_gradient(overrides):
    """DDP without find_unused_parameters needs every parameter in the graph."""
    model = tiny_model(cond_drop_prob=0.0, **overrides).train()
    cond = torch.tensor([0, 2]) if overrides.get("num_actions") else torch.randn(2, 5)
    model(torch.randn(2, 6, 7), torch.rand(2), cond, torch.tensor([6, 4])).square().sum().backward()
    missing = [name for name, p in model.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert not missing
