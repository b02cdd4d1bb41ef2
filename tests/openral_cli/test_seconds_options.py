"""Every seconds-valued option of every command takes one checked type: finite, in range, or exit 2 naming it."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from openral_cli.main import cli
from openral_cli.options import Seconds
from openral_dataset.highlight import MAX_HIGHLIGHT_S

SECONDS_OPTIONS = [
    ("deploy", "--duration"),
    ("deploy", "--episode-every-s"),
    ("deploy", "--highlight-s"),
    ("record", "--episode-time-s"),
    ("record", "--reset-time-s"),
    ("calibrate", "--record-s"),
]
MODEL_CHECKED = {("serve", "--client-idle-s")}
"""Options generated from a model that checks their values itself (``ServeLimits``: finite, in range)."""


def _options(group: click.Group, path: tuple[str, ...] = ()) -> Iterator[tuple[str, click.Option]]:
    for name, command in group.commands.items():
        if isinstance(command, click.Group):
            yield from _options(command, (*path, name))
            continue
        for param in command.params:
            if isinstance(param, click.Option):
                yield " ".join((*path, name)), param


def _says_seconds(option: click.Option) -> bool:
    return any(name.endswith("-s") or name in ("--duration", "--timeout") for name in option.opts)


def test_every_option_named_in_seconds_takes_the_checked_type() -> None:
    named = {(command, option.opts[0]): option for command, option in _options(cli) if _says_seconds(option)}
    assert set(SECONDS_OPTIONS) <= set(named)
    unchecked = sorted(
        key for key, option in named.items() if not isinstance(option.type, Seconds) and key not in MODEL_CHECKED
    )
    assert unchecked == []


def _invoke(command: str, option: str, value: str, tmp_path: Path) -> click.testing.Result:
    """``command`` with ``option value`` and a missing deployment file: only the option's own check can name it."""
    if command == "calibrate":
        args = ["calibrate", "--port", "/dev/null", "--output", str(tmp_path / "calibration.json")]
    else:
        args = [command, "--config", str(tmp_path / "missing.yaml"), "--dataset-out", str(tmp_path / "ds")]
    return CliRunner().invoke(cli, [*args, option, value])


@pytest.mark.parametrize(("command", "option"), SECONDS_OPTIONS)
@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "-1", "abc"])
def test_a_value_that_is_no_finite_number_of_seconds_exits_2_naming_the_option(
    tmp_path: Path, command: str, option: str, value: str
) -> None:
    result = _invoke(command, option, value, tmp_path)
    assert result.exit_code == 2
    assert f"Invalid value for '{option}'" in result.output


def test_a_highlight_longer_than_the_ring_holds_exits_2_saying_the_most() -> None:
    result = CliRunner().invoke(cli, ["deploy", "--config", "missing.yaml", "--highlight-s", "1e9"])
    assert result.exit_code == 2
    assert "'--highlight-s': '1e9' must be at most 600 s" in result.output
    assert MAX_HIGHLIGHT_S == 600


def test_the_pause_between_episodes_may_be_zero_an_episode_may_not() -> None:
    assert Seconds(zero_ok=True).convert("0", None, None) == 0
    assert Seconds(zero_ok=True).convert("2.5", None, None) == 2.5
    with pytest.raises(click.BadParameter, match="positive"):
        Seconds().convert("0", None, None)
    with pytest.raises(click.BadParameter, match="at least 1 s"):
        Seconds(1.0).convert("0.5", None, None)
    assert Seconds(maximum=MAX_HIGHLIGHT_S).convert(str(MAX_HIGHLIGHT_S), None, None) == MAX_HIGHLIGHT_S
