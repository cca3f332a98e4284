"""`lrfsim plan`'s speed-ups change no number (issue 47): the sparse cast shared with a forked helper process
(lrfsim.cast.forked) is bit-identical to one cast here, a helper that dies or a chunk that raises is handled here, the
plan of a cast made beforehand is the plan's own, the servo angles in blocks are the same numbers, and what runs
before the cast imports no scipy."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import yaml

from lrfcal.runtime.threads import LIBRARY_ENV
from lrfsim.cast import forked
from lrfsim.cast.forked import Forked, can_fork, run_forked, shared_empty
from lrfsim.plan.prediction import plan
from lrfsim.plan.sparse_cast import sparse_geometry, sparse_scans
from lrfsim.scenario.file import parse_scenario, with_changes
from lrfsim.sensors import servo
from lrfsim.simulation.simulate import cast_geometry

ROOT = Path(__file__).resolve().parents[1]
FORKS = can_fork(2)


def _fast_tunnel():  # tunnel_v at 30 deg/s, 2 passes: a third of its scans
    data = with_changes(yaml.safe_load((ROOT / "scenarios" / "tunnel_v.yaml").read_text()),
                        {"servo.speed_rad_s": math.radians(30.0), "servo.passes": 2})
    return parse_scenario(data, "fast tunnel")


def test_forked_cast_is_bit_identical_and_runs_meanwhile_here() -> None:
    sc = _fast_tunnel()
    here = cast_geometry(sc, noise=False, scans=partial(sparse_scans, sc), threads=1)
    calls: list[int] = []
    shared = cast_geometry(sc, noise=False, scans=partial(sparse_scans, sc),
                           threads=Forked(lambda: calls.append(os.getpid())))
    assert calls == [os.getpid()]  # once, in this process
    for name in ("ranges_m", "intensities"):
        a, b = getattr(here.cast, name), getattr(shared.cast, name)
        assert a.tobytes() == b.tobytes(), name
    assert np.isfinite(here.cast.ranges_m).sum() > 100_000  # a real cast, not two empty ones
    assert (here.cast.n_rays, here.cast.n_calls) == (shared.cast.n_rays, shared.cast.n_calls)
    assert np.array_equal(here.scans_cast, shared.scans_cast) and 0 < shared.scans_cast.sum() < len(shared.scans_cast)


def test_plan_of_a_sparse_cast_made_before_is_the_plans_own() -> None:
    """`lrfsim plan` casts first (imports overlapped) and hands plan() the cast: the same plan to the bit."""
    sc = _fast_tunnel()
    own = plan(sc)
    given = plan(sc, geometry=sparse_geometry(sc))
    assert own.sigma == given.sigma and own.n_surface_returns == given.n_surface_returns > 0
    assert own.covariance.tobytes() == given.covariance.tobytes()


def _until(done: Callable[[], bool]) -> Callable[[], None]:
    """A ``meanwhile`` that waits (at most 30 s) until ``done()``: what the helper does first is then certain."""

    def wait() -> None:
        t0 = time.monotonic()
        while not done() and time.monotonic() - t0 < 30.0:
            time.sleep(0.001)

    return wait


@pytest.mark.skipif(not FORKS, reason="no helper process can be forked here (Linux with 2 cores or more)")
def test_chunks_are_shared_with_the_helper() -> None:
    n = 24
    out = shared_empty((n,), np.nan)
    me = os.getpid()

    def run(i: int) -> tuple[int, int]:
        out[i] = 2.0 * i
        return i, os.getpid()

    values = run_forked(run, n, _until(lambda: bool(np.isfinite(out).any())))  # the helper has cast a chunk
    assert [i for i, _ in values] == list(range(n))
    assert np.array_equal(out, 2.0 * np.arange(n))  # the helper's writes reached this process
    assert {pid for _, pid in values} - {me}  # some chunks were cast by the helper


@pytest.mark.skipif(not FORKS, reason="no helper process can be forked here (Linux with 2 cores or more)")
@pytest.mark.parametrize("fate", ["dies", "is stuck"])
def test_a_helper_that_dies_or_is_stuck_leaves_its_chunks_here(fate: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(forked, "HELPER_PATIENCE_S", 0.5)
    monkeypatch.setattr(forked, "HELPER_PATIENCE_RATIO", 0.0)
    n = 8
    out = shared_empty((n,))
    me = os.getpid()

    def run(i: int) -> int:
        if os.getpid() != me:  # the helper, in its first chunk
            out[i] = -1.0
            if fate == "dies":
                os._exit(7)
            time.sleep(3600.0)
        time.sleep(0.01)
        out[i] = i + 1.0
        return i

    t0 = time.monotonic()
    assert run_forked(run, n, _until(lambda: bool((out == -1.0).any()))) == list(range(n))
    assert np.array_equal(out, np.arange(1.0, n + 1.0))  # its chunk cast again here
    assert time.monotonic() - t0 < 20.0


def test_an_error_in_a_chunk_is_raised_here() -> None:
    def run(i: int) -> int:
        if i == 3:
            raise ValueError("chunk 3")
        time.sleep(0.002)
        return i

    with pytest.raises(ValueError, match="chunk 3"):
        run_forked(run, 8)


def test_no_helper_casts_here_after_meanwhile(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(forked, "can_fork", lambda n: False)
    order: list[str] = []
    assert run_forked(lambda i: order.append(f"chunk {i}") or i, 2, lambda: order.append("meanwhile")) == [0, 1]
    assert order == ["meanwhile", "chunk 0", "chunk 1"]


def test_servo_angles_in_blocks_are_the_same_numbers(monkeypatch: pytest.MonkeyPatch) -> None:
    sc = _fast_tunnel()
    traj = servo.servo_trajectory(sc.servo)
    t = np.linspace(-0.5, traj.end_s + 0.5, 3 * servo.ANGLE_BLOCK + 17).reshape(-1, 1)
    blocked = traj.angle(t)
    monkeypatch.setattr(servo, "ANGLE_BLOCK", t.size)
    whole = traj.angle(t)
    assert blocked.shape == t.shape and blocked.tobytes() == whole.tobytes()
    assert np.ptp(whole) > 0.5  # the sweep moves


def test_what_runs_before_the_cast_imports_no_scipy() -> None:
    """`lrfsim plan`'s helper is forked once the scene is built: scipy (for the prediction) is imported after, while
    the helper casts."""
    code = ("import sys, lrfsim.plan.sparse_cast, lrfsim.simulation.simulate, lrfsim.world.scene, "
            "lrfsim.simulation.faults; "
            "print(','.join(m for m in ('scipy.special', 'scipy.spatial', 'scipy.ndimage') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == ""


@pytest.mark.parametrize(("env_value", "expected"), [(None, "disable"), ("glfw", "glfw")])
def test_the_program_loads_no_opengl_context(env_value: str | None, expected: str) -> None:
    """The console script sets MUJOCO_GL=disable (it renders nothing) unless the environment sets it."""
    code = ("import atexit, os, sys\n"
            "def report():\n"
            "    import mujoco\n"
            "    print(os.environ.get('MUJOCO_GL'), 'mujoco.glfw' in sys.modules)\n"
            "atexit.register(report)\n"
            "sys.argv = ['lrfsim', 'schema']\n"
            "from lrfsim.cli import main\n"
            "main()\n")
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}
    if env_value is not None:
        env["MUJOCO_GL"] = env_value
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.split()[-2:] == [expected, str(expected != "disable")]


def test_plan_limits_the_blas_scipy_loads_while_it_casts(tmp_path: Path) -> None:
    """`lrfsim plan` imports scipy while its helper casts, and scipy's BLAS is limited as it loads (the thread policy,
    applied before the command starts, set the variables the BLAS libraries read as they load)."""
    path = tmp_path / "fast.yaml"
    path.write_text(yaml.safe_dump(with_changes(yaml.safe_load((ROOT / "scenarios" / "tunnel_v.yaml").read_text()),
                                                {"servo.speed_rad_s": math.radians(30.0), "servo.passes": 2})))
    code = ("import atexit, json, sys, threadpoolctl\n"
            "atexit.register(lambda: print(json.dumps([i['num_threads'] for i in threadpoolctl.threadpool_info() "
            "if i['user_api'] == 'blas'])))\n"
            f"from lrfsim.cli import main\nmain(['plan', {str(path)!r}, '--json'])\n")
    env = {k: v for k, v in os.environ.items() if k != "LRF_CALIB_BLAS_THREADS" and k not in LIBRARY_ENV}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr
    threads = json.loads(out.stdout.strip().splitlines()[-1])
    assert len(threads) >= 2 and threads == [1] * len(threads), threads  # numpy's and scipy's OpenBLAS
