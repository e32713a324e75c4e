"""Style and layering checks as part of the test suite (so CI runs them with pytest).

``ruff check`` enforces the lint rules of ``[tool.ruff]``, ``lint-imports`` the import contracts of
``[tool.importlinter]`` (the model never imports the service, the viewer or a web framework) and ``mypy``
the static types of ``[tool.mypy]`` (the packages hippomap, server and web), all configured in
pyproject.toml. The tools come with the ``test`` extra; they are looked up beside the running
interpreter first (``.venv/bin`` after ``pip install -e ".[test]"``), then on ``PATH``.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]


def _tool(name: str) -> str:
    """The path of console script ``name``: the interpreter's bin folder first, then ``PATH``. The tools come
    with the test extra that the README's test command installs, so a missing one is a failure, not a skip."""
    beside = Path(sys.executable).parent / name
    if beside.is_file():
        return str(beside)
    found = shutil.which(name)
    if found is None:
        pytest.fail(f"{name} is not installed (it comes with the test extra: pip install -e '.[test]')")
    return found


def _run(args: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=240)


def test_ruff_check_is_clean():
    r = _run([_tool("ruff"), "check", "--no-cache", "."])
    assert r.returncode == 0, f"ruff check found problems (fix them or see [tool.ruff]):\n{r.stdout}\n{r.stderr}"


def test_import_contracts_hold():
    r = _run([_tool("lint-imports"), "--no-cache"])
    assert r.returncode == 0, f"an import contract of [tool.importlinter] is broken:\n{r.stdout}\n{r.stderr}"
    assert "0 broken" in r.stdout, r.stdout


def test_mypy_is_clean():
    """The packages type-check under [tool.mypy] (its cache, .mypy_cache, makes a re-run take seconds)."""
    r = _run([_tool("mypy")])
    assert r.returncode == 0, f"mypy found type errors (fix them or see [tool.mypy]):\n{r.stdout}\n{r.stderr}"
    assert "Success: no issues found" in r.stdout, r.stdout


def test_mypy_checks_the_three_packages():
    """The type check covers the model, the service and the viewer (a config edit cannot drop one silently)."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["mypy"]
    assert set(config["files"]) == {"hippomap", "server", "web"}
    assert config["python_version"] == "3.11"


def test_import_contracts_cover_the_model_boundary():
    """The contracts that keep the model free of the service exist (a config edit cannot drop them silently)."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    forbidden = {m for c in config["contracts"] if c["type"] == "forbidden" and c["source_modules"] == ["hippomap"]
                 for m in c["forbidden_modules"]}
    assert {"server", "web", "fastapi", "starlette", "uvicorn", "viser"} <= forbidden
    assert config["include_external_packages"] is True  # required for the contract on external packages


def test_tools_are_in_the_test_extra_and_the_pre_commit_hooks():
    """CI installs the test extra, so the checks run there; the pre-commit hooks run the same commands."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    extra = " ".join(project["optional-dependencies"]["test"])
    assert "ruff" in extra and "import-linter" in extra and "mypy" in extra
    config = yaml.safe_load((ROOT / ".pre-commit-config.yaml").read_text())
    hooks = {h["id"]: h for repo in config["repos"] for h in repo["hooks"]}
    assert hooks["ruff"]["entry"].split()[:2] == ["ruff", "check"]
    assert hooks["lint-imports"]["entry"].split()[0] == "lint-imports"
    assert hooks["mypy"]["entry"].split()[0] == "mypy" and hooks["mypy"]["pass_filenames"] is False
    assert all(h["language"] == "system" for h in hooks.values())  # nothing to download
