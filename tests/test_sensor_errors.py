"""Issue 12: each systematic error switched on alone changes the ranges as documented (lrfsim.sensors.lidar,
docs/sensor_errors.md), multi-echo returns split at edges, and the MultiEchoLaserScan topic reads back through
lrfcal.io.bag; a multi-echo recording calibrates through /echoes as through /scan, the strongest echo keeps a split
marker beam's marker return, `lrfcal inspect` proposes the strongest echo, and `lrfsim run` says whether the
scanner had systematic errors."""

from __future__ import annotations

import io
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_lidar import EXACT, _deep_update, _exact_rays_W, _marker_on_beam, _run, _tunnel_hits, small_scenario

from lrfcal.commands.inspect_bag import inspect_bag
from lrfcal.errors import InputError
from lrfcal.io.bag import read_bag
from lrfcal.io.bag_scans import select_echo
from lrfcal.io.recording import read_recording
from lrfcal.io.rig import ScanSource, ServoSource, parse_rig
from lrfcal.pipeline import CalibConfig
from lrfsim.cast import scans
from lrfsim.scenario.file import Scenario, load_scenario, parse_scenario, with_changes
from lrfsim.scenario.sections import SystematicConfig
from lrfsim.sensors import lidar
from lrfsim.sensors.servo import sweep_trajectory
from lrfsim.simulation.recording import write_recording
from lrfsim.simulation.simulate import simulate, systematic_truth
from lrfsim.trials.closed_loop import sensor_errors_line
from lrfsim.trials.trial import calibrate_recording, record
from lrfsim.world.scene import build_scene


def _with(sc: Scenario, **sensor: object) -> Scenario:
    return parse_scenario(_deep_update(sc.model_dump(mode="json"), {"sensor": sensor}), "test")


def _run_timed(sc: Scenario, scene=None, seed: int = 0):
    """Like test_lidar._run, passing the beam times (the drift needs them)."""
    scene = scene if scene is not None else build_scene(sc)
    traj = sweep_trajectory(sc.servo)
    t = lidar.beam_times(lidar.scan_start_times(traj.end_s, sc.sensor), sc.sensor)
    out = scans.simulate_scans(scene, sc.sensor, traj.angle(t), np.random.default_rng(seed), beam_times_s=t)
    return scene, t, out


@pytest.fixture(scope="module")
def exact_base():
    """tunnel_v's narrow sweep, exact sensor (no noise, centre ray only, no quantisation): scene and output."""
    sc = small_scenario(**EXACT)
    scene, t, out = _run_timed(sc)
    return sc, scene, t, out


def test_defaults_are_off() -> None:
    """Every systematic term and the echoes are off by default: no bias array, no echo arrays."""
    sensor = small_scenario().sensor
    assert sensor.systematic == SystematicConfig()
    assert lidar.systematic_bias_m(np.full((2, 3), 500.0), sensor, np.zeros((2, 3))) is None
    assert not sensor.echoes.enabled
    assert systematic_truth(sensor) is None


def test_ground_truth_declares_the_systematic_errors() -> None:
    sensor = small_scenario(sensor={"systematic": {"range_offset_m": 0.01, "intensity_bias_m_per_decade": -0.002,
                                                   "intensity_ref_counts": 100.0}}).sensor
    t = systematic_truth(sensor)
    assert t is not None and t["range_offset_m"] == 0.01 and "drift_amplitude_m" not in t
    assert t["saturated_return_bias_m"] == pytest.approx(-0.002 * math.log10(65535.0 / 100.0), abs=1e-15)


def test_constant_offset_shifts_every_range(exact_base) -> None:
    sc, scene, _, base = exact_base
    _, _, out = _run_timed(_with(sc, systematic={"range_offset_m": 0.0123}), scene)
    both = np.isfinite(base.ranges_m) & np.isfinite(out.ranges_m)
    assert both.sum() > 20000
    assert np.abs(out.ranges_m[both] - base.ranges_m[both] - 0.0123).max() < 1e-12
    assert np.array_equal(np.isfinite(out.ranges_m), np.isfinite(base.ranges_m))
    assert np.array_equal(out.intensities, base.intensities)  # the range bias leaves the intensities alone


