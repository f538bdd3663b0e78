#!/usr/bin/env bash
# One GPU session, end to end (issues 22 and 23): the paper preset's training throughput (fp32, bf16,
# bf16 + compile), a five-family store generated on the machine's cores, the paper preset trained on
# it in bf16, and the trained model scored beside the shipped small model and flow on every family's
# held-out test run and on the demo's fresh lab run. Everything it measures comes back in $OUT as
# split pieces of one tarball: cat $OUT/gpu-paper.tgz.part-* | tar xzf -
#
#   bash bench/gpu_paper.sh                       # on a GPU machine, from the repository root
#   LOCAL=1 DEVICE=cpu WORLDS=lab:1,rooms:1 GEN_MINUTES=1 MAX_STEPS=4 BATCH=8 N_VAL=32 SAMPLES=20 \
#     DEMO_MINUTES=1 BUDGET=400 OUT=/tmp/gpu-out bash bench/gpu_paper.sh   # a dry run of every stage here
#
# The wheels it installs: bench/gpu_lib.sh. Every stage has a deadline
# inside BUDGET seconds, so the tarball is written whatever a stage does.
set -u
BUDGET=${BUDGET:-540}
PRESET=${PRESET:-paper}
SAMPLES=${SAMPLES:-1000}
DEMO_MINUTES=${DEMO_MINUTES:-25}
EVAL_S=${EVAL_S:-170}  # reserved for the evaluations at the end
LOSS=${LOSS:-cc=1,w1=100,energy=2,nrmsd_capped=2}
GEOMETRY=${GEOMETRY:-32}
source "$(dirname "$0")/gpu_lib.sh"
pack() {
  cp "$W"/paper/model.json "$W"/paper/metrics.jsonl "$R"/ 2>/dev/null
  cp "$W"/paper/model.safetensors "$W/ship/" 2>/dev/null
  pack_results gpu-paper
}
trap pack EXIT
log "machine: $(head -c 300 "$R/machine.txt" | tr '\n' ' ')"
python3 -c "import zarr, numba, sonarset.sim, sonarset.models.echopt.train" > "$R/imports.txt" 2>&1 \
  || { log "imports failed: $(tail -3 "$R/imports.txt")"; exit 1; }

# 1. the store, on all but two cores, while the GPU is benchmarked
( $SS generate "$W/multi.zarr" --world "$WORLDS" --minutes "$GEN_MINUTES" --test-runs 1 \
    --seed "$SEED" --workers "$WORKERS" > "$R/generate.log" 2>&1 ) &
gen=$!
if [ "$DEVICE" = cuda ]; then
  timeout 150 python3 "$REPO/bench/bench_train.py" --presets "$PRESET" --devices cuda --cuda-batches "$BATCH" \
    > "$R/bench_train.txt" 2>&1
  log "bench_train: $(grep samples "$R/bench_train.txt" | tr '\n' ' ')"
fi
wait $gen
log "generate: $(grep -E 'wrote|error' "$R/generate.log" | tr '\n' ' ')"
grep -q wrote "$R/generate.log" || { log "no store: $(tail -5 "$R/generate.log")"; exit 1; }

# 2. training: steps sized from the measured bf16 rate so that the cosine schedule ends in the time left
#    (a k-step rollout costs ~k one-step passes; the curriculum averages k = 5.6), --max-minutes as a guard
train_s=$(( $(left) - EVAL_S - 30 ))
rate=$(grep -E "^$PRESET .*cuda" "$R/bench_train.txt" 2>/dev/null | sed -E 's/.*bf16 autocast: *([0-9]+).*/\1/' | head -1)
rate=${rate:-1000}
steps=${MAX_STEPS:-$(( rate * (train_s - 40) * 10 / (BATCH * 56 * 11 / 10) ))}
[ -z "${MAX_STEPS:-}" ] && [ "$steps" -lt 10 ] && steps=10
curriculum="0:2,$(( steps * 3 / 10 )):5,$(( steps * 7 / 10 )):10"
log "train: $train_s s, $steps steps at $rate samples/s measured, curriculum $curriculum"
# The shipped small model's recipe as BENCHMARKS.md measured it: the NRMSD term (its cells fail
# without it), inputs registered to the newest frame, the geometry branch trained with everything
# (no context noise: with it the branch learns to remove noise), harmonic step weights.
timeout "$train_s" $SS train "$W/multi.zarr" --preset "$PRESET" --prior flow --out "$W/paper" \
  --batch-size "$BATCH" --lr 2e-4 --optimizer adamw --schedule cosine --curriculum "$curriculum" \
  --loss "$LOSS" --inputs aligned --geometry-channels "$GEOMETRY" --step-weights harmonic \
  --context-noise 0 --val-horizon 10 --n-val "$N_VAL" \
  --eval-every $(( steps / 12 > 1 ? steps / 12 : 1 )) --max-steps "$steps" --max-minutes "$(( (train_s - 45) / 60 ))" \
  --test-samples 0 --seed 0 --device "$DEVICE" --precision auto > "$R/train.log" 2>&1
log "train exit $?: $(tail -c 400 "$R/train.log" | tr '\n' ' ')"

# 3. scores: flow, the shipped small model and the new one on every family's test run, and the demo
if [ -f "$W/paper/model.safetensors" ]; then
  ev=$(( $(left) - 25 ))
  export OMP_NUM_THREADS=2 NUMBA_NUM_THREADS=2 MKL_NUM_THREADS=2
  for fam in $(echo "$WORLDS" | tr ',' '\n' | cut -d: -f1); do
    timeout "$ev" python3 "$REPO/bench/bench_families.py" "$W/multi.zarr" --families "$fam" \
      --models echopt:pretrained,echopt:"$W/paper/model.safetensors" --samples "$SAMPLES" \
      --out "$R/families-$fam" --device "$DEVICE" > "$R/families-$fam.txt" 2>&1 &
  done
  timeout "$ev" $SS demo --out "$W/demo" --model "$W/paper/model.safetensors" --minutes "$DEMO_MINUTES" \
    --samples "$SAMPLES" --device "$DEVICE" > "$R/demo.txt" 2>&1 &
  wait
  cp "$W"/demo/report.md "$R/demo-report.md" 2>/dev/null; cp "$W"/demo/metrics.json "$R/demo-metrics.json" 2>/dev/null
  log "scores done"
fi
log "end, $(left) s of the budget left"
