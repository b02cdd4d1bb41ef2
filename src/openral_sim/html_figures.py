"""The benchmark report's figures: matplotlib on its Agg canvas, returned as SVG text to put inline in a page.

No pyplot: each figure is a standalone ``Figure`` on its own Agg canvas, so drawing never opens a
window, never loads a GUI backend whatever ``MPLBACKEND`` says, and keeps no global figure state.
SVG rather than PNG: sharp at any zoom, a few kB for bars and stairs, and its text (row names,
numbers) stays text. Every string from the user reaches the page through matplotlib's XML
escaping; ``$`` is escaped too, so a row name is never parsed as mathtext.

Each function takes the report's completed rows (dicts as ``benchmark run`` writes them) and
returns one ``<svg>`` element: one figure per kind, one bar or one panel per row.
"""

from __future__ import annotations

import io
import math
import re
from collections.abc import Mapping, Sequence
from typing import Any

from openral_core import ROSDependencyMissing

try:
    import matplotlib
    from matplotlib.axes import Axes
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import FuncFormatter, LogLocator, MaxNLocator, NullLocator
except ImportError as exc:
    raise ROSDependencyMissing(
        exc.name or "matplotlib", extra="report", needed_for="the HTML benchmark report (--html)"
    ) from exc

Row = Mapping[str, Any]

_COLUMNS = 3
_CELL = (3.3, 2.7)
"""A panel's width and height in inches, its margins included."""
_MARGINS = (0.6, 0.15, 0.55, 0.5)
"""Inches left of a panel (tick labels), right, above (a two-line title) and below (the axis label)."""
_LABEL_CHARS = 48
_STYLE: dict[Any, Any] = {  # matplotlib types rcParams keys as Literals
    "svg.fonttype": "none",  # text stays <text>: searchable, and small
    "font.family": "sans-serif",
    "font.sans-serif": ["DejaVu Sans"],
    "font.size": 9,
    "axes.spines.top": False,
    "axes.spines.right": False,
}
_SUCCESS = "#3b75af"
_BAR = "#6a9fcf"
_P50 = "#222222"
_P99 = "#c0392b"


def success_chart(rows: Sequence[Row]) -> str:
    """Each row's success rate (percent) as a bar, its Wilson 95 % interval as error bars, ``min_success`` marked."""
    with matplotlib.rc_context(_STYLE):
        return _svg(_success_chart(rows), "success")


def _success_chart(rows: Sequence[Row]) -> Figure:
    fig = Figure(figsize=(8.0, 1.0 + 0.42 * len(rows)), layout="constrained")
    ax = fig.add_subplot()
    positions = list(range(len(rows)))
    rates = [float(row["pc_success"]) for row in rows]
    below = [rate - float(row["pc_success_ci95"][0]) for rate, row in zip(rates, rows, strict=True)]
    above = [float(row["pc_success_ci95"][1]) - rate for rate, row in zip(rates, rows, strict=True)]
    ax.barh(positions, rates, xerr=[below, above], color=_SUCCESS, height=0.6, capsize=4, error_kw={"elinewidth": 1})
    marked = False
    for position, row in zip(positions, rows, strict=True):
        threshold = row.get("min_success")
        if threshold is not None:
            label = None if marked else "min success"
            ax.plot([threshold] * 2, [position - 0.4, position + 0.4], color=_P99, linewidth=2, label=label)
            marked = True
        low, high = row["pc_success_ci95"]
        ax.annotate(
            f"{row['pc_success']:.1f} % [{low:.1f}, {high:.1f}]",
            xy=(1.02, position),
            xycoords=("axes fraction", "data"),
            va="center",
            fontsize=8,
        )
    ax.set_yticks(positions, [_text(row["label"]) for row in rows])
    ax.invert_yaxis()
    ax.set_xlim(0, 100)
    ax.set_xlabel("success (%), 95 % Wilson interval")
    if marked:
        fig.legend(loc="outside upper right", fontsize=7, frameon=False)
    return fig


def steps_histograms(rows: Sequence[Row]) -> str:
    """One panel per row: how many steps its successful episodes took to succeed."""
    with matplotlib.rc_context(_STYLE):
        return _svg(_steps_histograms(rows), "steps")


def _steps_histograms(rows: Sequence[Row]) -> Figure:
    fig, panels = _panels(len(rows))
    for ax, row in zip(panels, rows, strict=False):
        episodes = row.get("episodes") or []
        steps = [int(e["steps_to_success"]) for e in episodes if e.get("steps_to_success") is not None]
        _title(ax, row, f"{len(steps)} of {len(episodes)} episodes succeeded")
        if not steps:
            _empty(ax, "no successful episode")
            continue
        low, high = min(steps), max(steps)
        bins = min(30, high - low + 1)
        edges = [low - 0.5 + i * (high - low + 1) / bins for i in range(bins + 1)]
        ax.hist(steps, bins=edges, color=_BAR, edgecolor="white", linewidth=0.5)
        ax.set_xlabel("steps to success")
        ax.set_ylabel("episodes")
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    return fig


