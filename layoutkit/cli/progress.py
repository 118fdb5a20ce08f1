"""One progress bar for every long command (rich, on stderr): what is counted, done / total,
elapsed time and the estimated time left. Quiet (``--json``) runs show none."""
from __future__ import annotations


def progress_bar(what: str, *, quiet: bool = False, fields: str = "", transient: bool = True):
    """A :class:`rich.progress.Progress` (use as a context manager; ``add_task(what, total=N, **f)``).

    what : the counted unit ("frames", "cells"); fields : an extra text column with task fields
    (``"running {task.fields[running]}"``); quiet : no output at all."""
    from rich.console import Console
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    cols = [TextColumn(what), BarColumn(), MofNCompleteColumn()]
    if fields:
        cols.append(TextColumn(fields))
    cols += [TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn()]
    return Progress(*cols, console=Console(stderr=True), transient=transient, disable=quiet)
