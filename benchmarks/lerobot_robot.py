"""LeRobot's driver vs openral's own HAL on an emulated SO-101 servo bus: tick cost, jitter, and where the time goes.

Part 1, deployments. Each row is a real deployment built by ``openral_runner.factory.build_runner``:
30 Hz, the ``hello`` wave, the ``envelope`` safety client (clamp), all rows identical but for the
HAL. The servos are openral's Feetech emulator (``ServoBusEmulator``), each bus in a process of
its own on a pseudo-terminal, so the HAL under test opens a serial port and waits on a reply
from another process, as it would on a USB adapter. Rows:

* ``openral-6``: ``so10x_follower`` (pyserial; per tick one SYNC_READ of position and speed, one
  SYNC_WRITE of goals) on one bus of the SO-101's 6 servos;
* ``lerobot-6``: ``lerobot_robot`` with LeRobot's ``so101_follower`` (``FeetechMotorsBus`` and the
  Feetech SDK ``scservo_sdk``) on the same kind of bus;
* ``openral-12``: ``so10x_follower`` on ONE bus of 12 servos (ids 1..12; a 12-joint manifest
  built here, the SO-101's joint limits twice, registered as an ``openral.robots`` plugin);
* ``lerobot-12``: ``lerobot_robot`` with LeRobot's ``bi_so_follower`` (its only 12-motor Feetech
  robot) on TWO buses of 6, under the ``bi_so101_follower`` manifest.

The 12-motor topologies differ: openral's row makes one transaction per tick for all 12 servos;
LeRobot's makes one per arm, left then right, each waiting for its own replies. So the
12-motor rows compare what each driver does for a 12-joint robot, not the same wire. The
emulator has no wire time (a pty moves bytes at memory speed): a real 1 Mbit/s bus adds about
10 µs per byte and the USB adapter's latency, the same for both drivers per transaction.

Per row: tick busy time p50/p99 (slot start to action sent), tick-start jitter p50/p99/max,
missed slots, and the HAL's own time per tick in ``read_state`` and ``send_action`` (each
wrapped as ``ComponentTimer`` wraps components). Ratios are LeRobot over openral, within the run.

Part 2, layers (6 servos, one emulated bus, both drivers in turn on the same one): each layer of
each driver called on its own with a pause before each call (default one 30 Hz period, as in the
loop), wall and CPU time per call. Reads: openral's ``FeetechBus.sync_read`` (2 bytes a servo,
LeRobot's payload; then 4, the HAL's position and speed) and ``read_state``; the SDK's sync-read
transaction, LeRobot's ``sync_read`` raw and normalised, ``get_observation``, ``lerobot_robot``'s
``read_state``. Writes likewise. Both ``read_state`` again beside one more Python thread that
always wants the GIL (what a camera or encoder thread does to a deployment), at Python's default 5
ms GIL switch interval and at the 1 ms openral's serial deployments set, with that thread's
progress: a reader that blocks lends it the GIL and may wait up to a switch interval to get it
back; a reader that spins takes the GIL back after every read and starves it. Then the SDK's
mechanics, counted per sync read (serial reads, deadline checks, the port flush before each send,
the reply deadline). The closing breakdown takes the waiting out: the same layers called back to
back on a port that answers at once (replies canned), so each layer's own Python work per call is
the difference of two medians (each the lowest of five batches), for both drivers; beside it, the
wait of the real transactions. That wait is bimodal for a busy-polling read (quick, or a few ms
while the reply waits for a CPU), so its p50 moves between runs: compare p50, mean and p99, over
more than one run.

What the layers look at (``motors/motors_bus.py``, ``motors/feetech/feetech.py`` and
``scservo_sdk`` beside them): the SDK opens the port with ``timeout=0`` and busy-polls, reading
each servo's reply in pieces (header, then the rest), one servo after another, checking a
``time.time()`` deadline between reads; its CPU time is about its wall time, so for as long as it
waits it holds a core (which the emulator, or the kernel's tty work that delivers the bytes,
needs) and drops and retakes the GIL at every read. Each packet is a list of ints with a Python
checksum loop, and every send first flushes (``tcdrain``: waits for output; stale input stays).
LeRobot then maps ids to names, decodes the sign and normalises motor by motor in Python;
``bi_so_follower`` does it all once per arm, in series. openral's bus makes one blocking read of
the exact reply size (the wait costs no CPU) and converts with a few float operations.

Run:  UV_PROJECT_ENVIRONMENT=.venv-py312 uv run --python 3.12 --no-sync python benchmarks/lerobot_robot.py
      [--seconds 10] [--rows openral-6,lerobot-6,openral-12,lerobot-12] [--calls 150] [--pause-ms 33.3] [--no-layers]
Without the 'lerobot' extra (Python 3.11), the LeRobot rows and layers are skipped with a line saying so.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import multiprocessing
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack, contextmanager, suppress
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from _common import ComponentTimer, machine_line

RATE_HZ = 30
ROWS = ("openral-6", "lerobot-6", "openral-12", "lerobot-12")
SO101_MOTORS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")
SYNC_READ = 0x82
"""The Feetech SYNC_READ instruction code."""
TWELVE = "so101_twelve_one_bus"
"""The benchmark's 12-joint robot: the SO-101's joints twice, servo ids 1..12, on one bus."""
LEROBOT_MISSING = "needs the 'lerobot' extra, which installs on Python 3.12 (UV_PROJECT_ENVIRONMENT=.venv-py312)"


def lerobot_available() -> bool:
    return importlib.util.find_spec("lerobot") is not None and importlib.util.find_spec("scservo_sdk") is not None


# -- emulated buses, each in a process of its own -------------------------------------------------


def _serve_bus(servo_ids: list[int], conn: Connection) -> None:
    """Child process: one emulated bus; sends its port, serves until the parent says stop (or goes)."""
    from openral_hal.feetech.emulator import ServoBusEmulator  # noqa: PLC0415

    with ServoBusEmulator(servo_ids) as emulator:
        conn.send(emulator.port)
        with suppress(EOFError):
            conn.recv()


@contextmanager
def emulated_buses(buses: Sequence[Sequence[int]]) -> Iterator[list[str]]:
    """One emulator process per bus (servo ids per bus); yields their ports."""
    ctx = multiprocessing.get_context("spawn")
    started: list[tuple[Any, Connection]] = []
    try:
        for ids in buses:
            parent, child = ctx.Pipe()
            proc = ctx.Process(target=_serve_bus, args=(list(ids), child), daemon=True)
            proc.start()
            started.append((proc, parent))
        ports = []
        for _, parent in started:
            if not parent.poll(60):
                raise RuntimeError("an emulator process did not start")
            ports.append(parent.recv())
        yield ports
    finally:
        for proc, parent in started:
            with suppress(OSError):  # a child that died has closed its end
                parent.send(None)
            proc.join(5)
            if proc.is_alive():
                proc.terminate()


# -- robots, calibrations, deployments -------------------------------------------------------------


def register_twelve_joint_robot(folder: Path) -> None:
    """Register the 12-joint manifest as an ``openral.robots`` plugin (a tiny distribution in ``folder``).

    Must run before ``openral_hal.manifests`` is imported: its registry reads the entry points once.
    """
    so101 = json.loads(json.dumps(_so101_joints()))
    joints = [
        {**joint, "name": f"{'a' if arm == 0 else 'b'}_{joint['name']}", "servo_id": arm * 6 + i + 1}
        for arm in (0, 1)
        for i, joint in enumerate(so101)
    ]
    manifest = {
        "robot_id": TWELVE,
        "name": "Two SO-101 arms on one bus (benchmark)",
        "description": "The SO-101's six joints twice, servo ids 1..12 on one Feetech bus.",
        "joints": joints,
    }
    (folder / "robot.yaml").write_text(json.dumps(manifest), encoding="utf-8")
    (folder / "openral_bench_robots.py").write_text(f"MANIFEST = {str(folder / 'robot.yaml')!r}\n", encoding="utf-8")
    dist = folder / "openral_bench_robots-0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: openral-bench-robots\nVersion: 0\n", encoding="utf-8")
    (dist / "entry_points.txt").write_text(
        f"[openral.robots]\n{TWELVE} = openral_bench_robots:MANIFEST\n", encoding="utf-8"
    )
    sys.path.insert(0, str(folder))


def _so101_joints() -> list[dict[str, Any]]:
    """The shipped SO-101 manifest's joints, read as data (no openral import yet)."""
    import yaml  # noqa: PLC0415

    spec = importlib.util.find_spec("openral_hal")
    if spec is None or spec.origin is None:
        raise RuntimeError("openral is not installed in this environment")
    path = Path(spec.origin).parent / "robots" / "so101_follower" / "robot.yaml"
    joints: list[dict[str, Any]] = yaml.safe_load(path.read_text(encoding="utf-8"))["joints"]
    return joints


def write_calibrations(robot_id: str, folder: Path) -> tuple[Path, dict[str, list[tuple[int, int]]]]:
    """openral's nominal calibration of ``robot_id`` as a file, and the same tick ranges per 6-motor arm."""
    from openral_hal.feetech.calibration import ArmCalibration, save_calibration  # noqa: PLC0415
    from openral_hal.manifests import load_robot_manifest  # noqa: PLC0415

    calibration = ArmCalibration.from_manifest(load_robot_manifest(robot_id))
    path = folder / f"{robot_id}.json"
    save_calibration(calibration, path)
    ranges = [(c.range_min, c.range_max) for c in calibration.joints.values()]
    return path, {"arm": ranges[:6], "second": ranges[6:]}


def write_lerobot_calibration(folder: Path, arm_id: str, ranges: Sequence[tuple[int, int]]) -> None:
    """A LeRobot calibration file (lerobot-calibrate's format) for one SO-101 arm with these tick ranges."""
    data = {
        name: {"id": i, "drive_mode": 0, "homing_offset": 0, "range_min": low, "range_max": high}
        for i, (name, (low, high)) in enumerate(zip(SO101_MOTORS, ranges, strict=True), start=1)
    }
    (folder / f"{arm_id}.json").write_text(json.dumps(data), encoding="utf-8")


def deployment(name: str, hal: dict[str, Any]) -> Any:
    """The benchmark's deployment: 30 Hz hello wave under the envelope, ``hal`` as given."""
    from openral_core import RobotEnvironment  # noqa: PLC0415

    return RobotEnvironment.model_validate(
        {
            "name": name,
            "rate_hz": RATE_HZ,
            "deadline_overrun_policy": "warn",
            "hal": hal,
            "vla": {"id": "hello", "params": {"amplitude_rad": 0.25, "frequency_hz": 0.3}},
            "safety": {"client": "envelope", "mode": "clamp", "max_joint_speed_factor": 0.8},
            "faults": {"max_consecutive_failures": 5},
        }
    )


@dataclass(frozen=True)
class RowSpec:
    name: str
    motors: int
    buses: tuple[tuple[int, ...], ...]
    needs_lerobot: bool
    topology: str


ROW_SPECS = {
    "openral-6": RowSpec("openral-6", 6, (tuple(range(1, 7)),), False, "so10x_follower, 1 bus x 6"),
    "lerobot-6": RowSpec("lerobot-6", 6, (tuple(range(1, 7)),), True, "so101_follower, 1 bus x 6"),
    "openral-12": RowSpec("openral-12", 12, (tuple(range(1, 13)),), False, "so10x_follower, 1 bus x 12"),
    "lerobot-12": RowSpec(
        "lerobot-12", 12, (tuple(range(1, 7)), tuple(range(1, 7))), True, "bi_so_follower, 2 buses x 6, in series"
    ),
}


def row_hal(spec: RowSpec, ports: list[str], folder: Path) -> dict[str, Any]:
    """The ``hal:`` block of a row, its calibration files written to ``folder``."""
    if spec.name.startswith("openral"):
        robot_id = "so101_follower" if spec.motors == 6 else TWELVE
        calibration, _ = write_calibrations(robot_id, folder)
        return {
            "robot_id": robot_id,
            "adapter": "so10x_follower",
            "params": {"port": ports[0], "calibration": str(calibration)},
        }
    _, ranges = write_calibrations("so101_follower", folder)
    if spec.motors == 6:
        write_lerobot_calibration(folder, "arm", ranges["arm"])
        params = {"type": "so101_follower", "port": ports[0], "id": "arm", "use_degrees": True}
        return {
            "robot_id": "so101_follower",
            "adapter": "lerobot_robot",
            "params": params | {"calibration_dir": str(folder)},
        }
    write_lerobot_calibration(folder, "pair_left", ranges["arm"])
    write_lerobot_calibration(folder, "pair_right", ranges["arm"])
    params = {
        "type": "bi_so_follower",
        "id": "pair",
        "calibration_dir": str(folder),
        "left_arm_config": {"port": ports[0]},
        "right_arm_config": {"port": ports[1]},
    }
    return {"robot_id": "bi_so101_follower", "adapter": "lerobot_robot", "params": params}


# -- part 1: deployments ---------------------------------------------------------------------------


@dataclass
class RowFigures:
    spec: RowSpec
    n_ticks: int
    achieved_hz: float
    failed_ticks: int
    missed_slots: int
    busy_p50_us: float
    busy_p99_us: float
    jitter_p50_us: float
    jitter_p99_us: float
    jitter_max_us: float
    read_p50_us: float
    read_p99_us: float
    send_p50_us: float
    send_p99_us: float

    def line(self) -> str:
        return (
            f"{self.spec.name:<10} {self.spec.motors:>2} motors  n={self.n_ticks:<5} {self.achieved_hz:7.3f} Hz  "
            f"failed {self.failed_ticks} missed {self.missed_slots}  "
            f"busy µs p50 {self.busy_p50_us:7.0f} p99 {self.busy_p99_us:7.0f}  "
            f"jitter µs p50 {self.jitter_p50_us:6.0f} p99 {self.jitter_p99_us:7.0f} max {self.jitter_max_us:7.0f}  "
            f"read_state µs p50 {self.read_p50_us:6.0f} p99 {self.read_p99_us:7.0f}  "
            f"send_action µs p50 {self.send_p50_us:6.0f} p99 {self.send_p99_us:7.0f}  ({self.spec.topology})"
        )


def run_row(spec: RowSpec, seconds: float) -> RowFigures:
    from openral_runner.factory import build_runner  # noqa: PLC0415

    with tempfile.TemporaryDirectory() as tmp, emulated_buses(spec.buses) as ports:
        folder = Path(tmp)
        runner, skill = build_runner(deployment(f"bench_{spec.name}", row_hal(spec, ports, folder)), base_dir=folder)
        reads, sends = ComponentTimer(), ComponentTimer()
        hal: Any = runner.hal
        hal.read_state = reads.wrap(hal.read_state, starts_tick=True)
        hal.send_action = sends.wrap(hal.send_action, starts_tick=True)
        skill.configure()
        skill.activate()
        runner.activate()
        try:
            result = runner.run(duration_s=seconds)
        finally:
            runner.deactivate()
            skill.shutdown()
    read_us = np.array(reads.per_tick) * 1e6
    send_us = np.array(sends.per_tick) * 1e6
    return RowFigures(
        spec=spec,
        n_ticks=result.n_ticks,
        achieved_hz=result.effective_rate_hz,
        failed_ticks=result.failed_ticks,
        missed_slots=result.missed_slots,
        busy_p50_us=result.tick_ms_p50 * 1e3,
        busy_p99_us=result.tick_ms_p99 * 1e3,
        jitter_p50_us=result.start_jitter_us_p50,
        jitter_p99_us=result.start_jitter_us_p99,
        jitter_max_us=result.start_jitter_us_max,
        read_p50_us=_pct(read_us, 50),
        read_p99_us=_pct(read_us, 99),
        send_p50_us=_pct(send_us, 50),
        send_p99_us=_pct(send_us, 99),
    )


def _pct(values: npt.NDArray[np.float64], q: float) -> float:
    return float(np.percentile(values, q)) if values.size else float("nan")


def print_ratios(figures: dict[str, RowFigures]) -> None:
    for motors in (6, 12):
        ours, theirs = figures.get(f"openral-{motors}"), figures.get(f"lerobot-{motors}")
        if ours is None or theirs is None:
            continue
        print(
            f"{motors:>2} motors, lerobot/openral: busy p50 {theirs.busy_p50_us / ours.busy_p50_us:.2f}x "
            f"p99 {theirs.busy_p99_us / ours.busy_p99_us:.2f}x; jitter p99 "
            f"{theirs.jitter_p99_us / max(ours.jitter_p99_us, 1e-9):.2f}x; read_state p50 "
            f"{theirs.read_p50_us / ours.read_p50_us:.2f}x; "
            f"send_action p50 {theirs.send_p50_us / ours.send_p50_us:.2f}x"
        )


# -- part 2: layers --------------------------------------------------------------------------------


@dataclass
class Layer:
    name: str
    wall_p50_us: float
    wall_p99_us: float
    wall_mean_us: float
    cpu_p50_us: float
    failed: int

    def line(self) -> str:
        failed = f"  FAILED {self.failed} of the calls" if self.failed else ""
        return (
            f"  {self.name:<62} wall µs p50 {self.wall_p50_us:6.0f} p99 {self.wall_p99_us:7.0f} "
            f"mean {self.wall_mean_us:6.0f}  "
            f"CPU µs p50 {self.cpu_p50_us:6.0f}{failed}"
        )


