"""The repository's promises about itself: CI runs the README's test command."""

from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_ci_runs_exactly_the_readme_test_command():
    ci_lines = (ROOT / ".ci" / "run").read_text().splitlines()
    command = ci_lines[-1].strip()
    readme = (ROOT / "README.md").read_text()
    assert command == "pip install -e '.[test]' && pytest", f".ci/run ends with {command!r}"
    assert command in readme, f"README.md must give the test command {command!r} that .ci/run runs"
