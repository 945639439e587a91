# How the bundled normal_small and brdf_small models were trained on a lent GPU (one H100, 16 CPU cores, 3 calls of ~9 min).
# The GPU machine could take 64 MiB per upload and kept its disk only while it was in use, so the training data
# went up as networks.datapack packs, one per call, and each call resumed both runs on the grown dataset:
#
#   python -m networks.datapack pack data/val128 packs/val --max-mb 40                               # -> val.npz
#   python -m networks.datapack pack data/train128 packs/t0 --max-mb 41 --start 0 --count 165        # -> t0.npz
#   python -m networks.datapack pack data/train128 packs/t1 --max-mb 47.5 --start 165                # -> t1a/t1b/t1c.npz
#   bash gpu_session.sh 1 500 t0.npz t1c.npz                                                # call 1: 184 scenes
#   DECAY=2500 bash gpu_session.sh 2 530 t1a.npz                                            # call 2: 440 scenes
#   DECAY=2000 LR_N=2.5e-4 LR_B=2.5e-4 bash gpu_session.sh 3 470 t1b.npz                    # call 3: 695 scenes
#
# Next time: BRDF_LOSS="--brdf-weights 1,2,2 --brdf-loss-before-relu" INIT_B=networks/weights/brdf_small.safetensors
# (the BRDF loss before the ReLU reaches the metals), `pack --quality 95` (lossy WebP basis renders, 3.3x smaller: ~430 scenes per 29 MiB) and, from call 2
# on, the bundled weights moved out of the working tree (DEVELOPING.md) would carry several times more scenes.
#
# usage: bash gpu_session.sh PHASE SECONDS PACK... (PHASE 1 starts both runs, 2+ adds data and resumes them);
# the weights come back as fp16 safetensors in $OUT (export_fp16.py).
set -u
phase=$1; secs=$2; shift 2
export PYTHONUNBUFFERED=1
T0=$(date +%s)
D=/tmp/d
COMMON="--preset small --canonical-resolution 128 --dropout 0 --resolution 128 --min-images 3 --max-images 6 --val-data $D/val --val-scenes 24 --val-every-s ${VAL_S:-90} --checkpoint-every-s 60 --bf16 --device cuda --workers 7 --quiet --steps 200000"
NARGS="--target normal --batch ${BATCH:-16} --pixel-samples 2048 --lr ${LR_N:-4e-4} --warmup-steps 200 --decay-every ${DECAY:-3000} --decay-factor 0.7 --out /tmp/run_n"
BARGS="--target brdf --batch ${BATCH:-16} --pixel-samples 2048 --lr ${LR_B:-4e-4} --warmup-steps 200 --decay-every ${DECAY:-3000} --decay-factor 0.7 --out /tmp/run_b ${BRDF_LOSS:-}"
if [ "$phase" = 1 ] || [ ! -d /tmp/run_n ]; then
  echo "fresh machine: phase $phase"; nvidia-smi -L; python3 -c "import torch, cv2, safetensors, numpy; print(torch.__version__, numpy.__version__, torch.cuda.is_available())"
  python3 -m networks.datapack unpack val.npz --out $D/val
  python3 -m networks.datapack unpack "$@" --out $D/train
  INIT_N=${INIT_N:-networks/weights/normal_small.safetensors}; INIT_B=${INIT_B:-networks/weights/normal_small.safetensors}
  setsid nohup python3 -m networks.train --data $D/train $COMMON $NARGS --init $INIT_N > /tmp/run_n.out 2>&1 < /dev/null &
  setsid nohup python3 -m networks.train --data $D/train $COMMON $BARGS --init $INIT_B > /tmp/run_b.out 2>&1 < /dev/null &
else
  python3 -m networks.datapack unpack "$@" --out $D/train
  pkill -TERM -f "networks.train"; while pgrep -f "networks.train" > /dev/null; do sleep 1; done
  tail -n 2 /tmp/run_n.out /tmp/run_b.out
  setsid nohup python3 -m networks.train --data $D/train $COMMON $NARGS --resume >> /tmp/run_n.out 2>&1 < /dev/null &
  setsid nohup python3 -m networks.train --data $D/train $COMMON $BARGS --resume >> /tmp/run_b.out 2>&1 < /dev/null &
fi
ls $D/train | wc -l
while [ $(( $(date +%s) - T0 )) -lt $secs ]; do
  sleep 30; pgrep -f networks.train > /dev/null || { echo "trainers exited"; break; }
  echo "--- $(( $(date +%s) - T0 )) s"; tail -n 1 /tmp/run_n/train.log /tmp/run_b/train.log 2>/dev/null | cut -c1-220
done
grep "event=val" /tmp/run_n/train.log | cut -c1-200 | tail -n 8
grep "event=val" /tmp/run_b/train.log | sed 's/mae_[a-z+]*=[0-9.]* //g' | cut -c1-300 | tail -n 8
nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv
tail -n 3 /tmp/run_n.out /tmp/run_b.out
for r in n b; do for w in best last; do python3 docs/recipes/export_fp16.py /tmp/run_$r/$w.safetensors $OUT/${r}_$w.safetensors; done; cp /tmp/run_$r/log.jsonl $OUT/${r}_log.jsonl 2>/dev/null; done
exit 0