class Layers:
    """Times layers one after another: ``calls`` calls each, a pause before each call (a loop's sleep)."""

    def __init__(self, calls: int, pause_s: float) -> None:
        self.calls = calls
        self.pause_s = pause_s
        self.timed: list[Layer] = []
        self.facts: dict[str, float] = {}
        self.no_io_us: dict[str, float] = {}

    def time(self, name: str, fn: Callable[[], object]) -> None:
        """Wall time and this thread's CPU time of each call of ``fn`` (a failed call counts, and is counted)."""
        wall = np.empty(self.calls)
        cpu = np.empty(self.calls)
        failed = 0
        perf, thread_time = time.perf_counter_ns, time.thread_time_ns
        for i in range(-1, self.calls):  # call -1 warms up
            time.sleep(self.pause_s)
            c0, w0 = thread_time(), perf()
            try:
                fn()
            except Exception:  # a failed transaction: its time is part of the cost
                failed += i >= 0
            w1, c1 = perf(), thread_time()
            if i >= 0:
                wall[i], cpu[i] = (w1 - w0) / 1e3, (c1 - c0) / 1e3
        self.timed.append(Layer(name, _pct(wall, 50), _pct(wall, 99), float(wall.mean()), _pct(cpu, 50), failed))

    def conversion(self, name: str, fn: Callable[[], object], batches: int = 5, calls: int = 400) -> None:
        """Time of a call that does no I/O (replies canned at the port), back to back: the lowest of
        ``batches`` medians, so that a batch another process interrupted does not count."""
        fn()
        times = np.empty(calls)
        perf = time.perf_counter_ns
        medians = []
        for _ in range(batches):
            for i in range(calls):
                start = perf()
                fn()
                times[i] = perf() - start
            medians.append(float(np.median(times)))
        self.no_io_us[name] = min(medians) / 1e3

    def timed_layer(self, prefix: str) -> Layer:
        return next(layer for layer in self.timed if layer.name.startswith(prefix))


SWITCH_INTERVALS_S = (0.005, 0.001)
"""Python's default GIL switch interval, and the one openral's serial deployments set (``realtime``)."""


@contextmanager
def busy_python_thread(switch_interval_s: float) -> Iterator[list[int]]:
    """Another Python thread that always wants the GIL (a camera conversion, a telemetry encoder).

    Yields a one-item list: the thread's loops so far (how much of the GIL it got).
    """
    stop = threading.Event()
    loops = [0]

    def spin() -> None:
        while not stop.is_set():
            sum(range(2000))
            loops[0] += 1

    saved = sys.getswitchinterval()
    sys.setswitchinterval(switch_interval_s)
    thread = threading.Thread(target=spin, name="busy-beside", daemon=True)
    thread.start()
    try:
        yield loops
    finally:
        stop.set()
        thread.join()
        sys.setswitchinterval(saved)


def time_beside_busy_thread(out: Layers, hal_name: str, read_state: Callable[[], object]) -> None:
    """``read_state`` with a busy Python thread beside, at each switch interval; the thread's share too."""
    for interval in SWITCH_INTERVALS_S:
        with busy_python_thread(interval) as loops:
            start = time.perf_counter()
            out.time(f"openral {hal_name}.read_state, busy thread, switch {interval * 1e3:g} ms", read_state)
            rate = loops[0] / (time.perf_counter() - start)
        out.facts[f"busy thread's loops/s beside {hal_name}, switch {interval * 1e3:g} ms"] = rate


class CountingSerial:
    """Factory of pyserial ports that count their ``read`` calls (for ``FeetechBus(serial_factory=...)``)."""

    def __init__(self) -> None:
        self.reads = 0

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        import serial  # noqa: PLC0415

        counter = self

        class Counted(serial.Serial):
            def read(self, size: int = 1) -> bytes:
                counter.reads += 1
                data: bytes = super().read(size)
                return data

        return Counted(*args, **kwargs)


class CannedSerial:
    """A pyserial stand-in that answers every SYNC_READ at once with ``reply``: a driver's own work, no I/O."""

    def __init__(self, reply: bytes) -> None:
        self.reply = reply
        self.pending = bytearray()
        self._file = tempfile.TemporaryFile()  # noqa: SIM115  (a descriptor for the bus's lock; closed in close())

    def fileno(self) -> int:
        return self._file.fileno()

    @property
    def in_waiting(self) -> int:
        return len(self.pending)

    def write(self, packet: bytes) -> int:
        if packet[4] == SYNC_READ:
            self.pending += self.reply
        return len(packet)

    def read(self, size: int = 1) -> bytes:
        data = bytes(self.pending[:size])
        del self.pending[:size]
        return data

    def reset_input_buffer(self) -> None:
        self.pending.clear()

    def close(self) -> None:
        self._file.close()


@contextmanager
def canned_sdk_port(port: Any, reply: bytes) -> Iterator[None]:
    """The SDK's port handler answering every sync read at once with ``reply`` (no flush, no I/O)."""
    pending = bytearray()

    def write_port(packet: list[int]) -> int:
        if packet[4] == SYNC_READ:
            pending.extend(reply)
        return len(packet)

    def read_port(length: int) -> bytes:
        data = bytes(pending[:length])
        del pending[:length]
        return data

    port.writePort, port.readPort, port.clearPort = write_port, read_port, lambda: None
    try:
        yield
    finally:
        del port.writePort, port.readPort, port.clearPort


def status_replies(ids: Sequence[int], data: bytes) -> bytes:
    """Every servo's status packet for a sync read of ``data``."""
    from openral_hal.feetech import protocol as p  # noqa: PLC0415

    return b"".join(p.status_packet(servo_id, 0, data) for servo_id in ids)


