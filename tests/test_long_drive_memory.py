"""Issue 17: a long drive's stage-1 memory depends on its segments, not on its length.

A 300-frame kitti-like drive (sparse depth, small images: fast) reconstructed whole and in 60 m segments, each
in a fresh process: the growth of the process's peak resident memory over its size before stage 1 must be well
below the whole-drive path's. Measured when written at 600 frames: 3.4 GB whole (its grids and fits over 600 m of
road, hardly the pixels: the same at a quarter and at 0.15 of the image size), 0.39 GB in 6 segments of 100 m; at
300 frames (2026-12-05, to keep the suite short: 48 s instead of 145 s) 0.67 GB whole, 0.25 GB in 5 segments.
The peak is the child's own address space (pavemap.memory): ru_maxrss is inherited across exec, and under a big
pytest parent it read a growth of 0."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

FRAMES = 300
SCALE = 0.15

_STAGE1 = """
import json, sys
from pavemap.io.sequence import read_sequence
from pavemap.memory import peak_rss_mb
from pavemap.mesh import MeshConfig, reconstruct
import pavemap.mesh.segments, pavemap.mesh.train  # noqa: F401  (imports are not the drive's memory)
seq = read_sequence(sys.argv[1])
cfg = MeshConfig.preset("kitti")
cfg.device, cfg.segment_m, cfg.segment_overlap_m = "cpu", float(sys.argv[2]), 20.0
before = peak_rss_mb()
_, m = reconstruct(seq, None, cfg, progress=False)
print(json.dumps({"growth_mb": peak_rss_mb() - before, "segments": len(m.get("segments") or [1]),
                  "psnr": m.get("psnr")}))
"""


def _stage1(seq_dir, segment_m: float) -> dict:
    got = subprocess.run([sys.executable, "-c", _STAGE1, str(seq_dir), str(segment_m)], capture_output=True,
                         text=True, timeout=900)
    assert got.returncode == 0, got.stderr[-3000:]
    return json.loads(got.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    from pavemap.synth import synthesize

    root = tmp_path_factory.mktemp("long-memory") / "seq"
    synthesize(root, "kitti-like", seed=4, frames=FRAMES, scale=SCALE, depth="sparse", progress=False)
    return root


def test_segments_bound_stage_one_memory(drive):
    whole = _stage1(drive, 0.0)
    cut = _stage1(drive, 60.0)
    assert whole["segments"] == 1 and cut["segments"] >= 4
    # the whole drive holds every view's pixels at once; a segment holds its own ~1/5 of them
    assert whole["growth_mb"] > 150, whole
    assert cut["growth_mb"] < 0.6 * whole["growth_mb"], (cut, whole)
    print("stage-1 memory growth, whole / cut:", whole, cut)
    # and the cut drive is still a reconstruction (at 600 frames 100 m segments cost ~1.2 dB, here 60 m ones
    # 0.04 dB: small tiles, short overlaps; the long-drive bench measures the cost at its own settings)
    assert cut["psnr"] > whole["psnr"] - 2.0


def test_a_child_process_peak_is_its_own_not_its_parents():
    """The measurement itself: a small child of a parent that has touched 400 MB more reads its own peak."""
    import numpy as np

    from pavemap.memory import peak_rss_mb

    ballast = np.ones(400 * 2**20 // 8)  # touched pages: the parent's resident set grows by 400 MB
    parent = peak_rss_mb()
    child = subprocess.run([sys.executable, "-c", "from pavemap.memory import peak_rss_mb; print(peak_rss_mb())"],
                           capture_output=True, text=True, timeout=120, check=True)
    del ballast
    assert float(child.stdout.strip()) < parent - 300, (child.stdout, parent)
