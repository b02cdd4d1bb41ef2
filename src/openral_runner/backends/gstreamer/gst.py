"""GStreamer through PyGObject, imported and initialised once, with errors that name the fix.

Every module of this package that touches a live pipeline imports ``Gst`` (and friends) from
here, so the import checks, the version pins and ``Gst.init`` live in one place.

Appsinks are driven through their action signals (``sink.emit("pull-sample")``), never through
``GstApp``'s methods: PyGObject fixes an element's Python class the first time it wraps one, so
if the application wrapped an appsink before ``GstApp`` was loaded (``Gst.parse_launch`` and
``get_by_name`` are enough), every appsink of the process stays a ``GstAppSink`` without
``pull_sample``. Signals and properties work whatever the class, so the import order cannot matter.
"""

from __future__ import annotations

from openral_core import ROSConfigError, ROSDependencyMissing

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
