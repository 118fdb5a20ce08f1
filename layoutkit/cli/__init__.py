"""The ``layoutkit`` command: a thin click group.

Each room of the package contributes its commands from its own module here
(``commands = [...]``); those modules import only click at import time, heavy
libraries inside the command bodies. Commands parse, call one workflow, print.
"""
from __future__ import annotations

import errno
import warnings

import click

from . import calibrate, camera, core, distributed, fake, importers, live, mesh, optimize, render, score
from ._common import fail
from .options import finite_types


def _show_warning(message, category, filename, lineno, file=None, line=None, _default=warnings.showwarning):
    """Input warnings (unknown keys, odd sizes, mesh checks) as one ``warning:`` line on stderr."""
    from .._validate import OddSizeWarning, ValidationWarning

    if issubclass(category, (ValidationWarning, OddSizeWarning)) or category.__name__.startswith("Mesh"):
        click.secho(f"warning: {message}", fg="yellow", err=True)
    else:
        _default(message, category, filename, lineno, file, line)


def _allow_odd_size(ctx, param, value):
    from .._validate import OddSizeWarning

    if value:  # inside the group's warnings context: only this run
        warnings.simplefilter("default", OddSizeWarning)
    return value


def _add_allow_odd_size(cmd) -> None:
    """Every command (recursively) gets ``--allow-odd-size``: a size that says the length unit is
    wrong (a layout or mesh far smaller than 1 cm or larger than 100 m) stops the command with an
    error unless it is given; commands that declare the flag themselves keep theirs."""
    if isinstance(cmd, click.Group):
        for sub in cmd.commands.values():
            _add_allow_odd_size(sub)
        return
    if any("--allow-odd-size" in getattr(p, "opts", ()) for p in cmd.params):
        return
    cmd.params.append(click.Option(["--allow-odd-size"], is_flag=True, expose_value=False, callback=_allow_odd_size,
                                   help="Go on although a layout's or mesh's size says its length unit is wrong."))


class _Group(click.Group):
    """The command group; a refused option or argument (click's usage errors, NaN or infinity in a
    number: :func:`.options.finite_types`) ends with ``error:`` naming it and exit 2; a file that
    cannot be read or written (missing folder, permissions, disk full) ends with one ``error:``
    line naming the file instead of a traceback. A layout or mesh
    whose size says its unit is wrong ends with one ``error:`` line unless ``--allow-odd-size``."""

    def invoke(self, ctx):
        from .._validate import OddSizeWarning

        argv = [*getattr(ctx, "_protected_args", ()), *ctx.args]
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            warnings.simplefilter("error", OddSizeWarning)
            try:
                return super().invoke(ctx)
            except OddSizeWarning as exc:
                fail(f"{exc}; give the right unit (the file's \"units\" / --units), or --allow-odd-size to go on")
            except click.UsageError as exc:
                if "--json" in argv and "extra argument" in exc.message:  # the old `--json PATH` form
                    exc.message += " (--json is a flag that prints JSON; write a file with --json-out FILE)"
                hint = f"\n  (see '{exc.ctx.command_path} --help')" if exc.ctx is not None else ""
                fail(exc.format_message() + hint, exc.exit_code)
            except OSError as exc:
                if isinstance(exc, BrokenPipeError) or exc.errno == errno.EPIPE:
                    raise  # click ends quietly on a closed pipe
                what = exc.strerror or str(exc)
                fail(f"{exc.filename}: {what}" if exc.filename else what)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(package_name="layoutkit")
def main():
    """Design and validate photodiode layouts for lighthouse (laser sweep) pose measurement.

    SI units inside; flags name their units (deg, arcsec, mm). Most commands take --json.
    """


for _mod in (core, mesh, render, optimize, score, live, fake, camera, importers, calibrate, distributed):
    for _cmd in _mod.commands:
        _add_allow_odd_size(_cmd)
        finite_types(_cmd)
        main.add_command(_cmd)
