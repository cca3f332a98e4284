"""The programs' progress display (lrfcal.terminal.progress.progress_display) and BLAS thread policy
(lrfcal.runtime.threads).

The display is drawn on a terminal only, never with --quiet: stage names, scans and trials appear on a (forced)
terminal, nothing of them on a pipe or a file. The thread limit is set by the console scripts' entry (run_app),
not by importing or calling the library.
"""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from rich.console import Console
from test_cli_sim import _main, _write_small
from test_memory import fresh_python

import lrfcal.terminal.progress as progress
from lrfcal.pipeline import STAGES
from lrfcal.stages.targetless import STAGES as TARGETLESS_STAGES
from lrfcal.terminal.progress import progress_display


def _terminal() -> tuple[Console, io.StringIO]:
    buf = io.StringIO()
    return Console(file=buf, force_terminal=True, width=120), buf


def _drive(console: Console, quiet: bool = False) -> None:
    """What a calibration in `lrfsim run` reports: scans, every stage, then what is written."""
    with progress_display("simulating x", quiet=quiet, console=console) as hooks:
        for done in (16, 32):
            hooks.scans(done, 32)
        for stage in STAGES:
            hooks.stage(stage)
        hooks.stage("figures and report")


def test_every_stage_appears_on_a_terminal() -> None:
    console, buf = _terminal()
    _drive(console)
    text = buf.getvalue()
    for stage in STAGES:
        assert f"calibrating: {stage}" in text, stage
    assert "writing figures and report" in text


def test_targetless_stages_are_counted_as_their_own() -> None:
    console, buf = _terminal()
    with progress_display("calibrating x", console=console) as hooks:
        for stage in TARGETLESS_STAGES:
            hooks.stage(stage)
    text = buf.getvalue()
    n = len(TARGETLESS_STAGES)
    for k, stage in enumerate(TARGETLESS_STAGES):
        assert f"calibrating: {stage}" in text and f"stage {k + 1}/{n}" in text, stage


def test_trials_and_steps_appear_on_a_terminal() -> None:
    console, buf = _terminal()
    with progress_display("study of x", console=console) as hooks:
        hooks.trials(1, 3)
    with progress_display("reprojecting x", console=console) as hooks:
        hooks.steps("reading", 5, 10)
        console.print("")  # the line is drawn with the next output at the latest
    assert "1/3 trials" in buf.getvalue() and "reprojecting x: reading" in buf.getvalue()


def test_nothing_on_a_pipe_or_with_quiet() -> None:
    buf = io.StringIO()
    _drive(Console(file=buf))  # not a terminal
    assert buf.getvalue() == ""
    console, buf = _terminal()
    _drive(console, quiet=True)
    assert buf.getvalue() == ""


def test_lrfsim_simulate_shows_scans_on_a_terminal_only(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    scen = _write_small(tmp_path)
    assert _main(["simulate", str(scen), "-o", str(tmp_path / "a")]) == 0  # stderr captured: not a terminal
    assert capsys.readouterr().err == ""
    console, buf = _terminal()
    monkeypatch.setattr(progress, "progress_console", lambda: console)
    assert _main(["simulate", str(scen), "-o", str(tmp_path / "b")]) == 0
    assert "simulating tunnel_v" in buf.getvalue()
    console, buf = _terminal()
    monkeypatch.setattr(progress, "progress_console", lambda: console)
    assert _main(["simulate", str(scen), "-o", str(tmp_path / "c"), "--quiet"]) == 0
    assert buf.getvalue() == ""
    assert capsys.readouterr().err == ""


def test_lrfsim_plan_shows_a_status_on_a_terminal(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    console, buf = _terminal()
    monkeypatch.setattr(progress, "progress_console", lambda: console)
    _main(["plan", str(_write_small(tmp_path)), "--markers-only"])  # exit 0 or 3: the display is what is tested
    assert "planning tunnel_v" in buf.getvalue()
    capsys.readouterr()


# --- the thread policy ----------------------------------------------------------------------------------------

PROBE = """
import json, sys
import threadpoolctl
from {package}.cli import app, main
from lrfcal.terminal.cliutil import Command

@app.command("probe", cls=Command)
def probe() -> None:
    assert "numpy" not in sys.modules and "scipy" not in sys.modules  # nothing loaded for the policy's sake
    import numpy, scipy.linalg  # the libraries a command loads are limited as they load
    print(json.dumps([i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"]))

main(["probe"])
"""


def _threads_in_a_run(package: str, env_value: str | None) -> list[int]:
    """BLAS threads per loaded BLAS library, as seen by a command run through the console entry of ``package``."""
    from lrfcal.runtime.threads import LIBRARY_ENV

    # neither the override nor the variables this process's own policy set (the policy under test sets them)
    env = {k: v for k, v in os.environ.items() if k != "LRF_CALIB_BLAS_THREADS" and k not in LIBRARY_ENV}
    if env_value is not None:
        env["LRF_CALIB_BLAS_THREADS"] = env_value
    proc = subprocess.run([sys.executable, "-c", PROBE.format(package=package)], capture_output=True, text=True,
                          env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("package", ["lrfcal", "lrfsim"])
def test_console_entry_limits_every_blas(package: str) -> None:
    threads = _threads_in_a_run(package, None)
    assert len(threads) >= 2 and threads == [1] * len(threads), threads  # numpy's and scipy's OpenBLAS
    threads = _threads_in_a_run(package, "2")  # the override reaches the libraries too (OpenBLAS: at most the cores)
    assert threads == [min(2, os.cpu_count() or 1)] * len(threads), threads


def test_library_leaves_the_callers_threads() -> None:
    """Importing the library and the policy's context manager leave the process's limits as they were."""
    code = ("import threadpoolctl, numpy, scipy.linalg; before = threadpoolctl.threadpool_limits(limits=2)\n"
            "import lrfcal.pipeline, lrfcal.cli, lrfsim.trials.study\n"
            "from lrfcal.runtime.threads import thread_policy\n"
            "info = threadpoolctl.threadpool_info\n"
            "n = lambda: sorted({i['num_threads'] for i in info() if i['user_api'] == 'blas'})\n"
            "a = n()\nwith thread_policy(): b = n()\nprint(a, b, n())")
    proc = fresh_python(code, unset="LRF_CALIB_BLAS_THREADS")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["[2]", "[1]", "[2]"], proc.stdout


def test_bad_override_is_one_line_exit_2(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("LRF_CALIB_BLAS_THREADS", "many")
    assert _main(["schema"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: LRF_CALIB_BLAS_THREADS") and "'many'" in err[0], err


def test_a_job_that_calibrates_nothing_does_not_load_the_pipeline() -> None:
    """``lrfsim plan`` and ``lrfsim simulate`` draw the progress line too: the calibration's stages (lrfcal.pipeline,
    which loads every stage and scipy.ndimage, 0.1 s) are imported only when a calibration reports its first stage."""
    probe = ("import sys\n"
             "from lrfcal.terminal.progress import progress_display\n"
             "with progress_display('job', quiet=True) as hooks:\n"
             "    hooks.scans(1, 2); hooks.steps('writing', 1, 1)\n"
             "    before = 'lrfcal.pipeline' in sys.modules\n"
             "    hooks.stage('mds')\n"
             "print(before, 'lrfcal.pipeline' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "True"]
