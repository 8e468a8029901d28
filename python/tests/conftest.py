"""Shared fixtures: the repository's test meshes, the shared meshes and the CLI binary.

A test that needs /work/shared (the shared meshes beside the checkout, or
$WILLOW_SHARED_MESHES) or the CLI ($WILLOW_CLI, else target/release/willow) fails with a
message saying where it looked: it never skips.
"""

from __future__ import annotations

import os
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
DATA = ROOT / "crates" / "willow" / "tests" / "data"
SPOT = DATA / "spot_triangulated.obj"


def shared_meshes() -> pathlib.Path:
    env = os.environ.get("WILLOW_SHARED_MESHES")
    return pathlib.Path(env) if env else ROOT.parent / "shared" / "meshes"


def shared(name: str) -> pathlib.Path:
    path = shared_meshes() / name
    if not path.is_file():
        pytest.fail(
            f"{path} is needed by this test: the shared meshes are part of the test data "
            f"(../shared/meshes beside the checkout, or $WILLOW_SHARED_MESHES)",
            pytrace=False,
        )
    return path


def cli() -> pathlib.Path:
    env = os.environ.get("WILLOW_CLI")
    path = pathlib.Path(env) if env else ROOT / "target" / "release" / "willow"
    if not os.access(path, os.X_OK):
        pytest.fail(
            f"the CLI binary {path} is needed by this test: build it with "
            f"`cargo build --release -p willow-service --bin willow` (scripts/python-package.sh "
            f"does) or set $WILLOW_CLI",
            pytrace=False,
        )
    return path


@pytest.fixture(scope="session")
def spot():
    import willow_fair

    return willow_fair.read(SPOT)
