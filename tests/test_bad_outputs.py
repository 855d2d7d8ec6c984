"""Faults on the output side through the command line: an output folder that is an input, lies inside
one or holds someone else's files; ``--overwrite`` deleting only what pavemap wrote; write errors
(read-only, disk full, permission) as one line naming the file, with nothing left that looks complete.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from fuzz_support import CAM, H, W, check, invoke, looks_complete, make_seq
from fuzz_support import pose as _pose


@pytest.fixture
def seq(tmp_path) -> Path:
    return make_seq(tmp_path / "seq")


# ---------------------------------------------------------------------------- output folders


def test_out_equal_to_or_inside_the_input_is_refused(seq, tmp_path):
    before = sorted(p.relative_to(seq) for p in seq.rglob("*"))
    for out in (seq, seq / "runs" / "r"):
        for extra in ([], ["--overwrite"]):
            check(invoke("run", seq, "--out", out, "--detector", "file", *extra), 2, "input")
    assert sorted(p.relative_to(seq) for p in seq.rglob("*")) == before, "the input folder changed"
    images = seq / "images" / CAM
    cams = tmp_path / "cameras.json"
    cams.write_text(json.dumps({"cameras": {CAM: {"width": W, "height": H, "fx": 30, "fy": 30, "cx": 15.5,
                                                   "cy": 11.5}}}))
    check(invoke("import", "folder", images, "--cameras", cams, "--poses", tmp_path / "p.csv", "--out",
                 images / "x", "--overwrite"), 2, "inside the input folder")


def test_a_folder_pavemap_did_not_write_is_never_overwritten(seq, tmp_path):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("years of work")
    for args in (["run", seq, "--out", mine, "--detector", "file", "--overwrite"],
                 ["synth", "--out", mine, "--frames", "2", "--overwrite"],
                 ["fuse", seq, "--out", mine, "--surface", "plane", "--overwrite"]):
        check(invoke(*args), 2, "mine", "not written by pavemap")
    assert [p.name for p in mine.iterdir()] == ["thesis.tex"]
    (tmp_path / "a_file").write_text("x")
    check(invoke("run", seq, "--out", tmp_path / "a_file", "--detector", "file"), 2, "a_file", "not a folder")


def test_overwrite_deletes_only_what_pavemap_wrote(tmp_path):
    from pavemap.errors import PavemapError
    from pavemap.io.owned import claim

    out = tmp_path / "out"
    folder = claim(out, "run", False, info={"source": "A"})
    (out / "sub").mkdir()
    for rel in ("defects.geojson", "sub/map.npy"):
        (out / rel).write_text("pavemap's")
    folder.record()
    (out / "notes.txt").write_text("a person's")
    (out / "sub" / "sketch.png").write_text("a person's")
    with pytest.raises(PavemapError, match="holds a pavemap run"):
        claim(out, "run", False, info={"source": "B"})
    claim(out, "run", True, info={"source": "B"})
    left = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
    assert left == [".pavemap-owner.json", "notes.txt", "sub/sketch.png"]
    # a manifest entry cannot reach outside the folder
    outside = tmp_path / "precious.txt"
    outside.write_text("keep")
    (out / ".pavemap-owner.json").write_text(json.dumps({"format": "pavemap-owner/1", "kind": "run",
                                                         "files": ["../precious.txt", str(outside)]}))
    claim(out, "run", True)
    assert outside.read_text() == "keep"


def test_synth_overwrite_replaces_only_its_own_sequence(tmp_path):
    out = tmp_path / "s"
    args = ["synth", "--out", out, "--preset", "kitti-like", "--frames", "2", "--scale", "0.1"]
    check(invoke(*args), 0)
    check(invoke(*args), 2, "already exists (a pavemap sequence)", "--overwrite")
    check(invoke(*args, "--overwrite"), 0)
    (out / "notes.txt").write_text("mine")
    check(invoke(*args, "--overwrite"), 2, "notes.txt", "did not write")
    assert (out / "notes.txt").read_text() == "mine" and (out / "sequence.json").is_file()


# ---------------------------------------------------------------------------- write errors


def _failing_replace(code: int, target: str):  # noqa: ANN202
    real = os.replace

    def replace(src, dst, *a, **k):  # noqa: ANN001, ANN002, ANN003, ANN202
        if Path(dst).name == target:
            raise OSError(code, os.strerror(code))
        return real(src, dst, *a, **k)
    return replace


WRITE_CASES = [
    ("synth disk full", errno.ENOSPC, "sequence.json", "synth", "no space left on device"),
    ("detect read-only", errno.EROFS, "d.jsonl", "detect", "read-only file system"),
    ("fuse disk full", errno.ENOSPC, "defect_map.json", "fuse", "no space left on device"),
    ("import disk full", errno.ENOSPC, "sequence.json", "import", "no space left on device"),
    ("eval read-only", errno.EROFS, "eval.json", "eval", "read-only file system"),
    ("compare permission", errno.EACCES, "changes.json", "compare", "permission denied"),
]


@pytest.mark.parametrize(("code", "target", "command", "words"), [c[1:] for c in WRITE_CASES],
                         ids=[c[0] for c in WRITE_CASES])
def test_write_errors_are_one_line_naming_the_file(seq, tiny_seq, tmp_path, monkeypatch, code, target, command,
                                                  words):
    out = tmp_path / "out"
    if command in ("eval", "compare"):
        seq = tiny_seq.root
        check(invoke("fuse", seq, "--out", out, "--surface", "truth", "--no-truth"), 0)
    args = {
        "synth": ["synth", "--out", out, "--preset", "kitti-like", "--frames", "2", "--scale", "0.1"],
        "detect": ["detect", seq, "--detector", "file", "--out", out / target],
        "fuse": ["fuse", seq, "--out", out, "--surface", "plane"],
        "import": ["import", "folder", seq / "images" / CAM, "--cameras", _cameras(tmp_path), "--poses",
                   _poses(tmp_path), "--out", out, "--no-semantics"],
        "eval": ["eval", out, "--truth", seq],
        "compare": ["compare", out, out, "--out", tmp_path / "cmp"],
    }[command]
    monkeypatch.setattr(os, "replace", _failing_replace(code, target))
    r = invoke(*args)
    check(r, 2, words, target)
    assert len([ln for ln in r.output.splitlines() if ln.startswith("error:")]) == 1
    assert not list(tmp_path.rglob("*.partial-*")), "a temporary file was left behind"
    if command in ("synth", "fuse", "import"):
        assert not looks_complete(out)


def _cameras(tmp_path: Path) -> Path:
    p = tmp_path / "cameras.json"
    p.write_text(json.dumps({"cameras": {CAM: {"width": W, "height": H, "K": [[30, 0, 15.5], [0, 30, 11.5],
                                                                             [0, 0, 1]]}}}))
    return p


def _poses(tmp_path: Path) -> Path:
    p = tmp_path / "poses.csv"
    rows = ["frame,camera,image,m00,m01,m02,m03,m10,m11,m12,m13,m20,m21,m22,m23"]
    for i in range(3):
        T = np.array(_pose(float(i)))
        rows.append(f"{i},{CAM},{i:06d}.png," + ",".join(f"{v:g}" for v in T[:3].reshape(-1)))
    p.write_text("\n".join(rows) + "\n")
    return p


@pytest.fixture(scope="module")
def finished_run(tiny_seq, tmp_path_factory):
    import pavemap
    from pavemap.config import load_config

    out = tmp_path_factory.mktemp("bad") / "run"
    cfg = load_config("kitti", overrides=["device=cpu", "mesh.epochs=1", "output.figures=false",
                                          "output.report=false"])
    pavemap.run(tiny_seq.root, cfg, out, progress=False)
    return out


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EROFS], ids=["disk full", "read-only"])
def test_a_late_export_error_leaves_nothing_that_looks_complete(finished_run, tiny_seq, tmp_path, monkeypatch, code):
    out = tmp_path / "run"
    shutil.copytree(finished_run, out)
    (out / "notes.txt").write_text("mine")
    monkeypatch.setattr(os, "replace", _failing_replace(code, "defects.csv"))
    r = invoke("run", tiny_seq.root, "--out", out, "--device", "cpu", "--epochs", "1", "--set",
               "output.figures=false", "output.report=false")
    check(r, 2, "defects.csv", os.strerror(code).lower() if code == errno.EROFS else "no space left on device")
    assert not looks_complete(out), "a failed run left files that look complete"
    assert (out / "notes.txt").read_text() == "mine"
    assert (out / "mesh" / "mesh.npz").is_file() and (out / "detections.jsonl").is_file()  # kept to resume
    owner = json.loads((out / ".pavemap-owner.json").read_text())
    assert owner["status"] == "failed" and "notes.txt" not in owner["files"]


def test_a_run_folder_that_cannot_be_created(seq, tmp_path):
    target = Path("/proc/pavemap-run") if os.geteuid() == 0 else tmp_path / "ro" / "run"
    if os.geteuid() != 0:
        (tmp_path / "ro").mkdir()
        (tmp_path / "ro").chmod(0o500)
    check(invoke("run", seq, "--out", target, "--detector", "file"), 2, str(target))
