"""The ESPNet / ESPNetv2 segmenter: a real nuScenes frame, weight errors, grey images, a drive without semantics."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from pavemap.errors import PavemapError

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
CLIP = DATA / "nuscenes-front-clip" / "images"
PRETRAINED = DATA / "pretrained"
V1 = PRETRAINED / "espnet-cityscapes" / "espnet_p_2_q_8.pth"
V2 = PRETRAINED / "espnetv2-cityscapes" / "espnetv2_s_2.0_city_1024x512.pth"
needs_data = pytest.mark.skipif(not (CLIP.is_dir() and V1.is_file() and V2.is_file()),
                                reason="../shared/data (nuScenes clip, pretrained weights) not present")


@needs_data
def test_real_frame_road_fraction_and_bonnet_masked():
    """nuScenes CAM_FRONT (Boston street): road a sane share of the frame, the parked cars movable, and the
    white bonnet (bottom ~12 %, which the model alone calls road) labelled ego through the clip's ego mask."""
    import cv2

    from pavemap.io.egomask import detect_ego_mask
    from pavemap.io.sequence import load_rgb
    from pavemap.segment.espnet import EspnetSegmenter

    paths = sorted(CLIP.glob("*.jpg"))
    img = cv2.resize(load_rgb(paths[6]), (640, 360), interpolation=cv2.INTER_AREA)  # a small real frame
    ego = detect_ego_mask(paths, 640, 360)
    seg = EspnetSegmenter(device="cpu", width=768)
    ids = {c.name: c.id for c in seg.classes}
    bare, lab = seg.segment([img, img], ego=[None, ego])
    road = (lab == ids["road"]).mean()
    assert 0.2 < road < 0.6, road
    assert np.isin(lab, [c.id for c in seg.classes if c.movable and c.name != "ego"]).mean() > 0.005  # cars
    bottom = slice(int(0.93 * 360), 360)
    assert ego[bottom].mean() > 0.9  # the bonnet was found ...
    assert (bare[bottom] == ids["road"]).mean() > 0.5  # ... the model alone calls it road ...
    assert (lab[bottom] == ids["road"]).mean() < 0.05 and (lab[bottom] == ids["ego"]).mean() > 0.9  # ... masked
    assert (lab[: int(0.3 * 360)] == ids["sky"]).mean() > 0.1  # the sky over the street


@needs_data
def test_sfm_masks_and_semantics_label_each_image_once(tmp_path, monkeypatch):
    """An SfM import labels its keyframes for the vehicle masks; the sequence's semantics then reuse those labels
    (same pixels, same network): the network runs once per image, and the labels are the same as fresh ones."""
    import cv2

    from pavemap.io.sequence import load_rgb
    from pavemap.segment.espnet import EspnetSegmenter
    from pavemap.segment.movers import movable_masks

    paths = []
    for k, p in enumerate(sorted(CLIP.glob("*.jpg"))[:3]):
        paths.append(tmp_path / f"{k}.png")
        cv2.imwrite(str(paths[-1]), cv2.resize(cv2.imread(str(p)), (480, 270), interpolation=cv2.INTER_AREA))
    masks, _ = movable_masks("espnetv2", V2, device="cpu")
    seg = masks.segmenter
    runs = []
    real = seg.logits
    monkeypatch.setattr(seg, "logits", lambda ims: runs.append(len(ims)) or real(ims))
    for p in paths:
        assert masks(p) is not None
    imgs = [load_rgb(p) for p in paths]
    again = seg.segment(imgs)
    assert runs == [1, 1, 1]  # the second pass came from memory
    fresh = EspnetSegmenter("espnetv2", V2, device="cpu").segment(imgs)
    assert all(np.array_equal(a, b) for a, b in zip(again, fresh, strict=True))
    other = imgs[0].copy()
    other[:10] = 255  # other pixels: labelled anew
    seg.segment([other])
    assert runs == [1, 1, 1, 1]


def test_missing_weights_name_the_file_and_where_to_put_it(tmp_path, monkeypatch):
    from pavemap.segment import espnet

    monkeypatch.setattr(espnet, "weight_dirs", lambda: [tmp_path / "env", tmp_path / "cache"])
    for arch in ("espnet", "espnetv2"):
        with pytest.raises(PavemapError) as e:
            espnet.EspnetSegmenter(arch, device="cpu")
        msg = str(e.value)
        assert espnet.ARCHS[arch].file in msg and str(tmp_path / "cache") in msg and "--segmenter-weights" in msg
        assert "\n" not in msg
    with pytest.raises(PavemapError, match=r"nope\.pth: segmenter weights not found"):
        espnet.EspnetSegmenter("espnet", weights=tmp_path / "nope.pth", device="cpu")


