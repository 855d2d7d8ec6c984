"""Bad input and faults through the command line: every case ends in one clear line (or ``info``'s list
of problems) naming the file or field, the right exit status, no traceback, and nothing left behind
that looks complete.

Exit status: 2 for an error (``error: ...``), 1 for ``pavemap info`` finding an invalid sequence.
"""

from __future__ import annotations

import copy
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from fuzz_support import CAM, H, W, check, invoke, make_seq
from fuzz_support import pose as _pose


@pytest.fixture
def seq(tmp_path) -> Path:
    return make_seq(tmp_path / "seq")


def _edit(seq: Path, change) -> None:  # noqa: ANN001
    d = json.loads((seq / "sequence.json").read_text())
    change(d)
    (seq / "sequence.json").write_text(json.dumps(d))


def _view(d: dict, i: int = 1) -> dict:
    return d["frames"][i]["views"][CAM]


def _set(path: str, value: object):  # noqa: ANN202
    """A change setting ``d[a][b]…`` (dotted, numbers index lists) to ``value``."""
    keys = [int(k) if k.lstrip("-").isdigit() else k for k in path.split(".")]

    def change(d: dict) -> None:
        for k in keys[:-1]:
            d = d[k]
        d[keys[-1]] = copy.deepcopy(value)
    return change


def _scaled(d: dict) -> None:
    _view(d)["T_world_cam"][0][0] = 2.0


def _reflected(d: dict) -> None:
    for r in range(3):
        _view(d)["T_world_cam"][r][0] *= -1


def _dup_class(d: dict) -> None:
    d["classes"][1]["id"] = 0


def _decreasing(d: dict) -> None:
    d["frames"][1]["index"], d["frames"][2]["index"] = 5, 4


def _repeat(d: dict) -> None:
    d["frames"][1]["index"] = 0


def _unknown_camera(d: dict) -> None:
    d["frames"][0]["views"]["CAM_BACK"] = d["frames"][0]["views"][CAM]


def _drop(key: str):  # noqa: ANN202
    return lambda d: d.pop(key)


# (id, change of the parsed sequence.json, words the message must hold)
JSON_CASES = [
    ("K is a string", _set(f"cameras.{CAM}.K", "abc"), [f"cameras.{CAM}.K", "3x3"]),
    ("K 2x3", _set(f"cameras.{CAM}.K", [[30, 0, 16], [0, 30, 12]]), [f"cameras.{CAM}.K", "3x3"]),
    ("K not upper-triangular", _set(f"cameras.{CAM}.K", [[30, 0, 16], [1, 30, 12], [0, 0, 1]]), ["upper-triangular"]),
    ("K negative focal", _set(f"cameras.{CAM}.K", [[-30, 0, 16], [0, 30, 12], [0, 0, 1]]), ["positive"]),
    ("K entry a string", _set(f"cameras.{CAM}.K", [["30", 0, 16], [0, 30, 12], [0, 0, 1]]),
     [f"cameras.{CAM}.K[0][0]", "number"]),
    ("views a list", _set("frames.1.views", []), ["frames[1].views", "object"]),
    ("views empty", _set("frames.1.views", {}), ["frames[1].views"]),
    ("image a number", _set(f"frames.1.views.{CAM}.image", 5), [f"frames[1].views.{CAM}.image", "string"]),
    ("image empty", _set(f"frames.1.views.{CAM}.image", ""), ["image", "empty"]),
    ("image with NUL", _set(f"frames.1.views.{CAM}.image", "a\x00b.png"), ["image", "control character"]),
    ("image path 5000 chars", _set(f"frames.1.views.{CAM}.image", "a" * 5000), ["image", "at most 4096"]),
    ("T a string", _set(f"frames.1.views.{CAM}.T_world_cam", "eye"), [f"frames[1].views.{CAM}.T_world_cam"]),
    ("T 3x4", _set(f"frames.1.views.{CAM}.T_world_cam", _pose(1)[:3]), ["T_world_cam", "4x4"]),
    ("T scaled", _scaled, [f"frames[1].views.{CAM}.T_world_cam", "orthonormal"]),
    ("T reflection", _reflected, ["T_world_cam", "det"]),
    ("T huge", _set(f"frames.1.views.{CAM}.T_world_cam.0.3", 1e300), ["T_world_cam[0][3]", "must be in"]),
    ("semantics a number", _set(f"frames.1.views.{CAM}.semantics", 3), [f"frames[1].views.{CAM}.semantics"]),
    ("road flag a string", _set("classes.0.road", "false"), ["classes[0].road", "true or false"]),
    ("class id a string", _set("classes.0.id", "0"), ["classes[0].id", "integer"]),
    ("class id 300", _set("classes.0.id", 300), ["classes[0].id", "0..255"]),
    ("class id repeated", _dup_class, ["classes[1].id", "repeats"]),
    ("class name missing", _set("classes.0", {"id": 0}), ["classes[0].name", "missing"]),
    ("classes an object", _set("classes", {"road": 0}), ["classes", "list"]),
    ("frames missing", _drop("frames"), ["frames", "missing"]),
    ("frames empty", _set("frames", []), ["frames", "at least 1"]),
    ("index 1.5", _set("frames.1.index", 1.5), ["frames[1].index", "integer"]),
    ("index true", _set("frames.1.index", True), ["frames[1].index", "integer"]),
    ("index negative", _set("frames.0.index", -1), ["frames[0].index"]),
    ("index decreasing", _decreasing, ["frames[2].index", "decreases"]),
    ("index repeated", _repeat, ["frames[1].index", "repeats"]),
    ("timestamp a string", _set("frames.0.timestamp", "noon"), ["frames[0].timestamp", "number"]),
    ("timestamps out of order", _set("frames.2.timestamp", -5.0), ["frames[2].timestamp", "out of order in time"]),
    ("unknown camera", _unknown_camera, ["frames[0].views.CAM_BACK", "unknown camera"]),
    ("width a string", _set(f"cameras.{CAM}.width", "32"), [f"cameras.{CAM}.width", "integer"]),
    ("width 0", _set(f"cameras.{CAM}.width", 0), [f"cameras.{CAM}.width"]),
    ("camera name with /", _set("cameras", {"a/b": {"width": W, "height": H, "K": [[30, 0, 16], [0, 30, 12],
                                                                                      [0, 0, 1]]}}), ["cameras key"]),
    ("cameras empty", _set("cameras", {}), ["cameras"]),
    ("format wrong", _set("format", "pavemap-sequence/9"), ["format", "pavemap-sequence/1"]),
    ("name a number", _set("name", 7), ["name", "string"]),
    ("name 10k chars", _set("name", "n" * 10000), ["name", "at most 256"]),
    ("geo lat 200", _set("geo_origin.lat", 200), ["geo_origin.lat"]),
    ("geo lon a string", _set("geo_origin.lon", "11.5"), ["geo_origin.lon", "number"]),
]


