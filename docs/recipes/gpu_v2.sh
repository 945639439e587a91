# One lent GPU session (30 minutes of device time, calls of at most 10 minutes, 64 MiB carried per call) spent on
# training `small` normal and BRDF from the bundled weights on data v2, validated every minute, returned as fp16.
# See docs/synth.md ("Data v2 on a lent GPU") for the plan and its arithmetic. Every call runs this script once:
#
#   bash docs/recipes/gpu_v2.sh CALL SECONDS PACK...      # on the device machine, from the repository root
#
# CALL 1 starts both runs (from networks/weights/*_small.safetensors; the BRDF run with the loss
# `--brdf-weights 1,2,2 --brdf-loss-before-relu`); a later CALL unpacks its packs while the runs go on, then
# restarts them with --resume on the grown data (the machine's disk lives as long as it is held: make each call
# right after the previous one returns). The runs are detached (setsid) and keep training between calls, so no
# call is idle; at SECONDS every call exports best/last of both runs as fp16 safetensors into $OUT (LAST=1 on the
# final call stops the runs first, so its weights are the final checkpoint's). A pack named val.npz becomes the
# validation set (carry it in call 1); the others are training data.
#
# Optional, untested on the device so far: RENDER_JOBS=N also renders more data v2 blocks on the machine's CPU
# cores in the background (docs/recipes/make_pool.py; needs Mitsuba there: carry a wheel folder named .mitsuba),
# and every later call adds the blocks finished by then. MATCAP_MITSUBA_VARIANT picks the variant (cuda_ad_rgb
# is tried first when unset, then scalar_rgb).
#
# DRY_RUN=1: the same steps on this CPU with tiny settings (3 steps per run, batch 1, K 3): tests/test_synth_recipe.py.
set -u
call=$1; secs=$2; shift 2
export PYTHONUNBUFFERED=1
T0=$(date +%s)
D=${DATA_DIR:-/tmp/d}
R=${RUNS_DIR:-/tmp}
OUTDIR=${OUT:-/tmp/gpu_v2_out}
mkdir -p "$D/train" "$D/val" "$OUTDIR"
PY=${PYTHON:-python3}
if [ "${DRY_RUN:-0}" = 1 ]; then
  RUN="--device cpu --threads 2 --workers 0 --resolution 128 --batch 1 --max-images 3 --pixel-samples 64 --steps 3"
  RUN="$RUN --val-scenes 1 --val-every-s 3600 --checkpoint-every-s 3600 --log-every 1"  # validated at the end
  MARGIN=0
else
  RUN="--device cuda --bf16 --workers ${WORKERS:-7} --resolution 128 --batch ${BATCH:-16} --pixel-samples 2048"
  RUN="$RUN --steps 200000 --val-scenes ${VAL_SCENES:-48} --val-every-s 60 --checkpoint-every-s 60"
  MARGIN=${MARGIN:-40}  # seconds kept for the fp16 export and the transfer back
fi
COMMON="--preset small --canonical-resolution 128 --dropout 0 --min-images 3 --max-images 6 --quiet $RUN"
NARGS="--target normal --lr ${LR_N:-2.5e-4} --warmup-steps 100 --decay-every ${DECAY:-2500} --decay-factor 0.7"
BARGS="--target brdf --lr ${LR_B:-2.5e-4} --warmup-steps 100 --decay-every ${DECAY:-2500} --decay-factor 0.7"
BARGS="$BARGS ${BRDF_LOSS:---brdf-weights 1,2,2 --brdf-loss-before-relu}"
INIT_N=${INIT_N:-networks/weights/normal_small.safetensors}
INIT_B=${INIT_B:-networks/weights/brdf_small.safetensors}

echo "gpu_v2 call $call on $(hostname): $(nvidia-smi -L 2>/dev/null | head -n 1)"
$PY -c "import torch, numpy; print('torch', torch.__version__, 'numpy', numpy.__version__, 'cuda', torch.cuda.is_available())"

unpack() {  # unpack each pack once (a marker per pack); val.npz into the validation set
  for p in "$@"; do
    name=$(basename "$p" .npz)
    [ -f "$D/.unpacked_$name" ] && continue
    if [ "$name" = val ]; then dest=$D/val; else dest=$D/train; fi
    $PY -m networks.datapack unpack "$p" --out "$dest" || { echo "gpu_v2: cannot unpack $p"; exit 2; }
    touch "$D/.unpacked_$name"
  done
}

stop_runs() {  # SIGTERM: each run finishes its step and writes its checkpoint; wait for both (by their pids)
  for r in n b; do [ -f "$R/run_$r.pid" ] && kill -TERM "$(cat "$R/run_$r.pid")" 2>/dev/null; done
  for r in n b; do
    if [ -f "$R/run_$r.pid" ]; then
      pid=$(cat "$R/run_$r.pid")
      while kill -0 "$pid" 2>/dev/null; do sleep 1; done
      rm -f "$R/run_$r.pid"
    fi
  done
}

