"""Speed of every command against the simulation, measured in one run (issues 19 and 47).

    python benchmarks/bench_speed.py [SCENARIO] [--trials N] [--repeat R] [--no-study] [--no-run]
    python benchmarks/bench_speed.py [SCENARIO] --only help,read [--recording REC]

The console scripts are timed as a user runs them (a subprocess of the installed ``lrfsim`` / ``lrfcal``, so the
imports count), all in this one run, so that a busy machine slows numerator and denominator alike:

1. ``lrfsim simulate`` of SCENARIO with every footprint sub-ray cast (``sensor.footprint_cast: full``, a copy of
   the scenario): the simulation issue 19 measured against (its cast within 1.3x of bare ``mj_multiRay``), the
   reference of every ratio; and ``lrfsim simulate SCENARIO`` as it runs by default (``footprint_cast: edges``,
   the ring cast only where it can change a beam);
2. ``lrfcal calibrate REC`` (and ``--no-figures`` when the CLI has it), ``lrfcal calibrate REC --targetless``,
   ``lrfsim plan SCENARIO``, ``lrfsim run SCENARIO``: walls and ratios to the simulation;
3. the calibration in-process (``lrfcal.pipeline.calibrate``, no CLI, no figures) with its stage times, under the
   programs' memory and thread policies (lrfcal.runtime.memory, lrfcal.runtime.threads);
4. ``lrfcal calibrate REC`` again with 4 busy processes beside it (started here, always killed in a finally);
5. the simulator's cast (lrfsim.cast.scans.cast_scans) against bare single-thread ``mj_multiRay`` over the same calls;
6. ``lrfsim study SCENARIO -n N -j 2``: trials per minute (the study's wall, plan and figures included);
7. start-up: ``lrfcal --help`` and ``lrfsim --help`` as console scripts (beside ``python -c pass``, the
   interpreter's own start), R runs each and at least 5;
8. reading the recording: :func:`read_recording_s`, whatever reader ``lrfcal.io`` has (read once first, untimed,
   so that its imports count in 7. and not here), R runs and at least 3.

``--only help,read`` runs the rows 7. and 8. alone (8. reads ``--recording REC`` or a recording of SCENARIO it
simulates first), e.g. to check a change to start-up or reading without the whole benchmark.

Each command of 1., 2. and 4. runs R times (default 3) and its median wall counts (its CPU: that run's), so that
one run slowed by other work on a shared machine does not decide a ratio.

Targets (issue 47): calibrate <= 0.4x the simulation, targetless <= 0.6x, plan <= 0.4x, calibrate beside 4 busy
processes <= 3x the quiet one, cast <= 0.75x bare mj_multiRay (issue 19), study >= 200 trials/min, ``lrfcal --help``
<= 0.3 s, reading the recording <= 0.1 s (these two are walls, not ratios). Every figure carries the 1-minute
load average when it was taken (2 cores shared with other work: compare ratios, not walls). Prints PASS/MISS per
target and exits 0 either way (it reports; the tests assert). Beside each wall, the CPU seconds (user + system) of
the run and their ratio to the simulation's: less sensitive to other work on the machine than the walls.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
TARGETS = {"calibrate": 0.4, "targetless": 0.6, "plan": 0.4, "loaded": 3.0, "cast": 0.75, "study": 200.0,
           "help": 0.3, "read": 0.1}
#: the rows ``--only`` can run alone
ONLY = ("help", "read")


def _env() -> dict[str, str]:
    env = dict(os.environ)
    # an installed package runs from its cached bytecode; a machine that sets PYTHONDONTWRITEBYTECODE (some CI
    # images do) would have every run compile the project's modules again (about 0.15 s of CPU per command)
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    env.setdefault("OMP_NUM_THREADS", "1")
    return env


def _load() -> float:
    return os.getloadavg()[0]


def _tool(name: str) -> str:
    path = BIN / name
    return str(path) if path.exists() else name


#: CPU seconds (user + system) of the last console-script run (timed), for the rows' "cpu" figures
LAST_CPU = [0.0]


def _children_cpu() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


#: runs of each timed command (--repeat): the median wall counts
REPEAT = [3]


def timed(args: list[str], ok: tuple[int, ...] = (0,), repeat: int | None = None) -> tuple[float, float]:
    """(median wall seconds, load average before) of ``repeat`` (default REPEAT) runs of a console script, "{i}" in
    ``args`` replaced by the run's index (its own output folder); a failing run stops the benchmark. The CPU seconds
    (user + system, all its threads and processes) of the median run go to LAST_CPU: on a machine shared with other
    work they move less than the wall."""
    load = _load()
    runs = []
    for i in range(repeat or REPEAT[0]):
        argv = [a.replace("{i}", str(i)) for a in args]
        cpu0 = _children_cpu()
        t0 = time.perf_counter()
        p = subprocess.run(argv, env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        runs.append((time.perf_counter() - t0, _children_cpu() - cpu0))
        if p.returncode not in ok:
            sys.exit(f"bench_speed: {' '.join(argv)} exited {p.returncode}: {p.stderr.strip()[-400:]}")
    wall, LAST_CPU[0] = sorted(runs)[len(runs) // 2]
    return wall, load


def has_option(tool: str, command: str, option: str) -> bool:
    p = subprocess.run([_tool(tool), command, "--help"], env=_env(), capture_output=True, text=True)
    return option in p.stdout


def busy_processes(n: int) -> list[subprocess.Popen[bytes]]:
    code = "while True:\n    pass\n"
    return [subprocess.Popen([sys.executable, "-c", code]) for _ in range(n)]


def cast_vs_bare(scenario_path: Path) -> tuple[float, float, int, float]:
    """(cast seconds of lrfsim.cast.scans.cast_scans, bare single-thread mj_multiRay seconds over the same calls,
    rays, load) on the scenario's noise-free motor angles."""

    from lrfsim.cast import scans
    from lrfsim.scenario.file import load_scenario
    from lrfsim.sensors import lidar
    from lrfsim.sensors.servo import servo_trajectory
    from lrfsim.world.scene import build_scene

    sc = load_scenario(scenario_path)
    scene = build_scene(sc)
    sensor = sc.sensor
    traj = servo_trajectory(sc.servo)
    lam = traj.angle(lidar.beam_times(lidar.scan_start_times(traj.end_s, sensor, 0.0), sensor))
    N, F = sensor.n_beams, sensor.footprint_rays
    cutoff = scans.cast_cutoff_m(sensor)
    gg = np.ascontiguousarray(scene.lidar_geomgroup, dtype=np.uint8)
    m, d = scene.model, scene.data
    load = _load()
    M = 16 * N * F
    gid, dist, nrm = np.empty(M, np.int32), np.empty(M), np.empty((M, 3))
    bare_s, n_rays = 0.0, 0
    for ch in scans.iter_ray_chunks(scene, sensor, lam):
        t0 = time.perf_counter()
        scans.cast_chunk(m, d, gg, ch, cutoff, gid, dist, nrm)  # mj_multiRay over the chunk's calls, nothing else
        bare_s += time.perf_counter() - t0
        n_rays += ch.directions.shape[0]
    cast = scans.cast_scans(scene, sensor, lam, footprint="full")  # every sub-ray: the bare loop's rays
    return cast.total_time_s, bare_s, n_rays, load


