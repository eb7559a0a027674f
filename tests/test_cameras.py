"""The camera convention (n2f2.cameras), tested against hand-derived answers."""

import numpy as np
import pytest

from n2f2.cameras import (
    Camera,
    from_opengl_c2w,
    look_at,
    qvec_to_rotmat,
    rotmat_to_qvec,
)


def _camera(eye=(3.0, -2.0, 1.5), target=(0.0, 0.0, 0.2)) -> Camera:
    R, t = look_at(np.array(eye), np.array(target))
    return Camera(fx=120.0, fy=110.0, cx=80.0, cy=60.0, width=160, height=120, R=R, t=t)


def test_identity_camera_axes_and_pixel_centres():
    cam = Camera(fx=100.0, fy=100.0, cx=2.0, cy=1.5, width=4, height=3)
    # A point straight ahead lands on the principal point (2.0, 1.5): the centre of a 4x3
    # image, which is the corner shared by pixels (row 0/1, col 1/2).
    uv, z = cam.project(np.array([0.0, 0.0, 5.0]))
    np.testing.assert_allclose(uv, [2.0, 1.5])
    assert z == 5.0
    # x right, y down: a point to the right and below projects right and down.
    uv, _ = cam.project(np.array([0.05, 0.05, 5.0]))
    np.testing.assert_allclose(uv, [3.0, 2.5])  # centre of pixel (row 2, col 2)
    centres = cam.pixel_centers()
    np.testing.assert_allclose(centres[2, 2], [2.5, 2.5])
    np.testing.assert_allclose(centres[0, 0], [0.5, 0.5])


def test_project_unproject_roundtrip():
    cam = _camera()
    pts = np.random.default_rng(0).normal(size=(100, 3)) * 0.4
    uv, z = cam.project(pts)
    assert (z > 0).all()
    np.testing.assert_allclose(cam.unproject(uv, z), pts, atol=1e-10)


def test_depth_to_points_is_z_depth():
    cam = _camera()
    depth = np.full((cam.height, cam.width), 2.0)
    pts = cam.depth_to_points(depth)
    # every point has camera-space z equal to the depth, and projects to its pixel centre
    pc = cam.world_to_cam_points(pts)
    np.testing.assert_allclose(pc[..., 2], 2.0, atol=1e-12)
    uv, _ = cam.project(pts)
    np.testing.assert_allclose(uv, cam.pixel_centers(), atol=1e-9)


def test_look_at_points_forward_and_keeps_up_up():
    cam = _camera(eye=(0.0, -4.0, 0.0), target=(0.0, 0.0, 0.0))
    # The target is straight ahead.
    uv, z = cam.project(np.zeros(3))
    np.testing.assert_allclose(uv, [cam.cx, cam.cy], atol=1e-9)
    assert z == pytest.approx(4.0)
    # World +z (up) appears above the centre, i.e. at smaller v.
    uv_up, _ = cam.project(np.array([0.0, 0.0, 0.5]))
    assert uv_up[1] < cam.cy
    np.testing.assert_allclose(cam.center, [0.0, -4.0, 0.0], atol=1e-12)


def test_opengl_roundtrip_and_axes():
    cam = _camera()
    c2w_gl = cam.opengl_c2w()
    # OpenGL camera looks down its -z axis: -z column of c2w is the viewing direction.
    forward_world = -c2w_gl[:3, 2]
    np.testing.assert_allclose(forward_world, cam.R[2], atol=1e-12)
    np.testing.assert_allclose(c2w_gl[:3, 3], cam.center, atol=1e-12)
    back = from_opengl_c2w(c2w_gl, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)
    np.testing.assert_allclose(back.R, cam.R, atol=1e-12)
    np.testing.assert_allclose(back.t, cam.t, atol=1e-12)


def test_scaling_keeps_pixel_centres_consistent():
    cam = _camera()
    half = cam.downscaled(2)
    assert (half.width, half.height) == (80, 60)
    pts = np.random.default_rng(1).normal(size=(20, 3)) * 0.3
    uv_full, _ = cam.project(pts)
    uv_half, _ = half.project(pts)
    # Continuous coordinates scale exactly with the pixel-centre-at-+0.5 convention.
    np.testing.assert_allclose(uv_half, uv_full / 2.0, atol=1e-9)


def test_quaternion_roundtrip_and_known_value():
    # 90 degrees about z: (w, x, y, z) = (cos 45, 0, 0, sin 45)
    q = np.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])
    R = qvec_to_rotmat(q)
    np.testing.assert_allclose(R @ np.array([1.0, 0.0, 0.0]), [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(rotmat_to_qvec(R), q, atol=1e-12)
    rng = np.random.default_rng(2)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        R = qvec_to_rotmat(q)
        np.testing.assert_allclose(qvec_to_rotmat(rotmat_to_qvec(R)), R, atol=1e-10)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(R=np.full((3, 3), np.nan)), "NaN"),
        (dict(R=np.eye(4)), "3x3"),
        (dict(R=np.diag([1.0, 1.0, 2.0])), "rotation"),
        (dict(t=np.zeros(4)), "3 entries"),
        (dict(fx=-1.0), "positive"),
    ],
)
def test_invalid_cameras_are_rejected(kwargs, message):
    args = dict(fx=100.0, fy=100.0, cx=8.0, cy=6.0, width=16, height=12, R=np.eye(3), t=np.zeros(3))
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        Camera(**args)
