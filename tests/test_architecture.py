"""The house rules of docs/architecture.md, checked on the source: the import tiers of the rooms,
no import of the CLI or the studies from below, no private names imported across rooms, and a
stated reason at the top of every module over 600 lines.

Proof kind: static analysis of every module's import statements (ast), so a violation anywhere in
the package fails with the module, line and the imported room.
"""
from __future__ import annotations

import ast
import re
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "layoutkit"

#: Room → tier (docs/architecture.md). A room may import rooms of a lower tier; within the core
#: (tier 1) rooms may import each other (no cycles: Python would fail); the data rooms (2.x) are
#: ordered among themselves.
TIERS = {
    "units": 0, "_validate": 0, "status": 0,
    "geometry": 1, "lighthouse": 1, "noise": 1, "joint": 1, "pnp": 1, "dop": 1, "dop_batch": 1,
    "simulate": 1, "visibility": 1, "quality": 1, "coverage_rule": 1, "filter": 1, "rotations": 1, "calibrate": 1,
    "parallel": 1, "montecarlo": 1,
    "io": 2.0, "_json": 2.1, "layout": 2.2, "shapes": 2.3, "envelope": 2.3, "mesh": 2.4, "candidates": 2.5,
    "importers": 2.6,
    "optimize": 3, "camera": 3, "render": 3, "live": 3,
    "workflows": 4,
    "studies": 5,
    "cli": 6,
    "__main__": 7,
}
#: Same-tier imports between different rooms that are part of the design.
ALLOWED_SIDEWAYS = {("camera", "render"),  # the synthetic camera renders with pyvista
                    ("live", "camera")}   # the live camera cross-check runs the camera room's solvers
SHARED_PRIVATE = {"_validate", "_json"}  # boundary-check helpers (and the old JSON shim) everyone may use


def _modules():
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(PKG.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
            pkg = parts
        else:
            pkg = parts[:-1]
        yield path, parts, pkg


def _imports(path, pkg):
    """(line, target module parts, imported names) of every layoutkit import in ``path``."""
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg[:len(pkg) - (node.level - 1)]
                target = base + (node.module.split(".") if node.module else [])
            else:
                target = (node.module or "").split(".")
            if target and target[0] == "layoutkit":
                yield node.lineno, target, [a.name for a in node.names], node.module is None
        elif isinstance(node, ast.Import):
            for a in node.names:
                t = a.name.split(".")
                if t[0] == "layoutkit":
                    yield node.lineno, t, [], False


def _room(parts):
    return parts[1] if len(parts) > 1 else "layoutkit"


def test_rooms_import_only_downwards():
    bad = []
    for path, parts, pkg in _modules():
        room = _room(parts)
        if room == "layoutkit" or room not in TIERS:
            continue  # the package's lazy __init__, or a room not yet on the map
        for line, target, names, from_pkg in _imports(path, pkg):
            targets = [target + [n] for n in names] if (from_pkg and len(target) == 1) else [target]
            for t in targets:
                other = _room(t)
                if other == room or other == "layoutkit":
                    continue
                if other not in TIERS:
                    if TIERS[room] <= 3:
                        bad.append(f"{path.relative_to(PKG.parent)}:{line}: {room} imports {other}, a room not on the map")
                    continue
                if TIERS[other] > TIERS[room] or (TIERS[other] == TIERS[room] and TIERS[room] > 1
                                                  and (room, other) not in ALLOWED_SIDEWAYS):
                    bad.append(f"{path.relative_to(PKG.parent)}:{line}: {room} (tier {TIERS[room]}) imports "
                               f"{other} (tier {TIERS[other]})")
    assert not bad, "\n".join(bad)


def test_no_private_names_across_rooms():
    bad = []
    for path, parts, pkg in _modules():
        room = _room(parts)
        for line, target, names, _ in _imports(path, pkg):
            if _room(target) == room:
                continue
            private = [n for n in names if n.startswith("_") and n not in SHARED_PRIVATE]
            private_mod = [p for p in target[1:] if p.startswith("_") and p not in SHARED_PRIVATE and p != "__init__"]
            if private or private_mod:
                bad.append(f"{path.relative_to(PKG.parent)}:{line}: imports {'.'.join(target)} {private}")
    assert not bad, "\n".join(bad)


def test_long_modules_state_their_reason():
    """A module over 600 lines says why at its top (its docstring gives its length and the reason)."""
    bad = []
    for path, _, _ in _modules():
        text = path.read_text()
        n = text.count("\n")
        if n <= 600:
            continue
        doc = ast.get_docstring(ast.parse(text)) or ""
        if not re.search(r"\d+ lines", doc):  # e.g. "Why one module of ~900 lines: ..."
            bad.append(f"{path.relative_to(PKG.parent)}: {n} lines and no reason stated in its docstring")
    assert not bad, "\n".join(bad)
