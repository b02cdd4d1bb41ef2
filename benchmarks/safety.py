"""Safety benchmark: what the envelope check costs per tick (target: under 20 µs).

``EnvelopeSafetyClient.check_action`` on the SO-101 manifest at 30 Hz, timed call by call
(``perf_counter_ns``; the timer's own cost, measured on an empty call, is reported and not
subtracted). The reference is the home pose, committed as a run commits the command sent. Cases:

* ``in-envelope``: allowed unchanged (returns ``None``);
* ``clamped``: ``clamp`` mode, every joint past its step limit (returns a replacement);
* ``rejected``: ``reject`` mode, one joint out of range (raises ``ROSSafetyViolation``);
* with the workspace box (forward kinematics of the gripper frame every check) the same three,
  plus ``box pull-back``: ``clamp`` mode, a target whose end effector leaves the box (the
  bisection back into it, the slowest path) and ``box rejected`` in ``reject`` mode.

Then the pieces compared: the site forward kinematics in pure Python against the same in numpy,
and the joint-limit/step loop in pure Python against a numpy version of it.

Run:  uv run python benchmarks/safety.py [--calls 20000]
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import numpy as np

from _common import machine_line
from openral_core import Action, JointState, ROSSafetyViolation, SafetyConfig, SafetyMode
from openral_hal.manifests import load_robot_manifest
from openral_runner.envelope import EnvelopeSafetyClient

RATE_HZ = 30.0
ROBOT = load_robot_manifest("so101_follower")
HOME = [0.0, 0.0, 0.0, 0.0, 0.0, 0.5]
BOX = {"workspace_min": (0.05, -0.25, 0.02), "workspace_max": (0.40, 0.25, 0.40)}


def _client(mode: SafetyMode, *, box: bool) -> EnvelopeSafetyClient:
    config = SafetyConfig(mode=mode, **BOX) if box else SafetyConfig(mode=mode)  # type: ignore[arg-type]
    client = EnvelopeSafetyClient.from_config(config, robot=ROBOT, rate_hz=RATE_HZ)
    client.observe_state(JointState(names=ROBOT.joint_names, positions=HOME))
    home = _action(HOME)  # as in a run: the reference is a command this client passed and the HAL took
    client.commit(client.check_action(home) or home)
    return client


def _action(row: list[float]) -> Action:
    return Action(joint_names=ROBOT.joint_names, targets=[row])


def _time_calls(fn: Callable[[], object], calls: int) -> list[float]:
    """Per-call wall time in µs."""
    clock = time.perf_counter_ns
    out = []
    for _ in range(calls):
        start = clock()
        try:  # noqa: SIM105 - contextlib.suppress would add its own cost to every sample
            fn()
        except ROSSafetyViolation:
            pass
        out.append((clock() - start) / 1e3)
    return out


def _line(label: str, samples: list[float]) -> str:
    ordered = sorted(samples)
    p50 = ordered[len(ordered) // 2]
    p99 = ordered[int(len(ordered) * 0.99)]
    return f"  {label:<28} p50 {p50:6.2f} µs   p99 {p99:6.2f} µs   mean {statistics.fmean(samples):6.2f} µs"


def envelope_section(calls: int) -> list[str]:
    """Envelope check µs per tick, case by case."""
    lines = []
    step = 4.71 / RATE_HZ
    past_step = [v + 2 * step for v in HOME]
    out_of_range = [*HOME[:5], 3.0]
    leaves_box = [0.0, 0.15, 0.0, 0.0, 0.0, 0.5]  # within the step; the gripper frame passes x = 0.40
    empty = _time_calls(lambda: None, calls)
    lines.append(_line("timer only (empty call)", empty))
    for box in (False, True):
        lines.append(f" workspace box {'on (FK of gripperframe each check)' if box else 'off'}:")
        cases: list[tuple[str, SafetyMode, list[float]]] = [
            ("in-envelope", SafetyMode.REJECT, [v + 0.5 * step for v in HOME]),
            ("clamped", SafetyMode.CLAMP, past_step),
            ("rejected", SafetyMode.REJECT, out_of_range),
        ]
        if box:
            cases += [("box pull-back", SafetyMode.CLAMP, leaves_box), ("box rejected", SafetyMode.REJECT, leaves_box)]
        for label, mode, row in cases:
            client, action = _client(mode, box=box), _action(row)
            _time_calls(lambda c=client, a=action: c.check_action(a), calls // 10)  # warm up
            lines.append(_line(label, _time_calls(lambda c=client, a=action: c.check_action(a), calls)))
    return lines


def pieces_section(calls: int) -> list[str]:
    """Pure Python against numpy for the two inner pieces, on six joints."""
    client = _client(SafetyMode.CLAMP, box=True)
    chain = client.kinematics
    assert chain is not None
    row = [v + 0.01 for v in HOME]
    rows = np.array([row])
    lower = np.array([j.lower for j in ROBOT.joints])
    upper = np.array([j.upper for j in ROBOT.joints])
    max_step = np.array(client.max_step)
    reference = np.array(HOME)
    target = np.array(row)

    def numpy_joint_check() -> object:
        if not np.isfinite(target).all():
            raise ROSSafetyViolation("non-finite", check_name="non_finite")
        lo = np.maximum(lower, reference - max_step)
        hi = np.minimum(upper, reference + max_step)
        return np.clip(target, lo, hi).tolist()

    no_box = _client(SafetyMode.CLAMP, box=False)
    action = _action(row)
    return [
        _line("FK pure Python", _time_calls(lambda: chain.position(row), calls)),
        _line("FK numpy", _time_calls(lambda: chain.positions(rows), calls)),
        _line("joint checks pure Python*", _time_calls(lambda: no_box.check_action(action), calls)),
        _line("joint checks numpy", _time_calls(numpy_joint_check, calls)),
        "  (* the whole check_action without the box, validation and replacement included)",
    ]


def serial_section(calls: int) -> list[str]:
    """Serial round trip per tick (sync-read positions + sync-write goals) against the bus emulator.

    The emulator answers on a pseudo-terminal, so this is the protocol and driver cost without
    wire time: a real 1 Mbit/s bus adds about 1 ms of transmission per tick plus the adapter's latency.
    """
    from openral_hal.feetech.hal import SO10xFollowerHAL  # noqa: PLC0415  (needs the 'serial' extra)

    hal = SO10xFollowerHAL(ROBOT, {"emulate": True})
    hal.connect()
    try:
        state = hal.read_state()
        action = Action(joint_names=ROBOT.joint_names, targets=[list(state.positions)])
        read_us: list[float] = []
        tick_us: list[float] = []
        for _ in range(min(calls, 2000)):
            start = time.perf_counter()
            hal.read_state()
            middle = time.perf_counter()
            hal.send_action(action)
            end = time.perf_counter()
            read_us.append((middle - start) * 1e6)
            tick_us.append((end - start) * 1e6)
    finally:
        hal.disconnect()
    return [_line("sync-read (6 servos)", read_us), _line("read + sync-write per tick", tick_us)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--calls", type=int, default=20_000, help="timed calls per case")
    args = parser.parse_args()
    print(machine_line())
    print(f"envelope check per tick, SO-101 at {RATE_HZ:g} Hz, {args.calls} calls per case:")
    print("\n".join(envelope_section(args.calls)))
    print("pure Python against numpy, six joints:")
    print("\n".join(pieces_section(args.calls)))
    print("serial round trip per tick:")
    print("\n".join(serial_section(args.calls)))
    print(machine_line())


if __name__ == "__main__":
    main()