def test_incidence_bias_matches_the_angle(exact_base) -> None:
    """k_theta * theta with theta the analytic incidence angle on the tunnel's planes (centre ray only)."""
    sc, scene, _, base = exact_base
    k = 0.02
    _, _, out = _run_timed(_with(sc, systematic={"incidence_bias_m": k}), scene)
    traj = sweep_trajectory(sc.servo)
    lam = traj.angle(lidar.beam_times(lidar.scan_start_times(traj.end_s, sc.sensor), sc.sensor))
    o, d = _exact_rays_W(sc, lam)
    r_true, cos, p = _tunnel_hits(sc, o, d)
    near_marker = np.min(np.linalg.norm(p[..., None, :] - scene.markers_W, axis=-1), axis=-1) < 0.02
    on_plane = np.isfinite(base.ranges_m) & (np.abs(base.ranges_m - r_true) < 1e-6) & ~near_marker
    assert on_plane.sum() > 20000
    theta = np.arccos(np.clip(cos, 0.0, 1.0))
    shift = out.ranges_m - base.ranges_m
    assert np.abs(shift[on_plane] - k * theta[on_plane]).max() < 1e-6
    assert theta[on_plane].max() - theta[on_plane].min() > 0.5  # a real spread of angles was checked


def test_drift_follows_the_exponential(exact_base) -> None:
    sc, scene, t, base = exact_base
    A, tau, t_on = 0.01, 2.0, 0.5
    cfg = {"drift_amplitude_m": A, "drift_time_constant_s": tau, "drift_elapsed_s": t_on}
    _, _, out = _run_timed(_with(sc, systematic=cfg), scene)
    both = np.isfinite(base.ranges_m) & np.isfinite(out.ranges_m)
    expected = A * np.exp(-(t_on + t) / tau)
    assert np.abs((out.ranges_m - base.ranges_m)[both] - expected[both]).max() < 1e-12
    per_scan = np.nanmean(np.where(both, out.ranges_m - base.ranges_m, np.nan), axis=1)
    assert per_scan[0] > 2 * per_scan[-1] > 0  # the warm-up decays over the recording
    with pytest.raises(InputError, match="beam times"):
        lidar.systematic_bias_m(np.ones((1, 2)), _with(sc, systematic=cfg).sensor)


def test_intensity_bias_markers_vs_surfaces() -> None:
    """k_I log10(min(I, saturation) / I_ref): the saturated marker shifts by k_I log10(65535 / I_ref), the
    painted steel around it by its own (noise-free) intensity's term; with k_I < 0 the marker reads short."""
    beam, D = 560, 1.0
    sc, _ = _marker_on_beam(beam, D, 1)
    k, ref = -0.004, 1000.0
    scene, lam, base = _run(sc)
    _, _, out = _run(_with(sc, systematic={"intensity_bias_m_per_decade": k, "intensity_ref_counts": ref}), scene)
    still = np.all(lam == sc.servo.start_rad, axis=1)
    marker = np.zeros_like(base.ranges_m, dtype=bool)
    marker[still, beam] = True
    shift = out.ranges_m - base.ranges_m
    assert base.intensities[marker].min() == sc.sensor.intensity.saturation_counts
    assert np.abs(shift[marker] - k * math.log10(65535.0 / ref)).max() < 1e-12
    surf = np.isfinite(base.ranges_m) & np.isfinite(out.ranges_m) & ~marker & (base.intensities < 60000)
    assert surf.sum() > 20000
    # base intensities are rounded to counts: the bias used the unrounded value (|I - I_rounded| <= 0.5)
    counts = base.intensities[surf]
    tol = abs(k) * np.log10(counts / (counts - 0.5)) + 1e-12
    assert np.all(np.abs(shift[surf] - k * np.log10(counts / ref)) <= tol)
    assert shift[marker].max() < shift[surf].min()  # k < 0: the saturated markers read shortest of all


