#!/bin/bash
# One resumable chunk of a training-queue job on a lent GPU machine (the `device` tool), from the repository root:
#   bash benchmarks/device_chunk.sh <job id> <minutes> [runs at once, default 6]   # carry: .carry (device_payload.py)
# Installs the carried wheels; restores the carried data (`device_payload.py --unpack`: every file, SHA-256 checked)
# where `--root ../shared/data/<name>` resolves to the same path as on the developer machine (the rows' keys hold the
# resolved path; the device's checkout is /work/main too); runs `train_queue.py run --only <job> --max-minutes
# <minutes> --jobs <n>` (an `lcreg reproduce` or `learning_curves.py` job trains n runs at once, each in its own
# process: one run of 256 points x 8 leaves an H100 mostly idle) with its runs in .gpu-runs/ (git-ignored, so a
# second call on the still-warm machine resumes a cut-off run from its last.ckpt); then packs the job's small result
# files (`sync`: JSONL rows, metrics.csv, hparams, reports, `best/` weights; no checkpoints) into $OUT/results.tgz and
# the log into $OUT/log.txt.
# Merge here with: tar xzf <files_at>/results.tgz -C docs/results/converge
set -u
job=${1:?job id}; minutes=${2:?minutes}; jobs=${3:-6}
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .carry/wheels/*.whl || exit 3
export PYTHONPATH=/tmp/site:$PWD/src PYTHONUNBUFFERED=1
mkdir -p ../shared/data
python3 benchmarks/device_payload.py --unpack .carry --to ../shared/data || exit 4   # every file, SHA-256 checked
nvidia-smi -L
python3 -c "import torch, lightning; print('torch', torch.__version__, 'lightning', lightning.__version__, 'cuda', torch.cuda.is_available())"
results=$PWD/.gpu-results; rm -rf "$results"; mkdir -p "$results"
[ -d "docs/results/converge/$job" ] && cp -r "docs/results/converge/$job" "$results/"   # restores finished rows
timeout $((minutes * 60 + 90)) python3 benchmarks/train_queue.py run --only "$job" --max-minutes "$minutes" \
    --jobs "$jobs" --runs "$PWD/.gpu-runs" --results "$results" > "$OUT/log.txt" 2>&1
echo "queue exit status $? (1: stopped at the limit, resumes)"
nvidia-smi --query-gpu=memory.used,memory.total,utilization.gpu --format=csv
grep -E "^queue|Traceback|Error" "$OUT/log.txt" | tail -30
tar czf "$OUT/results.tgz" -C "$results" --exclude='*.ckpt' "$job" && ls -la "$OUT"