def latency_histograms(rows: Sequence[Row], key: str, what: str) -> str:
    """One panel per row: the histogram the report keeps of ``row[key]`` (``tick_ms``, ``inference_ms``).

    The p50 and p99 are drawn over it; a log-binned histogram gets a log axis, so every bin is
    as wide as the next and the tail is as readable as the body.
    """
    with matplotlib.rc_context(_STYLE):
        return _svg(_latency_histograms(rows, key, what), key)


def _latency_histograms(rows: Sequence[Row], key: str, what: str) -> Figure:
    fig, panels = _panels(len(rows))
    for ax, row in zip(panels, rows, strict=False):
        stats = row.get(key) or {}
        histogram = stats.get("histogram")
        if histogram is None or stats.get("p50") is None:
            _title(ax, row, "")
            _empty(ax, "no samples in the report")
            continue
        counts = histogram["counts"]
        _title(ax, row, f"{sum(counts)} steps, p50 {stats['p50']:.3g} ms, p99 {stats['p99']:.3g} ms")
        ax.stairs(counts, histogram["edges_ms"], fill=True, color=_BAR)
        if histogram.get("scale") == "log":
            ax.set_xscale("log")
            # ticks as plain numbers (no mathtext), denser the narrower the range
            edges = histogram["edges_ms"]
            decades = math.log10(edges[-1] / edges[0])
            subs = (1.0,) if decades >= 2 else (1.0, 2.0, 5.0) if decades >= 1 else (1.0, 1.5, 2.0, 3.0, 5.0, 7.0)
            ax.xaxis.set_major_locator(LogLocator(subs=subs))
            ax.xaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
            ax.xaxis.set_minor_locator(NullLocator())  # minor log ticks cost most of the drawing
        ax.axvline(stats["p50"], color=_P50, linestyle="--", linewidth=1, label="p50")
        ax.axvline(stats["p99"], color=_P99, linestyle=":", linewidth=1.2, label="p99")
        ax.set_xlabel(f"{what} (ms)")
        ax.set_ylabel("steps")
        ax.legend(fontsize=7, frameon=False)
    return fig


def _panels(n: int) -> tuple[Figure, list[Axes]]:
    """A figure of ``n`` panels, ``_COLUMNS`` to a line; the panels past ``n`` are hidden.

    Margins are fixed (inches) rather than solved by a layout engine, which took seconds a
    panel: a suite of fifty rows draws in seconds, not minutes.
    """
    columns = max(1, min(_COLUMNS, n))
    lines = max(1, math.ceil(n / columns))
    width, height = _CELL[0] * columns, _CELL[1] * lines
    fig = Figure(figsize=(width, height))
    grid = fig.subplots(lines, columns, squeeze=False)
    left, right, top, bottom = _MARGINS
    fig.subplots_adjust(
        left=left / width,
        right=1 - right / width,
        top=1 - top / height,
        bottom=bottom / height,
        wspace=(left + right) / (_CELL[0] - left - right),
        hspace=(top + bottom) / (_CELL[1] - top - bottom),
    )
    panels = [ax for line in grid for ax in line]
    for ax in panels[n:]:
        ax.set_visible(False)
    return fig, panels[:n]


def _title(ax: Axes, row: Row, detail: str) -> None:
    ax.set_title(_text(row["label"]) + (f"\n{detail}" if detail else ""), fontsize=8)


def _empty(ax: Axes, message: str) -> None:
    ax.text(0.5, 0.5, message, ha="center", va="center", transform=ax.transAxes, color="#777777")
    ax.set_xticks([])
    ax.set_yticks([])


def _text(label: object) -> str:
    """A user's string as matplotlib shows it literally: shortened, and ``$`` escaped (no mathtext)."""
    text = str(label)
    if len(text) > _LABEL_CHARS:
        text = text[: _LABEL_CHARS - 1] + "…"
    return text.replace("$", r"\$")


_TAG = re.compile(r"<[^<>]+>")
_ID = re.compile(r'\bid="([^"]*)"')
_REF = re.compile(r'(url\(#|href="#)([^)"]*)')


def _svg(fig: Figure, name: str) -> str:
    """``fig`` as one ``<svg>`` element for an HTML page.

    The XML prologue, DOCTYPE, metadata and namespace declarations go (an HTML parser puts
    ``<svg>`` in the SVG namespace itself, and the page names no outside URL), and every id
    and reference to one gets the figure's prefix, so figures on one page never share an id.
    Only tags are rewritten, never text. Deterministic: the same rows give the same bytes.
    """
    FigureCanvasAgg(fig)
    buffer = io.StringIO()
    with matplotlib.rc_context({"svg.hashsalt": name}):
        fig.savefig(buffer, format="svg", metadata={"Date": None, "Creator": None, "Format": None, "Type": None})
    text = buffer.getvalue()
    text = text[text.index("<svg") :]
    prefix = f"fig-{name}-"

    def tag(match: re.Match[str]) -> str:
        rewritten = _ID.sub(lambda m: f'id="{prefix}{m.group(1)}"', match.group(0))
        rewritten = _REF.sub(lambda m: f"{m.group(1)}{prefix}{m.group(2)}", rewritten)
        return re.sub(r'\s+xmlns(:\w+)?="[^"]*"', "", rewritten)

    return _TAG.sub(tag, text).strip()
