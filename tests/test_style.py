"""Style and layering checks as part of the test suite (so CI runs them with pytest).

The size rule: no module of hippomap, server or web over ``MAX_MODULE_LINES`` lines, and no function over
``MAX_FUNCTION_LINES`` unless its docstring says why it stays whole, with the phrase "One function on purpose:"
followed by the reason (``LiveSession.submit``: the checks, the wait and the sequence numbers are one
critical section).

``ruff check`` enforces the lint rules of ``[tool.ruff]``, ``ruff format --check`` its layout,
``lint-imports`` the import contracts of ``[tool.importlinter]`` (the model never imports the service, the
viewer or a web framework) and ``mypy``
the static types of ``[tool.mypy]`` (the packages hippomap, server and web), all configured in
pyproject.toml. The tools come with the ``test`` extra; they are looked up beside the running
interpreter first (``.venv/bin`` after ``pip install -e ".[test]"``), then on ``PATH``.
"""

from __future__ import annotations

import ast
import re
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


def test_ruff_format_is_clean():
    """The tree is laid out by ``ruff format`` ([tool.ruff.format]): run it before committing."""
    r = _run([_tool("ruff"), "format", "--check", "--no-cache", "."])
    assert r.returncode == 0, f"ruff format would change these files (run ruff format .):\n{r.stdout}\n{r.stderr}"


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
    forbidden = {
        m
        for c in config["contracts"]
        if c["type"] == "forbidden" and c["source_modules"] == ["hippomap"]
        for m in c["forbidden_modules"]
    }
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
    assert hooks["ruff-format"]["entry"].split()[:2] == ["ruff", "format"]
    assert hooks["lint-imports"]["entry"].split()[0] == "lint-imports"
    assert hooks["mypy"]["entry"].split()[0] == "mypy" and hooks["mypy"]["pass_filenames"] is False
    assert all(h["language"] == "system" for h in hooks.values())  # nothing to download


# -- size: modules and functions ----------------------------------------------------------------------------

MAX_MODULE_LINES = 500
MAX_FUNCTION_LINES = 60
PACKAGES = ("hippomap", "server", "web")
#: the stated reason: "One function on purpose: <why>"
REASON = re.compile(r"One function on purpose: *\S")
#: functions over the limit without a stated reason, each with why it is tolerated here; nothing else belongs here
ALLOWED_LONG: set[str] = set()


def _modules() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py"))


def _dotted(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def long_functions(source: str, module: str) -> dict[str, int]:
    """The functions and methods of ``source`` (nested ones too, by qualified name under ``module``) longer than
    ``MAX_FUNCTION_LINES`` lines whose docstring does not state the reason; name -> lines."""
    found: dict[str, int] = {}

    def walk(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                name = f"{prefix}.{child.name}"
                if not isinstance(child, ast.ClassDef):
                    lines = (child.end_lineno or child.lineno) - child.lineno + 1
                    doc = " ".join((ast.get_docstring(child) or "").split())
                    if lines > MAX_FUNCTION_LINES and not REASON.search(doc):
                        found[name] = lines
                walk(child, name)
            else:
                walk(child, prefix)

    walk(ast.parse(source), module)
    return found


#: the stated reason of a longer module, in its docstring: "One module on purpose: <why>"
MODULE_REASON = re.compile(r"One module on purpose: *\S")


def _module_reason(source: str) -> bool:
    doc = ast.get_docstring(ast.parse(source)) or ""
    return bool(MODULE_REASON.search(doc))


def test_no_module_is_over_500_lines():
    """Modules stay small enough to read whole: split a longer one by concept (see docs/ARCHITECTURE.md),
    unless its docstring says why it stays one ("One module on purpose: ...": hippomap/config.py, the one
    config that holds every parameter with its default and source)."""
    texts = {str(p.relative_to(ROOT)): p.read_text() for p in _modules()}
    assert len(texts) > 50  # the three packages were found
    over = {
        name: len(text.splitlines())
        for name, text in texts.items()
        if len(text.splitlines()) > MAX_MODULE_LINES and not _module_reason(text)
    }
    assert not over, f"modules over {MAX_MODULE_LINES} lines (split them by concept): {over}"


def test_a_module_reason_is_read_from_the_module_docstring_only():
    assert _module_reason('"""Settings.\n\nOne module on purpose: every parameter in one place."""\nx = 1\n')
    assert not _module_reason('"""Settings."""\n# One module on purpose: a comment is not the docstring\n')
    assert not _module_reason('"""One module on purpose:"""\n')  # a reason must follow


def test_no_function_is_over_60_lines_without_a_stated_reason():
    """A longer function is broken into named steps, or its docstring says why it stays whole
    ("One function on purpose: ..."). ``ALLOWED_LONG`` lists the only exceptions and must not go stale."""
    found: dict[str, int] = {}
    for path in _modules():
        found.update(long_functions(path.read_text(), _dotted(path)))
    over = {name: n for name, n in found.items() if name not in ALLOWED_LONG}
    assert not over, (
        f"functions over {MAX_FUNCTION_LINES} lines with no 'One function on purpose: <why>' in their "
        f"docstring (break them into named steps, or state why they stay whole): {over}"
    )
    stale = ALLOWED_LONG - set(found)
    assert not stale, f"no longer long (or renamed): remove from ALLOWED_LONG: {sorted(stale)}"


def _function(name: str, lines: int, doc: str = "", indent: str = "") -> str:
    """Source of a function ``lines`` lines long (its def line, docstring and body), indented by ``indent``."""
    head = [f"def {name}():"] + ([f'    """{doc}"""'] if doc else [])
    body = [f"    x{i} = {i}" for i in range(lines - len(head) - 1)] + ["    return 0"]
    return "".join(f"{indent}{line}\n" for line in head + body)


def test_the_function_size_check_sees_long_functions_and_reasons():
    """The checker itself: a long function is reported (methods and nested functions by qualified name), a
    short one or one whose docstring states the reason (even across a line break) is not; the bare phrase with
    no reason after it does not count."""
    n = MAX_FUNCTION_LINES
    method = "class C:\n    def method(self):\n" + _function("inner", n + 1, indent="        ") + "        return 1\n"
    source = "\n".join(
        [
            _function("long", n + 1),
            _function("at_the_limit", n),
            method,
            _function("kept", n + 5, doc="Does a thing. One function on\n    purpose: one critical section."),
            _function("unexplained", n + 5, doc="One function on purpose:"),
        ]
    )
    assert long_functions(source, "m") == {
        "m.long": n + 1,
        "m.C.method": n + 3,
        "m.C.method.inner": n + 1,
        "m.unexplained": n + 5,
    }


def test_the_architecture_module_map_names_every_module():
    """docs/ARCHITECTURE.md's module map has a row for every module of the packages and of tests/support, and
    no row for a module that is gone (each ``### `folder/``` section lists that folder's modules)."""
    text = (ROOT / "docs" / "ARCHITECTURE.md").read_text()
    documented, folder = set(), None
    for line in text[text.index("## Module map") :].splitlines():
        if heading := re.match(r"### `([^`]+)/`", line):
            folder = heading.group(1)
        elif (row := re.match(r"\| `([^`]+\.py)` \|", line)) and folder:
            documented.add(f"{folder}/{row.group(1)}")
    actual = {str(p.relative_to(ROOT)) for p in _modules() + sorted((ROOT / "tests" / "support").glob("*.py"))}
    assert len(documented) > 50
    assert not actual - documented, f"modules missing from the module map: {sorted(actual - documented)}"
    assert not documented - actual, f"the module map names modules that do not exist: {sorted(documented - actual)}"
