"""The launcher's progress watchdog: a run whose steps stop advancing ends, naming the stage that
stopped, whatever stopped it (issue 44).

Liveliness finds a process that died or stopped. Nothing found a run whose processes all live on
while its steps stop or creep: a magnetorquer board that no longer got commands left a lock-step
plant waiting `run.command_timeout_s` + 1 s for each step's report, 600 steps in 1.8 hours, every
process alive. The watchdog judges the plant's own signed reports (StepDone: a step integrated;
and, when the plant has waited a second for something, what it waits for: bench/plant/stepping.py
WaitReport), with the processes' states to say who is stopped, and nothing else.

The bound (`stall_bound`), derived from the scenario:
- lock-step: the plant waits at most `run.command_timeout_s` for any one thing it needs for a step
  (the controller's command; on the CAN bus the board's report of it). The run has stalled when
  the plant has neither finished a step nor begun a new wait (what it waited for came) for that
  plus LOCKSTEP_MARGIN_S: 10.5 s with the defaults. The margin is below the 1 s the plant adds for
  a later frame's report, so a report that never comes stops the run instead of letting it creep.
- real time: the plant steps every `plant step / run.time_factor` of wall time whether commands
  come or not. The run has stalled when no step is done, or no command has come (on time or late),
  for `run.liveliness.stall_periods` periods (default 50), and at least REALTIME_MIN_BOUND_S. (A
  command gap is judged by what the plant reports, every second: up to a second after the bound.)
- before the loop has started (no step done, no wait reported): `run.liveliness.startup_timeout_s`
  more, the time the plant gives its peers to be ready.
A launcher that was itself not scheduled (two looks more than LATE_LOOK_S apart) does not count
the time it missed against the run.

Pure: no Zenoh, no processes; time is passed in (tests drive it with a fake clock). The launcher
feeds it (bench/launcher/follow.py `_follow_run`) and raises the stall as NodeFailed: exit 1.
"""
from __future__ import annotations

from dataclasses import dataclass

from bench.bus import keys
from bench.bus.can.sim_window import bus_on_simulated_time

LOCKSTEP_MARGIN_S = 0.5
REALTIME_MIN_BOUND_S = 5.0
LATE_LOOK_S = 1.0
WAIT_REPORT_S = 1.0        # the plant's (bench/plant/stepping.py): a real-time wait is reported this often


@dataclass(frozen=True)
class StallBound:
    seconds: float
    how: str               # the bound as a reader checks it against the scenario
    startup_s: float       # added until the loop has started


def stall_bound(scenario) -> StallBound:
    run = scenario.run
    if run.mode == "lock-step":
        return StallBound(run.command_timeout_s + LOCKSTEP_MARGIN_S,
                          f"lock-step: the plant's own wait, run.command_timeout_s = {run.command_timeout_s:g} s, "
                          f"+ {LOCKSTEP_MARGIN_S:g} s", run.liveliness.startup_timeout_s)
    period_s = scenario.step_s / run.time_factor
    periods = run.liveliness.stall_periods
    return StallBound(max(periods * period_s, REALTIME_MIN_BOUND_S),
                      f"real time: run.liveliness.stall_periods = {periods} periods of {period_s:g} s, "
                      f"at least {REALTIME_MIN_BOUND_S:g} s", run.liveliness.startup_timeout_s)


def stage_names(scenario) -> dict[str, str]:
    """What the plant waits for (a topic) -> the stage that owes it, as the stall's message says it."""
    names = {keys.COMMAND_THRUST: "no command from 'controller'", keys.COMMAND_DIPOLE: "no command from 'controller'"}
    if getattr(scenario, "can", None) is not None:
        if "board" in scenario.run.external:
            names[keys.ACTUATOR_MTQ] = "no board telemetry (the external board has not acknowledged the command)"
        elif bus_on_simulated_time(scenario):
            names[keys.ACTUATOR_MTQ] = "no board telemetry (the CAN bus and board, 'canbus', have not reported the coils)"
        else:
            names[keys.ACTUATOR_MTQ] = ("no board telemetry (the board 'mtq', behind the bus model 'canbus', has not "
                                        "reported the command)")
    return names


@dataclass(frozen=True)
class Stall:
    step: int              # the step the plant did not finish
    what: str              # the stage: what the plant waits for and from whom, or that it reports no wait
    seconds: float         # how long nothing has moved

    def describe(self, bound: StallBound, stopped: list[str] = ()) -> str:
        text = f"run stalled at step {self.step}: {self.what} for {self.seconds:.1f} s (bound {bound.seconds:g} s; {bound.how})"
        for name in stopped:
            text += f"; process '{name}' is stopped (state T)"
        return text


