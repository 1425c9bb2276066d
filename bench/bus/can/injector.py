"""What each fault of faults.py does to the frames in the bus model.

The bus model hands every frame a node submits to `FaultInjector.on_submit`, asks `babbler` for
the flood's frames when the bus is free, and asks `destroys` before each transmission attempt.
Each fault acts only inside its window, on its target frames, on every `every`-th of them, until
it has affected `count` frames; every action is logged (InjectionRecord) so that a test can
account for every frame and measure detection latency from the moment of injection. The hardware
faults (the board's power and coils) touch no frame here: the injector arms them with the others
(`hardware`, bench/bus/can/coils.py), for the board beside it and for the bus model, which takes a
board without power off the bus.
"""
from __future__ import annotations

import random
from dataclasses import dataclass, field

import can

from bench.bus.can import protocol as p
from bench.bus.can.coils import CoilHardware
from bench.bus.can.faults import FaultSpec
from bench.bus.spill import SpilledJson

SOURCE_INJECTOR = "injector"


@dataclass(eq=False)   # queues remove by identity: two copies of a frame are two transmissions
class Transmission:
    """A frame waiting for the bus: who sent it, when, and which nodes will hear it."""
    msg: can.Message
    source: str
    submitted_ns: int
    ready_ns: int
    destinations: tuple[str, ...]
    fault: str | None = None     # the fault that injected or altered it
    held: bool = False           # held back on the bus (by the injector), not in its sender's queue
    after: "Transmission | None" = None   # an injected frame goes only once this one has left its queue


@dataclass(frozen=True)
class InjectionRecord:
    t_ns: int
    fault: str                   # "<index>:<name>" of the fault in the scenario
    # dropped, delayed, injected, replaced, destroyed (a genuine frame, by an error frame: its
    # controller retries it), collided (an injected frame in a collision: nobody retries it)
    action: str
    frame_id: int
    data: str                    # hex of the frame as it now is (the original for "dropped")
    original: str = ""           # hex of the original for "replaced"


@dataclass
class SubmitOutcome:
    queued: list[Transmission] = field(default_factory=list)
    dropped: list[tuple[can.Message, str]] = field(default_factory=list)   # (frame, reason)
    replaced: list[can.Message] = field(default_factory=list)              # originals of altered frames


def _copy(msg: can.Message, data: bytes | None = None) -> can.Message:
    return can.Message(arbitration_id=msg.arbitration_id, is_extended_id=msg.is_extended_id,
                       is_remote_frame=msg.is_remote_frame, dlc=msg.dlc, is_fd=msg.is_fd,
                       data=bytes(msg.data) if data is None else data)


def _with_counter(msg: can.Message, counter: int) -> bytes:
    data = bytearray(msg.data)
    data[1] = (data[1] & 0xF0) | (counter % p.COUNTER_MODULO)
    return bytes(data)


class ActiveFault:
    """One fault of the scenario while the bus model runs."""

    def __init__(self, spec: FaultSpec, index: int, protocol: p.Protocol, seed: int, wall_s_per_sim_s: float = 1.0):
        self.spec = spec
        self.wall_s_per_sim_s = wall_s_per_sim_s
        self.label = f"{index}:{spec.name}"
        self.protocol = protocol
        self.start_ns: int | None = None   # set by arm(): nothing happens before
        self.end_ns: int | None = None
        # MTQ_CMD names the command of the bus's profile (MTQ_CMD_AUTH under "secoc").
        self.frame_ids = {protocol.frame_ids[protocol.resolve(name)] for name in spec.target_frames()}
        # One stream per fault: from the run's seed, the fault's place and its own seed parameter.
        self.rng = random.Random(f"{seed}:{index}:{spec.params.get('seed', 0)}")
        self.matched = 0
        self.affected = 0

    def arm(self, t0_ns: int) -> None:
        self.start_ns, self.end_ns = self.spec.window_ns(t0_ns, self.wall_s_per_sim_s)

    def in_window(self, t_ns: int) -> bool:
        return self.start_ns is not None and self.start_ns <= t_ns and (self.end_ns is None or t_ns < self.end_ns)

    def active(self, t_ns: int) -> bool:
        in_window = self.in_window(t_ns)
        return in_window and not (self.spec.count and self.affected >= self.spec.count)

    def takes(self, msg: can.Message, t_ns: int) -> bool:
        """Whether this fault acts on this frame (and count it if so)."""
        if msg.arbitration_id not in self.frame_ids or msg.is_error_frame or not self.active(t_ns):
            return False
        self.matched += 1
        if (self.matched - 1) % self.spec.every:
            return False
        self.affected += 1
        return True

    def apply(self, tx: Transmission, outcome: SubmitOutcome, injector: "FaultInjector") -> bool:
        """Act on a frame this fault took; False if the frame is gone (dropped)."""
        raise NotImplementedError


