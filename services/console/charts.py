"""Charts drawn on the server as inline SVG: no chart library, no script, the same picture in any
browser. Templates call `charts.lines(...)`, `charts.bars(...)` and `charts.coverage(...)`."""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Sequence
from dataclasses import dataclass

from markupsafe import Markup, escape

PALETTE = ("#2f6fde", "#e0732c", "#2a9d5b", "#c0392b", "#8e44ad", "#16a2b8", "#b7950b", "#5d6d7e")
_PAD_LEFT, _PAD_RIGHT, _PAD_TOP, _PAD_BOTTOM = 64, 12, 12, 28


@dataclass(frozen=True)
class Series:
    """One line: its name and its points (x, y), x ascending."""

    name: str
    points: Sequence[tuple[float, float]]


def _ticks(lo: float, hi: float) -> tuple[float, float]:
    if lo == hi:
        return lo - 1, hi + 1
    return lo, hi


def _label(value: float) -> str:
    if value != 0 and (abs(value) >= 1e6 or abs(value) < 1e-3):
        return f"{value:.3g}"
    return f"{value:,.2f}".rstrip("0").rstrip(".")


def lines(
    series: Sequence[Series],
    *,
    width: int = 720,
    height: int = 220,
    x_label: str = "",
    x_format: str = "number",
    title: str = "",
) -> Markup:
    """Line chart of `series` on shared axes, with min/max labels and a legend. `x_format`
    "number" or "time_ns" (x in nanoseconds since the epoch, labelled as UTC times)."""
    points = [p for s in series for p in s.points if math.isfinite(p[0]) and math.isfinite(p[1])]
    if not points:
        return Markup('<p class="empty">no values to plot</p>')
    x_lo, x_hi = _ticks(min(p[0] for p in points), max(p[0] for p in points))
    y_lo, y_hi = _ticks(min(p[1] for p in points), max(p[1] for p in points))
    plot_w, plot_h = width - _PAD_LEFT - _PAD_RIGHT, height - _PAD_TOP - _PAD_BOTTOM

    def at(x: float, y: float) -> str:
        px = _PAD_LEFT + (x - x_lo) / (x_hi - x_lo) * plot_w
        py = _PAD_TOP + (1 - (y - y_lo) / (y_hi - y_lo)) * plot_h
        return f"{px:.1f},{py:.1f}"

    parts = [
        f'<svg class="chart" role="img" viewBox="0 0 {width} {height}" width="{width}" height="{height}" '
        f'xmlns="http://www.w3.org/2000/svg"><title>{escape(title or "chart")}</title>',
        f'<rect x="{_PAD_LEFT}" y="{_PAD_TOP}" width="{plot_w}" height="{plot_h}" class="plot-area"/>',
    ]
    for i, line in enumerate(series):
        kept = [p for p in line.points if math.isfinite(p[0]) and math.isfinite(p[1])]
        if not kept:
            continue
        colour = PALETTE[i % len(PALETTE)]
        coords = " ".join(at(x, y) for x, y in kept)
        parts.append(
            f'<polyline fill="none" stroke="{colour}" stroke-width="1.5" points="{coords}" '
            f'data-series="{escape(line.name)}" data-points="{len(kept)}"/>'
        )
    parts += [
        f'<text x="{_PAD_LEFT - 6}" y="{_PAD_TOP + 10}" text-anchor="end" class="axis">{_label(y_hi)}</text>',
        f'<text x="{_PAD_LEFT - 6}" y="{_PAD_TOP + plot_h}" text-anchor="end" class="axis">{_label(y_lo)}</text>',
        f'<text x="{_PAD_LEFT}" y="{height - 8}" class="axis">{escape(_x_label(x_lo, x_format))}</text>',
        f'<text x="{width - _PAD_RIGHT}" y="{height - 8}" text-anchor="end" class="axis">'
        f"{escape(_x_label(x_hi, x_format))}</text>",
    ]
    if x_label:
        parts.append(
            f'<text x="{_PAD_LEFT + plot_w / 2:.0f}" y="{height - 8}" text-anchor="middle" class="axis">'
            f"{escape(x_label)}</text>"
        )
    parts.append("</svg>")
    legend = "".join(
        f'<span class="legend-item"><i style="background:{PALETTE[i % len(PALETTE)]}"></i>{escape(s.name)}</span>'
        for i, s in enumerate(series)
    )
    return Markup("".join(parts) + (f'<div class="legend">{legend}</div>' if len(series) > 1 else ""))


def _x_label(value: float, x_format: str) -> str:
    if x_format == "time_ns":
        return dt.datetime.fromtimestamp(value / 1e9, dt.UTC).strftime("%Y-%m-%d %H:%M:%S")
    return _label(value)


