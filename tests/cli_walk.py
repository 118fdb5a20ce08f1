"""Every leaf command of ``layoutkit``, walked from the click group, so that each CLI-wide test
(fuzz, required options, file fuzz) covers a new command without a line of its own."""
from __future__ import annotations

import click


def leaf_commands(cmd=None, path=()):
    """Yield ``(path tuple, click.Command)`` for every command that is not a group, in name order."""
    if cmd is None:
        from layoutkit.cli import main as cmd
    if isinstance(cmd, click.Group):
        for name, sub in sorted(cmd.commands.items()):
            yield from leaf_commands(sub, path + (name,))
    else:
        yield path, cmd
