"""layoutkit.live.stopping: real signals raised in this process (proof by the signal itself, no mock)."""
import signal

from layoutkit.live.stopping import stop_on_signals


def test_first_stop_signal_is_recorded_and_announced_once_and_handlers_are_restored():
    before = signal.getsignal(signal.SIGTERM)
    heard = []
    with stop_on_signals(on_request=heard.append) as stop:
        assert not stop.requested
        signal.raise_signal(signal.SIGTERM)
        assert stop.requested and stop.name == "SIGTERM" and heard == ["SIGTERM"]
        signal.raise_signal(signal.SIGTERM)  # a second stop signal: the first one wins, no second call
        assert stop.signum == signal.SIGTERM and heard == ["SIGTERM"]
    assert signal.getsignal(signal.SIGTERM) is before


def test_request_by_hand_announces_like_a_signal():
    heard = []
    with stop_on_signals(on_request=heard.append) as stop:
        stop.request(signal.SIGTERM)
        stop.request(signal.SIGINT)
    assert stop.name == "SIGTERM" and heard == ["SIGTERM"]
