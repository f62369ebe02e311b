"""The paper's counts that ship with the package, and a catalogue held against them
(``packings.service.paper``, shown by ``packings stats``)."""

from __future__ import annotations

import pytest

from packings.service import paper


def test_the_counts_the_package_carries_are_the_papers(paper_counts):
    """The package's copy is the tests' own copy of the paper's Tables 1 and 3, number for number."""
    for n, table in paper_counts["clusters_by_contacts"].items():
        assert paper.by_contacts(int(n)) == {int(m): c for m, c in table.items()}
        assert sum(table.values()) == paper_counts["totals"][n]
    for n, m in paper_counts["max_contacts"].items():
        assert paper.max_contacts(int(n)) == m
    assert paper.by_contacts(15) is None and paper.max_contacts(15) == 44
    assert paper.by_contacts(4) is None and paper.max_contacts(20) is None


def test_the_papers_own_counts_are_the_same(paper_counts):
    for n, table in paper_counts["clusters_by_contacts"].items():
        a = paper.against_paper(int(n), {int(m): c for m, c in table.items()})
        assert a["same"] is True and a["fewer"] == a["more"] == {}
        assert a["by_contacts"] == table and a["total"] == paper_counts["totals"][n]
        assert paper.verdict(int(n), a, complete=True) == (
            f"as the paper at every number of contacts: {paper_counts['totals'][n]} ({paper.SOURCE}, Table 1)"
        )


def test_a_missing_and_an_extra_cluster_are_each_named():
    """n = 11 with the cluster no path reaches missing and one junk 28-contact cluster: both said."""
    found = {25: 2, 26: 17, 27: 1618, 28: 21, 29: 1}
    a = paper.against_paper(11, found)
    assert a["same"] is False and a["fewer"] == {"26": [17, 18]} and a["more"] == {"28": [21, 20]}
    text = paper.verdict(11, a, complete=True)
    assert "MORE THAN THE PAPER: 21 with 28 contacts (the paper 20)" in text
    assert "fewer than the paper: 17 with 26 contacts (the paper 18)" in text and "partial" not in text
    # contacts the paper does not have at all, and contacts the catalogue has none of
    a = paper.against_paper(10, {24: 259, 25: 3, 26: 1})
    assert a["fewer"] == {"23": [0, 1]} and a["more"] == {"26": [1, 0]}


def test_a_partial_run_says_so():
    a = paper.against_paper(12, {30: 5000, 31: 100})
    assert set(a["fewer"]) == {"28", "29", "30", "31", "32", "33"} and a["more"] == {}
    assert paper.verdict(12, a, complete=False).endswith("(partial: no full run is complete)")


def test_a_restricted_run_is_compared_from_its_fewest_contacts_up():
    a = paper.against_paper(14, {39: 79, 40: 4}, min_contacts=39)
    assert a["same"] is True and a["by_contacts"] == {"39": 79, "40": 4} and a["total"] == 83
    assert paper.verdict(14, a, complete=False, min_contacts=39) == (
        f"as the paper at every number of contacts, with at least 39 contacts: 83 ({paper.SOURCE}, Table 1)"
    )
    a = paper.against_paper(14, {38: 800, 39: 79, 40: 4}, min_contacts=38)
    assert a["fewer"] == {"38": [800, 878]} and a["more"] == {}
    assert "misses the clusters reached only through fewer contacts" in paper.verdict(14, a, False, 38)


@pytest.mark.parametrize("found, more", [({43: 55, 44: 6}, {}), ({44: 6, 45: 1}, {"45": [1, 0]})])
def test_beyond_the_papers_table_only_its_maximum_is_held_against(found, more):
    """n = 15: the paper gives M(n) = 44 and no table; a cluster with more contacts is flagged."""
    a = paper.against_paper(15, found, min_contacts=43)
    assert a["by_contacts"] is None and a["same"] is None and a["max_contacts"] == 44 and a["more"] == more
    text = paper.verdict(15, a, complete=False, min_contacts=43)
    assert (
        text.startswith("MORE CONTACTS THAN THE PAPER'S MAXIMUM M(15) = 44: 1 with 45")
        if more
        else "M(n) = 44" in text and "no cluster here has more" in text
    )


def test_no_comparison_where_the_paper_says_nothing():
    assert paper.against_paper(4, {6: 1}) is None and paper.verdict(4, None, True) is None
    assert paper.against_paper(25, {69: 1}) is None
