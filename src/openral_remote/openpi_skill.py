"""``openpi_policy``: a robot or a simulation driven by any server that speaks openpi's websocket protocol.

openpi's ``serve_policy`` (π0, π0.5), SGLang, vLLM-Omni and ``openral serve --protocol openpi``
all answer it: one websocket, a metadata frame first, then one msgpack observation in, one
``{"actions": (H, D)}`` out (:mod:`openral_remote.msgpack_numpy`). The observation is the dict of
one of openpi's example clients, or openral's own (:mod:`openral_remote.openpi_profiles`).

The chunk executor asks for each chunk on its worker, never on the tick; the first ``rows`` rows of
each chunk are used (openpi's ``replan_steps``), columns ``action_slice`` of them. How the rows are
meant (``representation``) is a parameter, or the server's ``openral`` metadata when it sends one
(an openral server does: the anchor a local run would use). When the parameters leave the
representation or the rows open, the metadata is read once when the skill is built.

A server that is gone (a refused connection, a closed socket) or silent past ``deadline_ms`` marks
the link down: :meth:`available` turns ``False`` and the executor's fallback acts, as for
``remote_policy``; the link is tried again every ``reconnect_s`` and taken back when the server
answers with the same metadata. A late answer is never used: the protocol has no request ids, so
the connection is dropped. A text frame (openpi's traceback) is the server's policy failing:
:class:`~openral_core.ROSRuntimeError` with its message. The protocol has no reset: each episode
opens a new connection (one connection is one client episode on the server).
"""

from __future__ import annotations

import contextlib
import math
import socket
import ssl
import struct
import threading
import time
from collections.abc import Mapping
from typing import Any, Self

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from openral_core import (
    ControlMode,
    RobotManifest,
    ROSConfigError,
    ROSRuntimeError,
    ROSUnavailable,
    RSkillInfo,
    RSkillState,
)
from openral_core.config_files import read_config_file, require_user_file
from openral_core.errors import renamed_field
from openral_remote.codec import WireFormatError
from openral_remote.config import TlsConfig
from openral_remote.meta import PolicyMeta
from openral_remote.msgpack_numpy import Limits, packb, unpackb
from openral_remote.openpi_profiles import CameraOrientation, OpenpiProfile, ProfileName
from openral_remote.tls import check_tls
from openral_rskill.anchoring import (
    AbsoluteAnchor,
    ActionRepresentation,
    Anchor,
    AnchorSpec,
    EndEffectorDeltaAnchor,
    StateOffsetAnchor,
    UnanchoredRows,
)
from openral_rskill.base import ChunkingSkillBase, validate_params
from openral_rskill.chunks import ChunkRequest

SKILL_ID = "openpi_policy"
OPENRAL_META = "openral"
"""Metadata key of an openral server: its :class:`~openral_remote.meta.PolicyMeta`."""

_log = structlog.get_logger(__name__)


