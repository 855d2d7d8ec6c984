"""Command-line options shared by the stage benchmarks (mesh_bench, pose_bench)."""

from __future__ import annotations

import argparse
import os
from pathlib import Path


def bench_parser(doc: str, presets: str, results: Path) -> argparse.ArgumentParser:
    """--device, --data (PAVEMAP_BENCH_DATA, default /tmp/pavemap-bench), --presets, --epochs, --results."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("PAVEMAP_BENCH_DATA", "/tmp/pavemap-bench")))
    ap.add_argument("--presets", default=presets)
    ap.add_argument("--epochs", type=int, default=None)
    ap.add_argument("--results", type=Path, default=results)
    return ap


def git_commit() -> str:
    """The checkout's short commit hash, the one every results entry names ("unknown" outside a git clone)."""
    import subprocess

    r = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                       cwd=Path(__file__).resolve().parent)
    return r.stdout.strip() or "unknown"


def machine_entry() -> dict:
    """Machine and date of a results entry."""
    import platform
    import time

    import torch

    return {"machine": f"{platform.machine()} {os.cpu_count()} cores, torch {torch.__version__}",
            "date": time.strftime("%Y-%m-%d %H:%M")}


def write_results(path: Path, results: dict) -> None:
    """Write the results JSON atomically (never a half-written file) and say where."""
    from pavemap.io.atomic import atomic_write_json

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(path, results)
    print(f"-> {path}")


def no_depth_copy(src: Path, dst: Path) -> Path:
    """``dst``: the drive ``src`` without its depth layer (sequence.json rewritten, images / labels / truth
    linked), made once; what the no-depth rows of a benchmark read."""
    import json

    if not (dst / "sequence.json").is_file():
        dst.mkdir(parents=True, exist_ok=True)
        for sub in ("images", "semantics", "truth"):
            if (src / sub).exists() and not (dst / sub).exists():
                (dst / sub).symlink_to((src / sub).resolve())
        d = json.loads((src / "sequence.json").read_text())
        for f in d["frames"]:
            for v in f["views"].values():
                v["depth"] = None
        (dst / "sequence.json").write_text(json.dumps(d))
    return dst


def fresh_run_folder(out: Path) -> None:
    """Empty a run folder of an earlier benchmark run, deleting only what pavemap wrote there (a rerun into it
    would lend its stages and be no measurement); stops when other files remain."""
    from pavemap.io.owned import read_owner, remove_owned

    if not out.exists():
        return
    owner = read_owner(out)
    left = remove_owned(out, owner) if owner is not None else sorted(p.name for p in out.iterdir())
    if left:
        raise SystemExit(f"{out}: holds files pavemap did not write ({', '.join(left[:5])}); move them or pick "
                         "another --data folder")
