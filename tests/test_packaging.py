"""The wheel ships the product only: the packages hippomap, server and web, without test scaffolding.

The wheel is built from a copy of the checkout that still holds ``tests/`` and ``bench/`` (so the
package discovery of ``[tool.setuptools.packages.find]`` is what keeps them out), with pip's
ordinary PEP 517 build (``pip wheel --no-deps``). Its contents are compared with the source tree:
every module of the three packages is in it, and nothing of the test support (``tests.*``, or a
module named testing / simfeed / screenshot, which used to live in ``server`` and ``web``). Its metadata
keeps the core install light: the optional packages are only in the extras that need them.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

from hippomap.extras import EXTRAS

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("hippomap", "server", "web")
#: module names of the former test/benchmark scaffolding in the product packages
SCAFFOLDING = {"testing.py", "simfeed.py", "screenshot.py"}
#: what the copy leaves out: version control, caches and build output (tests/ and bench/ are copied)
NOT_COPIED = shutil.ignore_patterns(
    ".git",
    ".venv",
    "__pycache__",
    "*.pyc",
    "*.egg-info",
    "build",
    "dist",
    ".pytest_cache",
    ".hypothesis",
    ".ruff_cache",
    ".import_linter_cache",
    "test-artifacts",
    "results",
    "hippomap-data",
)


@pytest.fixture(scope="module")
def wheel_file(tmp_path_factory) -> Path:
    """A wheel built from a copy of this checkout."""
    tmp = tmp_path_factory.mktemp("wheel")
    src, out = tmp / "src", tmp / "out"
    shutil.copytree(ROOT, src, ignore=NOT_COPIED)
    assert (src / "tests" / "support" / "live.py").is_file()  # the scaffolding is there to be left out
    cmd = [
        sys.executable,
        "-m",
        "pip",
        "wheel",
        "--no-deps",
        "--disable-pip-version-check",
        "-q",
        "-w",
        str(out),
        str(src),
    ]
    res = subprocess.run(cmd, cwd=tmp, capture_output=True, text=True, timeout=280)
    assert res.returncode == 0, f"{' '.join(cmd)} failed:\n{res.stdout}\n{res.stderr}"
    wheels = list(out.glob("hippomap-*.whl"))
    assert len(wheels) == 1, list(out.iterdir())
    return wheels[0]


@pytest.fixture(scope="module")
def wheel(wheel_file) -> list[str]:
    """The file names in the wheel."""
    with zipfile.ZipFile(wheel_file) as z:
        return z.namelist()


@pytest.fixture(scope="module")
def requirements(wheel_file) -> dict[str | None, set[str]]:
    """The wheel's ``Requires-Dist`` by extra (None: the core install), as normalised project names;
    an extra that names another (``hippomap[viz]``) gets that one's requirements too."""
    with zipfile.ZipFile(wheel_file) as z:
        meta = next(z.read(n).decode() for n in z.namelist() if n.endswith(".dist-info/METADATA"))
    own: dict[str | None, set[str]] = {None: set()}
    includes: dict[str, set[str]] = {}
    for line in meta.splitlines():
        if line.startswith("Provides-Extra:"):
            own.setdefault(line.split(":", 1)[1].strip(), set())
        if not line.startswith("Requires-Dist:"):
            continue
        req = Requirement(line.split(":", 1)[1].strip())
        extras = [e for e in own if e is not None and req.marker is not None and req.marker.evaluate({"extra": e})]
        assert len(extras) <= 1, line
        extra = extras[0] if extras else None
        assert extra is not None or req.marker is None, f"a core requirement with a marker: {line}"
        if canonicalize_name(req.name) == "hippomap":
            includes.setdefault(extra or "", set()).update(req.extras)
        else:
            own[extra].add(canonicalize_name(req.name))

    def resolve(extra: str | None, seen: frozenset = frozenset()) -> set[str]:
        names = set(own[extra])
        for other in includes.get(extra or "", ()):
            if other not in seen:
                names |= resolve(other, seen | {other})
        return names

    return {extra: resolve(extra) for extra in own}


def test_the_find_configuration_names_only_the_product_packages():
    find = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]
    assert sorted(find["include"]) == ["hippomap*", "server*", "web*"]


def test_wheel_holds_every_product_module(wheel):
    names = set(wheel)
    modules = {
        p.relative_to(ROOT).as_posix()
        for pkg in PACKAGES
        for p in (ROOT / pkg).rglob("*.py")
        if "__pycache__" not in p.parts
    }
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


def test_the_core_install_is_light_and_each_extra_installs_its_packages(requirements):
    """The core install has none of the extras' packages; each extra of ``hippomap.extras.EXTRAS`` installs
    the packages that table names (their import and project names are the same), and the server and test
    extras pull in every one of them (the service writes TUM files, figures and ROS 2 bags; the tests
    exercise it all)."""
    optional = {m for modules in EXTRAS.values() for m in modules}
    assert {"numpy", "scipy", "opencv-python-headless", "pydantic"} <= requirements[None]
    assert not requirements[None] & optional, requirements[None] & optional
    for extra, modules in EXTRAS.items():
        assert extra in requirements, f"pyproject.toml has no extra {extra!r}"
        assert set(modules) <= requirements[extra], (extra, requirements[extra])
    assert optional <= requirements["server"]
    assert optional <= requirements["test"]
