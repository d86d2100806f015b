#!/usr/bin/env bash
# Reproduces the shipped weights pointpillars.pt: the PointPillars-style LiDAR-only Car detector
# (0.32 m pillars on x 0..70.4 m, y -40..40 m; PointNet 9->64, backbone 64/128/128 at strides 2/4/8,
# upsampled and concatenated at stride 2 (0.64 m), CenterPoint-style heatmap head; 1.35 M parameters),
# trained from scratch on the embedded train split on ONE CPU thread, bf16 autocast (float32 weights).
# Measured: 12 epochs, 2976 steps of 4 frames in 39.4 min wall (37.5 min training at 0.76 s a step, 1.6 min
# validation on 100 val frames per epoch) on one thread of a 2-core AMD EPYC (AVX512-BF16) shared with
# other jobs; peak memory 4.2 GB. The train frames are read once and held in memory.
# The same CPU type and thread count give the same bytes. The ONNX twin pointpillars-onnx/ is the last
# command (the one recorded in its manifest).
# Usage: bash victims/weights/reproduce-pointpillars.sh [OUT_DIR]   (default runs/weights)
set -euo pipefail
OUT="${1:-runs/weights}"
DATA="${ROBUSTBENCH3D_CACHE:-$HOME/.cache/robustbench3d}/datasets/synth"
export OMP_WAIT_POLICY=PASSIVE
robustbench3d data synth --out "$DATA" --frames 2000 --seed 0 --val-fraction 0.5 --workers 2
robustbench3d victims train-pointpillars --data "$DATA" --out "$OUT/pointpillars" --threads 1 --seed 0 --epochs 12 --batch-size 4 --precision bf16 --val-limit 100 --checkpoint-every 50 --no-progress
cp "$OUT/pointpillars/model.pt" "$OUT/pointpillars.pt"
robustbench3d run --victims pointpillars --victim-arg "pointpillars:weights=$OUT/pointpillars.pt" --attacks none --proposals detector --full --out "$OUT/check-pointpillars"
robustbench3d export-onnx pointpillars --out "$OUT/pointpillars-onnx" --exporter dynamo --victim-arg "weights=$OUT/pointpillars.pt"
