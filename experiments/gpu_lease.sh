#!/usr/bin/env bash
# One training run sized to one short GPU lease (#48). Usage on the device, from the repo root, with the
# wheels meshseal needs there in .whl/ (pytorch-msssim alone, on the H200 image of 2026-11) and gpu_data/
# (python experiments/gpu_data.py) carried:
#   bash experiments/gpu_lease.sh END_SECONDS CONFIG [RUN]
# It times the networks in NCHW and NHWC order (benchmarks/train_networks.py), bakes the views (into
# gpu_data/gbuffers), runs the config 20 s to measure the step rate (and the batch-norm measurement on a few rendered
# pictures that follows training, `bn_renders`, so that its time is kept), sizes its schedule to end about END_SECONDS after the script started
# (experiments/lease_config.py), trains into runs/RUN and leaves runs/RUN as $OUT/RUN.tar with the logs.
# A second call on the warm machine reuses the timing and the rate; it must carry gpu_data again (an ignored
# path that a call does not carry is gone there; the run bakes its views again) and the run it continues
# (runs/NAME, for init_from), extracted here from the first call's tar.
# Then, here: meshseal eval --data data --model runs/RUN/model.safetensors --protocol seed
set -u
end=$1 config=$2 name=${3:-$(basename "$2" .yaml)}
device=${DEVICE:-cuda} data=${DATA:-gpu_data} OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
if [ -d .whl ] && ! python3 -c "import pytorch_msssim" 2>/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
fi
export PYTHONPATH=/tmp/site:$PWD/src PYTHONUNBUFFERED=1
[ "$device" = cuda ] && nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
meshseal() { python3 -c "import sys; from meshseal.cli import main; sys.exit(main())" "$@"; }
quiet() { tr '\r' '\n' | grep -v "baking\|it/s\|step/s\|steps/s]"; }
again=""; [ -f /tmp/bench.txt ] && [ -f /tmp/calib/log.csv ] && again=1  # a second call on the same machine
[ -z "$again" ] && { python3 benchmarks/train_networks.py --config "$config" --device "$device" --steps ${BENCH_STEPS:-30} > /tmp/bench.txt 2>&1; }
# The bake: one step of the config with no batch-norm measurement after it (lease_config --bn-renders 0).
[ -z "$again" ] && { python3 experiments/lease_config.py "$config" --calibration --bn-renders 0 --out /tmp/bake.yaml
  meshseal train --config /tmp/bake.yaml --data "$data" --out /tmp/bake --device "$device" --time-limit 0 2>&1 | quiet | tail -n 2; }
echo "[$SECONDS s] views baked"
cat /tmp/bench.txt; cp /tmp/bench.txt "$OUT/bench.txt"
ratio=$(sed -n 's/.*nhwc_over_nchw=\([0-9.]*\).*/\1/p' /tmp/bench.txt)
last=""; python3 -c "import sys; sys.exit(0 if float('${ratio:-0}') > 1.05 else 1)" && last="--channels-last"
python3 experiments/lease_config.py "$config" --calibration $last --out /tmp/calib.yaml
# The calibration also times the batch-norm measurement on a few rendered pictures (its output kept).
[ -z "$again" ] && meshseal train --config /tmp/calib.yaml --data "$data" --out /tmp/calib --device "$device" --time-limit ${CALIBRATE_MINUTES:-0.33} 2>&1 | quiet > /tmp/calib.out
tail -n 2 /tmp/calib.out
left=$(( end - SECONDS - ${RESERVE_S:-25} ))
echo "[$SECONDS s] calibrated; $left s left"
python3 experiments/lease_config.py "$config" --log /tmp/calib/log.csv --seconds $left $last --bn-from /tmp/calib.out \
  --out /tmp/lease.yaml > /tmp/lease.txt || exit 1
cat /tmp/lease.txt
train_s=$(sed -n 's/^train_seconds=\([0-9]*\)$/\1/p' /tmp/lease.txt)
meshseal train --config /tmp/lease.yaml --data "$data" --out "runs/$name" --device "$device" ${RESUME:-} \
  --time-limit $(python3 -c "print((${train_s:-$left} + 5) / 60)") 2>&1 | quiet > "$OUT/$name.log"
tail -n 3 "$OUT/$name.log"; cat "runs/$name/val.csv"
cp /tmp/lease.yaml "runs/$name/lease.yaml"
tar -C runs -cf "$OUT/$name.tar" "$name"
echo "[$SECONDS s] done"
[ "$device" = cuda ] && nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader
exit 0
