"""Shared fixtures: tiny synthetic sequences (rendered once per test session).

* ``tiny_seq``: kitti-like, 8 frames, one camera at scale 0.25 (310x94), with sim detections.
* ``tiny_nuscenes_seq``: nuscenes-like, 4 frames x 6 cameras at scale 0.15 (240x135), with sim detections.

Both return the Sequence (``seq.root`` is the folder). They also hold ``truth/`` (defects.geojson,
height.npy/json, world.json, instances) and ``detections.jsonl`` + ``truth/detections_truth.jsonl``.
Treat them as read-only: copy the folder (shutil.copytree) before changing anything.
"""

from __future__ import annotations

import pytest

from pavemap.io.sequence import read_sequence


@pytest.fixture(scope="session")
def tiny_seq(tmp_path_factory):
    from pavemap.synth import detect_sequence, synthesize

    root = tmp_path_factory.mktemp("synth") / "tiny_kitti"
    synthesize(root, preset="kitti-like", seed=0, frames=8, scale=0.25, progress=False, road_after=40.0)
    seq = read_sequence(root)
    detect_sequence(seq, seed=0)
    return read_sequence(root)


@pytest.fixture(scope="session")
def tiny_nuscenes_seq(tmp_path_factory):
    from pavemap.synth import detect_sequence, synthesize

    root = tmp_path_factory.mktemp("synth") / "tiny_nuscenes"
    synthesize(root, preset="nuscenes-like", seed=1, frames=4, scale=0.15, progress=False, road_after=45.0)
    seq = read_sequence(root)
    detect_sequence(seq, seed=0)
    return read_sequence(root)
