"""Monte-Carlo studies: many trials of one scenario, each with new noise, on one core, a process pool or a cluster.

Trial k of a study uses the scenario with ``seed = seed0 + k``: new laser phase, range and intensity noise, tape
noise and fault draws (lrfsim.simulation.simulate's and lrfsim.simulation.faults' seeded streams). The scene, and with
it the marker layout (a jittered board grid or V is seeded by the scenario's seed too), is built once from the scenario
as given, so every trial sees the same markers and only the noise changes. No wasted casting: the rays are cast once per
batch (lrfsim.simulation.simulate.cast_geometry, with the laser phase of the scenario's own seed) and each trial only
draws its noise on that cast (simulate_from_geometry); ``recast=True`` casts every trial anew instead, its laser phase
drawn from the trial's seed as well. Each trial then runs the whole path of a real
recording: simulate, write the recording folder, read it back, calibrate (lrfsim.trials.trial.calibrate_recording), and
is recorded as calibrated (errors against the truth, reported sigma) or refused (the reason).

Marker-less scenarios: each trial is calibrated targetless exactly as ``lrfcal calibrate REC --targetless
--no-figures`` does (lrfsim.trials.trial.calibrate_as_user: lrfcal.workflow.calibrate_folder with the command's
configuration); a DH parameter the calibration held (the scene does not determine it) has an empty sigma in
trials.csv and counts in no RMS of error / sigma; no plan's prediction is made (it needs markers).

Drawn truth (``truth_spread = s > 0``, ``--truth-spread S``): each trial's true DH (``rig.dh``) is drawn around the
nominal DH, uniform in +-s times :data:`TRUTH_HALF_WIDTH` (s = 1: a, b +-5 mm, alpha, beta +-1.5 deg), from the trial's
seed alone (lrfsim.trials.variants.drawn_truth), and the trial's nominal.yaml declares that spread as the nominal's
1-sigma (``dh_tolerance``: the half width / sqrt 3); every trial then builds its scene and casts its rays (the true DH
is in the scene's model).

Perturbed start (``perturb_start = s > 0``, ``--perturb-start S``): each trial's nominal values (the scenario's
``rig.nominal_dh`` and ``rig.nominal_mount``, written to the trial's nominal.yaml, where the calibration starts)
are moved by independent draws, uniform in +-s times :data:`PERTURB_HALF_WIDTH` (s = 1: a, b +-5 mm, alpha, beta
+-1 deg; mount x, y, z +-2 cm, roll, pitch, yaw +-1 deg), from the trial's seed alone
(``default_rng([seed, 0x73746172])``, a stream of its own): the same seeds give the same starts however the
study runs. Without it every trial starts from the scenario's nominal values.

Execution: trials are cut into batches (one batch = one task: the scene is built once per batch); batches run
in-process (``workers=1``), in a ``concurrent.futures.ProcessPoolExecutor`` (``workers=K``: one trial per batch,
handed out as workers free up, each worker holding the shared cast and its scene from its start,
lrfsim.trials.pool) or on a dask.distributed cluster (``dask_address`` or a ``distributed.Client``). A trial's outcome
depends only on its seed, and the table is sorted by trial, so every way of running gives the same table. While
the workers run, this process makes the plan's prediction (and whatever the caller asks, ``meanwhile``).

Outputs (:func:`write_study`, atomic): ``trials.csv`` (one row per trial and varied value), ``summary.md`` (per DH
parameter: bias, std, RMSE, predicted sigma from lrfsim.plan.prediction, RMSE / predicted sigma, RMS of error / reported
sigma, refusal rate), ``hist_<P>.png`` (error histograms with the predicted sigma drawn) and, with a varied
field, ``vary_sigma.png`` (predicted and measured sigma against the value).
"""

from __future__ import annotations

import math
import shutil
import tempfile
import time
from collections.abc import Callable, Iterable, Sequence
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from lrfcal import apply_memory_policy, apply_thread_policy, call_with_thread_policy, keep_freed_memory
from lrfcal.errors import CalibrationError, InputError
from lrfsim.plan.prediction import plan
from lrfsim.plan.result import Plan
from lrfsim.scenario.file import Scenario

from .pool import run_counted, worker_held
from .study_result import Study, StudyPart, TrialRow
from .variants import (
    TrialDesign,
    drawn_truth,
    perturbed_start,
    with_field,
)

if TYPE_CHECKING:
    from lrfsim.simulation.simulate import Geometry
    from lrfsim.world.scene import Scene

FloatArray = NDArray[np.float64]

# --- running trials -------------------------------------------------------------------------------------------

