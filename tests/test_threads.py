"""The numerical libraries run on one thread per caller inside the working-size stages, and get
their counts back after."""

from __future__ import annotations

import pykdtree.kdtree  # noqa: F401 (loads the OpenMP runtime the geometry uses)
from threadpoolctl import threadpool_info

from logdesc_rt.threads import one_thread_per_caller


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
