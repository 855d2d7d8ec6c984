"""YOLO backend: offline loading, boxes in original pixels, class mapping, clear errors, no network."""

from __future__ import annotations

import json
import socket
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from pavemap.errors import PavemapError
from pavemap.io.sequence import read_detections, read_sequence, write_sequence
from pavemap.types import Camera, Frame, SemanticClass, Sequence, View

MODEL_NAMES = {0: "D00", 1: "Pothole", 2: "Repair", 3: "d20"}


@pytest.fixture(autouse=True)
def no_network(monkeypatch):
    """Fail any connection attempt other than a local AF_UNIX socket."""
    real_connect = socket.socket.connect
    real_connect_ex = socket.socket.connect_ex
    attempts: list[object] = []

    def guard(real):
        def connect(self, address):
            if self.family == socket.AF_UNIX:
                return real(self, address)
            attempts.append(address)
            raise AssertionError(f"network access attempted: {address!r}")

        return connect

    monkeypatch.setattr(socket.socket, "connect", guard(real_connect))
    monkeypatch.setattr(socket.socket, "connect_ex", guard(real_connect_ex))

    def no_dns(*args, **kwargs):
        attempts.append(args)
        raise AssertionError(f"DNS lookup attempted: {args!r}")

    monkeypatch.setattr(socket, "getaddrinfo", no_dns)
    yield attempts
    assert not attempts, f"network attempts: {attempts}"


@pytest.fixture(scope="module")
def yolo_env(tmp_path_factory):
    """Offline ultralytics with a config folder under tmp."""
    import os

    from pavemap.assets import prepare_ultralytics
    from pavemap.detect.compat import ensure_torchvision

    old = os.environ.get("YOLO_CONFIG_DIR")
    cfg = prepare_ultralytics(tmp_path_factory.mktemp("yolo_cfg"))
    ensure_torchvision()
    yield cfg
    if old is not None:
        os.environ["YOLO_CONFIG_DIR"] = old


@pytest.fixture(scope="module")
def det_weights(yolo_env, tmp_path_factory) -> Path:
    """A YOLOv8n from its yaml (random weights, nc=4), saved to a .pt; its class logits are biased up
    so that the random net emits boxes of every class above conf 0.05."""
    from ultralytics import YOLO
    from ultralytics.nn.tasks import DetectionModel

    torch.manual_seed(0)
    y = YOLO("yolov8n.yaml")
    m = DetectionModel("yolov8n.yaml", nc=4, verbose=False)
    m.names = dict(MODEL_NAMES)
    head = m.model[-1]
    with torch.no_grad():
        for seq in head.cv3:
            seq[-1].bias.fill_(0.5)
    y.model = m
    path = tmp_path_factory.mktemp("w") / "rand_v8n.pt"
    y.save(path)
    assert path.is_file()
    return path


