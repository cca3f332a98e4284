"""lrfcal.checks: the scan plane's attitude (a DH chain near its singularity is refused, not trusted)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lrfcal.checks import NEAR_PERPENDICULAR_RAD, attitude_check
from lrfcal.model.kinematics import DH, Params, Pose
from lrfcal.types import Solution


def _solution(alpha: float) -> Solution:
    return Solution(params=Params(Pose(), DH(0.01, alpha, 0.02, 0.0)), covariance=np.eye(10), sigma=np.ones(10),
                    residual_rms_m=0.0, residuals_m=np.zeros((0, 3)), per_marker_rms_m=np.zeros(0), n_observations=0,
                    n_iterations=0, status="")


@pytest.mark.parametrize("alpha_deg", [0.0, 4.0, -8.1, 14.0, 20.1, -26.6, 180.0, -172.0, 155.0])
def test_near_perpendicular_scan_plane_is_refused(alpha_deg: float) -> None:
    check = attitude_check(_solution(math.radians(alpha_deg)).params.dh)
    assert not check.passed
    assert "near-singular" in check.detail and f"{alpha_deg:.1f}" in check.detail


@pytest.mark.parametrize("alpha_deg", [90.0, -90.0, 35.0, 140.0, 45.0])
def test_other_attitudes_pass(alpha_deg: float) -> None:
    assert math.degrees(NEAR_PERPENDICULAR_RAD) <= 35.0
    assert attitude_check(_solution(math.radians(alpha_deg)).params.dh).passed


def test_plan_says_a_near_perpendicular_rig_would_be_refused() -> None:
    """`lrfsim plan` applies the same attitude check: the spinning rig tilted 35 deg is determined, at 25 deg not."""
    from pathlib import Path

    import yaml

    from lrfsim.plan import plan
    from lrfsim.scenario import parse_scenario, with_changes

    data = yaml.safe_load((Path(__file__).resolve().parents[1] / "scenarios" / "spinning_tilted.yaml").read_text())
    assert plan(parse_scenario(data, "tilted_35")).attitude_ok
    flat = with_changes(data, {"rig.dh.alpha": math.radians(25.0), "rig.nominal_dh.alpha": math.radians(25.0)})
    p = plan(parse_scenario(flat, "tilted_25"))
    assert not p.attitude_ok and not p.determined
    assert any("near-singular" in n for n in p.notes), p.notes


def test_placeholder_dh_is_refused_naming_the_key(shipped_recording, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """A rig file whose DH are all 0 (what `lrfcal inspect` writes to be filled in): exit 2 naming ``dh``, before any
    work, through the installed console script."""
    import shutil
    import subprocess

    import yaml

    rec = tmp_path / "rec"
    shutil.copytree(shipped_recording("tunnel_v"), rec)
    rig = yaml.safe_load((rec / "nominal.yaml").read_text())
    rig["dh"] = {"a": 0, "alpha": 0, "b": 0, "beta": 0}
    (rec / "nominal.yaml").write_text(yaml.safe_dump(rig))
    out = subprocess.run([shutil.which("lrfcal") or "lrfcal", "calibrate", str(rec), "-o", str(tmp_path / "cal"),
                          "--quiet"], capture_output=True, text=True)
    assert out.returncode == 2, out.stderr
    assert "dh" in out.stderr and "placeholder" in out.stderr and "Traceback" not in out.stderr
    assert not (tmp_path / "cal").exists()


# --- the chain's exact twins and the mirror-image check (issue 18, item 2) ----------------------------------------

def test_dh_twins_are_the_same_cloud_moved_by_their_isometry() -> None:
    """Each twin's cloud is the rig's moved by its fixed isometry Q for every range, motor angle and bearing; Q
    commutes with the motor's turn; only "turned" is a proper rotation (the same rig, the mount absorbs it)."""
    from lrfcal.model.kinematics import dh_twins, points_M, rot_z

    rng = np.random.default_rng(7)
    r, lam, mu = rng.uniform(0.3, 8, 500), rng.uniform(-7, 7, 500), rng.uniform(-2.4, 2.4, 500)
    for dh in (DH(a=0.03, alpha=1.2, b=0.07, beta=0.4), DH(a=-0.01, alpha=-2.9, b=0.2, beta=-3.0)):
        P = points_M(r, lam, mu, dh)
        proper = []
        for name, twin, Q in dh_twins(dh):
            np.testing.assert_allclose(points_M(r, lam, mu, twin), P @ Q.T, atol=1e-12, err_msg=name)
            np.testing.assert_allclose(Q @ rot_z(0.7), rot_z(0.7) @ Q, atol=1e-15)
            if np.linalg.det(Q) > 0:
                proper.append(name)
        assert proper == ["turned"]


def test_mirror_check_passes_when_the_nominal_tells_the_rig_from_its_mirror_image() -> None:
    from lrfcal.checks import mirror_check
    from lrfcal.config import CalibConfig

    config = CalibConfig()
    est = DH(a=0.012, alpha=math.radians(35.0), b=0.04, beta=0.1)
    near = mirror_check(est, DH(a=0.010, alpha=math.radians(33.0), b=0.042, beta=0.09), config)
    assert near.passed and "mirror image" in near.name
    # 45 deg off, but the mirror image (alpha -35 deg) is farther still: passed
    assert mirror_check(est, DH(a=0.012, alpha=math.radians(80.0), b=0.04, beta=0.1), config).passed


def test_mirror_check_refuses_a_nominal_nearer_the_mirror_image_naming_both() -> None:
    """A nominal alpha of -10 deg for an estimate of +35 deg: the mirror image (alpha -35 deg, b negated) is nearer
    the drawings than the estimate, and the data cannot tell them apart: refused, naming the mirror image."""
    from lrfcal.checks import mirror_check
    from lrfcal.config import CalibConfig

    est = DH(a=0.012, alpha=math.radians(35.0), b=0.04, beta=0.1)
    c = mirror_check(est, DH(a=0.012, alpha=math.radians(-10.0), b=0.0, beta=0.1), CalibConfig())
    assert not c.passed
    assert "mirrored" in c.detail and "alpha -35.00 deg" in c.detail and "signs of alpha and b" in c.detail
