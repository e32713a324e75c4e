"""The core install stays light: the model, every module of ``hippomap`` and the command line work without
the extras' packages (evo, matplotlib, rosbags, httpx, websockets), and code that needs one of them fails
with :class:`~hippomap.extras.MissingExtraError` naming the extra to install.

The suite runs with every extra installed, so the checks that need a package missing run in a child
interpreter whose import system refuses those packages (as on a core install, ``import evo`` raises
``ModuleNotFoundError``)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from hippomap.errors import HippomapError
from hippomap.extras import EXTRAS, MissingExtraError, extra_for, requires

ROOT = Path(__file__).resolve().parents[1]
#: every package an extra installs: none of them is part of the core install
EXTRA_MODULES = sorted({m for modules in EXTRAS.values() for m in modules})

#: prepended to the child's script: an import finder, first in line, that refuses the extras' packages
BLOCKER = textwrap.dedent("""
    import importlib.abc, sys
    BLOCKED = set({blocked!r})
    class Refuse(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.partition(".")[0] in BLOCKED:
                raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
            return None
    sys.meta_path.insert(0, Refuse())
    """)


def _run_without(blocked: list[str], script: str, tmp_path: Path) -> dict:
    """Run ``script`` in a child interpreter without the ``blocked`` packages; it prints one JSON line."""
    code = BLOCKER.format(blocked=blocked) + textwrap.dedent(script)
    proc = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path)], cwd=ROOT, capture_output=True, text=True, timeout=240
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_the_model_and_the_command_line_need_no_extra(tmp_path):
    """Every module of the package imports without the extras, ``hippomap --help`` lists every command
    as available, and a simulated run is mapped; only its exports and metrics (through evo) need the
    ``eval`` extra, which ``hippomap run`` says before it starts mapping."""
    out = _run_without(
        EXTRA_MODULES,
        """
        import contextlib, importlib, io, json, pkgutil, sys
        from pathlib import Path
        import hippomap
        tmp = Path(sys.argv[1])
        modules = sorted(m.name for m in pkgutil.walk_packages(hippomap.__path__, "hippomap."))
        for m in modules:
            if not m.endswith("__main__"):
                importlib.import_module(m)
        from hippomap.cli import build_parser, main
        help_text = build_parser().format_help()
        assert main(["simulate", "corridor", "--laps", "1", "--width", "96", "--height", "64",
                     "--frame-every", "20", "--out", str(tmp / "sim"), "--no-progress"]) == 0
        from hippomap.cli.run import open_dataset, run_dataset
        mapper, _ = run_dataset(open_dataset(tmp / "sim"))
        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            code = main(["run", str(tmp / "sim"), "--out", str(tmp / "out"), "--no-progress"])
        print(json.dumps({"modules": modules, "help": help_text, "nodes": len(mapper.cmap.poses),
                          "code": code, "stderr": err.getvalue()}))
    """,
        tmp_path,
    )
    assert {
        "hippomap.mapper",
        "hippomap.io.rosbag",
        "hippomap.eval.evaluation",
        "hippomap.viz.place_field_figure",
        "hippomap.client",
        "hippomap.client.replay",
        "hippomap.cli.run",
    } <= set(out["modules"])
    assert "unavailable" not in out["help"]
    for command in ("run", "run-odometry", "eval-vpr", "simulate", "replay"):
        assert command in out["help"]
    assert out["nodes"] > 10
    assert out["code"] == 2
    assert (
        out["stderr"] == "hippomap run: error: hippomap run (TUM files, metrics, map plot) needs evo, "
        "which is not installed: pip install 'hippomap[eval]'\n"
    )
    assert not (tmp_path / "out").exists()  # refused before mapping, not after


def test_each_entry_point_of_an_extra_names_that_extra(tmp_path):
    """The functions that need an extra's package raise :class:`MissingExtraError` naming the extra
    when the package is missing: figures (viz), evaluation (eval), ROS bags (rosbag), the client."""
    out = _run_without(
        EXTRA_MODULES,
        """
        import json, sys
        from pathlib import Path
        import numpy as np
        from hippomap.extras import MissingExtraError
        tmp = Path(sys.argv[1])
        poses = np.zeros((3, 3))
        times = np.arange(3.0)
        calls = {
            "write_tum": lambda: __import__("hippomap.io.exports", fromlist=["x"]).write_tum(tmp / "a.tum", times,
                                                                                            poses),
            "plot_map": lambda: __import__("hippomap.io.exports", fromlist=["x"]).plot_map(tmp / "a.png", poses,
                                                                                          poses),
            "trajectory_metrics": lambda: __import__("hippomap.eval.evaluation", fromlist=["x"]).trajectory_metrics(
                times, poses, times, poses),
            "read_rosbag": lambda: __import__("hippomap.io.rosbag", fromlist=["x"]).read_rosbag(tmp, "/a", "/b"),
            "write_rosbag2": lambda: __import__("hippomap.io.session_export", fromlist=["x"]).write_rosbag2(
                tmp / "bag", []),
            "Client": lambda: __import__("hippomap.client", fromlist=["x"]).Client("http://127.0.0.1:9"),
        }
        seen = {}
        for name, call in calls.items():
            try:
                call()
                seen[name] = None
            except MissingExtraError as exc:
                seen[name] = [exc.extra, exc.name, str(exc), isinstance(exc, ImportError)]
        print(json.dumps(seen))
    """,
        tmp_path,
    )
    expected = {
        "write_tum": ("eval", "evo"),
        "plot_map": ("viz", "matplotlib"),
        "trajectory_metrics": ("eval", "evo"),
        "read_rosbag": ("rosbag", "rosbags"),
        "write_rosbag2": ("rosbag", "rosbags"),
        "Client": ("client", "httpx"),
    }
    for name, (extra, module) in expected.items():
        assert out[name] is not None, f"{name} ran without {module}"
        got_extra, got_module, message, is_import_error = out[name]
        assert (got_extra, got_module) == (extra, module), name
        assert message.endswith(f"needs {module}, which is not installed: pip install 'hippomap[{extra}]'")
        assert is_import_error


def test_a_command_whose_module_is_missing_names_its_extra(tmp_path):
    """``hippomap --help`` keeps a command whose import fails, marked unavailable with the extra that
    installs the missing package; the server's command names the server extra."""
    from hippomap.cli import _unavailable

    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="command")
    _unavailable(sub, "eval-vpr", ModuleNotFoundError("x", name="matplotlib.pyplot"), own=True)
    _unavailable(sub, "serve", ModuleNotFoundError("x", name="websockets"), own=False)
    text = " ".join(parser.format_help().split())
    assert "pip install 'hippomap[viz]'" in text and "pip install 'hippomap[server]'" in text
    args = parser.parse_args(["eval-vpr"])
    assert args.func(args) == 2


