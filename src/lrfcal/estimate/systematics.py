"""The one place a calibration's covariance is widened for the errors its noise does not hold: the systematic errors a
way names (lrfcal.pipeline calls :func:`widened` once, on the chosen estimate).

Two kinds, each a way's to name:

- a **model error** (:class:`ModelError`): a variant of the estimate's problem, as defensible as the model solved,
  whose solution differs from the model's by d in the DH parameters; neither is right alone, so their difference is
  a model error the noise's sigma does not hold, and the DH covariance grows by d d^T (the marker way: only the
  in-plane part of the lateral residual where the sweep turns on a marker, lrfcal.stages.markers);
- **held parameters** (:class:`Considered`): parameters held at the nominal value because the data do not determine
  them, whose uncertainty (the design drawing's tolerance) is carried into the estimated ones as a "consider"
  covariance, cov_e += S C_h S^T, S = -I_ee^-1 I_eh the sensitivity of the estimate to the held values (the plane
  way: the DH parameters the scene's planes do not determine, lrfcal.stages.scene).

The variants are requests the orchestrator solves (lrfcal.estimate.engine.solved); what the held parameters need is
the information at the estimate (lrfcal.estimate.information), which the way evaluates.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from lrfcal.estimate.checks import dh_text
from lrfcal.estimate.request import Request
from lrfcal.model.kinematics import DH
from lrfcal.model.unknowns import CORE_NAMES, DH_SLICE, dh_difference
from lrfcal.types import Noted, Solution

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ModelError:
    """A model error to add to the DH covariance: ``variant`` solved, its DH minus ``reference``'s (the solution of the
    model the variant varies) is d; ``what`` names the variant for the note ("... differ by d, added to the
    covariance")."""

    what: str
    variant: Request
    reference: Solution


@dataclass(frozen=True)
class Considered:
    """Held parameters whose uncertainty is carried into the estimated ones: the information at the estimate over
    ``names`` (the estimated and the held core unknowns, before scaling by the reduced chi-square) and each held
    one's 1-sigma (``tolerance``: name -> sigma, the nominal tolerance)."""

    information: FloatArray
    names: tuple[str, ...]
    tolerance: Mapping[str, float]


@dataclass(frozen=True)
class Systematics:
    """What a way names to widen its estimate's covariance by: model errors (each a variant to solve) and held
    parameters (none: the covariance stands)."""

    model_errors: tuple[ModelError, ...] = ()
    considered: Considered | None = None


def widened(sol: Solution, systematics: Systematics, variants: Sequence[Solution | None]) -> Noted[Solution]:
    """``sol`` with its covariance widened by the held parameters' uncertainty (``systematics.considered``) and by
    d d^T for each model error whose variant was solved (``variants``, in ``systematics.model_errors``' order; None:
    the variant could not be solved, no term), with a note for each model error added."""
    notes: list[str] = []
    cov = sol.covariance
    if systematics.considered is not None:
        cov = _considered(cov, systematics.considered, sol.reduced_chi2)
    for error, variant in zip(systematics.model_errors, variants, strict=True):
        if variant is None:
            continue
        d = dh_difference(variant.params.dh.vector(), error.reference.params.dh.vector())
        cov = np.array(cov, dtype=float)
        cov[DH_SLICE, DH_SLICE] += np.outer(d, d)
        notes.append(f"{error.what} differ by {dh_text(DH(*d))}, added to the covariance")
    if cov is sol.covariance:
        return Noted(sol)
    return Noted(replace(sol, covariance=cov, sigma=np.sqrt(np.clip(np.diag(cov), 0.0, None))), tuple(notes))


def _considered(cov: FloatArray, held: Considered, reduced_chi2: float) -> FloatArray:
    """``cov`` (10, 10) plus S C_h S^T over the estimated core unknowns of ``held.names`` (module docstring), the
    information scaled by the reduced chi-square (at least 1)."""
    info = held.information / max(reduced_chi2, 1.0)
    names = held.names
    est = [i for i, n in enumerate(names) if n not in held.tolerance]
    hid = [names.index(n) for n in held.tolerance]
    S = -np.linalg.solve(info[np.ix_(est, est)], info[np.ix_(est, hid)])
    extra = S @ np.diag([held.tolerance[n] ** 2 for n in held.tolerance]) @ S.T
    cov = cov.copy()
    pos = {n: CORE_NAMES.index(n) for n in names}
    for i, a in enumerate(est):
        for j, b in enumerate(est):
            ia, ib = pos[names[a]], pos[names[b]]
            if ia < 10 and ib < 10:
                cov[ia, ib] += extra[i, j]
    return cov


__all__ = ["Considered", "ModelError", "Systematics", "widened"]