def run_batch(scenario: Scenario, value: str, trials: Sequence[tuple[int, int]], design: TrialDesign | None = None,
              threads: int | None = None, shared_cast: dict[str, Any] | None = None,
              progress: Callable[[int], None] | None = None, scene: Scene | None = None) -> list[TrialRow]:
    """Run trials ``[(trial, seed), ...]`` of ``scenario`` (one task of a study). The scene (marker layout) is
    built once from ``scenario``, and so is the ray cast (lrfsim.simulation.simulate.cast_geometry: the laser phase of
    the scenario's own seed); each trial draws only its noise from its own seed (module docstring), and differs as
    ``design`` says (:class:`TrialDesign`; None: in its noise only). ``threads``: the cast's
    threads (default: the cores available; 1 when batches run in parallel processes). ``shared_cast``: the fields
    of a lrfsim.simulation.simulate.Geometry of ``scenario`` but its scene, cast once by the caller for every batch (the
    scene is rebuilt here, or ``scene``, built before from ``scenario``: MjSpec does not pickle); None: cast here.
    ``progress(k)`` is called after the k-th trial of the batch."""
    from lrfsim.simulation.recording import write_recording
    from lrfsim.simulation.simulate import Geometry, cast_geometry, simulate, simulate_from_geometry
    from lrfsim.world.scene import build_scene

    from .trial import calibrate_as_user, calibrate_recording

    design = design or TrialDesign()
    if design.own_scene:
        scene = None
    elif scene is None:
        scene = build_scene(scenario)
    geometry = None
    if shared_cast is not None and scene is not None:
        geometry = Geometry(scene=scene, **shared_cast)
    elif not design.own_cast:
        geometry = cast_geometry(scenario, scene=scene, threads=threads)
    rows = []
    with tempfile.TemporaryDirectory(prefix="lrfsim-study-") as tmp:
        for trial, seed in trials:
            sc = perturbed_start(scenario.model_copy(update={"seed": int(seed)}), seed, design.perturb_start)
            sc = drawn_truth(sc, seed, design.truth_spread)
            folder = Path(tmp) / f"trial_{trial}"
            sim = (simulate(sc, scene=scene, threads=threads) if geometry is None
                   else simulate_from_geometry(sc, geometry))
            write_recording(sim, sc, folder)  # the bag written and read as a real recording's (in bulk: lrfcal.io.wire)
            label = f"{scenario.name}#{trial}"
            # a marker-less recording: calibrated targetless as `lrfcal calibrate REC --targetless` does
            t = (calibrate_as_user(folder, name=label, force=design.force) if sc.markers is None
                 else calibrate_recording(folder, name=label, force=design.force))
            shutil.rmtree(folder, ignore_errors=True)
            rows.append(TrialRow(value=value, trial=int(trial), seed=int(seed), status=t.status,
                                 reason=" ".join(t.reason.split()), exit_code=int(t.exit_code),
                                 errors=tuple(float(v) for v in t.errors), sigma=tuple(float(v) for v in t.sigma),
                                 clock_offset_error_s=float(t.clock_offset_error_s), seconds=float(t.seconds)))
            if progress is not None:
                progress(len(rows))
    return rows


def _worker_policy() -> None:
    """A process-pool worker's policies: the programs' memory and thread policy (lrfcal.runtime.memory,
    lrfcal.runtime.threads), the large blocks its trials free kept for the next trial's (keep_freed_memory: 0.06-0.09
    s of page faults a trial of tunnel_v), and what it inherited from the study (modules, the shared cast) frozen out
    of the garbage collector, whose full passes walked it in every trial (13 ms a trial, 1.5 %)."""
    import gc

    apply_memory_policy()
    keep_freed_memory()
    apply_thread_policy()
    gc.freeze()


def _pool_batch(scenario: Scenario, value: str, design: TrialDesign, trials: Sequence[tuple[int, int]],
                progress: Callable[[int], None] | None = None) -> list[TrialRow]:
    """:func:`run_batch` on a local pool's worker: with the shared cast the worker holds (lrfsim.trials.pool), and the
    scene it builds at its first batch and keeps for the next (8 ms for tunnel_v, once per worker)."""
    held = worker_held()
    if held.get("scene") is None and not design.own_scene:
        from lrfsim.world.scene import build_scene

        held["scene"] = build_scene(scenario)
    return run_batch(scenario, value, trials, design, threads=1, shared_cast=held.get("cast"),
                     progress=progress, scene=held.get("scene"))


