"""KITTI odometry importer on a tiny fixture written in the real layout and formats."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from pavemap.errors import PavemapError
from pavemap.ingest.kitti import import_kitti
from pavemap.io.kitti import A_KITTI_TO_WORLD, read_calib
from pavemap.io.sequence import SequenceError, load_depth, load_rgb, read_sequence

W, H = 96, 40
F = 60.0
# KITTI-like rectified rig, scaled down: P_i = K [I | t_i], P[0, 3] = fx * t_x
K = np.array([[F, 0, 47.5], [0, F, 19.5], [0, 0, 1.0]])
T_I = {0: [0, 0, 0], 1: [-0.54, 0, 0], 2: [0.06, -0.0003, 0.0027], 3: [-0.47, 0.002, 0.003]}
# velodyne -> cam0 (KITTI's is close to this axis swap plus a small offset)
TR = np.array([[0, -1, 0, 0.01], [0, 0, -1, -0.08], [1, 0, 0, -0.27], [0, 0, 0, 1.0]])
CAM_H = 1.65
N = 4


def _proj(i: int) -> np.ndarray:
    return K @ np.hstack([np.eye(3), np.array(T_I[i], float)[:, None]])


def _poses() -> np.ndarray:
    """cam0-to-world (KITTI frame): drive forward (+z) 1.2 m per frame while yawing left a little."""
    T = np.tile(np.eye(4), (N, 1, 1))
    for k in range(N):
        a = -0.05 * k  # rotation about KITTI y (down): negative = turning left
        c, s = np.cos(a), np.sin(a)
        T[k, :3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
        T[k, :3, 3] = [0.1 * k * k, 0.0, 1.2 * k]
    return T


def _fmt(m) -> str:
    return " ".join(f"{x:.12e}" for x in np.asarray(m).ravel())


def write_fixture(root, calib_style="labelled", grey=True, colour=True, velodyne=True, n_poses=N):
    seq = root / "sequences" / "00"
    seq.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for k in range(N):
        if colour:
            (seq / "image_2").mkdir(exist_ok=True)
            Image.fromarray(rng.integers(0, 255, (H, W, 3), dtype=np.uint8)).save(seq / "image_2" / f"{k:06d}.png")
        if grey:
            (seq / "image_0").mkdir(exist_ok=True)
            Image.fromarray(rng.integers(0, 255, (H, W), dtype=np.uint8)).save(seq / "image_0" / f"{k:06d}.png")
        if velodyne:
            (seq / "velodyne").mkdir(exist_ok=True)
            # ground points 1.65 m below cam0, 4..30 m ahead, in velodyne coordinates
            x = rng.uniform(-6, 6, 4000)
            z = rng.uniform(4, 30, 4000)
            cam0 = np.stack([x, np.full_like(x, CAM_H), z, np.ones_like(x)], 1)
            velo = (np.linalg.inv(TR) @ cam0.T).T[:, :3]
            pts = np.hstack([velo, rng.uniform(0, 1, (len(x), 1))]).astype(np.float32)
            pts.tofile(seq / "velodyne" / f"{k:06d}.bin")
    if calib_style == "labelled":
        lines = [f"P{i}: {_fmt(_proj(i))}" for i in range(4)] + [f"Tr: {_fmt(TR[:3])}"]
    elif calib_style == "bare5":
        lines = [_fmt(_proj(i)) for i in range(4)] + [_fmt(TR[:3])]
    else:  # two bare rows: P0, P1 only
        lines = [_fmt(_proj(i)) for i in range(2)]
    (seq / "calib.txt").write_text("\n".join(lines) + "\n")
    (seq / "times.txt").write_text("\n".join(f"{0.1 * k:.6e}" for k in range(N)) + "\n")
    (root / "poses").mkdir()
    (root / "poses" / "00.txt").write_text("\n".join(_fmt(T[:3]) for T in _poses()[:n_poses]) + "\n")
    return root


def _project_kitti(Xk: np.ndarray, k: int, cam: int) -> np.ndarray:
    """KITTI's own convention: u ~ P_cam · inv(T_cam0_k) · X."""
    Xc0 = np.linalg.inv(_poses()[k]) @ np.append(Xk, 1.0)
    u = _proj(cam) @ Xc0
    return u[:2] / u[2]


def _project_ours(seq, Xk: np.ndarray, frame: int, cam: str) -> np.ndarray:
    Xw = A_KITTI_TO_WORLD @ Xk
    v = seq.frame_by_index()[frame].views[cam]
    Xc = np.linalg.inv(v.T_world_cam) @ np.append(Xw, 1.0)
    u = seq.cameras[cam].K @ Xc[:3]
    return u[:2] / u[2]


