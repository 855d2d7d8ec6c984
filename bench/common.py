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
