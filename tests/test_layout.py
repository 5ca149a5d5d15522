"""The layout holds: imports run one way, without cycles, and HTTP stays out of the engine.

The import graph is read from the source with ``ast`` (nothing is imported): every
``import`` and ``from ... import`` of the project's modules counts, at module level, inside
functions alike. Imports inside ``if TYPE_CHECKING:`` blocks never run: the graph of what
runs leaves them out, and may have no cycle; the full graph counts them too, since a
type-only import still ties two modules' designs together, and may have no cycle either
(move the shared type down into a module both import, as ``vfm_core.jobs.results``).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import service.errors as errors
from service.http.errors import STATUS, status_of

pytestmark = pytest.mark.timeout(60)

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("vfm_core", "service", "replay")

#: cycles inside vfm_core that predate this check; vfm_core is not the service's to change.
#: A new cycle fails; one of these disappearing does not.
KNOWN_VFM_CORE_CYCLES: set[frozenset[str]] = set()
#: cycles closed only by a type-only import (``if TYPE_CHECKING:``), each to be removed
KNOWN_TYPE_ONLY_CYCLES: set[frozenset[str]] = {
    # issue 37: removed with the diagnosis rework
    frozenset({"vfm_core.jobs.diagnose", "vfm_core.reporting.diagnosis"}),
}


def _modules() -> dict[str, Path]:
    found = {}
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join(parts)] = path
    return found


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imports(tree: ast.AST, module: str, is_package: bool, type_only: bool) -> list[str]:
    """Every module name an import in ``tree`` names (``from a import b`` gives a.b and a);
    with ``type_only``, those in ``if TYPE_CHECKING:`` blocks too."""
    names: list[str] = []

    def visit(node: ast.AST) -> None:
        if not type_only and isinstance(node, ast.If) and _is_type_checking(node):
            for statement in node.orelse:
                visit(statement)
            return
        if isinstance(node, ast.Import):
            names.extend(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if is_package else module.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                source = ".".join([*base, *([node.module] if node.module else [])])
            else:
                source = node.module or ""
            names.extend(f"{source}.{alias.name}" for alias in node.names)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return names


def import_graph(type_only: bool = True) -> dict[str, set[str]]:
    """Project module -> the project modules it imports (``type_only``: counting the imports
    for types only; else only those that run)."""
    modules = _modules()

    def resolve(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {m: set() for m in modules}
    for module, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for name in _imports(tree, module, path.name == "__init__.py", type_only):
            target = resolve(name)
            if target is not None and target != module:
                graph[module].add(target)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[frozenset[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[frozenset[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.add(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(frozenset(component))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return found


def test_the_graph_sees_function_level_imports() -> None:
    """The check can fail: a function-level import back from vfm_core makes a cycle."""
    graph = import_graph()
    assert "service.engine.core" in graph["service.app"] or "service.engine" in graph["service.app"]
    assert "service.http" in graph["service.app"]  # module level
    assert "service.testing" in graph["replay.demo"]  # inside run_demo
    looped = {**graph, "vfm_core.messages": graph["vfm_core.messages"] | {"service.engine.core"}}
    assert any("service.engine.core" in c for c in cycles(looped))


def test_the_graph_sees_type_only_imports() -> None:
    """The engine names the transport's Source for its types only: counted in the full
    graph, not in the graph of what runs; the study's result type lives below both the job
    and the report, so the report no longer imports the job."""
    full, runs = import_graph(), import_graph(type_only=False)
    assert "service.transport" in full["service.engine.worker"]
    assert "service.transport" not in runs["service.engine.worker"]
    assert "vfm_core.jobs.evaluate" not in full["vfm_core.reporting.study"]
    assert "vfm_core.jobs.results" in full["vfm_core.reporting.study"]
    looped = {**full, "vfm_core.jobs.results": {"vfm_core.reporting.study"}}
    assert any("vfm_core.jobs.results" in c for c in cycles(looped))


def test_no_import_cycle() -> None:
    found = set(cycles(import_graph(type_only=False)))
    assert found - KNOWN_VFM_CORE_CYCLES == set(), found - KNOWN_VFM_CORE_CYCLES
    assert all(all(m.startswith("vfm_core.") for m in c) for c in found)


def test_no_import_cycle_through_a_type_only_import() -> None:
    found = set(cycles(import_graph()))
    assert found - KNOWN_TYPE_ONLY_CYCLES == set(), found - KNOWN_TYPE_ONLY_CYCLES


def test_imports_run_one_way() -> None:
    graph = import_graph()
    for module, targets in graph.items():
        if module.startswith("vfm_core"):
            assert not {t for t in targets if not t.startswith("vfm_core")}, module
        if module.startswith("service"):  # the service never imports the field side
            assert not {t for t in targets if t.startswith("replay")}, module
        if module.startswith("service.http"):  # the HTTP layer is handed the service
            assert "service.app" not in targets, module
    # the field client and the replay talk to a bus, never to the service's code
    for module in ("replay.client", "replay.replayer", "replay.cli"):
        assert not {t for t in graph[module] if t.startswith("service")}, module


def test_no_http_in_the_engine() -> None:
    """The engine raises domain errors: no web framework, no status codes."""
    for path in (ROOT / "service" / "engine").rglob("*.py"):
        text = path.read_text(encoding="utf-8")
        for word in ("fastapi", "starlette", "service.http", "status="):
            assert word not in text, (path.name, word)
    for cls in (errors.ServiceError, *vars(errors).values()):
        if isinstance(cls, type) and issubclass(cls, errors.ServiceError):
            assert not hasattr(cls, "status"), cls


def test_every_domain_error_has_one_status() -> None:
    leaves = [
        getattr(errors, name)
        for name in errors.__all__
        if isinstance(getattr(errors, name), type)
        and issubclass(getattr(errors, name), errors.ServiceError)
        and not getattr(errors, name).__subclasses__()
    ]
    assert len(leaves) == 9
    for cls in leaves:
        assert cls in STATUS, cls
        assert status_of(cls("A sentence.")) in (401, 403, 404, 409, 422, 503)
    assert status_of(errors.Busy("x")) == status_of(errors.Stopping("x")) == 503
    assert status_of(errors.ServiceError("x")) == 500  # never raised as such
    with pytest.raises(ValueError, match="not a rejection reason"):
        errors.InvalidRequest("A sentence.", "no such reason")


def test_every_slow_entry_names_a_test() -> None:
    """The ``slow`` lists of tests/conftest.py name files and tests that exist: a renamed
    test would otherwise leave the fast tier silently."""
    import conftest

    tests = ROOT / "tests"
    for file in conftest.SLOW_FILES:
        assert (tests / file).is_file(), file
    named = [*conftest.SLOW_TESTS, *(test for test, _ in conftest.SLOW_CASES)]
    for entry in named:
        file, _, name = entry.partition("::")
        tree = ast.parse((tests / file).read_text(encoding="utf-8"))
        defined = {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}
        assert name in defined, entry
