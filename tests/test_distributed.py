import json
import os
import subprocess
import sys
from concurrent.futures import Future
from functools import partial
from pathlib import Path

import pytest
import torch
from conftest import load_launch_script, start_two_at_a_time
from torch import nn

from pipeline.distributed import (
    Dist,
    LaunchError,
    MixedPrecisionError,
    check_launch_environment,
    check_world_size,
    resolve_mixed_precision,
)

REPO_ROOT = Path(__file__).resolve().parents[1]
WORKER = REPO_ROOT / "tests" / "dist_collectives_worker.py"
ACCELERATE_CONFIGS = REPO_ROOT / "configs" / "accelerate"
LAUNCH_VARS = ("WORLD_SIZE", "RANK", "LOCAL_RANK", "LOCAL_WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT",
               "ACCELERATE_USE_CPU", "ACCELERATE_MIXED_PRECISION", "TORCHELASTIC_RUN_ID")


@pytest.fixture
def single_process_env(monkeypatch):
    """This pytest process as a plain `python script.py` launch, whatever launched pytest."""
    for name in LAUNCH_VARS:
        monkeypatch.delenv(name, raising=False)


def test_single_process_is_the_same_code_path(single_process_env):
    with Dist(mixed_precision="auto", cpu=True) as dist:
        assert (dist.rank, dist.world_size, dist.local_rank) == (0, 1, 0)
        assert dist.is_main and dist.is_local_main and not dist.is_distributed
        assert dist.device.type == "cpu"
        assert dist.mixed_precision == "no"  # auto on CPU

        values = torch.tensor([1.0, -2.0])
        for reduce in (dist.all_reduce_sum, dist.all_reduce_max, dist.all_reduce_min):
            out = reduce(values)
            assert torch.equal(out, values) and out.data_ptr() != values.data_ptr()
        assert dist.any_across_ranks(True) and not dist.any_across_ranks(False)
        assert dist.all_across_ranks(True) and not dist.all_across_ranks(False)
        payload = {"resume": "runs/x/step-00000010"}
        assert dist.broadcast_object(payload) is payload
        assert dist.all_gather_object(3) == [3]
        assert torch.equal(dist.gather_tensor(torch.arange(6).view(3, 2)), torch.arange(6).view(3, 2))
        with pytest.raises(ValueError, match="leading dimension"):
            dist.gather_tensor(torch.tensor(1.0))
        dist.barrier()

        # one optimizer step through the accelerate hooks
        torch.manual_seed(0)
        model = nn.Linear(4, 2)
        optimizer = torch.optim.SGD(model.parameters(), lr=0.1)
        model, optimizer = dist.prepare(model, optimizer)
        before = dist.unwrap(model).weight.detach().clone()
        with dist.accumulate(model):
            with dist.autocast():
                loss = model(torch.randn(8, 4)).pow(2).mean()
            dist.backward(loss)
            assert dist.sync_gradients
            norm = dist.clip_grad_norm_(model.parameters(), 1.0)
            optimizer.step()
            optimizer.zero_grad()
        assert torch.isfinite(norm) and norm > 0
        assert not torch.equal(dist.unwrap(model).weight, before)

        with pytest.raises(TypeError, match="DataLoader"):
            dist.prepare(torch.utils.data.DataLoader(list(range(4))))

    # close() forgets accelerate's process-wide state: a Dist with other settings can follow
    with Dist(mixed_precision="no", grad_accum=2, cpu=True) as dist:
        model = dist.prepare(nn.Linear(2, 2))
        syncs = []
        for _ in range(4):
            with dist.accumulate(model):
                syncs.append(dist.sync_gradients)
        assert syncs == [False, True, False, True]


def test_resolve_mixed_precision():
    assert resolve_mixed_precision("no") == "no"
    assert resolve_mixed_precision("bf16") == "bf16"
    expected_auto = "bf16" if torch.cuda.is_available() and torch.cuda.is_bf16_supported() else "no"
    assert resolve_mixed_precision("auto") == expected_auto
    with pytest.raises(ValueError, match="fp16"):
        resolve_mixed_precision("fp16")
    # accelerate launch --mixed_precision: bf16 is honoured by auto and refused against an explicit "no"; "no" is
    # also accelerate's default, so it never turns a configured bf16 off; fp16 is refused where nothing scales the
    # loss, with what to use instead (the trainer's fp16: tests/test_fp16_training.py)
    assert resolve_mixed_precision("auto", "bf16") == "bf16"
    assert resolve_mixed_precision("bf16", "no") == "bf16" and resolve_mixed_precision("auto", "no") == expected_auto
    with pytest.raises(MixedPrecisionError, match="--mixed_precision bf16 disagrees with train.mixed_precision=no"):
        resolve_mixed_precision("no", "bf16")
    with pytest.raises(MixedPrecisionError, match="no fp16 loss scaling.*bf16"):
        resolve_mixed_precision("auto", "fp16")