def test_requires_turns_only_the_extras_modules_into_the_named_error():
    with pytest.raises(MissingExtraError) as info:
        with requires("eval", "the trajectory metrics"):
            raise ModuleNotFoundError("No module named 'evo'", name="evo.core")
    err = info.value
    assert isinstance(err, HippomapError) and isinstance(err, ImportError)
    assert (err.extra, err.name) == ("eval", "evo")
    assert str(err) == "the trajectory metrics needs evo, which is not installed: pip install 'hippomap[eval]'"
    # a module of no extra (a broken install of something else) is not misreported
    with pytest.raises(ModuleNotFoundError) as other:
        with requires("eval", "the trajectory metrics"):
            raise ModuleNotFoundError("No module named 'pandas'", name="pandas")
    assert not isinstance(other.value, MissingExtraError)
    with pytest.raises(ValueError, match="unknown extra 'plots'"):
        with requires("plots", "x"):
            pass


def test_extra_for_names_the_smallest_extra():
    assert extra_for("matplotlib.pyplot") == "viz"  # eval installs it too, viz is enough
    assert extra_for("evo.core.sync") == "eval"
    assert extra_for("rosbags") == "rosbag"
    assert extra_for("websockets.asyncio.client") == "client"
    assert extra_for("fastapi") is None


def test_check_finds_a_missing_package_without_importing_it(tmp_path):
    out = _run_without(
        ["rosbags"],
        """
        import json, sys
        from hippomap.extras import MissingExtraError, check
        check("eval", "x")  # installed: nothing raised
        try:
            check("rosbag", "hippomap run BAG")
            raised = None
        except MissingExtraError as exc:
            raised = str(exc)
        print(json.dumps({"raised": raised, "evo_imported": "evo" in sys.modules}))
    """,
        tmp_path,
    )
    assert out == {
        "raised": "hippomap run BAG needs rosbags, which is not installed: pip install 'hippomap[rosbag]'",
        "evo_imported": False,
    }


def test_the_import_contracts_cover_every_model_module():
    """The two contracts that keep the model apart from the sub-packages and from the extras' packages
    (``[tool.importlinter]``) list the model's modules by name: every top-level module of ``hippomap``
    but the package's entry files, so a new model module cannot be left out of them."""
    import tomllib

    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    model = {f"hippomap.{p.stem}" for p in (ROOT / "hippomap").glob("*.py") if p.stem not in ("__init__", "__main__")}
    subpackages = {f"hippomap.{p.parent.name}" for p in (ROOT / "hippomap").glob("*/__init__.py")}
    assert subpackages == {
        "hippomap.cli",
        "hippomap.io",
        "hippomap.eval",
        "hippomap.viz",
        "hippomap.client",
        "hippomap.sim",
    }
    contracts = {c["name"]: c for c in config["contracts"] if c["type"] == "forbidden"}
    around = [c for c in contracts.values() if set(c["forbidden_modules"]) == subpackages]
    extras = [c for c in contracts.values() if set(c["forbidden_modules"]) == set(EXTRA_MODULES)]
    assert len(around) == 1 and len(extras) == 1, sorted(contracts)
    for contract in around + extras:
        assert set(contract["source_modules"]) == model, contract["name"]
