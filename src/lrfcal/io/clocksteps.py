"""Clock steps: stamps of the scans or of the servo that step against the bag's receive times (an NTP correction on
the laser's or the servo's computer, a clock reset), found when the bag is read (docs/formats.md, "Clock steps").

The calibration estimates one laser-minus-servo clock offset for the whole recording. A clock that steps by X
halfway through makes the offset X different on the two sides of the step, and one offset for both is wrong for
both; worse, a servo clock that steps back makes its later stamps overlap its earlier ones, and the joint states
sorted by stamp interleave two motions. So a step is found before anything is sorted, and what does not share the
longest part's clocks is left out.

How it is found: per stream, in the bag's order (its receive times r, on the recorder's clock), d = r - stamp is
the stream's transport delay plus the offset between the recorder's clock and the stream's; it is steady but for
jitter. A clock step of that stream's clock moves d by the step and keeps it there. :func:`level_steps` compares
the median of d over a window of messages before each message with the median over a window after: a change larger
than :data:`MIN_STEP_S` and :data:`NOISE_FACTOR` times d's own jitter, that lasts at least half a window, is a step,
placed at the message that best separates the two levels. A step that both streams show alike, at about the same
receive time, is a step of the recorder's clock (or a stall of the recorder): the stamps, and their offset, are
unaffected, and it is only named. A step of one stream changes the laser-minus-servo offset: the bag is cut there
(both streams, at the receive time of the step), and the longest part with one offset is kept, with every other
part of the same offset whose stamps do not overlap it (:func:`clock_cut`). When the part kept holds fewer than
:data:`MIN_KEPT_SHARE` of the scans the recording is refused naming the steps (exit 3: the data, well-formed, do not
support one clock offset).

What it cannot see: a step of both the laser's and the servo's clock by the same amount at the same time looks like
a step of the recorder's clock (the offset is unchanged, but a step back makes each stream's stamps overlap
themselves: such stamps are named where the scans are read, not cut); a step smaller than the larger of
:data:`MIN_STEP_S` and the delays' jitter; a step within the first or last :data:`EDGE_SAMPLES` messages of a stream.
A stream whose stamps are its receive times (``stamp: receive``) or are the scans' own stamps cannot step against
them.

Array shapes: M messages of a stream.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import CalibrationError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: a change of a stream's receive-minus-stamp smaller than this is not a step [s]: a fifth of a 100 Hz servo's sample
#: period, above the jitter of a window's median of a bag's receive times on one computer and well below a clock step
#: (ntpd steps a clock only when it is off by more than 0.128 s, and slews it below)
MIN_STEP_S = 0.002
#: ... nor one smaller than this many times the robust standard deviation of its delays' jitter
NOISE_FACTOR = 8.0
#: the window of messages on each side of a step, at most (a twentieth of the stream, at least EDGE_SAMPLES)
MAX_WINDOW = 50
#: a stream's first and last this many messages are not tested for a step
EDGE_SAMPLES = 3
#: the part kept must hold at least this share of the scans, else the recording is refused
MIN_KEPT_SHARE = 0.25


@dataclass(frozen=True)
class LevelStep:
    """A step of one stream's receive-minus-stamp: at its message ``index`` (the first after the step, in the bag's
    order), received at ``recv_s`` [s], by ``size_s`` [s] (positive: the stamps step back against the receive
    times)."""

    index: int
    recv_s: float
    size_s: float


def jitter_s(d: FloatArray) -> float:
    """A robust standard deviation of the jitter of ``d`` (M,): from the median absolute deviation of its
    differences (0 for fewer than 3 values)."""
    if d.size < 3:
        return 0.0
    dd = np.diff(d)
    return float(1.4826 * np.median(np.abs(dd - np.median(dd))) / np.sqrt(2.0))


def level_steps(recv_s: FloatArray, stamps_s: FloatArray) -> tuple[list[LevelStep], float]:
    """The steps of d = recv - stamp of one stream (in the bag's order, ``recv_s`` non-decreasing) (module
    docstring), and the threshold used [s]."""
    d = np.asarray(recv_s, dtype=np.float64) - np.asarray(stamps_s, dtype=np.float64)
    n = d.size
    threshold = max(MIN_STEP_S, NOISE_FACTOR * jitter_s(d))
    if n < 2 * EDGE_SAMPLES:
        return [], threshold
    w = int(min(MAX_WINDOW, max(EDGE_SAMPLES, n // 20)))
    score = np.zeros(n + 1)  # score[k]: the step between message k - 1 and k
    if n >= 2 * w:
        med = np.median(np.lib.stride_tricks.sliding_window_view(d, w), axis=1)  # med[i]: d[i:i + w]
        score[w:n - w + 1] = med[w:] - med[:n - 2 * w + 1]
    for k in [*range(EDGE_SAMPLES, min(w, n - EDGE_SAMPLES + 1)), *range(max(n - w + 1, w), n - EDGE_SAMPLES + 1)]:
        m = min(k, n - k, w)  # near the ends: as many messages as there are on the short side
        score[k] = np.median(d[k:k + m]) - np.median(d[k - m:k])
    above = np.abs(score) > threshold
    steps = []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], above.astype(np.int8), [0]])))
    runs: list[list[int]] = []
    for a, b in zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True):  # runs [a, b) of k above
        if runs and a - runs[-1][1] < w:  # closer than a window: one step (a recorder's step interleaves messages)
            runs[-1][1] = b
        else:
            runs.append([a, b])
    for a, b in runs:
        lo, hi = max(a - w, 0), min(b - 1 + w, n)
        before = float(np.median(d[max(a - 1 - w, 0):max(a - 1, 1)]))
        after = float(np.median(d[min(b - 1, n - 1):min(b - 1 + w, n)]))
        if abs(after - before) <= threshold:
            continue
        seg = d[lo:hi]
        # the split of seg that fits the two levels best: cost of k = sum |d - before| left of k + |d - after| from k
        left = np.concatenate([[0.0], np.cumsum(np.abs(seg - before))])
        right = np.concatenate([np.cumsum(np.abs(seg - after)[::-1])[::-1], [0.0]])
        k = lo + int(np.argmin(left + right))
        k = min(max(k, 1), n - 1)
        steps.append(LevelStep(index=k, recv_s=float(recv_s[k]), size_s=after - before))
    return steps, threshold


@dataclass(frozen=True)
class ClockCut:
    """What :func:`clock_cut` keeps: the scans and the servo samples (masks in the order given) and the notes."""

    keep_scans: BoolArray
    keep_servo: BoolArray
    notes: tuple[str, ...]


def clock_cut(scan_recv_s: FloatArray, scan_stamps_s: FloatArray, servo_recv_s: FloatArray | None,
              servo_stamps_s: FloatArray | None, where_scan: str, where_servo: str) -> ClockCut:
    """The scans and servo samples that share one laser-minus-servo clock offset (module docstring).

    Args:
        scan_recv_s, scan_stamps_s: (S,) the scans' receive times and stamps [s], in any order.
        servo_recv_s, servo_stamps_s: (J,) the servo samples' (None: the servo has no clock of its own: its angle
            travels in the scans, or is constant).
        where_scan, where_servo: the bag and topic, for the notes.
    Raises:
        CalibrationError: the longest part with one offset holds fewer than MIN_KEPT_SHARE of the scans.
    """
    t0 = float(np.min(scan_recv_s)) if servo_recv_s is None else float(min(np.min(scan_recv_s),
                                                                            np.min(servo_recv_s)))
    streams = {"scan": _ordered(scan_recv_s, scan_stamps_s)}
    if servo_recv_s is not None and servo_stamps_s is not None:
        streams["servo"] = _ordered(servo_recv_s, servo_stamps_s)
    found = {name: level_steps(r, s) for name, (r, s, _) in streams.items()}
    notes: list[str] = []
    scan_steps, scan_thr = found["scan"]
    servo_steps, servo_thr = found.get("servo", ([], 0.0))
    # a step both streams show alike (the recorder's clock) is named only; the others change the offset
    recorder = []
    for s in list(scan_steps):
        twin = next((j for j in servo_steps if abs(j.recv_s - s.recv_s) <= _near_s(streams)
                     and abs(j.size_s - s.size_s) <= max(scan_thr, servo_thr)), None)
        if twin is not None:
            recorder.append(s)
            scan_steps.remove(s)
            servo_steps.remove(twin)
    for s in recorder:
        notes.append(f"the bag's receive times step by {-s.size_s:+.3f} s against both the scan and the servo stamps "
                     f"{s.recv_s - t0:.2f} s after the bag's first message (the recorder's clock, or a stall of the "
                     f"recorder): the stamps and their offset are unaffected")
    cuts = sorted([(s.recv_s, "scan", s) for s in scan_steps] + [(j.recv_s, "servo", j) for j in servo_steps],
                  key=lambda c: c[0])
    keep_scans = np.ones(np.size(scan_recv_s), dtype=bool)
    keep_servo = np.ones(0 if servo_recv_s is None else np.size(servo_recv_s), dtype=bool)
    if not cuts:
        return ClockCut(keep_scans, keep_servo, tuple(notes))
    bounds = [c[0] for c in cuts]
    names = "; ".join(_describe(kind, st, where_scan if kind == "scan" else where_servo, streams[kind][0], t0)
                      for _, kind, st in cuts)
    part_scan = np.searchsorted(bounds, scan_recv_s, side="right")  # part 0 before the first step, ...
    part_servo = (np.searchsorted(bounds, servo_recv_s, side="right") if servo_recv_s is not None
                  else np.zeros(0, dtype=np.int64))
    # the laser-minus-servo offset of each part, relative to the first: + servo steps, - scan steps
    change = np.concatenate([[0.0], np.cumsum([st.size_s if kind == "servo" else -st.size_s
                                               for _, kind, st in cuts])])
    n_parts = len(bounds) + 1
    counts = np.bincount(part_scan, minlength=n_parts)
    tol = max(scan_thr, servo_thr)
    best = int(np.argmax(counts))
    chosen = [best]
    for p in np.argsort(-counts, kind="stable").tolist():
        if p == best or counts[p] == 0 or abs(change[p] - change[best]) > tol:
            continue
        if all(not _overlap(scan_stamps_s, part_scan, p, q) and (servo_stamps_s is None or not _overlap(
                servo_stamps_s, part_servo, p, q)) for q in chosen):
            chosen.append(p)
    keep_scans = np.isin(part_scan, chosen)
    keep_servo = np.isin(part_servo, chosen)
    kept, total = int(keep_scans.sum()), int(keep_scans.size)
    spans = ", ".join(_span(bounds, p, t0) for p in sorted(chosen))
    if kept < MIN_KEPT_SHARE * total:
        raise CalibrationError(
            f"clock step: {names}; the scans and the joint states lose their common clock there, and the longest "
            f"part with one clock offset holds only {kept} of {total} scans (fewer than {MIN_KEPT_SHARE:.0%}): one "
            "clock offset cannot serve this recording; record again with the clocks synchronised before the start "
            "(chrony or ntpd stepping only at boot), or cut the bag at the steps")
    notes.append(f"clock step: {names}; one clock offset cannot serve both sides, so only the part(s) with one offset "
                 f"are kept ({spans} after the bag's first message): {kept} of {total} scans and "
                 f"{int(keep_servo.sum())} of {keep_servo.size} servo samples; {total - kept} scans left out")
    return ClockCut(keep_scans, keep_servo, tuple(notes))


def _ordered(recv_s: FloatArray, stamps_s: FloatArray) -> tuple[FloatArray, FloatArray, NDArray[np.int64]]:
    """A stream's (receive times, stamps) in the bag's order (by receive time, stably) and that order."""
    order = np.argsort(recv_s, kind="stable")
    return np.asarray(recv_s)[order], np.asarray(stamps_s)[order], order


def _near_s(streams: dict[str, tuple[FloatArray, FloatArray, NDArray[np.int64]]]) -> float:
    """How far apart [s] two streams' steps may be and still be one step of the recorder: the longer of the two
    streams' windows (MAX_WINDOW median periods)."""
    out = 0.0
    for r, _, _ in streams.values():
        if r.size > 1:
            out = max(out, float(np.median(np.diff(r))) * min(MAX_WINDOW, max(EDGE_SAMPLES, r.size // 20)))
    return out


def _overlap(stamps: FloatArray, part: NDArray[np.int64], p: int, q: int) -> bool:
    """Whether the stamps of parts p and q of a stream overlap in time."""
    a, b = stamps[part == p], stamps[part == q]
    if not a.size or not b.size:
        return False
    return bool(a.min() <= b.max() and b.min() <= a.max())


def _span(bounds: list[float], p: int, t0: float) -> str:
    lo = "start" if p == 0 else f"{bounds[p - 1] - t0:.2f} s"
    hi = "end" if p == len(bounds) else f"{bounds[p] - t0:.2f} s"
    return f"{lo} to {hi}"


def _describe(kind: str, step: LevelStep, where: str, recv: FloatArray, t0: float) -> str:
    """One step in words: which stamps, by how much, where; and what it does to the laser-minus-servo offset."""
    offset = step.size_s if kind == "servo" else -step.size_s
    return (f"the {'scan' if kind == 'scan' else 'servo'} stamps of {where} step by {-step.size_s:+.3f} s against the "
            f"bag's receive times {step.recv_s - t0:.2f} s after the bag's first message (message {step.index + 1} "
            f"of {recv.size}): the laser-minus-servo offset changes there by {offset:+.3f} s")


__all__ = ["EDGE_SAMPLES", "MAX_WINDOW", "MIN_KEPT_SHARE", "MIN_STEP_S", "NOISE_FACTOR", "ClockCut", "LevelStep",
           "clock_cut", "jitter_s", "level_steps"]
