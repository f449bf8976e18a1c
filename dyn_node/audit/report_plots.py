"""The report's plot primitives (Pillow canvas, axes, ticks, legend) and the effort plot.

Plots are drawn with Pillow (anti-aliased by drawing at twice the size); matplotlib is not
imported, since importing and laying out a matplotlib figure took longer than auditing a minute
of 1 kHz joint states.
"""
from __future__ import annotations

import io
import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np

# --- plots: drawn with Pillow (no matplotlib: its import and layout cost more than a whole audit)
_S = 2  # supersampling: drawn at 2× and box-averaged down, which anti-aliases lines and edges
_WHITE = (255, 255, 255)
_GRID, _AXIS, _TEXT = (226, 229, 234), (60, 64, 72), (29, 36, 51)
_BLUE, _DARK_BLUE, _ORANGE, _RED, _GREEN = "#2f6db5", "#1b3f6b", "#e08a00", "#b3261e", "#1e7d3a"
# ColorBrewer RdYlGn, reversed (green = low utilisation, red = at or over the limit)
_RDYLGN_R = ("#006837", "#1a9850", "#66bd63", "#a6d96a", "#d9ef8b", "#ffffbf", "#fee08b", "#fdae61",
             "#f46d43", "#d73027", "#a50026")
_fonts: dict[Any, Any] = {}  # pixel size → font; "file" → the font file


def _rgb(c: str | tuple) -> tuple[int, int, int]:
    if isinstance(c, tuple):
        return c
    return int(c[1:3], 16), int(c[3:5], 16), int(c[5:7], 16)


def _blend(c: str | tuple, alpha: float) -> tuple[int, int, int]:
    """``c`` at opacity ``alpha`` over white (areas are drawn first, on the white axes)."""
    return tuple(int(round(255 + alpha * (x - 255))) for x in _rgb(c))


def _font_file() -> str | None:
    """A DejaVu Sans file: the one in matplotlib's data (located without importing matplotlib),
    else Debian's fonts-dejavu-core; None when neither is there."""
    import importlib.util

    candidates = []
    try:
        spec = importlib.util.find_spec("matplotlib")
        if spec is not None and spec.origin:
            candidates.append(Path(spec.origin).parent / "mpl-data" / "fonts" / "ttf" / "DejaVuSans.ttf")
    except (ImportError, ValueError):
        pass
    candidates.append(Path("/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf"))
    return next((str(c) for c in candidates if c.is_file()), None)


def _font(size: float):
    """DejaVu Sans at ``size`` points of the final image; Pillow's built-in font when no DejaVu
    file is found."""
    px = int(round(size * _S * 1.3))
    f = _fonts.get(px)
    if f is None:
        from PIL import ImageFont

        path = _fonts.get("file", "?")
        if path == "?":
            path = _fonts["file"] = _font_file()
        try:
            f = ImageFont.truetype(path, px) if path else ImageFont.load_default(px)
        except OSError:
            f = ImageFont.load_default(px)
        _fonts[px] = f
    return f


