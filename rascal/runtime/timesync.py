"""Sans-IO NTP-style estimator of a shared (master) clock.

A client stamps a request with its local clock (t1), the master stamps receipt
and reply with the shared clock (t2, t3) and the client stamps the reply (t4).
One-way delays are never negative, so every exchange bounds the offset
(shared - local) from both sides: offset(t1) <= t2 - t1 and
offset(t4) >= t3 - t4. The estimator keeps a window of the most informative
samples and fits offset = a + b * (local - t_ref) through the centre of the set
of lines that respect all of those bounds, which tracks drift as well as offset
and yields an honest error bound. No I/O and no clock reads: the caller passes
every timestamp in, which keeps it deterministic and testable.
"""

from __future__ import annotations

import enum
import math
from collections import deque
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

_INT64_MIN = -(2**63)
_INT64_MAX = 2**63 - 1
_UNBOUNDED_NS = _INT64_MAX  # error bound reported before any fit
_FIT_GRID = 129  # slopes per scan of the set of consistent lines
_FIT_RESOLVED = 32  # consistent slopes needed before the scan stops zooming in
_FIT_ROUNDS = 4


class SyncState(enum.IntEnum):
    """Lifecycle of the estimate."""

    UNSYNCED = 0
    SYNCED = 1
    HOLDOVER = 2


@dataclass(frozen=True)
class TimeSyncConfig:
    """Tunables; durations in nanoseconds, clock rates in ppm."""

    window_samples: int = 64
    min_samples: int = 4
    holdover_after_ns: int = 5_000_000_000  # two settled exchanges (2 s apart) lost, and slack
    max_delay_ns: int = 500_000_000
    # Timestamping noise can make a near-zero round trip slightly negative.
    negative_delay_tolerance_ns: int = 10_000
    # Samples older than this are dropped even if informative: drift wanders
    # with temperature, so a straight line only holds for so long.
    max_sample_age_ns: int = 60_000_000_000
    # Hard limit and 1-sigma prior of the local clock's rate error; the prior
    # keeps the drift sane while a short, noisy window cannot pin it down.
    max_drift_ppm: float = 500.0
    drift_prior_ppm: float = 100.0
    # Rate wander assumed on top of the fitted drift when extrapolating.
    drift_wander_ppm: float = 0.1
    # A sample that misses the model by more than the error bound plus this
    # margin is a step candidate (e.g. the master restarted with a new clock).
    step_threshold_ns: int = 1_000_000
    # A step is confirmed once this many of the last step_window_samples
    # samples are candidates (not all, since jitter hides some of them).
    step_confirm_samples: int = 4
    step_window_samples: int = 8


@dataclass(frozen=True)
class SyncStatus:
    """Snapshot of the estimator at a given local time."""

    state: SyncState
    offset_ns: int  # shared - local at the time of the query
    drift_ppm: float  # d(offset)/d(local) in ppm: negative if local runs fast
    delay_ns: int  # round trip of the best sample in the window
    error_bound_ns: int
    samples: int
    rejected: int  # add_sample calls that returned False
    resets: int
    last_sample_local_ns: int | None


class _Sample(NamedTuple):
    t1: int
    up: int  # t2 - t1: offset at t1 plus the outbound delay, so >= offset
    t4: int
    lo: int  # t3 - t4: offset at t4 minus the return delay, so <= offset
    delay: int


class _Model(NamedTuple):
    """offset(local) = off_ref + a + b * (local - t_ref), with error bounds."""

    t_ref: int
    off_ref: int
    a: float
    b: float
    a_err: float
    b_err: float

    def offset(self, local_ns: int) -> float:
        return self.off_ref + self.a + self.b * (local_ns - self.t_ref)

    def error_bound(self, local_ns: int, wander: float) -> float:
        return self.a_err + abs(local_ns - self.t_ref) * (self.b_err + wander)


