"""Readers of foreign formats, one module per format; each produces layoutkit's own files
(:mod:`layoutkit.io`): layout JSON, frame table, pose table, stations JSON, capture + sidecar.

- :mod:`.libsurvive` — libsurvive ``.rec`` / ``.rec.gz`` text recordings and their ``.json``
  lighthouse configuration (cntools/libsurvive ``src/survive_recording.c``);
- :mod:`.vive` — Vive / Index device calibration JSON (``lighthouse_config``);
- :mod:`.cfusdlog` — Crazyflie microSD event logs (bitcraze ``tools/usdlog/cfusdlog.py``).

Motion-capture reference tables (pose or position only; CSV or ``.npy``) are read by the one pose
reader, :func:`layoutkit.io.poses.read_reference`.

The angle and frame conventions that connect them to layoutkit's are derived in docs/real-data.md.
"""
