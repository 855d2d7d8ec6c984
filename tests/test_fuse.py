"""Stage 3: association modes, accumulators, instances, maps on a flat synthetic scene."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pavemap.detect.config import FilterConfig
from pavemap.export.run_files import write_fusion_outputs
from pavemap.fuse import FusionConfig, FusionResult
from pavemap.fuse.accumulate import Accumulators, accumulate, probability
from pavemap.fuse.associate import ASSOCIATIONS, DetectionBatch, associate_ray, window_pairs
from pavemap.fuse.config import AssociationMode
from pavemap.geometry import HeightField, pixel_rays, project
from pavemap.types import Camera, Detection, Frame, SemanticClass, Sequence, View

W, H, F = 640, 360, 400.0


def cam_pose(x: float, y: float = 0.0, height: float = 1.5, pitch_deg: float = 20.0) -> np.ndarray:
    """Camera at (x, y, height) looking along world +x, pitched down."""
    t = math.radians(pitch_deg)
    z = np.array([math.cos(t), 0.0, -math.sin(t)])
    xa = np.array([0.0, -1.0, 0.0])
    ya = np.cross(z, xa)
    T = np.eye(4)
    T[:3, :3] = np.stack([xa, ya, z], 1)
    T[:3, 3] = [x, y, height]
    return T


def make_seq(n_frames: int = 5, step: float = 1.0, root=None, semantics: bool = False) -> Sequence:  # noqa: ANN001
    K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])
    cams = {"front": Camera("front", W, H, K)}
    frames = [Frame(i, float(i), {"front": View("front", f"images/front/{i:06d}.png", cam_pose(i * step),
                                                 f"semantics/front/{i:06d}.png" if semantics else None)})
              for i in range(n_frames)]
    classes = [SemanticClass(0, "road", road=True), SemanticClass(1, "sidewalk"), SemanticClass(2, "car", movable=True)]
    return Sequence("flat", classes, cams, frames, root=root)


def box_of(seq: Sequence, frame: int, centre_xy: tuple[float, float], half: float = 0.2) -> tuple | None:
    """Bounding box in the image of a square of half-size ``half`` m on the plane z = 0."""
    v = seq.frames[frame].views["front"]
    cx, cy = centre_xy
    pts = torch.tensor([[cx + a, cy + b, 0.0] for a in (-half, half) for b in (-half, half)], dtype=torch.float64)
    uv, depth = project(seq.cameras["front"].K, v.T_world_cam, pts)
    if (depth <= 0).any():
        return None
    uv = uv.numpy()
    x1, y1 = uv.min(0)
    x2, y2 = uv.max(0)
    if x1 < 0 or y1 < 0 or x2 > W or y2 > H:
        return None
    return (float(x1), float(y1), float(x2), float(y2))


DEFECTS = [((9.0, 0.5), 0), ((11.0, -1.2), 3), ((13.5, 1.0), 2)]


def detections_for(seq: Sequence, defects=DEFECTS, conf: float = 0.6) -> list[Detection]:  # noqa: ANN001
    out = []
    for f in seq.frames:
        for xy, cls in defects:
            b = box_of(seq, f.index, xy)
            if b is not None:
                out.append(Detection(f.index, "front", b, cls, conf))
    return out


def run_fusion(seq: Sequence, dets: list[Detection], surface: HeightField, cfg: FusionConfig | None = None,
               mesh: object | None = None, filt: FilterConfig | None = None) -> FusionResult:
    """Stage 2's filter, then stage 3, chained as the pipeline does."""
    from pavemap.pipeline import filter_and_fuse

    return filter_and_fuse(seq, dets, surface, filt or FilterConfig(tau_conf=0.05), cfg or FusionConfig(), mesh=mesh,
                           progress=False)


@pytest.fixture()
def plane() -> HeightField:
    return HeightField.plane(0.0, -5.0, 0.1, 251, 101)


