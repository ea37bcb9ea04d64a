#!/usr/bin/env bash
# Table 6 (texture only, 8 bits) on a lent GPU: several variants of configs/blind8_gbuffer.yaml trained side
# by side on one card (each process is host-bound, so they share it well), from gpu_data/ (a dataset folder:
# meshes, textures, manifest). Usage on the device, from the repo root, with the wheels meshseal needs in
# .whl/: bash experiments/gpu_table6.sh MINUTES CONFIG... ; each run's model, checkpoint, logs and summary
# land in $OUT/NAME.tar (the checkpoint lets the next lease go on with --resume). Then, here:
# meshseal eval --data data --model runs/NAME/model.safetensors --protocol seed
set -u
minutes=$1; shift
device=${DEVICE:-cuda}
if [ "$device" = cuda ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
  nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
fi
export PYTHONPATH=/tmp/site:$PWD/src PYTHONUNBUFFERED=1
meshseal() { python3 -c "import sys; from meshseal.cli import main; sys.exit(main())" "$@"; }
first=$1
# bake the shared view banks once, before the runs start side by side
start=$SECONDS
meshseal train --config "$first" --data "${DATA:-gpu_data}" --out /tmp/bake --device $device --time-limit 0 2>&1 | tr '\r' '\n' | grep -v "baking\|it/s\|step/s" | tail -n 3
echo "views baked in $((SECONDS - start)) s"
for config in "$@"; do
  name=$(basename "$config" .yaml)
  (meshseal train --config "$config" --data "${DATA:-gpu_data}" --out "/tmp/runs/$name" --device $device --time-limit "$minutes" 2>&1 \
     | tr '\r' '\n' | grep -v "step/s" > "/tmp/$name.log"; \
   tar -C /tmp/runs -cf "$OUT/$name.tar" "$name"; cp "/tmp/$name.log" "$OUT/$name.log" 2>/dev/null) &
done
wait
for config in "$@"; do name=$(basename "$config" .yaml); echo "== $name"; cat "/tmp/runs/$name/val.csv"; tail -n 1 "/tmp/$name.log"; done
[ "$device" = cuda ] && nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader
