"""One way to save a report picture: checked (title, labelled axes, caption) and written atomically.

``save_figure(fig, path, caption=...)`` adds the caption line (what is shown) under the figure,
refuses a figure without a title or with an unlabelled data axis (ValueError listing what is
missing: a report picture must say what it shows, in which units), writes the PNG through
:func:`layoutkit.io.atomic.atomic_write` (complete or not at all) and closes the figure.
``integer_ticks(ax)`` puts counts (lit sensors, k) on whole-number ticks.
"""
from __future__ import annotations

from pathlib import Path

__all__ = ["save_figure", "figure_problems", "integer_ticks", "layout_problems", "CAPTION_GID"]

CAPTION_GID = "layoutkit-caption"


def _has_content(ax) -> bool:
    return bool(ax.lines or ax.collections or ax.patches or ax.images)


def figure_problems(fig) -> list[str]:
    """What a report figure lacks: a title (suptitle or on every data axes), x/y labels on every
    rectilinear data axes that shows its axis (images and colour bars exempt), the caption line."""
    problems = []
    sup = fig._suptitle.get_text().strip() if getattr(fig, "_suptitle", None) is not None else ""
    data_axes = [a for a in fig.axes if _has_content(a) and not hasattr(a, "_colorbar")
                 and a.get_label() != "<colorbar>"]
    if not sup and (not data_axes or any(not a.get_title().strip() for a in data_axes)):
        problems.append("no title")
    for a in data_axes:
        if a.name != "rectilinear" or not a.axison or (a.images and not a.lines and not a.collections):
            continue
        for name in ("x", "y"):  # a shared axis is labelled once (on the bottom / left axes)
            sib = getattr(a, f"get_shared_{name}_axes")().get_siblings(a)
            if (getattr(a, f"{name}axis").get_visible() and getattr(a, f"get_{name}ticks")().size
                    and not any(getattr(b, f"get_{name}label")().strip() for b in sib)):
                problems.append(f"axes {a.get_title() or fig.axes.index(a)}: no {name} label")
    if not any(t.get_gid() == CAPTION_GID and t.get_text().strip() for t in fig.texts):
        problems.append("no caption line")
    return problems


def _texts(fig):
    """(name, text artist) of every visible, non-empty text the figure draws."""
    out = []
    for t in fig.texts:
        out.append(("caption" if t.get_gid() == CAPTION_GID else "figure text", t))
    if getattr(fig, "_suptitle", None) is not None:
        out.append(("suptitle", fig._suptitle))
    for i, a in enumerate(fig.axes):
        name = a.get_title() or a.get_label() or f"axes {i}"
        out += [(f"{name}: title", t) for t in (a.title, a._left_title, a._right_title)]
        if a.axison:
            out += [(f"{name}: x label", a.xaxis.label), (f"{name}: y label", a.yaxis.label)]
            for axis, tag in ((a.xaxis, "x tick"), (a.yaxis, "y tick")):
                lo, hi = sorted(axis.get_view_interval())
                for tick in axis.get_major_ticks():
                    if lo - 1e-9 * (hi - lo) <= tick.get_loc() <= hi + 1e-9 * (hi - lo):
                        out += [(f"{name}: {tag}", tick.label1), (f"{name}: {tag}", tick.label2)]
        out += [(f"{name}: text", t) for t in a.texts]
        leg = a.get_legend()
        if leg is not None:
            out += [(f"{name}: legend", t) for t in leg.get_texts()]
    return [(n, t) for n, t in out if t and t.get_visible() and t.get_text().strip()]


def layout_problems(fig, *, pad_px: float = 0.5) -> list[str]:
    """Overlaps a reader would see: text artists whose boxes intersect (titles, labels, tick labels,
    legends, captions, annotations; two tick labels of one axis included) and a data axes drawn over
    another (a colour bar over a panel). Draws the figure first. (Nothing is cut by the edge: report
    figures are saved with a tight bounding box.)
    Tick labels of the two axes of one axes meeting at its corner are not counted."""
    if fig.stale:  # layout and tick positions (not the pixels), unless known since the last change
        fig.draw_without_rendering()
    r = fig.canvas.get_renderer()
    boxes = [(n, t, t.get_window_extent(r).expanded(1.0, 1.0)) for n, t in _texts(fig)]
    problems = []
    for i in range(len(boxes)):
        ni, ti, bi = boxes[i]
        for j in range(i + 1, len(boxes)):
            nj, tj, bj = boxes[j]
            if ti is tj:
                continue
            ov_w = min(bi.x1, bj.x1) - max(bi.x0, bj.x0)
            ov_h = min(bi.y1, bj.y1) - max(bi.y0, bj.y0)
            if ov_w > pad_px and ov_h > pad_px:
                same_axes = ni.rsplit(":", 1)[0] == nj.rsplit(":", 1)[0]
                if same_axes and {ni.rsplit(": ", 1)[-1], nj.rsplit(": ", 1)[-1]} == {"x tick", "y tick"}:
                    continue
                problems.append(f"{ni} {ti.get_text()!r} overlaps {nj} {tj.get_text()!r}")
    axes = [a for a in fig.axes if a.get_visible() and a.axison]
    for i in range(len(axes)):
        for j in range(i + 1, len(axes)):
            a, b = axes[i].get_window_extent(r), axes[j].get_window_extent(r)
            if min(a.x1, b.x1) - max(a.x0, b.x0) > 2 and min(a.y1, b.y1) - max(a.y0, b.y0) > 2:
                inset = axes[i].get_label() == "inset" or axes[j].get_label() == "inset"
                if not inset:
                    problems.append(f"axes {axes[i].get_title() or axes[i].get_label() or i} and "
                                    f"{axes[j].get_title() or axes[j].get_label() or j} overlap")
    return problems


