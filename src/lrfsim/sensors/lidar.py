"""The Hokuyo UTM-30LX-EW on the turning servo, ray cast with MuJoCo (the cast itself: lrfsim.cast.scans).

Timing (Hokuyo UTM-30LX-EW spec sheet: 25 ms per scan, 0.25 deg = 360 / 1440 deg steps; LaserScan fields as the
ROS driver urg_node fills them, github.com/ros-drivers/urg_node). Scan s starts at t_s (true time = servo clock);
beam i (i = 0 .. N-1, bearing
mu_i = angle_min + i * angle_increment) is fired at t_s + i * time_increment (25 ms / 1440 = 17.36 us), so the
270 deg of a scan take 18.75 ms while the servo keeps turning. Every beam is therefore cast from the rig's pose
at its own time: lambda_si = lambda(t_s + i * time_increment).

Pose of every beam. Per scan, ``mj_kinematics`` at the reference angle lambda_s (the scan's middle beam) gives
the laser site's pose (p_s, R_s) and the hinge's world anchor a and unit axis u (``data.xanchor``,
``data.xaxis``). A hinge moves its subtree by a rotation about (a, u), so beam i's pose is exactly

    o_si = a + Rot(u, d_si) (p_s - a),   R_si = Rot(u, d_si) R_s,   d_si = lambda_si - lambda_s,

with Rot the Rodrigues rotation. Sub-ray directions are R_si times fixed directions in the laser frame.

Batching. ``mj_multiRay`` casts many rays from ONE origin. Beams of a scan are grouped in runs of n
consecutive beams that share the exact origin of the run's middle beam; n is chosen per scan so that the
largest distance from a beam's exact origin to its run's origin stays below ``origin_tol_m`` (1 um by
default): with step length delta = max_i |o_i+1 - o_i| (an upper bound on the arc between neighbours),
n = 2 floor(tol / delta) + 1. Directions are never shared: every sub-ray has its exact direction (direction
error 0). The residual range error of the shared origin e = o_run - o_i is then removed to first order with the
surface normal n returned by MuJoCo (exact for planes): r_i = t + n.e / n.d, where t is the distance from the
run's origin along d (applied where |n.d| > 1e-4).

Footprint (``divergence_rad`` full angle, unverified for the UTM-30LX, HELIOS++ default 0.3 mrad).
``footprint_rays`` F sub-rays: the centre ray plus a ring of F-1 rays at the half-angle that makes them
equal-area samples of a uniform disc of radius divergence/2 (ring at the centroid radius of the annulus outside
the centre's share: rho = 2/3 (1 - q^3) / (1 - q^2) * divergence / 2 with q = 1 / sqrt(F)). F = 1: centre only.
``footprint_cast: edges`` (the default) casts the ring only where it can change a beam; elsewhere the sub-rays
meet the centre ray's tangent plane (lrfsim.cast.chunks.cast_chunk_edges); ``full`` casts every sub-ray.

Received power per sub-ray (radar equation as in HELIOS++, with the sensor's constants folded into a gain):

    P_f = gain * rho_g * g_g(theta) * (r_ref / r_f)^2,
    g(theta) = cos(theta)                 Lambertian surfaces (HELIOS++ Lambert BRDF; Robotec T|cos theta|),
    g(theta) = cos(theta)^0.1             retroreflective markers (glass-bead/prismatic sheeting keeps most of
                                          its return over wide entrance angles; Gazebo's laser_retro is the
                                          limit g = 1),

rho_g the geom's reflectivity (albedo; an effective gain >> 1 for retroreflectors). Kneip et al. (ICRA 2009)
and the Photonics 2018 UST-20LX study motivate the incidence dependence and the mixed pixels.

Mixed pixel (one echo per beam): the beam's range is the received-power-weighted mean of its sub-rays'
ranges, r = sum_f P_f r_f / sum_f P_f, and its intensity the mean received power over all F sub-rays (a miss
contributes 0), I = sum_f P_f / F. A bright retroreflector in part of the footprint therefore dominates both.
This mixture is /scan; the UTM-30LX-EW also reports up to 3 separate echoes (``sensor.echoes``, below).

Noise (``noise: true``): I <- I * max(0, 1 + relative_noise * z), then I is rounded to integer counts and
clipped at ``saturation_counts``; I < ``min_detectable_counts`` -> no return. Range: r <- r + sigma(r) z with
sigma from the first ``noise_bands`` entry with r <= up_to_m (the last band beyond), then quantised to
``quantisation_m`` (1 mm; 0 = exact); with ``noise_range_fraction`` k > 0, sigma(r) = max(band sigma, k r) (noise
proportional to the range, as the URG-04LX datasheet's 1 % of range beyond 1 m). Ranges outside [range_min,
range_max] -> no return. No return is NaN (urg_node) or +inf (``no_return: inf``). ``noise: false`` skips both
random terms only.

Systematic errors (``sensor.systematic``, all off by default; docs/sensor_errors.md). Incidence: every sub-ray's
range gets k_theta * theta_f (theta_f = arccos|n.d| its incidence angle) before the mixture (the received power
still uses the true range). Then, before noise, every return (beam or echo) gets

    b = offset + k_I * log10(min(I, saturation_counts) / I_ref) + A * exp(-(t_on + t) / tau)
        + A_beam * sin(2 pi i / P_beam) + A_range * sin(2 pi r / P_range),

I the return's noise-free intensity (the mean received power above), t the beam's true time from the start of the
sweep, t_on the time from power-on to that start, i the beam's index in its scan (a wiggle along the scan, the same
in every scan) and r the return's noise-free range (a cyclic error). Every term is skipped when its coefficient is
0, so the defaults reproduce the ranges without the model bit for bit.

Multi-echo (``sensor.echoes.enabled``). Per beam the hit sub-rays are sorted by (biased) range; a gap wider than
``separation_m`` starts a new echo; echo e's range is the power-weighted mean of its group, its intensity the
group's power summed over the group and divided by F (so the echoes' intensities add up to the beam's). Echoes
are kept nearest first, at most ``max_echoes``. A beam whose hits form one group has one echo, equal bit for bit
to its /scan return (same noise draws); further echoes get noise draws of their own. Each echo then goes through
the same bias, noise, saturation, drop-out and quantisation as /scan; a dropped echo is NaN; the valid echoes
are then ordered by their reported range (arrival order: noise may swap two close echoes), dropped ones last.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import InputError
from lrfsim.scenario.sections import SensorConfig

if TYPE_CHECKING:
    import mujoco

FloatArray = NDArray[np.float64]

#: Incidence exponent of retroreflective markers: g = cos(theta)^RETRO_EXPONENT (see module docstring).
RETRO_EXPONENT = 0.1
#: Rays closer than this to perpendicular to the surface get no parallax correction (|n.d| below it).
_MIN_NORMAL_DOT = 1e-4


class SceneLike(Protocol):
    """What the lidar needs of ``lrfsim.world.scene.Scene``."""

    @property
    def model(self) -> mujoco.MjModel: ...
    @property
    def data(self) -> mujoco.MjData: ...
    @property
    def site_id(self) -> int: ...
    @property
    def joint_qpos_adr(self) -> int: ...
    @property
    def joint_id(self) -> int: ...
    @property
    def geom_reflectivity(self) -> FloatArray: ...
    @property
    def geom_is_marker(self) -> NDArray[np.bool_]: ...
    @property
    def lidar_geomgroup(self) -> NDArray[np.uint8]: ...


# --- geometry of the sensor -----------------------------------------------------------------------------------

def beam_angles(sensor: SensorConfig) -> FloatArray:
    """Beam bearings mu_i = angle_min + i * angle_increment, shape (N,)."""
    return sensor.angle_min_rad + np.arange(sensor.n_beams) * sensor.angle_increment_rad


def ring_half_angle(sensor: SensorConfig) -> float:
    """Angle [rad] between the centre ray and the ring sub-rays (module docstring); 0 for F = 1."""
    F = sensor.footprint_rays
    if F == 1:
        return 0.0
    q = 1.0 / math.sqrt(F)
    return (2.0 / 3.0) * (1.0 - q**3) / (1.0 - q**2) * 0.5 * sensor.divergence_rad


def footprint_coefficients(sensor: SensorConfig) -> FloatArray:
    """Sub-ray directions in a beam's own frame (e, t, z), shape (F, 3), unit rows.

    e = [cos mu, sin mu, 0] the beam centre, t = [-sin mu, cos mu, 0] the in-plane tangent, z the mirror axis.
    Row 0 is the centre (1, 0, 0); row k >= 1 is tilted by :func:`ring_half_angle` rho towards
    psi_k = 2 pi (k - 1) / (F - 1) from t to z: (cos rho, sin rho cos psi_k, sin rho sin psi_k).
    """
    F = sensor.footprint_rays
    rho = ring_half_angle(sensor)
    psi = 2.0 * math.pi * np.arange(F - 1) / max(F - 1, 1)
    out = np.empty((F, 3))
    out[0] = (1.0, 0.0, 0.0)
    out[1:, 0] = math.cos(rho)
    out[1:, 1] = math.sin(rho) * np.cos(psi)
    out[1:, 2] = math.sin(rho) * np.sin(psi)
    return out


def footprint_directions_L(sensor: SensorConfig) -> FloatArray:
    """Unit sub-ray directions in the laser frame L (+x bearing 0, +z mirror axis), shape (N, F, 3):
    Rz(mu_i) applied to :func:`footprint_coefficients`."""
    mu = beam_angles(sensor)
    c = footprint_coefficients(sensor)
    cm, sm = np.cos(mu)[:, None], np.sin(mu)[:, None]
    return np.stack([cm * c[:, 0] - sm * c[:, 1], sm * c[:, 0] + cm * c[:, 1],
                     np.broadcast_to(c[:, 2], cm.shape[:1] + c.shape[:1])], -1)


def scan_start_times(duration_s: float, sensor: SensorConfig, phase_s: float = 0.0) -> FloatArray:
    """True times (servo clock) of beam 0 of every scan lying wholly in [0, duration_s], shape (S,).

    Scans start at phase_s + s * scan_period_s (phase_s in [0, scan_period_s): the laser runs free).
    """
    last_beam_s = (sensor.n_beams - 1) * sensor.time_increment_s
    if last_beam_s > sensor.scan_period_s:
        raise InputError(f"sensor: {sensor.n_beams} beams x time_increment_s {sensor.time_increment_s} do not "
                         f"fit in scan_period_s {sensor.scan_period_s}")
    n = int(math.floor((duration_s - last_beam_s - phase_s) / sensor.scan_period_s + 1e-9)) + 1
    return phase_s + np.arange(max(n, 0)) * sensor.scan_period_s


def beam_times(scan_starts_s: FloatArray, sensor: SensorConfig) -> FloatArray:
    """Time of every beam: t_s + i * time_increment, shape (S, N)."""
    return scan_starts_s[:, None] + np.arange(sensor.n_beams) * sensor.time_increment_s


def rotate_about_axis(v: FloatArray, axis: FloatArray, angle: FloatArray) -> FloatArray:
    """Rodrigues: rotate vectors v (..., 3) about the unit ``axis`` (3,) by ``angle`` (...) [rad]."""
    c = np.cos(angle)[..., None]
    s = np.sin(angle)[..., None]
    K = _skew(axis)
    return v * c + (v @ K.T) * s + (v @ axis)[..., None] * axis * (1.0 - c)


def _skew(u: FloatArray) -> FloatArray:
    return np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])


def site_poses_W(scene: SceneLike, lambda_rad: FloatArray, data: mujoco.MjData | None = None
                 ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """MuJoCo forward kinematics of the laser site at motor angles lambda (K,), in ``data`` (default scene.data;
    a thread of the cast passes its own).

    Returns positions (K, 3), rotations R_W_L (K, 3, 3), and the hinge's world anchor (3,) and unit axis (3,)
    (from the first angle; a hinge on a fixed base does not move its own axis).
    """
    import mujoco

    m, d = scene.model, (scene.data if data is None else data)
    lam = np.atleast_1d(np.asarray(lambda_rad, dtype=float))
    pos = np.empty((lam.size, 3))
    rot = np.empty((lam.size, 3, 3))
    anchor = axis = np.zeros(3)
    for k, q in enumerate(lam.tolist()):
        d.qpos[scene.joint_qpos_adr] = q
        mujoco.mj_kinematics(m, d)
        pos[k] = d.site_xpos[scene.site_id]
        rot[k] = d.site_xmat[scene.site_id].reshape(3, 3)
        if k == 0:
            anchor = d.xanchor[scene.joint_id].copy()
            axis = d.xaxis[scene.joint_id].copy()
    return pos, rot, anchor, axis / np.linalg.norm(axis)


def beam_poses_W(scene: SceneLike, beam_lambda_rad: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Exact per-beam poses: origins (S, N, 3) and rotations R_W_L (S, N, 3, 3) at motor angles (S, N).

    Per scan: kinematics at the middle beam's angle, then the hinge rotation by each beam's delta-lambda.
    """
    lam = np.asarray(beam_lambda_rad, dtype=float)
    ref = lam[:, lam.shape[1] // 2]
    p, R, a, u = site_poses_W(scene, ref)
    delta = lam - ref[:, None]
    origins = a + rotate_about_axis((p - a)[:, None, :], u, delta)
    cols = [rotate_about_axis(np.broadcast_to(R[:, None, :, j], lam.shape + (3,)), u, delta) for j in range(3)]
    return origins, np.stack(cols, -1)


# --- the sensor model ------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class LidarOutput:
    """Simulated scans: ranges_m (S, N) (NaN/inf: no return), intensities (S, N) counts, and run statistics:
    rays cast, mj_multiRay calls, seconds inside the cast loop and in total, the largest shared-origin error
    (m) and direction error (rad) batching introduced, and the largest parallax correction applied (m)."""

    ranges_m: FloatArray
    intensities: FloatArray
    n_rays: int
    n_calls: int
    cast_time_s: float
    total_time_s: float
    max_origin_error_m: float
    max_direction_error_rad: float
    max_parallax_correction_m: float
    #: multi-echo returns (S, N, E) nearest first, NaN where absent, and their intensities; None without echoes
    echo_ranges_m: FloatArray | None = None
    echo_intensities: FloatArray | None = None


def systematic_bias_m(intensities: FloatArray, sensor: SensorConfig,
                      beam_times_s: FloatArray | None = None, ranges_m: FloatArray | None = None) -> FloatArray | None:
    """The return-level systematic range bias [m] (module docstring), shape of ``intensities`` ((S, N) or
    (S, N, E)); None when offset, intensity bias, drift and wiggles are all off. ``intensities``: noise-free received
    intensity [counts]; ``beam_times_s`` (S, N): true beam times [s], needed only for the drift; ``ranges_m`` (the
    shape of ``intensities``): noise-free ranges [m], needed only for the range wiggle."""
    c = sensor.systematic
    out = _drift_and_levels(intensities, sensor, beam_times_s)
    if c.beam_wiggle_m != 0.0:
        i = np.arange(intensities.shape[1], dtype=float)
        b = c.beam_wiggle_m * np.sin(2.0 * np.pi * i / c.beam_wiggle_period_beams)
        b = b[:, None] if intensities.ndim == 3 else b
        out = np.broadcast_to(b, intensities.shape).copy() if out is None else out + b
    if c.range_wiggle_m != 0.0:
        if ranges_m is None:
            raise InputError("lidar: sensor.systematic.range_wiggle_m needs the noise-free ranges")
        b = c.range_wiggle_m * np.sin(2.0 * np.pi * np.asarray(ranges_m, dtype=float) / c.range_wiggle_period_m)
        out = b if out is None else out + b
    return out


def _drift_and_levels(intensities: FloatArray, sensor: SensorConfig,
                      beam_times_s: FloatArray | None) -> FloatArray | None:
    """The offset, intensity bias and warm-up drift of :func:`systematic_bias_m` (None when all three are off)."""
    c = sensor.systematic
    out: FloatArray | None = None
    if c.range_offset_m != 0.0:
        out = np.full(intensities.shape, c.range_offset_m)
    if c.intensity_bias_m_per_decade != 0.0:
        level = np.clip(intensities, 1e-300, sensor.intensity.saturation_counts) / c.intensity_ref_counts
        b = c.intensity_bias_m_per_decade * np.log10(level)
        out = b if out is None else out + b
    if c.drift_amplitude_m != 0.0:
        if beam_times_s is None:
            raise InputError("lidar: sensor.systematic.drift_amplitude_m needs the beam times")
        t = np.asarray(beam_times_s, dtype=float)
        b = c.drift_amplitude_m * np.exp(-(c.drift_elapsed_s + t) / c.drift_time_constant_s)
        if intensities.ndim == 3:
            b = b[..., None]
        out = np.broadcast_to(b, intensities.shape).copy() if out is None else out + b
    return out


def _sensor_model(ranges: FloatArray, intens: FloatArray, sensor: SensorConfig, z_range: FloatArray | None,
                  z_int: FloatArray | None, bias: FloatArray | None) -> FloatArray:
    """Bias, noise, saturation, drop-out and quantisation (module docstring) on noise-free returns of any shape;
    ``ranges`` and ``intens`` are modified in place (the ranges also returned; no return: NaN or inf). Each step is
    the same floating-point operation as written out (``r = round(r / q) * q``, ...), done in place: the same
    bits without a fresh 13 MB array per step for tunnel_v."""
    received = intens > 0
    if bias is not None:
        ranges += bias
    if sensor.noise and z_int is not None:
        gain = np.multiply(z_int, sensor.intensity.relative_noise)
        gain += 1.0
        intens *= np.maximum(0.0, gain, out=gain)
    np.round(intens, out=intens)
    np.minimum(intens, sensor.intensity.saturation_counts, out=intens)
    valid = received & (intens >= sensor.intensity.min_detectable_counts)
    if sensor.noise and z_range is not None:
        noise = range_sigma(np.where(received, ranges, 0.0), sensor)
        noise *= z_range
        ranges += noise
    if sensor.quantisation_m > 0:
        ranges /= sensor.quantisation_m
        np.round(ranges, out=ranges)
        ranges *= sensor.quantisation_m
    with np.errstate(invalid="ignore"):
        valid &= (ranges >= sensor.range_min_m) & (ranges <= sensor.range_max_m)
    ranges[~valid] = np.inf if sensor.no_return == "inf" else np.nan
    return ranges


def split_echoes(r_m: FloatArray, power: FloatArray, hit: NDArray[np.bool_], separation_m: float,
                 max_echoes: int) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """Group a beam's sub-rays into echoes (module docstring). r_m, power, hit: (..., F) per sub-ray.

    Returns the echoes' power-weighted ranges (..., E) (NaN: no echo), their summed powers (..., E), and
    whether all hit sub-rays fell into the first echo (...,) (the beam does not split)."""
    rs = np.where(hit, r_m, np.inf)
    order = np.argsort(rs, axis=-1, kind="stable")
    rsort = np.take_along_axis(rs, order, -1)
    psort = np.take_along_axis(np.where(hit, power, 0.0), order, -1)
    hsort = np.take_along_axis(hit, order, -1)
    with np.errstate(invalid="ignore"):
        gap = np.diff(rsort, axis=-1) > separation_m
    group = np.concatenate([np.zeros(gap.shape[:-1] + (1,), dtype=np.int64), np.cumsum(gap, axis=-1)], -1)
    onehot = group[..., None] == np.arange(max_echoes)
    rfin = np.where(hsort, rsort, 0.0)
    pe = np.einsum("...f,...fe->...e", psort, onehot)
    pre = np.einsum("...f,...fe->...e", psort * rfin, onehot)
    re = np.divide(pre, pe, out=np.full_like(pe, np.nan), where=pe > 0)
    single = np.all(~hsort | (group == 0), axis=-1)
    return re, pe, single


def _bands(sensor: SensorConfig) -> tuple[FloatArray, FloatArray]:
    """The noise bands sorted by ``up_to_m``: (up_to_m (B,), sigma_m (B,)) [m]."""
    up = np.array([b.up_to_m for b in sensor.noise_bands], dtype=float)
    sig = np.array([b.sigma_m for b in sensor.noise_bands], dtype=float)
    order = np.argsort(up)
    return up[order], sig[order]


def _band_index(ranges_m: FloatArray, up_m: FloatArray) -> NDArray[np.uint8] | NDArray[np.intp]:
    """Per range, the index of its band (``up_m`` (B,) ascending, B >= 1): the first band with r <= up_to_m, the
    last beyond and for NaN; ``np.searchsorted(up_m, r, side="left")`` clipped to B - 1, counted with B - 1
    comparisons (``not r <= up``: NaN counts as beyond, as it sorts last), 5-10x faster for a handful of bands."""
    if up_m.size > 8:
        return np.minimum(np.searchsorted(up_m, ranges_m, side="left"), up_m.size - 1)
    idx = np.zeros(np.shape(ranges_m), dtype=np.uint8)
    for u in up_m[:-1]:
        idx += ~(ranges_m <= u)
    return idx


def range_sigma(ranges_m: FloatArray, sensor: SensorConfig) -> FloatArray:
    """Range noise sigma [m] per range from ``noise_bands`` (first band with r <= up_to_m; last beyond), at least
    ``noise_range_fraction`` times the range."""
    if not sensor.noise_bands:
        sigma = np.zeros_like(ranges_m, dtype=float)
    else:
        up, sig = _bands(sensor)
        sigma = np.take(sig, _band_index(np.asarray(ranges_m), up))
    if sensor.noise_range_fraction > 0.0:
        with np.errstate(invalid="ignore"):
            sigma = np.fmax(sigma, sensor.noise_range_fraction * np.abs(np.asarray(ranges_m, dtype=float)))
    return sigma


def typical_range_sigma(ranges_m: FloatArray, sensor: SensorConfig) -> float | None:
    """The sensor's range noise at typical ranges [m]: the median over the finite ``ranges_m`` (any shape) of
    :func:`range_sigma`; None for a noise-free sensor or no finite range. What a recording declares as its
    scanner's noise (nominal.yaml ``range_sigma_m``) and what ``lrfsim plan`` predicts with. The median of the
    band sigmas is taken from each band's count of ranges, not from an array of a sigma per range: the same
    number (the middle one or two of the same sorted values), without the array."""
    r = np.asarray(ranges_m, dtype=float)
    r = r[np.isfinite(r)]
    if not sensor.noise or r.size == 0 or not (sensor.noise_bands or sensor.noise_range_fraction > 0.0):
        return None
    if sensor.noise_range_fraction > 0.0:  # a sigma per range: the median of the array
        return float(np.median(range_sigma(r, sensor)))
    up, sig = _bands(sensor)
    if up.size > 8:
        counts = np.bincount(_band_index(r, up), minlength=up.size)
    else:  # ranges beyond each band's limit, counted (r is finite here: "not r <= up" is r > up)
        beyond = np.array([r.size] + [np.count_nonzero(r > u) for u in up[:-1]] + [0])
        counts = beyond[:-1] - beyond[1:]
    order = np.argsort(sig, kind="stable")
    values, ends = sig[order], np.cumsum(counts[order])  # the sorted sigmas: values[k] up to index ends[k] - 1
    n = int(r.size)
    middle = [n // 2] if n % 2 else [n // 2 - 1, n // 2]
    return float(np.median(values[np.searchsorted(ends, middle, side="right")]))


@dataclass(frozen=True)
class Cast:
    """The noise-free part of a simulation: the mixed-pixel range ranges_m (S, N) (NaN: no sub-ray hit; the
    incidence bias, a geometric effect, already applied per sub-ray) and the mean received power intensities
    (S, N), the echoes' ranges and received power (S, N, E) when echoes are enabled, with the statistics of the
    cast (see LidarOutput). Cast once, it can take any number of noise draws (:func:`sensor_model`)."""

    ranges_m: FloatArray
    intensities: FloatArray
    n_rays: int
    n_calls: int
    cast_time_s: float
    total_time_s: float
    max_origin_error_m: float
    max_parallax_correction_m: float
    cutoff_m: float
    echo_ranges_m: FloatArray | None = None
    echo_power: FloatArray | None = None


def correlated_along_beams(z: FloatArray, rho: float) -> FloatArray:
    """Independent standard normal draws z (S, N) made an AR(1) process along the beams of each scan, with the
    same unit variance: e_0 = z_0, e_i = rho e_(i-1) + sqrt(1 - rho^2) z_i, so the correlation of beams k apart is
    rho^k. ``rho`` = 0 returns ``z`` itself (the same numbers, bit for bit)."""
    if rho == 0.0:
        return z
    c = math.sqrt(1.0 - rho * rho)
    e = np.empty_like(z)
    e[:, 0] = z[:, 0]  # the first beam of a scan: the stationary start
    for i in range(1, z.shape[1]):
        e[:, i] = rho * e[:, i - 1] + c * z[:, i]
    return e


def sensor_model(cast: Cast, sensor: SensorConfig, rng: np.random.Generator,
                 beam_times_s: FloatArray | None = None) -> LidarOutput:
    """The sensor model (module docstring) on a cast's whole (S, N) arrays: noise drawn from ``rng`` (range, then
    intensity, all up front; the echoes' extra draws after), the systematic biases (``beam_times_s`` (S, N) for
    the warm-up drift), rounding, saturation, detection and range limits. ``cast`` is not modified."""
    t_start = time.perf_counter()
    S, N = cast.ranges_m.shape
    F = sensor.footprint_rays
    z_range = z_int = None
    if sensor.noise:
        z_range = correlated_along_beams(rng.standard_normal((S, N)), sensor.noise_correlation)
        z_int = rng.standard_normal((S, N))
    echo_ranges = echo_intens = None
    if cast.echo_ranges_m is not None and cast.echo_power is not None:
        E = cast.echo_ranges_m.shape[-1]
        echo_intens = cast.echo_power / F
        zr = zi = None
        if sensor.noise and z_range is not None and z_int is not None:
            zr = np.concatenate([z_range[..., None], rng.standard_normal((S, N, E - 1))], -1)
            zi = np.concatenate([z_int[..., None], rng.standard_normal((S, N, E - 1))], -1)
        echo_ranges = _sensor_model(cast.echo_ranges_m.copy(), echo_intens, sensor, zr, zi,
                                    systematic_bias_m(echo_intens, sensor, beam_times_s, cast.echo_ranges_m))
        # reported in arrival order: noise may swap close echoes; no-return echoes last
        order = np.argsort(np.where(np.isfinite(echo_ranges), echo_ranges, np.inf), axis=-1, kind="stable")
        echo_ranges = np.take_along_axis(echo_ranges, order, -1)
        echo_intens = np.take_along_axis(echo_intens, order, -1)
    intens = cast.intensities.copy()
    ranges = _sensor_model(cast.ranges_m.copy(), intens, sensor, z_range, z_int,
                           systematic_bias_m(intens, sensor, beam_times_s, cast.ranges_m))
    return LidarOutput(ranges_m=ranges, intensities=intens, n_rays=cast.n_rays, n_calls=cast.n_calls,
                       cast_time_s=cast.cast_time_s, total_time_s=cast.total_time_s + time.perf_counter() - t_start,
                       max_origin_error_m=cast.max_origin_error_m, max_direction_error_rad=0.0,
                       max_parallax_correction_m=cast.max_parallax_correction_m,
                       echo_ranges_m=echo_ranges, echo_intensities=echo_intens)


__all__ = [
    "RETRO_EXPONENT", "Cast", "LidarOutput", "SceneLike", "beam_angles", "beam_poses_W", "beam_times",
    "footprint_coefficients", "footprint_directions_L", "range_sigma", "ring_half_angle", "rotate_about_axis",
    "scan_start_times", "sensor_model", "site_poses_W", "split_echoes", "systematic_bias_m",
]
