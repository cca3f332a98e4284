"""The marker pipeline's fast paths (issue 47) give the bits of the general code they shortcut: the sphere's depth
without the rim's masking where no point is beyond it (and kept for the next call of the same beams), rotations and
skew matrices of one angle or vector without the stacks, cross products written out, the Kabsch determinant's sign by
cofactors, per-plane values repeated over runs of rows, the normal equations' plane rows copied where already in
plane order, points and rays of the same beams from one cos / sin."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import expit

from lrfcal.estimate.normal_equations import assemble, scores_by_cluster
from lrfcal.model import kinematics, sphere
from lrfcal.model.kinematics import DH, Params, Pose, beam_rays_W, beam_rays_W_trig, beam_trig, points_W, points_W_trig
from lrfcal.model.observations import Blocks
from lrfcal.model.plane import PlaneSet
from lrfcal.model.rays import _cross
from lrfcal.stages import detection
from lrfcal.stages.association import _det3
from lrfcal.types import Scans


def _sphere_depth_masked(u: np.ndarray, eta: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """sphere_depth as written before its fast path: both branches masked everywhere."""
    q = (1.0 - u * u) / eta
    far = q < -30.0
    qn = np.where(far, 0.0, q)
    s_near = np.sqrt(eta * np.logaddexp(0.0, qn))
    s = np.where(far, np.sqrt(eta) * np.exp(0.5 * q), s_near)
    ds = np.where(far, -u * np.exp(0.5 * q) / np.sqrt(eta), -u * expit(qn) / s_near)
    return s, ds


def _footprint_small_masked(u: np.ndarray, k: np.ndarray, eta: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """footprint_depth's k <= 1 branch as written before its fast paths."""
    x1, x2 = sphere._DISC[:, 0], sphere._DISC[:, 1]
    us, ks = u[:, None], k[:, None]
    a = us + ks * x1
    rho = np.sqrt(a * a + (ks * x2) ** 2)
    s, ds = _sphere_depth_masked(rho, eta)
    q = (1.0 - rho * rho) / eta
    drho = np.where(rho > 1e-12, a / np.maximum(rho, 1e-12), 1.0)
    return sphere._weighted_mean(s, ds * drho, q, -2.0 * rho * drho / eta)


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("top", [0.9, 1.2, 3.0])  # no point beyond the rim; near it; some far beyond it
def test_sphere_depth_same_bits(top: float) -> None:
    u = np.random.default_rng(3).uniform(-top, top, 997)
    u[:3] = (0.0, -0.0, 1.0)
    for got, want in zip(sphere.sphere_depth(u), _sphere_depth_masked(u), strict=True):
        assert _same(got, want)


@pytest.mark.parametrize("top", [0.5, 1.3, 2.5])
def test_footprint_depth_same_bits(top: float) -> None:
    rng = np.random.default_rng(4)
    u = rng.uniform(0.0, top, 500)
    u[0] = 0.0  # the beam's axis through the centre: a footprint point at rho near 0 is possible only with k = 0
    k = rng.uniform(0.05, 1.0, 500)
    got = sphere.footprint_depth(u, k)
    want = _footprint_small_masked(u, k)
    assert all(_same(g, w) for g, w in zip(got, want, strict=True))


def test_rotations_of_one_angle_same_bits() -> None:
    for t in [*np.random.default_rng(5).normal(size=50), 0.0, -0.0, np.pi, 1e-300]:
        for rot in (kinematics.rot_x, kinematics.rot_y, kinematics.rot_z):
            assert _same(rot(t), rot(np.array([t]))[0])  # the one-angle path against the stacked one


def test_skew_of_one_vector_same_bits() -> None:
    vs = [*np.random.default_rng(6).normal(size=(50, 3)), np.zeros(3), -np.zeros(3), np.array([1e-9, -0.0, 2.0])]
    for v in vs:
        assert _same(kinematics.skew(v), kinematics.skew(v[None])[0])


def test_cross_same_bits() -> None:
    rng = np.random.default_rng(8)
    A, b = rng.normal(size=(300, 3)), rng.normal(size=3)
    A[0] = (0.0, -0.0, 1.0)
    for x, y in ((A, b), (b, A), (A, A[::-1].copy())):
        assert _same(_cross(x, y), np.cross(x, y))


def test_kabsch_determinant_sign() -> None:
    """The sign of det(V U^T) by cofactors is np.linalg.det's for the SVDs of random (and degenerate) cross-
    covariances, so the batch Kabsch picks the same rotations."""
    rng = np.random.default_rng(9)
    Hm = rng.normal(size=(4000, 3, 3))
    Hm[:500, 2] = 0.0  # rank 2: collinear-ish triangles
    Hm[500:600] = 0.0
    U, _, Vt = np.linalg.svd(Hm)
    M = np.einsum("hji,hkj->hik", Vt, U)
    want = np.linalg.det(M)
    got = _det3(M)
    assert np.array_equal(got < 0, want < 0) and np.all(np.abs(np.abs(got) - 1.0) < 1e-12)


