"""``openral benchmark run --html``: one self-contained page that shows what the JSON report says."""

from __future__ import annotations

import importlib
import json
import re
import sys
from html.parser import HTMLParser
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

import openral_sim
from openral_cli.main import cli
from openral_core import ROSDependencyMissing

ROOT = Path(__file__).resolve().parents[2]
MOCK_SCENE = ROOT / "scenes" / "sim" / "mock_reach.yaml"
HOSTILE = "<script>alert(1)</script>"
PLOT_KINDS = ["success", "steps-to-success", "tick-latency", "inference-latency"]


class Page(HTMLParser):
    """What a browser would see: elements, the text in each figure, the tables' cells, every URL-bearing value."""

    def __init__(self, text: str) -> None:
        super().__init__(convert_charrefs=True)
        self.tags: list[str] = []
        self.references: list[str] = []
        self.figures: dict[str, list[str]] = {}
        self.results: list[dict[str, str]] = []
        self.provenance: dict[str, str] = {}
        self.rows: list[list[str]] = []
        self.smoothness: list[dict[str, str]] = []
        self._figure: str | None = None
        self._table: str | None = None
        self._cell: tuple[str, str] | None = None
        self._text: list[str] = []
        self.feed(text)
        self.close()

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.append(tag)
        values = dict(attrs)
        self.references += [v or "" for k, v in attrs if k in {"src", "href", "xlink:href", "action", "data"}]
        if tag == "figure":
            self._figure = values["data-kind"]
            self.figures[self._figure] = []
        elif tag == "table" and self._figure is None:
            self._table = values.get("class") or "results"
        elif tag == "tbody" and self._table == "results":
            self.results = []
        elif tag == "tbody" and self._table == "rows":
            self.rows = []
        elif tag == "tr" and self._table == "results":
            self.results.append({})
        elif tag == "tr" and self._table == "rows":
            self.rows.append([])
        elif tag == "tbody" and self._table == "smoothness":
            self.smoothness = []
        elif tag == "tr" and self._table == "smoothness":
            self.smoothness.append({})
        elif tag in {"td", "th"} and self._table is not None:
            self._cell = (tag, (values.get("class") or "").split(" ")[0])
            self._text = []

    def handle_endtag(self, tag: str) -> None:
        if tag == "figure":
            self._figure = None
        elif tag == "table":
            self._table = None
        elif tag in {"td", "th"} and self._cell is not None:
            text = "".join(self._text).strip()
            kind, name = self._cell
            if self._table == "results" and kind == "td":
                self.results[-1][name] = text
            elif self._table == "rows" and kind == "td":
                self.rows[-1].append(text)
            elif self._table == "smoothness" and kind == "td":
                self.smoothness[-1][name] = text
            elif self._table == "provenance":
                if kind == "th":
                    self._key = text
                else:
                    self.provenance[self._key] = text
            self._cell = None

    def handle_data(self, data: str) -> None:
        if self._figure is not None and data.strip():
            self.figures[self._figure].append(data.strip())
        if self._cell is not None:
            self._text.append(data)


def _suite(tmp_path: Path) -> Path:
    suite = tmp_path / "suite.yaml"
    suite.write_text(
        f"name: 'tiny <b>suite</b>'\n"
        f"runs:\n"
        f"  - {{scene: {MOCK_SCENE}, skill: mock_reach_expert, n_episodes: 3, min_success: 50}}\n"
        f"  - {{scene: {MOCK_SCENE}, skill: zero, n_episodes: 2, seed: 7, label: '{HOSTILE}'}}\n",
        encoding="utf-8",
    )
    return suite


