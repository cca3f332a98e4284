"""``lrfcal inspect`` proposes the DH from the scene's planes (lrfcal.stages.propose), and ``reproject`` refuses the
placeholder DH (issue 20, item 2).

The real recordings are read from ../shared/realbags beside the repository (not part of a clone): those tests skip
with the reason when it is absent. The authors of the URG-04LX stand use alpha = 90 deg, b = 0.08 m (a nominal, not
a measurement: tests/test_real_bags.py).
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_bag_shapes import write

from lrfcal.cli import main
from lrfcal.commands.inspect_log import inspect_path
from lrfcal.model.kinematics import DH, points_M
from lrfcal.stages.propose import DETERMINED, canonical
from lrfcal.types import JointStates, Scans
from lrfsim.trials.compare import load_truth

REALBAGS = Path(__file__).resolve().parents[2] / "shared" / "realbags"
ABSENT = f"real recordings not present at {REALBAGS} (public recordings shared beside the project, not part of a clone)"
LONGARM = REALBAGS / "longarm" / "batchScanned20191114103039.txt"
RPLIDAR = REALBAGS / "rplidar_servo_3hz"
#: the authors' model of the URG-04LX stand (liangfok/tilting_lidar_scanner)
URG_ALPHA, URG_B = math.pi / 2, 0.08


def _main(monkeypatch: pytest.MonkeyPatch, argv: list[str]) -> int:
    monkeypatch.setattr(sys, "argv", ["lrfcal", *argv])
    monkeypatch.setenv("COLUMNS", "250")
    try:
        main()
    except SystemExit as e:
        return int(e.code or 0)
    return 0


def test_equivalent_dh_give_the_same_cloud_up_to_an_isometry() -> None:
    """What canonical() folds together are the same cloud up to a rigid motion and a mirror (all pairwise distances
    equal): (a, -alpha, -b, beta) and (-a, alpha, -b, beta + 180 deg); the representative has alpha in [0, 180]
    deg and b >= 0."""
    rng = np.random.default_rng(3)
    r, lam, mu = rng.uniform(0.5, 5, 200), rng.uniform(-1.5, 1.5, 200), rng.uniform(-2, 2, 200)
    dh = DH(a=0.03, alpha=1.2, b=0.07, beta=0.4)

    def dist(d: DH) -> np.ndarray:
        P = points_M(r, lam, mu, d)
        return np.linalg.norm(P[:, None] - P[None], axis=2)

    for other in (DH(a=0.03, alpha=-1.2, b=-0.07, beta=0.4), DH(a=-0.03, alpha=1.2, b=-0.07, beta=0.4 + math.pi)):
        np.testing.assert_allclose(dist(other), dist(dh), atol=1e-9)
        c = canonical(other)
        assert (c.a, c.alpha, c.b, c.beta) == pytest.approx((dh.a, dh.alpha, dh.b, dh.beta), abs=1e-12)


@pytest.fixture(scope="module")
def room_box_inspected(shipped_recording, tmp_path_factory) -> tuple[Path, Path, str]:  # type: ignore[no-untyped-def]
    """room_box (the simulated UTM-30LX-EW rig in a room with boxes; its shipped sweep: one quick pass leaves the
    attitude ambiguous, and the proposal says so) inspected through the CLI with -o: the recording, the written rig
    file and stdout."""
    folder = shipped_recording("room_box")
    out = tmp_path_factory.mktemp("inspect") / "rig.yaml"
    mp = pytest.MonkeyPatch()
    try:
        import contextlib
        import io

        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            code = _main(mp, ["inspect", str(folder / "bag"), "-o", str(out), "--quiet"])
    finally:
        mp.undo()
    assert code == 0
    return folder, out, buf.getvalue()


def test_inspect_proposes_the_simulated_truth(room_box_inspected) -> None:  # type: ignore[no-untyped-def]
    """On a simulated recording with known truth, the proposed DH (canonical representative) are within 3 of their
    stated 1-sigma or a coarse tolerance (1 cm, 2 deg) of the truth, and every value is called determined."""
    folder, out, stdout = room_box_inspected
    truth = canonical(load_truth(folder / "ground_truth.yaml").dh)
    rig = yaml.safe_load(out.read_text())
    first = out.read_text().splitlines()[0]
    assert first.startswith("# dh: proposed from the scene's planes") and "1-sigma" in first
    sig = {k: float(v) for k, v in zip(("a", "alpha", "b", "beta"), _sigmas(first), strict=True)}
    coarse = {"a": 0.01, "alpha": math.radians(2), "b": 0.01, "beta": math.radians(2)}
    for n in ("a", "alpha", "b", "beta"):
        err = abs(rig["dh"][n] - getattr(truth, n))
        assert err <= max(3 * sig[n], coarse[n]), (n, rig["dh"][n], getattr(truth, n), sig[n])
        assert sig[n] <= DETERMINED[n]
    assert "not determined" not in first and "proposed from the scene's planes" in stdout


def _sigmas(comment: str) -> list[float]:
    """(a [m], alpha [rad], b [m], beta [rad]) 1-sigma from a proposal's comment line."""
    import re

    v = [float(x) for x in re.findall(r"\+-([0-9.]+) (?:mm|deg)", comment)]
    return [v[0] / 1000, math.radians(v[1]), v[2] / 1000, math.radians(v[3])]


