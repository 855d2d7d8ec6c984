"""Simulated detector: statistics follow the configuration; truth side file is aligned and honest."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from pavemap.errors import PavemapError
from pavemap.io.sequence import DETECTIONS_FILE, load_semantics, read_detections, read_sequence
from pavemap.synth import SimDetectorConfig, detect_sequence, read_detection_truth, synthesize


@pytest.fixture(scope="module")
def busy_seq(tmp_path_factory):
    """Many defects in view: enough (defect, view) pairs for statistics."""
    root = tmp_path_factory.mktemp("simdet") / "busy"
    synthesize(root, preset="kitti-like", seed=5, frames=16, scale=0.5, depth="none", progress=False,
               defect_density=70.0, road_after=35.0)
    return read_sequence(root)


def _visible_pairs(seq, min_pixels: int) -> int:
    n = 0
    for f in seq.frames:
        for cam, v in f.views.items():
            with Image.open(seq.root / "truth" / "instances" / cam / Path(v.image).name) as im:
                low = np.asarray(im).astype(np.int64) & 0x3FFF
            ids = low[(low > 0) & (low < 10000)]
            n += int((np.bincount(ids) >= min_pixels).sum())
    return n


@pytest.mark.parametrize(("miss", "offroad"), [(0.2, 0.35), (0.5, 0.2)])
def test_statistics_follow_config(busy_seq, tmp_path, miss, offroad):
    cfg = SimDetectorConfig(miss_rate=miss, offroad_share=offroad, onroad_fp_share=0.05, confusion=0.1)
    out = tmp_path / "dets.jsonl"
    n = detect_sequence(busy_seq, seed=3, out=out, config=cfg)
    dets = read_detections(out)
    truth = read_detection_truth(busy_seq.root)
    assert n == len(dets) == len(truth) > 50
    visible = _visible_pairs(busy_seq, cfg.min_pixels)
    n_true = sum(t["true"] for t in truth)
    assert visible > 100, visible
    assert abs((1 - n_true / visible) - miss) < 0.07, (n_true, visible)
    share = np.mean([t["offroad"] for t in truth])
    assert abs(share - offroad) < 0.04, share
    # each true detection really is one of its defect's class most of the time (confusion 10 %)
    wrong = np.mean([d.cls != t["cls_true"] for d, t in zip(dets, truth, strict=True) if t["true"]])
    assert wrong < 0.2
    assert {t["source"] for t in truth if not t["true"]} & {"vehicle", "building", "vegetation", "streak"}


def test_offroad_flag_is_measured_from_semantics(busy_seq, tmp_path):
    out = tmp_path / "d.jsonl"
    detect_sequence(busy_seq, seed=0, out=out)
    dets = read_detections(out)
    truth = read_detection_truth(busy_seq.root)
    frames = busy_seq.frame_by_index()
    road = busy_seq.class_lut("road")
    for d, t in list(zip(dets, truth, strict=True))[:80]:
        v = frames[d.frame].views[d.camera]
        sem = load_semantics(busy_seq.root / v.semantics)
        H, W = sem.shape
        x1, y1, x2, y2 = (int(round(c)) for c in d.box)
        assert 0 <= x1 < x2 <= W and 0 <= y1 < y2 <= H
        frac = road[sem[y1:y2, x1:x2]].mean()
        assert (frac <= 0.5) == t["offroad"], (frac, t)
        if t["true"]:  # a true box covers pixels of its own defect
            with Image.open(busy_seq.root / "truth" / "instances" / d.camera / Path(v.image).name) as im:
                inst = np.asarray(im).astype(np.int64) & 0x3FFF
            pad = 3
            win = inst[max(0, y1 - pad): y2 + pad, max(0, x1 - pad): x2 + pad]
            assert (win == t["defect_id"] + 1).any()


def test_same_seed_same_detections_and_default_path(tiny_seq, tmp_path):
    root = tmp_path / "copy"
    shutil.copytree(tiny_seq.root, root)
    seq = read_sequence(root)
    n1 = detect_sequence(seq, seed=11)
    a = (root / DETECTIONS_FILE).read_bytes()
    n2 = detect_sequence(seq, seed=11)
    assert n1 == n2 and a == (root / DETECTIONS_FILE).read_bytes()
    detect_sequence(seq, seed=12)
    assert a != (root / DETECTIONS_FILE).read_bytes()
    read_sequence(root)  # detections validate against the folder


def test_needs_synthetic_truth(tiny_seq, tmp_path):
    root = tmp_path / "copy"
    shutil.copytree(tiny_seq.root, root)
    shutil.rmtree(root / "truth" / "instances")
    with pytest.raises(PavemapError, match="synthetic"):
        detect_sequence(read_sequence(root))
    with pytest.raises(PavemapError, match="miss_rate"):
        detect_sequence(tiny_seq, config=SimDetectorConfig(miss_rate=1.5))


def test_cli_detect_sim(tiny_nuscenes_seq, tmp_path):
    from typer.testing import CliRunner

    from pavemap.cli import app

    root = tmp_path / "copy"
    shutil.copytree(tiny_nuscenes_seq.root, root)
    res = CliRunner().invoke(app, ["detect", str(root), "--detector", "sim", "--seed", "2"])
    assert res.exit_code == 0, res.output
    assert len(read_detections(root / DETECTIONS_FILE)) == len(read_detection_truth(root))


def test_contact_sheet(tiny_nuscenes_seq, tmp_path):
    from pavemap.synth import contact_sheet

    out = contact_sheet(tiny_nuscenes_seq.root, tmp_path / "sheet.png", n_frames=2)
    with Image.open(out) as im:
        assert im.width >= 6 * 200 and im.height > 200
        a = np.asarray(im.convert("RGB"))
    assert a.std() > 20  # not a blank canvas


def test_views_are_kept_compact_and_expand_to_their_pixel_pools(busy_seq):
    """A drive's views stay in memory while false positives are drawn: each keeps a compressed pixel-code map
    (not int64 index arrays), and expanding it gives exactly the pools read from the view's own files."""
    from pavemap.synth import simdetector as sd

    names = {c.name: c.id for c in busy_seq.classes}
    road_lut = busy_seq.class_lut("road")
    f = busy_seq.frames[3]
    cam = next(iter(f.views))
    view, road_ii, _ = sd._load_view(busy_seq, f, cam, names, road_lut, sd.SimDetectorConfig())
    assert len(view.code) < view.W * view.H // 4  # compressed: a fraction of one byte a pixel
    kept: list = []
    pools, ii = view.expand(kept)
    assert np.array_equal(ii, road_ii) and kept == [view]
    sem = load_semantics(busy_seq.root / f.views[cam].semantics)
    with Image.open(busy_seq.root / "truth" / "instances" / cam / Path(f.views[cam].image).name) as im:
        shadow = (np.asarray(im).astype(np.int64) & sd.SHADOW_BIT) > 0
    road = road_lut[sem]
    assert np.array_equal(pools["road"], np.flatnonzero(road))
    assert np.array_equal(pools["vehicle"], np.flatnonzero(sem == names["vehicle"]))
    assert np.array_equal(pools["vegetation"], np.flatnonzero(sem == names["terrain"]))
    assert np.array_equal(pools["road_shadow"], np.flatnonzero(shadow & road))
    assert np.array_equal(pools["shadow"], np.flatnonzero(shadow & ~road))
    assert view.sizes == {k: len(v) for k, v in pools.items()}
    # only a few views stay expanded at once: the oldest is dropped back to its compressed form
    others = [sd._load_view(busy_seq, g, cam, names, road_lut, sd.SimDetectorConfig())[0]
              for g in busy_seq.frames[: sd._EXPANDED_KEEP]]
    for o in others:
        o.expand(kept)
    assert len(kept) == sd._EXPANDED_KEEP and view._expanded is None
    assert all(o._expanded is not None for o in others)
