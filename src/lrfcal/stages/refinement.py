"""6b: the marker way's sets chosen again after the choice of its alternative (lrfcal.stages.markers.MarkerWay's
``reselect``), one solve at a time: each step says what the next solve adds, and what follows its solution.

1. **The joint rounds** (lrfcal.stages.joint): from the marker-only solution, the surfaces the markers sit on and
   their returns chosen at the estimate and solved jointly with the markers (the range offset and the marker range
   bias too, held at 0 where the recording does not separate them), chosen again at the joint estimate while it moves
   them (lrfcal.stages.surfaces.RESELECT_M, at most ROUNDS times); then every other plane of the scene with
   ``all_planes``.
2. **The scales** the joint solution contradicts (lrfcal.stages.joint.most_off): freed, the marker-only solution
   solved again with it, and the rounds again from there.
3. **The blobs judged at the joint solution**: a disagreement with the marker map that the marker-only fit found but
   could not judge, as it does not determine the DH parameters (one scan line per marker: there a wrong match cannot
   be told from a moved marker, and a good marker can look moved), judged where the surfaces determine them: the
   blobs that disagree there (lrfcal.stages.association.inconsistent_blobs) left out and the rounds run again from
   the joint solution, at most three times; the marker-only solution solved again with the blobs kept. Where no
   surface returns lie where the marker-only fit puts them (a wrong match can pull it far), the rounds start from the
   marker-only fit without the blobs it finds disagreeing (at most three times), and every blob is judged from there.

Refused (CalibrationError): no surface returns to judge by, or blobs that still disagree after three are left out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from lrfcal.errors import CalibrationError
from lrfcal.estimate import observability
from lrfcal.stages import association, joint, surfaces
from lrfcal.stages.alternatives import without_blobs
from lrfcal.stages.marker_sets import (
    AllPlanes,
    Chosen,
    Ended,
    Found,
    Joint,
    Judging,
    MarkerSets,
    Refining,
    Refit,
    Rounds,
    Scales,
    Settled,
    Then,
    Unjoined,
)
from lrfcal.types import Association, Fit, Observations, Solution

#: what follows a solve: the next sets to solve, the estimate on sets chosen again (nothing to solve), or none
Next = MarkerSets | Fit[MarkerSets] | None


@dataclass(frozen=True)
class Context:
    """What the refinement's choices read: its configuration (lrfcal.stages.markers.RefineConfig) and the recording
    as the joint solve reads it (its signed joint states and its detections)."""

    config: joint.JointConfig
    max_reduced_chi2: float
    recorded: joint.Recorded


def refined(ctx: Context, fit: Fit[MarkerSets]) -> Next:
    """The sets chosen again after the solve of ``fit.sets`` gave ``fit.solution`` (module docstring)."""
    sets, sol = fit.sets, fit.solution
    match sets.step:
        case Chosen():
            return _begin(ctx, replace(sets, refining=Refining(sol)), sol, sets.alt.matched, Scales())
        case Joint() as step:
            return _after_joint(ctx, sets, step, sol)
        case AllPlanes() as step:
            return _then(ctx, sets, step.rounds.then, Ended(sol, step.rounds.found, step.notes, True))
        case Refit(after=None, judged=None):  # a scale freed: the rounds again from the marker-only solution
            return _begin(ctx, replace(sets, refining=replace(sets.refined, marker_only=sol)), sol, sets.alt.matched,
                          Scales())
        case Refit(after=Unjoined() as after):
            return _begin(ctx, sets, sol, after.matched, replace(after, sol=sol))
        case Refit(judged=Ended() as judged) as step:
            refining = Refining(sol, (*sets.refined.notes, *step.notes))
            notes = (*refining.notes, *judged.notes)
            return Fit(replace(sets, alt=replace(sets.alt, notes=(*sets.alt.notes, *notes)), refining=refining,
                               step=Settled(judged)), judged.ours)
    return None


def _begin(ctx: Context, sets: MarkerSets, origin: Solution, matched: Observations, then: Then) -> Next:
    """The joint rounds from ``origin`` with the returns ``matched`` (the marker-only solution itself, with nothing
    found, where the surfaces are not asked for)."""
    rounds = Rounds(origin, matched, origin, 0, Found(), origin, then)
    if not ctx.config.surfaces:
        return _then(ctx, sets, then, Ended(origin, Found(), (), False))
    return _round(ctx, sets, rounds)


def _round(ctx: Context, sets: MarkerSets, r: Rounds) -> Next:
    """A round: the surfaces chosen at ``r.at`` (the first choice kept even when empty), solved jointly; the rounds
    end where none are found."""
    found, returns = joint.surfaces_at(r.at, sets.alt.markers, ctx.recorded, ctx.config)
    if r.found.returns is None or len(returns):
        r = replace(r, found=Found(tuple(found), returns))
    if not len(returns):
        return _ended(ctx, sets, r)
    return _solve(sets, r.at, Joint(r, ctx.config.estimate_range_bias))


def _solve(sets: MarkerSets, at: Solution, step: Joint | AllPlanes | Refit) -> MarkerSets:
    return replace(sets, origin=at.params, tau=at.clock_offset_s, step=step)


def _after_joint(ctx: Context, sets: MarkerSets, step: Joint, sol: Solution) -> Next:
    """After a round's joint solve: solved again with the range bias held where it is not separable; the next round
    where the estimate moved the surface returns beyond RESELECT_M (after ROUNDS the last stands)."""
    r = step.rounds
    if step.range_bias and (why := joint.unseparated_range_bias(sol)):
        return _solve(sets, r.at, Joint(replace(r, note=why), False))
    r = replace(r, ours=sol, joined=True)
    assert r.found.returns is not None
    moved = surfaces.moved_m(r.found.returns, (r.at.params, r.at.intrinsic_values), (sol.params, sol.intrinsic_values))
    if moved <= surfaces.RESELECT_M or r.round + 1 >= surfaces.ROUNDS:
        return _ended(ctx, sets, r)
    return _round(ctx, sets, replace(r, at=sol, round=r.round + 1))


def _ended(ctx: Context, sets: MarkerSets, r: Rounds) -> Next:
    """The rounds' end: their notes; with ``all_planes``, every other plane of the scene solved jointly too."""
    notes = (r.note,) if r.note else ()
    if r.found.returns is not None and not len(r.found.returns) and ctx.config.estimate_range_bias:
        notes = (*notes, joint.NO_SURFACE_RANGE_BIAS)
    if ctx.config.all_planes:
        every = joint.every_plane(r.ours, (list(r.found.surfaces), r.found.returns), ctx.recorded, ctx.config)
        if every is not None:
            found = Found(tuple(every.value[0]), every.value[1])
            return _solve(sets, r.ours, AllPlanes(replace(r, found=found), (*notes, *every.notes),
                                                  math.isfinite(r.ours.range_offset_sigma_m)))
    return _then(ctx, sets, r.then, Ended(r.ours, r.found, notes, r.joined))


