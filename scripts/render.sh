#!/usr/bin/env bash
# Renders meshes side by side to a PNG, headless (scripts/render/render.py: flat shading, one
# shared framing). Installs its pinned numpy and pillow from PyPI into target/render-tools/ on
# first use. Example, a denoising pair and Willow's result at the defaults:
#   cargo run --release -- fair ../shared/meshes/denoise/Fandisk0.3_Noisy.obj -o /tmp/fandisk.obj
#   scripts/render.sh docs/images/fandisk.png noisy=../shared/meshes/denoise/Fandisk0.3_Noisy.obj \
#       willow=/tmp/fandisk.obj clean=../shared/meshes/denoise/Fandisk0.3_Original.obj
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$root/target/render-tools"
if [[ ! -x "$venv/bin/python" ]] || ! "$venv/bin/python" -c 'import numpy, PIL' 2>/dev/null; then
    python3 -m venv "$venv"
    "$venv/bin/python" -m pip install --quiet --disable-pip-version-check numpy==2.3.5 pillow==12.0.0
fi
exec "$venv/bin/python" "$root/scripts/render/render.py" "$@"
