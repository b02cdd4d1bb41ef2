"""What a person can do to a running command beside stopping it: take over, save a highlight.

The terminal's keys and the web console's buttons reach the same callables, so a key and a button
always do the same thing. Each is offered only where the deployment asks for it: the takeover key
where ``takeover.via`` lists ``key``, its button where it lists ``console``; the highlight key and
button where the recording keeps a highlight ring.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from openral_cli.keys import KeyCommand
from openral_core import RobotEnvironment, TakeoverTrigger
from openral_runner.skill_runner import SkillRunnerBase

if TYPE_CHECKING:
    from openral_dataset.recorder import RolloutRecorder

HIGHLIGHT_KEY = "s"


@dataclass
class RunControls:
    """The actions a running command offers, by command, and the keys and buttons that reach them."""

    actions: dict[KeyCommand, Callable[[], None]] = field(default_factory=dict)
    keys: dict[str, KeyCommand] = field(default_factory=dict)
    """Keys beside the recording keys (one character each)."""
    buttons: dict[str, Callable[[], None]] = field(default_factory=dict)
    """The console's buttons beyond stop, by name."""

    def __call__(self, command: KeyCommand) -> None:
        """Do what ``command`` asks if it is one of these actions (another command is ignored)."""
        action = self.actions.get(command)
        if action is not None:
            action()

    def offers(self, command: KeyCommand) -> bool:
        """Whether ``command`` is one of these actions."""
        return command in self.actions


def takeover_keys(env: RobotEnvironment) -> dict[str, KeyCommand]:
    """The takeover key of a deployment whose takeover is reached by key (known before anything starts)."""
    takeover = env.takeover
    if takeover is None or TakeoverTrigger.KEY not in takeover.via:
        return {}
    return {takeover.key: KeyCommand.TAKEOVER}


def run_controls(
    env: RobotEnvironment, runner: SkillRunnerBase, recorder: RolloutRecorder | None = None
) -> RunControls:
    """The takeover and highlight controls of a started runner (none when the deployment has neither)."""
    controls = RunControls()
    takeover = runner.takeover
    if takeover is not None and env.takeover is not None:
        toggle = takeover.request
        controls.actions[KeyCommand.TAKEOVER] = toggle
        controls.keys.update(takeover_keys(env))
        if TakeoverTrigger.CONSOLE in env.takeover.via:
            controls.buttons[KeyCommand.TAKEOVER.value] = toggle
    if recorder is not None and recorder.highlight_s is not None:
        save = recorder.save_highlight

        def save_highlight() -> None:
            save()  # written on the recorder's own thread; the outcome is logged there

        controls.actions[KeyCommand.HIGHLIGHT] = save_highlight
        controls.keys[HIGHLIGHT_KEY] = KeyCommand.HIGHLIGHT
        controls.buttons[KeyCommand.HIGHLIGHT.value] = save_highlight
    return controls