def _nice_ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    """Round tick values (1, 2, 2.5, 5 × 10^k steps) inside [lo, hi]."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo] if math.isfinite(lo) else []
    raw = (hi - lo) / max(n, 1)
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)
    first = math.ceil(lo / step - 1e-9) * step
    out = []
    k = 0
    while first + k * step <= hi + 1e-9 * step:
        v = first + k * step
        out.append(0.0 if abs(v) < step * 1e-9 else v)
        k += 1
    return out


def _fmt_tick(v: float, ticks: Sequence[float]) -> str:
    step = abs(ticks[1] - ticks[0]) if len(ticks) > 1 else abs(v) or 1.0
    mag = math.floor(math.log10(step))
    digits = max(0, -mag + (1 if round(step / 10 ** mag, 6) == 2.5 else 0))  # 0.25 needs 2 digits
    return f"{v:.{digits}f}".replace("-", "−")


class _Canvas:
    """A white image of ``w`` × ``h`` final pixels, drawn at :data:`_S` times that size."""

    def __init__(self, w: int, h: int):
        from PIL import Image, ImageDraw

        self.img = Image.new("RGB", (w * _S, h * _S), _WHITE)
        self.d = ImageDraw.Draw(self.img)

    def text(self, x: float, y: float, s: str, size: float = 8, anchor: str = "la", color=_TEXT) -> None:
        self.d.text((x * _S, y * _S), s, fill=_rgb(color), font=_font(size), anchor=anchor)

    def png(self) -> bytes:
        small = self.img.reduce(_S)  # box average of each S×S block: the anti-aliasing
        buf = io.BytesIO()
        small.save(buf, format="PNG")
        return buf.getvalue()


class _Axes:
    """A plot box at final-pixel rectangle (left, top, right, bottom) with data limits."""

    def __init__(self, cv: _Canvas, box: tuple[float, float, float, float],
                 xlim: tuple[float, float], ylim: tuple[float, float]):
        self.cv, self.d = cv, cv.d
        self.l, self.t, self.r, self.b = (v * _S for v in box)
        self.x0, self.x1 = xlim if xlim[1] != xlim[0] else (xlim[0] - 0.5, xlim[0] + 0.5)
        self.y0, self.y1 = ylim if ylim[1] != ylim[0] else (ylim[0] - 0.5, ylim[0] + 0.5)

    def px(self, x) -> np.ndarray:
        return self.l + (np.asarray(x, dtype=float) - self.x0) / (self.x1 - self.x0) * (self.r - self.l)

    def py(self, y) -> np.ndarray:
        return self.b - (np.asarray(y, dtype=float) - self.y0) / (self.y1 - self.y0) * (self.b - self.t)

    def _clip_y(self, y: np.ndarray) -> np.ndarray:
        return np.clip(y, self.t - 2 * _S, self.b + 2 * _S)

    def grid(self, xticks: Sequence[float], yticks: Sequence[float], xlabels: bool = True,
             ylabels: bool = True, size: float = 7.5, ygrid: bool = True, xgrid: bool = True) -> None:
        d = self.d
        for v in xticks if xgrid else ():
            x = float(self.px(v))
            d.line([(x, self.t), (x, self.b)], fill=_GRID, width=_S)
        for v in yticks if ygrid else ():
            y = float(self.py(v))
            d.line([(self.l, y), (self.r, y)], fill=_GRID, width=_S)
        for v in xticks:
            x = float(self.px(v))
            d.line([(x, self.b), (x, self.b + 3 * _S)], fill=_AXIS, width=_S)
            if xlabels:
                self.cv.text(x / _S, self.b / _S + 4, _fmt_tick(v, xticks), size, "ma")
        for v in yticks:
            y = float(self.py(v))
            d.line([(self.l - 3 * _S, y), (self.l, y)], fill=_AXIS, width=_S)
            if ylabels:
                self.cv.text(self.l / _S - 5, y / _S, _fmt_tick(v, yticks), size, "rm")

    def frame(self) -> None:
        self.d.rectangle([self.l, self.t, self.r, self.b], outline=_AXIS, width=_S)

    def vspan(self, x0: float, x1: float, color) -> None:
        a, b = float(np.clip(self.px(x0), self.l, self.r)), float(np.clip(self.px(x1), self.l, self.r))
        if b > a:
            self.d.rectangle([a, self.t, max(b, a + _S), self.b], fill=color)

    def hline(self, y: float, color, width: float = 1.0, dash: bool = False) -> None:
        yy = float(self.py(y))
        if not self.t <= yy <= self.b:
            return
        w = max(1, int(round(width * _S)))
        if not dash:
            self.d.line([(self.l, yy), (self.r, yy)], fill=_rgb(color), width=w)
            return
        x, step = self.l, 6 * _S
        while x < self.r:
            self.d.line([(x, yy), (min(x + step * 0.6, self.r), yy)], fill=_rgb(color), width=w)
            x += step

    def line(self, x, y, color, width: float = 1.0) -> None:
        """A polyline through the finite points (NaN breaks it)."""
        X, Y = self.px(x), self._clip_y(self.py(y))
        ok = np.isfinite(X) & np.isfinite(Y)
        w = max(1, int(round(width * _S)))
        for seg in np.split(np.arange(len(X)), np.flatnonzero(np.diff(ok.astype(np.int8)) != 0) + 1):
            if len(seg) and ok[seg[0]]:
                pts = list(zip(X[seg].tolist(), Y[seg].tolist()))
                if len(pts) == 1:
                    pts = pts * 2
                self.d.line(pts, fill=_rgb(color), width=w, joint="curve")

    def steps(self, centres, width_s: float, y, color, width: float = 1.0) -> None:
        """A step line: value y[i] over [centre − w/2, centre + w/2] (matplotlib's steps-mid)."""
        c = np.asarray(centres, dtype=float)
        y = np.asarray(y, dtype=float)
        x = np.column_stack([c - width_s / 2, c + width_s / 2]).ravel()
        self.line(x, np.repeat(y, 2), color, width)

    def bars(self, left, right, lo, hi, color) -> None:
        """Filled rectangles [left, right] × [lo, hi] (NaN: skipped); one colour or one each."""
        L, R = self.px(left), self.px(right)
        A, B = self._clip_y(self.py(lo)), self._clip_y(self.py(hi))
        colors = [color] * len(L) if isinstance(color, (str, tuple)) else color
        for l, r, a, b, c in zip(L.tolist(), R.tolist(), A.tolist(), B.tolist(), colors):
            if a == a and b == b:
                top, bot = min(a, b), max(a, b)
                self.d.rectangle([l, top, max(r, l + _S) - 1, max(bot, top + _S)], fill=_rgb(c))


def _legend(cv: _Canvas, x: float, y: float, items: Sequence[tuple[str, Any, str]]) -> None:
    """One row of (label, colour, 'line' | 'area') entries starting at final pixel (x, y)."""
    for label, color, kind in items:
        if kind == "area":
            cv.d.rectangle([x * _S, (y - 4) * _S, (x + 18) * _S, (y + 4) * _S], fill=_rgb(color))
        else:
            cv.d.line([(x * _S, y * _S), ((x + 18) * _S, y * _S)], fill=_rgb(color), width=2 * _S)
        cv.text(x + 23, y, label, 8, "lm")
        x += 23 + _font(8).getlength(label) / _S + 18


def _centres(series, start_ns: int) -> np.ndarray:
    n = series.n
    return ((series.t0 - start_ns) + (np.arange(n) + 0.5) * series.width) * 1e-9


def effort_plot(series, joint_names: Sequence[str], start_ns: int, violations: list[dict]) -> bytes:
    """Per joint: the band of RNEA torque (min..max per time bin), the measured effort's min and
    max per bin, both signed (a sign disagreement shows as one), and the ±limit envelope (N·m)
    over time since the bag start (s)."""
    nv = len(joint_names)
    W, row, top, left, right = 1100, 150, 62, 110, 16
    H = top + nv * row + 40
    cv = _Canvas(W, H)
    cv.text(W / 2, 16, "Effort vs limit over time (shaded red: effort violations)", 11, "ma")
    t = _centres(series, start_ns)
    n = series.n
    have = series.count[:n] > 0
    legend = [("model torque (min–max per bin)", _blend(_BLUE, 0.55), "area")]
    if np.isfinite(series.meas_max[:n]).any():
        legend.append(("measured effort (min and max per bin)", _ORANGE, "line"))
    if (have[:, None] & np.isfinite(series.limit[:n])).any():
        legend.append(("±effort limit", _RED, "line"))
    _legend(cv, left, 44, legend)
    w_s = series.width * 1e-9
    xlim = (float(t[0] - w_s / 2), float(t[-1] + w_s / 2)) if n else (0.0, 1.0)
    xticks = _nice_ticks(*xlim, n=10)
    band = _blend(_BLUE, 0.55)
    shade = _blend(_RED, 0.18)
    for j in range(nv):
        lo = np.where(have, series.tau_min[:n, j], np.nan)
        hi = np.where(have, series.tau_max[:n, j], np.nan)
        lim = series.limit[:n, j]
        m_lo, m_hi = series.meas_min[:n, j], series.meas_max[:n, j]
        finite = have & np.isfinite(lim)
        env = np.where(finite, lim, np.nan)
        vals = np.concatenate([lo[have], hi[have], env[finite], -env[finite], m_lo[np.isfinite(m_lo)],
                               m_hi[np.isfinite(m_hi)]])
        if finite.any():
            big = float(np.nanmax(np.abs(vals)))
            ylim = (-1.15 * big, 1.15 * big)
        elif vals.size:
            a, b = float(np.min(vals)), float(np.max(vals))
            pad = 0.05 * (b - a) or 0.5
            ylim = (a - pad, b + pad)
        else:
            ylim = (-1.0, 1.0)
        y_top = top + j * row
        ax = _Axes(cv, (left, y_top, W - right, y_top + row - 14), xlim, ylim)
        for v in violations:
            if v["joint"] == joint_names[j] and v["kind"] == "effort":
                ax.vspan(v["start_s"], max(v["end_s"], v["start_s"] + w_s), shade)
        ax.grid(xticks, _nice_ticks(*ylim, n=4), xlabels=j == nv - 1)
        ax.bars(t - w_s / 2, t + w_s / 2, lo, hi, band)
        ax.line(t, (lo + hi) / 2, _DARK_BLUE, 0.7)
        if np.isfinite(m_hi).any():
            ax.steps(t, w_s, m_lo, _ORANGE, 1.0)
            ax.steps(t, w_s, m_hi, _ORANGE, 1.0)
        if finite.any():
            ax.steps(t, w_s, env, _RED, 1.3)
            ax.steps(t, w_s, -env, _RED, 1.3)
        ax.frame()
        cv.text(8, y_top + (row - 14) / 2 - 7, str(joint_names[j]), 8, "lm")
        cv.text(8, y_top + (row - 14) / 2 + 7, "N·m", 8, "lm")
    cv.text(left + (W - right - left) / 2, H - 14, "time since bag start (s)", 9, "ms")
    return cv.png()