def _batches(items: list[tuple[int, int]], n_batches: int) -> list[list[tuple[int, int]]]:
    n_batches = max(1, min(n_batches, len(items)))
    return [b for b in (items[i::n_batches] for i in range(n_batches)) if b]


def run_trials(
    scenario: Scenario, trials: int, *, seed0: int | None = None, value: str = "", workers: int = 1,
    dask: Any = None, batch_size: int | None = None, progress: Callable[[int, int], None] | None = None,
    recast: bool = False, perturb_start: float = 0.0, new_layout: bool = False, geometry: Geometry | None = None,
    meanwhile: Callable[[], None] | None = None, truth_spread: float = 0.0, force: bool = False,
) -> list[TrialRow]:
    """Run ``trials`` trials (seeds seed0 .. seed0 + trials - 1; seed0 defaults to the scenario's seed), sorted by
    trial. ``workers`` > 1: a local process pool; ``dask``: a dask.distributed address (str) or Client, then
    ``workers`` only sets the number of batches. Batches hold ``batch_size`` trials (default: one trial each on a
    local pool, handed out as workers free up; about 2 batches per worker on dask; all in one in this process);
    the local workers share one cast (:func:`_shared_cast`: ``geometry`` when the caller has made it; not with
    ``recast``, ``new_layout`` or ``truth_spread``), handed to each once. ``recast``, ``perturb_start``,
    ``new_layout``, ``truth_spread``, ``force``: see :class:`TrialDesign`. ``progress(done, trials)`` after every
    trial in this process or on local workers (lrfsim.trials.pool), after every batch on dask. ``meanwhile()`` runs
    in this process while the workers (local or dask) run the trials, before them in this process. Worker processes
    (pool and dask) run BLAS with the programs' thread limit (lrfcal.runtime.threads); this process is left as the
    caller set it."""
    if trials < 1:
        raise InputError(f"study: --trials must be >= 1, got {trials}")
    perturbed_start(scenario, 0, perturb_start)  # a bad scale is refused before any trial runs
    drawn_truth(scenario, 0, truth_spread)
    design = TrialDesign(recast, perturb_start, new_layout, truth_spread, force)
    s0 = scenario.seed if seed0 is None else int(seed0)
    items = [(k, s0 + k) for k in range(trials)]
    batches = _batches(items, _n_batches(trials, workers, dask, batch_size))
    shared = None
    if design.own_cast:  # every trial casts its own
        geometry = None
    elif geometry is None:
        geometry = _shared_cast(scenario, trials, workers, dask, batch_size, design)
    if geometry is not None:  # one cast (on every core) for all the local workers, instead of one per worker
        from dataclasses import fields

        shared = {f.name: getattr(geometry, f.name) for f in fields(geometry) if f.name != "scene"}
    task = partial(run_batch, scenario, value, design=design, threads=1 if workers > 1 or dask is not None else None,
                   shared_cast=shared)
    rows: list[TrialRow] = []

    def collect(parts: Iterable[list[TrialRow]]) -> None:
        for part in parts:
            rows.extend(part)
            if progress:
                progress(len(rows), trials)

    if dask is not None:
        client, own = _dask_client(dask)
        try:  # a dask worker is not ours to change for good: the limit is restored after each batch
            futures = client.map(partial(call_with_thread_policy, task), batches, pure=False)
            if meanwhile is not None:
                meanwhile()
            collect(fut.result() for fut in futures)
        finally:
            if own:
                client.close()
    elif workers > 1:  # counted as each trial finishes in any worker (lrfsim.trials.pool)
        for part in run_counted(partial(_pool_batch, scenario, value, design), batches, workers, _worker_policy,
                                None if progress is None else (lambda k: progress(k, trials)),
                                held={"cast": shared}, meanwhile=meanwhile):
            rows.extend(part)
        if progress:
            progress(len(rows), trials)
    else:
        if meanwhile is not None:
            meanwhile()
        hook = None if progress is None else (lambda k: progress(len(rows) + k, trials))
        collect(task(b, progress=hook) for b in batches)
    return sorted(rows, key=lambda r: r.trial)


def _n_batches(trials: int, workers: int, dask: Any, batch_size: int | None) -> int:
    return (math.ceil(trials / batch_size) if batch_size else 2 * max(workers, 1) if dask is not None
            else trials if workers > 1 else 1)


