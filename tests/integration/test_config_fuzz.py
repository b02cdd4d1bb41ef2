"""Hostile deployment files: at least 1,000 mutations of the shipped deployments through ``openral validate``.

Every case ends one of three ways, and any other is a failure:

* ``validate`` exits 2 with exactly one line on stderr, starting ``error:`` and naming a field the
  mutation touched (or the file, for file-level damage);
* ``validate`` exits 0 and ``deploy`` (a few ticks) runs it: exit 0 with a RunResult;
* ``validate`` exits 0 and ``deploy`` fails on hardware the configuration names but this machine
  lacks (exit 1, one line, a hardware or runtime error), which no configuration check can know.

Never a traceback, never a hang, never exit 0 from ``validate`` on a file ``deploy`` then refuses
as configuration. Mutations: wrong types, unknown keys, extreme numbers, removed keys, encodings,
YAML tags, anchors and aliases (bombs included), duplicate keys, truncation, deep nesting and
non-regular files. They are generated from a fixed seed, so a failure reproduces.
"""

from __future__ import annotations

import copy
import ctypes.util
import importlib.util
import json
import os
import random
import socket
import threading
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import yaml
from click.testing import CliRunner

from openral_cli.main import cli

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]

DEPLOYMENTS = Path(__file__).resolve().parents[2] / "deployments"
N_CASES = 1200
SEED = 20261123
CASE_TIMEOUT_S = 60.0

# The shipped deployments and the optional module each needs (CI installs them all).
SEEDS = {
    "so101_twin_hello.yaml": "mujoco",
    "so101_serial_emulated.yaml": "serial",
    "video_file.yaml": "cv2",
    "gstreamer_testsrc.yaml": "gi",
    "so101_twin_camera.yaml": "mujoco",
}
# The camera twin renders on the CPU (~1 s per deploy): mutate it less often.
SEED_WEIGHTS = {"so101_twin_camera.yaml": 1, "so101_twin_hello.yaml": 4}

WRONG_VALUES: list[Any] = [True, False, None, "text", "", [], [1, 2], {}, {"x": 1}, 3, -1, 0.5, "30"]
EXTREME_NUMBERS: list[Any] = [
    10**30,
    -(10**30),
    2**63,
    -1,
    0,
    1e308,
    -1e308,
    1e-300,
    float("nan"),
    float("inf"),
    float("-inf"),
    0.0001,
]
TAGS = [
    "!!python/object/apply:os.system ['true']",
    "!!python/name:os.system",
    "!!binary aGVsbG8=",
    "!!timestamp 2024-01-01",
    "!!set {a, b}",
    "!!omap [{a: 1}]",
    "!custom value",
    "!!str 30",
    "!!int '12'",
    "!!float '1.5'",
    "!!bool 'yes'",
    "!!null ''",
]


@dataclass
class Case:
    """One generated file and what an error about it must mention."""

    category: str
    seed: str
    data: bytes | None = None
    special: str | None = None  # a non-regular file kind instead of data
    names: set[str] = field(default_factory=set)


def _runnable(name: str, module: str) -> bool:
    """Whether this machine has what the shipped deployment needs (CI has everything)."""
    if importlib.util.find_spec(module) is None:
        return False
    if name == "so101_twin_camera.yaml":  # renders off screen: Mesa's EGL or OSMesa
        return any(ctypes.util.find_library(lib) for lib in ("EGL", "OSMesa"))
    return True


def _available_seeds() -> dict[str, dict[str, Any]]:
    seeds = {}
    for name, module in SEEDS.items():
        if not _runnable(name, module):
            continue
        tree = yaml.safe_load((DEPLOYMENTS / name).read_text(encoding="utf-8"))
        for sensor in tree.get("sensors", []):  # the fuzzed copies live elsewhere: make paths absolute
            device = sensor.get("backend_params", {}).get("device")
            if isinstance(device, str) and not device.startswith(("/", "rtsp:")) and not device.isdigit():
                sensor["backend_params"]["device"] = str(DEPLOYMENTS / device)
        seeds[name] = tree
    return seeds


