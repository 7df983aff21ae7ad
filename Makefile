# Set-up finds a Python >= 3.12 (PATH first, then pyenv's versions), makes .venv and installs the
# package editable with its test extras. Every user-facing target depends on it.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: setup demo test test-fast bench sweep research research-bench research-frontier proto clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	@set -e; \
	pick=""; \
	for c in python3.14 python3.13 python3.12 python3; do \
	  p=$$(command -v $$c 2>/dev/null) || continue; \
	  if $$p -c 'import sys; sys.exit(sys.version_info < (3, 12))' 2>/dev/null; then pick=$$p; break; fi; \
	done; \
	if [ -z "$$pick" ] && command -v pyenv >/dev/null 2>&1; then \
	  for p in $$(ls -d "$$(pyenv root)"/versions/3.1[2-9]*/bin/python 2>/dev/null | sort -rV); do \
	    if $$p -c 'import sys; sys.exit(sys.version_info < (3, 12))' 2>/dev/null; then pick=$$p; break; fi; \
	  done; \
	fi; \
	if [ -z "$$pick" ]; then echo "error: no Python >= 3.12 found on PATH or in pyenv; install one (lerobot 0.6 needs it)" >&2; exit 1; fi; \
	echo "using $$pick ($$($$pick --version))"; \
	[ -x $(PY) ] || $$pick -m venv $(VENV); \
	$(PY) -m pip install --quiet --upgrade pip; \
	$(PY) -m pip install --quiet -e '.[test]'; \
	touch $(STAMP)

# The main job on an embedded default (no GPU, no robot, no download): the real server serving the
# analytic demo policy with an emulated L40S pi0.5 latency profile to four simulated robots (two
# fast on the dynamic task, two slow on the static task), 20 s under each of RR, EDF and LA, then a
# small reference sweep in the simulator.
demo: setup
	$(VENV)/bin/lerobot-armory-bench --preset=libero --mix=half-fast --robots=4 \
	    --schedulers=rr,edf,lookahead@3 --emulate_profile=l40s-pi05 --duration_s=20 --output=out/demo/live.json
	$(VENV)/bin/lerobot-armory-sweep --profile=demo --out_dir=out/demo

# Every test CI runs, on WORKERS pytest-xdist workers (two on the 2-core reference machine; about
# 12 minutes there). --dist=loadgroup keeps each xdist_group (the Ray tests, the demo kinds) on one
# worker. test-fast: the inner loop, without the slow, subprocess, Ray, openpi and GPU tiers
# (docs/testing.md).
WORKERS ?= 2
FAST := not slow and not subprocess and not ray and not openpi and not gpu

test: setup
	$(PY) -m pytest -n $(WORKERS) --dist=loadgroup

test-fast: setup
	$(PY) -m pytest -n $(WORKERS) --dist=loadgroup -m "$(FAST)"

bench: setup
	$(PY) benchmarks/sim_speed.py
	$(PY) benchmarks/decision_time.py
	$(PY) benchmarks/engine_efficiency.py
	$(PY) benchmarks/pi05_ops.py
	$(PY) benchmarks/pi05_ops.py --kind=smolvla
	$(PY) benchmarks/bf16_accuracy.py
	$(PY) benchmarks/serving_overhead.py
	$(PY) benchmarks/load.py 64 30
	$(VENV)/bin/lerobot-armory-bench --preset=libero --mix=half-fast --robots=4 \
	    --schedulers=rr,edf,lookahead@3 --emulate_profile=l40s-pi05 --duration_s=20

# The full reference sweep of SPEC §5 (about 15 minutes on 2 cores).
sweep: setup
	$(VENV)/bin/lerobot-armory-sweep --profile=full --out_dir=docs/results

# The offline scheduling study (research/README.md): research/ is not part of the installed package
# and `make test` does not collect its tests (about 1-1.5 min on 2 cores in all, the slowest ~20 s).
research: setup
	$(PY) -m pytest research/tests

# The study's benchmarks: small-fleet + decision-time targets (~20 s), the N = 10 target on 48
# paired seeds (~20 min), then the other-horizons diagnostic (~4 min). Exit 1 on a missed target.
research-bench: setup
	$(PY) research/benchmarks/frontier.py
	$(PY) research/benchmarks/n10_paired.py
	$(PY) research/benchmarks/frontier_horizons.py

# Regenerate the frontier study's committed results in docs/results/frontier (about 1 h on 2 cores).
research-frontier: setup
	PYTHONPATH=research $(PY) -m armory_research.frontier --profile=full --out_dir=docs/results/frontier --workers=2

# Regenerate the committed code of lerobot_armory/proto/armory.proto: the messages (armory_pb2.py,
# armory_pb2.pyi) and the gRPC client stub and servicer base (armory_pb2_grpc.py; grpc_tools has no
# typed-stub option for it). The server binds them through entrypoints/grpc/hardening.py, which swaps in request
# deserializers that never raise (see its docstring). tests/entrypoints/test_server.py fails when they are stale.
proto: setup
	@$(PY) -c 'import grpc_tools' 2>/dev/null || $(PY) -m pip install --quiet -e '.[dev]'
	$(PY) -m grpc_tools.protoc -I. --python_out=. --pyi_out=. --grpc_python_out=. lerobot_armory/proto/armory.proto

clean:
	rm -rf $(VENV) out .pytest_cache
