#!/usr/bin/env bash
# The CUDA path end to end, on a machine with a GPU (a Jetson, a lent CUDA box), in a few minutes:
#   deploy/check-cuda.sh [OUT_DIR] [PROFILE]
# 1. python -m benchmarks.cuda_check: CPU vs CUDA hash-encoding parity (forward, gradients, Adam),
#    the tiny scene mapped with PROFILE's settings (default orin-agx) on CUDA, a mesh and a
#    held-out render evaluated against ground truth, the decoders' onnxruntime providers;
#    writes OUT_DIR/cuda_check.json
# 2. the mapping tests with every mapper forced onto CUDA (H3EDGE_TEST_DEVICE=cuda)
# Exit status: non-zero when either part fails; 2 when torch sees no CUDA device.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT="${1:-out/cuda_check}"
PROFILE="${2:-orin-agx}"
PY="${PYTHON:-python3}"
mkdir -p "$OUT"
"$PY" -c "import torch, sys; print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.is_available()); sys.exit(0 if torch.cuda.is_available() else 2)" || exit 2
"$PY" -m benchmarks.cuda_check --profile "$PROFILE" --out "$OUT" 2>&1 | tee "$OUT/cuda_check.log"
rc1=${PIPESTATUS[0]}
H3EDGE_TEST_DEVICE=cuda "$PY" -m pytest -q -p no:cacheprovider -x \
    tests/test_mapper.py tests/test_trainer.py tests/test_state.py tests/test_onnx.py tests/test_texture.py \
    2>&1 | tee "$OUT/pytest_cuda.log" | tail -n 15
rc2=${PIPESTATUS[0]}
echo "cuda_check rc=$rc1, tests on cuda rc=$rc2"
[ "$rc1" -eq 0 ] && [ "$rc2" -eq 0 ]