def openral_layers(port: str, out: Layers, folder: Path) -> None:
    from openral_core import Action  # noqa: PLC0415
    from openral_hal.feetech import protocol as p  # noqa: PLC0415
    from openral_hal.feetech.bus import FeetechBus  # noqa: PLC0415
    from openral_hal.feetech.hal import SO10xFollowerHAL  # noqa: PLC0415
    from openral_hal.feetech.protocol import Register  # noqa: PLC0415
    from openral_hal.manifests import load_robot_manifest  # noqa: PLC0415

    ids = list(range(1, 7))
    counting = CountingSerial()
    with FeetechBus(port, serial_factory=counting) as bus:
        goals = {i: p.u16(p.encode_sign_magnitude(2048)) for i in ids}
        out.time("openral FeetechBus.sync_read, 2 B/servo", lambda: bus.sync_read(ids, Register.PRESENT_POSITION, 2))
        out.time("openral FeetechBus.sync_read, 4 B/servo (the HAL's)", lambda: bus.sync_read(ids, 56, 4))
        before = counting.reads
        for _ in range(100):
            bus.sync_read(ids, Register.PRESENT_POSITION, 4)
        out.facts["openral serial reads per sync read"] = (counting.reads - before) / 100
        out.time("openral FeetechBus.sync_write goals", lambda: bus.sync_write(Register.GOAL_POSITION, goals))
    calibration, _ = write_calibrations("so101_follower", folder)
    hal = SO10xFollowerHAL(load_robot_manifest("so101_follower"), {"port": port, "calibration": str(calibration)})
    hal.connect()
    try:
        state = hal.read_state()
        hold = Action(joint_names=state.names, targets=[list(state.positions)])
        out.time("openral so10x_follower.read_state", hal.read_state)
        time_beside_busy_thread(out, "so10x_follower", hal.read_state)
        out.time("openral so10x_follower.send_action", lambda: hal.send_action(hold))
        real = hal.bus

        def canned_port(*_: Any, **__: Any) -> Any:
            return CannedSerial(status_replies(ids, bytes(4)))

        with FeetechBus("canned", serial_factory=canned_port) as bus:
            hal.bus = bus
            try:
                out.conversion("openral FeetechBus.sync_read", lambda: bus.sync_read(ids, Register.PRESENT_POSITION, 4))
                out.conversion("openral so10x_follower.read_state", hal.read_state)
                out.conversion("openral FeetechBus.sync_write", lambda: bus.sync_write(Register.GOAL_POSITION, goals))
                out.conversion("openral so10x_follower.send_action", lambda: hal.send_action(hold))
            finally:
                hal.bus = real
    finally:
        hal.disconnect()


def lerobot_layers(port: str, out: Layers, folder: Path) -> None:
    from openral_core import Action  # noqa: PLC0415
    from openral_hal.lerobot.robot_hal import LeRobotRobotHAL  # noqa: PLC0415
    from openral_hal.manifests import load_robot_manifest  # noqa: PLC0415

    _, ranges = write_calibrations("so101_follower", folder)
    write_lerobot_calibration(folder, "arm", ranges["arm"])
    params = {"type": "so101_follower", "port": port, "id": "arm", "use_degrees": True, "calibration_dir": str(folder)}
    hal = LeRobotRobotHAL(load_robot_manifest("so101_follower"), params)
    hal.connect()
    try:
        robot = hal.robot
        bus = robot.bus
        ids = [motor.id for motor in bus.motors.values()]
        position, goal, length = 56, 42, 2  # Present_Position, Goal_Position: 2 bytes on the STS3215
        raw = bus.sync_read("Present_Position", normalize=False)
        normalised = bus.sync_read("Present_Position")
        action = {f"{name}.pos": value for name, value in normalised.items()}
        raw_ids = {bus.motors[name].id: value for name, value in raw.items()}
        out.time("SDK sync-read transaction (bus._sync_read)", lambda: bus._sync_read(position, length, ids))
        out.time(
            "LeRobot bus.sync_read raw (normalize=False)", lambda: bus.sync_read("Present_Position", normalize=False)
        )
        out.time("LeRobot bus.sync_read normalised (degrees)", lambda: bus.sync_read("Present_Position"))
        out.time("LeRobot robot.get_observation()", robot.get_observation)
        out.time("openral lerobot_robot.read_state", hal.read_state)
        time_beside_busy_thread(out, "lerobot_robot", hal.read_state)
        state = hal.read_state()
        hold = Action(joint_names=state.names, targets=[list(state.positions)])
        out.time("SDK sync-write packet (bus._sync_write)", lambda: bus._sync_write(goal, length, raw_ids))
        out.time(
            "LeRobot bus.sync_write raw (normalize=False)",
            lambda: bus.sync_write("Goal_Position", raw, normalize=False),
        )
        out.time("LeRobot bus.sync_write normalised", lambda: bus.sync_write("Goal_Position", normalised))
        out.time("LeRobot robot.send_action()", lambda: robot.send_action(action))
        out.time("openral lerobot_robot.send_action", lambda: hal.send_action(hold))
        out.facts |= sdk_mechanics(bus, position, length, ids, out.pause_s)
        with canned_sdk_port(bus.port_handler, status_replies(ids, (2048).to_bytes(2, "little"))):
            out.conversion("SDK sync read", lambda: bus._sync_read(position, length, ids))
            out.conversion("LeRobot bus.sync_read raw", lambda: bus.sync_read("Present_Position", normalize=False))
            out.conversion("LeRobot bus.sync_read normalised", lambda: bus.sync_read("Present_Position"))
            out.conversion("LeRobot robot.get_observation", robot.get_observation)
            out.conversion("openral lerobot_robot.read_state", hal.read_state)
            out.conversion("SDK sync write", lambda: bus._sync_write(goal, length, raw_ids))
            out.conversion("LeRobot bus.sync_write raw", lambda: bus.sync_write("Goal_Position", raw, normalize=False))
            out.conversion("LeRobot bus.sync_write normalised", lambda: bus.sync_write("Goal_Position", normalised))
            out.conversion("LeRobot robot.send_action", lambda: robot.send_action(action))
            out.conversion("openral lerobot_robot.send_action", lambda: hal.send_action(hold))
    finally:
        hal.disconnect()


