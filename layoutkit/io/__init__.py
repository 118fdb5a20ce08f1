"""layoutkit's own file formats, one owner each (after OpenSfM's ``dataset.py``).

Each format layoutkit reads or writes (pose tables, frame tables, capture sidecars, stations
JSON, ...) is read and written in exactly one module of this package; other modules call these
functions and never parse or format the files themselves. Foreign formats (libsurvive
recordings, Crazyflie logs, device calibration dumps) are importers under
:mod:`layoutkit.importers` and produce these files.

Derived files are written atomically (:func:`layoutkit.io.atomic.atomic_write`): a temporary
file in the target folder, renamed over the target on success, so a failed write (disk full, a
signal) leaves no truncated output behind. Captures are the exception: they are raw bytes written
as they arrive and never overwritten (:mod:`layoutkit.live.capture`).
"""
