"""docker/Dockerfile and docker/compose.yml checked against the project (no Docker engine here).

The image is never built in the tests: instead every command and path in the two files is
checked against what the project really has — copied paths exist and pass .dockerignore, the
entry point is a console script, the exposed port is ``hippomap serve``'s default, the health
check (run for real against a live server) hits a route of the app, the volume is the data
folder, the user is not root, the extras exist, and every ``hippomap serve`` / ``ray start``
command line in compose.yml parses with the real command-line parsers.
"""

from __future__ import annotations

import argparse
import ast
import json
import re
import shlex
import subprocess
import sys
import tomllib
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, packages_distributions, requires
from pathlib import Path
from urllib.parse import urlsplit

import pytest
import yaml
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

from server.settings import ServerSettings

ROOT = Path(__file__).resolve().parents[1]
DOCKERFILE = ROOT / "docker" / "Dockerfile"
COMPOSE = ROOT / "docker" / "compose.yml"
DOCKERIGNORE = ROOT / ".dockerignore"
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
#: HIPPOMAP_* variables read outside ServerSettings (server/logs.py, server/app.py)
EXTRA_ENV = {"HIPPOMAP_LOG_FORMAT", "HIPPOMAP_METRICS_TOKEN"}


# ------------------------------------------------------------------ parsing
@dataclass
class Instruction:
    op: str
    args: str
    line: int

    def json_args(self) -> list[str] | None:
        """The exec form (``["a", "b"]``) as a list, or None for the shell form."""
        text = self.args.strip()
        if text.startswith("["):
            value = json.loads(text)
            assert isinstance(value, list) and all(isinstance(v, str) for v in value), self
            return value
        return None

    def flags_and_rest(self) -> tuple[dict[str, str], list[str]]:
        """``--flag=value`` options in front (COPY, HEALTHCHECK) and the remaining words."""
        words = shlex.split(self.args) if not self.args.lstrip().startswith("[") else []
        flags: dict[str, str] = {}
        while words and words[0].startswith("--"):
            key, _, value = words.pop(0)[2:].partition("=")
            flags[key] = value
        return flags, words


@dataclass
class Stage:
    base: str
    name: str | None
    instructions: list[Instruction] = field(default_factory=list)

    def all(self, op: str) -> list[Instruction]:
        return [i for i in self.instructions if i.op == op]

    def env(self) -> dict[str, str]:
        out: dict[str, str] = {}
        for ins in self.all("ENV"):
            for word in shlex.split(ins.args):
                key, eq, value = word.partition("=")
                assert eq, f"line {ins.line}: use ENV key=value, got {word!r}"
                out[key] = value
        return out


def parse_dockerfile(text: str) -> tuple[dict[str, str], list[Stage]]:
    """Global ARGs (before the first FROM) with their defaults, and the stages in order."""
    logical: list[tuple[int, str]] = []
    buf, start = "", 0
    for n, raw in enumerate(text.splitlines(), 1):
        stripped = raw.strip()
        if not buf and (not stripped or stripped.startswith("#")):
            continue
        if buf and stripped.startswith("#"):  # comment lines inside a continued instruction are dropped
            continue
        if not buf:
            start = n
        if stripped.endswith("\\"):
            buf += stripped[:-1] + " "
            continue
        logical.append((start, buf + stripped))
        buf = ""
    assert not buf, "the Dockerfile ends inside a continued line"
    global_args: dict[str, str] = {}
    stages: list[Stage] = []
    for line, text_ in logical:
        op, _, args = text_.partition(" ")
        op = op.upper()
        if op == "FROM":
            words = args.split()
            name = words[2] if len(words) == 3 and words[1].upper() == "AS" else None
            assert len(words) in (1, 3), f"line {line}: FROM {args}"
            stages.append(Stage(words[0], name))
        elif not stages:
            assert op == "ARG", f"line {line}: only ARG may come before FROM, got {op}"
            key, _, value = args.strip().partition("=")
            global_args[key] = value
        else:
            stages[-1].instructions.append(Instruction(op, args.strip(), line))
    return global_args, stages


GLOBAL_ARGS, STAGES = parse_dockerfile(DOCKERFILE.read_text())
RUNTIME = STAGES[-1]
COMPOSE_DOC = yaml.safe_load(COMPOSE.read_text())
SERVICES: dict[str, dict] = COMPOSE_DOC["services"]


