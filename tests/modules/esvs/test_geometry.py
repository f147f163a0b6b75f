"""The stereo rig: RASCAL's 10-35 m band is in view, and the frames invert each other."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from modules.esvs.geometry import RASCAL_RIG, StereoRig


def test_rascal_field_of_view_covers_10_to_35_m_of_ground() -> None:
    rig = RASCAL_RIG
    assert rig.focal_px == pytest.approx(871.4, abs=0.5)
    for forward in (10.0, 20.0, 35.0):
        row = rig.ground_row(forward + rig.mount_forward_m)
        assert 0 <= row < rig.height_px
    assert rig.ground_row(10.0) > rig.ground_row(35.0) > rig.horizon_row() > 0
    # A 2 m obstacle at 10 m is still in view up to its top.
    _, top_row, _ = rig.project(np.array([10.0 + rig.mount_forward_m, 0.0, 2.0]))
    assert top_row > 0


def test_frames_round_trip_and_project_consistently() -> None:
    rig = StereoRig(pitch_down_deg=7.5)
    rng = np.random.default_rng(3)
    points = np.column_stack([rng.uniform(8, 40, 50), rng.uniform(-6, 6, 50), rng.uniform(0, 2, 50)])
    np.testing.assert_allclose(rig.camera_to_vehicle(rig.vehicle_to_camera(points)), points, atol=1e-9)
    u_left, v_left, depth = rig.project(points)
    u_right, v_right, _ = rig.project(points, right=True)
    np.testing.assert_allclose(v_left, v_right, atol=1e-9)  # rectified: same rows
    np.testing.assert_allclose(u_left - u_right, rig.disparity_px(depth), rtol=1e-9)


def test_q_matrix_reprojects_to_the_vehicle_point() -> None:
    rig = RASCAL_RIG
    point = np.array([[22.0, -1.5, 0.4]])
    u, v, depth = rig.project(point)
    disparity = np.zeros((rig.height_px, rig.width_px), np.float32)
    row, col = round(float(v[0])), round(float(u[0]))
    disparity[row, col] = rig.disparity_px(depth)[0]
    camera = cv2.reprojectImageTo3D(disparity, rig.q_matrix)[row, col].astype(float)
    back = rig.camera_to_vehicle(camera)
    # Pixel rounding moves the point by at most half a pixel's footprint at 22 m.
    np.testing.assert_allclose(back, point[0], atol=22.0 / rig.focal_px)
