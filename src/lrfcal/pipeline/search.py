"""The DH search (lrfcal.stages.propose, ``lrfcal inspect``'s proposal, and a targetless calibration's other starts)
run on the machine's cores: the stage says what each start estimates and what the candidates propose; this module
solves the starts (lrfcal.estimate.engine.solved) in forked helpers beside this process (lrfcal.runtime.forked.Ahead),
or ahead, in niced children while a targetless calibration goes on (:func:`proposal_ahead`, begun by the orchestrator
where the way's ``SEARCH`` asks for it), and collects them in start order.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator

import numpy as np

from lrfcal.errors import CalibrationError
from lrfcal.estimate.engine import solved
from lrfcal.model.kinematics import DH
from lrfcal.runtime.forked import Ahead, cores
from lrfcal.stages import propose
from lrfcal.stages.timing import usable_scans
from lrfcal.types import JointStates, Nominal, Recording, Scans

#: the starts solved: (start index, its candidate or None), in the order asked for
Solved = list[tuple[int, propose.Candidate | None]]


def propose_dh(scans: Scans, joints: JointStates, progress: Callable[[int, int], None] | None = None
               ) -> propose.DHProposal:
    """Search the DH parameters that make the scene's planes planar (module docstring). ``scans``: the scans the
    joint states cover; ``progress(done, total)`` after every start."""
    t0 = time.perf_counter()
    search = propose.search_of(scans, joints, t0)
    if isinstance(search, propose.DHProposal):
        return search
    # the starts are independent: solved on the cores (lrfcal.runtime.forked), collected in start order
    every = _solve_on_cores(search, list(range(len(search.starts))), progress)
    return propose.proposal_of(search, [every], t0, progress)


#: the niceness added to the children of :func:`proposal_ahead`: they take idle cores only, never the fit's
AHEAD_NICE = 19


@contextlib.contextmanager
def proposal_ahead(scans: Scans, joints: JointStates) -> Iterator[propose.Proposal]:
    """:func:`propose_dh` ``(scans, joints)`` begun now, while this process goes on (the targetless fit: the search
    does not depend on it), in forked children at the lowest priority (lrfcal.runtime.forked.Ahead, one per core beside
    this process, each inheriting the sampled returns, :data:`AHEAD_NICE`): they use cores that would idle, and take
    no time from this process where the cores are busy. The callable yielded returns the proposal: the starts the
    children finished, the others solved then as :func:`propose_dh` solves them (on the cores, at the usual priority),
    the same proposal as :func:`propose_dh`'s. The children end when it is asked for, or when the context is left (a
    refused fit)."""
    t0 = time.perf_counter()
    search = propose.search_of(scans, joints, t0)
    if isinstance(search, propose.DHProposal):
        yield lambda: search
        return
    n = search.n_groups
    # one child per core the fit leaves idle (niced children sharing one core would each have a start cut short
    # when the proposal is asked for), the starts in turn
    n_ahead = max(1, min(n, cores() - 1))
    groups = [list(range(g, len(search.starts), n_ahead)) for g in range(n_ahead)]
    with contextlib.ExitStack() as stack:
        aheads = [stack.enter_context(Ahead(_ready, inherit=(search,), nice=AHEAD_NICE)) for _ in groups]
        for ahead, ks in zip(aheads, groups, strict=True):
            for k in ks:  # one call per start: what is done when the proposal is asked for is kept
                ahead.start(_solve_starts, search, [k])
        taken: list[propose.DHProposal] = []

        def proposal() -> propose.DHProposal:
            if not taken:
                done: list[tuple[int, propose.Candidate | None]] = []
                for ahead, ks in zip(aheads, groups, strict=True):
                    for _ in ks:
                        if not ahead.ready():
                            break
                        done.extend(ahead.result())
                stack.close()  # the children end (one still solving a start at once)
                have = {k for k, _ in done}
                missing = [k for k in range(len(search.starts)) if k not in have]
                taken.append(propose.proposal_of(search, [done, _solve_on_cores(search, missing)], t0, None))
            return taken[0]

        yield proposal


def _ready() -> None:
    """An :class:`~lrfcal.runtime.forked.Ahead` child's preparation: none (it inherited what the search reads)."""


