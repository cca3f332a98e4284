"""Stage 3: beam times and motor angles by linear interpolation of the joint states."""

from __future__ import annotations

import numpy as np
import pytest

from lrfcal.errors import InputError
from lrfcal.stages.timing import beam_motor_angles, beam_times, covered_scans, motor_angles, scan_angles
from lrfcal.types import JointStates, Scans

T0 = 1_700_000_000.0
OMEGA = 0.8  # rad/s


def _joints(t0=T0 - 0.05, t1=T0 + 1.05, dt=0.01, phase=0.3) -> JointStates:
    t = np.linspace(t0, t1, int(round((t1 - t0) / dt)) + 1)
    return JointStates(stamps_s=t, positions_rad=phase + OMEGA * (t - T0))


def _scans(S=20, N=1081, t_inc=0.025 / 1440) -> Scans:
    stamps = T0 + 0.025 * np.arange(S)
    z = np.zeros((S, N))
    return Scans(stamps_s=stamps, ranges_m=z + 1.0, intensities=z, mu_rad=np.linspace(-2.356, 2.356, N),
                 time_increment_s=t_inc, scan_time_s=0.025, range_min_m=0.023, range_max_m=60.0)


def test_beam_times():
    s = _scans()
    t = beam_times(s)
    assert t.shape == (20, 1081)
    assert t[3, 0] == s.stamps_s[3]
    assert t[3, 1080] - t[3, 0] == pytest.approx(1080 * 0.025 / 1440, abs=1e-6)  # float64 epoch: 0.2 us
    np.testing.assert_array_equal(t, s.beam_times_s)


def test_interpolation_exact_on_linear_motion():
    j = _joints()
    t = T0 + np.random.default_rng(0).uniform(0, 1, (7, 5))
    lam = motor_angles(t, j)
    assert lam.shape == (7, 5)
    np.testing.assert_allclose(lam, 0.3 + OMEGA * (t - T0), atol=1e-6)


def test_per_beam_angles_change_within_a_scan():
    s, j = _scans(), _joints()
    lam = beam_motor_angles(s, j)
    assert lam.shape == s.ranges_m.shape
    np.testing.assert_allclose(lam[:, -1] - lam[:, 0], OMEGA * 1080 * 0.025 / 1440, atol=1e-6)
    np.testing.assert_allclose(scan_angles(s, j), lam[:, 0], atol=1e-12)


def test_clock_offset():
    # laser stamp = servo stamp + offset: a laser time t is the servo time t - offset
    j = _joints()
    off = 0.0123
    t = T0 + np.array([0.2, 0.5, 0.9])
    lam = motor_angles(t, j, clock_offset_s=off)
    np.testing.assert_allclose(lam, 0.3 + OMEGA * (t - off - T0), atol=1e-6)


def test_wrapped_encoder_is_unwrapped():
    t = np.arange(0.0, 2.0, 0.01)
    true = 3.0 + 1.0 * t  # crosses +pi
    wrapped = (true + np.pi) % (2 * np.pi) - np.pi
    j = JointStates(stamps_s=t, positions_rad=wrapped)
    q = np.array([0.105, 0.145, 0.5])
    lam = motor_angles(q, j)
    np.testing.assert_allclose(np.cos(lam), np.cos(3.0 + q), atol=1e-9)
    np.testing.assert_allclose(np.sin(lam), np.sin(3.0 + q), atol=1e-9)


def test_out_of_span_error_and_tolerance():
    j = _joints(T0, T0 + 1.0)
    # within one sample period: extrapolated linearly
    lam = motor_angles([T0 - 0.005, T0 + 1.008], j)
    np.testing.assert_allclose(lam, 0.3 + OMEGA * np.array([-0.005, 1.008]), atol=1e-6)
    with pytest.raises(InputError, match=r"time 1699999999.950000 s .* outside the joint-state span"):
        motor_angles([T0 - 0.05], j)
    with pytest.raises(InputError, match="outside the joint-state span"):
        motor_angles([T0 + 1.5], j)
    with pytest.raises(InputError, match="outside"):
        motor_angles([T0 + 0.995], j, clock_offset_s=-0.1)


def test_covered_scans():
    s = _scans(S=20)
    j = _joints(T0 + 0.1, T0 + 0.4)
    m = covered_scans(s, j)
    # scans k with stamp >= T0+0.09 (tolerance 10 ms) and last beam <= T0+0.41
    k = np.arange(20)
    t0 = T0 + 0.025 * k
    expect = (t0 >= T0 + 0.09 - 1e-9) & (t0 + 1080 * 0.025 / 1440 <= T0 + 0.41 + 1e-9)
    np.testing.assert_array_equal(m, expect)
    motor_angles(beam_times(s)[m], j)
