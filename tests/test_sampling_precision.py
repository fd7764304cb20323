"""bf16 sampling (issue 26): the model's passes under bf16 autocast while the ODE state, the guidance mix and the
solver stay fp32; the same motions as fp32 within a stated bound; what ``auto`` means on each device."""

from __future__ import annotations

import pytest
import torch

from mfm.diffusion import GaussianDiffusion, learned_variance_transformer
from mfm.diffusion_sampling import sample_diffusion
from mfm.guidance import classifier_free_guidance, resolve_precision
from mfm.model import MotionFlowTransformer
from mfm.solvers import guided_velocity, sample, solve
from pipeline.config import TrainConfig, load_config

BF16_MAX_ABS = 0.05
"""Largest |bf16 − fp32| of a sampled motion (normalised features, std ≈ 1.1) the tiny model may show. Measured on
the CPU (torch 2.14, AVX-512 BF16/AMX): 0.0108-0.0129 over seeds 0-2, i.e. the bound has about 4× margin. Why that
size: bf16 keeps 8 significant bits, so every matmul output is rounded by up to 2^-9 ≈ 0.2 % of its magnitude; the
guided velocity amplifies the conditional-unconditional difference by the scale 2.5 and 10 Euler steps add up ten
such errors, while the state itself is never rounded (it stays fp32), so the error does not compound through it."""
BF16_MEAN_ABS = 0.005
"""Mean |bf16 − fp32| over every valid value; measured 0.0013-0.0014 over the same seeds (3.5× margin)."""


def tiny_model(seed: int = 0, learned_variance: bool = False) -> MotionFlowTransformer:
    """configs/tiny.yaml's model (2 layers, width 64), randomly initialised with ``seed``, in eval mode."""
    config = load_config(TrainConfig, "tiny", []).model
    torch.manual_seed(seed)
    model = learned_variance_transformer(config) if learned_variance else MotionFlowTransformer(config)
    return model.eval()


def batch_of(model: MotionFlowTransformer, size: int = 6) -> tuple[torch.Tensor, torch.Tensor]:
    config = model.config
    lengths = torch.tensor([config.max_frames - 5 * i for i in range(size)])
    cond = torch.randn(size, config.cond_dim, generator=torch.Generator().manual_seed(3))
    return cond, lengths


@pytest.mark.parametrize("seed", [0, 1])
def test_bf16_samples_are_the_fp32_motions_within_the_bound(seed):
    model = tiny_model(seed)
    cond, lengths = batch_of(model)
    frames = int(lengths.max())
    with torch.no_grad():
        fp32 = sample(model, cond, lengths, num_frames=frames, seed=5).x1
        bf16 = sample(model, cond, lengths, num_frames=frames, seed=5, precision="bf16").x1
    difference = (bf16 - fp32).abs()
    assert bf16.dtype == torch.float32
    assert float(difference.max()) <= BF16_MAX_ABS and float(difference.mean()) <= BF16_MEAN_ABS
    assert float(difference.max()) > 1e-5  # the passes did run in bf16 (an fp32 run gives exactly 0)
    valid = torch.arange(frames)[None, :] < lengths[:, None]
    assert not bf16[~valid].any()  # padded frames stay exactly zero


