# Shared by the bench/gpu_*.sh sessions (sourced, not run): their common settings (each may be set
# in the environment), the clock, the log, the install of the wheels an offline GPU image lacks,
# and the packing of what comes back. Each script sets BUDGET (seconds) before sourcing this file.
#
# Where the image lacks zarr/pydantic, .whl/ holds their wheels and sonarset's own
# (bash ../shared/tools/device-wheels.sh; pip wheel --no-deps -w .whl .). LOCAL=1 skips the install:
# a dry run of a script on this machine.
T0=$(date +%s)
OUT=${OUT:-/tmp/gpu-out}
W=/tmp/gpu-work
DEVICE=${DEVICE:-cuda}
# the five-family store every GPU session generates (the same seed: the same test runs)
WORLDS=${WORLDS:-lab:8,corridor:6,orchard:6,warehouse:6,rooms:6}
GEN_MINUTES=${GEN_MINUTES:-10}
SEED=${SEED:-2027}
BATCH=${BATCH:-64}
N_VAL=${N_VAL:-512}
REPO=$(pwd)
R=$OUT/r
rm -rf "$W" && mkdir -p "$W" "$R" "$W/ship"
log() { echo "[$(( $(date +%s) - T0 )) s] $*" | tee -a "$R/session.log"; }
left() { echo $(( BUDGET - ($(date +%s) - T0) )); }

# Everything under $R and the checkpoints copied into $W/ship come back as split pieces of one
# tarball (the device returns files of 16 MiB at most): cat $OUT/NAME.tgz.part-* | tar xzf -
pack_results() {
  tar czf - -C "$OUT" r -C "$W" ship | split -b 15m - "$OUT/$1.tgz.part-"
  rm -rf "$R"
  ls -la "$OUT"
}

if [ -z "${LOCAL:-}" ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/site "$REPO"/.whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site
fi
# Run from the work folder, not the repository root: the root's sonarset/ lacks models/ and cli/,
# which the wheel installs inside it.
cd "$W"
SS="python3 -m sonarset.cli"
WORKERS=$(( $(nproc) > 4 ? $(nproc) - 2 : 2 ))
{ nvidia-smi; python3 -c "import torch, sonarset; print('torch', torch.__version__, 'sonarset', sonarset.__file__)"; \
  lscpu | head -20; } > "$R/machine.txt" 2>&1
