"""Reading the files a user names (deployments, manifests, calibrations, scenes) without trusting them.

Every such file goes through :func:`read_config_file` and :func:`parse_config_text`, so each loader
gets the same guarantees:

* only a regular file of bounded size is read: a FIFO, a tty or ``/dev/zero`` is refused before
  anything blocks or fills memory;
* text must be UTF-8 (a byte-order mark is fine; UTF-16 is named as such);
* YAML is parsed with duplicate keys refused (a second ``safety:`` block is an error, not a silent
  override), nesting bounded, merge keys (``<<``) resolved without the exponential blow-up of a
  merge-key bomb, and anchors/aliases bounded by the size of the expanded document;
* the result is plain data (mappings with string keys, lists, strings, numbers, booleans, null);
  anything else YAML can produce (dates, binary, sets, non-string keys) is an error naming the field.

Every failure is one :class:`~openral_core.errors.ROSConfigError` on one line naming the field and the fix.
"""

from __future__ import annotations

import codecs
import json
import math
import os
import stat
from pathlib import Path
from typing import Any, Final

import yaml
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

from openral_core.errors import ROSConfigError

MAX_CONFIG_BYTES: Final = 1 << 20
"""Largest configuration file read (1 MiB): far above any real deployment, manifest or calibration."""

MAX_DEPTH: Final = 64
"""Deepest nesting of mappings and lists accepted in a configuration file."""

MAX_VALUES: Final = 100_000
"""Most values a configuration may expand to once anchors and aliases are followed."""

_MERGE_TAG: Final = "tag:yaml.org,2002:merge"
_STR_TAG: Final = "tag:yaml.org,2002:str"
_FILE_KINDS: Final = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)
_WIDE_BOMS: Final = (
    (codecs.BOM_UTF32_LE, "UTF-32"),
    (codecs.BOM_UTF32_BE, "UTF-32"),
    (codecs.BOM_UTF16_LE, "UTF-16"),
    (codecs.BOM_UTF16_BE, "UTF-16"),
)


CONFIG_DIR: Final = "config_dir"
"""Validation-context key under which a file's own folder is passed to the model validating it."""


def expand_user_path(value: str | os.PathLike[str], *, field: str | None = None) -> Path:
    """``value`` as a path with ``~`` expanded.

    Raises:
        ROSConfigError: The path is empty or holds a NUL byte (no file system accepts one).
    """
    text = os.fspath(value)
    if "\x00" in text:
        raise ROSConfigError(f"path {text!r} contains a NUL byte", field=field, hint="remove it")
    if not text.strip():
        raise ROSConfigError("path is empty", field=field, hint="name a file")
    return Path(text).expanduser()


def resolve_user_path(value: str | os.PathLike[str], base_dir: Path | None = None, *, field: str | None = None) -> Path:
    """``value`` with ``~`` expanded and, when relative, taken relative to ``base_dir`` (the deployment's folder)."""
    path = expand_user_path(value, field=field)
    if not path.is_absolute() and base_dir is not None:
        path = base_dir / path
    return path


def is_regular_file(path: Path) -> bool:
    """Whether ``path`` is a regular file; ``False`` for any path that cannot be one (a name too long)."""
    try:
        return path.is_file()
    except OSError:
        return False


def require_user_file(
    value: str | os.PathLike[str],
    base_dir: Path | None = None,
    *,
    field: str | None = None,
    what: str = "file",
    hint: str = "check the path; a relative one is taken from the deployment file's folder",
) -> Path:
    """The regular file a user names, resolved as :func:`resolve_user_path`; it must exist now.

    Any path that cannot be a file is a configuration error naming ``field``: missing, a directory
    or device, a name longer than the file system allows, a component that is not a folder.

    Raises:
        ROSConfigError: ``value`` does not name a readable regular file.
    """
    path = resolve_user_path(value, base_dir, field=field)
    try:
        info = os.stat(path)
    except FileNotFoundError as exc:
        raise ROSConfigError(f"{what} not found: {path}", field=field, hint=hint) from exc
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise ROSConfigError(f"{what} {str(path)[:120]!r} cannot be a file: {reason}", field=field, hint=hint) from exc
    _refuse_irregular(path, field, info)
    return path