class TimeSyncEstimator:
    """Estimates shared time from 4-timestamp exchanges with a time master."""

    def __init__(self, config: TimeSyncConfig = TimeSyncConfig()) -> None:
        self._cfg = config
        self._wander = config.drift_wander_ppm * 1e-6
        self._window: list[_Sample] = []  # in arrival order, newest last
        # Last few samples and whether each contradicted the model: step evidence.
        self._recent: deque[tuple[_Sample, bool]] = deque(maxlen=config.step_window_samples)
        self._evict_next = 0  # window index to evict next when over capacity
        self._model: _Model | None = None
        self._rejected = 0
        self._resets = 0

    def add_sample(self, t1_ns: int, t2_ns: int, t3_ns: int, t4_ns: int) -> bool:
        """Feed one exchange; returns False (and counts it) if it is not used."""
        sample = self._check(t1_ns, t2_ns, t3_ns, t4_ns)
        if sample is None:
            self._rejected += 1
            return False
        contradicts = self._contradicts(sample)
        self._recent.append((sample, contradicts))
        if contradicts:
            restart_from = self._confirmed_step() or self._lost()
            if restart_from is None:
                self._rejected += 1
                return False
            # Older samples describe a clock relation that is gone.
            self._window = restart_from
            self._recent.clear()
            self._resets += 1
        else:
            self._window.append(sample)
            self._evict()
        self._refit()
        return True

    @property
    def synced(self) -> bool:
        """SYNCED or HOLDOVER: cheap enough for every bus poll (status() is not)."""
        return self._model is not None and len(self._window) >= self._cfg.min_samples

    @property
    def settled(self) -> bool:
        """Synced on a full step window of samples, none of which contradicted the model: the
        estimate can coast on fewer exchanges (a client may ask less often)."""
        recent = self._recent
        return self.synced and len(recent) == recent.maxlen and not any(flag for _sample, flag in recent)

    def to_shared(self, local_ns: int) -> int:
        """Map a local timestamp to shared time (identity until first sync)."""
        m = self._model
        if m is None:
            return local_ns
        return local_ns + m.off_ref + round(m.a + m.b * (local_ns - m.t_ref))

    def status(self, local_now_ns: int) -> SyncStatus:
        """Report state, offset and error bound at local time local_now_ns."""
        cfg, m = self._cfg, self._model
        if m is None or len(self._window) < cfg.min_samples:
            state = SyncState.UNSYNCED
        elif local_now_ns - self._window[-1].t4 > cfg.holdover_after_ns:
            state = SyncState.HOLDOVER
        else:
            state = SyncState.SYNCED
        if m is None:
            drift_ppm, bound = 0.0, _UNBOUNDED_NS
        else:
            drift_ppm = m.b * 1e6
            bound = min(math.ceil(m.error_bound(local_now_ns, self._wander)), _UNBOUNDED_NS)
        return SyncStatus(
            state=state,
            offset_ns=self.to_shared(local_now_ns) - local_now_ns,
            drift_ppm=drift_ppm,
            delay_ns=min((s.delay for s in self._window), default=0),
            error_bound_ns=bound,
            samples=len(self._window),
            rejected=self._rejected,
            resets=self._resets,
            last_sample_local_ns=self._window[-1].t4 if self._window else None,
        )

    def _check(self, t1: int, t2: int, t3: int, t4: int) -> _Sample | None:
        """Turn an exchange into a sample, or None if it cannot be genuine."""
        cfg = self._cfg
        if not all(_INT64_MIN <= t <= _INT64_MAX for t in (t1, t2, t3, t4)):
            return None
        local_rtt, master_hold = t4 - t1, t3 - t2
        delay = local_rtt - master_hold
        if local_rtt < 0 or master_hold < 0:
            return None
        if delay < -cfg.negative_delay_tolerance_ns or delay > cfg.max_delay_ns:
            return None
        return _Sample(t1, t2 - t1, t4, t3 - t4, max(delay, 0))

    def _contradicts(self, s: _Sample) -> bool:
        """True if the sample misses the model by more than its error bounds allow."""
        if self._window and s.t4 < self._window[-1].t4:
            return True  # local time ran backwards: the line cannot model that
        m = self._model
        if m is None or len(self._window) < self._cfg.min_samples:
            return False
        margin = self._cfg.step_threshold_ns
        too_low = s.up < m.offset(s.t1) - m.error_bound(s.t1, self._wander) - margin
        too_high = s.lo > m.offset(s.t4) + m.error_bound(s.t4, self._wander) + margin
        return too_low or too_high

    def _confirmed_step(self) -> list[_Sample] | None:
        """The samples since a clock step, if the recent ones confirm there was one.

        Enough recent samples must contradict the model, and every sample since
        the first contradiction must fit one line at the current drift, so a
        few garbage replies cannot pass for a step. On a jittery link some
        post-step samples still look consistent; they count as post-step too.
        """
        flags = [contradicts for _, contradicts in self._recent]
        if sum(flags) < self._cfg.step_confirm_samples:
            return None
        since = [s for s, _ in self._recent][flags.index(True) :]
        b = self._model.b if self._model is not None else 0.0
        t_ref, off_ref = since[0].t4, since[0].lo
        top = min(s.up - off_ref - b * (s.t1 - t_ref) for s in since)
        bottom = max(s.lo - off_ref - b * (s.t4 - t_ref) for s in since)
        return since if bottom <= top + self._cfg.step_threshold_ns else None

    def _lost(self) -> list[_Sample] | None:
        """The recent samples, if every one of a full step window contradicted the model without
        agreeing on a step: the master's clock is being jerked about (an agent stepping it to and
        fro), and a model that rejects everything would coast on, ever more wrong, in holdover.
        Starting again from them gives a fit whose error bound spans their disagreement."""
        recent = self._recent
        if len(recent) < self._cfg.step_window_samples or not all(flag for _sample, flag in recent):
            return None
        return [s for s, _ in recent]

    def _evict(self) -> None:
        """Drop the least informative sample if over capacity, then stale ones."""
        cfg, window = self._cfg, self._window
        if len(window) > cfg.window_samples:
            # _evict_next indexes the window as it was before this append.
            del window[self._evict_next]
        # Keep min_samples even if stale so the fit survives a long outage.
        newest = window[-1].t4
        while len(window) > cfg.min_samples and newest - window[0].t4 > cfg.max_sample_age_ns:
            del window[0]

    def _refit(self) -> None:
        """Refit the model to the whole window (see _fit_line)."""
        cfg = self._cfg
        if len(self._window) < cfg.min_samples:
            self._evict_next = 0  # nothing to rank samples by: oldest first
            return  # keep the previous model: dropping it would jump shared time
        newest = self._window[-1]
        t_ref, off_ref = newest.t4, newest.lo
        # Subtract the references in ints so float math only sees small values.
        rel = [(s.t1 - t_ref, s.up - off_ref, s.t4 - t_ref, s.lo - off_ref) for s in self._window]
        x_up, up, x_lo, lo = np.array(rel, dtype=np.float64).T
        a, b, a_err, b_err = _fit_line(x_up, up, x_lo, lo, cfg.max_drift_ppm * 1e-6, cfg.drift_prior_ppm * 1e-6)
        self._model = _Model(t_ref, off_ref, a, b, a_err, b_err)
        # Choose the next eviction; the newest sample always stays. Samples the
        # line violates saw a clock change too small to flag as a step: drop
        # the oldest of them first. Otherwise a sample matters only through its
        # tightest bound, and dropping the one whose tightest bound is loosest,
        # rather than the oldest, lengthens the baseline that drift needs.
        slack = np.minimum(up - (a + b * x_up), (a + b * x_lo) - lo)[:-1]
        violated = np.flatnonzero(slack < -1.0)
        if len(violated):
            self._evict_next = int(violated[0])
        else:
            self._evict_next = int(slack.argmax()) if len(slack) else 0


