"""The ``layoutkit`` command: a thin click group.

Each room of the package contributes its commands from its own module here
(``commands = [...]``); those modules import only click at import time, heavy
libraries inside the command bodies. Commands parse, call one workflow, print.
"""
from __future__ import annotations

import click

from . import camera, core, fake, live, mesh, optimize, render


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(package_name="layoutkit")
def main():
    """Design and validate photodiode layouts for lighthouse (laser sweep) pose measurement.

    SI units inside; flags name their units (deg, arcsec, mm). Most commands take --json.
    """


for _mod in (core, mesh, render, optimize, live, fake, camera):
    for _cmd in _mod.commands:
        main.add_command(_cmd)
