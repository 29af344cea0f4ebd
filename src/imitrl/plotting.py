"""Writing a figure with every label inside the canvas, and the check that says so.

Every figure the project writes goes through :func:`save_figure`: a figure that has not
laid itself out is given matplotlib's constrained layout, which sizes the margins to the
drawn tick labels, axis labels, titles, colorbars and legends (fixed ``subplots_adjust``
margins cut off two-line tick labels and long ones such as ``0.7275``).
:func:`outside_canvas` returns the text artists a reader would see cut off; the tests
draw every figure and assert it returns nothing.
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol, cast

from matplotlib.artist import Artist
from matplotlib.backend_bases import FigureCanvasBase, RendererBase
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.legend import Legend
from matplotlib.text import Text

__all__ = ["outside_canvas", "save_figure"]


class _Rendering(Protocol):
    """A canvas that draws (Agg's, which :func:`_with_canvas` gives a figure without one,
    and each interactive backend's): matplotlib types ``Figure.canvas`` as the base
    class, which has no ``get_renderer``."""

    def get_renderer(self) -> RendererBase: ...


def _with_canvas(fig: Figure) -> Figure:
    """``fig`` with an Agg canvas when it has none that renders (``Figure()`` built directly)."""
    if type(fig.canvas) is FigureCanvasBase:
        FigureCanvasAgg(fig)
    return fig


def save_figure(fig: Figure, path: Path, *, dpi: int = 110) -> Path:
    """Write ``fig`` to ``path`` (PNG by its suffix) with every label inside the canvas.

    A figure without a layout engine gets the constrained one; a figure that laid itself
    out (``layout="constrained"``, or ``tight_layout()`` with its own ``rect``, e.g. for a
    figure legend in a strip) keeps its layout. Returns ``path``.
    """
    _with_canvas(fig)
    if fig.get_layout_engine() is None:
        fig.set_layout_engine("constrained")
    fig.savefig(path, dpi=dpi)
    return Path(path)


def _tick_labels(fig: Figure) -> tuple[list[Text], set[Text]]:
    """The tick labels drawn (tick inside the view interval, axes on), and every tick label.

    An axis keeps tick objects beyond its view limits (not drawn, positions stale):
    they are left out of the check.
    """
    drawn: list[Text] = []
    every: set[Text] = set()
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            lo, hi = sorted(axis.get_view_interval())
            eps = 1e-9 * max(abs(hi - lo), 1.0)
            for tick in [*axis.get_major_ticks(), *axis.get_minor_ticks()]:
                labels = (tick.label1, tick.label2)
                every.update(labels)
                if ax.get_visible() and ax.axison and lo - eps <= tick.get_loc() <= hi + eps:
                    drawn.extend(t for t in labels if t.get_visible() and tick.get_visible())
    return drawn, every


def outside_canvas(fig: Figure, *, tolerance: float = 1.0) -> list[Artist]:
    """The visible text artists and legends of ``fig`` whose drawn extent leaves the canvas.

    ``fig`` is drawn first (its layout engine runs, as when it is saved). Checked: tick
    labels, axis labels, titles, suptitles, annotations and other texts, legends (each
    with its window extent in pixels against ``fig.bbox``, ``tolerance`` pixels of slack
    for rounding). Empty texts and those of hidden axes are skipped.
    """
    _with_canvas(fig)
    fig.draw_without_rendering()
    renderer = cast(_Rendering, fig.canvas).get_renderer()
    drawn, ticks = _tick_labels(fig)
    hidden = set()
    for ax in fig.axes:
        if not ax.get_visible() or not ax.axison:
            hidden.update(
                {ax.xaxis.label, ax.yaxis.label, ax.xaxis.offsetText, ax.yaxis.offsetText}
            )
        if not ax.get_visible():
            hidden.update(ax.findobj(Text))
    texts = [t for t in fig.findobj(Text) if t not in ticks and t not in hidden]
    texts = [t for t in texts if t.get_visible() and t.get_text().strip()]
    legends = [g for g in fig.findobj(Legend) if g.get_visible() and g not in hidden]
    box = fig.bbox
    out: list[Artist] = []
    for artist in [*drawn, *texts, *legends]:
        if isinstance(artist, Text) and not artist.get_text().strip():
            continue
        ext = artist.get_window_extent(renderer)
        if (
            ext.x0 < box.x0 - tolerance
            or ext.y0 < box.y0 - tolerance
            or ext.x1 > box.x1 + tolerance
            or ext.y1 > box.y1 + tolerance
        ):
            out.append(artist)
    return out
