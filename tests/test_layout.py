"""The package layout's import rules (README "What is where"): mfm/ is the library and imports nothing of the jobs;
inside pipeline/, the shared modules import no job package, data imports only shared modules, training and
generation may import data and the shared modules, evaluation may also import generation, and nothing imports
evaluation from outside it; the commands (pipeline/cli/) may import every part and no part imports them. launch/
holds one thin file per command, importing nothing of the project but its command's ``main``. A module that breaks
a rule is named with the import."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = "shared"  # pipeline/config.py, distributed.py, checkpoint.py, claims.py
JOB_PACKAGES = ("data", "training", "generation", "evaluation")
COMMANDS = "cli"  # pipeline/cli/: the command lines of the jobs (console scripts, launch/ files)

# What each part of pipeline/ may import from pipeline/ (besides itself).
ALLOWED = {
    SHARED: {SHARED},
    "data": {SHARED, "data"},
    "training": {SHARED, "data", "training"},
    "generation": {SHARED, "data", "generation"},
    "evaluation": {SHARED, "data", "generation", "evaluation"},
    COMMANDS: {SHARED, *JOB_PACKAGES, COMMANDS},
}


def part_of(module: str) -> str | None:
    """'pipeline.generation.sampling' -> 'generation', 'pipeline.config' -> 'shared', 'mfm.x' -> None."""
    parts = module.split(".")
    if parts[0] != "pipeline" or len(parts) == 1:
        return None
    return parts[1] if parts[1] in (*JOB_PACKAGES, COMMANDS) else SHARED


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imported_modules(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module) of every import in ``path``, including function-level ones; ``from pipeline import
    x`` counts as ``pipeline.x``, relative imports are resolved against the module's package."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    found: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                package = module_name(path).split(".")[: -1 if path.name != "__init__.py" else None]
                base = ".".join(package[: len(package) - node.level + 1] + ([base] if base else []))
            # ``from pipeline import evaluation`` imports the package pipeline.evaluation.
            found += [(node.lineno, f"{base}.{alias.name}" if base == "pipeline" else base) for alias in node.names]
    return found


def python_files(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob("*.py"))


def test_the_layout_has_the_job_packages():
    for package in JOB_PACKAGES:
        init = ROOT / "pipeline" / package / "__init__.py"
        assert init.is_file(), f"pipeline/{package}/ is not a package"
        assert ast.get_docstring(ast.parse(init.read_text(encoding="utf-8"))), f"{init}: no module docstring"
    shared = sorted(p.stem for p in (ROOT / "pipeline").glob("*.py") if p.stem != "__init__")
    assert shared == ["checkpoint", "claims", "config", "distributed"], f"pipeline/ top level holds {shared}"


@pytest.mark.parametrize("path", python_files("pipeline"), ids=lambda p: str(p.relative_to(ROOT)))
def test_pipeline_imports_flow_one_way(path):
    here = part_of(module_name(path))
    if here is None:  # pipeline/__init__.py
        here = SHARED
    broken = [f"line {line}: {module}" for line, module in imported_modules(path)
              if (there := part_of(module)) is not None and there not in ALLOWED[here]]
    assert not broken, f"{path.relative_to(ROOT)} ({here}) imports above itself: {broken}"


@pytest.mark.parametrize("folder", ["mfm"])
def test_the_library_imports_no_job(folder):
    broken = [f"{path.relative_to(ROOT)} line {line}: {module}" for path in python_files(folder)
              for line, module in imported_modules(path) if module.split(".")[0] in ("pipeline", "launch")]
    assert not broken, f"mfm/ must not import the jobs: {broken}"


def test_the_rule_catches_an_upward_import(tmp_path):
    """The check is not vacuous: a data module importing training, and a generation module importing evaluation,
    are both reported."""
    for part, text in (("data", "from pipeline.training.trainer import Trainer\n"),
                       ("generation", "import pipeline.evaluation.job\n"),
                       ("training", "from pipeline import evaluation\n"),
                       ("evaluation", "from pipeline.cli.evaluate import main\n")):
        module = tmp_path / f"{part}_probe.py"
        module.write_text(text, encoding="utf-8")
        imported = [m for _, m in imported_modules(module)]
        assert any(part_of(m) not in ALLOWED[part] for m in imported), (part, imported)


def test_launch_files_are_thin_and_mirror_the_commands():
    """Each launch/<name>.py (run as a file from a checkout, e.g. ``accelerate launch launch/train.py``) imports its
    command's ``main`` from pipeline/cli/<name>.py and nothing else of the project, and every command has one."""
    launch_files = {p.stem: p for p in (ROOT / "launch").glob("*.py") if p.stem != "__init__"}
    commands = {p.stem for p in (ROOT / "pipeline" / COMMANDS).glob("*.py") if p.stem != "__init__"}
    assert launch_files and set(launch_files) == commands, (sorted(launch_files), sorted(commands))
    for name, path in launch_files.items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        assert ast.get_docstring(tree), f"{path.relative_to(ROOT)}: no module docstring"
        project = [module for _, module in imported_modules(path)
                   if module.split(".")[0] in ("mfm", "pipeline", "preprocess", "launch")]
        assert project == [f"pipeline.cli.{name}"], f"{path.relative_to(ROOT)} imports {project}"
        functions = [node.name for node in ast.walk(tree) if isinstance(node, (ast.FunctionDef, ast.ClassDef))]
        assert not functions, f"{path.relative_to(ROOT)} defines {functions}: it belongs in pipeline/cli/{name}.py"
