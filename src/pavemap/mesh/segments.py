"""Long drives in segments (issue 17): memory that depends on a segment, not on the drive.

The path is cut by length into segments of about ``mesh.segment_m`` that overlap by ``mesh.segment_overlap_m``;
road a later pass drives again is no segment's own but the earlier pass's segments', which hold the later pass's
frames there; frames of other passes near a segment's road (a crossing) join its views; frames of a standing
vehicle are skipped. Each segment is reconstructed from its own frames' pixels only (:func:`reconstruct_segment`, a
pure function of its inputs, so that segments can run as separate tasks), written to
``DIR/segments/NNN/`` as soon as it is done (a stopped run resumes at the first segment not written), and
blended into the drive's surface (:mod:`pavemap.mesh.stitch`). The held-out frames are the drive's, so that
no held-out frame trains a neighbouring segment.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from tqdm.auto import tqdm

from pavemap.device import resolve_device
from pavemap.io.truth import has_truth_height
from pavemap.mesh import tiles
from pavemap.mesh.config import MeshConfig
from pavemap.mesh.data import finite_views, split_frames
from pavemap.mesh.evaluate import truth_metrics
from pavemap.mesh.model import RoadMesh
from pavemap.mesh.setup import trajectory_grid
from pavemap.mesh.stitch import Stitcher, core_ramp, own_path, segment_weights
from pavemap.mesh.texture_check import texture_summary
from pavemap.mesh.tiles import SEGMENTS_DIR, TileJob, tile_stamp
from pavemap.mesh.train import reconstruct_piece
from pavemap.types import Sequence

log = logging.getLogger("pavemap")


@dataclass(frozen=True)
class SegmentPlan:
    """One segment: ``core`` the path-length interval (m from the first frame) whose road it owns (-inf / inf
    at the drive's ends); ``own`` the positions (in the sequence's frame list) of its stretch of path, the core
    and the overlap either side; ``revisit`` those of other passes over its road, and ``share`` for each of
    them the part of that pass's road this segment owns (1 on road the pass revisits, ramping to 0 over the
    overlap at the ends of the revisit, 0 where the pass's own segments own its road) and ``revisit_at`` the
    path length of the own road beside it (NaN with share 0)."""

    index: int
    core: tuple[float, float]
    own: tuple[int, ...]
    revisit: tuple[int, ...] = ()
    share: tuple[float, ...] = ()
    revisit_at: tuple[float, ...] = ()

    @property
    def positions(self) -> tuple[int, ...]:
        return tuple(sorted(set(self.own) | set(self.revisit)))

    def to_dict(self) -> dict:
        return {"index": self.index, "core_m": [None if math.isinf(c) else round(c, 3) for c in self.core],
                "own": [self.own[0], self.own[-1]], "own_frames": len(self.own), "revisit_frames": len(self.revisit),
                "revisit_owned_frames": int(sum(f > 0 for f in self.share))}


def path_metres(traj_xy: np.ndarray) -> np.ndarray:
    """(F,) float64 path length at each position of the trajectory (F, 2), from 0."""
    t = np.asarray(traj_xy, dtype=np.float64).reshape(-1, 2)
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(t, axis=0), axis=1))])


def moving_frames(traj_xy: np.ndarray, min_step_m: float) -> np.ndarray:
    """(F,) bool: the frames kept when frames within ``min_step_m`` of the last kept one are skipped (a standing
    vehicle repeats one view); the first and the last frame are always kept."""
    t = np.asarray(traj_xy, dtype=np.float64).reshape(-1, 2)
    keep = np.zeros(len(t), bool)
    last = None
    for i, p in enumerate(t):  # sequential by nature; O(F) over frames, not pixels
        if last is None or float(np.hypot(*(p - last))) >= min_step_m:
            keep[i], last = True, p
    keep[-1] = True
    return keep


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """The maximal runs of True in ``mask`` (F,) as (first, last) index pairs."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1).tolist(), (np.flatnonzero(d == -1) - 1).tolist(), strict=True))


