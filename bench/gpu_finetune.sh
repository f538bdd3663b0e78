#!/usr/bin/env bash
# The second GPU call of issues 22/23 (after bench/gpu_paper.sh): on the same five-family store
# (same seed, so the same test runs), two trainings share the GPU for TRAIN_MIN minutes: the shipped
# small model fine-tuned (k = 10 rollouts, batch 64) and the paper preset continued from
# gpu_paper.sh's checkpoint (PAPER_INIT); then both are scored beside the shipped model and flow on
# every family's test run and on the demo's fresh lab run. Results come back as gpu-paper.sh's do.
#
#   PAPER_INIT=.gpu/paper1/model.safetensors bash bench/gpu_finetune.sh
set -u
BUDGET=${BUDGET:-360}
SAMPLES=${SAMPLES:-1000}
DEMO_MINUTES=${DEMO_MINUTES:-25}
EVAL_S=${EVAL_S:-80}
PAPER_INIT=$(realpath "${PAPER_INIT:-.gpu/paper1/model.safetensors}")
source "$(dirname "$0")/gpu_lib.sh"
pack() {
  for m in small paper; do
    cp "$W/$m/model.json" "$R/$m-model.json" 2>/dev/null; cp "$W/$m/metrics.jsonl" "$R/$m-metrics.jsonl" 2>/dev/null
    cp "$W/$m/model.safetensors" "$W/ship/$m.safetensors" 2>/dev/null
  done
  pack_results gpu-ft
}
trap pack EXIT
$SS generate "$W/multi.zarr" --world "$WORLDS" --minutes "$GEN_MINUTES" --test-runs 1 --seed "$SEED" \
  --workers "$WORKERS" > "$R/generate.log" 2>&1
log "generate: $(grep -E 'wrote|error' "$R/generate.log" | tr '\n' ' ')"
grep -q wrote "$R/generate.log" || exit 1
train_s=$(( $(left) - EVAL_S - 20 ))
minutes=$(python3 -c "print(round(($train_s - 40) / 60, 2))")
log "train: both for $minutes min"
common=(--prior flow --batch-size "$BATCH" --optimizer adamw --lr 1e-4 --curriculum 10 --loss cc=1,w1=100,energy=2
        --context-noise 0.01 --val-horizon 10 --n-val "$N_VAL" --max-minutes "$minutes" --test-samples 0 --seed 1
        --device "$DEVICE" --precision auto)
timeout "$train_s" $SS train "$W/multi.zarr" --preset small --init pretrained --out "$W/small" --eval-every 100 \
  "${common[@]}" > "$R/train-small.log" 2>&1 &
timeout "$train_s" $SS train "$W/multi.zarr" --preset paper --init "$PAPER_INIT" --out "$W/paper" --eval-every 40 \
  "${common[@]}" > "$R/train-paper.log" 2>&1 &
wait
for m in small paper; do log "train $m: $(tail -c 300 "$R/train-$m.log" | tr '\n' ' ')"; done
ev=$(( $(left) - 15 ))
export OMP_NUM_THREADS=2 NUMBA_NUM_THREADS=2 MKL_NUM_THREADS=2
models=echopt:pretrained
for m in small paper; do [ -f "$W/$m/model.safetensors" ] && models="$models,echopt:$W/$m/model.safetensors"; done
for fam in $(echo "$WORLDS" | tr ',' '\n' | cut -d: -f1); do
  timeout "$ev" python3 "$REPO/bench/bench_families.py" "$W/multi.zarr" --families "$fam" --models "$models" \
    --samples "$SAMPLES" --out "$R/families-$fam" --device "$DEVICE" > "$R/families-$fam.txt" 2>&1 &
done
for m in small paper; do
  [ -f "$W/$m/model.safetensors" ] && timeout "$ev" $SS demo --out "$W/demo-$m" --model "$W/$m/model.safetensors" \
    --minutes "$DEMO_MINUTES" --samples "$SAMPLES" --device "$DEVICE" > "$R/demo-$m.txt" 2>&1 &
done
wait
log "end, $(left) s of the budget left"
