"""Suite-wide policy and fixtures.

* On CI every optional backend is installed, so only ROS 2 tests may skip (and, on Python 3.11, the
  'lerobot' extra's, which .ci/run runs on Python 3.12).
* ``otel`` installs in-memory OpenTelemetry providers once per session (globals can be set only
  once per process); ``telemetry`` hands it to a test with spans cleared and a metric baseline.
* ``installed_package`` makes a real installed distribution (a third-party LeRobot plugin, say) in
  a folder of the test's own, for a child process's ``PYTHONPATH`` or for this process.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import sys
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path

import pytest
from opentelemetry import metrics, trace
from opentelemetry.sdk.metrics import MeterProvider
from opentelemetry.sdk.metrics.export import InMemoryMetricReader
from opentelemetry.sdk.trace import TracerProvider
from opentelemetry.sdk.trace.export import SimpleSpanProcessor
from opentelemetry.sdk.trace.export.in_memory_span_exporter import InMemorySpanExporter

# GEOS (shapely's library, under gym-pusht) crashes in ``intersection`` once libraries that other
# tests load into this one process (codecs, GStreamer plugins) have bound the same global symbols
# first: loaded before anything else, it binds its own.
with contextlib.suppress(ImportError):
    import shapely.geometry  # noqa: F401

ALLOWED_CI_SKIP = ("rclpy", "ROS 2")
"""ROS 2 has no installable distribution here; every other optional system package is installed by .ci/run."""

LEROBOT_ON_OLDER_PYTHON = "installs on Python 3.12 or newer"
"""The 'lerobot' extra's tests skip on Python 3.11 with this reason; .ci/run runs them again on Python 3.12."""

SYSTEM_DEPS = "scripts/install-system-deps.sh"
"""Installs the system packages pip cannot; skip reasons name it."""

GSTREAMER_REASON = f"needs GStreamer and PyGObject: run {SYSTEM_DEPS}, then uv sync --extra gstreamer"
GL_REASON = f"needs an off-screen OpenGL library (EGL or OSMesa): run {SYSTEM_DEPS}"


def offscreen_gl_available() -> bool:
    """Whether Mesa's EGL or OSMesa is installed (MuJoCo renders headless through one of them)."""
    import ctypes.util  # noqa: PLC0415

    return any(ctypes.util.find_library(name) for name in ("EGL", "OSMesa"))


def gstreamer_available() -> bool:
    """Whether PyGObject and GStreamer's introspection data import."""
    try:
        import gi  # noqa: PLC0415

        gi.require_version("Gst", "1.0")
        from gi.repository import Gst  # noqa: F401, PLC0415
    except (ImportError, ValueError):
        return False
    return True


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto``: one worker more than this process may use CPUs, one per CPU for the slow tail.

    About a fifth of the default run waits on child processes, sockets and live cameras, so a spare
    worker keeps the CPUs busy. The slow tail's tests start clusters and worker pools of their own.
    """
    cpus = len(os.sched_getaffinity(0))
    return cpus if config.getoption("markexpr") == "slow" else cpus + 1


def pytest_runtest_setup(item: pytest.Item) -> None:
    """Tests marked ``gl`` or ``gstreamer`` skip, naming the script that installs what they need."""
    if item.get_closest_marker("gl") is not None and not offscreen_gl_available():
        pytest.skip(GL_REASON)
    if item.get_closest_marker("gstreamer") is not None and not gstreamer_available():
        pytest.skip(GSTREAMER_REASON)


def _fail_ci_skip(report: pytest.TestReport | pytest.CollectReport) -> None:
    """Under CI=true a skip is a failure, unless it is ROS 2's."""
    if os.environ.get("CI") != "true" or not report.skipped:
        return
    reason = str(report.longrepr[-1]) if isinstance(report.longrepr, tuple) else str(report.longrepr)
    allowed_here = (*ALLOWED_CI_SKIP, LEROBOT_ON_OLDER_PYTHON) if sys.version_info < (3, 12) else ALLOWED_CI_SKIP
    if not any(allowed in reason for allowed in allowed_here):
        report.outcome = "failed"
        report.longrepr = f"skipped on CI, where every optional dependency must be installed: {reason}"


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]):
    outcome = yield
    _fail_ci_skip(outcome.get_result())


