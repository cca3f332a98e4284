"""The BLAS thread policy (lrfcal.runtime.threads) measured: wall time of ``lrfcal calibrate`` and ``lrfcal calibrate
--targetless`` on one simulated tunnel_v recording, with the libraries' default threads and with the policy's
limit, on the machine as it is ("quiet") and with BUSY extra processes spinning on the cores ("loaded").

    python benchmarks/bench_threads.py [--busy 4] [--repeats 2] [--recording DIR]

The busy processes (``python -c "while True: pass"``) are started by this script and killed when it ends, also on
an error or Ctrl-C. The load average before each measurement is printed: the cores may be shared with others.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
#: (label, extra arguments of lrfcal calibrate)
COMMANDS = (("markers", []), ("targetless", ["--targetless"]))
#: (label, value of LRF_CALIB_BLAS_THREADS)
POLICIES = (("default threads", "default"), ("1 thread", "1"))


def _calibrate(recording: Path, out: Path, extra: list[str], threads: str, timeout_s: float) -> float:
    env = dict(os.environ, LRF_CALIB_BLAS_THREADS=threads)
    t0 = time.perf_counter()
    proc = subprocess.run([str(BIN / "lrfcal"), "calibrate", str(recording), "-o", str(out), "--overwrite", *extra],
                          env=env, capture_output=True, text=True, timeout=timeout_s)
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"lrfcal calibrate {' '.join(extra)} failed ({proc.returncode}): {proc.stderr.strip()}")
    return seconds


def _measure(recording: Path, tmp: Path, repeats: int, timeout_s: float) -> dict[tuple[str, str], float]:
    out: dict[tuple[str, str], float] = {}
    for cmd, extra in COMMANDS:
        for policy, value in POLICIES:
            load = os.getloadavg()[0]
            times = [_calibrate(recording, tmp / f"cal_{cmd}", extra, value, timeout_s) for _ in range(repeats)]
            out[(cmd, policy)] = statistics.median(times)
            print(f"  {cmd:10s} {policy:16s} {' '.join(f'{t:6.1f}' for t in times)} s (load before {load:.2f})",
                  flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--busy", type=int, default=4, help="busy processes for the loaded measurement")
    ap.add_argument("--repeats", type=int, default=2, help="runs per case (the median is shown)")
    ap.add_argument("--recording", type=Path, help="a recording folder (default: simulate tunnel_v)")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per run before giving up")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-threads-") as tmp_name:
        tmp = Path(tmp_name)
        recording = args.recording
        if recording is None:
            recording = tmp / "rec"
            subprocess.run([str(BIN / "lrfsim"), "simulate", str(ROOT / "scenarios" / "tunnel_v.yaml"), "-o",
                            str(recording)], check=True, capture_output=True)
        print(f"{os.cpu_count()} cores; quiet (nothing started by this script):", flush=True)
        quiet = _measure(recording, tmp, args.repeats, args.timeout)
        busy: list[subprocess.Popen[bytes]] = []
        try:
            busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.busy)]
            time.sleep(5.0)
            print(f"loaded ({args.busy} busy processes):", flush=True)
            loaded = _measure(recording, tmp, args.repeats, args.timeout)
        finally:
            for p in busy:
                p.kill()
            for p in busy:
                p.wait()
        shutil.rmtree(tmp / "rec", ignore_errors=True)
    print("\n| command | threads | quiet [s] | loaded [s] | loaded / quiet |\n|---|---|---|---|---|")
    for cmd, _ in COMMANDS:
        for policy, _ in POLICIES:
            q, ld = quiet[(cmd, policy)], loaded[(cmd, policy)]
            print(f"| {cmd} | {policy} | {q:.1f} | {ld:.1f} | {ld / q:.1f} |")


if __name__ == "__main__":
    main()
