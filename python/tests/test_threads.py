"""Two flows on two Python threads at once, and a proof that a flow releases the GIL."""

from __future__ import annotations

import sys
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

import willow_fair
from conftest import shared

PARAMS = dict(method="conformal", steps=6, until_converged=False, tau=0.2)


def test_two_flows_on_two_threads_match_sequential(spot):
    V, F = spot
    W, G = willow_fair.read(shared("denoise/Fandisk0.3_Noisy.obj"))
    jobs = [(V, F, PARAMS), (W, G, dict(steps=10))]
    sequential = [willow_fair.fair(a, b, **p) for a, b, p in jobs]
    start = threading.Barrier(2)

    def work(job):
        a, b, p = job
        start.wait()
        return willow_fair.fair(a, b, **p)

    with ThreadPoolExecutor(max_workers=2) as pool:
        concurrent = list(pool.map(work, jobs))
    for s, c in zip(sequential, concurrent):
        assert np.array_equal(s.vertices, c.vertices)
        assert (s.outcome, s.reason) == (c.outcome, c.reason)
        assert len(s.metrics) == len(c.metrics) > 0


def test_a_flow_releases_the_gil(spot):
    # With a switch interval of 1000 s the interpreter never takes the GIL from a thread that
    # holds it: another Python thread runs only when the holder releases it. The observer is
    # woken just before run() and records whether run() is still going when it gets to run:
    # True only if run() released the GIL (held throughout, the observer would run once the
    # main thread blocks in join(), after `running` is False). An order, not a timing.
    V, F = spot
    flow = willow_fair.Flow(V, F, **PARAMS)  # built before: only the run is observed
    ready, go = threading.Event(), threading.Event()
    running = [False]
    seen = []

    def observe():
        ready.set()
        go.wait()
        seen.append(running[0])

    observer = threading.Thread(target=observe)
    observer.start()
    ready.wait()
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1000.0)
    try:
        running[0] = True
        go.set()
        metrics = flow.run()
        running[0] = False
        observer.join()
    finally:
        sys.setswitchinterval(interval)
    assert len(metrics) == PARAMS["steps"]
    assert seen == [True]


def test_two_threads_stepping_one_flow_take_turns(spot):
    V, F = spot
    expected = willow_fair.fair(V, F, **PARAMS)
    flow = willow_fair.Flow(V, F, **PARAMS)
    steps = []

    def stepper():
        while (m := flow.step()) is not None:
            steps.append(m["step"])

    threads = [threading.Thread(target=stepper) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(steps) == list(range(1, PARAMS["steps"] + 1))
    assert np.array_equal(flow.vertices, expected.vertices)
