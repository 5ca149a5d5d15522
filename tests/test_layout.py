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
from service.http.error_responses import STATUS, status_of

pytestmark = pytest.mark.timeout(60)

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("vfm_core", "service", "replay")

#: cycles inside vfm_core that predate this check; vfm_core is not the service's to change.
#: A new cycle fails; one of these disappearing does not.
KNOWN_VFM_CORE_CYCLES: set[frozenset[str]] = set()
#: cycles closed only by a type-only import (``if TYPE_CHECKING:``), each to be removed
KNOWN_TYPE_ONLY_CYCLES: set[frozenset[str]] = set()


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
        assert status_of(cls("A sentence.")) in (401, 403, 404, 409, 415, 422, 503)
    assert status_of(errors.Busy("x")) == status_of(errors.Stopping("x")) == 503
    assert status_of(errors.ServiceError("x")) == 500  # never raised as such
    with pytest.raises(ValueError, match="not a rejection reason"):
        errors.InvalidRequest("A sentence.", "no such reason")


def test_every_slow_entry_names_a_test() -> None:
    """The ``slow`` lists of tests/conftest.py name files and tests that exist: a renamed
    test would otherwise leave the fast tier silently."""
    import conftest

    tests = ROOT / "tests"
    for file in (*conftest.SLOW_FILES, *conftest.LONGEST_FIRST):
        assert (tests / file).is_file(), file
    named = [*conftest.SLOW_TESTS, *(test for test, _ in conftest.SLOW_CASES)]
    for entry in named:
        file, _, name = entry.partition("::")
        tree = ast.parse((tests / file).read_text(encoding="utf-8"))
        defined = {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}
        assert name in defined, entry


#: the most lines a function may take, from its ``def`` to its last line (issue 37)
MAX_FUNCTION_LINES = 80
#: functions over that limit when the check began (``path::qualified name``: lines), to be
#: split where a name explains the part. A new one fails, a listed one may not grow, and
#: one split or cut to the limit must leave the list: the list only shrinks.
LONG_FUNCTIONS: dict[str, int] = {}


def _function_lengths(tree: ast.AST) -> dict[str, int]:
    """Lines of every function in ``tree`` (methods and nested functions by qualified name)."""
    lengths: dict[str, int] = {}

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                name = prefix + child.name
                lengths[name] = (child.end_lineno or child.lineno) - child.lineno + 1
                visit(child, name + ".")
            elif isinstance(child, ast.ClassDef):
                visit(child, prefix + child.name + ".")
            else:
                visit(child, prefix)

    visit(tree, "")
    return lengths


def test_no_new_function_over_80_lines() -> None:
    """No function grows past :data:`MAX_FUNCTION_LINES` lines; the long ones of
    :data:`LONG_FUNCTIONS` may only get shorter, and leave the list when they are split."""
    found: dict[str, int] = {}
    for _, path in sorted(_modules().items()):
        where = path.relative_to(ROOT).as_posix()
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for name, lines in _function_lengths(tree).items():
            if lines > MAX_FUNCTION_LINES:
                found[f"{where}::{name}"] = lines
    new = [f"{k}: {n} lines" for k, n in found.items() if k not in LONG_FUNCTIONS]
    grown = [
        f"{k}: {n} lines, {LONG_FUNCTIONS[k]} allowed"
        for k, n in found.items()
        if k in LONG_FUNCTIONS and n > LONG_FUNCTIONS[k]
    ]
    gone = [k for k in LONG_FUNCTIONS if k not in found]
    assert not new, (
        f"Functions over {MAX_FUNCTION_LINES} lines: {new}; split them where a name "
        "explains the part."
    )
    assert not grown, f"Long functions grew: {grown}; split them instead."
    assert not gone, (
        f"No longer over {MAX_FUNCTION_LINES} lines (or renamed): {gone}; remove them from "
        "LONG_FUNCTIONS, so the list only shrinks."
    )


def test_the_function_length_check_counts_methods_and_nested_functions() -> None:
    """The count above sees a method and a nested function, from ``def`` to the last line."""
    method = "    def long(self):\n" + "".join(f"        x{i} = {i}\n" for i in range(80))
    nested = "def outer():\n    def inner():\n        return 1\n    return inner\n"
    source = "class A:\n" + method + nested
    lengths = _function_lengths(ast.parse(source))
    assert lengths == {"A.long": 81, "outer": 4, "outer.inner": 2}


#: private attributes a module may read on an object it does not own, and why. Everything
#: else named ``<name>._attr`` (``<name>`` not ``self`` / ``cls`` nor an imported module)
#: must be defined in the same module (its own class's state, read on another instance).
PRIVATE_READS_ALLOWED: dict[str, str] = {
    "_buffers": "torch.nn.Module keeps its buffers there; read (and swapped, as "
    "torch.func.functional_call does) on the hot path where Module.__getattr__ costs more",
    "_parameters": "torch.nn.Module keeps its parameters there (stacking swaps them in place)",
    "_modules": "torch.nn.Module keeps its submodules there (the path to a stacked tensor)",
    "_version": "torch.Tensor's in-place change counter: a cache kept while a tensor is unchanged",
    "_optimizer_step_pre_hooks": "torch.optim.Optimizer's hooks: a plain optimiser has none, "
    "so its step may be taken without torch's per-step wrapper",
    "_optimizer_step_post_hooks": "as _optimizer_step_pre_hooks",
    "_vfm_plain": "the project's own mark on a torch optimiser (training.py sets and reads it)",
}


