"""expand(): one cluster's paths; invariance under rotation, reflection and relabelling."""

from collections import Counter

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from packings.workers.cluster import Cluster
from packings.workers.expand import CIRCULAR, NOT_1D, REARRANGED, break_sizes, expand, same_labelled
from packings.workers.identity import certificate_hex
from packings.workers.params import Params
from packings.workers.paths import RIGID
from packings.workers.seeds import seed_cluster
from tests.helpers import catalogue, congruent_copy, random_orthogonal, relabel

P = Params()


def _endpoint_keys(ex):
    return Counter((e.outcome, certificate_hex(e.cluster) if e.cluster is not None else None) for e in ex.endpoints)


def test_break_sizes():
    assert list(break_sizes(24, 24, P)) == [1]  # n = 10, regular isostatic
    assert list(break_sizes(25, 24, P)) == [1, 2]  # regular, one stress
    assert list(break_sizes(24, 23, P)) == [1, 2]  # singular: one flex held by one stress
    assert list(break_sizes(23, 22, P)) == [1, 2]  # hypostatic singular
    assert list(break_sizes(20, 24, P)) == [1]  # never fewer than single breaks
    assert list(break_sizes(40, 36, P)) == [1, 2, 3, 4, 5]  # no cap by default: n = 14's 40-contact clusters
    assert list(break_sizes(33, 30, P)) == [1, 2, 3, 4]  # n = 12's 33-contact cluster
    assert list(break_sizes(40, 36, P.with_(max_break=3))) == [1, 2, 3]  # a restricted run's cap


def test_expand_octahedron_reaches_only_itself_and_the_polytetrahedron():
    seed = seed_cluster(6)
    ex = expand(seed, P)
    assert ex.subsets_tried == 12
    ends = {certificate_hex(e.cluster) for e in ex.endpoints if e.outcome in (RIGID, CIRCULAR, REARRANGED)}
    assert len(ends) == 2  # n = 6 has two rigid clusters
    for e in ex.endpoints:
        if e.cluster is not None:
            assert e.cluster.m == 12
            assert e.cluster.min_distance() > 1 - 1e-5
            assert len(e.broken) == 1 and e.direction in (1, -1)


def _as_values(ex) -> list[tuple]:
    """An expansion's attempts as plain values, to the last bit: the subset, the direction, the outcome, the
    contacts formed, whether an image, and the exact coordinates and contacts reached."""
    return [
        (e.broken, e.direction, e.outcome, e.new_contacts, e.image)
        + (() if e.cluster is None else (e.cluster.coords.tobytes(), e.cluster.contacts))
        for e in ex.endpoints
    ]


def test_expand_is_a_pure_function_of_its_inputs(monkeypatch):
    """What expand gives depends on the cluster and the parameters alone: not on the caches the process has
    filled (automorphism groups and keys by certificate, canonical forms by cluster) nor on what it expanded
    before, and a later expansion leaves an earlier one's result as it was."""
    from packings.workers import identity

    c = seed_cluster(7)  # symmetric: its images go through the cached automorphism groups
    monkeypatch.setattr(identity, "_GROUPS", {})
    monkeypatch.setattr(identity, "_KEYS", {})
    cold = expand(Cluster(c.coords.copy(), c.contacts), P)  # a cluster of its own: no canonical form cached
    seen = _as_values(cold)
    assert any(e.image for e in cold.endpoints) and any(e.outcome == RIGID for e in cold.endpoints)
    for other in catalogue(7).clusters:  # the caches filled with other clusters' forms
        expand(other, P)
    assert _as_values(expand(c, P)) == seen
    assert _as_values(cold) == seen


def _same_distinct_clusters(a, b) -> bool:
    return Counter(certificate_hex(a.endpoints[i].cluster) for i in a.distinct()) == Counter(
        certificate_hex(b.endpoints[i].cluster) for i in b.distinct()
    )


