#!/usr/bin/env bash
# Property-based API tests with schemathesis (PyPI, pinned below) against the OpenAPI document
# of a real `willow serve`: every operation of /openapi.json gets generated requests (valid
# and invalid), and every response must pass
#
#   not_a_server_error            no 5xx, whatever the request
#   status_code_conformance       the status is one the document lists for the operation
#   content_type_conformance      the Content-Type is the one documented for that status
#   response_schema_conformance   the body matches the documented schema
#
# The server runs on a free loopback port (port 0) with a temporary data dir and one worker,
# and is stopped at the end. Bounded: WILLOW_SCHEMATHESIS_EXAMPLES (default 30) examples per
# operation and per phase, WILLOW_SCHEMATHESIS_MAX_TIME (default 150) seconds in all.
# Exits non-zero on any failed check (see the end for schemathesis' own errors). Extra arguments go to `schemathesis run` (e.g. `--seed 1`).
#
# schemathesis goes into a venv under target/schemathesis/ (the first run takes ~30 s; after
# that a stamp makes this quick). Reports (JUnit) go to target/schemathesis/report/.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"

requirement="schemathesis==4.32.5"
tools="$root/target/schemathesis"
venv="$tools/venv"
stamp="$tools/.installed"
python="${PYTHON:-python3}"

if [[ ! -x "$venv/bin/schemathesis" || ! -f "$stamp" || "$(cat "$stamp")" != "$requirement" ]]; then
    echo "schemathesis.sh: installing $requirement into $venv (pip, from PyPI)"
    rm -rf "$venv" "$stamp"
    "$python" -m venv "$venv"
    "$venv/bin/python" -m pip install --quiet --disable-pip-version-check "$requirement"
    echo "$requirement" > "$stamp"
fi

# The binary under test.
nice -n 10 cargo build --bin willow --quiet
willow="${CARGO_TARGET_DIR:-$root/target}/debug/willow"

data_dir="$(mktemp -d)"
server_out="$data_dir/server.out"
server_pid=""
cleanup() {
    if [[ -n "$server_pid" ]]; then kill "$server_pid" 2>/dev/null || true; wait "$server_pid" 2>/dev/null || true; fi
    rm -rf "$data_dir"
}
trap cleanup EXIT

"$willow" serve --addr 127.0.0.1:0 --data-dir "$data_dir/data" --workers 1 \
    --log-format text >"$server_out" 2>"$data_dir/server.err" &
server_pid=$!
for _ in $(seq 1 100); do
    if grep -q '^listening on ' "$server_out"; then break; fi
    if ! kill -0 "$server_pid" 2>/dev/null; then
        echo "schemathesis.sh: willow serve exited:" >&2
        cat "$data_dir/server.err" >&2
        exit 1
    fi
    sleep 0.1
done
url="$(sed -n 's/^listening on //p' "$server_out" | head -n1)"
if [[ -z "$url" ]]; then
    echo "schemathesis.sh: willow serve did not start" >&2
    exit 1
fi
echo "schemathesis.sh: willow serve at $url"

report="$tools/report"
rm -rf "$report"
mkdir -p "$report"
status=0
# From target/schemathesis/: schemathesis keeps its state in ./.schemathesis/.
# filter_too_much is schemathesis' own health check on its generator, not a check of the API:
# POST /v1/jobs (binary bodies in four media types, an optional header) trips it.
cd "$tools"
"$venv/bin/schemathesis" run "$url/openapi.json" --url "$url" \
    --suppress-health-check filter_too_much \
    --checks not_a_server_error,status_code_conformance,content_type_conformance,response_schema_conformance \
    --max-examples "${WILLOW_SCHEMATHESIS_EXAMPLES:-30}" \
    --max-time "${WILLOW_SCHEMATHESIS_MAX_TIME:-150}" \
    --request-timeout 20 --workers 2 --no-color \
    --generation-database none \
    --report junit --report-junit-path "$report/junit.xml" "$@" || status=$?
# A failed check is a <failure> in the JUnit report. An <error> without one is schemathesis
# failing in itself (e.g. hypothesis' "AST constructor recursion depth mismatch" while it
# builds coverage cases for one operation): reported above, but not a finding about the API,
# so it does not fail the run. No report at all (schemathesis could not start) fails it.
if [[ $status -ne 0 && -f "$report/junit.xml" ]] && ! grep -q '<failure' "$report/junit.xml"; then
    echo "schemathesis.sh: no check failed; schemathesis' own errors (above) are not counted" >&2
    status=0
fi
if [[ $status -ne 0 ]]; then
    echo "schemathesis.sh: FAILED; the server's log (last 40 lines):" >&2
    tail -n 40 "$data_dir/server.err" >&2
fi
exit $status
