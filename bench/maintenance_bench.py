"""Maintenance benchmark (issue 16): surface measures of mapped defects against the synthetic truth.

Per preset (kitti-like, nuscenes-like; a shorter drive than the presets' defaults, more defects per
100 m, so each run fits a few minutes of the shared 2-core CPU) and depth mode (``none``: monocular,
pavemap's default, rows first; ``sparse``: LiDAR-like sparse depth), the drive is synthesized once with
sparse depth (the no-depth copy is its sequence.json without the depth layer), ``pavemap.run`` maps it,
fusion is redone in memory for the instance label image, and :func:`pavemap.maintain.measure.measure_instances`
measures every instance on the reconstructed mesh. Mapped defects are matched to the truth with
:func:`pavemap.evaluate.match` (centroids within 0.5 m or polygons overlapping, one to one); measures are
compared on matched pairs of the same class:

- pothole depth error (mm, max depth below the ring plane vs the carved truth ``depth_max_m``),
  median and p90 of |error|, mean depth and volume errors, how many were not measurable (and why);
- area error (%, |mapped area_m2 - truth area| / truth) of potholes and alligator cracking;
- crack length error (%, skeleton ``crack_length_m`` vs the truth polyline ``length_m``; the principal
  extent ``length_m`` alongside for comparison) and the share with ``orientation_ok``;
- severity level agreement (:func:`pavemap.maintain.policy.severity_level` of mapped and truth measures),
  per class with every disagreeing pair and its measures (``severity_by_class``, also printed);
- the same pothole measures on the *true* surface sampled at the mesh grid (``truth_surface``): the
  error of the measuring method alone, so a miss can be told apart from the mesh's smoothing;
- the same measures after fusing the same detections on the same mesh with ``fusion.association:
  footprint`` (``footprint_association``): the default ``hit`` association puts each detection on a
  0.3 m disk around its box centre's surface point, so a 4 m crack's instance is ~1 m long.

A rerun resumes each run (the mesh is reused), so its ``run`` seconds are short; ``seconds.previous``
keeps the seconds of the results file it replaces.

The segment row (``segments``, :func:`segment_row`; ``--no-segments`` leaves it out): a kitti-like drive
whose first half is clean and second half damaged (``pavemap synth --defect-free-until``), mapped end to
end without depth, cut into 10 m segments; per segment the mapped PCI-like index beside the truth's density
and the truth's own index, and whether the index falls as the density rises.

Writes ``bench/results/maintenance.json`` (commit, uptime, seconds per run).

    python bench/maintenance_bench.py [--presets kitti-like nuscenes-like] [--depth none sparse] [--device cpu]
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
sys.path.insert(0, str(Path(__file__).parent))

from common import git_commit, machine_entry, no_depth_copy, write_results  # noqa: E402

RESULTS = ROOT / "bench" / "results" / "maintenance.json"
CONFIG_OF = {"nuscenes-like": "nuscenes", "kitti-like": "kitti"}
# Shorter drives with more defects (potholes over-weighted so the depth statistics have samples).
DRIVES = {"kitti-like": {"frames": 40, "scale": 0.5, "road_after": 30.0},
          "nuscenes-like": {"frames": 14, "scale": 0.3, "road_after": 30.0}}
WORLD = {"defect_density": 40.0, "class_mix": (0.3, 0.2, 0.15, 0.35)}
TARGETS = {"pothole_depth_abs_err_mm": {"median": 10.0, "p90": 20.0}, "area_err_pct_median": 25.0,
           "crack_length_err_pct_median": 20.0, "severity_agreement": 0.85}
# The segment row: a kitti-like drive of 79 m without depth, no defect centred in its first 40 m (synth's
# defect_free_until_m), cut into 10 m segments (4 clean, 4 damaged), so the index meets a range of densities.
SEGMENT_DRIVE = {"preset": "kitti-like", "seed": 1, "frames": 80, "scale": 0.5, "road_after": 8.0,
                 "defect_free_until_m": 40.0, "defect_density": 40.0, "class_mix": WORLD["class_mix"]}
SEGMENT_M = 10.0


def drive(data: Path, preset: str, depth: str, device: str) -> Path:
    """The synthesized drive of ``preset`` with sparse depth, or its copy without the depth layer."""
    from pavemap.synth import synthesize

    src = data / f"maint-{preset}-sparse"
    if not (src / "sequence.json").is_file():
        t = time.perf_counter()
        synthesize(src, preset, seed=0, depth="sparse", device=device, progress=False, **DRIVES[preset], **WORLD)
        print(f"{preset}: synthesized in {time.perf_counter() - t:.0f} s", flush=True)
    if depth == "sparse":
        return src
    return no_depth_copy(src, data / f"maint-{preset}-none")


def truth_surface(seq_root: Path, surface):  # noqa: ANN001, ANN201
    """The true surface (truth/height.npy, bilinear) sampled at the mesh's vertices: a HeightField."""

    from pavemap.geometry import HeightField
    from pavemap.io.truth import read_truth_height

    t = read_truth_height(seq_root)
    z, inside = t.height_at(surface.grid_xy().reshape(-1, 2).double().cpu())
    ny, nx = surface.heights.shape
    return HeightField(surface.x0, surface.y0, surface.res, z.float().reshape(ny, nx),
                       inside.reshape(ny, nx) & surface.valid.cpu())


