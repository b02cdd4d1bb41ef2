"""``openral serve``'s batching and admission options: a value out of range is one line naming the option once."""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from openral_cli import main


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (["--max-wait-ms", "nan"], "error: --max-wait-ms: Input should be a finite number"),
        (["--max-wait-ms", "inf"], "error: --max-wait-ms: Input should be a finite number"),
        (["--max-wait-ms", "2000"], "error: --max-wait-ms: Input should be less than or equal to 1000"),
        (["--max-batch", "0"], "error: --max-batch: Input should be greater than or equal to 1"),
    ],
)
def test_a_limit_out_of_range_is_one_line_naming_its_option_once(args: list[str], line: str) -> None:
    # An unknown skill would be the error if anything after the limits' check ran.
    out = CliRunner().invoke(main.cli, ["serve", "--skill", "no_such_skill", *args])
    assert out.exit_code == 2, out.output
    assert out.stderr.splitlines() == [line]