def _paths(node: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    out = [prefix] if prefix else []
    if isinstance(node, dict):
        for key, value in node.items():
            out += _paths(value, (*prefix, key))
    elif isinstance(node, list):
        for index, value in enumerate(node):
            out += _paths(value, (*prefix, index))
    return out


def _get(tree: Any, path: tuple[Any, ...]) -> Any:
    for part in path:
        tree = tree[part]
    return tree


def _set(tree: Any, path: tuple[Any, ...], value: Any) -> None:
    _get(tree, path[:-1])[path[-1]] = value


def _names(path: tuple[Any, ...]) -> set[str]:
    """What an error about ``path`` may name: any key on it (an error may be reported one level up)."""
    return {part for part in path if isinstance(part, str)}


def _dump(tree: Any) -> str:
    return yaml.safe_dump(tree, sort_keys=False, allow_unicode=True)


class Generator:
    def __init__(self, seeds: dict[str, dict[str, Any]], rng: random.Random) -> None:
        self.seeds = seeds
        self.rng = rng
        names = list(seeds)
        self.seed_names = [n for n in names for _ in range(SEED_WEIGHTS.get(n, 2))]

    def case(self) -> Case:
        seed = self.rng.choice(self.seed_names)
        tree = copy.deepcopy(self.seeds[seed])
        kind = self.rng.choice(
            [
                "wrong_type",
                "wrong_type",
                "unknown_key",
                "extreme_number",
                "extreme_number",
                "remove_key",
                "encoding",
                "yaml_tag",
                "anchor",
                "duplicate_key",
                "truncate",
                "nesting",
                "string_value",
                "non_regular",
            ]
        )
        return getattr(self, kind)(seed, tree)

    def _pick(self, tree: Any, *, numeric: bool = False, mapping_parent: bool = False) -> tuple[Any, ...]:
        paths = _paths(tree)
        if numeric:
            numeric_paths = [
                p for p in paths if isinstance(_get(tree, p), int | float) and not isinstance(_get(tree, p), bool)
            ]
            paths = numeric_paths or paths
        if mapping_parent:
            paths = [p for p in paths if isinstance(p[-1], str)]
        return self.rng.choice(paths)

    def wrong_type(self, seed: str, tree: Any) -> Case:
        path = self._pick(tree)
        _set(tree, path, copy.deepcopy(self.rng.choice(WRONG_VALUES)))
        return Case("wrong_type", seed, _dump(tree).encode(), names=_names(path))

    def extreme_number(self, seed: str, tree: Any) -> Case:
        path = self._pick(tree, numeric=True)
        _set(tree, path, self.rng.choice(EXTREME_NUMBERS))
        return Case("extreme_number", seed, _dump(tree).encode(), names=_names(path))

    def string_value(self, seed: str, tree: Any) -> Case:
        path = self._pick(tree)
        value = self.rng.choice(
            ["x" * 5000, "so100_follower", "null", "../../etc/passwd", "/dev/zero", "a\x00b", "é☃", "-1", "~", "0"]
        )
        _set(tree, path, value)
        return Case("string_value", seed, _dump(tree).encode(), names=_names(path))

    def unknown_key(self, seed: str, tree: Any) -> Case:
        mappings = [p for p in _paths(tree) if isinstance(_get(tree, p), dict)] + [()]
        path = self.rng.choice(mappings)
        target = _get(tree, path) if path else tree
        existing = list(target) or ["key"]
        base = self.rng.choice(existing)
        key = self.rng.choice([base + "s", base[:-1] or "k", base.upper(), "unknown_" + base, "x y", "ünïcode"])
        target[key] = self.rng.choice([1, "v", True, None, [1]])
        return Case("unknown_key", seed, _dump(tree).encode(), names={key, *map(str, path)})

    def remove_key(self, seed: str, tree: Any) -> Case:
        path = self._pick(tree, mapping_parent=True)
        del _get(tree, path[:-1])[path[-1]]
        return Case("remove_key", seed, _dump(tree).encode(), names=_names(path))

    def encoding(self, seed: str, tree: Any) -> Case:
        tree.setdefault("task", {})["instruction"] = "wave héllo ☃"
        text = _dump(tree)
        variant = self.rng.choice(["utf-16", "utf-32", "latin-1", "utf-8-sig", "nul", "invalid", "control"])
        if variant in ("utf-16", "utf-32", "utf-8-sig"):
            data = text.encode(variant)
        elif variant == "latin-1":
            data = text.encode("latin-1", errors="replace")
        elif variant == "nul":
            cut = self.rng.randrange(len(text))
            data = (text[:cut] + "\x00" + text[cut:]).encode()
        elif variant == "invalid":
            cut = self.rng.randrange(len(text))
            data = text[:cut].encode() + b"\xff\xfe\x80" + text[cut:].encode()
        else:
            cut = self.rng.randrange(len(text))
            data = (text[:cut] + "\x07\x1b" + text[cut:]).encode()
        return Case("encoding", seed, data, names={"UTF", "YAML", "line"})

    def yaml_tag(self, seed: str, tree: Any) -> Case:
        path = self._pick(tree, mapping_parent=True)
        marker = "__TAGGED__"
        _set(tree, path, marker)
        text = _dump(tree).replace(f"'{marker}'", marker).replace(marker, self.rng.choice(TAGS))
        return Case("yaml_tag", seed, text.encode(), names=_names(path) | {"YAML", "line"})

    def anchor(self, seed: str, tree: Any) -> Case:
        variant = self.rng.choice(["reuse", "merge", "merge_bomb", "alias_bomb", "recursive", "undefined"])
        text = _dump(tree)
        if variant == "reuse":  # a legitimate anchor: must load as if written out
            text = text.replace("vla:\n  id:", "vla: &skill\n  id:", 1) + "x_copy: *skill\n"
            return Case("anchor", seed, text.encode(), names={"x_copy"})
        if variant == "merge":
            text = "defaults: &d {rate_hz: 20}\n" + text
            return Case("anchor", seed, text.encode(), names={"defaults"})
        if variant == "merge_bomb":
            lines = ["a0: &a0 {k: v}"] + [
                f"a{i}: &a{i} {{<<: [{', '.join([f'*a{i - 1}'] * 9)}]}}" for i in range(1, 25)
            ]
            return Case("anchor", seed, (text + "\n".join(lines) + "\n").encode(), names={"a0", "a1", "a24"})
        if variant == "alias_bomb":
            lines = ["l0: &l0 [x, x, x, x, x, x, x, x, x, x]"]
            lines += [f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 10)}]" for i in range(1, 10)]
            key = self.rng.choice(["task", "vla"])
            tail = f"\n{key}_bomb: *l9\n"
            return Case("anchor", seed, (text + "\n".join(lines) + tail).encode(), names={"values", "l0", "l9"})
        if variant == "recursive":
            return Case("anchor", seed, (text + "loop: &loop [*loop]\n").encode(), names={"nested", "loop"})
        return Case("anchor", seed, (text + "ghost: *nowhere\n").encode(), names={"YAML", "line"})

    def duplicate_key(self, seed: str, tree: Any) -> Case:
        text = _dump(tree)
        variant = self.rng.choice(["top", "safety", "nested"])
        if variant == "safety":
            text += "safety:\n  client: null\n"
            return Case("duplicate_key", seed, text.encode(), names={"duplicate key 'safety'"})
        if variant == "top":
            key = self.rng.choice([k for k in tree if not isinstance(tree[k], dict | list)] or ["name"])
            text += f"{key}: {json.dumps(tree.get(key, 'x'))}\n"
            return Case("duplicate_key", seed, text.encode(), names={f"duplicate key '{key}'"})
        text = text.replace("hal:\n", "hal:\n  robot_id: so100_follower\n", 1)
        return Case("duplicate_key", seed, text.encode(), names={"duplicate key 'robot_id'"})

    def truncate(self, seed: str, tree: Any) -> Case:
        text = _dump(tree)
        cut = self.rng.randrange(1, len(text))
        return Case("truncate", seed, text[:cut].encode(), names=set(tree) | {"YAML", "line", "mapping"})

    def nesting(self, seed: str, tree: Any) -> Case:
        depth = self.rng.choice([65, 200, 1000, 20000])
        style = self.rng.choice(["flow", "block"])
        if style == "flow":
            text = _dump(tree) + "deep: " + "[" * depth + "]" * depth + "\n"
        else:
            text = _dump(tree) + "deep:\n" + "".join("  " * i + f"k{i}:\n" for i in range(min(depth, 400)))
        return Case("nesting", seed, text.encode(), names={"nested", "deep"})

    def non_regular(self, seed: str, tree: Any) -> Case:
        special = self.rng.choice(["fifo", "directory", "dev_zero", "tty", "socket", "missing"])
        where = self.rng.choice(["config", "manifest", "calibration"])
        if where == "config":
            return Case("non_regular", seed, special=special, names={"--config", "regular file", "not found"})
        if where == "manifest":
            tree.setdefault("vla", {})["manifest"] = f"@{special}@"
            return Case("non_regular", seed, _dump(tree).encode(), special=special, names={"vla.manifest"})
        tree["hal"] = {"robot_id": "so101_follower", "adapter": "so10x_follower"}
        tree["hal"]["params"] = {"emulate": True, "calibration": f"@{special}@"}
        return Case("non_regular", seed, _dump(tree).encode(), special=special, names={"hal.params.calibration"})


