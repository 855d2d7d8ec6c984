"""Ground points triangulated from images with fixed poses, the camera height they give, the surface check."""

from __future__ import annotations

import copy
import dataclasses
import json

import numpy as np
import pytest

from pavemap.geometry.grid import GridSpec
from pavemap.geometry.triangulate import check_residuals, sample_grid, triangulate_tracks
from pavemap.io.sequence import read_sequence
from pavemap.mesh.geometry import check_surface, depth_image
from pavemap.mesh.ground_points import (
    GroundConfig,
    estimate_camera_height,
    find_ground_points,
)


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """A small no-depth front-camera drive (12 frames at 10 Hz, half resolution) and its truth."""
    from pavemap.synth import synthesize

    root = tmp_path_factory.mktemp("ground") / "kitti"
    synthesize(root, "kitti-like", seed=5, frames=12, scale=0.5, depth="none", progress=False)
    seq = read_sequence(root)
    grid = GridSpec.from_dict(json.loads((root / "truth" / "height.json").read_text()))
    heights = np.load(root / "truth" / "height.npy").astype(np.float64)
    return seq, grid, heights


@pytest.fixture(scope="module")
def points(drive):
    return find_ground_points(drive[0])


def _true_height(seq, grid, heights) -> float:
    C = np.array([f.views["CAM_FRONT"].T_world_cam[:3, 3] for f in seq.frames])
    return float(np.median(C[:, 2] - sample_grid(grid, heights, C[:, :2])))


def test_ground_points_match_the_truth(drive, points):
    seq, grid, heights = drive
    assert points.observable and len(points) >= 200
    err = points.points[:, 2] - sample_grid(grid, heights, points.points[:, :2])
    assert abs(np.nanmedian(err)) <= 0.015
    assert points.obs_depth.min() > 0 and (points.n_views >= 2).all()
    # observations feed a depth layer: the depth at an observation's pixel is that observation's depth
    cam = seq.cameras["CAM_FRONT"]
    dep = depth_image(points, int(points.obs_view[0]), cam.width, cam.height)
    u, v = np.rint(points.obs_uv[0]).astype(int)
    assert dep[v, u] > 0 and (dep > 0).sum() >= 20


@pytest.mark.parametrize("prior", [1.5, 2.0])
def test_camera_height_within_2cm_whatever_the_prior(drive, points, prior):
    seq, grid, heights = drive
    gp = points if prior == 1.5 else find_ground_points(seq, GroundConfig(prior_height=prior))
    est = estimate_camera_height(seq, gp)["CAM_FRONT"]
    assert est.observable
    assert abs(est.median - _true_height(seq, grid, heights)) <= 0.02
    assert est.spread < 0.05


def test_surface_check_flags_a_shifted_surface(drive, points):
    _, grid, heights = drive
    good = check_surface(points, grid, heights)
    assert not good.flagged and abs(good.median) < 0.01
    bad = check_surface(points, grid, heights, offset=0.3)
    assert bad.flagged and "off" in bad.reason and bad.median == pytest.approx(-0.3, abs=0.02)


def test_a_single_frame_is_not_observable(drive):
    seq = copy.copy(drive[0])
    seq.frames = seq.frames[:1]
    gp = find_ground_points(seq)
    assert not gp.observable and len(gp) == 0 and "not observable" in gp.reason
    est = estimate_camera_height(seq, gp)["CAM_FRONT"]
    assert not est.observable and np.isnan(est.median)
    assert check_surface(gp, drive[1], drive[2]).flagged


def test_a_stationary_vehicle_is_not_observable(drive):
    seq = copy.deepcopy(drive[0])
    T0 = seq.frames[0].views["CAM_FRONT"].T_world_cam
    for f in seq.frames[:4]:
        f.views["CAM_FRONT"].T_world_cam = T0.copy()
    seq.frames = seq.frames[:4]
    gp = find_ground_points(seq)
    assert not gp.observable