def pipeline_inprocess(rec: Path) -> tuple[float, dict[str, float], float]:
    """(seconds, stage seconds, load) of lrfcal.pipeline.calibrate on the recording (no CLI, no figures, no
    output files; the CLI's configuration)."""
    from lrfcal.io.recording import read_recording
    from lrfcal.pipeline import CalibConfig, calibrate

    recording = read_recording(rec)
    load = _load()
    t0 = time.perf_counter()
    result = calibrate(recording, CalibConfig())
    return time.perf_counter() - t0, dict(result.timings_s), load


def read_recording_s(rec: Path, repeat: int) -> tuple[float, float, int]:
    """(median seconds, load, scans) of reading the recording folder ``rec`` in-process through lrfcal.io
    (lrfcal.io.recording.read_recording: bag, tape distances and rig file), ``repeat`` runs after an untimed one."""
    from lrfcal.io.recording import read_recording

    n_scans = read_recording(rec).scans.ranges_m.shape[0]  # imports and the file cache: not the reading's
    load = _load()
    runs = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        read_recording(rec)
        runs.append(time.perf_counter() - t0)
    return float(np.median(runs)), load, n_scans


Row = Callable[..., None]


def startup_rows(row: Row, judge: Callable[[bool], str]) -> None:
    """Rows 7. (module docstring): ``lrfcal --help`` and ``lrfsim --help`` beside ``python -c pass``."""
    repeat = max(5, REPEAT[0])
    bare, _ = timed([sys.executable, "-c", "pass"], repeat=repeat)
    for tool in ("lrfcal", "lrfsim"):
        wall, load = timed([_tool(tool), "--help"], repeat=repeat)
        target = f"; target <= {TARGETS['help']} s" if tool == "lrfcal" else ""
        row(f"{tool} --help", f"{wall:.3f} s (python -c pass {bare:.3f} s{target}; median of {repeat}; load "
            f"{load:.1f})", judge(wall <= TARGETS["help"]) if tool == "lrfcal" else "")


