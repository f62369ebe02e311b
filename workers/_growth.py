"""The growth of close-packed fragments (:func:`packings.workers.fragments._grown`), compiled.

Nothing outside :mod:`packings.workers.fragments` should import this module.  One call grows every
fragment of one size by one site, exactly as a dictionary of tuples grown one fragment at a time in
Python would (the same fragments, in the same order, with the same contacts; the tests compare the
two), but holds each fragment as one row of
small integers and tells them apart with an open-addressing hash table instead of a dictionary of
tuples: about 120 bytes a fragment of 19 sites instead of about 750, and no Python per candidate
site.

A row is ``[positions of the layers (-1 past the stack's height), sites in increasing order]``,
with the encodings of :mod:`packings.workers.fragments` (site = layer S^2 + (i + O) S + (j + O);
position 0, 1, 2 for A, B, C); its lowest layer is in position A and its first site at (0, 0)
(:func:`packings.workers.fragments._grown` says how a fragment is moved there).
"""

from __future__ import annotations

import numba
import numpy as np

_JIT = dict(cache=True, nogil=True)

#: candidate kinds: a site in a layer the fragment spans, or in a new layer above (1 + p) or below (4 + p)
#: it, in position p
_KINDS = 7
_EMPTY = -1


@numba.njit(**_JIT)
def _hash(row):
    """64 bits of a row: FNV-1a over its integers, then the finaliser of MurmurHash3 (the table takes the
    low bits)."""
    h = np.uint64(1469598103934665603)
    for v in row:
        h = (h ^ np.uint64(v & 0xFFFFFFFF)) * np.uint64(1099511628211)
    h = (h ^ (h >> np.uint64(33))) * np.uint64(0xFF51AFD7ED558CCD)
    h = (h ^ (h >> np.uint64(33))) * np.uint64(0xC4CEB9FE1A85EC53)
    return h ^ (h >> np.uint64(33))


@numba.njit(**_JIT)
def _find(table, rows, row, h):
    """The index in ``table`` where ``row`` is stored, or the empty slot where it would go."""
    mask = table.size - 1
    i = np.int64(h & np.uint64(mask))
    width = row.size
    while True:
        r = table[i]
        if r == _EMPTY:
            return i
        same = True
        for c in range(width):
            if rows[r, c] != row[c]:
                same = False
                break
        if same:
            return i
        i = (i + 1) & mask


@numba.njit(**_JIT)
def _count(keys, stamp, kind, q, qmax, nkeys):
    """One more contact for the candidate (kind, q) of the parent stamped ``stamp`` (sites below ``qmax``), a
    new candidate if it is the first; returns the number of candidates.  ``keys`` = (stamp of each slot,
    its candidate's index, and each candidate's kind, site and gain)."""
    key_stamp, key_index, kind_of, q_of, gain = keys
    slot = kind * qmax + q
    if key_stamp[slot] != stamp:
        key_stamp[slot] = stamp
        key_index[slot] = nkeys
        kind_of[nkeys] = kind
        q_of[nkeys] = q
        gain[nkeys] = 1
        return nkeys + 1
    gain[key_index[slot]] += 1
    return nkeys