@settings(max_examples=6, deadline=None, derandomize=True)
@given(st.integers(0, 2**31 - 1), st.booleans())
def test_expand_invariant_under_rotation_reflection_relabelling(seed, reflect):
    c = seed_cluster(7)
    a, b = expand(c, P), expand(congruent_copy(c, seed, reflect)[0], P)
    assert _endpoint_keys(a) == _endpoint_keys(b)
    assert _same_distinct_clusters(a, b)  # the same distinct clusters among the endpoints


def test_the_endpoints_that_are_one_cluster_point_at_the_first_of_them():
    """Many paths from one cluster end at the same cluster: expand tells them apart once, and the
    write-back compares each distinct one only with the stored clusters."""
    from packings.workers.identity import same_geometry

    c = max(catalogue(9).clusters, key=lambda c: c.m)  # a hyperstatic cluster: pairs broken, many paths
    ex = expand(c, P)
    rigid = [i for i, e in enumerate(ex.endpoints) if e.outcome == RIGID]
    first = ex.distinct()
    assert len(rigid) > len(first) > 1
    assert len(ex.same_as) == len(ex.endpoints)
    for i, j in enumerate(ex.same_as):
        if i not in rigid:
            assert j is None
            continue
        assert (
            j <= i and ex.same_as[j] == j and same_geometry(ex.endpoints[i].cluster, ex.endpoints[j].cluster, P.tol_d)
        )
    for k, i in enumerate(first):
        assert not any(same_geometry(ex.endpoints[i].cluster, ex.endpoints[j].cluster, P.tol_d) for j in first[:k])


def test_an_expansion_holds_each_contact_pair_once_and_canonical_forms_of_distinct_endpoints_only():
    """What keeps a worker's memory down when one expansion has hundreds of thousands of attempts: every
    broken subset, endpoint contact and formed contact is made of the one shared tuple of its pair, an
    endpoint has no per-instance dict, and only the distinct rigid endpoints keep their canonical forms
    (the write-back compares only those again), with the arrivals of a regular cluster, a few dozen
    (the write-back relabels them onto their targets: Expansion.retraceable)."""
    from packings.workers.cluster import pair
    from packings.workers.identity import _CANONICAL

    c = max(catalogue(9).clusters, key=lambda c: c.m)
    assert Cluster(c.coords.copy(), [(j, i) for i, j in c.contacts]).contacts[0] is c.contacts[0]
    ex = expand(c, P)
    own = {id(p) for p in c.contacts}
    assert all(id(p) in own for e in ex.endpoints for p in e.broken)
    held = [p for e in ex.endpoints if e.cluster is not None for p in e.cluster.contacts + e.new_contacts]
    assert held and all(p is pair(*p) for p in held)
    assert not hasattr(ex.endpoints[0], "__dict__")
    rigid = [i for i, e in enumerate(ex.endpoints) if e.outcome == RIGID]
    assert len(rigid) > len(ex.distinct())
    # an image's canonical form is never computed
    keep = [ex.same_as[i] == i or (ex.retraceable(i) and not ex.endpoints[i].image) for i in rigid]
    assert all((ex.endpoints[i].cluster in _CANONICAL) == k for i, k in zip(rigid, keep))


def _symmetric_clusters():
    """Clusters with symmetries: the seed of n = 6 (4), the n = 10 hyperstatic cluster of the test data (4),
    the n = 9 clusters with the most symmetries."""
    import json
    from pathlib import Path

    from packings.workers.identity import symmetries

    d = json.loads((Path(__file__).parents[1] / "data" / "clusters_n10.json").read_text())
    nine = sorted(catalogue(9).clusters, key=lambda c: -len(symmetries(c, P.tol_d)))[:2]
    return [seed_cluster(6), Cluster.from_dict(d["n10_m25_first-order"])] + nine


def _by_subset(ex):
    """Each subset's attempts: (outcome, contacts formed, certificate of the cluster reached), sorted."""
    out = {}
    for e in ex.endpoints:
        cert = certificate_hex(e.cluster) if e.cluster is not None else None
        out.setdefault(e.broken, []).append((e.outcome, e.new_contacts, cert))
    return {k: sorted(v, key=repr) for k, v in out.items()}