@pytest.hookimpl(hookwrapper=True)
def pytest_make_collect_report(collector: pytest.Collector):
    """A whole module skipped at import (``pytest.importorskip`` at module level) counts too."""
    outcome = yield
    _fail_ci_skip(outcome.get_result())


class OTelCapture:
    """The suite's in-memory telemetry: every finished span and the cumulative metric points.

    Metrics are cumulative over the whole session, so tests compare against a baseline taken
    with :meth:`reset` (the ``telemetry`` fixture does it) through :meth:`metric`.
    """

    def __init__(self) -> None:
        self.exporter = InMemorySpanExporter(max_spans=200_000)
        self.reader = InMemoryMetricReader()
        self.tracer_provider = TracerProvider()
        self.tracer_provider.add_span_processor(SimpleSpanProcessor(self.exporter))
        self.meter_provider = MeterProvider(metric_readers=[self.reader])
        trace.set_tracer_provider(self.tracer_provider)
        metrics.set_meter_provider(self.meter_provider)
        if trace.get_tracer_provider() is not self.tracer_provider:
            raise RuntimeError("a tracer provider was installed before the session's 'otel' fixture")
        self._baseline: dict[tuple[str, frozenset[tuple[str, object]]], tuple[float, float]] = {}

    def reset(self) -> None:
        """Forget finished spans and take the metric baseline."""
        self.exporter.clear()
        self._baseline = self._collect()

    def spans(self, name: str | None = None) -> list:
        """Finished spans since the last reset, optionally only those called ``name``."""
        return [s for s in self.exporter.get_finished_spans() if name is None or s.name == name]

    def metric(self, name: str, *, field: str = "value", **attributes: object) -> float:
        """Change since the last reset of a metric, summed over points whose attributes include ``attributes``.

        ``field`` is ``value`` (counters; histograms give their count) or ``sum`` (histograms).
        """
        index = 0 if field == "value" else 1
        total = 0.0
        for (metric, attrs), values in self._collect().items():
            if metric != name or not set(attributes.items()) <= attrs:
                continue
            before = self._baseline.get((metric, attrs), (0.0, 0.0))
            total += values[index] - before[index]
        return total

    def _collect(self) -> dict[tuple[str, frozenset[tuple[str, object]]], tuple[float, float]]:
        out: dict[tuple[str, frozenset[tuple[str, object]]], tuple[float, float]] = {}
        data = self.reader.get_metrics_data()
        if data is None:
            return out
        for resource in data.resource_metrics:
            for scope in resource.scope_metrics:
                for metric in scope.metrics:
                    for point in metric.data.data_points:
                        key = (metric.name, frozenset((point.attributes or {}).items()))
                        if hasattr(point, "count"):
                            out[key] = (float(point.count), float(point.sum))
                        else:
                            out[key] = (float(point.value), float(point.value))
        return out


@pytest.fixture(scope="session")
def otel() -> Iterator[OTelCapture]:
    """SDK tracer and meter providers with in-memory exporters, installed globally once per session."""
    capture = OTelCapture()
    yield capture
    capture.tracer_provider.shutdown()
    capture.meter_provider.shutdown()


@pytest.fixture
def telemetry(otel: OTelCapture) -> OTelCapture:
    """The session's in-memory telemetry, with spans cleared and the metric baseline taken."""
    otel.reset()
    return otel