@pytest.mark.parametrize("mode", ["hit", "footprint", "ray"])
def test_modes_localise_defects(plane: HeightField, mode: str) -> None:
    seq = make_seq()
    dets = detections_for(seq)
    cfg = FusionConfig(association=mode, n_min=2)
    res = run_fusion(seq, dets, plane, cfg)
    assert res.metrics["valid_detections"] == len(dets)
    assert res.metrics["msr"] == 1.0
    assert len(res.instances) == len(DEFECTS)
    for (xy, cls) in DEFECTS:
        best = min(res.instances, key=lambda i: math.dist(i.centroid, xy))
        # The ray mode spreads along the viewing direction (its streak), so it is looser in x.
        tol = 0.6 if mode == "ray" else 0.1
        assert math.dist(best.centroid, xy) < tol, (mode, best.centroid, xy)
        assert best.cls == cls
        assert best.observations == sum(1 for d in dets if d.cls == cls)
    if mode == "footprint":
        # The 0.4 m square's footprint: area close to 0.16 m2 (cells of 0.01 m2 at its border).
        areas = sorted(i.area_m2 for i in res.instances)
        assert all(0.1 <= a <= 0.4 for a in areas), areas


def test_ray_mode_matches_brute_force(plane: HeightField) -> None:
    """Spatial pruning must find exactly the vertices a full scan within d_thresh finds."""
    seq = make_seq(3)
    dets = detections_for(seq)
    K = torch.tensor(np.array([seq.cameras["front"].K] * len(dets)))
    T = torch.tensor(np.array([seq.frames[d.frame].views["front"].T_world_cam for d in dets]))
    boxes = torch.tensor([d.box for d in dets], dtype=torch.float64)
    conf = torch.tensor([0.3] * len(dets), dtype=torch.float64)
    batch = DetectionBatch(boxes, K, T, conf)
    o, d = batch.centre_rays()
    cfg = FusionConfig(association="ray", beta0=2.5, beta1=1.0)
    asc = associate_ray(plane, batch, cfg)
    V = plane.vertices().double()
    lam = (((V[None] - o[:, None]) * d[:, None]).sum(-1) / (d * d).sum(-1)[:, None]).clamp(min=0)
    dist = (V[None] - (o[:, None] + lam[..., None] * d[:, None])).norm(dim=-1)
    thr = 2.5 * plane.res + 1.0 * (1 - 0.3)
    ref = torch.nonzero(dist < thr)
    got = torch.stack([asc.det, asc.vid], 1)
    assert sorted(map(tuple, ref.tolist())) == sorted(map(tuple, got.tolist()))
    assert torch.allclose(asc.distance, dist.min(1).values, atol=1e-5)  # float32 vertex grid


def test_batched_pixel_rays_match_single_view() -> None:
    """The batched form (one K / pose per pixel) the association uses equals the single-view form."""
    seq = make_seq(1)
    K = seq.cameras["front"].K
    T = seq.frames[0].views["front"].T_world_cam
    uv = torch.tensor([[10.0, 20.0], [300.5, 200.0]], dtype=torch.float64)
    o1, d1 = pixel_rays(K, T, uv)
    o2, d2 = pixel_rays(torch.tensor(np.array([K, K])), torch.tensor(np.array([T, T])), uv)
    assert torch.allclose(o1, o2) and torch.allclose(d1, d2)


def test_association_table_matches_the_config_modes() -> None:
    """One table of association modes, one signature; the config's Literal lists exactly its keys."""
    import inspect
    import typing

    assert set(ASSOCIATIONS) == set(typing.get_args(AssociationMode))
    sigs = {tuple(inspect.signature(f).parameters) for f in ASSOCIATIONS.values()}
    assert sigs == {("hf", "dets", "cfg")}
    with pytest.raises(Exception, match="fusion.association"):
        FusionConfig(association="nearest")  # type: ignore[arg-type]


def test_window_pairs_ragged() -> None:
    owner, i, j = window_pairs(torch.tensor([0, 5, 3]), torch.tensor([0, 2, 1]),
                               torch.tensor([1, 5, 2]), torch.tensor([1, 4, 0]))
    got = sorted(zip(owner.tolist(), i.tolist(), j.tolist(), strict=True))
    assert got == [(0, 0, 0), (0, 0, 1), (0, 1, 0), (0, 1, 1), (1, 5, 2), (1, 5, 3), (1, 5, 4)]


