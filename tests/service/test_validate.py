"""The parameters of a run are checked in one place (packings.service.validate): the Python API and the
command line refuse the same values, each with one line."""

from __future__ import annotations

import subprocess
import sys

import pytest

import packings
from packings.service import validate
from packings.service.errors import UsageError


@pytest.mark.parametrize("name", sorted(validate.RANGES))
def test_each_range_refuses_just_outside_its_bounds(name):
    low, high = validate.RANGES[name]
    validate.check_range(name, low)
    with pytest.raises(UsageError, match=f"^{name} must be .*got {low - 1}"):
        validate.check_range(name, low - 1)
    if high is not None:
        validate.check_range(name, high)
        with pytest.raises(UsageError, match=f"^{name} must be between {low} and {high}"):
            validate.check_range(name, high + 1)
    with pytest.raises(UsageError):
        validate.check_range(name, True)  # a bool is not a count
    validate.check_range(name, None)  # the default


@pytest.mark.parametrize("name", sorted(validate.RANGES))
def test_the_command_lines_types_take_the_same_bounds(name):
    low, high = validate.RANGES[name]
    t = validate.int_range(name)
    assert (t.min, t.max) == (low, high)


@pytest.mark.parametrize(
    "kwargs, words",
    [
        ({"workers": 0}, "workers must be between 1 and 512"),
        ({"max_break": 11}, "max_break must be between 1 and 10"),
        ({"max_attempts": 0}, "max_attempts must be between 1 and 100"),
        ({"workers": 2, "scheduler": "tcp://127.0.0.1:1"}, "not both"),
        ({"dashboard_address": "nonsense"}, "dashboard_address must be HOST:PORT"),
    ],
)
def test_the_api_refuses_before_anything_starts(kwargs, words, tmp_path):
    with pytest.raises(UsageError, match=words):
        packings.enumerate(7, f"sqlite:///{tmp_path / 'x.db'}", progress=False, **kwargs)
    assert not (tmp_path / "x.db").exists()


@pytest.mark.parametrize("n, words", [(3, "at least 4"), (validate.MAX_N + 1, "too large"), ("7", "an integer")])
def test_n_out_of_range(n, words):
    with pytest.raises(UsageError, match=words):
        validate.check_n(n)


@pytest.mark.parametrize(
    "args, words",
    [
        (["enumerate", "7", "--workers", "0"], "0 is not in the range 1<=x<=512"),
        (["enumerate", "7", "--max-break", "11"], "11 is not in the range 1<=x<=10"),
        (["enumerate", "3"], "n must be at least 4"),
        (["catalyse", "7", "--workers", "1", "--scheduler", "tcp://127.0.0.1:1"], "give either --workers"),
        (["enumerate", "7", "--dashboard-address", "nonsense"], "--dashboard-address must be HOST:PORT"),
        (["enumerate", "7", "--dashboard-address", "127.0.0.1:70000"], "PORT from 0 to 65535"),
        (["enumerate", "7", "--dashboard-address", "no-such-host.invalid:8787"], "no such host"),
        (["catalyse", "7", "--glued", "--dashboard-address", "8787"], "--dashboard-address must be HOST:PORT"),
    ],
)
def test_the_command_line_refuses_in_one_line_with_status_2(args, words, tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "packings.service.cli", *args, "--db", f"sqlite:///{tmp_path / 'x.db'}"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("packings: error: ") and words in lines[0], r.stderr
    assert not (tmp_path / "x.db").exists()


@pytest.mark.parametrize("address", ["127.0.0.1:8787", ":0", "localhost:0", "[::1]:8787", "0.0.0.0:1"])
def test_a_dashboard_address_a_local_cluster_can_serve_on_passes(address):
    validate.check_dashboard_address(address)
