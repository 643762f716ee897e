#!/usr/bin/env bash
# Mutation check (cosmic-ray, from PyPI): mutate core/ or the service's request mapping, run the tests that guard
# it, list the mutants that survived. Not in CI (one test run per mutant: hours); results in docs/DESIGN.md.
#
#   bash mutation/run.sh core [module.py ...]     # default: every module named in mutation/core.toml
#   bash mutation/run.sh service
#
# Mutants are applied in place, so this runs in a scratch copy of the tree (mutation/work/, git-ignored), whose
# pranet package shadows the editable install through PYTHONPATH: the checkout you work in is never mutated.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
target="${1:?usage: mutation/run.sh core|service [module ...]}"
shift
repo="$PWD"
work="$repo/mutation/work"
.venv/bin/pip install --quiet "cosmic-ray==8.7.0"
rm -rf "$work" && mkdir -p "$work/pkg/pranet"
git ls-files -z core service model client training tests | xargs -0 cp --parents -t "$work"
touch "$work/pkg/pranet/__init__.py"
for p in core service model client training; do ln -s "$work/$p" "$work/pkg/pranet/$p"; done
config="$work/$target.toml"
cp "mutation/$target.toml" "$config"
if (($#)); then  # a subset of modules
    modules=$(printf '"%s", ' "$@")
    sed -i "s|^module-path = .*|module-path = [${modules%, }]|" "$config"
fi
sed -i "s|\.venv/bin/python|$repo/.venv/bin/python|" "$config"
cd "$work"
export PYTHONPATH="$work/pkg" OMP_NUM_THREADS=1 OMP_WAIT_POLICY=PASSIVE
"$repo/.venv/bin/python" -c "import pranet.core, sys; assert pranet.core.__file__.startswith('$work'), pranet.core.__file__"
"$repo/.venv/bin/cosmic-ray" init "$config" "$target.sqlite"
"$repo/.venv/bin/cosmic-ray" baseline "$config"
"$repo/.venv/bin/cosmic-ray" exec "$config" "$target.sqlite"
"$repo/.venv/bin/cr-report" "$target.sqlite" | tail -n 3 | tee "$repo/mutation/$target-summary.txt"
"$repo/.venv/bin/cr-report" "$target.sqlite" --surviving-only > "$repo/mutation/$target-survivors.txt" || true
echo "survivors: mutation/$target-survivors.txt"
