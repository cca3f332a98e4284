"""Stage 2: range-normalised threshold, 8-connected blobs, peaks, observations and blob centres."""

from __future__ import annotations

import numpy as np
import pytest

from lrfcal.model.kinematics import DH, points_M
from lrfcal.stages.detection import (
    MAX_CONTRAST,
    MIN_CONTRAST,
    blob_centres_M,
    contrast,
    detect,
    observations,
    split_by_pass,
)
from lrfcal.types import Blob, Detections, JointStates, Scans

S, N = 240, 400
T0 = 1_700_000_000.0
T_INC = 0.025 / 1440


def _image(seed=0, cos_min=0.3):
    """A scene whose background spans >3 orders of magnitude of intensity over range 0.4..20 m.

    Returns scans and the list of markers (pixels, peak pixel).
    """
    rng = np.random.default_rng(seed)
    s = np.arange(S)[:, None]
    b = np.arange(N)[None, :]
    # smooth range field: near on the left, far on the right, varying with scan
    r = 0.4 * np.exp(np.log(50.0) * b / (N - 1)) * (1 + 0.1 * np.sin(s / 30.0))
    cos_inc = rng.uniform(cos_min, 1.0, (S, N))
    inten = 3e4 * cos_inc / r**2 * np.exp(rng.normal(0, 0.1, (S, N)))
    r = r + rng.normal(0, 0.01, (S, N))
    r[100:120, 150:180] = np.nan  # no returns
    markers = []
    # (scan, beam) corners and shapes incl. all four image borders and both range extremes
    for (s0, b0, hs, hb) in [(0, 0, 2, 2), (S - 2, N - 3, 2, 3), (50, 0, 3, 2), (0, 200, 2, 3),
                             (120, N - 2, 3, 2), (70, 30, 3, 3), (180, 330, 2, 2), (30, 380, 1, 1),
                             (200, 100, 4, 2)]:
        ss, bb = np.mgrid[s0:s0 + hs, b0:b0 + hb]
        ss, bb = ss.ravel(), bb.ravel()
        bg = 3e4 / r[ss, bb] ** 2
        inten[ss, bb] = 100 * bg * rng.uniform(0.6, 0.9, ss.size)
        k = rng.integers(ss.size)
        inten[ss[k], bb[k]] = 100 * bg[k]  # the peak
        markers.append((set(zip(ss.tolist(), bb.tolist(), strict=True)), (int(ss[k]), int(bb[k]))))
    scans = Scans(stamps_s=T0 + 0.025 * np.arange(S), ranges_m=r, intensities=inten,
                  mu_rad=np.linspace(-2.356, 2.356, N), time_increment_s=T_INC, scan_time_s=0.025,
                  range_min_m=0.023, range_max_m=60.0, source="test.bag: /scan")
    return scans, markers


def test_background_spans_orders_of_magnitude_and_global_threshold_fails():
    scans, markers = _image()
    valid = np.isfinite(scans.ranges_m)
    bg = scans.intensities[valid]
    assert np.percentile(bg, 99.9) / np.percentile(bg, 0.1) > 1000
    # a far marker is dimmer than much of the near background: no single intensity threshold works
    far_peak = min(scans.intensities[p] for _, p in markers)
    assert far_peak < np.percentile(bg, 95)


def test_detect_finds_every_marker_and_nothing_else():
    scans, markers = _image()
    det = detect(scans)
    assert len(det.blobs) == len(markers)
    found = {frozenset(zip(b.scan_idx.tolist(), b.beam_idx.tolist(), strict=True)): b for b in det.blobs}
    for pixels, peak in markers:
        blob = found[frozenset(pixels)]
        assert (blob.peak_scan, blob.peak_beam) == peak
        assert blob.peak_intensity == scans.intensities[peak]
    # labels image consistent with blobs
    for k, b in enumerate(det.blobs):
        assert (det.labels[b.scan_idx, b.beam_idx] == k).all()
    assert (det.labels >= 0).sum() == sum(len(p) for p, _ in markers)
    assert det.threshold > 0


@pytest.mark.parametrize("seed,cos_min", [(1, 0.3), (2, 0.05), (3, 0.01)])
def test_threshold_between_background_and_markers(seed, cos_min):
    """Also with a wide incidence spread (a head-on surface much brighter than the median at that range)."""
    scans, markers = _image(seed, cos_min)
    z, t, _ = contrast(scans)
    marker_px = np.zeros(z.shape, bool)
    for pixels, _ in markers:
        for p in pixels:
            marker_px[p] = True
    bg = z[~marker_px & np.isfinite(z)]
    assert bg.max() < t < z[marker_px].min()
    assert np.log(MIN_CONTRAST) <= t <= np.log(MAX_CONTRAST)


def test_min_blob_size_and_diagonal_connectivity():
    scans, _ = _image()
    inten = scans.intensities.copy()
    r = scans.ranges_m
    # a diagonal pair (8-connected -> one blob)
    for p in [(150, 250), (151, 251)]:
        inten[p] = 100 * 3e4 / r[p] ** 2
    sc = Scans(**{**scans.__dict__, "intensities": inten})
    det = detect(sc)
    diag = [b for b in det.blobs if (150, 250) in zip(b.scan_idx.tolist(), b.beam_idx.tolist(), strict=True)]
    assert len(diag) == 1 and diag[0].size == 2
    n_single = sum(b.size == 1 for b in det.blobs)
    assert len(detect(sc, min_blob_size=2).blobs) == len(det.blobs) - n_single


