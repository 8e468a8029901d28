#!/usr/bin/env bash
# The Python package willow-fair (python/), end to end: a venv under target/python-package/
# with the pinned tools of python/tests/requirements.txt (maturin, pytest, numpy, trimesh;
# idempotent and quick when nothing changed: a stamp file records the hash of what was
# installed), the package installed into it by `pip install ./python` (maturin's release
# build, with the pinned maturin: no build isolation), the CLI binary the comparison tests
# run (`cargo build --release -p willow-service --bin willow`), then pytest on python/tests.
# With WILLOW_PYTHON_FRESH=1 (CI sets it), first `pip install ./python` into a new, empty venv
# exactly as a user does (build isolation: pip fetches maturin from PyPI) and one fair() there.
# Extra arguments go to pytest. `--bench` instead runs python/bench.py (nefertiti: fair() against
# the CLI's flow time).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$root/target}"
base="$CARGO_TARGET_DIR/python-package"
venv="$base/venv"
req="$root/python/tests/requirements.txt"
stamp="$venv/.willow-requirements.sha256"
python="${PYTHON:-python3}"
pip() { "$1/bin/python" -m pip --disable-pip-version-check --quiet "${@:2}"; }

want="$(sha256sum "$req" | cut -d' ' -f1)"
if [[ -x "$venv/bin/python" && -f "$stamp" && "$(cat "$stamp")" == "$want" ]] \
    && "$venv/bin/python" -c 'import maturin, pytest, numpy, trimesh' 2>/dev/null; then
    echo "python-package: $venv is up to date"
else
    [[ -x "$venv/bin/python" ]] || "$python" -m venv "$venv"
    echo "python-package: installing $req into $venv"
    pip "$venv" install -r "$req"
    echo "$want" > "$stamp"
fi

if [[ "${WILLOW_PYTHON_FRESH:-0}" == 1 ]]; then
    fresh="$base/fresh-venv"
    rm -rf "$fresh"
    "$python" -m venv "$fresh"
    echo "python-package: pip install ./python into a fresh venv ($fresh)"
    pip "$fresh" install "$root/python"
    "$fresh/bin/python" - <<'PY'
import numpy as np, willow_fair
V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
F = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
r = willow_fair.fair(V, F, method="mcf", steps=2)
print(f"python-package: fresh venv: willow_fair {willow_fair.__version__}: {r.outcome}")
PY
    rm -rf "$fresh"
fi

echo "python-package: pip install ./python (release build)"
# The venv's bin on PATH: maturin's build backend runs the `maturin` program.
PATH="$venv/bin:$PATH" pip "$venv" install --no-build-isolation --no-deps --force-reinstall \
    "$root/python"
echo "python-package: the CLI for the comparison tests"
cargo build --release --locked -p willow-service --bin willow --quiet
export WILLOW_CLI="$CARGO_TARGET_DIR/release/willow"

if [[ "${1:-}" == --bench ]]; then
    exec "$venv/bin/python" "$root/python/bench.py" "${@:2}"
fi
# From the root, so that python/willow_fair (the source, without the extension) does not shadow
# the installed package; no cache directory in the tree.
exec "$venv/bin/python" -m pytest -p no:cacheprovider "$root/python/tests" "$@"