def sdk_mechanics(bus: Any, address: int, length: int, ids: list[int], pause_s: float) -> dict[str, float]:
    """What the SDK does per sync read, counted over 100 of them (wrappers on its port handler)."""
    port = bus.port_handler
    counts = {"reads": 0, "timeout_checks": 0, "flush_s": 0.0, "flushes": 0}
    read_port, is_timeout, clear_port = port.readPort, port.isPacketTimeout, port.clearPort

    def counted_read(n: int) -> Any:
        counts["reads"] += 1
        return read_port(n)

    def counted_timeout() -> bool:
        counts["timeout_checks"] += 1
        result: bool = is_timeout()
        return result

    def timed_clear() -> None:
        start = time.perf_counter()
        clear_port()
        counts["flush_s"] += time.perf_counter() - start
        counts["flushes"] += 1

    port.readPort, port.isPacketTimeout, port.clearPort = counted_read, counted_timeout, timed_clear
    try:
        for _ in range(100):
            time.sleep(pause_s)
            bus._sync_read(address, length, ids)
        facts = {
            "SDK serial reads per sync read (port opened with timeout=0)": counts["reads"] / 100,
            "SDK timeout checks (spin iterations) per sync read": counts["timeout_checks"] / 100,
            "SDK port flush (tcdrain) before each send (µs)": counts["flush_s"] / max(counts["flushes"], 1) * 1e6,
        }
    finally:
        port.readPort, port.isPacketTimeout, port.clearPort = read_port, is_timeout, clear_port
    saved = port.packet_start_time, port.packet_timeout
    port.setPacketTimeout((6 + length) * len(ids))  # what syncReadTx sets (LeRobot's patched formula)
    facts["SDK reply deadline of a 6-servo sync read (ms)"] = port.packet_timeout
    port.packet_start_time, port.packet_timeout = saved
    return facts


def run_layers(calls: int, pause_s: float, with_lerobot: bool) -> None:
    print(
        f"layers: 6 servos on one emulated bus (own process), {calls} calls each, {pause_s * 1e3:.0f} ms pause "
        "before each call; 'busy thread': one more Python thread always wanting the GIL, at the given GIL "
        "switch interval"
    )
    out = Layers(calls, pause_s)
    with tempfile.TemporaryDirectory() as tmp, emulated_buses([range(1, 7)]) as ports:
        openral_layers(ports[0], out, Path(tmp))
        if with_lerobot:
            lerobot_layers(ports[0], out, Path(tmp))
    for layer in out.timed:
        print(layer.line())
    for name, value in out.facts.items():
        print(f"  {name:<62} {value:8.2f}")
    if not with_lerobot:
        for name, value in out.no_io_us.items():
            print(f"  {name + ', no I/O (µs, lowest of 5 medians)':<62} {value:8.1f}")
        print(f"  LeRobot layers: skipped, {LEROBOT_MISSING}")
        return
    print_breakdown(out)


