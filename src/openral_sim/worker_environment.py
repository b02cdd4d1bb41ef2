"""The environment an evaluation's worker processes start with: the threads each numeric library may use.

numpy's OpenBLAS, OpenMP (PyTorch, MKL) and their kin size their thread pools from environment
variables once, when they load, and a spawned worker process imports them before any code of
ours runs in it (unpickling its first task imports the modules it names). So the limits are put
in the worker's environment before it starts: :func:`spawning_with` sets them in this process's
environment while the workers are started (a spawned process copies the environment it is
started with; :mod:`multiprocessing` has no per-process environment), and a Ray task gets them in
its ``runtime_env``. ONNX Runtime reads none of these: the ``onnx_policy`` skill sizes its session
from :data:`~openral_rskill.worker_threads.THREADS_PER_WORKER_VARIABLE`, as ``lerobot_policy``
sizes PyTorch's pool, unless the skill's own parameters name a count.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
from collections.abc import Iterator, Mapping
from typing import Any

from openral_rskill.worker_threads import THREADS_PER_WORKER_VARIABLE

LIBRARY_VARIABLES = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
)
"""What OpenMP, OpenBLAS, MKL, Accelerate and numexpr read for their thread counts as they load."""

_SPAWNING = threading.Lock()


def worker_environment(threads: int | None) -> dict[str, str]:
    """The variables a worker process starts with for ``threads`` threads per library (none for ``None``)."""
    if threads is None:
        return {}
    return dict.fromkeys((THREADS_PER_WORKER_VARIABLE, *LIBRARY_VARIABLES), str(threads))


@contextlib.contextmanager
def spawning_with(environment: Mapping[str, str]) -> Iterator[None]:
    """While inside, processes started from here get ``environment`` over this process's own variables.

    This process's environment is changed for that time and restored after, under a lock, so
    that two evaluators starting workers at once do not restore each other's values. Libraries
    already loaded here do not read it again.
    """
    if not environment:
        yield
        return
    with _SPAWNING:
        saved = {name: os.environ.get(name) for name in environment}
        os.environ.update(environment)
        try:
            yield
        finally:
            for name, value in saved.items():
                if value is None:
                    os.environ.pop(name, None)
                else:
                    os.environ[name] = value


def thread_report() -> dict[str, Any]:
    """What this process's numeric libraries were told: the variables, and PyTorch's threads once it is loaded."""
    torch: Any = sys.modules.get("torch")
    return {
        "variables": {name: os.environ.get(name) for name in (THREADS_PER_WORKER_VARIABLE, *LIBRARY_VARIABLES)},
        "torch_threads": None if torch is None else int(torch.get_num_threads()),
    }
