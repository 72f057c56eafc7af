#!/usr/bin/env bash
# One call's worth of GPU measurements, for a session lent a GPU machine for a few minutes
# (session 46 ran these steps by hand on an H200; docs/brax_comparison.md).
#
# Here, once (the machine has JAX with CUDA but not brax or mujoco, and cannot download):
#   echo /.whl/ >> .git/info/exclude
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#       --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
#       --platform manylinux2014_x86_64 -d .whl brax==0.14.2 mujoco==4.0.1 mujoco-core==4.0.1 \
#       mujoco-mjx==3.17.0 jaxopt trimesh==5.2.0 glfw pyopengl ml-collections
# Then on the GPU machine, from the repository root, with .whl carried:
#   bash benchmarks/gpu_session.sh [SECONDS]
# Every result goes to $OUT (or results-gpu/ without it), each step under its own time limit out of
# SECONDS (default 420) so that what finished comes back. Steps, most informative first:
#   1. kernels per step and their time (kernel_trace.py), DBD and impulse solvers and Brax
#      positional, humanoid, batch 4096, and their time per source line (--by-line: on the GPU the
#      kernels' names not yet checked against the HLO's), with each program's optimised HLO kept
#      for hlo_kernels.py;
#   2. throughput and compile times of dbdjax DBD and Brax positional on the humanoid, batches 1,
#      256, 4096, 32768 (brax_comparison.py, written to a fresh file, not merged with an earlier GPU's).
# PYTHON (default python3) runs the scripts. Without a GPU (no nvidia-smi) nothing is installed and
# step 2 is left out, so that the CPU results in benchmarks/results are not touched; a check here:
#   PYTHON=.venv/bin/python OUT=/tmp/gpu-check bash benchmarks/gpu_session.sh 300
set -u
SECONDS_FOR_ALL=${1:-420}
PYTHON=${PYTHON:-python3}
OUT=$(realpath -m "${OUT:-results-gpu}")
mkdir -p "$OUT"
on_gpu=$(command -v nvidia-smi >/dev/null && echo yes)
if [ -n "$on_gpu" ] && [ -d .whl ]; then
    $PYTHON -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
        .whl/*.whl || exit 1
    export PYTHONPATH=/tmp/site:$PWD
fi
export PYTHONUNBUFFERED=1
(nvidia-smi --query-gpu=name,driver_version,clocks.sm,memory.used --format=csv || echo "no GPU") | tee "$OUT/gpu.txt"
cd benchmarks || exit 1
started=$(date +%s)
left() { echo $((SECONDS_FOR_ALL - ($(date +%s) - started))); }

rm -rf /tmp/dump
timeout $(($(left) / 3)) $PYTHON kernel_trace.py --models humanoid \
    --engines dbdjax-dbd dbdjax-impulse brax-positional --batch 4096 --steps 10 --top 40 \
    --by-line --dump /tmp/dump --out "$OUT/kernel_trace_gpu.json" 2>&1 | grep -v -i warn
# Each engine's traced program is the largest optimised module in its directory.
for engine in /tmp/dump/*/; do
    dump=$(ls -S "$engine"*after_optimizations.txt 2>/dev/null | head -1)
    [ -n "$dump" ] && gzip -c "$dump" > "$OUT/$(basename "$engine")_4096.txt.gz"
done
$PYTHON hlo_kernels.py "$OUT"/*_4096.txt.gz --steps 10 --top 20 --out "$OUT/hlo_kernels_gpu.json"

[ -n "$on_gpu" ] || { echo "no GPU: step 2 left out"; ls -la "$OUT"; exit 0; }
rm -f results/brax_comparison_gpu.json
timeout "$(left)" $PYTHON brax_comparison.py --models humanoid --engines dbdjax-dbd brax-positional \
    --tasks throughput compile --batches 1 256 4096 32768 --note "$(head -2 "$OUT/gpu.txt" | tail -1)" 2>&1 \
    | grep -v -i warn
cp results/brax_comparison_gpu.json results/brax_comparison_gpu.png "$OUT/" 2>/dev/null
ls -la "$OUT"