class Drop(ActiveFault):
    def apply(self, tx, outcome, injector):
        injector.drop(tx, outcome, self.label)
        return False


class Delay(ActiveFault):
    def apply(self, tx, outcome, injector):
        tx.ready_ns += round(self.spec.param("delay_s") * 1e9)
        tx.held = True   # later frames of the same sender overtake it, as behind a slow gateway
        injector.record(tx.submitted_ns, self.label, "delayed", tx.msg)
        return True


class Duplicate(ActiveFault):
    def apply(self, tx, outcome, injector):
        for _ in range(int(self.spec.param("copies"))):
            injector.inject(tx.msg, tx.ready_ns, outcome, self.label, after=tx)
        return True


class Replay(ActiveFault):
    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.recorded: can.Message | None = None
        self.recorded_ns = 0

    def apply(self, tx, outcome, injector):
        if self.recorded is None:
            self.recorded, self.recorded_ns = _copy(tx.msg), tx.submitted_ns
            self.affected -= 1   # recording is not an injection
            return True
        if tx.submitted_ns - self.recorded_ns >= self.spec.param("after_s") * 1e9:
            injector.inject(self.recorded, tx.ready_ns, outcome, self.label, after=tx)
        else:
            self.affected -= 1
        return True


class Corrupt(ActiveFault):
    """The same bits, drawn once from the seed, flipped in every frame it takes (a stuck wire or
    a bad memory cell rather than noise: every affected frame is wrong the same way)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        # Data bits only: a flipped counter bit selects another data id, which can mask the
        # corruption (E2E profile 2's known weakness, shown in test_can_protocol).
        candidates = [b for b in range(64) if b not in p.COUNTER_BITS]
        self.bits = sorted(self.rng.sample(candidates, int(self.spec.param("bits"))))

    def apply(self, tx, outcome, injector):
        data = bytearray(tx.msg.data)
        for bit in self.bits:
            if bit < 8 * len(data):
                data[bit // 8] ^= 1 << (bit % 8)
        altered = _copy(tx.msg, bytes(data))
        if self.spec.param("recompute_crc") and self.protocol.name_of(altered.arbitration_id):
            altered = self.protocol.reprotect(altered)
        injector.replace(tx, altered, outcome, self.label)
        return True


class Spoof(ActiveFault):
    """A forged command right after each genuine one, with the next alive counter. On the secoc
    profile the spoofer knows everything but the key: the frame layout, the data ids, the
    freshness scheme (it takes the genuine frame's freshness value plus one tick) and computes a
    MAC with a key of its own."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.attacker = p.Protocol(self.protocol.node_id, self.protocol.profile,
                                   key=bytes(self.rng.randrange(256) for _ in range(16)))

    def apply(self, tx, outcome, injector):
        frame = self.protocol.decode(tx.msg)
        counter = (frame.counter + 1) if frame is not None and frame.counter is not None else 0
        dipole = [self.spec.param("dipole_am2")] * 3
        freshness = None
        if frame is not None and "Freshness" in frame.signals:
            freshness = int(frame.signals["Freshness"]) + 1
        forged = self.attacker.encode(self.attacker.command_name,
                                      {"Mode": p.MODE_DIPOLE, **{f"Dipole{a}": v for a, v in zip(p.AXES, dipole)}},
                                      counter, freshness if freshness is not None else 0)
        if not self.spec.param("knows_data_id"):
            forged = self.protocol.reprotect(forged, data_ids=(int(self.spec.param("data_id")),) * p.COUNTER_MODULO)
        injector.inject(forged, tx.ready_ns, outcome, self.label, after=tx)
        return True


class CounterFreeze(ActiveFault):
    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.frozen: int | None = None

    def apply(self, tx, outcome, injector):
        current = tx.msg.data[1] & 0x0F
        if self.frozen is None:
            self.frozen = current
        altered = self.protocol.reprotect(_copy(tx.msg, _with_counter(tx.msg, self.frozen)))
        if bytes(altered.data) != bytes(tx.msg.data):
            injector.replace(tx, altered, outcome, self.label)
        return True


