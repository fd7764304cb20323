"""Composition / extrapolation sampling (FlowMDM) with the flow-matching model."""

import json
import math

import pytest
import torch

from mfm.composition import (
    BABEL_SWITCH,
    HUMANML3D_SWITCH,
    BoundInputs,
    compose,
    extrapolate,
    flow_time_of_diffusion_step,
    read_prompt_file,
    resolve_switch,
    segment_boundaries,
    segment_index,
)
from mfm.flow import SIGMA_MIN
from mfm.model import ModelConfig, MotionFlowTransformer
from mfm.solvers import sample

FEATURES, COND, TOKEN_DIM = 7, 5, 6


def tiny_model(seed: int = 0, **overrides) -> MotionFlowTransformer:
    values = dict(feature_dim=FEATURES, latent_dim=32, ff_dim=64, num_layers=2, num_heads=4, cond_dim=COND,
                  max_len=64, max_frames=32, dropout=0.0, attention_horizon=6, token_dim=TOKEN_DIM)
    values.update(overrides)
    torch.manual_seed(seed)
    return MotionFlowTransformer(ModelConfig(**values)).eval()


def conditions(n: int, seed: int = 0) -> list[torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    return list(torch.randn(n, COND, generator=generator))


def record_modes(model: MotionFlowTransformer) -> tuple[list, torch.utils.hooks.RemovableHandle]:
    """(t, positional_mode) of every model call."""
    calls: list[tuple[torch.Tensor, torch.Tensor | None]] = []

    def hook(module, args, kwargs):
        calls.append((args[1].clone(), kwargs.get("positional_mode")))

    return calls, model.register_forward_pre_hook(hook, with_kwargs=True)


# ---------------------------------------------------------------------------------------------- prompt files


def test_reads_flowmdm_prompt_files(reference_data):
    prompts = reference_data / "prompts"
    composition = read_prompt_file(prompts / "composition_humanml.json")
    assert len(composition) == 32
    assert composition[0] == ("person walks backwards quickly, then stops.", 99)
    assert all(isinstance(text, str) and isinstance(length, int) and length > 0 for text, length in composition)
    extrapolation = read_prompt_file(prompts / "extrapolation_humanml.json")
    assert {text for text, _ in extrapolation} == {"the person is walking on the treadmill."}
    assert sum(length for _, length in extrapolation) == 3200  # far longer than any 196-frame training clip
    babel = read_prompt_file(prompts / "composition_babel.json")
    assert babel[:2] == [("turn left", 64), ("walk", 42)]
    assert min(length for _, length in babel) >= 30


@pytest.mark.parametrize(
    "content, reason",
    [
        ("{not json", "cannot read"),
        (json.dumps({"text": ["a"]}), '"lengths"'),
        (json.dumps({"text": ["a", "b"], "lengths": [10]}), "equal size"),
        (json.dumps({"text": ["a"], "lengths": [0]}), "positive int"),
        (json.dumps({"text": ["a"], "lengths": [12.5]}), "positive int"),
        (json.dumps({"text": [""], "lengths": [12]}), "non-empty string"),
    ],
)
def test_prompt_file_errors_name_the_file(tmp_path, content, reason):
    path = tmp_path / "bad.json"
    path.write_text(content)
    with pytest.raises(ValueError, match=reason) as error:
        read_prompt_file(path)
    assert "bad.json" in str(error.value)


def test_segment_layout():
    assert segment_index([2, 3, 1]).tolist() == [0, 0, 1, 1, 1, 2]
    assert segment_boundaries([2, 3, 1]) == [(0, 2), (2, 5), (5, 6)]


# ---------------------------------------------------------------------------------------------- BPE switch


def test_switch_matches_flowmdm_noise_level():
    """FlowMDM's first relative step t = 1000 − k has ᾱ = f((1001 − k)/1000) / f(0) with the cosine
    f(s) = cos²((s + 0.008)/1.008 · π/2) (the betas' product telescopes); the flow time has the same SNR."""

    def closed_form_alpha_bar(step: int) -> float:
        f = lambda s: math.cos((s + 0.008) / 1.008 * math.pi / 2) ** 2  # noqa: E731
        return f((step + 1) / 1000) / f(0.0)

    for k, switch in ((60, HUMANML3D_SWITCH), (125, BABEL_SWITCH)):
        alpha_bar = closed_form_alpha_bar(1000 - k)
        snr = math.sqrt(alpha_bar / (1 - alpha_bar))
        assert switch / (1 - (1 - SIGMA_MIN) * switch) == pytest.approx(snr, rel=1e-9)
    assert 0.05 < HUMANML3D_SWITCH < BABEL_SWITCH < 0.25
    assert flow_time_of_diffusion_step(0) == 0.0
    times = [flow_time_of_diffusion_step(k) for k in range(0, 1001, 50)]
    assert times == sorted(times) and times[-1] < 1.0


def test_resolve_switch():
    assert resolve_switch(3, 10) == pytest.approx(0.3)
    assert resolve_switch(10, 10) == math.inf and resolve_switch(1.0, 10) == math.inf
    assert resolve_switch(0, 10) == 0.0 and resolve_switch(0.25, 10) == 0.25
    for bad in (11, -1, 1.5, True):
        with pytest.raises(ValueError, match="switch"):
            resolve_switch(bad, 10)


@pytest.mark.parametrize("switch, absolute_calls", [(3, 3), (0.25, 3), (0.0, 0), (1.0, 10), (HUMANML3D_SWITCH, 1)])
def test_absolute_mode_before_the_switch_relative_after(switch, absolute_calls):
    model = tiny_model(positional="bpe", conditioning="pccat")
    calls, handle = record_modes(model)
    result = compose(model, [(c, 8) for c in conditions(2)], steps=10, switch=switch, guidance=2.5)
    handle.remove()
    assert result.nfe == len(calls) == 10  # guidance is one batched pass per evaluation
    for index, (t, mode) in enumerate(calls):
        assert t.shape == mode.shape == (2,)  # conditional + unconditional halves
        assert torch.all(t == index / 10)
        assert bool(mode.all()) == (index >= absolute_calls) and bool(mode.any()) == (index >= absolute_calls)


# ---------------------------------------------------------------------------------------------- composition


@pytest.mark.parametrize(
    "overrides, switch",
    [
        (dict(positional="bpe", conditioning="pccat"), 1.0),
        (dict(positional="bpe", conditioning="prefix"), 6),  # all 6 steps absolute
        (dict(positional="absolute", conditioning="prefix"), 0.0),  # no BPE: the switch does not apply
        (dict(positional="absolute", conditioning="pccat"), HUMANML3D_SWITCH),
    ],
)
def test_one_segment_equals_ordinary_sampling(overrides, switch):
    model = tiny_model(**overrides)
    cond = conditions(1)[0]
    composed = compose(model, [(cond, 14)], solver="midpoint", steps=6, guidance=2.5, switch=switch, seed=3)
    sampled = sample(model, cond[None], [14], num_frames=14, solver="midpoint", steps=6, guidance=2.5, seed=3)
    assert composed.motion.shape == (14, FEATURES) and composed.boundaries == [(0, 14)]
    assert composed.nfe == sampled.nfe == 12
    torch.testing.assert_close(composed.motion, sampled.x1[0], atol=1e-5, rtol=1e-5)


def test_relative_steps_change_a_single_segment():
    """Non-vacuity of the test above: with relative steps the bpe model computes something else."""
    model = tiny_model(positional="bpe", conditioning="pccat")
    cond = conditions(1)[0]
    absolute = compose(model, [(cond, 14)], steps=6, switch=1.0)
    blended = compose(model, [(cond, 14)], steps=6, switch=0.5)
    assert not torch.allclose(absolute.motion, blended.motion, atol=1e-4)


def test_segments_are_independent_in_absolute_mode_and_blend_in_relative_mode():
    model = tiny_model(positional="bpe", conditioning="pccat")
    first, second, other_second = conditions(3)
    lengths = (10, 12)
    runs = {}
    for switch in (1.0, 0.3):
        a = compose(model, [(first, lengths[0]), (second, lengths[1])], steps=10, switch=switch, seed=5)
        b = compose(model, [(first, lengths[0]), (other_second, lengths[1])], steps=10, switch=switch, seed=5)
        runs[switch] = (a, b)
    a, b = runs[1.0]
    assert a.boundaries == [(0, 10), (10, 22)]
    torch.testing.assert_close(a.segment(0), b.segment(0), atol=1e-6, rtol=0)  # never sees segment 2
    assert not torch.allclose(a.segment(1), b.segment(1))
    a, b = runs[0.3]
    assert not torch.allclose(a.segment(0), b.segment(0))  # relative steps carry the transition across
    # Each relative evaluation reaches 2 layers × horizon 6 frames across the boundary, so the change is
    # strongest next to it.
    change = (a.segment(0) - b.segment(0)).abs().amax(dim=-1)
    assert change[-3:].mean() > change[:3].mean()


def test_distinct_texts_need_pccat_and_other_misuse_is_rejected():
    cond_a, cond_b = conditions(2)
    prefix = tiny_model(positional="bpe")
    with pytest.raises(ValueError, match="pccat"):
        compose(prefix, [(cond_a, 8), (cond_b, 8)])
    same = compose(prefix, [(cond_a, 8), (cond_a, 8)], steps=2)  # one text over two segments is fine
    assert same.motion.shape == (16, FEATURES)
    with pytest.raises(ValueError, match="fixed-step"):
        compose(prefix, [(cond_a, 8)], solver="dopri5")
    with pytest.raises(ValueError, match="max_nfe"):
        compose(prefix, [(cond_a, 8)], solver="rk4", steps=13)
    with pytest.raises(ValueError, match="max_nfe"):
        compose(prefix, [(cond_a, 8)], steps=51)
    with pytest.raises(ValueError, match="positive int"):
        compose(prefix, [(cond_a, 0)])
    with pytest.raises(ValueError, match="at least one"):
        compose(prefix, [])
    with pytest.raises(ValueError, match="attention_chunk"):
        compose(tiny_model(), [(cond_a, 8)], attention_chunk=4)
    with pytest.raises(ValueError, match="text_tokens"):
        compose(tiny_model(conditioning="cross_attention"), [(cond_a, 8)])


def test_cross_attention_model_composes_one_text_with_its_tokens():
    model = tiny_model(positional="bpe", conditioning="cross_attention")
    cond = conditions(1)[0]
    tokens = torch.randn(4, TOKEN_DIM)
    result = compose(model, [(cond, 9), (cond, 7)], steps=3, text_tokens=tokens, text_token_len=3)
    other = compose(model, [(cond, 9), (cond, 7)], steps=3, text_tokens=tokens + 1.0, text_token_len=3)
    assert result.motion.shape == (16, FEATURES) and torch.isfinite(result.motion).all()
    assert not torch.allclose(result.motion, other.motion)


def test_guidance_scale_one_is_a_single_conditional_pass():
    model = tiny_model(positional="bpe", conditioning="pccat")
    calls, handle = record_modes(model)
    compose(model, [(c, 6) for c in conditions(2)], steps=4, guidance=1.0)
    handle.remove()
    assert [t.shape[0] for t, _ in calls] == [1] * 4


def test_bound_inputs_repeat_for_guidance_halves():
    model = tiny_model(conditioning="pccat")
    frame_cond = torch.randn(2, 5, COND)
    bound = BoundInputs(model, {"frame_cond": frame_cond})
    x, t, cond = torch.randn(4, 5, FEATURES), torch.rand(4), torch.randn(4, COND)
    mask = torch.tensor([False, False, True, True])
    with torch.no_grad():
        direct = model(x, t, cond, cond_mask=mask, frame_cond=torch.cat([frame_cond, frame_cond]))
        torch.testing.assert_close(bound(x, t, cond, cond_mask=mask), direct)
        with pytest.raises(ValueError, match="multiple"):
            bound(x[:3], t[:3], cond[:3])


# ---------------------------------------------------------------------------------------------- extrapolation


def test_extrapolation_beyond_the_positional_table_with_chunked_attention(monkeypatch):
    model = tiny_model(positional="bpe", conditioning="prefix")  # max_len 64, horizon 6
    cond = conditions(1)[0]
    lengths = [30] * 5  # 150 frames: more than max_len, positions restart per segment
    dense = extrapolate(model, cond, lengths, attention_chunk=None, steps=4, switch=2)
    chunked = extrapolate(model, cond, lengths, steps=4, switch=2)  # auto: blocks of the horizon
    assert chunked.motion.shape == (150, FEATURES) and chunked.boundaries[-1] == (120, 150)
    torch.testing.assert_close(chunked.motion, dense.motion, atol=1e-5, rtol=1e-5)

    # Memory: the largest attention block does not grow with the number of segments.
    largest = {}
    original = torch.nn.functional.scaled_dot_product_attention
    for count in (4, 8):
        sizes = []

        def spy(q, k, v, **kwargs):
            sizes.append(q.shape[-2] * k.shape[-2])
            return original(q, k, v, **kwargs)

        monkeypatch.setattr(torch.nn.functional, "scaled_dot_product_attention", spy)
        extrapolate(model, cond, [30] * count, steps=1)
        monkeypatch.setattr(torch.nn.functional, "scaled_dot_product_attention", original)
        largest[count] = max(sizes)
    assert largest[4] == largest[8] < (30 * 4) ** 2


def test_absolute_positional_model_cannot_extrapolate_past_its_table():
    with pytest.raises(ValueError, match="max_len"):
        extrapolate(tiny_model(), conditions(1)[0], [30] * 3, steps=1)
