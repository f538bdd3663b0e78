#!/usr/bin/env bash
# The third GPU call of issue 23: four fine-tunes of the then-shipped small model (the CPU
# five-family one; aligned-nrmsd2 became the shipped model) share the GPU for the
# same wall time on a five-family store generated there, to separate what aligned inputs and the
# NRMSD loss term each buy at ~5x the CPU fine-tunes' budget:
#   aligned-nrmsd  --inputs aligned, loss + nrmsd=NRMSD_W
#   raw-nrmsd      raw inputs (the shipped model's), loss + nrmsd=NRMSD_W
#   aligned        --inputs aligned, the shipped loss (the control)
#   aligned-nrmsd2 --inputs aligned, loss + nrmsd=2*NRMSD_W
# The checkpoints (ship/NAME.safetensors with its card NAME.json) come back and are scored here,
# on the held-out test runs of the CPU's store (a different seed: none of its worlds is in this
# store), with bench/bench_families.py.
#
#   bash bench/gpu_nrmsd.sh                         # on the GPU machine, from the repository root
#   LOCAL=1 DEVICE=cpu WORLDS=lab:1,rooms:1 GEN_MINUTES=1 STEPS=3 BATCH=4 N_VAL=8 BUDGET=300 \
#     OUT=/tmp/gpu-out bash bench/gpu_nrmsd.sh     # a dry run of every stage here
set -u
BUDGET=${BUDGET:-540}
STEPS=${STEPS:-1000}  # the cosine schedule's length; --max-minutes stops it sooner if the GPU is slower
NRMSD_W=${NRMSD_W:-0.5}
RUNS=(aligned-nrmsd raw-nrmsd aligned aligned-nrmsd2)
source "$(dirname "$0")/gpu_lib.sh"
trap 'for m in "${RUNS[@]}"; do cp "$W/$m/model.json" "$W/ship/$m.json"; \
  cp "$W/$m/metrics.jsonl" "$R/$m-metrics.jsonl"; cp "$W/$m/model.safetensors" "$W/ship/$m.safetensors"; \
  done 2>/dev/null; pack_results gpu-nrmsd' EXIT
log "machine: $(grep -m1 -E 'H200|H100|Model name' "$R/machine.txt")"

$SS generate "$W/multi.zarr" --world "$WORLDS" --minutes "$GEN_MINUTES" --test-runs 1 --seed "$SEED" \
  --workers "$WORKERS" > "$R/generate.log" 2>&1
log "generate: $(grep -E 'wrote|error' "$R/generate.log" | tr '\n' ' ')"
grep -q wrote "$R/generate.log" || exit 1

train_s=$(( $(left) - 25 ))
minutes=$(python3 -c "print(round(($train_s - 30) / 60, 2))")
log "train: four fine-tunes, $STEPS cosine steps or $minutes min"
base=cc=1,w1=100,energy=2
common=(--preset small --init pretrained --prior flow --batch-size "$BATCH" --optimizer adamw --lr 1e-4
        --schedule cosine --curriculum 10 --context-noise 0.01 --val-horizon 10 --n-val "$N_VAL"
        --eval-every $(( STEPS / 10 > 1 ? STEPS / 10 : 1 )) --max-steps "$STEPS" --max-minutes "$minutes"
        --test-samples 0 --seed 4 --device "$DEVICE" --precision auto)
export OMP_NUM_THREADS=3 MKL_NUM_THREADS=3 NUMBA_NUM_THREADS=3
run() {  # name, inputs, loss
  timeout "$train_s" $SS train "$W/multi.zarr" --out "$W/$1" --inputs "$2" --loss "$3" "${common[@]}" \
    > "$R/train-$1.log" 2>&1
}
run aligned-nrmsd aligned "$base,nrmsd=$NRMSD_W" &
run raw-nrmsd raw "$base,nrmsd=$NRMSD_W" &
run aligned aligned "$base" &
run aligned-nrmsd2 aligned "$base,nrmsd=$(python3 -c "print(2 * $NRMSD_W)")" &
wait
for m in "${RUNS[@]}"; do log "train $m: $(tail -c 250 "$R/train-$m.log" | tr '\n' ' ')"; done
log "end, $(left) s of the budget left"
