"""``pavemap fuse`` (stages 2-3 on a sequence) and ``pavemap eval`` (score a run against synthetic truth)."""

from __future__ import annotations

import enum
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from pavemap.commands import options as opt
from pavemap.errors import PavemapError

if TYPE_CHECKING:  # the stages load when the command runs, not with the CLI
    from pavemap.config import RunConfig
    from pavemap.fuse.core import FusionResult
    from pavemap.geometry import HeightField
    from pavemap.types import Sequence


class Surface(enum.StrEnum):
    """The surface ``pavemap fuse`` casts detections onto."""

    auto = "auto"
    mesh = "mesh"
    truth = "truth"
    plane = "plane"


def _surface(kind: str, seq, mesh_dir: Path | None):  # noqa: ANN001, ANN202
    """(surface HeightField, mesh or None) for --surface mesh|truth|plane."""
    mesh = None
    if kind == "auto":
        has_truth = seq.root is not None and (seq.root / "truth" / "height.npy").is_file()
        kind = "mesh" if mesh_dir is not None else ("truth" if has_truth else "plane")
    if mesh_dir is not None:
        from pavemap.mesh import load_mesh

        mesh = load_mesh(mesh_dir)
    if kind == "mesh":
        if mesh is None:
            raise PavemapError("--surface mesh needs --mesh DIR (a stage-1 output folder)")
        return mesh.surface, mesh
    if kind == "truth":
        from pavemap.io.truth import read_truth_height

        return read_truth_height(seq.root), mesh
    if kind == "plane":
        import numpy as np

        from pavemap.geometry import HeightField

        if mesh is not None:
            s = mesh.surface
            return HeightField.plane(s.x0, s.y0, s.res, s.nx, s.ny, 0.0), mesh
        # A flat road under the trajectory: cameras' mean height above the road is unknown, so the
        # plane is z = 0 (the world convention of our importers) over the trajectory's box + 20 m.
        c = seq.camera_centres()
        res = 0.1
        x0, y0 = np.floor(c[:, :2].min(0) - 20.0)
        x1, y1 = np.ceil(c[:, :2].max(0) + 20.0)
        return HeightField.plane(x0, y0, res, int((x1 - x0) / res) + 1, int((y1 - y0) / res) + 1), mesh
    raise PavemapError(f"unknown --surface {kind!r}; choose mesh, truth or plane")


def register(app: typer.Typer) -> None:
    @app.command()
    def fuse(
        seq: Path = typer.Argument(..., help="Sequence folder."),
        mesh: Path | None = typer.Option(None, "--mesh", help="Stage-1 mesh folder (surface and mesh road mask)."),
        detections: Path | None = typer.Option(
            None, "--detections", help="detections.jsonl or a folder of YOLO txt files (default SEQ/detections.jsonl)."
        ),
        out: Path = typer.Option(..., "--out", "-o", help="Output folder."),
        surface: Surface = typer.Option(
            Surface.auto, help="mesh (needs --mesh), truth (synthetic), plane (z = 0); auto: mesh with --mesh, "
            "else truth where the sequence has it, else plane."
        ),
        config: str | None = opt.CONFIG,
        sets: list[str] | None = opt.SET,
        truth: bool = typer.Option(True, help="Also write eval.json when the sequence has truth."),
        crs: str | None = opt.CRS,
        overwrite: bool = typer.Option(False, help="Replace a folder holding pavemap output of another sequence "
                                       "(deletes only the files pavemap wrote there)."),
    ) -> None:
        """Filter detections, cast them onto the road surface and fuse them into defect instances."""
        from pavemap.detect.sources import load_detections
        from pavemap.export.run_files import write_fusion_outputs
        from pavemap.io.owned import writing
        from pavemap.io.sequence import DETECTIONS_FILE, read_sequence
        from pavemap.pipeline import filter_and_fuse, skipped_text
        from pavemap.run_folder import legacy_run

        s = read_sequence(seq)
        rc = opt.resolve_config(s, config, sets, {"output.crs": crs})
        from pavemap.geo.crs import output_crs

        output_crs(s.geo_origin, rc.output.crs)  # a CRS the sequence cannot have fails before anything is written
        cfg = rc.fusion
        det_path = detections if detections is not None else seq / DETECTIONS_FILE
        if not det_path.exists():
            raise PavemapError(f"{det_path}: no detections (run `pavemap detect {seq}` or give --detections)")
        dets = load_detections(det_path, s)
        from pavemap.detect.backends import resolved_filter
        from pavemap.detect.sources import detections_model

        rc.filter, said = resolved_filter(rc.filter, rc.preset, detections_model(det_path))  # the boxes' model's
        typer.echo(said, err=True)
        source = str(seq.resolve())
        with writing(out, "fuse", overwrite, inputs=(seq, mesh, detections), info={"source": source},
                     same=lambda o: o.get("source") == source, legacy=legacy_run, early=False) as folder:
            folder.remove_own("metrics.json")  # an earlier result's completion marker, until this one is done
            surf, m = _surface(surface.value, s, mesh)
            result = filter_and_fuse(s, dets, surf, rc.filter, cfg, mesh=m)
            _assess(result, s, seq, surf, m if surface.value in ("mesh", "auto") else None, rc)
            ev = None
            if truth and (seq / "truth" / "defects.geojson").is_file():
                from pavemap.evaluate import evaluate

                ev = evaluate(result, seq)
            write_fusion_outputs(out, result, s.geo_origin, evaluation=ev, seq=s, surface=surf, output=rc.output)
        skipped = skipped_text(result.metrics)
        if skipped:
            typer.echo(skipped)
        typer.echo(_fuse_line(result.metrics, len(result.instances), out))
        if ev is not None:
            typer.echo(_eval_line(ev))

    @app.command(name="eval")
    def eval_(
        run: Path = typer.Argument(..., help="Run folder written by `pavemap fuse` or `pavemap run`."),
        truth: Path = typer.Option(..., "--truth", help="Synthetic sequence folder holding truth/."),
    ) -> None:
        """Score a run's defects against ground truth -> RUN/eval.json."""
        from pavemap.evaluate import evaluate
        from pavemap.export.run_files import write_eval

        ev = evaluate(run, truth)
        write_eval(run, ev)
        typer.echo(_eval_line(ev))
        typer.echo(f"-> {run / 'eval.json'}")


