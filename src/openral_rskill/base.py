"""The skill lifecycle: a managed-node state machine around one ``step(world_state) -> Action``.

A skill moves through the ROS 2 managed-node states (:class:`~openral_core.skills.RSkillState`)::

    UNCONFIGURED --configure--> INACTIVE --activate--> ACTIVE
                                INACTIVE <--deactivate-- ACTIVE
    any --shutdown--> FINALIZED            ACTIVE/INACTIVE --reset--> (same state, new episode)
    a failing hook or step --> ERROR --recover--> INACTIVE (UNCONFIGURED if configure itself failed)

Subclasses implement the ``_on_*`` hooks (all optional) and :meth:`RSkillBase._step_impl`; the base
owns the state, the error latch and the per-step latency figures, so every skill behaves the same
under the runner. A skill whose model answers in chunks derives from :class:`ChunkingSkillBase`
instead and implements ``_chunk_impl`` alone: its step is the chunk's row 0.

Error latch: an exception escaping a hook or ``_step_impl`` moves the skill to ``ERROR`` and is
re-raised as :class:`~openral_core.errors.ROSSkillError` (``from`` the original) naming the skill and
the phase. While latched, ``step`` fails immediately without calling the skill. :meth:`RSkillBase.recover`
is the only way out (besides ``shutdown``); ``reset`` does not clear the latch, so a new episode never
silently starts on a skill that failed. ``ROSEStopRequested`` and ``ROSStopRequested`` raised by
``_step_impl`` are requests, not failures: they pass through unchanged and do not latch.

Plugin construction convention: every class registered in the ``openral.skills`` entry-point group
provides a classmethod (see :class:`RSkillPlugin`)::

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> Self

that validates ``params`` with the skill's own pydantic model (``extra="forbid"``) through
:func:`validate_params`, so a wrong key names the field and lists the allowed keys. ``rate_hz`` is the
tick rate the runner will call ``step`` at; skills that generate trajectories use it instead of wall time.
The factory returns an ``UNCONFIGURED`` skill; the caller drives the lifecycle.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from time import perf_counter_ns
from typing import Any, Protocol, TypeVar, runtime_checkable

import numpy as np
from opentelemetry import trace
from pydantic import BaseModel

from openral_core.actions import Action
from openral_core.config import validate_model
from openral_core.errors import ROSEStopRequested, ROSSkillError, ROSStopRequested, ROSUnavailable
from openral_core.robot import RobotManifest
from openral_core.skills import RSkillInfo, RSkillState
from openral_core.world import WorldState
from openral_observability import semconv
from openral_rskill.anchoring import AbsoluteAnchor, Anchor
from openral_rskill.chunks import ChunkRequest

ParamsT = TypeVar("ParamsT", bound=BaseModel)
_In = TypeVar("_In")
_Out = TypeVar("_Out")

_S = RSkillState


class RSkillPlugin(Protocol):
    """What the runner factory needs from a class in the ``openral.skills`` group."""

    def from_config(self, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> RSkillBase:
        """Build an ``UNCONFIGURED`` skill for ``robot`` stepped at ``rate_hz`` from its ``vla.params``."""
        ...


@runtime_checkable
class OfflineConfigCheck(Protocol):
    """A skill class whose building needs a peer (a policy server) and that can check its parameters without one.

    ``openral validate`` calls :meth:`check_config` instead of ``from_config`` for such a class, so
    validating a file never waits for, or connects to, anything. Every other skill is checked by
    building it, which by the plugin convention loads files but opens no link.
    """

    def check_config(self, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> None:
        """Raise ``ROSConfigError`` naming the field for whatever is wrong in ``params``, offline."""
        ...


@runtime_checkable
class OfflineObservation(Protocol):
    """An :class:`OfflineConfigCheck` skill class that knows from its parameters alone what it reads.

    ``openral validate`` checks the cameras among those fields against the deployment's sensors, as
    it does for a skill it builds.
    """

    def offline_observation(self, params: Mapping[str, Any]) -> list[str]:
        """The world-state fields it reads (as ``RSkillInfo.observation``) with ``params``; empty: not known offline."""
        ...


@runtime_checkable
class RobotInputCheck(Protocol):
    """A skill that runs on a simulator's world state as well as a robot's, and can check the second before it runs.

    A simulator gives more than a robot measures (a state vector of its own, object poses), so
    such a skill cannot refuse these inputs when it is built. The runner factory calls
    :meth:`check_robot_inputs` on a skill built for a robot, so ``openral validate`` refuses
    them rather than the first tick.
    """

    def check_robot_inputs(self) -> None:
        """Raise ``ROSConfigError`` naming an input a robot's world state cannot give."""
        ...