def test_a_symmetric_cluster_follows_one_path_of_each_congruent_set_and_reaches_what_every_path_does():
    """A subset that a symmetry of the cluster takes an earlier one to is not followed again: its attempts are
    the earlier subset's relabelled, and they are what following its own paths gives: the same outcomes, the
    same contacts formed, the same clusters reached (certificate and geometry), subset by subset."""
    from packings.workers.identity import same_geometry, symmetries

    for c in _symmetric_clusters():
        assert len(symmetries(c, P.tol_d)) > 1
        a, every = expand(c, P), expand(c, P, symmetric=False)
        assert [e.broken for e in a.endpoints] == [e.broken for e in every.endpoints]
        assert not any(e.image for e in every.endpoints) and every.paths_by_symmetry == 0
        assert a.paths_by_symmetry > 0 and a.paths_followed + a.paths_by_symmetry == every.paths_followed
        assert _by_subset(a) == _by_subset(every)
        reached = {}
        for e in every.endpoints:
            if e.outcome == RIGID:
                reached.setdefault(e.broken, []).append(e.cluster)
        for e in a.endpoints:
            if e.outcome == RIGID:
                assert any(same_geometry(e.cluster, f, P.tol_d) for f in reached[e.broken])
        assert _same_distinct_clusters(a, every)


def test_an_image_is_an_attempt_made_relabelled_by_a_symmetry():
    """Each image's endpoint is its own subset's: the contacts broken are not among the endpoint's, the contacts
    formed are, and it is the same cluster (a relabelled copy) as an attempt made with the same outcome."""
    from packings.workers.identity import same_geometry

    c = seed_cluster(6)  # three tetrahedra around an edge: four symmetries, five orbits of the 12 contacts
    ex = expand(c, P)
    made = [e for e in ex.endpoints if not e.image]
    images = [e for e in ex.endpoints if e.image]
    assert len({e.broken for e in made}) == 5 and len(images) == 7
    for e in images:
        assert not set(e.broken) & set(e.cluster.contacts) and set(e.new_contacts) <= set(e.cluster.contacts)
        assert any(same_geometry(e.cluster, f.cluster, P.tol_d) for f in made if f.outcome == e.outcome)
        assert e.cluster.min_distance() > 1 - P.tol_a


def test_hyperstatic_cluster_breaks_pairs():
    import json
    from pathlib import Path

    d = json.loads((Path(__file__).parents[1] / "data" / "clusters_n10.json").read_text())
    c = Cluster.from_dict(d["n10_m25_first-order"])
    ex = expand(c, P)
    sizes = Counter(len(e.broken) for e in ex.endpoints if e.outcome in (RIGID, CIRCULAR, REARRANGED))
    assert sizes[2] > 0
    singles = [e for e in ex.endpoints if len(e.broken) == 1]
    assert any(e.outcome == NOT_1D and e.dim == 0 for e in singles)


def test_every_path_of_the_bipyramid_reaches_another_isomer_of_it_not_a_circle():
    """n = 5 has one rigid cluster: each of its 9 contacts opens a path to the bipyramid with its spheres
    permuted (a rearrangement), never back to every sphere's place (a circle)."""
    ex = expand(seed_cluster(5), P)
    assert ex.subsets_tried == 9
    assert set(ex.outcomes()) == {REARRANGED}
    assert ex.rigid_endpoints() == []


def test_no_circle_below_ten_spheres_and_those_of_ten_widen():
    """The paper finds its first circle at n = 11.  Below n = 10 none; n = 10's are all paths of its singular
    clusters whose set is two-dimensional from the first step on (docs/method.md); every other path that
    comes back to its start's contact graph and shape ends at another isomer of it."""
    for n in (6, 7, 8, 9):
        assert catalogue(n).outcomes[CIRCULAR] == 0 and catalogue(n).outcomes[REARRANGED] > 0
    ten = catalogue(10)
    circles = [
        e for c in ten.clusters if c.m == 24 and _singular(c) for e in expand(c, P).endpoints if e.outcome == CIRCULAR
    ]
    assert len(circles) == ten.outcomes[CIRCULAR] > 0
    assert all(e.first_step_dim == 2 and e.new_contacts == e.broken for e in circles)