def test_the_launchers_bf16_reaches_the_run_and_a_conflict_is_one_line_exit_2(monkeypatch, tmp_path, capsys):
    monkeypatch.setenv("ACCELERATE_MIXED_PRECISION", "bf16")
    with Dist(mixed_precision="auto", cpu=True) as dist:
        assert dist.mixed_precision == "bf16"
    train = load_launch_script("train").main
    assert train(["--config", "tiny", "train.mixed_precision=no", f"train.out_dir={tmp_path / 'run'}"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "train.mixed_precision=no" in err and "Traceback" not in err


@pytest.mark.parametrize("native", [True, False])
def test_bf16_on_a_cpu_without_native_bf16_warns_that_fp32_is_faster(native, monkeypatch, caplog):
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: native)
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: False)
    with caplog.at_level("WARNING", logger="pipeline.distributed"), Dist(mixed_precision="bf16", cpu=True) as dist:
        assert dist.mixed_precision == "bf16"
    warned = [r.getMessage() for r in caplog.records if "without native bf16" in r.getMessage()]
    assert len(warned) == (0 if native else 1)
    assert not warned or "train.mixed_precision=no" in warned[0]


# Environments as the launchers set them (captured from accelerate 1.15 and torch 2.14 on this machine).
ACCELERATE_CPU_N2 = {"ACCELERATE_USE_CPU": "True", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": "29500",
                     "ACCELERATE_MIXED_PRECISION": "no", "OMP_NUM_THREADS": "1"}
ACCELERATE_MULTI_GPU_ON_CPU = {"ACCELERATE_USE_CPU": "1", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": "29500",
                               "WORLD_SIZE": "2", "RANK": "1", "LOCAL_RANK": "1", "LOCAL_WORLD_SIZE": "2"}
TORCHRUN = {"MASTER_ADDR": "localhost", "MASTER_PORT": "41535", "WORLD_SIZE": "2", "RANK": "0", "LOCAL_RANK": "0"}
MPIRUN_CPU = {"ACCELERATE_USE_CPU": "True", "MASTER_ADDR": "node0", "OMPI_COMM_WORLD_SIZE": "4"}


def test_accelerate_silent_single_process_cpu_launch_is_refused():
    with pytest.raises(LaunchError, match="ACCELERATE_USE_CPU=1 accelerate launch --multi_gpu"):
        check_launch_environment(ACCELERATE_CPU_N2)


@pytest.mark.parametrize(
    "environ", [{}, {"ACCELERATE_USE_CPU": "True"}, ACCELERATE_MULTI_GPU_ON_CPU, TORCHRUN, MPIRUN_CPU]
)
def test_working_launches_pass_the_check(environ):
    check_launch_environment(environ)


def test_world_size_mismatch_is_refused():
    check_world_size(2, {"WORLD_SIZE": "2"})
    check_world_size(1, {})
    with pytest.raises(LaunchError, match="WORLD_SIZE=2 but accelerate initialised 1"):
        check_world_size(1, {"WORLD_SIZE": "2"})


def _launch_env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in LAUNCH_VARS}
    env["OMP_NUM_THREADS"] = "1"
    return env


def _launch(command: list[str], out_dir: Path, env=None) -> subprocess.CompletedProcess:
    return subprocess.run(command + [str(WORKER), str(out_dir)], cwd=REPO_ROOT, env=env or _launch_env(),
                          capture_output=True, text=True, timeout=180)


def _two_rank_results(proc: subprocess.CompletedProcess, out_dir: Path) -> list[dict]:
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return [json.loads((out_dir / f"rank{r}.json").read_text()) for r in (0, 1)]


def _run_two_ranks(command: list[str], out_dir, env=None) -> list[dict]:
    return _two_rank_results(_launch(command, out_dir, env), out_dir)


