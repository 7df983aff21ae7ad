#!/usr/bin/env bash
# Prepare, on a machine with PyPI (this one), what a GPU device machine lacks to run the
# benchmarks: the wheels of the exact versions the project tests with, in .whl/ (git-ignored),
# for Python 3.12 on x86-64 Linux. The device image already has torch, numpy, safetensors,
# huggingface-hub, sentencepiece, msgpack, prometheus-client, matplotlib (docs/results/gpu/README.md
# lists what was carried before). Run once per checkout; `benchmarks/gpu/run.sh` installs them there.
set -euo pipefail
cd "$(dirname "$0")/../.."
PKGS=(
  lerobot==0.6.1 transformers==5.5.4 tokenizers==0.22.2
  draccus==0.11.6 mergedeep==1.3.4 toml==0.10.2 typing-inspect==0.9.0 mypy-extensions==1.2.0
  gymnasium==1.4.0 farama-notifications==0.0.6 cloudpickle==3.1.3 termcolor==3.3.0
  grpcio==1.85.1 grpcio-health-checking==1.85.1 protobuf==7.36.2 websockets==17.4
  pydantic==2.14.4 pydantic-core==2.50.5 annotated-types==0.8.0 typing-inspection==0.4.5
  num2words==0.5.14  # transformers' SmolVLM processor (the smolvla step); its docopt is built below
)
PY=${PYTHON:-python3}
mkdir -p .whl
grep -qx '/.whl/' .git/info/exclude 2>/dev/null || grep -qx '/.whl/' .gitignore || echo '/.whl/' >> .git/info/exclude
$PY -m pip download --quiet --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
  --platform manylinux2014_x86_64 --platform manylinux1_x86_64 --platform any -d .whl "${PKGS[@]}"
# docopt (num2words' one dependency) is published as a source archive only: build its wheel here.
ls .whl/docopt-0.6.2-*.whl >/dev/null 2>&1 || $PY -m pip wheel --quiet --no-deps -w .whl docopt==0.6.2
# One version of each package: two stop the whole install on the device.
dupes=$(ls .whl/*.whl | xargs -n1 basename | sed 's/-[0-9].*//' | tr 'A-Z-' 'a-z_' | sort | uniq -d)
[ -z "$dupes" ] || { echo "two versions of: $dupes (remove the older from .whl/)" >&2; exit 1; }
echo "wheels in .whl/: $(ls .whl/*.whl | wc -l) files, $(du -sm .whl | cut -f1) MiB (a device call carries at most 64 MiB)"
