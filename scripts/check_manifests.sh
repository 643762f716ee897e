#!/usr/bin/env bash
# The deployment files, checked offline with tools from PyPI (requirements/deploy-tools.txt, in .venv-deploy):
#   kubernetes-validate --strict: every manifest under deploy/k8s against the Kubernetes schemas it ships, for the
#     oldest version with every field used here GA (1.33: the Job's backoffLimitPerIndex) and the newest it knows;
#   checkov: a security scan of deploy/k8s and of the Dockerfile. A finding that does not apply is skipped in the
#     manifest itself (checkov.io/skip annotation), with the reason.
# Both run without the network where this shell may drop it (unshare), so a check that phones home fails here.
# Usage: scripts/check_manifests.sh            (PYTHON=python3.11 to choose the interpreter of .venv-deploy)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

PYTHON="${PYTHON:-python3}"
TOOLS=".venv-deploy"
K8S_VERSIONS=("1.33.0" "1.37.0")

if [[ ! -x "$TOOLS/bin/python" ]]; then
    "$PYTHON" -m venv "$TOOLS"
fi
"$TOOLS/bin/pip" install --quiet -r requirements/deploy-tools.txt 2> >(grep -v -e "WARNING: Location" >&2)

# No network from here on, when a network namespace can be made (root, or unprivileged user namespaces).
OFFLINE=()
if unshare -n true 2>/dev/null; then
    OFFLINE=(unshare -n)
elif unshare -rn true 2>/dev/null; then
    OFFLINE=(unshare -rn)
fi
if ((${#OFFLINE[@]})); then
    echo "[manifests] running offline (${OFFLINE[*]})"
else
    echo "[manifests] cannot drop the network here (no unshare): running as is"
fi

mapfile -t MANIFESTS < <(find deploy/k8s -name '*.yaml' | sort)
for version in "${K8S_VERSIONS[@]}"; do
    "${OFFLINE[@]}" "$TOOLS/bin/kubernetes-validate" --strict --quiet -k "$version" "${MANIFESTS[@]}"
    echo "[manifests] kubernetes-validate --strict, Kubernetes $version: ${#MANIFESTS[@]} files valid"
done

# --skip-download: no guidelines or policies from the vendor's platform (it would be tried, and fail, offline).
"${OFFLINE[@]}" "$TOOLS/bin/checkov" --quiet --compact --skip-download --framework kubernetes -d deploy/k8s
"${OFFLINE[@]}" "$TOOLS/bin/checkov" --quiet --compact --skip-download --framework dockerfile -f Dockerfile
echo "[manifests] checkov: no finding in deploy/k8s or the Dockerfile"
