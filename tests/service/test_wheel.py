"""The wheel, as a user and every worker machine installs it: built with ``pip wheel``, installed with
pip into a fresh virtual environment, and run from an empty directory, with no checkout in sight.

Slow (a fresh environment installs every dependency, from pip's cache when it has them).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def wheel_env(tmp_path_factory):
    """(the wheel, the bin directory of a fresh virtual environment with the wheel installed)."""
    work = tmp_path_factory.mktemp("wheel")
    src = work / "src"  # what the Dockerfile copies: pip builds in the source tree, not in this checkout
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    for name in ("packings", "service", "workers", "alembic"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__"))
    r = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "--wheel-dir", str(work / "dist"), str(src)],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert r.returncode == 0, r.stderr
    (wheel,) = (work / "dist").glob("packings-*.whl")
    subprocess.run([sys.executable, "-m", "venv", str(work / "venv")], check=True, timeout=300)
    bin_dir = work / "venv" / "bin"
    r = subprocess.run(
        [str(bin_dir / "python"), "-m", "pip", "install", "--quiet", str(wheel)],
        capture_output=True,
        text=True,
        timeout=1800,
    )
    assert r.returncode == 0, r.stderr
    return wheel, bin_dir


def run(bin_dir: Path, args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """A command of the fresh environment, in ``cwd``, with nothing of this checkout or of the test
    environment on its path."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PACKINGS_DB", "VIRTUAL_ENV")}
    env["PATH"] = f"{bin_dir}{os.pathsep}{env.get('PATH', '')}"
    return subprocess.run(args, capture_output=True, text=True, timeout=900, cwd=cwd, env=env)


def test_the_wheel_is_one_package_with_its_migrations(wheel_env):
    wheel, _ = wheel_env
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
        (top_level,) = [n for n in names if n.endswith(".dist-info/top_level.txt")]
        assert z.read(top_level).decode().split() == ["packings"]
    assert all(n.startswith(("packings/", "packings-")) for n in names), names
    for name in (
        "packings/migrations/env.py",
        "packings/migrations/script.py.mako",
        "packings/migrations/versions/0001_initial.py",
        "packings/workers/paths.py",
        "packings/__init__.py",
        "packings/service/cli.py",
        "packings/service/paper_counts.json",
    ):
        assert name in names, name


def test_the_installed_wheel_enumerates_in_an_empty_directory(wheel_env, tmp_path):
    _, bin_dir = wheel_env
    where = run(bin_dir, ["python", "-c", "import packings, packings.workers; print(packings.__file__)"], tmp_path)
    assert where.returncode == 0, where.stderr
    assert Path(where.stdout.strip()).is_relative_to(bin_dir.parent), "packings comes from the fresh environment"
    for name in ("service", "workers"):
        r = run(bin_dir, ["python", "-c", f"import {name}"], tmp_path)
        assert r.returncode != 0 and "ModuleNotFoundError" in r.stderr, f"the wheel installs a top-level {name}"

    r = run(bin_dir, ["packings", "enumerate", "7", "--workers", "1", "--quiet", "--json"], tmp_path)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert (out["status"], out["total"]) == ("complete", 5)
    # a fresh installation compiles its kernels, and says so; the next run loads them from the cache
    assert "packings: compiling the numerical kernels" in r.stderr
    r = run(bin_dir, ["packings", "enumerate", "7", "--workers", "1", "--quiet", "--json"], tmp_path)
    assert r.returncode == 0 and json.loads(r.stdout)["total"] == 5 and "compiling" not in r.stderr, r.stderr
    assert (tmp_path / "packings.db").is_file(), "the default database is created where the command runs"
    r = run(bin_dir, ["packings", "stats", "--n", "7"], tmp_path)  # the paper's counts ship with the wheel
    assert r.returncode == 0 and "as the paper at every number of contacts: 5 (" in r.stdout, r.stdout + r.stderr
    r = run(bin_dir, ["packings", "db", "version"], tmp_path)
    assert r.returncode == 0 and r.stdout.splitlines()[-1] == "up to date", r.stdout + r.stderr
    code = "import packings; c = packings.connect(); print(c.count(n=7), c.get(1).coords.shape)"
    r = run(bin_dir, ["python", "-c", code], tmp_path)
    assert r.returncode == 0 and r.stdout.split() == ["5", "(7,", "3)"], r.stderr


def test_the_installed_wheel_upgrades_a_postgresql_database(wheel_env, pg_url, tmp_path):
    _, bin_dir = wheel_env
    r = run(bin_dir, ["packings", "db", "upgrade", "--db", pg_url], tmp_path)
    assert r.returncode == 0, r.stderr
    r = run(bin_dir, ["packings", "db", "version", "--db", pg_url], tmp_path)
    assert r.returncode == 0 and r.stdout.splitlines()[-1] == "up to date", r.stdout + r.stderr
