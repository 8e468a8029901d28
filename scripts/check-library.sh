#!/usr/bin/env bash
# The numeric library (crates/willow) is a library a CAD pipeline adds in one line: its normal
# dependency tree holds no async runtime, transport or database and at most 120 packages, and it
# builds with no node or npm on PATH (no build script in its tree needs them, or the network).
# Run by .ci/run; quick after the first run (its own target dir, kept under target/).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"

max_packages=120
forbidden='tokio|axum|tonic|hyper|rusqlite|async-nats|prost|utoipa|jsonwebtoken|reqwest'

tree="$(cargo tree -p willow -e normal --prefix none --locked | sed 's/ (\*)$//' | sort -u)"
count="$(printf '%s\n' "$tree" | wc -l)"
bad="$(printf '%s\n' "$tree" | grep -E "^($forbidden) v" || true)"
if [[ -n "$bad" ]]; then
    echo "check-library.sh: the library's tree holds service packages:" >&2
    printf '%s\n' "$bad" >&2
    exit 1
fi
if (( count > max_packages )); then
    echo "check-library.sh: the library's tree has $count packages (at most $max_packages)" >&2
    exit 1
fi
echo "check-library.sh: cargo tree -p willow -e normal: $count packages, none of $forbidden"

# A PATH without node, npm and npx: every other program of the current PATH, linked into one
# directory (cargo, the C compiler for metis-sys, ...). Built in a target dir of its own so
# that the library and its dependencies really build here, not from the workspace's cache.
bin="$root/target/no-node-bin"
rm -rf "$bin"
mkdir -p "$bin"
IFS=: read -r -a dirs <<<"$PATH"
for dir in "${dirs[@]}"; do
    [[ -d "$dir" ]] || continue
    for exe in "$dir"/*; do
        name="${exe##*/}"
        case "$name" in node | nodejs | npm | npx | corepack) continue ;; esac
        [[ -x "$exe" && ! -e "$bin/$name" ]] && ln -s "$exe" "$bin/$name"
    done
done
if PATH="$bin" command -v node >/dev/null || PATH="$bin" command -v npm >/dev/null; then
    echo "check-library.sh: could not take node and npm off PATH" >&2
    exit 1
fi
PATH="$bin" cargo build -p willow --locked --target-dir "$root/target/library-only" --quiet
echo "check-library.sh: cargo build -p willow: built with no node or npm on PATH"
