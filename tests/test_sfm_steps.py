"""Issue 13: each step of an SfM path re-measured on the road's image motion (pavemap.sfm.steps)."""

from __future__ import annotations

import numpy as np
import pytest

from pavemap.errors import PavemapError
from pavemap.geometry.triangulate import plane_homography
from pavemap.sfm.steps import StepConfig, StepEstimate, relength_path, road_steps, sweep_step


def test_sweep_finds_the_step_of_a_warped_road_texture():
    import cv2

    rng = np.random.default_rng(0)
    K = np.array([[400.0, 0, 320], [0, 400, 120], [0, 0, 1]])
    img = cv2.GaussianBlur(rng.random((240, 640)).astype(np.float32), (0, 0), 1.2)
    T = np.eye(4)
    T[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]  # camera z forward along world x, y down
    T[:3, 3] = [0.0, 0.0, 1.6]
    fwd, up, h = np.array([1.0, 0, 0]), np.array([0.0, 0, 1]), 1.6
    roi = np.zeros((240, 640), bool)
    roi[140:230, 100:540] = True
    for true in (0.7, 2.3):
        T2 = T.copy()
        T2[:3, 3] += true * fwd
        moved = cv2.warpPerspective(img, plane_homography(K, T, K, T2, up, 0.0), (640, 240))
        e = sweep_step(img, moved, K, T, T[:3, :3], fwd, up, h, roi, None, StepConfig(max_step_m=5.0))
        assert e.trusted and abs(e.length_m - true) < 0.02 * true
    # a texture that does not move with the road (a static bonnet, a wall) gives no trusted step
    e = sweep_step(img, rng.random((240, 640)).astype(np.float32), K, T, T[:3, :3], fwd, up, h, roi, None,
                   StepConfig())
    assert not e.trusted


def _render_ground_and_sky(K: np.ndarray, T: np.ndarray, ground: np.ndarray, sky: np.ndarray,
                           shape: tuple[int, int], cell: float = 0.15) -> np.ndarray:
    """(H, W) float32 view from ``T`` (camera-to-world, z up, road at z = 0) of a textured road (``ground`` cells
    of ``cell`` m from x = -20, y = -30 m) under a textured sky and skyline (``sky`` by azimuth and elevation)."""
    import cv2

    from pavemap.sfm.steps import _pixel_rays

    rays = _pixel_rays(K, shape) @ T[:3, :3].T
    C = T[:3, 3]
    down = -rays[..., 2]
    hit = down > 1e-6
    lam = np.where(hit, C[2] / np.where(hit, down, 1.0), 0.0)
    gx = ((C[0] + lam * rays[..., 0] + 20.0) / cell).astype(np.float32)
    gy = ((C[1] + lam * rays[..., 1] + 30.0) / cell).astype(np.float32)
    road = cv2.remap(ground, gx, gy, cv2.INTER_LINEAR)
    az = np.arctan2(rays[..., 1], rays[..., 0])
    el = np.arctan2(rays[..., 2], np.hypot(rays[..., 0], rays[..., 1]))
    sx = ((az + np.pi) / (2 * np.pi) * (sky.shape[1] - 1)).astype(np.float32)
    sy = ((el + np.pi / 2) / np.pi * (sky.shape[0] - 1)).astype(np.float32)
    return np.where(hit & (lam < 80.0), road, cv2.remap(sky, sx, sy, cv2.INTER_LINEAR)).astype(np.float32)


