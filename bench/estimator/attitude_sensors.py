"""The attitude estimator's sensor inputs: `sense/gyro`, `sense/mag` and `sense/star` gathered into ticks.

Each sensor has its own topic and rate. The plant publishes a tick's magnetometer and star-tracker
samples before its gyro sample, over one session, and the estimator reads them through one
subscriber (`sense/*`), which keeps that order (three subscribers do not); the gyro closes the tick. The estimator knows its sensors' schedule (their rates, from the scenario's
[attitude.sensors], are what the flight software configures them to):
- lock-step: for a tick whose schedule has a magnetometer or star-tracker sample, it waits up to
  `wait_s` for it (a star tracker in an outage still reports, without a fix), so the processes fuse
  exactly the samples the in-process loop fuses;
- real-time: it waits at most a few milliseconds for a scheduled sample, and takes what has
  arrived; a sample that comes after its tick was closed is late, counted and dropped.

A message that decodes but whose values are unusable (non-finite, a zero model field, a star-tracker
quaternion that is not unit, a tick beyond the run) is counted under its topic in `malformed` and
dropped, as NodeContext.subscribe does with payloads that do not decode. A gyro sample refused that
way still closes its tick: the estimator holds the previous gyro sample over it.
"""
from __future__ import annotations

import threading
import time
from collections import Counter
from dataclasses import dataclass

import numpy as np

from bench.bus import keys
from bench.bus.schemas import GyroSample, Header, MagnetometerSample, Message, StarTrackerSample

UNIT_QUATERNION_TOLERANCE = 1e-3      # the smoother's (bench.estimator.attitude._rotation)


@dataclass(frozen=True)
class SensorSchedule:
    """Which plant ticks carry a magnetometer or star-tracker sample (the gyro is on every tick)."""

    magnetometer_every: int       # 0: not on a schedule (sampled in the board's coil-blanking windows)
    star_tracker_every: int

    @classmethod
    def from_sensors(cls, sensors) -> "SensorSchedule":
        """From [attitude.sensors] (AttitudeSensorsConfig): periods as whole numbers of gyro ticks."""
        scheduled = sensors.magnetometer_sampling == "schedule"
        return cls(int(round(sensors.magnetometer_period_s * sensors.gyro_rate_hz)) if scheduled else 0,
                   int(round(sensors.star_tracker_period_s * sensors.gyro_rate_hz)))

    def has_magnetometer(self, k: int) -> bool:
        return self.magnetometer_every > 0 and k % self.magnetometer_every == 0

    def has_star_tracker(self, k: int) -> bool:
        return k % self.star_tracker_every == 0


@dataclass
class SensorTick:
    """The samples of plant tick `seq` as the estimator fuses them (None: none this tick)."""

    seq: int
    sim_time_s: float
    header: Header | None                     # the gyro's (else the first sample's) header
    gyro_radps: list | None = None            # None: lost or refused, the previous one is held
    magnetometer_t: list | None = None
    field_model_inertial_t: list | None = None
    star_tracker_wxyz: list | None = None


def refusal(message: Message, n_steps: int) -> str | None:
    """Why a decoded sensor message cannot be used, or None."""
    if message.header.seq >= n_steps:
        return f"tick {message.header.seq} is beyond the run's {n_steps} steps"
    if not np.isfinite(message.header.sim_time_s):
        return "sim_time_s is not finite"
    if isinstance(message, GyroSample):
        if not np.all(np.isfinite(message.rate_radps)):
            return "rate_radps is not finite"
    elif isinstance(message, MagnetometerSample):
        if not (np.all(np.isfinite(message.field_body_t)) and np.all(np.isfinite(message.field_model_inertial_t))):
            return "field is not finite"
        if not np.linalg.norm(message.field_model_inertial_t) > 0:
            return "field_model_inertial_t is zero"
    elif isinstance(message, StarTrackerSample) and message.q_wxyz is not None:
        q = np.asarray(message.q_wxyz, dtype=float)
        if not np.all(np.isfinite(q)):
            return "q_wxyz is not finite"
        if abs(np.linalg.norm(q) - 1.0) > UNIT_QUATERNION_TOLERANCE:
            return f"q_wxyz is not a unit quaternion (norm {np.linalg.norm(q):.6g})"
    return None