def map_and_measure(seq_dir: Path, run_dir: Path, preset: str, device: str, floor_sweep: bool = False) -> tuple:
    """pavemap.run, then fusion again in memory (label image) and the maintenance stage the pipeline runs
    (:func:`pavemap.maintain.assess`: surface and sample measures, footprint sizes) on the mesh, and the surface
    measures on the true surface without samples (the measuring method alone); ``floor_sweep``: the maintenance
    stage's ``floor_sweep`` (pothole floors from the images where the drive has no depth layer)."""
    import pavemap
    from pavemap.detect.config import PAPER_TAU_CONF
    from pavemap.io.sequence import DETECTIONS_FILE, read_detections, read_sequence
    from pavemap.maintain import assess
    from pavemap.maintain.measure import MeasureConfig, measure_instances
    from pavemap.mesh import load_mesh
    from pavemap.mesh.geometry import mark_observed
    from pavemap.pipeline import filter_and_fuse

    cfg = pavemap.load_config(CONFIG_OF[preset])
    cfg.device = device
    t = time.perf_counter()
    pavemap.run(seq_dir, cfg, run_dir, overwrite=True, progress=False)  # a rerun resumes: the mesh is reused
    run_s = time.perf_counter() - t
    seq = read_sequence(seq_dir)
    mesh = load_mesh(run_dir / "mesh")
    dets = read_detections(run_dir / DETECTIONS_FILE)
    filt = dataclasses.replace(cfg.filter, tau_conf=PAPER_TAU_CONF[cfg.preset])  # sim detections, as the run
    res = filter_and_fuse(seq, dets, mesh.surface, filt, cfg.fusion, mesh=mesh, progress=False)
    mark_observed(res.instances, mesh)
    on_truth = copy.deepcopy(res.instances)
    t = time.perf_counter()
    assess(res.instances, seq, mesh.surface, res.instance_labels, mesh.observed, samples=mesh.samples,
           floor_sweep=floor_sweep)
    measure_s = time.perf_counter() - t
    # the measuring method alone: the true surface is the floor's measurement, no samples (assess would add the
    # drive's depth pixels, which made this row 4.5 mm with sparse depth against 0.7 mm without)
    measure_instances(on_truth, truth_surface(seq_dir, mesh.surface), res.instance_labels,
                      config=MeasureConfig(surface_floor=True))
    # Diagnostic: the same mesh and detections fused with fusion.association = footprint (each detection
    # on the vertices under its whole box, not a 0.3 m disk around the box centre's hit)
    fc = dataclasses.replace(cfg.fusion, association="footprint")
    alt = filter_and_fuse(seq, dets, mesh.surface, filt, fc, mesh=mesh, progress=False)
    assess(alt.instances, seq, mesh.surface, alt.instance_labels, mesh.observed, samples=mesh.samples)
    return res.instances, on_truth, alt.instances, {"run": round(run_s, 1), "measure": round(measure_s, 3)}


def _q(v: list[float], p: float) -> float | None:
    return round(float(np.percentile(v, p)), 2) if v else None


def _severity(cls: int, measures: dict) -> str | None:
    try:
        from pavemap.maintain.policy import severity_level
    except ImportError:  # the policy module is helper B's; without it there is no severity row
        return None
    return severity_level(cls, measures)


