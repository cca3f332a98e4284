"""The first hour of a new user (issue 11), through the INSTALLED console scripts ``lrfcal`` and ``lrfsim`` (their help
and usage errors, :func:`_run`) and through their entry points called in this process (:func:`_call`: the same
``main(argv)`` the scripts call, without a new interpreter's start-up for every call).

Every mistake ends in exit code 2 (bad input or usage), exactly one line on stderr starting with ``error:``, no
traceback, and nothing written or deleted that should not be. Every command's help shows its units and defaults.
"""

from __future__ import annotations

import contextlib
import copy
import importlib
import io
import json
import os
import shutil
import subprocess
import traceback
from collections.abc import Callable
from pathlib import Path

import pytest
import yaml
from conftest import console_script

from lrfcal.io.files import MANIFEST_NAME
from lrfsim.scenario.file import Scenario, load_scenario

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "scenarios"




def _env(columns: int = 80) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["COLUMNS"] = str(columns)
    return env


def _run(prog: str, *args: str | Path, cwd: Path | None = None, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([console_script(prog), *map(str, args)], capture_output=True, text=True, cwd=cwd, env=_env(),
                          timeout=timeout)


def _call(prog: str, *args: str | Path, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """``prog``'s ``main(argv)`` called in this process as its console script calls it, with what :func:`_run` gives
    the script (COLUMNS=80, no display, ``cwd``) and its stdout, stderr and exit code caught alike: an exception
    that escapes ``main`` is a crash, its traceback on stderr and exit 1, as the interpreter would end the script.
    The environment and the working folder are restored after. For the tests of what a command does; the scripts
    themselves are run by :func:`_run` (their start-up, tests/test_startup.py)."""
    main = importlib.import_module(f"{prog}.cli").main
    argv = [str(a) for a in args]
    out, err = io.StringIO(), io.StringIO()
    env, here = dict(os.environ), Path.cwd()
    os.environ.clear()
    os.environ.update(_env())
    code: int = 0
    try:
        if cwd is not None:
            os.chdir(cwd)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                main(argv)
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
            except Exception:  # the crash, as the interpreter reports it
                traceback.print_exc()
                code = 1
    finally:
        os.chdir(here)
        os.environ.clear()
        os.environ.update(env)
    return subprocess.CompletedProcess([prog, *argv], code, out.getvalue(), err.getvalue())


def _one_error_line(proc: subprocess.CompletedProcess, code: int = 2) -> str:
    """Assert: exit ``code``, exactly one stderr line 'error: ...', no traceback; return the line."""
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == code, (proc.returncode, proc.stderr)
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("error: "), lines[0]
    return lines[0]


def _tree(folder: Path) -> dict[str, bytes]:
    """Every file below ``folder`` with its content (to prove nothing changed)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _small(tmp_path: Path, name: str = "small.yaml", **changes: object) -> Path:
    """A tiny tunnel scenario (30 scans): the sweep of tests/test_cli_sim.py's _write_small."""
    data = copy.deepcopy(yaml.safe_load((SCENARIOS / "tunnel_v.yaml").read_text()))
    data["servo"].update({"start_rad": 0.05, "end_rad": -0.05, "passes": 1, "settle_s": 0.05})
    for dotted, value in changes.items():
        node = data
        *head, last = dotted.split(".")
        for k in head:
            node = node.setdefault(k, {})
        node[last] = value
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small recording written by the installed ``lrfsim simulate``."""
    tmp = tmp_path_factory.mktemp("rec")
    rec = tmp / "rec"
    proc = _run("lrfsim", "simulate", _small(tmp), "-o", rec)
    assert proc.returncode == 0, proc.stderr
    return rec


# --- help -----------------------------------------------------------------------------------------------------

HELP = {
    ("lrfcal", "calibrate"): ["[m]", "[s]", "[default: the rig file's range_sigma_m, else 0.01]", "[default: 0.0",
                              "[default: RECORDING/bag]"],
    ("lrfcal", "check"): ["CALIBRATION RECORDING -o DIR", "[default: 0.05]", "[default: the calibration's own rig "
                          "file]", "4: drifted"],
    ("lrfcal", "convert"): ["LOG -o BAG", "[default: guessed from the log, as lrfcal inspect does]",
                            "sensor_msgs/LaserScan on /scan", "Scan logs"],
    ("lrfsim", "simulate"): ["-o DIR", "SCENARIO"],
    ("lrfsim", "run"): ["[default: runs/<scenario name>]", "[default: DIR/rerun.rrd]"],
    ("lrfsim", "schema"): ["--markdown"],
}


@pytest.mark.parametrize(("prog", "cmd"), list(HELP))
def test_help_shows_units_defaults_and_clean_usage(prog: str, cmd: str) -> None:
    proc = _run(prog, cmd, "--help")
    assert proc.returncode == 0 and proc.stderr == ""
    out = proc.stdout
    flat = " ".join(out.split())  # help wraps at 80 columns
    for words in HELP[(prog, cmd)]:
        assert words in flat, (words, out)
    usage = out.splitlines()[0]
    assert usage.startswith(f"Usage: {prog} {cmd} ") and "{" not in usage, usage
    assert "<bool>" not in out and "thin CLI" not in out
    assert max(len(line) for line in out.splitlines()) <= 80, out


def test_top_level_help() -> None:
    for prog, commands in (("lrfcal", ["calibrate", "check", "inspect", "reproject", "convert"]),
                           ("lrfsim", ["simulate", "run", "schema"])):
        proc = _run(prog, "--help")
        assert proc.returncode == 0 and "thin CLI" not in proc.stdout
        assert all(c in proc.stdout for c in commands)
    sim = _run("lrfsim", "simulate", "--help").stdout
    assert "DIR" not in sim.replace("-o DIR", "").replace("--out DIR", "")  # no phantom DIR argument


# --- usage errors ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("prog", ["lrfcal", "lrfsim"])
def test_no_arguments_shows_help_and_exits_2(prog: str) -> None:
    proc = _run(prog)
    assert "Usage:" in proc.stdout
    assert "no command given" in _one_error_line(proc)


USAGE_ERRORS = [
    ("lrfcal", ["calibrate"], "Missing argument 'RECORDING'"),
    ("lrfcal", ["calibrate", "REC"], "Missing option '-o'"),
    ("lrfcal", ["calibrate", "REC", "-o", "OUT", "--range-sigma", "0"], "--range-sigma"),
    ("lrfcal", ["calibrate", "REC", "-o", "OUT", "--range-sigma", "abc"], "--range-sigma"),
    ("lrfcal", ["calibrate", "REC", "-o", "OUT", "--clock-offset", "nan"], "finite"),
    ("lrfcal", ["calibrate", "REC", "-o", "OUT", "--clock-offset", "inf"], "finite"),
    ("lrfcal", ["calibrate", "REC", "-o", "OUT", "--bogus"], "No such option: --bogus"),
    ("lrfcal", ["calibrat"], "No such command"),
    ("lrfsim", ["simulate"], "Missing argument 'SCENARIO'"),
    ("lrfsim", ["simulate", "x.yaml"], "Missing option '-o'"),
    ("lrfsim", ["run", "x.yaml", "--bogus"], "No such option"),
    ("lrfsim", ["simulate", "x.yaml", "-o"], "requires an argument"),
]


@pytest.mark.parametrize(("prog", "args", "words"), USAGE_ERRORS)
def test_usage_errors_one_line_exit_2(prog: str, args: list[str], words: str, tmp_path: Path) -> None:
    proc = _run(prog, *args, cwd=tmp_path)
    line = _one_error_line(proc)
    assert words in line and "--help" in line
    assert list(tmp_path.iterdir()) == []


# --- bad scenarios --------------------------------------------------------------------------------------------

BAD_SCENARIOS = [
    ({"markers.layout.z_apex_m": float("nan")}, "markers.layout.z_apex_m: must be a finite number"),
    ({"scene.tunnel.plate_x_m": float("inf")}, "scene.tunnel.plate_x_m: must be a finite number"),
    ({"markers.layout": {"kind": "points", "positions": [[0.5, 0.3, 1.0], [1.0, 0.3, float("nan")]]}},
     "markers.layout.positions[1][2]: must be a finite number"),
    ({"sensor.scan_period_s": 1e-6, "sensor.time_increment_s": 1e-10}, "GiB"),
    ({"sensor.n_beams": 100000, "sensor.angle_increment_rad": 6e-5, "sensor.time_increment_s": 2.5e-7,
      "servo.passes": 100}, "GiB"),
    ({"sensor.n_beams": 100000}, "more than a turn"),
    ({"sensor.scan_period_s": 1e-6}, "longer than scan_period_s"),
    ({"servo.sped_rad_s": 1.0}, "did you mean 'speed_rad_s'"),
    ({"markers.layout.z_apx_m": 1.0}, "did you mean 'z_apex_m'"),
]


@pytest.mark.parametrize(("changes", "words"), BAD_SCENARIOS)
def test_bad_scenario_one_line_nothing_written(changes: dict[str, object], words: str, tmp_path: Path) -> None:
    scen = _small(tmp_path, **changes)
    proc = _call("lrfsim", "simulate", scen, "-o", tmp_path / "rec")
    line = _one_error_line(proc)
    assert words in line and str(scen) in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["small.yaml"]
    if "GiB" in words:  # the estimate is in the message and nothing was cast
        assert "scans x" in line and "beams" in line


def test_binary_and_broken_yaml_scenarios(tmp_path: Path) -> None:
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(bytes(range(256)) * 4)
    assert "not a text (UTF-8) file" in _one_error_line(_call("lrfsim", "simulate", binary, "-o", tmp_path / "o"))
    broken = tmp_path / "broken.yaml"
    broken.write_text("name: x\nrig: {dh: [1, 2\n")
    line = _one_error_line(_call("lrfsim", "run", broken, "-o", tmp_path / "o"))
    assert f"{broken}:3:1: YAML syntax error" in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["binary.yaml", "broken.yaml"]


def test_unwritable_output(tmp_path: Path) -> None:
    scen = _small(tmp_path)
    blocker = tmp_path / "file"
    blocker.write_text("x")
    line = _one_error_line(_call("lrfsim", "simulate", scen, "-o", blocker / "sub" / "rec"))
    assert "cannot write" in line and str(blocker / "sub" / "rec") in line
    line = _one_error_line(_call("lrfcal", "calibrate", tmp_path, "-o", blocker / "cal"))
    assert "cannot write" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "small.yaml"]


def test_output_may_not_overlap_the_scenario(tmp_path: Path) -> None:
    scen = _small(tmp_path)
    line = _one_error_line(_call("lrfsim", "simulate", scen, "-o", tmp_path, "--overwrite"))
    assert "overlap" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["small.yaml"]


def test_run_without_o_keeps_user_files(tmp_path: Path) -> None:
    scen = _small(tmp_path)
    mine = tmp_path / "runs" / "tunnel_v" / "my_notes.txt"
    mine.parent.mkdir(parents=True)
    mine.write_text("precious")
    line = _one_error_line(_call("lrfsim", "run", scen, cwd=tmp_path))
    assert "not written by lrf-calib" in line
    assert mine.read_text() == "precious"
    assert sorted(p.name for p in mine.parent.iterdir()) == ["my_notes.txt"]


# --- bad recordings and outputs for lrfcal --------------------------------------------------------------------

def test_recording_is_never_an_output(recording: Path, tmp_path: Path) -> None:
    before = _tree(recording)
    for out in (recording, recording / "bag", recording.parent):
        line = _one_error_line(_call("lrfcal", "calibrate", recording, "-o", out, "--overwrite"))
        assert "outputs never overlap inputs" in line, line
    line = _one_error_line(_call("lrfcal", "calibrate", recording, "-o", tmp_path / "cal", "--rrd",
                                recording / "nominal.yaml"))
    assert "--rrd" in line
    assert _tree(recording) == before and list(tmp_path.iterdir()) == []
    # inside the recording folder but beside its inputs is allowed (REC/calibration touches no input file)
    proc = _call("lrfcal", "calibrate", recording, "-o", recording / "calibration")
    assert "overlap" not in proc.stderr and "Traceback" not in proc.stderr
    assert {k: v for k, v in _tree(recording).items() if not k.startswith("calibration")} == before


def test_overwrite_only_replaces_own_output(recording: Path, tmp_path: Path) -> None:
    out = tmp_path / "cal"
    out.mkdir()
    (out / "thesis.tex").write_text("years of work")
    for extra in ((), ("--overwrite",)):  # without --overwrite the message already says it would not help
        line = _one_error_line(_call("lrfcal", "calibrate", recording, "-o", out, *extra))
        assert "not written by lrf-calib" in line and "not even with --overwrite" in line
    (out / MANIFEST_NAME).write_text(yaml.safe_dump({"written_by": "lrfcal calibrate", "entries": ["report.md"]}))
    line = _one_error_line(_call("lrfcal", "calibrate", recording, "-o", out, "--overwrite"))
    assert "thesis.tex" in line and "did not write" in line
    assert (out / "thesis.tex").read_text() == "years of work"
    (tmp_path / "thesis.tex").write_bytes((out / "thesis.tex").read_bytes())
    (out / "thesis.tex").unlink()  # the user moves it away: now it is our own folder, --overwrite replaces it
    line = _one_error_line(_call("lrfcal", "calibrate", recording, "-o", out))
    assert "use --overwrite" in line


def _copy_recording(recording: Path, tmp_path: Path) -> Path:
    rec = tmp_path / "rec"
    shutil.copytree(recording, rec)
    return rec


def test_nominal_alpha_in_degrees(recording: Path, tmp_path: Path) -> None:
    rec = _copy_recording(recording, tmp_path)
    nominal = yaml.safe_load((rec / "nominal.yaml").read_text())
    nominal["dh"]["alpha"] = 90
    (rec / "nominal.yaml").write_text(yaml.safe_dump(nominal))
    line = _one_error_line(_call("lrfcal", "calibrate", rec, "-o", tmp_path / "cal"))
    assert "dh.alpha" in line and "looks like degrees" in line and "nominal.yaml" in line
    assert not (tmp_path / "cal").exists()


def test_nominal_yaml_syntax_error_has_line_and_column(recording: Path, tmp_path: Path) -> None:
    rec = _copy_recording(recording, tmp_path)
    (rec / "nominal.yaml").write_text("dh: {a: 0.01, alpha: 1.57\nmount: x\n")
    line = _one_error_line(_call("lrfcal", "calibrate", rec, "-o", tmp_path / "cal"))
    assert "nominal.yaml:" in line and "YAML syntax error" in line
    assert line.split("nominal.yaml:")[1].split(":")[0].isdigit() and line.split("nominal.yaml:")[1].split(":")[1]\
        .isdigit()


@pytest.mark.parametrize(("scale", "unit"), [(1000.0, "millimetres"), (100.0, "centimetres"), (30.0, "centimetres")])
def test_tape_in_mm_or_cm(recording: Path, tmp_path: Path, scale: float, unit: str) -> None:
    """x1000 and x100: the median is too long; x30: the median passes, the longest distance exceeds the ranges."""
    rec = _copy_recording(recording, tmp_path)
    rows = (rec / "distances.csv").read_text().splitlines()
    scaled = [rows[0]] + [",".join([*r.split(",")[:2], f"{float(r.split(',')[2]) * scale:.3f}"]) for r in rows[1:]]
    (rec / "distances.csv").write_text("\n".join(scaled) + "\n")
    line = _one_error_line(_call("lrfcal", "calibrate", rec, "-o", tmp_path / "cal"))
    assert "distances.csv" in line and unit in line.split("looks like it is in")[1].split(" or ")[0], line
    assert not (tmp_path / "cal").exists()


# --- --spawn where no viewer can start (lrfsim run --spawn: tests/test_cli_sim.py) -------------------------------

def test_spawn_without_viewer_saves_rrd_and_goes_on(tmp_path: Path, recording_of: Callable[[Scenario], Path]
                                                    ) -> None:
    scen = _small(tmp_path, **{"servo.start_rad": 1.5707963267948966, "servo.end_rad": -1.5707963267948966,
                               "servo.speed_rad_s": 0.5235987755982988, "servo.settle_s": 0.2})
    recording = recording_of(load_scenario(scen))
    # lrfcal on a recording, --spawn without --rrd: the recording lands in the output folder
    cal = tmp_path / "cal"
    proc = _call("lrfcal", "calibrate", recording, "-o", cal, "--spawn", "--no-figures")
    assert proc.returncode == 0, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and "rerun.rrd" in proc.stderr
    assert (cal / "rerun.rrd").stat().st_size > 0
    assert "rerun.rrd" in yaml.safe_load((cal / MANIFEST_NAME).read_text())["entries"]
    # the calibration table's title is short; the solver status has its own line
    first = proc.stdout.strip().splitlines()[0].strip()
    assert first == "Calibration", first
    assert any(line.startswith("solver: ") for line in proc.stdout.splitlines())
    assert all(f"{n} (deg)" in proc.stdout for n in ("rx", "ry", "rz"))  # the rotation's sigma rows
    # a second run into the same folder replaces only what lrfcal wrote
    proc = _call("lrfcal", "calibrate", recording, "-o", cal, "--overwrite", "--no-figures")
    assert proc.returncode == 0, proc.stderr


# --- the scenario format is documented ------------------------------------------------------------------------

def test_schema_and_docs_page_up_to_date() -> None:
    from lrfsim.scenario.markdown_page import scenario_markdown

    proc = _call("lrfsim", "schema")
    assert proc.returncode == 0
    schema = json.loads(proc.stdout)
    sensor = schema["$defs"]["SensorConfig"]["properties"]
    assert "[s]" in sensor["scan_period_s"]["description"] and sensor["scan_period_s"]["default"] == 0.025
    page = (ROOT / "docs" / "scenario.md").read_text()
    assert page == scenario_markdown(), "docs/scenario.md is stale: run lrfsim schema --markdown > docs/scenario.md"
    assert _call("lrfsim", "schema", "--markdown").stdout == page


def test_every_scenario_field_has_a_description_with_unit_or_meaning() -> None:
    from pydantic import BaseModel

    from lrfsim.scenario import file, sections

    models = [m for sc in (file, sections) for m in vars(sc).values()
              if isinstance(m, type) and issubclass(m, BaseModel) and m is not BaseModel
              and m.__module__ == sc.__name__ and not m.__name__.startswith("_")]
    assert len(models) >= 15
    for m in models:
        for name, info in m.model_fields.items():
            assert info.description, f"{m.__name__}.{name} has no description"
            for suffix, unit in (("_rad_s2", "[rad/s^2]"), ("_rad_s", "[rad/s]"), ("_m", "[m]"), ("_rad", "[rad]"),
                                 ("_s", "[s]"), ("_hz", "[Hz]")):
                if name.endswith(suffix):
                    assert unit in info.description, f"{m.__name__}.{name}: {info.description!r} lacks {unit}"
                    break