def dockerignore_excludes(path: str, patterns: list[str]) -> bool:
    """Docker's .dockerignore rule: the last pattern matching the path or one of its parent folders
    wins; ``!`` re-includes; ``*`` stays inside one path element, ``**`` spans any number."""

    def regex(pattern: str) -> re.Pattern[str]:
        out, i = "", 0
        while i < len(pattern):
            if pattern.startswith("**/", i):
                out, i = out + "(?:.*/)?", i + 3
            elif pattern.startswith("**", i):
                out, i = out + ".*", i + 2
            elif pattern[i] == "*":
                out, i = out + "[^/]*", i + 1
            elif pattern[i] == "?":
                out, i = out + "[^/]", i + 1
            else:
                out, i = out + re.escape(pattern[i]), i + 1
        return re.compile(out)

    parts = path.strip("/").split("/")
    prefixes = ["/".join(parts[:k]) for k in range(1, len(parts) + 1)]
    excluded = False
    for pattern in patterns:
        negate = pattern.startswith("!")
        body = pattern[1:] if negate else pattern
        body = body.strip().strip("/")
        if body and any(regex(body).fullmatch(p) for p in prefixes):
            excluded = not negate
    return excluded


def ignore_patterns() -> list[str]:
    return [ln.strip() for ln in DOCKERIGNORE.read_text().splitlines() if ln.strip() and not ln.startswith("#")]


def serve_parser() -> argparse.ArgumentParser:
    """The real ``hippomap`` parser (console script and its entry-point commands)."""
    from hippomap.cli import build_parser

    return build_parser()


def parse_serve(args: list[str]) -> argparse.Namespace:
    """``hippomap serve ARGS`` as the console script parses it; fails on unknown flags or bad choices."""
    parser = serve_parser()
    try:
        return parser.parse_args(["serve", *args])
    except SystemExit:
        pytest.fail(f"`hippomap serve {' '.join(args)}` is rejected by the command-line parser")


def default_port() -> int:
    return parse_serve([]).port


def extras_of(value: str) -> list[str]:
    return [e.strip() for e in value.split(",") if e.strip()]


def build_arg_default(stage: Stage, name: str) -> str:
    for ins in stage.all("ARG"):
        key, _, value = ins.args.partition("=")
        if key == name:
            return value
    raise AssertionError(f"ARG {name} not declared in stage {stage.name}")


def resolve_compose_env(value: str) -> str:
    """``${VAR:-default}`` → default (what compose uses when the variable is unset)."""
    return re.sub(r"\$\{[A-Z_]+:-([^}]*)\}", r"\1", str(value))


def command_lines(service: dict, image_entrypoint: list[str]) -> list[list[str]]:
    """The command lines a compose service runs, split at ``&&`` when it goes through a shell."""
    entry = service.get("entrypoint", image_entrypoint)
    entry = shlex.split(entry) if isinstance(entry, str) else list(entry)
    command = service.get("command", [])
    command = shlex.split(command) if isinstance(command, str) else list(command)
    if entry[:2] == ["/bin/sh", "-c"]:
        script = " ".join(command)
        return [shlex.split(part) for part in script.split("&&")]
    return [entry + command]


def hippomap_serve_args(line: list[str]) -> list[str] | None:
    words = line[1:] if line and line[0] == "exec" else line
    if words[:2] == ["hippomap", "serve"]:
        return words[2:]
    return None


def built_from_dockerfile(service: dict) -> bool:
    build = service.get("build")
    if build is None:  # an image another service of this file builds
        return any(s.get("image") == service.get("image") and "build" in s for s in SERVICES.values())
    return (COMPOSE.parent / build["context"] / build["dockerfile"]).resolve() == DOCKERFILE.resolve()


HIPPOMAP_SERVICES = {name: s for name, s in SERVICES.items() if built_from_dockerfile(s)}
SERVE_SERVICES = {
    name: s
    for name, s in HIPPOMAP_SERVICES.items()
    if any(
        hippomap_serve_args(line) is not None
        for line in command_lines(s, RUNTIME.all("ENTRYPOINT")[-1].json_args() or [])
    )
}