def _singular(c: Cluster) -> bool:
    from packings.workers.free_energy import SINGULAR, free_energy

    return free_energy(c).kind == SINGULAR


@settings(derandomize=True, max_examples=20, deadline=None, database=None)
@given(seed=st.integers(0, 2**32 - 1), which=st.integers(0, 4))
def test_same_labelled_is_the_same_configuration_up_to_a_rotation_only(seed, which):
    """A rotated, translated copy with every label kept is the same labelled configuration; its mirror image
    is not (no cluster here is planar).  Relabelled by one of its symmetries it is the same configuration
    exactly when the symmetry is a rotation: as many as its symmetry number σ."""
    from packings.workers.free_energy import symmetry_numbers
    from packings.workers.identity import symmetries

    c = catalogue(7).clusters[which]
    rng = np.random.default_rng(seed)
    moved = c.coords @ random_orthogonal(rng, False).T + rng.standard_normal(3)
    assert same_labelled(c, Cluster(moved, c.contacts), P.tol_d)
    mirrored = c.coords @ random_orthogonal(rng, True).T
    assert not same_labelled(c, Cluster(mirrored, c.contacts), P.tol_d)
    proper = sum(same_labelled(c, relabel(c, t), P.tol_d) for t in symmetries(c, P.tol_d))
    assert proper == symmetry_numbers(c, P.tol_d)[0]


def test_rigid_endpoints_are_exact_and_record_how_they_were_reached():
    c = seed_cluster(8)
    ex = expand(c, P)
    ends = ex.rigid_endpoints()
    assert ends
    for e in ends:
        x = e.cluster.coords
        for i, j in e.cluster.contacts:
            assert abs(np.linalg.norm(x[i] - x[j]) - 1) < 1e-12
        assert e.cluster.min_distance() > 1 - 1e-12
        assert e.new_contacts and set(e.new_contacts) <= set(e.cluster.contacts)
        assert e.rigidity.rigid and e.steps > 0


def test_paths_that_widen_after_the_first_step_stop_only_when_asked():
    """Pair breaks of a singular cluster: some paths are one-dimensional at the start and two-dimensional
    after the first step (a thin set around a singular path).  the paper's rule stops them; otherwise they
    go on, and the widening is recorded."""
    import json
    from pathlib import Path

    from packings.workers.paths import DIMENSION_CHANGED

    d = json.loads((Path(__file__).parents[1] / "data" / "clusters_n10.json").read_text())
    c = Cluster.from_dict(d["n10_m24_prestress"])
    strict = expand(c, P.with_(stop_on_dimension_change=True))
    lenient = expand(c, P.with_(stop_on_dimension_change=False))
    stopped = {
        (e.broken, e.direction) for e in strict.endpoints if e.outcome == DIMENSION_CHANGED and e.first_step_dim == 2
    }
    assert stopped
    went_on = {(e.broken, e.direction): e for e in lenient.endpoints if (e.broken, e.direction) in stopped}
    assert all(e.first_step_dim == 2 and e.outcome != DIMENSION_CHANGED for e in went_on.values())
    assert lenient.widened_paths == len(went_on) > 0
    assert strict.widened_paths == 0
    # every cluster kept either way is rigid: going on cannot add a false cluster
    for e in lenient.rigid_endpoints():
        assert e.rigidity.rigid