def validate_params(model: type[ParamsT], params: Mapping[str, Any], *, skill_id: str) -> ParamsT:
    """Validate a skill's ``vla.params`` as ``model``.

    Raises:
        ROSConfigError: Naming the bad field (and, for an unknown key, the allowed keys).
    """
    return validate_model(model, dict(params), source=f"skill '{skill_id}'", field_prefix="vla.params")


class RSkillBase(ABC):
    """Base of every skill: lifecycle state machine, error latch and step latency bookkeeping.

    ``step`` is on the tick hot path (up to 1 kHz), so the wrapper does an identity check on the
    state, two clock reads and a few integer updates: no validation, no logging, no allocation
    beyond what ``_step_impl`` does.
    """

    def __init__(self) -> None:
        self._state: RSkillState = _S.UNCONFIGURED
        self._configured = False  # _on_configure succeeded and _on_shutdown has not run
        self._activated = False  # _on_activate succeeded and _on_deactivate has not run
        self._last_error: BaseException | None = None
        self._error_phase: str | None = None
        self._step_count = 0
        self._last_step_ns = 0
        self._total_step_ns = 0
        self._max_step_ns = 0
        self.episode_seed: int | None = None
        """The seed of the episode under way, when the runner gives one (see :meth:`reset`)."""

    # -- identity ---------------------------------------------------------------------------

    @property
    @abstractmethod
    def info(self) -> RSkillInfo:
        """What this skill is (id, licence, control mode, chunk size)."""

    # -- hooks for subclasses ---------------------------------------------------------------

    def _on_configure(self) -> None:  # noqa: B027 (optional hook)
        """Load weights, allocate buffers. On failure, release what was acquired before raising."""

    def _on_activate(self) -> None:  # noqa: B027 (optional hook)
        """Prepare to step (warm-up, start of the first episode). Clean up after itself on failure."""

    def _on_deactivate(self) -> None:  # noqa: B027 (optional hook)
        """Stop stepping; keep what ``configure`` loaded."""

    def _on_shutdown(self) -> None:  # noqa: B027 (optional hook)
        """Release everything ``configure`` acquired."""

    def action_anchor(self) -> Anchor:
        """How a chunking skill's rows become targets (see :mod:`openral_rskill.anchoring`); absolute by default."""
        return AbsoluteAnchor()

    def available(self) -> bool:
        """Whether the skill can be asked now (a remote policy whose server is down cannot); asked every tick."""
        return True

    def _on_reset(self) -> None:  # noqa: B027 (optional hook)
        """Start a new episode: clear per-episode state (latched poses, chunk queues, step counters)."""

    def serves_many_episodes(self) -> bool:
        """Whether one instance can serve several episodes at once: its chunk depends on the request alone.

        True for a policy whose chunk is a function of the request's observation, history and
        prefix (no plan, queue or generator carried between calls). A policy server then shares
        one loaded model between its robots; otherwise each robot gets an instance of its own.
        """
        return False

    def batch_capacity(self) -> int:
        """How many requests one inference can take (:meth:`step_chunks`); 1: one at a time."""
        return 1

    def _chunks_impl(self, requests: Sequence[ChunkRequest]) -> list[np.ndarray]:
        """The chunks of several requests; by default one :meth:`_chunk_impl` each. Batching skills override it."""
        return [self._chunk_impl(request) for request in requests]

    @abstractmethod
    def _step_impl(self, world_state: WorldState) -> Action:
        """Compute the action for this tick from ``world_state``."""

    def _chunk_impl(self, request: ChunkRequest) -> np.ndarray:
        """The ``(rows, dims)`` chunk for ``request``; here the targets of :meth:`_step_impl`.

        A skill whose model answers in chunks (and uses the request's history or prefix) derives
        from :class:`ChunkingSkillBase`, where this is the hook and the step is derived from it.
        """
        return np.asarray(self._step_impl(request.world).targets, dtype=np.float64)

    # -- state --------------------------------------------------------------------------------

    @property
    def state(self) -> RSkillState:
        """Current lifecycle state."""
        return self._state

    @property
    def last_error(self) -> BaseException | None:
        """The exception that set the error latch (``None`` when not latched)."""
        return self._last_error

    # -- transitions ----------------------------------------------------------------------------

    def configure(self) -> None:
        """``UNCONFIGURED -> INACTIVE``: run ``_on_configure``.

        Raises:
            ROSSkillError: Wrong state, or the hook failed (the skill is then in ``ERROR``).
        """
        self._require("configure", (_S.UNCONFIGURED,))
        self._run_hook("configure", self._on_configure)
        self._configured = True
        self._state = _S.INACTIVE

    def activate(self) -> None:
        """``INACTIVE -> ACTIVE``: run ``_on_activate``.

        Raises:
            ROSSkillError: Wrong state, or the hook failed (the skill is then in ``ERROR``).
        """
        self._require("activate", (_S.INACTIVE,))
        self._run_hook("activate", self._on_activate)
        self._activated = True
        self._state = _S.ACTIVE

    def deactivate(self) -> None:
        """``ACTIVE -> INACTIVE``: run ``_on_deactivate``.

        Raises:
            ROSSkillError: Wrong state, or the hook failed (the skill is then in ``ERROR``).
        """
        self._require("deactivate", (_S.ACTIVE,))
        self._activated = False  # attempted once; a failing deactivate is not retried by recover()
        self._run_hook("deactivate", self._on_deactivate)
        self._state = _S.INACTIVE

    def reset(self, *, seed: int | None = None) -> None:
        """Start a new episode in the current state (``ACTIVE`` or ``INACTIVE``): run ``_on_reset``.

        Does not clear the error latch; use :meth:`recover` for that.

        Args:
            seed: The episode's seed (a simulation's), kept in :attr:`episode_seed` for
                ``_on_reset``: a skill that draws random numbers seeds its generator from it, so
                an episode's outcome depends on its seed alone.

        Raises:
            ROSSkillError: Wrong state, or the hook failed (the skill is then in ``ERROR``).
        """
        self._require("reset", (_S.ACTIVE, _S.INACTIVE))
        self.episode_seed = seed
        self._run_hook("reset", self._on_reset)

    def recover(self) -> None:
        """``ERROR -> INACTIVE``: clear the error latch.

        If the error struck while the skill was active, ``_on_deactivate`` runs first so the skill
        rests in ``INACTIVE`` with its configuration kept; ``activate`` then starts a fresh episode.
        If ``configure`` itself failed, the skill returns to ``UNCONFIGURED`` instead.

        Raises:
            ROSSkillError: Not in ``ERROR``, or ``_on_deactivate`` failed (the latch stays set).
        """
        self._require("recover", (_S.ERROR,))
        if self._activated:
            self._activated = False
            self._run_hook("recover", self._on_deactivate)
        self._last_error = None
        self._error_phase = None
        self._state = _S.INACTIVE if self._configured else _S.UNCONFIGURED

    def shutdown(self) -> None:
        """Any state ``-> FINALIZED``, releasing what is held; idempotent.

        Runs ``_on_deactivate`` if the skill is active and ``_on_shutdown`` if it is configured.
        The skill ends ``FINALIZED`` even when a hook fails, so that cleanup code (an ``ExitStack``,
        a ``finally``) never leaves a half-released skill to retry; the failure is still raised.

        Raises:
            ROSSkillError: A hook failed (after the skill reached ``FINALIZED``).
        """
        if self._state is _S.FINALIZED:
            return
        failures: list[tuple[str, Exception]] = []
        for active, phase, hook in (
            (self._activated, "deactivate", self._on_deactivate),
            (self._configured, "shutdown", self._on_shutdown),
        ):
            if not active:
                continue
            try:
                hook()
            except Exception as exc:
                failures.append((phase, exc))
        self._activated = False
        self._configured = False
        self._state = _S.FINALIZED
        if failures:
            failed_phase, cause = failures[0]
            message = f"skill '{self._skill_id()}' failed in {failed_phase} during shutdown: {_describe(cause)}"
            raise ROSSkillError(message) from cause

    # -- stepping ----------------------------------------------------------------------------

    def step(self, world_state: WorldState) -> Action:
        """Compute this tick's action. Only allowed in ``ACTIVE``.

        Raises:
            ROSSkillError: Not ``ACTIVE`` (including a set error latch), or ``_step_impl`` raised
                (the skill is then in ``ERROR``; the original exception is the ``__cause__``).
            ROSEStopRequested: The skill requested an emergency stop; passed through unchanged and
                without latching, so the runner stops and calls ``HAL.estop()``.
            ROSStopRequested: The skill ended the run cooperatively; passed through, no latch.
            ROSUnavailable: Something the skill needs cannot answer now; passed through, no latch.
        """
        return self._stepped(self._step_impl, world_state)

    def step_chunk(self, request: ChunkRequest) -> np.ndarray:
        """A chunking skill's chunk for ``request`` as one ``(rows, dims)`` array: what the chunk executor calls.

        The same lifecycle, error latch and latency figures as :meth:`step`.

        Raises:
            ROSSkillError: As :meth:`step`.
        """
        return self._stepped(self._chunk_impl, request)

    def step_chunks(self, requests: Sequence[ChunkRequest]) -> list[np.ndarray]:
        """The chunks of several requests in one inference (at most :meth:`batch_capacity`), in their order.

        A policy server batches concurrent robots' requests through it. The same lifecycle and
        error latch as :meth:`step`; the latency figures count the batch as one step.

        Raises:
            ROSSkillError: As :meth:`step`.
        """
        return self._stepped(self._chunks_impl, requests)

    def _stepped(self, compute: Callable[[_In], _Out], argument: _In) -> _Out:
        if self._state is not _S.ACTIVE:
            raise self._transition_error("step", (_S.ACTIVE,))
        start = perf_counter_ns()
        try:
            output = compute(argument)
        except (ROSEStopRequested, ROSStopRequested, ROSUnavailable):
            raise  # control flow for the runner, or a dependency that may come back: no latch
        except Exception as exc:
            raise self._latch("step", exc) from exc
        elapsed = perf_counter_ns() - start
        self._last_step_ns = elapsed
        self._total_step_ns += elapsed
        self._step_count += 1
        self._max_step_ns = max(self._max_step_ns, elapsed)
        return output

    # -- latency ----------------------------------------------------------------------------

    @property
    def step_count(self) -> int:
        """Successful steps since construction (or :meth:`reset_step_stats`)."""
        return self._step_count

    @property
    def last_step_ms(self) -> float:
        """Duration of the last successful ``_step_impl`` call, ms (0 before the first)."""
        return self._last_step_ns / 1e6

    @property
    def mean_step_ms(self) -> float:
        """Mean ``_step_impl`` duration over :attr:`step_count` steps, ms (0 before the first)."""
        return self._total_step_ns / self._step_count / 1e6 if self._step_count else 0.0

    @property
    def max_step_ms(self) -> float:
        """Longest ``_step_impl`` duration, ms (0 before the first)."""
        return self._max_step_ns / 1e6

    def reset_step_stats(self) -> None:
        """Zero the step count and latency figures (for example after a warm-up)."""
        self._step_count = 0
        self._last_step_ns = 0
        self._total_step_ns = 0
        self._max_step_ns = 0

    # -- internals ----------------------------------------------------------------------------

    def _skill_id(self) -> str:
        try:
            return self.info.skill_id
        except Exception:
            return type(self).__name__

    def _require(self, transition: str, allowed: tuple[RSkillState, ...]) -> None:
        if self._state not in allowed:
            raise self._transition_error(transition, allowed)

    def _transition_error(self, transition: str, allowed: tuple[RSkillState, ...]) -> ROSSkillError:
        skill_id = self._skill_id()
        if self._state is _S.ERROR:
            return ROSSkillError(
                f"skill '{skill_id}' cannot {transition}: its error latch is set "
                f"(failed in {self._error_phase}: {_describe(self._last_error)}); call recover() or shutdown()"
            )
        states = " or ".join(s.value.upper() for s in allowed)
        return ROSSkillError(
            f"skill '{skill_id}' cannot {transition} in state {self._state.value.upper()}; {transition} needs {states}"
        )

    def _run_hook(self, phase: str, hook: Callable[[], None]) -> None:
        try:
            hook()
        except Exception as exc:
            raise self._latch(phase, exc) from exc

    def _latch(self, phase: str, exc: Exception) -> ROSSkillError:
        self._state = _S.ERROR
        self._last_error = exc
        self._error_phase = phase
        skill_id = self._skill_id()
        trace.get_current_span().add_event(
            semconv.EVENT_ERROR_LATCHED,
            {semconv.ATTR_SKILL_ID: skill_id, "exception.type": type(exc).__name__},
        )
        return ROSSkillError(f"skill '{skill_id}' failed in {phase}: {_describe(exc)}")


