"""A dependency-free SVG scatter plot for the evidence page: speed on x, error on y, one colour a series.

matplotlib is not a dependency of the project, and these plots need only points, lines and labels.
"""

from __future__ import annotations

import html
import math
from dataclasses import dataclass, field

COLOURS = ["#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"]
WIDTH, HEIGHT, LEFT, RIGHT, TOP, BOTTOM = 720, 440, 70, 230, 40, 50


@dataclass
class Series:
    name: str
    points: list[tuple[float, float]] = field(default_factory=list)  # (x, y)
    joined: bool = False  # draw a line through the points in order


def _ticks(lo: float, hi: float, log: bool) -> list[float]:
    if log:
        decades = range(math.floor(math.log10(lo)), math.ceil(math.log10(hi)) + 1)
        marks = (1, 2, 5) if math.log10(hi / lo) < 2 else (1,)
        return [m * 10.0**e for e in decades for m in marks]
    step = 10.0 ** math.floor(math.log10((hi - lo) or 1.0))
    while (hi - lo) / step < 4:
        step /= 2
    return [k * step for k in range(math.ceil(lo / step), math.floor(hi / step) + 1)]


def _axis(values: list[float], log: bool) -> tuple[float, float]:
    """Padded (low, high) of the values, in log10 units when `log`."""
    if log:
        values = [math.log10(v) for v in values if v > 0]
    lo, hi = min(values), max(values)
    pad = 0.06 * (hi - lo) if hi > lo else (0.5 if log else abs(lo) * 0.1 or 1.0)
    return lo - pad, hi + pad


def _label(v: float) -> str:
    return f"{v:.3g}"


def scatter_svg(title: str, x_label: str, y_label: str, series: list[Series],
                log_x: bool = False, log_y: bool = False) -> str:
    """The plot as an SVG document; points with a non-positive value are left out of a log axis."""
    def usable(x: float, y: float) -> bool:
        return (x > 0 or not log_x) and (y > 0 or not log_y) and math.isfinite(x) and math.isfinite(y)

    series = [Series(s.name, [p for p in s.points if usable(*p)], s.joined) for s in series]
    xs = [x for s in series for x, _ in s.points]
    ys = [y for s in series for _, y in s.points]
    if not xs:
        raise ValueError(f"{title}: no points to plot")
    (x0, x1), (y0, y1) = _axis(xs, log_x), _axis(ys, log_y)
    plot_w, plot_h = WIDTH - LEFT - RIGHT, HEIGHT - TOP - BOTTOM

    def px(x: float) -> float:
        return LEFT + plot_w * ((math.log10(x) if log_x else x) - x0) / (x1 - x0)

    def py(y: float) -> float:
        return TOP + plot_h - plot_h * ((math.log10(y) if log_y else y) - y0) / (y1 - y0)

    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{WIDTH}" height="{HEIGHT}" '
             f'font-family="sans-serif" font-size="11">',
             '<rect width="100%" height="100%" fill="white"/>',
             f'<text x="{LEFT}" y="20" font-size="13">{html.escape(title)}</text>',
             f'<rect x="{LEFT}" y="{TOP}" width="{plot_w}" height="{plot_h}" fill="none" stroke="black"/>',
             f'<text x="{LEFT + plot_w / 2:.0f}" y="{HEIGHT - 12}" text-anchor="middle">{html.escape(x_label)}</text>',
             f'<text transform="translate(16 {TOP + plot_h / 2:.0f}) rotate(-90)" text-anchor="middle">'
             f'{html.escape(y_label)}</text>']
    lo_x, hi_x = (10**x0, 10**x1) if log_x else (x0, x1)
    lo_y, hi_y = (10**y0, 10**y1) if log_y else (y0, y1)
    for t in _ticks(lo_x, hi_x, log_x):
        if lo_x <= t <= hi_x:
            parts.append(f'<line x1="{px(t):.1f}" y1="{TOP + plot_h}" x2="{px(t):.1f}" y2="{TOP + plot_h + 4}" '
                         f'stroke="black"/><text x="{px(t):.1f}" y="{TOP + plot_h + 16}" text-anchor="middle">'
                         f'{_label(t)}</text>')
    for t in _ticks(lo_y, hi_y, log_y):
        if lo_y <= t <= hi_y:
            parts.append(f'<line x1="{LEFT - 4}" y1="{py(t):.1f}" x2="{LEFT}" y2="{py(t):.1f}" stroke="black"/>'
                         f'<text x="{LEFT - 6}" y="{py(t) + 4:.1f}" text-anchor="end">{_label(t)}</text>')
    for k, s in enumerate(series):
        colour = COLOURS[k % len(COLOURS)]
        if s.joined and len(s.points) > 1:
            points = " ".join(f"{px(x):.1f},{py(y):.1f}" for x, y in s.points)
            parts.append(f'<polyline points="{points}" fill="none" stroke="{colour}" stroke-width="1.5"/>')
        parts.extend(f'<circle cx="{px(x):.1f}" cy="{py(y):.1f}" r="3.5" fill="{colour}"/>' for x, y in s.points)
        parts.append(f'<circle cx="{WIDTH - RIGHT + 14}" cy="{TOP + 6 + 15 * k}" r="4" fill="{colour}"/>'
                     f'<text x="{WIDTH - RIGHT + 24}" y="{TOP + 10 + 15 * k}">{html.escape(s.name)}</text>')
    parts.append("</svg>\n")
    return "".join(parts)
