# Two commands on a fresh clone:  `make demo`  and  `make test`.
# Both create .venv when missing and install torch (CPU build, pinned) before the package.
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.pavemap-installed
EXTRAS ?= yolo,nuscenes,sfm,dev

.PHONY: demo test install lint bench clean docs

install: $(STAMP)

$(STAMP): pyproject.toml constraints.txt Makefile scripts/setup_system.sh
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	# constraints keep ultralytics' torchvision from pulling a multi-GB CUDA torch
	$(PY) -m pip install -q -c constraints.txt -e '.[$(EXTRAS)]'
	bash scripts/setup_system.sh
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/pavemap demo

test: $(STAMP)
	$(PY) -m pytest -q tests

# regenerate the reference and benchmark pages, then build the site strictly into site/ (git-ignored)
docs: $(STAMP)
	$(PY) scripts/gen_docs.py
	$(VENV)/bin/mkdocs build --strict

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests bench

bench: $(STAMP)
	$(PY) bench/synth_bench.py
	$(PY) bench/mesh_bench.py
	$(PY) bench/pose_bench.py
	$(PY) bench/pose_bench.py --presets nuscenes-like --per frame --skip-true
	$(PY) bench/fusion_bench.py
	$(PY) bench/run_bench.py

clean:
	rm -rf $(VENV) build *.egg-info
