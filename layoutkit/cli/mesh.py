"""CLI commands (mesh)."""
from __future__ import annotations

import click  # noqa: F401

commands: list = []
