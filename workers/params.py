"""Numerical parameters of the method (docs/method.md), with the paper's values as defaults."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace


@dataclass(frozen=True)
class Params:
    """Every tolerance and step of the enumeration in one place.

    Defaults are the values used by Holmes-Cerfon (SIAM Review 2016).  The three
    dimension-test tolerances default to multiples of ``ds`` as in the paper;
    they are stored explicitly so that a run records what it used.
    """

    ds: float = 5e-3  #: step along a path in the endgame
    ds0: float = 5e-2  #: step along a path away from contacts, and the probe step of the dimension test
    tol: float = 9e-16  #: Newton converged when sum_k f_k^2 < tol
    tol_n: float = 1e-6  #: singular values below this count as zero
    dx_max: float = 0.02  #: largest Newton step (2-norm)
    tol_a: float = 1e-5  #: two spheres touch if their distance is below 1 + tol_a
    tol_a0: float = 1e-3  #: a path stops when a pair comes within 1 + tol_a0
    tol_d: float = 1e-5  #: two clusters are identical if their geometry agrees within tol_d
    x_tol_max: float = field(default=None)  # type: ignore[assignment]
    x_tol_min: float = field(default=None)  # type: ignore[assignment]
    v_tol: float = field(default=None)  # type: ignore[assignment]
    tol_psd: float = 1e-5  #: smallest eigenvalue that counts as positive in the pre-stress test
    newton_max_iter: int = 200  #: Newton iterations before a projection is reported as failed
    #: the dimension test's probe first projects with its correction orthogonal to the probe
    #: direction; that projection is given up once its residual has not improved for this many
    #: iterations (0: it runs the full newton_max_iter), see packings.workers.dimension.solution_dimension
    probe_stall: int = 10
    max_path_steps: int = 3000  #: steps along one path before it is abandoned
    #: largest number of contacts broken at once; None (the default, as in the paper for every n <= 14)
    #: breaks up to m - rank(R) + 1, a cap is for restricted runs (n >= 15), see packings.workers.expand.break_sizes
    max_break: int | None = None
    #: stop a path whose set is more than one-dimensional after its first step (the paper's rule);
    #: by default such a path goes on and is counted (see packings.workers.paths.follow_path)
    stop_on_dimension_change: bool = False
    min_contacts: int | None = None  #: keep only rigid clusters with at least this many contacts

    def __post_init__(self) -> None:
        if self.x_tol_max is None:
            object.__setattr__(self, "x_tol_max", 10 * self.ds)
        if self.x_tol_min is None:
            object.__setattr__(self, "x_tol_min", self.ds / 8)
        if self.v_tol is None:
            object.__setattr__(self, "v_tol", 2 * self.ds)
        if self.max_break is not None and self.max_break < 1:
            raise ValueError("max_break must be at least 1")

    def to_dict(self) -> dict:
        return asdict(self)

    def newton(self, **extra) -> dict:
        """The Newton projection's settings (packings.workers.kernels.project), with ``extra`` ones."""
        return dict(tol=self.tol, dx_max=self.dx_max, max_iter=self.newton_max_iter, tol_n=self.tol_n, **extra)

    def to_json(self) -> str:
        """The parameters as JSON with sorted keys: a run's ``params`` column, which tells runs apart."""
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict) -> "Params":
        return cls(**d)

    def with_(self, **changes) -> "Params":
        return replace(self, **changes)


DEFAULT = Params()
