"""mfm.flops: the model FLOPs behind MFU (counted, held to MFM's closed form and to a counted backward pass) and
the dense bf16 peak table."""

import pytest
import torch
from torch.nn.attention import SDPBackend, sdpa_kernel
from torch.utils.flop_counter import FlopCounterMode

from mfm.flops import BACKWARD_FACTOR, TrainingFlops, dense_bf16_peak, forward_flops, model_flops_utilisation
from mfm.model import ModelConfig, MotionFlowTransformer


def mfm_closed_form(config: ModelConfig, frames: int) -> float:
    """docs/performance.md's forward FLOPs of MFM's architecture (one prefix token, absolute positions): the L layers'
    per-token matmuls, the frames' input and output projections, the per-sample time MLP and text projection, and
    attention's QKᵀ and AV over S = frames + 1 tokens."""
    d, layers, tokens = config.latent_dim, config.num_layers, frames + 1
    per_token = layers * (4 * d * d + 2 * d * config.ff_dim)
    projections = config.feature_dim * d + d * config.output_size
    per_sample = 2 * d * d + config.cond_dim * d
    return 2.0 * per_token * tokens + 2.0 * projections * frames + 2.0 * per_sample + layers * 4 * tokens ** 2 * d


@pytest.mark.parametrize("frames", [196, 120])
def test_the_count_of_mfms_model_is_the_closed_form_and_three_forwards_are_its_backward_too(frames):
    torch.manual_seed(0)
    config = ModelConfig(dropout=0.0)  # the HumanML3D preset's model
    model = MotionFlowTransformer(config)
    assert forward_flops(model, frames) == mfm_closed_form(config, frames)
    x = torch.randn(1, frames, config.feature_dim, requires_grad=True)
    cond = torch.randn(1, config.cond_dim, requires_grad=True)
    with sdpa_kernel(SDPBackend.MATH), FlopCounterMode(display=False) as counter:
        model(x, torch.rand(1), cond, torch.full((1,), frames)).square().mean().backward()
    # forward + backward counted: 3 forwards but for the time MLP's first input gradient (its sinusoid needs none)
    per_sample = TrainingFlops(model).per_sample(frames)
    assert per_sample == BACKWARD_FACTOR * mfm_closed_form(config, frames)
    assert counter.get_total_flops() == pytest.approx(per_sample, rel=1e-4)
    if frames == 196:
        assert per_sample == pytest.approx(22.06e9, rel=1e-3)  # the figure docs/performance.md gives


def tiny(**variant) -> MotionFlowTransformer:
    torch.manual_seed(0)
    return MotionFlowTransformer(ModelConfig(feature_dim=12, latent_dim=32, ff_dim=64, num_layers=2, num_heads=4,
                                             cond_dim=16, max_frames=64, **variant))


def test_variants_are_counted_as_built_and_the_model_is_left_as_it_was():
    plain = forward_flops(tiny(), 40)
    assert plain == mfm_closed_form(tiny().config, 40)
    assert forward_flops(tiny(num_actions=5), 40) == plain - 2 * 16 * 32  # an action id is looked up, not projected
    assert forward_flops(tiny(positional="bpe", conditioning="pccat"), 40) > plain  # FlowMDM's per-layer condition
    # grouped frames: half the tokens, so well under the plain model's count (the closed form would not see it)
    assert forward_flops(tiny(frames_per_token=2), 40) < 0.6 * plain
    cross = tiny(conditioning="cross_attention", token_dim=24)
    short, long = forward_flops(cross, 40, text_tokens=5), forward_flops(cross, 40, text_tokens=30)
    assert plain < short < long  # the caption's tokens are attended to in every layer
    with pytest.raises(ValueError, match="text_tokens"):
        forward_flops(cross, 40)
    model = tiny(dropout=0.5, layer_dropout=0.5)
    model.train()
    weights = {k: v.clone() for k, v in model.state_dict().items()}
    rng = torch.get_rng_state()
    counted = forward_flops(model, 40)
    assert model.training and torch.equal(torch.get_rng_state(), rng)
    assert all(torch.equal(v, weights[k]) for k, v in model.state_dict().items())
    assert counted == forward_flops(tiny(dropout=0.5), 40)  # every block counted, none dropped at random


def test_training_flops_count_each_shape_once():
    flops = TrainingFlops(tiny())
    assert flops.per_sample(40) == BACKWARD_FACTOR * forward_flops(tiny(), 40)
    flops.model = None  # a second count of a known shape would need the model
    assert flops.per_sample(40) == BACKWARD_FACTOR * forward_flops(tiny(), 40)
    with pytest.raises(AttributeError):
        flops.per_sample(48)


def test_mfu_is_the_achieved_rate_over_the_peak_and_none_without_one():
    assert model_flops_utilisation(494.7e12, 989.4) == pytest.approx(0.5)
    assert model_flops_utilisation(1e12, None) is None


@pytest.mark.parametrize(("name", "peak"), [
    ("NVIDIA H100 80GB HBM3", 989.4), ("NVIDIA H100 PCIe", 756.0), ("NVIDIA H200", 989.4),
    ("NVIDIA A100-SXM4-80GB", 312.0), ("NVIDIA L4", 121.0), ("NVIDIA GeForce RTX 4090", 165.2),
    ("NVIDIA L40S", None), ("NVIDIA H100 NVL", None), ("NVIDIA H200 NVL", None), ("Tesla V100-SXM2-32GB", None),
])
def test_dense_bf16_peak_table(name, peak):
    lookup = dense_bf16_peak("cuda", name)
    assert lookup.tflops == peak and lookup.source
    cpu = dense_bf16_peak("cpu", "cpu: anything")
    assert cpu.tflops is None and "CPU" in cpu.source


def test_a_torch_device_is_looked_up_by_its_cuda_name_and_a_cpu_has_no_peak(monkeypatch):
    from mfm.flops import device_peak

    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device=None: "NVIDIA H100 80GB HBM3")
    assert device_peak("cuda:1").tflops == 989.4 and device_peak(torch.device("cuda")).source.startswith("H100 SXM")
    assert device_peak("cpu").tflops is None
