"""The rig model's unknowns: each one named, with its unit, its start value and whether it is estimated by default
(and why not), and their order in the solver's vector (:data:`CORE_NAMES`), packed and unpacked here only.

The core vector: the mount translation x, y, z, a rotation vector rx, ry, rz in frame M (the mount's rotation is
R_ref Exp(w), so the solver never meets an Euler-angle singularity; roll, pitch and yaw are an output format), the DH
parameters a, alpha, b, beta, the laser-servo clock offset, and the servo's and scanner's intrinsics (:data:`UNKNOWNS`
with kind "intrinsic"); then 3 nuisances per plane (lrfcal.model.plane.PlaneSet).

Adding an unknown is adding a row to :data:`UNKNOWNS` and its effect to the model function it belongs to (the motor
angle in :mod:`.motor`, the range in :mod:`.scanner`, the chain in :mod:`.rays` and :mod:`.plane`); the solver,
its covariance and the written results take it from there.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrfcal.errors import InputError
from lrfcal.model.kinematics import DH, ESTIMATE_NAMES, Params, Pose, exp_so3

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Unknown:
    """One unknown of the rig model.

    name: as in files and APIs; unit: "m", "rad", "s", "1" or "m/rad"; kind: "mount", "dh", "clock" or "intrinsic";
    start: its value before any data (and while held, unless a stage gives another); held: empty when the
    calibration estimates it by default, else why it is held by default; meaning: one line for reports;
    tested_with: an unknown freed beside it in its score test (lrfcal.estimate.solve) when a solve holds both (a scale
    is
    told from an offset only with the offset free)."""

    name: str
    unit: str
    kind: str
    start: float
    held: str
    meaning: str
    tested_with: str = ""


#: Every unknown of the rig model, in the solver's order.
UNKNOWNS: tuple[Unknown, ...] = (
    *(Unknown(n, "m", "mount", 0.0, "", f"mount translation {n} (T_W_M)") for n in ("x", "y", "z")),
    *(Unknown(n, "rad", "mount", 0.0, "", "mount rotation increment, a rotation vector in M")
      for n in ("rx", "ry", "rz")),
    Unknown("a", "m", "dh", 0.0, "", "DH offset along the common normal"),
    Unknown("alpha", "rad", "dh", 0.0, "", "DH twist of the scan plane's axis about the common normal"),
    Unknown("b", "m", "dh", 0.0, "", "DH offset along the scanner's axis"),
    Unknown("beta", "rad", "dh", 0.0, "", "DH angle of the scanner's zero beam about its axis"),
    Unknown("clock_offset", "s", "clock", 0.0, "", "laser stamp minus servo stamp"),
    Unknown("range_offset", "m", "intrinsic", 0.0, "", "added to every range the scanner reports"),
    Unknown("marker_range_bias", "m", "intrinsic", 0.0, "", "added to the ranges of marker returns only"),
    Unknown("range_scale", "1", "intrinsic", 1.0,
            "the scanner's range scale is trusted: held at 1 unless the tape contradicts it",
            "the scanner reports this times the true range (plus the range offset)", "range_offset"),
    Unknown("motor_scale", "1", "intrinsic", 1.0, "the servo's angle scale (gear ratio) is trusted: held at 1",
            "the joint's reported angle times this is the motor angle (a gear ratio or counts per turn off)"),
    Unknown("beam_scale", "1", "intrinsic", 1.0, "the scan's declared angle increment is trusted: held at 1",
            "the declared bearing times this is the beam's bearing (an angle increment declared wrongly)"),
    Unknown("incidence_bias", "m/rad", "intrinsic", 0.0,
            "the ranges are taken as independent of the beam's incidence on the surface: held at 0 unless the data "
            "contradict it", "added to a range per radian of the beam's incidence on the surface it meets [m/rad]",
            "range_offset"),
)
assert tuple(u.name for u in UNKNOWNS[:10]) == ESTIMATE_NAMES

#: The solver's core unknowns, in this order (then 3 nuisances per plane): see the module docstring.
CORE_NAMES: tuple[str, ...] = tuple(u.name for u in UNKNOWNS)
N_CORE = len(CORE_NAMES)
BY_NAME: dict[str, Unknown] = {u.name: u for u in UNKNOWNS}
TAU = CORE_NAMES.index("clock_offset")
ROFF = CORE_NAMES.index("range_offset")
MBIAS = CORE_NAMES.index("marker_range_bias")
RSCALE = CORE_NAMES.index("range_scale")
SCALE = CORE_NAMES.index("motor_scale")
BSCALE = CORE_NAMES.index("beam_scale")
INC = CORE_NAMES.index("incidence_bias")
DH_SLICE = slice(6, 10)
INTRINSICS: tuple[str, ...] = tuple(u.name for u in UNKNOWNS if u.kind == "intrinsic")


def wrap_pi(a: ArrayLike) -> FloatArray:
    """Wrap angles to (-pi, pi]."""
    a = np.asarray(a, dtype=float)
    return a - 2 * np.pi * np.ceil((a - np.pi) / (2 * np.pi))


def dh_difference(p: ArrayLike, q: ArrayLike) -> FloatArray:
    """(4,) the DH vector p - q (a, alpha, b, beta), alpha's and beta's differences wrapped to (-pi, pi]."""
    d = np.asarray(p, dtype=float) - np.asarray(q, dtype=float)
    d[[1, 3]] = wrap_pi(d[[1, 3]])
    return d


def pack(params: Params, clock_offset_s: float = 0.0) -> tuple[FloatArray, FloatArray]:
    """The core vector (N_CORE,) of ``params`` with w = 0 and every other unknown at its start, and R_ref (3, 3)
    (roll, pitch and yaw are only a format)."""
    T = params.mount.matrix()
    core = np.array([u.start for u in UNKNOWNS])
    core[:3] = T[:3, 3]
    core[3:6] = 0.0
    core[DH_SLICE] = params.dh.vector()
    core[TAU] = clock_offset_s
    return core, T[:3, :3].copy()


def core_vector(dh: DH, intrinsics: Mapping[str, float]) -> FloatArray:
    """(N_CORE,) a core vector with ``dh``, the ``intrinsics`` named (by name: value), the mount at the identity and
    every other unknown at its start: what the model functions acting on ranges, bearings and motor angles take.

    Raises:
        InputError: a name in ``intrinsics`` is not an intrinsic of the model.
    """
    unknown = sorted(set(intrinsics) - set(INTRINSICS))
    if unknown:
        raise InputError(f"not intrinsics of the rig model: {', '.join(unknown)} (known: {', '.join(INTRINSICS)})")
    core = np.array([u.start for u in UNKNOWNS])
    core[DH_SLICE] = dh.vector()
    for name, value in intrinsics.items():
        core[CORE_NAMES.index(name)] = value
    return core


def unpack(core: FloatArray, R_ref: FloatArray) -> Params:
    """The 10 parameters of a core vector (N_CORE,) (the mount R_ref Exp(w); alpha and beta wrapped)."""
    T = np.eye(4)
    T[:3, :3] = R_ref @ exp_so3(core[3:6])
    T[:3, 3] = core[:3]
    v = np.array(core[DH_SLICE], dtype=float)
    v[[1, 3]] = wrap_pi(v[[1, 3]])
    return Params(Pose.from_matrix(T), DH(*map(float, v)))


def free_by_default(hold: Sequence[str] = (), estimate: Sequence[str] = ()) -> NDArray[np.bool_]:
    """(N_CORE,) the unknowns a calibration estimates unless a stage holds them: all but those :data:`UNKNOWNS`
    holds by default (unless named in ``estimate``) and those named in ``hold``.

    Raises:
        InputError: a name in ``hold`` or ``estimate`` is not an unknown of the model.
    """
    for what, names in (("hold", hold), ("estimate", estimate)):
        unknown = sorted(set(names) - set(CORE_NAMES))
        if unknown:
            raise InputError(f"solve: {what}: unknown parameter {unknown[0]!r} (expected one of "
                             f"{', '.join(CORE_NAMES)})")
    return np.array([(not u.held or u.name in estimate) and u.name not in hold for u in UNKNOWNS])


def plane_nuisance_start(normals: FloatArray, offsets: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray,
                                                                            FloatArray]:
    """Tangent bases t1, t2 (P, 3) of initial normals (P, 3) and the start nuisance vector (3P,)."""
    n0 = np.asarray(normals, dtype=float).reshape(-1, 3)
    helper = np.where(np.abs(n0[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(n0, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n0, t1)
    nu0 = np.column_stack([np.zeros(len(n0)), np.zeros(len(n0)), np.asarray(offsets, dtype=float)]).ravel()
    return n0, t1, t2, nu0


