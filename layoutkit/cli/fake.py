"""CLI commands (fake-fpga hardware simulator)."""
from __future__ import annotations

import click  # noqa: F401

commands: list = []
