"""Long drives in segments (issue 17): the plan, the blend, gaps and standing frames (small, no rendering)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pavemap.geometry import GridSpec, HeightField
from pavemap.mesh.model import RoadMesh, build_grid
from pavemap.mesh.segments import moving_frames, path_metres, plan_segments, revisited_frames
from pavemap.mesh.setup import path_pieces
from pavemap.mesh.stitch import Stitcher, own_path, segment_weights


def _line(n: int, step: float) -> np.ndarray:
    return np.stack([np.arange(n) * step, np.zeros(n)], 1)


def test_plan_cuts_by_length_with_overlap():
    xy = _line(401, 1.0)  # 400 m
    plans = plan_segments(xy, 150.0, 20.0, 10.0)
    assert len(plans) == 3  # round(400 / 150)
    s = path_metres(xy)
    assert plans[0].core[0] == -math.inf and plans[-1].core[1] == math.inf
    for a, b in zip(plans[:-1], plans[1:], strict=True):
        cut = a.core[1]
        assert cut == pytest.approx(b.core[0])
        # both segments hold the frames 20 m either side of their seam
        assert s[a.own[-1]] >= cut + 19.0 and s[b.own[0]] <= cut - 19.0
    assert all(not p.revisit for p in plans)  # a straight road never comes back
    assert len(plan_segments(xy, 0.0, 20.0, 10.0)) == 1


def test_plan_reconstructs_road_driven_twice_once():
    """Out and back on the opposite lane: the way back is no segment's own road, the way out's segments hold
    its frames (one per revisit spacing) and own its road; the turn and a crossing stay with their own pass."""
    out = _line(201, 1.0)
    back = out[::-1] + [0.0, 3.5]  # U-turn: the opposite lane, 3.5 m over
    xy = np.concatenate([out, back[1:]])
    s = path_metres(xy)
    plans = plan_segments(xy, 100.0, 15.0, 10.0)
    # the way back revisits where it is more than 15 + 2 x 10 m of path past the way out's frame beside it
    again = revisited_frames(xy, 10.0, 35.0, 30.0)
    # (the 12th frame back lies within 10 m of the way out's frame 9.4 m behind it, 2 x 12 + 2.6 + 9.4 m of path before)
    assert not again[:212].any() and again[212:].all()
    assert len(plans) == 2  # 214 m of new road; 4 segments when each pass had its own
    assert plans[-1].core[1] == pytest.approx(0.5 * (s[211] + s[212]))
    own = set().union(*(p.own for p in plans))
    assert not own & set(range(240, 401))  # past the overlap the way back is no segment's own
    first = plans[0]
    got = np.array(first.revisit)
    assert xy[got, 1].min() == pytest.approx(3.5) and xy[got, 0].min() < 5 and xy[got, 0].max() < 140
    share = np.array(first.share)
    assert np.all(share[xy[got, 0] < 150] == 1.0)  # road the way back revisits: owned through the way out
    # each revisit frame is owned as the road of the way out beside it (the frame beside it, within 10 m)
    last = plans[-1]
    rx, at = xy[list(last.revisit), 0], np.array(last.revisit_at)
    beside = rx >= xy[last.own[0], 0]  # (the others look at its road from before its first own frame)
    assert rx.size and np.all(np.array(last.share) == 1.0) and np.abs(at - rx)[beside].max() <= 10.0
    # the turn's own frames on the way back (its overlap) are no revisit of their own segment
    assert not set(last.revisit) & set(last.own)
    # thinned to one revisit frame per 3 m of their pass: the same stretch of the other pass, a third of its views
    thin = plan_segments(xy, 100.0, 15.0, 10.0, revisit_spacing_m=3.0)
    assert [p.own for p in thin] == [p.own for p in plans]
    kept = np.array(thin[0].revisit)
    assert set(kept) <= set(first.revisit) and abs(len(kept) - len(first.revisit) / 3) <= 2
    # a crossing (a second road across the first) is too short a revisit: both passes keep their own road
    cross = np.concatenate([_line(201, 1.0), np.stack([np.full(200, 250.0), np.arange(200) - 100.0], 1)])
    cross = np.concatenate([cross[:201], np.linspace(cross[200], cross[201], 60)[1:-1], cross[201:]])
    assert not revisited_frames(cross, 10.0, 35.0, 30.0).any()


def test_standing_vehicle_frames_are_skipped():
    xy = np.concatenate([_line(50, 1.0), np.tile([[49.0, 0.0]], (1000, 1)), _line(50, 1.0) + [50.0, 0.0]])
    keep = moving_frames(xy, 0.1)
    assert keep.sum() == 100  # the moving frames only: the standing ones add nothing
    assert keep[0] and keep[-1]


def test_path_pieces_cut_at_a_gap_and_name_it():
    xy = np.concatenate([_line(50, 1.0), _line(50, 1.0) + [99.0, 0.0]])  # frames 49 and 50 lie 50 m apart
    said: list[str] = []
    pieces = path_pieces(xy, list(range(100)), said.append)
    assert [len(p) for p in pieces] == [50, 50]
    assert len(said) == 1 and "frames 49 and 50" in said[0] and "50 m apart" in said[0]
    # the crop follows the pieces: no surface in the middle of the gap
    grid = build_grid(pieces[0], 0.5, 4.0, pieces[1:])
    g = grid.spec
    i, j = int(round((74.0 - g.x0) / g.res)), int(round((0.0 - g.y0) / g.res))
    assert not grid.valid[j, i]
    assert path_pieces(_line(50, 1.0), list(range(50))) [0].shape == (50, 2)


def _tile(xy: np.ndarray, offset: float, res: float = 0.1, crop: float = 3.0, contested: bool = True) -> RoadMesh:
    """A tile of the plane z = 0.01 x + offset over the crop of ``xy``."""
    grid = build_grid(xy, res, crop)
    g = grid.spec
    X, Y = g.centres()
    h = torch.from_numpy((0.01 * X + offset).astype(np.float32))
    rgb = torch.full((g.ny, g.nx, 3), 0.5)
    sem = torch.zeros((g.ny, g.nx, 2))
    layer = torch.from_numpy((X > 10) & (X < 12) & grid.valid) if contested else None  # a vehicle, 2 m of road
    return RoadMesh(HeightField(g.x0, g.y0, g.res, h, torch.from_numpy(grid.valid)), rgb, sem, [0, 1], True,
                    torch.from_numpy(grid.valid.copy()), None, layer)


def _blend(offsets: tuple[float, float], contested: bool = True) -> tuple[RoadMesh, dict, GridSpec]:
    xy = _line(121, 1.0)  # 120 m, cut at 60 m, overlap 20 m
    s = path_metres(xy)
    plans = plan_segments(xy, 60.0, 20.0, 10.0)
    drive = build_grid(xy, 0.1, 3.0).spec
    st = Stitcher(drive)
    seams = []
    for plan, off in zip(plans, offsets, strict=True):
        own = xy[list(plan.own)]
        tile = _tile(own, off, contested=contested)
        from pavemap.mesh.segments import _tile_grid

        pxy, ps = own_path(own, s[list(plan.own)])
        w = segment_weights(_tile_grid(tile), pxy, ps, plan.core, 20.0, 3.2)
        seams.append(st.add(tile, w, plan.index + 1, plan.index or None))  # after the one before it on the path
    return st.mesh([0, 1], True), seams[1], drive


def test_blend_is_continuous_across_the_seam_and_measures_the_step():
    mesh, seam, g = _blend((0.0, 0.02))  # the second tile 2 cm higher
    assert seam["seam_median_abs_m"] == pytest.approx(0.02, abs=1e-4)
    h = mesh.surface.heights.numpy()
    j = int(round((0.0 - g.y0) / g.res))
    row = h[j] - 0.01 * (g.x0 + np.arange(g.nx) * g.res)  # the blend minus the plane
    x = g.x0 + np.arange(g.nx) * g.res
    assert np.allclose(row[x < 45], 0.0, atol=1e-4) and np.allclose(row[(x > 75) & (x < 115)], 0.02, atol=1e-4)
    # the 2 cm are shared out over the 20 m ramp: no step larger than 0.02 * 0.1 / 20 between cells
    assert np.abs(np.diff(row[(x > 1) & (x < 119)])).max() < 2e-4 + 1e-6
    assert mesh.observed.numpy()[j, (x > 1) & (x < 119)].all()
    c = mesh.contested.numpy()[j]  # the stitched texture says where a tile's texture may hold a vehicle
    assert c[(x > 10.05) & (x < 11.95)].all() and not c[(x < 9.95) | (x > 12.05)].any()
    unchecked, _, _ = _blend((0.0, 0.02), contested=False)  # tiles without the check: the drive has none
    assert unchecked.contested is None


def test_overlap_with_a_segment_not_before_it_on_the_path_is_no_seam():
    xy = _line(121, 1.0)
    s = path_metres(xy)
    plans = plan_segments(xy, 60.0, 20.0, 10.0)
    st = Stitcher(build_grid(xy, 0.1, 3.0).spec)
    from pavemap.mesh.segments import _tile_grid

    got = []
    for plan, off in zip(plans, (0.0, 0.02), strict=True):
        tile = _tile(xy[list(plan.own)], off)
        pxy, ps = own_path(xy[list(plan.own)], s[list(plan.own)])
        got.append(st.add(tile, segment_weights(_tile_grid(tile), pxy, ps, plan.core, 20.0, 3.2), plan.index + 1))
    # as another pass's segment would (a crossing): its disagreement is the passes', not a seam's
    assert got[1]["seam_cells"] == 0 and got[1]["pass_median_abs_m"] == pytest.approx(0.02, abs=1e-4)


def test_blend_of_agreeing_tiles_is_the_plane():
    mesh, seam, g = _blend((0.0, 0.0))
    assert seam["seam_median_abs_m"] == pytest.approx(0.0, abs=1e-5)
    s = mesh.surface
    v = s.valid.numpy()
    X, _ = g.centres()
    assert np.allclose(s.heights.numpy()[v], 0.01 * X[v], atol=1e-4)


def test_revisited_road_is_one_surface():
    """The way back 6 m beside the way out (beyond the way out's reach, within the revisit distance): the way out's
    segments own it through its frames, it is observed, and where the way back becomes its own again (the turn)
    the blend ramps without a step."""
    from pavemap.mesh.segments import _tile_grid

    out = _line(301, 1.0)
    xy = np.concatenate([out, out[::-1][1:] + [0.0, 6.0]])
    s = path_metres(xy)
    plans = plan_segments(xy, 100.0, 20.0, 10.0)
    st = Stitcher(build_grid(xy, 0.1, 3.0).spec)
    back = plans[-1]  # its core reaches round the turn onto the way back
    for plan in plans:
        tile = _tile(xy[list(plan.positions)], 0.02 if plan is back else 0.0)
        pxy, ps = own_path(xy[list(plan.own)], s[list(plan.own)])
        stats = st.add(tile, segment_weights(_tile_grid(tile), pxy, ps, plan.core, 20.0, 3.2, xy[list(plan.revisit)],
                                             np.array(plan.revisit_at), np.array(plan.share)),
                       plan.index + 1, plan.index or None)
    # the turn's segment meets the segment before it along the path (and beside the way back, where that one
    # owns the way back's road): 2 cm apart, reported as its seam; no other pass's segment shares its road
    assert stats["seam_median_abs_m"] == pytest.approx(0.02, abs=1e-4) and stats["pass_cells"] == 0
    m = st.mesh([0, 1], True)
    g = m.surface.grid
    X, Y = g.centres()
    resid = m.surface.heights.numpy() - 0.01 * X
    valid = m.surface.valid.numpy()
    lane = valid & (np.abs(Y - 6.0) < 1.0)
    # the way back's road far from the turn: the way out's segments' surface, owned (observed), one layer
    far = lane & (X > 20) & (X < 200)
    assert far.sum() > 1000 and np.allclose(resid[far], 0.0, atol=1e-4) and m.observed.numpy()[far].all()
    # towards the turn the way back's own segment takes over: continuous, at most the 2 cm over the 20 m ramp
    j = int(round((6.0 - g.y0) / g.res))
    x = g.x0 + np.arange(g.nx) * g.res
    row = resid[j][(x > 20) & (x < 298) & valid[j]]
    assert row.max() == pytest.approx(0.02, abs=1e-3)
    assert np.abs(np.diff(row)).max() < 2.5e-4


def test_a_standing_vehicle_is_skipped_before_training():
    """1,000 frames at one place: the whole-drive path drops them too, and says so."""
    from pavemap.mesh import MeshConfig
    from pavemap.mesh.segments import skip_standing
    from pavemap.types import Camera, Frame, Sequence, View

    def frame(i: int, x: float) -> Frame:
        T = np.eye(4)
        T[0, 3] = x
        return Frame(i, i * 0.1, {"c": View("c", f"images/{i}.png", T)})

    xs = [float(i) for i in range(40)] + [39.0] * 1000 + [40.0 + i for i in range(40)]
    seq = Sequence("s", [], {"c": Camera("c", 10, 10, np.eye(3))}, [frame(i, x) for i, x in enumerate(xs)])
    out, note = skip_standing(seq, MeshConfig())
    assert len(out.frames) == 80 and "1000 frame(s) skipped (frames 40..1039)" in note
    assert skip_standing(out, MeshConfig())[1] is None  # nothing standing left


def test_stitcher_holds_only_the_cells_of_its_tiles():
    """The blend's sums exist for the cells the tiles hold, not for the drive's grid box (a looped drive's box
    is ~10x its road): an L-shaped drive's sums cover its two arms' crops, and the mesh's vertices are those."""
    arm1 = _line(61, 1.0)
    arm2 = arm1[-1] + np.stack([np.zeros(60), np.arange(1, 61, dtype=float)], 1)
    xy = np.concatenate([arm1, arm2])
    box = build_grid(xy, 0.1, 3.0).spec
    st = Stitcher(box)
    union = set()
    from pavemap.mesh.segments import _tile_grid

    for part in (arm1, arm2):
        tile = _tile(part, 0.0)
        g = tile.surface.grid
        tj, ti = np.divmod(tile.vertex_ids.numpy(), g.nx)
        ox, oy = round((g.x0 - box.x0) / box.res), round((g.y0 - box.y0) / box.res)
        union |= set(((tj + oy) * box.nx + ti + ox).tolist())
        st.add(tile, np.ones(tile.surface.valid.shape, np.float32) * _tile_grid(tile).valid)
    assert len(st.cells) == len(union) < box.nx * box.ny / 4
    assert all(len(a) == len(union) for a in st.sums.values())
    m = st.mesh([0, 1], True)
    assert int(m.surface.valid.sum()) == len(union) and m.rgb.shape == (len(union), 3)