def test_a_long_step_measured_onto_the_rear_view_ignores_the_road_behind_the_front_camera():
    """A clip numbered backwards (the SfM's 'reverse'; both shared nuScenes clips) sweeps each step onto the rear
    view: the near road it compares lies behind the front camera for a step longer than ~8 m here. Its points
    must not be projected through the camera mirrored onto the front view's buildings and sky (the plane's
    normalised homography did that, and read 12 and 14 m steps as 2.2 m; on clip 1 it read 13 m steps 20 %
    short)."""
    import cv2

    from pavemap.sfm.steps import _pixel_rays, _road_roi

    rng = np.random.default_rng(0)
    ground = cv2.GaussianBlur(rng.random((400, 2000)).astype(np.float32), (0, 0), 1.5)
    sky = cv2.GaussianBlur(rng.random((600, 2400)).astype(np.float32), (0, 0), 1.5)
    K = np.array([[400.0, 0, 320], [0, 400, 120], [0, 0, 1]])
    K3 = K.copy()
    K3[:2] *= 3
    K3[:2, 2] += 1.0  # rendered 3x over and averaged down: a camera integrates its pixels, it does not alias
    R = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])  # camera z forward along world x, y down
    up, fwd, h, cfg = np.array([0.0, 0, 1]), np.array([1.0, 0, 0]), 1.6, StepConfig()
    roi = _road_roi(_pixel_rays(K, (240, 640)), -R.T @ up, h, cfg, None)
    for d in (4.0, 12.0, 14.0):
        rear, front = np.eye(4), np.eye(4)
        rear[:3, :3] = front[:3, :3] = R
        rear[:3, 3], front[:3, 3] = [0.0, 0, h], [d, 0, h]
        rear_img, front_img = (cv2.resize(_render_ground_and_sky(K3, T, ground, sky, (720, 1920)), (640, 240),
                                          interpolation=cv2.INTER_AREA) for T in (rear, front))
        e = sweep_step(front_img, rear_img, K, front, R, -fwd, up, h, roi, None, cfg)  # front -> rear, backwards
        assert e.trusted and abs(e.length_m - d) < 0.01 * d, (d, e.length_m, e.peak)


def test_road_steps_undo_an_sfm_path_with_wrong_step_lengths(tiny_seq):
    cam = next(iter(tiny_seq.cameras.values()))
    views = [f.views[cam.name] for f in tiny_seq.frames]
    T = np.stack([v.T_world_cam for v in views])
    C = T[:, :3, 3]
    d = np.diff(C, axis=0)
    true = np.linalg.norm(d, axis=1)
    # forward-motion SfM's failure: steps alternately 1.6x and 0.6x, the whole path at 0.8 of its scale
    f = np.where(np.arange(len(d)) % 2, 0.6, 1.6) * 0.8
    bad = T.copy()
    bad[1:, :3, 3] = C[0] + np.cumsum(d * f[:, None], axis=0)
    est = road_steps([tiny_seq.root / v.image for v in views], bad, cam, 1.65)  # the kitti-like mount
    ok = np.array([e.trusted for e in est])
    got = np.array([e.length_m for e in est])
    assert ok.sum() >= len(est) - 1
    assert np.max(np.abs(got[ok] / true[ok] - 1)) < 0.08
    fixed, factor = relength_path(bad[:, :3, 3], est)
    path = float(true.sum())
    assert np.linalg.norm(fixed - C, axis=1).max() < 0.03 * path
    assert np.linalg.norm(bad[:, :3, 3] - C, axis=1).max() > 0.1 * path  # the test's path was wrong


def test_relength_keeps_a_path_the_road_could_not_measure_and_interpolates_gaps():
    C = np.c_[np.arange(5.0), np.zeros(5), np.full(5, 1.5)]

    def est(length: float, trusted: bool) -> StepEstimate:
        return StepEstimate(length, 0.5, 0.1, trusted, np.zeros(0), np.zeros(0))

    same, factor = relength_path(C, [est(float("nan"), False)] * 4)
    assert np.array_equal(same, C) and np.all(factor == 1)
    out, factor = relength_path(C, [est(2.0, True), est(9.0, False), est(2.0, True), est(2.0, True)])
    assert np.allclose(np.diff(out[:, 0]), 2.0)  # the unmeasured step takes its neighbours' ratio