# ------------------------------------------------------------------ Dockerfile
def test_two_stages_on_python_311_slim():
    assert len(STAGES) == 2 and STAGES[0].name == "builder"
    for stage in STAGES:
        base = stage.base.replace("${PYTHON_IMAGE}", GLOBAL_ARGS.get("PYTHON_IMAGE", ""))
        assert base == "python:3.11-slim", stage
    assert sys.version_info[:2] == (3, 11) and PYPROJECT["project"]["requires-python"] == ">=3.11"


def test_every_copied_path_exists_and_reaches_the_build_context():
    patterns = ignore_patterns()
    copies = [(stage, ins) for stage in STAGES for ins in stage.all("COPY") + stage.all("ADD")]
    assert copies
    sources = []
    for stage, ins in copies:
        assert ins.op == "COPY", f"line {ins.line}: use COPY, not ADD"
        flags, words = ins.flags_and_rest()
        *srcs, _dest = words
        if "from" in flags:  # from another stage: that stage must exist and be earlier
            assert flags["from"] in [s.name for s in STAGES[: STAGES.index(stage)]], ins
            continue
        for src in srcs:
            path = ROOT / src
            assert path.exists(), f"Dockerfile line {ins.line}: COPY source {src!r} does not exist in the repository"
            assert not dockerignore_excludes(src, patterns), f"{src!r} is excluded by .dockerignore"
            sources.append(src.rstrip("/"))
    # the packages setuptools installs are all copied (pyproject's packages.find include list)
    for package in PYPROJECT["tool"]["setuptools"]["packages"]["find"]["include"]:
        assert package.rstrip("*") in sources, package
    assert PYPROJECT["project"]["readme"] in sources  # pip install . reads it
    assert "pyproject.toml" in sources


def test_dockerignore_keeps_the_context_small():
    patterns = ignore_patterns()
    for heavy in (
        ".venv/lib/python3.11/site-packages/numpy/__init__.py",
        ".git/HEAD",
        "tests/conftest.py",
        "bench/bench_mapper.py",
        "docs/MODEL.md",
        "test-artifacts/x.png",
        "hippomap/__pycache__/a.pyc",
    ):
        assert dockerignore_excludes(heavy, patterns), heavy
    for needed in ("hippomap/mapper.py", "server/app.py", "server/viewer.py", "pyproject.toml"):
        assert (ROOT / needed).exists() and not dockerignore_excludes(needed, patterns), needed


def test_runtime_stage_copies_only_the_virtualenv():
    copies = RUNTIME.all("COPY")
    assert copies
    for ins in copies:
        flags, words = ins.flags_and_rest()
        assert flags.get("from") == "builder", f"line {ins.line}: the runtime stage copies from the builder only"
        assert words == ["/opt/venv", "/opt/venv"], ins
    install = " ".join(i.args for i in STAGES[0].all("RUN"))
    assert 'pip install ".[${EXTRAS}]"' in install  # a regular (not editable) install: no sources needed at run time
    assert "/opt/venv" in " ".join(i.args for i in STAGES[0].all("RUN"))
    assert RUNTIME.env()["PATH"].startswith("/opt/venv/bin:")
    copied_roots = {
        src.strip("/").split("/")[0]
        for stage in STAGES
        for ins in stage.all("COPY")
        for src in ins.flags_and_rest()[1][:-1]
    }
    assert not copied_roots & {"tests", "bench", "docs", ".ci", ".", "test-artifacts"}, copied_roots


def test_entry_point_is_the_console_script_and_its_command_parses():
    entry = RUNTIME.all("ENTRYPOINT")[-1].json_args()
    cmd = RUNTIME.all("CMD")[-1].json_args()
    assert entry == ["hippomap"]
    assert entry[0] in PYPROJECT["project"]["scripts"]
    assert PYPROJECT["project"]["scripts"]["hippomap"] == "hippomap.cli:main"
    assert cmd[0] == "serve" and cmd[0] in PYPROJECT["project"]["entry-points"]["hippomap.commands"]
    args = parse_serve(cmd[1:])
    assert args.host == "0.0.0.0"  # reachable through the published port


def test_exposed_port_is_the_serve_default():
    exposed = [int(p.split("/")[0]) for ins in RUNTIME.all("EXPOSE") for p in ins.args.split()]
    assert exposed == [default_port()]


