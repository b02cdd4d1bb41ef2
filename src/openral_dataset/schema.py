"""The columns of an openral recording: LeRobot's features, then what really happened under ``openral.*``.

LeRobot's loader reads ``observation.state``, ``action``, one ``observation.images.<cam>`` video per
camera and the five default columns (``timestamp``, ``frame_index``, ``episode_index``, ``index``,
``task_index``, last). Everything else is prefixed ``openral.``: no key starting ``observation`` or
``action`` (those become policy inputs and outputs), no ``/`` in a key.

A column that mirrors a ``TickResult`` field is declared on that field (its ``DatasetColumn``) and
named ``openral.<field>``; the one exception, ``openral.tick_start_ns`` for ``start_ns``, is the
name datasets were recorded with. A camera's columns are ``openral.<camera>.<what>``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Final, NamedTuple

from openral_core import ROSDependencyMissing
from openral_core.results import DatasetColumn, tick_fields_with

try:
    import pyarrow as pa
except ImportError as exc:
    raise ROSDependencyMissing("pyarrow", extra="dataset", needed_for="recording datasets") from exc


STATE: Final = "observation.state"
ENVIRONMENT_STATE: Final = "observation.environment_state"
ACTION: Final = "action"
IMAGE_PREFIX: Final = "observation.images."
DEFAULT_COLUMNS: Final = ("timestamp", "frame_index", "episode_index", "index", "task_index")

ACTIONS: Final = "actions"
"""The dtype of a :data:`TICK_COLUMNS` column holding one float32 per action name."""


class TickColumn(NamedTuple):
    """A data column that records one ``TickResult`` field as it is (``None``: the column's absent value)."""

    tick_field: str
    column: str
    dtype: str


def _declared_columns(*, takeover: bool) -> tuple[TickColumn, ...]:
    return tuple(
        TickColumn(name, declared.name or f"openral.{name}", declared.dtype)
        for name, declared in tick_fields_with(DatasetColumn).items()
        if declared.takeover is takeover
    )


TICK_COLUMNS: Final = _declared_columns(takeover=False)
"""The ``openral.*`` columns that mirror ``TickResult`` fields, in field order; the trace and span id
(:data:`TRACE_ID`, :data:`SPAN_ID`) follow them, taken from its ``trace_context``."""

TAKEOVER_COLUMNS: Final = _declared_columns(takeover=True)
"""The columns of a deployment with a takeover skill, after :data:`TICK_COLUMNS`: which ticks a person drove,
whose action each row is, what the policy proposed (DAgger labels: ``NaN`` where it proposed nothing), and
which commands were limited to one envelope step just after control passed."""

_COLUMN_OF: Final = {c.tick_field: c.column for c in (*TICK_COLUMNS, *TAKEOVER_COLUMNS)}
TICK_IDX: Final = _COLUMN_OF["tick_idx"]
TICK_START_NS: Final = _COLUMN_OF["start_ns"]
LATENESS_MS: Final = _COLUMN_OF["lateness_ms"]
ACTION_APPLIED: Final = _COLUMN_OF["action_applied"]
WITHHELD_REASON: Final = _COLUMN_OF["withheld_reason"]
REQUESTED_ACTION: Final = _COLUMN_OF["requested_action"]
INTERVENTION: Final = _COLUMN_OF["intervention"]
ACTIVE_SKILL: Final = _COLUMN_OF["active_skill"]
POLICY_ACTION: Final = _COLUMN_OF["policy_action"]
HANDOVER_RAMP: Final = _COLUMN_OF["handover_ramp"]
TRACE_ID: Final = "openral.trace_id"
SPAN_ID: Final = "openral.span_id"


def tick_columns(*, takeover: bool) -> tuple[TickColumn, ...]:
    """The columns a recording mirrors from ``TickResult``, in order: the takeover ones only with a takeover skill."""
    return (*TICK_COLUMNS, *TAKEOVER_COLUMNS) if takeover else TICK_COLUMNS


_SCALARS: Final = {"int64": pa.int64(), "float32": pa.float32(), "bool": pa.bool_(), "string": pa.string()}
_ABSENT: Final[dict[str, Any]] = {"int64": -1, "float32": float("nan"), "bool": False, "string": ""}

TIMESTAMP_EXACT_S: Final = 2048.0
"""How long an episode may run before its float32 ``timestamp`` (LeRobot's dtype) can sit more than
LeRobot's 1e-4 s tolerance off the ``1 / fps`` grid: from 2048 s on, half a float32 step exceeds it."""


def camera_column(camera: str, what: str) -> str:
    """The ``openral.<camera>.<what>`` column of one camera (``stamp_ns``, ``seq``, ``age_ms``, ``repeated``)."""
    return f"openral.{camera}.{what}"


def video_key(camera: str) -> str:
    """The LeRobot feature (and video folder) name of a camera."""
    return f"{IMAGE_PREFIX}{camera}"


@dataclass(frozen=True)
class CameraSpec:
    """One recorded camera: its sensor id and the video's size (0 until known)."""

    sensor_id: str
    width: int = 0
    height: int = 0


def features(
    joint_names: Sequence[str],
    cameras: Sequence[CameraSpec],
    *,
    fps: int,
    vcodec: str,
    action_names: Sequence[str] | None = None,
    environment_state_names: Sequence[str] = (),
    takeover: bool = False,
) -> dict[str, dict[str, Any]]:
    """The ``features`` block of ``meta/info.json``, in column order, the five defaults last.

    Args:
        joint_names: Names of ``observation.state``.
        action_names: Names of ``action`` (the joints by default: a robot commanded in joint space).
        environment_state_names: Names of ``observation.environment_state`` (a simulator's object
            state), recorded only when given.
        takeover: Add :data:`TAKEOVER_COLUMNS` (a deployment with a takeover skill).
    """
    joints = list(joint_names)
    actions = joints if action_names is None else list(action_names)
    out: dict[str, dict[str, Any]] = {
        STATE: {"dtype": "float32", "shape": [len(joints)], "names": joints},
    }
    if environment_state_names:
        names = list(environment_state_names)
        out[ENVIRONMENT_STATE] = {"dtype": "float32", "shape": [len(names)], "names": names}
    out[ACTION] = {"dtype": "float32", "shape": [len(actions)], "names": actions}
    for cam in cameras:
        out[video_key(cam.sensor_id)] = {
            "dtype": "video",
            "shape": [cam.height, cam.width, 3],
            "names": ["height", "width", "channels"],
            "info": {
                "video.height": cam.height,
                "video.width": cam.width,
                "video.codec": "av1" if vcodec == "libsvtav1" else "h264",
                "video.pix_fmt": "yuv420p",
                "video.is_depth_map": False,
                "video.fps": fps,
                "video.channels": 3,
                "has_audio": False,
            },
        }
    for tick_column in tick_columns(takeover=takeover):
        if tick_column.dtype == ACTIONS:
            out[tick_column.column] = {"dtype": "float32", "shape": [len(actions)], "names": actions}
        else:
            out[tick_column.column] = _scalar(tick_column.dtype)
    out[TRACE_ID] = _scalar("string")
    out[SPAN_ID] = _scalar("string")
    for cam in cameras:
        out[camera_column(cam.sensor_id, "stamp_ns")] = _scalar("int64")
        out[camera_column(cam.sensor_id, "seq")] = _scalar("int64")
        out[camera_column(cam.sensor_id, "age_ms")] = _scalar("float32")
        out[camera_column(cam.sensor_id, "repeated")] = _scalar("bool")
    out["timestamp"] = _scalar("float32")
    for name in DEFAULT_COLUMNS[1:]:
        out[name] = _scalar("int64")
    return out


def arrow_schema(feature_block: dict[str, dict[str, Any]]) -> pa.Schema:
    """The data parquet schema for ``feature_block`` (videos are not columns)."""
    fields = []
    for name, spec in feature_block.items():
        if spec["dtype"] == "video":
            continue
        scalar = _SCALARS[spec["dtype"]]
        shape = spec["shape"]
        if shape == [1]:
            fields.append(pa.field(name, scalar))
        else:
            fields.append(pa.field(name, pa.list_(scalar, shape[0])))
    return pa.schema(fields)


def absent_values(feature_block: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """What a data column holds where a tick had no value: never null, since LeRobot's collate refuses nulls.

    ``""`` for strings (no withheld reason, an untraced tick), ``-1`` for integers (no camera frame
    yet), ``NaN`` for floats and vectors (no requested action), ``False`` for flags.
    """
    out: dict[str, Any] = {}
    for name, spec in feature_block.items():
        if spec["dtype"] == "video":
            continue
        value = _ABSENT[spec["dtype"]]
        out[name] = value if spec["shape"] == [1] else [value] * spec["shape"][0]
    return out


def stat_features(feature_block: dict[str, dict[str, Any]]) -> list[str]:
    """The features LeRobot keeps statistics of: every one but text, videos last.

    LeRobot appends episodes only to a dataset whose episode rows have exactly the columns it
    writes itself, statistics of every numeric and boolean feature included.
    """
    plain = [name for name, spec in feature_block.items() if spec["dtype"] not in ("string", "video")]
    return plain + [name for name, spec in feature_block.items() if spec["dtype"] == "video"]


def episode_schema(feature_block: dict[str, dict[str, Any]], stat_names: Sequence[str]) -> pa.Schema:
    """The schema of ``meta/episodes`` rows: the same for every episode, so LeRobot can concatenate them."""
    fields = [
        pa.field("episode_index", pa.int64()),
        pa.field("tasks", pa.list_(pa.string())),
        pa.field("length", pa.int64()),
        pa.field("data/chunk_index", pa.int64()),
        pa.field("data/file_index", pa.int64()),
        pa.field("dataset_from_index", pa.int64()),
        pa.field("dataset_to_index", pa.int64()),
    ]
    videos = [name for name, spec in feature_block.items() if spec["dtype"] == "video"]
    for key in videos:
        fields += [
            pa.field(f"videos/{key}/chunk_index", pa.int64()),
            pa.field(f"videos/{key}/file_index", pa.int64()),
            pa.field(f"videos/{key}/from_timestamp", pa.float64()),
            pa.field(f"videos/{key}/to_timestamp", pa.float64()),
        ]
    fields += [pa.field("meta/episodes/chunk_index", pa.int64()), pa.field("meta/episodes/file_index", pa.int64())]
    image_value = pa.list_(pa.list_(pa.list_(pa.float64())))
    for feature in stat_features(feature_block):
        for stat in stat_names:
            if stat == "count":
                value = pa.list_(pa.int64())
            else:
                value = image_value if feature in videos else pa.list_(pa.float64())
            fields.append(pa.field(f"stats/{feature}/{stat}", value))
    return pa.schema(fields)


def _scalar(dtype: str) -> dict[str, Any]:
    return {"dtype": dtype, "shape": [1], "names": None}