def truth_measures(props: dict) -> dict:
    """The truth record in the measure keys the policy reads (carved depth in mm, polyline length)."""
    m = dict(props)
    if props.get("depth_max_m") is not None:
        m["depth_max_mm"] = 1000.0 * props["depth_max_m"]
    if props.get("cls") in (0, 1):
        m["crack_length_m"] = props["length_m"]
    return m


def compare(instances: list, on_truth: list, seq_root: Path) -> dict:
    """Per matched pair of one class: the measure errors (rows) and the severity agreement."""
    from pavemap.evaluate import match
    from pavemap.synth.generate import load_truth_defects

    truth = load_truth_defects(seq_root)
    pxy = np.array([i.centroid for i in instances], float).reshape(-1, 2)
    gxy = np.array([[t.polygon.centroid.x, t.polygon.centroid.y] for t in truth], float).reshape(-1, 2)
    pairs = match([i.polygon for i in instances], pxy, [t.polygon for t in truth], gxy)
    rows = []
    for p, g, dist in pairs:
        inst, tr, tp = instances[p], truth[g], truth[g].properties
        row = {"truth_id": tr.id, "cls": tr.cls, "mapped_cls": inst.cls, "dist_m": round(dist, 3),
               "area_m2": round(inst.area_m2, 3), "truth_area_m2": tp["area_m2"]}
        if inst.cls == tr.cls:
            e, et = inst.extra, on_truth[p].extra
            if tr.cls == 3:
                row.update({k: e.get(k) for k in ("measurable", "measure_note", "depth_max_mm", "depth_mean_mm",
                                                  "volume_l", "depth_sigma_mm")})
                row.update({"truth_depth_max_mm": round(1000 * tp["depth_max_m"], 1),
                            "truth_depth_mean_mm": round(1000 * tp["depth_mean_m"], 1),
                            "truth_volume_l": tp["volume_l"], "on_true_surface_depth_max_mm": et.get("depth_max_mm"),
                            "on_true_surface_volume_l": et.get("volume_l")})
            elif tr.cls in (0, 1):
                row.update({"crack_length_m": e.get("crack_length_m"), "extent_m": round(inst.length_m, 3),
                            "truth_length_m": tp["length_m"], "orientation_deg": e.get("orientation_deg"),
                            "orientation_ok": e.get("orientation_ok")})
            mapped = {**e, "area_m2": inst.area_m2, "length_m": inst.length_m}
            lv, lt = _severity(inst.cls, mapped), _severity(tr.cls, truth_measures(tp))
            if lv is not None:
                row.update({"severity_level": lv, "truth_severity_level": lt})
        rows.append(row)
    n_truth = {c: sum(1 for t in truth if t.cls == c) for c in range(4)}
    return {"rows": rows, "truth_by_class": n_truth, "mapped": len(instances), "matched": len(pairs)}


