"""CUDA check of the whole pipeline (run on a GPU machine): demo-size scene, device cuda.

Prints one JSON line and writes it to $OUT/cuda_pipeline.json when OUT is set.
"""

import json
import os
import time

import torch

import pavemap
from pavemap.synth import detect_sequence, synthesize

out = os.environ.get("OUT")
t = time.time()
seq = synthesize("/tmp/scene", preset="nuscenes-like", seed=0, frames=16, scale=0.25, progress=False)
detect_sequence(seq, seed=0)
synth_s = time.time() - t
cfg = pavemap.load_config("nuscenes")
cfg.device = "cuda"
cfg.mesh.epochs = 4
t = time.time()
res = pavemap.run("/tmp/scene", cfg, "/tmp/run", progress=False)
rec = {"device": torch.cuda.get_device_name(0), "synth_s": synth_s, "run_s": time.time() - t,
                  "summary": res.summary(), "seconds": res.metrics["seconds"],
                  "mesh": {k: res.metrics["mesh"].get(k) for k in ("psnr", "sem_acc", "height_rmse", "device")}}
print(json.dumps(rec))
if out:
    with open(os.path.join(out, "cuda_pipeline.json"), "w") as f:
        json.dump(rec, f, indent=2)