def test_an_endpoint_satisfies_every_contact_it_is_said_to_have():
    """Two path endpoints of one n = 12 contact graph, each with a pair within tol_a of touching that
    was not projected onto (stored before as two of 74 distinct "rigid" clusters): the endpoint is
    projected with every contact, so both hold all of them to the Newton tolerance and are one cluster.
    (It fails without the re-projection in packings.workers.paths._endpoint.)"""
    import json
    from pathlib import Path

    from packings.workers import kernels
    from packings.workers.cluster import Cluster
    from packings.workers.identity import same_geometry
    from packings.workers.params import DEFAULT
    from packings.workers.paths import close_pairs, endpoint_rigidity
    from packings.workers.rigidity import contact_triangle

    data = json.loads((Path(__file__).parents[1] / "data" / "n12_near_miss.json").read_text())
    ends = []
    for m in data["endpoints"]:
        c = Cluster(np.array(m["coords"]), tuple(map(tuple, m["contacts"])))
        edges = c.edges()
        near = np.array([m["near_pair"]], dtype=np.int64)
        keep = np.array([e for e in edges.tolist() if e != m["near_pair"]], dtype=np.int64)
        assert len(keep) == len(edges) - 1 == 30
        assert abs(kernels.residual(c.coords.ravel(), near)[0]) ** 2 > DEFAULT.tol  # as stored: not a contact to tol
        tri = contact_triangle(keep)
        free = kernels.free_coordinates(c.n, tri)
        xe, contacts = close_pairs(kernels.to_frame(c.coords, tri).ravel(), keep, near, free, DEFAULT)
        # projected onto every contact, the point moves onto the cluster the path passed by, which may
        # bring further pairs into contact: those are projected onto too
        assert endpoint_rigidity(xe, contacts, free, DEFAULT).rigid and set(map(tuple, m["contacts"])) <= set(contacts)
        f = kernels.residual(xe, np.array(contacts, dtype=np.int64))
        assert float(f @ f) < DEFAULT.tol
        ends.append(Cluster(xe.reshape(-1, 3), contacts))
    assert not same_geometry(
        *(Cluster(np.array(m["coords"]), tuple(map(tuple, m["contacts"]))) for m in data["endpoints"]), DEFAULT.tol_d
    )  # stored: two clusters
    assert same_geometry(ends[0], ends[1], DEFAULT.tol_d)  # now: one


def test_every_path_starts_in_the_frame_of_the_first_triangle_of_what_is_left():
    """_attempts reuses the cluster's own triangle unless a broken contact is a side of it: every path
    start is in the frame of contact_triangle(what is left), for clusters whose own triangle is broken
    and whose is not, in subsets of one, two and three contacts."""
    import json
    from pathlib import Path

    from packings.workers import kernels
    from packings.workers.expand import PathStart, _attempts
    from packings.workers.rigidity import contact_triangle

    fixtures = json.loads((Path(__file__).parents[1] / "data" / "clusters_n10.json").read_text())
    reused = changed = 0
    for c in [Cluster.from_dict(d) for d in fixtures.values()] + [seed_cluster(9)]:
        own = contact_triangle(c.edges())
        for a in _attempts(c, P):
            if isinstance(a, PathStart):
                tri = contact_triangle(a.keep)
                assert np.array_equal(a.x, kernels.to_frame(c.coords, tri).ravel())
                assert np.array_equal(a.free, kernels.free_coordinates(c.n, tri))
                reused += tri == own
                changed += tri != own
    assert reused > 0 and changed > 0


def test_a_path_between_regular_clusters_is_retraced_by_the_path_back():
    """The path from A that breaks contact c and ends at a regular B by forming c' is the curve that B's
    path breaking c' follows back: it ends at A, forming c (docs/method.md; ``python -m benchmarks retrace``
    counts them in a stored run)."""
    import json
    from pathlib import Path

    from packings.workers.expand import cluster_rank
    from packings.workers.identity import same_geometry

    fixtures = json.loads((Path(__file__).parents[1] / "data" / "clusters_n10.json").read_text())
    retraced = 0
    for a in (seed_cluster(9), Cluster.from_dict(fixtures["n10_m24_first-order"])):
        regular = 3 * a.n - 6
        for e in expand(a, P).rigid_endpoints():
            b = e.cluster
            if len(e.broken) != 1 or len(e.new_contacts) != 1 or b.m != regular or cluster_rank(b, P) != regular:
                continue
            [back] = [f for f in expand(b, P).endpoints if f.broken == e.new_contacts and f.direction != 0]
            assert back.outcome == RIGID and back.new_contacts == e.broken
            assert same_geometry(back.cluster, a, P.tol_d)
            retraced += 1
    assert retraced >= 20


