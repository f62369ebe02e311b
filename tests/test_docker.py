"""docker/Dockerfile and docker/compose.yaml, checked without a Docker engine.

No image is built and no container runs here.  What is checked: the compose
file has the services and commands the README describes; every command a
service runs exists in this project's environment and accepts its arguments;
the Dockerfile starts from the Python the project requires, copies only paths
that exist and installs the repository editable; the build context and
Dockerfile that compose names exist; and, where a Docker Compose v2 client is
installed, ``docker compose config`` accepts the file.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
import yaml
from packaging.requirements import Requirement
from packaging.specifiers import SpecifierSet

ROOT = Path(__file__).resolve().parent.parent
DOCKER = ROOT / "docker"
COMPOSE = DOCKER / "compose.yaml"
DOCKERFILE = DOCKER / "Dockerfile"
BIN = Path(sys.executable).parent
IMAGE_SERVICES = ("scheduler", "worker", "coordinator")  # the services that run the packings image
PG_URL = "postgresql://packings:packings@postgres:5432/packings"


# --------------------------------------------------------------------------- helpers


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


@pytest.fixture(scope="module")
def pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def interpolate(s: str, env: dict[str, str] | None = None) -> str:
    """Compose's ``${VAR:-default}`` / ``${VAR}`` / ``$VAR`` interpolation (enough for this file)."""
    env = {} if env is None else env

    def sub(m: re.Match) -> str:
        name, default = m.group(1) or m.group(3), m.group(2)
        return env.get(name) or (default if default is not None else "")

    return re.sub(r"\$\{(\w+)(?::-([^}]*))?\}|\$(\w+)", sub, s)


def argv(service: dict, env: dict[str, str] | None = None) -> list[str]:
    cmd = service["command"]
    return [interpolate(a, env) for a in cmd] if isinstance(cmd, list) else shlex.split(interpolate(cmd, env))


def instructions() -> list[tuple[str, str]]:
    """The Dockerfile as (INSTRUCTION, arguments), comments dropped and continuation lines joined."""
    out: list[tuple[str, str]] = []
    buf = ""
    for line in DOCKERFILE.read_text().splitlines():
        stripped = line.strip()
        if not buf and (not stripped or stripped.startswith("#")):
            continue
        if buf and stripped.startswith("#"):
            continue  # a comment inside a continued instruction
        if stripped.endswith("\\"):
            buf += stripped[:-1] + " "
            continue
        buf += stripped
        word, _, rest = buf.partition(" ")
        out.append((word.upper(), rest.strip()))
        buf = ""
    assert not buf, "the Dockerfile ends inside a continued line"
    return out


def copy_sources(args: str) -> tuple[list[str], str] | None:
    """The context sources and destination of a COPY/ADD, or None for COPY --from=stage."""
    parts = json.loads(args) if args.startswith("[") else shlex.split(args)
    flags = [p for p in parts if p.startswith("--")]
    if any(f.startswith("--from") for f in flags):
        return None
    paths = [p for p in parts if not p.startswith("--")]
    return paths[:-1], paths[-1]


def dockerignore_patterns() -> list[str]:
    lines = (ROOT / ".dockerignore").read_text().splitlines()
    return [ln.strip() for ln in lines if ln.strip() and not ln.strip().startswith("#")]


def _pattern_regex(pattern: str) -> re.Pattern:
    """Docker's .dockerignore matching: relative to the context root, ``*`` and ``?`` stop at ``/``, ``**`` does not."""
    out, i = "", 0
    pattern = pattern.strip("/")
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


def ignored(path: str, patterns: list[str]) -> bool:
    """Whether .dockerignore drops ``path``: it, or a folder above it, matches a pattern (no '!' lines here)."""
    assert not any(p.startswith("!") for p in patterns), "exception lines are not modelled by this test"
    parts = path.strip("/").split("/")
    prefixes = ["/".join(parts[: k + 1]) for k in range(len(parts))]
    return any(_pattern_regex(p).fullmatch(q) for p in patterns for q in prefixes)


def run(args: list[str], timeout: float = 120) -> subprocess.CompletedProcess:
    env = dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}")
    return subprocess.run(args, capture_output=True, text=True, timeout=timeout, env=env, cwd=ROOT)


# --------------------------------------------------------------------------- compose.yaml


def test_compose_has_the_services(compose):
    assert set(compose["services"]) == {"postgres", *IMAGE_SERVICES}


