"""Small helpers shared by CLI modules: JSON output and error reporting."""
from __future__ import annotations

import contextlib
import json
import sys

import click


def echo_json(obj, path=None) -> None:
    """Write ``obj`` as JSON to ``path`` ('-' or None: standard output)."""
    from ..io.jsonfile import to_jsonable  # numpy, imported when output is written

    text = json.dumps(to_jsonable(obj), indent=2)
    if path in (None, "-"):
        click.echo(text)
    else:
        from ..io.atomic import atomic_write_text

        atomic_write_text(path, text + "\n")


def emit_json(obj, as_json: bool, json_out=None) -> bool:
    """The ``--json`` / ``--json-out FILE`` pair: write ``obj`` to ``json_out`` (a file, or '-' for
    stdout) and/or print it with ``--json``. True when JSON went to stdout (print nothing else)."""
    if json_out:
        echo_json(obj, json_out)
    if as_json:
        echo_json(obj)
    return bool(as_json or json_out == "-")


def fail(message: str, code: int = 2):
    """Print a clear error (no traceback) and exit with ``code``."""
    click.secho(f"error: {message}", fg="red", err=True)
    sys.exit(code)


@contextlib.contextmanager
def bad_input(prefix: str = ""):
    """Inside the block, a ``ValueError`` (bad input, named by the code that raised it: file, field,
    option) becomes one ``error: <prefix><message>`` line and exit 2 instead of a traceback."""
    try:
        yield
    except ValueError as exc:
        fail(f"{prefix}{exc}")


def call_or_fail(fn, *args, **kwargs):
    """``fn(*args, **kwargs)`` under :func:`bad_input`."""
    with bad_input():
        return fn(*args, **kwargs)


def refuse_existing(path, overwrite: bool, what: str) -> None:
    """End with exit 2 when ``path`` exists and ``--overwrite`` was not given: a derived file of an
    earlier run (``what`` says what it holds) is never replaced silently (issue 29)."""
    from pathlib import Path

    if Path(path).exists() and not overwrite:
        fail(f"{path}: already exists ({what}); give --overwrite to replace it, or another --out")
