"""Mutation fuzzing of decoders: damage a valid byte stream, decode it, check what must hold.

Used by ``tests/test_live_fuzz.py`` (hypothesis, test-sized) and
``benchmarks/fuzz_live_decode.py`` (>= 1e5 mutations). Mutations: bit flips, inserted runs of
random bytes (sometimes starting with the frame magic, to fake a frame start), deleted runs and
truncation. Every byte of the damaged stream remembers which original byte it is (or -1 for
inserted bytes), so an original frame is *intact* iff all its bytes survive, untouched and
still adjacent.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Mutation", "mutate", "intact_frames", "check_layoutkit_decode", "FuzzOutcome"]

KINDS = ("bitflip", "insert", "delete", "truncate")


@dataclass(frozen=True)
class Mutation:
    """A damaged copy of a stream: ``data``; ``origin[i]`` = original index of byte i or -1;
    ``damaged[j]`` = original byte j was flipped or deleted; ``kinds`` applied, in order."""

    data: bytes
    origin: np.ndarray
    damaged: np.ndarray
    kinds: tuple


def mutate(data: bytes, rng: np.random.Generator, n: int, *, magic: bytes = b"", max_run: int = 64,
           kinds=KINDS) -> Mutation:
    """Apply ``n`` random mutations (kinds drawn uniformly from ``kinds``; truncation at most once,
    applied last)."""
    buf = np.frombuffer(data, np.uint8).copy()
    org = np.arange(len(buf), dtype=np.int64)
    damaged = np.zeros(len(buf), bool)
    done = []
    trunc = False
    for _ in range(n):
        kind = kinds[int(rng.integers(len(kinds)))]
        L = len(buf)
        if kind == "truncate":
            trunc = True
            done.append(kind)
            continue
        if kind == "bitflip" and L:
            p = int(rng.integers(L))
            buf[p] ^= np.uint8(1 << int(rng.integers(8)))
            if org[p] >= 0:
                damaged[org[p]] = True
        elif kind == "insert":
            p = int(rng.integers(L + 1))
            run = rng.integers(0, 256, int(rng.integers(1, max_run + 1)), dtype=np.uint8)
            if magic and rng.random() < 0.3:
                run = np.concatenate([np.frombuffer(magic, np.uint8), run])
            buf = np.concatenate([buf[:p], run, buf[p:]])
            org = np.concatenate([org[:p], np.full(len(run), -1, np.int64), org[p:]])
        elif kind == "delete" and L:
            p = int(rng.integers(L))
            k = int(rng.integers(1, max_run + 1))
            gone = org[p:p + k]
            damaged[gone[gone >= 0]] = True
            buf = np.concatenate([buf[:p], buf[p + k:]])
            org = np.concatenate([org[:p], org[p + k:]])
        else:
            continue
        done.append(kind)
    if trunc and len(buf):
        p = int(rng.integers(len(buf)))
        gone = org[p:]
        damaged[gone[gone >= 0]] = True
        buf, org = buf[:p], org[:p]
    return Mutation(buf.tobytes(), org, damaged, tuple(done))


def intact_frames(m: Mutation, spans) -> np.ndarray:
    """(K,) bool: which original frames ``spans`` [(start, end), ...] survive intact in ``m``."""
    spans = np.asarray(spans, np.int64).reshape(-1, 2)
    inv = np.full(len(m.damaged) + 1, -1, np.int64)
    ok = m.origin >= 0
    inv[m.origin[ok]] = np.flatnonzero(ok)
    # a frame is intact iff none of its bytes was damaged or deleted and its first and last bytes
    # are exactly (length - 1) apart (nothing inserted in between)
    bad = np.concatenate([[0], np.cumsum(m.damaged | (inv[:-1] < 0))])
    s, e = spans[:, 0], spans[:, 1]
    clean = bad[e] - bad[s] == 0
    return clean & (inv[e - 1] - inv[s] == e - s - 1)


@dataclass
class FuzzOutcome:
    """Counts from one or many fuzz runs."""

    runs: int = 0
    mutations: dict = field(default_factory=lambda: {k: 0 for k in KINDS})
    frames: int = 0
    intact: int = 0
    intact_decoded: int = 0
    damaged_decoded_equal: int = 0  # a damaged frame decoded to exactly its original content
    false_good: int = 0  # decoded content that matches no original frame (must stay 0)
    exceptions: int = 0
    decoder_errors: int = 0
    damage_events: int = 0
    resync_next_intact: int = 0  # damage events whose next intact frame was decoded

    @property
    def n_mutations(self) -> int:
        return int(sum(self.mutations.values()))

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        d["n_mutations"] = self.n_mutations
        return d


def check_layoutkit_decode(data: bytes, frames: list, truth: dict, m: Mutation, rng: np.random.Generator,
                           outcome: FuzzOutcome, n_sensors: int) -> list[str]:
    """Decode ``m.data`` in random chunks with the layoutkit decoder; update ``outcome``; return
    the violated properties (empty = all hold).

    frames : the original frames (bytes, in stream order); truth : seq → (t, station, axis, angles).
    """
    from .layoutkit import LayoutkitDecoder

    problems = []
    spans, pos = [], 0
    for f in frames:
        spans.append((pos, pos + len(f)))
        pos += len(f)
    seqs = list(truth)
    dec = LayoutkitDecoder(n_sensors)
    out = []
    try:
        p = 0
        while p < len(m.data):
            k = int(rng.integers(1, 600))
            out += dec.feed(m.data[p:p + k])
            p += k
        out += dec.flush()
    except Exception as exc:  # noqa: BLE001 - that is what we are looking for
        outcome.exceptions += 1
        problems.append(f"exception {exc!r}")
    outcome.runs += 1
    for kind in m.kinds:
        outcome.mutations[kind] += 1
    outcome.decoder_errors += dec.stats.errors
    intact = intact_frames(m, spans)
    index = {q: k for k, q in enumerate(seqs)}
    T = np.array([truth[q][0] for q in seqs])
    SA = np.array([truth[q][1:3] for q in seqs])
    A = np.nan_to_num(np.array([truth[q][3] for q in seqs]), nan=-1.0)
    decoded = {}
    if out:
        k = np.array([index.get(s.seq, -1) for s in out])
        known = k >= 0
        kk = np.where(known, k, 0)
        got_a = np.nan_to_num(np.array([s.angles for s in out]), nan=-1.0)
        same = known & (np.abs(np.array([s.t for s in out]) - T[kk]) < 1e-9)
        same &= np.all(np.array([(s.station, s.axis) for s in out]) == SA[kk], axis=1)
        same &= np.all(np.abs(got_a - A[kk]) <= 1e-12, axis=1)
        for s_, ok_ in zip(out, same):
            decoded[s_.seq] = bool(ok_)
            if not ok_:
                outcome.false_good += 1
                problems.append(f"frame reported good but not an original frame: seq {s_.seq}")
    outcome.frames += len(frames)
    outcome.intact += int(intact.sum())
    for k in np.flatnonzero(intact):
        if decoded.get(seqs[k]):
            outcome.intact_decoded += 1
        else:
            problems.append(f"intact frame seq {seqs[k]} not decoded")
    outcome.damaged_decoded_equal += sum(1 for k in np.flatnonzero(~intact) if decoded.get(seqs[k]))
    # resynchronisation: after each run of damaged frames, the next intact frame is decoded
    k = 0
    while k < len(frames):
        if not intact[k]:
            j = k
            while j < len(frames) and not intact[j]:
                j += 1
            if j < len(frames):
                outcome.damage_events += 1
                outcome.resync_next_intact += int(bool(decoded.get(seqs[j])))
            k = j
        else:
            k += 1
    return problems