def _assess(result: FusionResult, s: Sequence, seq: Path, surf: HeightField, mesh: object | None,
            rc: RunConfig) -> None:
    """The maintenance assessment of a fused ``result`` (segments and the metrics' ``maintenance``), with the
    same defect schema as `pavemap run` (issue 16). ``mesh``: the stage-1 mesh when it is the surface (its
    observed cells and samples), else None."""
    from pavemap.maintain import assess, load_policy, summary
    from pavemap.maintain.assessment import survey_inputs

    mc = rc.maintenance
    # a detections file: the image's own pixels; sim where the sequence is synthetic (like detector auto)
    kind = "sim" if (seq / "truth" / "defects.geojson").is_file() else "file"
    seen = survey_inputs(s, kind, result.metrics, load_policy(mc.policy), tau_conf=rc.filter.tau_conf)
    result.segments = assess(result.instances, s, surf, result.instance_labels, getattr(mesh, "observed", None),
                             policy=mc.policy, segment_m=mc.segment_m, lane_width_m=mc.lane_width_m,
                             samples=getattr(mesh, "samples", None), floor_sweep=mc.floor_sweep, **seen)
    result.metrics["maintenance"] = summary(result.instances, result.segments, seen["check"])


def _fuse_line(mt: dict, defects: int, out: Path) -> str:
    """The one-line summary of a fusion's metrics ``mt``."""
    return (f"{mt['input_detections']} detections: {mt['invalid_detections']} invalid, {mt['below_conf']} below "
            f"conf, {mt['filtered_detections']} off road (FR {mt['filter_rate']:.1%}), {mt['valid_detections']} "
            f"valid, MSR {mt['msr']:.1%} -> {defects} defects in {out}")


def _eval_line(ev: dict) -> str:
    def f(v: object, fmt: str = ".2f") -> str:
        return "n/a" if v is None else format(v, fmt)

    b = ev["baseline"]
    return (f"F1 {f(ev['f1'])} (P {f(ev['precision'])}, R {f(ev['recall'])}), median error "
            f"{f(ev['median_error_m'], '.3f')} m, p90 {f(ev['p90_error_m'], '.3f')} m, off-road FP removed "
            f"{f(ev['fp_removed'], '.1%')}, true lost {f(ev['tp_lost'], '.1%')}; single-frame baseline F1 "
            f"{f(b['f1'])} (P {f(b['precision'])}, R {f(b['recall'])})")
