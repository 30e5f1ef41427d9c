"""Figure styles: ``screen`` (PNG and SVG at the size each figure is
drawn, the default) and the paper styles, vector output at a journal's
column width: ``paper`` (a single column, 3.5 in = 88.9 mm, as IEEE's
and most two-column journals') and ``paper-wide`` (the full text width,
7.16 in = 181.9 mm). A paper figure is laid out again at that width
(:func:`fit_to_width`: at most two panels a row in a column, three
across the page, each keeping its aspect ratio), set in 8 pt type
(titles 9 pt, legends and ticks 6-7 pt, never under 6 pt), and written
as PDF (fonts
embedded as TrueType, fonttype 42: no Type 3 fonts, which IEEE's PDF
eXpress and many publishers refuse) and SVG (its text kept as text), and
a 300 dpi PNG to preview.

The style in force is set by :func:`figure_style` (a context manager)
around the calls that write figures; :func:`save_figure` writes one."""

import contextlib
import contextvars
import os
from dataclasses import dataclass


@dataclass(frozen=True)
class Style:
    name: str
    width_in: float = None          # [in] the figure's width (None: as drawn)
    formats: tuple = ("png", "svg")
    dpi: int = 110                  # the PNG's resolution [dots/in]


STYLES = {
    "screen": Style("screen"),
    "paper": Style("paper", width_in=3.5, formats=("pdf", "svg", "png"), dpi=300),
    "paper-wide": Style("paper-wide", width_in=7.16, formats=("pdf", "svg", "png"), dpi=300),
}
_CURRENT = contextvars.ContextVar("figure_style", default=STYLES["screen"])
_PAPER_RC = {"pdf.fonttype": 42, "ps.fonttype": 42, "svg.fonttype": "none"}


def style_named(name):
    """The :class:`Style` called ``name`` (ValueError naming the choices)."""
    try:
        return STYLES[name]
    except KeyError:
        raise ValueError(f"figure style must be one of {', '.join(STYLES)}, got {name!r}") from None


@contextlib.contextmanager
def figure_style(name):
    """Figures saved inside are written in the style ``name``."""
    token = _CURRENT.set(style_named(name or "screen"))
    try:
        yield _CURRENT.get()
    finally:
        _CURRENT.reset(token)


def current_style():
    return _CURRENT.get()


def drawn_size(width_in, height_in, style=None):
    """The size [in] to draw a figure designed at (width_in, height_in): as
    designed on screen; in a paper style, scaled to the style's width
    (its aspect kept) -- a figure drawn so is saved with ``drawn=True``."""
    style = current_style() if style is None else style
    if not style.width_in:
        return (width_in, height_in)
    return (style.width_in, style.width_in * height_in / width_in)


def drawing_rc(style=None):
    """rcParams to draw a figure in (``matplotlib.rc_context``): none on
    screen; a paper style's type sizes (text 7 pt, titles 8 pt, ticks and
    legends 6 pt) and thinner lines, so that a figure drawn at the
    column's width (:func:`drawn_size`) is laid out with them."""
    style = current_style() if style is None else style
    if not style.width_in:
        return {}
    return {"font.size": 7.0, "axes.titlesize": 8.0, "axes.labelsize": 7.0, "xtick.labelsize": 6.0,
            "ytick.labelsize": 6.0, "legend.fontsize": 6.0, "figure.titlesize": 8.0, "lines.linewidth": 1.0,
            "lines.markersize": 4.0, "axes.linewidth": 0.6, "xtick.major.size": 2.5, "ytick.major.size": 2.5}


def paper_font_size(size_pt):
    """A text's size [pt] in a paper figure: 0.8 of its screen size within
    [6, 9] (screen 10 -> 8 pt, titles 12 -> 9, legends 8 -> 6.4)."""
    return min(max(0.8 * float(size_pt), 6.0), 9.0)


def _cells(fig):
    """[(axes, row, col)] and the grid (rows, cols) when every axes of
    ``fig`` fills one cell of one grid (None otherwise: spans, colour bars
    or insets, whose layout is kept)."""
    cells, grid = [], None
    for ax in fig.axes:
        spec = ax.get_subplotspec()
        if spec is None:
            return None, None
        g = spec.get_gridspec()
        if grid is None:
            grid = g
        if g is not grid or spec.num1 != spec.num2:
            return None, None
        r, c = divmod(spec.num1, g.ncols)
        cells.append((ax, r, c))
    return (cells, (grid.nrows, grid.ncols)) if cells else (None, None)