def _texture(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (h // 8, w // 8, 3), dtype=np.uint8)
    return np.kron(small, np.ones((8, 8, 1), dtype=np.uint8))  # blocky, so detail survives resizing


def _two_scale_sequence(root: Path) -> Sequence:
    """One frame seen by a 320x240 camera and by a 640x480 camera whose image is the same picture
    upscaled 2x (nearest): at imgsz 320 both reach the network as identical tensors."""
    img = _texture(240, 320, 1)
    big = np.repeat(np.repeat(img, 2, axis=0), 2, axis=1)
    (root / "images" / "small").mkdir(parents=True)
    (root / "images" / "big").mkdir(parents=True)
    Image.fromarray(img).save(root / "images" / "small" / "000000.png")
    Image.fromarray(big).save(root / "images" / "big" / "000000.png")
    K1 = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    small = Camera("small", 320, 240, K1)
    cams = {"small": small, "big": Camera("big", 640, 480, small.scaled(2).K)}
    T = np.eye(4)
    views = {
        "small": View("small", "images/small/000000.png", T),
        "big": View("big", "images/big/000000.png", T),
    }
    seq = Sequence("two-scale", [SemanticClass(0, "road", road=True)], cams, [Frame(0, 0.0, views)])
    write_sequence(seq, root)
    return read_sequence(root)


def test_nms_matches_reference(yolo_env):
    from ultralytics.utils.nms import TorchNMS

    from pavemap.detect.compat import nms

    g = torch.Generator().manual_seed(3)
    xy = torch.rand(1500, 2, generator=g) * 400
    wh = torch.rand(1500, 2, generator=g) * 60 + 1
    boxes = torch.cat([xy, xy + wh], 1)
    scores = torch.rand(1500, generator=g)
    for thr in (0.3, 0.5, 0.7):
        keep = nms(boxes, scores, thr)
        assert torch.equal(keep, TorchNMS.nms(boxes, scores, thr))
    assert nms(boxes[:0], scores[:0], 0.5).numel() == 0


def test_torchvision_importable_and_nms_works(yolo_env):
    import torchvision

    from pavemap.detect.compat import ensure_torchvision

    b = torch.tensor([[0, 0, 10, 10], [1, 1, 10, 10], [20, 20, 30, 30]], dtype=torch.float32)
    s = torch.tensor([0.9, 0.8, 0.7])
    assert torchvision.ops.nms(b, s, 0.5).tolist() == [0, 2]
    assert ensure_torchvision() == ensure_torchvision()  # idempotent


def test_class_map_defaults_and_overrides(tmp_path):
    from pavemap.detect.classmap import DROP, build_class_map, load_class_map

    lut, dropped = build_class_map({0: "D00", 1: "D10", 2: "D20", 3: "D40", 4: "D43", 5: "Repair"})
    assert lut.tolist() == [0, 1, 2, 3, DROP, DROP]
    assert dropped == ["D43", "Repair"]
    lut, _ = build_class_map(["longitudinal crack", "alligator_crack", "pothole", "car"])
    assert lut.tolist() == [0, 2, 3, DROP]

    f = tmp_path / "map.yaml"
    f.write_text("map:\n  D43: D40\n  Repair: drop\n  D00: 1\n  5: D20\n")
    over = load_class_map(f)
    lut, dropped = build_class_map({0: "D00", 4: "D43", 5: "crack-x", 6: "Repair"}, over)
    assert lut[[0, 4, 5, 6]].tolist() == [1, 3, 2, DROP]
    assert "Repair" in dropped

    bad = tmp_path / "bad.yaml"
    bad.write_text("D43: D99\n")
    with pytest.raises(PavemapError, match="D99"):
        load_class_map(bad)
    with pytest.raises(PavemapError, match="no model class maps"):
        build_class_map({0: "car", 1: "person"})


def test_detect_sequence_boxes_in_original_pixels(det_weights, tmp_path):
    from pavemap.detect.yolo import detect_sequence

    seq = _two_scale_sequence(tmp_path / "seq")
    out = tmp_path / "seq" / "detections.jsonl"
    n = detect_sequence(seq, weights=det_weights, out=out, imgsz=320, conf=0.05, device="cpu", batch=2)
    dets = read_detections(out)
    assert n == len(dets) > 0
    small = sorted((d for d in dets if d.camera == "small"), key=lambda d: (-d.conf, d.box))
    big = sorted((d for d in dets if d.camera == "big"), key=lambda d: (-d.conf, d.box))
    assert len(small) == len(big) > 0
    a = np.array([d.box for d in small])
    b = np.array([d.box for d in big])
    # the big image holds the same picture at twice the pixels: boxes must be exactly 2x
    np.testing.assert_allclose(b, 2 * a, atol=0.1)
    assert b[:, 2].max() > 320 or b[:, 3].max() > 240  # not letterbox (network-input) coordinates
    assert (a[:, [0, 2]] <= 320).all() and (a[:, [1, 3]] <= 240).all() and (a >= 0).all()
    assert (b[:, [0, 2]] <= 640).all() and (b[:, [1, 3]] <= 480).all()
    np.testing.assert_allclose([d.conf for d in small], [d.conf for d in big], atol=1e-3)

    # class mapping by name: D00 -> 0, Pothole -> 3 (D40), d20 -> 2, Repair dropped
    recs = [json.loads(line) for line in out.read_text().splitlines()]
    expect = {"D00": 0, "Pothole": 3, "d20": 2}
    assert {r["model_cls"] for r in recs} <= set(expect)
    assert all(r["cls"] == expect[r["model_cls"]] for r in recs)
    assert len({r["model_cls"] for r in recs}) >= 2  # the biased random head emits several classes
    from pavemap.detect.sources import detections_model
    from pavemap.weights.registry import sha256_of

    assert detections_model(out) == sha256_of(det_weights)  # each line names its model (its operating point)


def test_detect_sequence_class_map_override(det_weights, tmp_path):
    from pavemap.detect.yolo import detect_sequence

    seq = _two_scale_sequence(tmp_path / "seq")
    out = tmp_path / "d.jsonl"
    base = detect_sequence(seq, weights=det_weights, out=out, imgsz=320, conf=0.05, device="cpu", batch=1)
    base_recs = [json.loads(x) for x in out.read_text().splitlines()]
    cmap = tmp_path / "cmap.yaml"
    cmap.write_text("Repair: D10\nD00: drop\n")
    n = detect_sequence(seq, weights=det_weights, out=out, imgsz=320, conf=0.05, device="cpu", class_map=cmap)
    recs = [json.loads(x) for x in out.read_text().splitlines()]
    assert all(r["model_cls"] != "D00" for r in recs)
    assert all(r["cls"] == 1 for r in recs if r["model_cls"] == "Repair")
    n_d00 = sum(r["model_cls"] == "D00" for r in base_recs)
    n_repair = sum(r["model_cls"] == "Repair" for r in recs)
    assert n == base - n_d00 + n_repair


def test_weights_errors(yolo_env, tmp_path):
    from ultralytics import YOLO

    from pavemap.detect.yolo import load_detector

    with pytest.raises(PavemapError, match="never downloads"):
        load_detector(tmp_path / "nope.pt")
    with pytest.raises(PavemapError, match="not found"):
        load_detector("yolov8n.pt")  # a bare hub name must not trigger a download
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(PavemapError, match="cannot load"):
        load_detector(junk)
    cls_w = tmp_path / "cls.pt"
    YOLO("yolov8n-cls.yaml").save(cls_w)
    with pytest.raises(PavemapError, match="'classify' weights"):
        load_detector(cls_w)


def test_cli_detect_yolo(det_weights, tmp_path):
    from typer.testing import CliRunner

    from pavemap.cli import app

    _two_scale_sequence(tmp_path / "seq")
    r = CliRunner().invoke(
        app, ["detect", str(tmp_path / "seq"), "--detector", "yolo", "--weights", str(det_weights),
              "--set", "detector.imgsz=320", "--device", "cpu"],
    )
    assert r.exit_code == 0, r.output
    assert "detections ->" in r.output
    assert len(read_detections(tmp_path / "seq" / "detections.jsonl")) > 0


def test_resolve_data_yaml(tmp_path):
    import yaml

    from pavemap.detect.yolo import resolve_data_yaml

    (tmp_path / "ds" / "images" / "train").mkdir(parents=True)
    (tmp_path / "ds" / "images" / "val").mkdir(parents=True)
    f = tmp_path / "ds" / "data.yaml"
    f.write_text("path: .\ntrain: images/train\nval: images/val\nnames: {0: D00}\n")
    out = resolve_data_yaml(f, tmp_path / "run")
    assert yaml.safe_load(out.read_text())["path"] == str((tmp_path / "ds").resolve())
    f.write_text("path: .\ntrain: images/train\nval: images/test\nnames: {0: D00}\n")
    with pytest.raises(PavemapError, match="val folder"):
        resolve_data_yaml(f, tmp_path / "run")


def test_compat_is_noop_when_op_exists():
    """Where torchvision's compiled nms is registered (a working install), the shim must not install."""
    import subprocess
    import sys

    code = (
        "import torch\n"
        "lib = torch.library.Library('torchvision', 'DEF')\n"
        "lib.define('nms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor')\n"
        "from pavemap.detect import compat\n"
        "print(compat.ensure_torchvision(), compat.shim_installed(), compat._STATE['library'] is None)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["False", "False", "True"]


@pytest.mark.slow
def test_train_detector_tiny(yolo_env, tmp_path):
    """One CPU epoch on 4 tiny images through train_detector; the result loads as a D00..D40 detector."""
    from pavemap.detect.yolo import load_detector, train_detector

    ds = tmp_path / "ds"
    rng = np.random.default_rng(0)
    for split in ("train", "val"):
        (ds / "images" / split).mkdir(parents=True)
        (ds / "labels" / split).mkdir(parents=True)
        for k in range(4 if split == "train" else 2):
            Image.fromarray(rng.integers(0, 255, (64, 64, 3), dtype=np.uint8)).save(ds / "images" / split / f"{k}.jpg")
            (ds / "labels" / split / f"{k}.txt").write_text(f"{k % 4} 0.5 0.5 0.3 0.2\n")
    (ds / "data.yaml").write_text(
        "path: .\ntrain: images/train\nval: images/val\nnames: {0: D00, 1: D10, 2: D20, 3: D40}\n"
    )
    best = train_detector(ds / "data.yaml", model="yolov8n.yaml", epochs=1, imgsz=64, device="cpu", batch=4,
                          project=tmp_path / "runs", name="t", workers=0)
    assert best.is_file() and best.parent.name == "weights"
    m = load_detector(best)
    assert m.names == {0: "D00", 1: "D10", 2: "D20", 3: "D40"}
