"""Start-up of the command-line programs: help and usage errors answer without loading the heavy modules.

``lrfcal`` and ``lrfsim`` import numpy, scipy, mujoco, matplotlib, rerun and rosbags inside the commands that use
them (issue 47), and the thread and memory policies run only once a command's arguments are parsed
(lrfcal.terminal.cliutil.Command.invoke), loading nothing themselves. A calibration's bad input is answered before the
method's modules load (scipy, the pipeline, matplotlib). Each program is run in a fresh interpreter, as its console
script runs it (``main()`` with ``sys.argv``), for every case in turn; after each, the heavy modules in
``sys.modules`` are listed. Not timed: the time is benchmarks/bench_speed.py's (docs/speed.md).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

#: modules that must not be loaded by help or a usage error (top-level package names)
HEAVY = ("numpy", "scipy", "mujoco", "matplotlib", "rerun", "rosbags", "PIL", "threadpoolctl")

#: (program, arguments, expected exit code): the programs' help, every command's help, usage errors
CASES: dict[str, list[tuple[list[str], int]]] = {
    "lrfcal": [
        (["--help"], 0), ([], 2), (["--version"], 0),
        (["calibrate", "--help"], 0), (["inspect", "--help"], 0), (["reproject", "--help"], 0),
        (["convert", "--help"], 0), (["check", "--help"], 0), (["check", "cal", "rec"], 2),
        (["calibrate"], 2), (["calibrate", "rec"], 2), (["calibrate", "rec", "-o", "out", "--bogus"], 2),
        (["calibrate", "rec", "-o", "out", "--range-sigma", "nan"], 2), (["nonsense"], 2), (["--bogus"], 2),
    ],
    "lrfsim": [
        (["--help"], 0), ([], 2),
        (["simulate", "--help"], 0), (["run", "--help"], 0), (["plan", "--help"], 0), (["study", "--help"], 0),
        (["schema", "--help"], 0),
        (["simulate"], 2), (["study", "s.yaml", "-n", "zero"], 2), (["nonsense"], 2),
    ],
}

PROBE = """
import contextlib, io, json, sys
from {package}.cli import main

HEAVY = {heavy!r}
report = []
for argv, _ in {cases!r}:
    sys.argv = ["{package}", *argv]  # as the console script calls main()
    out, err = io.StringIO(), io.StringIO()
    code = None
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            main()
        except SystemExit as e:
            code = e.code
    loaded = sorted({{m.split(".")[0] for m in sys.modules}} & set(HEAVY))
    report.append([argv, code, loaded, err.getvalue()])
print(json.dumps(report))
"""


@pytest.mark.parametrize("package", sorted(CASES))
def test_help_and_usage_errors_import_nothing_heavy(package: str, tmp_path: Path) -> None:
    cases = CASES[package]
    code = PROBE.format(package=package, heavy=HEAVY, cases=cases)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          cwd=tmp_path)  # the relative paths of the cases: nothing is written there either
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert len(report) == len(cases)
    for (argv, want), (_, got, loaded, err) in zip(cases, report, strict=True):
        assert got == want, f"{package} {' '.join(argv)}: exit {got}, expected {want}; stderr: {err}"
        assert loaded == [], f"{package} {' '.join(argv)} loaded {loaded}"
        if want == 2:  # one line naming what is wrong (the no-argument case prints the help on stdout first)
            lines = err.strip().splitlines()
            assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert list(tmp_path.iterdir()) == []


BAD_INPUT_PROBE = """
import contextlib, io, json, sys
from lrfcal.cli import main

sys.argv = ["lrfcal", *sys.argv[1:]]
err = io.StringIO()
with contextlib.redirect_stderr(err):
    try:
        main()
    except SystemExit as e:
        code = e.code
method = ("scipy", "matplotlib", "rerun", "mujoco", "lrfcal.pipeline", "lrfcal.estimate.engine",
          "lrfcal.stages.propose")
