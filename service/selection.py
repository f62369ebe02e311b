"""Selecting clusters: a compact selection language, in the spirit of ``ase db``.

A selection is comma-separated terms, all of which must hold::

    n=10,contacts<24,singular      !singular,min_gap>0.1      hyperstatic      run=1
    n=11,lattice=fcc               close_packed,geometries>1  !reached

Terms:

* ``key``: a boolean key is true (a key that may be missing, such as
  ``min_gap``, is present);
* ``!key`` or ``not key``: the opposite;
* ``key OP value`` with OP one of ``= != < <= > >=``.  The value is read by the
  key's type: int, float, bool (true/false, 1/0, yes/no) or string (optionally
  quoted).  A comparison with a missing value is false, except ``!=``.

The keys are the entries of :data:`KEYS` (aliases in :data:`ALIASES`): a new key
is one more :class:`Key` there.  The empty selection selects everything.
"""

from __future__ import annotations

import math
import operator
import re
from dataclasses import dataclass
from typing import Any, Callable, NamedTuple

from sqlalchemy import ColumnElement, Select, and_, case, false, func, not_, select, true
from sqlalchemy.orm import aliased, with_expression

from packings.service.errors import UsageError
from packings.service.models import (
    FOUND_CATALYSIS,
    FOUND_CLOSE_PACKED,
    FOUND_PATH,
    FOUND_SEED,
    AttemptsRow,
    ClusterRow,
    Edge,
    ExpansionRow,
)
from packings.workers.classify import LATTICES
from packings.workers.free_energy import HYPERSTATIC, HYPOSTATIC, SINGULAR

OPERATORS = ("=", "!=", "<", "<=", ">", ">=")
EQUALITY = ("=", "!=")


class SelectionError(UsageError):
    """A selection (or sort key) that cannot be read; the message is one line."""


@dataclass(frozen=True)
class Key:
    """One selection key.

    ``expr`` builds the key's value as an SQL expression (a boolean clause for
    bool keys); ``where`` instead builds the whole condition from ``(op, value)``
    for keys that are not a value of the row (such as ``run``).
    """

    type: type  #: int, float, bool or str: how values are read
    help: str
    expr: Callable[[], ColumnElement] | None = None
    where: Callable[[str, Any], ColumnElement] | None = None
    ops: tuple[str, ...] | None = None  #: the operators allowed (default: by type)
    nullable: bool = False  #: the value may be missing (NULL)
    values: tuple[str, ...] | None = None  #: a string key's possible values (None: any)

    @property
    def allowed(self) -> tuple[str, ...]:
        if self.ops is not None:
            return self.ops
        return EQUALITY if self.type in (bool, str) else OPERATORS


def _column(name: str, type_: type, help: str, nullable: bool = False, values: tuple[str, ...] | None = None) -> Key:
    return Key(type_, help, expr=lambda: getattr(ClusterRow, name), nullable=nullable, values=values)


def _excess() -> ColumnElement:
    return ClusterRow.contacts - (3 * ClusterRow.n - 6)


def _lattice_in(*labels: str) -> Callable[[], ColumnElement]:
    return lambda: func.coalesce(ClusterRow.lattice.in_(labels), false())


def _static() -> ColumnElement:
    return case((_excess() < 0, "hypostatic"), (_excess() == 0, "isostatic"), else_="hyperstatic")


def _geometries() -> ColumnElement:
    """How many stored clusters share this one's contact graph (itself included)."""
    other = aliased(ClusterRow)
    return (
        select(func.count())
        .where(other.n == ClusterRow.n, other.certificate == ClusterRow.certificate)
        .correlate(ClusterRow)
        .scalar_subquery()
    )


def _sum(column, *conds) -> ColumnElement:
    """The sum of ``column`` over the rows that satisfy ``conds`` (0 if none), for each cluster."""
    return select(func.coalesce(func.sum(column), 0)).where(*conds).correlate(ClusterRow).scalar_subquery()


def _paths_out() -> ColumnElement:
    """Paths (attempts with a direction) from the cluster, over every run."""
    return _sum(AttemptsRow.paths, AttemptsRow.source_id == ClusterRow.id)


def _paths_in() -> ColumnElement:
    """Paths from other clusters that reached the cluster, over every run."""
    return _sum(Edge.paths, Edge.target_id == ClusterRow.id, Edge.source_id != ClusterRow.id)


def _circular() -> ColumnElement:
    return _sum(AttemptsRow.circular, AttemptsRow.source_id == ClusterRow.id)


def _rearranged() -> ColumnElement:
    return _sum(AttemptsRow.rearranged, AttemptsRow.source_id == ClusterRow.id)


def _in_run(op: str, run_id: int) -> ColumnElement:
    frontier = select(ExpansionRow.cluster_id).where(ExpansionRow.run_id == run_id)
    return ClusterRow.id.in_(frontier) if op == "=" else ClusterRow.id.not_in(frontier)


