"""Thread counts of the numerical libraries under the stages at the working size, and the
two clouds' own stages side by side.

pykdtree's queries run on an OpenMP team and NumPy's matrix products on OpenBLAS's threads.
Between calls, the threads of both spin-wait (for up to ~0.1 s) before they sleep, and on a
small machine they take the cores from whatever runs next: on 2 cores, verification right
after Sinkhorn took 2-4x its time (about 60 against 17 ms at 1024 points), and the geometry of
the two clouds, computed in two Python threads, ran four library threads on two cores. The
stages from the working subsets to the verified pose therefore run their array work on one
thread per Python thread (:func:`one_thread_per_caller`); the stages on the full clouds (ICP,
the fitness evaluation), where a query covers 10^4 - 10^5 points, keep the libraries' own
counts. Measured on the 2-core machine, 1024-point pair of ``benchmarks/latency.py``, three
alternating rounds of fresh processes, this limit on and off: verification 49-72 against
87-94 ms; geometry and Sinkhorn the same within the machine's drift.

threadpoolctl (BSD-3, the scikit-learn team's) finds the libraries loaded in the process and sets
and restores their counts; onnxruntime's own thread pools are not among them and keep their
``threads``.

The stages done once per cloud (the working subset and its extent, the geometry, verification's
normals) run for the two clouds at once (:func:`per_cloud`), on one long-lived worker thread and
the caller's. Measured in one process on
the 2-core machine, 1024-point clouds of ``benchmarks/latency.py``, three rounds: working subsets
3.6-3.7 ms one after the other, 2.5-3.5 ms side by side; geometry 6.6-8.4 against 4.5-5.5 ms.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import TypeVar

from threadpoolctl import ThreadpoolController

T = TypeVar("T")

_CONTROLLER: ThreadpoolController | None = None
_LOCK = threading.Lock()


def _controller() -> ThreadpoolController:
    global _CONTROLLER
    with _LOCK:
        if _CONTROLLER is None:
            # After numpy, scipy and pykdtree are imported (this package imports them first).
            _CONTROLLER = ThreadpoolController()
        return _CONTROLLER


@contextmanager
def one_thread_per_caller() -> Iterator[None]:
    """OpenMP (in the calling thread) and BLAS (process-wide) on one thread inside the block,
    their previous counts restored after it. Enter it in each Python thread that does the work:
    OpenMP's count is per thread. BLAS's is process-wide, and threadpoolctl lets one thread at a
    time hold it: a block entered while another thread holds BLAS limits only its OpenMP."""
    with _controller().limit(limits=1):
        yield


class ResidentThread:
    """One worker thread per process, started on first use and kept between pairs (a thread
    started for every pair costs about half a millisecond); a forked child, which has no copy of
    it, starts its own when it first needs one.

    Args:
        name: the thread's name prefix (seen in profilers and ``threading.enumerate()``).
        initializer: optional callable run once on the thread when it starts; it must not
            raise (a thread pool whose initializer raises runs nothing).
    """

    def __init__(self, name: str, initializer: Callable[[], object] | None = None):
        self._name = name
        self._initializer = initializer
        self._executor: ThreadPoolExecutor | None = None
        self._lock = threading.Lock()
        os.register_at_fork(after_in_child=self._forget)

    def executor(self) -> ThreadPoolExecutor:
        """The thread, as a one-worker executor (started here on the first call)."""
        with self._lock:
            if self._executor is None:
                self._executor = ThreadPoolExecutor(
                    max_workers=1, thread_name_prefix=self._name, initializer=self._initializer
                )
            return self._executor

    def _forget(self) -> None:
        self._executor, self._lock = None, threading.Lock()


# The worker that does the source cloud's share of per_cloud.
_CLOUD_THREAD = ResidentThread("logdesc-rt-cloud")


def per_cloud(function: Callable[..., T], source: tuple, target: tuple) -> tuple[T, T]:
    """``(function(*source), function(*target))``, the two calls at once: the source's on a worker
    thread, the target's on the calling one, each with its libraries on one thread
    (:func:`one_thread_per_caller`). The per-cloud stages (working subset, geometry) are kNN
    queries, compiled kernels and array work that release the interpreter lock, so two clouds
    take about the time of one on two cores. An exception in either call is raised here."""

    def source_on_the_worker() -> T:
        with _controller().select(user_api="openmp").limit(limits=1):
            return function(*source)

    # BLAS's count is process-wide and threadpoolctl lets one thread at a time set it: the caller
    # holds it at one for both calls, and the worker sets only its own OpenMP count.
    with one_thread_per_caller():
        source_job = _CLOUD_THREAD.executor().submit(source_on_the_worker)
        target_result = function(*target)
        return source_job.result(), target_result
