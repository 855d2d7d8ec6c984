"""The synthetic road world, its ray caster, the sequence writer and the simulated detector.

Public API::

    synthesize(out, preset="nuscenes-like", seed=0, frames=None, scale=None, depth="sparse", **overrides)
    make_world(preset, seed, **overrides) -> World ; render_view(world, camera, T_world_cam) -> RenderOutput
    detect_sequence(seq, seed=0, out=None, config=None) -> int ; SimDetectorConfig
    load_truth_defects(seq_root) -> list[TruthDefect] ; load_truth_height(seq_root) ; load_world(seq_root)
    contact_sheet(seq_root, out_png, n_frames=3)
    perturb_poses(seq, degrees, metres, seed) -> (seq copy, true poses) ; pose_errors(poses, truth)
"""

from pavemap.synth.contact import contact_sheet
from pavemap.synth.generate import (
    TruthDefect,
    load_truth_defects,
    load_truth_height,
    load_world,
    synthesize,
)
from pavemap.synth.params import CLASSES, WorldParams
from pavemap.synth.render import RenderOutput, render_view
from pavemap.synth.rig import perturb_poses, pose_errors
from pavemap.synth.scene import World
from pavemap.synth.simdetector import SimDetectorConfig, detect_sequence, read_detection_truth
from pavemap.synth.world import make_world

__all__ = [
    "CLASSES",
    "RenderOutput",
    "SimDetectorConfig",
    "TruthDefect",
    "World",
    "WorldParams",
    "contact_sheet",
    "detect_sequence",
    "load_truth_defects",
    "load_truth_height",
    "load_world",
    "make_world",
    "perturb_poses",
    "pose_errors",
    "read_detection_truth",
    "render_view",
    "synthesize",
]
