"""The repository's promises about itself: CI runs the README's test command and builds the
documentation site the README points to, the README stays a short first page, and the code
imports the project as the one installed package, beamctl."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TEST_COMMAND = "pip install -e '.[test]' && pytest"
DOCS_COMMAND = "pip install -e '.[docs]' && mkdocs build --strict -f docs/mkdocs.yml"
WHEEL_CHECK = ".ci/wheel-check \"$work\""
README_MAX_LINES = 250
# the rooms pyproject.toml installs as beamctl.<room>
FOLDERS = tuple(sorted(p.parent.name for p in ROOT.glob("*/__init__.py")
                       if p.parent.name not in ("tests", "docs")))


def test_ci_runs_exactly_the_readme_test_command():
    ci_lines = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()]
    readme = (ROOT / "README.md").read_text()
    assert TEST_COMMAND in ci_lines, f".ci/run must run {TEST_COMMAND!r} on a line of its own"
    assert TEST_COMMAND in readme, f"README.md must give the test command {TEST_COMMAND!r} that .ci/run runs"
    assert WHEEL_CHECK in ci_lines, "CI checks the installed wheel"
    assert ci_lines.index(TEST_COMMAND) < ci_lines.index(WHEEL_CHECK), "CI checks the wheel after the tests"
    assert ci_lines[-1] == DOCS_COMMAND, f"CI ends by building the documentation: {DOCS_COMMAND!r}"


def test_the_readme_is_a_short_first_page_and_the_docs_site_is_configured():
    """README.md is what a newcomer reads first (what it is, install, the first commands, where to
    read on); the manual is the MkDocs site of docs/, built as the README says."""
    import yaml

    readme = (ROOT / "README.md").read_text()
    lines = len(readme.splitlines())
    assert lines <= README_MAX_LINES, f"README.md has {lines} lines, at most {README_MAX_LINES}"
    assert DOCS_COMMAND in readme, f"README.md must say how to build the documentation: {DOCS_COMMAND!r}"
    config_path = ROOT / "docs" / "mkdocs.yml"
    config = yaml.safe_load(config_path.read_text())   # no !!python tags in it: the safe loader reads it
    docs = config_path.parent
    assert (docs / config["docs_dir"] / "index.md").is_file(), "the site's pages are missing"
    assert all((docs / hook).is_file() for hook in config.get("hooks", [])), "a docs hook is missing"


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