def _leaves(value: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(value, dict) and value:
        return {k: v for key, inner in value.items() for k, v in _leaves(inner, f"{prefix}{key}.").items()}
    return {prefix.rstrip("."): value}


def test_the_page_plots_every_row_prints_the_json_numbers_and_its_provenance(tmp_path: Path) -> None:
    out, page_path = tmp_path / "bench.json", tmp_path / "report.html"
    result = CliRunner().invoke(
        cli, ["benchmark", "run", "--config", str(_suite(tmp_path)), "--out", str(out), "--html", str(page_path)]
    )
    assert result.exit_code == 0, result.output
    document = json.loads(out.read_text())
    text = page_path.read_text(encoding="utf-8")
    page = Page(text)
    rows = document["results"]
    labels = [row["label"] for row in rows]
    assert labels == ["mock_reach/mock_reach_expert", HOSTILE]

    # One figure per kind, each naming every row; the chart prints each rate with its interval.
    assert [tag for tag in page.tags if tag == "figure"] == ["figure"] * len(PLOT_KINDS)
    assert list(page.figures) == PLOT_KINDS
    for kind, texts in page.figures.items():
        for label in labels:
            assert label in texts, (kind, label)
    for row in rows:
        low, high = row["pc_success_ci95"]
        assert f"{row['pc_success']:.1f} % [{low:.1f}, {high:.1f}]" in page.figures["success"]
    assert "3 of 3 episodes succeeded" in page.figures["steps-to-success"]
    assert "0 of 2 episodes succeeded" in page.figures["steps-to-success"]

    # The results table prints what the JSON says.
    assert [cells["label"] for cells in page.results] == labels
    for cells, row in zip(page.results, rows, strict=True):
        low, high = row["pc_success_ci95"]
        assert cells["pc-success"] == f"{row['pc_success']:.1f} %"
        assert cells["ci95"] == f"{low:.1f} – {high:.1f} %"
        assert cells["successes"] == str(row["n_success"])
        assert cells["seeds"] == f"{row['seeds'][0]}–{row['seeds'][1]}"
    assert page.results[0]["pc-success"] == "100.0 %"
    # Time to success in simulated seconds, and each row's smoothness, as the JSON says.
    seconds = rows[0]["time_to_success"]
    low_s, high_s = seconds["p50_s_ci95"]
    assert page.results[0]["time-p50-s"] == f"{seconds['p50_s']:.2f} ({low_s:.2f} – {high_s:.2f})"
    assert page.results[1]["time-p50-s"] == "— (— – —)"  # the zero policy never succeeds
    for cells, row in zip(page.smoothness, rows, strict=True):
        jerk = row["smoothness"]["jerk_rms"]
        assert cells["label"] == row["label"]
        assert cells["jerk_rms"] == f"{jerk['mean']:.3g} / {jerk['p95']:.3g}"
        assert cells["ee_path_length_m"] == "— / —"  # the mock env reports no end effector
    assert [cells["efficiency"] for cells in page.results] == ["—", "—"]  # no one-worker baseline to measure against

    # Against a one-worker baseline: the efficiency with its speed-up and the workers it was reached on.
    from openral_sim import html_report  # noqa: PLC0415 - as the command imports it

    measured = json.loads(out.read_text())
    measured["provenance"]["workers"] = 2
    measured["results"][0].update(speedup=1.8, efficiency=0.9)
    again = Page(html_report.render(measured))
    assert [cells["efficiency"] for cells in again.results] == ["0.90 (1.80× on 2 workers)", "—"]
    assert "1.00 is perfect scaling" in html_report.render(measured)

    # Every provenance value, and what each row ran with its seeds.
    provenance = _leaves(document["provenance"])
    assert set(page.provenance) == set(provenance)
    for key, value in provenance.items():
        expected = "—" if value is None else value if isinstance(value, str) else json.dumps(value)
        assert page.provenance[key] == expected, key
    assert page.provenance["config_sha256"] == document["provenance"]["config_sha256"]
    assert page.provenance["packages.numpy"] == document["provenance"]["packages"]["numpy"]
    assert [cells[0] for cells in page.rows] == labels
    assert [cells[-2:] for cells in page.rows] == [["[0, 2]", "virtual"], ["[7, 8]", "virtual"]]

    # Self-contained: nothing is fetched, nothing runs, and user strings come out as text.
    assert not {"script", "link", "img", "iframe", "object", "embed"} & set(page.tags)
    assert all(ref.startswith("#") for ref in page.references), page.references
    assert re.findall(r"url\((?!#)|@import|https?:", text) == []
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in text
    assert "<title>Benchmark report: tiny &lt;b&gt;suite&lt;/b&gt;</title>" in text


def test_the_report_keeps_a_latency_histogram_of_every_step(tmp_path: Path) -> None:
    out = tmp_path / "bench.json"
    result = CliRunner().invoke(cli, ["benchmark", "run", "--config", str(_suite(tmp_path)), "--out", str(out)])
    assert result.exit_code == 0, result.output
    for row in json.loads(out.read_text())["results"]:
        steps = sum(episode["steps"] for episode in row["episodes"])
        for key in ("tick_ms", "inference_ms"):
            histogram = row[key]["histogram"]
            assert sum(histogram["counts"]) == steps
            assert len(histogram["edges_ms"]) == len(histogram["counts"]) + 1
            assert histogram["edges_ms"] == sorted(histogram["edges_ms"])
            assert histogram["edges_ms"][0] <= row[key]["p50"] <= row[key]["max"] <= histogram["edges_ms"][-1]


@pytest.mark.parametrize(
    ("where", "message"),
    [
        (lambda tmp: tmp, "is a folder"),
        (lambda tmp: tmp / "missing" / "report.html", "does not exist"),
        (lambda tmp: tmp / "file.txt" / "report.html", "is not a folder"),
    ],
    ids=["a folder", "a missing folder", "a file as folder"],
)
def test_a_path_the_page_cannot_be_written_to_fails_at_once_with_exit_2(
    tmp_path: Path, where: Any, message: str
) -> None:
    (tmp_path / "file.txt").write_text("not a folder", encoding="utf-8")
    out = tmp_path / "bench.json"
    html = where(tmp_path)
    result = CliRunner().invoke(
        cli, ["benchmark", "run", "--config", str(_suite(tmp_path)), "--out", str(out), "--html", str(html)]
    )
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1, result.output  # no row ran: no progress line before the error
    assert lines[0].startswith("error: --html: ")
    assert message in lines[0]
    assert not out.exists()


def test_without_matplotlib_the_option_fails_before_the_run_naming_the_report_extra(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib now raises ImportError
    for name in ("html_report", "html_figures"):  # as in a process that never imported them
        monkeypatch.delitem(sys.modules, f"openral_sim.{name}", raising=False)
        monkeypatch.delattr(openral_sim, name, raising=False)
    with pytest.raises(ROSDependencyMissing) as missing:
        importlib.import_module("openral_sim.html_report")
    assert missing.value.extra == "report"
    assert missing.value.module == "matplotlib"

    out = tmp_path / "bench.json"
    result = CliRunner().invoke(
        cli,
        ["benchmark", "run", "--config", str(_suite(tmp_path)), "--out", str(out), "--html", str(tmp_path / "r.html")],
    )
    assert result.exit_code == 2, result.output
    assert "needs the Python module 'matplotlib'" in result.output
    assert "uv sync --extra report" in result.output
    assert not out.exists()


def test_a_suite_whose_rows_all_failed_gets_a_page_of_its_errors_and_no_empty_plots() -> None:
    from openral_sim.html_report import render  # noqa: PLC0415

    document = {
        "suite": "broken",
        "results": [
            {
                "label": "so101/pick",
                "status": "failed",
                "seeds": [0, 2],
                "error": 'ROSRuntimeError: <img src="x" onerror="alert(1)">',
                "episodes": [],
            }
        ],
        "provenance": {"workers": 1, "ray": None},
        "not_run": ["later <row>"],
    }
    page = Page(render(document))
    assert page.figures == {}
    assert "img" not in page.tags
    (cells,) = page.results
    assert cells["status"] == "failed"
    assert cells["pc-success"] == "—"
    assert cells["note"] == 'ROSRuntimeError: <img src="x" onerror="alert(1)">'
    assert page.provenance == {"workers": "1", "ray": "—"}