def test_written_rig_file_reads_back_one_line_each(room_box_inspected) -> None:  # type: ignore[no-untyped-def]
    """inspect -o writes the rig file printed last: no trailing spaces, no wrapped line (the comment is one line),
    and it reads as a rig file whose dh are not the placeholder."""
    from lrfcal.io.rig import load_rig
    from lrfcal.model.kinematics import is_placeholder_dh

    _, out, stdout = room_box_inspected
    text = out.read_text()
    assert all(line == line.rstrip() for line in text.splitlines())
    assert sum(line.startswith("#") for line in text.splitlines()) == 1
    assert text.rstrip("\n") in stdout
    assert not is_placeholder_dh(load_rig(out).dh)


def test_reproject_refuses_the_placeholder_dh(tmp_path, monkeypatch, capsys) -> None:  # type: ignore[no-untyped-def]
    """A rig file whose dh are all 0 (what inspect writes when the scene determines no proposal): reproject exits 2
    naming the key dh, and writes nothing."""
    bag = write(tmp_path / "bag", "mcap", "canonical")
    rig = tmp_path / "rig.yaml"
    rig.write_text(yaml.safe_dump({"dh": {"a": 0.0, "alpha": 0.0, "b": 0.0, "beta": 0.0},
                                   "servo": {"joint": "servo"}}))
    code = _main(monkeypatch, ["reproject", str(bag), "--nominal", str(rig), "-o", str(tmp_path / "c.ply"), "-q"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "dh:" in err and "placeholder" in err and "Traceback" not in err
    assert not (tmp_path / "c.ply").exists()


def test_inspect_no_dh_keeps_the_placeholder(tmp_path, monkeypatch, capsys) -> None:  # type: ignore[no-untyped-def]
    bag = write(tmp_path / "bag", "mcap", "canonical")
    out = tmp_path / "rig.yaml"
    assert _main(monkeypatch, ["inspect", str(bag), "--no-dh", "-o", str(out), "-q"]) == 0
    assert yaml.safe_load(out.read_text())["dh"] == {"a": 0.0, "alpha": 0.0, "b": 0.0, "beta": 0.0}
    assert out.read_text().startswith("# dh: fill in from the drawings")


# --- real recordings --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Proposed:
    """What a rig file written by ``lrfcal inspect -o`` proposes: the DH (None: no proposal, ``reason`` says why; m,
    rad, rounded to 1e-4), their 1-sigma (m, rad; to 0.1 mm and 0.01 deg) and the parameters called not determined
    by the scene, read from its values and its one comment line (lrfcal.stages.propose.DHProposal.comment)."""

    dh: DH | None
    sigma: dict[str, float]
    undetermined: tuple[str, ...]
    reason: str


def _proposed(rig_file: Path) -> Proposed:
    text = rig_file.read_text()
    first = text.splitlines()[0]
    if not first.startswith("# dh: proposed from the scene's planes"):
        return Proposed(None, {}, (), first)
    dh = yaml.safe_load(text)["dh"]
    sigma = dict(zip(("a", "alpha", "b", "beta"), _sigmas(first), strict=True))
    tail = first.split("; not determined by the scene: ")
    undetermined = tuple(tail[1].split(";")[0].split(", ")) if len(tail) > 1 else ()
    return Proposed(DH(**dh), sigma, undetermined, "")


@pytest.fixture(scope="module")
def urg_proposals(real_inspected) -> dict[str, Proposed]:  # type: ignore[no-untyped-def]
    """The DH proposed for the URG-04LX stand's two bags: the rig files ``lrfcal inspect -o`` wrote (the session's
    runs through the installed console script, tests/conftest.py: real_inspected, shared with
    tests/test_real_walkthrough.py)."""
    if not REALBAGS.is_dir():
        pytest.skip(ABSENT)
    out = {}
    for name in ("cardboard_box", "room_240"):
        proc, rig_file = real_inspected(name)
        assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
        out[name] = p = _proposed(rig_file)
        print(name, p.dh, {k: round(v, 4) for k, v in p.sigma.items()}, p.undetermined, p.reason)
    return out


@pytest.mark.parametrize("name", ["cardboard_box", "room_240"])
def test_real_urg_stand_proposes_alpha_90(urg_proposals, name) -> None:  # type: ignore[no-untyped-def]
    """The URG-04LX stand: alpha within 15 deg of the authors' 90 deg, and called determined."""
    p = urg_proposals[name]
    assert p.dh is not None, p.reason
    assert abs(p.dh.alpha - URG_ALPHA) <= math.radians(15.0)
    assert "alpha" not in p.undetermined


@pytest.mark.parametrize("name", ["room_240"])
def test_real_urg_stand_names_b_not_determined(urg_proposals, name) -> None:  # type: ignore[no-untyped-def]
    """room_240 does not determine b, and the proposal says so. Its starts segment on subsamples of their own
    (lrfcal.stages.sampling.hash_key): their b spread over 10 cm and more (redraws of the subsamples propose 158 and
    225 mm, docs/starts.md), so b is named not determined with a 1-sigma of about 8 cm. (When every start segmented
    on nearly the same subsample, b landed 14 mm from the authors' 0.08 m with a 1-sigma of 53 mm: one draw's
    chance.) The next test asks that the authors' value lie within 2 of that sigma."""
    p = urg_proposals[name]
    assert p.dh is not None, p.reason
    assert "b" in p.undetermined and p.sigma["b"] > 0.04


@pytest.mark.parametrize("name", ["cardboard_box", "room_240"])
def test_real_urg_stand_b_is_near_the_authors_or_not_determined(urg_proposals, name) -> None:  # type: ignore[no-untyped-def]
    """Never a confident b far from the authors' 0.08 m: b within 4 cm of it, or named not determined with the
    authors' value within 2 of its sigma."""
    p = urg_proposals[name]
    assert p.dh is not None, p.reason
    if abs(p.dh.b - URG_B) > 0.04:
        assert "b" in p.undetermined and abs(p.dh.b - URG_B) <= 2.0 * p.sigma["b"], (p.dh, p.sigma)


@pytest.mark.skipif(not REALBAGS.is_dir(), reason=ABSENT)
@pytest.mark.parametrize("path", [LONGARM, RPLIDAR], ids=["longarm", "rplidar_servo_3hz"])
def test_poor_recordings_get_no_proposal_and_the_reason(path) -> None:  # type: ignore[no-untyped-def]
    """2.9 deg of motor turn (the long-arm log), or a motor angle the joint states cannot interpolate (the RPLIDAR
    servo): no proposal, the placeholder kept, and the reason in the rig file's one comment line."""
    res = inspect_path(path)
    assert res.proposal is not None and res.proposal.dh is None
    first = res.rig_snippet.splitlines()[0]
    assert first.startswith("# dh: not proposed: ") and len(res.rig_snippet.splitlines()[0]) > 40
    assert yaml.safe_load(res.rig_snippet)["dh"] == {"a": 0.0, "alpha": 0.0, "b": 0.0, "beta": 0.0}


def test_the_search_gives_the_same_candidates_on_any_number_of_cores(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """The DH search's starts are solved in groups on the cores (one in this process, the others in forked children)
    and collected in start order: the candidates reach the consensus in the same order whatever the number of cores,
    and the progress ends at the number of starts."""
    import lrfcal.stages.propose as propose

    def candidate(beams, seg, motor, start, config):  # type: ignore[no-untyped-def]
        # a cheap stand-in for a solve: fails on some starts, else depends on the start and its own subsample
        if start.b > 0 and start.beta < 0:
            return None
        return start, np.array([float(seg[:50].sum()), start.alpha])

    seen: dict[int, list] = {}

    def consensus(found, n_starts):  # type: ignore[no-untyped-def]
        seen[n_cores] = [(c[0], c[1].tolist()) for c in found]
        return propose._Consensus(None, {}, len(found), 0, "stand-in")

    monkeypatch.setattr(propose, "_candidate", candidate)
    monkeypatch.setattr(propose, "_consensus", consensus)
    scans, joints = _random_scans()
    for n_cores in (1, 2, 3):
        monkeypatch.setattr(propose, "cores", lambda n=n_cores: n)
        ticks: list[tuple[int, int]] = []
        propose.propose_dh(scans, joints, progress=lambda done, total, t=ticks: t.append((done, total)))
        n_starts = len(propose.START_ALPHA_DEG) * len(propose.START_BETA_DEG) * len(propose.START_B_M)
        assert ticks[-1] == (n_starts, n_starts) and all(d <= n_starts for d, _ in ticks)
    assert seen[1] == seen[2] == seen[3]
    assert 0 < len(seen[1]) < n_starts  # some starts failed, in the middle of the groups


def test_the_search_shares_its_starts_between_this_process_and_a_helper_from_both_ends(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """On two cores the starts are solved by a forked helper from the front and by this process from the back: each
    start once, this process's a run of the last starts, the helper's a run of the first, none left out."""
    import os
    import time

    import lrfcal.stages.propose as propose
    from lrfcal.runtime import forked

    here = os.getpid()

    def candidate(beams, seg, motor, start, config):  # type: ignore[no-untyped-def]
        time.sleep(0.05)
        return start, np.array([float(os.getpid() == here), 0.0, 0.0, 0.0])

    monkeypatch.setattr(propose, "_candidate", candidate)
    monkeypatch.setattr(propose, "cores", lambda: 2)
    scans, joints = _random_scans()
    search = propose._search(scans, joints, 0.0)
    assert isinstance(search, propose._Search)
    ks = list(range(len(search.starts)))
    solved = propose._solve_on_cores(search, ks)
    assert [k for k, _ in solved] == ks
    by_here = [k for k, cand in solved if cand is not None and cand[1][0] == 1.0]
    if forked._can_fork():
        assert 0 < len(by_here) < len(ks)
        assert by_here == ks[len(ks) - len(by_here):]  # a run from the back; the helper's a run from the front
    else:
        assert by_here == ks


def test_the_search_begun_ahead_gives_the_same_proposal_and_ends_with_a_refusal(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """lrfcal.stages.propose.proposal_ahead (the targetless calibration's DH search, begun in forked children while
    the fit runs) gives propose_dh's proposal; leaving it without asking (a refused fit) ends its children at once,
    before their starts are solved."""
    import multiprocessing
    import time

    import lrfcal.stages.propose as propose
    from lrfcal.model.kinematics import DH

    slow = [0.0]

    def candidate(beams, seg, motor, start, config):  # type: ignore[no-untyped-def]
        time.sleep(slow[0])
        if start.b > 0 and start.beta < 0:
            return None
        return DH(a=0.0, alpha=1.5 + 1e-3 * float(seg[:50].sum() % 7), b=0.01, beta=0.1), np.full(4, 1e-3)

    monkeypatch.setattr(propose, "_candidate", candidate)
    monkeypatch.setattr(propose, "cores", lambda: 2)
    scans, joints = _random_scans()
    here = propose.propose_dh(scans, joints)
    with propose.proposal_ahead(scans, joints) as proposal:
        ahead = proposal()
        assert proposal() is ahead  # asked twice: the same
    assert here.dh is not None and ahead.dh == here.dh and ahead.agreeing == here.agreeing
    assert (ahead.sigma, ahead.n_converged, ahead.n_agreeing, ahead.reason) == (here.sigma, here.n_converged,
                                                                               here.n_agreeing, here.reason)
    slow[0] = 5.0  # each group would take 30 s
    t0 = time.perf_counter()
    with pytest.raises(RuntimeError, match="refused"), propose.proposal_ahead(scans, joints):
        assert len(multiprocessing.active_children()) >= 1 or propose.cores() < 2
        raise RuntimeError("refused")
    assert time.perf_counter() - t0 < 15.0
    assert not multiprocessing.active_children()


def _random_scans() -> tuple[Scans, JointStates]:
    """40 scans of 200 random ranges and a motor turning 2 rad over them: input for stand-in searches."""
    rng = np.random.default_rng(3)
    S, N = 40, 200
    scans = Scans(stamps_s=np.arange(S) * 0.025, ranges_m=rng.uniform(1.0, 5.0, (S, N)), intensities=np.ones((S, N)),
                  mu_rad=np.linspace(-2.0, 2.0, N), time_increment_s=np.full(S, 1e-5), scan_time_s=0.025,
                  range_min_m=0.1, range_max_m=30.0)
    return scans, JointStates(stamps_s=np.linspace(-0.1, 1.1, 50), positions_rad=np.linspace(-1.0, 1.0, 50))