def test_ema_matches_sequential_update() -> None:
    """Closed-form EMA over all frames = applying detections one by one in frame order."""
    rng = np.random.default_rng(0)
    V, N, alpha, w = 30, 40, 0.3, (0.3, 0.4, 0.7, 1.0)
    cls = rng.integers(0, 4, N)
    conf = rng.uniform(0.1, 1.0, N)
    frame = rng.integers(0, 6, N)
    order = np.lexsort((np.arange(N), frame))
    rank = np.empty(N, dtype=np.int64)
    rank[order] = np.arange(N)
    pairs = sorted({(int(d), int(v)) for d, v in zip(rng.integers(0, N, 200), rng.integers(0, V, 200), strict=True)})
    det = torch.tensor([p[0] for p in pairs])
    vid = torch.tensor([p[1] for p in pairs])
    acc = accumulate(det, vid, torch.tensor(rank), torch.tensor(cls), torch.tensor(conf), alpha, w)
    sev = np.zeros(V)
    cnt = np.zeros((V, 4), dtype=np.int64)
    cmax = np.zeros(V)
    for k in order:  # the reference: the paper's update, detection by detection
        for d, v in pairs:
            if d == k:
                sev[v] = alpha * w[cls[k]] + (1 - alpha) * sev[v]
                cnt[v, cls[k]] += 1
                cmax[v] = max(cmax[v], conf[k])
    seen = acc.seen.numpy()  # the state lives on the observed vertices only
    assert (seen == np.unique(vid.numpy())).all()
    assert np.allclose(acc.sev.numpy(), sev[seen]) and not sev[np.setdiff1d(np.arange(V), seen)].any()
    assert (acc.counts.numpy() == cnt[seen]).all()
    assert np.allclose(acc.conf.numpy(), cmax[seen])


def test_probability_forms() -> None:
    counts = torch.tensor([[0, 0, 0, 0], [2, 0, 0, 1]])
    acc = Accumulators(counts, torch.tensor([0.0, 0.5], dtype=torch.float64), torch.zeros(2, dtype=torch.float64))
    p, pc = probability(acc, "tanh")
    x = 0.5 * math.log(4)
    assert p[0] == 0.0 and math.isclose(p[1].item(), 2 / (1 + math.exp(-x)) - 1)
    assert math.isclose(pc[1, 0].item(), 2 / 3 * p[1].item(), rel_tol=1e-6) and pc[1, 1] == 0
    ps, _ = probability(acc, "sigmoid")
    assert ps[0] == 0.5  # the paper's form: unobserved vertices at 50 % (SPEC erratum)


def test_n_min_and_maps(plane: HeightField, tmp_path) -> None:  # noqa: ANN001
    seq = make_seq(5)
    dets = detections_for(seq)
    lone = Detection(0, "front", box_of(seq, 0, (7.0, -2.0)), 1, 0.9)  # seen once only
    res = run_fusion(seq, dets + [lone], plane, FusionConfig(n_min=2))
    assert all(math.dist(i.centroid, (7.0, -2.0)) > 1.0 for i in res.instances)
    res1 = run_fusion(seq, dets + [lone], plane, FusionConfig(n_min=1, min_instance_obs=1))
    assert any(math.dist(i.centroid, (7.0, -2.0)) < 0.1 for i in res1.instances)
    # Map: peak near each defect, zero far away, values in [0, 1].
    g = res.grid
    assert res.prob_map.shape == g.shape and res.class_maps.shape == (4, *g.shape)
    assert res.prob_map.min() >= 0.0 and res.prob_map.max() <= 1.0
    r, c = round((0.5 - g.y0) / g.res), round((9.0 - g.x0) / g.res)
    assert res.prob_map[r, c] > 0.05 and res.class_maps[0, r, c] > 0.05 and res.class_maps[3, r, c] == 0
    assert res.prob_map[round((4.0 - g.y0) / g.res), c] == 0
    write_fusion_outputs(tmp_path, res)
    # no geo origin: no GeoJSON (WGS84 only), the layers go to survey.gpkg in a local CRS (issue 15)
    assert not (tmp_path / "defects.geojson").exists()
    for name in ("survey.gpkg", "defect_map.npy", "defect_map_D40.npy", "metrics.json",
                 "detections_mapped.jsonl"):
        assert (tmp_path / name).is_file()
    assert np.load(tmp_path / "defect_map.npy").shape == res.prob_map.shape
    import json

    from pavemap.geometry.grid import GridSpec

    assert GridSpec.from_dict(json.loads((tmp_path / "defect_map.json").read_text())) == g