def integer_ticks(ax, axis: str = "y") -> None:
    """Whole-number ticks on ``axis`` ('x', 'y' or 'both') for counts."""
    from matplotlib.ticker import MaxNLocator

    for name in ("x", "y") if axis == "both" else (axis,):
        getattr(ax, f"{name}axis").set_major_locator(MaxNLocator(integer=True))


def _wrapped(caption: str, width_pt: float, fontsize: float) -> str:
    import textwrap

    chars = max(30, int(width_pt / (0.52 * fontsize)))
    return "\n".join(textwrap.wrap(caption, chars)) or caption


def _place_caption(fig, caption: str, fontsize: float = 7.0, pad_in: float = 0.08):
    """The caption line(s) under everything the figure draws: wrapped to the drawn width and put
    below the lowest artist. Returns the box to save (inches): everything drawn, the caption included,
    padded by ``pad_in`` — what ``bbox_inches="tight"`` would find, without the extra drawing pass
    savefig makes to find it (nothing is moved or cut)."""
    from matplotlib.transforms import Bbox

    fig.draw_without_rendering()  # the layout and tick positions, not the pixels
    r = fig.canvas.get_renderer()
    box = fig.get_tightbbox(r)  # inches
    y = (box.y0 * fig.dpi - 4.0) / fig.bbox.height
    x = max(box.x0 * fig.dpi, 0.0) / fig.bbox.width
    t = fig.text(x, y, _wrapped(caption, box.width * 72.0, fontsize), fontsize=fontsize, ha="left", va="top",
                 color="0.25", gid=CAPTION_GID)
    cap = t.get_window_extent(r).transformed(fig.dpi_scale_trans.inverted())
    fig.stale = False  # laid out: the caption's box comes from the renderer, nothing else moved since
    return Bbox.union([box, cap]).padded(pad_in)


def _reserve_caption(fig, caption: str, fontsize: float):
    """A picture of an exact pixel size: the caption at the bottom edge and a constrained layout of
    everything else in the rest (titles, colour bars and labels included)."""
    t = fig.text(0.01, 0.004, _wrapped(caption, fig.bbox.width * 72.0 / fig.dpi * 0.98, fontsize),
                 fontsize=fontsize, ha="left", va="bottom", color="0.25", gid=CAPTION_GID)
    fig.canvas.draw()
    frac = min(0.4, (t.get_window_extent(fig.canvas.get_renderer()).height + 6.0) / fig.bbox.height)
    engine = fig.get_layout_engine()
    if engine is not None and hasattr(engine, "set") and "rect" in engine.get():
        engine.set(rect=(0.0, frac, 1.0, 1.0 - frac))
    else:  # colour bars made without a layout engine cannot join one later: move the panels up
        fig.subplots_adjust(bottom=max(fig.subplotpars.bottom, frac + 0.02))
    fig.stale = True  # the layout moved (a layout engine's new rect does not say so itself)
    return t


def save_figure(fig, path, *, caption: str, dpi: int = 110, close: bool = True,
                size_px: tuple[int, int] | None = None, fontsize: float = 7.0) -> Path:
    """Add ``caption`` under ``fig``, check it (:func:`figure_problems`), write ``path`` atomically.

    The caption goes below the lowest artist and the picture is saved with a tight bounding box,
    so no axes are moved after a layout (a colour bar stays beside its panel) and no text is cut.
    ``size_px``: the picture must be exactly W × H pixels (a size the user asked for): the caption
    sits at the bottom edge and a constrained layout places the rest above it.
    Returns the path. Raises ValueError naming the file and what is missing."""
    from .atomic import atomic_write

    path = Path(path)
    if size_px is not None:
        _reserve_caption(fig, caption, fontsize)
        box = None
    else:  # laid out at the dpi it is saved at: text extents (hinted glyphs) depend on it
        fig.set_dpi(dpi)
        box = _place_caption(fig, caption, fontsize)
    problems = figure_problems(fig)
    if problems:
        import matplotlib.pyplot as plt

        plt.close(fig)
        raise ValueError(f"{path}: report figure is missing: {', '.join(problems)}")
    if size_px is None and fig.get_layout_engine() is not None:  # placed: the layout must not move it now
        fig.set_layout_engine("none")
    tight = {} if box is None else {"bbox_inches": box}
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format=path.suffix.lstrip(".") or "png", dpi=dpi, **tight)
    if close:
        import matplotlib.pyplot as plt

        plt.close(fig)
    return path