def revisited_frames(traj_xy: np.ndarray, revisit_m: float, after_m: float, min_run_m: float) -> np.ndarray:
    """(F,) bool: the frames on road an earlier pass drove, whose road that pass's segments own.

    A frame revisits when it lies within ``revisit_m`` of a frame more than ``after_m`` of path before it that
    does not revisit itself, in a run of such frames at least ``min_run_m`` of path long: a crossing or a short
    stretch of shared road stays with its own pass (whose segments would otherwise be cut there)."""
    t = np.asarray(traj_xy, dtype=np.float64).reshape(-1, 2)
    s = path_metres(t)
    out = np.zeros(len(t), bool)
    if len(t) < 2 or revisit_m <= 0:
        return out
    pairs = cKDTree(t).query_pairs(revisit_m, output_type="ndarray")
    if not len(pairs):
        return out
    a, b = pairs.min(1), pairs.max(1)
    far = s[b] - s[a] > after_m
    a, b = a[far], b[far]
    for _ in range(2):  # a third pass near a second pass's road is owned by the first pass only if near it too
        near = np.zeros(len(t), bool)
        near[b[~out[a]]] = True
        out = np.zeros(len(t), bool)
        for i, j in _runs(near):
            out[i:j + 1] = s[j] - s[i] >= min_run_m
    return out


def plan_segments(traj_xy: np.ndarray, length_m: float, overlap_m: float, revisit_m: float,
                  revisit_spacing_m: float = 0.0) -> list[SegmentPlan]:
    """Segments of the path (F, 2) by length, each road reconstructed once.

    The frames that revisit road an earlier pass drove (:func:`revisited_frames`) are no segment's own: the
    rest of the path falls into stretches of new road, each cut into ``round(length / length_m)`` equal cores
    (at least one). A segment holds the frames within ``overlap_m`` of its core along the path, plus the frames
    of other passes within ``revisit_m`` of its core's path and those within ``overlap_m`` of them along their
    own pass (the frames that look at it), of those one per ``revisit_spacing_m`` of path (0: all)."""
    t = np.asarray(traj_xy, dtype=np.float64).reshape(-1, 2)
    s = path_metres(t)
    band_m = overlap_m + 2 * revisit_m
    again = revisited_frames(t, revisit_m, band_m, 2 * overlap_m) if length_m > 0 else np.zeros(len(t), bool)
    bounds = [0.5 * (s[j] + s[j + 1]) for j in np.flatnonzero(np.diff(again.astype(np.int8)) != 0)]
    edges = [-math.inf, *bounds, math.inf]
    pieces = list(zip(edges[:-1], edges[1:], strict=True))
    runs = pieces[0::2]  # new road and revisits alternate; the first frame has no earlier pass to revisit
    share = np.zeros(len(t))
    for piece in pieces[1::2]:
        share = np.maximum(share, core_ramp(s, piece, overlap_m))
    cores: list[tuple[float, float]] = []
    for lo, hi in runs:
        span = min(hi, s[-1]) - max(lo, 0.0)
        n = max(1, int(round(span / length_m))) if length_m > 0 else 1
        cuts = np.linspace(max(lo, 0.0), min(hi, s[-1]), n + 1)
        cores += [(lo if k == 0 else float(cuts[k]), hi if k == n - 1 else float(cuts[k + 1])) for k in range(n)]
    plans = []
    for k, (lo, hi) in enumerate(cores):
        own = np.flatnonzero((s >= lo - overlap_m) & (s <= hi + overlap_m))
        core = np.flatnonzero((s >= lo - 0.5 * overlap_m) & (s <= hi + 0.5 * overlap_m))
        # Another pass: frames far along the path from this stretch (not its own continuation), near its road.
        mine = np.zeros(len(t), bool)
        mine[own] = True
        others = np.flatnonzero(((s < lo - band_m) | (s > hi + band_m) | again) & ~mine)
        revisit = np.zeros(0, np.int64)
        if others.size and core.size:
            d, _ = cKDTree(t[core]).query(t[others])
            near_s = np.sort(s[others[d < revisit_m]])
            if near_s.size:
                j = np.clip(np.searchsorted(near_s, s[others]), 1, near_s.size)
                gap = np.minimum(np.abs(s[others] - near_s[j - 1]), np.abs(near_s[np.minimum(j, near_s.size - 1)]
                                                                          - s[others]))
                revisit = _thin(others[gap <= overlap_m], s, revisit_spacing_m)
        at = _revisited_at(t, s, own, revisit, band_m)
        owned = np.where(np.isfinite(at), share[revisit], 0.0)
        plans.append(SegmentPlan(k, (float(lo), float(hi)), tuple(int(i) for i in own), tuple(int(i) for i in revisit),
                                 tuple(round(float(f), 4) for f in owned), tuple(round(float(a), 3) for a in at)))
    return plans


