"""Stage 2: sanitising, integral-image road ratio, mask sources, detection files."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
from PIL import Image

from pavemap.detect import box_ratio, filter_detections, load_detections, sanitize
from pavemap.detect.config import FilterConfig
from pavemap.types import Camera, Detection, Frame, SemanticClass, Sequence, View

W, H = 80, 60


def make_seq(root, semantics: list[np.ndarray | None]) -> Sequence:  # noqa: ANN001
    """One camera, one frame per semantic map (None = a view without semantics)."""
    K = np.array([[50.0, 0, W / 2], [0, 50.0, H / 2], [0, 0, 1]])
    frames = []
    for i, sem in enumerate(semantics):
        rel = None
        if sem is not None:
            rel = f"semantics/cam/{i:06d}.png"
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(sem.astype(np.uint8)).save(root / rel)
        frames.append(Frame(i, float(i), {"cam": View("cam", f"images/cam/{i:06d}.png", np.eye(4), rel)}))
    classes = [SemanticClass(0, "road", road=True), SemanticClass(1, "marking", road=True),
               SemanticClass(2, "sidewalk"), SemanticClass(5, "car", movable=True)]
    return Sequence("t", classes, {"cam": Camera("cam", W, H, K)}, frames, root=root)


def test_box_ratio_matches_brute_force() -> None:
    rng = np.random.default_rng(1)
    mask = rng.random((H, W)) < 0.4
    x1 = rng.uniform(-5, W - 3, 200)
    y1 = rng.uniform(-5, H - 3, 200)
    boxes = np.stack([x1, y1, x1 + rng.uniform(2, 30, 200), y1 + rng.uniform(2, 30, 200)], 1)
    got = box_ratio(mask, boxes)
    for b, g in zip(boxes, got, strict=True):
        cols = [c for c in range(W) if b[0] <= c <= b[2]]  # pixel centres inside the box
        rows = [r for r in range(H) if b[1] <= r <= b[3]]
        assert math.isclose(g, mask[np.ix_(rows, cols)].mean(), abs_tol=1e-12)


@pytest.mark.parametrize("shape", [(0, 4), (1, 1), (1, 9), (7, 1), (37, 53)])
def test_integral_image_is_the_zero_padded_summed_area_table(shape) -> None:
    """scikit-image's table, padded: each entry is the count of True pixels above and left of it."""
    from pavemap.detect.boxes import integral_image

    mask = np.random.default_rng(2).random(shape) < 0.5
    ii = integral_image(mask)
    assert ii.shape == (shape[0] + 1, shape[1] + 1) and ii.dtype == np.int64
    want = np.array([[mask[:r, :c].sum() for c in range(shape[1] + 1)] for r in range(shape[0] + 1)])
    assert np.array_equal(ii, want.reshape(ii.shape))


