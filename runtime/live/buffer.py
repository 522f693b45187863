"""Per-binding buffering (latest, delayed), One Euro smoothing, status and counters."""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from itertools import islice

import numpy as np

from rigspace.runtime.live.source_frame import DecodeCounters, SourceFrame, quat_slerp
from rigspace.sdk.schema import LOST_FACTOR

LATEST = "latest"
DELAYED = "delayed"
MODES = (LATEST, DELAYED)

WAITING = "waiting"
CONNECTED = "connected"
STALE = "stale"
LOST = "lost"

RECENT = 256
"""Snapshots a frame's delayed pose looks back through (all the buffer kept before takes could
catch up; `history` keeps more for them): the per-frame cost stays what it was."""
CLOCK_RESET_SECONDS = 1.0
"""A sender's clock is trusted while it keeps pace with the receive clock: a timestamp this far
behind the stream's last one (a restarted sender), or a sample whose offset from the receive
clock moved this far either way (a clock that jumped ahead or back, an absurd value), starts
the stream's clock over (a new `_Clock`) instead of dropping everything until it catches up."""
ONE_EURO_MAX_CUTOFF = 5.0
"""Minimum cutoff (Hz) of the One Euro filter at smoothing strength 0+; it falls as (1 - s)^2."""
ONE_EURO_BETA = 0.8
"""Speed coefficient for unit-quaternion components (per second): fast motion opens the filter.
Casiez's 0.007 is for pixels; quaternion components move about 1 unit/s in brisk motion."""
ONE_EURO_D_CUTOFF = 1.0
"""Cutoff (Hz) of the derivative's low-pass, the reference implementation's default."""


@dataclass(frozen=True)
class BufferSettings:
    """How one binding's samples meet frames (from the RigspaceLiveBindingAPI attributes)."""

    mode: str = LATEST
    """latest: the newest sample; delayed: the pose `delay` seconds ago, slerped between the
    two samples around it on the source's clock (hides network jitter for a fixed latency)."""
    delay: float | None = 0.05
    """Seconds behind now for `delayed`; None: one sample interval (the median recent one)."""
    smoothing: str = "none"
    """none, exponential (slerp towards each sample by 1 - strength) or oneEuro."""
    strength: float = 0.5
    """Smoothing strength in [0, 1): 0 passes samples through."""
    timeout: float = 0.5
    """Seconds without data before the binding is stale (holds its last pose)."""
    lost: float | None = None
    """Seconds without data before the binding is lost (blends back to the stage animation);
    None: LOST_FACTOR x timeout (Live Link too holds a subject's last pose before dropping it)."""
    blend: float = 0.5
    """Seconds over which a lost binding blends back to the stage animation."""
    history: int = 2048
    """Snapshots kept for `delayed` and for a take recorder that catches up (`pose_at`):
    34 s at 60 Hz, bounded, so a flood cannot grow memory (2048 x 55 bones: 3.6 MB)."""

    @property
    def lost_after(self) -> float:
        return self.timeout * LOST_FACTOR if self.lost is None else self.lost

    @classmethod
    def from_binding(cls, binding) -> BufferSettings:
        """From an sdk.schema.LiveBinding (whose reader already turned deprecated buffering
        tokens into these): latest, or delayed by bufferSeconds (0: one sample interval);
        stale after timeoutSeconds, lost after lostSeconds (0: LOST_FACTOR x timeoutSeconds)."""
        if binding.buffering not in MODES:
            raise ValueError(f"buffering {binding.buffering!r} is not one of {MODES}")
        seconds = float(binding.buffer_seconds)
        lost = float(getattr(binding, "lost_seconds", 0.0))
        return cls(
            mode=binding.buffering,
            delay=seconds if seconds > 0 else None,
            smoothing=binding.smoothing,
            strength=float(binding.smoothing_strength),
            timeout=float(binding.timeout_seconds),
            lost=lost if lost > 0 else None,
        )


def one_euro_alpha(cutoff: np.ndarray | float, te: np.ndarray | float) -> np.ndarray:
    """Smoothing factor of a first-order low-pass at `cutoff` Hz for a step of `te` seconds."""
    tau = 1.0 / (2.0 * math.pi * np.asarray(cutoff))
    return 1.0 / (1.0 + tau / np.asarray(te))


