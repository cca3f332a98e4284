"""Observation sets: the one interface every kind of observation the calibration estimates from implements.

An observation set (:class:`ObservationSet`) is a set of returns with one observation model: its whitened residual
rows and Jacobian blocks at a state (:class:`Blocks`: dense rows on the core unknowns, or plane rows on the core
unknowns and their own plane's nuisances), its nuisances (the free planes' 3 per plane), its clusters for the
cluster-robust covariance, how its returns are kept by the robust pass (:meth:`ObservationSet.kept`) and how it is
chosen again at a new estimate (:meth:`ObservationSet.chosen_at`). Implemented by the marker returns
(lrfcal.model.marker.MarkerSet), the plane returns (lrfcal.model.plane.PlaneSet) and the design drawing's prior on
the DH parameters (:class:`DHPrior`). One estimate (lrfcal.estimate.engine) takes a list of them.

The sensor constants of the marker observation model travel as one typed object (:class:`MarkerSensor`, the model
variant a :class:`MarkerModel`).
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, TypeVar, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import InputError
from lrfcal.model.motor import MotorClock
from lrfcal.model.range_pattern import PatternRows
from lrfcal.model.unknowns import DH_SLICE, N_CORE, dh_difference

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

#: the robust pass keeps a return whose score is within this many robust sigma
CUT_SIGMA = 4.0


class MarkerModel(str, enum.Enum):
    """The marker observation model (lrfcal.model.marker): the seed paper's eq. (10) or ray-sphere (equal to its
    name as a string, as configuration files and older calls give it)."""

    PAPER = "paper"
    SPHERE = "sphere"

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class MarkerSensor:
    """The constants of the marker observation model: the model variant, the marker radius R_m [m], the scanner's
    full beam divergence [rad] (0: the beam's axis alone) and its range noise sigma_r [m]."""

    model: MarkerModel = MarkerModel.SPHERE
    radius_m: float = 0.05
    divergence_rad: float = 0.0
    range_sigma_m: float = 0.010

    @classmethod
    def of(cls, model: str, radius_m: float, divergence_rad: float = 0.0, range_sigma_m: float = 0.010
           ) -> MarkerSensor:
        """The sensor of loose values, checked.

        Raises:
            InputError: a model, radius, noise or divergence out of its domain."""
        try:
            variant = MarkerModel(model)
        except ValueError:
            raise InputError(f"solve: model must be one of {', '.join(m.value for m in list(MarkerModel))}, "
                             f"got {model!r}") from None
        if not radius_m > 0 or not range_sigma_m > 0:
            raise InputError(f"solve: marker_radius_m and range_sigma_m must be > 0, got {radius_m}, "
                             f"{range_sigma_m}")
        if not 0.0 <= divergence_rad < 0.1:
            raise InputError(f"solve: beam_divergence_rad must be in [0, 0.1) rad, got {divergence_rad}")
        return cls(variant, float(radius_m), float(divergence_rad), float(range_sigma_m))


@dataclass(frozen=True)
class Blocks:
    """The whitened residuals of one or more observation sets and, with the Jacobian, their blocks
    (lrfcal.estimate.normal_equations).

    r_dense (m,), J_dense (m, n_core); r_plane (K,), Jc_plane (K, n_core), Jn_plane (K, 3), plane (K,) the plane of
    each plane row; r_prior (3P,) and w_prior (3P,) the nuisance priors' residuals and 1 / sigma (None: free
    planes); n_planes P. Jacobians None when only residuals were asked for."""

    r_dense: FloatArray
    J_dense: FloatArray | None
    r_plane: FloatArray
    Jc_plane: FloatArray | None
    Jn_plane: FloatArray | None
    plane: IntArray
    n_planes: int
    r_prior: FloatArray | None = None
    w_prior: FloatArray | None = None
    segments: tuple[IntArray, IntArray] | None = None  # the plane rows ordered by plane, and each plane's bounds
    #: the plane rows' range pattern along the scan (lrfcal.model.range_pattern), eliminated beside the core unknowns;
    #: r_plane is then the residual with the best pattern taken out (None: no pattern)
    pattern: PatternRows | None = None

    @classmethod
    def dense(cls, r: FloatArray, J: FloatArray | None) -> Blocks:
        """Dense rows only: r (m,), J (m, n_core) or None."""
        return cls(r, J, np.zeros(0), np.zeros((0, N_CORE)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64), 0)

    def residuals(self) -> FloatArray:
        """All whitened residuals, dense rows then plane rows then priors."""
        parts = [self.r_dense, self.r_plane]
        if self.r_prior is not None:
            parts.append(self.r_prior)
        return np.concatenate(parts)


def stack_blocks(parts: Sequence[Blocks]) -> Blocks:
    """The blocks of several observation sets as one: dense rows and plane rows each in the sets' order, the planes
    numbered after the previous sets' (their nuisances follow each other in the same order). Where one set alone
    has dense (or plane) rows, its arrays are taken as they are."""
    if len(parts) == 1:
        return parts[0]
    dense = [p for p in parts if p.r_dense.size] or [parts[0]]
    planes = [p for p in parts if p.r_plane.size or p.n_planes]
    if len(dense) == 1:
        r_d, J_d = dense[0].r_dense, dense[0].J_dense
    else:
        r_d = np.concatenate([p.r_dense for p in dense])
        Js = [p.J_dense for p in dense if p.J_dense is not None]
        J_d = np.vstack(Js) if len(Js) == len(dense) else None
    if len(planes) <= 1:
        q = planes[0] if planes else parts[0]
        return Blocks(r_d, J_d, q.r_plane, q.Jc_plane, q.Jn_plane, q.plane, q.n_planes, q.r_prior, q.w_prior,
                      q.segments, q.pattern)
    assert all(p.pattern is None for p in planes), "a range pattern is the one plane set's (the targetless cost)"
    offsets = np.cumsum([0, *(p.n_planes for p in planes)])
    jac = all(p.Jc_plane is not None and p.Jn_plane is not None for p in planes)
    priors = any(p.r_prior is not None for p in planes)

    def prior(p: Blocks, which: str) -> FloatArray:
        v = getattr(p, which)
        return np.zeros(3 * p.n_planes) if v is None else v

    return Blocks(
        r_d, J_d, np.concatenate([p.r_plane for p in planes]),
        np.vstack([p.Jc_plane for p in planes if p.Jc_plane is not None]) if jac else None,
        np.vstack([p.Jn_plane for p in planes if p.Jn_plane is not None]) if jac else None,
        np.concatenate([p.plane + off for p, off in zip(planes, offsets[:-1], strict=True)]), int(offsets[-1]),
        np.concatenate([prior(p, "r_prior") for p in planes]) if priors else None,
        np.concatenate([prior(p, "w_prior") for p in planes]) if priors else None)


@dataclass(frozen=True)
class RowContext:
    """How a set's rows are evaluated: the range noise sigma_r [m] that whitens the range residuals, the motor clock
    (the clock offset an unknown; None: held), whether the mount's Jacobian columns are computed (False: a held
    mount, left 0), the chart (6, 4) the scan-plane columns are derivatives by (lrfcal.model.chart; None: the
    DH parameters), and whether the incidence bias's column is computed (False: held and never tested, left 0)."""

    sigma_r: float
    clock: MotorClock | None = None
    mount_jac: bool = True
    chart: FloatArray | None = None
    incidence_jac: bool = True


_Set = TypeVar("_Set", bound="ObservationSet")


@runtime_checkable
class ObservationSet(Protocol):
    """A set of observations with one observation model (module docstring). ``th`` is the core unknowns followed by
    this set's own nuisances (N_CORE + n_nuisance,); R_ref the mount's reference rotation."""

    @property
    def size(self) -> int:
        """The number of returns (what :meth:`subset` and :meth:`kept` index)."""
        ...

    @property
    def n_nuisance(self) -> int:
        """The number of nuisance unknowns (3 per free plane)."""
        ...

    @property
    def n_independent(self) -> int:
        """The independent residuals (the degrees of freedom the reduced chi-square counts), priors included."""
        ...

    @property
    def min_kept(self) -> int:
        """Fewer kept returns than this stop the robust passes (the set would no longer determine anything)."""
        ...

    def blocks(self, th: FloatArray, R_ref: FloatArray, ctx: RowContext, jac: bool = True) -> Blocks:
        """The whitened residual rows and their Jacobian blocks at th."""
        ...

    def subset(self: _Set, keep: BoolArray) -> _Set:
        """The returns ``keep`` (size,)."""
        ...

    def kept(self, th: FloatArray, R_ref: FloatArray, ctx: RowContext, keep: BoolArray) -> BoolArray:
        """(size,) the returns the robust pass keeps at th: score within CUT_SIGMA of the robust scale of the
        scores of the returns ``keep`` kept so far."""
        ...

    def chosen_at(self: _Set, th: FloatArray, R_ref: FloatArray, ctx: RowContext) -> _Set:
        """The set as it is used at a new estimate th (which residuals of each return count)."""
        ...

    def clusters(self, first: int) -> tuple[IntArray, IntArray]:
        """The cluster of each dense row and of each plane row for the cluster-robust covariance; ids the set
        makes up itself start at ``first`` (above every scan id)."""
        ...

    def groups(self) -> IntArray | None:
        """(dense rows,) the group (a marker) whose rows share an error of their own, for the per-group
        widening of the covariance; None: no such groups."""
        ...

    @property
    def scan(self) -> IntArray | None:
        """(size,) each return's scan (the clusters' ids start above them), or None."""
        ...


@dataclass(frozen=True)
class DHPrior:
    """The design drawing's word on the DH parameters: mean (4,) and sigma (4,) of a, alpha, b, beta as 4 dense
    prior rows (d(a, alpha, b, beta) - mean) / sigma, each its own cluster. Never left out by the robust pass."""

    mean: FloatArray
    sigma: FloatArray

    @property
    def size(self) -> int:
        return 4

    @property
    def n_nuisance(self) -> int:
        return 0

    @property
    def n_independent(self) -> int:
        return 4

    @property
    def min_kept(self) -> int:
        return 0

    @property
    def scan(self) -> IntArray | None:
        return None

    def blocks(self, th: FloatArray, R_ref: FloatArray, ctx: RowContext, jac: bool = True) -> Blocks:
        assert ctx.chart is None, "a prior on the DH parameters needs the DH chart"
        r = dh_difference(th[DH_SLICE], self.mean) / self.sigma
        J = None
        if jac:
            J = np.zeros((4, N_CORE))
            J[:, DH_SLICE] = np.diag(1.0 / self.sigma)
        return Blocks.dense(r, J)

    def subset(self, keep: BoolArray) -> DHPrior:
        return self

    def kept(self, th: FloatArray, R_ref: FloatArray, ctx: RowContext, keep: BoolArray) -> BoolArray:
        return np.ones(4, dtype=bool)

    def chosen_at(self, th: FloatArray, R_ref: FloatArray, ctx: RowContext) -> DHPrior:
        return self

    def clusters(self, first: int) -> tuple[IntArray, IntArray]:
        return -1 - np.arange(4, dtype=np.int64), np.zeros(0, dtype=np.int64)

    def groups(self) -> IntArray | None:
        return None


def robust_scale(score: FloatArray, keep: BoolArray, median_of_unit: float, squared: bool) -> float:
    """The robust scale of the scores kept so far (``keep``): their median over its value ``median_of_unit`` for unit
    noise (of score^2 when ``squared``)."""
    if squared:
        return float(np.sqrt(np.median(score[keep] ** 2) / median_of_unit))
    return float(np.median(score[keep]) / median_of_unit)


def within_cut(score: FloatArray, scale: float) -> BoolArray:
    """(K,) the scores within CUT_SIGMA times the robust ``scale``, never below 1 (the model's own noise)."""
    return score <= CUT_SIGMA * max(1.0, scale)


def robust_kept(score: FloatArray, keep: BoolArray, median_of_unit: float, squared: bool) -> BoolArray:
    """(K,) the scores within CUT_SIGMA robust sigma (:func:`within_cut`), the scale :func:`robust_scale`'s."""
    return within_cut(score, robust_scale(score, keep, median_of_unit, squared))


__all__ = ["CUT_SIGMA", "Blocks", "DHPrior", "MarkerModel", "MarkerSensor", "ObservationSet", "RowContext",
           "robust_kept", "robust_scale", "stack_blocks", "within_cut"]
