"""pyarrow's errors stay Python exceptions in a process that also runs the twin and a GStreamer camera.

MuJoCo, then GStreamer (which links libunwind), then pyarrow: in that load order a C++ exception
inside pyarrow (a damaged table read, a write to a full disk) must not abort the whole process.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = """
import resource, signal, sys
import mujoco  # the twin's libraries first, as a deployment builds its HAL first
import openral_runner.backends.gstreamer.gst  # then a GStreamer camera's
import pyarrow as pa
import pyarrow.parquet as pq

folder = sys.argv[1]
with open(folder + "/damaged.parquet", "wb") as damaged:
    damaged.write(b"PAR1" + bytes(200))
try:
    pq.read_table(folder + "/damaged.parquet")
except pa.ArrowException as exc:
    print("read:", type(exc).__name__)
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, 64 * 1024))  # a disk that fills up
try:
    pq.write_table(pa.table({"frame_index": list(range(1_000_000))}), folder + "/full.parquet")
except OSError as exc:
    print("write:", type(exc).__name__)
"""


@pytest.mark.gstreamer
def test_a_damaged_read_and_a_full_disk_raise_instead_of_aborting(tmp_path: Path) -> None:
    pytest.importorskip("mujoco", reason="needs the 'twin' extra")
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(tmp_path)], capture_output=True, text=True, timeout=120, check=False
    )
    assert proc.returncode == 0, f"exit {proc.returncode}: {proc.stderr}"
    assert proc.stdout.split("\n")[:2] == ["read: ArrowInvalid", "write: OSError"], proc.stdout