def test_instance_stats(plane: HeightField) -> None:
    seq = make_seq(5)
    dets = detections_for(seq, defects=[((10.0, 0.0), 3)])
    res = run_fusion(seq, dets, plane, FusionConfig(association="footprint", alpha=0.5))
    (inst,) = res.instances
    assert inst.code == "D40" and inst.observations == len(dets)
    assert inst.severity_max <= 1.0 and inst.severity_mean > 0.4
    assert math.isclose(inst.area_m2, inst.polygon.area, rel_tol=1e-6)
    assert 0.3 <= inst.length_m <= 0.8
    assert inst.priority == "unassessed"  # urgency is the maintenance stage's (pavemap.maintain.assess)
    assert inst.confidence == pytest.approx(0.6)


def test_off_surface_detection_not_mapped(plane: HeightField) -> None:
    seq = make_seq(2)
    # A box above the horizon: its ray never meets the road.
    d = Detection(0, "front", (300.0, 10.0, 340.0, 30.0), 0, 0.9)
    for mode in ("hit", "footprint", "ray"):
        res = run_fusion(seq, [d], plane, FusionConfig(association=mode))
        rec = res.detections[0]
        assert rec["kept"] and not rec["mapped"] and rec["distance_m"] is None
        assert res.metrics["msr"] == 0.0


def test_cli_fuse_and_eval_on_synthetic(tiny_nuscenes_seq, tmp_path) -> None:  # noqa: ANN001
    """End to end on the simulated detector: filter, hit mode on the true surface, eval.json."""
    import json

    from typer.testing import CliRunner

    from pavemap.cli import app

    seq = tiny_nuscenes_seq.root
    out = tmp_path / "run"
    r = CliRunner().invoke(app, ["fuse", str(seq), "--out", str(out), "--surface", "truth", "--no-truth"])
    assert r.exit_code == 0, r.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["valid_detections"] > 0 and metrics["msr"] >= 0.9
    assert metrics["invalid_detections"] == 0
    r = CliRunner().invoke(app, ["eval", str(out), "--truth", str(seq)])
    assert r.exit_code == 0, r.output
    ev = json.loads((out / "eval.json").read_text())
    assert ev["fp_removed"] >= 0.9 and ev["tp_lost"] <= 0.1
    assert ev["recall"] >= 0.5 and ev["f1"] > ev["baseline"]["f1"]  # fusion beats the single-frame baseline
    geo = json.loads((out / "defects.geojson").read_text())
    assert len(geo["features"]) == metrics["instances"]


def test_footprint_centre_removes_centre_ray_bias(plane: HeightField) -> None:
    """A long patch's box-centre ray lands short of its middle (harmonic mean depth); the footprint centroid not."""
    seq = make_seq(1)
    b = box_of(seq, 0, (8.0, 0.0), half=1.5)  # 3 m patch seen from 8 m
    d = Detection(0, "front", b, 3, 0.9)
    errs = {}
    for hp in ("centre", "footprint"):
        res = run_fusion(seq, [d], plane, FusionConfig(hit_point=hp, n_min=1, min_instance_obs=1))
        errs[hp] = math.dist(res.detections[0]["hit_xyz"][:2], (8.0, 0.0))
    # The box's ground trapezoid is wider at its far end than the patch, so some bias is left.
    assert errs["centre"] > 0.2 and errs["footprint"] < errs["centre"] / 2, errs


def test_mesh_mask_from_surface_semantics(plane: HeightField) -> None:
    """Mesh road mask sampled by rays: a box over a non-road strip of the mesh is filtered."""
    from pavemap.mesh.model import RoadMesh

    seq = make_seq(1)
    logits = torch.zeros((plane.ny, plane.nx, 2))
    logits[..., 0] = 1.0  # road (class 0) everywhere ...
    ys = plane.y0 + plane.res * torch.arange(plane.ny)
    logits[ys < -2.0, :, 1] = 5.0  # ... except y < -2 m: sidewalk (class 1)
    mesh = RoadMesh(plane, torch.zeros((plane.ny, plane.nx, 3)), logits, [0, 1])  # dense -> per vertex
    on = Detection(0, "front", box_of(seq, 0, (9.0, 0.5)), 0, 0.9)
    off = Detection(0, "front", box_of(seq, 0, (9.0, -3.5)), 0, 0.9)
    res = run_fusion(seq, [on, off], plane, FusionConfig(n_min=1, min_instance_obs=1), mesh=mesh,
                     filt=FilterConfig(tau_conf=0.05, mask="mesh"))
    assert [r["reason"] for r in res.detections] == ["kept", "off_road"]
    assert res.detections[0]["r_road"] == 1.0 and res.detections[1]["r_road"] == 0.0