def _special_file(kind: str, directory: Path) -> str:
    path = directory / f"special_{kind}"
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "directory":
        path.mkdir()
    elif kind == "dev_zero":
        path.symlink_to("/dev/zero")
    elif kind == "tty":
        master, slave = os.openpty()
        path.symlink_to(os.ttyname(slave))
        _keep_open.extend([master, slave])
    elif kind == "socket":
        server = socket.socket(socket.AF_UNIX)
        server.bind(str(path))
        _keep_open.append(server)
    return str(path)


_keep_open: list[Any] = []


def _invoke(args: list[str]) -> tuple[int, str, str]:
    """Run the CLI in this process; returns exit code, stdout and stderr.

    ``deploy`` installs signal handlers, which only the main thread may do: it runs there, under the
    test's timeout. ``validate`` runs on a thread with a per-case hang guard.
    """
    if args[0] == "deploy":
        result = CliRunner().invoke(cli, args, catch_exceptions=True)
        if result.exception is not None and not isinstance(result.exception, SystemExit):
            raise AssertionError(f"openral {' '.join(args)} crashed with {result.exception!r}") from result.exception
        return result.exit_code, result.stdout, result.stderr
    outcome: list[Any] = []

    def target() -> None:
        try:
            result = CliRunner().invoke(cli, args, catch_exceptions=True)
            outcome.append(result)
        except BaseException as exc:  # reported below
            outcome.append(exc)

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(CASE_TIMEOUT_S)
    assert outcome, f"openral {' '.join(args)} did not finish within {CASE_TIMEOUT_S} s (a hang)"
    result = outcome[0]
    assert not isinstance(result, BaseException), f"openral {' '.join(args)} raised {result!r}"
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise AssertionError(f"openral {' '.join(args)} crashed with {result.exception!r}") from result.exception
    return result.exit_code, result.stdout, result.stderr


