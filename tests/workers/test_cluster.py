"""Cluster's contacts: one normal form, however they are given."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from packings.workers.cluster import Cluster, contacts_from_distances, normalise_contacts, upper_pairs

SETTINGS = settings(derandomize=True, max_examples=60, deadline=None, database=None)


def _slow(contacts) -> tuple:
    """The normal form by its definition: (min, max) of each, as Python ints, no repeats, sorted."""
    return tuple(sorted({(min(int(a), int(b)), max(int(a), int(b))) for a, b in contacts}))


pair_lists = st.lists(st.tuples(st.integers(0, 12), st.integers(0, 12)).filter(lambda p: p[0] != p[1]), max_size=40)


@SETTINGS
@given(pair_lists, st.sampled_from(["tuple", "list", "lists", "array", "numpy ints"]))
def test_contacts_are_normalised_however_given(pairs, form) -> None:
    given_ = {
        "tuple": tuple(pairs),
        "list": list(pairs),
        "lists": tuple(list(p) for p in pairs),
        "array": np.array(pairs, dtype=np.int64).reshape(-1, 2),
        "numpy ints": tuple((np.int64(a), np.int64(b)) for a, b in pairs),
    }[form]
    out = normalise_contacts(given_)
    assert out == _slow(pairs)
    assert all(type(i) is int and type(j) is int for i, j in out)
    assert normalise_contacts(out) is out  # already normal: kept as it is


@SETTINGS
@given(st.integers(2, 13), st.data())
def test_an_endpoint_s_contacts_are_kept_as_they_are(n, data) -> None:
    """Contacts read off distances are already normal: the cluster keeps that very tuple."""
    d = np.array(data.draw(st.lists(st.floats(0.9, 1.5), min_size=n * (n - 1) // 2, max_size=n * (n - 1) // 2)))
    contacts = contacts_from_distances(upper_pairs(n), d, 1e-3)
    c = Cluster(np.zeros((n, 3)), contacts)
    assert c.contacts is contacts
    assert contacts == _slow(contacts)


def test_equal_tuples_that_are_not_the_shared_pairs_are_normalised_all_the_same() -> None:
    fresh = tuple((i, i + 1) for i in range(5))  # new tuples, equal to the shared ones
    assert normalise_contacts(fresh) == fresh
    assert normalise_contacts(((1, 2), (0, 1))) == ((0, 1), (1, 2))  # out of order
    assert normalise_contacts(((0, 1), (0, 1))) == ((0, 1),)  # repeated
    assert normalise_contacts(((2, 1),)) == ((1, 2),)  # reversed
