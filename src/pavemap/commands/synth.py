"""``pavemap synth``: generate a synthetic drive with exact ground truth as a sequence folder."""

from __future__ import annotations

from pathlib import Path

import typer

from pavemap.commands.options import DEVICE_HELP


def register(app: typer.Typer) -> None:
    @app.command()
    def synth(
        out: Path = typer.Option(..., "--out", "-o", help="Sequence folder to create."),
        preset: str = typer.Option("nuscenes-like", help="World and rig: nuscenes-like (6 cameras, 2 Hz) or "
                                   "kitti-like (1 camera, 10 Hz)."),
        seed: int = typer.Option(0, help="Random seed: same seed, same files."),
        frames: int | None = typer.Option(None, help="Number of frames (default: 40 nuscenes-like, 80 kitti-like)."),
        scale: float | None = typer.Option(None, help="Image scale (default: 0.5 nuscenes-like, 1.0 kitti-like)."),
        depth: str = typer.Option("sparse", help="Depth maps: none, sparse (LiDAR-like) or dense."),
        defect_density: float | None = typer.Option(None, help="Defects per 100 m of road (default 25)."),
        defect_free_until: float | None = typer.Option(
            None, "--defect-free-until", help="No defect centred before this many metres along the drive from the "
            "first frame: a clean stretch, then the damaged rest (e.g. half the drive; default: defects everywhere)."),
        trajectory: Path | None = typer.Option(
            None, "--trajectory", help="Drive along this trajectory: a KITTI odometry pose file (12 numbers per "
            "line, e.g. kitti-odometry-poses/00.txt); FRAMES poses from --trajectory-start (default: all)."),
        trajectory_start: int = typer.Option(0, "--trajectory-start", help="First pose of --trajectory used."),
        shadows: bool = typer.Option(True, help="Cast shadows of objects on the ground."),
        overwrite: bool = typer.Option(False, help="Replace OUT if it exists."),
        device: str = typer.Option("cpu", help=f"Render device: {DEVICE_HELP}."),
        threads: int = typer.Option(1, help="torch CPU threads while rendering."),
    ) -> None:
        """Render a synthetic road world (images, semantics, depth, truth) into a sequence folder."""
        from pavemap.synth import synthesize

        path = None
        if trajectory is not None:
            from pavemap.synth.trajectory import read_trajectory

            path = read_trajectory(trajectory, frames, trajectory_start)
            frames = len(path)
            path = [[round(float(v), 4) for v in row] for row in path]
        seq = synthesize(out, preset=preset, seed=seed, frames=frames, scale=scale, depth=depth,
                         overwrite=overwrite, device=device, threads=threads, defect_density=defect_density,
                         defect_free_until_m=defect_free_until, shadows=shadows, path=path)
        views = sum(len(f.views) for f in seq.frames)
        typer.echo(f"{len(seq.frames)} frames, {views} views -> {out}")