class OpenpiPolicyParams(BaseModel):
    """``params`` of the ``openpi_policy`` skill."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    host: str = Field(default="127.0.0.1", min_length=1, description="The server's host name or address.")
    port: int = Field(default=8000, ge=1, le=65535, description="The server's port (openpi's default 8000).")
    api_key: str | None = Field(default=None, min_length=1, description="Sent as 'Authorization: Api-Key <key>'.")
    api_key_file: str | None = Field(default=None, description="A file holding the API key (instead of api_key).")
    tls: TlsConfig | None = Field(default=None, description="wss://: the CA that signed the server's certificate.")
    profile: ProfileName = Field(default="openral", description="The observation dict: openral, libero, aloha, droid.")
    cameras: dict[str, str] | None = Field(
        default=None, description="The profile's camera slot -> this robot's sensor id (the profile's defaults)."
    )
    image_size: int | None = Field(
        default=None, ge=1, le=4096, description="Side of the square images sent; default 224 (openral: as captured)."
    )
    camera_orientation: CameraOrientation = Field(
        default="upright", description="libero: whether the frames are upright or mirrored as LeRobot's datasets."
    )
    rows: int | None = Field(
        default=None, ge=1, le=4096, description="Rows of each chunk used (openpi's replan_steps); default: all."
    )
    action_slice: tuple[int, int] | None = Field(
        default=None, description="[start, stop): the action columns this robot takes; default: all of them."
    )
    representation: ActionRepresentation | None = Field(
        default=None, description="How the rows are meant; default: the server's openral metadata, else absolute."
    )
    anchor_key: str | None = Field(default=None, description="delta_ee: the privileged position the rows move.")
    action_scale: float = Field(default=1.0, gt=0, description="delta_ee: metres per unit of action.")
    position_dims: list[int] = Field(default_factory=lambda: [0, 1, 2], description="delta_ee: the moving dims.")
    connect_timeout_s: float = Field(default=10.0, gt=0, le=600, description="Connecting and the metadata frame.")
    deadline_ms: float = Field(
        default=2000.0, gt=0, le=600_000, description="A chunk not answered by then: the link is dropped (late)."
    )
    reconnect_s: float = Field(default=1.0, gt=0, le=3600, description="How often a down server is tried again.")
    max_message_bytes: int = Field(
        default=64 << 20, ge=1024, le=1 << 30, description="The largest answer taken (a frame past it closes the link)."
    )

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        if self.api_key is not None and self.api_key_file is not None:
            raise ValueError("give api_key or api_key_file, not both")
        if self.action_slice is not None and not 0 <= self.action_slice[0] < self.action_slice[1]:
            raise ValueError("action_slice is [start, stop) with 0 <= start < stop")
        if self.representation is ActionRepresentation.DELTA_EE and self.anchor_key is None:
            raise ValueError("representation delta_ee needs anchor_key (the privileged position the rows move)")
        return self


class OpenpiUnavailable(ROSUnavailable):
    """The openpi server cannot be reached, or its connection was lost."""


class OpenpiTimeout(OpenpiUnavailable, TimeoutError):
    """The server did not answer before the deadline (the executor counts it late)."""


class _Link:
    """One websocket to the server: metadata on connect, then request/reply with a deadline."""

    def __init__(self, params: OpenpiPolicyParams, api_key: str | None) -> None:
        scheme = "wss" if params.tls is not None else "ws"
        host = f"[{params.host}]" if ":" in params.host else params.host
        self.uri = f"{scheme}://{host}:{params.port}"
        self.params = params
        self._headers = {"Authorization": f"Api-Key {api_key}"} if api_key else None
        self._ssl = _ssl_context(params.tls) if params.tls is not None else None
        self._limits = Limits(max_bytes=params.max_message_bytes)
        self._ws: Any = None
        self._stack: contextlib.ExitStack | None = None

    def open(self) -> dict[str, Any]:
        """Connect and read the metadata frame.

        Raises:
            OpenpiUnavailable: Refused, timed out, or the first frame is not a metadata map.
        """
        from websockets.exceptions import InvalidHandshake, WebSocketException  # noqa: PLC0415
        from websockets.sync.client import connect  # noqa: PLC0415

        timeout = self.params.connect_timeout_s
        stack = contextlib.ExitStack()  # a long-lived connection, closed by close()
        try:
            ws = stack.enter_context(
                connect(
                    self.uri,
                    open_timeout=timeout,
                    close_timeout=1.0,
                    compression=None,
                    max_size=self.params.max_message_bytes,
                    additional_headers=self._headers,
                    ssl=self._ssl,
                )
            )
        except InvalidHandshake as exc:
            raise OpenpiUnavailable(f"{self.uri} refused the websocket: {exc}") from None
        except (OSError, TimeoutError, WebSocketException) as exc:
            raise OpenpiUnavailable(f"cannot reach the openpi server at {self.uri}: {exc}") from None
        self._ws, self._stack = ws, stack
        # A server that stops reading must not wedge a send: each write to the socket gives up after the deadline.
        seconds = self.params.deadline_ms / 1000.0
        timeval = struct.pack("ll", int(seconds), int((seconds % 1.0) * 1e6))
        try:
            ws.socket.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, timeval)
        except OSError as exc:  # the server closed at once, and the client's reader closed the socket
            self.close()
            raise OpenpiUnavailable(f"the openpi server at {self.uri} closed the connection at once: {exc}") from None
        try:
            metadata = self._decode(self._receive(timeout))
        except BaseException:
            self.close()
            raise
        if not isinstance(metadata, dict) or not all(isinstance(key, str) for key in metadata):
            self.close()
            raise OpenpiUnavailable(f"{self.uri} sent no metadata map first")
        return metadata

    def infer(self, obs: Mapping[str, Any]) -> Any:
        """The server's answer to ``obs`` (decoded).

        Raises:
            OpenpiUnavailable: The connection is gone (the link is closed).
            OpenpiTimeout: No answer by the deadline (the link is closed: a late answer cannot be told apart).
            ROSRuntimeError: The server answered with an error text.
        """
        from websockets.exceptions import WebSocketException  # noqa: PLC0415

        if self._ws is None:
            raise OpenpiUnavailable(f"no connection to {self.uri}")
        message = packb(dict(obs))
        try:
            self._ws.send(message)
        except (OSError, WebSocketException) as exc:
            self.close()
            raise OpenpiUnavailable(f"the openpi server at {self.uri} is gone: {exc}") from None
        return self._decode(self._receive(self.params.deadline_ms / 1000.0))

    def _receive(self, timeout: float) -> bytes:
        from websockets.exceptions import WebSocketException  # noqa: PLC0415

        try:
            frame = self._ws.recv(timeout=timeout)
        except TimeoutError:
            self.close()
            raise OpenpiTimeout(f"the openpi server at {self.uri} did not answer within {timeout:g} s") from None
        except (OSError, WebSocketException) as exc:
            self.close()
            raise OpenpiUnavailable(f"the openpi server at {self.uri} is gone: {exc}") from None
        if isinstance(frame, str):
            self.close()
            raise ROSRuntimeError(f"the openpi server at {self.uri} failed: {frame.strip()[-2000:]}")
        return bytes(frame)

    def _decode(self, frame: bytes) -> Any:
        try:
            return unpackb(frame, limits=self._limits)
        except WireFormatError as exc:
            self.close()
            raise ROSRuntimeError(f"the openpi server at {self.uri} sent a malformed frame: {exc}") from None

    def close(self) -> None:
        stack, self._ws, self._stack = self._stack, None, None
        if stack is not None:
            stack.close()


class OpenpiPolicySkill(ChunkingSkillBase):
    """Asks an openpi-protocol server for each chunk.

    Args:
        robot: This robot (its joints are the action's width after ``action_slice``).
        params: The server, the profile, how the rows are used.
        rate_hz: The loop's rate (an openral server's step must match it).
        metadata: The server's metadata, read at build when the parameters leave something to it.
    """

    def __init__(
        self,
        robot: RobotManifest,
        params: OpenpiPolicyParams,
        *,
        rate_hz: float,
        metadata: Mapping[str, Any] | None = None,
    ) -> None:
        super().__init__()
        self.robot = robot
        self.params = params
        self.rate_hz = rate_hz
        self.profile = _profile(params)
        self.api_key = _api_key(params)
        self.metadata = dict(metadata) if metadata is not None else None
        self.served = _served_meta(self.metadata, field="vla.params.host")
        rows = params.rows or (self.served.chunk_size if self.served else None) or _horizon(self.metadata)
        if rows is None:
            raise ROSConfigError("the server says no action_horizon: give rows", field="vla.params.rows")
        self.rows = rows
        self.anchor_spec = self._anchor_spec()
        _check_meta(self, self.metadata)
        self._link: _Link | None = None
        self._up = False
        self._lock = threading.Lock()
        self._reconnecting = False
        self._next_try = 0.0
        self._info = RSkillInfo(
            skill_id=SKILL_ID,
            name=f"openpi policy at {params.host}:{params.port} ({params.profile} profile)",
            control_mode=ControlMode.EE_DELTA
            if self.anchor_spec.representation is ActionRepresentation.DELTA_EE
            else ControlMode.JOINT_POSITION,
            chunk_size=self.rows,
            description=f"chunks from an openpi-protocol server, observation as openpi's {params.profile} client",
            observation=self.reads or self.profile.world_fields(),
        )

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> Self:
        """Build the skill; the server's metadata is read now when the parameters leave the rows or the anchor to it."""
        checked = validate_params(OpenpiPolicyParams, params, skill_id=SKILL_ID)
        _check_offline(checked, robot)
        metadata = None
        if checked.representation is None or checked.rows is None:
            link = _Link(checked, _api_key(checked))
            try:
                metadata = link.open()
            except OpenpiUnavailable as exc:
                raise ROSConfigError(
                    f"{exc}; it is asked at start-up for how its rows are meant",
                    field="vla.params.host",
                    hint="start the server first, or give rows and representation",
                ) from None
            finally:
                link.close()
        return cls(robot, checked, rate_hz=rate_hz, metadata=metadata)

    @classmethod
    def check_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> None:
        """Check the parameters, the profile against the robot, and the key and TLS files without connecting."""
        checked = validate_params(OpenpiPolicyParams, params, skill_id=SKILL_ID)
        _check_offline(checked, robot)
        _check_state(_profile(checked), robot)

    @classmethod
    def offline_observation(cls, params: Mapping[str, Any]) -> list[str]:
        """What the profile reads of the world (its cameras by sensor id); empty for openral (the server says)."""
        return _profile(validate_params(OpenpiPolicyParams, params, skill_id=SKILL_ID)).world_fields()

    @property
    def info(self) -> RSkillInfo:
        return self._info

    @property
    def action_names(self) -> list[str]:
        return list(self.robot.joint_names)

    @property
    def reads(self) -> list[str]:
        """The world-state fields an openral server's policy reads (empty: everything, or the profile's)."""
        return list(self.served.observation) if self.served is not None else []

    def check_robot_inputs(self) -> None:
        """On a robot: the profile's state is the robot's joints."""
        _check_state(self.profile, self.robot)

    def action_anchor(self) -> Anchor:
        spec = self.anchor_spec
        if spec.representation is ActionRepresentation.RELATIVE_TO_STATE:
            return StateOffsetAnchor(spec.names or self.robot.joint_names)
        if spec.representation is ActionRepresentation.DELTA_EE and spec.position_key is not None:
            return EndEffectorDeltaAnchor(spec.position_key, spec.scale, spec.position_dims)
        if spec.representation in (ActionRepresentation.DELTA_EE, ActionRepresentation.UNANCHORED):
            return UnanchoredRows()
        return AbsoluteAnchor()

    def available(self) -> bool:
        """Whether the link is up: O(1); while down, a reconnection is tried in the background every ``reconnect_s``."""
        if not self._up and self.state is RSkillState.ACTIVE:
            self._maybe_reconnect()
        return self._up

    # -- lifecycle ---------------------------------------------------------------------------

    def _on_configure(self) -> None:
        link = _Link(self.params, self.api_key)
        try:
            metadata = link.open()
        except OpenpiUnavailable as exc:
            raise ROSConfigError(
                str(exc), field="vla.params.host", hint="start the server, or check host and port"
            ) from None
        try:
            self._judge(metadata)
        except ROSConfigError:
            link.close()
            raise
        self._swap(link)

    def _on_shutdown(self) -> None:
        self._swap(None)

    def _on_reset(self) -> None:
        """A new episode: a new connection (the protocol has no reset; one connection is one client episode)."""
        link = _Link(self.params, self.api_key)
        try:
            metadata = link.open()
            self._judge(metadata)
        except (OpenpiUnavailable, ROSConfigError) as exc:
            link.close()
            _log.warning("openpi server unavailable at episode start", uri=link.uri, error=str(exc))
            self._swap(None)
            return
        self._swap(link)

    def _chunk_impl(self, request: ChunkRequest) -> np.ndarray:
        """The server's chunk for the request's observation: the first ``rows`` rows, ``action_slice`` columns."""
        link = self._link
        if link is None or not self._up:
            raise OpenpiUnavailable(f"the openpi server at {self.params.host}:{self.params.port} is down")
        obs = self.profile.observation(request.world, reads=self.reads)
        try:
            answer = link.infer(obs)
        except (OpenpiUnavailable, ROSRuntimeError):
            self._mark_down(link)
            raise
        return self._rows(answer)

    # -- internals ---------------------------------------------------------------------------

    def _rows(self, answer: Any) -> np.ndarray:
        actions = answer.get("actions") if isinstance(answer, dict) else None
        if not isinstance(actions, np.ndarray) or actions.ndim != 2 or actions.dtype.kind not in "iuf":
            raise ROSRuntimeError(f"the openpi server answered without an actions array (H, D): {_brief(answer)}")
        if self.params.action_slice is not None:
            start, stop = self.params.action_slice
            if actions.shape[1] < stop:
                raise ROSRuntimeError(f"the server's actions are {actions.shape[1]} wide, action_slice ends at {stop}")
            actions = actions[:, start:stop]
        if actions.shape[1] != len(self.robot.joint_names):
            raise ROSRuntimeError(
                f"the server's actions are {actions.shape[1]} wide, this robot takes {len(self.robot.joint_names)}"
            )
        return np.asarray(actions[: self.rows], dtype=np.float64)

    def _judge(self, metadata: dict[str, Any]) -> None:
        """Refuse a server whose metadata differs from the first seen (at build, else at configure), or does not fit.

        An openral server's ``warmup_ms`` may differ: a restart of the same model is taken back.
        """
        _check_meta(self, metadata)
        if self.metadata is None:
            self.metadata = dict(metadata)
            return
        changed = _changed(self.metadata, metadata)
        if changed:
            raise ROSConfigError(
                f"the openpi server's metadata changed since start-up ({', '.join(changed)})", field="vla.params.host"
            )

    def _anchor_spec(self) -> AnchorSpec:
        params = self.params
        if params.representation is None and self.served is not None:
            return self.served.anchor
        representation = params.representation or ActionRepresentation.ABSOLUTE
        return AnchorSpec(
            representation=representation,
            names=list(self.robot.joint_names) if representation is ActionRepresentation.RELATIVE_TO_STATE else [],
            position_key=params.anchor_key,
            scale=params.action_scale,
            position_dims=params.position_dims,
        )

    def _swap(self, link: _Link | None) -> None:
        with self._lock:
            old, self._link = self._link, link
            self._up = link is not None
        if old is not None and old is not link:
            old.close()

    def _mark_down(self, link: _Link) -> None:
        with self._lock:
            if self._link is link:
                self._up = False
                self._next_try = time.monotonic() + self.params.reconnect_s
        link.close()

    def _maybe_reconnect(self) -> None:
        with self._lock:
            if self._reconnecting or time.monotonic() < self._next_try:
                return
            self._reconnecting = True
            self._next_try = time.monotonic() + self.params.reconnect_s
        threading.Thread(target=self._reconnect, name="openral-openpi-reconnect", daemon=True).start()

    def _reconnect(self) -> None:
        link = _Link(self.params, self.api_key)
        try:
            self._judge(link.open())
        except (OpenpiUnavailable, ROSConfigError, ROSRuntimeError) as exc:
            link.close()
            _log.debug("openpi server still unavailable", uri=link.uri, error=str(exc))
        else:
            if self.state is RSkillState.ACTIVE:
                _log.info("openpi server is back", uri=link.uri)
                self._swap(link)
            else:  # shut down meanwhile: nobody would close it
                link.close()
        finally:
            with self._lock:
                self._reconnecting = False


