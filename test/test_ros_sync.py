"""Approximate-time synchronizer: pairs true partners, drops and counts the rest, as message_filters' C++ policy."""
from __future__ import annotations

import numpy as np
import pytest

from eslam_ros.sync import ApproximateTimeSynchronizer, NonMonotonicStampError, SyncConfigError


def _arrivals(stamps_per_topic, max_delay, rng):
    """(arrival time, topic, stamp, msg) in arrival order; msg = (topic, index, stamp). Each message arrives a
    random delay after its stamp, so topics interleave randomly; each topic is delivered in order (FIFO)."""
    events = []
    for topic, stamps in enumerate(stamps_per_topic):
        arrivals = np.maximum.accumulate(stamps + rng.uniform(0.0, max_delay, len(stamps)))
        events += [(a, topic, s, (topic, k, s)) for k, (s, a) in enumerate(zip(stamps, arrivals))]
    events.sort(key=lambda e: e[0])
    return events


def _run(sync, events):
    """Feed the events, then flush; return the emitted sets and, per set, the delay from its newest stamp to the
    arrival that completed it."""
    sets, latencies = [], []
    for arrival, topic, stamp, msg in events:
        for s in sync.add(topic, stamp, msg):
            sets.append(s)
            latencies.append(arrival - max(m[2] for m in s))
    return sets + sync.flush(), latencies


def test_jittered_30hz_streams_pair_every_frame_with_its_true_partner():
    rng = np.random.default_rng(1)
    n = 300
    clock = 1000.0 + np.arange(n) / 30.0
    rgb = clock + rng.uniform(-0.003, 0.003, n)
    depth = clock + rng.uniform(-0.003, 0.003, n)
    events = _arrivals([rgb, depth], max_delay=0.02, rng=rng)

    for bounds, max_latency in [(None, 0.06), ([0.025, 0.025], 0.0201)]:
        sync = ApproximateTimeSynchronizer(2, queue_size=10, inter_message_lower_bounds=bounds)
        sets, latencies = _run(sync, events)
        assert [(a[1], d[1]) for a, d in sets] == [(k, k) for k in range(n)]  # true partners, each once, in order
        assert all(a[0] == 0 and d[0] == 1 for a, d in sets)  # tuples in topic order
        assert sync.dropped == [0, 0] and sync.pending == 0
        # Without rate bounds a set is proven only when the next frame shows up (~1/30 s later); with them it
        # is emitted as soon as both halves have arrived.
        assert max(latencies) < max_latency


def test_30hz_and_15hz_pair_each_slow_message_with_the_nearest_fast_one():
    rng = np.random.default_rng(2)
    fast = np.arange(60) / 30.0 + rng.uniform(-0.003, 0.003, 60)
    slow = np.arange(0, 60, 2) / 30.0 + 0.006 + rng.uniform(-0.003, 0.003, 30)
    events = _arrivals([fast, slow], max_delay=0.01, rng=rng)
    sync = ApproximateTimeSynchronizer(2)
    sets, _ = _run(sync, events)

    nearest_fast = [int(np.argmin(np.abs(fast - s))) for s in slow]
    assert [(f[1], s[1]) for f, s in sets] == list(zip(nearest_fast, range(30)))
    assert sync.dropped == [30, 0]


def test_max_interval_rejects_sets_with_too_large_a_gap():
    # rgb misses frame 5 and depth misses frame 6: depth 5 and rgb 6 (33 ms apart) have no true partner.
    stamps = np.arange(10) / 30.0
    rgb = [(0, k, s) for k, s in enumerate(stamps) if k != 5]
    depth = [(1, k, s + 0.002) for k, s in enumerate(stamps) if k != 6]

    def pairs(max_interval):
        sync = ApproximateTimeSynchronizer(2, max_interval=max_interval)
        sets = []
        for m in sorted(rgb + depth, key=lambda m: (m[2], m[0])):
            sets += sync.add(m[0], m[2], m)
        sets += sync.flush()
        return [(a[1], d[1]) for a, d in sets], sync.dropped

    # Without a limit the orphans are paired with each other: a wrong 31 ms match.
    unlimited, _ = pairs(None)
    assert (6, 5) in unlimited
    limited, dropped = pairs(0.01)
    assert limited == [(k, k) for k in range(10) if k not in (5, 6)]
    assert dropped == [1, 1]


def test_flush_emits_the_last_pending_pair_and_counts_leftovers():
    sync = ApproximateTimeSynchronizer(2)
    assert sync.add(0, 0.000, "rgb0") == []
    assert sync.add(1, 0.001, "depth0") == []
    # rgb1 proves (rgb0, depth0) optimal: any other set for depth0 would span >= 32 ms.
    assert sync.add(0, 0.033, "rgb1") == [("rgb0", "depth0")]
    # (rgb1, depth1) waits: a later rgb could still be closer to depth1.
    assert sync.add(1, 0.034, "depth1") == []
    assert sync.add(0, 0.066, "rgb2") == [("rgb1", "depth1")]
    assert sync.add(1, 0.067, "depth2") == []
    assert sync.add(0, 0.100, "rgb3") == [("rgb2", "depth2")]
    assert sync.pending == 1
    assert sync.add(1, 0.101, "depth3") == []
    assert sync.pending == 2
    assert sync.flush() == [("rgb3", "depth3")]
    assert sync.pending == 0 and sync.dropped == [0, 0]

    # A stream that ends with an unmatched message: flush drops and counts it, then accepts a new stream.
    assert sync.add(0, 5.0, "lonely") == []
    assert sync.flush() == []
    assert sync.dropped == [1, 0]
    assert sync.add(0, 0.0, "new stream") == []


