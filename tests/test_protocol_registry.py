"""The protocol registry: one symmetric entry per protocol, used by simulator, fake-fpga, replay, live.

Proof kind: round trip through the registry API only (simulated sweeps → ``entry.encode`` →
``entry.make_decoder(stations)`` → angles equal to the simulator's quantised angles within the
protocol's clock tick), for every protocol that has an encoder; the decoder options follow the
station set-up (a non-default rotor speed decodes right only when taken from the stations).
"""
import numpy as np
import pytest

from layoutkit.lighthouse import Station
from layoutkit.live.protocols import ENCODERS, PROTOCOLS, ProtocolEntry, get_protocol, protocol_entry
from layoutkit.live.simulator import simulate_sweeps
from layoutkit.shapes import chen_target

TICK = {"layoutkit": 1e-12, "bitcraze-lh1": np.pi / 400000 + 1e-12}  # exact ticks / half a 24 MHz tick


def test_entries_are_named_and_complete():
    assert set(PROTOCOLS) == {"layoutkit", "bitcraze-lh1", "bitcraze-lh2"}
    for name, e in PROTOCOLS.items():
        assert isinstance(e, ProtocolEntry) and e.name == name and e.description
        assert get_protocol(name) is e.decoder
    assert set(ENCODERS) == set(TICK)
    with pytest.raises(ValueError, match=r"^protocol bitcraze-lh2: layoutkit cannot emit this protocol"):
        PROTOCOLS["bitcraze-lh2"].encode(None)
    with pytest.raises(ValueError, match=r"^protocol: expected one of \['bitcraze-lh1', 'bitcraze-lh2', 'layoutkit'\], got 'nmea'$"):
        protocol_entry("nmea")


@pytest.mark.parametrize("name", sorted(ENCODERS))
def test_encode_decode_round_trip_through_the_entry(name):
    lay = chen_target()[1].subset([0, 1, 2, 3])
    e = PROTOCOLS[name]
    sw = simulate_sweeps(lay, duration=2.0, seed=3)
    frames = e.encode(sw)
    assert len(frames) == len(sw.t)
    dec = e.make_decoder(lay.n, sw.stations)
    out = [m for f in frames if f is not None for m in dec.feed(f)] + dec.flush()
    t = np.array([m.t for m in out])
    k = np.searchsorted(sw.t, t - 1e-6)
    np.testing.assert_allclose(t, sw.t[k], atol=1e-8)
    assert len(out) >= len(sw.t) - 2  # the deck loses the first sweep of each axis (no period yet)
    want = np.where(sw.emitted[:, None], sw.measured_angles(), np.nan)[k]
    got = np.array([m.angles for m in out])
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(got, want, atol=TICK[name])


def test_decoder_options_come_from_the_stations():
    """A 3000 rpm LH1 station: decoded with the station's options the angles are right; with the
    decoder's 3600 rpm default they are 20 % off (so the options are really used)."""
    lay = chen_target()[1]
    st = Station(rotor_rpm=3000.0)
    sw = simulate_sweeps(lay, duration=0.5, seed=1, stations=[st])
    e = PROTOCOLS["layoutkit"]
    assert e.options([st], lay.n) == {"n_sensors": lay.n, "rotor_rpm": 3000.0, "clock_hz": 50e6}
    data = b"".join(f for f in e.encode(sw) if f is not None)
    for dec, ok in ((e.make_decoder(lay.n, [st]), True), (e.make_decoder(lay.n), False)):
        got = np.array([m.angles for m in dec.feed(data)])
        want = sw.measured_angles()[sw.emitted]
        assert np.allclose(got, want, atol=1e-12, equal_nan=True) is ok