def _profile(params: OpenpiPolicyParams) -> OpenpiProfile:
    size = params.image_size if params.image_size is not None else (None if params.profile == "openral" else 224)
    try:
        return OpenpiProfile(
            params.profile, cameras=params.cameras, image_size=size, camera_orientation=params.camera_orientation
        )
    except ROSConfigError as exc:  # the profile names its own argument: name the parameter
        field = exc.field or "profile"
        raise renamed_field(exc, (field,), f"vla.params.{field}") from None


def _api_key(params: OpenpiPolicyParams) -> str | None:
    if params.api_key_file is None:
        return params.api_key
    key = read_config_file(params.api_key_file, field="vla.params.api_key_file", max_bytes=4096).strip()
    if not key or any(ch in key for ch in "\r\n"):
        raise ROSConfigError(
            f"{params.api_key_file} does not hold one key on one line", field="vla.params.api_key_file"
        )
    return key


def _check_offline(params: OpenpiPolicyParams, robot: RobotManifest) -> None:
    """Everything that needs no server: the profile, the key file, the CA file."""
    _profile(params)
    _api_key(params)
    if params.tls is not None:
        check_tls(params.tls, prefix="vla.params.tls.")
    if params.action_slice is not None and params.action_slice[1] - params.action_slice[0] != len(robot.joint_names):
        raise ROSConfigError(
            f"action_slice {list(params.action_slice)} takes {params.action_slice[1] - params.action_slice[0]} "
            f"columns, robot {robot.robot_id} has {len(robot.joint_names)} action dimensions",
            field="vla.params.action_slice",
        )


