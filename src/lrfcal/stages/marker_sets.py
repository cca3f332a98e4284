"""The marker way's observation sets as chosen, and where its choices stand: what lrfcal.stages.markers.MarkerWay hands
the orchestrator (lrfcal.pipeline) with each solve and takes back with its solution.

:class:`MarkerSets` is one solve's sets: the :class:`Alternative` (the marker returns matched to the marker map, the
unknowns found to need estimating, the notes so far), where the solve starts, and the :data:`Step`: what the solve
adds to the marker-only problem (the surfaces, the range bias) and what the way does with its solution (the way's
``reselect``: lrfcal.stages.alternatives for a candidate start, lrfcal.stages.refinement after the choice). Every
step is a frozen record: the way keeps no state between its steps; what a later choice needs travels in the sets.
"""

from __future__ import annotations

from dataclasses import dataclass

from lrfcal.model.kinematics import Params
from lrfcal.model.motor import MotorClock
from lrfcal.types import Association, MarkerMap, Observations, Solution, Surface, SurfaceReturns


@dataclass(frozen=True)
class Alternative:
    """One discrete alternative of the start (a direction of the servo, the map's handedness, the DH
    representative): the servo's sign with the marker returns matched to the marker map, the start (the mount pose
    from the association, the DH it was made with) and the motor clock (None: the clock offset held)."""

    sign: int
    markers: MarkerMap
    assoc: Association
    matched: Observations
    start: Params
    clock: MotorClock | None
    notes: tuple[str, ...] = ()  # what its start noted (then what its refinement noted)
    estimate: tuple[str, ...] = ()  # the unknowns held by default that its solves estimate (scales found off)
    #: a disagreement with the marker map (in words) that the marker-only fit found but could not judge, as it does
    #: not determine the DH parameters (one scan line per marker): judged at the joint solution (lrfcal.stages.
    #: refinement)
    unjudged: str = ""


# --- a candidate start's steps (lrfcal.stages.alternatives) ---


@dataclass(frozen=True)
class FromStart:
    """A direction's marker-only solve: ``left_out`` < 0 while the scales the data contradict are freed, then the
    times blobs that disagree with the marker map were left out (at most three)."""

    left_out: int = -1


@dataclass(frozen=True)
class Once:
    """A further start's marker-only solve (the map's other handedness, the turned DH representative): solved once."""


@dataclass(frozen=True)
class Stood:
    """The start's sets stand: a disagreement with the marker map left to the joint solution to judge."""


@dataclass(frozen=True)
class Chosen:
    """The alternative chosen with its marker-only solution: the refinement begins (lrfcal.stages.refinement)."""


# --- the refinement's steps (lrfcal.stages.refinement) ---


@dataclass(frozen=True)
class Found:
    """The marker-carrying surfaces and their returns chosen (None: none looked for)."""

    surfaces: tuple[Surface, ...] = ()
    returns: SurfaceReturns | None = None


@dataclass(frozen=True)
class Ended:
    """The joint solve's rounds ended (lrfcal.stages.joint): the estimate (``origin`` itself when no joint solve ran),
    the surfaces and their returns, the rounds' notes, whether a joint solve ran."""

    ours: Solution
    found: Found
    notes: tuple[str, ...]
    joined: bool


@dataclass(frozen=True)
class Scales:
    """After the rounds: the scales the joint solution contradicts freed, then the unjudged blobs judged."""


@dataclass(frozen=True)
class Unjoined:
    """After the rounds from a marker-only fit without the blobs it found disagreeing (``left_out`` times, the blobs
    kept ``assoc`` and ``matched``, its solution ``sol``): judged again unless they joined the surfaces."""

    left_out: int
    assoc: Association
    matched: Observations
    sol: Solution


@dataclass(frozen=True)
class Judging:
    """After the rounds from ``start``, the joint solution the blobs are judged at, with the blobs kept so far
    (``assoc``, ``matched``; ``left_out`` times some left out) and the judgement's notes."""

    left_out: int
    assoc: Association
    matched: Observations
    start: Solution
    notes: tuple[str, ...] = ()


#: what follows the joint solve's rounds
Then = Scales | Unjoined | Judging


@dataclass(frozen=True)
class Rounds:
    """The joint solve's rounds (lrfcal.stages.joint) from ``origin`` with the returns ``matched``: round ``round``,
    its surfaces chosen at ``at``; the estimate so far ``ours``, the range bias's note, whether a joint solve ran,
    and what follows them."""

    origin: Solution
    matched: Observations
    at: Solution
    round: int
    found: Found
    ours: Solution
    then: Then
    note: str = ""
    joined: bool = False


@dataclass(frozen=True)
class Joint:
    """A joint solve of a round (``range_bias``: with the range offset and the marker range bias estimated)."""

    rounds: Rounds
    range_bias: bool


@dataclass(frozen=True)
class AllPlanes:
    """The joint solve with every other plane of the scene too (``rounds.found``: all of them), with the rounds'
    ``notes`` and the range bias estimated where the rounds' estimate determined it."""

    rounds: Rounds
    notes: tuple[str, ...]
    range_bias: bool


@dataclass(frozen=True)
class Refit:
    """The marker-only solve again: from the marker-only solution with a scale freed (``judged``: None), or with
    the blobs some rounds left out (:class:`Unjoined`), or with the blobs as judged at the joint solution (the
    rounds' end ``judged`` and the judgement's notes)."""

    after: Unjoined | None = None
    judged: Ended | None = None
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class Settled:
    """The refinement ended: the joint estimate's rounds (``joint``)."""

    joint: Ended


#: where the marker way's choices stand after a solve
Step = FromStart | Once | Stood | Chosen | Joint | AllPlanes | Refit | Settled


@dataclass(frozen=True)
class Refining:
    """What the refinement keeps beside the sets: the alternative's marker-only solution and the refinement's notes
    so far (scales found off, blobs judged)."""

    marker_only: Solution
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class MarkerSets:
    """One solve of the marker way: the alternative's returns, where the solve starts (``origin`` and the clock
    offset ``tau``), the step (what it solves beyond the marker-only problem, and what follows), and the refinement
    so far (None before the choice)."""

    alt: Alternative
    origin: Params
    tau: float
    step: Step
    refining: Refining | None = None

    @property
    def refined(self) -> Refining:
        """The refinement so far (the sets after the choice)."""
        assert self.refining is not None, "the refinement begins at the choice (Chosen)"
        return self.refining


__all__ = ["AllPlanes", "Alternative", "Chosen", "Ended", "Found", "FromStart", "Joint", "Judging", "MarkerSets",
           "Once", "Refining", "Refit", "Rounds", "Scales", "Settled", "Step", "Stood", "Then", "Unjoined"]
