"""The per-sweep JSON line of ``replay / live --filter ekf --json-lines``, fast.

:func:`json_line` is ``json.dumps(o.record())`` of a :class:`layoutkit.filter.tracker.FilterOutput`
``o``, byte for byte, without the generic encoder (the encoder and the record's arrays were ~15 µs of
a ~70 µs sweep in ``replay --filter ekf``): the record's values formatted into a fixed template,
floats by ``float.__repr__`` as the encoder spells finite ones. The record (keys, order, values) is
defined once, by ``FilterOutput.record``; this falls back to ``json.dumps(o.record())`` whenever a
value is not finite (json's NaN / Infinity spellings) or not of the usual type. Tested against
``json.dumps(record())`` in tests/test_filter.py.
"""
from __future__ import annotations

import json
import math
from json.encoder import encode_basestring_ascii as _esc

import numpy as np

from ..units import RAD2DEG
from .so3 import rotvec_floats

__all__ = ["json_line"]

#: The line: ``json.dumps`` of ``FilterOutput.record``'s
#: keys in its order, with json's separators.
_LINE = ('{"t": %r, "status": %s, "rotvec": [%r, %r, %r], "translation": [%r, %r, %r], '
         '"cov_rot_deg": [%r, %r, %r], "cov_pos_m": [%r, %r, %r], "station": %d, "axis": %d, "used": %d, '
         '"rejected": %d, "nis": %s, "dof": %d, "static": %s, "event": %s}')
#: the same with the smoother's mark (``FilterOutput.smoothed``)
_LINE_SMOOTHED = _LINE[:-1] + ', "smoothed": true}'
#: json's spelling of the usual status and event strings (others through the encoder's own escape)
_QUOTED = {k: _esc(k) for k in ("ok", "uncertain", "lost", "", "init")}


def json_line(o) -> str:
    """``json.dumps(o.record())`` of a FilterOutput ``o`` (see the module docstring)."""
    d = o.state_cov.diagonal().tolist()
    # np.sqrt of the diagonal, as record(): NaN for a negative variance (math.sqrt would raise)
    v0, v1, v2, v3, v4, v5 = d[0], d[1], d[2], d[6], d[7], d[8]
    if v0 >= 0.0 and v1 >= 0.0 and v2 >= 0.0 and v3 >= 0.0 and v4 >= 0.0 and v5 >= 0.0:
        sq = math.sqrt
        s0, s1, s2, s3, s4, s5 = sq(v0), sq(v1), sq(v2), sq(v3), sq(v4), sq(v5)
    else:
        return json.dumps(o.record())
    nis = o.nis
    station, axis, used, rejected, dof = o.station, o.axis, o.used, o.rejected, o.dof
    if not (type(o.status) is str and type(o.event) is str and type(o.static) is bool
            and type(station) is int and type(axis) is int and type(used) is int and type(rejected) is int
            and type(dof) is int and isinstance(nis, float) and isinstance(o.t, float)
            and type(o.smoothed) is bool):
        return json.dumps(o.record())
    fl = (o.t, *rotvec_floats(o.quaternion), *np.asarray(o.translation, float).tolist(),
          s0 * RAD2DEG, s1 * RAD2DEG, s2 * RAD2DEG, s3, s4, s5)
    if not math.isfinite(sum(fl)):  # a NaN / infinity among them (or an overflowing sum): json's spellings
        return json.dumps(o.record())
    nis_s = float.__repr__(nis) if math.isfinite(nis) else "null"
    # %r of a Python float is float.__repr__ (json's spelling of a finite float); t may be a numpy
    # float (json writes float.__repr__ of it too): float() keeps its value
    status, event = o.status, o.event
    return (_LINE_SMOOTHED if o.smoothed is True else _LINE) % (
        float(fl[0]), _QUOTED.get(status) or _esc(status), *fl[1:], station, axis, used, rejected, nis_s, dof,
        "true" if o.static else "false", _QUOTED.get(event) or _esc(event))
