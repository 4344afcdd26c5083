"""The root in one canonical frame for every skeleton (issue 20): Euler algebra for every
rotation order against scipy, the CMU ASF path unchanged bit for bit, and CMU's BVH of a take
giving the same root features as its AMC."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocap.representation import Representation, _matrix_to_rxyz, _rxyz_to_matrix, wrap180
from mocap.rootframe import RootFrame, euler_to_matrix, matrix_to_euler

ORDERS = ["xyz", "xzy", "yxz", "yzx", "zxy", "zyx"]


@pytest.mark.parametrize("order", ORDERS)
def test_euler_matches_scipy_and_round_trips(order, rng):
    a = rng.uniform(-np.pi, np.pi, (200, 3))
    a[:, 1] = rng.uniform(-1.4, 1.4, 200)  # away from gimbal lock
    R = euler_to_matrix(a, order)
    # scipy's intrinsic upper-case sequence "ZXY" is Rz @ Rx @ Ry
    np.testing.assert_allclose(R, Rotation.from_euler(order.upper(), a).as_matrix(), atol=1e-12)
    back = matrix_to_euler(R, order, np.rad2deg(a))
    np.testing.assert_allclose(wrap180(back - np.rad2deg(a)), 0.0, atol=1e-9)
    # the other solution when it is nearer the previous frame
    other = np.stack([a[:, 0] + np.pi, np.pi - a[:, 1], a[:, 2] + np.pi], 1)
    np.testing.assert_allclose(euler_to_matrix(other, order), R, atol=1e-12)
    alt = matrix_to_euler(R, order, np.rad2deg(other))
    np.testing.assert_allclose(wrap180(alt - np.rad2deg(other)), 0.0, atol=1e-9)


def test_cmu_asf_convention_is_the_original_algebra_bit_for_bit(rng):
    f = RootFrame(None)
    r = rng.uniform(-3, 3, (50, 3))
    assert f.identity
    assert np.array_equal(f.matrix(r), _rxyz_to_matrix(r[:, 0], r[:, 1], r[:, 2]))
    R = _rxyz_to_matrix(r[:, 0], r[:, 1], r[:, 2])
    prev = np.rad2deg(r)
    assert np.array_equal(f.angles(R, prev), _matrix_to_rxyz(R, prev))


@pytest.mark.parametrize("up", ["y", "z", "x"])
@pytest.mark.parametrize("order", ["zxy", "zyx", "yxz"])
def test_root_frame_round_trips_and_puts_up_on_y(up, order, rng):
    f = RootFrame({"order": order, "up": up, "rest": [90.0, 0.0, 0.0] if up == "z" else None})
    deg = rng.uniform(-170, 170, (100, 3))
    deg[:, "xyz".index(order[1])] = rng.uniform(-70, 70, 100)
    back = f.angles(f.matrix(np.deg2rad(deg)), deg)
    np.testing.assert_allclose(wrap180(back - deg), 0.0, atol=1e-8)
    p = rng.normal(size=(100, 3))
    pc = f.to_canonical(p)
    np.testing.assert_allclose(pc[:, 1], p[:, "xyz".index(up)], atol=1e-12)  # height
    np.testing.assert_allclose(f.from_canonical(pc), p, atol=1e-12)


@pytest.mark.realdata
def test_cmu_bvh_root_features_equal_the_amc_of_the_same_take(data):
    """07_01 as AMC (y up, root R = Rz Ry Rx) and as CMU's BVH (z up, Hips upright at
    Xrotation 90): the heading-relative root features agree (BVH frame t + 1 = AMC frame t),
    within the BVH's 4-decimal rounding; decoding them gives the BVH's own channels back."""
    from mocap.io import read_motion
    from mocap.tpose import skip_tpose

    b = skip_tpose(read_motion(data / "bvh" / "07_01.bvh"), quiet=True)
    a = read_motion(data / "cmu" / "07" / "07_01.amc")
    rb = Representation.fit([b.frames], b.channels, root_mode="relative", normalize=False)
    ra = Representation.fit([a.frames], a.channels, root_mode="relative", normalize=False)
    assert ra.root is None and rb.root["up"] == "z" and rb.root["rest"] == [90.0, 0.0, 0.0]
    Fb, Fa = rb.transform(b.frames), ra.transform(a.frames)
    tol = {"root.dside": 0.03, "root.ty": 0.1, "root.dfwd": 0.03, "root.dyaw": 0.05, "root.pitch": 0.5,
           "root.roll": 0.05}  # file units per frame, file units, degrees per frame, degrees
    for k, name in enumerate(rb.features[:6]):
        assert np.abs(Fb[:, k] - Fa[:, k]).max() < tol[name], name
    back = rb.inverse(Fb, first=b.frames[0])
    cols = b.index(rb.root["rot"] + rb.root["pos"])
    np.testing.assert_allclose(wrap180(back[:, cols] - b.frames[:, cols]), 0.0, atol=1e-9)
    assert Representation.from_dict(rb.to_dict()).root == rb.root
