"""CLI commands (core)."""
from __future__ import annotations

import click  # noqa: F401

commands: list = []