@pytest.fixture(scope="session", autouse=True)
def state_home(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """``XDG_STATE_HOME`` of the session: policy servers the tests start keep their ids there, not in the user's."""
    folder = str(tmp_path_factory.mktemp("state"))
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("XDG_STATE_HOME", folder)
        yield folder


class DeployProcess:
    """``openral deploy`` in a child process of its own process group, as a user's shell or systemd starts it.

    stderr is read on a thread so the test can wait for a line (readiness) instead of sleeping.

    Args:
        args: Arguments after ``openral``.
        keys: Give it a pipe for standard input, for :meth:`press`.
        through_uv: Start it as ``uv run openral ...`` (uv forwards signals to its child), else
            ``python -m openral_cli ...``.
    """

    def __init__(
        self, args: list[str], *, through_uv: bool = False, cwd: str | None = None, keys: bool = False
    ) -> None:
        import shutil  # noqa: PLC0415
        import subprocess  # noqa: PLC0415
        import sys  # noqa: PLC0415
        import threading  # noqa: PLC0415

        if through_uv:
            uv = shutil.which("uv")
            if uv is None:
                pytest.skip("uv is not on PATH")
            command = [uv, "run", "--no-sync", "--quiet", "openral", *args]
        else:
            command = [sys.executable, "-m", "openral_cli", *args]
        self.proc = subprocess.Popen(
            command,
            # No terminal: a key reader sees end of input, or (``keys``) what :meth:`press` writes.
            stdin=subprocess.PIPE if keys else subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
            cwd=cwd,
        )
        self.stderr_lines: list[str] = []
        self._changed = threading.Condition()
        self._reader = threading.Thread(target=self._read_stderr, daemon=True)
        self._reader.start()

    def _read_stderr(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            with self._changed:
                self.stderr_lines.append(line)
                self._changed.notify_all()
        with self._changed:
            self._changed.notify_all()

    def wait_for(self, text: str, timeout: float = 60.0) -> str:
        """Block until a stderr line contains ``text``; fail if the process exits first or time runs out."""
        import time  # noqa: PLC0415

        deadline = time.monotonic() + timeout
        with self._changed:
            while True:
                for line in self.stderr_lines:
                    if text in line:
                        return line
                if self.proc.poll() is not None and not self._reader.is_alive():
                    pytest.fail(f"deploy exited ({self.proc.returncode}) before printing {text!r}:\n{self.stderr}")
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    pytest.fail(f"deploy did not print {text!r} within {timeout} s:\n{self.stderr}")
                self._changed.wait(min(remaining, 0.2))

    def press(self, keys: str) -> None:
        """Type ``keys`` into the process's standard input (started with ``keys=True``)."""
        assert self.proc.stdin is not None, "start it with keys=True"
        self.proc.stdin.write(keys)
        self.proc.stdin.flush()

    def signal_group(self, signum: int) -> None:
        """Send ``signum`` to the whole process group (uv and its child), as a terminal or systemd does."""
        import os  # noqa: PLC0415

        os.killpg(self.proc.pid, signum)

    def finish(self, timeout: float = 60.0) -> tuple[int, str]:
        """Wait for exit; returns the exit code and stdout."""
        assert self.proc.stdout is not None
        stdout = self.proc.stdout.read()
        self.proc.wait(timeout)
        self.close()
        return self.proc.returncode, stdout

    def close(self) -> None:
        """Close the pipes once the process has exited."""
        self._reader.join(5)
        for stream in (self.proc.stdin, self.proc.stdout, self.proc.stderr):
            if stream is not None:
                stream.close()

    @property
    def stderr(self) -> str:
        return "".join(self.stderr_lines)

    def kill(self) -> None:
        import contextlib  # noqa: PLC0415
        import os  # noqa: PLC0415
        import signal  # noqa: PLC0415

        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait(10)
        self.close()


@pytest.fixture
def deploy_process() -> Iterator[Callable[..., DeployProcess]]:
    """Start ``openral deploy`` processes (see :class:`DeployProcess`); any still running are killed afterwards."""
    started: list[DeployProcess] = []

    def start(args: list[str], **kwargs: object) -> DeployProcess:
        process = DeployProcess(args, **kwargs)  # type: ignore[arg-type]
        started.append(process)
        return process

    yield start
    for process in started:
        if process.proc.poll() is None:
            process.kill()
        else:
            process.close()


class InstalledPackages:
    """Distributions installed into one folder as pip installs them: the package and its ``.dist-info``.

    ``importlib.metadata.distributions()`` finds them wherever the folder is on the path, so LeRobot's
    ``register_third_party_plugins()`` imports a ``lerobot_policy_*`` (``_robot_``, ``_camera_``, ...)
    one like any installed plugin. :attr:`site` is the folder: put it on a child process's
    ``PYTHONPATH`` (:meth:`pythonpath`), or make a package importable here with
    ``importable=True``; the fixture then takes it out of ``sys.path``, ``sys.modules`` and the
    import caches again afterwards. What an imported package registered elsewhere (a config class
    in LeRobot's registry) stays for the process: give each test its own type names.

    Args:
        site: The folder (empty).
    """

    def __init__(self, site: Path) -> None:
        self.site = site
        self._modules: list[str] = []

    def __call__(
        self,
        name: str,
        source: str,
        *,
        files: Mapping[str, str] | None = None,
        importable: bool = False,
        license_id: str | None = None,
    ) -> Path:
        """Install distribution ``name`` (its import name too, as LeRobot imports it) into :attr:`site`; returns it.

        Args:
            name: The distribution's ``Name`` and the package's module name (``lerobot_policy_x``).
            source: The package's ``__init__.py``.
            files: More modules of the package, file name (``modeling_x.py``) to source.
            importable: Also put :attr:`site` on this process's ``sys.path`` until the test ends.
            license_id: The ``License-Expression`` its metadata declares (``None``: none, as many plugins).
        """
        package = self.site / name
        package.mkdir()
        written = {"__init__.py": source, **(files or {})}
        for file_name, text in written.items():
            (package / file_name).write_text(text, encoding="utf-8")
        info = self.site / f"{name}-0.1.dist-info"
        info.mkdir()
        declared = "" if license_id is None else f"License-Expression: {license_id}\n"
        (info / "METADATA").write_text(
            f"Metadata-Version: 2.4\nName: {name}\nVersion: 0.1\n{declared}", encoding="utf-8"
        )
        (info / "INSTALLER").write_text("pip\n", encoding="utf-8")
        records = [f"{name}/{file_name},," for file_name in written]
        records += [f"{info.name}/{entry},," for entry in ("METADATA", "INSTALLER", "RECORD")]
        (info / "RECORD").write_text("\n".join(records) + "\n", encoding="utf-8")
        self._modules.append(name)
        if importable and str(self.site) not in sys.path:
            sys.path.insert(0, str(self.site))
        _forget_imports()
        return self.site

    def pythonpath(self) -> str:
        """``PYTHONPATH`` for a child process: :attr:`site`, then what this process was given."""
        return os.pathsep.join(filter(None, (str(self.site), os.environ.get("PYTHONPATH"))))

    def remove(self) -> None:
        """Take :attr:`site` and every module imported from its packages out of this process."""
        while str(self.site) in sys.path:
            sys.path.remove(str(self.site))
        for module in list(sys.modules):
            if module.split(".")[0] in self._modules:
                del sys.modules[module]
        _forget_imports()


def _forget_imports() -> None:
    """Path finders and ``importlib.metadata`` re-read the folders; LeRobot's plugins are looked for again."""
    importlib.invalidate_caches()
    plugins = sys.modules.get("openral_hal.lerobot.plugins")  # only where this process loaded it
    if plugins is not None:
        plugins.load_lerobot_plugins.cache_clear()


@pytest.fixture
def installed_package(tmp_path_factory: pytest.TempPathFactory) -> Iterator[InstalledPackages]:
    """Install made-up distributions for this test (see :class:`InstalledPackages`); removed again afterwards."""
    packages = InstalledPackages(tmp_path_factory.mktemp("site-packages"))
    yield packages
    packages.remove()


@pytest.fixture
def quick_thread_switches() -> Iterator[None]:
    """Let an emulated device on a thread of this process answer LeRobot's Feetech SDK in time.

    A real servo answers from its own chip within a millisecond; the emulator's thread shares this
    interpreter with the SDK, which busy-waits for each reply (tens of ms) and so holds the GIL a
    whole switch interval (5 ms by default) at a time: on a loaded machine the reply comes too late.
    Shorter switch intervals hand the emulator the interpreter sooner; requests and replies are unchanged.
    """
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-4)
    yield
    sys.setswitchinterval(interval)


WITHOUT_LEROBOT = """
import importlib.abc, sys


class Blocker(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {"lerobot", "draccus", "torch"}:
            raise ModuleNotFoundError(f"No module named {name!r} (blocked)", name=name)
        return None


sys.meta_path.insert(0, Blocker())
"""
"""Python that makes the rest of a ``python -c`` program run as if the ``lerobot`` extra were not installed."""
