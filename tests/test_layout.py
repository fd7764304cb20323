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


# ---------------------------------------------------------------------------------------------------------------
# inside pipeline/generation/: one-way layers, no import cycle broken by a function-level import

GENERATION = ROOT / "pipeline" / "generation"
# The layers, bottom first (README "What is where"): loading a model (inference: a run, a checkpoint or an exported
# folder) under the request and the integrator, those under the files a run writes (outputs), the page writer
# (browse) above the outputs, sampling above both, then composition, the contact sheet, the reflow pairs and the
# MotionPipeline API (pretrained) on top. A module imports only modules of layers below its own.
GENERATION_LAYERS = (("inference",), ("request",), ("integration",), ("outputs",), ("browse",), ("sampling",),
                     ("composing", "contact_sheet", "pairs", "pretrained"))


def generation_imports(path: Path) -> tuple[set[str], list[tuple[int, str]]]:
    """(generation modules ``path`` imports when it is imported, [(line, module)] of those it imports inside a
    function or class body); 'pipeline.generation.x' and 'pipeline.generation.x.y' both count as 'x'. Imports
    under a module-level ``if``/``try`` are module-level."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    siblings_here = {p.stem for p in GENERATION.glob("*.py")}
    at_module, in_function = set(), []

    def siblings(node: ast.Import | ast.ImportFrom) -> list[str]:
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        else:
            base = node.module or ""
            if node.level:  # relative to pipeline.generation (one level) or above
                base = ".".join(["pipeline", "generation"][: 3 - node.level] + ([base] if base else []))
            names = [f"{base}.{alias.name}" for alias in node.names]
        return sorted({n.split(".")[2] for n in names
                       if n.startswith("pipeline.generation.") and n.split(".")[2] in siblings_here})

    def visit(node: ast.AST, nested: bool) -> None:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            if nested:
                in_function.extend((node.lineno, s) for s in siblings(node))
            else:
                at_module.update(siblings(node))
        for child in ast.iter_child_nodes(node):
            visit(child, nested or isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef,
                                                     ast.Lambda)))

    visit(tree, False)
    return at_module - {path.stem}, in_function


def import_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` (module -> modules it imports) as [a, b, ..., a], or None."""
    state: dict[str, str] = {}

    def visit(node: str, trail: list[str]) -> list[str] | None:
        state[node] = "open"
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == "open":
                return trail[trail.index(nxt):] + [node, nxt] if nxt in trail else [node, nxt]
            if nxt not in state and (found := visit(nxt, trail + [node])):
                return found
        state[node] = "done"
        return None

    for start in sorted(graph):
        if start not in state and (found := visit(start, [])):
            return found
    return None


def generation_graph() -> tuple[dict[str, set[str]], dict[str, list[tuple[int, str]]]]:
    graph, nested = {}, {}
    for path in sorted(GENERATION.glob("*.py")):
        if path.stem == "__init__":
            continue
        graph[path.stem], nested[path.stem] = generation_imports(path)
    return graph, nested


def test_generation_modules_import_in_one_direction():
    """No cycle and no upward import, counting function-level imports too (a cycle they close is still a cycle)."""
    graph, nested = generation_graph()
    graph = {module: imported | {other for _, other in nested[module]} - {module} for module, imported in graph.items()}
    layer = {module: rank for rank, modules in enumerate(GENERATION_LAYERS) for module in modules}
    assert set(graph) == set(layer), (f"GENERATION_LAYERS lists {sorted(layer)}, "
                                      f"pipeline/generation/ has {sorted(graph)}")
    cycle = import_cycle(graph)
    assert cycle is None, f"pipeline/generation/ imports in a circle: {' -> '.join(cycle)}"
    upward = [f"{module} imports {other}" for module, others in graph.items() for other in sorted(others)
              if layer[other] >= layer[module]]
    assert not upward, f"pipeline/generation/ imports a module of its own layer or above: {upward}"


def test_no_generation_module_imports_a_sibling_inside_a_function():
    """A function-level import of a sibling is how a cycle hides from the module-level graph: none is allowed (code
    two modules both need belongs in the lower one). Function-level imports that defer a heavy dependency (e.g.
    torchdiffeq, which brings scipy) are not sibling imports and not checked here."""
    _, nested = generation_graph()
    hidden = [f"pipeline/generation/{module}.py line {line}: imports {other}" for module, found in nested.items()
              for line, other in found]
    assert not hidden, f"function-level imports of sibling generation modules: {hidden}"


def test_the_generation_checks_catch_a_cycle_and_a_hidden_import(tmp_path):
    """Not vacuous: a cycle, module-level imports (relative, under an ``if``) and function- or class-level sibling
    imports are all found."""
    assert import_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) in (["a", "b", "c", "a"], ["b", "c", "a", "b"],
                                                                  ["c", "a", "b", "c"])
    assert import_cycle({"a": {"b"}, "b": set()}) is None
    probe = tmp_path / "outputs.py"
    probe.write_text("from pipeline.generation.inference import TrainedModel\n"
                     "def f():\n    from pipeline.generation.browse import is_our_page\n", encoding="utf-8")
    assert generation_imports(probe) == ({"inference"}, [(3, "browse")])
    probe.write_text("from . import request\nfrom .sampling import run_sampling\n"
                     "if True:\n    import pipeline.generation.browse\n"
                     "class A:\n    from pipeline.generation import composing\n", encoding="utf-8")
    assert generation_imports(probe) == ({"request", "sampling", "browse"}, [(6, "composing")])

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
