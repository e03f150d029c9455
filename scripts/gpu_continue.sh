#!/usr/bin/env bash
# Continue training the shipped student on one GPU, in one command of under 10 minutes, and leave
# its weights in $OUT in parts of under 16 MiB, for a GPU machine that hands back only small files
# (docs/training.md, "Continuing the shipped model on one GPU"). The shipped run's own checkpoint,
# with its optimiser's state, was not kept, so this starts a new run from the shipped package
# (--init-from: the export's 28 basis planes grow back to 64) with a fresh optimiser, the rays
# throughout and a schedule short enough to finish inside the time guard.
#
#   OUT=/some/folder bash scripts/gpu_continue.sh           # on the GPU machine, from the repo root
#
# Then, on the machine that keeps the repo:
#   python scripts/checkpoint_parts.py join FOLDER/step-NNNNNN.parts.json runs/gpu-ft/step-NNNNNN.pt
#   lp3d eval runs/gpu-ft/step-NNNNNN.pt --refine 30      # 16 held-out identities, on the CPU
#
# Settings (environment; defaults in brackets): STEPS [2000], LR_SCALE [0.3], BATCH [32],
# IDENTITIES [4096], CHECKPOINT_EVERY [200], TRAIN_S [470: the run is stopped (SIGINT, it saves a
# checkpoint first) after this many seconds], DEVICE [cuda], CONFIG [small-colour],
# INIT [python/lp3d/lift/models/small.pt; empty: no warm start], RUN [/tmp/lp3d-gpu-run].
# The defaults are sized to finish well inside TRAIN_S on one H200-class GPU, dataset included
# (the step time measured there: docs/training.md, "On one GPU: how the shipped model was trained").
set -euo pipefail

: "${OUT:?set OUT to the folder the parts and logs go to}"
STEPS=${STEPS:-2000}
LR_SCALE=${LR_SCALE:-0.3}
BATCH=${BATCH:-32}
IDENTITIES=${IDENTITIES:-4096}
CHECKPOINT_EVERY=${CHECKPOINT_EVERY:-200}
TRAIN_S=${TRAIN_S:-470}
DEVICE=${DEVICE:-cuda}
CONFIG=${CONFIG:-small-colour}
INIT=${INIT-python/lp3d/lift/models/small.pt}
RUN=${RUN:-/tmp/lp3d-gpu-run}
PYTHON=${PYTHON:-python3}

cd "$(dirname "$0")/.."
export PYTHONPATH="$PWD/python${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
mkdir -p "$OUT"
stamp() { echo "[$(date +%T)] $*"; }

# Fail in seconds, not after the dataset, when the device is missing.
"$PYTHON" - "$DEVICE" <<'EOF'
import sys, torch
device = sys.argv[1]
if device.startswith("cuda") and not torch.cuda.is_available():
    sys.exit(f"--device {device}: torch {torch.__version__} sees no CUDA device")
name = torch.cuda.get_device_name() if device.startswith("cuda") else "cpu"
print(f"torch {torch.__version__} on {name}")
EOF

init=()
if [ -n "$INIT" ]; then init=(--init-from "$INIT"); fi
stamp "training $CONFIG: $STEPS steps of batch $BATCH, lr x$LR_SCALE, rays from step 0, guard ${TRAIN_S}s"
rc=0
timeout -s INT -k 60 "$TRAIN_S" "$PYTHON" -m lp3d.train --config "$CONFIG" --device "$DEVICE" "${init[@]}" \
    --batch "$BATCH" --dataset-identities "$IDENTITIES" --total-steps "$STEPS" --ray-from 0 \
    --lr-scale "$LR_SCALE" --checkpoint-every "$CHECKPOINT_EVERY" --out "$RUN" --no-progress \
    >"$OUT/train.log" 2>&1 || rc=$?
tail -n 5 "$OUT/train.log"
# 130: stopped by the guard after saving a checkpoint; anything else but 0 is a failure.
if [ "$rc" -ne 0 ] && [ "$rc" -ne 130 ]; then
    stamp "training failed (exit $rc); the log is $OUT/train.log"
    exit "$rc"
fi
[ "$rc" -eq 130 ] && stamp "stopped by the ${TRAIN_S}s guard before step $STEPS: the schedule did not finish"
stamp "splitting the newest checkpoint's weights"
"$PYTHON" scripts/checkpoint_parts.py split "$RUN" "$OUT" --part-mib 15.9
# Few files, each small: the parts (4 for small-colour), the manifest, the log and the run's CSV
# files and configuration in one archive.
tar -czf "$OUT/run-logs.tar.gz" -C "$RUN" log.csv heldout.csv config.json
echo "held-out curve (heldout.csv):"
cat "$RUN/heldout.csv"
stamp "done: $(ls "$OUT" | tr '\n' ' ')"