def _joints(omega=0.7):
    t = np.linspace(T0 - 0.1, T0 + 0.025 * S + 0.1, 800)
    return JointStates(stamps_s=t, positions_rad=-1.0 + omega * (t - T0))


def test_observations_per_beam_time_and_angle():
    scans, markers = _image()
    det = detect(scans)
    j = _joints()
    b2m = np.arange(len(det.blobs)) % 3 - 1
    obs = observations(scans, j, det, blob_to_marker=b2m, clock_offset_s=0.002)
    assert len(obs) == sum(b.size for b in det.blobs)
    t_expect = scans.stamps_s[obs.scan] + obs.beam * T_INC
    np.testing.assert_allclose(obs.times_s, t_expect, rtol=0, atol=1e-9)
    np.testing.assert_allclose(obs.lambda_rad, -1.0 + 0.7 * (t_expect - 0.002 - T0), atol=1e-6)
    np.testing.assert_array_equal(obs.ranges_m, scans.ranges_m[obs.scan, obs.beam])
    np.testing.assert_array_equal(obs.mu_rad, scans.mu_rad[obs.scan, obs.beam])
    np.testing.assert_array_equal(obs.marker, b2m[obs.blob])
    assert obs.is_peak.sum() == len(det.blobs)
    for k, b in enumerate(det.blobs):
        row = np.flatnonzero(obs.is_peak & (obs.blob == k))[0]
        assert (obs.scan[row], obs.beam[row]) == (b.peak_scan, b.peak_beam)
    # beams of one scan get different motor angles
    one = det.blobs[[b.size for b in det.blobs].index(max(b.size for b in det.blobs))]
    assert one.size > 1


def test_observations_no_blobs():
    scans, _ = _image()
    det = Detections(threshold=1.0, blobs=(), labels=np.full((S, N), -1))
    obs = observations(scans, _joints(), det)
    assert len(obs) == 0


def test_blob_centres_recover_sphere_centre():
    """Returns on a sphere of radius R: the mean of r + 2R/3 lands near the centre (sub-beam)."""
    from lrfcal.model.kinematics import beam_rays_M
    from lrfcal.types import Observations

    dh = DH(0.01, 1.5708, 0.02, 0.3)
    R = 0.005
    lam0, mu0 = 0.4, -0.2
    o0, d0 = beam_rays_M(np.array([lam0]), np.array([mu0]), dh)
    c = o0[0] + 1.5 * d0[0]
    rng = np.random.default_rng(0)
    lam = lam0 + rng.uniform(-0.006, 0.006, 6000)
    mu = mu0 + rng.uniform(-0.006, 0.006, 6000)
    o, d = beam_rays_M(lam, mu, dh)
    oc = c - o
    tca = (oc * d).sum(1)
    d2 = (oc**2).sum(1) - tca**2
    hit = d2 < R**2
    r = tca[hit] - np.sqrt(R**2 - d2[hit])
    K = int(hit.sum())
    assert K > 100
    z = np.zeros(K, np.int64)
    obs = Observations(blob=z, marker=z, scan=z, beam=z, ranges_m=r, mu_rad=mu[hit], lambda_rad=lam[hit],
                       times_s=np.zeros(K), intensity=np.ones(K), is_peak=np.zeros(K, bool))
    est = blob_centres_M(obs, dh, R)
    assert est.shape == (1, 3)
    assert np.linalg.norm(est[0] - c) < 0.1 * R
    # the naive (front surface) estimate is about R/3 short
    naive = points_M(r, lam[hit], mu[hit], dh).mean(0)
    assert np.linalg.norm(naive - c) > 0.25 * R
    # a blob index without returns gives NaN
    assert np.isnan(blob_centres_M(obs, dh, R, n_blobs=2)[1]).all()


def test_split_by_pass():
    # a blob spanning scans 8..12 with a motor reversal at scan 10
    lam = np.concatenate([np.linspace(0, 1, 11), np.linspace(0.9, 0, 10)])
    inten = np.ones((21, 5))
    inten[9, 2] = 5
    inten[11, 3] = 7
    ss = np.array([8, 9, 10, 11, 12])
    bb = np.array([2, 2, 3, 3, 3])
    blob = Blob(scan_idx=ss, beam_idx=bb, peak_scan=11, peak_beam=3, peak_intensity=7.0)
    labels = np.full((21, 5), -1)
    labels[ss, bb] = 0
    out = split_by_pass(Detections(1.0, (blob,), labels), lam, inten)
    assert len(out.blobs) == 2
    assert sorted(out.blobs[0].scan_idx.tolist()) == [8, 9, 10]
    assert (out.blobs[0].peak_scan, out.blobs[1].peak_scan) == (9, 11)
    assert (out.labels[ss, bb] == [0, 0, 0, 1, 1]).all()


def test_median_in_place_is_np_median_bit_for_bit() -> None:
    """The detection's medians (the background's bins, the contrast's median and spread) partition their own arrays
    once instead of calling np.median: the same bits on odd and even sizes, with ties, and NaN with a NaN."""
    from lrfcal.stages.detection import _median_in_place

    rng = np.random.default_rng(7)
    for n in (*range(1, 40), 4000, 4001, 150_000):
        a = np.round(np.abs(rng.normal(size=n)) * 30) / 7  # many ties (and zeros)
        got = np.float64(_median_in_place(a.copy()))
        assert got.tobytes() == np.median(a).tobytes(), n
    a = rng.normal(size=101)
    a[17] = np.nan
    assert np.isnan(_median_in_place(a.copy())) and np.isnan(np.median(a))