def test_echoes_split_at_edges_and_match_scan_elsewhere() -> None:
    """Footprint 7 at 20 mrad over a marker: edge beams split into a marker echo and a surface echo (the /scan
    mixture between them); single-surface beams' only echo is their /scan return bit for bit (noise on); /scan
    itself does not change when the echoes are switched on."""
    beam, D = 500, 1.0  # the tunnel's far end (about 1.6-2.2 m) behind the marker
    sc0, _ = _marker_on_beam(beam, D, 7)
    sc0 = _with(sc0, divergence_rad=0.02, noise=True, quantisation_m=0.001)
    sc = _with(sc0, echoes={"enabled": True, "separation_m": 0.1})
    scene, lam, plain = _run(sc0, seed=5)
    _, _, out = _run(sc, scene, seed=5)
    assert plain.echo_ranges_m is None and out.echo_ranges_m is not None and out.echo_intensities is not None
    assert np.array_equal(plain.ranges_m, out.ranges_m, equal_nan=True)
    assert np.array_equal(plain.intensities, out.intensities)
    er, ei = out.echo_ranges_m, out.echo_intensities
    assert er.shape == plain.ranges_m.shape + (3,)
    still = np.flatnonzero(np.all(lam == sc.servo.start_rad, axis=1))
    s = still[0]
    far = np.r_[beam - 60:beam - 15, beam + 15:beam + 60]
    far = far[np.isfinite(out.ranges_m[s, far])]
    assert far.size > 50
    assert np.array_equal(er[s, far, 0], out.ranges_m[s, far])
    assert np.array_equal(ei[s, far, 0], out.intensities[s, far])
    assert np.isnan(er[s, far, 1:]).all()
    edge = np.arange(beam - 8, beam + 9)
    two = edge[np.isfinite(er[s, edge, 1])]
    assert two.size >= 2
    for b in two:
        assert D - 0.04 < er[s, b, 0] < D + 0.04  # the marker (range noise 10 mm), nearest first
        assert er[s, b, 1] > D + 0.4  # the surface behind
        assert er[s, b, 0] - 0.04 < out.ranges_m[s, b] < er[s, b, 1] + 0.04  # /scan: their mixture
    # across the whole run: echoes nearest first, the beams' noise-free power shared between their echoes
    ok = np.isfinite(er[..., 0]) & np.isfinite(er[..., 1])
    assert ok.any() and np.all(er[..., 1][ok] > er[..., 0][ok])


def test_select_echo() -> None:
    class E:  # a LaserEcho
        def __init__(self, v):
            self.echoes = np.asarray(v, dtype=np.float32)

    ranges = [E([1.0, 2.5]), E([]), E([0.0, 3.0]), E([70.0])]
    intens = [E([100.0, 900.0]), E([]), E([5.0, 50.0]), E([10.0])]
    r, i = select_echo(ranges, intens, 0.023, 60.0, "first")
    assert np.allclose(r[[0, 2]], [1.0, 3.0]) and np.isnan(r[[1, 3]]).all() and i[1] == 0
    r, _ = select_echo(ranges, intens, 0.023, 60.0, "last")
    assert np.allclose(r[[0, 2]], [2.5, 3.0])
    r, i = select_echo(ranges, intens, 0.023, 60.0, "strongest")
    assert np.allclose(r[[0, 2]], [2.5, 3.0]) and np.allclose(i[[0, 2]], [900.0, 50.0])


def test_rig_file_echo_key() -> None:
    dh = {"a": 0.0, "alpha": 0.0, "b": 0.0, "beta": 0.0}
    rig = parse_rig({"dh": dh, "scan": {"topic": "/echoes", "echo": "first"}}, "nominal.yaml")
    assert rig.scan_source().echo == "first"
    assert parse_rig({"dh": dh}, "nominal.yaml").scan_source().echo == "strongest"
    with pytest.raises(InputError, match="scan.echo"):
        parse_rig({"dh": dh, "scan": {"topic": "/echoes", "echo": "second"}}, "nominal.yaml")