@numba.njit(**_JIT)
def grow(rows, contacts, most, threshold, in_layer, across, S, O):
    """Every fragment of k + 1 sites grown by one touching site from the fragments ``rows`` (B x (most + k),
    as the module says) with ``contacts`` (B) contacts, kept if it has at least ``threshold``; a layer
    not spanned yet may be added above or below while the stack has fewer than ``most`` layers.  The
    order and the contacts are those of the dictionary loop it replaces: parents in order, each
    parent's candidate sites in the order first met (its sites in increasing order; for each, the six
    of its layer, then those of the layer below, then above), each new fragment kept where first made.
    ``in_layer`` (6) and ``across`` (3 x 3 x 3: from a layer in position p to one in q) are the site
    offsets di S + dj of the touching sites.  Returns (rows, contacts) of the new size.

    One compiled loop of about 120 lines on purpose: its work arrays and hash table are allocated once
    for all the parents of a size, and split into functions they would be passed through every call."""
    B = rows.shape[0]
    k = rows.shape[1] - most
    S2 = S * S
    base = O * S + O
    qmax = S2 * (most + 1)
    width = most + k + 1
    inside = np.zeros(qmax, dtype=np.int64)  # stamp of the parent a site belongs to
    key_stamp = np.zeros(_KINDS * qmax, dtype=np.int64)
    key_index = np.zeros(_KINDS * qmax, dtype=np.int64)
    cap = max(1024, 2 * B)
    out = np.empty((cap, width), dtype=rows.dtype)
    out_c = np.empty(cap, dtype=contacts.dtype)
    size = 1  # the table: a power of two, at least twice the rows
    while size < 2 * cap:
        size *= 2
    table = np.full(size, _EMPTY, dtype=np.int64)
    count = 0
    most_keys = k * 18
    kind_of = np.empty(most_keys, dtype=np.int64)
    q_of = np.empty(most_keys, dtype=np.int64)
    gain = np.empty(most_keys, dtype=np.int64)
    keys = (key_stamp, key_index, kind_of, q_of, gain)
    pos = np.empty(most, dtype=np.int64)
    child = np.empty(width, dtype=rows.dtype)
    sites = np.empty(k + 1, dtype=np.int64)
    for b in range(B):
        stamp = b + 1
        height = 0
        for layer in range(most):
            pos[layer] = rows[b, layer]
            if pos[layer] >= 0:
                height = layer + 1
        for a in range(k):
            inside[rows[b, most + a]] = stamp
        nkeys = 0
        for a in range(k):
            u = rows[b, most + a]
            layer = u // S2
            for o in range(6):
                q = u + in_layer[o]
                if inside[q] != stamp:
                    nkeys = _count(keys, stamp, 0, q, qmax, nkeys)
            for dl in (-1, 1):
                other = layer + dl
                if 0 <= other < height:
                    for o in range(3):
                        q = u + dl * S2 + across[pos[layer], pos[other], o]
                        if inside[q] != stamp:
                            nkeys = _count(keys, stamp, 0, q, qmax, nkeys)
                elif height < most:
                    for p in range(3):
                        if p != pos[layer]:
                            kind = 1 + p if dl == 1 else 4 + p
                            for o in range(3):
                                q = u + max(dl, 0) * S2 + across[pos[layer], p, o]
                                nkeys = _count(keys, stamp, kind, q, qmax, nkeys)
        c = contacts[b]
        for e in range(nkeys):
            if c + gain[e] < threshold:
                continue
            kind = kind_of[e]
            q = q_of[e]
            for layer in range(most):
                child[layer] = pos[layer]
            if kind <= 3:
                if kind > 0:
                    child[height] = kind - 1
                for a in range(k):
                    sites[a] = rows[b, most + a]
                sites[k] = q
            else:  # a new lowest layer: every layer goes up one, then the stack is moved to begin with A
                p0 = kind - 4
                child[0] = p0
                for layer in range(height):
                    child[layer + 1] = pos[layer]
                for a in range(k):
                    sites[a] = rows[b, most + a] + S2
                sites[k] = q
                for a in range(k + 1):
                    if child[sites[a] // S2] < p0:
                        sites[a] -= S + 1
                for layer in range(height + 1):
                    child[layer] = (child[layer] - p0) % 3
            first = sites[0]
            for a in range(1, k + 1):
                first = min(first, sites[a])
            shift = first % S2 - base
            for a in range(k + 1):
                sites[a] -= shift
            sites.sort()
            for a in range(k + 1):
                child[most + a] = sites[a]
            h = _hash(child)
            i = _find(table, out, child, h)
            if table[i] != _EMPTY:
                continue
            if count == cap:  # grow the rows and the table
                cap *= 2
                bigger = np.empty((cap, width), dtype=rows.dtype)
                bigger[:count] = out[:count]
                out = bigger
                bigger_c = np.empty(cap, dtype=contacts.dtype)
                bigger_c[:count] = out_c[:count]
                out_c = bigger_c
                table = np.full(2 * table.size, _EMPTY, dtype=np.int64)
                for r in range(count):
                    table[_find(table, out, out[r], _hash(out[r]))] = r
                i = _find(table, out, child, h)
            out[count] = child
            out_c[count] = c + gain[e]
            table[i] = count
            count += 1
    return out[:count].copy(), out_c[:count].copy()