def test_relength_smooths_the_roads_noise_along_an_sfm_path_and_keeps_its_own_errors():
    """SfM's scale drifts slowly (the KITTI sample: +22 % over 50 steps) and one road sweep reads a step to a
    few per cent: the median ratio of the neighbouring steps follows the drift with less of the noise. A step
    whose SfM length is far off its neighbours' (a forward-motion failure) takes the road's own reading."""
    true = np.full(30, 5.0)
    sfm = true * np.linspace(1.0, 1.25, 30)
    sfm[12] *= 1.6  # SfM's length of one step is wrong by itself
    C = np.c_[np.r_[0.0, np.cumsum(sfm)], np.zeros(31), np.full(31, 1.5)]
    others = np.arange(30) != 12

    def est(length: float) -> StepEstimate:
        return StepEstimate(length, 0.8, 0.2, True, np.zeros(0), np.zeros(0))

    errors = {"per_step": [], "smooth": []}
    for seed in range(20):
        noise = 1 + 0.04 * np.random.default_rng(seed).standard_normal(30)
        steps = [est(v) for v in true * noise]
        for name, kw in (("per_step", {"window": 0}), ("smooth", {})):
            got = np.diff(relength_path(C, steps, **kw)[0][:, 0])
            errors[name].append(np.median(np.abs(got[others] / 5.0 - 1)))
            assert abs(got[12] - 5.0 * noise[12]) < 1e-9  # the off step: the road's own length
    assert np.mean(errors["smooth"]) < 0.8 * np.mean(errors["per_step"]), errors
    # a step whose length the path only guessed (a repaired skid) takes the road's reading, however close
    guessed = np.zeros(30, bool)
    guessed[20] = True
    fixed, _ = relength_path(C, steps, guessed_length=guessed)
    smooth, _ = relength_path(C, steps)
    assert abs(np.diff(fixed[:, 0])[20] - 5.0 * noise[20]) < 1e-9
    assert abs(np.diff(smooth[:, 0])[20] - 5.0 * noise[20]) > 1e-3


def test_a_step_far_off_its_neighbours_takes_the_road_only_where_the_road_contradicts_them():
    """A step whose road-to-SfM ratio is far off its neighbours' takes the road's own reading only where the road's
    sweep scores the neighbours' length clearly lower than its peak (the SfM's length is wrong there). A sweep
    with a second, near-equal peak at the neighbours' length (clip 1: a plateau read a 5 m step as 14 m) does not
    contradict them, and the step keeps their ratio."""
    sweep = np.linspace(0.5, 20.0, 80)

    def est(length: float, score: np.ndarray | None = None) -> StepEstimate:
        score = np.exp(-0.5 * ((sweep - length) / 0.6) ** 2) * 0.8 if score is None else score
        return StepEstimate(length, float(np.max(score)), 0.2, True, sweep, score)

    C = np.c_[np.r_[0.0, np.cumsum(np.full(10, 5.0))], np.zeros(11), np.full(11, 1.5)]  # SfM: 5 m steps
    two_peaks = 0.8 * np.exp(-0.5 * ((sweep - 14.0) / 0.6) ** 2) + 0.75 * np.exp(-0.5 * ((sweep - 5.0) / 0.6) ** 2)
    for score, want in ((None, 14.0), (two_peaks, 5.0)):
        steps = [est(5.0)] * 10
        steps[5] = est(14.0, score)
        got = np.diff(relength_path(C, steps)[0][:, 0])
        assert abs(got[5] - want) < 1e-6, (want, got[5])
        assert np.allclose(np.delete(got, 5), 5.0)


def test_a_road_without_texture_measures_no_step(tmp_path):
    from PIL import Image

    from pavemap.types import Camera

    cam = Camera("front", 320, 120, np.array([[200.0, 0, 160], [0, 200, 50], [0, 0, 1]]))
    paths = []
    for i in range(3):
        paths.append(tmp_path / f"{i}.png")
        Image.fromarray(np.full((120, 320), 128, np.uint8)).save(paths[-1])
    T = np.tile(np.eye(4), (3, 1, 1))
    T[:, :3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]  # camera z forward along world x, y down
    T[:, :3, 3] = [[i * 1.0, 0, 1.5] for i in range(3)]
    est = road_steps(paths, T, cam, 1.5)
    assert len(est) == 2 and not any(e.trusted for e in est)
    Image.fromarray(np.full((100, 320), 128, np.uint8)).save(paths[1])  # one image of another size
    with pytest.raises(PavemapError, match=r"1\.png: image is not 320x120"):
        road_steps(paths, T, cam, 1.5)
    fixed, _ = relength_path(T[:, :3, 3], est)
    assert np.array_equal(fixed, T[:, :3, 3])


