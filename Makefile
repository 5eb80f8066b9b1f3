# qpctl — two commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: all env demo test soak soak-brake robust bench bench-quick peers perception perception-canopies harvest simulators camera robots sweep-small sweep-1k sweep-throughput lint clean

all: test

# The environment is built from pyproject.toml only; it is rebuilt when pyproject.toml changes.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	$(PY) -m qpctl.native
	touch $(STAMP)

env: $(STAMP)

# The paper reproduction: tables and figures into results/paper and Markdown for docs/paper.md.
demo: $(STAMP)
	MPLBACKEND=Agg $(PY) -m reproduction --out results/paper

# Two workers (pytest-xdist), one per core of the 2-core machines this runs on: the suite took 11 min on
# one (the 2-core AMD EPYC, 2026-12-07), 6 min on two. numba compiles each kernel once per checkout and
# caches it; the workers share that cache.
test: $(STAMP)
	MPLBACKEND=Agg $(PY) -m pytest -q -x -n 2 -p no:cacheprovider

soak: $(STAMP)
	MPLBACKEND=Agg $(PY) -m pytest -q -m slow -p no:cacheprovider

# Stop before contact on a fresh seeded set of 200 scenes behind the verified backup, two processes
# (docs/reliability.md, "Stop before contact"): results/soak/summary_brake.json.
soak-brake: $(STAMP)
	MPLBACKEND=Agg $(PY) -m benchmarks.soak_brake --scenes 200 --jobs 2 --out results/soak

# Every fault kind at three levels, paper / hsu / qp on 22 seeded scenes (docs/reliability.md, "Faults and robustness").
robust: $(STAMP)
	MPLBACKEND=Agg $(PY) -m benchmarks.robustness --out results/robust

bench: $(STAMP)
	MPLBACKEND=Agg $(VENV)/bin/qpctl bench --out results/bench

bench-quick: $(STAMP)
	MPLBACKEND=Agg $(VENV)/bin/qpctl bench --quick --out results/bench-quick

# qpctl, Pink and mink on the Panda canopy in one process (docs/performance.md, "Peers"): installs the
# [peers] extra (pin-pink, mink: pure Python, beside the environment's pin and MuJoCo), runs the
# benchmark into results/peers/peers.md, then its test.
peers: $(STAMP)
	$(PY) -m pip install --quiet -e '.[peers]'
	mkdir -p results/peers
	MPLBACKEND=Agg $(PY) -m benchmarks.peers > results/peers/peers.md && cat results/peers/peers.md
	MPLBACKEND=Agg $(PY) -m pytest -q -m slow -p no:cacheprovider tests/test_peers.py

# The depth map (docs/perception.md): frame → field on recorded 640×480 frames, EDT backends, field queries,
# the tick beside the map worker; and the closed loop on panda_canopy_depth under 20 canopy seeds.
perception: $(STAMP)
	MPLBACKEND=Agg $(PY) -m benchmarks.perception --out results/perception

perception-canopies: $(STAMP)
	MPLBACKEND=Agg $(PY) -m benchmarks.perception --canopies 20 --duration 30 --jobs 2 --out results/perception-canopies

# The harvesting scenario under every law, approach and pose tasks: results/harvest/harvest.md (docs/harvesting.md).
harvest: $(STAMP)
	MPLBACKEND=Agg $(PY) -m benchmarks.harvest --out results/harvest

# Built-in / MuJoCo / PyBullet / Drake side by side: results/simulators/simulators.md (docs/simulators.md, "Other simulators").
simulators: $(STAMP)
	MPLBACKEND=Agg $(PY) -m benchmarks.simulators --out results/simulators

# example-robot-data's arms with fitted capsules, their SRDF and a QP reach: results/robots/robots.md (docs/robots.md).
robots: $(STAMP)
	MPLBACKEND=Agg $(PY) -m benchmarks.robots --out results/robots

# The simulated depth camera: the kernel against mj_multiRay on panda_canopy_depth, and a frame's figure (docs/camera.md).
camera: $(STAMP)
	MPLBACKEND=Agg $(PY) -m benchmarks.camera --out results/camera

# Sweeps (docs/sweeps.md). The packaged canopy_small (40 runs) and canopy_1k (1,000 runs) specs; rerunning
# a target resumes the sweep in its folder. sweep-throughput makes the runs/min table of docs/sweeps.md.
sweep-small: $(STAMP)
	MPLBACKEND=Agg $(VENV)/bin/qpctl sweep canopy_small --out results/sweep-canopy_small

sweep-1k: $(STAMP)
	MPLBACKEND=Agg $(VENV)/bin/qpctl sweep canopy_1k --jobs 2 --out results/sweep-canopy_1k

sweep-throughput: $(STAMP)
	MPLBACKEND=Agg $(PY) -m benchmarks.sweep_throughput --wait-quiet 600 --out results/sweep-throughput

lint: $(STAMP)
	$(VENV)/bin/ruff check qpctl baselines benchmarks reproduction tests examples
	$(VENV)/bin/mypy qpctl

clean:
	rm -rf $(VENV) results build *.egg-info
