import os
import tempfile
from collections.abc import Callable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TypeVar

import pytest
import torch

# No model hub or dataset site at run time: fail fast instead of retrying downloads.
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
# W&B: off whatever the caller's environment says (a W&B user's WANDB_MODE=offline would otherwise write W&B
# folders and let third-party chatter in: tests/test_build_shards.py tests that case explicitly). The other
# WANDB_* variables (project, entity, directory) are the caller's and are dropped for the same reason.
for _name in [n for n in os.environ if n.startswith("WANDB_")]:
    del os.environ[_name]
os.environ["WANDB_MODE"] = "disabled"
# Tiny models on 2 cores: one intra-op thread per process is faster than two fighting over the cores, and the
# multi-rank tests start several processes (they inherit this).
os.environ.setdefault("OMP_NUM_THREADS", "1")
# The shard-verification cache (pipeline/data/shard_cache.py) of the test runs stays out of the user's ~/.cache.
os.environ.setdefault("MFM_VERIFY_CACHE", tempfile.mkdtemp(prefix="mfm-verify-cache-"))

torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DIR = Path(os.environ.get("MFM_SHARED_DIR", REPO_ROOT.parent / "shared"))
REFERENCE_DATA = SHARED_DIR / "reference-data"

K, T = TypeVar("K"), TypeVar("T")


@pytest.fixture
def single_thread():
    """One intra-op thread for the test, restored after: thousands of tiny ops (diffusion loops, small models)
    run several times faster without OpenMP spin-waits when other jobs share the cores."""
    from preprocess.processing import single_threaded_torch

    with single_threaded_torch():
        yield


class RecordedCompile(torch.nn.Module):
    """What the ``compile_calls`` fixture's ``torch.compile`` returns: the model itself, counting its calls."""

    def __init__(self, model: torch.nn.Module, mode: str | None, options: dict | None = None) -> None:
        super().__init__()
        self.inner, self.mode, self.calls = model, mode, 0
        self.options = options or {}  # torch.compile's other keywords (dynamic=...)
        self.train(model.training)  # as torch.compile's OptimizedModule, which is in its model's mode

    def forward(self, *args, **kwargs):
        self.calls += 1
        return self.inner(*args, **kwargs)


@pytest.fixture
def compile_calls(monkeypatch) -> list[RecordedCompile]:
    """``torch.compile`` replaced by a recording identity wrapper (inductor would take minutes on a CPU): the list
    of the wrappers it made, one per compile."""
    made: list[RecordedCompile] = []

    def recording_compile(model, *, mode=None, **options):
        made.append(RecordedCompile(model, mode, options))
        return made[-1]

    monkeypatch.setattr(torch, "compile", recording_compile)
    return made


@pytest.fixture
def reference_data() -> Path:
    """The real HumanML3D clip and normalisation files (../shared/reference-data)."""
    if not REFERENCE_DATA.is_dir():
        pytest.skip(f"reference data not found at {REFERENCE_DATA} (set MFM_SHARED_DIR or place shared/ beside the checkout)")
    return REFERENCE_DATA


def embedded_dataset_once(tmp_path_factory) -> Path:
    """The embedded default dataset (the real DeepMimic clips with MiniLM captions), built once per test session."""
    from preprocess.shards import BuildConfig, build_dataset

    data = tmp_path_factory.getbasetemp() / "deepmimic-minilm"
    if not (data / "manifest.json").exists():
        build_dataset(BuildConfig(out=data, progress=False))  # the defaults: deepmimic + minilm
    return data


def start_two_at_a_time(launches: Mapping[K, Callable[[], T]]) -> dict[K, Future[T]]:
    """Start independent launches (each a call that runs subprocesses and returns their outcome) in the background,
    in this order, two at a time, and return their futures. A launch is mostly single-threaded Python starts (torch,
    the text encoder, a launcher and its ranks) that leave the second core idle, so two side by side take little
    longer than one. Only for launches whose results do not depend on timing: every process computes with one
    intra-op thread whatever runs beside it, and faults strike at steps, not at times. A launch's exception is
    raised where its result is read, failing only the tests that read it."""
    pool = ThreadPoolExecutor(max_workers=2)
    futures = {name: pool.submit(launch) for name, launch in launches.items()}
    pool.shutdown(wait=False)  # the pool's threads finish the launches; nothing waits here
    return futures


def selected_tests(request: pytest.FixtureRequest) -> set[str]:
    """The names (parameters left out) of the requesting module's tests that this session runs, after -k and -m: a
    fixture that starts the launches of several tests at once starts those of the tests that run, so a test
    deselected by its marker (``slow``, ``multirank``) costs nothing."""
    return {item.originalname for item in request.session.items if item.module is request.module}


def _module_from_file(module_name: str, path: Path):
    import importlib.util

    spec = importlib.util.spec_from_file_location(module_name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def load_launch_script(name: str):
    """``launch/<name>.py`` as a module (the launch scripts are run as files, not imported as a package)."""
    return _module_from_file(f"launch_{name}", REPO_ROOT / "launch" / f"{name}.py")


def load_benchmark(name: str):
    """``benchmarks/<name>.py`` as a module, with benchmarks/ on sys.path as when it runs as a script (the scripts
    import their siblings, e.g. length_sweep)."""
    import sys

    folder = str(REPO_ROOT / "benchmarks")
    if folder not in sys.path:
        sys.path.insert(0, folder)
    return _module_from_file(name, REPO_ROOT / "benchmarks" / f"{name}.py")


def flip_byte(path: Path, offset: int) -> None:
    """Invert one byte of ``path`` at ``offset``: a same-size corruption that only a hash can see."""
    data = bytearray(path.read_bytes())
    data[offset] ^= 0xFF
    path.write_bytes(bytes(data))