def summarise(rows: list[dict]) -> dict:
    """Median / p90 figures over matched rows (one preset, or several pooled)."""
    pits = [r for r in rows if r["cls"] == 3 and r["mapped_cls"] == 3]
    meas = [r for r in pits if r.get("measurable")]
    dep = [abs(r["depth_max_mm"] - r["truth_depth_max_mm"]) for r in meas]
    sdep = [r["depth_max_mm"] - r["truth_depth_max_mm"] for r in meas]
    mean = [abs(r["depth_mean_mm"] - r["truth_depth_mean_mm"]) for r in meas]
    vol = [100 * abs(r["volume_l"] - r["truth_volume_l"]) / max(r["truth_volume_l"], 1e-6) for r in meas]
    on_t = [abs(r["on_true_surface_depth_max_mm"] - r["truth_depth_max_mm"]) for r in pits
            if r.get("on_true_surface_depth_max_mm") is not None]
    area = [100 * abs(r["area_m2"] - r["truth_area_m2"]) / r["truth_area_m2"] for r in rows
            if r["cls"] in (2, 3) and r["mapped_cls"] == r["cls"]]
    cracks = [r for r in rows if r["cls"] in (0, 1) and r["mapped_cls"] == r["cls"]]
    clen = [100 * abs(r["crack_length_m"] - r["truth_length_m"]) / r["truth_length_m"] for r in cracks
            if r.get("crack_length_m") is not None]
    ext = [100 * abs(r["extent_m"] - r["truth_length_m"]) / r["truth_length_m"] for r in cracks]
    orient = [r["orientation_ok"] for r in cracks if r.get("orientation_ok") is not None]
    sev = [r["severity_level"] == r["truth_severity_level"] for r in rows if "severity_level" in r]
    notes: dict[str, int] = {}
    for r in pits:
        if not r.get("measurable"):  # why, without the fallback's own value ("; severity from area_m2 = 0.42")
            why = (r.get("measure_note") or "?").split("; severity from")[0]
            notes[why] = notes.get(why, 0) + 1
    return {
        "potholes_matched": len(pits), "potholes_measured": len(meas), "not_measurable": notes,
        "depth_abs_err_mm": {"median": _q(dep, 50), "p90": _q(dep, 90)},
        "depth_signed_err_mm_median": _q(sdep, 50),
        "depth_mean_abs_err_mm_median": _q(mean, 50), "volume_err_pct_median": _q(vol, 50),
        "depth_abs_err_on_true_surface_mm": {"median": _q(on_t, 50), "p90": _q(on_t, 90)},
        "area_pairs": len(area), "area_err_pct_median": _q(area, 50),
        "cracks_matched": len(cracks), "crack_length_err_pct_median": _q(clen, 50),
        "extent_length_err_pct_median": _q(ext, 50),
        "orientation_ok_share": round(float(np.mean(orient)), 3) if orient else None,
        "severity_pairs": len(sev), "severity_agreement": round(float(np.mean(sev)), 3) if sev else None,
    }


#: The measure the policy grades each class by (mapped key, truth key of a compare() row).
SEVERITY_MEASURE = {0: ("crack_length_m", "truth_length_m"), 1: ("crack_length_m", "truth_length_m"),
                    2: ("area_m2", "truth_area_m2"), 3: ("depth_max_mm", "truth_depth_max_mm")}


def severity_by_class(rows: list[dict]) -> dict:
    """Per class: matched pairs graded, how many agree, and each disagreeing pair with the mapped and the true
    measure (potholes also their areas: without a measured depth the policy's fallback grades by area)."""
    from pavemap.types import DEFECT_CODES

    out = {}
    for c, (mk, tk) in SEVERITY_MEASURE.items():
        graded = [r for r in rows if r["cls"] == c and "severity_level" in r]
        bad = []
        for r in graded:
            if r["severity_level"] == r["truth_severity_level"]:
                continue
            bad.append({"preset": r.get("preset"), "truth_id": r["truth_id"], "truth": r["truth_severity_level"],
                        "mapped": r["severity_level"], "measure": mk, "mapped_value": r.get(mk),
                        "truth_value": r.get(tk),
                        **({"area_m2": r["area_m2"], "truth_area_m2": r["truth_area_m2"]} if c == 3 else {}),
                        **({"note": r["measure_note"]} if r.get("measure_note") else {})})
        out[DEFECT_CODES[c]] = {"pairs": len(graded), "agree": len(graded) - len(bad), "disagree": bad}
    return out


def print_severity(depth: str, table: dict) -> None:
    """The disagreeing pairs, one line each: which class, level and measure missed."""
    for code, t in table.items():
        print(f"severity {depth} {code}: {t['agree']} / {t['pairs']} agree", flush=True)
        for b in t["disagree"]:
            area = f", area_m2 {b['area_m2']} (truth {b['truth_area_m2']})" if "area_m2" in b else ""
            print(f"  {b['preset']} #{b['truth_id']}: truth {b['truth']}, mapped {b['mapped']}: {b['measure']} "
                  f"{b['mapped_value']} (truth {b['truth_value']}){area} {b.get('note', '')}", flush=True)


def meets(s: dict) -> dict:
    t = TARGETS

    def ok(v: float | None, lim: float, ge: bool = False) -> bool | None:
        return None if v is None else (v >= lim if ge else v <= lim)

    return {"depth_median": ok(s["depth_abs_err_mm"]["median"], t["pothole_depth_abs_err_mm"]["median"]),
            "depth_p90": ok(s["depth_abs_err_mm"]["p90"], t["pothole_depth_abs_err_mm"]["p90"]),
            "area": ok(s["area_err_pct_median"], t["area_err_pct_median"]),
            "crack_length": ok(s["crack_length_err_pct_median"], t["crack_length_err_pct_median"]),
            "severity": ok(s["severity_agreement"], t["severity_agreement"], ge=True)}