def read_row(row: Row, judge: Callable[[bool], str], rec: Path, name: str) -> None:
    """Row 8. (module docstring): reading the recording ``rec`` (of ``name``) through lrfcal.io."""
    repeat = max(3, REPEAT[0])
    rd, load, n_scans = read_recording_s(rec, repeat)
    row(f"reading {name}'s recording (lrfcal.io, in-process)", f"{rd:.3f} s for {n_scans} scans (target <= "
        f"{TARGETS['read']} s; median of {repeat}; load {load:.1f})", judge(rd <= TARGETS["read"]))


def only_rows(args: argparse.Namespace, row: Row, judge: Callable[[bool], str], tmp: Path) -> None:
    """``--only``: the rows named in ``args.only`` (:data:`ONLY`) alone."""
    names = [n.strip() for n in args.only.split(",") if n.strip()]
    bad = [n for n in names if n not in ONLY]
    if bad:
        sys.exit(f"bench_speed: --only takes {', '.join(ONLY)}, got {', '.join(bad)}")
    if "help" in names:
        startup_rows(row, judge)
    if "read" in names:
        rec = args.recording
        if rec is None:
            rec = tmp / "rec"
            timed([_tool("lrfsim"), "simulate", str(args.scenario), "-o", str(rec)], repeat=1)
        read_row(row, judge, rec, args.scenario.stem)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenario", nargs="?", type=Path, default=ROOT / "scenarios" / "tunnel_v.yaml")
    ap.add_argument("--trials", type=int, default=40, help="trials of the study (default 40)")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each timed command, the median counts (default 3)")
    ap.add_argument("--no-study", action="store_true")
    ap.add_argument("--no-run", action="store_true")
    ap.add_argument("--only", metavar="ROWS", help=f"run only these rows, comma-separated: {', '.join(ONLY)}")
    ap.add_argument("--recording", type=Path, metavar="REC", help="--only read: this recording folder (default: "
                    "a simulation of SCENARIO)")
    args = ap.parse_args()
    from lrfcal.runtime.memory import apply_memory_policy
    from lrfcal.runtime.threads import apply_thread_policy
    from lrfsim.scenario.file import dump_scenario, load_scenario
    from lrfsim.trials.variants import with_field

    apply_memory_policy()  # the in-process measurements (3., 5.) under the programs' policies, as the commands run
    apply_thread_policy()
    sc = str(args.scenario)
    REPEAT[0] = max(1, args.repeat)
    lrfsim, lrfcal = _tool("lrfsim"), _tool("lrfcal")
    rows: list[tuple[str, str, str]] = []

    def row(name: str, value: str, verdict: str = "") -> None:
        rows.append((name, value, verdict))
        print(f"  {name}: {value} {verdict}", file=sys.stderr, flush=True)

    def judge(ok: bool) -> str:
        return "PASS" if ok else "MISS"

    tmp = Path(tempfile.mkdtemp(prefix="bench-speed-"))
    try:
        if args.only:
            only_rows(args, row, judge, tmp)
            return print_table(args, rows)
        rec = tmp / "rec0"
        full_sc = tmp / "full_footprint.yaml"
        full_sc.write_text(dump_scenario(with_field(load_scenario(args.scenario), "sensor.footprint_cast", "full")))
        sim, load = timed([lrfsim, "simulate", str(full_sc), "-o", str(tmp / "rec_full{i}")])
        sim_cpu = LAST_CPU[0]
        row("lrfsim simulate, every sub-ray cast (reference)", f"{sim:.2f} s, cpu {sim_cpu:.2f} s (load {load:.1f})")
        dflt, load = timed([lrfsim, "simulate", sc, "-o", str(tmp / "rec{i}")])
        row("lrfsim simulate (default: footprint_cast edges)", f"{dflt:.2f} s = {dflt / sim:.2f}x reference (cpu "
            f"{LAST_CPU[0]:.2f} s; load {load:.1f})")
        startup_rows(row, judge)
        read_row(row, judge, rec, args.scenario.stem)

        cal, load = timed([lrfcal, "calibrate", str(rec), "-o", str(tmp / "cal{i}")])
        cal_cpu = LAST_CPU[0]
        row("lrfcal calibrate", f"{cal:.2f} s = {cal / sim:.2f}x reference (target <= {TARGETS['calibrate']}x; "
            f"cpu {LAST_CPU[0]:.2f} s = {LAST_CPU[0] / sim_cpu:.2f}x; load {load:.1f})",
            judge(cal / sim <= TARGETS["calibrate"]))
        if has_option("lrfcal", "calibrate", "--no-figures"):
            nf, load = timed([lrfcal, "calibrate", str(rec), "-o", str(tmp / "cal_nf{i}"), "--no-figures"])
            row("lrfcal calibrate --no-figures", f"{nf:.2f} s = {nf / sim:.2f}x reference (cpu "
                f"{LAST_CPU[0] / sim_cpu:.2f}x; load {load:.1f})")
        tl, load = timed([lrfcal, "calibrate", str(rec), "-o", str(tmp / "tl{i}"), "--targetless"])
        row("lrfcal calibrate --targetless", f"{tl:.2f} s = {tl / sim:.2f}x reference (target <= "
            f"{TARGETS['targetless']}x; cpu {LAST_CPU[0]:.2f} s = {LAST_CPU[0] / sim_cpu:.2f}x; load {load:.1f})",
            judge(tl / sim <= TARGETS["targetless"]))
        pl, load = timed([lrfsim, "plan", sc], ok=(0, 3))
        row("lrfsim plan", f"{pl:.2f} s = {pl / sim:.2f}x reference (target <= {TARGETS['plan']}x; cpu "
            f"{LAST_CPU[0]:.2f} s = {LAST_CPU[0] / sim_cpu:.2f}x; load {load:.1f})", judge(pl / sim <= TARGETS["plan"]))
        if not args.no_run:
            rn, load = timed([lrfsim, "run", sc, "-o", str(tmp / "run{i}")], ok=(0, 1))
            row("lrfsim run", f"{rn:.2f} s = {rn / sim:.2f}x reference (cpu {LAST_CPU[0]:.2f} s = "
                f"{LAST_CPU[0] / sim_cpu:.2f}x; load {load:.1f})")

        pipe, stages, load = pipeline_inprocess(rec)
        top = ", ".join(f"{k} {v:.2f}" for k, v in sorted(stages.items(), key=lambda kv: -kv[1])[:4])
        row("pipeline in-process (no CLI, no figures)", f"{pipe:.2f} s = {pipe / sim:.2f}x reference ({top}; "
            f"load {load:.1f})")

        busy = busy_processes(4)
        try:
            time.sleep(1.0)
            loaded, load = timed([lrfcal, "calibrate", str(rec), "-o", str(tmp / "cal_loaded{i}")])
        finally:
            for p in busy:
                p.kill()
            for p in busy:
                p.wait()
        row("lrfcal calibrate beside 4 busy processes", f"{loaded:.2f} s = {loaded / cal:.2f}x quiet (target <= "
            f"{TARGETS['loaded']}x; cpu {LAST_CPU[0]:.2f} s = {LAST_CPU[0] / cal_cpu:.2f}x quiet's; load {load:.1f})",
            judge(loaded / cal <= TARGETS["loaded"]))

        cast_s, bare_s, n_rays, load = cast_vs_bare(args.scenario)
        row("cast vs bare mj_multiRay (1 thread)", f"{cast_s:.2f} s vs {bare_s:.2f} s = {cast_s / bare_s:.2f}x "
            f"({n_rays / 1e6:.1f} M rays; target <= {TARGETS['cast']}x; load {load:.1f})",
            judge(cast_s / bare_s <= TARGETS["cast"]))

        if not args.no_study:
            st, load = timed([lrfsim, "study", sc, "-n", str(args.trials), "-j", "2", "-o", str(tmp / "study")],
                             repeat=1)
            rate = args.trials / st * 60.0
            row(f"lrfsim study -n {args.trials} -j 2", f"{st:.1f} s = {rate:.0f} trials/min (target >= "
                f"{TARGETS['study']:.0f}; cpu {LAST_CPU[0]:.1f} s = {LAST_CPU[0] / args.trials:.2f} s per trial; "
                f"load {load:.1f})", judge(rate >= TARGETS["study"]))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print_table(args, rows)


def print_table(args: argparse.Namespace, rows: list[tuple[str, str, str]]) -> None:
    """The rows as a markdown table on stdout."""
    print(f"bench_speed {args.scenario.stem} ({os.cpu_count()} cores; OPENBLAS_NUM_THREADS="
          f"{_env()['OPENBLAS_NUM_THREADS']}; load now {_load():.1f})")
    print("| measurement | value | target |")
    print("|---|---|---|")
    for name, value, verdict in rows:
        print(f"| {name} | {value} | {verdict} |")


if __name__ == "__main__":
    main()