class OneEuroFilter:
    """The One Euro filter (Casiez, Roussel, Vogel, CHI 2012), vectorised over rows.

    Each row (a joint) is a vector filtered with one cutoff from the norm of its smoothed
    derivative; for 1-vectors this is exactly the reference scalar filter. Rows are updated
    independently (`indices`), each with its own previous time.
    """

    def __init__(self, rows: int, dim: int, min_cutoff: float, beta: float, d_cutoff: float):
        self.min_cutoff, self.beta, self.d_cutoff = min_cutoff, beta, d_cutoff
        self.x = np.zeros((rows, dim))
        self.dx = np.zeros((rows, dim))
        self.t = np.full(rows, -np.inf)

    def __call__(self, indices: np.ndarray, x: np.ndarray, t: float) -> np.ndarray:
        te = t - self.t[indices]
        first = ~(te > 0)  # never seen, or time did not advance (a restarted clock): restart
        te = np.where(first, 1.0, te)[:, None]
        x_prev, dx_prev = self.x[indices], self.dx[indices]
        dx = (x - x_prev) / te
        dx_hat = (
            one_euro_alpha(self.d_cutoff, te) * dx
            + (1 - one_euro_alpha(self.d_cutoff, te)) * dx_prev
        )
        cutoff = self.min_cutoff + self.beta * np.linalg.norm(dx_hat, axis=1, keepdims=True)
        a = one_euro_alpha(cutoff, te)
        x_hat = a * x + (1 - a) * x_prev
        x_hat = np.where(first[:, None], x, x_hat)
        dx_hat = np.where(first[:, None], 0.0, dx_hat)
        self.x[indices], self.dx[indices], self.t[indices] = x_hat, dx_hat, t
        return x_hat


@dataclass(frozen=True)
class LivePose:
    """What a binding gives a frame: its bones' rotations, status and blend weight."""

    rotations: np.ndarray
    """(B, 4) unit quaternions (w, x, y, z) per source bone, identity where never received."""
    valid: np.ndarray
    """(B,) bool: bones received at least once."""
    root_position: np.ndarray | None
    """(3,) in source units, or None when the source sent none."""
    status: str
    weight: float
    """1 while connected or stale; falls to 0 over `blend` seconds once lost; 0 while waiting."""
    sample_time: float
    """Local monotonic time of the newest sample in this pose on the source's clock (nan while
    waiting)."""
    weights: dict[str, float] = field(default_factory=dict)
    """The source's blend shape weights by its names, the latest of each (empty: none sent)."""
    received: float = math.nan
    """Local monotonic time the newest sample in this pose arrived (nan while waiting): the
    start of its latency."""


@dataclass
class BindingCounters:
    """One binding's health, as every frame's report carries it."""

    status: str
    packets: int
    samples: int
    malformed: int
    ignored: int
    unknown_bones: int
    dropped: int
    """Everything sent that never reached a pose: the frames the buffer dropped (duplicates and
    out of order) plus the datagrams the kernel dropped (`kernel_dropped`)."""
    duplicates: int
    out_of_order: int
    kernel_dropped: int | None
    """Datagrams the kernel dropped before the receiver read them (its receive buffer was full:
    the receiver fell behind a flood), from the socket; None where the transport cannot tell
    (TCP, serial, a device, a replay) or the system does not say."""
    clock_resets: int
    reconnects: int
    last_seen: float | None
    """Seconds since the last sample (None: nothing yet)."""
    jitter_p50_ms: float | None
    jitter_p99_ms: float | None
    latency_p50_ms: float | None
    """Receive-to-pose latency per read: bytes read to decoded, and pushed to pose() where
    the read completes a frame."""
    latency_p99_ms: float | None

    def as_dict(self) -> dict:
        return dict(self.__dict__)  # flat scalars: asdict's deep copy cost 0.1 ms a frame


