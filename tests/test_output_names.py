"""Files and feedback (issue 46, case 6), through the entry points of ``lrfcal`` and ``lrfsim`` as their console
scripts call them (``main(argv)`` in this process: tests/test_cli_usage.py's ``_call``).

* No output folder keeps a temporary name: every command that writes a file or a folder (lrfcal calibrate, convert,
  inspect -o, reproject with --bag-out and --rrd; lrfsim simulate, run, study; lrfsim plan --json writes nothing)
  runs into one folder, whose whole tree is then walked for the tools' temporary naming pattern
  (lrfcal.io.files.TEMP_NAME: ``.NAME.tmp-XXXX``, ``.NAME.XXXX.tmp``, ``.NAME.old-XXXX``, ...). A bag's data file
  carries its folder's final name (rosbags names it after the folder it writes).
* Four bad inputs that were unclear get one line naming the file, the field or value and the fix, exit 2.
* Held parameters show "held", never a NaN 1-sigma; a study on local workers counts every trial as it finishes.
"""

from __future__ import annotations

import io
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
import yaml
from rich.console import Console
from synthetic import make_result
from test_cli_usage import _call, _one_error_line, _small
from test_scanlog import HEADER_LAYOUT, _write_header_log

from lrfcal.io.files import TEMP_NAME
from lrfcal.model.kinematics import ESTIMATE_NAMES
from lrfcal.report.markdown import render_report
from lrfcal.report.summary import print_summary
from lrfsim.scenario.file import load_scenario
from lrfsim.trials.study import run_trials

#: a full +-90 deg sweep of the small tunnel (30 deg/s): it calibrates (tests/test_cli_usage.py's --spawn test)
FULL_SWEEP = {"servo.start_rad": 1.5707963267948966, "servo.end_rad": -1.5707963267948966,
              "servo.speed_rad_s": 0.5235987755982988, "servo.settle_s": 0.2}
#: what a leftover temporary looks like, beyond TEMP_NAME: any hidden name with a tmp or old part
LOOSE_TEMP = re.compile(r"^\..*[.-](tmp|old)([.-]|$)")


def _temporaries(root: Path) -> list[str]:
    return [str(p.relative_to(root)) for p in root.rglob("*") if TEMP_NAME.match(p.name) or LOOSE_TEMP.match(p.name)]


def test_no_command_leaves_a_temporary_name(full_sweep_run: tuple[subprocess.CompletedProcess, Path],
                                           tmp_path: Path) -> None:
    """Every command into one folder, its tree walked; ``lrfsim run`` is the session's run of the same full sweep
    (tests/conftest.py: full_sweep_run, without -o: runs/tunnel_v beside its scenario file, shared with
    tests/test_cli_sim.py), its folder walked likewise."""
    scen = _small(tmp_path, "full.yaml", **FULL_SWEEP)
    tiny = _small(tmp_path, "tiny.yaml")
    out = tmp_path / "out"
    out.mkdir()
    rec = out / "sim"
    steps: list[tuple[str, ...]] = [
        ("lrfsim", "simulate", str(scen), "-o", str(rec), "-q"),
        ("lrfcal", "calibrate", str(rec), "-o", str(out / "cal"), "--rrd", str(out / "cal.rrd"), "-q"),
        ("lrfcal", "inspect", str(rec / "bag"), "--nominal", str(rec / "nominal.yaml"), "-o", str(out / "rig.yaml"),
         "--no-dh", "-q"),
        ("lrfcal", "reproject", str(rec / "bag"), "--nominal", str(rec / "nominal.yaml"), "-o",
         str(out / "cloud.ply"), "--bag-out", str(out / "cloudbag"), "--rrd", str(out / "cloud.rrd"), "-q"),
        ("lrfsim", "study", str(tiny), "-n", "1", "-o", str(out / "study"), "-q"),
    ]
    log = _write_header_log(tmp_path / "scan.txt")
    rig = tmp_path / "logrig.yaml"
    rig.write_text(yaml.safe_dump({"dh": {"a": 0.01, "alpha": 0.0, "b": 0.0, "beta": 0.0}, "servo": {"unit": "deg"},
                                   "log": HEADER_LAYOUT.model_dump(mode="json", exclude_defaults=True)}))
    steps.append(("lrfcal", "convert", str(log), "--nominal", str(rig), "-o", str(out / "converted")))
    for prog, *args in steps:
        proc = _call(prog, *args)
        assert proc.returncode in (0, 3), (prog, args[0], proc.returncode, proc.stderr)  # run, study: may refuse
        assert "Traceback" not in proc.stderr, proc.stderr
    proc = _call("lrfsim", "plan", tiny, "--json", "-q", cwd=out)  # prints only
    assert "Traceback" not in proc.stderr, proc.stderr
    assert _temporaries(out) == []
    assert _temporaries(tmp_path) == []
    run, ran_in = full_sweep_run
    assert run.returncode in (0, 3) and "Traceback" not in run.stderr, run.stderr  # as every command above
    assert _temporaries(ran_in) == []
    for bag in ("converted", "cloudbag", "sim/bag"):  # every bag's data file under its folder's final name
        assert sorted(p.name for p in (out / bag).iterdir()) == sorted([f"{Path(bag).name}.mcap", "metadata.yaml"])
    written = {p.name for p in out.iterdir()}
    assert {"sim", "cal", "cal.rrd", "rig.yaml", "cloud.ply", "cloudbag", "cloud.rrd", "study",
            "converted"} <= written, written


