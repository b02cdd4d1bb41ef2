"""The CPU threads an evaluation worker process allows each numeric library, as a skill reads it.

Worker processes that each spread their math over every core fight over the cores
(oversubscription), and that is what caps an evaluation's scaling. So an evaluation starts its
worker processes with :data:`THREADS_PER_WORKER_VARIABLE` set (beside the BLAS and OpenMP
variables that numpy and PyTorch read). A skill that builds a thread pool of its own (an ONNX
Runtime session, PyTorch's intra-op pool) sizes it from :func:`threads_per_worker` unless its
parameters name a count: the skill's own request wins.
"""

from __future__ import annotations

import os

THREADS_PER_WORKER_VARIABLE = "OPENRAL_THREADS_PER_WORKER"
"""Set in an evaluation's worker processes: the threads each numeric library there may use."""


def threads_per_worker() -> int | None:
    """The threads this process's evaluation allows a numeric library; ``None`` outside such a worker."""
    value = os.environ.get(THREADS_PER_WORKER_VARIABLE, "")
    return int(value) if value.isdigit() and int(value) >= 1 else None