class ChunkingSkillBase(RSkillBase):
    """Base of a skill whose model answers in chunks: it writes :meth:`_chunk_impl` and names the chunk's columns.

    The chunk is the one thing such a skill computes. The chunk executor runs its rows; a bare
    :meth:`~RSkillBase.step` (no executor) is row 0 of the chunk for the tick's world state, made
    into an :class:`~openral_core.actions.Action` here, so no chunking skill builds one by hand.
    """

    @property
    @abstractmethod
    def action_names(self) -> list[str]:
        """The joints (or action dimensions) of the chunk's columns, in order."""

    @abstractmethod
    def _chunk_impl(self, request: ChunkRequest) -> np.ndarray:
        """The ``(rows, dims)`` chunk for ``request``: the model's array as it is."""

    def _step_impl(self, world_state: WorldState) -> Action:
        """Row 0 of the chunk for ``world_state``."""
        return self._rows_action(world_state, self._chunk_impl(ChunkRequest(world_state))[:1])

    def _rows_action(self, world_state: WorldState, rows: np.ndarray) -> Action:
        """``rows`` (``(rows, dims)``) as the action of the tick that saw ``world_state``."""
        info = self.info
        return Action(
            control_mode=info.control_mode,
            joint_names=self.action_names,
            targets=rows.tolist(),
            stamp_ns=world_state.stamp_ns,
            skill_id=info.skill_id,
        )


def _describe(exc: BaseException | None) -> str:
    text = str(exc)
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


rSkillBase = RSkillBase  # noqa: N816 (the spec's name)
"""The spec's name for :class:`RSkillBase`."""