# --- the unclear bad inputs -----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny recording by the installed ``lrfsim simulate`` (only read: each test copies what it changes)."""
    tmp = tmp_path_factory.mktemp("rec")
    rec = tmp / "rec"
    proc = _call("lrfsim", "simulate", _small(tmp), "-o", rec, "-q")
    assert proc.returncode == 0, proc.stderr
    return rec


def _copy(rec: Path, dest: Path) -> Path:
    import shutil

    shutil.copytree(rec, dest)
    return dest


def test_a_folder_given_as_a_scenario_or_rig_file(recording: Path, tmp_path: Path) -> None:
    line = _one_error_line(_call("lrfsim", "simulate", recording, "-o", tmp_path / "o"))
    assert f"{recording}: a folder, not a scenario file: give the file itself, e.g. {recording / 'scenario.yaml'}" \
        in line, line
    line = _one_error_line(_call("lrfsim", "plan", tmp_path))  # a folder without any YAML file
    assert "a folder, not a scenario file" in line and "holds no YAML file" in line, line
    line = _one_error_line(_call("lrfcal", "calibrate", recording, "-o", tmp_path / "c", "--nominal", recording))
    assert f"a folder, not a nominal file: give the file itself, e.g. {recording / 'nominal.yaml'}" in line, line
    assert not (tmp_path / "o").exists() and not (tmp_path / "c").exists()


def test_an_empty_bag_folder(recording: Path, tmp_path: Path) -> None:
    rec = _copy(recording, tmp_path / "rec")
    for p in (rec / "bag").iterdir():
        p.unlink()
    line = _one_error_line(_call("lrfcal", "calibrate", rec, "-o", tmp_path / "c"))
    assert f"{rec / 'bag'}: empty folder, not a ROS 2 bag" in line and "metadata.yaml" in line, line
    assert "Expected metadata file" not in line  # not rosbags' own words, which call the folder a metadata file
    (rec / "bag" / "bag.mcap").write_bytes((recording / "bag" / "bag.mcap").read_bytes())  # the data, no metadata
    line = _one_error_line(_call("lrfcal", "inspect", rec / "bag"))
    assert f"metadata.yaml missing from the bag folder (it holds bag.mcap): give that file itself, " \
           f"{rec / 'bag' / 'bag.mcap'}" in line, line


def test_a_binary_distances_file(recording: Path, tmp_path: Path) -> None:
    rec = _copy(recording, tmp_path / "rec")
    (rec / "distances.csv").write_bytes(bytes(range(256)) * 4)
    line = _one_error_line(_call("lrfcal", "calibrate", rec, "-o", tmp_path / "c"))
    assert f"{rec / 'distances.csv'}: not a text (UTF-8) file: byte 0x80 at offset 128" in line, line
    assert "marker_i,marker_j,distance_m" in line and "codec" not in line, line


def test_marker_radius_zero_is_named_at_the_rig_file(recording: Path, tmp_path: Path) -> None:
    rec = _copy(recording, tmp_path / "rec")
    rig = yaml.safe_load((rec / "nominal.yaml").read_text())
    rig["marker_radius_m"] = 0
    (rec / "nominal.yaml").write_text(yaml.safe_dump(rig))
    line = _one_error_line(_call("lrfcal", "calibrate", rec, "-o", tmp_path / "c"))
    assert f"{rec / 'nominal.yaml'}: marker_radius_m: 0 m is no sphere" in line and "> 0" in line, line
    assert "e.g. 0.005" in line and line.endswith("got 0"), line


# --- feedback -------------------------------------------------------------------------------------------------

def test_held_parameters_say_held() -> None:
    result = make_result(n_scans=20, n_beams=61)
    sigma = np.array(result.solution.sigma, dtype=float)
    sigma[ESTIMATE_NAMES.index("b")] = np.nan  # b not estimated
    from dataclasses import replace

    held = replace(result, solution=replace(result.solution, sigma=sigma))
    buf = io.StringIO()
    print_summary(held, Console(file=buf, width=200))
    row = next(line for line in buf.getvalue().splitlines() if line.strip("│ ").startswith("b (mm)"))
    assert "held" in row and "nan" not in buf.getvalue().lower(), buf.getvalue()
    report = render_report(held)
    row = next(line for line in report.splitlines() if line.startswith("| b |"))
    assert "| held |" in row and "nan" not in row.lower(), row


def test_study_on_workers_counts_each_trial(tmp_path: Path) -> None:
    sc = load_scenario(_small(tmp_path))
    calls: list[tuple[int, int]] = []
    rows = run_trials(sc, 4, workers=2, progress=lambda done, n: calls.append((done, n)))
    assert len(rows) == 4
    # one batch of 2 trials per worker: counting batches would give 2/4, 4/4; every trial is counted
    assert [d for d, _ in calls if d < 4] == [1, 2, 3], calls
    assert calls[-1] == (4, 4) and all(n == 4 for _, n in calls), calls
