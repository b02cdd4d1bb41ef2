"""``benchmark run --html``: the benchmark report as one self-contained HTML page, for a person to read.

The page opens offline anywhere: no script, nothing fetched (no stylesheet, font or image URL),
the figures inline as SVG (:mod:`openral_sim.html_figures`, which needs the ``report`` extra).
It is a view of the JSON document ``benchmark run`` writes with ``--out``, never a second source
of numbers: it prints what the JSON says, formatted. Everything that came from a user (suite, row
and scene names, parameters, paths, errors) is escaped here with :func:`html.escape`.
"""

from __future__ import annotations

import html
import json
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from openral_sim import html_comparison, html_figures, report_files
from openral_sim.smoothness import METRICS

Document = Mapping[str, Any]

_CSS = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 75em; padding: 0 1em; color: #222; }
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; margin-top: 2em; border-bottom: 1px solid #ddd; }
table { border-collapse: collapse; font-size: 0.9em; margin: 0.5em 0; }
th, td { border: 1px solid #ddd; padding: 0.25em 0.6em; text-align: left; vertical-align: top; }
td.number { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
.wide { overflow-x: auto; }
tr.failed td { background: #fdecea; }
code { font-size: 0.95em; overflow-wrap: anywhere; }
figure { margin: 1em 0; } figure svg { max-width: 100%; height: auto; }
figcaption { color: #555; font-size: 0.9em; }
"""

_NUMBER = " number"
_PLOTS = (
    ("success", "Success rate", "Each row's success rate with its Wilson 95 % interval; red: its min_success."),
    ("steps-to-success", "Steps to success", "Steps each successful episode took, per row."),
    ("tick-latency", "Tick latency", "Time of every step (one tick), per row, with its p50 and p99."),
    ("inference-latency", "Inference latency", "Time of every step's inference, per row, with its p50 and p99."),
)


def check_writable(path: Path, *, option: str = "--html") -> None:
    """Fail now, before a benchmark runs for minutes, if the page could not be written to ``path``.

    Raises:
        ROSConfigError: As :func:`openral_sim.report_files.check_output_file`.
    """
    report_files.check_output_file(path, option=option, example_name="report.html")


def write(document: Document, path: Path) -> None:
    """Render the page and write it to ``path``: whole or not at all (a new file renamed over it).

    Raises:
        ROSRuntimeError: The page could not be written (the message names the path).
    """
    report_files.write_whole(path, render(document), what="the HTML report")


def render(document: Document) -> str:
    """The report ``document`` (as ``benchmark run --out`` writes it) as one HTML page."""
    results: Sequence[Mapping[str, Any]] = document.get("results") or []
    completed = [row for row in results if row.get("status") == "completed"]
    suite = _e(document.get("suite", "benchmark"))
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en">',
        "<head>",
        '<meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>Benchmark report: {suite}</title>",
        f"<style>{_CSS}</style>",
        "</head>",
        "<body>",
        f"<h1>Benchmark report: {suite}</h1>",
        _overview(document, results, completed),
        '<section id="results">',
        "<h2>Results</h2>",
        f'<div class="wide">{_results_table(results, (document.get("provenance") or {}).get("workers"))}</div>',
        f"<p>{_EFFICIENCY_NOTE}</p>",
        "</section>",
        '<section id="smoothness">',
        "<h2>Smoothness</h2>",
        "<p>Of the commands sent to the robot each step (after the safety envelope, held steps included); "
        "each metric's mean / p95 over the row's episodes. The README defines each metric and its unit.</p>",
        f'<div class="wide">{_smoothness_table(completed)}</div>',
        "</section>",
        *_real_time_section(completed),
        *([html_comparison.comparison_section(document["comparison"])] if document.get("comparison") else []),
        *_figures(completed),
        '<section id="provenance">',
        "<h2>Provenance</h2>",
        _provenance_table(document.get("provenance") or {}),
        "<h3>Rows</h3>",
        f'<div class="wide">{_rows_table(results)}</div>',
        "</section>",
        "</body>",
        "</html>",
    ]
    return "\n".join(parts) + "\n"


def _overview(document: Document, results: Sequence[Mapping[str, Any]], completed: Sequence[Any]) -> str:
    failed = len(results) - len(completed)
    text = f"{len(completed)} of {len(results)} rows completed"
    if failed:
        text += f", {failed} failed"
    if document.get("wall_s") is not None:
        text += f"; {_number(document['wall_s'], '.1f')} s in all"
    if document.get("startup_s") is not None:
        text += f" (start-up {_number(document['startup_s'], '.1f')} s)"
    paragraphs = [f"<p>{text}.</p>"]
    not_run = document.get("not_run")
    if not_run:
        names = ", ".join(f"<code>{_e(name)}</code>" for name in not_run)
        paragraphs.append(f"<p>Not run after the failure: {names}</p>")
    return "\n".join(paragraphs)


_EFFICIENCY_NOTE = (
    "Efficiency: a row's episodes per second divided by the workers and by the episodes per second one worker "
    "reached on the same episodes, measured by the <code>--baseline</code> run (<code>--workers 1</code>); "
    "1.00 is perfect scaling. Without such a baseline it is not known and reads —."
)


def _results_table(results: Sequence[Mapping[str, Any]], workers: int | None) -> str:
    head = (
        "row",
        "status",
        "seeds",
        "episodes",
        "successes",
        "success",
        "95 % CI",
        "steps to success (p50)",
        "time to success p50 (s, 95 % CI)",
        "tick ms (p50 / p99)",
        "inference ms (p50 / p99)",
        "episodes/s",
        "efficiency (speed-up)",
        "note",
    )
    lines = ["<table>", "<thead><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr></thead>", "<tbody>"]
    for row in results:
        done = row.get("status") == "completed"
        seeds = row.get("seeds") or []
        cells = [
            ("label", _e(row.get("label")), False),
            ("status", _e(row.get("status")), False),
            ("seeds", "–".join(_e(s) for s in seeds), True),
            ("episodes", _e(row.get("n_episodes", len(row.get("episodes") or []))), True),
            ("successes", _e(row["n_success"]) if done else "—", True),
            ("pc-success", f"{_number(row['pc_success'], '.1f')} %" if done else "—", True),
            ("ci95", _interval(row["pc_success_ci95"]) if done else "—", True),
            ("steps-p50", _number((row.get("steps_to_success") or {}).get("p50"), ".0f"), True),
            ("time-p50-s", _seconds(row.get("time_to_success")), True),
            ("tick-ms", _pair(row.get("tick_ms")), True),
            ("inference-ms", _pair(row.get("inference_ms")), True),
            ("episodes-per-s", _number(row.get("episodes_per_s"), ".2f"), True),
            ("efficiency", _efficiency(row, workers), True),
            ("note", _e(row.get("error", "")), False),
        ]
        tds = "".join(f'<td class="{name}{_NUMBER if numeric else ""}">{value}</td>' for name, value, numeric in cells)
        lines.append(f'<tr class="{"completed" if done else "failed"}">{tds}</tr>')
    lines += ["</tbody>", "</table>"]
    return "\n".join(lines)


def _seconds(summary: Mapping[str, Any] | None) -> str:
    """Time to success's p50 in simulated seconds with its interval (— : not recorded, or beyond the limit)."""
    if not summary or "p50_s" not in summary:
        return "—"
    interval = summary.get("p50_s_ci95") or [None, None]
    return f"{_number(summary['p50_s'], '.2f')} ({_number(interval[0], '.2f')} – {_number(interval[1], '.2f')})"


def _smoothness_table(completed: Sequence[Mapping[str, Any]]) -> str:
    """Per row, each smoothness metric's mean / p95 over its episodes; a row without them says so."""
    head = ["row", *(f"{label} ({unit})" for label, unit in METRICS.values())]
    lines = ['<table class="smoothness">', "<thead><tr>" + "".join(f"<th>{_e(h)}</th>" for h in head) + "</tr></thead>"]
    lines.append("<tbody>")
    for row in completed:
        summary = row.get("smoothness")
        cells = [f'<td class="label">{_e(row.get("label"))}</td>']
        if not summary:
            cells.append(f'<td class="unavailable" colspan="{len(METRICS)}">unavailable (not recorded)</td>')
        else:
            for name in METRICS:
                stats = summary[name]
                value = f"{_number(stats['mean'], '.3g')} / {_number(stats['p95'], '.3g')}"
                cells.append(f'<td class="{name}{_NUMBER}">{value}</td>')
        lines.append("<tr>" + "".join(cells) + "</tr>")
    lines += ["</tbody>", "</table>"]
    return "\n".join(lines)


def _figures(completed: Sequence[Mapping[str, Any]]) -> Iterable[str]:
    drawings = {
        "success": lambda: html_figures.success_chart(completed),
        "steps-to-success": lambda: html_figures.steps_histograms(completed),
        "tick-latency": lambda: html_figures.latency_histograms(completed, "tick_ms", "tick"),
        "inference-latency": lambda: html_figures.latency_histograms(completed, "inference_ms", "inference"),
    }
    for kind, title, caption in _PLOTS:
        yield f'<section id="{kind}">'
        yield f"<h2>{title}</h2>"
        if completed:
            yield f'<figure class="plot" data-kind="{kind}" role="img" aria-label="{title}">'
            yield drawings[kind]()
            yield f"<figcaption>{caption}</figcaption>"
            yield "</figure>"
        else:
            yield "<p>No row completed: nothing to plot.</p>"
        yield "</section>"


def _real_time_section(completed: Sequence[Mapping[str, Any]]) -> Iterable[str]:
    """The rows run in real time: their share of stale or held steps and effective rates (none: no section)."""
    live = [row for row in completed if row.get("real_time")]
    if not live:
        return
    head = ("row", "stale or held steps", "held", "stale", "held slots", "policy commands/s", "steps/s")
    yield '<section id="real-time">'
    yield "<h2>Real time</h2>"
    yield (
        "<p>Rows paced by the wall clock with the policy's real inference time "
        "(<code>virtual_latency: measured</code>): their outcomes depend on the machine.</p>"
    )
    yield "<table><thead><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr></thead><tbody>"
    for row in live:
        figures = row["real_time"]
        cells = [
            f"<td>{_e(row.get('label'))}</td>",
            *(
                f'<td class="{_NUMBER.strip()}">{_number(100.0 * figures[key], ".1f")} %</td>'
                for key in ("stale_or_held_ratio", "held_ratio", "stale_ratio")
            ),
            f'<td class="{_NUMBER.strip()}">{_e(figures["held_slots"])}</td>',
            f'<td class="{_NUMBER.strip()}">{_number(figures["commands_per_s"], ".1f")}</td>',
            f'<td class="{_NUMBER.strip()}">{_number(figures["steps_per_s"], ".1f")}</td>',
        ]
        yield "<tr>" + "".join(cells) + "</tr>"
    yield "</tbody></table>"
    yield "</section>"


def _provenance_table(provenance: Mapping[str, Any]) -> str:
    lines = ['<table class="provenance">', "<tbody>"]
    for key, value in flatten(provenance):
        lines.append(f'<tr><th scope="row">{_e(key)}</th><td><code>{_e(display(value))}</code></td></tr>')
    lines += ["</tbody>", "</table>"]
    return "\n".join(lines)


def _rows_table(results: Sequence[Mapping[str, Any]]) -> str:
    """What each row ran: its scene, environment, skill with its parameters, and seeds."""
    keys = ("label", "scene", "env", "env_id", "skill", "skill_params", "seeds", "timing")
    lines = ['<table class="rows">', "<thead><tr>" + "".join(f"<th>{k}</th>" for k in keys) + "</tr></thead>"]
    lines.append("<tbody>")
    for row in results:
        lines.append("<tr>" + "".join(f"<td><code>{_e(display(row.get(k)))}</code></td>" for k in keys) + "</tr>")
    lines += ["</tbody>", "</table>"]
    return "\n".join(lines)


def flatten(value: Any, prefix: str = "") -> list[tuple[str, Any]]:
    """Nested mappings as ``(dotted.key, leaf)`` pairs in order: ``{"packages": {"numpy": …}}`` → ``packages.numpy``."""
    if isinstance(value, Mapping) and value:
        pairs: list[tuple[str, Any]] = []
        for key, inner in value.items():
            pairs.extend(flatten(inner, f"{prefix}.{key}" if prefix else str(key)))
        return pairs
    return [(prefix, value)]


def display(value: Any) -> str:
    """A JSON leaf as the page shows it: strings as they are, ``null`` as ``—``, anything else as JSON."""
    if value is None:
        return "—"
    if isinstance(value, str):
        return value
    return json.dumps(value, ensure_ascii=False)


def _e(value: Any) -> str:
    return html.escape(str(value), quote=True)


def _number(value: Any, spec: str) -> str:
    return "—" if value is None else format(float(value), spec)


def _efficiency(row: Mapping[str, Any], workers: int | None) -> str:
    """``0.93 (1.86× on 2 workers)``: the row's efficiency and speed-up against the one-worker baseline."""
    if row.get("efficiency") is None or row.get("speedup") is None:
        return "—"
    return f"{_number(row['efficiency'], '.2f')} ({_number(row['speedup'], '.2f')}× on {_e(workers)} workers)"


def _interval(bounds: Sequence[float]) -> str:
    return f"{_number(bounds[0], '.1f')} – {_number(bounds[1], '.1f')} %"


def _pair(stats: Mapping[str, Any] | None) -> str:
    if not stats or stats.get("p50") is None:
        return "—"
    return f"{_number(stats['p50'], '.2f')} / {_number(stats['p99'], '.2f')}"