def test_postgres_service(compose):
    pg = compose["services"]["postgres"]
    assert pg["image"] == "postgres:15"
    env = pg["environment"]
    assert (env["POSTGRES_USER"], env["POSTGRES_PASSWORD"], env["POSTGRES_DB"]) == ("packings",) * 3
    assert "pg_isready" in " ".join(pg["healthcheck"]["test"])
    volume = pg["volumes"][0].split(":")[0]
    assert volume in compose["volumes"], "postgres keeps its data in a named volume"


def test_scheduler_service(compose):
    s = compose["services"]["scheduler"]
    assert argv(s) == ["dask", "scheduler", "--host", "0.0.0.0", "--dashboard-address", ":8787"]
    assert sorted(s["ports"]) == ["127.0.0.1:8786:8786", "127.0.0.1:8787:8787"], "published on localhost only"
    check = s["healthcheck"]["test"]
    assert check[:3] == ["CMD", "python", "-c"] and "8787/health" in check[3]
    compile(check[3], "healthcheck", "exec")


def test_worker_service(compose):
    w = compose["services"]["worker"]
    assert argv(w) == ["dask", "worker", "tcp://scheduler:8786", "--nworkers", "1", "--nthreads", "1"]
    assert w["deploy"]["replicas"] == 2
    assert "scheduler" in w["depends_on"]
    assert w["environment"]["PACKINGS_DB"] == PG_URL


def test_coordinator_service(compose):
    c = compose["services"]["coordinator"]
    assert argv(c) == ["packings", "enumerate", "10", "--scheduler", "tcp://scheduler:8786"]
    assert argv(c, {"N": "11"})[2] == "11", "N comes from the environment"
    assert c["environment"]["PACKINGS_DB"] == PG_URL
    deps = c["depends_on"]
    assert deps["postgres"]["condition"] == "service_healthy"
    assert {"scheduler", "worker"} <= set(deps)
    assert c["restart"] == "no"


def test_one_image_for_every_dask_process(compose):
    """Scheduler, workers and coordinator must run the same Dask: one image, which each can build."""
    services = compose["services"]
    images = {services[name]["image"] for name in IMAGE_SERVICES}
    assert len(images) == 1 and images != {"postgres:15"}
    for name in IMAGE_SERVICES:
        build = services[name]["build"]
        context = (COMPOSE.parent / build["context"]).resolve()
        assert context == ROOT, f"{name}: the build context is the repository root"
        assert (context / build["dockerfile"]).resolve() == DOCKERFILE
        assert (context / ".dockerignore").is_file()


@pytest.mark.parametrize("service", IMAGE_SERVICES)
def test_every_command_exists_and_accepts_its_arguments(compose, service):
    """The program each service runs is installed next to this Python, and its parser accepts the arguments.

    ``--help`` is eager in click (dask's and packings' parser): an unknown option
    still fails, but nothing is started or connected to.
    """
    args = argv(compose["services"][service])
    exe = shutil.which(args[0], path=str(BIN))
    assert exe is not None, f"{args[0]} is not installed in {BIN}"
    r = run([exe, *args[1:], "--help"])
    assert r.returncode == 0, r.stderr
    assert "Usage" in r.stdout


def parsed(args: list[str]) -> dict:
    """The parameters the real click command of ``args`` parses them into (nothing runs).

    This catches what ``--help`` cannot: ``dask worker`` passes unknown options
    through to its preload scripts, and values are converted only here.
    """
    import click

    if args[0] == "dask":
        from importlib.metadata import entry_points

        command = entry_points(group="dask_cli")[args[1]].load()
    else:
        assert args[0] == "packings", args
        from service.cli import cli

        command = cli.commands[args[1]]
    try:
        return command.make_context(" ".join(args[:2]), args[2:]).params
    except click.ClickException as e:
        pytest.fail(f"{' '.join(args)}: {e.format_message()}")


def test_commands_parse_to_the_intended_settings(compose):
    services = compose["services"]
    p = parsed(argv(services["scheduler"]))
    assert (p["host"], p["dashboard_address"], p["port"]) == ("0.0.0.0", ":8787", None)  # port None: 8786
    p = parsed(argv(services["worker"]))
    assert (p["scheduler"], int(p["n_workers"]), p["nthreads"], p["preload_argv"]) == ("tcp://scheduler:8786", 1, 1, ())
    p = parsed(argv(services["coordinator"], {"N": "11"}))
    assert (p["n"], p["scheduler"], p["db_url"], p["n_workers"]) == (11, "tcp://scheduler:8786", None, None)


def test_stats_command_for_the_readme():
    exe = shutil.which("packings", path=str(BIN))
    assert exe is not None
    r = run([exe, "stats", "--help"])
    assert r.returncode == 0, r.stderr