def _revisited_at(t: np.ndarray, s: np.ndarray, own: np.ndarray, revisit: np.ndarray, band_m: float) -> np.ndarray:
    """(R,) the path length of the own frame nearest to each revisit frame among those more than ``band_m`` of
    path before it (the earlier pass it revisits; NaN where there is none: the frame's pass came first)."""
    at = np.full(len(revisit), np.nan)
    if not len(revisit) or not len(own):
        return at
    k = min(len(own), 32)
    _, nn = cKDTree(t[own]).query(t[revisit], k=k)
    cand = own[np.asarray(nn).reshape(len(revisit), k)]  # (R, k) nearest first
    ok = s[cand] <= s[revisit, None] - band_m
    first = ok.argmax(1)
    hit = ok[np.arange(len(revisit)), first]
    at[hit] = s[cand[np.flatnonzero(hit), first[hit]]]
    return at


def _thin(idx: np.ndarray, s: np.ndarray, spacing_m: float) -> np.ndarray:
    """The first of the frames ``idx`` (sorted) in each ``spacing_m`` of path length ``s`` (all with 0)."""
    if spacing_m <= 0 or idx.size == 0:
        return idx
    _, first = np.unique(np.floor(s[idx] / spacing_m), return_index=True)
    return idx[np.sort(first)]


def _drive_positions(seq: Sequence) -> tuple[list[int], np.ndarray]:
    """Positions of the frames whose every view has a finite pose, and their trajectory (F, 3)."""
    pos = [p for p, f in enumerate(seq.frames) if f.views and finite_views(seq, [p])[1] == 0]
    traj = np.array([np.mean([v.T_world_cam[:3, 3] for v in seq.frames[p].views.values()], axis=0) for p in pos])
    return pos, traj.reshape(-1, 3)


def skip_standing(seq: Sequence, cfg: MeshConfig, at_least: int = 10) -> tuple[Sequence, str | None]:
    """The sequence without the frames of a standing vehicle (:func:`moving_frames`) when there are at least
    ``at_least`` of them (a few slow frames are views like any other), and the note saying so."""
    pos, traj = _drive_positions(seq)
    if len(pos) < 3:
        return seq, None
    keep = moving_frames(traj[:, :2], cfg.segment_min_step_m)
    drop = {pos[i] for i in np.flatnonzero(~keep)}
    if len(drop) < at_least:
        return seq, None
    ids = [seq.frames[p].index for p in sorted(drop)]
    note = (f"{len(drop)} frame(s) skipped (frames {ids[0]}..{ids[-1]}): within mesh.segment_min_step_m "
            f"{cfg.segment_min_step_m:g} m of the previous frame kept, a standing vehicle adds no view")
    return dataclasses.replace(seq, frames=[f for p, f in enumerate(seq.frames) if p not in drop]), note


def needs_segments(seq: Sequence, cfg: MeshConfig) -> bool:
    """Whether the drive's path is longer than 1.5 ``cfg.segment_m`` (0: never segmented)."""
    if cfg.segment_m <= 0 or len(seq.frames) < 3:
        return False
    _, traj = _drive_positions(seq)
    return len(traj) >= 3 and float(path_metres(traj[:, :2])[-1]) > 1.5 * cfg.segment_m


def reconstruct_segment(seq: Sequence, positions: tuple[int, ...], cfg: MeshConfig, heldout_frames: set[int],
                        label: str = "segment") -> tuple[RoadMesh, dict]:
    """Stage 1 on the frames at ``positions`` of ``seq`` alone, holding out ``heldout_frames`` (frame
    indices): the segment's tile and its metrics. Its warnings are re-issued prefixed with ``label``."""
    return tiles.segment_tile(tiles.sub_sequence(seq, positions), cfg, heldout_frames, label)


