"""Small helpers shared by CLI modules: JSON output and error reporting."""
from __future__ import annotations

import json
import sys

import click
import numpy as np


def to_jsonable(o):
    """Recursively convert numpy values to plain Python for ``json.dumps``; inf/nan → None."""
    if isinstance(o, dict):
        return {str(k): to_jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [to_jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return to_jsonable(o.tolist())
    if isinstance(o, (np.floating, float)):
        v = float(o)
        return v if np.isfinite(v) else None
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    return o


def echo_json(obj, path=None) -> None:
    """Write ``obj`` as JSON to ``path`` ('-' or None: standard output)."""
    text = json.dumps(to_jsonable(obj), indent=2)
    if path in (None, "-"):
        click.echo(text)
    else:
        with open(path, "w") as fh:
            fh.write(text + "\n")


def fail(message: str, code: int = 2):
    """Print a clear error (no traceback) and exit with ``code``."""
    click.secho(f"error: {message}", fg="red", err=True)
    sys.exit(code)
