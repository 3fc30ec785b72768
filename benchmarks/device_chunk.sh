#!/bin/bash
# One resumable chunk of a training-queue job on a lent GPU machine (the `device` tool), from the repository root:
#   bash benchmarks/device_chunk.sh <job id[,job id...]> <minutes> [runs at once, default 6]   # carry: .carry
#   bash benchmarks/device_chunk.sh "<ids>@<runs at once>+<ids>@<runs at once>" <minutes>      # groups at once
# Installs the carried wheels; restores the carried data (`device_payload.py --unpack`: every file, SHA-256 checked)
# where `--root ../shared/data/<name>` resolves to the same path as on the developer machine (the rows' keys hold the
# resolved path; the device's checkout is /work/main too); runs `train_queue.py run --only <jobs> --max-minutes
# <minutes> --jobs <n>` (the jobs in the order given, the minutes shared; an `lcreg reproduce` or `learning_curves.py`
# job trains n runs at once, each in its own process: one run of 256 points x 8 leaves an H100 mostly idle) with its
# runs in .gpu-runs/ (git-ignored, so a second call on the still-warm machine resumes a cut-off run from its
# last.ckpt). Groups joined by '+' run at the same time, each its own queue process with the whole <minutes> and its
# own runs at once ('@n'; default the third argument), so that jobs that leave the GPU idle share it (session 19:
# PRNet alone and the DVDs ablation beside it); each group's log is $OUT/log-<k>.txt and nvidia-smi samples the
# GPU's use every 30 s into $OUT/gpu.csv. Then packs the jobs' small result files (`sync`: JSONL rows, metrics.csv, hparams, reports, `best/`
# weights; no checkpoints) into $OUT/results.tgz.
# Merge here with: tar xzf <files_at>/results.tgz -C docs/results/converge
set -u
groups=${1:?job ids, comma-separated; groups joined by +}; minutes=${2:?minutes}; jobs=${3:-6}
python=${PYTHON:-python3}
shopt -s nullglob; wheels=(.carry/wheels/*.whl); shopt -u nullglob
if [ ${#wheels[@]} -gt 0 ]; then
    $python -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "${wheels[@]}" || exit 3
fi
export PYTHONPATH=/tmp/site:$PWD/src PYTHONUNBUFFERED=1
mkdir -p ../shared/data
$python benchmarks/device_payload.py --unpack .carry --to ../shared/data || exit 4   # every file, SHA-256 checked
if command -v nvidia-smi > /dev/null; then
    nvidia-smi -L
    nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv -l 30 > "$OUT/gpu.csv" &
    sampler=$!
fi
$python -c "import torch, lightning; print('torch', torch.__version__, 'lightning', lightning.__version__, 'cuda', torch.cuda.is_available())"
results=$PWD/.gpu-results; rm -rf "$results"; mkdir -p "$results"
all=""; k=0; pids=()
IFS='+' read -ra parts <<< "$groups"
for part in "${parts[@]}"; do
    k=$((k + 1)); ids=${part%@*}; ids=${ids//,/ }; n=$jobs
    [[ $part == *@* ]] && n=${part##*@}
    all="$all $ids"
    for job in $ids; do   # restores finished rows
        [ -d "docs/results/converge/$job" ] && cp -r "docs/results/converge/$job" "$results/"
    done
    # in this group's order; --max-minutes is the time of the group's jobs together (train_queue.py)
    # shellcheck disable=SC2086  # $ids: one word per job
    (timeout $((minutes * 60 + 90)) $python benchmarks/train_queue.py run --only $ids --max-minutes "$minutes" \
        --jobs "$n" --runs "$PWD/.gpu-runs" --results "$results" > "$OUT/log-$k.txt" 2>&1
     echo "group $k ($ids, $n at once): queue exit status $? (1: stopped at the limit, resumes)") &
    pids+=($!)
done
wait "${pids[@]}"
[ -n "${sampler:-}" ] && kill "$sampler" && nvidia-smi --query-gpu=memory.used,memory.total,utilization.gpu --format=csv
grep -hE "^queue|Traceback|Error" "$OUT"/log-*.txt | tail -30
packed=$(cd "$results" && for job in $all; do [ -d "$job" ] && echo "$job"; done)
# shellcheck disable=SC2086
tar czf "$OUT/results.tgz" -C "$results" --exclude='*.ckpt' $packed && ls -la "$OUT"
