"""Two policies side by side on the same seeds, as HTML: ``benchmark compare --html`` and the report's section.

A view of the comparison document (:mod:`openral_sim.benchmark.compare`), never a second source of
numbers. Plain tables, no script and nothing fetched; every name that came from a user is escaped.
"""

from __future__ import annotations

import html
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from openral_sim import report_files
from openral_sim.smoothness import METRICS

Comparison = Mapping[str, Any]

_CSS = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 75em; padding: 0 1em; color: #222; }
table { border-collapse: collapse; font-size: 0.9em; margin: 0.5em 0; }
th, td { border: 1px solid #ddd; padding: 0.25em 0.6em; text-align: left; }
td.number { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
"""


def comparison_section(comparison: Comparison) -> str:
    """The comparison as one ``<section>``: per scene, A and B side by side and what B − A is worth."""
    head = "".join(
        f"<th>{h}</th>"
        for h in (
            "scene",
            "success A",
            "success B",
            "B − A (95 % CI, paired)",
            "McNemar p",
            "only A / only B / pairs",
            "time to success p50 A / B",
            "steps B − A, both solved (95 % CI)",
        )
    )
    rows = []
    for row in comparison.get("rows", []):
        low, high = row["difference_pp_ci95"]
        steps = row["steps_to_success"]
        steps_text = "—"
        if steps.get("mean_difference") is not None:
            s_low, s_high = steps["mean_difference_ci95"]
            steps_text = (
                f"{steps['mean_difference']:+.1f} ({s_low:+.1f} to {s_high:+.1f}), n={steps['n_both_succeeded']}"
            )
        discordant = row["discordant"]
        cells = [
            _e(row["scene"]),
            _num(f"{row['pc_success_a']:.1f} %"),
            _num(f"{row['pc_success_b']:.1f} %"),
            _num(f"{row['difference_pp']:+.1f} pp ({low:+.1f} to {high:+.1f})"),
            _num(f"{row['mcnemar_p']:.3g}"),
            _num(f"{discordant['only_a']} / {discordant['only_b']} / {row['n_pairs']}"),
            _num(f"{_p50(row.get('time_to_success_a'))} / {_p50(row.get('time_to_success_b'))}"),
            _num(steps_text),
        ]
        rows.append(
            "<tr>" + "".join(cell if cell.startswith("<td") else f"<td>{cell}</td>" for cell in cells) + "</tr>"
        )
    a, b = comparison.get("a", {}), comparison.get("b", {})
    return "\n".join(
        [
            '<section id="comparison">',
            "<h2>A against B on the same seeds</h2>",
            f"<p>A: {_who(a)}; B: {_who(b)}. Success interval: Newcombe's method 10 for paired proportions; "
            "McNemar: exact, on the seeds only one of them solved; steps: paired bootstrap on the seeds both solved. "
            "Time to success counts every episode (failures censored at the limit; — : beyond it).</p>",
            f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(rows)}</tbody></table>",
            "<h3>Smoothness, A and B on the same seeds</h3>",
            "<p>Per metric (README: definitions and units): the means of A and B over the seeds where both have "
            "it, B − A with its paired bootstrap 95 % interval, how many seeds B was lower / higher, and the exact "
            "sign test.</p>",
            _smoothness_table(comparison),
            "</section>",
        ]
    )


def _smoothness_table(comparison: Comparison) -> str:
    head = "".join(
        f"<th>{h}</th>"
        for h in ("scene", "metric", "A", "B", "B − A (95 % CI, paired)", "B lower / higher / pairs", "sign test p")
    )
    rows = []
    for row in comparison.get("rows", []):
        smoothness = row.get("smoothness")
        if smoothness is None:
            rows.append(f'<tr><td>{_e(row["scene"])}</td><td colspan="6">unavailable (not recorded)</td></tr>')
            continue
        for name, (label, unit) in METRICS.items():
            paired = smoothness.get(name)
            cells = [_e(row["scene"]), _e(f"{label} ({unit})")]
            if paired is None:
                cells += ["—"] * 5
            else:
                low, high = paired["mean_difference_ci95"]
                cells += [
                    _num(f"{paired['mean_a']:.3g}"),
                    _num(f"{paired['mean_b']:.3g}"),
                    _num(f"{paired['mean_difference']:+.3g} ({low:+.3g} to {high:+.3g})"),
                    _num(f"{paired['b_lower']} / {paired['b_higher']} / {paired['n_pairs']}"),
                    _num(f"{paired['sign_test_p']:.3g}"),
                ]
            rows.append(
                "<tr>" + "".join(cell if cell.startswith("<td") else f"<td>{cell}</td>" for cell in cells) + "</tr>"
            )
    body = "".join(rows)
    return f'<table class="smoothness"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


def render(comparison: Comparison) -> str:
    """The comparison as one self-contained HTML page."""
    return (
        "\n".join(
            [
                "<!DOCTYPE html>",
                '<html lang="en">',
                '<head><meta charset="utf-8"><title>Benchmark comparison</title>',
                f"<style>{_CSS}</style></head>",
                "<body>",
                "<h1>Benchmark comparison</h1>",
                comparison_section(comparison),
                "</body>",
                "</html>",
            ]
        )
        + "\n"
    )


def write(comparison: Comparison, path: Path) -> None:
    """Write the page whole or not at all (a new file renamed over ``path``)."""
    report_files.write_whole(path, render(comparison), what="the HTML comparison")


def _who(side: Mapping[str, Any]) -> str:
    skills = ", ".join(str(s) for s in side.get("skills", []))
    return f"<code>{_e(side.get('suite'))}</code> ({_e(skills)})"


def _p50(summary: Mapping[str, Any] | None) -> str:
    if not summary or summary.get("p50") is None:
        return "—"
    seconds = summary.get("p50_s")
    return f"{summary['p50']:.0f}" + ("" if seconds is None else f" ({seconds:.2f} s)")


def _num(text: str) -> str:
    return f'<td class="number">{_e(text)}</td>'


def _e(value: Any) -> str:
    return html.escape(str(value), quote=True)
