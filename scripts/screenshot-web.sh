#!/usr/bin/env bash
# The README's picture of the web page, remade headless from the real program: builds the
# release binary, starts `willow serve` on a free loopback port with a temporary data dir,
# opens the page in Debian's headless chromium (playwright-core from tests/browser's pinned
# npm lock, as scripts/browser-test.sh does; software WebGL), submits a noisy scan with the
# default method, waits until the job has succeeded and its last frame is drawn, and saves a
# PNG of the page (1200×750 CSS pixels).
#
#   scripts/screenshot-web.sh                          -> docs/images/web-page.png
#   scripts/screenshot-web.sh OUT.png [MESH]           another output or mesh
#
# MESH defaults to ../shared/meshes/denoise/Fandisk0.3_Noisy.obj (beside the checkout, else
# /work/shared/meshes/...); without it, crates/willow/tests/data/spot_triangulated.obj.
# Installs chromium with apt-get (as root) when /usr/bin/chromium is missing, and the npm
# packages into tests/browser/node_modules.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"

out="$(realpath -m "${1:-docs/images/web-page.png}")"
mesh="${2:-}"
if [[ -z "$mesh" ]]; then
    for m in "$root/../shared/meshes/denoise/Fandisk0.3_Noisy.obj" \
        /work/shared/meshes/denoise/Fandisk0.3_Noisy.obj \
        "$root/crates/willow/tests/data/spot_triangulated.obj"; do
        if [[ -f "$m" ]]; then mesh="$m"; break; fi
    done
fi
mesh="$(realpath "$mesh")"

export CHROMIUM="${CHROMIUM:-/usr/bin/chromium}"
if [[ ! -x "$CHROMIUM" ]]; then
    if [[ "$(id -u)" != 0 ]]; then
        echo "screenshot-web.sh: $CHROMIUM is missing and this is not root: install the chromium package" >&2
        exit 1
    fi
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null
fi
if [[ ! -d tests/browser/node_modules/playwright-core ]] \
    || ! cmp -s tests/browser/package-lock.json tests/browser/node_modules/.package-lock-installed.json; then
    PLAYWRIGHT_SKIP_BROWSER_DOWNLOAD=1 npm ci --prefix tests/browser --no-audit --no-fund --loglevel=error
    cp tests/browser/package-lock.json tests/browser/node_modules/.package-lock-installed.json
fi

cargo build --release --bin willow --quiet
willow="${CARGO_TARGET_DIR:-$root/target}/release/willow"

data_dir="$(mktemp -d)"
server_pid=""
cleanup() {
    if [[ -n "$server_pid" ]]; then kill "$server_pid" 2>/dev/null || true; wait "$server_pid" 2>/dev/null || true; fi
    rm -rf "$data_dir"
}
trap cleanup EXIT

# Port 0: the server picks a free port and prints "listening on http://127.0.0.1:PORT".
"$willow" serve --addr 127.0.0.1:0 --data-dir "$data_dir/data" --log-format text \
    >"$data_dir/server.out" 2>"$data_dir/server.err" &
server_pid=$!
for _ in $(seq 1 100); do
    if grep -q '^listening on ' "$data_dir/server.out"; then break; fi
    if ! kill -0 "$server_pid" 2>/dev/null; then cat "$data_dir/server.err" >&2; exit 1; fi
    sleep 0.1
done
url="$(sed -n 's/^listening on //p' "$data_dir/server.out" | head -n1)"
[[ -n "$url" ]] || { echo "screenshot-web.sh: willow serve did not start" >&2; exit 1; }

mkdir -p "$(dirname "$out")"
WILLOW_URL="$url" node scripts/screenshot/web-page.mjs "$mesh" "$out"
echo "screenshot-web.sh: $out ($(stat -c %s "$out") bytes) of $mesh"
