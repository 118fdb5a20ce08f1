"""Orchestration with file I/O: what a command does, reusable by studies/."""