class CounterOffset(ActiveFault):
    def apply(self, tx, outcome, injector):
        counter = (tx.msg.data[1] & 0x0F) + int(self.spec.param("offset"))
        injector.replace(tx, self.protocol.reprotect(_copy(tx.msg, _with_counter(tx.msg, counter))), outcome, self.label)
        return True


class HardwareFault(ActiveFault):
    """A fault of the board's hardware (coils.py): no frame is its to touch; armed and reported here."""

    def takes(self, msg, t_ns):
        return False


class TelemetryFreeze(ActiveFault):
    """The board's telemetry keeps its values from the fault's start; the board and its coils go on
    as commanded (a frozen telemetry buffer, not a stuck actuator)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.frozen: dict[int, bytes] = {}

    def apply(self, tx, outcome, injector):
        frame_id = tx.msg.arbitration_id
        if frame_id not in self.frozen:
            self.frozen[frame_id] = bytes(tx.msg.data)
            return True
        frozen = self.frozen[frame_id]
        if not self.spec.param("freeze_counter"):
            # The board's E2E layer protects whatever its application hands it.
            frozen = bytes(self.protocol.reprotect(_copy(tx.msg, _with_counter(_copy(tx.msg, frozen),
                                                                               tx.msg.data[1] & 0x0F))).data)
        if frozen != bytes(tx.msg.data):
            injector.replace(tx, _copy(tx.msg, frozen), outcome, self.label)
        return True


class Flood(ActiveFault):
    """A babbling node: not triggered by frames, it wants the bus all through its window."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.frame_ids = set()
        self.next_ns = 0
        self.msg = can.Message(arbitration_id=int(self.spec.param("frame_id")), is_extended_id=False,
                               data=bytes(int(self.spec.param("dlc"))))

    def frame_ready_ns(self) -> int | None:
        """When the babbler next wants the bus (None: no more in its window)."""
        if self.start_ns is None:
            return None
        ready = max(self.next_ns, self.start_ns)
        if self.end_ns is not None and ready >= self.end_ns:
            return None
        if self.spec.count and self.affected >= self.spec.count:
            return None
        return ready

    def sent(self, start_ns: int) -> None:
        self.affected += 1
        self.next_ns = start_ns + round(self.spec.param("period_s") * 1e9)


class ErrorFrames(ActiveFault):
    """Destroys transmission attempts; acts in the bus model's arbitration, not on submit."""


KINDS: dict[str, type[ActiveFault]] = {
    "drop": Drop, "delay": Delay, "duplicate": Duplicate, "replay": Replay, "corrupt": Corrupt,
    "spoof": Spoof, "counter_freeze": CounterFreeze, "counter_offset": CounterOffset, "flood": Flood,
    "telemetry_freeze": TelemetryFreeze, "error_frames": ErrorFrames,
}


