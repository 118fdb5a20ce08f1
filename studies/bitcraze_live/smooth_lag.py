"""The smoother's lag on move/log01 and log00 (the lag choice of docs/filter.md, "Offline smoothing"):

    python studies/bitcraze_live/smooth_lag.py 0.5,1.0,1.5,3.0 log01 log00 > studies/bitcraze_live/smooth_lag.jsonl

run from the repository root after studies/bitcraze_live/run.py (its calibration/stations_refined.json);
one JSON line per log and lag: 100 ms coverage, RMS / max error vs motion capture of the ok outputs, the
ok outputs in one-station intervals, the largest buffer (steps), filter CPU s and replay wall s."""
import json
import os
import sys

import numpy as np
sys.path.insert(0, '.'); sys.path.insert(0, 'studies/bitcraze_live')
import run as R
from layoutkit.filter.smoother import SmootherConfig
from layoutkit.studies.bitcraze_dataset import coverage, align_to_mocap, firmware_series
D = os.path.expanduser(os.environ.get('BITCRAZE_MOVE', '~/.cache/layoutkit-realdata/bitcraze/lh2_crossingBeam_move/'))
st = 'studies/bitcraze_live/calibration/stations_refined.json'
for log in sys.argv[2:]:
    fw = firmware_series(D + log); on, off = fw['markers']
    mc = np.load(D + 'mocap' + log[-2:] + '.npy')
    for lag in [float(x) for x in sys.argv[1].split(',')]:
        s, F, wall = R.replay(D + log, D + 'system-config.yaml', stations=st, filt=True, imu=True,
                              smooth=SmootherConfig(lag_s=lag))
        ok = F['status'] == 'ok'; tf, pf = F['t'][ok], F['p'][ok]
        al = align_to_mocap(tf, pf, mc, on, off)
        e = R.errors_by_alignment(al, mc, on, off, tf, pf, tf, pf)
        one = R.ok_errors_by_interval_stations(F, e, on, off)['1_station']
        sm = s['filter']['smoother']
        print(json.dumps({'log': log, 'lag_s': lag, 'coverage': round(coverage(tf, on, off), 4), 'rms_mm': R.mm(al['rms_m']),
                          'max_mm': R.mm(al['max_m']), 'one_station': one, 'max_buffer': sm['max_buffer'],
                          'filter_cpu_s': round(s['filter']['filter_cpu_seconds'], 2), 'wall_s': round(wall, 1)}), flush=True)