def bars(labels: Sequence[str], values: Sequence[float], *, width: int = 720, title: str = "") -> Markup:
    """Horizontal bars, one per label, longest = the largest value."""
    if not values:
        return Markup('<p class="empty">no values to plot</p>')
    top = max(max(values), 0) or 1
    row, label_w = 22, 160
    height = row * len(values) + 8
    parts = [
        f'<svg class="chart bars" role="img" viewBox="0 0 {width} {height}" width="{width}" height="{height}" '
        f'xmlns="http://www.w3.org/2000/svg"><title>{escape(title or "bars")}</title>'
    ]
    for i, (label, value) in enumerate(zip(labels, values, strict=True)):
        y = 4 + i * row
        length = max(value, 0) / top * (width - label_w - 80)
        parts.append(
            f'<text x="{label_w - 6}" y="{y + 14}" text-anchor="end" class="axis">{escape(label)}</text>'
            f'<rect x="{label_w}" y="{y + 3}" width="{length:.1f}" height="{row - 8}" fill="{PALETTE[0]}" '
            f'data-label="{escape(label)}" data-value="{value}"/>'
            f'<text x="{label_w + length + 6:.1f}" y="{y + 14}" class="axis">{_label(value)}</text>'
        )
    parts.append("</svg>")
    return Markup("".join(parts))


@dataclass(frozen=True)
class Mark:
    """An event drawn on the coverage: its range, where clicking it leads, and what hovering says."""

    start: float
    end: float
    href: str
    title: str
    severity: str = "info"
    ident: str = ""


SEVERITY_COLOURS = {"info": PALETTE[0], "warn": PALETTE[1], "error": PALETTE[3]}


def coverage(
    rows: Sequence[tuple[str, float, float]],
    lo: float,
    hi: float,
    *,
    width: int = 720,
    marks: Sequence[Mark] = (),
) -> Markup:
    """Where each row (an entity, a timeline) has data between `lo` and `hi`: one bar per row; with
    `marks`, a first row of events, each a link (a span, or a tick for an instant)."""
    if not rows and not marks:
        return Markup('<p class="empty">no time ranges</p>')
    row, label_w = 20, 240
    plot_w = width - label_w - 8
    span = (hi - lo) or 1
    first = 1 if marks else 0
    height = row * (len(rows) + first) + 4
    parts = [
        f'<svg class="chart coverage" role="img" viewBox="0 0 {width} {height}" width="{width}" '
        f'height="{height}" xmlns="http://www.w3.org/2000/svg"><title>timeline coverage</title>'
    ]
    if marks:
        parts.append(_marks(marks, lo, span, label_w, plot_w, row))
    for i, (label, start, end) in enumerate(rows, start=first):
        y = 2 + i * row
        x0 = label_w + (start - lo) / span * plot_w
        x1 = label_w + (end - lo) / span * plot_w
        parts.append(
            f'<text x="{label_w - 6}" y="{y + 13}" text-anchor="end" class="axis">{escape(label)}</text>'
            f'<rect x="{label_w}" y="{y + 3}" width="{plot_w}" height="{row - 6}" class="track"/>'
            f'<rect x="{x0:.1f}" y="{y + 3}" width="{max(x1 - x0, 2):.1f}" height="{row - 6}" '
            f'fill="{PALETTE[2]}" data-label="{escape(label)}"/>'
        )
    parts.append("</svg>")
    return Markup("".join(parts))


def _marks(marks: Sequence[Mark], lo: float, span: float, label_w: int, plot_w: int, row: int) -> str:
    """The events' row: each mark a link (an SVG `<a>`), clamped to the drawn span."""

    def at(value: float) -> float:
        return label_w + min(max((value - lo) / span, 0.0), 1.0) * plot_w

    parts = [
        f'<text x="{label_w - 6}" y="15" text-anchor="end" class="axis">events</text>'
        f'<rect x="{label_w}" y="5" width="{plot_w}" height="{row - 6}" class="track"/>'
    ]
    for mark in marks:
        x0, x1 = at(mark.start), at(mark.end)
        colour = SEVERITY_COLOURS.get(mark.severity, PALETTE[0])
        parts.append(
            f'<a href="{escape(mark.href)}" class="event-mark" data-event="{escape(mark.ident)}">'
            f"<title>{escape(mark.title)}</title>"
            f'<rect x="{min(x0, label_w + plot_w - 3):.1f}" y="3" width="{max(x1 - x0, 3):.1f}" height="{row - 2}" '
            f'fill="{colour}" fill-opacity="0.8"/></a>'
        )
    return "".join(parts)
