"""The static checks configured in pyproject.toml, as part of the suite so CI enforces them:
ruff's lint and format check over the repository and mypy (strict on pipeline/). A finding fails the test with
the tool's own report."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _run(*command: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", *command], cwd=ROOT, capture_output=True, text=True, timeout=540)


def test_ruff_finds_nothing() -> None:
    result = _run("ruff", "check", "--no-cache", "--output-format", "concise", ".")
    assert result.returncode == 0, result.stdout + result.stderr


def test_ruff_format_changes_nothing() -> None:
    result = _run("ruff", "format", "--check", "--no-cache", ".")
    assert result.returncode == 0, "run `ruff format .`:\n" + result.stdout + result.stderr


@pytest.mark.timeout(600)
def test_mypy_finds_nothing() -> None:
    # The files and strictness come from [tool.mypy] in pyproject.toml; the cache makes reruns fast.
    result = _run("mypy")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "Success: no issues found" in result.stdout


def test_tests_mirror_the_packages() -> None:
    """Every folder of tests/ is a package's, so a module's tests are found where the module is
    (tests/<package>/test_<module>.py); and test file names are unique across folders, as
    pytest's default import mode needs (tests/ is not a package)."""
    from benchmarks.import_graph import LAYERS

    packages = {layer.package for layer in LAYERS}
    folders = {path.name for path in (ROOT / "tests").iterdir() if path.is_dir() and not path.name.startswith((".", "_"))}
    assert folders - packages == set(), f"test folders that are no package's: {sorted(folders - packages)}"
    names = [path.name for path in (ROOT / "tests").rglob("test_*.py")]
    assert len(names) == len(set(names)), sorted({name for name in names if names.count(name) > 1})