def _check_two_rank_results(results: list[dict]) -> None:
    for rank, res in enumerate(results):
        assert (res["rank"], res["world_size"], res["local_rank"], res["is_main"]) == (rank, 2, rank, rank == 0)
        assert res["device"].startswith("cpu")
        # rank r contributed [r, 10 - r]
        assert res["max"] == [1.0, 10.0] and res["min"] == [0.0, 9.0] and res["sum"] == [1.0, 19.0]
        assert res["input_untouched"]
        assert res["bool_max"] == [True, False]
        assert res["any_rank1"] is True and res["any_none"] is False
        assert res["all_rank1"] is False and res["all_true"] is True
        assert res["broadcast"] == {"from": 0, "path": "ckpt-of-rank-0"}
        assert res["broadcast_src1"] == 100
        assert res["all_gather"] == [{"rank": 0}, {"rank": 1}]
        assert res["gather"] == [[0.0, 0.0], [1.0, 1.0], [1.0, 1.0]]  # uneven rows, rank order, no padding
        assert res["gather_bool"] == [True, True, False]
        # checkpoint flow: rank 0 saved the gathered per-rank states, every rank restored its own
        assert res["resume"] == "step-00000005"
        assert res["rng_restored"] is True
        assert res["data_state"] == {"rank": rank, "sample_in_epoch": 10 * rank}


@pytest.mark.multirank
def test_two_gloo_ranks_under_torchrun(tmp_path):
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]
    _check_two_rank_results(_run_two_ranks(command, tmp_path))


ACCELERATE_LAUNCH = [sys.executable, "-m", "accelerate.commands.launch"]
# The accelerate launches of the slow tests below: launch arguments and whether ACCELERATE_USE_CPU=1 is set.
ACCELERATE_LAUNCHES = {
    "cli-recipe": (["--multi_gpu", "--num_processes", "2", "--num_machines", "1", "--mixed_precision", "no",
                    "--dynamo_backend", "no", "--main_process_port", "0"], True),
    "cpu_2ranks.yaml": (["--config_file", str(ACCELERATE_CONFIGS / "cpu_2ranks.yaml")], True),
    "cpu-num-processes-2": (["--cpu", "--num_processes", "2"], False),  # refused: one process would run
}


@pytest.fixture(scope="module")
def accelerate_launches(tmp_path_factory) -> dict[str, tuple[Path, Future]]:
    """Every launch of ACCELERATE_LAUNCHES, started together (start_two_at_a_time); per launch its output folder
    (empty when the launch starts) and its result."""
    root = tmp_path_factory.mktemp("accelerate")
    launches = {}
    for name, (args, use_cpu) in ACCELERATE_LAUNCHES.items():
        (root / name).mkdir()
        env = {**_launch_env(), "ACCELERATE_USE_CPU": "1"} if use_cpu else _launch_env()
        launches[name] = partial(_launch, ACCELERATE_LAUNCH + args, root / name, env)
    started = start_two_at_a_time(launches)
    return {name: (root / name, started[name]) for name in launches}


@pytest.mark.multirank
@pytest.mark.slow
@pytest.mark.parametrize("launch", ["cli-recipe", "cpu_2ranks.yaml"])
def test_two_gloo_ranks_under_accelerate_launch(accelerate_launches, launch):
    out_dir, started = accelerate_launches[launch]
    _check_two_rank_results(_two_rank_results(started.result(), out_dir))


@pytest.mark.multirank
@pytest.mark.slow
def test_accelerate_cpu_num_processes_2_is_refused_not_run_once(accelerate_launches):
    out_dir, started = accelerate_launches["cpu-num-processes-2"]
    proc = started.result()
    assert proc.returncode != 0
    assert "LaunchError" in proc.stderr and "--multi_gpu" in proc.stderr
    assert list(out_dir.iterdir()) == []  # the lone process did no work


@pytest.mark.parametrize("name", ["cpu_2ranks", "single_gpu", "multi_gpu", "multi_node"])
def test_accelerate_config_files_parse(name):
    from accelerate.commands.config.config_args import load_config_from_file
    from accelerate.utils import DistributedType

    config = load_config_from_file(str(ACCELERATE_CONFIGS / f"{name}.yaml"))
    expected = {
        "cpu_2ranks": (DistributedType.MULTI_GPU, 2, 1),  # MULTI_CPU would silently run one process
        "single_gpu": (DistributedType.NO, 1, 1),
        "multi_gpu": (DistributedType.MULTI_GPU, 4, 1),
        "multi_node": (DistributedType.MULTI_GPU, 16, 2),
    }[name]
    assert (config.distributed_type, config.num_processes, config.num_machines) == expected
    assert config.mixed_precision == "no"  # precision comes from the training config