def _then(ctx: Context, sets: MarkerSets, then: Then, ended: Ended) -> Next:
    """What follows the rounds."""
    match then:
        case Scales():
            return _scales(ctx, sets, ended)
        case Unjoined() as after:
            if ended.joined:
                return _judge(ctx, sets, ended.ours)
            return _unjoined(ctx, sets, after.left_out + 1, after.sol, after.assoc, after.matched)
        case Judging() as judging:
            return _judged(ctx, sets, judging, ended)
    raise AssertionError(then)


def _scales(ctx: Context, sets: MarkerSets, ended: Ended) -> Next:
    """A scale the joint solution contradicts freed, and the marker-only solution solved again with it; else the
    unjudged blobs judged, or the refinement ends."""
    refining, alt = sets.refined, sets.alt
    if off := joint.most_off(ended.ours, ctx.max_reduced_chi2):
        alt = replace(alt, estimate=(*alt.estimate, off.value))  # estimated in every solve from then on
        return _solve(replace(sets, alt=alt, refining=replace(refining, notes=(*refining.notes, *off.notes))),
                      refining.marker_only, Refit())
    if alt.unjudged:
        if not ended.joined:  # no surface returns where the marker-only fit puts them: try it without the blobs
            return _unjoined(ctx, sets, 0, refining.marker_only, alt.assoc, alt.matched)  # it finds disagreeing
        return _judge(ctx, sets, ended.ours)
    notes = (*refining.notes, *ended.notes)
    return Fit(replace(sets, alt=replace(alt, notes=(*alt.notes, *notes)), step=Settled(ended)), ended.ours)