def _shared_cast(scenario: Scenario, trials: int, workers: int, dask: Any, batch_size: int | None,
                 design: TrialDesign) -> Geometry | None:
    """The cast :func:`run_trials` makes once for all its batches (lrfsim.simulation.simulate.cast_geometry), when it
    makes one: local workers (no dask), one layout, one truth and one laser phase (not ``design.own_cast``), more
    than one batch; else None (each batch casts its own). Cast beside a forked helper process (lrfsim.cast.forked):
    the cast's many short calls hold the GIL, so two processes cast it faster than two threads (tunnel_v: 0.85 s
    against 1.2 s, the same arrays)."""
    if not (workers > 1 and dask is None and not design.own_cast
            and min(trials, _n_batches(trials, workers, dask, batch_size)) > 1):
        return None
    from lrfsim.cast.forked import Forked
    from lrfsim.simulation.simulate import cast_geometry

    return cast_geometry(scenario, threads=Forked())


def _dask_client(dask: Any) -> tuple[Any, bool]:
    """(client, whether we own it): a Client passed in is used as is; an address is connected to."""
    if not isinstance(dask, str):
        return dask, False
    try:
        from distributed import Client
    except ImportError:  # pragma: no cover - a dependency of the project
        raise InputError("--dask: dask.distributed is not installed (pip install 'dask[distributed]')") from None
    try:
        return Client(dask, timeout="10s"), True
    except (OSError, TimeoutError) as e:
        raise InputError(f"--dask: cannot connect to the scheduler at {dask} ({e})") from None


def study(
    scenario: Scenario, trials: int, *, seed0: int | None = None, workers: int = 1, dask: Any = None,
    vary: tuple[str, list[Any]] | None = None, batch_size: int | None = None,
    progress: Callable[[str, int, int], None] | None = None, recast: bool = False, perturb_start: float = 0.0,
    new_layout: bool = False, meanwhile: Callable[[], None] | None = None, truth_spread: float = 0.0,
    force: bool = False,
) -> Study:
    """A Monte-Carlo study of ``scenario`` (module docstring); ``vary = (dotted key, values)`` repeats it for each
    value of one field (the same seeds for every value); ``perturb_start``: the scale of each trial's perturbed
    start (:func:`perturbed_start`); ``truth_spread``: the scale of each trial's drawn truth (:func:`drawn_truth`);
    ``force``: every trial calibrates as with ``lrfcal calibrate --force`` (:class:`TrialDesign`);
    ``recast``, ``new_layout``: see :class:`TrialDesign` (the predicted sigma is then the scenario's own layout's and
    truth's). The plan's prediction (none for a marker-less scenario) is made while the workers run the trials, and
    so is ``meanwhile()`` (once, during the first part's trials; e.g. the figures' imports)."""
    t0 = time.perf_counter()
    variants: list[tuple[str, Scenario]] = [("", scenario)]
    if vary is not None:
        key, values = vary
        variants = [(str(v), with_field(scenario, key, v)) for v in values]
    parts = []
    for k, (value, sc) in enumerate(variants):
        design = TrialDesign(recast, perturb_start, new_layout, truth_spread, force)
        geometry = _shared_cast(sc, trials, workers, dask, batch_size, design)  # plan's cast too
        predicted: list[Plan | None] = []
        predict = partial(_predict, sc, geometry, predicted, meanwhile if k == 0 else None)
        hook = None if progress is None else (lambda d, n, v=value: progress(v, d, n))
        rows = run_trials(sc, trials, seed0=seed0, value=value, workers=workers, dask=dask, batch_size=batch_size,
                          progress=hook, recast=recast, perturb_start=perturb_start, new_layout=new_layout,
                          geometry=geometry, meanwhile=predict, truth_spread=truth_spread, force=force)
        parts.append(StudyPart(value=value, scenario=sc, plan=predicted[0], rows=tuple(rows)))
    where = ("dask" if dask is not None else f"{workers} worker{'s' if workers > 1 else ''}")
    return Study(name=scenario.name, key=None if vary is None else vary[0], parts=tuple(parts),
                 seconds=time.perf_counter() - t0, workers=where, perturb_start=perturb_start,
                 draws="layout" if new_layout else "truth" if truth_spread > 0 else "cast" if recast else "noise",
                 truth_spread=truth_spread, forced=force)


def _predict(scenario: Scenario, geometry: Geometry | None, into: list[Plan | None],
             then: Callable[[], None] | None) -> None:
    """The plan's prediction for ``scenario`` (on ``geometry``, the trials' shared cast, when there is one) appended
    to ``into``, None when the plan is refused (too few markers seen: the trials will say how the calibration
    fares; a marker-less scenario, whose calibration is targetless); then ``then()``."""
    try:
        into.append(None if scenario.markers is None else plan(scenario, geometry=geometry))
    except CalibrationError:
        into.append(None)
    if then is not None:
        then()


__all__ = ["run_batch", "run_trials", "study"]
