"""The wheel ships the product only: the packages hippomap, server and web, without test scaffolding.

The wheel is built from a copy of the checkout that still holds ``tests/`` and ``bench/`` (so the
package discovery of ``[tool.setuptools.packages.find]`` is what keeps them out), with pip's
ordinary PEP 517 build (``pip wheel --no-deps``). Its contents are compared with the source tree:
every module of the three packages is in it, and nothing of the test support (``tests.*``, or a
module named testing / simfeed / screenshot, which used to live in ``server`` and ``web``).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("hippomap", "server", "web")
#: module names of the former test/benchmark scaffolding in the product packages
SCAFFOLDING = {"testing.py", "simfeed.py", "screenshot.py"}
#: what the copy leaves out: version control, caches and build output (tests/ and bench/ are copied)
NOT_COPIED = shutil.ignore_patterns(".git", ".venv", "__pycache__", "*.pyc", "*.egg-info", "build", "dist",
                                    ".pytest_cache", ".hypothesis", ".ruff_cache", ".import_linter_cache",
                                    "test-artifacts", "results", "hippomap-data")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> list[str]:
    """The file names in a wheel built from a copy of this checkout."""
    tmp = tmp_path_factory.mktemp("wheel")
    src, out = tmp / "src", tmp / "out"
    shutil.copytree(ROOT, src, ignore=NOT_COPIED)
    assert (src / "tests" / "support" / "live.py").is_file()  # the scaffolding is there to be left out
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--disable-pip-version-check", "-q", "-w", str(out),
           str(src)]
    res = subprocess.run(cmd, cwd=tmp, capture_output=True, text=True, timeout=280)
    assert res.returncode == 0, f"{' '.join(cmd)} failed:\n{res.stdout}\n{res.stderr}"
    wheels = list(out.glob("hippomap-*.whl"))
    assert len(wheels) == 1, list(out.iterdir())
    with zipfile.ZipFile(wheels[0]) as z:
        return z.namelist()


def test_the_find_configuration_names_only_the_product_packages():
    find = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]
    assert sorted(find["include"]) == ["hippomap*", "server*", "web*"]


def test_wheel_holds_every_product_module(wheel):
    names = set(wheel)
    modules = {p.relative_to(ROOT).as_posix() for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")
               if "__pycache__" not in p.parts}
    assert "hippomap/protocol.py" in modules and "server/formats/protocol.py" in modules
    assert not modules - names, f"modules missing from the wheel: {sorted(modules - names)}"
    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    tops = {n.split("/")[0] for n in names}
    assert tops == {*PACKAGES, f"hippomap-{version}.dist-info"}, tops


def test_wheel_holds_no_test_scaffolding(wheel):
    leaked = [n for n in wheel if n.split("/")[0] in ("tests", "bench") or n.rsplit("/", 1)[-1] in SCAFFOLDING]
    assert not leaked, f"test scaffolding in the wheel: {leaked}"
    modules = {n[:-3].replace("/", ".") for n in wheel if n.endswith(".py")}
    assert not {m for m in modules if m == "tests" or m.startswith("tests.")}
    assert not {m for m in modules if m.rsplit(".", 1)[-1] in {"testing", "simfeed", "screenshot"}}
