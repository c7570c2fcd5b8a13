"""The import structure (DESIGN.md "services/: layered"): the import-linter contracts of
pyproject.toml hold, no module of ``services``, ``spine_engine`` or ``benches`` is in an import cycle, the
engine does not import the benches (they sit on top of the engine, outside its wheel), and no
import hides inside a function except the few marked ``# lazy: <why>`` (an entry point's optional
heavy dependency, e.g. the HTTP server for ``spine serve`` only)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import grimp
import pytest

ROOT = Path(__file__).resolve().parents[2]
SERVICES = ROOT / "services"
ENGINE = ROOT / "spine_engine"
BENCHES = ROOT / "benches"
LAZY_ALLOWED = 6
"""Marked lazy imports allowed in all of services/ (today: the CLI's per-command imports)."""
LAZY_ALLOWED_ENGINE = 2
"""Marked lazy imports allowed in spine_engine/ (today: ``register`` on first use, and matplotlib's drawing
in ``figures.render_figure``)."""
LAZY_ALLOWED_BENCHES = 3
"""Marked lazy imports allowed in benches/ (today: matplotlib for plots, in ``benches.report``)."""


def test_import_linter_contracts_are_kept() -> None:
    lint = Path(sys.executable).with_name("lint-imports")
    run = subprocess.run([str(lint), "--no-cache"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]
    assert "0 broken" in run.stdout


def _cycles(graph: grimp.ImportGraph, modules: set[str]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), i.e. import cycles."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph.find_modules_directly_imported_by(v) & modules:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for module in sorted(modules):
        if module not in index:
            visit(module)
    return found


def test_no_module_import_cycle() -> None:
    graph = grimp.build_graph("services", cache_dir=None)
    modules = {m for m in graph.modules if m.startswith("services")}
    assert len(modules) > 40  # the graph was really read
    assert _cycles(graph, modules) == []


@pytest.mark.parametrize(("package", "at_least"), [("spine_engine", 25), ("benches", 10)])
def test_no_module_import_cycle_in_the_engine_or_the_benches(package: str, at_least: int) -> None:
    """Imports under ``if TYPE_CHECKING`` are left out: ``fit.pose_rows`` names
    ``fit.problem.RegistrationProblem`` in its signatures only (the problem calls its pose rows
    with itself)."""
    graph = grimp.build_graph(package, cache_dir=None, exclude_type_checking_imports=True)
    modules = {m for m in graph.modules if m.startswith(package)}
    assert len(modules) > at_least
    assert _cycles(graph, modules) == []


def test_the_engine_does_not_import_the_benches() -> None:
    """Checked on the graph of both packages (grimp sees every import, also one inside a function);
    the engine's data written by a bench (profiles/*.json, priors/*.json) is read as JSON."""
    graph = grimp.build_graph("spine_engine", "benches", cache_dir=None)
    engine = {m for m in graph.modules if m.split(".")[0] == "spine_engine"}
    assert "spine_engine.reconstruction" in engine and "spine_engine.warmup" in engine
    assert "benches.clinic" in graph.modules  # the benches were read: the check below can fail
    offenders = sorted(
        f"{m} -> {imported}"
        for m in engine
        for imported in graph.find_modules_directly_imported_by(m)
        if imported.split(".")[0] == "benches"
    )
    assert offenders == []
    assert not (ENGINE / "experiments").exists()


def test_the_api_and_the_worker_start_without_matplotlib() -> None:
    """matplotlib was a fifth of the API's and the worker's import time (about 0.45 s of CPU at every
    start of `spine serve`, a worker or a restarted one): only drawing a figure
    (``spine_engine.figure_drawing``) imports it. Checked in a fresh interpreter."""
    assert _loaded_after("import services.api.app, services.worker.celery_app", ("matplotlib",)) == []


def test_a_client_command_loads_none_of_the_service() -> None:
    """``spine get|submit|list…`` of the full install went through the service's commands and loaded
    SQLAlchemy, alembic, psycopg and Celery, about 0.75 s of CPU a command more than the client alone
    (docs/client.md). Checked in a fresh interpreter, on the code ``spine`` runs (``services.cli.main``)."""
    code = (
        "import contextlib, io\n"
        "from services.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):\n"
        "    main(['get', '--help'])\n"
    )
    loaded = _loaded_after(code, ("sqlalchemy", "alembic", "psycopg", "celery", "spine_client.cli"))
    assert loaded == ["spine_client.cli"]


def _loaded_after(code: str, modules: tuple[str, ...]) -> list[str]:
    """Which of ``modules`` a fresh interpreter has loaded after running ``code`` in the repository."""
    probe = f"import sys\n{code}\nprint(*sorted(m for m in {modules!r} if m in sys.modules))\n"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout.split()


def test_a_cycle_is_found() -> None:
    """The cycle finder finds a cycle (so that the test above can fail)."""
    graph = grimp.ImportGraph()
    for name in ("a", "b", "c"):
        graph.add_module(name)
    graph.add_import(importer="a", imported="b")
    graph.add_import(importer="b", imported="a")
    graph.add_import(importer="b", imported="c")
    assert _cycles(graph, {"a", "b", "c"}) == [["a", "b"]]


def _function_imports(path: Path) -> list[tuple[int, bool]]:
    """(line, marked lazy) of every import statement inside a function or method of ``path``."""
    source = path.read_text()
    lines = source.splitlines()
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            for inner in ast.walk(node):
                if isinstance(inner, ast.Import | ast.ImportFrom):
                    found.append((inner.lineno, "# lazy:" in lines[inner.lineno - 1]))
    return found


def _unmarked_and_lazy(folder: Path) -> tuple[list[str], int]:
    unmarked, lazy = [], 0
    for path in sorted(folder.rglob("*.py")):
        for line, marked in _function_imports(path):
            if marked:
                lazy += 1
            else:
                unmarked.append(f"{path.relative_to(ROOT)}:{line}")
    return unmarked, lazy


@pytest.mark.parametrize(
    ("folder", "allowed"), [(SERVICES, LAZY_ALLOWED), (ENGINE, LAZY_ALLOWED_ENGINE), (BENCHES, LAZY_ALLOWED_BENCHES)]
)
def test_no_import_inside_a_function(folder: Path, allowed: int) -> None:
    unmarked, lazy = _unmarked_and_lazy(folder)
    assert unmarked == []
    assert lazy <= allowed


def test_loose_modules_are_gone() -> None:
    """services/ holds packages only (layers), no loose module beside them."""
    loose = [p.name for p in SERVICES.glob("*.py") if p.name != "__init__.py"]
    assert loose == []
