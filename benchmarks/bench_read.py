"""Reading and writing a recording's bag: the bulk paths against rosbags' generic ones, A/B in one run (issue 47).

    python benchmarks/bench_read.py [BAG] [--repeat R] [--old-src SRC]

BAG: a bag (default: tunnel_v simulated into a temporary folder, ``lrfsim simulate scenarios/tunnel_v.yaml``).
Timed in this process, interleaved R times (default 7), the median of each counting, so that a busy machine slows
both alike:

* ``generic``: lrfcal.io.bag.read_bag with ``bulk=False``: rosbags reads and decodes every message;
* ``bulk``: read_bag as it runs (LaserScan and JointState read in bulk, lrfcal.io.bag_arrays; an indexed MCAP file's
  messages found from its index, lrfcal.io.bag_raw);

and with ``--old-src SRC`` (a source tree of the project from before, e.g. the main branch's ``src``) also
``old``: read_bag of that tree, timed in a subprocess of its own interleaved with one of this tree (both after one
warm-up read, imports not counted). Prints each median wall and CPU time (user + system of the process: less
sensitive to other work on a shared machine) and the ratios to ``generic`` / ``old``. Target: reading
tunnel_v's recording <= 0.1 s where it took ~0.5 s (a ratio <= 0.2).

Without BAG also the writing of tunnel_v's bag, interleaved the same way: ``write generic``
(lrfsim.simulation.recording.write_bag with ``bulk=False``: one rosbags serialiser call per message) and ``write bulk``
(write_bag as it runs: the messages serialised as arrays, lrfcal.io.wire, the file assembled from them,
lrfcal.io.mcap_write), the same file byte for byte (benchmarks/bench_write.py: against rosbags' Writer alone).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
TARGET_RATIO = 0.2

_CHILD = """
import sys, time
from lrfcal.io.bag import read_bag
from lrfcal.io.recording import read_nominal
from lrfcal.runtime.memory import apply_memory_policy
apply_memory_policy()
nom = read_nominal(sys.argv[2])
read_bag(sys.argv[1], nom.scan, nom.servo, warn=lambda text: None)
t0, c0 = time.perf_counter(), time.process_time()
read_bag(sys.argv[1], nom.scan, nom.servo, warn=lambda text: None)
print(time.perf_counter() - t0, time.process_time() - c0)
"""


def _simulated(tmp: Path, repeat: int, times: dict[str, list[float]], cpus: dict[str, list[float]]) -> Path:
    """tunnel_v simulated and written into ``tmp``; its bag's writing timed both ways (module docstring)."""
    from lrfsim.scenario.file import load_scenario
    from lrfsim.simulation.recording import write_bag, write_recording
    from lrfsim.simulation.simulate import simulate

    scenario = load_scenario(ROOT / "scenarios" / "tunnel_v.yaml")
    result = simulate(scenario)
    for k in range(repeat + 1):  # the first round warms up
        for name, bulk in (("write generic", False), ("write bulk", True)):
            t0, c0 = time.perf_counter(), time.process_time()
            write_bag(result, scenario, tmp / f"{name.split()[1]}{k}" / "bag", bulk=bulk)
            if k:
                times.setdefault(name, []).append(time.perf_counter() - t0)
                cpus.setdefault(name, []).append(time.process_time() - c0)
    return write_recording(result, scenario, tmp / "tunnel_v") / "bag"


def _child(src: Path, bag: Path, nominal: Path) -> tuple[float, float]:
    env = dict(os.environ, PYTHONPATH=str(src), OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", _CHILD, str(bag), str(nominal)], env=env, check=True,
                         capture_output=True, text=True)
    wall, cpu = out.stdout.split()[-2:]
    return float(wall), float(cpu)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("bag", nargs="?", type=Path, help="a bag (default: tunnel_v simulated)")
    ap.add_argument("--repeat", type=int, default=7, help="interleaved runs of each path (default 7)")
    ap.add_argument("--old-src", type=Path, help="a source tree of the project from before: time its read_bag too")
    args = ap.parse_args()

    from lrfcal.io.bag import read_bag
    from lrfcal.io.recording import read_nominal
    from lrfcal.io.rig import ScanSource, ServoSource
    from lrfcal.runtime.memory import apply_memory_policy

    apply_memory_policy()  # as the programs run (lrfcal.runtime.memory)

    times: dict[str, list[float]] = {}
    cpus: dict[str, list[float]] = {}
    with tempfile.TemporaryDirectory(prefix="bench-read-") as tmp:
        bag = args.bag or _simulated(Path(tmp), args.repeat, times, cpus)
        nominal = bag.parent / "nominal.yaml"
        if nominal.is_file():
            nom = read_nominal(nominal)
            scan, servo = nom.scan, nom.servo
        else:
            scan, servo = ScanSource(), ServoSource(topic="/joint_states", joint="servo")
        for name in ("generic", "bulk"):
            times[name], cpus[name] = [], []
        for bulk in (False, True):  # warm-up: imports, the page cache
            read_bag(bag, scan, servo, bulk=bulk, warn=lambda text: None)
        for _ in range(args.repeat):
            for name, bulk in (("generic", False), ("bulk", True)):
                t0, c0 = time.perf_counter(), time.process_time()
                read_bag(bag, scan, servo, bulk=bulk, warn=lambda text: None)
                times[name].append(time.perf_counter() - t0)
                cpus[name].append(time.process_time() - c0)
        if args.old_src is not None:
            if not nominal.is_file():
                raise SystemExit("--old-src needs a recording folder's bag (its nominal.yaml says where the data are)")
            for name in ("old", "new"):
                times[name], cpus[name] = [], []
            for _ in range(args.repeat):
                for name, src in (("old", args.old_src.resolve()), ("new", ROOT / "src")):
                    wall, cpu = _child(src, bag, nominal)
                    times[name].append(wall)
                    cpus[name].append(cpu)
    med = {k: float(np.median(v)) for k, v in times.items()}
    cpu = {k: float(np.median(v)) for k, v in cpus.items()}
    print(f"bag: {bag if args.bag else 'tunnel_v simulated'}; {args.repeat} interleaved runs, medians; "
          f"load average {os.getloadavg()[0]:.2f}")
    for name, value in med.items():
        print(f"  {name:13s} wall {value * 1000:8.1f} ms (min {min(times[name]) * 1000:.1f})   "
              f"CPU {cpu[name] * 1000:8.1f} ms (min {min(cpus[name]) * 1000:.1f})")
    for a, b, what in (("write bulk", "write generic", "in this process"), ("bulk", "generic", "in this process"),
                       ("new", "old", "subprocesses")):
        if a in med:
            ratio, cratio = med[a] / med[b], cpu[a] / cpu[b]
            verdict = "" if a.startswith("write") else \
                f"  ({'PASS' if ratio <= TARGET_RATIO else 'MISS'} <= {TARGET_RATIO}, wall)"
            print(f"{a} / {b} ({what}): wall {ratio:.3f}, CPU {cratio:.3f}{verdict}")


if __name__ == "__main__":
    main()
