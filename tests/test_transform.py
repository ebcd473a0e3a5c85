"""Poses and rigid transforms (paper §2.1) against scipy's rotations and closed forms."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pmdsim.geometry.transform import RigidTransform, givens_angles, givens_rotation


@pytest.mark.parametrize("angles", [(45, 10, 10), (135, 0, 0), (45, -10, -10), (-30, 20, 170), (0, 0, 0)])
def test_givens_rotation_matches_scipy_intrinsic_zyx(angles):
    a, b, g = angles
    ref = Rotation.from_euler("ZYX", [g, b, a], degrees=True).as_matrix()
    np.testing.assert_allclose(givens_rotation(angles), ref, atol=1e-15)
    np.testing.assert_allclose(givens_angles(ref), angles, atol=1e-12)


def test_axes_are_columns_in_world():
    # Rx(90°): the component's y axis is world +z, its z axis world −y.
    T = RigidTransform.from_origin_angles([1.0, 2.0, 3.0], [90.0, 0.0, 0.0])
    np.testing.assert_allclose(T.apply_vector([0.0, 1.0, 0.0]), [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(T.apply_vector([0.0, 0.0, 1.0]), [0, -1, 0], atol=1e-15)
    # The component's origin maps to its world position.
    np.testing.assert_allclose(T.apply([0.0, 0.0, 0.0]), [1, 2, 3])


def test_inverse_and_composition_eq1():
    rng = np.random.default_rng(1)
    T_w_a = RigidTransform.from_origin_angles(rng.normal(size=3) * 100, rng.uniform(-180, 180, 3))
    T_w_b = RigidTransform.from_origin_angles(rng.normal(size=3) * 100, rng.uniform(-180, 180, 3))
    p_a = rng.normal(size=(5, 4, 3))
    # eq. (1): T_ba = T_bw · T_aw^-1
    T_b_a = T_w_b.inv() @ T_w_a
    np.testing.assert_allclose(T_b_a.apply(p_a), T_w_b.inv().apply(T_w_a.apply(p_a)), atol=1e-12)
    M = np.linalg.inv(T_w_b.as_matrix()) @ T_w_a.as_matrix()
    ph = np.concatenate([p_a, np.ones(p_a.shape[:-1] + (1,))], axis=-1)
    np.testing.assert_allclose(T_b_a.apply(p_a), (ph @ M.T)[..., :3], atol=1e-12)
    np.testing.assert_allclose((T_w_a @ T_w_a.inv()).as_matrix(), np.eye(4), atol=1e-13)


def test_apply_leaves_its_input_and_matches_scipy():
    # apply adds the translation in place to the rotated copy: the input stays untouched, and
    # the result is scipy's rotation plus the translation, for a single point, a (N, 3) list
    # and an (H, W, 3) image of points (read-only input included).
    rng = np.random.default_rng(7)
    rotvec, t = rng.normal(size=3), rng.normal(size=3) * 50
    T = RigidTransform(Rotation.from_rotvec(rotvec).as_matrix(), t)
    for p in (rng.normal(size=3), rng.normal(size=(6, 3)), rng.normal(size=(4, 5, 3))):
        keep = p.copy()
        p.flags.writeable = False
        out = T.apply(p)
        assert np.array_equal(p, keep) and out.shape == p.shape and out.dtype == np.float64
        ref = Rotation.from_rotvec(rotvec).apply(keep.reshape(-1, 3)).reshape(p.shape) + t
        np.testing.assert_allclose(out, ref, rtol=0, atol=1e-12)
    assert np.array_equal(T.apply([[1, 2, 3]]), T.apply(np.array([[1.0, 2.0, 3.0]])))  # ints are cast


def test_rejects_bad_rotation():
    with pytest.raises(ValueError, match="rotation"):
        RigidTransform(np.diag([1.0, 1.0, -1.0]), np.zeros(3))
    with pytest.raises(ValueError, match="finite"):
        RigidTransform(np.eye(3), [np.nan, 0, 0])


def test_rotation_angle_matches_scipy():
    from pmdsim.geometry.transform import rotation_angle_rad

    for rv in ([0.0, 0.0, 0.0], [0.3, -0.2, 0.1], [0.0, 3.0, 0.0], [1e-9, 0.0, 0.0]):
        r = Rotation.from_rotvec(rv)
        assert abs(rotation_angle_rad(r.as_matrix()) - r.magnitude()) < 1e-7
