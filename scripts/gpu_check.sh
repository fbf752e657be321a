#!/usr/bin/env bash
# The GPU checks in one call, on a machine with an NVIDIA GPU, torch, nvcc
# and no network: build the native extension with CUDA, run the `gpu` tests (CUDA against the
# CPU backend), time the renderer (against gsplat 1.5.3 when its wheel is in .whl/) and the
# K-nearest SPH density, reconstruct a paper-scale dataset and evaluate it; prints one table.
#
#   bash scripts/gpu_check.sh [DATASET] [ITERATIONS]
#
# DATASET: a rendered dataset folder (default: data/ws_paper, made on a CPU machine with
#   gf-cli simulate water_sphere --particles 10000 --fps 60 --out ws_paper.h5
#   gf-cli render-dataset ws_paper.h5 --out data/ws_paper --views 5 --test-views 1 --resolution 400 --frames 0:60
# Results go to $OUT (the device tool's folder) or ./gpu_out. Environment: SKIP_RENDER_BENCH=1 leaves
# out `bench render`; SKIP_TESTS=1 the `gpu` tests; PROFILE_STEPS=1 adds scripts/profile_steps.py
# (where a training step's time goes) on DATASET; RECON_BUDGET (seconds, default 150) bounds the
# reconstruction; RECON_ARGS adds options to it (e.g. --config FILE). MATRIX="DIR [DIR...]" also
# reconstructs each of those datasets (scene-matrix scenes from `gf-cli bench scenes`) on the GPU with
# the default preset, `--time-budget ${MATRIX_BUDGET:-300}`, and evaluates it.
set -uo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
cd "$ROOT"
OUT=${OUT:-$ROOT/gpu_out}
mkdir -p "$OUT"
DATASET=${1:-data/ws_splat400}
ITERS=${2:-4000}
PY=${PYTHON:-python3}
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} PYTHONUNBUFFERED=1 GF_REQUIRE_NATIVE=1 GF_EXT_DIR=${GF_EXT_DIR:-/tmp/gf_ext}
# the source tree as packages (the CLI's import name is gf_cli)
mkdir -p /tmp/gf_pp && ln -sfn "$ROOT/cli" /tmp/gf_pp/gf_cli
export PYTHONPATH="$ROOT:/tmp/gf_pp:${PYTHONPATH:-}"
T0=$(date +%s)
stamp() { echo "[$(( $(date +%s) - T0 )) s] $*"; }

nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
$PY -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)" | tee -a "$OUT/gpu.txt"

# gsplat JIT-builds its CUDA code on first import: start it now, beside our build
if ls .whl/gsplat-*.whl >/dev/null 2>&1; then
  (set -x; $PY -m pip install -q --no-index --no-deps --target /tmp/gs .whl/gsplat-*.whl &&
   MAX_JOBS=10 PYTHONPATH=/tmp/gs:$PYTHONPATH $PY -c "import gsplat.cuda._backend as b; print('gsplat built', b._C is not None)") \
   > "$OUT/gsplat_build.log" 2>&1 &
  GS_PID=$!
fi

stamp "building the native extension (CPU + CUDA)"
$PY -c "from gf_core import native; assert native.load() is not None; print('has_cuda', native.has_cuda())" \
  2>&1 | tail -30 || { stamp "BUILD FAILED"; exit 1; }
if [ -z "${SKIP_TESTS:-}" ]; then
  stamp "gpu tests"
  timeout 300 $PY -m pytest -q -m gpu -p no:cacheprovider tests/native/test_gpu.py 2>&1 | tee "$OUT/pytest_gpu.log" | tail -25
fi
stamp "K-nearest SPH density and renderer timings"
if [ -n "${GS_PID:-}" ]; then wait $GS_PID; tail -3 "$OUT/gsplat_build.log"; export PYTHONPATH=/tmp/gs:$PYTHONPATH; fi
$PY -m gf_cli.main bench gpu --out "$OUT/bench_gpu.json" 2>&1 | tail -12
if [ -z "${SKIP_RENDER_BENCH:-}" ]; then
  $PY -m gf_cli.main bench render --device cuda --backends native,reference --particles 1000,50000,200000 \
    --resolutions 128,400,800 --repeats 20 --out "$OUT/bench_render_cuda.json" 2>&1 | tail -14
fi
if [ -n "${PROFILE_STEPS:-}" ] && [ -d "$DATASET" ]; then
  stamp "training step profile on $DATASET"
  $PY scripts/profile_steps.py "$DATASET" --device cuda ${PROFILE_ARGS:---config scripts/paper_gpu.toml} \
    --out "$OUT/profile_steps.json" 2>&1 | grep -v "^USDT\|^ERROR:.*DeviceProperties" | tail -62
fi
if [ -d "$DATASET" ] && [ "$ITERS" != 0 ]; then
  stamp "paper-scale reconstruction of $DATASET"
  $PY -m gf_cli.main reconstruct "$DATASET" --out /tmp/paper_run --device cuda --iterations "$ITERS" \
    --init-particles 40000 --max-particles 50000 --time-budget "${RECON_BUDGET:-150}" ${RECON_ARGS:-} \
    --force --quiet 2>&1 | tail -8
  $PY -m gf_cli.main evaluate /tmp/paper_run --dataset "$DATASET" --device cuda 2>&1 | tail -6
  tar -czf "$OUT/paper_run.tar.gz" -C /tmp/paper_run --exclude checkpoint.pt --exclude recon.h5 .
fi
for DS in ${MATRIX:-}; do
  NAME=$(basename "$DS")
  stamp "scene-matrix scene $NAME on the GPU"
  $PY -m gf_cli.main reconstruct "$DS" --out "/tmp/matrix_$NAME" --device cuda --seed 0 \
    --time-budget "${MATRIX_BUDGET:-300}" --force --quiet 2>&1 | tail -4
  $PY -m gf_cli.main evaluate "/tmp/matrix_$NAME" --dataset "$DS" --device cuda 2>&1 | tail -6
  tar -czf "$OUT/matrix_$NAME.tar.gz" -C "/tmp/matrix_$NAME" --exclude checkpoint.pt --exclude recon.h5 .
done
stamp "done"
