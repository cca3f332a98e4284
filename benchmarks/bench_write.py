"""Writing the simulator's bag: rosbags' Writer against the bulk MCAP writer, A/B in one process (issue 47).

    python benchmarks/bench_write.py [--trials T] [--repeat R] [--old-src SRC]

A study trial of tunnel_v as ``lrfsim study`` runs it (lrfsim.trials.study.run_batch: the cast once, then per trial its
noise drawn on that cast, the recording written, read back and calibrated), in this process, the worker's memory
and thread policies applied; for each of T trials (default 4) the CPU time (time.process_time: user + system of
the process, less sensitive to other work on a shared machine than the wall time) of the trial's parts, and the
bag of that trial written R times (default 3) each way, interleaved, so that a busy machine slows both alike:

* ``rosbags``: lrfsim.simulation.recording.write_bag of the source tree SRC (``--old-src``, e.g. the main branch's
  ``src``; without it, skipped): the messages serialised in bulk, the file written by rosbags' Writer,
  one call per message (the version before lrfcal.io.mcap_write);
* ``bulk``: write_bag as it runs (lrfcal.io.mcap_write), whose file must be the same, byte for byte (checked);
* ``generic``: write_bag(bulk=False): rosbags' serialiser and Writer, one call each per message (the reference);

and the recording's declared range noise (nominal.yaml ``range_sigma_m``) both ways, interleaved the same way:
``np.median`` of every finite range's sigma (before) and lrfsim.sensors.lidar.typical_range_sigma (counted by band), the
same float (checked). Prints the median CPU of each, the ratios, and the write's share of a whole trial's CPU.
"""

from __future__ import annotations

import argparse
import importlib.util
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _old_write_bag(src: Path):  # noqa: ANN202 - the old tree's write_bag, imported beside this tree's package
    # its relative imports resolve in this tree's package: a tree of the same layout (lrfsim's rooms), not one from
    # before them (src/lrfsim/recording.py)
    spec = importlib.util.spec_from_file_location("lrfsim.simulation._old_recording",
                                                  src / "lrfsim" / "simulation" / "recording.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.write_bag


def _median_sigma(ranges_m, sensor) -> float:  # noqa: ANN001 - typical_range_sigma as it was
    import numpy as np

    from lrfsim.sensors.lidar import range_sigma

    return float(np.median(range_sigma(ranges_m[np.isfinite(ranges_m)], sensor)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--old-src", type=Path, default=None)
    args = ap.parse_args()

    import numpy as np

    from lrfcal.runtime.memory import apply_memory_policy
    from lrfcal.runtime.threads import apply_thread_policy
    from lrfsim.scenario.file import load_scenario
    from lrfsim.sensors.lidar import typical_range_sigma
    from lrfsim.simulation.recording import write_bag, write_recording
    from lrfsim.simulation.simulate import cast_geometry, simulate_from_geometry
    from lrfsim.trials.trial import calibrate_recording

    apply_memory_policy()
    apply_thread_policy()
    ways = {"generic": lambda r, s, p: write_bag(r, s, p, bulk=False), "bulk": write_bag}
    if args.old_src is not None:
        ways = {"rosbags": _old_write_bag(args.old_src), **ways}
    else:
        print("without --old-src: rosbags' Writer after bulk serialisation not timed")
    scenario = load_scenario(ROOT / "scenarios" / "tunnel_v.yaml")
    geometry = cast_geometry(scenario)
    cpu: dict[str, list[float]] = {}

    def timed(name: str, fn, *a) -> object:  # noqa: ANN001
        c0 = time.process_time()
        out = fn(*a)
        cpu.setdefault(name, []).append(time.process_time() - c0)
        return out

    with tempfile.TemporaryDirectory() as tmp:
        for trial in range(args.trials):
            sc = scenario.model_copy(update={"seed": 100 + trial})
            folder = Path(tmp) / f"trial_{trial}"
            sim = timed("trial: simulate on the cast", simulate_from_geometry, sc, geometry)
            timed("trial: write the recording", write_recording, sim, sc, folder)
            timed("trial: read and calibrate", calibrate_recording, folder)
            reference = (folder / "bag" / "bag.mcap").read_bytes()
            finite = sim.ranges_m[np.isfinite(sim.ranges_m)]
            for _ in range(args.repeat):
                median = timed("range sigma np.median", _median_sigma, sim.ranges_m, sc.sensor)
                counted = timed("range sigma counted", typical_range_sigma, sim.ranges_m, sc.sensor)
                assert median == counted and finite.size, "another range sigma"
            for k in range(args.repeat):
                for name, fn in ways.items():
                    bag = Path(tmp) / f"{name}{k}" / "bag"
                    timed(f"write_bag {name}", fn, sim, sc, bag)
                    assert (bag / "bag.mcap").read_bytes() == reference, f"{name}: another file"
                    shutil.rmtree(bag.parent)
            shutil.rmtree(folder)
    med = {name: statistics.median(v) for name, v in cpu.items()}
    for name, v in med.items():
        print(f"{name:30s} median CPU {v * 1e3:7.1f} ms  ({len(cpu[name])} runs)")
    trial = sum(v for k, v in med.items() if k.startswith("trial:"))
    print(f"{'a whole trial':30s} median CPU {trial * 1e3:7.1f} ms (the sum of its parts' medians)")
    print(f"bag.mcap {len(reference) / 1e6:.1f} MB, the same bytes every way")
    print(f"range sigma counted / np.median: {med['range sigma counted'] / med['range sigma np.median']:.2f}")
    if "write_bag rosbags" in med:
        print(f"bulk / rosbags: {med['write_bag bulk'] / med['write_bag rosbags']:.2f}; the write's share of a "
              f"trial: {med['write_bag rosbags'] / trial:.1%} -> {med['write_bag bulk'] / trial:.1%}")
    print(f"bulk / generic: {med['write_bag bulk'] / med['write_bag generic']:.2f}")


if __name__ == "__main__":
    sys.exit(main())
