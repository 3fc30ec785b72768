#!/usr/bin/env bash
# Merge the rows (and metrics CSVs) of the four jobs of 'LC + DCP-v2 beats DCP-v2' at lr 2.5e-4 into lc_dcp_bf16_lr/.
set -euo pipefail
cd "$(dirname "$0")"/..   # docs/results/converge (run: bash docs/results/converge/lc_dcp_bf16_lr/merge.sh)
out=lc_dcp_bf16_lr
jobs=(dcp_bf16_lr_256 dcp_bf16_lr_seed2_256 lc_dcp_bf16_lr_256 lc_dcp_bf16_lr_seed2_256)
: > "$out/lc.jsonl"
for job in "${jobs[@]}"; do
  [ -f "$job/runs/lc.jsonl" ] || continue
  cat "$job/runs/lc.jsonl" >> "$out/lc.jsonl"
  (cd "$job/runs" && find runs -path '*/run/metrics*.csv' -not -path '*retest*' -print0 | xargs -0 -I{} cp --parents {} "../../$out/")
done