def read_config_file(
    path: str | os.PathLike[str],
    *,
    field: str | None = None,
    max_bytes: int = MAX_CONFIG_BYTES,
    missing_hint: str = "check the path",
) -> str:
    """The text of a regular, UTF-8 file of at most ``max_bytes``.

    The file is opened without blocking (a FIFO without a writer or a tty does not hang) and
    checked on the open descriptor, so it cannot be swapped for something else in between.

    Args:
        path: The file; ``~`` is expanded.
        field: The option or field that named it (``--config``, ``vla.manifest``), for the error.
        max_bytes: Size limit.
        missing_hint: What to do when the file does not exist.

    Raises:
        ROSConfigError: Missing, unreadable, not a regular file, too large, or not UTF-8.
    """
    file = expand_user_path(path, field=field)
    try:
        fd = os.open(file, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except FileNotFoundError as exc:
        raise ROSConfigError(f"file not found: {file}", field=field, hint=missing_hint) from exc
    except PermissionError as exc:
        raise ROSConfigError(f"cannot read {file}: permission denied", field=field) from exc
    except OSError as exc:
        _refuse_irregular(file, field, _stat_or_none(file))
        raise ROSConfigError(f"cannot open {file}: {exc.strerror or exc}", field=field) from exc
    try:
        info = os.fstat(fd)
        _refuse_irregular(file, field, info)
        if info.st_size > max_bytes:
            raise ROSConfigError(
                f"{file} is {info.st_size} bytes; configuration files over {max_bytes} bytes are refused", field=field
            )
        data = _read_at_most(fd, max_bytes + 1)
    except OSError as exc:
        raise ROSConfigError(f"cannot read {file}: {exc.strerror or exc}", field=field) from exc
    finally:
        os.close(fd)
    if len(data) > max_bytes:
        raise ROSConfigError(
            f"{file} is over {max_bytes} bytes; configuration files that large are refused", field=field
        )
    return decode_config_bytes(data, source=str(file), field=field)


def _stat_or_none(path: Path) -> os.stat_result | None:
    try:
        return os.stat(path)
    except OSError:
        return None


def _refuse_irregular(file: Path, field: str | None, info: os.stat_result | None) -> None:
    if info is None:
        return
    for is_kind, kind in _FILE_KINDS:
        if is_kind(info.st_mode):
            raise ROSConfigError(f"{file} is {kind}, not a regular file", field=field, hint="name a regular file")


def _read_at_most(fd: int, limit: int) -> bytes:
    chunks: list[bytes] = []
    size = 0
    while size < limit:
        chunk = os.read(fd, min(65536, limit - size))
        if not chunk:
            break
        chunks.append(chunk)
        size += len(chunk)
    return b"".join(chunks)


def decode_config_bytes(data: bytes, *, source: str, field: str | None = None) -> str:
    """UTF-8 text of a configuration file (a UTF-8 byte-order mark is dropped).

    Raises:
        ROSConfigError: The bytes are UTF-16/32 or not valid UTF-8.
    """
    for bom, name in _WIDE_BOMS:
        if data.startswith(bom):
            raise ROSConfigError(f"{source} is {name} text", field=field, hint="save it as UTF-8")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ROSConfigError(
            f"{source} is not UTF-8 text (byte 0x{data[exc.start]:02x} at offset {exc.start})",
            field=field,
            hint="save it as UTF-8",
        ) from exc


def parse_config_text(text: str, *, source: str, field: str | None = None, json_text: bool = False) -> Any:
    """Parse YAML (or JSON with ``json_text``) into plain data, with the limits described above.

    Raises:
        ROSConfigError: Syntax error, duplicate key, too deep, too large once expanded, or a value
            that is not plain data; one line, naming the line and column or the field.
    """
    parse = _parse_json if json_text else _parse_yaml
    data = parse(text, source=source, field=field)
    return to_plain(data, source=source, field=field)


def load_config_file(
    path: str | os.PathLike[str], *, field: str | None = None, missing_hint: str = "check the path"
) -> Any:
    """Read and parse a configuration file: JSON when its name ends in ``.json``, YAML otherwise."""
    file = expand_user_path(path, field=field)
    text = read_config_file(file, field=field, missing_hint=missing_hint)
    return parse_config_text(text, source=str(file), field=field, json_text=file.suffix.lower() == ".json")


def load_json_file(
    path: str | os.PathLike[str], *, field: str | None = None, missing_hint: str = "check the path"
) -> Any:
    """Read and parse a JSON file a tool or a person wrote (a checkpoint's ``config.json``, a recorded trajectory).

    Bounded as every configuration file (size, nesting, duplicate keys), and its numbers finite:
    JSON has no infinity or NaN, yet Python's parser reads ``Infinity``, ``NaN`` and a number no
    float can hold (``1e400``) as one.

    Raises:
        ROSConfigError: One line naming the file: unreadable, not JSON, too deep or too large, or a
            number that is not finite.
    """
    file = expand_user_path(path, field=field)
    text = read_config_file(file, field=field, missing_hint=missing_hint)
    data = _parse_json(text, source=str(file), field=field, finite=True)
    return to_plain(data, source=str(file), field=field)


# -- YAML --------------------------------------------------------------------------------------------


class _ConfigLoader(yaml.SafeLoader):
    """PyYAML's safe loader with duplicate keys refused, bounded nesting and linear merge keys."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0
        self._flattened: set[int] = set()

    def compose_node(self, parent: Node | None, index: int) -> Node | None:
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                event = self.peek_event()  # type: ignore[no-untyped-call]
                raise yaml.YAMLError(f"nested more than {MAX_DEPTH} levels deep{_mark(event.start_mark)}")
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def flatten_mapping(self, node: MappingNode) -> None:
        """Resolve ``<<`` merge keys once per node, keeping each key once (explicit keys win)."""
        if id(node) in self._flattened:
            return
        self._flattened.add(id(node))
        explicit: list[tuple[Node, Node]] = []
        sources: list[Node] = []
        for key_node, value_node in node.value:
            if key_node.tag == _MERGE_TAG:
                sources.extend(value_node.value if isinstance(value_node, SequenceNode) else [value_node])
            else:
                explicit.append((key_node, value_node))
        seen: set[tuple[str, str]] = set()
        for key_node, _ in explicit:
            key = _key_of(key_node)
            if key in seen:
                raise yaml.YAMLError(f"duplicate key '{key[1]}'{_mark(key_node.start_mark)}")
            seen.add(key)
        merged: list[tuple[Node, Node]] = []
        for source in sources:
            if not isinstance(source, MappingNode):
                raise yaml.YAMLError(f"'<<' must merge a mapping or a list of mappings{_mark(source.start_mark)}")
            self.flatten_mapping(source)
            for key_node, value_node in source.value:
                key = _key_of(key_node)
                if key not in seen:
                    seen.add(key)
                    merged.append((key_node, value_node))
        node.value = explicit + merged


def _key_of(node: Node) -> tuple[str, str]:
    if not isinstance(node, ScalarNode):
        raise yaml.YAMLError(f"a key must be plain text, not a mapping or list{_mark(node.start_mark)}")
    return node.tag, node.value


def _mark(mark: Any) -> str:
    return "" if mark is None else f" at line {mark.line + 1}, column {mark.column + 1}"


def _parse_yaml(text: str, *, source: str, field: str | None) -> Any:
    loader: _ConfigLoader | None = None
    try:
        loader = _ConfigLoader(text)
        return loader.get_single_data()
    except yaml.reader.ReaderError as exc:
        character = f"U+{exc.character:04X}" if isinstance(exc.character, int) else repr(exc.character)
        raise ROSConfigError(
            f"{source} is not valid YAML: control character {character} at offset {exc.position}",
            field=field,
            hint="remove it",
        ) from exc
    except yaml.MarkedYAMLError as exc:
        problem = " ".join(str(exc.problem or exc.context or "invalid YAML").split())
        raise ROSConfigError(f"{source} is not valid YAML: {problem}{_mark(exc.problem_mark)}", field=field) from exc
    except yaml.YAMLError as exc:
        raise ROSConfigError(f"{source} is not valid YAML: {' '.join(str(exc).split())}", field=field) from exc
    except RecursionError as exc:
        raise ROSConfigError(f"{source} is nested too deeply", field=field) from exc
    finally:
        if loader is not None:
            loader.dispose()


def _parse_json(text: str, *, source: str, field: str | None, finite: bool = False) -> Any:
    def unique(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for key, value in pairs:
            if key in out:
                raise ValueError(f"duplicate key '{key}'")
            out[key] = value
        return out

    try:
        if finite:
            return json.loads(text, object_pairs_hook=unique, parse_float=_finite, parse_constant=_no_constant)
        return json.loads(text, object_pairs_hook=unique)
    except json.JSONDecodeError as exc:
        raise ROSConfigError(
            f"{source} is not valid JSON: {exc.msg} at line {exc.lineno}, column {exc.colno}", field=field
        ) from exc
    except ValueError as exc:
        raise ROSConfigError(f"{source} is not valid JSON: {exc}", field=field) from exc
    except RecursionError as exc:
        raise ROSConfigError(f"{source} is nested too deeply", field=field) from exc


def _finite(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"number {text[:24]} is too large for a float")
    return value


def _no_constant(name: str) -> float:
    raise ValueError(f"{name} is not a JSON number")


# -- plain data ----------------------------------------------------------------------------------------

_PLAIN_SCALARS: Final = (str, bool, int, float, type(None))
_YAML_TYPE_NAMES: Final = {
    "date": "a date (quote it to make it text)",
    "datetime": "a date and time (quote it to make it text)",
    "bytes": "binary data (!!binary)",
    "set": "a set (!!set)",
    "tuple": "a pair list (!!omap or !!pairs)",
}


def to_plain(data: Any, *, source: str, field: str | None = None) -> Any:
    """Check that ``data`` is plain configuration data, bounded in depth and size once aliases are expanded.

    Returns ``data`` itself (lists and mappings are not copied).

    Raises:
        ROSConfigError: Naming the first offending field.
    """
    budget = [MAX_VALUES]
    _check_plain(data, field or "", 0, budget, source)
    return data


def _check_plain(value: Any, where: str, depth: int, budget: list[int], source: str) -> None:
    budget[0] -= 1
    if budget[0] < 0:
        raise ROSConfigError(
            f"{source} expands to more than {MAX_VALUES} values (anchors and aliases repeat content)",
            field=where or None,
            hint="write the configuration out without deeply nested aliases",
        )
    if depth > MAX_DEPTH:
        raise ROSConfigError(f"{source} is nested more than {MAX_DEPTH} levels deep", field=where or None)
    if isinstance(value, dict):
        for key, item in value.items():
            if not isinstance(key, str):
                raise ROSConfigError(
                    f"key {key!r} is read as {type(key).__name__}, not text",
                    field=where or None,
                    hint=f"quote it: '{key}'",
                )
            _check_plain(item, f"{where}.{key}" if where else key, depth + 1, budget, source)
    elif isinstance(value, list):
        for index, item in enumerate(value):
            _check_plain(item, f"{where}[{index}]", depth + 1, budget, source)
    elif not isinstance(value, _PLAIN_SCALARS):
        kind = _YAML_TYPE_NAMES.get(type(value).__name__, type(value).__name__)
        raise ROSConfigError(f"is {kind}, which a configuration value cannot be", field=where or None)


def is_plain(data: Any) -> bool:
    """Whether ``data`` is plain configuration data (as :func:`to_plain` accepts)."""
    try:
        to_plain(data, source="data")
    except ROSConfigError:
        return False
    return True