def healthcheck_code() -> tuple[dict[str, str], str]:
    ins = RUNTIME.all("HEALTHCHECK")[-1]
    head, _, rest = ins.args.partition(" CMD ")
    flags = dict(f[2:].partition("=")[::2] for f in head.split())
    exec_form = json.loads(rest)
    assert exec_form[:2] == ["python", "-c"], exec_form  # slim has no curl
    return flags, exec_form[2]


def test_healthcheck_hits_a_real_route_on_the_default_port():
    from server.app import create_app

    flags, code = healthcheck_code()
    ast.parse(code)
    urls = re.findall(r"http://[^'\"\s]+", code)
    assert len(urls) == 1
    url = urlsplit(urls[0])
    assert url.hostname == "127.0.0.1" and url.port == default_port()
    routes = {getattr(r, "path", None) for r in create_app(ServerSettings(data_dir=ROOT / "unused")).routes}
    assert url.path in routes
    assert url.path == "/health"  # liveness, no token
    assert {"interval", "timeout", "start-period", "retries"} <= set(flags)


def test_healthcheck_command_against_a_live_server(tmp_path):
    """The image's check, run as written but aimed at a live server: exit 0 while it serves, 1 once it is gone."""
    from tests.support.live import LiveServer

    _, code = healthcheck_code()
    srv = LiveServer(tmp_path / "data").start()
    try:
        live_code = code.replace(f"127.0.0.1:{default_port()}", urlsplit(srv.url).netloc)
        assert subprocess.run([sys.executable, "-c", live_code], timeout=30).returncode == 0
    finally:
        srv.stop()
    failed = subprocess.run([sys.executable, "-c", live_code], capture_output=True, timeout=30)
    assert failed.returncode == 1


def test_volume_is_the_data_folder_and_user_is_not_root():
    volumes = [v for ins in RUNTIME.all("VOLUME") for v in (ins.json_args() or ins.args.split())]
    env = RUNTIME.env()
    assert volumes == [env["HIPPOMAP_DATA_DIR"]]
    # the variable is the server's real setting: a server started in the image uses that folder
    assert ServerSettings.model_validate({"data_dir": env["HIPPOMAP_DATA_DIR"]}).data_dir == Path(volumes[0])
    for key in env:
        if key.startswith("HIPPOMAP_"):
            assert key[len("HIPPOMAP_") :].lower() in ServerSettings.model_fields or key in EXTRA_ENV, key
    users = RUNTIME.all("USER")
    assert users, "the runtime stage must set USER"
    user = users[-1].args.split(":")[0]
    assert user not in ("root", "0")
    runs = " ".join(i.args for i in RUNTIME.all("RUN"))
    assert re.search(rf"useradd\b.*--uid {re.escape(user)}\b", runs) or re.search(
        rf"useradd\b.*\b{user}\s*(&&|$)", runs
    )
    assert re.search(r"chown [^ ]+ /data|chown [^ ]+ " + re.escape(volumes[0]), runs), (
        "the data folder must be writable"
    )
    order = [i.op for i in RUNTIME.instructions]
    assert order.index("USER") < order.index("ENTRYPOINT") and order.index("USER") < order.index("VOLUME")


def test_extras_named_in_dockerfile_and_compose_exist_in_pyproject():
    known = set(PYPROJECT["project"]["optional-dependencies"])
    named = {"Dockerfile ARG EXTRAS": build_arg_default(STAGES[0], "EXTRAS")}
    for name, service in SERVICES.items():
        args = (service.get("build") or {}).get("args") or {}
        if "EXTRAS" in args:
            named[f"compose service {name}"] = args["EXTRAS"]
    assert len(named) >= 3
    for where, value in named.items():
        extras = extras_of(value)
        assert "server" in extras, where
        missing = [e for e in extras if e not in known]
        assert not missing, f"{where} installs extras {missing} that pyproject.toml does not define ({sorted(known)})"


# ------------------------------------------------------------------ compose
def test_compose_services_and_profiles():
    assert "hippomap" in SERVICES and "profiles" not in SERVICES["hippomap"]  # `docker compose up` runs it
    scale = {name for name, s in SERVICES.items() if "scale" in s.get("profiles", [])}
    assert {"postgres", "ray-head"} <= scale
    assert SERVICES["postgres"]["image"].split(":")[0] == "postgres"
    assert len(SERVE_SERVICES) >= 3  # the embedded server and at least two replicas
    for name, service in SERVICES.items():
        for mount in service.get("volumes", []):
            source = mount.split(":")[0]
            assert source in (COMPOSE_DOC.get("volumes") or {}), f"{name}: volume {source!r} is not declared"


