"""Clusters as text: records, JSON, CSV, XYZ and extended XYZ.

Pure functions from cluster rows (:class:`packings.service.models.ClusterRow`) to records
(plain dicts) and from records to text chunks, plus :func:`write_atomic`.

* Coordinates are the exact float64 values of the ``coords`` blob, written with
  Python's shortest round-trip repr, so every format reads back bit-exactly.
  Positions are in units of the sphere diameter.
* XYZ and extended XYZ name every sphere ``X`` (ASE reads it as its dummy
  element, atomic number 0).  The extended XYZ comment line carries
  ``Properties=species:S:1:pos:R:3`` and the cluster's facts as key=value
  pairs, named so that ASE's database accepts them as keys (``cluster_id`` for
  ``id``, ``self_stresses`` for ``stresses``: :data:`ASE_NAMES`); note that ASE
  turns any value that looks like a number into one, so a certificate made only
  of digits reads back as an int there (``cluster_id`` is the key to join back
  to the database).
* In records ``contacts`` is the number of contacts (as in the database and the
  selection language) and ``contact_list`` the pairs ``[[i, j], ...]``.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import tempfile
from pathlib import Path
from typing import IO, Callable, Iterable, Iterator

from packings.service.errors import UsageError

#: the scalar facts of a cluster, in the order the formats list them
FACTS = (
    "id",
    "n",
    "contacts",
    "excess",
    "static",
    "embedding",
    "geometries",
    "certificate",
    "rigid_kind",
    "rigid_method",
    "margin",
    "flexes",
    "stresses",
    "singular",
    "min_gap",
    "lattice",
    "close_packed",
    "sigma",
    "chiral",
    "log_z",
    "z_reason",
    "eps_power",
    "log_z_square_well",
    "found_in_run",
    "found_by",
    "source_id",
    "created_at",
)
#: the facts on an extended XYZ comment line (None values are left out)
XYZ_FACTS = tuple(f for f in FACTS if f not in ("found_in_run", "found_by", "source_id", "created_at"))
#: the names ASE's database reserves, and what extended XYZ and ase.Atoms.info call those facts instead
#: (so that ``ase.db`` takes ``atoms.info`` as key-value pairs as it is)
ASE_NAMES = {"id": "cluster_id", "stresses": "self_stresses"}
#: facts computed from the row rather than read from a column
_DERIVED = ("excess", "static", "close_packed", "created_at")
SPECIES = "X"
FORMATS = ("extxyz", "xyz", "json")


def facts(c) -> dict:
    """The scalar facts of a cluster row."""
    from packings.workers.classify import LATTICES, static_class  # here: the command line imports this module light

    out = {name: getattr(c, name) for name in FACTS if name not in _DERIVED}
    out["excess"] = c.contacts - (3 * c.n - 6)
    out["static"] = static_class(c.n, c.contacts)
    out["close_packed"] = None if c.lattice is None else c.lattice in LATTICES
    out["created_at"] = c.created_at.isoformat() if c.created_at is not None else None
    return {name: out[name] for name in FACTS}


def record(c) -> dict:
    """Facts, coordinates (n x 3 lists of floats) and contact pairs of a cluster row."""
    core = c.to_core()
    return {**facts(c), "coords": core.coords.tolist(), "contact_list": [list(p) for p in core.contacts]}


def to_json(records: Iterable[dict]) -> Iterator[str]:
    """A JSON list, one object a line."""
    sep = "[\n"
    for r in records:
        yield sep + json.dumps(r)
        sep = ",\n"
    yield "[]\n" if sep == "[\n" else "\n]\n"


def to_csv(records: Iterable[dict], columns=FACTS) -> Iterator[str]:
    """CSV with a header line; missing values are empty."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in records:
        w.writerow(["" if r[c] is None else r[c] for c in columns])
        yield buf.getvalue()
        buf.seek(0)
        buf.truncate()
    yield buf.getvalue()


def table(cols: list[str], rows: list[list]) -> str:
    """A text table: a header line and one line per row, columns right-aligned, None as empty."""
    cells = [[("" if v is None else str(v)) for v in r] for r in rows]
    widths = [max([len(c), *(len(r[i]) for r in cells)]) for i, c in enumerate(cols)]
    out = ["  ".join(c.rjust(w) for c, w in zip(cols, widths))]
    out += ["  ".join(v.rjust(w) for v, w in zip(r, widths)) for r in cells]
    return "\n".join(out)


def _xyz_value(v) -> str:
    if isinstance(v, bool):
        return "T" if v else "F"
    if isinstance(v, float):
        return repr(v)
    s = str(v)
    return f'"{s}"' if not s or any(ch.isspace() or ch in "=\"'" for ch in s) else s


def ase_info(facts: dict, names=None) -> dict:
    """The facts (``names``, default all) that are not None, under the names ASE accepts as
    database keys (:data:`ASE_NAMES`)."""
    return {ASE_NAMES.get(k, k): facts[k] for k in (names or facts) if facts[k] is not None}


def xyz_comment(r: dict, extended: bool = True) -> str:
    pairs = [f"{k}={_xyz_value(v)}" for k, v in ase_info(r, XYZ_FACTS).items()]
    return " ".join((["Properties=species:S:1:pos:R:3"] if extended else []) + pairs)


def to_xyz(records: Iterable[dict], extended: bool = True) -> Iterator[str]:
    """One XYZ frame per cluster: the count, a comment line, ``X x y z`` lines."""
    for r in records:
        lines = [str(len(r["coords"])), xyz_comment(r, extended)]
        lines += [f"{SPECIES} {x!r} {y!r} {z!r}" for x, y, z in r["coords"]]
        yield "\n".join(lines) + "\n"


def render(fmt: str, records: Iterable[dict]) -> Iterator[str]:
    """``records`` as text chunks in one of :data:`FORMATS`."""
    if fmt == "json":
        return to_json(records)
    if fmt in ("extxyz", "xyz"):
        return to_xyz(records, extended=fmt == "extxyz")
    raise ValueError(f"unknown format {fmt!r}: use one of {', '.join(FORMATS)}")


def counted(k: int, noun: str, plural: str | None = None) -> str:
    """``k`` and ``noun`` as English has them: "1 cluster", "2 clusters" (``plural``: other than noun + s)."""
    return f"{k} {noun if k == 1 else plural or noun + 's'}"


def format_for(path: str | None) -> str:
    """The format a file name implies (.json, .xyz, .extxyz; standard output, no name: extxyz); any other
    suffix is a :class:`packings.service.errors.UsageError` (nothing is written in a format the name does
    not say)."""
    if not path:
        return "extxyz"
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix not in FORMATS:
        raise UsageError(
            f"cannot tell the format of {path} from its suffix: name it .{', .'.join(FORMATS)}, or give --format"
        )
    return suffix


def replace_file(path: str | os.PathLike, write: Callable[[IO], None], binary: bool = False) -> Path:
    """Call ``write(f)`` on a temporary file beside ``path``, then rename it
    over ``path``: ``path`` is either left as it was or holds the whole
    content, and on any failure no temporary file is left."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") if binary else os.fdopen(fd, "w", encoding="utf-8", newline="\n") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    return path


def write_atomic(path: str | os.PathLike, chunks: Iterable[str]) -> None:
    """Write the text ``chunks`` to ``path`` through :func:`replace_file`."""
    replace_file(path, lambda f: f.writelines(chunks))
