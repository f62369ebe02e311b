"""docker/Dockerfile and docker/compose.yaml, checked without a Docker engine.

No image is built and no container runs here.  compose.yaml is read by Docker Compose itself: ``docker
compose config`` (the docker CLI's plugin, or ``docker-compose``; Debian's package is enough, .ci/run
installs it) validates the file and prints it normalised, interpolated and with its anchors merged, and the
tests read that.  What is checked is what would break a build or a start: every command a compose service
runs exists in this project's environment and its real parser turns the arguments into the intended
settings; every path the Dockerfile copies exists in the build context and is not excluded by
.dockerignore; the build context and Dockerfile that compose names exist.  Without a Compose client the
compose tests skip, saying so; under CI (CI=true) they fail instead.  The image installs packings from its
wheel with ``pip``, which tests/service/test_wheel.py does in a fresh virtual environment.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent
DOCKER = ROOT / "docker"
COMPOSE = DOCKER / "compose.yaml"
DOCKERFILE = DOCKER / "Dockerfile"
BIN = Path(sys.executable).parent
IMAGE_SERVICES = ("scheduler", "worker", "coordinator")  # the services that run the packings image


# --------------------------------------------------------------------------- helpers

NO_COMPOSE = (
    "no Docker Compose client: neither `docker compose` nor `docker-compose` runs here "
    "(Debian: apt-get install docker-compose), so docker/compose.yaml cannot be validated"
)


def _compose_client() -> tuple[list[str], int] | None:
    """A Docker Compose client and its major version: the docker CLI's compose plugin, or docker-compose
    (Debian 12's is Compose v1, 1.29; later ones are v2)."""
    for command in (["docker", "compose"], ["docker-compose"]):
        if shutil.which(command[0]) is None:
            continue
        r = subprocess.run([*command, "version", "--short"], capture_output=True, text=True, timeout=60)
        if r.returncode == 0 and r.stdout.strip():
            return command, int(r.stdout.strip().lstrip("v").split(".")[0])
    return None


def compose_config(tmp: Path) -> dict:
    """``docker compose config`` of docker/compose.yaml, parsed: the file validated by Compose and printed
    normalised (variables interpolated, N unset; anchors merged; paths absolute).  Skips without a Compose
    client, or fails under CI.

    Compose v1 (Debian 12's docker-compose) predates the file's top-level ``name``: it is given the file
    without that one key, the name as its project name, and validates all the rest."""
    client = _compose_client()
    if client is None:
        if os.environ.get("CI", "").lower() in ("true", "1"):
            pytest.fail(f"{NO_COMPOSE}; CI must check it (.ci/run installs docker-compose)")
        pytest.skip(NO_COMPOSE)
    command, major = client
    env = {k: v for k, v in os.environ.items() if k != "N"}
    if major >= 2:
        args = [*command, "-f", str(COMPOSE), "config", "--format", "json"]
    else:
        spec = yaml.safe_load(COMPOSE.read_text())
        name = spec.pop("name")
        rest = tmp / "compose-v1.yaml"
        rest.write_text(yaml.safe_dump(spec, sort_keys=False))
        args = [*command, "-p", name, "--project-directory", str(DOCKER), "-f", str(rest), "config"]
    r = subprocess.run(args, capture_output=True, text=True, timeout=120, env=env, cwd=ROOT)
    # stderr too: a wrapper script may lose compose's exit status, and a warning is worth fixing
    assert r.returncode == 0 and not r.stderr.strip(), r.stderr
    if major >= 2:
        return json.loads(r.stdout)
    return {"name": name, **yaml.safe_load(r.stdout)}


@pytest.fixture(scope="module")
def compose(tmp_path_factory) -> dict:
    return compose_config(tmp_path_factory.mktemp("compose"))


def argv(service: dict) -> list[str]:
    """A service's command as Compose runs it: a list, or a string Compose splits as a shell would."""
    cmd = service["command"]
    return list(cmd) if isinstance(cmd, list) else shlex.split(cmd)


def seconds(duration: str) -> float:
    """A Compose duration (``1m``, ``1m0s``, ``90s``, ``1m30s``) in seconds."""
    units = {"h": 3600.0, "m": 60.0, "s": 1.0, "ms": 1e-3, "us": 1e-6}
    parts = re.findall(r"(\d+(?:\.\d+)?)(h|ms|us|m|s)", duration)
    assert parts and "".join(a + u for a, u in parts) == duration, duration
    return sum(float(a) * units[u] for a, u in parts)


def published_on(ports: list) -> set[str]:
    """The host addresses a service's ports are published on (Compose v2's mappings, or v1's strings)."""
    return {p["host_ip"] if isinstance(p, dict) else p.rsplit(":", 2)[0] for p in ports}


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


def test_one_image_for_every_dask_process(compose):
    """Scheduler, workers and coordinator must run the same Dask: one image, which each can build."""
    services = compose["services"]
    images = {services[name]["image"] for name in IMAGE_SERVICES}
    assert len(images) == 1 and images != {"postgres:15"}
    for name in IMAGE_SERVICES:
        build = services[name]["build"]
        context = Path(build["context"]).resolve()
        assert context == ROOT, f"{name}: the build context is the repository root"
        assert (context / build["dockerfile"]).resolve() == DOCKERFILE
        assert (context / ".dockerignore").is_file()


def test_the_scheduler_and_the_workers_are_started_again_when_they_end(compose):
    """A Dask worker ends when it loses its scheduler; the coordinator waits for a scheduler to come back
    (PACKINGS_RECONNECT_SECONDS): both must be restarted, the coordinator not (it ends with the run)."""
    services = compose["services"]
    assert services["scheduler"]["restart"] == services["worker"]["restart"] == "unless-stopped"
    assert services["coordinator"]["restart"] == "no"


def test_the_coordinator_is_stopped_with_sigterm_and_time_to_put_its_leases_back(compose):
    """`docker compose stop` sends SIGTERM to the container's first process: packings itself (an
    exec-form command, no shell between), which stops as on Ctrl-C, given a minute before SIGKILL."""
    coordinator = compose["services"]["coordinator"]
    assert argv(coordinator)[0] == "packings" and coordinator.get("entrypoint") is None
    assert (coordinator.get("stop_signal") or "SIGTERM") == "SIGTERM" and seconds(
        coordinator["stop_grace_period"]
    ) == 60


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
        from packings.service.cli import cli

        command = cli.commands[args[1]]
    try:
        return command.make_context(" ".join(args[:2]), args[2:]).params
    except click.ClickException as e:
        pytest.fail(f"{' '.join(args)}: {e.format_message()}")


def test_commands_parse_to_the_intended_settings(compose):
    services = compose["services"]
    p = parsed(argv(services["scheduler"]))
    assert (p["host"], p["dashboard_address"], p["port"]) == ("0.0.0.0", ":8787", None)  # port None: 8786
    assert p["preload"] == ("packings.service.dashboard",) and services["scheduler"]["environment"]["PACKINGS_DB"]
    import importlib

    assert hasattr(importlib.import_module(p["preload"][0]), "dask_setup")  # a module the scheduler can preload
    p = parsed(argv(services["worker"]))
    assert (p["scheduler"], int(p["n_workers"]), p["nthreads"], p["preload_argv"]) == ("tcp://scheduler:8786", 1, 1, ())
    p = parsed(argv(services["coordinator"]))
    assert (p["n"], p["scheduler"], p["db_url"], p["n_workers"]) == (10, "tcp://scheduler:8786", None, None)  # N unset


def test_docker_compose_config_accepts_the_file(compose):
    """Compose validated the file (the fixture): the project, its four services, the database's volume,
    two workers, and the dashboard and scheduler published on 127.0.0.1 only, as the file's header says."""
    services = compose["services"]
    assert compose["name"] == "packings" and set(services) == {"postgres", *IMAGE_SERVICES}
    assert "pgdata" in compose["volumes"] and services["worker"]["deploy"]["replicas"] == 2
    assert published_on(services["scheduler"]["ports"]) == {"127.0.0.1"}
    assert all("ports" not in services[name] for name in services if name != "scheduler")
    assert services["coordinator"]["depends_on"]["postgres"]["condition"] == "service_healthy"


# --------------------------------------------------------------------------- Dockerfile


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
