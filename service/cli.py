"""The ``packings`` command line.

For now ``packings enumerate N`` runs the in-process enumeration of
``workers.explore``; the distributed service (SQL frontier, Dask workers)
replaces its engine without changing what it prints.
"""

from __future__ import annotations

import json
import sys

import click

from workers.params import Params

MAX_N = 24  #: beyond this the catalogue cannot be enumerated on any machine (the count grows like (n-5)!)


def format_counts(n: int, by_contacts: dict[int, int]) -> str:
    """The paper's table: clusters by number of contacts, relative to 3n - 6."""
    lines = [f"n = {n}: {sum(by_contacts.values())} rigid clusters", f"{'contacts':>10} {'3n-6+':>6} {'clusters':>9}"]
    for m, count in sorted(by_contacts.items()):
        lines.append(f"{m:>10} {m - (3 * n - 6):>+6} {count:>9}")
    return "\n".join(lines)


def check_n(n: int) -> None:
    if n < 4:
        raise click.UsageError(f"n must be at least 4 (got {n}): smaller clusters have no contact triangle to pin")
    if n > MAX_N:
        raise click.UsageError(f"n = {n} is too large: at most {MAX_N} (the number of clusters grows like (n-5)!)")


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def cli() -> None:
    """Enumerate every rigid cluster of n identical hard spheres."""


@cli.command("enumerate")
@click.argument("n", type=int)
@click.option("--max-break", type=click.IntRange(1, 10), default=Params.max_break, show_default=True,
              help="Largest number of contacts broken at once.")
@click.option("--min-contacts", type=int, default=None, help="Keep only clusters with at least this many contacts.")
@click.option("--json", "as_json", is_flag=True, help="Print the counts and diagnostics as JSON.")
@click.option("--quiet", is_flag=True, help="No progress lines.")
def enumerate_cmd(n: int, max_break: int, min_contacts: int | None, as_json: bool, quiet: bool) -> None:
    """Enumerate the rigid clusters of N spheres and print them by number of contacts."""
    from workers.explore import explore

    check_n(n)
    params = Params(max_break=max_break, min_contacts=min_contacts)

    def progress(done, _ex, cat):
        if not quiet and (done % 25 == 0 or done == len(cat.clusters)):
            click.echo(f"\rexpanded {done} / {len(cat.clusters)} clusters found", nl=False, err=True)

    cat = explore(n, params, on_expansion=progress)
    if not quiet:
        click.echo("", err=True)
    if as_json:
        click.echo(json.dumps({"n": n, "total": cat.total,
                               "by_contacts": {str(k): v for k, v in cat.by_contacts().items()},
                               "diagnostics": cat.diagnostics()}))
        return
    click.echo(format_counts(n, cat.by_contacts()))
    click.echo("diagnostics: " + ", ".join(f"{k} {v}" for k, v in cat.diagnostics().items()))


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    try:
        cli.main(args=argv or ["--help"], prog_name="packings", standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("aborted", err=True)
        sys.exit(130)
    except click.ClickException as e:
        click.echo(f"packings: error: {e.format_message()}", err=True)
        sys.exit(e.exit_code)


if __name__ == "__main__":
    main()