def _defined_here(tree: ast.AST) -> set[str]:
    """Names a module defines: functions, classes, class-level names, ``self.x`` / ``cls.x``."""
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            names.add(node.name)
        if isinstance(node, ast.ClassDef):
            for st in node.body:
                targets = (
                    st.targets
                    if isinstance(st, ast.Assign)
                    else [st.target]
                    if isinstance(st, ast.AnnAssign)
                    else []
                )
                names.update(t.id for t in targets if isinstance(t, ast.Name))
        if (
            isinstance(node, ast.Attribute)
            and isinstance(node.ctx, ast.Store)
            and isinstance(node.value, ast.Name)
            and node.value.id in ("self", "cls")
        ):
            names.add(node.attr)
    return names


def _private_reads(tree: ast.AST) -> list[tuple[int, str]]:
    """``<name>._attr`` reads in ``tree`` of attributes defined elsewhere (line, text)."""
    imported: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imported.update((a.asname or a.name).split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            imported.update(a.asname or a.name for a in node.names)
    own = _defined_here(tree)
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Attribute):
            continue
        attr, base = node.attr, node.value
        if not attr.startswith("_") or attr.startswith("__") or attr in own:
            continue
        if isinstance(base, ast.Name) and (base.id in ("self", "cls") or base.id in imported):
            continue
        if attr not in PRIVATE_READS_ALLOWED:
            found.append((node.lineno, ast.unparse(node)))
    return found


def test_no_module_reads_another_classs_private_attributes() -> None:
    """A module reads only its own classes' private state (issue 37): what one class needs
    of another is a public method or attribute (as the learning methods' group operations,
    ``group_key`` / ``predict_group`` / ``learn_key`` / ``learn_group``, replaced the
    streaming module's reading of the methods' optimisers and filter states)."""
    offences = []
    for module, path in sorted(_modules().items()):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        offences += [f"{module}:{line}: {text}" for line, text in _private_reads(tree)]
    assert not offences, "\n".join(offences)


def test_the_private_read_check_finds_a_read() -> None:
    """The check above catches a read of another class's private attribute, and not one of
    the module's own class or of an allowed torch internal."""
    source = (
        "import torch\n"
        "class A:\n"
        "    def __init__(self):\n"
        "        self._mine = 1\n"
        "    def same(self, other):\n"
        "        return other._mine\n"
        "def reach(method, model):\n"
        "    return method._q, model._buffers, torch._foreach_add_\n"
    )
    assert _private_reads(ast.parse(source)) == [(8, "method._q")]


#: the concrete learner classes the service holds through ``vfm_core.learning.streaming.Learner``
CONCRETE_LEARNERS = {"WellLearner", "FieldWell"}


def _learner_class_checks(tree: ast.AST) -> list[tuple[int, str]]:
    """``isinstance`` / ``issubclass`` calls in ``tree`` naming a concrete learner class
    (alone, in a tuple or a union, or as ``module.Class``): line and text."""
    found = []
    for node in ast.walk(tree):
        if not (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Name)
            and node.func.id in ("isinstance", "issubclass")
            and len(node.args) == 2
        ):
            continue
        named = {n.id for n in ast.walk(node.args[1]) if isinstance(n, ast.Name)}
        named |= {n.attr for n in ast.walk(node.args[1]) if isinstance(n, ast.Attribute)}
        if named & CONCRETE_LEARNERS:
            found.append((node.lineno, ast.unparse(node)))
    return found


def test_the_service_asks_the_learner_protocol_not_its_class() -> None:
    """No module under service/ branches on a learner's class (issue 37): what differs
    between a well's own learner and a well of the field-wide model (a shared model, a
    checkpoint group, steps in groups, ...) is asked of the ``Learner`` protocol, so a third
    kind of learner needs no service edit. The check finds such calls in an example."""
    example = (
        "from vfm_core.learning.streaming import WellLearner\n"
        "import vfm_core.learning.field as fl\n"
        "def f(st, learner):\n"
        "    if isinstance(st.learner, WellLearner):\n"
        "        return 1\n"
        "    return isinstance(learner, (int, fl.FieldWell)) or isinstance(learner, Learner)\n"
    )
    assert [line for line, _ in _learner_class_checks(ast.parse(example))] == [4, 6]
    offences = []
    for module, path in sorted(_modules().items()):
        if module.split(".")[0] == "service":
            tree = ast.parse(path.read_text(encoding="utf-8"))
            offences += [f"{module}:{n}: {text}" for n, text in _learner_class_checks(tree)]
    assert not offences, "\n".join(offences)
