"""Write the shipped models of layoutkit.shapes to models/ (run from the repository root).

    .venv/bin/python models/build_models.py

Outputs (metres, body frame): chen_target.stl + chen_target.layout.json (the 12-sensor
reconstruction, with the mesh hash), zhai_target.glb/.stl, cubesat_3u.glb/.ply,
docking_target.glb/.stl, camera_frames/ (three synthetic 1292 x 964 camera frames of the Zhai
target for `layoutkit camera-attitude`, with truth.csv). GLB files keep the named parts as scene nodes. Deterministic: running it
again gives the same files.
"""
from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

from layoutkit import shapes
from layoutkit.layout import save_layout
from layoutkit.mesh import load_mesh, mesh_hash, save_mesh

OUT = Path(__file__).resolve().parent


def main(out: Path = OUT) -> list:
    out.mkdir(parents=True, exist_ok=True)
    written = []
    mesh, layout = shapes.chen_target()
    save_mesh(mesh, out / "chen_target.stl")
    back = load_mesh(out / "chen_target.stl")  # hash of what a user reading the file gets
    layout = replace(layout, metadata={**layout.metadata, "mesh": "chen_target.stl", "mesh_sha256": mesh_hash(back)})
    save_layout(layout, out / "chen_target.layout.json")
    written += ["chen_target.stl", "chen_target.layout.json"]
    for name, builder, formats in (("zhai_target", shapes.zhai_target, ("glb", "stl")),
                                   ("cubesat_3u", shapes.cubesat_3u, ("glb", "ply")),
                                   ("docking_target", shapes.docking_target, ("glb", "stl"))):
        mesh = builder()
        for fmt in formats:
            save_mesh(mesh, out / f"{name}.{fmt}")
            written.append(f"{name}.{fmt}")
    try:  # a few synthetic camera frames for `layoutkit camera-attitude` (needs off-screen rendering)
        from layoutkit.studies.zhai2014 import write_example_frames

        written += [str(p.relative_to(out)) for p in write_example_frames(out / "camera_frames")]
    except Exception as exc:  # noqa: BLE001 - no EGL/OSMesa here: the meshes are still written
        print(f"note: camera frames skipped ({type(exc).__name__}: {exc})", file=sys.stderr)
    return written


if __name__ == "__main__":
    for f in main(Path(sys.argv[1]) if len(sys.argv) > 1 else OUT):
        print(f)