def test_compose_serve_commands_parse_and_match_the_image():
    entry = RUNTIME.all("ENTRYPOINT")[-1].json_args() or []
    port = default_port()
    data_dir = RUNTIME.env()["HIPPOMAP_DATA_DIR"]
    for name, service in SERVE_SERVICES.items():
        lines = command_lines(service, entry)
        serve = [hippomap_serve_args(line) for line in lines if hippomap_serve_args(line) is not None]
        assert len(serve) == 1, name
        args = parse_serve(serve[0])
        assert args.host == "0.0.0.0", name
        published = [str(p).split(":") for p in service.get("ports", [])]
        assert published and all(int(p[-1]) == args.port == port for p in published), name
        mounts = [v.split(":") for v in service.get("volumes", [])]
        assert [m[1] for m in mounts] == [data_dir], name
        env = {k: resolve_compose_env(v) for k, v in (service.get("environment") or {}).items()}
        for key in env:
            assert key.startswith("HIPPOMAP_") and (
                key[len("HIPPOMAP_") :].lower() in ServerSettings.model_fields or key in EXTRA_ENV
            ), f"{name}: {key}"
        # what the server will run with, from these flags and this environment
        settings = ServerSettings.model_validate({k[len("HIPPOMAP_") :].lower(): v for k, v in env.items() if v})
        if "scale" in service.get("profiles", []):
            assert args.backend == "ray" or settings.backend == "ray", name
            ray_address = args.ray_address or settings.ray_address
            host, _, ray_port = ray_address.rpartition(":")
            assert host in SERVICES and SERVICES[host] is SERVICES["ray-head"], name
            head = ray_start_options(command_lines(SERVICES["ray-head"], entry)[0])
            assert head["head"] and str(head["port"]) == ray_port, name
            url = urlsplit(settings.database or "")
            assert url.scheme in ("postgresql", "postgres") and url.hostname in SERVICES, name
            pg_env = SERVICES[url.hostname]["environment"]
            assert url.username == pg_env["POSTGRES_USER"] and url.path.lstrip("/") == pg_env["POSTGRES_DB"]
            assert url.password == resolve_compose_env(pg_env["POSTGRES_PASSWORD"])
            assert url.port == 5432
            depends = service.get("depends_on") or {}
            assert {url.hostname, host} <= set(depends), name
        else:
            assert args.backend in (None, "inprocess") and not settings.database, name


def ray_start_options(line: list[str]) -> dict:
    """``ray start ...`` parsed by Ray's own command-line definition (click); fails on unknown options."""
    from ray.scripts.scripts import start

    assert line[:2] == ["ray", "start"], line
    ctx = start.make_context("ray start", line[2:])
    return ctx.params


def test_compose_ray_commands_parse():
    entry = RUNTIME.all("ENTRYPOINT")[-1].json_args() or []
    seen = 0
    for name, service in HIPPOMAP_SERVICES.items():
        for line in command_lines(service, entry):
            if line[:2] == ["ray", "start"]:
                opts = ray_start_options(line)
                seen += 1
                assert opts["disable_usage_stats"], name
                if opts["head"]:
                    assert opts["block"] and opts["include_dashboard"] is False, name
                else:
                    host, _, port = opts["address"].rpartition(":")
                    assert SERVICES.get(host) is SERVICES["ray-head"] and port == "6379", name
    assert seen >= 3  # the head and each replica joining it
    check = SERVICES["ray-head"]["healthcheck"]["test"]
    assert check[0] == "CMD" and check[1:3] == ["ray", "status"], check
    from ray.scripts.scripts import status

    address = status.make_context("ray status", check[3:]).params["address"]
    head = ray_start_options(command_lines(SERVICES["ray-head"], [])[0])
    assert address == f"127.0.0.1:{head['port']}"


def test_compose_health_dependencies_have_health_checks():
    image_has_check = bool(RUNTIME.all("HEALTHCHECK"))
    for name, service in SERVICES.items():
        for dep, cond in (service.get("depends_on") or {}).items():
            assert dep in SERVICES, f"{name} depends on unknown service {dep}"
            if cond.get("condition") == "service_healthy":
                target = SERVICES[dep]
                assert "healthcheck" in target or (dep in HIPPOMAP_SERVICES and image_has_check), (name, dep)
    pg = SERVICES["postgres"]["healthcheck"]["test"]
    assert "pg_isready" in " ".join(pg)