def test_multiecho_bag_reads_back(tmp_path) -> None:
    """simulate -> write (MultiEchoLaserScan beside /scan) -> read_bag: every echo choice returns the written
    echoes (float32), and where a beam has one echo all three choices equal the /scan reading."""
    sc = small_scenario(sensor={"echoes": {"enabled": True, "separation_m": 0.004}, "divergence_rad": 0.01},
                        faults={"dropped_scans_fraction": 0.05})
    res = simulate(sc)
    assert res.echo_ranges_m is not None and res.echo_ranges_m.shape[0] == res.ranges_m.shape[0]
    out = write_recording(res, sc, tmp_path / "rec")
    assert "systematic" not in (out / "ground_truth.yaml").read_text()  # every systematic error off
    servo = ServoSource(joint="servo")
    scan = read_bag(out / "bag", ScanSource(), servo).scans
    got = {e: read_bag(out / "bag", ScanSource(topic="/echoes", echo=e), servo).scans
           for e in ("first", "strongest", "last")}
    er = res.echo_ranges_m.astype(np.float32).astype(float)
    ei = res.echo_intensities.astype(np.float32).astype(float)
    n_valid = np.isfinite(er).sum(-1)
    # beams that did not split: no power in a second echo (a dropped echo keeps its intensity in the result)
    one = (n_valid == 1) & (ei[..., 1:] == 0).all(-1)
    assert one.sum() > 10000 and (n_valid >= 2).sum() > 10
    for e, s in got.items():
        assert np.array_equal(s.stamps_s, scan.stamps_s)
        assert np.array_equal(s.ranges_m[one], scan.ranges_m[one]), e
    first = np.min(np.where(np.isfinite(er), er, np.inf), -1)
    last = np.max(np.where(np.isfinite(er), er, -np.inf), -1)
    has = n_valid > 0
    assert np.array_equal(got["first"].ranges_m[has], first[has])
    assert np.array_equal(got["last"].ranges_m[has], last[has])
    pick = np.argmax(np.where(np.isfinite(er), ei, -1.0), -1)
    strongest = np.take_along_axis(er, pick[..., None], -1)[..., 0]
    assert np.array_equal(got["strongest"].ranges_m[has], strongest[has])
    assert np.isnan(got["first"].ranges_m[~has]).all()
    insp = inspect_bag(out / "bag", ScanSource(topic="/echoes", echo="first"), servo, propose=False)
    assert insp.geometry is not None and insp.geometry.has_intensities and insp.geometry.beam_count == (1081, 1081)
    assert "echo: first" in insp.rig_snippet and insp.report is not None
    assert insp.report.n_scans == scan.stamps_s.size
    split = n_valid >= 2  # the split beams' first echo is nearer than their /scan mixture
    assert np.all(got["first"].ranges_m[split] <= got["last"].ranges_m[split])
    assert np.all(np.diff(res.echo_ranges_m[split][:, :2], axis=-1) >= 0)  # written in arrival order
    assert np.mean(got["first"].ranges_m[split] <= scan.ranges_m[split]) > 0.9


# --- the calibration side: /echoes read and calibrated like /scan; the echo choice ---------------------------------

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
FAST = CalibConfig(baseline=False, geometry=False)


def _read_echoes(folder: Path, echo: str = "strongest") -> Path:
    """A copy of a recording folder whose rig file reads the MultiEchoLaserScan topic (``echo`` per beam)."""
    out = folder.with_name(folder.name + f"_echoes_{echo}")
    shutil.copytree(folder, out)
    rig = yaml.safe_load((out / "nominal.yaml").read_text())
    rig["scan"] = {"topic": "/echoes", "stamp": "header", "echo": echo}
    (out / "nominal.yaml").write_text(yaml.safe_dump(rig, sort_keys=False))
    return out