def _crack_instances(cells: list[tuple[slice, slice, int]], crack_join_m: float) -> list:
    """build_instances on a 10 cm grid whose defect vertices are the given (rows, cols, class) rectangles."""
    from pavemap.fuse.instances import build_instances

    ny, nx = 80, 120
    cls = np.full((ny, nx), -1)
    for rows, cols, c in cells:
        cls[rows, cols] = c
    vertices = np.arange(ny * nx, dtype=np.int64)
    defect = (cls >= 0).reshape(-1)
    counts = np.zeros((ny * nx, 4), np.int64)
    counts[defect, cls.reshape(-1)[defect]] = 3
    ones = np.ones(ny * nx)
    pair_vid = np.flatnonzero(defect)
    pair_det = np.arange(len(pair_vid)) % 5
    inst, _ = build_instances((ny, nx), vertices, defect, ones, counts, ones, ones, pair_det, pair_vid,
                              0.0, 0.0, 0.1, min_obs=1, merge_gap_m=0.4, crack_join_m=crack_join_m)
    return inst


def test_pieces_of_one_crack_join_but_neighbouring_defects_do_not() -> None:
    """A longitudinal crack (class 0) faint over 0.7 m falls into two pieces: one instance. A parallel crack
    0.7 m beside it, a transverse crack (class 1) 0.7 m beyond its end and an alligator patch (class 2) in line
    stay apart, and with crack_join_m 0 nothing joins."""
    line = [(slice(10, 12), slice(5, 35), 0), (slice(10, 12), slice(42, 60), 0)]  # 3 m and 1.8 m, 0.7 m gap
    beside = [(slice(18, 20), slice(5, 35), 0)]  # parallel, 0.7 m to the side
    transverse = [(slice(30, 60), slice(67, 69), 1), (slice(30, 60), slice(76, 78), 1)]  # side by side across
    patch = [(slice(9, 14), slice(67, 80), 2)]  # areal, 0.7 m past the crack's end
    inst = _crack_instances(line + beside + transverse + patch, 1.0)
    got = sorted((i.cls, round(i.area_m2, 2)) for i in inst)
    assert got == [(0, 0.6), (0, 0.96), (1, 0.6), (1, 0.6), (2, 0.65)], got
    joined = next(i for i in inst if i.cls == 0 and round(i.area_m2, 2) == 0.96)
    assert joined.length_m == pytest.approx(5.5, abs=0.15)  # end to end across the gap
    assert len(_crack_instances(line + beside, 0.0)) == 3
    assert len(_crack_instances(line, 0.5)) == 2  # the gap is wider than the join distance
    # the pieces of a faint crack are blobs (the 0.3 m disks around its detections): neither is longer than it
    # is wide, together they are a line
    blobs = [(slice(40, 49), slice(10, 22), 0), (slice(42, 48), slice(27, 31), 0)]  # 1.2 x 0.9 m, 0.4 x 0.6 m
    assert sorted(round(i.area_m2, 2) for i in _crack_instances(blobs, 1.0)) == [1.32]
    # a blob 0.5 m beside the middle of a crack is not a piece of it
    assert len(_crack_instances([line[0], (slice(17, 22), slice(18, 23), 0)], 1.0)) == 2
    # a wisp of 12 cells at an angle (elongated, but 0.6 m long: no direction of its own) 0.7 m before a crack's
    # piece, in line with it, is a piece of it (KITTI-00 drive at 7b4866e: split across a seam before)
    wisp = [(slice(40, 41), slice(10, 15), 0), (slice(41, 42), slice(10, 14), 0), (slice(42, 43), slice(9, 11), 0),
            (slice(43, 44), slice(10, 11), 0)]
    piece = [(slice(51, 59), slice(9, 15), 0)]
    assert len(_crack_instances(wisp + piece, 1.0)) == 1
    assert len(_crack_instances(wisp + piece, 0.5)) == 2