KEYS: dict[str, Key] = {
    "id": _column("id", int, "cluster id"),
    "n": _column("n", int, "number of spheres"),
    "contacts": _column("contacts", int, "number of contacts"),
    "embedding": _column("embedding", int, "0, 1, ... among clusters with one contact graph"),
    "flexes": _column("flexes", int, "dimension of the linear flexes"),
    "stresses": _column("stresses", int, "dimension of the self-stresses"),
    "singular": _column("singular", bool, "rigid with a linear flex held by a stress"),
    "min_gap": _column("min_gap", float, "smallest gap between spheres not in contact", nullable=True),
    "margin": _column("margin", float, "smallest eigenvalue of the best stress combination", nullable=True),
    "certificate": _column("certificate", str, "contact graph key (hex)"),
    "rigid_kind": _column("rigid_kind", str, "first-order or prestress", values=("first-order", "prestress")),
    "rigid_method": _column(
        "rigid_method",
        str,
        "test that decided: first-order, single-flex, single-stress, e_k, sdp",
        values=("first-order", "single-flex", "single-stress", "e_k", "sdp"),
    ),
    "found_in_run": _column("found_in_run", int, "run that first stored it", nullable=True),
    "found_by": _column(
        "found_by",
        str,
        "how it was first found: seed, path, catalysis or close-packed",
        values=(FOUND_SEED, FOUND_PATH, FOUND_CATALYSIS, FOUND_CLOSE_PACKED),
    ),
    "source_id": _column(
        "source_id", int, "the cluster it was found from (a path's start, a catalysis parent)", nullable=True
    ),
    "sigma": _column("sigma", int, "symmetry number: the rotations among its symmetries", nullable=True),
    "chiral": _column("chiral", bool, "its mirror image is not a rotation of it"),
    "log_z": _column("log_z", float, "log z of its partition function Z = kappa^m z (sticky limit)", nullable=True),
    "z_reason": _column(
        "z_reason",
        str,
        "why log_z is missing: singular, hypostatic or hyperstatic",
        nullable=True,
        values=(SINGULAR, HYPOSTATIC, HYPERSTATIC),
    ),
    "eps_power": _column("eps_power", float, "a square well of width eps: Z ~ kappa^m eps^eps_power", nullable=True),
    "log_z_square_well": _column(
        "log_z_square_well", float, "a square well: log of Z's coefficient of kappa^m eps^eps_power", nullable=True
    ),
    "excess": Key(int, "contacts - (3n-6)", expr=_excess),
    "hypostatic": Key(bool, "excess < 0", expr=lambda: _excess() < 0),
    "isostatic": Key(bool, "excess = 0", expr=lambda: _excess() == 0),
    "hyperstatic": Key(bool, "excess > 0", expr=lambda: _excess() > 0),
    "static": Key(
        str, "hypostatic, isostatic or hyperstatic", expr=_static, values=("hypostatic", "isostatic", "hyperstatic")
    ),
    "lattice": _column(
        "lattice",
        str,
        "close-packed lattice: fcc, hcp, both (two layers), random (stacking), 2d, or none",
        nullable=True,
        values=(*LATTICES, "none"),
    ),
    "close_packed": Key(
        bool, "a fragment of a close-packed lattice (lattice is not none)", expr=_lattice_in(*LATTICES)
    ),
    "fcc": Key(bool, "a fragment of fcc (lattice fcc or both)", expr=_lattice_in("fcc", "both")),
    "hcp": Key(bool, "a fragment of hcp (lattice hcp or both)", expr=_lattice_in("hcp", "both")),
    "geometries": Key(int, "clusters with this contact graph (1: its adjacency has one geometry)", expr=_geometries),
    "paths_out": Key(int, "paths from it (followed, by symmetry or retraced), all runs", expr=_paths_out),
    "paths_in": Key(int, "paths from other clusters that reached it, all runs", expr=_paths_in),
    "circular": Key(int, "paths from it that came back to it, every sphere where it was (circles)", expr=_circular),
    "rearranged": Key(int, "paths from it that ended at it with its spheres permuted", expr=_rearranged),
    "reached": Key(
        bool, "some path from another cluster reaches it (false: only a seed)", expr=lambda: _paths_in() > 0
    ),
    "run": Key(int, "in the frontier of run R (run=R, run!=R)", where=_in_run, ops=EQUALITY),
}
ALIASES: dict[str, str] = {"m": "contacts"}


class Term(NamedTuple):
    """One condition: ``key op value``; a value of None means missing (NULL)."""

    key: str
    op: str
    value: Any


_TERM = re.compile(r"^(?:(?P<neg>!|not\s+)\s*)?(?P<key>[A-Za-z_]\w*)\s*(?:(?P<op>[<>=!~]+)\s*(?P<value>.*))?$", re.S)
_BOOLS = {"true": True, "yes": True, "1": True, "false": False, "no": False, "0": False}


def known_keys() -> str:
    return ", ".join(KEYS)


def resolve(name: str) -> tuple[str, Key]:
    """The key's canonical name and descriptor (aliases and case folded)."""
    canonical = ALIASES.get(name.lower(), name.lower())
    if canonical not in KEYS:
        raise SelectionError(f"unknown key {name!r}; known keys: {known_keys()}")
    return canonical, KEYS[canonical]


