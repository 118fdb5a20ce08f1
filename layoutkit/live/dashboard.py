"""Terminal dashboard of a live run (rich): rate, lit sensors, pose, ADOP/PDOP, precision against
prediction, error counters and the port's reconnect state. Renders the plain snapshot dict of
:meth:`layoutkit.live.session.LiveSession.snapshot`; holds no pipeline state itself.
"""
from __future__ import annotations

import numpy as np

from ..units import RAD2DEG as DEG, SIGMA_THETA_PAPER

__all__ = ["render_snapshot", "Dashboard"]


def _fmt(x, spec=".3f", none="–"):
    if x is None:
        return none
    try:
        if not np.isfinite(x):
            return none
    except TypeError:
        return str(x)
    return format(x, spec)


def render_snapshot(snap: dict):
    """A rich renderable (table) for one snapshot dict."""
    from rich.table import Table

    sig = snap.get("sigma_theta", SIGMA_THETA_PAPER)
    t = Table(title="layoutkit live", show_header=False, expand=False, min_width=60)
    t.add_column("item", style="bold cyan", no_wrap=True)
    t.add_column("value")
    t.add_row("rate", f"{_fmt(snap.get('rate_fps'), '.1f')} frames/s   (wall {_fmt(snap.get('wall_s'), '.1f')} s)")
    dec = snap.get("decode") or {}
    t.add_row("frames", f"good {snap.get('good', 0)}   bad {snap.get('bad', 0)}   "
                        f"too few lit {snap.get('too_few_lit', 0)}   unpaired sweeps {snap.get('unpaired_sweeps', 0)}")
    t.add_row("decoder", f"good {dec.get('good', 0)}   bad {dec.get('bad', 0)}   dropped {dec.get('dropped', 0)}   "
                         f"resyncs {dec.get('resyncs', 0)}   skipped bytes {dec.get('skipped_bytes', 0)}")
    last = snap.get("last")
    if last:
        rv = np.asarray(last["rotvec"], float)
        tr = np.asarray(last["translation"], float)
        t.add_row("lit sensors", f"{last['n_lit']}   (mean {_fmt(snap.get('mean_lit'), '.2f')})")
        t.add_row("pose t", f"{last['t']:.3f} s")
        t.add_row("rotation vector", f"[{rv[0]:+.4f} {rv[1]:+.4f} {rv[2]:+.4f}] rad  |{np.linalg.norm(rv) * DEG:.2f}°|")
        t.add_row("translation", f"[{tr[0]:+.4f} {tr[1]:+.4f} {tr[2]:+.4f}] m")
        t.add_row("ADOP / PDOP", f"{_fmt(last['adop'], '.1f')} deg/rad  {_fmt(last['pdop'], '.2f')} m/rad  → "
                                 f"σ {_fmt(last['adop'] * sig, '.3f')}°  {_fmt(last['pdop'] * sig * 1e3, '.2f')} mm")
        t.add_row("residual RMS", f"{_fmt(last['residual_rms'] / sig if last['residual_rms'] is not None else None, '.2f')} σθ")
    else:
        t.add_row("pose", "waiting for frames …")
    g = snap.get("static_group")
    if g:
        t.add_row("static precision", f"{_fmt(g['sigma_rot_deg'], '.3f')}° / {_fmt(g['sigma_trans_m'] * 1e3, '.2f')} mm "
                                      f"(pred {_fmt(g['predicted_rot_deg'], '.3f')}° / "
                                      f"{_fmt(g['predicted_trans_m'] * 1e3, '.2f')} mm, n={g['n']}, "
                                      f"groups {snap.get('static_groups', 0)})")
    else:
        t.add_row("static precision", "no static window yet")
    e = snap.get("truth")
    if e:
        t.add_row("error vs truth", f"RMS {_fmt(e['rms_rot_deg'], '.3f')}° / {_fmt(e['rms_trans_m'] * 1e3, '.2f')} mm "
                                    f"(pred {_fmt(e['predicted_rot_deg'], '.3f')}° / "
                                    f"{_fmt(e['predicted_trans_m'] * 1e3, '.2f')} mm, n={e['n']})")
    cam = snap.get("camera")
    if cam:
        t.add_row("camera", f"frames {cam.get('frames', 0)}   solved {cam.get('solved', 0)}   "
                            f"{cam.get('state', '')}" + (f"   error: {cam['error']}" if cam.get("error") else ""))
        last_c = cam.get("last")
        if cam.get("disagreement_rms_deg") is not None:
            flag = ""
            if last_c and last_c.get("mirror_branch"):
                flag = "   [red]mirror branch?[/]"
            elif last_c and last_c.get("face_on"):
                flag = "   [yellow]face-on (tilt sign weak)[/]"
            t.add_row("LH vs camera", f"last {_fmt(last_c and last_c['disagreement_deg'], '.3f')}° "
                                      f"(pred {_fmt(last_c and last_c['predicted_deg'], '.3f')}°)   RMS "
                                      f"{_fmt(cam['disagreement_rms_deg'], '.3f')}° (pred "
                                      f"{_fmt(cam.get('predicted_rms_deg'), '.3f')}°){flag}")
    src = snap.get("source")
    if src:
        state = "[green]connected[/]" if src.get("connected") else "[red]disconnected[/] (retrying)"
        t.add_row("port", f"{state}   connects {src.get('connects', 0)}   disconnects {src.get('disconnects', 0)}"
                          + (f"   last error: {src['last_error']}" if src.get("last_error") else ""))
    return t


class Dashboard:
    """``with Dashboard() as d: d.update(snapshot)`` — a rich ``Live`` display on standard error."""

    def __init__(self, refresh_per_second: float = 4.0):
        from rich.console import Console
        from rich.live import Live

        self._live = Live(render_snapshot({}), console=Console(stderr=True),
                          refresh_per_second=refresh_per_second, transient=False)

    def __enter__(self):
        self._live.__enter__()
        return self

    def update(self, snap: dict) -> None:
        self._live.update(render_snapshot(snap))

    def __exit__(self, *exc):
        return self._live.__exit__(*exc)