def test_bf16_runs_the_network_in_bf16_and_keeps_the_state_and_velocity_fp32():
    model = tiny_model()
    cond, lengths = batch_of(model, 3)
    frames = int(lengths.max())
    inside: list[torch.dtype] = []
    head: list[tuple[torch.dtype, torch.dtype]] = []
    model.input_proj.register_forward_hook(lambda module, args, out: inside.append(out.dtype))
    # The output head stays fp32 under autocast (its bf16 rounding would be frame-to-frame jitter in the motion).
    model.output_proj.register_forward_hook(lambda module, args, out: head.append((args[0].dtype, out.dtype)))
    velocity = guided_velocity(model, cond, scale=2.5, lengths=lengths, precision="bf16")
    seen: list[tuple[torch.dtype, torch.dtype]] = []

    def recorded(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        v = velocity(x, t)
        seen.append((x.dtype, v.dtype))
        return v

    with torch.no_grad():
        x0 = torch.randn(3, frames, model.config.feature_dim)
        result = solve(recorded, x0, steps=4, return_trajectory=True)
    assert inside == [torch.bfloat16] * 4  # one batched (2B) pass per step, in bf16
    assert head == [(torch.float32, torch.float32)] * 4
    assert seen == [(torch.float32, torch.float32)] * 4  # what the solver holds and gets back
    assert result.x1.dtype == result.x1_hat.dtype == torch.float32
    inside.clear()
    with torch.no_grad():
        guided_velocity(model, cond, scale=2.5, lengths=lengths)(x0, torch.zeros(3))
    assert inside == [torch.float32]  # the default (fp32) leaves the model alone


class LinearVelocity(torch.nn.Module):
    """A model whose output is its last Linear's (under bf16 autocast: a bf16 tensor, unlike MotionFlowTransformer,
    whose padding mask brings its output back to fp32)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.linear = torch.nn.Linear(dim, dim)

    def forward(self, x, t, cond, lengths=None, *, cond_mask=None):
        return self.linear(x + t[:, None, None] + cond.mean(dim=-1)[:, None, None])


def test_a_model_that_returns_bf16_still_hands_the_solver_fp32():
    model = LinearVelocity(5)
    cond = torch.randn(2, 3)
    velocity = guided_velocity(model, cond, scale=2.5, precision="bf16")
    with torch.no_grad():
        with torch.autocast("cpu", dtype=torch.bfloat16):
            assert model(torch.randn(2, 4, 5), torch.zeros(2), cond).dtype == torch.bfloat16  # what it gives
        v = velocity(torch.randn(2, 4, 5), torch.zeros(2))
        result = solve(velocity, torch.randn(2, 4, 5), steps=3)
    assert v.dtype == result.x1.dtype == torch.float32


BF16_PASS_RELATIVE = 0.05
"""One guided denoiser pass in bf16 against fp32: max |difference| / max |fp32 output|. Measured 1.2-1.4 % on the
tiny learned-variance model (seeds 0-2; mean |difference| 0.5 % of the mean |output|). A whole diffusion chain of a
random network is not bounded the same way: its x0 estimates are hundreds of units, so the clamp or the 1/√ᾱ
rescaling turns a 1 % pass error into any size; trained chains are what the evaluator measures."""


def test_a_diffusion_chain_in_bf16_stays_fp32_and_each_pass_is_close():
    model = tiny_model(learned_variance=True)  # FLAME's denoiser shape: ε and the learned variance
    feature_dim = model.config.feature_dim
    cond, lengths = batch_of(model, 2)
    frames = int(lengths.max())
    diffusion = GaussianDiffusion(20, learn_sigma=True)
    with torch.no_grad():
        runs = {precision: sample_diffusion(model, diffusion, cond, lengths, num_frames=frames, sampler="ddim",
                                            steps=5, guidance=2.5, seed=1, precision=precision)
                for precision in ("fp32", "bf16")}
        x = torch.randn(2, frames, feature_dim, generator=torch.Generator().manual_seed(0))
        passes = {precision: classifier_free_guidance(model, cond, scale=2.5, lengths=lengths,
                                                      guided_channels=feature_dim, precision=precision)(
                      x, torch.full((2,), 0.5)) for precision in ("fp32", "bf16")}
    assert runs["bf16"].x1.dtype == torch.float32 and runs["bf16"].nfe == 5
    assert torch.isfinite(runs["bf16"].x1).all() and not torch.equal(runs["bf16"].x1, runs["fp32"].x1)
    assert passes["bf16"].dtype == torch.float32 and passes["bf16"].shape[-1] == 2 * feature_dim
    error = float((passes["bf16"] - passes["fp32"]).abs().max() / passes["fp32"].abs().max())
    assert 0 < error <= BF16_PASS_RELATIVE


def test_auto_is_bf16_only_on_a_cuda_gpu_with_bf16(monkeypatch):
    assert resolve_precision("auto", "cpu") == "fp32"  # the CPU default stays fp32
    assert resolve_precision("bf16", "cpu") == "bf16"  # asked for: CPU autocast has bf16
    assert resolve_precision("fp32", "cuda") == "fp32"
    with pytest.raises(ValueError, match="mps"):
        resolve_precision("bf16", "mps")
    with pytest.raises(ValueError, match="precision must be one of"):
        resolve_precision("fp16", "cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *args, **kwargs: True)
    assert resolve_precision("auto", "cuda") == resolve_precision("bf16", "cuda:0") == "bf16"
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *args, **kwargs: False)  # a pre-Ampere GPU
    assert resolve_precision("auto", "cuda") == "fp32"
    with pytest.raises(ValueError, match="no bf16"):
        resolve_precision("bf16", "cuda")


def test_bf16_on_a_gpu_without_it_is_a_clear_error_for_sampling_and_the_evaluator(monkeypatch):
    """launch/sample.py and launch/evaluate.py turn these errors into one line and exit 2 (their error contract)."""
    from types import SimpleNamespace

    from mfm.model import ModelConfig
    from pipeline.evaluation.config import load_eval_config
    from pipeline.evaluation.replications import sampling_precision
    from pipeline.evaluation.spaces import EvaluationError
    from pipeline.generation.integration import resolve_integrator
    from pipeline.generation.request import SampleRequest, SamplingError

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *args, **kwargs: False)
    gpu_model = SimpleNamespace(device=torch.device("cuda"), objective="flow", model_config=ModelConfig())
    with pytest.raises(SamplingError, match="precision bf16: autocast has no bf16 on device 'cuda'"):
        resolve_integrator(SampleRequest(checkpoint="c", out_dir="o", precision="bf16"), gpu_model)
    assert resolve_integrator(SampleRequest(checkpoint="c", out_dir="o"), gpu_model).precision == "fp32"  # auto
    with pytest.raises(EvaluationError, match="sampling.precision bf16"):
        sampling_precision(load_eval_config("fast", overrides=["sampling.precision=bf16"]).sampling, "cuda")
    with pytest.raises(SamplingError, match="precision must be one of"):
        SampleRequest(checkpoint="c", out_dir="o", precision="half")
