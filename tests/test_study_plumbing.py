"""The plumbing of a study's trials made faster without changing a bit (issue 47, item 3): the range noise bands by
comparisons and counts, the unit check's median only when it matters, and the local pool (the shared cast handed
to each worker once, one trial per task, the plan's prediction made while the workers run)."""

from __future__ import annotations

import pickle
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from lrfcal.io.recording import _median_beyond
from lrfsim.scenario.file import load_scenario
from lrfsim.scenario.sections import NoiseBand
from lrfsim.sensors import lidar
from lrfsim.trials import pool

ROOT = Path(__file__).resolve().parents[1]


def _reference_sigma(r: np.ndarray, bands: tuple[NoiseBand, ...]) -> np.ndarray:
    """range_sigma as it was written before: np.searchsorted over the sorted band limits, clipped to the last."""
    up = np.array([b.up_to_m for b in bands])
    sig = np.array([b.sigma_m for b in bands])
    order = np.argsort(up)
    return sig[order][np.minimum(np.searchsorted(up[order], r, side="left"), up.size - 1)]


@pytest.mark.parametrize("bands", [
    ((10.0, 0.01), (30.0, 0.03), (60.0, 0.05)),  # tunnel_v's
    ((30.0, 0.03), (10.0, 0.05), (60.0, 0.01)),  # unsorted limits, sigmas not rising with range
    ((5.0, 0.02),),
    ((5.0, 0.02), (5.0, 0.03), (9.0, 0.01)),  # a repeated limit
    tuple((float(u), float(s)) for u, s in zip(np.linspace(1, 40, 11), np.linspace(0.05, 0.01, 11), strict=True)),
])
def test_range_sigma_and_its_median_are_the_searchsorted_ones_bit_for_bit(bands) -> None:
    sensor = load_scenario(ROOT / "scenarios" / "tunnel_v.yaml").sensor.model_copy(
        update={"noise_bands": tuple(NoiseBand(up_to_m=u, sigma_m=s) for u, s in bands)})
    limits = [b.up_to_m for b in sensor.noise_bands]
    rng = np.random.default_rng(7)
    for n in (1, 2, 3, 10, 1000, 1001):
        for _ in range(10):
            r = rng.uniform(-1.0, 70.0, n)
            at = rng.random(n) < 0.2  # exactly on a band's limit
            r[at] = rng.choice(limits, int(at.sum()))
            r[rng.random(n) < 0.1] = np.nan
            r[rng.random(n) < 0.05] = np.inf
            assert np.array_equal(lidar.range_sigma(r, sensor), _reference_sigma(r, sensor.noise_bands))
            finite = r[np.isfinite(r)]
            expected = float(np.median(_reference_sigma(finite, sensor.noise_bands))) if finite.size else None
            assert lidar.typical_range_sigma(r, sensor) == expected
    assert lidar.typical_range_sigma(np.array([np.nan, np.inf]), sensor) is None


def test_unit_check_median_computed_when_it_can_be_beyond_the_limit() -> None:
    """0.0 (the median not computed) only where the median is within the limit; the exact median otherwise."""
    rng = np.random.default_rng(3)
    for n in (1, 2, 3, 4, 11, 12):
        for _ in range(200):
            r = rng.choice([-1.0, 0.0, 5.0, 9.0, 10.0, 11.0, 50.0, np.nan, np.inf], size=n)
            valid = r[np.isfinite(r) & (r > 0)]
            median = float(np.median(valid)) if valid.size else 0.0
            got = _median_beyond(r, 10.0)
            assert (got > 10.0) == (median > 10.0), r
            assert got == median or (got == 0.0 and median <= 10.0), r


def _held_task(batch: list[int], progress=None) -> list[int]:
    """A pool task: what the worker holds, for each item of the batch (and the calling process told it started)."""
    held = pool.worker_held()
    held["started"].set()
    out = []
    for k in batch:
        if "ran" in held:
            with held["ran"].get_lock():
                held["ran"].value += 1
            time.sleep(0.05)
        out.append(held["base"] + k)
        if progress is not None:
            progress(len(out))
    return out


def _no_policy() -> None:
    return None


def test_pool_hands_held_values_to_workers_and_runs_meanwhile_while_they_work() -> None:
    import multiprocessing

    started = multiprocessing.get_context().Event()
    seen = []

    def meanwhile() -> None:  # runs here once the workers have started: it sees a batch begin
        seen.append(started.wait(timeout=60))

    done = []
    out = pool.run_counted(_held_task, [[1, 2], [3], [4]], 2, _no_policy, done.append,
                              held={"base": 100, "started": started}, meanwhile=meanwhile)
    assert out == [[101, 102], [103], [104]] and seen == [True]
    assert done[-1] == 4 and done == sorted(done)


def test_pool_meanwhile_failure_is_raised_and_stops_the_batches() -> None:
    import multiprocessing

    ctx = multiprocessing.get_context()
    ran = ctx.Value("i", 0)

    def fails() -> None:
        raise RuntimeError("meanwhile failed")

    with pytest.raises(RuntimeError, match="meanwhile failed"):  # 50 batches of 50 ms: 1.25 s on 2 workers
        pool.run_counted(_held_task, [[k] for k in range(50)], 2, _no_policy, None,
                            held={"base": 0, "started": ctx.Event(), "ran": ran}, meanwhile=fails)
    assert ran.value < 10  # the batches already handed out ran, the others were cancelled
    assert pool.worker_held() == {}  # the calling process holds nothing


def test_study_pool_sends_one_small_task_per_trial_and_the_cast_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """A local pool gets one trial per batch (handed out as workers free up); the tasks carry the scenario, not the
    shared cast (51 MB for tunnel_v), which every worker holds from its start; the plan runs meanwhile, on the
    same cast."""
    import lrfsim.trials.study as study_module
    from lrfsim.trials.study import run_trials

    sc = load_scenario(ROOT / "scenarios" / "tunnel_v.yaml")
    sent = {}

    def spy(task, batches, workers, initializer, progress, *, held=None, meanwhile=None):
        sent.update(task=task, batches=batches, held=held)
        if meanwhile is not None:
            meanwhile()
        return [[] for _ in batches]

    from dataclasses import fields

    from lrfsim.simulation.simulate import Geometry

    cast = np.zeros((1470, 1081))  # stands in for the cast: run_trials hands the fields but the scene to the workers
    geometry = Geometry(**{f.name: None for f in fields(Geometry)} | {"cast": cast})
    monkeypatch.setattr(study_module, "run_counted", spy)
    ran = threading.Event()
    run_trials(sc, 5, seed0=3, workers=2, geometry=geometry, meanwhile=ran.set)
    assert [list(b) for b in sent["batches"]] == [[(k, 3 + k)] for k in range(5)]
    assert sent["held"]["cast"]["cast"] is cast and "scene" not in sent["held"]["cast"]
    assert len(pickle.dumps(sent["task"])) < 100_000 < cast.nbytes
    assert ran.is_set()
