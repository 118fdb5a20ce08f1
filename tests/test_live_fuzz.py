"""Fuzzing the decoders with damaged captures (hypothesis, test-sized; the >= 1e5-mutation run is
benchmarks/fuzz_live_decode.py).

Properties checked against the undamaged original (an independent record of every frame):
no exception; every intact frame decoded; resynchronised on the first intact frame after damage;
no damaged frame reported as good (CRC-32); the Bitcraze decoder never raises.
"""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from layoutkit.layout import load_layout
from layoutkit.live.protocols import bitcraze as bc
from layoutkit.live.protocols import get_protocol
from layoutkit.live.protocols.fuzzing import FuzzOutcome, check_layoutkit_decode, intact_frames, mutate
from layoutkit.live.protocols.layoutkit import MAGIC
from layoutkit.live.simulator import encode_frames, simulate_sweeps

_LAYOUT = load_layout("tests/data/chen_layout.json")
_SW = simulate_sweeps(_LAYOUT, duration=0.5, seed=1, dropout=0.1)
_FRAMES = encode_frames(_SW)
_DATA = b"".join(_FRAMES)
_MEAS = _SW.measured_angles()
_TRUTH = {int(_SW.seq[k]): (float(_SW.t[k]), int(_SW.station[k]), int(_SW.axis[k]), _MEAS[k]) for k in range(len(_FRAMES))}


def test_mutation_bookkeeping():
    """intact_frames: a flip inside frame 2 and an insertion inside frame 5 damage exactly them."""
    rng = np.random.default_rng(0)
    m = mutate(_DATA, rng, 0)
    spans = [(63 * k, 63 * (k + 1)) for k in range(len(_FRAMES))]
    assert intact_frames(m, spans).all()
    buf = bytearray(_DATA)
    buf[63 * 2 + 10] ^= 1
    org = np.arange(len(buf))
    damaged = np.zeros(len(buf), bool)
    damaged[63 * 2 + 10] = True
    buf[63 * 5 + 3:63 * 5 + 3] = b"xyz"
    org = np.concatenate([org[:63 * 5 + 3], [-1, -1, -1], org[63 * 5 + 3:]])
    from layoutkit.live.protocols.fuzzing import Mutation

    ok = intact_frames(Mutation(bytes(buf), org, damaged, ()), spans)
    assert np.flatnonzero(~ok).tolist() == [2, 5]


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 8))
def test_layoutkit_decoder_survives_mutations(seed, n):
    """Random bit flips, inserted/deleted runs and truncation: all properties hold."""
    rng = np.random.default_rng(seed)
    m = mutate(_DATA, rng, n, magic=MAGIC)
    outcome = FuzzOutcome()
    problems = check_layoutkit_decode(_DATA, _FRAMES, _TRUTH, m, rng, outcome, _LAYOUT.n)
    assert problems == []
    assert outcome.resync_next_intact == outcome.damage_events


def test_fuzz_many_runs_counts():
    """A few hundred runs: counters add up, nothing false reported good, every intact frame decoded."""
    rng = np.random.default_rng(42)
    outcome = FuzzOutcome()
    for _ in range(300):
        m = mutate(_DATA, rng, int(rng.integers(1, 6)), magic=MAGIC)
        check_layoutkit_decode(_DATA, _FRAMES, _TRUTH, m, rng, outcome, _LAYOUT.n)
    assert outcome.runs == 300 and outcome.n_mutations >= 300
    assert outcome.exceptions == outcome.false_good == outcome.decoder_errors == 0
    assert outcome.intact_decoded == outcome.intact > 0
    assert outcome.intact < outcome.frames  # the mutations did damage frames


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 8), st.sampled_from(["bitcraze-lh1", "bitcraze-lh2"]))
def test_bitcraze_decoder_never_raises(seed, n, name):
    """The deck stream has no checksum (a flipped bit can change an angle); the decoder must still
    never raise, and keep producing sweeps after damage."""
    rng = np.random.default_rng(seed)
    if name == "bitcraze-lh2":
        alpha = rng.uniform(-0.6, 0.6, (20, 1, 2)) + rng.uniform(-0.01, 0.01, (20, 4, 2))
        data, _, _ = bc.lh2_deck_stream(alpha, channel=2, sync_every=5)
    else:
        theta = np.deg2rad(rng.uniform(60, 120, (40, 1))) + rng.uniform(-0.01, 0.01, (40, 4))
        data, _, _ = bc.lh1_deck_stream(theta, sync_every_frames=10)
    m = mutate(data, rng, n, magic=bc.SYNC_FRAME[:2])
    dec = get_protocol(name)(n_sensors=4)
    p = 0
    while p < len(m.data):
        k = int(rng.integers(1, 100))
        for s in dec.feed(m.data[p:p + k]):
            assert s.angles.shape == (4,)
        p += k
    dec.flush()
    assert dec.stats.errors == 0
