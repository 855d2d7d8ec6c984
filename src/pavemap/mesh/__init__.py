"""Stage 1: the differentiable BEV road mesh (SPEC §1).

Public API: MeshConfig, RoadMesh, reconstruct(seq, out_dir, config) -> (mesh, metrics),
load_mesh(out_dir), render_view(mesh, camera, T_world_cam, scale).

Layout: config (MeshConfig), setup (sequence -> pixel pools, grid), init_surface (the starting heights),
model (grid, height MLP, RoadMesh), step (losses and one optimiser update), pose (pose alignment and
corrections), bake (closed-form colours), evaluate (PSNR, height error, metrics), checkpoint, outputs
(files), train (one piece: ``reconstruct_piece``), segments (the entry ``reconstruct``: a long drive in segment
tiles, the rest in one piece).
"""

from pavemap.mesh.config import MeshConfig
from pavemap.mesh.model import MeshGrid, RoadMesh, RoadMeshModel, build_grid
from pavemap.mesh.outputs import bev_rasters, load_mesh, write_outputs
from pavemap.mesh.render import render_view
from pavemap.mesh.segments import reconstruct
from pavemap.palette import class_colour

__all__ = [
    "MeshConfig", "MeshGrid", "RoadMesh", "RoadMeshModel", "bev_rasters", "build_grid", "class_colour",
    "load_mesh", "reconstruct", "render_view", "write_outputs",
]