def _moved(c: Cluster, rng) -> Cluster:
    """``c`` rotated, reflected and relabelled: as a run may have stored it."""
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    p = rng.permutation(c.n)  # new sphere k is old sphere p[k]
    inv = np.argsort(p)
    return Cluster(
        (c.coords @ q.T + 1.0)[p], tuple(sorted(tuple(sorted((int(inv[i]), int(inv[j])))) for i, j in c.contacts))
    )


def test_a_cluster_takes_the_paths_that_arrived_from_the_end_they_arrived_at():
    """expand(B, arrivals=...) with the paths that came from first-order rigid clusters A to a first-order
    rigid B (relabelled onto B as stored by identity.alignment) follows none of the paths back where B's
    break of the contacts formed leaves a smooth curve, and gives each the attempt that following it gives:
    the same direction, outcome rigid at A, the same contacts formed, and A's spheres where the path back's
    endpoint puts them; every other attempt is unchanged.  The clusters A: regular ones of n = 9 and 10, a
    hyperstatic one of n = 10 (its paths break two or more contacts and form one at regular clusters B), and
    a regular one that it reaches (whose paths to it form two contacts at the hyperstatic B).  Paths between
    two hyperstatic clusters are not taken from the other end."""
    import json
    from pathlib import Path

    from packings.workers import kernels
    from packings.workers.expand import arrivals
    from packings.workers.identity import alignment

    fixtures = json.loads((Path(__file__).parents[1] / "data" / "clusters_n10.json").read_text())
    hyper = Cluster.from_dict(fixtures["n10_m25_first-order"])
    from_hyper = expand(hyper, P)
    back = next(e.cluster for i, e in enumerate(from_hyper.endpoints) if from_hyper.retraceable(i))
    # a path between two hyperstatic clusters is followed from both ends: its endpoint gets no labels
    between = [
        i for i, e in enumerate(from_hyper.endpoints) if e.outcome == RIGID and e.cluster.m > 3 * e.cluster.n - 6
    ]
    assert between and not any(from_hyper.retraceable(i) for i in between)
    rng = np.random.default_rng(7)
    checked = Counter()
    for a in (seed_cluster(9), Cluster.from_dict(fixtures["n10_m24_first-order"]), hyper, back):
        ex = expand(a, P)
        assert ex.first_order_rigid
        came: dict[int, tuple[Cluster, list]] = {}  # B (first endpoint of it) -> B as stored, its arrivals
        for i, e in enumerate(ex.endpoints):
            if not ex.retraceable(i):
                continue
            j = ex.same_as[i]
            if j not in came:
                came[j] = (_moved(ex.endpoints[j].cluster, rng), [])
            b, rows = came[j]
            t = alignment(e.cluster, b, P.tol_d)
            rows.append(("A", [list(p) for p in e.broken], [list(p) for p in e.new_contacts], e.steps, t.tolist()))
        assert len(came) >= 2
        for b, rows in came.values():
            came_by = arrivals(rows)
            full, short = expand(b, P), expand(b, P, arrivals=came_by)
            assert short.first_order_rigid and short.paths_retraced > 0
            taken = {g.broken for g in short.endpoints if g.reached is not None}
            if b.m == 3 * b.n - 6:  # a regular B: every single break leaves a smooth curve
                assert taken >= set(came_by)
            assert short.paths_followed + short.paths_retraced == full.paths_followed
            assert [(f.broken, f.direction) for f in full.endpoints] == [
                (f.broken, f.direction) for f in short.endpoints
            ]
            for f, g in zip(full.endpoints, short.endpoints):
                if g.reached is None:
                    assert (f.outcome, f.new_contacts, f.steps) == (g.outcome, g.new_contacts, g.steps)
                    continue
                assert g.reached.target == "A" and g.cluster is None and f.outcome == g.outcome == RIGID
                assert f.new_contacts == g.new_contacts == g.reached.formed
                back_at = f.cluster.coords - f.cluster.coords.mean(axis=0)
                at_a = a.coords[list(g.reached.labels)]
                assert kernels.aligned_max_error(back_at, at_a - at_a.mean(axis=0)) <= P.tol_d
                assert g.steps == g.reached.steps > 0  # the steps of the path that arrived (adaptive: not f's)
                checked[("regular" if b.m == 3 * b.n - 6 else "hyperstatic", len(g.broken), len(g.new_contacts))] += 1
            assert short.same_as == tuple(
                None if g.reached is not None else s for g, s in zip(short.endpoints, full.same_as)
            )
    assert sum(checked.values()) >= 20
    # paths back that form two contacts at once, and paths back from a hyperstatic B
    assert any(formed >= 2 for (_, _, formed) in checked) and any(k[0] == "hyperstatic" for k in checked), checked