def previous_seconds(path: Path) -> dict:
    """{(depth, preset): seconds} of the results file already there (empty when none)."""
    try:
        old = json.loads(path.read_text())
        # without their own "previous": one run back, not a chain of every earlier run
        return {(d, p): {k: v for k, v in e["seconds"].items() if k != "previous"}
                for d, r in old["results"].items() for p, e in r["presets"].items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


def segment_row(data: Path, device: str) -> dict:
    """The clean-then-damaged drive (:data:`SEGMENT_DRIVE`) mapped end to end without depth (``pavemap.run``,
    ``maintenance.segment_m`` = :data:`SEGMENT_M`): per segment the mapped index and defects beside the truth's
    (its defects per 100 m² of corridor, and the same index computed on the truth records); whether the mapped
    index falls as the truth's density rises (Spearman rank, pairwise order, clean segments above damaged ones)."""
    import pavemap
    from pavemap.geometry.chainage import chainage, route_polyline
    from pavemap.maintain.policy import load_policy, severity_level
    from pavemap.maintain.segments import build_segments
    from pavemap.synth import load_truth_defects, synthesize

    kw = dict(SEGMENT_DRIVE)
    preset, seed = kw.pop("preset"), kw.pop("seed")
    seq_dir, run_dir = data / f"maint-segments-{preset}-none", data / f"maint-segments-run-{preset}-none"
    t = time.perf_counter()
    if not (seq_dir / "sequence.json").is_file():
        synthesize(seq_dir, preset, seed=seed, depth="none", device=device, progress=False, **kw)
    synth_s = time.perf_counter() - t
    cfg = pavemap.load_config(CONFIG_OF[preset])
    cfg.device, cfg.maintenance.segment_m = device, SEGMENT_M
    t = time.perf_counter()
    res = pavemap.run(seq_dir, cfg, run_dir, overwrite=True, progress=False)  # a rerun resumes the mesh
    run_s = time.perf_counter() - t
    from pavemap.io.sequence import read_sequence

    route = route_polyline(read_sequence(seq_dir).trajectory())
    pol = load_policy()
    truth = [truth_measures(t.properties) for t in load_truth_defects(seq_dir)]
    s, _ = chainage(route, np.array([[r["x_m"], r["y_m"]] for r in truth]).reshape(-1, 2))
    for r, sk in zip(truth, s, strict=True):
        r["chainage_m"] = float(sk)
        r["severity_level"] = severity_level(r["cls"], r, pol)
    tsegs = build_segments(route, truth, pol, SEGMENT_M)
    if [(a.start_m, a.end_m) for a in tsegs] != [(b.start_m, b.end_m) for b in res.segments]:
        raise RuntimeError("the truth's segments and the run's differ: not the same route")
    rows = [{"segment": m.id, "chainage_m": [round(m.start_m, 1), round(m.end_m, 1)],
             "truth_defects": sum(tr.counts.values()),
             "truth_per_100m2": round(100.0 * sum(tr.counts.values()) / tr.corridor_area_m2, 3),
             "truth_pci": round(tr.pci, 1), "truth_total_deduct": round(tr.total_deduct, 1),
             "mapped_defects": sum(m.counts.values()), "pci": round(m.pci, 1), "total_deduct": round(m.total_deduct, 1)}
            for tr, m in zip(tsegs, res.segments, strict=True)]
    return {"drive": {**SEGMENT_DRIVE, "segment_m": SEGMENT_M}, "rows": rows, **segment_order(rows),
            "seconds": {"synth": round(synth_s, 1), "run": round(run_s, 1)}}


def segment_order(rows: list[dict]) -> dict:
    """Does the mapped index fall as the truth's density rises? Spearman rank of the index against the truth's
    density and against the truth's own index; pairs of segments whose order disagrees with the truth's
    density (a denser one scored higher); whether every clean segment scores above every damaged one. The index
    is 0 wherever the corrected deduct reaches 100 (one high pothole in a 10 m segment does), so the summed
    deducts (each capped at 100, not their total) are ranked against the density among the damaged segments."""
    from scipy.stats import spearmanr

    dens = np.array([r["truth_per_100m2"] for r in rows])
    pci = np.array([r["pci"] for r in rows])
    tpci = np.array([r["truth_pci"] for r in rows])

    def rho(a: np.ndarray, b: np.ndarray) -> float | None:
        v = spearmanr(a, b).statistic if len(a) > 2 and np.ptp(a) > 0 and np.ptp(b) > 0 else None
        return None if v is None or not np.isfinite(v) else round(float(v), 3)

    worse = [(int(rows[i]["segment"]), int(rows[j]["segment"])) for i in range(len(rows)) for j in range(len(rows))
             if dens[j] > dens[i] and pci[j] > pci[i]]  # j denser in the truth, yet scored better
    clean, damaged = pci[dens == 0], pci[dens > 0]
    tdd = np.array([r["total_deduct"] for r in rows])
    return {"spearman_pci_vs_truth_density": rho(pci, dens), "spearman_pci_vs_truth_pci": rho(pci, tpci),
            "spearman_total_deduct_vs_truth_density_damaged": rho(tdd[dens > 0], dens[dens > 0]),
            "order_violations": worse, "monotone": not worse,
            "clean_above_damaged": bool(len(clean) and len(damaged) and clean.min() > damaged.max())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", nargs="+", default=["kitti-like", "nuscenes-like"])
    ap.add_argument("--depth", nargs="+", default=["none", "sparse"], choices=("none", "sparse"))
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("PAVEMAP_BENCH_DATA", "/tmp/pavemap-bench")))
    ap.add_argument("--results", type=Path, default=RESULTS)
    ap.add_argument("--no-segments", action="store_true", help="leave out the clean-then-damaged segment row")
    args = ap.parse_args()
    t0 = time.perf_counter()
    previous = previous_seconds(args.results)  # a rerun resumes the mesh: keep the last run's stage seconds
    commit = git_commit()
    load_start = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    out: dict = {"benchmark": "surface measures of mapped defects vs synthetic truth (issue 16)",
                 **machine_entry(), "commit": commit, "uptime_start": load_start, "targets": TARGETS,
                 "drives": {p: {**DRIVES[p], **WORLD, "seed": 0} for p in args.presets}, "results": {}}
    for depth in args.depth:  # no depth first: pavemap's default
        rows_all: list[dict] = []
        rows_alt: list[dict] = []
        per = {}
        for preset in args.presets:
            t = time.perf_counter()
            seq_dir = drive(args.data, preset, depth, args.device)
            synth_s = time.perf_counter() - t
            inst, on_truth, alt, secs = map_and_measure(seq_dir, args.data / f"maint-run-{preset}-{depth}",
                                                        preset, args.device)
            cmp = compare(inst, on_truth, seq_dir)
            for r in cmp["rows"]:
                r["preset"] = preset
            rows_all += cmp["rows"]
            alt_rows = compare(alt, alt, seq_dir)["rows"]
            rows_alt += alt_rows
            s = summarise(cmp["rows"])
            per[preset] = {**s, "meets": meets(s), "mapped": cmp["mapped"], "matched": cmp["matched"],
                           "truth_by_class": cmp["truth_by_class"],
                           "seconds": {"synth": round(synth_s, 1), **secs, "previous": previous.get((depth, preset))},
                           "footprint_association": summarise(alt_rows), "pairs": cmp["rows"]}
            print(depth, preset, json.dumps({k: v for k, v in per[preset].items() if k != "pairs"}), flush=True)
        pooled = summarise(rows_all)
        alt_pooled = summarise(rows_alt)
        pooled["severity_by_class"] = severity_by_class(rows_all)
        print_severity(depth, pooled["severity_by_class"])
        out["results"][depth] = {"pooled": {**pooled, "meets": meets(pooled)},
                                 "pooled_footprint_association": {**alt_pooled, "meets": meets(alt_pooled)},
                                 "presets": per}
    if not args.no_segments:
        out["segments"] = segment_row(args.data, args.device)
        print("segments", json.dumps(out["segments"]), flush=True)
    out["uptime_end"] = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    out["seconds_total"] = round(time.perf_counter() - t0, 1)
    write_results(args.results, out)


if __name__ == "__main__":
    main()
