"""Faults of the real world (issue 46): a damaged frame, two runs into one folder, a full disk, a pose that is
not a rotation, a duplicated JSON key, and the smaller messages. Each case checks the exit status, the
message's key words, that no traceback was printed and that no complete-looking output was left.

The runs are real ``pavemap`` processes on a copy of the tiny synthetic drive (``tiny_seq``), 1 epoch.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

SRC = str(Path(__file__).resolve().parents[1] / "src")
FAST = ["--set", "device=cpu", "mesh.epochs=1", "mesh.threads=1", "output.figures=false", "output.report=false",
        "output.overlay_frames=0"]


def pavemap(*args: object, timeout: float = 300, env: dict | None = None) -> subprocess.CompletedProcess:
    """``pavemap ARGS`` in a fresh process (this checkout's code)."""
    e = {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", ""), **(env or {})}
    return subprocess.run([sys.executable, "-m", "pavemap.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, env=e)


def no_traceback(p: subprocess.CompletedProcess) -> None:
    assert "Traceback" not in p.stderr and "Traceback" not in p.stdout, p.stderr[-3000:]


def last_error(p: subprocess.CompletedProcess) -> str:
    """The ``error: ...`` line, which ends the output (a progress bar may precede it on the same line)."""
    err = p.stderr[p.stderr.rindex("error: "):].strip()
    assert "\n" not in err, err
    return err


def complete(out: Path) -> bool:
    """A run folder that looks finished: its completion file and an owner marker saying complete."""
    marker = out / ".pavemap-owner.json"
    return (out / "metrics.json").is_file() or (marker.is_file() and json.loads(marker.read_text())
                                                .get("status") == "complete")


@pytest.fixture
def seq(tiny_seq, tmp_path) -> Path:
    dst = tmp_path / "seq"
    shutil.copytree(tiny_seq.root, dst)
    return dst


# ---------------------------------------------------------------------------- 1. a damaged frame


def _truncate_as_jpeg(seq: Path, frame: int) -> str:
    """Frame ``frame``'s image re-saved as a JPEG cut in half (an interrupted copy); returns its path."""
    d = json.loads((seq / "sequence.json").read_text())
    view = next(iter(d["frames"][frame]["views"].values()))
    png = seq / view["image"]
    jpg = png.with_suffix(".jpg")
    Image.open(png).convert("RGB").save(jpg, quality=95)
    data = jpg.read_bytes()
    jpg.write_bytes(data[: len(data) // 2])
    view["image"] = str(jpg.relative_to(seq))
    (seq / "sequence.json").write_text(json.dumps(d))
    return view["image"]


def test_truncated_jpeg_is_an_error_and_skip_bad_frames_drops_it(seq, tmp_path):
    rel = _truncate_as_jpeg(seq, 3)
    info = pavemap("info", seq)
    assert info.returncode == 1 and "truncated" in info.stdout and rel in info.stdout
    out = tmp_path / "run"
    p = pavemap("run", seq, "--out", out, *FAST)
    no_traceback(p)
    assert p.returncode == 2, p.stderr
    assert "truncated" in p.stderr and rel in p.stderr and "--skip-bad-frames" in p.stderr
    assert not out.exists() or not complete(out)  # refused before anything was written
    p = pavemap("run", seq, "--out", out, "--skip-bad-frames", *FAST)
    no_traceback(p)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "skipped 1 of 8 frame(s)" in p.stderr and "frame 3" in p.stderr and rel in p.stderr
    assert complete(out)
    log = (out / "run.log").read_text()
    assert "Premature end" not in p.stderr + log


# ---------------------------------------------------------------------------- 2. two runs into one folder


def _wait_for(pred, timeout: float = 120.0) -> None:
    t = time.time()
    while not pred():
        assert time.time() - t < timeout, "timed out"
        time.sleep(0.05)


def test_second_run_into_a_locked_folder_stops_naming_the_first(seq, tmp_path):
    out = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": SRC}
    first = subprocess.Popen([sys.executable, "-m", "pavemap.cli", "run", seq, "--out", out, *FAST],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        _wait_for(lambda: (out / ".pavemap-lock").is_file() and (out / ".pavemap-lock").stat().st_size > 0)
        second = pavemap("run", seq, "--out", out, *FAST[:2], "mesh.epochs=2")
        no_traceback(second)
        assert second.returncode == 2
        assert f"pavemap process {first.pid} on host {socket.gethostname()}" in second.stderr
        assert "in use by" in second.stderr and "choose another --out" in second.stderr
        _, err = first.communicate(timeout=300)
    finally:
        if first.poll() is None:
            first.kill()
    assert first.returncode == 0, err[-2000:]
    cfg = (out / "config.yaml").read_text()
    assert "epochs: 1" in cfg and "epochs: 2" not in cfg  # the folder holds the first run's settings only
    assert not (out / ".pavemap-lock").exists()  # released, and not listed as an output
    assert ".pavemap-lock" not in (out / ".pavemap-owner.json").read_text()


def test_stale_lock_of_a_killed_run_is_taken_over_with_a_warning(seq, tmp_path):
    out = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; sys.path.insert(0, sys.argv[1]); "
                               "from pavemap.io.lock import acquire; acquire(sys.argv[2]); print('held', flush=True); "
                               "time.sleep(600)", SRC, str(out)], stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    os.kill(holder.pid, signal.SIGKILL)  # a power cut: the lock file stays, the kernel's lock goes
    holder.wait()
    assert str(holder.pid) in (out / ".pavemap-lock").read_text()
    p = pavemap("run", seq, "--out", out, *FAST)
    no_traceback(p)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "took over the lock" in p.stderr and f"process {holder.pid}" in p.stderr
    assert complete(out)


# ---------------------------------------------------------------------------- 3. a full disk


@contextlib.contextmanager
def _tmpfs(path: Path, size: str):
    path.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({r.stderr.decode().strip()})")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], check=False)


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0, reason="a size-limited tmpfs needs root")
def test_full_disk_is_one_line_and_the_rerun_resumes(seq, tmp_path):
    with _tmpfs(tmp_path / "small", "3m") as disk:
        out = disk / "run"
        p = pavemap("run", seq, "--out", out, *FAST)
        no_traceback(p)
        assert p.returncode == 2, p.stderr[-2000:]
        err = last_error(p)
        assert str(out) in err and "no space left on device" in err
        assert "rerun" in err
        assert not complete(out)
        subprocess.run(["mount", "-o", "remount,size=200m", str(disk)], check=True)
        p = pavemap("run", seq, "--out", out, *FAST)
        no_traceback(p)
        assert p.returncode == 0, p.stderr[-2000:]
        assert complete(out)


def test_injected_disk_full_in_torch_save_is_one_line(seq, tmp_path):
    """torch.save's own words for a short write, injected: the same one line, nothing complete left, and a rerun
    finishes."""
    out = tmp_path / "run"
    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(
        "import torch\n"
        "def save(*a, **k):\n"
        "    raise RuntimeError('[enforce fail at inline_container.cc:672] . unexpected pos 1280 vs 1174')\n"
        "torch.save = save\n")
    p = pavemap("run", seq, "--out", out, *FAST, env={"PYTHONPATH": f"{hook}{os.pathsep}{SRC}"})
    no_traceback(p)
    assert p.returncode == 2, p.stderr[-2000:]
    err = last_error(p)
    assert str(out) in err and "no space left on device" in err and "MB free" in err
    assert not complete(out)
    p = pavemap("run", seq, "--out", out, *FAST)
    assert p.returncode == 0, p.stderr[-2000:]
    assert complete(out)


def test_injected_enospc_from_a_write_is_one_line(seq, tmp_path, monkeypatch):
    import errno

    from pavemap.errors import PavemapError
    from pavemap.preflight import write_failure

    e = OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "run" / "mesh" / "mesh.npz"))
    worded = write_failure(e, tmp_path / "run")
    assert isinstance(worded, PavemapError)
    assert str(worded).startswith(f"{tmp_path / 'run'}: no space left on device") and "mesh.npz" in str(worded)
    assert write_failure(OSError(errno.EROFS, "x"), tmp_path).args[0].endswith(f"writable --out (not {tmp_path})")
    assert write_failure(ValueError("unexpected pos"), tmp_path) is None


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0, reason="a read-only mount needs root")
def test_read_only_out_stops_before_any_stage(seq, tmp_path):
    with _tmpfs(tmp_path / "ro", "1m") as disk:
        subprocess.run(["mount", "-o", "remount,ro", str(disk)], check=True)
        t = time.perf_counter()
        p = pavemap("run", seq, "--out", disk / "run", *FAST)
        took = time.perf_counter() - t
    no_traceback(p)
    assert p.returncode == 2 and "read-only file system" in p.stderr.lower() and str(disk / "run") in p.stderr
    assert "mesh:" not in p.stderr and took < 60


def test_unloadable_weights_stop_before_stage_one(seq, tmp_path):
    bad = tmp_path / "cut.pt"
    bad.write_bytes(b"PK\x03\x04" + os.urandom(2000))  # the start of a zip, its directory cut off
    out = tmp_path / "run"
    p = pavemap("run", seq, "--out", out, "--weights", bad, *FAST)
    no_traceback(p)
    assert p.returncode == 2 and f"{bad}: not loadable as PyTorch weights" in p.stderr
    assert not (out / "mesh").exists()


# ---------------------------------------------------------------------------- 4. a pose that is not a rotation


def _kitti(root: Path, poses: list[np.ndarray]) -> Path:
    s = root / "sequences" / "00"
    (s / "image_2").mkdir(parents=True)
    for k in range(len(poses)):
        Image.fromarray(np.full((32, 64, 3), 40 * k, np.uint8)).save(s / "image_2" / f"{k:06d}.png")
    P = "50 0 32 0 0 50 16 0 0 0 1 0"
    (s / "calib.txt").write_text("".join(f"P{i}: {P}\n" for i in range(4)))
    (root / "poses").mkdir()
    (root / "poses" / "00.txt").write_text("".join(" ".join(f"{x:.6e}" for x in T[:3].ravel()) + "\n"
                                                   for T in poses))
    return root


def _walk(k: int) -> np.ndarray:
    T = np.eye(4)
    T[2, 3] = 1.2 * k
    return T


@pytest.mark.parametrize("bad, words", [
    (np.diag([1.1, 1.1, 1.1, 1.0]), ["line 3", "not orthonormal", "scaled by 1.1"]),
    (np.full((4, 4), np.nan), ["line 3", "NaN"]),
])
def test_kitti_pose_that_is_not_a_rotation_is_an_error(tmp_path, bad, words):
    poses = [_walk(k) for k in range(4)]
    poses[2] = bad
    root = _kitti(tmp_path / "kitti", poses)
    p = pavemap("import", "kitti", root, "--out", tmp_path / "seq", "--no-semantics", "--no-lidar")
    no_traceback(p)
    assert p.returncode == 2, p.stderr
    assert "poses/00.txt" in p.stderr and all(w in p.stderr for w in words), p.stderr
    assert not (tmp_path / "seq" / "sequence.json").exists()


def test_kitti_rounding_is_accepted(tmp_path):
    from pavemap.io.kitti import read_poses

    a = 0.3
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    (tmp_path / "p.txt").write_text(" ".join(f"{x:.5f}" for x in np.hstack([R, [[1], [2], [3]]]).ravel()) + "\n")
    assert read_poses(tmp_path / "p.txt").shape == (1, 4, 4)


@pytest.mark.parametrize("quat, words", [
    ("0.0,0.0,0.0,2.2", ["line 3", "norm 2.2", "expected 1"]),
    ("nan,0,0,0", ["line 3", "NaN"]),
])
def test_poses_csv_quaternion_not_unit_is_an_error(tmp_path, quat, words):
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    for k in range(3):
        Image.fromarray(np.full((32, 64, 3), 40 * k, np.uint8)).save(imgs / f"{k:03d}.png")
    (tmp_path / "cameras.json").write_text(json.dumps({"front": {"width": 64, "height": 32, "fx": 50, "cx": 32,
                                                                 "cy": 16}}))
    rows = ["tx,ty,tz,qw,qx,qy,qz", "0,0,1.5,0.5,-0.5,0.5,-0.5", f"1,0,1.5,{quat}", "2,0,1.5,0.5,-0.5,0.5,-0.5"]
    (tmp_path / "poses.csv").write_text("\n".join(rows) + "\n")
    p = pavemap("import", "folder", imgs, "--cameras", tmp_path / "cameras.json", "--poses",
                tmp_path / "poses.csv", "--out", tmp_path / "seq", "--no-semantics")
    no_traceback(p)
    assert p.returncode == 2, p.stderr
    assert "poses.csv" in p.stderr and all(w in p.stderr for w in words), p.stderr
    assert not (tmp_path / "seq" / "sequence.json").exists()


# ---------------------------------------------------------------------------- 5. a duplicated JSON key


def test_duplicate_json_key_is_refused_naming_key_and_file(seq, tmp_path):
    text = (seq / "sequence.json").read_text()
    d = json.loads(text)
    two = json.dumps(d["frames"][:2])
    (seq / "sequence.json").write_text(text.rstrip().rstrip("}") + f', "frames": {two}}}')
    assert len(json.loads((seq / "sequence.json").read_text())["frames"]) == 2  # what json would have read
    info = pavemap("info", seq)
    assert info.returncode == 1 and 'duplicate key "frames"' in info.stdout and "sequence.json" in info.stdout
    out = tmp_path / "run"
    p = pavemap("run", seq, "--out", out, *FAST)
    no_traceback(p)
    assert p.returncode == 2 and 'duplicate key "frames"' in p.stderr and str(seq / "sequence.json") in p.stderr
    assert not out.exists()


def test_duplicate_key_in_cameras_json_and_a_detections_line(tmp_path):
    from pavemap.errors import SequenceError
    from pavemap.io.folder import read_cameras_json
    from pavemap.io.sequence import read_detections

    (tmp_path / "cameras.json").write_text('{"front": {"width": 64, "height": 32, "fx": 50, "cx": 32, "cy": 16, '
                                           '"width": 640}}')
    with pytest.raises(SequenceError, match=r'cameras.json: duplicate key "width"'):
        read_cameras_json(tmp_path / "cameras.json")
    (tmp_path / "d.jsonl").write_text('{"frame": 0, "camera": "c", "box": [0, 0, 1, 1], "cls": 0, "conf": 0.5, '
                                      '"cls": 1}\n')
    with pytest.raises(SequenceError, match=r'd.jsonl: line 1: duplicate key "cls"'):
        read_detections(tmp_path / "d.jsonl")


# ---------------------------------------------------------------------------- 6. smaller messages


def test_segmenter_name_that_is_not_a_file(tmp_path):
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    for k in range(2):
        Image.fromarray(np.full((32, 64, 3), 40 * k, np.uint8)).save(imgs / f"{k:03d}.png")
    (tmp_path / "cameras.json").write_text(json.dumps({"front": {"width": 64, "height": 32, "fx": 50, "cx": 32,
                                                                 "cy": 16}}))
    (tmp_path / "poses.csv").write_text("tx,ty,tz,qw,qx,qy,qz\n0,0,1.5,0.5,-0.5,0.5,-0.5\n1,0,1.5,0.5,-0.5,0.5,-0.5\n")
    p = pavemap("import", "folder", imgs, "--cameras", tmp_path / "cameras.json", "--poses", tmp_path / "poses.csv",
                "--out", tmp_path / "seq", "--segmenter", "roadseg.pt")
    no_traceback(p)
    assert p.returncode == 2 and "--segmenter roadseg.pt: no such file" in p.stderr
    assert "semantic-segmentation .pt" in p.stderr and "YOLO detection" not in p.stderr
    assert not (tmp_path / "seq" / "sequence.json").exists()


def test_scheduler_with_nothing_listening_is_refused_at_once(seq, tmp_path):
    (tmp_path / "m.yaml").write_text(f"drives:\n  - path: {seq}\n    date: 2024-01-01\n")
    t = time.perf_counter()
    p = pavemap("batch", tmp_path / "m.yaml", "--out", tmp_path / "net", "--scheduler", "tcp://127.0.0.1:1")
    took = time.perf_counter() - t
    no_traceback(p)
    assert p.returncode == 2 and "connection refused" in p.stderr and "127.0.0.1:1" in p.stderr
    assert took < 15  # dask's own wait is 20 s
    assert not (tmp_path / "net").exists()


def test_semantics_without_a_road_pixel_say_so(seq, tmp_path):
    d = json.loads((seq / "sequence.json").read_text())
    road = [c["id"] for c in d["classes"] if c.get("road")]
    kerb = next(c["id"] for c in d["classes"] if not (c.get("road") or c.get("sky") or c.get("movable")))
    for png in (seq / "semantics").rglob("*.png"):
        a = np.asarray(Image.open(png)).copy()
        a[np.isin(a, road)] = kerb
        Image.fromarray(a).save(png)
    p = pavemap("run", seq, "--out", tmp_path / "run", *FAST)
    no_traceback(p)
    assert "the semantic maps label no pixel as road" in p.stderr, p.stderr[-2000:]
