"""A refusal leads with the cause the data support (issue 46, case 5).

Near-perpendicular random rigs (lrfsim.testing.random_scenarios.random_scenario_wide(seed, broad=True), seed % 3 == 2)
whose markers alone do not determine b and beta were refused with "marker mXX: its returns sit 6-31 mm from its tape
position (moved after taping?)" and told to sweep slower, in clean simulations where no marker moved. Where the DH
parameters are not determined, good markers look moved; the refusal now leads with what the data do not determine and
its remedy (lrfcal.estimate.observability.unjudged_refusal), and the failed checks are ranked
(lrfcal.estimate.checks.FOLLOWS_FROM).
"""

from __future__ import annotations

import math
import subprocess
from pathlib import Path

import numpy as np
import pytest
from conftest import console_script

from lrfcal.config import CalibConfig
from lrfcal.errors import CalibrationError
from lrfcal.estimate.checks import refuse_failed
from lrfcal.estimate.observability import LIMITS, Observability, of_solution, unjudged_refusal
from lrfcal.types import Check
from lrfsim.simulation.recording import write_recording
from lrfsim.simulation.simulate import simulate
from lrfsim.testing.random_scenarios import alpha_kind_of, random_scenario_wide
from lrfsim.trials.variants import with_field

DISAGREEMENT = "marker m17: its returns sit 14 mm from its tape position on average (moved after taping?)"




def test_near_perpendicular_rig_is_refused_for_what_it_does_not_determine(tmp_path: Path) -> None:
    # seed 77 of the broad random truths (scan plane 3.5 deg from perpendicular, 19 markers on the tunnel's walls,
    # no surface returns found), shortened from 1.66 to 0.7 turns: the marker-only fit leaves b and beta 2x
    # beyond their limits and sees marker m17 14 mm off its tape position; before, the refusal's first words
    # blamed m17 ("moved after taping?") and advised a slower sweep
    sc = with_field(random_scenario_wide(77, broad=True), "servo.revolutions", 0.7)
    assert alpha_kind_of(sc) == "near_perpendicular"
    rec = tmp_path / "rec"
    write_recording(simulate(sc), sc, rec)
    proc = subprocess.run([console_script("lrfcal"), "calibrate", str(rec), "-o", str(tmp_path / "cal"),
                           "--no-figures", "--no-baseline", "-q"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 3, (proc.returncode, proc.stderr)
    assert "Traceback" not in proc.stderr, proc.stderr
    first = proc.stderr.strip().splitlines()[0]
    assert first.startswith("error: the markers alone do not determine b, beta here"), first
    assert "tilt the scan plane further from perpendicular" in first, first  # the remedy of that cause
    lead = first.split("; at such a solution")[0]
    assert "moved" not in lead and "sweep slower" not in first, first
    assert "moved after taping?" not in first, first  # the symptom is named, without blaming the marker
    assert not (tmp_path / "cal").exists()


def _obs(sigma: list[float], alpha: float = 0.05) -> Observability:
    info = np.diag(1.0 / np.asarray(sigma) ** 2)
    return of_solution(info, ("a", "alpha", "b", "beta"), np.asarray(sigma), alpha)


def test_unjudged_refusal_ranks_observability_before_a_moved_marker() -> None:
    loose = _obs([1e-4, 1e-3, 2.0 * LIMITS["b"], 1e-3])  # b twice its limit, the plane 2.9 deg from perpendicular
    assert not loose.determined
    text = unjudged_refusal(loose, "the markers alone", "and no surface returns were found to add", DISAGREEMENT)
    assert text.startswith("the markers alone do not determine b here (b alone; 1-sigma a 0.1 mm"), text
    assert "b 10 mm" in text and "tilt the scan plane further from perpendicular" in text, text
    assert text.endswith("(marker m17: its returns sit 14 mm from its tape position on average)"), text
    tight = _obs([1e-4, 1e-3, 1e-3, 1e-3])  # determined: then the marker's disagreement is the finding
    assert tight.determined
    text = unjudged_refusal(tight, "the markers and the surfaces they sit on", "", DISAGREEMENT)
    assert text.startswith(DISAGREEMENT) and "do not determine" not in text, text
    assert "sweep slower or more passes" in text, text  # one scan line per marker: the sweep's remedy


def test_a_widened_sigma_beyond_the_limit_is_not_determined() -> None:
    info = np.diag(1.0 / np.array([1e-4, 1e-3, 1e-3, 1e-3]) ** 2)  # the information alone determines them
    widened = np.array([1e-4, 1e-3, 1e-3, math.radians(1.5)])  # the reported beta beyond its 1 deg
    obs = of_solution(info, ("a", "alpha", "b", "beta"), widened, math.radians(90.0))
    assert not obs.determined and obs.undetermined == ("beta",)
    assert of_solution(None, (), widened, 0.0).determined is False  # rank loss: nothing is determined


def test_failed_checks_lead_with_observability() -> None:
    checks = [Check("convergence", False, "stopped at the iteration limit"), Check("mirror image", True, "ok"),
              Check("observability", False, "weakest direction b alone at 3 of the limit"),
              Check("second opinion", False, "even and odd passes differ")]
    with pytest.raises(CalibrationError) as err:
        refuse_failed(checks, CalibConfig())
    assert str(err.value).startswith("observability: weakest direction b alone"), err.value
    assert "(and 2 more failed checks)" in str(err.value)
    with pytest.raises(CalibrationError, match=r"^convergence: stopped"):  # without it, the checks' own order
        refuse_failed([checks[0], checks[3]], CalibConfig())
    agree = Check("starts agree", False, "another minimum fits the scene's planes as well, beta 3 sigma apart")
    with pytest.raises(CalibrationError, match=r"^starts agree: "):  # a cause observability follows from leads
        refuse_failed([agree, *checks], CalibConfig())


def test_a_targetless_cost_that_runs_off_from_the_rig_files_dh_is_refused_for_convergence() -> None:
    """When the solve from the rig file's DH ends where too few returns count (its cost ran off: the real URG-04LX
    box from a rig file 0.05 deg off inspect's proposal, tests/test_real_walkthrough.py), the calibration's refusal
    names the check and what the data say (the scene's planes do not hold the DH there) with the start, not the
    solver's count of returns per unknown."""
    from lrfcal.errors import RunOffError
    from lrfcal.model.kinematics import DH
    from lrfcal.stages.scene import PlaneWay
    from lrfcal.stages.starts import PlaneStart
    from lrfcal.types import Tried

    start = PlaneStart("the rig file's DH", DH(-0.1553, math.radians(89.27), 0.0272, 0.0034))
    ran_off = RunOffError("targetless solve: 0 of 69413 plane returns count at the estimate", 0, 69413)
    way = PlaneWay.__new__(PlaneWay)  # choose reads nothing of the way before the first start's outcome
    with pytest.raises(CalibrationError) as err:
        way.choose(None, [Tried(start, ran_off)])  # type: ignore[arg-type]
    text = str(err.value)
    assert text.startswith("convergence: ") and "0 of its 69413 returns" in text, text
    assert "a -155.3 mm, alpha 89.27 deg, b 27.2 mm, beta 0.19 deg" in text and "do not hold the DH" in text, text
    assert "need 10 each" not in text