def test_echoes_recording_calibrates_like_scan(tmp_path: Path) -> None:
    """tunnel_v with multi-echo on (one pass at 20 deg/s, for speed), read through /echoes (strongest echo) and
    through /scan: the same scans, and the same DH estimates to within 0.1 sigma. (Measured: no beam of tunnel_v
    splits at the default 0.1 m echo separation, since the markers sit 5-10 mm before the steel, so the two
    readings and estimates are identical: 0 of 413 000 beams differ.)"""
    data = yaml.safe_load((SCENARIOS / "tunnel_v.yaml").read_text())
    sc = parse_scenario(with_changes(data, {"name": "tunnel_echoes", "servo.speed_rad_s": math.radians(20.0),
                                            "servo.passes": 1, "sensor.echoes.enabled": True}),
                        "tunnel_echoes")
    folder = record(sc, tmp_path / sc.name)
    echoes = _read_echoes(folder)
    a, b = read_recording(folder).scans, read_recording(echoes).scans
    assert a.ranges_m.shape == b.ranges_m.shape and a.ranges_m.shape[0] > 300
    assert np.array_equal(a.stamps_s, b.stamps_s)
    differ = (a.ranges_m != b.ranges_m) & (np.isfinite(a.ranges_m) | np.isfinite(b.ranges_m))
    assert differ.mean() < 1e-3, f"{differ.sum()} of {differ.size} beams differ"
    echo = calibrate_recording(echoes, FAST)
    assert echo.status == "calibrated", echo.describe()
    assert np.all(np.abs(echo.z) <= 4.0), echo.describe()
    if differ.any():  # identical scans calibrate identically: /scan needs its own run only where a beam differs
        scan = calibrate_recording(folder, FAST)
        assert scan.status == "calibrated", scan.describe()
        assert np.all(np.abs(echo.errors - scan.errors) <= 0.1 * scan.sigma), (scan.describe(), echo.describe())


def test_strongest_echo_keeps_the_marker_where_scan_mixes(tmp_path: Path) -> None:
    """A marker 1 m out on a beam, the tunnel's far end 0.6-1.2 m behind it (far beyond echoes.separation_m): the
    beams over the marker's edge split into a marker echo and a wall echo. Read back from the bag, ``strongest``
    is the marker's return (saturated, at the sphere), ``last`` the wall's, and /scan the power-weighted mixture,
    pulled towards the wall. (Measured: by 0.1-0.6 mm only: the retroreflector outshines the steel by about three
    orders of magnitude, so the marker dominates the mixture.)"""
    beam, D, R = 500, 1.0, 0.005
    sc0, _ = _marker_on_beam(beam, D, 7)
    sc = _with(sc0, divergence_rad=0.02, echoes={"enabled": True})
    res = simulate(sc)
    out = write_recording(res, sc, tmp_path / "rec")
    servo = ServoSource(joint="servo")
    scan = read_bag(out / "bag", ScanSource(), servo).scans
    strongest, last = (read_bag(out / "bag", ScanSource(topic="/echoes", echo=e), servo).scans
                       for e in ("strongest", "last"))
    assert res.echo_ranges_m is not None
    split = np.isfinite(res.echo_ranges_m[..., 1])
    assert split.sum() >= 20
    r = strongest.ranges_m[split]
    assert np.all(np.abs(r - D) <= R + 0.002), r  # on the sphere (noise off; the sweep moves it by < 2 mm)
    assert np.all(strongest.intensities[split] == sc.sensor.intensity.saturation_counts)
    assert np.all(last.ranges_m[split] > D + 0.5)  # the wall behind
    mix = scan.ranges_m[split] - r
    assert np.all(mix > 0) and np.all(mix < last.ranges_m[split] - r), mix  # between marker and wall
    one = ~split & np.isfinite(scan.ranges_m)
    assert np.array_equal(strongest.ranges_m[one], scan.ranges_m[one])  # a beam that does not split: /scan


