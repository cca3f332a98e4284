"""eq. (3): the closed forms against the literal product of the paper's matrices; pose conventions."""

import numpy as np
import pytest

from lrfcal.errors import InputError
from lrfcal.model.kinematics import (
    DH,
    Params,
    Pose,
    beam_rays_M,
    chain_T_M_L,
    dh_from_mapping,
    points_M,
    points_W,
    pose_matrix,
    rot_x,
    rot_y,
    rot_z,
    transform_points,
)


def _random_dh(rng: np.random.Generator) -> DH:
    return DH(
        rng.uniform(-0.05, 0.05),
        rng.uniform(-np.pi, np.pi),
        rng.uniform(-0.05, 0.05),
        rng.uniform(-np.pi, np.pi),
    )


def test_closed_form_equals_matrix_product() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        dh = _random_dh(rng)
        lam, mu, r = rng.uniform(-np.pi, np.pi, 100), rng.uniform(-2.4, 2.4, 100), rng.uniform(0.02, 30, 100)
        T = chain_T_M_L(lam, mu, dh)
        p_ref = T[:, :3, 0] * r[:, None] + T[:, :3, 3]  # [r, 0, 0] in L
        np.testing.assert_allclose(points_M(r, lam, mu, dh), p_ref, atol=1e-12)
        o, d = beam_rays_M(lam, mu, dh)
        np.testing.assert_allclose(o, T[:, :3, 3], atol=1e-15)
        np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-15)


def test_chain_order_is_the_papers() -> None:
    # a = 0, b = 0, alpha = 0: the beam angle just adds to lambda and beta about the same z axis
    dh = DH(0.0, 0.0, 0.0, 0.3)
    p = points_M([1.0], [0.2], [0.1], dh)[0]
    assert np.allclose(p, [np.cos(0.6), np.sin(0.6), 0.0])
    # pure offsets: a along x of M', b along the mirror axis (z of I')
    dh = DH(0.01, np.pi / 2, 0.02, 0.0)
    np.testing.assert_allclose(beam_rays_M([0.0], [0.0], dh)[0][0], [0.01, -0.02, 0.0], atol=1e-15)


def test_pose_is_urdf_rpy() -> None:
    rng = np.random.default_rng(1)
    for _ in range(20):
        x, y, z, roll, pitch, yaw = rng.uniform(-1, 1, 6)
        T = pose_matrix(x, y, z, roll, pitch, yaw)
        np.testing.assert_allclose(T[:3, :3], rot_z(yaw) @ rot_y(pitch) @ rot_x(roll), atol=1e-15)
        back = Pose.from_matrix(T)
        np.testing.assert_allclose(back.matrix(), T, atol=1e-12)


def test_points_W_composes_T_W_M_and_T_M_L() -> None:
    rng = np.random.default_rng(2)
    params = Params(Pose(*rng.uniform(-1, 1, 6)), _random_dh(rng))
    lam, mu, r = rng.uniform(-1, 1, 10), rng.uniform(-1, 1, 10), rng.uniform(0.1, 5, 10)
    T_W_L = params.mount.matrix() @ chain_T_M_L(lam, mu, params.dh)
    expected = T_W_L[:, :3, 0] * r[:, None] + T_W_L[:, :3, 3]
    np.testing.assert_allclose(points_W(r, lam, mu, params), expected, atol=1e-12)
    np.testing.assert_allclose(Params.from_vector(params.vector()).vector(), params.vector())
    np.testing.assert_allclose(transform_points(np.eye(4), expected), expected)


@pytest.mark.parametrize(
    ("data", "field"),
    [
        ({"a": 0, "alpha": 0, "b": 0}, "beta"),
        ({"a": 0, "alpha": 0, "b": 0, "beta": 0, "c": 1}, "c"),
        ({"a": "x", "alpha": 0, "b": 0, "beta": 0}, "a"),
    ],
)
def test_dh_mapping_errors_name_the_field(data: dict, field: str) -> None:
    with pytest.raises(InputError, match=rf"nominal\.yaml: dh\.{field}"):
        dh_from_mapping(data, "nominal.yaml: dh")