def test_box_ratio_scaled_mask() -> None:
    mask = np.zeros((H // 2, W // 2), dtype=bool)
    mask[H // 4:] = True  # lower half road at half resolution
    r = box_ratio(mask, np.array([[10, 40, 30, 58], [10, 2, 30, 20], [10, 20, 30, 39]]), scale=0.5)
    assert r[0] == 1.0 and r[1] == 0.0 and 0.3 < r[2] < 0.7


def test_sanitize_reasons_and_warning(tmp_path, caplog) -> None:  # noqa: ANN001
    seq = make_seq(tmp_path, [None, None])
    dets = [
        Detection(0, "cam", (10, 10, 20, 20), 0, 0.5),          # ok
        Detection(7, "cam", (10, 10, 20, 20), 0, 0.5),          # unknown frame
        Detection(1, "left", (10, 10, 20, 20), 0, 0.5),         # unknown camera
        Detection(0, "cam", (20, 10, 10, 20), 0, 0.5),          # inverted
        Detection(0, "cam", (100, 10, 120, 20), 0, 0.5),        # outside the image
        Detection(0, "cam", (10, 10, 10, 20), 0, 0.5),          # zero width
        Detection(0, "cam", (10, 10, 20, 20), 9, 0.5),          # unknown class
        Detection(0, "cam", (10, 10, 20, 20), 1, float("nan")),  # NaN conf
        Detection(0, "cam", (10, 10, 20, 20), 1, 1.5),          # conf > 1
        Detection(0, "cam", (float("nan"), 10, 20, 20), 1, 0.5),  # NaN box
        Detection(0, "cam", (-10, 50, 30, 70), 2, 0.5),         # partly outside: clipped, ok
    ]
    clean, reasons = sanitize(seq, dets)
    assert reasons == ["ok", "unknown_frame", "unknown_camera", "inverted_box", "outside_image", "outside_image",
                       "unknown_cls", "bad_conf", "bad_conf", "bad_box", "ok"]
    assert clean[-1].box == (0.0, 50.0, 30.0, 60.0)
    with caplog.at_level(logging.WARNING, logger="pavemap"):
        res = filter_detections(seq, dets, FilterConfig(tau_conf=0.05))
    kept, recs = res.kept, res.records
    assert len(kept) == 2 and [r["kept"] for r in recs].count(True) == 2
    assert "skipped 9 unusable detection(s)" in caplog.text and "#1 frame 7" in caplog.text
    assert "no semantic map" in caplog.text  # fallback: no mask, not filtered, but said so


def _road_bottom() -> np.ndarray:
    sem = np.full((H, W), 2, dtype=np.uint8)  # sidewalk
    sem[H // 2:] = 0
    sem[H // 2:, 38:42] = 1  # lane marking counts as road
    sem[40:, 60:] = 5  # a parked car on the road
    return sem


def test_frame_filter_and_conf(tmp_path) -> None:  # noqa: ANN001
    seq = make_seq(tmp_path, [_road_bottom()])
    dets = [
        Detection(0, "cam", (10, 35, 30, 55), 0, 0.5),   # road
        Detection(0, "cam", (10, 5, 30, 25), 0, 0.5),    # sidewalk
        Detection(0, "cam", (30, 35, 50, 55), 1, 0.5),   # road + marking
        Detection(0, "cam", (62, 42, 78, 58), 3, 0.9),   # on the car
        Detection(0, "cam", (10, 35, 30, 55), 0, 0.04),  # below tau_conf
        Detection(0, "cam", (10, 20, 30, 38), 0, 0.5),   # rows 20..38, road from 30: R = 9/19
    ]
    recs = filter_detections(seq, dets, FilterConfig(tau_conf=0.05, tau_road=0.5)).records
    assert [r["reason"] for r in recs] == ["kept", "off_road", "kept", "off_road", "low_conf", "off_road"]
    assert recs[0]["r_road"] == 1.0 and recs[1]["r_road"] == 0.0
    recs = filter_detections(seq, dets, FilterConfig(tau_conf=0.05, tau_road=0.3)).records
    assert recs[5]["reason"] == "kept"


class _FakeMesh:
    """Stands in for a RoadMesh: render_view is patched to return 'road everywhere'."""


def test_mesh_and_both_masks(tmp_path, monkeypatch) -> None:  # noqa: ANN001
    import torch

    import pavemap.mesh as mesh_mod

    def fake_render(mesh, camera, T, scale=1.0):  # noqa: ANN001, ANN202
        h, w = round(camera.height * scale), round(camera.width * scale)
        labels = torch.zeros((h, w), dtype=torch.long)
        labels[: h // 4] = 7  # sky, not road
        return {"labels": labels, "valid": torch.ones((h, w), dtype=torch.bool)}

    monkeypatch.setattr(mesh_mod, "render_view", fake_render, raising=False)
    seq = make_seq(tmp_path, [_road_bottom(), None])
    car = Detection(0, "cam", (62, 42, 78, 58), 3, 0.9)
    high = Detection(1, "cam", (10, 0, 30, 10), 0, 0.9)  # view 1 has no semantics: mesh fallback
    low = Detection(1, "cam", (10, 40, 30, 58), 0, 0.9)
    mesh = _FakeMesh()
    res = {}
    for mode in ("frame", "mesh", "both"):
        recs = filter_detections(seq, [car, high, low], FilterConfig(tau_conf=0.05, mask=mode), mesh=mesh).records
        res[mode] = [r["kept"] for r in recs]
    # The mesh mask shows road under the parked car (SPEC §5); the frame mask sees the car.
    assert res["frame"] == [False, False, True]
    assert res["mesh"] == [True, False, True]
    assert res["both"] == [False, False, True]


def test_mesh_mode_without_mesh_falls_back(tmp_path, caplog) -> None:  # noqa: ANN001
    seq = make_seq(tmp_path, [_road_bottom()])
    with caplog.at_level(logging.WARNING, logger="pavemap"):
        res = filter_detections(seq, [Detection(0, "cam", (10, 5, 30, 25), 0, 0.5)],
                                FilterConfig(tau_conf=0.05, mask="mesh"))
    recs = res.records
    assert res.mask_used == "frame" and res.mask_fallbacks == {"no_mesh": 1}
    assert recs[0]["reason"] == "off_road" and "needs a mesh" in caplog.text


def test_yolo_txt_folder(tmp_path) -> None:  # noqa: ANN001
    seq = make_seq(tmp_path, [None, None])
    lab = tmp_path / "labels" / "cam"
    lab.mkdir(parents=True)
    (lab / "000000.txt").write_text("0 0.5 0.5 0.25 0.5 0.8\n3 0.1 0.9 0.1 0.1\n")
    (lab / "000001.txt").write_text("7 0.5 0.5 0.2 0.2 0.3\n")
    (lab / "999999.txt").write_text("0 0.5 0.5 0.2 0.2 0.3\n")  # no such image: skipped with a warning
    dets = load_detections(tmp_path / "labels", seq)
    assert len(dets) == 3
    assert dets[0].box == pytest.approx((30.0, 15.0, 50.0, 45.0)) and dets[0].conf == 0.8
    assert dets[1].conf == 1.0 and dets[1].cls == 3 and dets[2].frame == 1
    recs = filter_detections(seq, dets, FilterConfig(tau_conf=0.05)).records
    assert recs[2]["reason"] == "unknown_cls"


def test_yolo_txt_bad_line(tmp_path) -> None:  # noqa: ANN001
    from pavemap.io.sequence import SequenceError

    seq = make_seq(tmp_path, [None])
    lab = tmp_path / "labels" / "cam"
    lab.mkdir(parents=True)
    (lab / "000000.txt").write_text("0 0.5 0.5\n")
    with pytest.raises(SequenceError, match="000000.txt: line 1"):
        load_detections(tmp_path / "labels", seq)


def test_jsonl_file(tmp_path) -> None:  # noqa: ANN001
    from pavemap.io.sequence import write_detections

    seq = make_seq(tmp_path, [None])
    write_detections(tmp_path / "d.jsonl", [Detection(0, "cam", (1, 2, 3, 4), 2, 0.5)])
    (d,) = load_detections(tmp_path / "d.jsonl", seq)
    assert d.box == (1, 2, 3, 4) and d.cls == 2