class _Clock:
    """One run of a stream's clock: its source times map to local time by the offset of its
    least-delayed sample (the smallest receive - timestamp of its last RECENT samples).

    A stream whose clock jumps starts a new one; every snapshot keeps the clock it was stamped
    on, so a restarted sender's new offset never moves the old stream's snapshots (it put them
    after the new ones: a take replayed the old stream). Times are kept relative to the clock's
    first timestamp, so a clock at 3e38 still maps to the receive clock's precision."""

    __slots__ = ("base", "offset", "offsets")

    def __init__(self, base: float) -> None:
        self.base = base
        self.offsets: deque[float] = deque(maxlen=RECENT)
        self.offset = math.inf

    def drift(self, ts: float, received: float) -> float:
        """How far a sample's offset is from the clock's (its delay over the least-delayed
        sample's; far negative: the sender's clock ran ahead)."""
        return received - (ts - self.base) - self.offset

    def add(self, ts: float, received: float) -> float:
        """Take a sample's offset into account; its time on the local clock."""
        self.offsets.append(received - (ts - self.base))
        self.offset = min(self.offsets)
        return ts - self.base + self.offset


class _Stream:
    """Ordering, clock and jitter state of one clock domain."""

    __slots__ = ("clock", "last_received", "last_ts")

    def __init__(self) -> None:
        self.last_ts = -math.inf
        self.last_received = -math.inf
        self.clock: _Clock | None = None

    def jumped(self, ts: float, received: float) -> bool:
        """Whether `ts` leaves the stream's clock: far behind its last timestamp (a restarted
        sender), or its offset from the receive clock moved by more than CLOCK_RESET_SECONDS
        (a clock that jumped ahead, or fell behind: a sender restarted after a pause)."""
        clock = self.clock
        if clock is None:
            return False
        return ts < self.last_ts - CLOCK_RESET_SECONDS or not (
            abs(clock.drift(ts, received)) <= CLOCK_RESET_SECONDS
        )


@dataclass(frozen=True, slots=True)
class _Snapshot:
    """The binding's state after one push, as the history keeps it."""

    rotations: np.ndarray
    valid: np.ndarray
    root: np.ndarray | None
    clock: _Clock
    """The clock its newest sample was stamped on (its local time follows that clock's offset
    as it improves)."""
    source: float
    """The newest sample's source time, relative to `clock.base`."""
    received: float
    """Local time the newest sample in it arrived."""
    weights: dict[str, float]
    """The blend shape weights as of it (the buffer's dict, replaced whole, never changed)."""


class _Ring:
    """The last `size` values of a measurement (jitter, latency) and their p50/p99 in ms.

    A preallocated array, not a deque: counters() runs every frame, and turning a 1,024-item
    deque into an array cost more than the rest of the binding's frame work. Appends come from
    receiver threads; `percentiles` reads without a lock (a value written meanwhile is either in
    this frame's figures or the next's) and recomputes only when values arrived since.
    """

    __slots__ = ("_cached", "count", "values")

    def __init__(self, size: int = 1024) -> None:
        self.values = np.zeros(size)
        self.count = 0
        self._cached: tuple[int, float | None, float | None] = (0, None, None)

    def append(self, value: float) -> None:
        self.values[self.count % len(self.values)] = value
        self.count += 1

    def extend(self, values) -> None:
        for value in values:
            self.append(float(value))

    def percentiles(self) -> tuple[float | None, float | None]:
        """p50 and p99 in ms of the kept values (numpy's default linear method)."""
        count, p50, p99 = self._cached
        if count == self.count:
            return p50, p99
        count = self.count
        n = min(count, len(self.values))
        if n == 0:
            return None, None
        # One partition (linear time) puts the four order statistics both percentiles need
        # where a full sort would.
        at = np.array([0.5, 0.99]) * (n - 1)
        lo = np.floor(at).astype(int)
        hi = np.minimum(lo + 1, n - 1)
        part = np.partition(self.values[:n], np.unique(np.concatenate([lo, hi])))
        p50, p99 = (part[lo] + (part[hi] - part[lo]) * (at - lo)) * 1e3
        self._cached = (count, float(p50), float(p99))
        return float(p50), float(p99)


@dataclass(frozen=True)
class _Published:
    """What the last push left for the frame thread (its arrays are never changed after)."""

    rotations: np.ndarray
    valid: np.ndarray
    root: np.ndarray | None
    sample_time: float
    last_seen: float
    weights: dict[str, float] = field(default_factory=dict)
    received: float = math.nan


