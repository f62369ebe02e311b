"""``python -m benchmarks <subcommand> [options]``: a small dispatcher.

Add a subcommand by writing a module with ``add_arguments(parser)`` and
``run(args)`` (returning an exit status or None) and listing it in SUBCOMMANDS.
"""

from __future__ import annotations

import argparse
import sys

from benchmarks import (
    classes,
    enumeration,
    free_energy,
    frontier,
    memory,
    network,
    paths,
    progress,
    replay,
    retrace,
    screenshot,
    soak,
)

#: subcommand name -> module with add_arguments(parser) and run(args)
SUBCOMMANDS = {
    "paths": paths,
    "classes": classes,
    "enumerate": enumeration,
    "memory": memory,
    "retrace": retrace,
    "soak": soak,
    "replay": replay,
    "screenshot": screenshot,
    "free_energy": free_energy,
    "network": network,
    "progress": progress,
    "frontier": frontier,
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="SUBCOMMAND")
    for name, module in SUBCOMMANDS.items():
        doc = (module.__doc__ or name).strip()
        p = sub.add_parser(
            name, help=doc.splitlines()[0], description=doc, formatter_class=argparse.RawDescriptionHelpFormatter
        )
        module.add_arguments(p)
    args = parser.parse_args(argv)
    return SUBCOMMANDS[args.command].run(args) or 0


if __name__ == "__main__":
    sys.exit(main())