def test_sfm_warns_when_the_road_steps_and_the_ground_points_disagree(monkeypatch, caplog):
    from pavemap.sfm import pipeline as sfm
    from pavemap.sfm import scale as sfm_scale
    from pavemap.types import Camera

    cam = Camera("front", 320, 120, np.array([[200.0, 0, 160], [0, 200, 50], [0, 0, 1]]))
    for factor, warned in ((1.10, True), (1.03, False)):
        res = sfm.SfmResult(np.tile(np.eye(4), (3, 1, 1)), np.ones(3, bool), 1.0, 0, np.zeros((0, 3)), {})
        res.T_world_cam[:, :3, 3] = [[i, 0.0, 1.5] for i in range(3)]
        monkeypatch.setattr(sfm_scale, "refine_scale",
                            lambda *a, f=factor, **k: (f, np.full(3, 1.5 * f), {"ground_points": 100}))
        caplog.clear()
        with caplog.at_level("WARNING", logger="pavemap.sfm.scale"):
            sfm_scale.dense_rescale(res, ["a.png"] * 3, cam, 1.5, None, apply=False)
        assert ("disagree on the scale by +10 %" in caplog.text) is warned
        assert res.info["dense_scale"].get("disagrees", False) is warned
        assert np.allclose(res.T_world_cam[:, 0, 3], [0, 1, 2])  # the road's scale stays
        assert np.allclose(res.T_world_cam[:, 2, 3], 1.5)  # the road at z = 0 under the cameras


def test_road_sideways_sees_a_path_that_drifts_sideways(tiny_seq):
    """The road's check of a path's shape: on the true path every step's sideways offset is 0; a path whose
    steps were swung 0.2 m to one side (an SfM drift the lengths do not show) gets -0.2 m from the road."""
    from pavemap.sfm.steps import road_sideways

    cam = next(iter(tiny_seq.cameras.values()))
    views = [f.views[cam.name] for f in tiny_seq.frames]
    T = np.stack([v.T_world_cam for v in views])
    ims = [tiny_seq.root / v.image for v in views]
    rows = road_sideways(ims, T, cam, 1.65)
    got = np.array([r["best_offset_m"] if r["best_offset_m"] is not None else np.nan for r in rows])
    assert np.isfinite(got).sum() >= len(rows) - 1 and np.nanmax(np.abs(got)) <= 0.05, got
    at_zero_true = np.array([r["at_zero"] for r in rows if r["at_zero"] is not None])
    assert all(r["margin"] > 0.2 for r in rows if r["margin"] is not None)  # a clear peak, not a plateau
    d = np.diff(T[:, :3, 3], axis=0)
    side = np.cross([0.0, 0.0, 1.0], d / np.linalg.norm(d, axis=1, keepdims=True))  # left of the travel
    swung = T.copy()
    swung[1:, :3, 3] = T[0, :3, 3] + np.cumsum(d + 0.2 * side, axis=0)  # each step 0.2 m to the left
    rows = road_sideways(ims, swung, cam, 1.65)
    got = np.array([r["best_offset_m"] if r["best_offset_m"] is not None else np.nan for r in rows])
    assert np.isfinite(got).sum() >= len(rows) - 1 and np.nanmax(np.abs(got + 0.2)) <= 0.06, got
    # the swung path's own positions match the road far worse than the true path's did
    at_zero_swung = np.array([r["at_zero"] for r in rows if r["at_zero"] is not None])
    assert len(at_zero_swung) == len(at_zero_true) and np.all(at_zero_swung < at_zero_true - 0.2)