def test_run_cli_missing_weights_is_one_line(tiny_seq, tmp_path):
    import subprocess
    import sys

    seq = tmp_path / "seq"
    shutil.copytree(tiny_seq.root, seq)
    _strip_semantics(seq)
    proc = subprocess.run([sys.executable, "-m", "pavemap.cli", "run", str(seq), "--out", str(tmp_path / "r"),
                           "--detector", "file", "--segmenter", "espnetv2", "--segmenter-weights",
                           str(tmp_path / "none.pth")],
                          capture_output=True, text=True)
    assert proc.returncode != 0 and "none.pth: segmenter weights not found" in proc.stderr
    assert "Traceback" not in proc.stderr


@needs_data
def test_bad_weight_files_are_one_line_errors(tmp_path):
    import torch

    from pavemap.segment.espnet import EspnetSegmenter

    with pytest.raises(PavemapError, match=r"not espnet weights .*look like espnetv2"):
        EspnetSegmenter("espnet", weights=V2, device="cpu")
    sd = torch.load(V1, map_location="cpu", weights_only=True)
    sd["classifier.weight"] = sd["classifier.weight"][:19, :19]
    torch.save(sd, tmp_path / "c19.pth")
    with pytest.raises(PavemapError, match=r"c19\.pth: the weights have 19 output classes"):
        EspnetSegmenter("espnet", weights=tmp_path / "c19.pth", device="cpu")
    (tmp_path / "cut.pth").write_bytes(V1.read_bytes()[:50_000])
    with pytest.raises(PavemapError, match=r"cut\.pth: not a readable PyTorch weight file"):
        EspnetSegmenter("espnet", weights=tmp_path / "cut.pth", device="cpu")
    (tmp_path / "text.pth").write_text("hello")
    with pytest.raises(PavemapError, match=r"text\.pth: not a readable"):
        EspnetSegmenter("espnet", weights=tmp_path / "text.pth", device="cpu")


def test_grey_images_are_refused_naming_the_file(tiny_seq, tmp_path):
    import cv2

    from pavemap.io.sequence import read_sequence
    from pavemap.segment.auto import GreyImagesError, check_colour

    seq = tmp_path / "seq"
    shutil.copytree(tiny_seq.root, seq)
    s = read_sequence(seq)
    check_colour(s)  # colour: fine
    for f in s.frames:
        for v in f.views.values():
            p = s.path(v.image)
            cv2.imwrite(str(p), cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2GRAY))
    with pytest.raises(GreyImagesError, match=r"000000\.png: grey image"):
        check_colour(s)


def _strip_semantics(seq: Path) -> None:
    d = json.loads((seq / "sequence.json").read_text())
    for f in d["frames"]:
        for v in f["views"].values():
            v["semantics"] = None
    (seq / "sequence.json").write_text(json.dumps(d))
    shutil.rmtree(seq / "semantics")


@needs_data
def test_drive_without_semantics_runs_end_to_end_with_the_segmenter(tiny_seq, tmp_path):
    """Semantics withheld: ``run`` labels the drive into the run folder (not the sequence folder), every stage
    reads those maps, and the road it finds overlaps the synthetic truth."""
    import pavemap
    from pavemap.config import load_config
    from pavemap.io.sequence import load_semantics, read_sequence

    seq = tmp_path / "seq"
    shutil.copytree(tiny_seq.root, seq)
    truth = {f.index: load_semantics(tiny_seq.path(f.views["CAM_FRONT"].semantics)) for f in tiny_seq.frames}
    _strip_semantics(seq)
    before = sorted(p.relative_to(seq) for p in seq.rglob("*"))
    cfg = load_config("kitti")
    cfg.device, cfg.mesh.epochs, cfg.detector.backend = "cpu", 1, "file"
    cfg.output.figures = cfg.output.report = False
    out = tmp_path / "run"
    result = pavemap.run(read_sequence(seq), cfg, out, progress=False, segmenter="espnetv2")
    assert result.metrics["semantics"].startswith("espnetv2 segmenter")
    assert sorted(p.relative_to(seq) for p in seq.rglob("*")) == before  # the sequence folder is untouched
    labs = sorted((out / "semantics" / "CAM_FRONT").glob("*.png"))
    assert len(labs) == len(tiny_seq.frames)
    assert not result.metrics["mask_fallbacks"].get("no_semantics")  # the filter used the segmenter's maps
    road_t = tiny_seq.class_lut("road")
    inter = union = 0
    for p in labs:
        pred, tr = load_semantics(p) == 0, road_t[truth[int(p.stem)]]
        inter, union = inter + (pred & tr).sum(), union + (pred | tr).sum()
    assert inter / union > 0.5, inter / union
    again = pavemap.run(read_sequence(seq), cfg, out, progress=False, segmenter="espnetv2")
    assert "reused" in again.metrics["semantics"]
