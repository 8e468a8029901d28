#!/usr/bin/env bash
# Makes the virtualenv that scripts/cgal-fill-holes.py runs in: CGAL's SWIG bindings from PyPI
# (package `cgal`, CGAL 6.0.1, GPL-3.0-or-later) and the numpy they import, at pinned versions.
# The project uses that script to pin CGAL's hole-filling figures; nothing in CI needs this.
#
# The venv lives at ${WILLOW_CGAL_VENV:-$HOME/.cache/willow/cgal-venv}, outside the repository.
# Idempotent: when the venv already has the pinned versions it only checks them. Progress goes
# to stderr; the last line (the only one on stdout) is the venv's python, so
#     py="$(scripts/cgal-fill-holes-setup.sh)" && "$py" scripts/cgal-fill-holes.py IN.obj OUT.obj
# works. The `cgal` wheels are CPython-version specific (3.11 is what the project uses).
set -euo pipefail

venv="${WILLOW_CGAL_VENV:-$HOME/.cache/willow/cgal-venv}"
python="${PYTHON:-python3}"
pins=(cgal==6.0.1.post202410241521 numpy==2.4.6)

have_pins() {
    "$venv/bin/python" - "${pins[@]}" <<'EOF' 2>/dev/null
import sys
from importlib.metadata import version
for pin in sys.argv[1:]:
    name, want = pin.split("==")
    if version(name) != want:
        sys.exit(1)
from CGAL import CGAL_Polygon_mesh_processing  # noqa: F401  (the .so files load)
EOF
}

if [[ -x "$venv/bin/python" ]] && have_pins; then
    echo "cgal-fill-holes-setup: $venv is up to date" >&2
else
    if [[ ! -x "$venv/bin/python" ]]; then
        echo "cgal-fill-holes-setup: creating $venv with $("$python" --version 2>&1)" >&2
        mkdir -p "$(dirname "$venv")"
        "$python" -m venv "$venv"
    fi
    echo "cgal-fill-holes-setup: installing ${pins[*]}" >&2
    "$venv/bin/python" -m pip install --quiet --disable-pip-version-check "${pins[@]}" >&2
    have_pins || { echo "cgal-fill-holes-setup: the CGAL bindings do not import" >&2; exit 1; }
    echo "cgal-fill-holes-setup: ready" >&2
fi
echo "$venv/bin/python"