def _local_times(snapshots: list[_Snapshot]) -> np.ndarray:
    """The snapshots' times on the local clock, each by its own clock's current offset, made
    non-decreasing (snapshots of several streams interleave)."""
    mapped = [snapshot.source + snapshot.clock.offset for snapshot in snapshots]
    return np.maximum.accumulate(np.array(mapped, dtype=np.float64))


class LiveBuffer:
    """Samples of one binding, pushed by a receiver thread and read by the frame thread.

    `push` holds one lock for constant-time array copies (never around I/O or decoding) and
    publishes the newest state as one immutable reference; `pose(now)` never waits for it.
    """

    def __init__(self, bones: tuple[str, ...], settings: BufferSettings | None = None) -> None:
        self.bones = tuple(bones)
        self.settings = s = settings or BufferSettings()
        if s.mode not in MODES:
            raise ValueError(f"buffer mode {s.mode!r} is not one of {MODES}")
        n = len(self.bones)
        self._lock = threading.Lock()
        self._current = np.zeros((n, 4))
        self._current[:, 0] = 1.0
        self._valid = np.zeros(n, dtype=bool)
        self._root: np.ndarray | None = None
        self._weights: dict[str, float] = {}
        """The latest weight of each blend shape the source named (not delayed: a face
        stream's weights are taken as they come)."""
        self._times: deque[float] = deque(maxlen=s.history)
        """Local time of each snapshot when it was pushed (orders snapshots across streams)."""
        self._snapshots: deque[_Snapshot] = deque(maxlen=s.history)
        """Mapped to local time at pose() with their clocks' offsets as known then (they only
        improve as samples arrive)."""
        self._streams: dict[int, _Stream] = {}
        self._last_seen = math.nan
        self._published: _Published | None = None
        """The newest state, replaced whole by each push: `pose` reads it without the lock."""
        self._held: tuple[np.ndarray, np.ndarray | None, float, np.ndarray, float] | None = None
        """The last delayed pose (rotations, root, sample time, valid, received), for a frame
        that finds the receiver mid-push."""
        self._jitter = _Ring()
        self._latency = _Ring()
        self.samples = self.duplicates = self.out_of_order = self.clock_resets = 0
        self._filter: OneEuroFilter | None = None
        if s.smoothing == "oneEuro" and s.strength > 0:
            cutoff = ONE_EURO_MAX_CUTOFF * (1.0 - s.strength) ** 2
            self._filter = OneEuroFilter(n, 4, cutoff, ONE_EURO_BETA, ONE_EURO_D_CUTOFF)

    # -- receiver side -------------------------------------------------------------------
    def push(self, frame: SourceFrame, received: float) -> bool:
        """Add a frame received at local monotonic time `received`; False if it was dropped."""
        with self._lock:
            stream = self._streams.get(frame.stream)
            if stream is None:
                stream = self._streams[frame.stream] = _Stream()
            ts = frame.timestamp
            clock = stream.clock
            if clock is None or stream.jumped(ts, received):
                if clock is not None:
                    self.clock_resets += 1
                clock = stream.clock = _Clock(ts)
            elif ts == stream.last_ts:
                self.duplicates += 1
                return False
            elif ts < stream.last_ts:
                self.out_of_order += 1
                return False
            else:
                self._jitter.append(abs((received - stream.last_received) - (ts - stream.last_ts)))
            stream.last_ts, stream.last_received = ts, received
            local = clock.add(ts, received)  # the least-delayed sample fixes the clock offset
            rotations = self._smooth(frame, ts)
            idx = frame.indices
            self._current[idx] = rotations
            self._valid[idx] = True
            if frame.root_position is not None:
                self._root = frame.root_position
            if frame.weights:
                self._weights = {**self._weights, **frame.weights}  # replaced whole: shared
            valid = self._valid.copy()
            state = (self._current.copy(), valid, self._root)
            if self._times and local <= self._times[-1]:
                # Another stream's sample at or before the last snapshot: update that snapshot
                # (snapshot times stay strictly increasing for the delayed lookup).
                last = self._snapshots[-1]
                snapshot = _Snapshot(*state, last.clock, last.source, received, self._weights)
                self._snapshots[-1] = snapshot
            else:
                self._times.append(local)
                snapshot = _Snapshot(*state, clock, ts - clock.base, received, self._weights)
                self._snapshots.append(snapshot)
            self._last_seen = received
            self.samples += len(idx)
            # The frame thread reads this without the lock: one reference, replaced whole.
            self._published = _Published(
                self._snapshots[-1].rotations,
                valid,
                self._root,
                self._times[-1],
                received,
                self._weights,
                received,
            )
            return True

    def _smooth(self, frame: SourceFrame, ts: float) -> np.ndarray:
        q = frame.rotations
        idx = frame.indices
        prev = self._current[idx]
        # Same hemisphere as the previous value, so filters and slerp take the short arc.
        q = np.where(np.sum(q * prev, axis=1, keepdims=True) < 0, -q, q)
        s = self.settings
        if self._filter is not None:
            q = self._filter(idx, q, ts)
        elif s.smoothing == "exponential" and s.strength > 0:
            q = np.where(self._valid[idx, None], quat_slerp(prev, q, 1.0 - s.strength), q)
        return q / np.linalg.norm(q, axis=1, keepdims=True)

    def note_latency(self, seconds: float) -> None:
        """Record one packet's receive-to-pose latency (the transport times read to push)."""
        with self._lock:  # receivers of a multi-device source append from several threads
            self._latency.append(seconds)

    # -- frame side ----------------------------------------------------------------------
    def _status(self, now: float, last_seen: float) -> str:
        if math.isnan(last_seen):
            return WAITING
        age = now - last_seen
        if age <= self.settings.timeout:
            return CONNECTED
        return STALE if age <= self.settings.lost_after else LOST

    def pose(self, now: float | None = None) -> LivePose:
        """The binding's pose at local monotonic time `now` (default: time.monotonic()).

        Never waits for the receiver: `latest` reads the state the last push published (one
        reference), and `delayed` takes the lock only if it is free; a frame that finds a push
        in progress takes the previous delayed pose (at most one frame older). The receiver
        holds the lock across Python code, so it can lose the GIL there: waiting on it would
        cost the frame up to the interpreter's switch interval (5 ms) per wait.
        """
        now = time.monotonic() if now is None else now
        s = self.settings
        published = self._published
        if published is None:
            n = len(self.bones)
            rotations = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
            return LivePose(rotations, np.zeros(n, dtype=bool), None, WAITING, 0.0, math.nan)
        status = self._status(now, published.last_seen)
        rotations, root, sample_time, valid, received = (
            published.rotations,
            published.root,
            published.sample_time,
            published.valid,
            published.received,
        )
        if s.mode != LATEST and len(self._times) >= 2:
            if self._lock.acquire(blocking=False):
                try:
                    recent = islice(self._snapshots, max(0, len(self._snapshots) - RECENT), None)
                    rotations, root, sample_time, received = self._delayed(now, list(recent))
                    valid = self._valid.copy()
                    self._held = (rotations, root, sample_time, valid, received)
                finally:
                    self._lock.release()
            elif self._held is not None:
                rotations, root, sample_time, valid, received = self._held
        weight = 1.0
        if status == LOST:
            gone = now - (published.last_seen + s.lost_after)
            weight = max(0.0, 1.0 - gone / s.blend) if s.blend > 0 else 0.0
        # Copies: the caller may keep or change them; the published arrays are shared.
        return LivePose(
            rotations.copy(),
            valid.copy(),
            None if root is None else np.array(root, dtype=np.float64),
            status,
            weight,
            sample_time,
            dict(published.weights),
            received,
        )

    def pose_at(self, when: float) -> LivePose:
        """The pose a frame at local monotonic time `when` (now or past) shows, from the kept
        snapshots received by then: the newest one (latest), or the pose `delay` before `when`
        among them (delayed). A frame (when = now) and a take tick (when = its due time, also
        for a recorder catching up after a stall) read the same way, so a take holds what the
        screen showed. Never waits for the receiver: the history is copied in one C-level step
        (no other thread runs during it) and each snapshot is immutable. Before the first
        snapshot: the waiting pose."""
        n = len(self.bones)
        last = self._snapshots[-1] if self._snapshots else None
        if self.settings.mode == LATEST and last is not None and last.received <= when:
            snapshots, end = [last], 1  # a frame now: the newest, without copying the history
        else:
            snapshots = list(self._snapshots)  # one consistent copy, without the lock
            end = len(snapshots)
        while end and snapshots[end - 1].received > when:  # arrived after `when`: not yet there
            end -= 1
        if not end:
            rest = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
            return LivePose(rest, np.zeros(n, bool), None, WAITING, 0.0, math.nan)
        newest = snapshots[end - 1]
        if self.settings.mode == DELAYED and end >= 2:
            window = snapshots[max(0, end - RECENT) : end]
            if end > RECENT and when - self._delay() < _local_times(window)[0]:
                window = snapshots[:end]  # a recorder far behind: look through them all
            rotations, root, sample_time, received = self._delayed(when, window)
        else:
            rotations, root = newest.rotations, newest.root
            sample_time, received = _local_times([newest])[0], newest.received
        s = self.settings
        status = self._status(when, newest.received)
        weight = 1.0
        if status == LOST:
            gone = when - (newest.received + s.lost_after)
            weight = max(0.0, 1.0 - gone / s.blend) if s.blend > 0 else 0.0
        return LivePose(
            rotations.copy(),
            newest.valid.copy(),
            None if root is None else np.array(root, dtype=np.float64),
            status,
            weight,
            float(sample_time),
            dict(newest.weights),
            received,
        )

    def _delay(self) -> float:
        """Seconds `delayed` looks back: `delay`, or one sample interval."""
        return self.settings.delay if self.settings.delay is not None else self._sample_interval()

    def _delayed(
        self, now: float, snapshots: list[_Snapshot]
    ) -> tuple[np.ndarray, np.ndarray | None, float, float]:
        """The pose `delay` seconds before `now`, slerped between the two of `snapshots` (in
        order, the newest last) around it."""
        times = _local_times(snapshots)
        target = now - self._delay()
        i = int(np.searchsorted(times, target, side="right"))
        if i == 0 or i == len(times):
            k = 0 if i == 0 else -1
            snapshot = snapshots[k]
            return snapshot.rotations, snapshot.root, float(times[k]), snapshot.received
        t0, t1 = times[i - 1], times[i]
        a, b = snapshots[i - 1], snapshots[i]
        u = (target - t0) / (t1 - t0) if t1 > t0 else 1.0
        rotations = quat_slerp(a.rotations, b.rotations, u)
        p0, p1 = a.root, b.root
        root = p0 if p0 is None or p1 is None else p0 + u * (p1 - p0)
        return rotations, root, float(target), b.received

    def _sample_interval(self) -> float:
        times = list(self._times)[-33:]
        return float(np.median(np.diff(times))) if len(times) > 1 else 0.0

    def counters(
        self,
        now: float | None = None,
        decoded: DecodeCounters | None = None,
        reconnects: int = 0,
        kernel_dropped: int | None = None,
    ) -> BindingCounters:
        """A snapshot of this binding's status and counters (decoder counts from `decoded`, the
        transport's reconnects and the datagrams its kernel dropped)."""
        now = time.monotonic() if now is None else now
        d = decoded or DecodeCounters()
        # No lock (the frame thread calls this every frame): single reads, and the rings'
        # percentiles from their own arrays.
        seen = self._last_seen
        status = self._status(now, seen)
        last_seen = None if math.isnan(seen) else now - seen
        jitter_p50, jitter_p99 = self._jitter.percentiles()
        latency_p50, latency_p99 = self._latency.percentiles()

        return BindingCounters(
            status=status,
            packets=d.packets,
            samples=self.samples,
            malformed=d.malformed,
            ignored=d.ignored,
            unknown_bones=d.unknown_bones,
            dropped=self.duplicates + self.out_of_order + (kernel_dropped or 0),
            duplicates=self.duplicates,
            out_of_order=self.out_of_order,
            kernel_dropped=kernel_dropped,
            clock_resets=self.clock_resets,
            reconnects=reconnects,
            last_seen=last_seen,
            jitter_p50_ms=jitter_p50,
            jitter_p99_ms=jitter_p99,
            latency_p50_ms=latency_p50,
            latency_p99_ms=latency_p99,
        )