print(json.dumps([code, sorted(m for m in method if m in sys.modules), err.getvalue()]))
"""


def test_bad_input_is_answered_before_the_method_loads(tmp_path: Path) -> None:
    """A missing recording, a folder without a bag, a rig file that does not parse (lrfcal calibrate), a missing
    calibration (check), a missing bag (inspect), a missing scan log (convert): exit 2 and one line, with neither
    scipy nor the method's modules (the pipeline, the estimate, the stages' search) nor matplotlib, rerun or mujoco
    loaded (each command reads and judges its inputs first: lrfcal.commands.calibrate imports
    lrfcal.commands.calibration_run only then, check and inspect the pipeline and the DH search only then)."""
    empty = tmp_path / "empty"
    empty.mkdir()
    broken = tmp_path / "broken"
    (broken / "bag").mkdir(parents=True)
    (broken / "nominal.yaml").write_text("dh: [unclosed\n")
    out, nowhere = tmp_path / "out", tmp_path / "nowhere"
    cases = [(["calibrate", nowhere, "-o", out], "not found"), (["calibrate", empty, "-o", out], "bag"),
             (["calibrate", broken, "-o", out], "nominal.yaml"), (["check", nowhere, empty, "-o", out], "nowhere"),
             (["inspect", nowhere / "bag"], "nowhere"), (["convert", nowhere / "scan.log", "-o", out], "nowhere")]
    for argv, words in cases:
        proc = subprocess.run([sys.executable, "-c", BAD_INPUT_PROBE, *map(str, argv)], capture_output=True,
                              text=True, timeout=60)
        code, loaded, err = json.loads(proc.stdout.strip().splitlines()[-1])
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and words in lines[0], (argv[:2], err)
        assert loaded == [], f"lrfcal {argv[0]} {argv[1]}: {loaded} loaded before the input was judged"
    assert not out.exists()


def test_every_command_applies_the_programs_policies() -> None:
    """The thread and memory policies run in Command.invoke: every command of both programs must be a Command (or
    a subclass of it)."""
    from lrfcal.cli import app as lrfcal_app
    from lrfcal.terminal.cliutil import Command
    from lrfsim.cli import app as lrfsim_app

    for app in (lrfcal_app, lrfsim_app):
        assert app.registered_commands
        for info in app.registered_commands:
            assert isinstance(info.cls, type) and issubclass(info.cls, Command), \
                f"{info.name or info.callback}: cls={info.cls}"


def test_the_model_names_load_on_first_use() -> None:
    """``import lrfcal`` loads no numpy; ``lrfcal.Params`` and the other model names still resolve (PEP 562)."""
    code = ("import sys, lrfcal\nbefore = 'numpy' in sys.modules\n"
            "from lrfcal import DH, PARAM_NAMES, Params, Pose\nfrom lrfcal.model import kinematics as k\n"
            "print(before, Params is k.Params and DH is k.DH and Pose is k.Pose and PARAM_NAMES == k.PARAM_NAMES)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.stdout.split() == ["False", "True"], proc.stderr
    import lrfcal

    with pytest.raises(AttributeError):
        _ = lrfcal.no_such_name


def test_the_console_script_freezes_what_is_left_before_the_exit_and_a_call_with_argv_does_not() -> None:
    """``main()`` as the console script calls it (no argv) freezes the objects left out of the garbage collector
    before the interpreter exits (the exit need not walk them: 0.1 s of a calibration); ``main(argv)``, as tests and
    scripts call it, leaves the collector of the calling process alone."""
    code = ("import gc, sys\nfrom lrfcal.cli import main\n"
            "def run(*argv):\n"
            "    try:\n        main(*argv)\n    except SystemExit as e:\n        return e.code\n"
            "sys.argv = ['lrfcal', '--version']\n"
            "print(run(['--version']), gc.get_freeze_count() == 0, run(), gc.get_freeze_count() > 0)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.stdout.split()[-4:] == ["0", "True", "0", "True"], (proc.stdout, proc.stderr)
