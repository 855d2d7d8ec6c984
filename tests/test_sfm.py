"""Poses from plain images with pycolmap SfM, metric scale from the camera mounting height."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("pycolmap")

from pavemap.errors import PavemapError  # noqa: E402
from pavemap.ingest.folder import import_folder  # noqa: E402
from pavemap.io.sequence import read_sequence  # noqa: E402
from pavemap.sfm.pipeline import sfm_poses  # noqa: E402

MOUNT_HEIGHT = 1.65  # the kitti-like rig's camera height above the road (synth/rig.py)


def _rigid_align_error(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Per-frame position error after the best rotation + translation (no scale: scale is under test)."""
    ce, cg = est.mean(0), gt.mean(0)
    U, _, Vt = np.linalg.svd((gt - cg).T @ (est - ce))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    return np.linalg.norm((est - ce) @ R.T + cg - gt, axis=1)


@pytest.mark.slow
def test_sfm_trajectory_on_synthetic_kitti_drive(tmp_path):
    from pavemap.synth import synthesize

    truth = synthesize(tmp_path / "truth", preset="kitti-like", seed=0, frames=30, scale=0.5, depth="none",
                       progress=False)
    cam = truth.cameras["CAM_FRONT"]
    (tmp_path / "cameras.json").write_text(json.dumps(
        {"cameras": {"CAM_FRONT": {"width": cam.width, "height": cam.height, "K": cam.K.tolist()}}}))
    fps = 1.0 / (truth.frames[1].timestamp - truth.frames[0].timestamp)  # the speed check runs and passes
    seq = import_folder(tmp_path / "truth" / "images" / "CAM_FRONT", tmp_path / "cameras.json", "sfm",
                        tmp_path / "seq", camera_height=MOUNT_HEIGHT, fps=fps)
    s = read_sequence(tmp_path / "seq")
    assert len(s.frames) == len(truth.frames)  # every frame registered
    assert s.frames[3].timestamp == pytest.approx(3 / fps)
    est = np.stack([f.views["CAM_FRONT"].T_world_cam[:3, 3] for f in s.frames])
    gt = np.stack([f.views["CAM_FRONT"].T_world_cam[:3, 3] for f in truth.frames])
    path = float(np.linalg.norm(np.diff(gt, axis=0), axis=1).sum())
    err = _rigid_align_error(est, gt)
    rmse_pct = 100 * float(np.sqrt((err**2).mean())) / path
    scale_ratio = float(np.linalg.norm(np.diff(est, axis=0), axis=1).sum()) / path
    print(f"\nSfM trajectory: RMSE {rmse_pct:.2f} % of {path:.1f} m path, max {err.max():.3f} m, "
          f"path-length ratio {scale_ratio:.4f}")
    assert rmse_pct <= 2.0
    assert abs(scale_ratio - 1) < 0.05
    # z-up metric world with the road at z ~ 0: cameras at the mounting height, looking forward
    assert np.all(np.abs(est[:, 2] - MOUNT_HEIGHT) < 0.2)
    R0 = s.frames[0].views["CAM_FRONT"].T_world_cam[:3, :3]
    assert R0[2, 1] < -0.98  # camera y (down) is world -z
    assert seq.frames[-1].views["CAM_FRONT"].T_world_cam[0, 3] > 20  # drove ~29 m along +x
    # what SfM measured travels with the sequence: each step by SfM and by the road, the checks' figures
    report = json.loads((tmp_path / "seq" / "sfm.json").read_text())
    assert report["checks"]["max_accel_mps2"] is not None  # the frame times reached the speed check
    road = report["road_steps"]["road_m"]
    assert len(road) == len(truth.frames) - 1 and sum(r is not None for r in road) >= 0.8 * len(road)
    # the report describes the poses written: the saved path's steps, the road's reading where it was taken
    saved = np.linalg.norm(np.diff(est, axis=0), axis=1)
    assert np.allclose(saved, report["road_steps"]["path_m"], atol=0.006)
    own = np.array(report["road_steps"]["own_reading"])
    assert np.allclose(saved[own], np.array(road, dtype=float)[own], atol=0.006)
    # COLMAP's path: most steps take their measured neighbours' ratio, not their own noisy reading
    assert own.sum() < 0.5 * len(own)


