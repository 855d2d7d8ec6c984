"""Own-drive importers: images folder + cameras.json + poses.csv, and video splitting."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from pavemap.ingest.folder import import_folder
from pavemap.ingest.video import import_video
from pavemap.io.folder import read_poses_csv
from pavemap.io.sequence import SequenceError, load_rgb, read_sequence

W, H = 48, 32
KMAT = [[40.0, 0, 23.5], [0, 40.0, 15.5], [0, 0, 1]]


def _cams(path, names=("front",)):
    path.write_text(json.dumps({"cameras": {n: {"width": W, "height": H, "K": KMAT} for n in names}}))
    return path


def _images(folder, n, seed=0, ext="png"):
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    for k in range(n):
        Image.fromarray(rng.integers(0, 255, (H, W, 3), dtype=np.uint8)).save(folder / f"img_{k:03d}.{ext}")


def _quat_rows(n, camera=None):
    head = "frame,camera,timestamp,tx,ty,tz,qw,qx,qy,qz" if camera else "frame,timestamp,tx,ty,tz,qw,qx,qy,qz"
    rows = [head]
    Rs = []
    for k in range(n):
        # OpenCV camera looking along world +x (z up), yawing slowly
        R = Rotation.from_euler("z", 0.1 * k).as_matrix() @ np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]])
        x, y, z, w = Rotation.from_matrix(R).as_quat()
        Rs.append(R)
        cam = f"{camera}," if camera else ""
        rows.append(f"{k},{cam}{0.1 * k},{2.0 * k},{0.5 * k},1.5,{w},{x},{y},{z}")
    return "\n".join(rows) + "\n", Rs


def test_folder_quaternion_poses(tmp_path):
    _images(tmp_path / "imgs", 4)
    text, Rs = _quat_rows(4)
    (tmp_path / "poses.csv").write_text(text)
    s = import_folder(tmp_path / "imgs", _cams(tmp_path / "cameras.json"), tmp_path / "poses.csv", tmp_path / "seq")
    r = read_sequence(tmp_path / "seq")
    assert len(r.frames) == 4 and r.cameras["front"].width == W
    for k, f in enumerate(r.frames):
        T = f.views["front"].T_world_cam
        np.testing.assert_allclose(T[:3, :3], Rs[k], atol=1e-9)
        np.testing.assert_allclose(T[:3, 3], [2.0 * k, 0.5 * k, 1.5])
        assert f.timestamp == pytest.approx(0.1 * k)
    src = np.asarray(Image.open(tmp_path / "imgs" / "img_002.png"))
    assert np.array_equal(load_rgb(r.path(r.frames[2].views["front"].image)), src)
    assert s.name == "imgs"


def test_folder_matrix_poses_two_cameras(tmp_path):
    _images(tmp_path / "imgs" / "left", 3, seed=1, ext="jpg")
    _images(tmp_path / "imgs" / "right", 3, seed=2, ext="jpg")
    rows = ["frame,camera,image," + ",".join(f"m{r}{c}" for r in range(3) for c in range(4))]
    for k in range(3):
        for cam, dx in (("left", 0.0), ("right", 0.5)):
            M = np.hstack([np.eye(3), [[k + dx], [0], [1.2]]])
            rows.append(f"{k},{cam},img_{k:03d}.jpg," + ",".join(str(x) for x in M.ravel()))
    (tmp_path / "poses.csv").write_text("\n".join(rows) + "\n")
    import_folder(tmp_path / "imgs", _cams(tmp_path / "cameras.json", ("left", "right")), tmp_path / "poses.csv",
                  tmp_path / "seq")
    r = read_sequence(tmp_path / "seq")
    assert [sorted(f.views) for f in r.frames] == [["left", "right"]] * 3
    assert r.frames[2].views["right"].T_world_cam[0, 3] == pytest.approx(2.5)
    assert r.frames[1].views["left"].image == "images/left/000001.jpg"


def test_folder_bad_inputs(tmp_path):
    _images(tmp_path / "imgs", 3)
    cams = _cams(tmp_path / "cameras.json")
    text, _ = _quat_rows(4)
    (tmp_path / "poses.csv").write_text(text)
    with pytest.raises(SequenceError, match="4 poses but 3 images"):
        import_folder(tmp_path / "imgs", cams, tmp_path / "poses.csv", tmp_path / "seq")
    text, _ = _quat_rows(3, camera="rear")
    (tmp_path / "poses.csv").write_text(text)
    with pytest.raises(SequenceError, match=r"unknown camera 'rear'; cameras.json has \['front'\]"):
        import_folder(tmp_path / "imgs", cams, tmp_path / "poses.csv", tmp_path / "seq")
    (tmp_path / "poses.csv").write_text("frame,tx,ty,tz,qw,qx,qy,qz\n0,1,2,3,0,0,0,0\n")
    with pytest.raises(SequenceError, match="line 2"):
        read_poses_csv(tmp_path / "poses.csv")
    (tmp_path / "poses.csv").write_text("frame,x,y\n0,1,2\n")
    with pytest.raises(SequenceError, match="needs pose columns"):
        read_poses_csv(tmp_path / "poses.csv")
    with pytest.raises(SequenceError, match="poses file not found"):
        import_folder(tmp_path / "imgs", cams, tmp_path / "missing.csv", tmp_path / "seq")
    (tmp_path / "cam2.json").write_text(json.dumps({"front": {"width": W, "height": H}}))
    with pytest.raises(SequenceError, match="needs width, height and K"):
        import_folder(tmp_path / "imgs", tmp_path / "cam2.json", tmp_path / "poses.csv", tmp_path / "seq")
    text, _ = _quat_rows(3)
    (tmp_path / "poses.csv").write_text(text)
    (tmp_path / "imgs" / "img_001.png").write_bytes(b"broken")
    with pytest.raises(SequenceError, match="img_001.png: unreadable image"):
        import_folder(tmp_path / "imgs", cams, tmp_path / "poses.csv", tmp_path / "seq")


def _write_video(path, n=45, fps=15.0):
    import cv2

    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (W, H))
    assert vw.isOpened()
    for k in range(n):
        img = np.zeros((H, W, 3), np.uint8)
        img[:, (k % W):(k % W) + 4] = 255  # a moving bar, so frames differ
        vw.write(img)
    vw.release()


def test_video_with_timestamped_poses(tmp_path):
    _write_video(tmp_path / "drive.avi")
    cams = _cams(tmp_path / "cameras.json")
    # poses at 1 Hz; frames are taken at 5 Hz and get interpolated poses
    R = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    rows = ["timestamp,tx,ty,tz,qw,qx,qy,qz"] + [f"{t},{10.0 * t},0,1.4,{w},{x},{y},{z}" for t in range(4)]
    (tmp_path / "poses.csv").write_text("\n".join(rows) + "\n")
    s = import_video(tmp_path / "drive.avi", cams, tmp_path / "poses.csv", tmp_path / "seq", fps=5.0)
    r = read_sequence(tmp_path / "seq")
    assert len(r.frames) == 15  # 3 s of video at 5 Hz
    ts = np.array([f.timestamp for f in r.frames])
    np.testing.assert_allclose(np.diff(ts), 0.2, atol=1e-6)
    xs = np.array([f.views["front"].T_world_cam[0, 3] for f in r.frames])
    np.testing.assert_allclose(xs, 10.0 * ts, atol=1e-6)
    assert load_rgb(r.path(r.frames[3].views["front"].image)).shape == (H, W, 3)
    assert s.name == "drive"
    # one row per frame without timestamps must match the frame count
    rows = ["tx,ty,tz,qw,qx,qy,qz"] + [f"{k},0,1.4,{w},{x},{y},{z}" for k in range(4)]
    (tmp_path / "p2.csv").write_text("\n".join(rows) + "\n")
    with pytest.raises(SequenceError, match="4 poses for 15 extracted frames"):
        import_video(tmp_path / "drive.avi", cams, tmp_path / "p2.csv", tmp_path / "seq2", fps=5.0)
    with pytest.raises(SequenceError, match="video file not found"):
        import_video(tmp_path / "nope.mp4", cams, tmp_path / "p2.csv", tmp_path / "seq3")
