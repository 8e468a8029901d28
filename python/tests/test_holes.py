"""fill_holes on arrays: holes cut here into spot are closed, the caller's numbering kept."""

from __future__ import annotations

import numpy as np
import pytest

import willow_fair


def cut(V: np.ndarray, F: np.ndarray, centre: int, radius: float) -> np.ndarray:
    """F without the faces whose centroid is within radius of vertex `centre`."""
    centroids = V[F].mean(axis=1)
    return F[np.linalg.norm(centroids - V[centre], axis=1) > radius]


def edge_counts(F: np.ndarray) -> np.ndarray:
    edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return counts


def test_a_cut_hole_is_closed_fair_and_the_callers_arrays_come_first(spot):
    V, F = spot
    diagonal = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    holed = cut(V, F, 100, 0.05 * diagonal)
    removed = len(F) - len(holed)
    assert removed > 20
    assert (edge_counts(holed) == 1).any()

    V2, F2, filled, left_open = willow_fair.fill_holes(V, holed)
    assert (filled, left_open) == (1, [])
    assert len(V2) > len(V) and len(F2) > len(holed)
    np.testing.assert_array_equal(V2[: len(V)], V)
    np.testing.assert_array_equal(F2[: len(holed)], holed)
    assert (edge_counts(F2) == 2).all(), "closed: every edge has two faces"
    # The patch lies where the cut surface was: each new vertex within a mean edge of the
    # vertices the cut left without a face (a flat or wild patch would not).
    lone = np.setdiff1d(np.unique(F), np.unique(holed))
    new = V2[len(V) :]
    nearest = np.linalg.norm(new[:, None, :] - V[lone][None, :, :], axis=2).min(axis=1)
    edge = float(np.linalg.norm(V[F[:, 0]] - V[F[:, 1]], axis=1).mean())
    assert nearest.mean() < 0.5 * edge, (nearest.mean(), edge)


def test_max_leaves_larger_holes_open_and_the_mesh_as_it_was(spot):
    V, F = spot
    holed = cut(V, F, 100, 0.05 * float(np.linalg.norm(V.max(axis=0) - V.min(axis=0))))
    for small in (5, 1e-9):
        V2, F2, filled, left_open = willow_fair.fill_holes(V, holed, max=small)
        assert filled == 0 and len(left_open) == 1 and left_open[0] > 5
        np.testing.assert_array_equal(V2, V)
        np.testing.assert_array_equal(F2, holed)
    # A whole float is a length, not a count: 3.0 model units is larger than spot.
    assert willow_fair.fill_holes(V, holed, max=3.0).filled == 1
    assert willow_fair.fill_holes(V, holed, max=np.int64(1000)).filled == 1


def test_bad_sizes_are_refused_by_name(spot):
    V, F = spot
    with pytest.raises(ValueError, match="max: .*at least 3"):
        willow_fair.fill_holes(V, F, max=2)
    with pytest.raises(ValueError, match="max: "):
        willow_fair.fill_holes(V, F, max=-1.0)
    for bad in (True, "10", [3]):
        with pytest.raises(TypeError, match="max must be"):
            willow_fair.fill_holes(V, F, max=bad)
    with pytest.raises(ValueError, match="F must be"):
        willow_fair.fill_holes(V, F.astype(np.float64))
