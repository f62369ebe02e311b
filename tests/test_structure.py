"""The installed package's import graph: the numerics (packings.workers) import nothing of the service,
of a database or of Dask, and no module imports, directly or through others, one that imports it back.

Every import statement counts, at module level or inside a function: a function's import runs too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import packings

PACKAGE = Path(packings.__file__).resolve().parent
SERVICE_ONLY = ("sqlalchemy", "alembic", "dask", "distributed", "psycopg", "click", "tqdm", "matplotlib")


def module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def imports(path: Path) -> set[str]:
    """The absolute names of the modules ``path`` imports."""
    tree = ast.parse(path.read_text(), str(path))
    here = module_name(path).split(".")
    if path.name != "__init__.py":
        here = here[:-1]
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(here[: len(here) - node.level + 1] + ([base] if base else []))
            out.add(base)
            out.update(f"{base}.{a.name}" for a in node.names)  # `from packings import store`
    return out


def graph() -> dict[str, set[str]]:
    mods = {module_name(p): p for p in PACKAGE.rglob("*.py") if "migrations" not in p.parts}
    return {m: {i for i in imports(p) if i in mods and i != m} for m, p in mods.items()}


def test_the_package_has_the_modules_it_should():
    g = graph()
    assert {"packings", "packings.api", "packings.cli", "packings.workers", "packings.workers.paths"} <= set(g)
    assert (PACKAGE / "migrations" / "env.py").is_file()


def test_the_numerics_import_nothing_of_the_service():
    for path in (PACKAGE / "workers").rglob("*.py"):
        for name in imports(path):
            top = name.split(".")[0]
            assert top not in SERVICE_ONLY, f"{module_name(path)} imports {name}"
            if top == "packings":
                assert name == "packings.workers" or name.startswith("packings.workers."), \
                    f"{module_name(path)} imports {name}"


def test_the_import_graph_has_no_loop():
    g = graph()
    # the package's __init__ re-exports the API; a submodule importing `packings` itself is not a loop of code
    g = {m: deps - {"packings", "packings.workers"} for m, deps in g.items()}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for d in sorted(g[m]):
            if state.get(d) == 1:
                loop = stack[stack.index(d):] + [d]
                raise AssertionError("import loop: " + " -> ".join(loop))
            if d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(g):
        if m not in state:
            visit(m)