def test_arrivals_that_disagree_on_a_contact_leave_its_path_to_be_followed():
    from packings.workers.expand import arrivals

    n = 9
    ident = list(range(n))
    swap = [1, 0] + list(range(2, n))
    rows = [
        ("A", [[0, 1]], [[2, 3]], 10, ident),
        ("C", [[4, 5]], [[2, 3]], 12, ident),  # two clusters at (2, 3)
        ("A", [[0, 1]], [[3, 4]], 10, ident),
        ("A", [[0, 2]], [[3, 4]], 10, ident),  # two contacts formed at (3, 4)
        ("A", [[0, 1]], [[5, 6]], 10, ident),
        ("A", [[1, 0]], [[6, 5]], 10, swap),  # agree at (5, 6)
        ("A", [[1, 2], [0, 1]], [[7, 8]], 10, ident),  # two broken, formed again on the way back
        ("A", [[0, 1]], [[8, 7], [6, 8]], 11, swap),  # two formed: broken together on the way back
        ("A", [[0, 1]], [], 10, ident),
    ]  # none formed: not an arrival
    got = arrivals(rows)
    assert set(got) == {((5, 6),), ((7, 8),), ((6, 8), (7, 8))}
    assert got[((5, 6),)].target == "A" and got[((5, 6),)].formed == ((0, 1),) and got[((5, 6),)].steps == 10
    assert got[((7, 8),)].formed == ((0, 1), (1, 2))
    assert got[((6, 8), (7, 8))].formed == ((0, 1),) and got[((6, 8), (7, 8))].steps == 11


def _ground_state_12():
    """The n = 12 cluster with 33 contacts (hyperstatic, 3n - 6 + 3), broken up to three contacts at a time."""
    from packings.workers.seeds import listed_seed

    return listed_seed(12, 33), P.with_(max_break=3)


