"""Property-based: any mutation of ``sequence.json`` or ``detections.jsonl`` (wrong types, NaN / Infinity,
huge numbers, truncation, random bytes, deep nesting, other encodings) ends in success or the project's
own error, never another exception.

Fixed seed (``derandomize``) and a bounded number of examples, so CI is repeatable and stays within
about a minute; ``bench/fuzz_bench.py`` runs the same targets on 10,000+ cases.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fuzz_support import DETECTIONS, detections_target, dump, make_seq, mutated, mutated_bytes, sequence_target
from pavemap.io.sequence import read_sequence

FUZZ = settings(max_examples=250, derandomize=True, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
ROOT = Path(tempfile.mkdtemp(prefix="pavemap-fuzz-"))
SEQ = make_seq(ROOT / "seq")
BASE = json.loads((SEQ / "sequence.json").read_text())
SEQ_OBJ = read_sequence(SEQ)
DET_TEXT = (SEQ / "detections.jsonl").read_bytes()


@pytest.fixture(autouse=True, scope="module")
def _restore():
    yield
    (SEQ / "sequence.json").write_text(json.dumps(BASE))


def test_the_base_files_are_valid():
    assert sequence_target(SEQ, dump(BASE)) == "ok"
    assert detections_target(SEQ_OBJ, ROOT / "d.jsonl", DET_TEXT) == "ok"


@FUZZ
@given(mutated(BASE))
def test_sequence_json_structure(value):
    sequence_target(SEQ, dump(value))


@FUZZ
@given(mutated_bytes(dump(BASE)))
def test_sequence_json_bytes(data):
    sequence_target(SEQ, data)


@FUZZ
@given(st.lists(mutated(DETECTIONS[0]), min_size=1, max_size=3))
def test_detection_records(records):
    detections_target(SEQ_OBJ, ROOT / "d.jsonl", b"\n".join(dump(r) for r in records) + b"\n")


@FUZZ
@given(mutated_bytes(DET_TEXT))
def test_detections_bytes(data):
    detections_target(SEQ_OBJ, ROOT / "d.jsonl", data)
