#!/usr/bin/env bash
# Train the pose network of all four YCB objects at once, one `evtrack train` process per
# object sharing one GPU (the small networks leave a GPU mostly idle; the CPU cores that render
# and augment the data are the limit, so the script splits them between the four runs).
#
# Usage (from the repository root, after ./scripts/install.sh):
#   scripts/train_ycb_parallel.sh                      # all cores, 2 h of training each
#   CORES=8 MAX_TIME=00:01:00:00 scripts/train_ycb_parallel.sh --set data.train_samples=4096
#   (the cache holds ~0.9 MB per 640x480 sample: 4096 renders are ~3.7 GB per object)
#
# Environment:
#   CORES      CPU cores to use in all (default: nproc); each run gets CORES / (number of
#              configs), split into render processes (first) and loader workers (then)
#   MAX_TIME   training time of each run, Lightning's DD:HH:MM:SS (default 00:02:00:00); the
#              learning rate follows it (optim.schedule_by: time), so a run of any budget
#              anneals to the end of its cosine; rendering the cache comes before and is not
#              counted
#   OBJECTS    which configs (default: configs/pose_ycb_*.yaml)
#   LOG_DIR    one log per object (default runs/pose/logs)
# Further arguments go to every `evtrack train` (e.g. --set data.train_samples=4096).
# Outputs: runs/pose/<object>_<model>/<object>_<model>.pt and .md (copy them into
# models/weights to ship them; `evtrack evaluate` finds them there or with --weights-dir).
# Exits non-zero if any run failed, after all have finished.
# Measured (2026-11-27, one H200 with 16 cores, CORES=15, the tomato soup can, the mustard
# bottle and the potted meat can): 112 s to render their 2048 + 128 samples each (the
# processes' start included), then ~8 steps of 32 per second per run (the loaders, not the
# GPU, are the limit); each network's model card (models/weights/<object>_dope_lite_small.md)
# has its runs and results.
set -euo pipefail

cores=${CORES:-$(nproc)}
max_time=${MAX_TIME:-00:02:00:00}
log_dir=${LOG_DIR:-runs/pose/logs}
read -r -a configs <<< "${OBJECTS:-$(ls configs/pose_ycb_*.yaml | tr '\n' ' ')}"
n=${#configs[@]}
per_run=$(( cores / n ))
if (( per_run < 1 )); then per_run=1; fi
workers=$(( per_run > 1 ? per_run - 1 : 0 ))   # one core stays with the training process

mkdir -p "$log_dir"
pids=()
for config in "${configs[@]}"; do
    name=$(basename "$config" .yaml)
    echo "[$(date +%T)] $name: $per_run cores, max_time $max_time, log $log_dir/$name.log"
    OMP_NUM_THREADS=1 evtrack train --config "$config" --quiet \
        --set data.render_workers="$per_run" --set data.num_workers="$workers" \
        --set trainer.max_time="\"$max_time\"" --set optim.schedule_by=time \
        "$@" > "$log_dir/$name.log" 2>&1 &
    pids+=($!)
done

status=0
for i in "${!pids[@]}"; do
    if wait "${pids[$i]}"; then
        echo "[$(date +%T)] $(basename "${configs[$i]}" .yaml): done"
    else
        echo "[$(date +%T)] $(basename "${configs[$i]}" .yaml): FAILED, see $log_dir" >&2
        tail -n 20 "$log_dir/$(basename "${configs[$i]}" .yaml).log" >&2
        status=1
    fi
done
exit $status
