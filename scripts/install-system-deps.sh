#!/usr/bin/env bash
# System packages pip cannot install, for the parts of openral that need them (Debian/Ubuntu, apt):
#   - the GStreamer camera backend: GStreamer with its plugins and the headers PyGObject builds
#     against (then: uv sync --extra gstreamer);
#   - the twin's camera (mujoco_camera): Mesa's EGL and OSMesa for headless OpenGL rendering;
#   - the web console's browser tests: Chromium and its WebDriver, run headless.
# The twin itself, the serial arm, OpenCV cameras, telemetry and the tests of all of these need
# none of it. Run as root, or as a user who may sudo.
set -euo pipefail
export DEBIAN_FRONTEND=noninteractive

PACKAGES=(
    gstreamer1.0-tools gstreamer1.0-plugins-base gstreamer1.0-plugins-good gstreamer1.0-plugins-bad
    gstreamer1.0-libav gir1.2-gstreamer-1.0 gir1.2-gst-plugins-base-1.0
    libgirepository1.0-dev libcairo2-dev pkg-config
    libegl1 libegl-mesa0 libgl1 libgles2 libosmesa6
    chromium chromium-driver
)

if ! command -v apt-get >/dev/null 2>&1; then
    echo "apt-get not found: install the equivalents of these packages with your system's package manager:" >&2
    printf '  %s\n' "${PACKAGES[@]}" >&2
    exit 1
fi
if [ "$(id -u)" = "0" ]; then SUDO=""; else SUDO="sudo"; fi
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends "${PACKAGES[@]}" >/dev/null
echo "system packages installed; for the GStreamer backend also run: uv sync --extra gstreamer"
