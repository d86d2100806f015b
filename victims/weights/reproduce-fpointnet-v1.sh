#!/usr/bin/env bash
# Reproduces the shipped weights fpointnet-v1.pt: the mini3-YOLO 960x288 of fpointnet-v1-lite.pt
# (reproduce.sh) + Frustum-PointNet v1 at full width (N = 1024, 1.64 M parameters), trained from
# scratch on the embedded train split. The shipped F-PN was trained with DEVICE=cuda on one NVIDIA
# H200 (7 epochs, 8568 steps of 32 frustums, float32; 277 s wall, 1.6 GB peak GPU memory, 3.7 GB
# peak host memory). DEVICE=cpu (the default) runs the very same recipe on the CPU: same data,
# schedule and seeds, but several hours (a float32 step of the full network costs about 0.2 s per
# frustum per core on the 2-core AVX2 host it was packed on, measured under load: 8568 x 32
# frustums, roughly 8 h on 2 threads; bf16 is slower there, having no AVX512-BF16/AMX). Torch's
# CPU and CUDA generators draw different augmentations and dropout masks from one seed, so a CPU
# run trains an equivalent network, not the same bytes. On the CPU the same thread count gives
# the same bytes run to run; a GPU run is not bitwise repeatable (CUDA's atomic-add kernels).
# The train frustum set is read from a compact cache (--cache; written from the dataset first).
# fpointnet-v1.pt holds the F-PN and refers to fpointnet-v1-lite.pt beside it for the 2D stage
# (`pack --yolo-shared`: one copy of the detector ships); the ONNX twin fpointnet-v1-onnx/ is
# `robustbench3d export-onnx fpointnet-v1 --out DIR --exporter dynamo --share DIR/../fpointnet-v1-lite-onnx`
# (the command recorded in its manifest), which names the lite twin's byte-identical detector graph.
# Usage: [DEVICE=cuda] bash victims/weights/reproduce-fpointnet-v1.sh [OUT_DIR] [LITE_CASCADE]
set -euo pipefail
OUT="${1:-runs/weights}"
LITE="${2:-victims/weights/fpointnet-v1-lite.pt}"
DATA="${ROBUSTBENCH3D_CACHE:-$HOME/.cache/robustbench3d}/datasets/synth"
DEVICE="${DEVICE:-cpu}"
export OMP_WAIT_POLICY=PASSIVE
robustbench3d data synth --out "$DATA" --frames 2000 --seed 0 --val-fraction 0.5 --workers 2
robustbench3d train fpointnet --data "$DATA" --cache "$OUT/frustums_train.cache.npz" --out "$OUT/fpointnet-full" --model full --epochs 7 --batch-size 32 --seed 0 --threads 2 --lr 2e-3 --lr-schedule cosine --bn-decay-step 35000 --val-limit 0 --checkpoint-every 500 --no-progress --device "$DEVICE"
cp "$LITE" "$OUT/fpointnet-v1-lite.pt"
robustbench3d victims pack --yolo "$OUT/fpointnet-v1-lite.pt" --yolo-shared --fpointnet "$OUT/fpointnet-full/model.pt" --out "$OUT/fpointnet-v1.pt"
robustbench3d run --victims fpointnet-v1 --victim-arg "fpointnet-v1:weights=$OUT/fpointnet-v1.pt" --attacks none --proposals detector,gt --full --out "$OUT/check-v1"
