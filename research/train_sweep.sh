#!/usr/bin/env bash
# Universal-training settings side by side at equal wall time (docs/attacks.md, "Step size, batch and loss").
# On a fresh dataset of FRAMES frames of the embedded generator (its own train/val split), every variant below
# trains in its own process (one thread each; run it on a machine with at least as many cores as variants),
# is stopped after TRAIN_S seconds and written from its last checkpoint (--resume with --steps 1 writes the
# checkpointed object without another step; one that reached no checkpoint trains one step), then scored with the victim's own 2D boxes on the first EVAL
# val frames. Prints one line per variant: steps reached, Car BEV AP @0.7 R40 E/M/H, moderate relative drop,
# attack success rate.
# Usage: [ONLY=REGEX] bash research/train_sweep.sh FRAMES TRAIN_S EVAL OUT_DIR   (docs/attacks.md: 600 290 80)
set -u
FRAMES=$1; TRAIN_S=$2; EVAL=$3; OUT=$4
NP=$(nproc)  # before OMP_NUM_THREADS=1, which nproc obeys
export OMP_NUM_THREADS=1 OMP_WAIT_POLICY=PASSIVE MKL_NUM_THREADS=1
D="$OUT/data"; mkdir -p "$OUT/o"
robustbench3d data synth --out "$D" --frames "$FRAMES" --seed 0 --val-fraction 0.5 --workers "$NP" --no-progress \
  > "$OUT/synth.log" 2>&1 || { tail "$OUT/synth.log"; exit 1; }
declare -A V
V[tex_sum_lr05]="adv-texture --lr-color 0.05 --image-loss sum"
V[tex_sum_lr1]="adv-texture --lr-color 0.1 --image-loss sum"
V[tex_sum_lr2]="adv-texture --lr-color 0.2 --image-loss sum"
V[tex_sum_lr4]="adv-texture --lr-color 0.4 --image-loss sum"
V[tex_sum_lr1_b16]="adv-texture --lr-color 0.1 --image-loss sum --batch-cars 16"
V[tex_sum_lr2_b4]="adv-texture --lr-color 0.2 --image-loss sum --batch-cars 4"
V[tex_sum_lr1_nocls]="adv-texture --lr-color 0.1 --image-loss sum --no-class-prob"
V[tex_sum_lr1_jit]="adv-texture --lr-color 0.1 --image-loss sum --eot jitter"
V[tex_mean_lr05]="adv-texture --lr-color 0.05 --image-loss mean"
V[obj_sum_lr05]="adv-object --lidar-boxes detector --lidar-loss seed+box --lr-color 0.05 --lr-shape 0.02 --image-loss sum"
V[obj_sum_lr1]="adv-object --lidar-boxes detector --lidar-loss seed+box --lr-color 0.1 --lr-shape 0.02 --image-loss sum"
V[obj_sum_lr1_img3]="adv-object --lidar-boxes detector --lidar-loss seed+box --lr-color 0.1 --lr-shape 0.02 --image-loss sum --lambda-img 3"
V[obj_sum_lr2_shape05]="adv-object --lidar-boxes detector --lidar-loss seed+box --lr-color 0.2 --lr-shape 0.05 --image-loss sum"
V[obj_sum_lr1_gt]="adv-object --lidar-boxes gt --lidar-loss seed --lr-color 0.1 --lr-shape 0.02 --image-loss sum"
for n in "${!V[@]}"; do [[ $n =~ ${ONLY:-.} ]] || unset "V[$n]"; done  # ONLY=REGEX: a subset of the variants
run_train() {  # NAME STEPS [PREFIX...]: STEPS 1 writes the object of the last checkpoint (--resume)
  local n=$1 steps=$2 resume=(); shift 2
  [ "$steps" = 1 ] && resume=(--resume)
  "$@" robustbench3d attack train ${V[$n]} --victim fpointnet-v1-lite --data "$D" --out "$OUT/o/$n.ply" \
    --steps "$steps" --seed 0 --checkpoint-every 5 --no-progress "${resume[@]}" >> "$OUT/o/$n.log" 2>&1
}
for n in "${!V[@]}"; do run_train "$n" 100000 timeout "$TRAIN_S" & done
wait
for n in "${!V[@]}"; do run_train "$n" 1 & done
wait
for n in "${!V[@]}"; do
  robustbench3d run --victims fpointnet-v1-lite --attacks "none,$OUT/o/$n.ply" --proposals detector --data "$D" \
    --max-frames "$EVAL" --out "$OUT/eval/$n" > "$OUT/o/$n.eval.log" 2>&1 &
done
wait
python3 - "$OUT/eval" <<'PY'
import json, pathlib, sys
for d in sorted(pathlib.Path(sys.argv[1]).iterdir()):
    c = [x for x in json.loads((d / "summary.json").read_text()) if x["attack"] != "none"][0]
    made_by = c["provenance"]["config"]["attack"]["object"]["object"]["made_by"]
    e, b = c["attack_effect"], c["metrics"]["Car"]["bev"]["R40"]
    s = e["success"]
    print(f"{d.name:22s} steps {made_by['steps']:4d}  BEV R40 {b['easy']:.2f} / {b['moderate']:.2f} / {b['hard']:.2f}  "
          f"drop M {100 * e['relative_drop']['Car']['bev']['R40']['moderate']:.1f} %  "
          f"ASR {100 * s['rate']:.1f} % ({s['attacked_missed']}/{s['clean_matched']})")
PY
