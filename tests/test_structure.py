"""The installed package's layout and import graph: a repository folder's file ``F/X.py`` is the module
``packings.F.X`` (docs/architecture.md), the numerics (packings.workers) import nothing of the service,
of a database or of Dask, and no module imports, directly or through others, one that imports it back.

Every import statement counts, at module level or inside a function: a function's import runs too.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import packings.service

# the installed package (in a checkout, packings/__init__.py may be the checkout's: its subpackages are not)
PACKAGE = Path(packings.service.__file__).resolve().parents[1]
ROOT = Path(__file__).resolve().parents[1]
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
            out.update(f"{base}.{a.name}" for a in node.names)  # `from packings.service import store`
    return out


def graph() -> dict[str, set[str]]:
    mods = {module_name(p): p for p in PACKAGE.rglob("*.py") if "migrations" not in p.parts}
    return {m: {i for i in imports(p) if i in mods and i != m} for m, p in mods.items()}


def test_the_package_has_the_modules_it_should():
    g = graph()
    assert {
        "packings",
        "packings.service.api",
        "packings.service.cli",
        "packings.workers",
        "packings.workers.paths",
    } <= set(g)
    assert (PACKAGE / "migrations" / "env.py").is_file()


def test_a_files_path_is_its_import_name():
    """The one rule: service/X.py is packings.service.X and workers/X.py is packings.workers.X, in the
    installed package as in the repository."""
    for folder in ("service", "workers"):
        here = {p.name for p in (ROOT / folder).glob("*.py")}
        installed = {p.name for p in (PACKAGE / folder).glob("*.py")}
        assert here and here == installed, (folder, here ^ installed)
    assert {p.name for p in (PACKAGE / "migrations" / "versions").glob("*.py")} == {
        p.name for p in (ROOT / "alembic" / "versions").glob("*.py")
    }
    assert (ROOT / "packings" / "__init__.py").read_text() == (PACKAGE / "__init__.py").read_text()


def test_importing_the_numerics_loads_nothing_of_the_service():
    """A process that imports the numerics (a worker's kernels, a benchmark) gets no database, no Dask
    and no module of the service: the package's face loads them only when its names are used."""
    code = (
        "import sys, packings.workers.expand, packings.workers.catalysis\n"
        "heavy = sorted(m for m in sys.modules if m.split('.')[0] in {heavy!r} or m.startswith('packings.service'))\n"
        "print(heavy)\n"
        "import packings\n"
        "print(packings.connect.__module__, packings.PackingsError.__module__)\n"
    ).replace("{heavy!r}", repr(set(SERVICE_ONLY)))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=PACKAGE.parent)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == ["[]", "packings.service.api packings.service.errors"]


def test_the_numerics_import_nothing_of_the_service():
    for path in (PACKAGE / "workers").rglob("*.py"):
        for name in imports(path):
            top = name.split(".")[0]
            assert top not in SERVICE_ONLY, f"{module_name(path)} imports {name}"
            if top == "packings":
                assert name == "packings.workers" or name.startswith("packings.workers."), (
                    f"{module_name(path)} imports {name}"
                )


def test_the_import_graph_has_no_loop():
    g = graph()
    # the package's __init__ re-exports the API; a submodule importing `packings` itself is not a loop of code
    g = {m: deps - {"packings", "packings.service", "packings.workers"} for m, deps in g.items()}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for d in sorted(g[m]):
            if state.get(d) == 1:
                loop = stack[stack.index(d) :] + [d]
                raise AssertionError("import loop: " + " -> ".join(loop))
            if d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(g):
        if m not in state:
            visit(m)


#: the functions allowed over LONG code lines, each giving its reason in its docstring: (folder/file, name)
LONG_ALLOWED = {
    ("workers/_compiled.py", "follow_steps"),
    ("workers/_growth.py", "grow"),
    ("workers/expand.py", "_attempts"),
}
#: the most lines of code (docstring not counted) a function has without a reason in its docstring
LONG = 80


def code_lines(f: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """The lines of a function's body after its docstring, if it has one, to its end."""
    body = f.body
    has_doc = (
        isinstance(body[0], ast.Expr)
        and isinstance(body[0].value, ast.Constant)
        and isinstance(body[0].value.value, str)
    )
    start = body[0].end_lineno + 1 if has_doc else body[0].lineno
    return f.end_lineno - start + 1


def long_functions() -> dict[tuple[str, str], ast.FunctionDef | ast.AsyncFunctionDef]:
    """Every function (methods and nested ones too) of the repository's service, workers, benchmarks and
    packings folders with more than LONG lines of code, by (folder/file, name)."""
    out = {}
    for folder in ("service", "workers", "benchmarks", "packings"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and code_lines(node) > LONG:
                    out[(path.relative_to(ROOT).as_posix(), node.name)] = node
    return out


def test_no_function_is_long_without_a_reason():
    """The rule of the guide: no function over LONG lines of code without a reason in its docstring.  Those
    that have one are listed; a new long function fails here until it is split, or listed with its reason."""
    long = long_functions()
    assert set(long) <= LONG_ALLOWED, f"over {LONG} lines of code: {sorted(set(long) - LONG_ALLOWED)}"
    assert set(long) == LONG_ALLOWED, f"no longer over {LONG} lines, leave the list: {sorted(LONG_ALLOWED - set(long))}"
    for key, f in long.items():
        assert ast.get_docstring(f), f"{key} is long and has no docstring to say why"


def test_a_function_s_code_lines_leave_its_docstring_out():
    f = ast.parse('def f(x):\n    """What f does,\n    and why."""\n    y = x\n    return y\n').body[0]
    g = ast.parse("def g(\n    x,\n):\n    y = x\n    return y\n").body[0]
    assert (code_lines(f), code_lines(g)) == (2, 2)
