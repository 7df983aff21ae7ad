#!/usr/bin/env bash
# One device call: install the wheels carried in .whl/ (benchmarks/gpu/prepare.sh made them), then
# run the named steps in order, each under its own time limit so the call returns inside the device
# tool's 10 minutes with whatever finished. Everything goes to $OUT: log.txt (all output) and the
# results each step writes (JSON, figures). Steps and what each decides: docs/results/gpu/BACKLOG.md.
#
#   device run (carry .whl):  bash benchmarks/gpu/run.sh env graphs
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT=${OUT:-out/gpu}
mkdir -p "$OUT"
LOG="$OUT/log.txt"
touch /tmp/run_start
# The device tool gives a command at most 600 s: every step's limit is cut to what is left of
# CALL_S (from here, the wheels' install included), so the call returns with its log even when
# a one-time build ran before a long step.
CALL_END=$(( $(date +%s) + ${CALL_S:-585} ))
if [ -d .whl ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site:$PWD
else
  export PYTHONPATH=$PWD
fi
export PYTHONUNBUFFERED=1 TOKENIZERS_PARALLELISM=false

step() {  # step NAME SECONDS COMMAND... (COMMAND may be one of the functions below)
  local name=$1 limit=$2 left=$(( CALL_END - $(date +%s) ))
  shift 2
  if [ "$left" -lt 10 ]; then
    echo "=== [$name] skipped: ${left} s left of the call" | tee -a "$LOG"
    return 1
  fi
  [ "$left" -lt "$limit" ] && limit=$left
  # --line-buffered: a step the device tool kills must leave its lines in log.txt (grep into a
  # pipe buffers 4 KiB otherwise; a π0 step's whole output was lost that way on 2026-11-27).
  echo "=== [$name] $(date +%T) (limit ${limit} s): $*" | tee -a "$LOG"
  timeout "$limit" bash -c "$*" 2>&1 | grep --line-buffered -v -E "Vision embedding key|port of the OpenPI|OpenPI structure|Original implementation" | tee -a "$LOG"
  echo "=== [$name] $(date +%T) rc=${PIPESTATUS[0]}" | tee -a "$LOG"
}

env_report() {
  python3 --version
  nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm,clocks.max.sm --format=csv,noheader
  nproc
  python3 -c "import torch, lerobot, transformers, grpc; print(torch.__version__, lerobot.__version__, transformers.__version__, grpc.__version__, torch.cuda.get_device_name())"
}

# The π0.5 that robots on armory_sim are served: its features (one 64² camera, 2-d state), full
# size, bf16; chunk 10 (libero timing) unless said (built once per machine).
build_pi05() {  # build_pi05 DIR CHUNK [SEED]: the robots' full bf16 π0.5 in DIR, once per machine
  [ -f "$1/config.json" ] || python3 -c "from lerobot_armory.policies.demo.build import main; main(['--kind=pi05', '--size=full', '--dtype=bfloat16', '--chunk_size=$2', '--device=cuda', '--seed=${3:-0}', '--output=$1'])"
}
sim_pi05() { build_pi05 /tmp/pi05-sim 10; }
# The same π0.5 with chunk 50 (π0.5's own default; its builder sets n_action_steps = chunk_size),
# for vs_async50: does the comparison hold when a chunk may take 25 steps (833 ms), not 5 (167 ms)?
sim_pi05_50() { build_pi05 /tmp/pi05-sim50 50; }

live() {  # live N: EDF and Lookahead on the graphed π0.5, libero half-fast, real timing
  sim_pi05 && python3 -m lerobot_armory.bench.live --preset=libero --mix=half-fast --robots="$1" \
    --schedulers=edf,lookahead@3 --emulate_profile= --device=cuda --policy_path=/tmp/pi05-sim --groups=4 --max_batch_size=8 \
    --policy_args="--engine.cuda_graphs=on --engine.matmul_precision=${MATMUL:-high} --max_robots=64" --duration_s=30 \
    --output="$OUT/live_N$1.json" --work_dir=/tmp/live
}

vs_compare() {  # vs_compare POLICY CHUNK NAME N,N,...: ours (graphed π0.5) against LeRobot's async server, one π0.5 per stock robot
  # (stock with its observation filter off first: its serving path itself; then as it ships;
  # starvation from each robot's third chunk: a stock server's first passes on a GPU are cold)
  python3 benchmarks/vs_lerobot_async.py --device=cuda --policy="$1" --chunk="$2" --robots="$4" \
    --duration_s=30 --settle_chunks=3 --systems=ours,stock_nofilter,stock --ours_server_args="--engine.cuda_graphs=on" --max_batch_size=8 \
    --out="$OUT/$3" --work_dir="/tmp/$3"
}
vs_async() { sim_pi05 && vs_compare /tmp/pi05-sim 10 vs_async "$1"; }  # vs_async N,N,...: chunk 10
vs_async50() { sim_pi05_50 && vs_compare /tmp/pi05-sim50 50 vs_async50 "$1"; }  # a new chunk after 25 steps on both sides
swap_gpu() {  # a live swap between two full π0.5 checkpoints (seeds 0 and 1) under 8 robots, b <= 8
  sim_pi05 && build_pi05 /tmp/pi05-sim-b 10 1 \
    && python3 benchmarks/swap.py --old=/tmp/pi05-sim --new=/tmp/pi05-sim-b --device=cuda --max_batch_size=8 \
      --image_size=64 --robots=8 --window_s=15 --out="$OUT/swap_gpu.json"
}
export -f env_report build_pi05 sim_pi05 sim_pi05_50 live vs_compare vs_async vs_async50 swap_gpu
export OUT

for s in "$@"; do
  case $s in
    env) step env 40 env_report ;;
    smoke) step smoke 300 python3 benchmarks/gpu_profile.py --size=tiny --configs=pi05-bf16,pi05-bf16-graphs --reps=3 --out="$OUT/smoke_tiny.json" ;;
    graphs) step graphs 510 python3 benchmarks/gpu_profile.py --configs=pi05-bf16,pi05-bf16-graphs,pi05-bf16-graphs-sdpa,pi05-bf16-graphs-tf32 --work_dir=/tmp/gp ;;
    compiled) step compiled 560 python3 benchmarks/gpu_profile.py --configs=pi05-bf16-graphs-tf32-visionbf16,pi05-bf16-graphs-tf32-visionbf16-compiled --graph_buckets=1,2,3,4,5,6,7,8 --float32_reference --out="$OUT/compiled.json" --work_dir=/tmp/gp ;;
    fused) step fused 520 python3 benchmarks/gpu_profile.py --configs=pi05-bf16,pi05-bf16-graphs-tf32-ordered-fullprompt,pi05-bf16-graphs-tf32-fullprompt,pi05-bf16-graphs-tf32,pi05-bf16-graphs-tf32-visionbf16 --graph_buckets=1,2,3,4,5,6,7,8 --float32_reference --out="$OUT/fused.json" --work_dir=/tmp/gp ;;
    pi0) step pi0 400 python3 benchmarks/gpu_profile.py --configs=pi0-bf16,pi0-bf16-graphs-tf32 --graph_buckets=1,2,3,4,5,6,7,8 --float32_reference --out="$OUT/pi0.json" --work_dir=/tmp/gp ;;
    smolvla) step smolvla 420 python3 benchmarks/gpu_profile.py --configs=smolvla-fp32,smolvla-fp32-graphs-tf32-unaligned,smolvla-fp32-graphs-tf32 --graph_buckets=1,2,3,4,5,6,7,8 --out="$OUT/smolvla.json" --work_dir=/tmp/gp ;;
    stages) step stages 360 python3 benchmarks/gpu_profile.py --configs=pi05-bf16,pi05-bf16-graphs-tf32-visionbf16-twopasssoftmax,pi05-bf16-graphs-tf32-visionbf16 --graph_buckets=1,2,3,4,5,6,7,8 --stages --float32_reference --out="$OUT/stages.json" --work_dir=/tmp/gp ;;
    kernels) step kernels 270 python3 benchmarks/gpu_profile.py --configs=pi05-bf16-graphs-tf32-visionbf16-twopasssoftmax,pi05-bf16-graphs-tf32-visionbf16 --graph_buckets=1,8 --reps=3 --kernels --out="$OUT/kernels.json" --work_dir=/tmp/gp ;;
    micro) step micro 90 python3 benchmarks/gpu/micro.py --out="$OUT/micro.json" ;;
    buckets) step buckets 110 python3 benchmarks/gpu_profile.py --configs=pi05-bf16-graphs,pi05-bf16-graphs-tf32 --graph_buckets=1,2,3,4,5,6,7,8 --out="$OUT/all_buckets.json" --work_dir=/tmp/gp ;;
    efficiency) step efficiency 170 python3 benchmarks/engine_efficiency.py --policy=pi05-full --sizes=1,4,8 --cuda_graphs=on ;;
    # The robots' π0.5 is built in a step of its own (≈ 60 s on a fresh machine, once): built
    # inside a live step's limit it cut live10 on 2026-11-28.
    live[0-9]*) step sim 150 sim_pi05 && step "$s" 200 live "${s#live}" ;;  # liveN: N robots
    vs_async) step sim 150 sim_pi05 && step vs_async 560 vs_async 1,4 ;;
    vs_async8) step sim 150 sim_pi05 && step vs_async8 560 vs_async 8 ;;
    vs_async50) step sim50 150 sim_pi05_50 && step vs_async50 560 vs_async50 1,4 ;;
    # vs_async_N / vs_async50_N: one fleet size a call (N = 4's four stock π0.5 servers load for minutes)
    vs_async_[0-9]*) step sim 150 sim_pi05 && step "$s" 560 vs_async "${s#vs_async_}" ;;
    vs_async50_[0-9]*) step sim50 150 sim_pi05_50 && step "$s" 560 vs_async50 "${s#vs_async50_}" ;;
    faults) step faults 120 python3 benchmarks/gpu/device_faults.py --out="$OUT/device_faults.json" ;;
    swap) step sim 150 sim_pi05 && step swap 400 swap_gpu ;;
    *) echo "unknown step $s (env smoke graphs fused pi0 smolvla stages kernels micro buckets compiled efficiency liveN vs_async vs_async8 vs_async50 vs_async_N vs_async50_N faults swap)" | tee -a "$LOG" ;;
  esac
done
# Only what this call wrote (the files back are limited to 8).
find docs/results/gpu -maxdepth 1 -newer /tmp/run_start \( -name '*.json' -o -name '*.png' \) -exec cp {} "$OUT/" \;
ls -la "$OUT"