def test_sfm_rejects_too_few_images(tmp_path):
    from pavemap.types import Camera

    cam = Camera("c", 32, 24, np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]]))
    with pytest.raises(PavemapError, match="at least 3 images"):
        sfm_poses([tmp_path / "a.png", tmp_path / "b.png"], cam)
    with pytest.raises(PavemapError, match="camera height must be positive"):
        sfm_poses([tmp_path / f"{i}.png" for i in range(3)], cam, camera_height=0)
    with pytest.raises(PavemapError, match="2 frame times for 3 images"):  # before any SfM work
        sfm_poses([tmp_path / f"{i}.png" for i in range(3)], cam, times=np.zeros(2))


def _checked(C: np.ndarray, times: np.ndarray | None, nominal: bool = False) -> dict:
    from pavemap.sfm.checks import SfmChecks, check_sfm

    info = {"registered": len(C), "keyframes": len(C), "reproj_px": 0.5}
    return check_sfm(info, C, np.full(len(C), 1.5), SfmChecks(nominal_times=nominal), times=times)


def test_speed_check_passes_a_car_and_stops_a_jumping_path():
    rng = np.random.default_rng(0)
    t = np.arange(21) * 0.5  # nuScenes keyframes: 2 Hz
    v = np.clip(9.0 - 1.5 * t, 2.0, None)  # braking at 1.5 m/s^2, then crawling
    C = np.zeros((21, 3))
    C[1:, 0] = np.cumsum(v[:-1] * 0.5)
    f = _checked(C + rng.normal(0, 0.1, C.shape), t)  # SfM-sized position noise
    assert f["max_accel_mps2"] < 3.0
    # the step lengths SfM gave on the shared nuScenes clip (bench/results/sfm.json): 9 m, then 17 / 7.5 / 17 m
    # half a second apart, then 5 cm: 20 m/s^2, no car's
    steps = [9.32, 9.23, 9.29, 9.2, 17.05, 7.48, 17.13, 2.59, 1.8, 1.81, 0.05, 0.05, 0.34, 0.97, 11.92, 4.21, 11.68,
             6.08, 5.71, 5.04]
    J = np.zeros((21, 3))
    J[1:, 0] = np.cumsum(steps)
    with pytest.raises(PavemapError, match=r"speed changes by \d+\.\d m/s within one second .*not a car's"):
        _checked(J, t)
    # without frame times nothing is claimed about speed (the step-ratio check alone: 6.6 < 10 passes it)
    assert _checked(J, None)["max_accel_mps2"] is None
    # an image folder's --fps is a claim (irregular keyframes): the same path is reported and warned, not refused
    f = _checked(J, t, nominal=True)
    assert f["max_accel_mps2"] > 10 and f["frame_times"] == "nominal" and "not refused" in f["accel_unchecked"]
    assert "accel_unchecked" not in _checked(C, t) and _checked(C, t)["frame_times"] == "measured"


def test_a_jump_the_road_measured_at_both_steps_is_reported_not_refused():
    """The step-ratio check guards against an SfM scale jump. Clips 1 + 2 joined (as numbered): the road read a
    13.0 m step (a keyframe missing from the copy) and then 1.2 m as the car braked, 10.8x apart. Both are the
    road's own readings, so the path is kept and the jump is reported; the same path with SfM's lengths there
    is refused. (Here 17.0 then 1.6 m: with 5 m steps around them a 1.2 m step counts as a stop.)"""
    from pavemap.sfm.checks import SfmChecks, check_sfm

    steps = [5.2, 5.4, 5.2, 17.0, 1.6, 2.2, 3.3, 4.3, 5.4, 5.0]
    C = np.zeros((11, 3))
    C[1:, 0] = np.cumsum(steps)
    own = [False, False, False, True, True, False, False, False, False, False]
    info = {"registered": 11, "keyframes": 11, "reproj_px": 0.5, "road_steps": {"own_reading": own}}
    f = check_sfm(info, C, np.full(11, 1.5), SfmChecks())
    assert f["max_step_ratio"] > 10 and "not refused" in f["step_ratio_unchecked"]
    info["road_steps"]["own_reading"] = [False] * 10
    with pytest.raises(PavemapError, match="the trajectory jumps"):
        check_sfm(info, C, np.full(11, 1.5), SfmChecks())


