"""Shared-time estimator, checked against a simulated master, client clock and link."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rascal.runtime.timesync import SyncState, SyncStatus, TimeSyncConfig, TimeSyncEstimator

US = 1_000
MS = 1_000_000
S = 1_000_000_000
EPOCH_NS = 1_700_000_000 * S  # wall-clock magnitude, so float precision matters
PERIOD_NS = 100 * MS  # one request every 100 ms of true time
JITTERY_LINK = (0, 5 * MS)  # uniform one-way delay, drawn for each direction
LOOPBACK_LINK = (20 * US, 80 * US)
MASTER_HOLD_NS = 20 * US  # master time between receiving a request and replying


class Sim:
    """True time drives a master clock (shared = true) and a drifting client clock.

    The client sends a request every PERIOD_NS; each direction of the link has
    its own random delay stream and the master holds the request briefly, so
    t1..t4 are stamped exactly as a real exchange would stamp them.
    """

    def __init__(
        self,
        seed: int,
        offset_ns: int = 250 * MS,
        drift_ppm: int = 100,
        link: tuple[int, int] = JITTERY_LINK,
    ) -> None:
        self.uplink_rng = random.Random(2 * seed)
        self.downlink_rng = random.Random(2 * seed + 1)
        self.probe_rng = random.Random(-seed - 1)  # probing must not perturb the link
        self.offset_ns, self.drift_ppm, self.link = offset_ns, drift_ppm, link
        self.master_step_ns = 0
        self.true_ns = EPOCH_NS
        self.est = TimeSyncEstimator()

    def local(self, true_ns: int) -> int:
        elapsed = true_ns - EPOCH_NS
        return EPOCH_NS + elapsed + self.offset_ns + elapsed * self.drift_ppm // 1_000_000

    def master(self, true_ns: int) -> int:
        return true_ns + self.master_step_ns

    def exchange(self) -> bool:
        t = self.true_ns
        t1 = self.local(t)
        t += self.uplink_rng.randint(*self.link)
        t2 = self.master(t)
        t += MASTER_HOLD_NS
        t3 = self.master(t)
        t += self.downlink_rng.randint(*self.link)
        return self.est.add_sample(t1, t2, t3, self.local(t))

    def error_ns(self, true_ns: int) -> int:
        return self.est.to_shared(self.local(true_ns)) - self.master(true_ns)

    def run(self, duration_ns: int, probes_per_period: int = 0) -> int:
        """Exchange every period for duration_ns; return the worst |error| probed meanwhile."""
        worst = 0
        for _ in range(duration_ns // PERIOD_NS):
            self.exchange()
            for _ in range(probes_per_period):
                probe = self.true_ns + self.probe_rng.randrange(PERIOD_NS)
                worst = max(worst, abs(self.error_ns(probe)))
            self.true_ns += PERIOD_NS
        return worst

    def status(self) -> SyncStatus:
        return self.est.status(self.local(self.true_ns))


# After 5 s the data pin drift only to a few hundred ppm, so this sits near
# the information limit: about 1.5% of random runs exceed 0.5 ms around 5-6 s
# (worst seen 0.65 ms in 3000 runs). Knowing the drift exactly would give
# 0.36 ms worst. The 20 seeds here all stay below 0.42 ms.
@pytest.mark.parametrize(("offset_ns", "drift_ppm"), [(250 * MS, 100), (-250 * MS, -100)])
def test_jittery_link_converges_to_half_a_millisecond_within_5s(offset_ns: int, drift_ppm: int) -> None:
    worst = {}
    for seed in range(20):
        sim = Sim(seed, offset_ns, drift_ppm, JITTERY_LINK)
        sim.run(5 * S)
        worst[seed] = sim.run(5 * S, probes_per_period=4)
    assert max(worst.values()) <= 0.5 * MS, worst


def test_loopback_link_converges_to_50us_within_1s() -> None:
    worst = {}
    for seed in range(20):
        sim = Sim(seed, link=LOOPBACK_LINK)
        sim.run(1 * S)
        worst[seed] = sim.run(3 * S, probes_per_period=4)
    assert max(worst.values()) <= 50 * US, worst


def test_holdover_keeps_compensating_drift_and_widens_the_error_bound() -> None:
    sim = Sim(seed=1, link=LOOPBACK_LINK)
    sim.run(10 * S)
    last_sample_true = sim.true_ns - PERIOD_NS
    holdover_after = TimeSyncConfig().holdover_after_ns
    bounds = []
    for elapsed in (holdover_after - 10 * MS, holdover_after + 10 * MS, holdover_after + 2 * S, holdover_after + 5 * S):
        sim.true_ns = last_sample_true + elapsed
        status = sim.status()
        assert status.state is (SyncState.SYNCED if elapsed < holdover_after else SyncState.HOLDOVER)
        assert abs(sim.error_ns(sim.true_ns)) <= status.error_bound_ns
        bounds.append(status.error_bound_ns)
    # Uncompensated, 100 ppm over 10 s would be 1 ms off.
    assert abs(sim.error_ns(sim.true_ns)) < 0.2 * MS
    assert abs(status.drift_ppm + 100) < 5  # local runs fast, so shared - local shrinks
    assert bounds == sorted(bounds) and len(set(bounds)) == len(bounds)


def test_absurd_samples_are_rejected_counted_and_ignored() -> None:
    sim = Sim(seed=2, link=LOOPBACK_LINK)
    sim.run(2 * S)
    before = sim.status()
    probes = [sim.local(sim.true_ns + k * 10 * MS) for k in range(5)]
    shared_before = [sim.est.to_shared(p) for p in probes]
    t1 = sim.local(sim.true_ns)
    t2 = sim.master(sim.true_ns)
    negative_rtt = (t1, t2, t2 + US, t1 - 5 * US)
    master_held_longer_than_rtt = (t1, t2, t2 + MS, t1 + 100 * US)
    too_slow = (t1, t2, t2 + US, t1 + TimeSyncConfig().max_delay_ns + MS)
    for sample in (negative_rtt, master_held_longer_than_rtt, too_slow):
        assert not sim.est.add_sample(*sample)
    after = sim.status()
    assert after.rejected == before.rejected + 3
    assert after.samples == before.samples
    assert [sim.est.to_shared(p) for p in probes] == shared_before


def test_master_step_resets_the_window_and_reconverges() -> None:
    for seed in range(5):
        sim = Sim(seed, link=(0, 1 * MS))
        sim.run(5 * S)
        sim.master_step_ns = 2 * S
        sim.run(1 * S)
        assert sim.status().resets == 1
        assert sim.run(3 * S, probes_per_period=4) <= 0.5 * MS
        assert sim.status().resets == 1


def test_a_master_clock_jerked_to_and_fro_is_followed_with_an_honest_bound() -> None:
    """Something steps the master's clock 3 ms ahead, then 3 ms behind, in turn: no one step to
    confirm. The estimator must not freeze on its old model, rejecting everything in holdover: it
    starts again from the samples, with an error bound that spans their disagreement."""
    sim = Sim(seed=6, link=LOOPBACK_LINK)
    sim.run(5 * S)
    window = TimeSyncConfig().step_window_samples
    for k in range(50):
        sim.master_step_ns = 3 * MS if k % 2 else -3 * MS
        sim.run(PERIOD_NS)
        status = sim.status()
        if k >= window:
            assert status.state is SyncState.SYNCED, (k, status)
            assert abs(sim.error_ns(sim.true_ns)) <= status.error_bound_ns, (k, status)
    assert status.resets == 1 and status.rejected == window - 1, status


def test_error_bound_covers_the_actual_error() -> None:
    for seed in range(5):
        sim = Sim(seed, link=JITTERY_LINK)
        sim.run(PERIOD_NS * TimeSyncConfig().min_samples)
        for _ in range(100):
            sim.run(PERIOD_NS)
            probe = sim.true_ns + sim.probe_rng.randrange(PERIOD_NS)
            assert abs(sim.error_ns(probe)) <= sim.est.status(sim.local(probe)).error_bound_ns


def test_unsynced_until_min_samples_and_identity_meanwhile() -> None:
    sim = Sim(seed=4, link=LOOPBACK_LINK)
    min_samples = TimeSyncConfig().min_samples
    for _ in range(min_samples - 1):
        sim.run(PERIOD_NS)
        status = sim.status()
        assert status.state is SyncState.UNSYNCED
        for local in (0, sim.local(sim.true_ns), sim.local(sim.true_ns) + 123_456_789):
            assert sim.est.to_shared(local) == local
    sim.run(PERIOD_NS)
    assert sim.status().state is SyncState.SYNCED
    assert sim.est.to_shared(sim.local(sim.true_ns)) != sim.local(sim.true_ns)


_extreme = st.sampled_from([0, 1, -1, 2**63 - 1, -(2**63), 2**64, -(2**70)])
_garbage = st.tuples(*[st.integers(-(2**70), 2**70) | _extreme] * 4)
# Near-plausible exchanges get past the sanity checks and reach the fit.
_plausible = st.builds(
    lambda base, off, d1, hold, d2: (base, base + off + d1, base + off + d1 + hold, base + d1 + hold + d2),
    st.integers(-(2**62), 2**62) | st.just(EPOCH_NS),
    st.integers(-(2**40), 2**40) | st.just(0),
    st.integers(-10 * US, 10 * MS),
    st.integers(0, 1 * MS),
    st.integers(-10 * US, 10 * MS),
)


@settings(max_examples=150, deadline=None)
@given(
    samples=st.lists(_garbage | _plausible, max_size=40),
    queries=st.lists(st.integers(-(2**63), 2**63 - 1), min_size=1, max_size=5),
)
def test_garbage_never_raises_and_to_shared_stays_an_int(
    samples: list[tuple[int, int, int, int]], queries: list[int]
) -> None:
    est = TimeSyncEstimator()
    for sample in samples:
        assert isinstance(est.add_sample(*sample), bool)
        for local in queries:
            assert type(est.to_shared(local)) is int
    for local in queries:
        est.status(local)