def test_queue_overflow_drops_the_oldest_and_never_mispairs_its_partner():
    sync = ApproximateTimeSynchronizer(2, queue_size=5)
    for k in range(8):  # depth is silent: rgb overflows
        assert sync.add(0, k / 10, f"rgb{k}") == []
    assert sync.dropped == [3, 0] and sync.pending == 5  # rgb0..rgb2 are gone

    # depth's true partner (rgb0) was dropped: it must not be paired with rgb3, 250 ms away.
    assert sync.add(1, 0.05, "depth@0.05") == []
    assert sync.dropped == [3, 1]
    assert sync.add(1, 0.31, "depth@0.31") == [("rgb3", "depth@0.31")]
    assert sync.add(1, 0.41, "depth@0.41") == [("rgb4", "depth@0.41")]
    assert sync.flush() == []
    assert sync.dropped == [3 + 3, 1]  # rgb5..rgb7 never got a partner


def test_queue_overflow_while_a_candidate_waits_abandons_it_and_resumes_cleanly():
    # rgb stalls after frame 0 (frames 1-3 lost) while depth keeps coming: depth's queue overflows while the
    # candidate (rgb0, depth0) still waits for proof. The search restarts without depth0, so rgb0 (whose partner
    # was dropped) is dropped too, and pairing resumes with true partners once rgb is back.
    sync = ApproximateTimeSynchronizer(2, queue_size=3)
    sets = []
    for k in range(30):
        if not 1 <= k <= 3:
            sets += sync.add(0, k / 30, (0, k))
        sets += sync.add(1, k / 30 + 0.001, (1, k))
    sets += sync.flush()
    assert [(a[1], d[1]) for a, d in sets] == [(k, k) for k in range(4, 30)]
    assert sync.dropped == [1, 4]


@pytest.mark.parametrize("age_penalty, expected", [(0.1, ("rgb0", "depth0")), (0.0, ("rgb1", "depth0"))])
def test_age_penalty_keeps_an_older_set_unless_a_newer_one_is_clearly_better(age_penalty, expected):
    # (rgb1, depth0) spans 9.5 ms, (rgb0, depth0) 10 ms: only 5% better, under the 10% age penalty.
    sync = ApproximateTimeSynchronizer(2, age_penalty=age_penalty)
    sync.add(0, 0.0, "rgb0")
    sync.add(1, 0.010, "depth0")
    assert sync.add(0, 0.0195, "rgb1") == [expected]


@pytest.mark.parametrize("n_topics", [2, 3])
def test_random_streams_keep_every_message_accounted_for(n_topics):
    rng = np.random.default_rng(10 + n_topics)
    streams = []
    for _ in range(n_topics):
        rate = rng.uniform(10, 40)
        gaps = rng.uniform(0.5, 1.5, 150) / rate
        streams.append(np.cumsum(gaps))
    events = _arrivals(streams, max_delay=0.05, rng=rng)
    sync = ApproximateTimeSynchronizer(n_topics, queue_size=6, max_interval=0.05)
    sets, _ = _run(sync, events)

    assert len(sets) > 20
    for topic in range(n_topics):
        used = [s[topic][1] for s in sets]
        assert all(s[topic][0] == topic for s in sets)
        assert used == sorted(set(used))  # each message at most once, in time order
        assert len(used) + sync.dropped[topic] == 150
    assert all(max(m[2] for m in s) - min(m[2] for m in s) <= 0.05 for s in sets)


def test_non_monotonic_stamp_raises_with_both_stamps_and_is_skipped():
    sync = ApproximateTimeSynchronizer(2)
    sync.add(0, 1.0, "a")
    with pytest.raises(NonMonotonicStampError, match=r"0\.500000000.*1\.000000000"):
        sync.add(0, 0.5, "late")
    assert sync.pending == 1
    sync.add(1, 0.5, "other topic has its own clock")
    sync.add(0, 1.0, "equal stamp is accepted")
    assert sync.pending == 3


def test_bad_configuration_is_rejected_with_a_clear_error():
    with pytest.raises(SyncConfigError, match="n_topics"):
        ApproximateTimeSynchronizer(1)
    with pytest.raises(SyncConfigError, match="queue_size"):
        ApproximateTimeSynchronizer(2, queue_size=0)
    with pytest.raises(SyncConfigError, match="max_interval"):
        ApproximateTimeSynchronizer(2, max_interval=-1.0)
    sync = ApproximateTimeSynchronizer(2)
    with pytest.raises(SyncConfigError, match="topic_index"):
        sync.add(2, 0.0, "x")
    with pytest.raises(SyncConfigError, match="finite"):
        sync.add(0, float("nan"), "x")
