"""One promise (issue 56): `lrfsim plan` and `lrfcal calibrate` judge a layout by one rule, and a rig whose mirror image
nothing tells apart is refused naming it, through the installed console scripts.

The layout: a random near-perpendicular truth of the project's generator (lrfsim.testing.random_scenarios, broad seed
2: the scan plane 4.0 deg from perpendicular to the motor axis, a spin of 1.1 turns, markers where the beams meet the
tunnel), its rig file's alpha set to exactly 0, as a drawing of a scanner mounted square on its motor would give it.
Tape distances fix the marker map only up to a reflection, and the rig's mirror image (alpha +4.0 deg, b negated)
explains every return as well: the nominal lies between the two and cannot tell them apart. Plan must say so before
the rig is built, and calibrate must refuse with the same reason rather than report either (issue 56 found such a
rig calibrated to its mirror image with exit 0 and every check passed).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from test_cli_usage import _one_error_line, _run

from lrfsim.scenario.file import with_changes
from lrfsim.testing.random_scenarios import random_scenario_wide


@pytest.fixture(scope="module")
def mirror_tie(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The scenario file of the layout above (module docstring)."""
    sc = random_scenario_wide(2, broad=True)
    data = with_changes(sc.model_dump(mode="json"), {"rig.nominal_dh.alpha": 0.0, "name": "mirror_tie"})
    path = tmp_path_factory.mktemp("promise") / "mirror_tie.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_plan_and_calibrate_refuse_a_rig_whose_mirror_image_nothing_tells_apart(mirror_tie: Path,
                                                                                 tmp_path: Path) -> None:
    plan = _run("lrfsim", "plan", mirror_tie, "--json", "-q", timeout=600)
    said = json.loads(plan.stdout)  # printed whatever the verdict
    assert said["determined"] is False and "mirror image" in said["verdict"], said["verdict"]
    assert "a nominal alpha away from 0" in said["verdict"], said["verdict"]
    line = _one_error_line(plan, code=3)
    assert "the calibration would refuse: the rig cannot be told from its mirror image" in line, line
    rec = tmp_path / "rec"
    sim = _run("lrfsim", "simulate", mirror_tie, "-o", rec, "-q", timeout=600)
    assert sim.returncode == 0, sim.stderr
    out = tmp_path / "cal"
    cal = _run("lrfcal", "calibrate", rec, "-o", out, "--no-figures", timeout=600)
    line = _one_error_line(cal, code=3)
    assert line.startswith("error: mirror image:") and "a nominal alpha away from 0" in line, line
    assert not out.exists(), "a refusal writes nothing"
