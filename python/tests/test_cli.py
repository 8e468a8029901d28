"""fair() against `willow fair ... --json` on the same file: the same surface to 1e-12, the
same outcome and reason, the same metric names and values (step_ms aside)."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest

import willow_fair
from conftest import SPOT, cli, shared


def run_cli(path, out, flags):
    done = subprocess.run(
        [str(cli()), "fair", str(path), "-o", str(out), "--json", *flags],
        capture_output=True, text=True, check=False,
    )
    assert done.returncode == 0, done.stderr
    lines = [json.loads(line) for line in done.stdout.splitlines()]
    return lines[:-1], lines[-1]


@pytest.mark.parametrize(
    "mesh, flags, params",
    [
        # The defaults of both: method denoise, 10 steps, every core (a noisy scan).
        ("denoise/Fandisk0.3_Noisy.obj", [], {}),
        ("spot", ["--method", "conformal", "--steps", "5", "--tau", "0.2"],
         dict(method="conformal", steps=5, tau=0.2)),
        ("spot", ["--method", "mcf", "--steps", "3", "--preserve", "volume", "--all-steps",
                  "--measure-deviation"],
         dict(method="mcf", steps=3, preserve="volume", until_converged=False,
              measure_deviation=True)),
    ],
)
def test_fair_is_the_cli_on_the_same_file(tmp_path, mesh, flags, params):
    path = SPOT if mesh == "spot" else shared(mesh)
    out = tmp_path / "out.obj"
    steps, last = run_cli(path, out, flags)
    V, F = willow_fair.read(path)
    result = willow_fair.fair(V, F, **params)
    Vc, Fc = willow_fair.read(out)
    assert np.array_equal(Fc, F)
    assert np.abs(result.vertices - Vc).max() <= 1e-12
    assert (result.outcome, result.reason) == (last["outcome"], last["reason"])
    assert len(result.metrics) == len(steps) > 0
    for mine, theirs in zip(result.metrics, steps):
        assert list(mine) == list(theirs)  # the same names, in the same order
        for key, value in theirs.items():
            if key != "step_ms":
                assert mine[key] == pytest.approx(value, rel=1e-12, abs=1e-15), key
