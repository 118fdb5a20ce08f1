"""The ``layoutkit`` command: a thin click group.

Each room of the package contributes its commands from its own module here
(``commands = [...]``); those modules import only click at import time, heavy
libraries inside the command bodies. Commands parse, call one workflow, print.
"""
from __future__ import annotations

import errno

import click

from . import camera, core, fake, importers, live, mesh, optimize, render, score
from ._common import fail


class _Group(click.Group):
    """The command group; a file that cannot be read or written (missing folder, permissions, disk
    full) ends with one ``error:`` line naming the file instead of a traceback."""

    def invoke(self, ctx):
        argv = [*getattr(ctx, "_protected_args", ()), *ctx.args]
        try:
            return super().invoke(ctx)
        except click.UsageError as exc:
            if "--json" in argv and "extra argument" in exc.message:  # the old `--json PATH` form
                exc.message += " (--json is a flag that prints JSON; write a file with --json-out FILE)"
            raise
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


for _mod in (core, mesh, render, optimize, score, live, fake, camera, importers):
    for _cmd in _mod.commands:
        main.add_command(_cmd)
