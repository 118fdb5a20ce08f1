"""Smoothed vs causal error on the same outputs (move/log00..04): the sweep outputs ok in both
``replay --filter ekf --imu`` and ``--smooth`` (matched by time and station), each series in its own motion-capture
alignment; all of them and those in one-station 100 ms intervals:

    python studies/bitcraze_live/smooth_paired.py log00 log01 log02 log03 log04 > studies/bitcraze_live/smooth_paired.jsonl

run from the repository root after studies/bitcraze_live/run.py (its calibration/stations_refined.json)."""
import json
import os
import sys

import numpy as np
sys.path.insert(0,'.'); sys.path.insert(0,'studies/bitcraze_live')
import run as R
from layoutkit.studies.bitcraze_dataset import align_to_mocap, firmware_series
D=os.path.expanduser(os.environ.get('BITCRAZE_MOVE', '~/.cache/layoutkit-realdata/bitcraze/lh2_crossingBeam_move/'))
st='studies/bitcraze_live/calibration/stations_refined.json'
for log in sys.argv[1:]:
    fw=firmware_series(D+log); on,off=fw['markers']; mc=np.load(D+'mocap'+log[-2:]+'.npy')
    out={}
    for sm in (False, True):
        s,F,w=R.replay(D+log, D+'system-config.yaml', stations=st, filt=True, imu=True, smooth=sm or None)
        ok=F['status']=='ok'; tf,pf=F['t'][ok],F['p'][ok]
        al=align_to_mocap(tf,pf,mc,on,off)
        e=R.errors_by_alignment(al,mc,on,off,tf,pf,tf,pf)
        k,ns=R._interval_stations(F,on,off)
        one=np.zeros(len(tf),bool); kk=k[ok]; one[kk>=0]=ns[kk[kk>=0]]==1
        out[sm]={(round(t,9),int(s_)):(ee,o1) for t,s_,ee,o1 in zip(tf,F['station'][ok],e,one)}
    common=[key for key in out[False] if key in out[True] and np.isfinite(out[False][key][0]) and np.isfinite(out[True][key][0])]
    ec=np.array([out[False][k][0] for k in common]); es=np.array([out[True][k][0] for k in common]); o1=np.array([out[False][k][1] for k in common])
    r=lambda x: round(float(np.sqrt(np.mean(x**2)))*1e3,2)
    print(json.dumps({'log':log,'both_ok':len(common),'rms_causal_mm':r(ec),'rms_smoothed_mm':r(es),'one_station_n':int(o1.sum()),'one_station_causal_mm':r(ec[o1]) if o1.any() else None,'one_station_smoothed_mm':r(es[o1]) if o1.any() else None}), flush=True)
