#!/usr/bin/env bash
# Every GPU check in one run, within a time budget: the test suite with CUDA present, then the
# speed scripts, each writing its tables into one results folder.
#
#   RESULTS=benchmarks/results/h100 GEOFEAT_DATA=../shared/data bash benchmarks/speed/gpu_checks.sh
#
# Settings (environment):
#   RESULTS        results folder (default benchmarks/results/gpu); before/ in it for BEFORE's runs
#   BUDGET         seconds for the whole run (default 540); a step that would start with less
#                  than its own need left is skipped and says so
#   TEST_WORKERS   pytest-xdist processes for the suite (default 8), each with 2 threads
#   TEST_SECONDS   the suite's share of the budget (default 240)
#   BEFORE         a folder holding an earlier geofeat (pip install --target), timed beside this one
#   DSMK           a DeepShapeMatchingKit checkout, for its ULRSSM step beside ours
# The suite runs first; its log and JUnit file go to RESULTS/tests.log and RESULTS/tests.xml.
set -uo pipefail
cd "$(dirname "$0")/../.."
RESULTS="${RESULTS:-benchmarks/results/gpu}"
BUDGET="${BUDGET:-540}"
TEST_WORKERS="${TEST_WORKERS:-8}"
TEST_SECONDS="${TEST_SECONDS:-240}"
START=$(date +%s)
mkdir -p "$RESULTS/before"
export PYTHONUNBUFFERED=1

left() { echo $((BUDGET - ($(date +%s) - START))); }

# step NAME NEED CAP COMMAND...: run COMMAND with at most CAP seconds (and never past the budget),
# or skip it when less than NEED seconds are left.
step() {
    local name=$1 need=$2 cap=$3
    shift 3
    local remaining
    remaining=$(left)
    if [ "$remaining" -lt "$need" ]; then
        echo "== $name: skipped, ${remaining} s left of the budget (needs ${need} s)"
        return 0
    fi
    local limit=$((remaining < cap ? remaining : cap))
    echo "== $name (at most ${limit} s; $(($(date +%s) - START)) s into the run)"
    local begin=$(date +%s)
    timeout --signal=INT --kill-after=10 "$limit" "$@"
    echo "== $name: exit $? after $(($(date +%s) - begin)) s"
}

nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm,clocks.max.sm --format=csv,noheader || true
python - <<'EOF'
import torch, transformers
print("torch", torch.__version__, "transformers", transformers.__version__, "cuda", torch.cuda.is_available())
EOF

# 1. the test suite, CUDA cases included (2 threads per worker: the workers share the cores)
step "test suite" 60 "$TEST_SECONDS" env OMP_NUM_THREADS=2 MKL_NUM_THREADS=2 OPENBLAS_NUM_THREADS=2 \
    python -m pytest -q -n "$TEST_WORKERS" --timeout 150 -p no:cacheprovider -rfEs --durations=25 \
    --junitxml "$RESULTS/tests.xml" 2>&1 | tee "$RESULTS/tests.log" | tail -60

# 2. the multi-view DINO path, with a profile and the bfloat16-weights variant
step "speed_dino" 40 120 python -m benchmarks.speed.dino --device cuda --repeats 5 --profile --bf16-weights \
    --out "$RESULTS/speed_dino_bf16"

# 3. geofeat extract over the 100 FAUST_r shapes, without and with read-ahead
step "speed_extract" 40 120 python -m benchmarks.speed.extract --dinov3 --device cuda --prefetch 0 2 \
    --out "$RESULTS/speed_extract_dinov3.json"

# 4. GeoLoRA training at the paper's settings
step "speed_geolora" 40 90 python -m benchmarks.speed.geolora --model vitb16 --image-size 512 --device cuda \
    --steps 20 --out "$RESULTS/speed_geolora_vitb16_512_cuda"

# 5. the heads, and DeepShapeMatchingKit's ULRSSM step beside ours
step "speed_heads" 40 120 python -m benchmarks.speed.heads --device cuda --out "$RESULTS/speed_heads"
if [ -n "${DSMK:-}" ]; then
    step "speed_dsmk_ulrssm" 30 90 python -m benchmarks.speed.dsmk_ulrssm --dsmk "$DSMK" --work /tmp/dsmk_work \
        --device cuda --out "$RESULTS/speed_dsmk_ulrssm"
fi

# 6. BEFORE's DINO path (profiled), the reference recipe's training, BEFORE's training: as time allows.
# BEFORE's runs: python -P puts no folder before PYTHONPATH, so geofeat is imported from BEFORE and
# the benchmarks package from the checkout after it.
if [ -n "${BEFORE:-}" ]; then
    step "speed_dino (before)" 30 90 env PYTHONPATH="$BEFORE:$PWD" python -P -m benchmarks.speed.dino --device cuda \
        --repeats 5 --profile --out "$RESULTS/before/speed_dino_bf16"
fi
step "speed_geolora reference" 40 90 python -m benchmarks.speed.geolora --model vitb16 --image-size 512 \
    --device cuda --steps 20 --recipe reference --out "$RESULTS/speed_geolora_vitb16_512_cuda_reference"
if [ -n "${BEFORE:-}" ]; then
    step "speed_geolora (before)" 40 90 env PYTHONPATH="$BEFORE:$PWD" python -P -m benchmarks.speed.geolora --model vitb16 \
        --image-size 512 --device cuda --steps 20 --out "$RESULTS/before/speed_geolora_vitb16_512_cuda"
fi
echo "== done after $(($(date +%s) - START)) s"
