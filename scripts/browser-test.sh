#!/usr/bin/env bash
# Browser tests of the web page (issue 13): the real `willow serve` binary on a free loopback
# port with a temporary data dir, driven in Debian's headless chromium by playwright-core (npm,
# pinned by tests/browser/package-lock.json; no browser is downloaded). Screenshots and the
# downloaded result go to target/browser-artifacts/.
#
#   scripts/browser-test.sh            the tests (node --test tests/browser/*.test.mjs)
#   scripts/browser-test.sh FILE...    only these test files (e.g. tests/browser/region.test.mjs)
#   scripts/browser-test.sh --timing   the 100k-triangle timing instead (prints figures)
#
# Installs what it needs on a fresh machine: `chromium` with apt-get (as root) when
# /usr/bin/chromium is missing, and the npm packages.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"

mode=tests
if [[ "${1:-}" == "--timing" ]]; then mode=timing; fi
tests=("$@")
if [[ $mode == tests && ${#tests[@]} == 0 ]]; then tests=(tests/browser/); fi

export CHROMIUM="${CHROMIUM:-/usr/bin/chromium}"
if [[ ! -x "$CHROMIUM" ]]; then
    echo "browser-test.sh: installing Debian's chromium"
    if [[ "$(id -u)" != 0 ]]; then
        echo "browser-test.sh: $CHROMIUM is missing and this is not root: install the chromium package" >&2
        exit 1
    fi
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null
fi

if [[ ! -d tests/browser/node_modules/playwright-core ]] \
    || ! cmp -s tests/browser/package-lock.json tests/browser/node_modules/.package-lock-installed.json; then
    echo "browser-test.sh: installing playwright-core (npm ci)"
    PLAYWRIGHT_SKIP_BROWSER_DOWNLOAD=1 npm ci --prefix tests/browser --no-audit --no-fund --loglevel=error
    cp tests/browser/package-lock.json tests/browser/node_modules/.package-lock-installed.json
fi

# The binary under test (this also embeds the page: build.rs bundles web/).
nice -n 10 cargo build --bin willow --quiet
target_dir="${CARGO_TARGET_DIR:-$root/target}"
willow="$target_dir/debug/willow"

data_dir="$(mktemp -d)"
server_out="$data_dir/server.out"
server_pid=""
cleanup() {
    if [[ -n "$server_pid" ]]; then kill "$server_pid" 2>/dev/null || true; wait "$server_pid" 2>/dev/null || true; fi
    rm -rf "$data_dir"
}
trap cleanup EXIT

# Port 0: the server picks a free port and prints "listening on http://127.0.0.1:PORT".
# Two workers: the tests run a job and cancel a second one while it runs.
nice -n 10 "$willow" serve --addr 127.0.0.1:0 --data-dir "$data_dir/data" --workers 2 \
    --log-format text >"$server_out" 2>"$data_dir/server.err" &
server_pid=$!
for _ in $(seq 1 100); do
    if grep -q '^listening on ' "$server_out"; then break; fi
    if ! kill -0 "$server_pid" 2>/dev/null; then
        echo "browser-test.sh: willow serve exited:" >&2
        cat "$data_dir/server.err" >&2
        exit 1
    fi
    sleep 0.1
done
WILLOW_URL="$(sed -n 's/^listening on //p' "$server_out" | head -n1)"
if [[ -z "$WILLOW_URL" ]]; then
    echo "browser-test.sh: willow serve did not start" >&2
    exit 1
fi
export WILLOW_URL
# The auth test starts its own server (with --auth keys) from the same binary.
export WILLOW_BIN="$willow"
export WILLOW_ARTIFACTS="$root/target/browser-artifacts"
mkdir -p "$WILLOW_ARTIFACTS"
echo "browser-test.sh: willow serve at $WILLOW_URL, chromium $("$CHROMIUM" --version 2>/dev/null | tail -n1)"

if [[ "$mode" == timing ]]; then
    node tests/browser/timing-100k.mjs
else
    # One file at a time: the tests share the one server and its two workers.
    if ! node --test --test-concurrency=1 "${tests[@]}"; then
        echo "browser-test.sh: FAILED; the server's log (last 40 lines):" >&2
        tail -n 40 "$server_out" "$data_dir/server.err" >&2
        if [[ -n "${WILLOW_KEEP_LOG:-}" ]]; then cp "$server_out" "$WILLOW_KEEP_LOG"; fi
        exit 1
    fi
fi
