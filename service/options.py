"""The click options that more than one command module takes (:mod:`packings.service.cli`,
:mod:`packings.service.plot_commands`), defined once."""

from __future__ import annotations

import click

db_option = click.option(
    "--db",
    "db_url",
    default=None,
    metavar="URL",
    help="Database URL (default: $PACKINGS_DB, else sqlite:///packings.db).",
)
#: the square well of the probabilities (``packings stats --kappa``, ``packings plot probabilities``)
width_option = click.option(
    "--width",
    type=click.FloatRange(min=0.0, max=1.0, min_open=True, max_open=True),
    default=None,
    help="A square well of this width (sphere diameters) instead of the sticky limit: singular clusters "
    "(n ≥ 9) need it.",
)
