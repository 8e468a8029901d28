"""fair() against the CLI on nefertiti: the same file, the same parameters, the same run.

    scripts/python-package.sh --bench [--steps N] [--repeat R] [--mesh PATH]

Each repetition runs `willow fair MESH -o out.obj --json` with the method's flags and then, in
this process, `read` + `fair` + `write` of the same file with the same keywords (the CLI's
work: read, build the flow, N steps, write), and times both ends to end; it also sums each
run's per-step `step_ms`, and sets `fair()` alone against the CLI's flow time (its end to end
less the time `write(like=)` takes, which parses and writes the file as the CLI does). Printed:
the medians and the ratios (fair / CLI).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import statistics
import subprocess
import tempfile
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent
# Run as a script, python/ is on sys.path first: its willow_fair (the source, without the
# extension) must not shadow the installed package.
sys.path[:] = [p for p in sys.path if pathlib.Path(p or ".").resolve() != HERE]

import willow_fair  # noqa: E402


def main() -> None:
    shared = os.environ.get("WILLOW_SHARED_MESHES", str(ROOT.parent / "shared" / "meshes"))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default=os.path.join(shared, "nefertiti.obj"))
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--cli", default=os.environ.get("WILLOW_CLI", str(ROOT / "target/release/willow")))
    args = ap.parse_args()
    mesh = pathlib.Path(args.mesh)
    if not mesh.is_file():
        raise SystemExit(f"bench.py: {mesh} not found (the shared meshes, or --mesh)")
    flags = ["--method", "conformal", "--steps", str(args.steps), "--all-steps"]
    params = dict(method="conformal", steps=args.steps, until_converged=False)

    cli_wall, cli_steps, py_wall, py_steps = [], [], [], []
    py_fair, cli_flow = [], []
    with tempfile.TemporaryDirectory() as tmp:
        out = pathlib.Path(tmp) / "out.obj"
        for _ in range(args.repeat):
            t = time.perf_counter()
            done = subprocess.run([args.cli, "fair", str(mesh), "-o", str(out), "--json", *flags],
                                  capture_output=True, text=True, check=True)
            cli_wall.append(time.perf_counter() - t)
            lines = [json.loads(line) for line in done.stdout.splitlines()[:-1]]
            cli_steps.append(sum(m["step_ms"] for m in lines) / 1e3)

            t0 = time.perf_counter()
            V, F = willow_fair.read(mesh)
            t1 = time.perf_counter()
            r = willow_fair.fair(V, F, **params)
            t2 = time.perf_counter()
            willow_fair.write(out, r.vertices, F, like=mesh)
            t3 = time.perf_counter()
            py_wall.append(t3 - t0)
            py_fair.append(t2 - t1)
            # write(like=) parses the file again and writes it back: the CLI's own I/O
            # (one parse, one write) is about that.
            cli_flow.append(cli_wall[-1] - (t3 - t2))
            py_steps.append(sum(m["step_ms"] for m in r.metrics) / 1e3)
            assert len(r.metrics) == len(lines) == args.steps

    med = statistics.median
    print(f"mesh {mesh.name}: {len(V)} vertices, {len(F)} faces; conformal, {args.steps} steps, "
          f"{args.repeat} runs each, medians (every core: threads 0 in both)")
    print(f"  CLI  willow fair   : {med(cli_wall):7.3f} s end to end, {med(cli_steps):7.3f} s in steps")
    print(f"  Python read+fair+write: {med(py_wall):7.3f} s end to end, {med(py_steps):7.3f} s in steps")
    print(f"  fair() alone       : {med(py_fair):7.3f} s; the CLI's flow (end to end less "
          f"a parse and a write): {med(cli_flow):7.3f} s")
    print(f"  ratio fair / CLI   : {med(py_wall) / med(cli_wall):.3f} end to end, "
          f"{med(py_steps) / med(cli_steps):.3f} in steps, "
          f"{med(py_fair) / med(cli_flow):.3f} fair() against the CLI's flow")


if __name__ == "__main__":
    main()
