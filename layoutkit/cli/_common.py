"""Small helpers shared by CLI modules: JSON output and error reporting."""
from __future__ import annotations

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


def fail(message: str, code: int = 2):
    """Print a clear error (no traceback) and exit with ``code``."""
    click.secho(f"error: {message}", fg="red", err=True)
    sys.exit(code)
