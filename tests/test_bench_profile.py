"""tools/bench_profile.py's wait timer against a kernel whose time a plain finish() measures:
the wait is found where the host blocks (a blocking read, a dropped read's event, a
finish), the launch returns at once, the shares add up to the wall time, and pyopencl is
as it was afterwards."""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tools"))

from bench_profile import WaitTimer  # noqa: E402

BUSY = """
__kernel void busy(__global float *x, int n) {
    int i = get_global_id(0);
    float a = x[i];
    for (int k = 0; k < n; k++) a = a * 0.9999f + 0.5f * sin(a);
    x[i] = a;
}
"""
ITEMS = 4096


@pytest.fixture(scope="module")
def busy():
    """launch(): the kernel enqueued on a profiling queue, not waited for; its event. Its
    loop is long enough for a run of at least 50 ms on the device (the timings' noise is a
    few ms)."""
    import pyopencl as cl

    from clrefract.runtime import default_runtime

    rt = default_runtime()
    q = cl.CommandQueue(rt.context, properties=cl.command_queue_properties.PROFILING_ENABLE)
    kernel = cl.Program(rt.context, BUSY).build().busy
    x = np.ones(ITEMS, np.float32)
    buf = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=x)
    loop = [1]

    def launch():
        return kernel(q, (ITEMS,), (32,), buf, np.int32(loop[0]))

    launch().wait()  # the driver builds the launch's size on first use
    while loop[0] < 1 << 26:
        event = launch()
        event.wait()
        if ran(event) > 0.05:
            break
        loop[0] *= 4
    return cl, q, launch, x, buf


def ran(event) -> float:
    """The kernel's own run (its event's profile), seconds."""
    return 1e-9 * (event.profile.end - event.profile.start)


def test_the_wait_is_the_kernel_and_the_shares_add_up(busy):
    """A kernel's time is waited in the call that blocks, as a plain finish() waits for it;
    the launch is a small part of it, and host + waited make up the wall time. A loaded
    machine stretches the kernel from run to run: each wait is compared with its own
    kernel's run (its event's profile), and the medians of four runs are compared."""
    cl, q, launch, x, buf = busy
    blocking = lambda: cl.enqueue_copy(q, x, buf)  # noqa: E731
    dropped = lambda: cl.enqueue_copy(q, x, buf, is_blocking=False)  # noqa: E731
    for name, wait in (("enqueue_copy", blocking), ("enqueue_copy (dropped event)", dropped)):
        timer = WaitTimer()
        oracle, waited, off = [], [], []
        for _ in range(4):
            t0 = time.perf_counter()
            event = launch()
            q.finish()
            oracle.append((time.perf_counter() - t0) / ran(event))
            with timer:
                t0 = time.perf_counter()
                with timer.step() as s:
                    event = launch()
                    wait()
                    q.finish()  # nothing left to wait for
                wall = time.perf_counter() - t0
            waited.append(s["waited_s"] / ran(event))
            off.append(abs(s["host_s"] + s["waited_s"] - wall) / wall)
            # the enqueue is host work, and brief: its CPU time (its wall time grows where
            # the kernel's threads take the core from it)
            assert s["launches"] == 1 and s["launch_cpu_s"] < 0.02 * s["waited_s"], s
        assert np.median(waited) > 0.9, (name, waited)
        assert np.median(waited) > 0.8 * np.median(oracle), (name, waited, oracle)
        assert np.median(off) < 0.05, (name, off)
        assert timer.calls[name] == 4 and timer.calls["launch"] == 4, timer.calls
        assert timer.calls["finish"] == 4


def test_host_work_is_not_counted_and_pyopencl_is_restored(busy):
    """NumPy work between the launch and the wait is host time, however the kernel overlaps
    it; waits outside the timer, or on another thread, are not counted; afterwards
    pyopencl's functions are its own again."""
    cl, q, launch, x, buf = busy
    originals = (cl.enqueue_copy, cl.wait_for_events, cl.CommandQueue.finish, cl.Event.wait)
    a = np.random.default_rng(0).normal(size=(200, 200))
    with WaitTimer() as timer:
        with timer.step() as s:
            launch()
            t0 = time.perf_counter()
            for _ in range(5):
                a = np.linalg.qr(a)[0]
            numpy_s = time.perf_counter() - t0
            cl.wait_for_events([cl.enqueue_marker(q)])
        assert timer.calls["wait_for_events"] == 1 and timer.waited == s["waited_s"] > 0
        other = threading.Thread(target=lambda: (launch(), q.finish()))
        other.start()
        other.join()
        assert "finish" not in timer.calls  # another thread's
    assert s["host_s"] >= numpy_s and s["waited_s"] <= s["wall_s"] - numpy_s, (s, numpy_s)
    assert s["host_s"] + s["waited_s"] == pytest.approx(s["wall_s"], rel=1e-9)
    now = (cl.enqueue_copy, cl.wait_for_events, cl.CommandQueue.finish, cl.Event.wait)
    assert all(a is b for a, b in zip(now, originals))
    launch()
    q.finish()
    assert "finish" not in timer.calls and timer.waited == s["waited_s"]
