"""The counts the paper published, to hold a catalogue against: ``packings stats``.

Holmes-Cerfon (SIAM Review 58(2), 2016) gives, in Table 1, the number of rigid clusters of n = 5 … 14
spheres by number of contacts, and, in Table 3, the largest number of contacts M(n) for n up to 19.
They ship with the package (``paper_counts.json``) and are used only to compare: nothing the
enumeration does reads them.  A catalogue that differs from them is a finding, shown as such
(:func:`against_paper`), never adjusted.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Mapping
from importlib import resources

#: where the counts come from
SOURCE = "Holmes-Cerfon, SIAM Review 58(2) 2016"


@functools.cache
def _table() -> dict:
    return json.loads(resources.files("packings.service").joinpath("paper_counts.json").read_text(encoding="utf-8"))


def by_contacts(n: int) -> dict[int, int] | None:
    """The paper's number of rigid clusters of n spheres by number of contacts (Table 1), or None
    where it gives none (n < 5 or n > 14)."""
    table = _table()["clusters_by_contacts"].get(str(n))
    return None if table is None else {int(m): int(c) for m, c in table.items()}


def max_contacts(n: int) -> int | None:
    """The paper's largest number of contacts M(n) of a rigid cluster of n spheres, or None where it
    gives none."""
    m = _table()["max_contacts"].get(str(n))
    return None if m is None else int(m)


def paper_tables(ns, restricted: Mapping[int, int] | None = None) -> dict[int, dict[int, int]]:
    """{n: the paper's number of rigid clusters of n by number of contacts} for each n of ``ns`` that its
    Table 1 covers; for an n of ``restricted`` ({n: the fewest contacts kept}), from that many contacts up."""
    restricted = restricted or {}
    out = {}
    for n in ns:
        table = by_contacts(int(n))
        if table is not None:
            out[int(n)] = {m: c for m, c in table.items() if m >= restricted.get(int(n), 0)}
    return out


def paper_totals(ns, restricted: Mapping[int, int] | None = None) -> dict[int, int]:
    """{n: the paper's number of rigid clusters of n} (:func:`paper_tables`, summed)."""
    return {n: sum(t.values()) for n, t in paper_tables(ns, restricted).items()}


def against_paper(n: int, found: Mapping[int, int], min_contacts: int | None = None) -> dict | None:
    """The catalogue's counts of n by number of contacts (``found``) held against the paper's, or None
    where the paper gives neither a table nor M(n) for n.

    With ``min_contacts`` (a run restricted by ``--min-contacts``) only the numbers of contacts from
    ``min_contacts`` up are compared: the clusters with fewer were never kept.  The dict has
    ``by_contacts`` (the paper's counts compared, a string of the contacts to a count; None where the
    paper has no table for n), ``total`` (their sum, or None), ``max_contacts`` (M(n), or None), ``fewer``
    and ``more`` (a string of the contacts to ``[found, paper]`` where the catalogue has fewer or more
    than the paper; where the paper has no table, ``more`` lists the clusters with more contacts than
    M(n)) and ``same`` (True where the paper has a table and nothing differs, else False; None without a
    table)."""
    paper, top = paper_tables([n], {n: min_contacts or 0}).get(n), max_contacts(n)
    if paper is None and top is None:
        return None
    found = {int(m): int(c) for m, c in found.items() if int(m) >= (min_contacts or 0)}
    fewer: dict[str, list[int]] = {}
    more: dict[str, list[int]] = {}
    if paper is not None:
        for m in sorted(set(paper) | set(found)):
            f, p = found.get(m, 0), paper.get(m, 0)
            if f != p:
                (fewer if f < p else more)[str(m)] = [f, p]
    else:
        more = {str(m): [c, 0] for m, c in sorted(found.items()) if m > top and c}
    return {
        "source": SOURCE,
        "by_contacts": None if paper is None else {str(m): c for m, c in sorted(paper.items())},
        "total": None if paper is None else sum(paper.values()),
        "max_contacts": top,
        "fewer": fewer,
        "more": more,
        "same": None if paper is None else not fewer and not more,
    }


def _listed(d: Mapping[str, list[int]]) -> str:
    return ", ".join(f"{f} with {m} contacts (the paper {p})" for m, (f, p) in d.items())


def verdict(n: int, against: dict | None, complete: bool, min_contacts: int | None = None) -> str | None:
    """One line on ``against`` (:func:`against_paper`) for ``packings stats`` and ``enumerate``: the same as
    the paper, or where it differs; None where the paper gives nothing for n.  ``complete``: whether a
    full run of n is complete (else a full catalogue's counts are partial); ``min_contacts``: the counts
    are those of runs restricted by ``--min-contacts``."""
    if against is None:
        return None
    more, fewer = against["more"], against["fewer"]
    if against["by_contacts"] is None:
        top = against["max_contacts"]
        if more:
            return f"MORE CONTACTS THAN THE PAPER'S MAXIMUM M({n}) = {top}: {_listed(more)}; see `packings audit`"
        return (
            f"the paper's largest number of contacts for n = {n} is M(n) = {top} ({SOURCE}, Table 3); "
            "no cluster here has more"
        )
    scope = "" if min_contacts is None else f", with at least {min_contacts} contacts"
    if against["same"]:
        return f"as the paper at every number of contacts{scope}: {against['total']} ({SOURCE}, Table 1)"
    parts = []
    if more:
        parts.append(f"MORE THAN THE PAPER: {_listed(more)}; see `packings audit`")
    if fewer:
        why = (
            " (a run restricted by --min-contacts misses the clusters reached only through fewer contacts)"
            if min_contacts is not None
            else ""
            if complete
            else " (partial: no full run is complete)"
        )
        parts.append(f"fewer than the paper: {_listed(fewer)}{why}")
    return f"against the paper ({SOURCE}, Table 1){scope}: " + "; ".join(parts)