def _row(plan: SegmentPlan, own_m: np.ndarray, m: dict, seconds: float, reused: bool, seam: dict) -> dict:
    geo = m.get("geometry") or {}
    return {**plan.to_dict(), "path_m": [round(float(own_m[0]), 1), round(float(own_m[-1]), 1)],
            "seconds": round(seconds, 2), "reused": reused, "psnr": m.get("psnr"), "sem_acc": m.get("sem_acc"),
            "train_psnr": m.get("train_psnr"), "heldout_views": m.get("heldout_views"),
            "train_views": m.get("train_views"), "height_rmse": m.get("height_rmse"),
            "height_rmse_seen": m.get("height_rmse_seen"), "vertices": m.get("vertices"),
            "camera_height_m": (geo.get("camera_height") or {}).get("used_m"), "source": geo.get("source"),
            "trustworthy": geo.get("trustworthy"), "observed_fraction": geo.get("observed_fraction"), **seam}


@dataclass
class DrivePlan:
    """A segmented drive: the positions of its posed frames and their trajectory (F, 3) and path length
    (F,), the segments (in local and in sequence positions), the drive's held-out frame indices and notes."""

    pos: list[int]
    traj: np.ndarray
    s: np.ndarray
    local: list[SegmentPlan]
    plans: list[SegmentPlan]
    heldout: set[int]
    notes: list[str]

    def label(self, seq: Sequence, plan: SegmentPlan) -> str:
        return (f"segment {plan.index + 1}/{len(self.plans)} (frames {seq.frames[plan.own[0]].index}-"
                f"{seq.frames[plan.own[-1]].index})")


def plan_drive(seq: Sequence, cfg: MeshConfig) -> DrivePlan:
    """Cut ``seq`` into segments (:func:`plan_segments` on its posed frames) and choose the held-out frames."""
    notes: list[str] = []
    pos, traj = _drive_positions(seq)
    if len(pos) < len(seq.frames):
        notes.append(f"{len(seq.frames) - len(pos)} frame(s) with a NaN/infinite pose skipped")
    local = plan_segments(traj[:, :2], cfg.segment_m, cfg.segment_overlap_m, cfg.segment_revisit_m,
                          cfg.segment_revisit_spacing_m)
    plans = [dataclasses.replace(p, own=tuple(pos[i] for i in p.own), revisit=tuple(pos[i] for i in p.revisit))
             for p in local]
    held_local = split_frames(len(pos), cfg.holdout_every, 1)[1]
    heldout = {seq.frames[pos[i]].index for i in held_local}
    return DrivePlan(pos, traj, path_metres(traj[:, :2]), local, plans, heldout, notes)


def tile_jobs(seq: Sequence, cfg: MeshConfig, plan: DrivePlan, out_dir: Path) -> list[TileJob]:
    """A job for every segment whose tile under ``out_dir/segments/`` is missing or stale (every segment
    when ``cfg.resume`` is off)."""
    conf, jobs = tiles.stamp_config(cfg), []
    for p in plan.plans:
        stamp = tile_stamp(conf, p.to_dict(), seq, p.positions, plan.heldout)
        folder = Path(out_dir) / SEGMENTS_DIR / f"{p.index:03d}"
        if not (cfg.resume and tiles.tile_done(folder, stamp)):
            jobs.append(TileJob(tiles.sub_sequence(seq, p.positions), cfg, frozenset(plan.heldout), plan.label(seq, p),
                                folder, stamp))
    return jobs