def test_colour_camera_geometry_and_lidar(tmp_path):
    root = write_fixture(tmp_path / "kitti")
    seq = import_kitti(root, "00", tmp_path / "seq", camera=2)
    s = read_sequence(tmp_path / "seq")  # validates files on disk
    assert [f.index for f in s.frames] == [0, 1, 2, 3]
    assert s.cameras["cam2"].width == W and np.allclose(s.cameras["cam2"].K, K)
    # same pixel as KITTI's own projection for points ahead, in every frame
    for Xk in (np.array([1.0, 1.0, 12.0]), np.array([-2.0, 1.65, 25.0]), np.array([0.5, -1.0, 8.0])):
        for k in range(N):
            np.testing.assert_allclose(_project_ours(s, Xk, k, "cam2"), _project_kitti(Xk, k, 2), atol=1e-6)
    # z-up world: cameras look along +x at frame 0, camera y (down) is world -z
    R0 = s.frames[0].views["cam2"].T_world_cam[:3, :3]
    np.testing.assert_allclose(R0[:, 2], [1, 0, 0], atol=1e-9)
    np.testing.assert_allclose(R0[:, 1], [0, 0, -1], atol=1e-9)
    traj = s.trajectory()
    assert traj[-1, 0] > 3.0 and abs(traj[-1, 2] - traj[0, 2]) < 1e-6  # forward, flat
    assert traj[-1, 1] < -0.5  # the fixture drifts to KITTI +x (right), which is world -y
    # LiDAR depth: ground 1.65 m under cam0 → depth = fy * 1.65 / (v - cy) (cam2 is 0.0003 m lower)
    d = load_depth(s.path(s.frames[1].views["cam2"].depth))
    vs, us = np.nonzero(d)
    assert len(vs) > 50
    expect = F * (CAM_H + T_I[2][1]) / (vs - 19.5)
    # 1 px rounding of v and the 2.7 mm z offset of cam2 bound the error
    assert np.median(np.abs(d[vs, us] - expect) / expect) < 0.05
    assert d[: int(19.5)].max() == 0  # nothing above the horizon
    assert seq.name == "kitti-00"


def test_grey_camera_becomes_rgb_and_strided(tmp_path):
    root = write_fixture(tmp_path / "kitti", velodyne=False)
    s = import_kitti(root, "00", tmp_path / "seq", camera=0, start=1, stride=2)
    assert [f.index for f in s.frames] == [1, 3]
    img = load_rgb(tmp_path / "seq" / s.frames[0].views["cam0"].image)
    assert img.shape == (H, W, 3)
    src = np.asarray(Image.open(root / "sequences/00/image_0/000001.png"))
    assert np.array_equal(img[..., 0], src) and np.array_equal(img[..., 2], src)
    assert s.frames[0].views["cam0"].depth is None
    np.testing.assert_allclose(s.frames[1].timestamp, 0.3)
    Xk = np.array([0.3, 1.2, 10.0])
    np.testing.assert_allclose(_project_ours(s, Xk, 3, "cam0"), _project_kitti(Xk, 3, 0), atol=1e-6)


@pytest.mark.parametrize("style", ["bare5", "bare2"])
def test_bare_calib_variants(tmp_path, style):
    root = write_fixture(tmp_path / "kitti", calib_style=style, velodyne=(style == "bare5"))
    calib = read_calib(root / "sequences/00/calib.txt")
    assert sorted(calib.P) == ([0, 1, 2, 3] if style == "bare5" else [0, 1])
    assert (calib.Tr is not None) == (style == "bare5")
    if style == "bare5":
        np.testing.assert_allclose(calib.Tr, TR, atol=1e-9)
        s = import_kitti(root, "00", tmp_path / "seq", camera=2)
        depth_rel = s.frames[0].views["cam2"].depth
        assert depth_rel is not None and (load_depth(s.root / depth_rel) > 0).any(), \
            "velodyne points must land in the depth map"
    else:
        s = import_kitti(root, "00", tmp_path / "seq", camera=0)
        with pytest.raises(SequenceError, match="no P2"):
            import_kitti(root, "00", tmp_path / "seq2", camera=2)
    np.testing.assert_allclose(calib.t_cam0_to_cam(1), T_I[1], atol=1e-12)
    assert len(s.frames) == N


def test_bad_inputs(tmp_path):
    root = write_fixture(tmp_path / "a", n_poses=N - 1)
    with pytest.raises(SequenceError, match=r"3 poses but 4 images") as e:
        import_kitti(root, "00", tmp_path / "seq")
    assert "00.txt" in str(e.value)
    with pytest.raises(SequenceError, match=r"'07' not found; available: \['00'\]"):
        import_kitti(root, "07", tmp_path / "seq")
    (root / "sequences/00/calib.txt").unlink()
    with pytest.raises(SequenceError, match="calib.txt"):
        import_kitti(root, "00", tmp_path / "seq")
    root = write_fixture(tmp_path / "b")
    (root / "poses/00.txt").unlink()
    with pytest.raises(SequenceError, match="poses not found"):
        import_kitti(root, "00", tmp_path / "seq")
    root = write_fixture(tmp_path / "c")
    (root / "sequences/00/image_2/000002.png").write_bytes(b"garbage")
    with pytest.raises(SequenceError, match="000002.png: unreadable image"):
        import_kitti(root, "00", tmp_path / "seq")
    with pytest.raises(PavemapError, match="--camera"):
        import_kitti(root, "00", tmp_path / "seq", camera=5)
    (root / "sequences/00/calib.txt").write_text("P0: 1 2 3\n")
    with pytest.raises(SequenceError, match="P0 has 3 numbers"):
        import_kitti(root, "00", tmp_path / "seq")


def test_cli_import_kitti_with_corridor_fallback(tmp_path):
    from typer.testing import CliRunner

    from pavemap.cli import app
    from pavemap.io.sequence import load_semantics

    root = write_fixture(tmp_path / "kitti")
    with pytest.warns(UserWarning, match="corridor"):
        r = CliRunner().invoke(app, ["import", "kitti", str(root), "--sequence", "00", "--camera", "2",
                                     "--stride", "2", "--segmenter", "corridor",
                                     "-o", str(tmp_path / "seq")])  # -o as in the README
    assert r.exit_code == 0, r.output
    assert "kitti-00: 2 frames" in r.output and "corridor fallback" in r.output
    s = read_sequence(tmp_path / "seq")
    m = load_semantics(s.path(s.frames[0].views["cam2"].semantics))
    assert m.shape == (H, W) and (m[-1, W // 2] == 0)  # ground right below the camera is road
    r = CliRunner().invoke(app, ["import", "kitti", str(root), "--sequence", "05", "--out", str(tmp_path / "s2")])
    assert r.exit_code != 0