@pytest.mark.parametrize(("change", "words"), [c[1:] for c in JSON_CASES], ids=[c[0] for c in JSON_CASES])
def test_sequence_json_cases(seq, tmp_path, change, words):
    _edit(seq, change)
    check(invoke("info", seq), 1, "sequence.json", *words)
    out = tmp_path / "run"
    check(invoke("run", seq, "--out", out, "--detector", "file"), 2, "sequence.json", *words)
    assert not out.exists()


def _raw(seq: Path, text_change) -> None:  # noqa: ANN001
    p = seq / "sequence.json"
    data = text_change(p.read_bytes())
    p.write_bytes(data)


RAW_CASES = [
    ("NaN timestamp", lambda b: b.replace(b'"timestamp": 0.5', b'"timestamp": NaN'), ["frames[1].timestamp", "NaN"]),
    ("Infinity in a pose", lambda b: b.replace(b", 1.5]", b", Infinity]", 1), ["frames[0].views", "Infinity"]),
    ("NaN heading", lambda b: b.replace(b'"heading_deg": 90.0', b'"heading_deg": NaN'), ["geo_origin.heading_deg"]),
    ("5000-digit index", lambda b: b.replace(b'"index": 2', b'"index": ' + b"9" * 5000), ["frames[2].index",
                                                                                        "5000 digits"]),
    ("nested 100000 deep", lambda b: b[:-1] + b', "x": ' + b"[" * 100000 + b"]" * 100000 + b"}", ["nested"]),
    ("latin-1 bytes", lambda b: b.replace(b"bad-input-test", "d\u00e9faut".encode("latin-1")), ["UTF-8"]),
    ("UTF-16", lambda b: b.decode().encode("utf-16"), ["UTF-8"]),
    ("truncated", lambda b: b[: len(b) // 2], ["invalid JSON"]),
    ("empty file", lambda b: b"", ["invalid JSON"]),
    ("random bytes", lambda b: bytes(np.random.default_rng(0).integers(0, 256, 300, dtype=np.uint8)), ["UTF-8"]),
    ("top level a list", lambda b: b"[1, 2, 3]", ["must be an object"]),
]


@pytest.mark.parametrize(("text_change", "words"), [c[1:] for c in RAW_CASES], ids=[c[0] for c in RAW_CASES])
def test_sequence_json_bytes(seq, text_change, words):
    _raw(seq, text_change)
    check(invoke("info", seq), 1, "sequence.json", *words)
    check(invoke("detect", seq, "--detector", "file"), 2, "sequence.json", *words)


def test_sequence_folder_missing_or_a_file(tmp_path):
    check(invoke("info", tmp_path / "nope"), 2, "nope", "not a folder")
    (tmp_path / "file").write_text("x")
    check(invoke("run", tmp_path / "file", "--out", tmp_path / "r"), 2, "file", "not a folder")
    (tmp_path / "empty").mkdir()
    check(invoke("info", tmp_path / "empty"), 2, "sequence.json", "not found")
    (tmp_path / "dir" / "sequence.json").mkdir(parents=True)
    check(invoke("info", tmp_path / "dir"), 2, "sequence.json")


# ---------------------------------------------------------------------------- layers


def _layer(kind: str, i: int = 1) -> str:
    return f"{kind}/{CAM}/{i:06d}.png"


def _truncate(seq: Path) -> None:
    p = seq / _layer("images")
    p.write_bytes(p.read_bytes()[:-40])


def _rgb_semantics(seq: Path) -> None:
    Image.fromarray(np.zeros((H, W, 3), np.uint8)).save(seq / _layer("semantics"))


def _depth_8bit(seq: Path) -> None:
    Image.fromarray(np.full((H, W), 6, np.uint8)).save(seq / _layer("depth"))


def _depth_metres(seq: Path) -> None:
    Image.fromarray(np.full((H, W), 6, np.uint16)).save(seq / _layer("depth"))


def _unknown_ids(seq: Path) -> None:
    Image.fromarray(np.full((H, W), 200, np.uint8)).save(seq / _layer("semantics"))


def _not_png(seq: Path) -> None:
    (seq / _layer("images")).write_text("not an image")


def _wrong_size(seq: Path) -> None:
    Image.fromarray(np.zeros((H, W + 1, 3), np.uint8)).save(seq / _layer("images"))


def _missing(seq: Path) -> None:
    (seq / _layer("images")).unlink()


def _ids_above_255(seq: Path) -> None:
    Image.fromarray(np.full((H, W), 300, np.uint16)).save(seq / _layer("semantics"))


# (id, change, words, caught when the reader opens the header too (so `run` stops before any stage))
LAYER_CASES = [
    ("truncated PNG", _truncate, ["images/CAM_FRONT/000001.png", "unreadable image"], False),
    ("semantics saved as RGB", _rgb_semantics, ["semantics/CAM_FRONT/000001.png", "single-channel"], True),
    ("8-bit depth", _depth_8bit, ["depth/CAM_FRONT/000001.png", "16-bit", "8-bit"], True),
    ("depth in metres", _depth_metres, ["depth/CAM_FRONT/000001.png", "millimetres"], False),
    ("semantic ids not in the class table", _unknown_ids, ["semantics/CAM_FRONT/000001.png", "class id"], False),
    ("semantic ids above 255", _ids_above_255, ["semantics/CAM_FRONT/000001.png", "above 255"], False),
    ("image not a PNG", _not_png, ["images/CAM_FRONT/000001.png", "unreadable"], True),
    ("image of the wrong size", _wrong_size, ["images/CAM_FRONT/000001.png", "33x24"], True),
    ("image missing", _missing, ["images/CAM_FRONT/000001.png", "missing"], True),
]


@pytest.mark.parametrize(("change", "words", "at_read"), [c[1:] for c in LAYER_CASES], ids=[c[0] for c in LAYER_CASES])
def test_layer_cases(seq, tmp_path, change, words, at_read):
    change(seq)
    check(invoke("info", seq), 1, "INVALID", *words)
    if at_read:
        out = tmp_path / "run"
        check(invoke("run", seq, "--out", out, "--detector", "file"), 2, *words)
        assert not out.exists()


def test_truncated_image_stops_the_run_before_stage_1_with_nothing_written(seq, tmp_path):
    p = seq / _layer("images", 0)
    p.write_bytes(p.read_bytes()[:-40])
    out = tmp_path / "run"
    # every image is decoded up front, as `pavemap info` does (issue 46): the run stops before any stage
    check(invoke("run", seq, "--out", out, "--detector", "file", "--device", "cpu", "--epochs", "1"), 2,
          "images/CAM_FRONT/000000.png", "unreadable image", "truncated", "--skip-bad-frames")
    assert not out.exists()


# ---------------------------------------------------------------------------- detections


def _det(**change: object) -> str:
    rec = {"frame": 0, "camera": CAM, "box": [4, 14, 12, 20], "cls": 0, "conf": 0.8}
    rec.update(change)
    return json.dumps({k: v for k, v in rec.items() if v is not _DROP})


_DROP = object()
DET_CASES = [
    ("not JSON", "{frame: 0}", ["line 2", "invalid JSON"]),
    ("box a string", _det(box="1234"), ["line 2", "box", "list"]),
    ("box of 3", _det(box=[1, 2, 3]), ["line 2", "box", "exactly 4"]),
    ("box entry a string", _det(box=[1, "2", 3, 4]), ["box[1]", "number"]),
    ("cls 99", _det(cls=99), ["line 2", "unknown class id 99"]),
    ("cls a string", _det(cls="1"), ["cls", "integer"]),
    ("cls true", _det(cls=True), ["cls", "integer"]),
    ("frame 1.5", _det(frame=1.5), ["frame", "integer"]),
    ("camera a number", _det(camera=3), ["camera", "string"]),
    ("conf missing", _det(conf=_DROP), ["conf", "missing"]),
    ("conf a string", _det(conf="high"), ["conf", "number"]),
    ("a list, not a record", "[0, 1, 2]", ["line 2", "must be an object"]),
    ("5000-digit frame", _det(frame=0).replace('"frame": 0', '"frame": ' + "1" * 5000), ["frame", "5000 digits"]),
    ("nested 50000 deep", _det()[:-1] + ', "extra": ' + "[" * 50000 + "]" * 50000 + "}", ["line 2", "nested"]),
]


@pytest.mark.parametrize(("line", "words"), [c[1:] for c in DET_CASES], ids=[c[0] for c in DET_CASES])
def test_detection_cases(seq, tmp_path, line, words):
    bad = tmp_path / "bad.jsonl"
    bad.write_text(_det() + "\n" + line + "\n")
    out = tmp_path / "d.jsonl"
    check(invoke("detect", seq, "--detections", bad, "--out", out), 2, "bad.jsonl", *words)
    assert not out.exists()
    run = tmp_path / "run"
    check(invoke("run", seq, "--out", run, "--detections", bad), 2, "bad.jsonl", *words)  # before any stage
    assert not run.exists()


def test_detections_not_utf8_and_yolo_txt_not_utf8(seq, tmp_path):
    bad = tmp_path / "bad.jsonl"
    bad.write_bytes(_det().encode() + b"\n" + _det().encode().replace(b'"CAM_FRONT"', b'"CAM_\xff"') + b"\n")
    check(invoke("detect", seq, "--detections", bad, "--out", tmp_path / "o.jsonl"), 2, "bad.jsonl", "UTF-8",
          "line 2")
    yolo = tmp_path / "labels" / CAM
    yolo.mkdir(parents=True)
    (yolo / "000000.txt").write_bytes(b"0 0.5 0.5 0.1 0.1 0.\xe9\n")
    check(invoke("detect", seq, "--detections", tmp_path / "labels", "--out", tmp_path / "o.jsonl"), 2,
          "000000.txt", "UTF-8")


def test_unusable_detections_are_counted_by_reason_on_the_console(seq, tmp_path):
    """Well-formed but unusable values (NaN confidence, a frame the sequence lacks, a box off the image)
    are skipped by the filter; the console says how many and why (not only run.log)."""
    dets = tmp_path / "d.jsonl"
    lines = [_det(), _det(frame=1, box=[10, 15, 20, 22]), _det(conf=float("nan")), _det(frame=7),
             _det(box=[100, 100, 120, 120]), _det(box=[9, 9, 2, 2])]
    dets.write_text("\n".join(lines) + "\n")
    r = invoke("fuse", seq, "--detections", dets, "--out", tmp_path / "fused", "--surface", "plane")
    check(r, 0, "skipped", "bad conf 1", "unknown frame 1", "outside image 1", "inverted box 1")


# ---------------------------------------------------------------------------- configuration

CONFIG_CASES = [
    ("tau_road 7", ["--set", "filter.tau_road=7"], ["filter.tau_road"]),
    ("overlay_frames -5", ["--set", "output.overlay_frames=-5"], ["output.overlay_frames"]),
    ("epochs -1", ["--set", "mesh.epochs=-1"], ["mesh.epochs"]),
    ("lr nan", ["--set", "mesh.lr_rgb=nan"], ["mesh.lr_rgb"]),
    ("alpha 0", ["--set", "fusion.alpha=0"], ["fusion.alpha"]),
    ("detector conf 1.5", ["--set", "detector.conf=1.5"], ["detector.conf"]),
    ("unknown key", ["--set", "fusion.tau_road=0.5"], ["did you mean", "filter.tau_road"]),
    ("epochs abc", ["--set", "mesh.epochs=abc"], ["mesh.epochs", "integer"]),
    ("device banana", ["--set", "device=banana"], ["device"]),
    ("mask wrong", ["--set", "filter.mask=sky"], ["filter.mask", "frame"]),
]


@pytest.mark.parametrize(("args", "words"), [c[1:] for c in CONFIG_CASES], ids=[c[0] for c in CONFIG_CASES])
def test_config_values_are_checked_before_any_stage(seq, tmp_path, args, words):
    out = tmp_path / "run"
    check(invoke("run", seq, "--out", out, "--detector", "file", *args), 2, *words)
    assert not out.exists()


YAML_CASES = [
    ("not UTF-8", b"mesh: {epochs: 3}\nname: \xff\xfe\n", ["cfg.yaml", "UTF-8"]),
    ("invalid YAML", b"mesh: {epochs: [3\n", ["cfg.yaml", "invalid YAML"]),
    ("a list", b"- 1\n- 2\n", ["cfg.yaml", "mapping"]),
    ("section a list", b"mesh: [1, 2]\n", ["cfg.yaml", "mesh"]),
    ("deep nesting", b"mesh: " + b"[" * 5000 + b"]" * 5000 + b"\n", ["cfg.yaml"]),
    ("epochs .inf", b"mesh: {epochs: .inf}\n", ["cfg.yaml", "mesh.epochs"]),
]


@pytest.mark.parametrize(("text", "words"), [c[1:] for c in YAML_CASES], ids=[c[0] for c in YAML_CASES])
def test_config_file_cases(seq, tmp_path, text, words):
    (tmp_path / "cfg.yaml").write_bytes(text)
    check(invoke("config", seq, "--config", tmp_path / "cfg.yaml"), 2, *words)


def test_a_gpu_that_torch_does_not_see_is_an_error(seq, tmp_path, monkeypatch):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # the same on a machine with a GPU
    check(invoke("run", seq, "--out", tmp_path / "r", "--detector", "file", "--device", "cuda"), 2, "cuda")
    check(invoke("synth", "--out", tmp_path / "s", "--frames", "2", "--device", "cuda"), 2, "cuda")
    assert not (tmp_path / "r").exists() and not (tmp_path / "s").exists()


# ---------------------------------------------------------------------------- no semantics


def test_a_sequence_without_semantics_runs_with_the_fallback_filter(tiny_seq, tmp_path):
    seq = tmp_path / "nosem"
    shutil.copytree(tiny_seq.root, seq)
    shutil.rmtree(seq / "semantics")

    def strip(d: dict) -> None:
        for f in d["frames"]:
            for v in f["views"].values():
                v["semantics"] = None
    _edit(seq, strip)
    r = invoke("info", seq)
    check(r, 0, "semantics: no", "no semantic maps")
    check(invoke("run", seq, "--out", tmp_path / "sim", "--detector", "sim"), 2, "semantic map")
    out = tmp_path / "run"
    r = invoke("run", seq, "--out", out, "--detector", "file", "--device", "cpu", "--epochs", "1",
               "--segmenter", "none", "--set", "output.figures=false", "output.report=false")
    check(r, 0, "warning: mesh: no semantic maps", "defects", "semantics: none (--segmenter none)")
    assert (out / "metrics.json").is_file()
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["mask_fallbacks"].get("no_semantics", 0) > 0


def test_load_rgb_names_the_file_and_prints_nothing_else(tmp_path, capfd):
    """The OpenCV decoder reads good images; a missing, foreign or truncated file is PIL's SequenceError naming
    it, with nothing of OpenCV's on the console."""
    from pavemap.errors import SequenceError
    from pavemap.io.sequence import load_rgb

    good = tmp_path / "good.png"
    Image.fromarray(np.arange(24 * 33 * 3, dtype=np.uint8).reshape(24, 33, 3)).save(good)
    assert np.array_equal(load_rgb(good), np.asarray(Image.open(good).convert("RGB")))
    (tmp_path / "text.png").write_text("not an image")
    (tmp_path / "cut.png").write_bytes(good.read_bytes()[:60])
    for name, why in (("missing.png", "No such file"), ("text.png", "cannot identify"), ("cut.png", "truncated")):
        with pytest.raises(SequenceError, match=why) as e:
            load_rgb(tmp_path / name)
        assert name in str(e.value)
    out, err = capfd.readouterr()
    assert "imread" not in out + err and "WARN" not in out + err