def _check_state(profile: OpenpiProfile, robot: RobotManifest) -> None:
    """On a robot the state sent is its joints: the profile's state must have as many values."""
    dims = profile.state_dims
    if dims is not None and dims != len(robot.joint_names):
        raise ROSConfigError(
            f"the {profile.name} profile sends a state of {dims} values, robot "
            f"{robot.robot_id} measures {len(robot.joint_names)} joints",
            field="vla.params.profile",
        )


def _served_meta(metadata: Mapping[str, Any] | None, *, field: str) -> PolicyMeta | None:
    """An openral server's policy meta, when the metadata carries one."""
    if metadata is None or OPENRAL_META not in metadata:
        return None
    try:
        return PolicyMeta.model_validate(metadata[OPENRAL_META])
    except ValidationError as exc:
        raise ROSConfigError(f"the server's openral metadata is malformed: {_brief(exc)}", field=field) from None


def _changed(before: Mapping[str, Any], after: Mapping[str, Any]) -> list[str]:
    """The metadata keys whose values differ (``openral.<field>`` for an openral server's meta, ``warmup_ms`` aside)."""
    changed = sorted(key for key in {*before, *after} - {OPENRAL_META} if before.get(key) != after.get(key))
    mine, theirs = before.get(OPENRAL_META), after.get(OPENRAL_META)
    if isinstance(mine, dict) and isinstance(theirs, dict):
        fields = {*mine, *theirs} - {"warmup_ms"}
        changed += sorted(f"{OPENRAL_META}.{key}" for key in fields if mine.get(key) != theirs.get(key))
    elif mine != theirs:
        changed.append(OPENRAL_META)
    return changed


