"""The views vote on the road (pavemap.segment.road_vote): a road label that the other views of the same
ground contradict is relabelled, the road they agree on stays."""

from __future__ import annotations

import copy
import shutil

import numpy as np
import pytest

from pavemap.io.sequence import load_semantics, read_sequence
from pavemap.segment.road_vote import RoadVoteConfig, cell_keys, road_vote_sequence, tally, view_votes


def test_tally_one_vote_per_view_and_the_top_other_label():
    road_lut = np.zeros(256, dtype=bool)
    road_lut[0] = True
    keys = cell_keys(np.array([[0.05, 0.05]] * 3 + [[5.0, 5.0]]), 0.2)
    # a near view covers the cell with many road pixels, two far views with a few sidewalk (1) pixels each
    near = view_votes(np.repeat(keys[:1], 50), np.zeros(50, dtype=np.int64))
    far1 = view_votes(keys[:3], np.array([1, 1, 0]))
    far2 = view_votes(keys[:1], np.array([1]))
    lone = view_votes(keys[3:], np.array([0]))
    cells, share, other = tally([near, far1, far2, lone], road_lut, min_views=2)
    i = int(np.searchsorted(cells, keys[0]))
    assert share[i] == pytest.approx((1 + 1 / 3) / 3)  # one vote per view, not 51 road pixels to 3
    assert other[i] == 1
    assert np.isnan(share[np.searchsorted(cells, keys[3])])  # one view only: not judged


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    from pavemap.synth import synthesize

    root = tmp_path_factory.mktemp("vote") / "d"
    synthesize(root, preset="kitti-like", seed=0, frames=8, scale=0.25, depth="none", progress=False)
    return root


def _copy_labels(seq, work):
    seq = copy.deepcopy(seq)
    for f in seq.frames:
        for c, v in f.views.items():
            dst = work / c / f"{f.index:06d}.png"
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(seq.path(v.semantics), dst)
            v.semantics = str(dst)
    return seq


def test_a_wrong_road_label_in_one_view_is_outvoted(drive, tmp_path):
    from PIL import Image

    seq = read_sequence(drive)
    road_id = seq.road_class_ids[0]
    side = next(c.id for c in seq.classes if c.name == "sidewalk")
    work = _copy_labels(seq, tmp_path)
    # one frame's segmenter calls the sidewalk road (the side-camera mistake), the others are right
    bad = work.frames[4].views["CAM_FRONT"]
    lab = load_semantics(bad.semantics)
    wrong = lab == side
    assert wrong.sum() > 200
    Image.fromarray(np.where(wrong, road_id, lab).astype(np.uint8)).save(bad.semantics)
    truth_road = {f.index: np.isin(load_semantics(seq.path(f.views["CAM_FRONT"].semantics)), seq.road_class_ids)
                  for f in seq.frames}
    rep = road_vote_sequence(work, camera_height=1.65)
    assert rep.voted == len(seq.frames) and rep.relabelled_px > 0
    after = load_semantics(bad.semantics)
    near = wrong.copy()
    near[: lab.shape[0] // 2] = False  # the ground within the vote's range, below the horizon
    assert (after[near] == side).mean() > 0.7  # the wrong road is sidewalk again
    for f in work.frames:  # and the true road stays road
        kept = np.isin(load_semantics(f.views["CAM_FRONT"].semantics), seq.road_class_ids)[truth_road[f.index]]
        assert kept.mean() > 0.97


def test_no_camera_height_no_vote(drive, tmp_path):
    seq = _copy_labels(read_sequence(drive), tmp_path)
    for c in seq.cameras.values():
        c.height_m = None
    before = {f.index: load_semantics(f.views["CAM_FRONT"].semantics) for f in seq.frames}
    rep = road_vote_sequence(seq, None, RoadVoteConfig())
    assert rep.voted == 0 and rep.skipped == ["CAM_FRONT: no camera height known"]
    assert all((load_semantics(f.views["CAM_FRONT"].semantics) == before[f.index]).all() for f in seq.frames)
