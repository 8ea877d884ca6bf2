"""The numerical libraries run on one thread per caller inside the working-size stages, and get
their counts back after."""

from __future__ import annotations

import multiprocessing
import os
import threading

import pykdtree.kdtree  # noqa: F401 (loads the OpenMP runtime the geometry uses)
import pytest
from threadpoolctl import threadpool_info

from logdesc_rt.threads import ResidentThread, one_thread_per_caller, per_cloud


def _counts() -> dict[str, int]:
    return {info["user_api"]: info["num_threads"] for info in threadpool_info()}


def test_one_thread_inside_the_block_and_the_counts_restored_after():
    before = _counts()
    assert {"blas", "openmp"} <= set(before), before
    with one_thread_per_caller():
        assert set(_counts().values()) == {1}
        with one_thread_per_caller():  # nested (prepare inside match): still one, then restored
            assert set(_counts().values()) == {1}
        assert set(_counts().values()) == {1}
    assert _counts() == before


def test_per_cloud_returns_both_calls_in_order_each_on_one_library_thread():
    def probe(name):
        return name, threading.current_thread().name, set(_counts().values())

    (source, source_thread, source_counts), (target, target_thread, target_counts) = per_cloud(
        probe, ("source",), ("target",)
    )
    assert (source, target) == ("source", "target")
    assert source_thread != target_thread == threading.current_thread().name  # the two ran apart
    assert source_counts == target_counts == {1}


def test_per_cloud_many_times_leaves_the_counts_as_they_were():
    before = _counts()
    for _ in range(50):
        counts = per_cloud(lambda name: set(_counts().values()), ("source",), ("target",))
        assert counts == ({1}, {1})
    assert _counts() == before


def test_per_cloud_raises_the_source_calls_error_and_still_works_after():
    def fails_on_source(name):
        if name == "source":
            raise ValueError("bad source cloud")
        return name

    with pytest.raises(ValueError, match="bad source cloud"):
        per_cloud(fails_on_source, ("source",), ("target",))
    assert per_cloud(str.upper, ("a",), ("b",)) == ("A", "B")


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork on this platform")
def test_per_cloud_works_in_a_forked_child():
    per_cloud(str.upper, ("a",), ("b",))  # the parent's worker thread exists before the fork
    context = multiprocessing.get_context("fork")
    with context.Pool(1) as pool:
        assert pool.apply(per_cloud, (str.upper, ("a",), ("b",))) == ("A", "B")


def test_a_resident_thread_starts_once_runs_its_initializer_once_and_keeps_its_name():
    started = []
    resident = ResidentThread("test-resident", initializer=lambda: started.append(threading.get_ident()))
    names = {resident.executor().submit(lambda: threading.current_thread().name).result() for _ in range(5)}
    assert resident.executor() is resident.executor()
    assert len(names) == 1 and next(iter(names)).startswith("test-resident")
    assert len(started) == 1 and started[0] != threading.get_ident()


_FORKED = ResidentThread("test-resident-forked")


def _thread_ident_in_child() -> int:
    return _FORKED.executor().submit(threading.get_ident).result()


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork on this platform")
def test_a_resident_thread_is_started_afresh_in_a_forked_child():
    parent_ident = _FORKED.executor().submit(threading.get_ident).result()  # exists before the fork
    with multiprocessing.get_context("fork").Pool(1) as pool:
        # Without a fresh start the child's call would wait forever on the parent's thread.
        child_ident = pool.apply_async(_thread_ident_in_child).get(timeout=30)
    assert isinstance(child_ident, int)
    assert _FORKED.executor().submit(threading.get_ident).result() == parent_ident
