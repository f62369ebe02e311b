"""What can come of one attempt (a broken subset of contacts and a direction): the names stored (numbered
by ``packings.service.paths_codec.OUTCOMES``) and counted in ``expansions.outcomes``.

Plain names in a module of their own, so that the service can name them without importing the
numerical code (and its compiled kernels).
"""

# Outcomes of one path (packings.workers.paths).
RIGID = "rigid"  #: ended at a rigid cluster
FLOPPY = "floppy"  #: ended where new contacts form but the cluster is not rigid
UNDECIDED_END = "undecided"  #: ended at a cluster the pre-stress test could not decide
UNPROVED = "unproved"  #: ended at a point first-order rigid by the test but near no provable root (docs/method.md)
PROJECTION_FAILED = (
    "projection-failed"  #: no projection with any subset of the new contacts, or a step could not be projected
)
DIMENSION_CHANGED = "dimension-changed"  #: the path could not go on: its set was no longer one-dimensional
SHORTENS = "shortens"  #: the direction shortens a broken contact (the spheres would overlap)
OVERLAP = "overlap"  #: the projected endpoint has overlapping spheres
TOO_LONG = "too-long"  #: max_path_steps reached without a new contact

# Outcomes of one (broken subset, direction) beyond those of a path (packings.workers.expand).
CIRCULAR = "circular"  #: the path came back to the cluster it left, every sphere where it was: the paper's circle
#: the path ended at the cluster it left with its spheres permuted: another permutational isomer of it (an edge
#: of the labelled network, a self-loop of the unlabelled one), not a circle
REARRANGED = "rearranged"
NOT_1D = "not-1d"  #: removing the subset leaves a solution set of dimension != 1 (no path)
HELD = "held"  #: a broken contact the rest holds at its length: the set is a smaller subset's, whose path is followed
NO_DIRECTION = "no-direction"  #: no tangent direction lengthens every broken contact
NO_TRIANGLE = "no-triangle"  #: the remaining contacts hold no triangle to pin
BELOW_MIN_CONTACTS = "below-min-contacts"  #: rigid endpoint with fewer contacts than min_contacts
