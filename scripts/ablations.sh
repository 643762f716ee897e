#!/usr/bin/env bash
# The paper's ablations (Tables 5-8) as commands, on a reduced budget: they need not run to convergence.
# Each trains a variant of the cpu preset for EPOCHS epochs on LIMIT shapes, exports it and evaluates
# PRANet-v1 on PAIRS clean unseen-category pairs. Results: runs/ablation-*/eval.json and eval.txt.
#
#   bash scripts/ablations.sh                 # all of them (hours on 2 cores)
#   bash scripts/ablations.sh reward          # one group: reward | sampling | curriculum | policy
#   EPOCHS=2 LIMIT=500 PAIRS=50 bash scripts/ablations.sh curriculum
#   EPOCHS=3 LIMIT=1500 PAIRS=100 THREADS=1 bash scripts/ablations.sh reward sampling curriculum   # RESULTS.md
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
EPOCHS="${EPOCHS:-6}"
LIMIT="${LIMIT:-4601}"
PAIRS="${PAIRS:-200}"
THREADS="${THREADS:-2}"  # torch intra-op threads of each training run
BIN=.venv/bin
groups=("${@:-reward sampling curriculum policy}")

variant() {  # name, then --set overrides; trains, exports, evaluates on clean pairs
    local name=$1; shift
    local out="runs/ablation-$name"
    "$BIN/pranet-train" --preset cpu --epochs "$EPOCHS" --limit "$LIMIT" --out "$out" --no-progress --resume \
        --threads "$THREADS" "$@"
    "$BIN/pranet-export" "$out/last.pt" --out "$out/model" --name "ablation-$name" > /dev/null
    "$BIN/pranet-eval" --setting clean --limit "$PAIRS" --methods pranet-v1 --model "$out/model" \
        --json "$out/eval.json" --threads "$THREADS" ${EVAL_ARGS:-} --quiet | tee "$out/eval.txt"
}

for group in ${groups[*]}; do
    case "$group" in
    reward)  # Table 5: the SE(3) distance against point-based distances in the reward
        variant reward-se3 --set sampling.reward=se3
        variant reward-l2 --set sampling.reward=l2
        variant reward-mcd --set sampling.reward=mcd ;;
    sampling)  # Table 6: isotropic against naive Euler sampling, tested on naive pairs up to 32° per axis
        EVAL_ARGS="--rotation naive --max-angle 32" variant sampling-isotropic --set sampling.rotation=isotropic
        EVAL_ARGS="--rotation naive --max-angle 32" variant sampling-naive --set sampling.rotation=naive \
            --set 'sampling.full=[[32, 0.5, 0.5], [10, 0.1, 0.25], [2, 0.02, 0.25]]' ;;
    curriculum)  # Table 7: curriculum against uniform against ad-hoc 50/50
        variant curriculum-paper --set sampling.curriculum=paper
        variant curriculum-uniform --set sampling.curriculum=uniform
        variant curriculum-adhoc --set sampling.curriculum=adhoc ;;
    policy)  # Table 8: no retraining; the shipped model under each policy
        for policy in deterministic stoch1 stoch2; do
            mkdir -p runs/ablation-policy
            "$BIN/pranet-eval" --setting clean --limit "$PAIRS" --methods pranet-v1 --policy "$policy" \
                --json "runs/ablation-policy/$policy.json" --quiet | tee "runs/ablation-policy/$policy.txt"
        done ;;
    *) echo "unknown group $group (reward | sampling | curriculum | policy)" >&2; exit 2 ;;
    esac
done