LEROBOT_READ = (
    "SDK sync read",
    "LeRobot bus.sync_read raw",
    "LeRobot bus.sync_read normalised",
    "LeRobot robot.get_observation",
    "openral lerobot_robot.read_state",
)
LEROBOT_WRITE = (
    "SDK sync write",
    "LeRobot bus.sync_write raw",
    "LeRobot bus.sync_write normalised",
    "LeRobot robot.send_action",
    "openral lerobot_robot.send_action",
)
OPENRAL_READ = ("openral FeetechBus.sync_read", "openral so10x_follower.read_state")
OPENRAL_WRITE = ("openral FeetechBus.sync_write", "openral so10x_follower.send_action")
HAL_NAMES = ("so10x_follower", "lerobot_robot")


def print_breakdown(out: Layers) -> None:
    """Each driver's own work per call (no I/O) layer by layer, then the transaction's wait."""
    no_io = out.no_io_us
    print("breakdown: each driver's own work per call, replies canned at the port (no I/O; µs, lowest of 5 medians)")
    stacks = [("read", LEROBOT_READ, OPENRAL_READ), ("write", LEROBOT_WRITE, OPENRAL_WRITE)]
    for kind, lerobot_stack, openral_stack in stacks:
        for stack in (lerobot_stack, openral_stack):
            below = 0.0
            for name in stack:
                print(f"  {kind:<6} {name:<44} {no_io[name] - below:+8.1f}  (total {no_io[name]:6.1f})")
                below = no_io[name]
    sdk, bus = out.timed_layer("SDK sync-read"), out.timed_layer("openral FeetechBus.sync_read, 4")
    print(
        f"  the wait (real transactions, p50 wall/CPU µs): SDK sync read {sdk.wall_p50_us:.0f}/{sdk.cpu_p50_us:.0f} "
        f"({out.facts['SDK serial reads per sync read (port opened with timeout=0)']:.0f} serial reads, busy-polling), "
        f"openral FeetechBus.sync_read {bus.wall_p50_us:.0f}/{bus.cpu_p50_us:.0f} (1 blocking read)"
    )
    for interval in SWITCH_INTERVALS_S:
        at = f"switch {interval * 1e3:g} ms"
        ours, theirs = (out.timed_layer(f"openral {hal}.read_state, busy thread, {at}") for hal in HAL_NAMES)
        ours_loops, theirs_loops = (out.facts[f"busy thread's loops/s beside {hal}, {at}"] for hal in HAL_NAMES)
        print(
            f"  busy Python thread beside, {at}: read_state p50/p99 µs so10x_follower {ours.wall_p50_us:.0f}/"
            f"{ours.wall_p99_us:.0f}, lerobot_robot {theirs.wall_p50_us:.0f}/{theirs.wall_p99_us:.0f} "
            f"({ours.failed + theirs.failed} failed); the busy thread's loops/s beside them "
            f"{ours_loops:.0f} and {theirs_loops:.0f}"
        )


# -- main ------------------------------------------------------------------------------------------


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=10.0, help="run time per row")
    parser.add_argument("--rows", default=",".join(ROWS), help=f"comma-separated rows of {', '.join(ROWS)}")
    parser.add_argument("--calls", type=int, default=150, help="calls per layer in the layer breakdown")
    parser.add_argument(
        "--pause-ms", type=float, default=1000 / RATE_HZ, help="pause before each layer call (default: one tick period)"
    )
    parser.add_argument("--no-layers", action="store_true", help="skip the layer breakdown")
    args = parser.parse_args()
    rows = [r.strip() for r in args.rows.split(",") if r.strip()]
    unknown = [r for r in rows if r not in ROW_SPECS]
    if unknown:
        parser.error(f"unknown row(s) {unknown}; rows are {', '.join(ROWS)}")
    with ExitStack() as stack:
        register_twelve_joint_robot(Path(stack.enter_context(tempfile.TemporaryDirectory())))
        with_lerobot = lerobot_available()
        print(machine_line())
        print(
            f"{RATE_HZ} Hz, hello skill, envelope safety; each bus an emulator in its own process. The 12-motor rows "
            "differ in topology: openral drives one bus of 12 servos (one transaction per tick), LeRobot's "
            "bi_so_follower two buses of 6 read one after the other (two transactions per tick)."
        )
        figures: dict[str, RowFigures] = {}
        for row in rows:
            spec = ROW_SPECS[row]
            if spec.needs_lerobot and not with_lerobot:
                print(f"{row:<10} skipped: {LEROBOT_MISSING}")
                continue
            figures[row] = run_row(spec, args.seconds)
            print(figures[row].line())
        print_ratios(figures)
        if not args.no_layers:
            run_layers(args.calls, args.pause_ms / 1e3, with_lerobot)
        print(machine_line())


if __name__ == "__main__":
    main()
