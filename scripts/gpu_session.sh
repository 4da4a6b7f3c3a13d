#!/usr/bin/env bash
# The next GPU session's checks in one call (docs/gpu.md, "What the next GPU session runs"): under
# 10 minutes on an H200, every output under OUT (default $OUT, else ./gpu_session_out).
#
#   bash scripts/gpu_session.sh            # on the GPU machine, from the repository root
#   DRY=1 bash scripts/gpu_session.sh      # on a CPU: the same steps at the check's tiny size
#
# 1. the eager matrix, CUDA against the CPU and dense against sparse (gpu_check --modes eager, 160 s);
# 2. which head layouts the SDPA kernels take, and the models with the layout copies on and off
#    (gpu_diagnose --sections layout, ~60 s);
# 3. which Triton kernels each device should run (gpu_diagnose --sections kernels, ~60 s);
# 4. host syncs per call, and what upstream runs do around their captured steps (the fused AdamW
#    across MDM's resume, the logged norms in one sync, the schedule tables on the device; 0.9.7)
#    (gpu_diagnose --sections syncs optimizer, ~30 s);
# 5. the captured trans_enc bf16 loop and training step (reduce-overhead; ~180 s), with the graphs each
#    compiled, the CUDA-graph skips and why (TORCH_LOGS=cudagraphs) and a profile of each model's call
#    after its timing (--profile: host and GPU time, launches, the top host events): 0.9.2's 1.28x training step.
# Each step has its own time limit (600 s in all; about 8 minutes on the H200); a step that fails
# or runs out leaves what it wrote and the next runs. One file per step (its stdout and stderr) and the two tables: 7 files under OUT
# (the device tool brings back at most 8); each step's exit status is printed.
set -u
OUT="${OUT:-gpu_session_out}"
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
dry=()
diag=()
if [ -n "${DRY:-}" ]; then
  dry=(--dry-run --no-doc)
  diag=(--dry-run)
fi
cp docs/gpu.md "$OUT/gpu_check.md"                # gpu_check.py writes its table into a copy of the doc
cp docs/gpu.md "$OUT/gpu_check_captured.md"
step() {  # step NAME LIMIT_S CMD...
  local name=$1 limit=$2
  shift 2
  local t0=$SECONDS
  timeout "$limit" "$@" > "$OUT/$name.txt" 2>&1
  echo "$name: exit $? in $((SECONDS - t0)) s"
}
step eager 185 python3 scripts/gpu_check.py --modes eager --budget-s 160 --doc "$OUT/gpu_check.md" "${dry[@]}"
step layout 80 python3 scripts/gpu_diagnose.py --sections layout --out "$OUT" "${diag[@]}"
step kernels 75 python3 scripts/gpu_diagnose.py --sections kernels --out "$OUT" "${diag[@]}"
step syncs 60 python3 scripts/gpu_diagnose.py --sections syncs optimizer --out "$OUT" "${diag[@]}"
TORCH_LOGS=cudagraphs step captured 200 python3 scripts/gpu_check.py --modes reduce-overhead --models trans_enc --precisions bf16 \
  --calls loop train --budget-s 180 --profile --doc "$OUT/gpu_check_captured.md" "${dry[@]}"
