"""Report files: a path that is not a regular file is refused, and a report replaces only a regular file."""

from __future__ import annotations

import os
import stat
from collections.abc import Callable
from pathlib import Path

import pytest

from openral_core import ROSConfigError, ROSRuntimeError
from openral_sim import report_files


def test_a_new_path_or_a_regular_file_may_be_written(tmp_path: Path) -> None:
    report_files.check_output_file(tmp_path / "new.json", option="--out")
    existing = tmp_path / "old.json"
    existing.write_text("{}", encoding="utf-8")
    report_files.check_output_file(existing, option="--out")


def _link(path: Path) -> None:
    target = path.with_name("target.json")
    target.write_text("kept", encoding="utf-8")
    path.symlink_to(target)


@pytest.mark.parametrize(
    ("make", "kind"),
    [(os.mkfifo, "a FIFO (named pipe)"), (_link, "a symbolic link")],
    ids=["FIFO", "link"],
)
def test_a_path_that_is_no_regular_file_is_refused_naming_the_option(
    tmp_path: Path, make: Callable[[Path], None], kind: str
) -> None:
    path = tmp_path / "report.json"
    make(path)
    with pytest.raises(ROSConfigError) as info:
        report_files.check_output_file(path, option="--out")
    assert info.value.field == "--out"
    assert f"{path} is {kind}, not a regular file" in str(info.value)


def test_a_link_made_after_the_check_is_neither_followed_nor_replaced(tmp_path: Path) -> None:
    path = tmp_path / "report.json"
    report_files.check_output_file(path, option="--out")
    _link(path)  # between the check and the write, aimed at another file
    with pytest.raises(ROSRuntimeError, match="is now a symbolic link"):
        report_files.write_whole(path, "{}", what="the JSON report")
    assert path.is_symlink()
    assert (tmp_path / "target.json").read_text(encoding="utf-8") == "kept"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.json", "target.json"]


def test_a_path_that_became_a_fifo_after_the_check_is_not_replaced(tmp_path: Path) -> None:
    path = tmp_path / "report.html"
    report_files.check_output_file(path, option="--html")
    os.mkfifo(path)  # between the check and the write
    with pytest.raises(ROSRuntimeError, match=r"cannot write the HTML report to .*is now a FIFO"):
        report_files.write_whole(path, "<html></html>", what="the HTML report")
    assert stat.S_ISFIFO(os.stat(path).st_mode)  # still the FIFO
    assert [p.name for p in tmp_path.iterdir()] == ["report.html"]  # no partial file left
