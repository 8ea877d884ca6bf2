"""Thread counts of the numerical libraries under the stages at the working size.

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
"""

from __future__ import annotations

import threading
from contextlib import contextmanager
from typing import Iterator

from threadpoolctl import ThreadpoolController

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
    OpenMP's count is per thread."""
    with _controller().limit(limits=1):
        yield
