#!/usr/bin/env bash
# Reproduces the shipped weights fpointnet-v1-lite.pt (mini3-YOLO 960x288 + Frustum-PointNet v1 lite)
# from scratch on the embedded dataset, on the CPU. The mini-YOLO (640x192) and F-PN trainers run side
# by side, one thread each (about 115 minutes on a 2-core machine); then the mini3 layout (mini plus a
# stride-32 head) is fine-tuned from the mini-YOLO at 960x288 on two threads (about 40 minutes).
# The same CPU type and thread counts give the same bytes.
# Usage: bash victims/weights/reproduce.sh [OUT_DIR]   (default runs/weights)
set -euo pipefail
OUT="${1:-runs/weights}"
DATA="${ROBUSTBENCH3D_CACHE:-$HOME/.cache/robustbench3d}/datasets/synth"
export OMP_WAIT_POLICY=PASSIVE
robustbench3d data synth --out "$DATA" --frames 2000 --seed 0 --val-fraction 0.5 --workers 2
robustbench3d train yolo --data "$DATA" --out "$OUT/yolo" --epochs 80 --batch-size 16 --seed 0 --threads 1 --precision bf16 --lr-schedule cosine --scale-jitter 0.25 --val-limit 300 --no-progress &
YOLO=$!
robustbench3d train fpointnet --data "$DATA" --out "$OUT/fpointnet" --model lite --epochs 8 --batch-size 32 --seed 0 --threads 1 --lr 2e-3 --lr-schedule cosine --bn-decay-step 40000 --val-limit 1500 --no-progress &
FPN=$!
wait "$YOLO"  # each wait returns its trainer's exit status, so a failed run stops the script
wait "$FPN"
robustbench3d train yolo --data "$DATA" --out "$OUT/yolo3" --layout mini3 --init "$OUT/yolo/model.pt" --epochs 16 --batch-size 16 --seed 0 --threads 2 --precision bf16 --lr-schedule cosine --scale-jitter 0.25 --val-limit 300 --no-progress
robustbench3d victims pack --yolo "$OUT/yolo3/model.pt" --fpointnet "$OUT/fpointnet/model.pt" --out "$OUT/fpointnet-v1-lite.pt"
robustbench3d run --victims fpointnet-v1-lite --victim-arg "fpointnet-v1-lite:weights=$OUT/fpointnet-v1-lite.pt" --attacks none --proposals detector,gt --out "$OUT/check"