def _compose_client() -> list[str] | None:
    """A Docker Compose v2 client: the docker CLI plugin, or a standalone docker-compose v2."""
    if shutil.which("docker"):
        r = subprocess.run(["docker", "compose", "version"], capture_output=True, text=True, timeout=30)
        if r.returncode == 0:
            return ["docker", "compose"]
    if shutil.which("docker-compose"):
        r = subprocess.run(["docker-compose", "version"], capture_output=True, text=True, timeout=30)
        if r.returncode == 0 and re.search(r"v2\.", r.stdout):
            return ["docker-compose"]
    return None


def test_docker_compose_config_accepts_the_file():
    client = _compose_client()
    if client is None:
        reason = ("the docker client is missing" if shutil.which("docker") is None
                  else "the docker client has no compose plugin")
        pytest.skip(f"{reason}; cannot run `docker compose config` (needs no engine, but needs Compose v2)")
    r = subprocess.run([*client, "-f", str(COMPOSE), "config", "-q"], capture_output=True, text=True, timeout=60,
                       cwd=ROOT)
    # stderr too: a wrapper script may lose compose's exit status, and a warning is worth fixing
    assert r.returncode == 0 and not r.stderr.strip(), r.stderr


# --------------------------------------------------------------------------- Dockerfile


def test_dockerfile_base_image_is_the_required_python(pyproject):
    froms = [args.split()[0] for word, args in instructions() if word == "FROM"]
    assert froms, "no FROM"
    requires = SpecifierSet(pyproject["project"]["requires-python"])
    for image in froms:
        m = re.fullmatch(r"python:(\d+\.\d+)(-slim)?(-\w+)?", image)
        assert m, f"base image {image} is not an official python image"
        assert m.group(1) == "3.11", image
        assert requires.contains(m.group(1) + ".0"), f"{image} does not satisfy requires-python {requires}"
    assert froms[-1] == "python:3.11-slim"


def test_dockerfile_copies_the_repo_and_installs_it_editable():
    steps = instructions()
    copies = [copy_sources(args) for word, args in steps if word in ("COPY", "ADD")]
    assert any(c is not None and c[0] == ["."] and c[1].rstrip("/") == "/app" for c in copies), "COPY . /app"
    runs = " ".join(args for word, args in steps if word == "RUN")
    assert re.search(r"pip install --no-cache-dir (--no-deps )?-e /app\b", runs)


def test_every_copied_path_exists_and_is_not_ignored():
    patterns = dockerignore_patterns()
    for word, args in instructions():
        if word not in ("COPY", "ADD"):
            continue
        copied = copy_sources(args)
        if copied is None:
            continue  # from another build stage
        for src in copied[0]:
            assert (ROOT / src).exists(), f"{word} {src}: no such path in the repository"
            if src != ".":
                assert not ignored(src, patterns), f"{word} {src}: excluded by .dockerignore"


def test_dockerfile_runs_as_a_user_in_data_and_has_no_entrypoint():
    steps = instructions()
    words = [w for w, _ in steps]
    assert "ENTRYPOINT" not in words, "compose runs dask and packings from the same image"
    users = [args for w, args in steps if w == "USER"]
    assert users and users[-1] not in ("root", "0"), "the final image does not run as root"
    workdirs = [args for w, args in steps if w == "WORKDIR"]
    assert workdirs[-1] == "/data"
    assert any("/data" in args for w, args in steps if w == "VOLUME")
    cmd = [args for w, args in steps if w == "CMD"]
    assert json.loads(cmd[-1]) == ["packings", "--help"]


def test_dockerfile_builds_the_pynauty_the_project_requires(pyproject):
    """pynauty has no CPython 3.11 manylinux wheel: the Dockerfile builds it, with pyproject's version range."""
    wanted = next(Requirement(d) for d in pyproject["project"]["dependencies"] if d.startswith("pynauty"))
    m = re.search(r'pip wheel [^"]*"(pynauty[^"]*)"', DOCKERFILE.read_text())
    assert m, "the Dockerfile does not build pynauty"
    assert Requirement(m.group(1)).specifier == wanted.specifier


def test_dockerignore_keeps_local_state_out():
    patterns = dockerignore_patterns()
    for name in (".venv", ".git", "packings.db", "__pycache__", ".pytest_cache", ".hypothesis"):
        assert ignored(name, patterns), name
    for name in ("workers/__pycache__/kernels.cpython-311.pyc", "tests/data/x.db", "tests/.hypothesis"):
        assert ignored(name, patterns), name
    for name in ("pyproject.toml", "README.md", "alembic", "alembic.ini", "service", "workers"):
        assert not ignored(name, patterns), name
