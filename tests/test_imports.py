"""How the rooms import each other: no import circle among the product's modules, no import
inside a function to dodge one, and no room importing the command line.

The graph: an edge from a module to every beamctl module it imports, anywhere in its source
(module level, inside a function, under ``if TYPE_CHECKING:``): a circle through any of them is
one a reader follows round. ``from beamctl.x
import a`` is an edge to ``beamctl.x.a`` when that is a module, else to ``beamctl.x`` itself (the
names its ``__init__`` holds). A package's ``__init__`` importing its own modules to re-export
them is not a circle unless one of those modules imports names from the package."""

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
# every room the package installs (pyproject.toml's package-dir)
ROOMS = tuple(sorted(p.parent.name for p in ROOT.glob("*/__init__.py")
                     if p.parent.name not in ("tests", "docs")))
# The command line defers its imports until main() runs, so that a Ctrl-C while numpy and scipy
# load (about a second) still ends in one line, and `beamctl ctl` answers without loading them.
DEFERRED = {"tools/cli.py"}


def _modules() -> dict[str, Path]:
    out = {}
    for room in ROOMS:
        for path in sorted((ROOT / room).glob("*.py")):
            out[f"beamctl.{room}" + ("" if path.stem == "__init__" else f".{path.stem}")] = path
    return out


MODULES = _modules()


def _targets(node: ast.AST) -> list[str]:
    if isinstance(node, ast.Import):
        return [a.name for a in node.names if a.name in MODULES]
    if isinstance(node, ast.ImportFrom) and not node.level and (node.module or "").startswith("beamctl."):
        out = []
        for a in node.names:
            sub = f"{node.module}.{a.name}"
            out.append(sub if sub in MODULES else node.module)
        return [t for t in out if t in MODULES]
    return []


def _imports(path: Path) -> tuple[set[str], list[str]]:
    """(beamctl modules imported at module level outside ``if TYPE_CHECKING:``, 'line: module' of
    those imported in a function, every beamctl module imported anywhere)."""
    tree = ast.parse(path.read_text(), str(path))
    top: set[str] = set()
    inner: list[str] = []
    every: set[str] = set()

    def visit(node: ast.AST, in_function: bool, type_checking: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                targets = _targets(child)
                every.update(targets)
                if in_function:
                    inner.extend(f"{child.lineno}: {t}" for t in targets)
                elif not type_checking:
                    top.update(targets)
                continue
            guarded = isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test)
            checking = type_checking or guarded
            function = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            visit(child, function, checking)

    visit(tree, False, False)
    return top, inner, every


GRAPH = {name: _imports(path) for name, path in MODULES.items()}
# the command line imports each command's module by name when that command runs (tools/cli.py
# ``COMMANDS``): those are edges of the graph too
_CLI = "beamctl.tools.cli"
_named = ast.literal_eval(next(
    node.value for node in ast.parse(MODULES[_CLI].read_text()).body
    if isinstance(node, ast.Assign) and any(getattr(t, "id", "") == "COMMANDS" for t in node.targets)))
GRAPH[_CLI][2].update(f"beamctl.tools.{m}" for m in _named.values())


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), and self-imports."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = [0]

    def strong(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                strong(w)
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
            if len(component) > 1 or v in graph[v]:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            strong(v)
    return found


def test_no_import_circle_among_the_product_s_modules():
    graph = {name: every for name, (_, _, every) in GRAPH.items()}
    cycles = _cycles(graph)
    assert not cycles, f"modules that import each other (directly or round a circle): {cycles}"


def test_the_checker_sees_a_circle():
    """The check above on a made-up graph: a -> b -> c -> a is found, a tree is not."""
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b", "c"}, "b": {"c"}, "c": set()}) == []


def test_no_import_inside_a_function_but_where_the_command_line_defers_them():
    inner = {str(MODULES[name].relative_to(ROOT)): lines for name, (_, lines, _) in GRAPH.items() if lines}
    unexpected = {path: lines for path, lines in inner.items() if path not in DEFERRED}
    assert not unexpected, f"beamctl modules imported inside functions (import them at the top): {unexpected}"


def test_no_room_imports_the_command_line():
    offenders = {}
    for name, (top, inner, _) in GRAPH.items():
        found = sorted({t for t in top if t.startswith("beamctl.tools")}
                       | {i for i in inner if ": beamctl.tools" in i})
        if found and not name.startswith("beamctl.tools"):
            offenders[name] = found
    assert not offenders, f"library rooms importing tools/ (the command line only): {offenders}"


def test_only_the_lab_service_and_its_commands_import_the_service():
    """How a run is put together lives in assembly/; the lab service (service/) is one of its
    users, and only the command line's service commands (tools/) reach into it."""
    offenders = {name: sorted(t for t in every if t.startswith("beamctl.service"))
                 for name, (_, _, every) in GRAPH.items()
                 if not name.startswith(("beamctl.service", "beamctl.tools"))}
    offenders = {k: v for k, v in offenders.items() if v}
    assert not offenders, f"rooms other than service/ and tools/ importing the lab service: {offenders}"


def test_the_command_line_s_modules_by_name_are_in_the_graph():
    missing = sorted(m for m in GRAPH[_CLI][2] if m not in MODULES)
    assert not missing, f"tools/cli.py COMMANDS names modules that do not exist: {missing}"
    assert len(GRAPH[_CLI][2]) > 10, "the command line's command modules were not read into the graph"


def test_every_installed_room_is_in_the_graph():
    text = (ROOT / "pyproject.toml").read_text()
    section = text.split("[tool.setuptools.package-dir]", 1)[1].split("\n[", 1)[0]
    dirs = sorted(re.findall(r'^"beamctl\.\w+" = "(\w+)"', section, re.M))
    assert dirs == sorted(ROOMS), f"pyproject.toml installs {dirs}, the import checks read {sorted(ROOMS)}"
