"""The planar motion's body attitude: each step's roll and pitch change fitted with its yaw, and the world's up
taken from the axis the car turned about (issue 42)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pavemap.sfm.attitude import road_up, step_rotation, unit_path
from pavemap.sfm.planar import PlanarConfig, pair_attitude, pair_yaw


def _step_bearings(R_rel: np.ndarray, t: np.ndarray, seed: int = 3, noise_px: float = 0.3):
    """Matched unit bearings (M, 3) of points ahead of a car that moves by ``t`` (3,) and turns its body by
    ``R_rel`` (3, 3) (the later body's axes in the earlier's), 0.3 px of noise at f = 1000 px."""
    rng = np.random.default_rng(seed)
    X = np.c_[rng.uniform(5, 40, 300), rng.uniform(-15, 15, 300), rng.uniform(-1.5, 6, 300)]
    X2 = (X - t) @ R_rel  # in the later body: R_rel^T (X - t)
    b1 = X / np.linalg.norm(X, axis=1, keepdims=True)
    b2 = X2 / np.linalg.norm(X2, axis=1, keepdims=True) + rng.normal(0, noise_px / 1000, X2.shape)
    return b1, b2 / np.linalg.norm(b2, axis=1, keepdims=True)


def _angle_deg(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(Rotation.from_matrix(A.T @ B).as_rotvec())))


@pytest.mark.parametrize(("yaw", "roll", "pitch"), [(5.0, 0.8, -0.5), (-12.0, -1.2, 0.4), (0.5, 0.6, 0.6)])
def test_a_step_that_rolls_and_pitches_is_fitted_in_three_angles(yaw, roll, pitch):
    """The 1D yaw search turns the car about its up axis only, so a body that rolls and pitches on its springs
    leaves it a degree off; the three-angle fit recovers the rotation to a few hundredths of a degree."""
    R_true = step_rotation(*np.radians([yaw, roll, pitch]))
    th = np.radians(yaw)
    b1, b2 = _step_bearings(R_true, 3.0 * np.array([np.cos(th / 2), np.sin(th / 2), 0.0]))
    m = pair_yaw(b1, b2, PlanarConfig(), 1000.0)
    fitted = pair_attitude(b1, b2, m, PlanarConfig(), 1000.0)
    err_1d = _angle_deg(step_rotation(m.yaw), R_true)
    err_3 = _angle_deg(step_rotation(fitted.yaw, fitted.roll, fitted.pitch), R_true)
    assert err_3 < 0.05 and err_1d > 0.5
    assert np.degrees([fitted.roll, fitted.pitch]) == pytest.approx([roll, pitch], abs=0.05)
    assert fitted.sign == m.sign == 1 and fitted.inliers == m.inliers


def test_a_step_without_enough_matches_keeps_its_1d_reading():
    m = pair_yaw(np.zeros((5, 3)), np.zeros((5, 3)), PlanarConfig(), 1000.0)
    assert pair_attitude(np.zeros((5, 3)), np.zeros((5, 3)), m, PlanarConfig(), 1000.0) is m


def test_the_world_up_is_the_axis_the_car_turned_about():
    """A car whose mount's up is tilted 3 deg from the road's normal turns 90 deg about the normal: in the mount's
    body frame each step rolls and pitches a little. The path's world up is the normal (not the bodies' mean up,
    which the tilt times the turn would carry 3 deg off), so every camera keeps one tilt to it and the path stays
    level."""
    tilt = Rotation.from_rotvec(np.radians([2.0, -2.2, 0.0])).as_matrix()  # body <- road frame
    n_body = tilt @ np.array([0.0, 0.0, 1.0])  # the road's normal in the body
    turns = np.radians(np.r_[np.zeros(4), np.full(6, 15.0), np.zeros(4)])
    rel = np.stack([Rotation.from_rotvec(n_body * a).as_matrix() for a in turns])
    eul = Rotation.from_matrix(rel).as_euler("ZXY")  # yaw about z, then roll about x, pitch about y
    np.testing.assert_allclose(step_rotation(eul[:, 0], eul[:, 1], eul[:, 2]), rel, atol=1e-9)
    T = unit_path(eul[:, 0], np.eye(3), False, eul[:, 1], eul[:, 2])
    body_up_world = T[:, :3, 2]  # R_cm = I: the camera is the body here
    angle_to_z = np.degrees(np.arccos(np.clip(body_up_world[:, 2], -1, 1)))
    # within a quarter degree: the bodies' mean up weighs in as one 10 deg turn against these six 15 deg ones
    assert np.ptp(angle_to_z) < 0.1 and angle_to_z.mean() == pytest.approx(np.degrees(np.arccos(n_body[2])),
                                                                            abs=0.25)
    # the chord is horizontal in the tilted body, so the path climbs by the tilt: but evenly, not with the turn
    up = road_up(np.stack([np.eye(3)] * (len(turns) + 1)), rel, eul[:, 0])
    assert np.degrees(np.arccos(up @ n_body)) < 0.25
    mean_up = rel[0] @ np.array([0.0, 0.0, 1.0])  # the bodies' own up: 3 deg off
    assert np.degrees(np.arccos(mean_up @ n_body)) > 2.5


def test_a_straight_drive_keeps_the_bodies_mean_up():
    """No turn: nothing to take the up from, so the spring's roll and pitch noise must not tilt the world."""
    rng = np.random.default_rng(0)
    roll, pitch = np.radians(rng.normal(0, 0.3, (2, 19)))
    yaw = np.radians(rng.normal(0, 0.05, 19))
    T = unit_path(yaw, np.eye(3), False, roll, pitch)
    mean_up = T[:, :3, 2].mean(0)
    assert np.degrees(np.arccos(mean_up[2] / np.linalg.norm(mean_up))) < 0.3