def fit_to_width(fig, width_in, max_cols=None):
    """Lay ``fig`` out again at ``width_in`` [in] with every text in
    :func:`paper_font_size`: its panels, if they fill a simple grid, are
    set at most ``max_cols`` to a row (default: 2 under 5 in, 3 above;
    a row of three 1 in panels has no room for its labels), in their
    order, each keeping its aspect ratio; the height follows (0.45 in more
    for the title and a legend). Other layouts keep their aspect ratio.
    Then its layout engine (or matplotlib's tight layout) places them."""
    import math
    from matplotlib.gridspec import GridSpec
    from matplotlib.text import Text
    w, h = fig.get_size_inches()
    cells, grid = _cells(fig)
    if cells is None:
        fig.set_size_inches(width_in, width_in * h / w)
    else:
        rows, cols = grid
        aspect = (h / rows) / (w / cols)                   # a panel's height over its width
        new_cols = min(cols, max_cols or (2 if width_in < 5.0 else 3))
        new_rows = math.ceil(len(cells) / new_cols)
        fig.set_size_inches(width_in, new_rows * (width_in / new_cols) * aspect + 0.45)
        if (new_rows, new_cols) != (rows, cols):
            gs = GridSpec(new_rows, new_cols, figure=fig)
            for k, (ax, _, _) in enumerate(sorted(cells, key=lambda c: (c[1], c[2]))):
                ax.set_subplotspec(gs[k])
    for t in fig.findobj(Text):
        t.set_fontsize(paper_font_size(t.get_fontsize()))
    _thin_ticks(fig, width_in)
    for ax in fig.axes:         # (the tight layout leaves out a 3D axes' labels: its box drawn smaller)
        if ax.name == "3d":
            ax.set_box_aspect(ax.get_box_aspect(), zoom=0.75)
    _fit_legends(fig, width_in)


def _thin_ticks(fig, width_in, narrow_in=2.2):
    """At most 3 ticks on each linear axis of a panel narrower than
    ``narrow_in`` [in] (four 7 pt labels such as ``-0.015`` run into each
    other on 1.7 in); fixed and log locators are left as they are."""
    from matplotlib.ticker import MaxNLocator
    for ax in fig.axes:
        if ax.get_subplotspec() is None or ax.get_position().width * width_in >= narrow_in:
            continue
        for axis in (ax.xaxis, ax.yaxis, getattr(ax, "zaxis", None)):
            if axis is not None and isinstance(axis.get_major_locator(), MaxNLocator):    # (AutoLocator too)
                axis.set_major_locator(MaxNLocator(3))


def _fit_legends(fig, width_in):
    """The figure's legends in as many columns as fit (one per 1.3 in),
    and the layout's bottom margin made to hold them (the tight layout's
    ``rect``); without a layout engine, matplotlib's tight layout."""
    engine = fig.get_layout_engine()
    for leg in list(fig.legends):         # (a legend lays its entries out once: made again)
        texts = leg.get_texts()
        ncols = max(1, min(len(texts), int(width_in // 1.3)))
        if ncols == leg._ncols:
            continue
        loc, frame = leg._loc, leg.get_frame_on()
        leg.remove()
        fig.legend(leg.legend_handles, [t.get_text() for t in texts], loc=loc, ncols=ncols, frameon=frame,
                   fontsize=texts[0].get_fontsize() if texts else None)
    if engine is None:
        with contextlib.suppress(Exception):      # (tight layout warns, never fails, on 3D axes)
            fig.tight_layout()
        return
    if fig.legends and hasattr(engine, "set") and "rect" in engine.get():
        renderer = fig.canvas.get_renderer()
        height = max(leg.get_window_extent(renderer).height for leg in fig.legends) / fig.bbox.height
        engine.set(rect=(0.0, min(height + 0.01, 0.4), 1.0, 1.0))


def save_figure(fig, folder, stem, style=None, drawn=False):
    """Write ``fig`` as ``<folder>/<stem>.<ext>`` in every format of the
    style in force (or ``style``), close it, and return the paths.
    ``drawn``: the figure was drawn for the style (:func:`drawn_size`,
    :func:`drawing_rc`): not laid out again."""
    import matplotlib
    import matplotlib.pyplot as plt
    style = current_style() if style is None else style
    os.makedirs(folder, exist_ok=True)
    paths = []
    rc = _PAPER_RC if style.width_in else {}
    if style.width_in and not drawn:
        fit_to_width(fig, style.width_in)
    with matplotlib.rc_context(rc):
        for ext in style.formats:
            p = os.path.join(folder, f"{stem}.{ext}")
            fig.savefig(p, dpi=style.dpi)
            paths.append(p)
    plt.close(fig)
    return paths