def test_fps_must_be_positive(tmp_path):
    cam = {"width": 32, "height": 24, "K": [[30, 0, 16], [0, 30, 12], [0, 0, 1]]}
    (tmp_path / "cameras.json").write_text(json.dumps({"cameras": {"c": cam}}))
    (tmp_path / "img").mkdir()
    from PIL import Image

    Image.new("RGB", (32, 24)).save(tmp_path / "img" / "000000.png")
    for bad in (0, -2.0, float("inf"), float("nan")):  # inf would put every frame at t = 0
        with pytest.raises(PavemapError, match="--fps must be a positive"):
            import_folder(tmp_path / "img", tmp_path / "cameras.json", "sfm", tmp_path / "seq", fps=bad)


def _road_under_path(rng: np.random.Generator, n: int = 3000, length: float = 80.0, grade: float = 0.02,
                     fall: float = 0.08) -> tuple[np.ndarray, np.ndarray]:
    """A road along x with a grade and a cross-fall (z falls to the right, -y: a turn's superelevation), its
    points (n, 3) 3.5 m to the right of the path to 0.8 m to its left (the camera sees more of one side), 1 cm
    of noise, and the road's (grade, cross-fall)."""
    x = rng.uniform(0.0, length, n)
    y = rng.uniform(-3.5, 0.8, n)
    z = grade * x + fall * y + rng.normal(0.0, 0.01, n)
    return np.c_[x, y, z], np.array([grade, fall])


def test_camera_heights_follow_the_path_over_a_graded_cambered_road():
    from pavemap.geometry.road_height import camera_heights

    rng = np.random.default_rng(4)
    P, (grade, _) = _road_under_path(rng)
    x = np.arange(0.0, 81.0, 7.5)  # 2 Hz keyframes
    C = np.c_[x, np.zeros_like(x), grade * x + 1.5]
    # a parked car's sill 1.9 m to the right, 0.35 m over the road, on one stretch only; no road past 62 m
    car = np.c_[rng.uniform(30, 36, 40), rng.uniform(-2.1, -1.8, 40), np.zeros(40)]
    car[:, 2] = grade * car[:, 0] + 0.08 * car[:, 1] + 0.35
    P = np.r_[P[P[:, 0] < 62.0], car]
    h = camera_heights(P, C, np.array([0.0, 0.0, 1.0]))
    seen = np.isfinite(h)
    assert seen[:-1].all() and not seen[-1]  # the last camera, 13 m past the last road point: not measured
    np.testing.assert_allclose(h[seen], 1.5, atol=0.01)
    # the same road under a path whose scale drifts: the camera climbs 0.3 m over the road along it
    drift = C.copy()
    drift[:, 2] += 0.3 * x / x[-1]
    h2 = camera_heights(P, drift, np.array([0.0, 0.0, 1.0]))
    # each height averages the path's height over the road ±8 m along it: the drift shows, smoothed that much
    np.testing.assert_allclose(h2[seen], 1.5 + 0.3 * x[seen] / x[-1], atol=0.03)
    assert np.ptp(h2[seen]) > 0.2
    # a camera without a pose is not measured, and the others still are
    C[0] = np.nan
    h3 = camera_heights(P, C, np.array([0.0, 0.0, 1.0]))
    assert np.isnan(h3[0]) and np.isfinite(h3[1:-1]).all()


def test_chainage_of_a_long_route_equals_the_exhaustive_projection():
    from pavemap.geometry.chainage import chainage, cumulative_length, route_polyline

    rng = np.random.default_rng(2)
    th = np.cumsum(rng.normal(0.0, 0.08, 300))
    xy = np.c_[np.cumsum(np.cos(th)), np.cumsum(np.sin(th))]
    route = route_polyline(np.r_[xy, xy[::-1] + [0.0, 0.3]])  # there and back, 0.3 m apart: two passes
    pts = xy[rng.integers(0, len(xy), 2000)] + rng.normal(0.0, 4.0, (2000, 2))
    s, o = chainage(route, pts)
    a, d = route[:-1], np.diff(route, axis=0)
    t = np.clip(((pts[:, None] - a) * d).sum(-1) / (d * d).sum(-1), 0.0, 1.0)
    dist = np.linalg.norm(pts[:, None] - (a + t[..., None] * d), axis=-1)
    k = dist.argmin(1)
    np.testing.assert_allclose(np.abs(o), dist.min(1), atol=1e-9)
    np.testing.assert_allclose(s, cumulative_length(route)[k] + t[np.arange(len(k)), k] * np.linalg.norm(d[k], axis=1),
                               atol=1e-9)