def reconstruct_segmented(seq: Sequence, out_dir: Path | None, cfg: MeshConfig, progress: bool = True
                          ) -> tuple[RoadMesh, dict]:
    """Stage 1 on a long drive in segments; the blended mesh and the drive's metrics (``segments``: a row per
    segment; ``seams``: how neighbouring segments agree where they overlap). Writes ``out_dir`` as
    :func:`pavemap.mesh.reconstruct` does, plus ``out_dir/segments/NNN/`` per segment. Missing tiles are
    computed here one by one, or all at once by the runner of :func:`pavemap.mesh.tiles.tiles_run_by`."""
    from pavemap.mesh.outputs import write_outputs

    t0 = time.perf_counter()
    dp = plan_drive(seq, cfg)
    notes = list(dp.notes)  # the drive's own warnings (the segments' are issued as they run)
    views = [(f.index, v) for f in (seq.frames[p] for p in dp.pos) for v in f.views.values()]
    grid, _ = trajectory_grid(views, cfg, notes.append)
    log.info("mesh: %.0f m of path in %d segments of ~%.0f m (overlap %.0f m), %d frames%s", dp.s[-1],
             len(dp.plans), dp.s[-1] / len(dp.plans), cfg.segment_overlap_m, len(dp.pos),
             f", {sum(len(p.revisit) > 0 for p in dp.plans)} with revisits" if any(p.revisit for p in dp.plans)
             else "")
    for n in notes:
        warnings.warn(n, stacklevel=2)
    runner = tiles.tile_runner() if out_dir is not None else None
    fresh: dict[int, float] = {}  # segment index -> seconds, for tiles the runner computed now
    if runner is not None:
        jobs = tile_jobs(seq, cfg, dp, Path(out_dir))
        for job, got in zip(jobs, runner(jobs), strict=True):
            fresh[int(job.folder.name)] = got["seconds"]
            for w in got["warnings"]:
                warnings.warn(w, stacklevel=2)
    stitcher, rows, tiles_meta, seg_notes = Stitcher(grid.spec), [], None, []
    conf = tiles.stamp_config(cfg)
    bar = tqdm(dp.plans, disable=not progress, desc="segments", unit="segment", dynamic_ncols=True)
    for plan, lp in zip(bar, dp.local, strict=True):
        label = dp.label(seq, plan)
        stamp = tile_stamp(conf, plan.to_dict(), seq, plan.positions, dp.heldout)
        folder = None if out_dir is None else Path(out_dir) / SEGMENTS_DIR / f"{plan.index:03d}"
        t_seg = time.perf_counter()
        got = None if folder is None or not (cfg.resume or plan.index in fresh) else tiles.load_tile(folder, stamp)
        if got is None:
            tile, m = reconstruct_segment(seq, plan.positions, cfg, dp.heldout, label)
            if folder is not None:
                tiles.save_tile(folder, tile, m, stamp)
        else:
            tile, m = got
            if plan.index not in fresh:
                log.info("mesh: %s reused from %s", label, folder)
        path_xy, path_s = own_path(dp.traj[list(lp.own), :2], dp.s[list(lp.own)])
        w = segment_weights(_tile_grid(tile), path_xy, path_s, plan.core, cfg.segment_overlap_m,
                            cfg.crop_m + 2.0 * cfg.resolution, dp.traj[list(lp.revisit), :2], np.array(lp.revisit_at),
                            np.array(lp.share))
        before = dp.plans[plan.index - 1] if plan.index else None
        seam = stitcher.add(tile, w, plan.index + 1, plan.index if before and before.core[1] == plan.core[0] else None)
        seconds = fresh.get(plan.index, time.perf_counter() - t_seg)
        rows.append(_row(plan, dp.s[list(lp.own)], m, seconds, got is not None and plan.index not in fresh, seam))
        seg_notes += [f"segment {plan.index + 1}: {n}" for n in m.get("warnings", [])]
        tiles_meta = tiles_meta or (tile.class_ids, tile.has_semantics)
        bar.set_postfix(psnr=f"{m.get('psnr') or float('nan'):.2f}")
        del tile
    bar.close()
    tiles.drop_stale(out_dir, len(dp.plans))
    mesh = stitcher.mesh(*tiles_meta)
    metrics = _drive_metrics(seq, mesh, rows, notes + seg_notes, cfg, time.perf_counter() - t0, len(dp.pos))
    if out_dir is not None:
        write_outputs(Path(out_dir), mesh, metrics, seq.classes if tiles_meta[1] else [])
    return mesh, metrics


def _tile_grid(tile: RoadMesh):
    from pavemap.mesh.model import MeshGrid

    return MeshGrid(tile.surface.grid, tile.surface.valid.cpu().numpy())


def _mean_psnr(rows: list[dict], key: str, n_key: str) -> float | None:
    """The PSNR of the segments' pooled squared error, each weighted by its evaluation views."""
    got = [(r[key], r.get(n_key) or 1) for r in rows if r.get(key) is not None and math.isfinite(r[key])]
    if not got:
        return None
    mse = sum(n * 10 ** (-p / 10) for p, n in got) / sum(n for _, n in got)
    return round(-10 * math.log10(mse), 3)