def test_inspect_proposes_the_multiecho_topic_with_strongest(tmp_path: Path) -> None:
    """`lrfcal inspect` on a bag with /scan and /echoes proposes /echoes with `echo: strongest` and says why; asked
    for /scan, it says that /echoes is there; a bag without echoes gets /scan and no such note."""
    with_echoes = write_recording(simulate(small_scenario(sensor={"echoes": {"enabled": True}})), small_scenario(
        sensor={"echoes": {"enabled": True}}), tmp_path / "echoes")
    plain = write_recording(simulate(small_scenario()), small_scenario(), tmp_path / "plain")
    guessed = inspect_bag(with_echoes / "bag", propose=False)
    assert guessed.scan_source is not None and guessed.scan_source.topic == "/echoes"
    rig = yaml.safe_load(guessed.rig_snippet)
    assert rig["scan"]["topic"] == "/echoes" and rig["scan"]["echo"] == "strongest"
    assert parse_rig(rig, "snippet").scan_source().echo == "strongest"
    (note,) = guessed.notes
    for words in ("/echoes", "strongest", "/scan", "marker", "splits"):
        assert words in note, (words, note)
    assert guessed.report is not None and guessed.report.n_scans > 50
    asked = inspect_bag(with_echoes / "bag", ScanSource(topic="/scan"), propose=False)
    assert asked.scan_source == ScanSource(topic="/scan") and "echo" not in yaml.safe_load(asked.rig_snippet)["scan"]
    assert len(asked.notes) == 1 and "/echoes" in asked.notes[0] and "echo: strongest" in asked.notes[0]
    none = inspect_bag(plain / "bag", propose=False)
    assert none.scan_source is not None and none.scan_source.topic == "/scan" and not none.notes
    assert "echo" not in yaml.safe_load(none.rig_snippet)["scan"]


def test_inspect_prints_the_echo_note(tmp_path: Path) -> None:
    """The printed inspection carries the note (rich console into a string)."""
    from rich.console import Console

    from lrfcal.cli import print_inspection

    sc = small_scenario(sensor={"echoes": {"enabled": True}})
    out = write_recording(simulate(sc), sc, tmp_path / "rec")
    console = Console(width=200, record=True, file=io.StringIO())
    print_inspection(inspect_bag(out / "bag", propose=False), console)
    text = console.export_text()
    assert "note: scan: /echoes (MultiEchoLaserScan) with echo: strongest" in text
    assert "echo: strongest" in text.split("rig file")[1]


def test_sensor_errors_line_and_the_systematic_scenario() -> None:
    """`lrfsim run`'s one line on the sensor; scenarios/tunnel_v_systematic.yaml is tunnel_v with the four
    effects at the assumed magnitudes of docs/sensor_errors.md (and its own name and tolerances), nothing else."""
    base = load_scenario(SCENARIOS / "tunnel_v.yaml")
    sys_ = load_scenario(SCENARIOS / "tunnel_v_systematic.yaml")
    assert sys_.sensor.systematic == SystematicConfig(
        range_offset_m=0.010, intensity_bias_m_per_decade=-0.005, intensity_ref_counts=1000.0,
        incidence_bias_m=0.010, drift_amplitude_m=0.010, drift_time_constant_s=600.0)
    same = {"name", "sensor", "tolerances"}
    assert {k: v for k, v in sys_.model_dump().items() if k not in same} == {
        k: v for k, v in base.model_dump().items() if k not in same}
    assert sys_.sensor.model_copy(update={"systematic": SystematicConfig()}) == base.sensor
    text = (SCENARIOS / "tunnel_v_systematic.yaml").read_text()
    assert "ASSUMED MAGNITUDES, NOT MEASURED" in text
    idealised, on = sensor_errors_line(base.sensor), sensor_errors_line(sys_.sensor)
    assert "idealised" in idealised and "ON" not in idealised
    assert on.startswith("sensor: systematic range errors ON (offset +10 mm, intensity -5 mm/decade, incidence "
                         "+10 mm/rad, drift +10 mm (tau 600 s))")
    for line in (idealised, on):
        assert "\n" not in line and line.endswith("docs/sensor_errors.md")