class FaultInjector:
    """Fault times count from `arm(t0_ns)`: the bus model arms it with the first command frame,
    so that a scenario's start_s means "after commanding started", whenever the nodes came up.
    They are the run's simulated seconds: `wall_s_per_sim_s` of the bus's clock each (1 on a bus
    on simulated time, 1 / time_factor on a real-time run's wall clock)."""

    def __init__(self, specs: list[FaultSpec], protocol: p.Protocol, seed: int = 1, wall_s_per_sim_s: float = 1.0,
                 max_dipole_am2: float = float("inf")):
        self.protocol = protocol
        self.t0_ns: int | None = None
        self.wall_s_per_sim_s = wall_s_per_sim_s
        self.seed = seed
        self.live_labels: set[str] = set()     # faults added while the bus ran (add_live)
        self.faults = [(HardwareFault if s.hardware else KINDS[s.name])(s, i, protocol, seed, wall_s_per_sim_s)
                       for i, s in enumerate(specs)]
        # The board's power supply and coils under the hardware faults, armed with the others.
        self.hardware = CoilHardware(specs, max_dipole_am2, wall_s_per_sim_s)
        self.floods = [f for f in self.faults if isinstance(f, Flood)]
        self.error_faults = [f for f in self.faults if isinstance(f, ErrorFrames)]
        self.frame_faults = [f for f in self.faults if not isinstance(f, (Flood, ErrorFrames, HardwareFault))]
        # One record per frame a fault touched (a flood: every frame it sends): on disk as they
        # come (bench/bus/spill.py); iterating gives InjectionRecords back, oldest first.
        self.records = SpilledJson(encode=lambda r: r.__dict__, decode=lambda d: InjectionRecord(**d))
        self._span: dict[str, tuple[int, int]] = {}   # fault label -> its first and last record's t_ns

    # --- called by the bus model ----------------------------------------------------------
    def arm(self, t0_ns: int) -> None:
        self.t0_ns = t0_ns
        for fault in self.faults:
            fault.arm(t0_ns)
        self.hardware.arm(t0_ns / 1e9)

    def on_submit(self, tx: Transmission) -> SubmitOutcome:
        outcome = SubmitOutcome()
        for fault in self.frame_faults:
            if fault.takes(tx.msg, tx.submitted_ns) and not fault.apply(tx, outcome, self):
                return outcome
        outcome.queued.insert(0, tx)
        return outcome

    def babbler(self) -> tuple[Flood, int] | None:
        """The flood that wants the bus soonest, and when."""
        ready = [(f.frame_ready_ns(), i, f) for i, f in enumerate(self.floods)]
        ready = [(t, i, f) for t, i, f in ready if t is not None]
        if not ready:
            return None
        t_ns, _, flood = min(ready)
        return flood, t_ns

    def destroys(self, tx: Transmission, t_ns: int) -> ErrorFrames | None:
        for fault in self.error_faults:
            if fault.takes(tx.msg, t_ns):
                self.record(t_ns, fault.label, "destroyed", tx.msg)
                return fault
        return None

    def flood_active(self, t_ns: int) -> bool:
        return any(f.in_window(t_ns) for f in self.floods)

    # --- faults that arrive at run time (live injection: bench/bus/can/live_faults.py) -----
    def add_live(self, spec: FaultSpec) -> ActiveFault:
        """Add a fault while the bus runs: the next index of the scenario's list ("<index>:<name>"),
        armed at once (its start_s counts from the first command frame, as a scripted fault's; the
        caller checks the injector is armed), acting from the bus model's next event on. Called on
        another thread than the bus model's: the fault is whole before any list holds it."""
        index = len(self.faults)
        fault = (HardwareFault if spec.hardware else KINDS[spec.name])(spec, index, self.protocol, self.seed,
                                                                       self.wall_s_per_sim_s)
        if self.t0_ns is not None:
            fault.arm(self.t0_ns)
        if spec.hardware:
            self.hardware.add(index, spec)
        elif isinstance(fault, Flood):
            self.floods.append(fault)
        elif isinstance(fault, ErrorFrames):
            self.error_faults.append(fault)
        else:
            self.frame_faults.append(fault)
        self.faults.append(fault)
        self.live_labels.add(fault.label)
        return fault

    # --- used by the faults ---------------------------------------------------------------
    def record(self, t_ns: int, label: str, action: str, msg: can.Message, original: can.Message | None = None) -> None:
        self.records.append(InjectionRecord(t_ns, label, action, msg.arbitration_id, bytes(msg.data).hex(),
                                            bytes(original.data).hex() if original is not None else ""))
        self._span[label] = (self._span.get(label, (t_ns,))[0], t_ns)

    def drop(self, tx: Transmission, outcome: SubmitOutcome, label: str) -> None:
        outcome.dropped.append((tx.msg, label))
        self.record(tx.submitted_ns, label, "dropped", tx.msg)

    def inject(self, msg: can.Message, ready_ns: int, outcome: SubmitOutcome, label: str,
               after: Transmission | None = None) -> None:
        """A frame of the injector's own, ready at ready_ns; `after`: only once that frame is sent
        ("right after" it, rather than colliding with it on an equal identifier)."""
        t_ns = ready_ns
        outcome.queued.append(Transmission(_copy(msg), SOURCE_INJECTOR, t_ns, t_ns, ("flight", "board"), label,
                                           after=after))
        self.record(t_ns, label, "injected", msg)

    def replace(self, tx: Transmission, altered: can.Message, outcome: SubmitOutcome, label: str) -> None:
        outcome.replaced.append(tx.msg)
        self.record(tx.submitted_ns, label, "replaced", altered, original=tx.msg)
        tx.msg, tx.fault = altered, label

    def summary(self) -> list[dict]:
        out = []
        for fault in self.faults:
            first_ns, last_ns = self._span.get(fault.label, (None, None))
            out.append({"fault": fault.label, "affected": fault.affected,
                        "first_ns": first_ns, "last_ns": last_ns,
                        # its window on the bus's clock as armed (None: not armed, or no end)
                        "start_ns": fault.start_ns, "end_ns": fault.end_ns, "live": fault.label in self.live_labels})
        return out
