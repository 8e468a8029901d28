#!/usr/bin/env bash
# Creates .venv at the repository root with the pinned packages of tests/python/requirements.txt,
# for the Python gRPC interop test (tests/service_grpc_python.rs).
#
# Idempotent and quick when nothing changed: a stamp file records the hash of the requirements
# that were installed, and pip runs only when the hash differs (or the venv is broken).
set -euo pipefail

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$root/.venv"
req="$root/tests/python/requirements.txt"
stamp="$venv/.willow-requirements.sha256"
python="${PYTHON:-python3}"

want="$(sha256sum "$req" | cut -d' ' -f1)"
if [[ -x "$venv/bin/python" && -f "$stamp" && "$(cat "$stamp")" == "$want" ]] \
    && "$venv/bin/python" -c 'import grpc, grpc_tools, google.longrunning.operations_pb2' 2>/dev/null; then
    echo "python-env: $venv is up to date"
    exit 0
fi

if [[ ! -x "$venv/bin/python" ]]; then
    echo "python-env: creating $venv with $("$python" --version 2>&1)"
    "$python" -m venv "$venv"
fi
echo "python-env: installing $req"
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check -r "$req"
echo "$want" > "$stamp"
echo "python-env: ready"