def _horizon(metadata: Mapping[str, Any] | None) -> int | None:
    value = None if metadata is None else metadata.get("action_horizon")
    return value if isinstance(value, int) and not isinstance(value, bool) and value > 0 else None


def _check_meta(skill: OpenpiPolicySkill, metadata: Mapping[str, Any] | None) -> None:
    """The server's metadata against the robot and the parameters (what it says; openpi's may say nothing)."""
    if metadata is None:
        return
    horizon = _horizon(metadata)
    if horizon is not None and skill.rows > horizon:
        raise ROSConfigError(
            f"rows {skill.rows} exceeds the server's action_horizon {horizon}", field="vla.params.rows"
        )
    dims = metadata.get("action_dim")
    width = len(skill.robot.joint_names)
    slice_ = skill.params.action_slice
    needed = slice_[1] if slice_ is not None else width
    if isinstance(dims, int) and (dims < needed or (slice_ is None and dims != width)):
        raise ROSConfigError(
            f"the server's actions are {dims} wide, robot {skill.robot.robot_id} takes {width}",
            field="vla.params.action_slice",
            hint="give action_slice: [start, stop) of the columns this robot takes",
        )
    served = _served_meta(metadata, field="vla.params.host")
    if served is not None and not math.isclose(served.dt_s * skill.rate_hz, 1.0, rel_tol=1e-6):
        raise ROSConfigError(
            f"{served.policy} steps every {served.dt_s:g} s but the loop ticks at {skill.rate_hz:g} Hz",
            field="vla.params.host",
        )


def _ssl_context(tls: TlsConfig) -> ssl.SSLContext:
    context = ssl.create_default_context(cafile=str(require_user_file(tls.ca, field="vla.params.tls.ca", what="CA")))
    context.check_hostname = tls.verify_name
    if tls.cert is not None and tls.key is not None:
        context.load_cert_chain(
            str(require_user_file(tls.cert, field="vla.params.tls.cert", what="certificate")),
            str(require_user_file(tls.key, field="vla.params.tls.key", what="key")),
        )
    return context


def _brief(value: Any) -> str:
    text = str(value).replace("\n", " ")
    return text if len(text) <= 120 else f"{text[:117]}..."
