#!/bin/bash
# One resumable chunk of a training-queue job on a lent GPU machine (the `device` tool), from the repository root:
#   bash benchmarks/device_chunk.sh <job id[,job id...]> <minutes> [runs at once, default 6]   # carry: .carry
# Installs the carried wheels; restores the carried data (`device_payload.py --unpack`: every file, SHA-256 checked)
# where `--root ../shared/data/<name>` resolves to the same path as on the developer machine (the rows' keys hold the
# resolved path; the device's checkout is /work/main too); runs `train_queue.py run --only <jobs> --max-minutes
# <minutes> --jobs <n>` (the jobs in the order given, the minutes shared; an `lcreg reproduce` or `learning_curves.py`
# job trains n runs at once, each in its own process: one run of 256 points x 8 leaves an H100 mostly idle) with its
# runs in .gpu-runs/ (git-ignored, so a second call on the still-warm machine resumes a cut-off run from its
# last.ckpt); then packs the jobs' small result files (`sync`: JSONL rows, metrics.csv, hparams, reports, `best/`
# weights; no checkpoints) into $OUT/results.tgz and the log into $OUT/log.txt.
# Merge here with: tar xzf <files_at>/results.tgz -C docs/results/converge
set -u
ids=${1:?job ids, comma-separated}; minutes=${2:?minutes}; jobs=${3:-6}
ids=${ids//,/ }   # run in this order; --max-minutes is the time of them all (train_queue.py)
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .carry/wheels/*.whl || exit 3
export PYTHONPATH=/tmp/site:$PWD/src PYTHONUNBUFFERED=1
mkdir -p ../shared/data
python3 benchmarks/device_payload.py --unpack .carry --to ../shared/data || exit 4   # every file, SHA-256 checked
nvidia-smi -L
python3 -c "import torch, lightning; print('torch', torch.__version__, 'lightning', lightning.__version__, 'cuda', torch.cuda.is_available())"
results=$PWD/.gpu-results; rm -rf "$results"; mkdir -p "$results"
for job in $ids; do   # restores finished rows
    [ -d "docs/results/converge/$job" ] && cp -r "docs/results/converge/$job" "$results/"
done
# shellcheck disable=SC2086  # $ids: one word per job
timeout $((minutes * 60 + 90)) python3 benchmarks/train_queue.py run --only $ids --max-minutes "$minutes" \
    --jobs "$jobs" --runs "$PWD/.gpu-runs" --results "$results" > "$OUT/log.txt" 2>&1
echo "queue exit status $? (1: stopped at the limit, resumes)"
nvidia-smi --query-gpu=memory.used,memory.total,utilization.gpu --format=csv
grep -E "^queue|Traceback|Error" "$OUT/log.txt" | tail -30
packed=$(cd "$results" && for job in $ids; do [ -d "$job" ] && echo "$job"; done)
# shellcheck disable=SC2086
tar czf "$OUT/results.tgz" -C "$results" --exclude='*.ckpt' $packed && ls -la "$OUT"