def parse_value(key: str, text: str) -> Any:
    """``text`` read as a value of ``key``'s type."""
    key, k = resolve(key)
    type_ = k.type
    text = text.strip()
    if type_ is str:
        if len(text) >= 2 and text[0] == text[-1] and text[0] in "'\"":
            text = text[1:-1]
        if k.values is not None and text not in k.values:
            raise SelectionError(f"bad value {text!r} for {key}: expected one of {', '.join(k.values)}")
        return text
    try:
        if type_ is bool:
            return _BOOLS[text.lower()]
        value = type_(text)
    except (KeyError, ValueError):
        kinds = {int: "an integer", float: "a number", bool: "true or false"}
        raise SelectionError(f"bad value {text!r} for {key}: expected {kinds[type_]}") from None
    if type_ is float and not math.isfinite(value):
        raise SelectionError(f"bad value {text!r} for {key}: expected a finite number")
    return value


def parse_term(text: str) -> Term:
    m = _TERM.match(text.strip())
    if not m:
        raise SelectionError(
            f"cannot read {text.strip()!r}: expected key, !key, not key, or key OP value "
            f"(OP one of {' '.join(OPERATORS)})"
        )
    name, op, raw, negated = m["key"], m["op"], m["value"], bool(m["neg"])
    key, k = resolve(name)
    if op is None:
        if k.type is bool:
            return Term(key, "=", not negated)
        if k.nullable:
            return Term(key, "=" if negated else "!=", None)
        raise SelectionError(f"{key} is not a boolean key: write {key}=VALUE or {key}<VALUE etc.")
    if negated:
        raise SelectionError(
            f"cannot negate a comparison in {text.strip()!r}: '!' and 'not' go with a bare key, e.g. !singular"
        )
    if op not in OPERATORS:
        raise SelectionError(f"bad operator {op!r} in {text.strip()!r}: use one of {' '.join(OPERATORS)}")
    if op not in k.allowed:
        raise SelectionError(f"operator {op!r} does not apply to {key}: use one of {' '.join(k.allowed)}")
    if not raw.strip():
        raise SelectionError(f"missing value in {text.strip()!r}")
    return Term(key, op, parse_value(key, raw))


def parse(selection: str | None) -> list[Term]:
    """The terms of ``selection`` (none if it is empty)."""
    if selection is None or not selection.strip():
        return []
    parts = selection.split(",")
    if any(not p.strip() for p in parts):
        raise SelectionError(f"empty term in {selection!r} (two commas in a row, or one at an end?)")
    return [parse_term(p) for p in parts]


_COMPARE = {"=": operator.eq, "<": operator.lt, "<=": operator.le, ">": operator.gt, ">=": operator.ge}


def condition(term: Term) -> ColumnElement:
    """The SQL condition of one term."""
    k = KEYS[term.key]
    if k.where is not None:
        return k.where(term.op, term.value)
    expr = k.expr()
    if k.type is bool:
        return expr if term.value == (term.op == "=") else not_(expr)
    if term.value is None:
        return expr.is_(None) if term.op == "=" else expr.is_not(None)
    if term.op == "!=":
        return expr.is_distinct_from(term.value) if k.nullable else expr != term.value
    return _COMPARE[term.op](expr, term.value)


def where(selection: str | list[Term] | None) -> ColumnElement:
    """The where-clause over :class:`ClusterRow` of a selection (text or terms)."""
    terms = parse(selection) if selection is None or isinstance(selection, str) else selection
    return and_(true(), *(condition(t) for t in terms))


def order_by(sort: str | None) -> list:
    """ORDER BY for ``--sort KEY`` (``-KEY`` descending; ties by id); default n, contacts, id."""
    if not sort:
        return [ClusterRow.n, ClusterRow.contacts, ClusterRow.id]
    name = sort.strip()
    descending = name.startswith("-")
    name = name.lstrip("-").strip()
    name, k = resolve(name)
    if k.expr is None:
        sortable = ", ".join(n for n, v in KEYS.items() if v.expr is not None)
        raise SelectionError(f"cannot sort by {name}; sort keys: {sortable}")
    expr = k.expr()
    return [(expr.desc() if descending else expr.asc()).nulls_last(), ClusterRow.id]


def query(
    selection: str | None = None, sort: str | None = None, limit: int | None = None, n: int | None = None
) -> Select:
    """SELECT the clusters of a selection (and of ``n`` if given), in order."""
    q = (
        select(ClusterRow)
        .options(with_expression(ClusterRow.geometries, _geometries()))
        .where(where(selection))
        .order_by(*order_by(sort))
    )
    if n is not None:
        q = q.where(ClusterRow.n == n)
    return q if limit is None else q.limit(limit)


def describe_keys() -> str:
    """The keys, one a line, for ``--help``."""
    width = max(map(len, KEYS))
    alias = {v: k for k, v in ALIASES.items()}
    lines = []
    for name, k in KEYS.items():
        label = name + (f" ({alias[name]})" if name in alias else "")
        lines.append(f"{label:<{width + 4}} {k.type.__name__:<6}{k.help}")
    return "\n".join(lines)
