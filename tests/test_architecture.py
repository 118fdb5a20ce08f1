"""The house rules of docs/architecture.md, checked on the source: the import tiers of the rooms,
no import cycle between modules, no import of the CLI or the studies from below, no private names
imported across rooms, the rooms table of docs/architecture.md equal to the package, and a stated
(and current) reason at the top of every module over 600 lines.

Proof kind: static analysis of every module's import statements (ast) — top-level AND inside
functions, since an import inside a function still makes one module need another — so a violation
anywhere in the package fails with the module, line and the imported room; the import cycles are
the strongly connected components of the module graph (scipy.sparse.csgraph), reported as the
module path of one cycle each.

``python tests/test_architecture.py --write`` regenerates the rooms table in docs/architecture.md.
"""
from __future__ import annotations

import ast
import re
import sys
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest

PKG = Path(__file__).resolve().parents[1] / "layoutkit"
DOC = PKG.parent / "docs" / "architecture.md"

#: Room → tier (docs/architecture.md, whose rooms table is generated from this map). A room may
#: import rooms of a lower tier; the core rooms (tier 1) may import each other (the module graph
#: has no cycle: test_no_import_cycles); the data rooms (2.x) are ordered among themselves.
TIERS = {
    "units": 0, "_validate": 0, "status": 0, "resources": 0,
    "geometry": 1, "lighthouse": 1, "noise": 1, "pnp_result": 1, "lm_numba": 1, "pnp_numba": 1, "pnp_lh1": 1, "joint_numba": 1, "joint": 1,
    "pnp": 1,
    "dop": 1,
    "dop_batch": 1, "simulate": 1, "visibility": 1, "quality": 1, "coverage_rule": 1, "filter": 1, "rotations": 1,
    "calibrate": 1, "parallel": 1, "montecarlo": 1,
    "io": 2.0, "layout": 2.2, "shapes": 2.3, "envelope": 2.3, "mesh": 2.4, "candidates": 2.5,
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
SHARED_PRIVATE = {"_validate"}  # the boundary-check helper everyone may use
#: Import cycles being removed on other branches (issue 24 item 2): module set → owner. Each one is
#: a strict xfail below, so it turns into a failure (to drop the entry) the day the cycle is gone.
KNOWN_CYCLES = {
}
LONG_MODULE = 600       # lines; a longer module states why, with its length
STATED_LENGTH_TOL = 0.15  # the stated length may be off by this fraction (else it is stale)


# ------------------------------------------------------------------------------ the module graph

@lru_cache(maxsize=None)
def _modules():
    """Dotted module name → (path, package parts for relative imports), every module of the package."""
    out = {}
    for path in sorted(PKG.rglob("*.py")):
        parts = list(path.relative_to(PKG.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
            pkg = parts
        else:
            pkg = parts[:-1]
        out[".".join(parts)] = (path, tuple(pkg))
    return out


def _resolve(parts):
    """The module a dotted target names: itself, or the nearest enclosing module (``a.b.name``)."""
    mods = _modules()
    parts = list(parts)
    while parts and ".".join(parts) not in mods:
        parts = parts[:-1]
    return ".".join(parts)


def _imports(name):
    """(line, target parts, imported names, is ``from package import name``) of every layoutkit
    import in module ``name``, at any depth (module level, functions, methods, conditionals)."""
    path, pkg = _modules()[name]
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = list(pkg[:len(pkg) - (node.level - 1)])
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


@lru_cache(maxsize=None)
def _graph():
    """Module → {imported module: first line}: ``from pkg import sub`` points at the submodule."""
    mods = _modules()
    edges = {}
    for name in mods:
        out = edges.setdefault(name, {})
        for line, target, names, _ in _imports(name):
            subs = [target + [n] for n in names if ".".join(target + [n]) in mods]
            others = len(subs) < len(names) or not names
            for t in subs + ([target] if others else []):
                m = _resolve(t)
                if m and m != name:
                    out.setdefault(m, line)
    return edges


def _cycles():
    """The import cycles: one per strongly connected component of more than one module, as
    ``(frozenset of modules, [m0, m1, ..., m0] a cycle through them with lines)``."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import breadth_first_order, connected_components

    edges = _graph()
    names = sorted(edges)
    idx = {n: i for i, n in enumerate(names)}
    rows = [idx[a] for a, bs in edges.items() for b in bs]
    cols = [idx[b] for a, bs in edges.items() for b in bs]
    g = csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(names), len(names)))
    _, label = connected_components(g, directed=True, connection="strong")
    out = []
    for lab in np.unique(label):
        members = np.flatnonzero(label == lab)
        if members.size < 2:
            continue
        keep = np.zeros(len(names), bool)
        keep[members] = True
        sub = g.multiply(keep[:, None]).multiply(keep[None, :]).tocsr()
        start = members[0]
        # shortest path from start back to start: BFS from each successor of start
        best = None
        for nxt in sub[start].indices:
            order, pred = breadth_first_order(sub, nxt, directed=True, return_predecessors=True)
            if start not in order and nxt != start:
                continue
            path = [start]
            k = start
            while k != nxt:
                k = pred[k]
                path.append(k)
            path.append(start)
            path = path[::-1]
            if best is None or len(path) < len(best):
                best = path
        mods = [names[k] for k in best]
        steps = [f"{a} (line {edges[a][b]})" for a, b in zip(mods[:-1], mods[1:])] + [mods[-1]]
        out.append((frozenset(names[k] for k in members), " -> ".join(steps)))
    return out


def _room(parts):
    return parts[1] if len(parts) > 1 else "layoutkit"


# ------------------------------------------------------------------------------ the rules

def test_no_import_cycles():
    """No module needs itself through others, counting imports inside functions (a cycle hidden by
    a function-level import is still a cycle: the two modules cannot be understood or tested apart)."""
    bad = [path for members, path in _cycles() if members not in KNOWN_CYCLES]
    assert not bad, "import cycles:\n" + "\n".join(bad)


@pytest.mark.parametrize("cycle", sorted(KNOWN_CYCLES, key=sorted), ids=lambda c: "<->".join(sorted(c)))
def test_known_cycle_removed(cycle, request):
    request.applymarker(pytest.mark.xfail(strict=True, reason=f"being removed by {KNOWN_CYCLES[cycle]}; "
                                                                "drop its KNOWN_CYCLES entry when this passes"))
    assert cycle not in {members for members, _ in _cycles()}


def test_cycle_detector_finds_function_level_cycles(tmp_path, monkeypatch):
    """The detector itself: a two-module package whose only back edge sits inside a function."""
    pkg = tmp_path / "layoutkit"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from .b import g\n\ndef f():\n    return g()\n")
    (pkg / "b.py").write_text("def g():\n    from .a import f\n    return f\n")
    (pkg / "c.py").write_text("from . import a\n")
    monkeypatch.setattr(sys.modules[__name__], "PKG", pkg)
    for fn in (_modules, _graph):
        fn.cache_clear()
    try:
        cycles = _cycles()
    finally:
        for fn in (_modules, _graph):
            fn.cache_clear()
    assert [members for members, _ in cycles] == [frozenset({"layoutkit.a", "layoutkit.b"})]
    assert cycles[0][1] == "layoutkit.a (line 1) -> layoutkit.b (line 2) -> layoutkit.a"


def test_every_room_is_on_the_map():
    """Every top-level module and subpackage of layoutkit has a tier, and every tier names a room."""
    rooms = {_room(name.split(".")) for name in _modules()} - {"layoutkit"}
    assert rooms - set(TIERS) == set(), "rooms missing from TIERS (and docs/architecture.md)"
    assert set(TIERS) - rooms == set(), "TIERS names rooms that do not exist"


def test_rooms_import_only_downwards():
    bad = []
    for name in _modules():
        path, _ = _modules()[name]
        room = _room(name.split("."))
        if room == "layoutkit" or room not in TIERS:
            continue  # the package's lazy __init__; a room off the map fails test_every_room_is_on_the_map
        for line, target, names, from_pkg in _imports(name):
            targets = [target + [n] for n in names] if (from_pkg and len(target) == 1) else [target]
            for t in targets:
                other = _room(t)
                if other == room or other == "layoutkit":
                    continue
                if other not in TIERS:
                    bad.append(f"{path.relative_to(PKG.parent)}:{line}: {room} imports {other}, a room not on the map")
                    continue
                if TIERS[other] > TIERS[room] or (TIERS[other] == TIERS[room] and TIERS[room] > 1
                                                  and (room, other) not in ALLOWED_SIDEWAYS):
                    bad.append(f"{path.relative_to(PKG.parent)}:{line}: {room} (tier {TIERS[room]}) imports "
                               f"{other} (tier {TIERS[other]})")
    assert not bad, "\n".join(bad)


def test_no_private_names_across_rooms():
    bad = []
    for name, (path, _) in _modules().items():
        room = _room(name.split("."))
        for line, target, names, _ in _imports(name):
            if _room(target) == room:
                continue
            private = [n for n in names if n.startswith("_") and n not in SHARED_PRIVATE]
            private_mod = [p for p in target[1:] if p.startswith("_") and p not in SHARED_PRIVATE and p != "__init__"]
            if private or private_mod:
                bad.append(f"{path.relative_to(PKG.parent)}:{line}: imports {'.'.join(target)} {private}")
    assert not bad, "\n".join(bad)


def test_long_modules_state_their_reason():
    """A module over 600 lines says why at its top, with its length ("Why one module of ~900
    lines: ..."), and that length is current (within 15 %)."""
    bad = []
    for path, _ in _modules().values():
        text = path.read_text()
        n = text.count("\n")
        if n <= LONG_MODULE:
            continue
        doc = ast.get_docstring(ast.parse(text)) or ""
        m = re.search(r"(\d[\d,]*) lines", doc)
        if not m:
            bad.append(f"{path.relative_to(PKG.parent)}: {n} lines and no reason stated in its docstring")
        elif abs(int(m.group(1).replace(",", "")) - n) > STATED_LENGTH_TOL * n:
            bad.append(f"{path.relative_to(PKG.parent)}: {n} lines but its docstring says {m.group(0)} (stale)")
    assert not bad, "\n".join(bad)


# ------------------------------------------------------------------------------ the rooms table

_BEGIN = "<!-- rooms table: generated by `python tests/test_architecture.py --write`; do not edit -->"
_END = "<!-- end of rooms table -->"


def _summary(room):
    """First sentence of the room's module (or package ``__init__``) docstring, one line."""
    path = PKG / room / "__init__.py" if (PKG / room).is_dir() else PKG / f"{room}.py"
    doc = ast.get_docstring(ast.parse(path.read_text())) or ""
    para = " ".join(doc.split("\n\n")[0].split())
    text = re.split(r"\.\s+(?=[A-Z])", para + " ", maxsplit=1)[0].strip().rstrip(".")
    return text.replace("|", "\\|") or "(no docstring)"


def rooms_table():
    """The markdown rooms table: tier, room, kind (module or package) and its docstring's first sentence."""
    lines = [_BEGIN, "", "| tier | room | what it holds (its docstring) |", "|---|---|---|"]
    for room, tier in sorted(TIERS.items(), key=lambda kv: (kv[1], kv[0])):
        is_pkg = (PKG / room).is_dir()
        label = f"`{room}/`" if is_pkg else f"`{room}`"
        lines.append(f"| {tier:g} | {label} | {_summary(room)} |")
    lines += ["", _END]
    return "\n".join(lines)


def _doc_block(text):
    i, j = text.find(_BEGIN), text.find(_END)
    return None if i < 0 or j < 0 else text[i:j + len(_END)]


def test_architecture_doc_rooms_table_is_current():
    """docs/architecture.md lists every room with the tier of TIERS (its table is regenerated from
    the package; a new room, a changed tier or a changed docstring needs ``--write``)."""
    block = _doc_block(DOC.read_text())
    assert block is not None, f"{DOC}: no generated rooms table (markers missing)"
    assert block == rooms_table(), (f"{DOC}: the rooms table is stale; run "
                                    "`python tests/test_architecture.py --write`")
    assert not re.search(r"~\d+ lines|\b\d+-line", DOC.read_text()), f"{DOC}: module line counts go stale; state none"


if __name__ == "__main__":
    if sys.argv[1:] == ["--write"]:
        text = DOC.read_text()
        old = _doc_block(text)
        if old is None:
            sys.exit(f"{DOC}: add the two marker lines first:\n{_BEGIN}\n{_END}")
        DOC.write_text(text.replace(old, rooms_table()))
        print(f"wrote the rooms table of {DOC}")
    else:
        print(rooms_table())
