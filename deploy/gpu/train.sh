#!/bin/sh
# The oracle's reference GNS (latent 128, 10 message-passing steps) trained on one GPU machine
# in one time-boxed command: build the coarse-grained dataset with every core, train for the
# time left with checkpoints as it goes, score the best checkpoint on the test split.
#
#   sh deploy/gpu/train.sh         # full size, within BUDGET_S (540 s) of one command
#   TINY=1 sh deploy/gpu/train.sh  # a CPU smoke test: 4 short scenes, 30 s of training
#
# Results in $OUT (default data/gpu): gns_l128_m10.best.pt (best validation rollout), gns_l128_m10.pt
# (the last), eval.json (`minority oracle evaluate` on the test split), train.log. Ship a better
# one with `minority oracle ship $OUT/gns_l128_m10.best.pt -o gns/checkpoints/...` (gns/README.md).
#
# A machine without the project installed (the device machine: python3 with torch, numba,
# h5py, but not zenoh nor msgspec) gets it from the checkout and the wheels in .whl/
# (python -m pip download ... -d .whl eclipse-zenoh msgspec; gns/README.md, "Training on a GPU").
# Training gets what BUDGET_S leaves after the dataset, less 90 s for the last validation and
# the test split (at most TRAIN_S). The dataset stays in DATA: a second run on the same machine
# trains at once. Knobs: PYTHON (python3), JOBS (all cores), BUDGET_S (540), TRAIN_S (no
# bound), DATA (data/dataset_cg2x), CONFIG, EXTRA_TRAIN (48), EXTRA_VALID (4), BATCH (4).
set -eu
PY=${PYTHON:-python3}
OUT=${OUT:-data/gpu}
JOBS=${JOBS:-$(nproc)}
mkdir -p "$OUT"
LOG="$OUT/train.log"
say() { echo "gpu-train: $*" | tee -a "$LOG" >&2; }

if ! "$PY" -c "import minority.gns.train" 2>/dev/null; then
    say "installing the project into /tmp/site (no network: wheels from .whl/)"
    if [ -d .whl ]; then
        "$PY" -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl
    fi
    "$PY" -m pip install -q --no-index --no-deps --no-build-isolation --no-compile \
        --target /tmp/site .
    export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
    export PYTHONSAFEPATH=1  # import the installed copy in /tmp/site, not the checkout
    "$PY" -c "import minority.gns.train"
fi
"$PY" -c "import torch; print('gpu-train: torch', torch.__version__, 'cuda' if torch.cuda.is_available() else 'cpu only')" | tee -a "$LOG" >&2

if [ "${TINY:-0}" = 1 ]; then
    DATA=${DATA:-$OUT/dataset_tiny}
    CONFIG="$OUT/tiny.toml"
    cat > "$CONFIG" <<TOML
extends = "$(pwd)/gns/configs/column_sweep_cg2.toml"
duration_s = 0.04
named = []
[splits]
train = 2
valid = 1
test = 1
TOML
    TRAIN_S=${TRAIN_S:-30}
    set -- --latent 16 --message-passing 2 --val-every 5 --val-frames 4 --ckpt-every 5 --batch 1
    EXTRA=""
else
    DATA=${DATA:-data/dataset_cg2x}
    CONFIG=${CONFIG:-gns/configs/column_sweep_cg2.toml}
    TRAIN_S=${TRAIN_S:-100000}
    set -- --latent 128 --message-passing 10 --val-every 1000 --val-frames 195 \
        --ckpt-every 250 --batch "${BATCH:-4}" --lr 1e-3 --lr-decay-steps 20000 --noise-std 5e-5
    EXTRA="--extra-train ${EXTRA_TRAIN:-48} --extra-valid ${EXTRA_VALID:-4}"
fi

t0=$(date +%s)
if [ ! -f "$DATA/metadata.json" ]; then
    say "dataset $DATA from $CONFIG with $JOBS jobs"
    # shellcheck disable=SC2086  # EXTRA is two options or none
    "$PY" -m minority oracle dataset --config "$CONFIG" --runs "$DATA.runs" --out "$DATA" \
        --jobs "$JOBS" $EXTRA 2>>"$LOG"
fi
left=$(( ${BUDGET_S:-540} - ($(date +%s) - t0) - 90 ))
if [ "$left" -lt 30 ]; then
    say "the dataset took $(( $(date +%s) - t0 )) s of BUDGET_S; no time left to train (run again: DATA is kept)"
    exit 3
fi
[ "$left" -lt "$TRAIN_S" ] && TRAIN_S=$left
say "dataset ready after $(( $(date +%s) - t0 )) s; training for at most $TRAIN_S s"
"$PY" -m minority oracle train "$DATA" --out "$OUT/gns_l128_m10.pt" --max-wall-s "$TRAIN_S" \
    --steps 1000000 "$@" 2>>"$LOG"
BEST="$OUT/gns_l128_m10.best.pt"
[ -f "$BEST" ] || BEST="$OUT/gns_l128_m10.pt"
say "trained after $(( $(date +%s) - t0 )) s; scoring $BEST on the test split"
"$PY" -m minority oracle evaluate "$BEST" "$DATA" --split test --out "$OUT/eval.json" 2>>"$LOG" || \
    say "evaluate exited with $? (a diverged rollout; eval.json says where)"
say "done after $(( $(date +%s) - t0 )) s: $(ls "$OUT" | tr '\n' ' ')"