def _drive_metrics(seq: Sequence, mesh: RoadMesh, rows: list[dict], notes: list[str], cfg: MeshConfig,
                   seconds: float, frames: int) -> dict:
    """The drive's metrics.json from its segments' rows, on the blended ``mesh``."""
    s = mesh.surface
    valid = s.valid.numpy()
    observed = mesh.observed.numpy() & valid
    seam_abs = [r["seam_median_abs_m"] for r in rows if r.get("seam_median_abs_m") is not None]
    pass_abs = [r["pass_median_abs_m"] for r in rows if r.get("pass_median_abs_m") is not None]
    sem = [(r["sem_acc"], r.get("heldout_views") or 1) for r in rows if r.get("sem_acc") is not None]
    untrusted = [r["index"] + 1 for r in rows if r.get("trustworthy") is False]
    cam_h = [r["camera_height_m"] for r in rows if r.get("camera_height_m") is not None]
    geo_warn = [f"segment(s) {', '.join(map(str, untrusted))} of {len(rows)} not trustworthy"] if untrusted else []
    geometry = {"source": sorted({r["source"] for r in rows if r.get("source")}),
                "trustworthy": not untrusted,
                "observed_fraction": round(float(observed.sum() / max(1, valid.sum())), 4),
                "camera_height": {"used_m": float(np.median(cam_h)) if cam_h else None,
                                  "per_segment_m": cam_h, "prior_m": cfg.camera_height},
                "warnings": geo_warn + [n for n in notes if "trustworthy" in n or "not observable" in n]}
    vq = valid[:-1, :-1] & valid[1:, 1:]
    metrics: dict = {
        "segmented": True, "device": str(resolve_device(cfg.device)), "psnr": _mean_psnr(rows, "psnr", "heldout_views"),
        "train_psnr": _mean_psnr(rows, "train_psnr", "train_views"),
        "sem_acc": round(sum(a * n for a, n in sem) / sum(n for _, n in sem), 4) if sem else None,
        "vertices": int(valid.sum()), "faces": int((vq & valid[:-1, 1:]).sum() + (vq & valid[1:, :-1]).sum()),
        "grid": s.grid.to_dict(), "segments": rows,
        "seams": {"count": len(seam_abs), "median_abs_m": float(np.median(seam_abs)) if seam_abs else None,
                  "max_abs_m": max(seam_abs) if seam_abs else None},
        # where segments of different passes both own the road (a crossing, the ends of a revisit)
        "passes": {"count": len(pass_abs), "median_abs_m": float(np.median(pass_abs)) if pass_abs else None,
                   "max_abs_m": max(pass_abs) if pass_abs else None},
        "geometry": geometry, "warnings": notes, "history": [], "config": cfg.to_dict(),
        "seconds": seconds, "frames": frames, "seconds_per_frame": seconds / max(1, frames),
    }
    if mesh.contested is not None:  # the segments' contested patches, stitched (each filtered by its segment)
        metrics["texture_check"] = texture_summary(mesh.contested.numpy(), s.grid, 0.0, int(valid.sum()))[1]
    if has_truth_height(seq.root):
        metrics.update(truth_metrics(mesh, seq.root, mesh.observed))
    return metrics


def reconstruct(seq: Sequence, out_dir: Path | None, config: MeshConfig, progress: bool = True,
                heldout_frames: set[int] | None = None) -> tuple[RoadMesh, dict]:
    """Stage 1 on a sequence: returns the mesh and its metrics; writes outputs to ``out_dir`` when given.

    Metrics: psnr (held-out road pixels), sem_acc, height_rmse (with synthetic truth), seconds,
    vertices, faces, device, history (per epoch), warnings. A drive longer than 1.5 ``config.segment_m``
    is reconstructed in segments (:func:`pavemap.mesh.segments.reconstruct_segmented`); ``heldout_frames``
    (frame indices held out instead of every ``holdout_every``-th) always gives one piece.
    """
    if heldout_frames is None:
        seq, note = skip_standing(seq, config)
        if note:
            warnings.warn(note, stacklevel=2)
        if needs_segments(seq, config):
            return reconstruct_segmented(seq, out_dir, config, progress)
    return reconstruct_piece(seq, out_dir, config, progress, heldout_frames)
