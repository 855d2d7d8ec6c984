"""The refinement on the real samples (issue 47; part ``real`` of bench/refine_bench.py).

The real KITTI sample (``pavemap import kitti``, its true poses, grey left camera) and the two shared nuScenes
front-camera clips (``pavemap import folder --poses sfm``: pycolmap, a minute or more each on this CPU) are
imported once into ``WORK/<name>`` and reused; then ``pavemap run`` on each, without and with
``--set mesh.refine=true mesh.consistency_check=true``, as a user would type it. Per run: the refinement's offset,
the consistency check's offset and flag, the camera height stage 1 used and the camera's height above the
final surface (used minus the refinement's offset: the refinement moves the whole surface), held-out PSNR,
seconds (stage 1 and the whole run).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
REFINE = ("mesh.refine=true", "mesh.consistency_check=true")
# name -> (shared data folder, import arguments after the folder, what is known of the camera height)
SAMPLES = {
    "kitti-sample": ("kitti-odometry-sample", ["kitti", "{src}", "--sequence", "90", "--camera", "0"],
                     "1.65 m (KITTI's setup)"),
    "nuscenes-clip-1": ("nuscenes-front-clip", ["folder", "{src}/images", "--cameras", "{src}/cameras.json",
                                                "--poses", "sfm"], "~1.5 m (nuScenes' front camera); SfM scale"),
    "nuscenes-clip-2": ("nuscenes-front-clip-2", ["folder", "{src}/images", "--cameras", "{src}/cameras.json",
                                                  "--poses", "sfm"], "~1.5 m (nuScenes' front camera); SfM scale"),
}


def _pavemap(args: list[str], log: Path) -> float:
    """Run the CLI of this checkout (its src first on the path); seconds. Fails with the log's tail."""
    env = {**os.environ, "PYTHONPATH": f"{ROOT / 'src'}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    t = time.perf_counter()
    with log.open("w") as fh:
        rc = subprocess.run([sys.executable, "-c", "import sys; from pavemap.cli import main; sys.exit(main())",
                             *args], env=env, stdout=fh, stderr=subprocess.STDOUT).returncode
    if rc != 0:
        raise SystemExit(f"pavemap {' '.join(args)} failed ({rc}):\n{log.read_text()[-2000:]}")
    return time.perf_counter() - t


def imported(data: Path, work: Path, name: str) -> Path:
    """The sample ``name`` as a sequence folder under ``work`` (imported once)."""
    folder, args, _ = SAMPLES[name]
    src, seq = data / folder, work / name
    if not src.is_dir():
        raise SystemExit(f"{src}: not found (--real-data: the folder of the shared samples)")
    if not (seq / "sequence.json").is_file():
        work.mkdir(parents=True, exist_ok=True)
        secs = _pavemap(["import", *[a.format(src=src) for a in args], "--out", str(seq)], work / f"{name}.import.log")
        print(f"{name}: imported in {secs:.0f} s", flush=True)
    return seq


def one_run(seq: Path, out: Path, refine: bool) -> dict:
    """``pavemap run`` on ``seq`` into ``out`` (replaced), with or without the refinement: what it measured."""
    args = ["run", str(seq), "--out", str(out), "--overwrite"]
    secs = _pavemap(args + (["--set", *REFINE] if refine else []), out.parent / f"{out.name}.log")
    m = json.loads((out / "metrics.json").read_text())
    mesh = m.get("mesh", {})
    used = ((mesh.get("geometry") or {}).get("camera_height") or {}).get("used_m")
    refined = mesh.get("refine")
    moved = refined["offset_m"] if refined else 0.0
    return {"refine": refined, "consistency": mesh.get("consistency"),
            "camera_height_used_m": used,
            "camera_height_above_surface_m": None if used is None else round(used - moved, 4),
            "geometry_source": (mesh.get("geometry") or {}).get("source"),
            "heldout_psnr_db": None if mesh.get("psnr") is None else round(mesh["psnr"], 3),
            "seconds_stage1": (m.get("seconds") or {}).get("mesh"), "seconds_run": round(secs, 1),
            "warnings": mesh.get("warnings", [])}


def real_samples(data: Path, work: Path, names: tuple[str, ...] = tuple(SAMPLES)) -> dict:
    """Per sample: its known camera height, and the runs without (``closed_form``) and with (``refined``) the
    refinement; run folders under ``work``/runs (kept: their reports are worth a look)."""
    out = {}
    for name in names:
        seq = imported(data, work, name)
        entry: dict = {"camera_height_known": SAMPLES[name][2]}
        for refine in (False, True):
            run_dir = work / "runs" / f"{name}-{'refined' if refine else 'closed'}"
            run_dir.parent.mkdir(parents=True, exist_ok=True)  # `run --overwrite` replaces only what pavemap wrote
            entry["refined" if refine else "closed_form"] = r = one_run(seq, run_dir, refine)
            print(name, "refined" if refine else "closed form", json.dumps({k: v for k, v in r.items()
                                                                            if k != "warnings"}), flush=True)
        out[name] = entry
    return out