class SensorInbox:
    """The three sensor subscriptions (Zenoh threads add) and the estimator loop (takes ticks)."""

    TOPICS = {GyroSample: keys.SENSE_GYRO, MagnetometerSample: keys.SENSE_MAG, StarTrackerSample: keys.SENSE_STAR}

    def __init__(self, schedule: SensorSchedule, n_steps: int, step_s: float, wait_s: float, malformed: Counter,
                 log=None):
        self.schedule = schedule
        self.n_steps = n_steps
        self.step_s = step_s
        self.wait_s = wait_s                # lock-step: how long a scheduled sample is waited for
        self.malformed = malformed          # the node's per-topic count (NodeContext.malformed)
        self.late: Counter = Counter()      # samples that came after their tick was closed
        self.missing: Counter = Counter()   # scheduled samples that never came in time
        self.log = log
        self._cond = threading.Condition()
        self._samples: dict[str, dict[int, Message]] = {topic: {} for topic in self.TOPICS.values()}
        self._refused_gyro: set[int] = set()    # ticks whose gyro came but was refused
        self._next: int | None = None           # the next tick to close

    # --- Zenoh threads ----------------------------------------------------------------------
    def add(self, message: Message) -> None:
        topic = self.TOPICS[type(message)]
        reason = refusal(message, self.n_steps)
        with self._cond:
            seq = message.header.seq
            if reason is not None:
                self.malformed[topic] += 1
                if self.log is not None and self.malformed[topic] <= 5:
                    self.log.warning("%s sample %d refused: %s", topic, seq, reason)
                if topic == keys.SENSE_GYRO and seq < self.n_steps:
                    self._refused_gyro.add(seq)
                    self._cond.notify_all()
                return
            if self._next is not None and seq < self._next:
                self.late[topic] += 1
                return
            self._samples[topic][seq] = message
            self._cond.notify_all()

    # --- the estimator loop -----------------------------------------------------------------
    def next_tick(self, stop: threading.Event, poll_s: float = 0.02) -> SensorTick | None:
        """The next tick once its gyro sample (or a later tick's) is in; None when told to stop."""
        with self._cond:
            while True:
                if stop.is_set():
                    return None
                closing = [s for s in (*self._samples[keys.SENSE_GYRO], *self._refused_gyro)
                           if self._next is None or s >= self._next]
                if closing:
                    break
                self._cond.wait(poll_s)
            k = min(closing) if self._next is None else self._next
            self._refused_gyro.discard(k)
            gyro = self._samples[keys.SENSE_GYRO].pop(k, None)
            mag = self._take(keys.SENSE_MAG, k, self.schedule.has_magnetometer(k), stop)
            star = self._take(keys.SENSE_STAR, k, self.schedule.has_star_tracker(k), stop)
            self._next = k + 1
            for topic, samples in self._samples.items():     # anything older is late
                for seq in [s for s in samples if s < self._next]:
                    del samples[seq]
                    self.late[topic] += 1
            self._refused_gyro = {s for s in self._refused_gyro if s >= self._next}
        first = next((m for m in (gyro, mag, star) if m is not None), None)
        return SensorTick(
            k, first.header.sim_time_s if first is not None else k * self.step_s,
            first.header if first is not None else None,
            None if gyro is None else gyro.rate_radps,
            None if mag is None else mag.field_body_t, None if mag is None else mag.field_model_inertial_t,
            None if star is None else star.q_wxyz)

    def _take(self, topic: str, k: int, scheduled: bool, stop: threading.Event) -> Message | None:
        """Tick k's sample on `topic`; if the schedule has one, wait up to wait_s for it (lock held)."""
        samples = self._samples[topic]
        if scheduled and k not in samples and self.wait_s > 0:
            deadline = time.monotonic() + self.wait_s
            while k not in samples and not stop.is_set():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self._cond.wait(remaining)
        if scheduled and k not in samples:
            self.missing[topic] += 1
        return samples.pop(k, None)