def test_a_subset_with_a_contact_the_rest_holds_is_not_followed_and_nothing_reached_changes():
    """A subset B that leaves one flex, with a contact q such that B less q leaves a one-dimensional set, is
    ``held``: B's set is the curve B less q leaves, so q keeps its length along it.  A step along B's
    tangent, projected back onto what B leaves, finds every such q still touching to Newton's tolerance
    (a contact that merely keeps its length to first order would move by about the step squared).  Every
    other attempt is the same as when every path is followed, and so is every cluster reached."""
    from packings.workers import kernels
    from packings.workers.expand import HELD, NO_TRIANGLE
    from packings.workers.rigidity import contact_triangle

    c, p = _ground_state_12()
    ex, every = expand(c, p), expand(c, p, held=False)
    held = {e.broken for e in ex.endpoints if e.outcome == HELD}
    assert len(held) > 100 and HELD not in every.outcomes()
    assert all(e.direction == 0 and e.dim == 1 and e.cluster is None for e in ex.endpoints if e.outcome == HELD)

    def attempt(e):
        return (e.broken, e.direction, e.outcome, e.steps, e.new_contacts, e.cluster and e.cluster.coords.tobytes())

    assert [attempt(e) for e in ex.endpoints if e.broken not in held] == [
        attempt(e) for e in every.endpoints if e.broken not in held
    ]
    assert _same_distinct_clusters(ex, every)
    # following them is rounding's call: mostly shortens, some floppy, the odd one at a cluster reached anyway
    assert Counter(e.outcome for e in every.endpoints if e.broken in held)[RIGID] < len(held) / 10

    one_d = {e.broken for e in every.endpoints if e.outcome not in (NOT_1D, NO_TRIANGLE)}
    kw = p.newton()
    for b in sorted(held)[::7]:
        keep = np.array([e for e in c.contacts if e not in b])
        tri = contact_triangle(keep)
        x, free = kernels.to_frame(c.coords, tri).ravel(), kernels.free_coordinates(c.n, tri)
        ns = kernels.null_spaces(x, keep, free, p.tol_n)
        assert ns.V.shape[1] == 1
        pr = kernels.project(x + 0.05 * ns.V[:, 0], keep, free, **kw)
        assert pr.ok
        d = {q: float(np.linalg.norm(pr.x.reshape(-1, 3)[q[0]] - pr.x.reshape(-1, 3)[q[1]])) for q in b}
        holding = [q for q in b if tuple(sorted(set(b) - {q})) in one_d]
        assert holding and all(abs(d[q] - 1.0) < 1e-9 for q in holding)
        assert any(abs(d[q] - 1.0) > 1e-4 for q in b)  # the step moved the set: some broken contact opened or closed


@settings(max_examples=3, deadline=None, derandomize=True)
@given(st.integers(0, 2**31 - 1), st.booleans())
def test_the_held_subsets_are_the_same_after_rotation_reflection_relabelling(seed, reflect):
    from packings.workers.expand import HELD

    c, p = _ground_state_12()
    moved, inv = congruent_copy(c, seed, reflect)
    relabel = {(i, j): tuple(sorted((int(inv[i]), int(inv[j])))) for i, j in c.contacts}
    a, b = expand(c, p), expand(moved, p)
    held_a = {tuple(sorted(relabel[e] for e in x.broken)) for x in a.endpoints if x.outcome == HELD}
    held_b = {x.broken for x in b.endpoints if x.outcome == HELD}
    assert held_a and held_a == held_b
    assert _same_distinct_clusters(a, b)


def test_the_orbits_of_a_chunk_of_subsets_are_those_found_one_by_one():
    """_Orbits.firsts, read off a chunk at once, gives for every subset what comparing its images one symmetry
    at a time gives: whether it is the first of its orbit, else that first subset and the first symmetry that
    reaches it (its inverse relabels the first subset's attempts)."""
    from itertools import combinations

    from packings.workers.expand import _Orbits
    from packings.workers.identity import symmetries
    from packings.workers.seeds import close_packed_seed

    def one_by_one(orbits, idx):
        best, g = idx, -1
        for k, row in enumerate(np.sort(orbits.moves[:, idx], axis=1).tolist()):
            if tuple(row) < best:
                best, g = tuple(row), k
        if g < 0:
            return None
        inverse = np.empty_like(orbits.perms[g])
        inverse[orbits.perms[g]] = np.arange(inverse.size)
        return best, inverse

    for c, top in ((seed_cluster(5), 5), (seed_cluster(6), 4), (close_packed_seed(14), 3)):
        orbits = _Orbits(c, symmetries(c, P.tol_d))
        firsts = 0
        for k in range(1, top + 1):
            chunk = list(combinations(range(c.m), k))
            for idx, got in zip(chunk, orbits.firsts(chunk)):
                want = one_by_one(orbits, idx)
                assert (got is None) == (want is None), idx
                if want is not None:
                    assert got[0] == want[0] and np.array_equal(got[1], want[1]), idx
                else:
                    firsts += 1
        assert 0 < firsts < sum(len(list(combinations(range(c.m), k))) for k in range(1, top + 1))
