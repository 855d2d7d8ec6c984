"""The shipped detector and its COCO start: found from an installed package, read without foreign code."""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from pavemap.detect import backends
from pavemap.detect.pretrained import coco_start_checkpoint, read_yolov5_state
from pavemap.errors import PavemapError

REPO = Path(__file__).resolve().parents[1]
COCO = REPO.parent / "shared" / "data" / "pretrained" / "yolov5n-coco" / "yolov5n.pt"


@pytest.mark.skipif(not COCO.is_file(), reason="../shared/data/pretrained not present")
def test_coco_backbone_fits_ultralytics_yolov5n(tmp_path):
    state = read_yolov5_state(COCO)
    assert sum(k.startswith("model.24.") for k in state) > 0  # the anchor-based head is read but not used
    out = coco_start_checkpoint(COCO, tmp_path / "start.pt")
    from pavemap.detect.yolo import load_detector

    model = load_detector(out)
    assert model.names == {0: "D00", 1: "D10", 2: "D20", 3: "D40"}
    sd = model.model.state_dict()
    first = sd["model.0.conv.weight"].float()
    assert torch.allclose(first, state["model.0.conv.weight"], atol=1e-3)  # copied, not left random


def test_foreign_code_in_a_checkpoint_is_refused(tmp_path):
    class Evil:
        def __reduce__(self):
            return (os.system, ("echo pwned",))

    bad = tmp_path / "evil.pt"
    torch.save({"model": Evil()}, bad, pickle_module=pickle)
    with pytest.raises(PavemapError, match=r"evil\.pt: not a readable YOLOv5 checkpoint.*not allowed"):
        read_yolov5_state(bad)
    cut = tmp_path / "cut.pt"
    cut.write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(PavemapError, match=r"cut\.pt: not a readable"):
        read_yolov5_state(cut)
    with pytest.raises(PavemapError, match="not found"):
        read_yolov5_state(tmp_path / "missing.pt")


@pytest.mark.slow
def test_shipped_weights_load_from_an_installed_package(tmp_path):
    """A wheel installed outside the checkout finds and loads its detector, and writes nothing into the cwd."""
    target, cwd = tmp_path / "site", tmp_path / "elsewhere"
    cwd.mkdir()
    r = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                        "--no-index", "--target", str(target), str(REPO)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    code = ("import pavemap, pavemap.detect.backends as b, pavemap.detect.yolo as y;"
            "p = b.shipped_weights(); m = y.load_detector(p);"
            "print(pavemap.__file__); print(p); print(sorted(m.names.values()))")
    env = {**os.environ, "PYTHONPATH": str(target), "XDG_CACHE_HOME": str(tmp_path / "cache")}
    for k in ("PAVEMAP_CACHE", "YOLO_CONFIG_DIR", "PAVEMAP_YOLO_DIR"):
        env.pop(k, None)
    r = subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    pkg, weights, names = r.stdout.strip().splitlines()[-3:]
    assert pkg.startswith(str(target)) and weights.startswith(str(target))
    assert names == "['D00', 'D10', 'D20', 'D40']"
    assert list(cwd.iterdir()) == []  # no .yolo/ or anything else in the user's folder
    assert (tmp_path / "cache" / "pavemap" / "ultralytics").is_dir()


def test_shipped_weights_are_in_the_package():
    p = backends.shipped_weights()
    assert p.name == backends.SHIPPED_WEIGHTS and p.parent.name == "weights" and p.parent.parent.name == "pavemap"
    assert p.stat().st_size < 25 * 2**20