def _solve_on_cores(search: propose.Search, ks: list[int], progress: Callable[[int, int], None] | None = None
                    ) -> Solved:
    """The starts ``ks`` solved on the cores at the usual priority (``progress(done, total)`` after every start): a
    forked helper per other core (lrfcal.runtime.forked.Ahead, at most ``search.n_groups - 1``) takes its share
    (every n-th start) from the front, one call per start, while this process takes them from the back, skipping
    any its helper has begun or finished; then it waits for the helpers' starts it did not take (at most the one
    each is solving), and the helpers end. The cores so end together to within one start, where fixed shares (one
    group per core) left one core idle while the other solved its group's costlier starts. A start solved both here
    and by its helper gives the same candidate; it is kept once."""
    n_help = max(0, min(search.n_groups, len(ks)) - 1)
    shares = [ks[h::n_help] for h in range(n_help)]
    owner = {k: (h, p) for h, share in enumerate(shares) for p, k in enumerate(share)}
    out: dict[int, propose.Candidate | None] = {}
    with contextlib.ExitStack() as stack:
        helpers = [stack.enter_context(Ahead(_ready, inherit=(search,))) for _ in shares]
        for helper, share in zip(helpers, shares, strict=True):
            for k in share:
                helper.start(_solve_starts, search, [k])
        got = [0] * n_help  # the results taken from each helper (its share's first ones)

        def take(h: int) -> None:
            for k, cand in helpers[h].result():
                out.setdefault(k, cand)
            got[h] += 1

        here: set[int] = set()
        for k in reversed(ks):
            for h, helper in enumerate(helpers):
                while got[h] < len(shares[h]) and helper.ready():
                    take(h)
            if k in out or (k in owner and owner[k][1] <= got[owner[k][0]]):
                continue  # its helper has it (done, or the one it is solving)
            out.update(_solve_starts(search, [k]))
            here.add(k)
            if progress is not None:
                progress(min(len(search.starts) - 1, len(out)), len(search.starts))
        for h, share in enumerate(shares):  # what is left of each share: the first starts not solved here
            while got[h] < len(share) and share[got[h]] not in here:
                take(h)
    return [(k, out[k]) for k in ks]


def _solve_starts(search: propose.Search, ks: list[int], progress: Callable[[int, int], None] | None = None
                  ) -> Solved:
    """The starts ``ks`` solved (:func:`_candidate`); ``progress`` from the first group of :func:`propose_dh`, which
    runs in this process."""
    starts, n = search.starts, search.n_groups
    out: Solved = []
    for k in ks:
        out.append((k, _candidate(search, k)))
        if progress is not None:
            progress(min(len(starts) - 1, len(out) * n), len(starts))
    return out


def _candidate(search: propose.Search, k: int) -> propose.Candidate | None:
    """Start ``k`` solved (lrfcal.stages.propose.start_request, on its own segmentation subsample) and its candidate;
    None where its planes are too few, its solve fails or its minimum runs off."""
    request = propose.start_request(search, k)
    if request is None:
        return None
    try:
        return propose.candidate(solved(request))
    except (CalibrationError, np.linalg.LinAlgError):
        return None


def propose_for_recording(scans: Scans, joints: JointStates,
                          progress: Callable[[int, int], None] | None = None) -> propose.DHProposal:
    """:func:`propose_dh` on a recording as read (every scan, every joint state): the scans the joint states cover
    and interpolate well enough (lrfcal.stages.timing.usable_scans, as a calibration takes them); a recording whose
    motor
    angle cannot be interpolated gets no proposal, and the reason."""
    placeholder = Nominal(dh=DH(a=0.0, alpha=0.0, b=0.0, beta=0.0))
    try:
        covered, joints = usable_scans(Recording(scans=scans, joints=joints, tape=None, nominal=placeholder), 0.0,
                                       propose.RANGE_SIGMA_M).value
    except CalibrationError as err:
        return propose.DHProposal(None, reason=str(err))
    return propose_dh(covered, joints, progress)


__all__ = ["AHEAD_NICE", "propose_dh", "propose_for_recording", "proposal_ahead"]
