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