def _fit_line(
    x_up: np.ndarray,
    up: np.ndarray,
    x_lo: np.ndarray,
    lo: np.ndarray,
    max_b: float,
    prior_b: float,
) -> tuple[float, float, float, float]:
    """Centre of the lines a + b*x with line(x_up) <= up and line(x_lo) >= lo.

    Delays are never negative, so the true line is one of these. For a slope b
    the intercept may lie anywhere in [bottom(b), top(b)]; the estimate is the
    centroid of that set, weighted by a Gaussian prior on b. The slope axis is
    scanned on a grid that zooms in until the set is resolved. Returns
    (a, b, a_err, b_err), the errors being the set's extent around the estimate.
    """
    b_lo, b_hi = -max_b, max_b
    for _ in range(_FIT_ROUNDS):
        bs = np.linspace(b_lo, b_hi, _FIT_GRID)
        top = (up[None, :] - bs[:, None] * x_up[None, :]).min(axis=1)
        bottom = (lo[None, :] - bs[:, None] * x_lo[None, :]).max(axis=1)
        width = top - bottom
        # Clock noise can leave no line inside every bound: then keep the
        # slopes that miss by at most twice the smallest possible miss.
        floor = min(0.0, 2.0 * float(width.max()))
        inside = np.flatnonzero(width >= floor)
        step = bs[1] - bs[0]
        if len(inside) >= _FIT_RESOLVED:
            break
        b_lo = max(bs[inside[0]] - step, -max_b)
        b_hi = min(bs[inside[-1]] + step, max_b)
    bs, top, bottom = bs[inside], top[inside], bottom[inside]
    # In logs, so a tight prior far from the data cannot underflow every weight.
    log_weight = np.log(top - bottom - floor + 1e-9) - 0.5 * (bs / prior_b) ** 2
    weight = np.exp(log_weight - log_weight.max())
    b = float(np.average(bs, weights=weight))
    a = float(np.average((top + bottom) / 2, weights=weight))
    # Samples that no line fits leave top below bottom: the offset lies between them either way.
    a_err = max(float(np.maximum(top, bottom).max()) - a, a - float(np.minimum(top, bottom).min()))
    b_err = max(float(bs[-1]) - b, b - float(bs[0])) + step
    return a, b, a_err, b_err