def _one_error_line(stderr: str) -> str:
    lines = [line for line in stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1, f"expected exactly one error line, got:\n{stderr}"
    assert "Traceback" not in stderr
    return lines[0]


@pytest.fixture
def cases(tmp_path: Path) -> list[tuple[Case, Path]]:
    seeds = _available_seeds()
    if not seeds:
        pytest.skip("no shipped deployment can run here: install the extras (uv sync --all-extras)")
    rng = random.Random(SEED)
    generator = Generator(seeds, rng)
    out = []
    for index in range(N_CASES):
        case = generator.case()
        directory = tmp_path / f"case{index:04d}"
        directory.mkdir()
        path = directory / "deploy.yaml"
        special_path = _special_file(case.special, directory) if case.special else None
        if case.data is None:
            path = Path(special_path or directory / "absent.yaml")
            case.names.add(str(path))  # the file itself is the problem: the error names it
        else:
            data = case.data
            if special_path is not None:
                data = data.replace(f"@{case.special}@".encode(), special_path.encode())
            path.write_bytes(data)
        out.append((case, path))
    return out


def test_every_hostile_file_is_a_one_line_config_error_or_a_valid_run(
    cases: list[tuple[Case, Path]], capsys: pytest.CaptureFixture[str]
) -> None:
    outcomes: Counter[str] = Counter()
    by_category: Counter[str] = Counter()
    try:
        for case, path in cases:
            by_category[case.category] += 1
            where = f"case {case.category} from {case.seed} ({path})"
            code, _stdout, stderr = _invoke(["validate", str(path)])
            if code == 2:
                line = _one_error_line(stderr)
                assert any(name in line for name in case.names), f"{where}: error does not name {case.names}: {line}"
                outcomes["config error (exit 2)"] += 1
                continue
            assert code == 0, f"{where}: validate exited {code}:\n{stderr}"
            code, stdout, stderr = _invoke(
                ["deploy", "--config", str(path), "--max-ticks", "3", "--duration", "2", "--json"]
            )
            if code == 0:
                result = json.loads(stdout)
                assert result["n_ticks"] <= 3
                outcomes["valid run (exit 0)"] += 1
                continue
            line = _one_error_line(stderr)
            assert code == 1, f"{where}: validate accepted it but deploy exited {code}: {line}"
            assert line.startswith(("error: ROSHardwareError", "error: ROSRuntimeError")), f"{where}: {line}"
            outcomes["needs hardware this machine lacks (exit 1)"] += 1
    finally:
        for resource in _keep_open:
            if isinstance(resource, int):
                os.close(resource)
            else:
                resource.close()
        _keep_open.clear()
    with capsys.disabled():
        print(f"\nconfig fuzz: {len(cases)} files; {dict(outcomes)}; by mutation: {dict(by_category)}")
    assert len(cases) >= 1000
    assert outcomes["config error (exit 2)"] > 500
    assert outcomes["valid run (exit 0)"] > 50
