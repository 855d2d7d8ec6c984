"""Many drives on dask and the network defect register (issue 18).

Three small overlapping synthetic drives of one world: two vehicles on the same day (the right and the
left lane) and a later survey of the first vehicle's path in which some defects grew (area x9) and new
ones appeared. Run once one by one in this process and once on a LocalCluster of 2 worker processes,
with the worker of one drive killed in the middle of its task (after the mesh stage).

How register defects are matched to the truth: every observation (a defect of one drive's run) is
matched to the truth polygons by the evaluation's rule (:func:`pavemap.evaluate.gt.match`: one-to-one,
centroids within 0.5 m or overlapping polygons), in the world frame all three drives share. A truth
defect is *detected* when some observation matched it; the register defect it belongs to is the
``defect_id`` of those observations.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from pyproj import CRS

from pavemap.errors import PavemapError
from pavemap.export.gis import read_defect_layer
from pavemap.network.batch import run_batch, run_drive
from pavemap.network.folder import read_network
from pavemap.network.manifest import load_manifest
from pavemap.network.register import build_register, read_register
from pavemap.network.workers import forkserver_available
from qgis_support import REGISTER, check_styles

# A light mesh is enough: with footprint association the defect areas follow the boxes, whose size follows
# the defect; half-resolution images keep that measurement within ~1.2x between drives (quarter: ~2.5x).
OVERRIDES = ["device=cpu", "mesh.epochs=1", "mesh.threads=1", "mesh.render_scale=0.1", "mesh.pixels_per_step=16384",
             "output.figures=false", "output.report=false", "output.overlay_frames=0", "fusion.association=footprint"]
WORLD = dict(preset="kitti-like", seed=5, frames=24, hz=4.0, scale=0.5, road_after=30.0, defect_density=30.0,
             survey_growth=3.0, progress=False)
DRIVES = [("jan-van1", "2026-01-05", "van 1", {}), ("jan-van2", "2026-01-05", "van 2", {"ego_lane": 1}),
          ("jul-van1", "2026-07-05", "van 1", {"survey": 1})]
JAN, JUL = "2026-01-05", "2026-07-05"


def _manifest(path: Path, drives: list[dict], overrides: list[str] = OVERRIDES) -> Path:
    path.write_text(yaml.safe_dump({"config": "kitti", "set": overrides, "drives": drives}, sort_keys=False))
    return path


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    from pavemap.synth import synthesize

    root = tmp_path_factory.mktemp("network")
    for name, _, _, extra in DRIVES:
        synthesize(root / "seqs" / name, **WORLD, **extra)
    m = _manifest(root / "manifest.yaml", [{"path": f"seqs/{n}", "date": d, "name": n, "vehicle": v}
                                           for n, d, v, _ in DRIVES])
    return root, m


@pytest.fixture(scope="module")
def serial(world):
    root, m = world
    lines: list[str] = []
    s = run_batch(m, root / "net_serial", scheduler="serial", echo=lines.append)
    return root / "net_serial", s, lines


@pytest.fixture(scope="module")
def on_dask(world):
    root, m = world
    marker = root / "killed.txt"

    def killing_task(task: dict) -> dict:  # a closure: shipped to the workers by value
        if task["name"] == "jan-van2" and not marker.exists():
            import pavemap.pipeline as pipeline

            def die(*a, **k):  # the mesh is done and stamped, detection not: the worker dies mid-task
                marker.write_text(str(os.getpid()))
                os._exit(1)

            pipeline._detect_stage = die
        return run_drive(task)

    lines: list[str] = []
    s = run_batch(m, root / "net_dask", workers=2, retries=2, task_fn=killing_task, echo=lines.append)
    return root / "net_dask", s, lines, marker


def _records(run: Path) -> tuple[list, list]:
    layer = read_defect_layer(run / "survey.gpkg")
    return [g.wkb for g in layer.geometries], layer.properties


def _no_seconds(o: object) -> object:
    if isinstance(o, dict):
        return {k: _no_seconds(v) for k, v in o.items() if "second" not in k}
    return [_no_seconds(v) for v in o] if isinstance(o, list) else o


def test_dask_with_a_killed_worker_gives_the_serial_result(serial, on_dask):
    net_s, s_serial, _ = serial
    net_d, s_dask, lines, marker = on_dask
    assert s_serial["failed"] == [] and s_dask["failed"] == [], (s_serial, s_dask)
    assert marker.is_file(), "the worker was never killed"
    entry = next(e for e in s_dask["drives"] if e["name"] == "jan-van2")
    assert entry["status"] == "done" and not entry["worker"].endswith(f":{marker.read_text()}")  # a fresh worker
    assert s_dask["workers"] == 2 and any(x.startswith("dashboard: ") for x in lines)
    assert s_dask["worker_start"] == ("forkserver" if forkserver_available() else "spawn")
    for name, *_ in DRIVES:
        a, b = net_s / "drives" / name, net_d / "drives" / name
        assert _records(a) == _records(b), name
        ma, mb = (json.loads((r / "metrics.json").read_text()) for r in (a, b))
        assert _no_seconds(ma) == _no_seconds(mb), name
    for layer in ("observations", "defects"):
        assert read_register(net_s, layer) == read_register(net_d, layer)


def _truth_links(net: Path, root: Path) -> tuple[dict, dict, dict]:
    """(truth id -> register defect ids, register defect id -> truth ids, truth id -> dates it was detected)."""
    from pavemap.evaluate.gt import match
    from pavemap.synth import load_truth_defects

    truth = load_truth_defects(root / "seqs" / "jul-van1")  # the later survey holds every defect
    polys = [t.polygon for t in truth]
    txy = np.array([[p.centroid.x, p.centroid.y] for p in polys])
    obs_truth = {}
    for name, *_ in DRIVES:
        layer = read_defect_layer(net / "drives" / name / "survey.gpkg")
        xy = np.array([[g.centroid.x, g.centroid.y] for g in layer.geometries]).reshape(-1, 2)
        for i, j, _ in match(layer.geometries, xy, polys, txy, 0.5):
            obs_truth[(name, layer.properties[i]["id"])] = truth[j]
    t2d: dict = {}
    d2t: dict = {}
    seen: dict = {}
    for o in read_register(net, "observations"):
        t = obs_truth.get((o["drive"], o["instance_id"]))
        d2t.setdefault(o["defect_id"], set())
        if t is not None:
            d2t[o["defect_id"]].add(t.id)
            t2d.setdefault(t.id, set()).add(o["defect_id"])
            seen.setdefault(t.id, set()).add(o["date"])
    return t2d, d2t, seen | {"_truth": {t.id: t for t in truth}}


def test_register_has_one_record_per_detected_true_defect(serial, world):
    net, s, _ = serial
    t2d, d2t, _ = _truth_links(net, world[0])
    assert len(t2d) >= 10, f"too few defects detected for a meaningful test: {len(t2d)}"
    split = {t: d for t, d in t2d.items() if len(d) > 1}
    merged = {d: t for d, t in d2t.items() if len(t) > 1}
    assert not split, f"true defects split over several register records: {split}"
    assert not merged, f"register records holding several true defects: {merged}"
    false = [d for d, t in d2t.items() if not t]
    assert s["register"]["defects"] == len(t2d) + len(false)
    assert len(false) <= 3, f"register records without a true defect: {false}"


def test_register_flags_new_and_grown_as_in_the_truth(serial, world):
    net, _, _ = serial
    t2d, _, seen = _truth_links(net, world[0])
    truth = seen.pop("_truth")
    rows = {r["id"]: r for r in read_register(net)}
    checked = {"new": 0, "grown": 0, "unchanged": 0}
    for tid, (did,) in ((t, tuple(d)) for t, d in t2d.items()):
        r, p = rows[did], truth[tid].properties
        if JUL not in seen[tid]:  # the later drive missed it: the register cannot know it is still there
            assert r["status"] == "not seen again", (tid, r)
            continue
        if p.get("new_in_survey") or JAN not in seen[tid]:  # new, or no January drive detected it
            want = "new"
        else:
            want = "grown" if p.get("grown_in_survey") else "unchanged"
        assert r["status"] == want, (tid, p, r)
        checked[want] += 1
        assert r["first_seen"] == min(seen[tid]) and r["last_seen"] == max(seen[tid])
    assert min(checked.values()) >= 2, checked  # each flag was exercised
    page = (net / "network.html").read_text()
    assert "jan-van2" in page and "<svg" in page and page.count("<tr>") >= len(rows) + len(DRIVES)


def test_register_and_drive_layers_carry_the_defect_schema(serial):
    """Every drive's defect layers hold exactly the defect schema; the register's observations hold all of it
    (the drive's number of the defect as ``instance_id``), all in the drives' UTM zone."""
    import pyogrio

    from pavemap.export.geojson import PROPERTY_SCHEMA

    net, _, _ = serial
    schema = [n for n, *_ in PROPERTY_SCHEMA]
    for name, *_ in DRIVES:
        assert list(pyogrio.read_info(net / "drives" / name / "survey.gpkg", layer="defects")["fields"]) == schema
    fields = list(pyogrio.read_info(net / "register.gpkg", layer="observations")["fields"])
    assert [f for f in fields if f in schema] == schema[1:] and {"instance_id", "drive", "date"} <= set(fields)
    check_styles(net / "register.gpkg", REGISTER)  # QGIS styles: defects by status, observations by urgency
    for layer in [n for n, k in pyogrio.list_layers(net / "register.gpkg") if k is not None]:
        epsg = CRS.from_user_input(pyogrio.read_info(net / "register.gpkg", layer=layer)["crs"]).to_epsg()
        assert epsg is not None and epsg // 100 in (326, 327), (layer, epsg)  # WGS 84 / UTM north or south


def test_rerun_redoes_no_finished_drive(serial, world):
    root, m = world

    def must_not_run(task: dict) -> dict:
        raise AssertionError(f"{task['name']} was redone")

    s = run_batch(m, serial[0], scheduler="serial", task_fn=must_not_run, echo=lambda _: None)
    assert s["failed"] == [] and all(e.get("reused") for e in s["drives"])


# A drive long enough for two segments (issue 17): on the cluster its segments are tasks of their own.
LONG_OVERRIDES = [*OVERRIDES[:-1], "mesh.resolution=0.2", "mesh.segment_m=22", "mesh.segment_overlap_m=5"]


@pytest.fixture(scope="module")
def long_drive(tmp_path_factory):
    from pavemap.synth import synthesize

    root = tmp_path_factory.mktemp("long")
    synthesize(root / "seqs" / "long", preset="kitti-like", seed=5, frames=20, hz=4.0, scale=0.3, depth="sparse",
               progress=False)
    return root, _manifest(root / "m.yaml", [{"path": "seqs/long", "date": JAN}], LONG_OVERRIDES)


def test_segments_of_a_long_drive_are_tasks_and_a_killed_one_is_retried(long_drive):
    root, m = long_drive
    marker = root / "killed.txt"

    def killing_drive(task: dict) -> dict:  # on the drive's worker the first segment it runs kills it
        import pavemap.mesh.tiles as tiles

        real = tiles.run_tile

        def run_tile(job):  # noqa: ANN001, ANN202
            if not marker.exists():
                marker.write_text(str(os.getpid()))
                os._exit(1)
            return real(job)

        tiles.run_tile = run_tile
        return run_drive(task)

    s_serial = run_batch(m, root / "net_serial", scheduler="serial", echo=lambda _: None)
    lines: list[str] = []
    s_dask = run_batch(m, root / "net_dask", workers=2, retries=2, task_fn=killing_drive, echo=lines.append)
    assert s_serial["failed"] == [] and s_dask["failed"] == [], (s_serial, s_dask)
    assert marker.is_file(), "no worker was killed"
    (entry,) = s_dask["drives"]
    rows = entry["segment_tasks"]
    assert rows and {r["segment"] for r in rows} <= {0, 1}  # a tile finished before the kill is not redone
    assert not any(r["worker"].endswith(f":{marker.read_text()}") for r in rows)
    assert "segment_tasks" not in s_serial["drives"][0]  # one by one, the drive computes its own tiles
    a, b = root / "net_serial" / "drives" / "long", root / "net_dask" / "drives" / "long"
    ma, mb = (json.loads((r / "mesh" / "metrics.json").read_text()) for r in (a, b))
    assert ma["segmented"] and len(ma["segments"]) == 2
    assert _no_seconds({**ma, "segments": [{**r, "reused": None} for r in ma["segments"]]}) == \
        _no_seconds({**mb, "segments": [{**r, "reused": None} for r in mb["segments"]]})
    za, zb = (np.load(r / "mesh" / "mesh.npz") for r in (a, b))
    assert za.files == zb.files and all(np.array_equal(za[k], zb[k]) for k in za.files)
    assert _records(a) == _records(b)


@pytest.mark.parametrize("entry, message", [
    ({"path": "seqs/jan-van1"}, "drives[0]: 'date' is missing"),
    ({"path": "seqs/jan-van1", "date": "2026-13-01"}, "not an ISO date"),
    ({"path": "seqs/nowhere", "date": "2026-01-05"}, "does not exist"),
    ({"path": "seqs/jan-van1", "date": "2026-01-05", "name": "a b"}, "name 'a b'"),
    ({"path": "seqs/jan-van1", "date": "2026-01-05", "speed": 3}, "unknown key(s) ['speed']"),
])
def test_bad_manifest_entry_is_one_clear_error(world, entry, message):
    root, _ = world
    m = _manifest(root / "bad.yaml", [entry])
    with pytest.raises(PavemapError) as e:
        load_manifest(m)
    assert str(m) in str(e.value) and message in str(e.value), str(e.value)


def test_duplicate_names_are_refused(world):
    root, _ = world
    d = {"path": "seqs/jan-van1", "date": "2026-01-05", "name": "x"}
    with pytest.raises(PavemapError, match=r"drives\[1\] \(x\): the name is used by drives\[0\]"):
        load_manifest(_manifest(root / "dup.yaml", [d, d]))


@pytest.mark.filterwarnings("ignore:Measured \\(M\\) geometry types")
def test_drive_without_geo_origin_is_processed_but_refused_for_the_register(tiny_seq, tmp_path):
    from typer.testing import CliRunner

    from pavemap.cli import app

    plain = tmp_path / "no_origin"
    shutil.copytree(tiny_seq.root, plain)
    doc = json.loads((plain / "sequence.json").read_text())
    doc.pop("geo_origin", None)
    (plain / "sequence.json").write_text(json.dumps(doc))
    broken = tmp_path / "broken"
    shutil.copytree(tiny_seq.root, broken)
    next((broken / "images").rglob("*.png")).unlink()  # the run of this drive fails
    m = _manifest(tmp_path / "m.yaml", [{"path": "no_origin", "date": "2026-02-01"},
                                        {"path": "broken", "date": "2026-02-01"}], OVERRIDES[:-1])
    lines: list[str] = []
    s = run_batch(m, tmp_path / "net", scheduler="serial", echo=lines.append)
    status = {e["name"]: e["status"] for e in read_network(tmp_path / "net")["drives"]}
    assert status == {"no_origin": "done", "broken": "failed"} and s["failed"] == ["broken"]
    assert any("broken: FAILED" in x for x in lines)
    assert "no geo origin" in s["register"]["error"] and not (tmp_path / "net" / "register.gpkg").exists()
    with pytest.raises(PavemapError, match="no_origin have no geo origin"):
        build_register(tmp_path / "net")
    r = CliRunner().invoke(app, ["register", str(tmp_path / "net")])
    assert r.exit_code == 2 and "no geo origin" in r.output and "Traceback" not in r.output
    # the drive's run (`pavemap run` on a task): no layer anywhere in the network folder reads as EPSG:4326
    from test_gis_outputs import assert_no_wgs84_layer

    assert {"survey.gpkg", "defect_map.tif"} <= set(assert_no_wgs84_layer(tmp_path / "net"))


@pytest.mark.skipif(not forkserver_available(), reason="no forkserver on this platform")
def test_forkserver_workers_start_with_a_drives_imports_done_and_spawned_ones_without(monkeypatch):
    """Forked workers have what a drive imports before any task, and pavemap's variables set after the server
    started (it may be running since an earlier test) reach them as they do spawned ones."""
    from pavemap.network.batch import cluster
    from pavemap.network.workers import start_worker_forkserver

    def _loaded() -> tuple[list[str], str | None]:  # nested: shipped by value, unpickling imports no test module
        import os
        import sys

        mods = sorted(m for m in ("torch", "cv2", "pavemap.pipeline", "pavemap.mesh.train") if m in sys.modules)
        return mods, os.environ.get("PAVEMAP_TEST_FORWARDED")

    start_worker_forkserver()
    monkeypatch.setenv("PAVEMAP_TEST_FORWARDED", "yes")
    got = {}
    for start in ("forkserver", "spawn"):
        with cluster(None, 1, "2GB", 0, lambda _: None, worker_start=start) as client:
            got[start] = list(client.run(_loaded).values())  # type: ignore[attr-defined]
    assert got == {"forkserver": [(["cv2", "pavemap.mesh.train", "pavemap.pipeline", "torch"], "yes")],
                   "spawn": [([], "yes")]}


def test_unknown_worker_start_is_one_clear_error(world):
    with pytest.raises(PavemapError, match="--worker-start must be one of forkserver, spawn"):
        run_batch(world[1], world[0] / "net_bad_start", worker_start="thread", echo=lambda _: None)


@pytest.mark.parametrize("command", ["batch", "register"])
def test_help_renders(command):
    from typer.testing import CliRunner

    from pavemap.cli import app

    r = CliRunner().invoke(app, [command, "--help"])
    assert r.exit_code == 0 and "Usage" in r.output, r.output


def test_the_forkservers_preload_skips_a_module_that_fails_in_any_way(tmp_path, monkeypatch):
    """multiprocessing's own preload stops every worker start on anything but an ImportError: the one module
    it preloads imports the list itself and goes on past a module that raises."""
    import gc
    import importlib
    import sys

    import pavemap.network.workers as workers

    (tmp_path / "pavemap_test_broken.py").write_text("raise RuntimeError('broken at import')\n")
    (tmp_path / "pavemap_test_fine.py").write_text("LOADED = True\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(workers, "WORKER_IMPORTS", ("pavemap_test_broken", "pavemap_test_fine"))
    monkeypatch.delitem(sys.modules, "pavemap.network.forkserver_ready", raising=False)
    try:
        importlib.import_module("pavemap.network.forkserver_ready")
    finally:
        gc.unfreeze()  # the module freezes the heap, as the server should; this process is not the server
        sys.modules.pop("pavemap.network.forkserver_ready", None)
    assert sys.modules.pop("pavemap_test_fine").LOADED and "pavemap_test_broken" not in sys.modules
