"""Semantic masks: presets, YAML class maps, label folders, the ultralytics backend, the corridor fallback."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from pavemap.errors import PavemapError
from pavemap.io.sequence import SequenceError, load_semantics, read_sequence, write_sequence
from pavemap.segment import attach_label_folder, corridor_semantics, load_label_map, segment_sequence
from pavemap.segment.labels import VISTAS_V12
from pavemap.types import Camera, Frame, SemanticClass, Sequence, View

W, H = 64, 48


def _seq(root, n=3, cams=("front",)) -> Sequence:
    """A straight drive along +x at 1.5 m height, cameras looking forward (OpenCV axes, z up world)."""
    R = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)
    K = np.array([[40.0, 0, 31.5], [0, 40.0, 23.5], [0, 0, 1]])
    frames = []
    rng = np.random.default_rng(0)
    for k in range(n):
        views = {}
        for c in cams:
            rel = f"images/{c}/{k:06d}.png"
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(rng.integers(0, 255, (H, W, 3), dtype=np.uint8)).save(root / rel)
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = [2.0 * k, 0.0, 1.5]
            views[c] = View(c, rel, T)
        frames.append(Frame(k, 0.1 * k, views))
    seq = Sequence("drive", [SemanticClass(0, "road", road=True)], {c: Camera(c, W, H, K) for c in cams}, frames)
    write_sequence(seq, root)
    return read_sequence(root)


def test_presets():
    v = load_label_map("mapillary-vistas")
    ids = {c.name: c.id for c in v.classes}
    assert len(VISTAS_V12) == 66
    assert v.lut[VISTAS_V12.index("construction--flat--road")] == ids["road"]
    assert v.lut[VISTAS_V12.index("marking--crosswalk-zebra")] == ids["crosswalk"]
    assert v.lut[VISTAS_V12.index("object--manhole")] == ids["manhole"]
    assert v.lut[VISTAS_V12.index("object--vehicle--car")] == ids["movable"]
    assert v.lut[VISTAS_V12.index("nature--sky")] == ids["sky"]
    assert v.lut[VISTAS_V12.index("nature--vegetation")] == ids["other"]
    assert {c.name for c in v.classes if c.road} == {"road", "lane_marking", "crosswalk", "manhole"}
    k = load_label_map("rome-kitti")
    assert [c.name for c in k.classes if c.movable] == ["movable"]
    with pytest.raises(PavemapError, match="presets: rome-nuscenes"):
        load_label_map("cityscapes-x")


def test_label_folder_with_yaml_remap(tmp_path):
    seq = _seq(tmp_path / "seq")
    lab = tmp_path / "labels"
    lab.mkdir()
    for f in seq.frames:
        a = np.full((H, W), 30, np.uint8)  # vegetation-like id, not in remap -> default
        a[30:] = 13
        a[40:, :10] = 55
        Image.fromarray(a).save(lab / f"{f.index:06d}.png")
    cmap = tmp_path / "map.yaml"
    cmap.write_text(
        "classes:\n  - {id: 0, name: road, road: true}\n  - {id: 1, name: car, movable: true}\n"
        "  - {id: 2, name: other}\nremap: {13: road, 55: 1}\ndefault: other\n"
    )
    attach_label_folder(seq, lab, cmap)
    s = read_sequence(tmp_path / "seq")
    assert [c.name for c in s.classes] == ["road", "car", "other"] and s.road_class_ids == [0]
    m = load_semantics(s.path(s.frames[1].views["front"].semantics))
    assert (m[:30] == 2).all() and (m[30:40] == 0).all() and (m[40:, :10] == 1).all() and (m[40:, 10:] == 0).all()


def test_label_folder_preset_per_camera_and_errors(tmp_path):
    seq = _seq(tmp_path / "seq", n=2, cams=("front", "rear"))
    lab = tmp_path / "labels"
    for c in ("front", "rear"):
        (lab / c).mkdir(parents=True)
        for f in seq.frames:
            a = np.full((H, W), VISTAS_V12.index("construction--flat--road"), np.uint8)
            a[:10] = VISTAS_V12.index("nature--sky")
            Image.fromarray(a).save(lab / c / f"{f.index:06d}.png")
    attach_label_folder(seq, lab, "mapillary-vistas")
    s = read_sequence(tmp_path / "seq")
    m = load_semantics(s.path(s.frames[0].views["rear"].semantics))
    assert (m[:10] == 8).all() and (m[10:] == 0).all()  # sky 8, road 0 in RoMe's nuScenes table
    (lab / "rear" / "000001.png").unlink()
    with pytest.raises(SequenceError, match="no label PNG for frame 1 camera rear"):
        attach_label_folder(s, lab, "mapillary-vistas")
    Image.fromarray(np.zeros((H, W + 1), np.uint8)).save(lab / "rear" / "000001.png")
    with pytest.raises(SequenceError, match="label map is 65x48"):
        attach_label_folder(s, lab, "mapillary-vistas")
    Image.fromarray(np.full((H, W), 200, np.uint8)).save(lab / "rear" / "000001.png")
    (tmp_path / "ident.yaml").write_text("classes:\n  - {id: 0, name: road, road: true}\n  - {id: 1, name: car}\n")
    with pytest.raises(SequenceError, match=r"front/000000.png: label values \[13, 27\] are not in class map"):
        attach_label_folder(s, lab, tmp_path / "ident.yaml")


def test_corridor_fallback_warns_and_marks_road(tmp_path):
    seq = _seq(tmp_path / "seq", n=4)
    with pytest.warns(UserWarning, match="trajectory-corridor fallback"):
        corridor_semantics(seq, half_width=1.5, camera_height=1.5, step=2)
    s = read_sequence(tmp_path / "seq")
    m = load_semantics(s.path(s.frames[0].views["front"].semantics))
    # straight ahead below the horizon is road; far to the side at the bottom rows is not
    assert m[H - 2, W // 2] == 0 and m[30, W // 2] == 0
    # bottom-left corner (sampled at u=1, v=47): its ground point lies ~1.95 m left of the path
    lateral = 1.5 * (31.5 - 1) / (47 - 23.5)
    assert lateral > 1.5 and m[H - 1, 0] == 4 and m[H - 1, W - 1] == 4
    # last frame: the road ahead continues past the end of the driven path
    m3 = load_semantics(s.path(s.frames[3].views["front"].semantics))
    assert m3[30, W // 2] == 0
    assert (m[:20] == 7).all()  # well above the horizon: sky
    assert s.road_class_ids == [0, 1]


def test_ultralytics_semantic_backend(tmp_path, monkeypatch):
    import socket

    def no_net(self, addr):
        if self.family != socket.AF_UNIX:
            raise AssertionError(f"network access attempted: {addr!r}")

    monkeypatch.setattr(socket.socket, "connect", no_net)
    from pavemap.assets import prepare_ultralytics
    from pavemap.detect.compat import ensure_torchvision

    prepare_ultralytics(tmp_path / "cfg")
    ensure_torchvision()
    import torch
    from ultralytics import YOLO

    from pavemap.segment.yolo_seg import UltralyticsSegmenter

    torch.manual_seed(0)
    y = YOLO("yolo26n-sem.yaml")
    names = ["construction--flat--road", "nature--sky", "object--vehicle--car", "mystery"]
    y.model.names = {i: names[i % 4] for i in range(len(y.model.names))}
    w = tmp_path / "sem.pt"
    y.save(w)
    seg = UltralyticsSegmenter(w, "mapillary-vistas", imgsz=64, device="cpu")
    seq = _seq(tmp_path / "seq", n=1)
    segment_sequence(seq, seg)
    s = read_sequence(tmp_path / "seq")
    m = load_semantics(s.path(s.frames[0].views["front"].semantics))
    assert m.shape == (H, W)
    img = np.asarray(Image.open(s.path(s.frames[0].views["front"].image)))
    raw = seg.model.predict(np.ascontiguousarray(img[:, :, ::-1]), imgsz=64, device="cpu", verbose=False)[0]
    expect = {0: 0, 1: 8, 2: 6, 3: 7}  # road, sky, movable, other (mystery)
    want = np.vectorize(lambda c: expect[c % 4])(raw.semantic_mask.data.cpu().numpy())
    assert np.array_equal(m, want)
    det = tmp_path / "det.pt"
    YOLO("yolov8n.yaml").save(det)
    with pytest.raises(PavemapError, match="'detect' weights; the segmenter needs 'semantic'"):
        UltralyticsSegmenter(det, device="cpu")
