#!/usr/bin/env bash
# Device side of the detector training (the `device` tool runs it in the checkout's root; $OUT comes back).
#   bash scripts/detector_gpu/train.sh stage        call 1: unpack .devdata/cn (China copy) to /tmp/pm
#   bash scripts/detector_gpu/train.sh train HOURS  call 2: .devdata/cz (Czech copy + COCO start), train both runs
# Two calls because one call carries at most 64 MiB; the machine keeps /tmp between calls while it is warm.
set -euo pipefail
mode=${1:?stage or train}
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
export PYTHONPATH=/tmp/site:$PWD/src PYTHONUNBUFFERED=1
if ! python3 -c "import polars" 2>/dev/null; then
  # ultralytics reads its results.csv back with polars (54 MB wheel, over the carry limit): pandas does that here
  mkdir -p /tmp/site/polars
  cat > /tmp/site/polars/__init__.py <<'PY'
import io

import pandas as pd


class DataFrame:
    def __init__(self, data=None, **_):
        self._df = data if isinstance(data, pd.DataFrame) else pd.DataFrame(data)

    def to_dict(self, as_series=True):
        return {k: list(v) for k, v in self._df.to_dict(orient="list").items()}

    def write_csv(self, *_, **__):
        return self._df.to_csv(index=False)


def read_csv(src, **_):
    return DataFrame(pd.read_csv(io.BytesIO(src) if isinstance(src, (bytes, bytearray)) else src))
PY
fi
mkdir -p /tmp/pm
case $mode in
  stage)
    cp -r .devdata/cn /tmp/pm/
    du -sh /tmp/pm/cn; nproc; free -g | head -2; nvidia-smi -L
    python3 -c "import torch, ultralytics, polars; print(torch.__version__, ultralytics.__version__, torch.cuda.is_available())"
    ;;
  train)
    hours=${2:?hours}
    cp -r .devdata/cz /tmp/pm/
    ls /tmp/pm
    python3 scripts/detector_gpu/train.py --data /tmp/pm --work /tmp/pm-work --out "$OUT" \
      --coco-start /tmp/pm/cz/coco_start.pt --runs coco,shipped --hours "$hours" --workers 7 --batch 32 --device cuda
    nvidia-smi --query-gpu=name,memory.used --format=csv
    ;;
esac