def test_uniform_grey_road_is_not_observable(drive, tmp_path):
    from PIL import Image

    seq = copy.deepcopy(drive[0])
    seq.frames, seq.root = seq.frames[:4], tmp_path
    cam = seq.cameras["CAM_FRONT"]
    for f in seq.frames:
        v = f.views["CAM_FRONT"]
        (tmp_path / v.image).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.full((cam.height, cam.width, 3), 128, np.uint8)).save(tmp_path / v.image)
        v.semantics = None
    gp = find_ground_points(seq)
    assert not gp.observable and "texture" in gp.reason


def test_triangulation_rejects_mismatches_and_low_parallax():
    rng = np.random.default_rng(0)
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    # two cameras 1 m apart looking along +x (OpenCV axes: x right = -y world, y down = -z world)
    R = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    T = np.stack([np.eye(4)] * 3)
    for k, x in enumerate((0.0, 1.0, 2.0)):
        T[k, :3, :3], T[k, :3, 3] = R, (x, 0, 1.5)
    X = np.c_[rng.uniform(6, 15, 50), rng.uniform(-3, 3, 50), np.zeros(50)]
    X[:2] = (6.0, 2.0, 0.0)  # near, off to the side: parallax well above the 1 degree minimum
    pc = np.einsum("vji,nvj->nvi", T[:, :3, :3], X[:, None] - T[None, :, :3, 3])
    uv = (pc @ K.T)[..., :2] / pc[..., 2:3] + rng.normal(0, 0.05, (50, 3, 2))
    uv[0, 2] += (0.0, 8.0)  # one bad observation: dropped, the track keeps its other two views
    uv[1, 1:] += ((0.0, 8.0), (-6.0, -5.0))  # two bad of three: no two views agree
    track = np.repeat(np.arange(50), 3)
    Ks, Ts = np.tile(K, (150, 1, 1)), np.tile(T, (50, 1, 1))
    tri = triangulate_tracks(Ks, Ts, uv.reshape(-1, 2), track, 50)
    assert tri.ok[0] and tri.n_views[0] == 2 and not tri.used[2]
    assert not tri.ok[1]
    good = tri.ok.copy()
    good[:2] = False
    # forward motion: depth is the weak direction (0.05 px noise ~ 1 % at 15 m), height is not
    assert np.abs(tri.points[good, 2] - X[good, 2]).max() < 0.02
    assert (np.linalg.norm(tri.points[good] - X[good], axis=1) < 0.02 * X[good, 0]).all()
    far = triangulate_tracks(Ks, Ts, uv.reshape(-1, 2), track, 50, min_angle_deg=30.0)
    assert not far.ok.any()


def test_check_residuals_thresholds():
    r = np.random.default_rng(1).normal(0.0, 0.01, 500)
    assert not check_residuals(r).flagged
    assert check_residuals(r + 0.08).flagged
    assert check_residuals(np.random.default_rng(2).normal(0.0, 0.3, 500)).flagged
    assert check_residuals(r[:5]).flagged
    # a part of the surface metres off: median and MAD of the rest look fine, the p90 does not (KITTI-00 segment)
    gross = np.concatenate([r[:330], np.random.default_rng(3).uniform(0.3, 6.0, 170)])
    c = check_residuals(gross)
    assert abs(c.median) < 0.05 and c.robust_rms < 0.10 and c.flagged and "grossly wrong" in c.reason
    assert not check_residuals(np.concatenate([r[:470], np.full(30, 2.0)])).flagged  # 6 % stray points pass