@dataclass
class _Wait:
    step: int
    topic: str
    started_s: float       # on the launcher's clock: when the report came, less what the plant had waited
    heard_s: float


class ProgressWatchdog:
    def __init__(self, bound: StallBound, lock_step: bool, stages: dict[str, str], now_s: float,
                 period_s: float = 0.0, plant_wait_s: float | None = None):
        """period_s: real time, the plant's wall period. plant_wait_s: lock-step, how long the plant
        waits for one thing before it gives up (`gave_up`)."""
        self.bound = bound
        self.lock_step = lock_step
        self.plant_wait_s = plant_wait_s
        self.stages = stages
        self.steps_done = 0
        self.started = False
        self._progress_s = now_s               # the last step done (or the watch's start)
        self._last_look_s = now_s
        self._wait: _Wait | None = None
        # A real-time wait report is current while its repetitions keep coming.
        self._fresh_s = 3 * max(WAIT_REPORT_S, period_s)

    @classmethod
    def for_scenario(cls, scenario, now_s: float) -> "ProgressWatchdog":
        lock_step = scenario.run.mode == "lock-step"
        return cls(stall_bound(scenario), lock_step, stage_names(scenario), now_s,
                   0.0 if lock_step else scenario.step_s / scenario.run.time_factor,
                   scenario.run.command_timeout_s if lock_step else None)

    # --- what the plant reports -------------------------------------------------------------
    def step_done(self, steps_done: int, now_s: float) -> None:
        """Steps done so far (the progress the launcher counts from the plant's signed StepDone)."""
        if steps_done > self.steps_done:
            self.steps_done, self._progress_s, self.started = steps_done, now_s, True
            if self.lock_step:
                self._wait = None          # that step's waits are over

    def plant_waits(self, step: int, topic: str, waited_s: float, now_s: float) -> None:
        """A wait report: the plant has waited `waited_s` for `topic`, for step `step`."""
        if self.lock_step and step < self.steps_done:
            return                         # of a step done since (reports may overtake each other)
        self.started = True
        started_s = now_s - waited_s
        if self._wait is not None and (self._wait.step, self._wait.topic) == (step, topic):
            started_s = min(started_s, self._wait.started_s)   # the same wait, reported again
        self._wait = _Wait(step, topic, started_s, now_s)

    # --- the judgement ----------------------------------------------------------------------
    def look(self, now_s: float) -> Stall | None:
        """A stall, if nothing has moved for the bound (once per look of the launcher)."""
        late_s = now_s - self._last_look_s - LATE_LOOK_S
        if late_s > 0:
            # The launcher itself was not scheduled: that time is nobody's stall.
            self._progress_s += late_s
            if self._wait is not None:
                self._wait.started_s += late_s
                self._wait.heard_s += late_s
        self._last_look_s = now_s
        bound_s = self.bound.seconds + (0.0 if self.started else self.bound.startup_s)
        stall = self._stall(now_s)
        return stall if stall.seconds >= bound_s else None

    def gave_up(self, now_s: float) -> Stall | None:
        """The plant exited with an error: if it had been waiting for something about as long as it
        waits in lock-step (it gave up on it), the stage it waited for is the cause."""
        wait = self._current_wait(now_s)
        if wait is None or self.plant_wait_s is None or now_s - wait.started_s < 0.95 * self.plant_wait_s:
            return None
        return Stall(wait.step, self.stages.get(wait.topic, f"nothing on '{wait.topic}'"), now_s - wait.started_s)

    def _current_wait(self, now_s: float) -> _Wait | None:
        wait = self._wait
        if wait is None:
            return None
        if self.lock_step:
            return wait if wait.step >= self.steps_done else None
        return wait if now_s - wait.heard_s <= self._fresh_s else None

    def _stall(self, now_s: float) -> Stall:
        wait = self._current_wait(now_s)
        if self.lock_step:
            if wait is not None:           # the step's latest wait: the stage it is stuck on
                return Stall(wait.step, self.stages.get(wait.topic, f"nothing on '{wait.topic}'"),
                             now_s - max(wait.started_s, self._progress_s))
            what = "the plant has not finished it and reports no wait" if self.started else "the loop has not started"
            return Stall(self.steps_done, what, now_s - self._progress_s)
        since_step_s = now_s - self._progress_s
        # Real time: as long as the plant last said it had waited (it says so again every second
        # while the wait lasts, and nothing when it ends: more would be a guess).
        if wait is not None and wait.heard_s - wait.started_s > since_step_s:
            return Stall(self.steps_done, self.stages.get(wait.topic, f"nothing on '{wait.topic}'"),
                         wait.heard_s - wait.started_s)
        what = "the plant has done no step" if self.started else "the loop has not started"
        return Stall(self.steps_done, what, since_step_s)
