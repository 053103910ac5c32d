#!/usr/bin/env bash
# One GPU session's checks, in one command (each step time-limited, logs under $OUT):
#   1. the test cases parametrised over CUDA (pytest -k cuda);
#   2. bench_splat W1 on CUDA (dego vs gsplat when gsplat is importable, compat overhead);
#   3. dego.compat.gsplat vs gsplat's own rasterization (benchmarks/gsplat_parity.py),
#      when gsplat imports (its CUDA code is compiled on first import, in the background).
# Wheels in $WHEELS (e.g. beartype, gsplat) are installed first with --no-deps, for
# machines without a package index. Usage: [OUT=dir] [WHEELS=dir] bash benchmarks/gpu_check.sh
set -uo pipefail
OUT=${OUT:-gpu_check_out}
mkdir -p "$OUT"
export PYTHONPATH="$PWD/src:$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
if [ -n "${WHEELS:-}" ]; then
    python3 -m pip install --no-deps --no-index -q "$WHEELS"/*.whl 2>&1 | tail -2
fi
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee "$OUT/gpu.txt"
python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)" | tee -a "$OUT/gpu.txt"

# gsplat compiles its kernels on first import: start that now, next to the tests.
(TORCH_CUDA_ARCH_LIST="$(python3 -c 'import torch; print("%d.%d" % torch.cuda.get_device_capability())')" \
    MAX_JOBS=12 timeout 420 python3 -c "import gsplat, gsplat.cuda._backend as b; b._C.rasterize_to_pixels_3dgs_fwd" \
    >"$OUT/gsplat_build.txt" 2>&1; echo "gsplat build exit $?" >>"$OUT/gsplat_build.txt") &
build=$!

timeout 240 python3 -m pytest tests -q -p no:cacheprovider -k cuda --continue-on-collection-errors \
    2>&1 | tail -15 | tee "$OUT/tests.txt"
wait "$build"
tail -3 "$OUT/gsplat_build.txt"
timeout 200 python3 benchmarks/bench_splat.py --device cuda --repeats 5 --skip-w2 2>&1 | tee "$OUT/bench_splat.txt"
if grep -q "exit 0" "$OUT/gsplat_build.txt"; then
    timeout 120 python3 benchmarks/gsplat_parity.py 2>&1 | tee "$OUT/gsplat_parity.txt"
    timeout 60 python3 -m pytest tests/test_splat_backends.py -q -p no:cacheprovider 2>&1 | tail -5 | tee -a "$OUT/tests.txt"
fi