def test_plane_values_per_row_same_bits() -> None:
    """PlaneSet.per_row: v[plane] whether the rows are in plane order (repeated runs) or not (gathered)."""
    rng = np.random.default_rng(10)
    v = rng.normal(size=(4, 3))[:, 1]  # a strided column, as plane_rows passes them
    for plane in (np.sort(rng.integers(0, 4, 500)), rng.integers(0, 4, 500), np.array([1, 1, 3]),
                  np.zeros(0, dtype=np.int64)):
        K = plane.size
        s = PlaneSet(np.zeros(K), np.zeros(K), np.zeros(K), plane.astype(np.int64), np.zeros((4, 3)),
                     np.zeros((4, 3)), np.zeros((4, 3)))
        assert _same(s.per_row(v), v[plane])


def _assemble_gathered(b: Blocks, core: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """assemble's plane blocks as written before: every row gathered by the order of the planes."""
    Jc, Jn = b.Jc_plane[:, core], b.Jn_plane
    WJn, P = Jn, b.n_planes
    order = np.argsort(b.plane, kind="stable")
    bounds = np.searchsorted(b.plane[order], np.arange(P + 1))
    Jc_s, Jn_s, WJn_s, wr_s = Jc[order], Jn[order], WJn[order], b.r_plane[order]
    B, D, g_n = np.zeros((core.size, 3 * P)), np.zeros((P, 3, 3)), np.zeros(3 * P)
    for j in range(P):
        rows = slice(bounds[j], bounds[j + 1])
        B[:, 3 * j:3 * j + 3] = Jc_s[rows].T @ WJn_s[rows]
        D[j] = Jn_s[rows].T @ WJn_s[rows]
        g_n[3 * j:3 * j + 3] = Jn_s[rows].T @ wr_s[rows]
    return B, D, g_n


@pytest.mark.parametrize("layout", ["F", "C"])
@pytest.mark.parametrize("ordered", [True, False])
def test_assemble_rows_in_plane_order_same_bits(layout: str, ordered: bool) -> None:
    """Plane rows already in plane order are copied, not gathered: the same normal equations to the bit (the
    Jacobian blocks F-ordered as plane_rows makes them, or C-ordered)."""
    rng = np.random.default_rng(11)
    K, P = 5000, 3
    plane = np.sort(rng.integers(0, P, K)) if ordered else rng.integers(0, P, K)
    Jc = np.array(rng.normal(size=(K, 16)), order=layout)
    Jn = np.array(rng.normal(size=(K, 3)), order=layout)
    b = Blocks(np.zeros(0), np.zeros((0, 16)), rng.normal(size=K), Jc, Jn, plane, P)
    core = np.arange(13)
    got = assemble(b, core)
    for g, w in zip((got.B, got.D, got.g_n), _assemble_gathered(b, core), strict=True):
        assert _same(g, w)


def test_points_and_rays_from_shared_trig_same_bits() -> None:
    """observe_surfaces reprojects a try's returns and casts its candidates' rays from one beam_trig: the same
    bits as points_W and beam_rays_W of the same beams."""
    rng = np.random.default_rng(12)
    params = Params(Pose(0.1, -0.2, 0.3, 0.01, -0.02, 0.5), DH(a=0.02, alpha=1.4, b=0.05, beta=0.1))
    lam, mu, r = rng.uniform(-3, 3, 2000), rng.uniform(-2.3, 2.3, 2000), rng.uniform(0.1, 20, 2000)
    trig = beam_trig(lam, mu, params.dh)
    assert _same(points_W_trig(r, trig, params), points_W(r, lam, mu, params))
    i = np.sort(rng.choice(2000, 700, replace=False))
    sub = (trig[0][i], trig[1][i], trig[2][i], trig[3][i])
    for got, want in zip(beam_rays_W_trig(params, sub), beam_rays_W(params, lam[i], mu[i]), strict=True):
        assert _same(got, want)


def _scores_flat(b: Blocks, core: np.ndarray, cluster_dense: np.ndarray, cluster_plane: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """scores_by_cluster as written before: a bincount over all of G's entries per column, added to G."""
    P, c = b.n_planes, core.size
    n_prior = 0 if b.r_prior is None else b.r_prior.size
    rows = np.concatenate([cluster_dense, cluster_plane, np.iinfo(np.int64).min + np.arange(n_prior)])
    ids, inv = np.unique(rows, return_inverse=True)
    n_cl, m, K, n = ids.size, b.r_dense.size, b.r_plane.size, c + 3 * P
    G = np.zeros(n_cl * n)
    inv_d, inv_p, inv_q = inv[:m], inv[m:m + K], inv[m + K:]
    for k, col in enumerate(core):
        G += np.bincount(inv_d * n + k, weights=b.J_dense[:, col] * b.r_dense, minlength=n_cl * n)
        G += np.bincount(inv_p * n + k, weights=b.Jc_plane[:, col] * b.r_plane, minlength=n_cl * n)
    for i in range(3):
        G += np.bincount(inv_p * n + c + 3 * b.plane + i, weights=b.Jn_plane[:, i] * b.r_plane, minlength=n_cl * n)
    if n_prior and b.w_prior is not None and b.r_prior is not None:
        G[inv_q * n + c + np.arange(n_prior)] += b.w_prior * b.r_prior
    return ids, G.reshape(n_cl, n)


def test_scores_by_cluster_same_bits() -> None:
    """The cluster scores by one small bincount per column: the same bits as the bincount over all of G, with
    dense and plane rows sharing clusters or not, zeros and negative zeros among the products, and plane priors."""
    rng = np.random.default_rng(13)
    m, K, P = 600, 4000, 3
    Jd, Jc, Jn = rng.normal(size=(m, 16)), np.asfortranarray(rng.normal(size=(K, 16))), rng.normal(size=(K, 3))
    Jd[::7] = -0.0
    Jc[::5, 3] = 0.0
    r_p = rng.normal(size=K)
    r_p[::11] = -0.0
    b = Blocks(rng.normal(size=m), Jd, r_p, Jc, Jn, rng.integers(0, P, K), P, rng.normal(size=3 * P),
               rng.uniform(1, 2, 3 * P))
    core = np.array([0, 1, 2, 6, 7, 8, 9, 12])
    for dense_clusters in (rng.integers(0, 300, m), 1000 + rng.integers(0, 50, m)):  # shared with the scans; apart
        plane_clusters = rng.integers(0, 300, K)
        got = scores_by_cluster(b, core, dense_clusters, plane_clusters)
        want = _scores_flat(b, core, dense_clusters, plane_clusters)
        assert all(_same(g, w) for g, w in zip(got, want, strict=True))


def _contrast_allocating(scans: Scans) -> tuple[np.ndarray, float, float]:
    """detection.contrast as written before: fresh arrays for the logs, the contrast and its deviations."""
    r, inten = scans.ranges_m, scans.intensities
    valid = np.isfinite(r) & np.isfinite(inten) & (inten > 0)
    r_v = r[valid]
    log_r, log_i = np.log(r_v), np.log(inten[valid])
    kx, ky = detection._background_model_log(log_r, log_i)
    z = np.full(r.shape, np.nan)
    zv = log_i - np.interp(log_r, kx, ky)
    z[valid] = zv
    med = detection._median_in_place(zv)
    sigma = 1.4826 * detection._median_in_place(np.abs(zv - med))
    t = float(np.clip(med + detection.K_SIGMA * sigma, np.log(detection.MIN_CONTRAST), np.log(detection.MAX_CONTRAST)))
    r_med = detection._median_in_place(r_v)
    return z, t, float(np.exp(np.interp(np.log(r_med), kx, ky) + t))


def test_contrast_in_place_same_bits() -> None:
    rng = np.random.default_rng(14)
    S, N = 300, 541
    r = rng.uniform(0.5, 30.0, (S, N))
    r[rng.random((S, N)) < 0.05] = np.nan
    inten = 3e4 / r**2 * rng.uniform(0.3, 1.0, (S, N))
    inten[rng.random((S, N)) < 0.02] = 0.0
    inten[:5, :40] *= 200.0  # markers
    scans = Scans(stamps_s=0.025 * np.arange(S), ranges_m=r, intensities=inten, mu_rad=np.linspace(-2.356, 2.356, N),
                  time_increment_s=1.7e-5, scan_time_s=0.025, range_min_m=0.023, range_max_m=60.0)
    z, t, thr = detection.contrast(scans)
    z0, t0, thr0 = _contrast_allocating(scans)
    assert _same(z, z0) and t == t0 and thr == thr0


def test_plane_subset_carries_its_trig_same_bits() -> None:
    """A subset of a PlaneSet takes the subset of its cos and sin: the values it would compute itself."""
    rng = np.random.default_rng(15)
    K = 3000
    s = PlaneSet(rng.uniform(-3, 3, K), rng.uniform(-2.3, 2.3, K), rng.uniform(1, 9, K), np.sort(rng.integers(0, 2, K)),
                 np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((2, 3)))
    _ = s.trig_lam, s.trig_mu
    m = rng.random(K) < 0.7
    sub = s.subset(m)
    assert "trig_mu" in sub.__dict__ and "trig_lam" in sub.__dict__
    for got, want in ((sub.trig_lam, (np.cos(s.lam[m]), np.sin(s.lam[m]))),
                      (sub.trig_mu, (np.cos(s.mu[m]), np.sin(s.mu[m])))):
        assert _same(got[0], want[0]) and _same(got[1], want[1])
    assert "trig_mu" not in PlaneSet(s.lam, s.mu, s.r, s.plane, s.n0, s.t1, s.t2).subset(m).__dict__