def test_range_mask_is_the_per_pixel_ray_test():
    """The broadcast mask equals the ray-by-ray definition: below the horizon margin, on the prior plane
    within [min_range, max_range] (skewed intrinsics, tilted and rolled cameras, one looking up)."""
    from scipy.spatial.transform import Rotation

    from pavemap.geometry.range_mask import range_mask_numpy
    from pavemap.mesh.ground_points import _range_mask
    from pavemap.types import Camera

    cam = Camera("c", 64, 40, np.array([[50.0, 0.7, 31.0], [0.0, 48.0, 19.5], [0.0, 0.0, 1.0]]))
    cfg = GroundConfig(max_range=12.0, far_range=25.0)  # ranges that this small image's rows resolve
    v, u = np.mgrid[0:40, 0:64]
    rays = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3).astype(float) @ np.linalg.inv(cam.K).T
    forward = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float).T  # camera z along world x
    rng = np.random.default_rng(3)
    seen = 0
    for pitch in (0.0, 0.2, -0.4, -1.2):  # -1.2: mostly sky
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("xyz", [rng.normal(0, 0.05), pitch, rng.normal(0, 2)]).as_matrix() @ forward
        d = rays @ T[:3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        below = d[:, 2] < -np.sin(np.radians(cfg.horizon_margin_deg))
        with np.errstate(divide="ignore", invalid="ignore"):
            ground = cfg.prior_height / -d[:, 2] * np.linalg.norm(d[:, :2], axis=1)
        want = (below & (ground >= cfg.min_range) & (ground <= cfg.max_range)).reshape(40, 64)
        got = _range_mask(cam, T, cfg)  # the compiled kernel
        ref = range_mask_numpy(cam.K, T[:3, :3], (40, 64), cfg.prior_height, cfg.horizon_margin_deg,
                               cfg.min_range, cfg.max_range)
        assert got.shape == (40, 64) and got.dtype == bool
        assert np.array_equal(got, want), int((got != want).sum())
        assert np.array_equal(ref, want), int((ref != want).sum())
        # the far pass: its own horizon margin and range
        below = d[:, 2] < -np.sin(np.radians(cfg.far_horizon_deg))
        far = (below & (ground >= 0.8 * cfg.max_range) & (ground <= cfg.far_range)).reshape(40, 64)
        assert np.array_equal(_range_mask(cam, T, cfg, far=True), far)
        seen += int(want.sum())
    assert 0 < seen < 4 * 64 * 40


def test_compiled_sweep_score_equals_the_numpy_reference(drive, monkeypatch):
    """The numba NCC kernel (pavemap.geometry.patch_ncc) scores every hypothesis of a real view pair like the
    numpy reference (float64 and exact bilinear weights against float32 and cv2's 1/32 px positions), and the
    ground points found with either are the same points."""
    import cv2

    from pavemap.geometry import patch_ncc
    from pavemap.mesh.ground_points import _load
    from pavemap.mesh.ground_sweep import Sweep, ViewData

    assert patch_ncc.available(), "numba is a dependency of the package (pyproject.toml)"
    monkeypatch.delenv("PAVEMAP_NCC", raising=False)  # the compiled kernel, not the reference, is under test
    calls = []
    real_reference = patch_ncc.sweep_scores_numpy
    monkeypatch.setattr(patch_ncc, "sweep_scores_numpy", lambda *a: calls.append(1) or real_reference(*a))
    seq = drive[0]
    cfg = GroundConfig()
    luts = (seq.class_lut("ground") & ~seq.class_lut("movable"), seq.class_lut("road"))
    vds = []
    for pos in (0, 1):
        v = seq.frames[pos].views["CAM_FRONT"]
        vd = ViewData((seq.frames[pos].index, "CAM_FRONT"), pos, seq.cameras["CAM_FRONT"], v.T_world_cam)
        _load(seq, vd, v, cfg, *luts)
        vds.append(vd)
    corners = cv2.goodFeaturesToTrack(vds[0].grey, 200, cfg.quality, cfg.min_distance,
                                      mask=vds[0].mask.astype(np.uint8)).reshape(-1, 2).astype(np.float64)
    sw = Sweep(vds[0], vds[1], corners, cfg)
    rows = np.arange(len(corners))
    tau = np.broadcast_to(np.linspace(-cfg.sweep_range, cfg.sweep_range, 60), (len(rows), 60))
    for sparse in (True, False):
        got = sw.score(tau, rows, sparse)
        assert not calls  # the kernel scored, not the reference
        want = sw.score(tau, rows, sparse, reference=True)
        assert calls  # ... and this is the reference
        calls.clear()
        both = (got > -1) & (want > -1)
        assert both.mean() > 0.5 and ((got > -1) == (want > -1)).mean() > 0.999
        assert np.abs(got - want)[both].max() < 0.02, np.abs(got - want)[both].max()
        peaked = want.max(1) >= cfg.min_ncc  # where the reference has a match, both put it at the same place
        assert peaked.sum() > 20
        assert (np.abs(got.argmax(1) - want.argmax(1))[peaked] <= 1).mean() > 0.97
    a = find_ground_points(seq)
    monkeypatch.setenv("PAVEMAP_NCC", "numpy")
    b = find_ground_points(seq)
    assert abs(len(a) - len(b)) <= 0.03 * len(b)
    assert abs(np.median(a.points[:, 2]) - np.median(b.points[:, 2])) < 0.002


def test_a_drive_numbered_backwards_gives_the_same_ground_points(drive, points):
    """Each view pair is matched once, from the view whose ground the other sees more of, so the frames in
    reverse order (a clip numbered backwards, as both shared nuScenes clips) give the same points and camera
    height; matching from the earlier view of each pair gave about half as many going forwards."""
    seq = drive[0]
    back = find_ground_points(dataclasses.replace(seq, frames=seq.frames[::-1]))
    assert abs(len(back) / len(points) - 1) < 0.05, (len(back), len(points))
    h = {n: e.median for n, e in estimate_camera_height(seq, points).items()}
    hb = {n: e.median for n, e in estimate_camera_height(seq, back).items()}
    assert h.keys() == hb.keys() and all(abs(h[n] - hb[n]) < 0.002 for n in h), (h, hb)


def test_far_pass_observes_the_road_beyond_the_last_frame(drive, points):
    """The far pass adds points on the road ahead of the drive's end, beyond the near pass's reach, three views
    each and on the true surface (its planes follow the road's grade); it changes nothing elsewhere (its points
    are kept beyond the ends only)."""
    from pavemap.mesh.init_surface import travel_direction

    seq, grid, heights = drive
    near = find_ground_points(seq, GroundConfig(far_range=0.0))
    traj = seq.trajectory()[:, :2]
    out = travel_direction(traj, -1)

    def ahead(p):
        return (p.points[:, :2] - traj[-1]) @ out

    assert points.stats["far_pairs"] > 0 and near.stats["far_pairs"] == 0
    beyond = ahead(points) > ahead(near).max()
    # (the near pass matches each pair from the view ahead, so its points reach 20 m past the end here, 18 m when
    # it matched from the view behind, and fewer of the far pass's lie beyond them: 9 of its points, 19 before)
    assert beyond.sum() >= 5, beyond.sum()
    assert ahead(points).max() >= ahead(near).max() + 5.0
    err = points.points[beyond, 2] - sample_grid(grid, heights, points.points[beyond, :2])
    # on the grade of the road: level sweep planes put these points 5 cm low (their median: -5.1 cm)
    assert abs(np.nanmedian(err)) <= 0.025 and (points.n_views[beyond] >= 3).all()
    # behind the end, the points are the near pass's
    mine = {tuple(np.round(p, 6)) for p in points.points[ahead(points) <= 0]}
    theirs = {tuple(np.round(p, 6)) for p in near.points[ahead(near) <= 0]}
    assert len(mine ^ theirs) <= 0.02 * len(theirs)


def test_corners_in_the_mask_rows_are_the_full_images(drive):
    """Corners found in the rows the mask spans are those of the whole image (the far mask is a thin band)."""
    import cv2

    from pavemap.mesh.ground_points import _corners, _load
    from pavemap.mesh.ground_sweep import ViewData

    seq = drive[0]
    cfg = GroundConfig()
    v = seq.frames[3].views["CAM_FRONT"]
    vd = ViewData((3, "CAM_FRONT"), 3, seq.cameras["CAM_FRONT"], v.T_world_cam)
    _load(seq, vd, v, cfg, seq.class_lut("ground"), seq.class_lut("road"), far=True)
    for mask in (vd.mask, vd.far_mask):
        assert mask.any(1).sum() < 0.9 * len(mask)  # the crop is a real one
        full = cv2.goodFeaturesToTrack(vd.grey, 150, cfg.quality, cfg.min_distance, mask=mask.astype(np.uint8))
        got = _corners(vd.grey, mask, 150, cfg)
        assert got is not None and len(got) == len(full) > 10
        assert np.array_equal(np.sort(got.view("f8,f8"), axis=0), np.sort(full.reshape(-1, 2).astype(np.float64)
                                                                          .view("f8,f8"), axis=0))
    assert _corners(vd.grey, np.zeros_like(vd.mask), 150, cfg) is None


def test_a_point_the_other_views_contradict_is_dropped_as_moving(drive):
    """The static road matched a -> b scores in a third view c at the depth found; the same corners against a
    c whose content moved (25 px down, 40 px across, as a vehicle's flank moves between frames) are contradicted."""
    from pavemap.mesh.ground_points import _corners, _load
    from pavemap.mesh.ground_sweep import Patches, ViewData, contradicted, sweep_match

    seq = drive[0]
    cfg = GroundConfig()
    luts = (seq.class_lut("ground") & ~seq.class_lut("movable"), seq.class_lut("road"))
    vds = []
    for pos, f in enumerate(seq.frames[4:7]):
        v = f.views["CAM_FRONT"]
        vd = ViewData((f.index, "CAM_FRONT"), pos, seq.cameras["CAM_FRONT"].scaled(cfg.scale), v.T_world_cam)
        _load(seq, vd, v, cfg, *luts)
        vds.append(vd)
    a, b, c = vds
    corners = _corners(a.grey, a.mask, cfg.max_corners, cfg)
    patches = Patches(a, corners, cfg)
    idx, _, t = sweep_match(a, b, corners, cfg, np.full(len(corners), np.nan), patches)
    tau = np.full(len(corners), np.nan)
    tau[idx] = t
    assert len(idx) >= 50
    none = np.zeros((len(corners), 1), bool)
    static = contradicted(a, [c], corners, tau, none, cfg, patches)
    moved_c = copy.copy(c)
    moved_c.img = np.roll(c.img, (25, 40), axis=(0, 1))
    moved = contradicted(a, [moved_c], corners, tau, none, cfg, patches)
    assert static[idx].mean() <= 0.1, static[idx].mean()
    assert moved[idx].mean() >= 0.6, moved[idx].mean()
    # a view that matched the corner does not count against it, and a corner no view sees is kept
    assert not contradicted(a, [moved_c], corners, tau, np.ones((len(corners), 1), bool), cfg, patches).any()
    assert not contradicted(a, [], corners, tau, np.zeros((len(corners), 0), bool), cfg, patches).any()


def test_moved_points_are_dropped_and_checked_in_views_max_gap_frames_back_on_a_rig(drive, monkeypatch):
    """The check's verdict reaches the points (a strict threshold drops some, 0 none), and on a two-camera rig
    (the front camera twice) a reference's camera is still loaded max_gap frames back."""
    import pavemap.mesh.ground_points as gpm

    seq = copy.deepcopy(drive[0])
    seq.frames = seq.frames[:8]
    off = GroundConfig(static_ncc=0.0)
    strict = find_ground_points(seq, GroundConfig(static_ncc=0.99))
    assert strict.stats["moved"] > 0 and len(strict) < len(find_ground_points(seq, off))
    rig = copy.deepcopy(seq)
    rig.cameras["CAM_TWIN"] = rig.cameras["CAM_FRONT"]
    for f in rig.frames:
        f.views["CAM_TWIN"] = copy.deepcopy(f.views["CAM_FRONT"])
    backs = []
    real = gpm.moved_points

    def spy(vds, i, *args):
        a = vds[i]
        backs.extend(a.pos - b.pos for b in vds if b.img is not None and b.key[1] == a.key[1] and b.pos <= a.pos)
        return real(vds, i, *args)

    monkeypatch.setattr(gpm, "moved_points", spy)
    find_ground_points(rig, GroundConfig())
    assert max(backs) == GroundConfig().max_gap