start_run() {  # start_run n|b ARGS INIT: fresh from INIT, or --resume where a checkpoint exists
  r=$1; args=$2; init=$3
  if [ -f "$R/run_$r/checkpoint.pt" ]; then from="--resume"; else from="--init $init"; fi
  if [ "${DRY_RUN:-0}" = 1 ]; then
    $PY -m networks.train --data "$D/train" --val-data "$D/val" $COMMON $args --out "$R/run_$r" $from \
      >> "$R/run_$r.out" 2>&1 < /dev/null &
  else
    setsid nohup $PY -m networks.train --data "$D/train" --val-data "$D/val" $COMMON $args --out "$R/run_$r" $from \
      >> "$R/run_$r.out" 2>&1 < /dev/null &
  fi
  echo $! > "$R/run_$r.pid"
}

render_blocks() {  # optional: data v2 blocks rendered here in the background (RENDER_JOBS=N)
  [ -n "${RENDER_JOBS:-}" ] || return 0
  if [ -d .mitsuba ] && ! $PY -c "import mitsuba" 2>/dev/null; then
    $PY -m pip install -q --no-index --no-deps --target /tmp/site .mitsuba/*.whl && export PYTHONPATH=/tmp/site:${PYTHONPATH:-}
  fi
  $PY -c "import mitsuba" 2>/dev/null || { echo "no Mitsuba here: not rendering"; return 0; }
  if [ -z "${MATCAP_MITSUBA_VARIANT:-}" ]; then
    if $PY -c "import mitsuba as mi; mi.set_variant('cuda_ad_rgb'); mi.render(mi.load_dict({'type': 'scene', 'e': {'type': 'constant'}, 's': {'type': 'sphere'}, 'c': {'type': 'orthographic', 'film': {'type': 'hdrfilm', 'width': 8, 'height': 8}}}), spp=1)" >/dev/null 2>&1; then
      export MATCAP_MITSUBA_VARIANT=cuda_ad_rgb
    else
      export MATCAP_MITSUBA_VARIANT=scalar_rgb
    fi
  fi
  if [ ! -f "$R/render.pid" ] || ! kill -0 "$(cat "$R/render.pid")" 2>/dev/null; then
    threads=1; [ "$MATCAP_MITSUBA_VARIANT" = cuda_ad_rgb ] && threads=0
    echo "rendering blocks ${RENDER_BLOCKS:-100:140} with $RENDER_JOBS jobs ($MATCAP_MITSUBA_VARIANT)"
    setsid nohup nice -n 10 $PY docs/recipes/make_pool.py --out "$R/pool" --val 0 --blocks "${RENDER_BLOCKS:-100:140}" \
      --block "${RENDER_BLOCK:-50}" --jobs "$RENDER_JOBS" --threads $threads ${ASSETS:+--assets $ASSETS} \
      >> "$R/render.out" 2>&1 < /dev/null &
    echo $! > "$R/render.pid"
  fi
}

unpack "$@"
[ -d "$R/pool/packs" ] && unpack "$R"/pool/packs/train_*.npz
echo "training scenes: $(ls "$D/train" | wc -l), validation scenes: $(ls "$D/val" | wc -l)"
[ -n "$(ls "$D/train")" ] || { echo "gpu_v2: no training scenes (carry packs)"; exit 2; }
stop_runs
start_run n "$NARGS" "$INIT_N"
start_run b "$BARGS" "$INIT_B"
render_blocks

while [ $(( $(date +%s) - T0 )) -lt $(( secs - MARGIN )) ]; do
  sleep "${POLL_S:-30}"
  alive=0
  for r in n b; do kill -0 "$(cat "$R/run_$r.pid" 2>/dev/null)" 2>/dev/null && alive=1; done
  [ $alive = 1 ] || { echo "both runs have exited"; break; }
  echo "--- $(( $(date +%s) - T0 )) s"; tail -n 1 "$R/run_n/train.log" "$R/run_b/train.log" 2>/dev/null | cut -c1-200
done
if [ "${LAST:-0}" = 1 ] || [ "${DRY_RUN:-0}" = 1 ]; then stop_runs; fi
grep -h "event=val" "$R/run_n/train.log" 2>/dev/null | tail -n 5 | cut -c1-200
grep -h "event=val" "$R/run_b/train.log" 2>/dev/null | tail -n 5 | sed 's/mae_[a-z+]*=[0-9.]* //g' | cut -c1-300
nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv 2>/dev/null
tail -n 3 "$R/run_n.out" "$R/run_b.out"
[ -f "$R/render.out" ] && tail -n 3 "$R/render.out"
for r in n b; do
  for w in best last; do
    [ -f "$R/run_$r/$w.safetensors" ] && $PY docs/recipes/export_fp16.py "$R/run_$r/$w.safetensors" "$OUTDIR/${r}_$w.safetensors"
  done
  cp "$R/run_$r/log.jsonl" "$OUTDIR/${r}_log.jsonl" 2>/dev/null
done
ls -la "$OUTDIR"
echo "call $call done in $(( $(date +%s) - T0 )) s"
ls "$OUTDIR"/n_last.safetensors "$OUTDIR"/b_last.safetensors > /dev/null 2>&1 || { echo "gpu_v2: no weights to return (see $R/run_*.out)"; exit 1; }
exit 0
