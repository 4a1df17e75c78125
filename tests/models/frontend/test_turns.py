"""The decode threads' turns (models/frontend/turns.py): keys served in turn, each key in order, any
waiting call taken while a thread is free, a cancelled call never run, an exception kept for its caller."""

from __future__ import annotations

import threading

import pytest

from models.frontend.turns import TurnPool


def test_keys_take_turns_and_each_keys_calls_keep_their_order() -> None:
    pool, ran, gate, started = TurnPool(1, "t"), [], threading.Event(), threading.Event()
    first = pool.submit(lambda: (started.set(), gate.wait(30)), "a")  # holds the one thread
    assert started.wait(30)  # taken: the others queue behind it
    futs = [pool.submit(lambda i=i: ran.append(("a", i)), "a") for i in range(4)]
    futs += [pool.submit(lambda i=i: ran.append(("b", i)), "b") for i in range(2)]
    futs += [pool.submit(lambda: ran.append(("c", 0)), "c")]
    assert pool.waiting() == {"a": 4, "b": 2, "c": 1}
    gate.set()
    first.result(timeout=30)
    for f in futs:
        f.result(timeout=30)
    assert ran == [("a", 0), ("b", 0), ("c", 0), ("a", 1), ("b", 1), ("a", 2), ("a", 3)]
    assert pool.waiting() == {}


def test_one_key_is_first_in_first_out_and_every_thread_works() -> None:
    pool, barrier = TurnPool(3, "t"), threading.Barrier(3, timeout=30)
    # three calls that each wait for the other two: they finish only if three threads run them at once
    futs = [pool.submit(barrier.wait) for _ in range(3)]
    assert sorted(f.result(timeout=30) for f in futs) == [0, 1, 2]
    out: list[int] = []
    one = TurnPool(1, "t")
    for f in [one.submit(lambda i=i: out.append(i)) for i in range(20)]:
        f.result(timeout=30)
    assert out == list(range(20))


def test_a_cancelled_call_never_runs_and_an_exception_reaches_its_caller() -> None:
    pool, ran, gate = TurnPool(1, "t"), [], threading.Event()
    first = pool.submit(lambda: gate.wait(30), "a")
    skipped = pool.submit(lambda: ran.append("skipped"), "a")
    failing = pool.submit(lambda: 1 / 0, "b")
    after = pool.submit(lambda: ran.append("after"), "a")
    assert skipped.cancel()
    gate.set()
    first.result(timeout=30)
    with pytest.raises(ZeroDivisionError):
        failing.result(timeout=30)
    after.result(timeout=30)
    assert ran == ["after"]


def test_a_dropped_pools_threads_end() -> None:
    """Every encoder an evaluation builds has its decode threads: a pool no longer referenced lets them
    end (as a ThreadPoolExecutor's do), or a long loop of encoders leaks two threads each."""
    import gc
    import time

    def names() -> set[str]:
        return {t.name for t in threading.enumerate() if t.name.startswith("dropped-")}

    for i in range(5):
        pool = TurnPool(2, f"dropped-{i}")
        assert pool.submit(lambda: 7).result(timeout=30) == 7
    assert names()  # the last one's are alive while it is referenced
    del pool
    gc.collect()
    deadline = time.monotonic() + 30
    while names():
        assert time.monotonic() < deadline, names()
        time.sleep(0.01)


def test_close_cancels_the_waiting_calls_waits_for_the_running_ones_and_takes_no_more() -> None:
    pool, ran, gate, started = TurnPool(1, "closing"), [], threading.Event(), threading.Event()
    running = pool.submit(lambda: (started.set(), gate.wait(30), ran.append("running")), "a")
    assert started.wait(30)
    waiting = [pool.submit(lambda k=k: ran.append(k), k) for k in ("a", "b")]
    closer = threading.Thread(target=pool.close)
    closer.start()
    closer.join(0.2)
    assert closer.is_alive()  # the running call is waited for
    assert all(f.cancelled() for f in waiting)
    gate.set()
    closer.join(30)
    assert not closer.is_alive() and running.done() and ran == ["running"]
    assert not any(t.name.startswith("closing-") for t in threading.enumerate())
    with pytest.raises(RuntimeError):
        pool.submit(lambda: None, "a")
