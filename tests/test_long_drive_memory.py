"""Issue 17: a long drive's stage-1 memory depends on its segments, not on its length.

A 600-frame kitti-like drive (small images, sparse depth: the pixels held, not the ground points, are under test)
reconstructed whole and in segments, each in a fresh process: the growth of the process's peak resident memory
over its size before stage 1 must be well below the whole-drive path's.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

FRAMES = 600
SCALE = 0.25

_STAGE1 = """
import json, resource, sys
from pavemap.io.sequence import read_sequence
from pavemap.mesh import MeshConfig, reconstruct
import pavemap.mesh.segments, pavemap.mesh.train  # noqa: F401  (imports are not the drive's memory)
seq = read_sequence(sys.argv[1])
cfg = MeshConfig.preset("kitti")
cfg.device, cfg.segment_m, cfg.segment_overlap_m = "cpu", float(sys.argv[2]), 20.0
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
_, m = reconstruct(seq, None, cfg, progress=False)
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"growth_mb": (peak - before) / 1024, "segments": len(m.get("segments") or [1]),
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
    cut = _stage1(drive, 100.0)
    assert whole["segments"] == 1 and cut["segments"] >= 4
    # the whole drive holds every view's pixels at once; a segment holds its own ~1/5 of them
    assert whole["growth_mb"] > 150, whole
    assert cut["growth_mb"] < 0.6 * whole["growth_mb"], (cut, whole)
    assert cut["psnr"] > whole["psnr"] - 1.0  # and the cut drive is as good
