#!/usr/bin/env bash
# One-shot GPU check: what to run in the few minutes a GPU is lent, in one command.
#
#   bash benchmarks/gpu_check.sh OUT_DIR [--device cuda|cpu] [--wheels DIR]
#
# On a machine with CUDA and PyTorch already installed, from the repository root:
#   0. makes dego importable from this tree without touching the installed torch
#      (`pip install --no-deps --no-build-isolation -e .`, else PYTHONPATH=src); wheels in
#      --wheels DIR (e.g. beartype, gsplat for machines without a package index) are
#      installed first with --no-deps; gsplat, when importable, compiles its CUDA code in
#      the background while the tests run;
#   1. the CUDA-parametrised test cases (pytest -k cuda: the Triton kernels against the
#      torch path, the compiled training step and bf16 autocast on CUDA among them);
#   2. bench_splat (the torch path, backend="triton" and gsplat when it imports, and the
#      gsplat adapter's overhead), bench_splat_sweep (torch / triton / gsplat at 10k-200k
#      Gaussians and 256x704-900x1600), bench_compile (W1 compiled, backend="triton"),
#      gsplat_parity (when gsplat imports), bench_voxelize --skip-dense, bench_deformation,
#      bench_rayiou and bench_metrics, all with --device cuda;
# and writes OUT_DIR/report.md (one table: step, command, status, seconds) with each
# step's log beside it. Every step has its own time limit (the limits add up to at most
# 8 minutes; tests/test_gpu_check.py checks the sum) and the script goes on after a
# failure. gsplat's extension is built in the background while the tests run (bounded by
# their limit); loading it takes > 30 s in every new process, which each benchmark pays in
# its untimed warm-up call, never in a timed one. With --device cpu (or no CUDA) it is a
# dry run: the CUDA steps are listed as skipped and the report is still written (the
# test-suite runs this).
set -uo pipefail

usage() { echo "usage: $0 OUT_DIR [--device cuda|cpu] [--wheels DIR]" >&2; exit 2; }
[ $# -ge 1 ] || usage
OUT=$1
shift
DEVICE=cuda
WHEELS=""
while [ $# -gt 0 ]; do
    case $1 in
        --device) DEVICE=${2:-}; shift 2 ;;
        --wheels) WHEELS=${2:-}; shift 2 ;;
        *) usage ;;
    esac
done
[ "$DEVICE" = cuda ] || [ "$DEVICE" = cpu ] || usage
cd "$(dirname "$0")/.."
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)
PY=${PYTHON:-python3}
export PYTHONUNBUFFERED=1
REPORT="$OUT/report.md"

if [ "$DEVICE" = cuda ] && ! "$PY" -c "import torch, sys; sys.exit(not torch.cuda.is_available())" 2>/dev/null; then
    echo "no CUDA device visible: dry run" >&2
    DEVICE=cpu
fi

# 0. dego from this tree, the installed torch untouched
if [ "$DEVICE" = cuda ]; then
    if [ -n "$WHEELS" ]; then
        "$PY" -m pip install --no-deps --no-index -q "$WHEELS"/*.whl >"$OUT/install.log" 2>&1
    fi
    "$PY" -m pip install --no-deps --no-build-isolation -q -e . >>"$OUT/install.log" 2>&1 \
        || export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONPATH="$PWD/benchmarks${PYTHONPATH:+:$PYTHONPATH}"

{
    echo "# GPU check"
    echo
    echo "- date: $(date -u '+%Y-%m-%d %H:%M UTC'), commit $(git rev-parse --short HEAD 2>/dev/null || echo unknown)"
    echo "- device: $DEVICE$( [ "$DEVICE" = cuda ] && nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>/dev/null | sed 's/^/, /')"
    echo "- $("$PY" -c 'import sys, torch; print(f"python {sys.version.split()[0]}, torch {torch.__version__}, CUDA {torch.version.cuda}")' 2>&1)"
    echo
    echo "| step | command | status | seconds |"
    echo "|---|---|---|---|"
} >"$REPORT"

GSPLAT=absent
if [ "$DEVICE" = cuda ] && "$PY" -c "import gsplat" 2>/dev/null; then
    GSPLAT=building
    ( TORCH_CUDA_ARCH_LIST="$("$PY" -c 'import torch; print("%d.%d" % torch.cuda.get_device_capability())')" \
        MAX_JOBS=12 timeout 140 "$PY" -c "import gsplat.cuda._backend as b; b._C" \
        >"$OUT/gsplat_build.log" 2>&1; echo "exit $?" >>"$OUT/gsplat_build.log" ) &
    BUILD=$!
fi

# step NAME SECONDS NEEDS_CUDA COMMAND...: run with a time limit, log, add a report row.
step() {
    local name=$1 limit=$2 needs_cuda=$3
    shift 3
    local status start=$SECONDS
    if [ "$needs_cuda" = yes ] && [ "$DEVICE" != cuda ]; then
        status="skipped (no CUDA)"
    else
        timeout "$limit" "$@" >"$OUT/$name.log" 2>&1
        local rc=$?
        case $rc in
            0) status=ok ;;
            124|137) status="timed out after ${limit} s" ;;
            *) status="failed (exit $rc)" ;;
        esac
    fi
    echo "| $name | \`$*\` | $status | $((SECONDS - start)) |" >>"$REPORT"
    echo "$name: $status"
}

step tests 140 yes "$PY" -m pytest tests -q -p no:cacheprovider -n 4 -k cuda --continue-on-collection-errors
if [ "$GSPLAT" = building ]; then
    wait "$BUILD"
    grep -q "exit 0" "$OUT/gsplat_build.log" && GSPLAT=ready || GSPLAT="failed to build"
fi
step bench_splat 65 yes "$PY" benchmarks/bench_splat.py --device "$DEVICE" --repeats 10 --skip-w2
step bench_splat_sweep 110 yes "$PY" benchmarks/bench_splat_sweep.py --device "$DEVICE" --repeats 3 --budget 85 --torch-max-n 10000
step bench_compile 40 yes "$PY" benchmarks/bench_compile.py --device "$DEVICE" --repeats 5
if [ "$GSPLAT" = ready ]; then
    step gsplat_parity 30 yes "$PY" benchmarks/gsplat_parity.py
else
    echo "| gsplat_parity | \`benchmarks/gsplat_parity.py\` | skipped (gsplat $GSPLAT) | 0 |" >>"$REPORT"
fi
step bench_voxelize 30 yes "$PY" benchmarks/bench_voxelize.py --device "$DEVICE" --skip-dense
step bench_deformation 20 yes "$PY" benchmarks/bench_deformation.py --device "$DEVICE"
step bench_rayiou 25 yes "$PY" benchmarks/bench_rayiou.py --device "$DEVICE"
step bench_metrics 15 yes "$PY" benchmarks/bench_metrics.py --device "$DEVICE"

{
    echo
    echo "gsplat: $GSPLAT. Logs: \`$OUT/<step>.log\`."
    for log in "$OUT"/bench_*.log "$OUT"/gsplat_parity.log; do
        [ -f "$log" ] || continue
        echo
        echo "## $(basename "$log" .log)"
        echo
        echo '```text'
        tail -n 40 "$log"
        echo '```'
    done
} >>"$REPORT"
echo "report: $REPORT"
