"""`lrfsim plan` as text: the predicted sigma table, the verdict (the rule `lrfcal calibrate` refuses on), what would
strengthen the weakest direction, the tolerances, the held scales and the smallest drift `lrfcal check` detects."""

from __future__ import annotations

import math

from lrfcal import DEFAULT_FALSE_ALARM, LIMITS, SCALE_Z_LIMIT
from lrfcal.model.unknowns import BY_NAME
from lrfsim.plan.result import REACHABLE_K, Plan, format_value


def format_plan(p: Plan, false_alarm: float = DEFAULT_FALSE_ALARM) -> str:
    """The plan as text: the sigma table, the weakest direction, what would strengthen it, the tolerances, the
    smallest drift `lrfcal check` detects (:meth:`Plan.check_detects` at ``false_alarm``)."""
    lines = [f"plan {p.scenario}: {p.n_returns} marker returns on {p.n_markers_seen}/{p.n_markers} markers, "
             f"{p.n_surface_returns} surface returns, range noise {p.range_sigma_m * 1000:g} mm"
             + (f", correlated {p.range_correlation:g} between neighbouring beams" if p.range_correlation else ""),
             f"information: {p.information_source}", "",
             f"{'parameter':<14}{'predicted 1-sigma':>20}{'model-error part':>20}{'tape part':>14}{'limit':>14}"]
    for n in p.names:
        model = format_value(n, p.model_sigma[n]) if n in p.model_sigma else "-"
        tape = format_value(n, p.map_sigma[n]) if n in p.map_sigma else "-"
        lines.append(f"{n:<14}{format_value(n, p.sigma[n]):>20}{model:>20}{tape:>14}{format_value(n, LIMITS[n]):>14}")
    lines.append("")
    state = "determined" if p.determined else "NOT DETERMINED (the calibration would refuse, exit 3)"
    alone = (f"; {p.observability.weakest_sigma_in_limits:.2g} from the marker returns alone, the test the "
             "calibration refuses on before solving")
    lines.append(f"DH parameters: {state}; weakest direction: {p.weakest} "
                 f"(1-sigma {p.final_observability.weakest_sigma_in_limits:.2g} of the limit in the covariance above, "
                 f"as `lrfcal calibrate` judges it after solving{alone})")
    if not p.determined:
        lines.append(f"why: {p.verdict.reason() or 'a DH parameter has no finite sigma'}")
    lines.append(f"to strengthen it: {p.strengthen}")
    lines.append(f"tolerances (reachable when >= {REACHABLE_K:g} x predicted sigma):")
    for t in p.tolerances:
        ratio = t.tolerance / t.predicted if t.predicted > 0 and math.isfinite(t.predicted) else 0.0
        name = t.name if t.name in p.sigma else ("x" if t.name == "position" else "rx")
        lines.append(f"  {t.name:<10} {format_value(name, t.tolerance):>12} = {ratio:6.1f} sigma  "
                     f"{'reachable' if t.reachable else 'NOT reachable'}")
    lines.append(f"tolerances reachable: {'yes' if p.tolerances_reachable else 'no'}")
    if p.scale_sigma:
        lines.append(f"intrinsics held and tested, the scales at 1 and the incidence bias at 0 (estimated where the "
                     f"data put them beyond {SCALE_Z_LIMIT:g} sigma): the smallest error found, at least")
        lines.extend(f"  {n:<14} 1-sigma {_held_error(n, v)}: {_held_error(n, SCALE_Z_LIMIT * v)} or more"
                     for n, v in p.scale_sigma.items())
    detects = p.check_detects(false_alarm)
    lines.append(f"lrfcal check with this recording against a calibration of the same layout: the smallest drift of "
                 f"each parameter alone it detects with 95 % probability at a false-alarm rate of "
                 f"{100 * false_alarm:g} % ({len(detects)} parameters tested):")
    lines.append("  " + ", ".join(f"{n} {format_value(n, v)}" for n, v in detects.items()))
    lines.extend(f"note: {n}" for n in p.notes)
    lines.append(f"({p.seconds:.1f} s)")
    return "\n".join(lines)


def _held_error(name: str, v: float) -> str:
    """An error of a held intrinsic: a scale's in percent, the incidence bias's in mm per radian."""
    return f"{100 * v:.2g} %" if BY_NAME[name].unit == "1" else f"{1000 * v:.2g} mm/rad"


__all__ = ["format_plan"]
