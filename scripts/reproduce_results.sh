#!/usr/bin/env bash
# Every table and figure of RESULTS.md from the shipped model (or MODEL=dir), in one go, into results/.
# Tables 1-4 and Fig. 5: all methods in one pranet-eval run per setting (so the latencies of Table 4 are
# side by side), JOBS settings at a time at 1 thread each; then the policy ablation (Table 8), the
# confidence flag, the global mode and the real scans.
#
#   bash scripts/reproduce_results.sh            # about 40-60 minutes on 2 cores
#   LIMIT=50 POLICY_PAIRS=50 CONF_PAIRS=30 GLOBAL_PAIRS=5 bash scripts/reproduce_results.sh   # a quick pass
#   BASELINES_FROM=results/baselines bash scripts/reproduce_results.sh   # a new model: PRANet rows only, the
#       classical rows (model-independent, same pairs) merged from that folder's eval-*.json.gz; Table 4's
#       latencies then come from two runs
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
BIN=.venv/bin
JOBS="${JOBS:-2}"
LIMIT_ARGS=()
[[ -n "${LIMIT:-}" ]] && LIMIT_ARGS=(--limit "$LIMIT")
MODEL_ARGS=()
[[ -n "${MODEL:-}" ]] && MODEL_ARGS=(--model "$MODEL")
mkdir -p results/ablation-policy

METHODS="pranet-v1,pranet-v2,pranet-adaptive"
[[ -z "${BASELINES_FROM:-}" ]] && METHODS="$METHODS,icp,fgr,ransac"
table() {  # one setting: Tables 1-3 rows, Table 4 latencies, Fig. 5
    local s=$1
    "$BIN/pranet-eval" --setting "$s" --methods "$METHODS" --threads 1 \
        "${LIMIT_ARGS[@]}" "${MODEL_ARGS[@]}" --json "results/eval-$s.json" --plot "results/fig5-$s.png" --quiet \
        > "results/eval-$s.txt"
    gzip -f "results/eval-$s.json"
}
pids=()
for s in partial noisy clean; do  # the slowest first
    table "$s" &
    pids+=($!)
    while (($(jobs -rp | wc -l) >= JOBS)); do sleep 5; done
done
for p in "${pids[@]}"; do wait "$p"; done
BASELINE_FILES=()
[[ -n "${BASELINES_FROM:-}" ]] && BASELINE_FILES=("$BASELINES_FROM"/eval-{clean,noisy,partial}.json.gz)
# Later files win a method's row: the classical rows first, this run's after.
"$BIN/python" scripts/results_tables.py --markdown "${BASELINE_FILES[@]}" results/eval-{clean,noisy,partial}.json.gz \
    > results/tables.md

for policy in deterministic stoch1 stoch2; do  # Table 8: no retraining
    "$BIN/pranet-eval" --setting clean --limit "${POLICY_PAIRS:-300}" --methods pranet-v1 --policy "$policy" \
        "${MODEL_ARGS[@]}" --threads 1 --json "results/ablation-policy/$policy.json" --quiet \
        > "results/ablation-policy/$policy.txt"
    gzip -f "results/ablation-policy/$policy.json"
done
CONF_PAIRS="${CONF_PAIRS:-150}"
"$BIN/python" scripts/confidence_eval.py --pairs "$CONF_PAIRS" --calibration "$CONF_PAIRS" --settings noisy,partial \
    "${MODEL_ARGS[@]}" --threads 1 --json results/confidence.json > results/confidence.txt
"$BIN/python" scripts/global_eval.py --pairs "${GLOBAL_PAIRS:-30}" "${MODEL_ARGS[@]}" --threads 1 \
    --json results/global.json > results/global.txt
gzip -f results/confidence.json results/global.json
"$BIN/python" scripts/scan_check.py "${MODEL_ARGS[@]}" > results/scans.md
echo "results/: tables.md, eval-*.txt, fig5-*.png, ablation-policy/, confidence.txt, global.txt, scans.md"
