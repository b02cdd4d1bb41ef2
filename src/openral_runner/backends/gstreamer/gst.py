"""GStreamer through PyGObject, imported and initialised once, with errors that name the fix.

Every module of this package that touches a live pipeline imports ``Gst`` (and friends) from
here, so the import checks, the version pins and ``Gst.init`` live in one place.

Appsinks are driven through their action signals (``sink.emit("pull-sample")``), never through
``GstApp``'s methods: PyGObject fixes an element's Python class the first time it wraps one, so
if the application wrapped an appsink before ``GstApp`` was loaded (``Gst.parse_launch`` and
``get_by_name`` are enough), every appsink of the process stays a ``GstAppSink`` without
``pull_sample``. Signals and properties work whatever the class, so the import order cannot matter.

GStreamer links libunwind, whose ``_Unwind_*`` functions then serve the C++ libraries loaded
after it. An exception raised through the system unwinder (libgcc_s, which libstdc++ had bound to
when MuJoCo loaded it) and resumed through libunwind aborts the process: pyarrow reading a damaged
dataset, or writing to a full disk, would end a recording with SIGABRT instead of an error. So
libgcc_s is put in the global symbol scope first, and every library loaded later binds to it.
"""

from __future__ import annotations

import contextlib
import ctypes
import sys

from openral_core import ROSConfigError, ROSDependencyMissing


def _one_cxx_unwinder() -> None:
    """Put libgcc_s, the C++ unwinder, in the global symbol scope ahead of GStreamer's libunwind (Linux)."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError):  # no libgcc_s (a musl system): nothing to put first
            ctypes.CDLL("libgcc_s.so.1", mode=ctypes.RTLD_GLOBAL)


_one_cxx_unwinder()

try:
    import gi

    gi.require_version("Gst", "1.0")
    gi.require_version("GstApp", "1.0")
    gi.require_version("GstVideo", "1.0")
    from gi.repository import GLib, GObject, Gst, GstApp, GstVideo
except ImportError as exc:  # pragma: no cover - exercised only without the extra
    raise ROSDependencyMissing("gi", extra="gstreamer", needed_for="GStreamer cameras and branches") from exc
except ValueError as exc:  # pragma: no cover - gi present, typelibs missing
    raise ROSConfigError(
        f"GStreamer cameras need the GStreamer introspection data: {exc}",
        hint="apt-get install gir1.2-gstreamer-1.0 gir1.2-gst-plugins-base-1.0",
    ) from exc

Gst.init(None)

__all__ = ["GLib", "GObject", "Gst", "GstApp", "GstVideo"]
