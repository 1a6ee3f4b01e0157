"""The repository's promises about itself: CI runs the README's test command, and the code
imports the project as the one installed package, beamctl."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TEST_COMMAND = "pip install -e '.[test]' && pytest"
FOLDERS = ("config", "models", "gains", "rt", "hal", "common", "simulation", "identification", "service",
           "reports", "bench", "tools")


def test_ci_runs_exactly_the_readme_test_command():
    ci_lines = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()]
    readme = (ROOT / "README.md").read_text()
    assert TEST_COMMAND in ci_lines, f".ci/run must run {TEST_COMMAND!r} on a line of its own"
    assert TEST_COMMAND in readme, f"README.md must give the test command {TEST_COMMAND!r} that .ci/run runs"
    assert ci_lines[-1] == ".ci/wheel-check \"$work\"", "CI ends by checking the installed wheel"


def test_the_project_is_imported_as_beamctl_only():
    """models/, gains/, ... install as beamctl.models, beamctl.gains, ...: an import of a bare
    folder name works only inside the checkout and would pick up any other package of that
    name in site-packages (PyPI's rt, for one)."""
    bare = []
    for path in sorted(ROOT.glob("*/**/*.py")):
        if path.parts[len(ROOT.parts)] not in FOLDERS + ("tests",):
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level
                     else [])
            bare += [f"{path.relative_to(ROOT)}:{node.lineno} {n}" for n in names
                     if n.split(".")[0] in FOLDERS]
    assert not bare, f"imports of a bare project folder (use beamctl.<folder>): {bare}"
