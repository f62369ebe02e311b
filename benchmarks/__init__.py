"""Benchmarks of the numerics: ``python -m benchmarks <subcommand>`` from the repository root.

Each subcommand is a module with ``add_arguments(parser)`` and ``run(args)``,
registered in :data:`benchmarks.__main__.SUBCOMMANDS`.
"""
