"""What the orchestrator's loop passes between a way's steps (lrfcal.pipeline): a solve's outcome on a way's
observation sets, and a candidate start with what came of it.

A way's sets (its own type ``S``: the marker returns as matched with the scales freed and the surfaces chosen, or the
plane returns with the start they are solved from) and its starts (``St``) are opaque here: the orchestrator hands
them back to the way that made them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np

from lrfcal.errors import CalibrationError
from lrfcal.types.solution import Solution

S = TypeVar("S")
St = TypeVar("St")

#: what ends a start's estimate: a refusal, or a singular system
Refusal = CalibrationError | np.linalg.LinAlgError


@dataclass(frozen=True)
class Fit(Generic[S]):
    """The estimate on a way's observation sets: the sets as chosen (what was solved) and the solution."""

    sets: S
    solution: Solution


@dataclass(frozen=True)
class Tried(Generic[St, S]):
    """A candidate start and what came of it: its fit, the sets chosen again at each estimate until they stood, or
    the refusal that ended it (the way's ``choose`` judges which end the calibration and which only that start)."""

    start: St
    outcome: Fit[S] | Refusal

    @property
    def fit(self) -> Fit[S] | None:
        """The fit, None when the start was refused."""
        return self.outcome if isinstance(self.outcome, Fit) else None


__all__ = ["Fit", "Refusal", "Tried"]
