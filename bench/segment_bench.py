"""Segmenter benchmark: ESPNet vs ESPNetv2 (Cityscapes weights) on synthetic drives and real nuScenes frames.

Rows: road IoU against the synthetic truth (kitti-like, nuscenes-like; every view) and milliseconds per frame
per network and input width; on the shared nuScenes clips the road share, the bonnet rows called road by the
model alone and after the ego mask, ms per 1600 x 900 frame; end to end, the F1 of ``pavemap run`` on a
synthetic drive with its true semantics vs the same drive with semantics withheld and the segmenter's maps
(same detections, ``--detector file``). Writes ``bench/results/segment.json``.

    python bench/segment_bench.py [--device cpu|cuda] [--data DIR] [--e2e-frames 12] [--skip-e2e]
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import bench_parser, git_commit, machine_entry, write_results  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
CANDIDATES = [("espnet", 1024), ("espnet", 768), ("espnetv2", 512), ("espnetv2", 640), ("espnetv2", 768)]
SYNTH = {"kitti-like": {"frames": 6, "scale": 0.5}, "nuscenes-like": {"frames": 3, "scale": 0.25}}


def synth(data: Path, preset: str, frames: int, scale: float) -> Path:
    from pavemap.synth import synthesize

    root = data / f"segment-{preset}-{frames}-{scale}"
    if not (root / "sequence.json").is_file():
        synthesize(root, preset=preset, seed=0, frames=frames, scale=scale, depth="none", progress=False,
                   overwrite=True)
    return root


def synthetic_rows(data: Path, device: str) -> list[dict]:
    from pavemap.io.sequence import load_rgb, load_semantics, read_sequence
    from pavemap.segment.espnet import EspnetSegmenter

    rows = []
    for preset, p in SYNTH.items():
        seq = read_sequence(synth(data, preset, p["frames"], p["scale"]))
        views = [v for f in seq.frames for v in f.views.values()]
        imgs = [load_rgb(seq.path(v.image)) for v in views]
        truth = [seq.class_lut("road")[load_semantics(seq.path(v.semantics))] for v in views]
        for arch, width in CANDIDATES:
            seg = EspnetSegmenter(arch, device=device, width=width)
            seg.segment(imgs[:1])  # warm-up
            inter = union = 0
            ms = []
            for img, tr in zip(imgs, truth, strict=True):
                t0 = time.perf_counter()
                road = seg.segment([img])[0] == 0
                ms.append(1000 * (time.perf_counter() - t0))
                inter, union = inter + int((road & tr).sum()), union + int((road | tr).sum())
            size = list(seg.input_size(*imgs[0].shape[:2]))
            rows.append({"preset": preset, "arch": arch, "width": width, "input": size,
                         "image": list(imgs[0].shape[:2]), "views": len(imgs), "road_iou": round(inter / union, 4),
                         "ms_per_frame_median": round(float(np.median(ms)), 1)})
            print(rows[-1], flush=True)
    return rows


def confusion_rows(data: Path, device: str) -> list[dict]:
    """Where the default segmenter's road IoU is lost on each synthetic preset (at the bench's scale and at twice
    it): which classes it gives true road pixels, which true classes it calls road, the error by image band,
    and the IoU with the synthetic vehicles left out of both sides (the renderer's box cars are not cars a
    Cityscapes model knows: a property of the synthetic world, not of real footage; reported, not the target)."""
    from pavemap.io.sequence import load_rgb, load_semantics, read_sequence
    from pavemap.segment.espnet import EspnetSegmenter

    seg = EspnetSegmenter(device=device)
    names = [c.name for c in seg.classes]
    rows = []
    for preset, p in SYNTH.items():
        for scale in (p["scale"], 2 * p["scale"]):
            seq = read_sequence(synth(data, preset, p["frames"], scale))
            road_lut, mov_lut = seq.class_lut("road"), seq.class_lut("movable")
            truth_name = {c.id: c.name for c in seq.classes}
            missed: dict[str, int] = {}
            false: dict[str, int] = {}
            inter = union = inter_nv = union_nv = 0
            band_err = np.zeros(5)
            for f in seq.frames:
                for v in f.views.values():
                    sem = load_semantics(seq.path(v.semantics))
                    tr, mov = road_lut[sem].astype(bool), mov_lut[sem].astype(bool)
                    lab = seg.segment([load_rgb(seq.path(v.image))])[0]
                    pr = lab == names.index("road")
                    inter, union = inter + int((tr & pr).sum()), union + int((tr | pr).sum())
                    inter_nv += int((tr & pr & ~mov).sum())
                    union_nv += int(((tr | pr) & ~mov).sum())
                    for k, n in zip(*np.unique(lab[tr & ~pr], return_counts=True), strict=True):
                        missed[names[k]] = missed.get(names[k], 0) + int(n)
                    for k, n in zip(*np.unique(sem[pr & ~tr], return_counts=True), strict=True):
                        false[truth_name.get(int(k), str(k))] = false.get(truth_name.get(int(k), str(k)), 0) + int(n)
                    rows_of = np.arange(sem.shape[0]) * 5 // sem.shape[0]
                    band_err += np.bincount(rows_of, weights=(tr ^ pr).sum(1), minlength=5)
            rows.append({"preset": preset, "scale": scale, "image": list(sem.shape), "arch": seg.arch.name,
                         "road_iou": round(inter / union, 4),
                         "road_iou_without_vehicles": round(inter_nv / union_nv, 4),
                         "missed_road_as": _shares(missed, union), "false_road_on": _shares(false, union),
                         "error_by_band_top_to_bottom": (band_err / max(1.0, band_err.sum())).round(3).tolist()})
            print(rows[-1], flush=True)
    return rows


def _shares(counts: dict[str, int], union: int) -> dict[str, float]:
    """The six largest ``counts`` as shares of the road union."""
    return {k: round(n / union, 4) for k, n in sorted(counts.items(), key=lambda x: -x[1])[:6]}


def real_rows(device: str, n: int = 6) -> list[dict]:
    from pavemap.io.egomask import detect_ego_mask
    from pavemap.io.sequence import load_rgb
    from pavemap.segment.espnet import EspnetSegmenter

    rows = []
    for clip in ("nuscenes-front-clip", "nuscenes-front-clip-2"):
        paths = sorted((SHARED / clip / "images").glob("*.jpg"))
        if not paths:
            continue
        img0 = load_rgb(paths[0])
        h, w = img0.shape[:2]
        ego = detect_ego_mask(paths, w, h)
        pick = [paths[i] for i in np.linspace(0, len(paths) - 1, n).round().astype(int)]
        imgs = [load_rgb(p) for p in pick]
        bottom = slice(int(0.93 * h), h)
        for arch, width in CANDIDATES:
            seg = EspnetSegmenter(arch, device=device, width=width)
            seg.segment(imgs[:1])
            ms, road, bonnet_bare, bonnet = [], [], [], []
            for img in imgs:
                t0 = time.perf_counter()
                bare = seg.segment([img])[0]
                ms.append(1000 * (time.perf_counter() - t0))
                lab = np.where(ego, np.uint8(seg.ego_id), bare)
                road.append(float((lab == 0).mean()))
                bonnet_bare.append(float((bare[bottom] == 0).mean()))
                bonnet.append(float((lab[bottom] == 0).mean()))
            rows.append({"clip": clip, "arch": arch, "width": width, "frames": len(imgs),
                         "ego_mask_fraction": round(float(ego.mean()), 4),
                         "road_fraction_median": round(float(np.median(road)), 4),
                         "bottom_rows_road_without_ego_mask": round(float(np.median(bonnet_bare)), 4),
                         "bottom_rows_road_with_ego_mask": round(float(np.median(bonnet)), 4),
                         "ms_per_frame_median": round(float(np.median(ms)), 1)})
            print(rows[-1], flush=True)
    return rows


def e2e(data: Path, device: str, frames: int, epochs: int | None, preset: str = "kitti-like",
        scale: float = 0.5) -> dict:
    """F1 of the same run with the true semantics and with the segmenter's (semantics withheld), on a synthetic
    ``preset`` drive (the run's config preset of the same rig)."""
    import pavemap
    from pavemap.config import load_config
    from pavemap.io.sequence import read_sequence
    from pavemap.synth import detect_sequence

    src = synth(data, preset, frames, scale)
    if not (src / "detections.jsonl").is_file():
        detect_sequence(read_sequence(src), seed=0)
    tag = "" if preset == "kitti-like" else f"-{preset}"
    bare = data / f"segment-e2e-nosem{tag}-{frames}"
    if not (bare / "sequence.json").is_file():
        shutil.copytree(src, bare, ignore=shutil.ignore_patterns("semantics"))
        d = json.loads((bare / "sequence.json").read_text())
        for f in d["frames"]:
            for v in f["views"].values():
                v["semantics"] = None
        (bare / "sequence.json").write_text(json.dumps(d))
    out = {}
    for name, seq_dir in (("true_semantics", src), ("segmenter", bare)):
        cfg = load_config(preset.removesuffix("-like"))
        cfg.device, cfg.detector.backend = device, "file"
        if epochs:
            cfg.mesh.epochs = epochs
        cfg.output.figures = cfg.output.report = False
        run_dir = data / f"segment-e2e-run{tag}-{name}-{frames}"
        t0 = time.perf_counter()
        r = pavemap.run(read_sequence(seq_dir), cfg, run_dir, overwrite=True, progress=False)
        e = r.evaluation or {}
        out[name] = {"f1": e.get("f1"), "precision": e.get("precision"), "recall": e.get("recall"),
                     "defects": len(r.defects), "semantics": r.metrics.get("semantics"),
                     "seconds": round(time.perf_counter() - t0, 1)}
        print(name, out[name], flush=True)
    if out["true_semantics"]["f1"] is not None and out["segmenter"]["f1"] is not None:
        out["f1_difference"] = round(out["segmenter"]["f1"] - out["true_semantics"]["f1"], 4)
    out.update({"preset": preset, "frames": frames, "scale": scale, "mesh_epochs": epochs or "preset"})
    return out


def plane_check_rows(data: Path, device: str) -> dict:
    """Road IoU of the default pipeline's segmentation (ESPNetv2, ego masked) without and with the plane check
    (:mod:`pavemap.segment.plane_check`), and with the road vote after it (:mod:`pavemap.segment.road_vote`), on
    both synthetic presets (the true camera height), and what the check and the vote relabel on the shared
    nuScenes clips as imported by ``detector_bench.py --parts clips`` (no road truth
    there: shares, and the figure ``docs/plane_check_nuscenes.jpg``)."""
    import copy

    from pavemap.io.sequence import load_semantics, read_sequence
    from pavemap.segment.auto import espnet_semantics

    out: dict = {"synthetic": [], "real": []}
    for preset, p in SYNTH.items():
        seq = read_sequence(synth(data, preset, p["frames"], p["scale"]))
        truth = {(f.index, c): seq.class_lut("road")[load_semantics(seq.path(v.semantics))]
                 for f in seq.frames for c, v in f.views.items()}
        height = {"kitti-like": 1.65, "nuscenes-like": 1.509}[preset]
        row: dict = {"preset": preset, "views": len(truth), "camera_height_m": height}
        for key, check, vote in (("without_check", False, False), ("with_check", True, False),
                                 ("with_check_and_vote", True, True)):
            s = copy.deepcopy(seq)
            for f in s.frames:
                for v in f.views.values():
                    v.semantics = None
            folder = data / f"plane-check-{preset}-{key}"
            shutil.rmtree(folder, ignore_errors=True)
            t0 = time.perf_counter()
            s = espnet_semantics(s, device=device, out_root=folder, camera_height=height, plane_check=check,
                                 road_vote=vote)
            row[key] = {"road_iou": _road_iou(s, truth), "seconds": round(time.perf_counter() - t0, 2)}
            if not check:
                row["rules"] = _rule_rows(s, truth, height)
        print(row, flush=True)
        out["synthetic"].append(row)
    out["real"] = _plane_check_real(data)
    return out


VOTE_DRIVES = [("nuscenes-like", 12, 0.25, 0), ("nuscenes-like", 12, 0.25, 1), ("nuscenes-like", 12, 0.25, 2),
               ("kitti-like", 12, 0.5, 0), ("kitti-like", 12, 0.5, 1), ("kitti-like", 24, 0.5, 1)]
VOTE_SHARES = (0.5, 0.6, 0.7)


def road_vote_rows(data: Path, device: str) -> list[dict]:
    """Longer drives than the bench's (12-24 frames, three seeds of the nuScenes-like rig): road IoU of the
    segmenter with the plane check, then with the road vote at each ``min_road_share`` (the default 0.6), and
    the ego masks the pipeline found (none: the synthetic rigs show no bonnet)."""
    import copy

    from pavemap.io.sequence import load_semantics, read_sequence
    from pavemap.segment.auto import camera_ego_masks, espnet_semantics
    from pavemap.segment.road_vote import RoadVoteConfig, road_vote_sequence

    rows = []
    for preset, frames, scale, seed in VOTE_DRIVES:
        root = data / f"vote-{preset}-{frames}-{scale}-{seed}"
        if not (root / "sequence.json").is_file():
            from pavemap.synth import synthesize

            synthesize(root, preset=preset, seed=seed, frames=frames, scale=scale, depth="none", progress=False,
                       overwrite=True)
        seq = read_sequence(root)
        truth = {(f.index, c): seq.class_lut("road")[load_semantics(seq.path(v.semantics))]
                 for f in seq.frames for c, v in f.views.items()}
        height = {"kitti-like": 1.65, "nuscenes-like": 1.509}[preset]
        s = copy.deepcopy(seq)
        for f in s.frames:
            for v in f.views.values():
                v.semantics = None
        ego = {c: round(float(m.mean()), 4) if m is not None else 0.0 for c, m in camera_ego_masks(s).items()}
        folder = data / f"vote-labels-{preset}-{frames}-{scale}-{seed}"
        shutil.rmtree(folder, ignore_errors=True)
        s = espnet_semantics(s, device=device, out_root=folder, camera_height=height, road_vote=False)
        row = {"preset": preset, "frames": frames, "scale": scale, "seed": seed, "views": len(truth),
               "ego_mask_fraction": ego, "with_check": _road_iou(s, truth), "with_check_and_vote": {}}
        for share in VOTE_SHARES:
            v = copy.deepcopy(s)
            work = Path(tempfile.mkdtemp(prefix="pavemap-vote-"))
            _labels_copied_to(v, work)
            rep = road_vote_sequence(v, height, RoadVoteConfig(min_road_share=share))
            row["with_check_and_vote"][str(share)] = {
                "road_iou": _road_iou(v, truth),
                "road_share_relabelled": round(rep.relabelled_px / max(rep.road_px, 1), 4),
                "seconds_per_view": round(rep.seconds / max(rep.views, 1), 3)}
            shutil.rmtree(work)
        print(row, flush=True)
        rows.append(row)
    return rows


RULES = {"parallax only": {"horizon": False, "regions": False}, "parallax + horizon": {"regions": False},
         "parallax + regions": {"horizon": False}, "all (default)": {}}


def _rule_rows(seq, truth: dict, height: float) -> dict:
    """Road IoU of the plane check with each of its rules on or off (:data:`RULES`), on copies of the
    segmenter's labels of ``seq``; time per view of the check alone."""
    import copy

    from pavemap.segment.plane_check import PlaneCheckConfig, plane_check_sequence

    out = {}
    for name, kw in RULES.items():
        s = copy.deepcopy(seq)
        work = Path(tempfile.mkdtemp(prefix="pavemap-rules-"))
        _labels_copied_to(s, work)
        t0 = time.perf_counter()
        plane_check_sequence(s, height, PlaneCheckConfig(**kw))
        sec = time.perf_counter() - t0
        out[name] = {"road_iou": _road_iou(s, truth), "seconds_per_view": round(sec / len(truth), 3)}
        shutil.rmtree(work)
    return out


def _labels_copied_to(seq, work: Path) -> dict:
    """Copy each view's label PNG of ``seq`` to ``work``/<camera>/<frame>.png and point the view at the copy (the
    check rewrites labels in place); {(frame, camera): the labels as they were}."""
    from pavemap.io.sequence import load_semantics

    before = {}
    for f in seq.frames:
        for cam, v in f.views.items():
            dst = work / cam / f"{f.index:06d}.png"
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(seq.path(v.semantics), dst)
            v.semantics, before[(f.index, cam)] = str(dst), load_semantics(dst)
    return before


def _road_iou(seq, truth: dict) -> float:
    """Road IoU of ``seq``'s labels against ``truth`` {(frame, camera): (H, W) bool}, over all views."""
    from pavemap.io.sequence import load_semantics

    inter = union = 0
    for f in seq.frames:
        for c, v in f.views.items():
            road, tr = seq.class_lut("road")[load_semantics(seq.path(v.semantics))], truth[(f.index, c)]
            inter, union = inter + int((road & tr).sum()), union + int((road | tr).sum())
    return round(inter / union, 4)


def _plane_check_real(data: Path) -> list[dict]:
    import copy

    from PIL import Image

    from pavemap.io.sequence import load_rgb, load_semantics, read_sequence
    from pavemap.segment.auto import espnet_semantics
    from pavemap.segment.labels import PRESETS
    from pavemap.segment.plane_check import PlaneCheckConfig, plane_check_sequence
    from pavemap.segment.road_vote import road_vote_sequence

    rows, tiles = [], []
    for clip, show in (("nuscenes-clip-1", 18), ("nuscenes-clip-2", 5)):
        root = data / "real" / clip
        if not (root / "sequence.json").is_file():
            rows.append({"clip": clip, "skipped": f"{root} not imported (run detector_bench.py --parts clips)"})
            continue
        seq = copy.deepcopy(read_sequence(root))
        for f in seq.frames:  # the import's labels are checked and voted already: the segmenter's own, again
            for v in f.views.values():
                v.semantics = None
        raw = data / f"plane-check-{clip}-raw"
        shutil.rmtree(raw, ignore_errors=True)
        seq = espnet_semantics(seq, device="cpu", out_root=raw, plane_check=False, road_vote=False)
        seq.classes = list(PRESETS["cityscapes"]().classes)
        work = data / f"plane-check-{clip}"
        shutil.rmtree(work, ignore_errors=True)
        before = _labels_copied_to(seq, work)
        shares = {}
        for name, kw in RULES.items():  # the default last: its labels stay for the figure
            for f in seq.frames:
                for cam, v in f.views.items():
                    Image.fromarray(before[(f.index, cam)]).save(v.semantics)
            t0 = time.perf_counter()
            rep = plane_check_sequence(seq, cfg=PlaneCheckConfig(**kw))
            sec = time.perf_counter() - t0
            shares[name] = round(rep.relabelled_px / max(rep.road_px, 1), 4)
        checked = {(f.index, cam): load_semantics(v.semantics) for f in seq.frames for cam, v in f.views.items()}
        vote = road_vote_sequence(seq)
        rows.append({"clip": clip, "views": rep.views, "checked": rep.checked, "road_share_relabelled": shares[name],
                     "road_share_relabelled_by_rules": shares, "seconds": round(sec, 2),
                     "seconds_per_view": round(sec / max(rep.views, 1), 3), "left_unchanged": rep.skipped,
                     "road_vote": {"views": vote.voted, "road_share_relabelled":
                                   round(vote.relabelled_px / max(vote.road_px, 1), 4),
                                   "seconds_per_view": round(vote.seconds / max(vote.views, 1), 3),
                                   "skipped": vote.skipped}})
        print(rows[-1], flush=True)
        f = next(fr for fr in seq.frames if fr.index == show)
        cam, v = next(iter(f.views.items()))
        img, lab, was = load_rgb(seq.path(v.image)), load_semantics(v.semantics), before[(f.index, cam)]
        vis = img.copy()
        vis[lab == 0] = (0.6 * vis[lab == 0] + 0.4 * np.array([128, 64, 128])).astype(np.uint8)
        vis[(was == 0) & (checked[(f.index, cam)] != 0)] = [255, 0, 255]
        vis[(checked[(f.index, cam)] == 0) & (lab != 0)] = [0, 230, 255]
        tiles.append(np.asarray(Image.fromarray(vis).resize((800, 450))))
    if tiles:
        fig = ROOT / "docs" / "plane_check_nuscenes.jpg"
        Image.fromarray(np.concatenate(tiles, 1)).save(fig, quality=85)
    return rows


def main() -> None:
    ap = bench_parser(__doc__, "", ROOT / "bench" / "results" / "segment.json")
    ap.add_argument("--e2e-frames", type=int, default=12)
    ap.add_argument("--e2e-frames-nuscenes", type=int, default=8)
    ap.add_argument("--skip-e2e", action="store_true")
    ap.add_argument("--parts", nargs="+",
                    default=["synthetic", "real", "confusion", "plane_check", "road_vote", "e2e"],
                    help="what to run; the other parts keep their figures from the results file")
    args = ap.parse_args()
    args.data.mkdir(parents=True, exist_ok=True)
    commit = git_commit()
    res = json.loads(args.results.read_text()) if args.results.is_file() else {}
    res.update({**machine_entry(), "commit": commit, "device": args.device, "load_average_start": os.getloadavg()})
    if "synthetic" in args.parts:
        res["synthetic"] = synthetic_rows(args.data, args.device)
    if "real" in args.parts:
        res["real"] = real_rows(args.device)
    if "confusion" in args.parts:
        res["confusion"] = {"commit": commit, "rows": confusion_rows(args.data, args.device)}
    if "plane_check" in args.parts:
        res["plane_check"] = {"commit": commit, **plane_check_rows(args.data, args.device)}
    if "road_vote" in args.parts:
        res["road_vote"] = {"commit": commit, "rows": road_vote_rows(args.data, args.device)}
    if "e2e" in args.parts and not args.skip_e2e:
        res["end_to_end"] = e2e(args.data, args.device, args.e2e_frames, args.epochs)
        res["end_to_end_nuscenes"] = e2e(args.data, args.device, args.e2e_frames_nuscenes, args.epochs, "nuscenes-like",
                                         0.25)
    res["load_average_end"] = os.getloadavg()
    write_results(args.results, res)


if __name__ == "__main__":
    main()
