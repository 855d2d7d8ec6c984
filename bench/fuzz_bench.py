"""Fuzz benchmark: the readers of ``sequence.json`` and ``detections.jsonl`` on 10,000+ mutated files.

The same strategies and targets as ``tests/test_fuzz.py`` (``tests/fuzz_support.py``), many more cases:
each case ends in success, in the project's own error (SequenceError / PavemapError), or in an
*unexpected* exception, which is counted by type with its first message (the target is 0). Writes
``bench/results/fuzz.json``: cases per target, outcomes, unexpected exceptions, cases per second.

    python bench/fuzz_bench.py [--cases 10000] [--seed 14]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
import traceback
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(ROOT / "tests"))

from hypothesis import HealthCheck, given, seed, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from common import machine_entry, write_results  # noqa: E402
from fuzz_support import (  # noqa: E402
    DETECTIONS,
    detections_target,
    dump,
    make_seq,
    mutated,
    mutated_bytes,
    sequence_target,
)
from pavemap.io.sequence import read_sequence  # noqa: E402

OUT = ROOT / "bench" / "results" / "fuzz.json"


def _run(name: str, strategy: st.SearchStrategy, target, cases: int, rng_seed: int) -> dict:  # noqa: ANN001
    """Run ``target`` on ``cases`` examples of ``strategy``; count outcomes, never stop on a failure."""
    outcomes: Counter[str] = Counter()
    unexpected: dict[str, dict] = {}
    t0 = time.perf_counter()

    @seed(rng_seed)
    @settings(max_examples=cases, deadline=None, database=None, phases=[__import__("hypothesis").Phase.generate],
              suppress_health_check=list(HealthCheck))
    @given(strategy)
    def case(value: object) -> None:
        try:
            outcomes[target(value)] += 1
        except Exception as e:  # noqa: BLE001 - counting them is the point
            key = type(e).__name__
            outcomes["unexpected"] += 1
            entry = unexpected.setdefault(key, {"count": 0, "first": str(e)[:300],
                                                "where": traceback.format_exc(limit=-3)[-1200:]})
            entry["count"] += 1

    case()
    seconds = time.perf_counter() - t0
    n = sum(outcomes.values())
    print(f"{name}: {n} cases, {dict(outcomes)} in {seconds:.1f} s")
    return {"cases": n, "outcomes": dict(outcomes), "unexpected": unexpected, "seconds": round(seconds, 2),
            "cases_per_second": round(n / seconds, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=10000, help="total cases over the four targets")
    ap.add_argument("--seed", type=int, default=14)
    ap.add_argument("--results", type=Path, default=OUT)
    args = ap.parse_args()

    work = Path(tempfile.mkdtemp(prefix="pavemap-fuzz-bench-"))
    seq_dir = make_seq(work / "seq")
    base = json.loads((seq_dir / "sequence.json").read_text())
    seq = read_sequence(seq_dir)
    det_text = (seq_dir / "detections.jsonl").read_bytes()
    det_file = work / "d.jsonl"
    per = args.cases // 4 + (args.cases % 4 > 0)
    load = os.getloadavg()
    targets = {
        "sequence_json_structure": (mutated(base), lambda v: sequence_target(seq_dir, dump(v))),
        "sequence_json_bytes": (mutated_bytes(dump(base)), lambda b: sequence_target(seq_dir, b)),
        "detection_records": (st.lists(mutated(DETECTIONS[0]), min_size=1, max_size=3),
                              lambda rs: detections_target(seq, det_file, b"\n".join(dump(r) for r in rs) + b"\n")),
        "detections_bytes": (mutated_bytes(det_text), lambda b: detections_target(seq, det_file, b)),
    }
    results = {name: _run(name, strat, target, per, args.seed + i)
               for i, (name, (strat, target)) in enumerate(targets.items())}
    total = sum(r["cases"] for r in results.values())
    unexpected = sum(r["outcomes"].get("unexpected", 0) for r in results.values())
    entry = {**machine_entry(), "load_avg_1_5_15_before": [round(x, 2) for x in load],
             "load_avg_1_5_15_after": [round(x, 2) for x in os.getloadavg()], "seed": args.seed,
             "cases": total, "unexpected_exceptions": unexpected, "targets": results}
    write_results(args.results, entry)
    print(f"{total} cases, {unexpected} unexpected exceptions")


if __name__ == "__main__":
    main()