# ------------------------------------------------------------------ runtime dependencies of the image
#: modules of the installed packages that need more than ``.[server]`` (the image's default EXTRAS):
#: the scale-out backends (test scaffolding lives in tests/support, outside the packages)
OPTIONAL_MODULES = {"server/runtime/ray_backend.py": ("ray",), "server/storage/postgres.py": ("postgres",)}


def _closure(requirements: list[str]) -> set[str]:
    """Every distribution ``requirements`` pull in (from the installed packages' metadata, markers evaluated)."""
    seen: set[str] = set()
    todo = [(Requirement(r), "") for r in requirements]
    while todo:
        req, from_extra = todo.pop()
        if req.marker is not None and not req.marker.evaluate({"extra": from_extra}):
            continue
        name = canonicalize_name(req.name)
        key = name + "[" + ",".join(sorted(req.extras)) + "]"
        if key in seen:
            continue
        seen.add(key)
        if name == "hippomap":  # the project's own extras (e.g. test = ["hippomap[server]"])
            todo += [(Requirement(r), "") for e in req.extras for r in PYPROJECT["project"]["optional-dependencies"][e]]
            continue
        try:
            reqs = requires(req.name) or []
        except PackageNotFoundError:
            continue
        for r in reqs:
            sub = Requirement(r)
            for extra in ("", *req.extras):
                if sub.marker is None or sub.marker.evaluate({"extra": extra}):
                    todo.append((sub, extra))
                    break
    return {k.split("[")[0] for k in seen}


def _third_party_imports(path: Path) -> set[str]:
    """Top-level third-party modules ``path`` imports (anywhere, lazily too), except inside
    ``try: ... except ImportError`` (optional accelerators such as uvloop)."""
    tree = ast.parse(path.read_text())
    optional: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Try) and any(
            isinstance(h.type, ast.Name) and h.type.id in ("ImportError", "ModuleNotFoundError") for h in node.handlers
        ):
            optional |= {id(n) for stmt in node.body for n in ast.walk(stmt)}
    found = set()
    for node in ast.walk(tree):
        if id(node) in optional:
            continue
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module]
        else:
            continue
        for name in names:
            top = name.split(".")[0]
            if top not in sys.stdlib_module_names and top not in ("hippomap", "server", "web", "__future__"):
                found.add(top)
    return found


def test_the_image_installs_everything_the_server_imports():
    """``pip install ".[server]"`` (the image's default) must provide every module the installed
    packages import, so the runtime stage needs nothing else; the optional modules' imports come
    from their extras."""
    project = PYPROJECT["project"]
    extras = project["optional-dependencies"]
    image_extras = extras_of(build_arg_default(STAGES[0], "EXTRAS"))
    base = _closure(project["dependencies"] + [r for e in image_extras for r in extras.get(e, [])])
    providers = packages_distributions()
    problems = []
    packages = [p.rstrip("*") for p in PYPROJECT["tool"]["setuptools"]["packages"]["find"]["include"]]
    files = sorted(f for pkg in packages for f in (ROOT / pkg).rglob("*.py"))
    assert len(files) > 50
    for f in files:
        rel = f.relative_to(ROOT).as_posix()
        allowed = base
        if rel in OPTIONAL_MODULES:
            missing_extras = [e for e in OPTIONAL_MODULES[rel] if e not in extras]
            if missing_extras:
                problems.append(f"{rel}: pyproject.toml has no extra {missing_extras}")
                continue
            allowed = base | _closure([r for e in OPTIONAL_MODULES[rel] for r in extras[e]])
        for module in sorted(_third_party_imports(f)):
            dists = {canonicalize_name(d) for d in providers.get(module, [])}
            if not dists:
                problems.append(f"{rel} imports {module}, which no installed distribution provides")
            elif not dists & allowed:
                problems.append(
                    f"{rel} imports {module} ({', '.join(sorted(dists))}), not installed by "
                    f"hippomap[{','.join(image_extras)}]"
                    + (f" + {OPTIONAL_MODULES[rel]}" if rel in OPTIONAL_MODULES else "")
                )
    assert not problems, "\n".join(problems)
