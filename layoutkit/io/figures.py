"""One way to save a report picture: checked (title, labelled axes, caption) and written atomically.

``save_figure(fig, path, caption=...)`` adds the caption line (what is shown) under the figure,
refuses a figure without a title or with an unlabelled data axis (ValueError listing what is
missing: a report picture must say what it shows, in which units), writes the PNG through
:func:`layoutkit.io.atomic.atomic_write` (complete or not at all) and closes the figure.
``integer_ticks(ax)`` puts counts (lit sensors, k) on whole-number ticks.
"""
from __future__ import annotations

from pathlib import Path

__all__ = ["save_figure", "figure_problems", "integer_ticks", "CAPTION_GID"]

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


def integer_ticks(ax, axis: str = "y") -> None:
    """Whole-number ticks on ``axis`` ('x', 'y' or 'both') for counts."""
    from matplotlib.ticker import MaxNLocator

    for name in ("x", "y") if axis == "both" else (axis,):
        getattr(ax, f"{name}axis").set_major_locator(MaxNLocator(integer=True))


def save_figure(fig, path, *, caption: str, dpi: int = 110, close: bool = True) -> Path:
    """Add ``caption`` under ``fig``, check it (:func:`figure_problems`), write ``path`` atomically.

    Returns the path. Raises ValueError naming the file and what is missing."""
    from .atomic import atomic_write

    path = Path(path)
    fig.text(0.01, 0.003, caption, fontsize=7, ha="left", va="bottom", color="0.25", gid=CAPTION_GID, wrap=True)
    problems = figure_problems(fig)
    if problems:
        import matplotlib.pyplot as plt

        plt.close(fig)
        raise ValueError(f"{path}: report figure is missing: {', '.join(problems)}")
    if fig.get_layout_engine() is None:  # room for the caption line
        fig.subplots_adjust(bottom=max(fig.subplotpars.bottom, 0.12))
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format=path.suffix.lstrip(".") or "png", dpi=dpi)
    if close:
        import matplotlib.pyplot as plt

        plt.close(fig)
    return path
