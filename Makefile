# Set-up finds a Python >= 3.12 (PATH first, then pyenv's versions), makes .venv and installs the
# package editable with its test extras. Every user-facing target depends on it.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: setup demo test bench sweep proto clean

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

test: setup
	$(PY) -m pytest

bench: setup
	$(PY) benchmarks/sim_speed.py
	$(PY) benchmarks/decision_time.py
	$(PY) benchmarks/engine_efficiency.py
	$(PY) benchmarks/serving_overhead.py
	$(PY) benchmarks/load.py 64 30
	$(VENV)/bin/lerobot-armory-bench --preset=libero --mix=half-fast --robots=4 \
	    --schedulers=rr,edf,lookahead@3 --emulate_profile=l40s-pi05 --duration_s=20

# The full reference sweep of SPEC §5 (about 15 minutes on 2 cores).
sweep: setup
	$(VENV)/bin/lerobot-armory-sweep --profile=full --out_dir=docs/results

# Regenerate the committed protobuf messages from lerobot_armory/proto/armory.proto (the gRPC
# binding, lerobot_armory/proto/armory_grpc.py, is written by hand: see its docstring).
proto: setup
	$(PY) -m pip install --quiet -e '.[dev]'
	$(PY) -m grpc_tools.protoc -I. --python_out=. --pyi_out=. lerobot_armory/proto/armory.proto

clean:
	rm -rf $(VENV) out .pytest_cache
