"""The packed attempts of an expansion (packings.service.paths_codec): what is packed is read back."""

from __future__ import annotations

import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from packings.service.paths_codec import OUTCOMES, Attempt, CodecError, pack, summary, unpack
from packings.workers import outcomes


@st.composite
def attempts(draw, n=None):
    """A cluster's n and a list of its attempts: any pairs, outcomes, targets (few distinct), steps and
    labels (a permutation of n, or none)."""
    n = draw(st.integers(2, 40)) if n is None else n
    pairs = st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)), max_size=6).map(
        lambda ps: tuple(sorted({(min(i, j), max(i, j)) for i, j in ps if i != j}))
    )
    targets = draw(st.lists(st.integers(1, 2**40), min_size=1, max_size=5))
    one = st.builds(
        Attempt,
        pairs,
        st.sampled_from((-1, 0, 1)),
        st.sampled_from(OUTCOMES),
        st.one_of(st.none(), st.sampled_from(targets)),
        st.integers(0, 70_000),
        pairs,
        st.one_of(st.none(), st.permutations(range(n)).map(tuple)),
    )
    return n, draw(st.lists(one, max_size=40))


@settings(max_examples=200, deadline=None)
@given(attempts())
def test_packed_attempts_read_back_as_they_were(case):
    n, given_attempts = case
    p = unpack(pack(n, given_attempts))
    assert len(p) == len(given_attempts) and p.n == n
    assert list(p) == given_attempts
    assert [unpack(pack(n, given_attempts)).one(k) for k in range(len(p))] == given_attempts  # one alone, as made
    for t in {a.target for a in given_attempts} - {None}:
        assert [given_attempts[k] for k in p.to(t)] == [a for a in given_attempts if a.target == t]
        assert [given_attempts[k] for k in p.to(t, labelled=True)] == [
            a for a in given_attempts if a.target == t and a.labels is not None
        ]
    assert len(p.to(0)) == 0  # a cluster no attempt reached


@settings(max_examples=100, deadline=None)
@given(attempts())
def test_the_summary_counts_what_the_attempts_hold(case):
    _, given_attempts = case
    sm = summary(given_attempts)
    assert sm.attempts == len(given_attempts)
    assert sm.paths == sum(a.direction != 0 for a in given_attempts)
    assert sm.circular == sum(a.direction != 0 and a.outcome == outcomes.CIRCULAR for a in given_attempts)
    for t, (paths, labelled) in sm.edges.items():
        assert paths == sum(a.target == t for a in given_attempts)
        assert labelled == sum(a.target == t and a.labels is not None for a in given_attempts)
    assert set(sm.edges) == {a.target for a in given_attempts} - {None}


def test_wide_columns_take_wider_types():
    """Steps beyond 65,535, more than 255 pairs in one attempt and more than 255 distinct targets are
    packed in wider columns and read back."""
    n = 40
    many = tuple((i, j) for i in range(n) for j in range(i + 1, n))[:300]
    given_attempts = [Attempt(many, 1, outcomes.RIGID, 1000 + k, 100_000 + k, many[:3]) for k in range(300)]
    assert list(unpack(pack(n, given_attempts))) == given_attempts


def test_the_outcomes_are_every_name_an_attempt_may_have_once():
    """OUTCOMES numbers every outcome of packings.workers.outcomes (append only: a stored attempt's number
    keeps its meaning), each once."""
    names = {v for k, v in vars(outcomes).items() if k.isupper() and isinstance(v, str)}
    assert set(OUTCOMES) == names and len(OUTCOMES) == len(names)
    assert OUTCOMES[:3] == (outcomes.RIGID, outcomes.FLOPPY, outcomes.UNDECIDED_END)


@pytest.mark.parametrize(
    "n, attempt, words",
    [
        (8, Attempt(((0, 1),), 1, "vanished", None, 0, ()), "unknown outcome"),
        (8, Attempt(((0, 8),), 1, outcomes.RIGID, None, 0, ()), "outside"),
        (8, Attempt(((0, 1),), 1, outcomes.RIGID, 5, 0, (), (0, 1, 2)), "labels of other than 8 spheres"),
        (256, Attempt(((0, 1),), 1, outcomes.RIGID, None, 0, ()), "256 spheres"),
    ],
)
def test_what_cannot_be_packed_is_refused(n, attempt, words):
    with pytest.raises(CodecError, match=words):
        pack(n, [attempt])


def test_data_that_is_not_packed_attempts_is_refused():
    good = pack(8, [Attempt(((0, 1),), 1, outcomes.RIGID, 3, 5, ((2, 3),))])
    raw = zlib.decompress(good[1:])
    for bad, words in [
        (b"", "unknown version"),
        (bytes([2]) + good[1:], "unknown version"),
        (good[:1] + b"xyz", "do not decompress"),
        (good[:1] + zlib.compress(raw[:-3]), "cut short"),
        (good[:1] + zlib.compress(raw + b"\0"), "disagree"),
        (good[:1] + zlib.compress(raw[: 32 + 8 + 1] + bytes([250]) + raw[32 + 8 + 2 :]), "outcome"),
    ]:
        with pytest.raises(CodecError, match=words):
            unpack(bad)


def test_an_empty_expansion_packs():
    p = unpack(pack(5, []))
    assert len(p) == 0 and list(p) == [] and len(p.to(1)) == 0
    assert np.array_equal(p.broken_at, [0])