def _unjoined(ctx: Context, sets: MarkerSets, left_out: int, sol: Solution, assoc: Association,
              matched: Observations) -> Next:
    """The marker-only fit ``sol`` without the blobs it finds disagreeing, for a start only: solved again and the
    rounds run from it, until they join the surfaces (at most three times; refused where they never do)."""
    assert ctx.config.range_sigma_m is not None  # resolved by lrfcal.pipeline.calibrate
    bad, why = (association.inconsistent_blobs(matched, sol, sets.alt.markers, ctx.config.range_sigma_m)
                if left_out < 3 else (None, ""))
    if bad is None or not bad.size:
        raise _no_surfaces(sets)
    kept = without_blobs(assoc, matched, bad, why)
    return _solve(sets, sol, Refit(after=Unjoined(left_out, *kept, sol)))


def _no_surfaces(sets: MarkerSets) -> CalibrationError:
    return CalibrationError(observability.unjudged_refusal(
        _observability(sets.refined.marker_only), "the markers alone", "and no surface returns were found to add",
        sets.alt.unjudged))


def _judge(ctx: Context, sets: MarkerSets, start: Solution) -> Next:
    """Every blob judged at the joint solution ``start``: the rounds from it with the blobs kept so far."""
    if start.n_surface_returns == 0:
        raise _no_surfaces(sets)
    alt = sets.alt
    return _begin(ctx, sets, start, alt.matched, Judging(0, alt.assoc, alt.matched, start))


def _judged(ctx: Context, sets: MarkerSets, judging: Judging, ended: Ended) -> Next:
    """After the rounds from the joint solution: the blobs that disagree there left out and the rounds again (what
    leads a refusal after three: the cause the data support); where none do, the marker-only solution solved again
    with the blobs kept."""
    if not ended.joined:  # no surface returns for these blobs
        raise _no_surfaces(sets)
    assert ctx.config.range_sigma_m is not None  # resolved by lrfcal.pipeline.calibrate
    tried, alt, notes = ended.ours, sets.alt, judging.notes
    bad, why = association.inconsistent_blobs(judging.matched, tried, alt.markers, ctx.config.range_sigma_m)
    if not bad.size:
        if not judging.left_out:
            notes = (*notes, f"the marker-only fit disagreed with the marker map ({alt.unjudged}); the joint solution "
                     "with the surfaces does not (the markers alone do not determine the DH parameters here)")
        kept = replace(alt, assoc=judging.assoc, matched=judging.matched, unjudged="")
        return _solve(replace(sets, alt=kept), sets.refined.marker_only, Refit(judged=ended, notes=notes))
    if judging.left_out == 3:
        raise CalibrationError(observability.unjudged_refusal(
            _observability(tried), "the markers and the surfaces they sit on", "",
            f"{why.removesuffix(': left out')}, judged at the joint solution with the surfaces, after three blobs "
            "were left out"))
    assoc, matched = without_blobs(judging.assoc, judging.matched, bad, why)
    return _begin(ctx, sets, judging.start, matched, Judging(judging.left_out + 1, assoc, matched, judging.start,
                                                             (*notes, f"{why} (judged at the joint solution with "
                                                                      "the surfaces)")))


def _observability(sol: Solution) -> observability.Observability:
    return observability.of_solution(sol.information, sol.information_names, sol.dh_sigma, sol.params.dh.alpha)


__all__ = ["Context", "Next", "refined"]
