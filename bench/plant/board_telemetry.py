"""The plant's view of a magnetorquer board provided from outside: its telemetry frames on the CAN bus.

With `[run] external = ["board"]` the board is real hardware (or anything standing in for it on
the bus): it publishes no Zenoh message, so the plant listens on the board's bus itself and
turns each MTQ_TLM_DIPOLE frame into the MtqApplied report its real-time loop holds over a step
(bench/plant/attitude_node.py). Frames are decoded with the project's DBC (bench/bus/can/protocol.py)
and E2E-checked as the driver checks them; a frame failing either is counted and not used.

What the frames carry, and so what the plant gets, differs from the simulated board's Zenoh report:
- AppliedDipole is the dipole of the coil currents: it lags the set-point by the coils' time
  constant and is quantised to the DBC's 1e-4 A m^2, where the simulated board reports its coil
  drivers' target. A run with an external board therefore does not equal the built-in run exactly.
- The frame carries no time of its own: the report's "applied" stamp is the frame's arrival at the
  plant, so the report's age (DipoleAcceptance) is counted from there, not from the board's action.
- Which command the coils follow (LastCommandCounter) is in MTQ_TLM_COIL, sent beside it: the
  report carries the latest COIL frame's counter and currents (0 before the first COIL frame).

That is real time (`source="dipole"`). Lock-step (`source="setpoint"`) needs what each command did,
not the coils' lagging current: a board that acknowledges its commands (MTQ_TLM_SETPOINT, sent
right after it applies a command and whenever its set-point changes without one) gives the coil
drivers' set-point and the counter of the command it applied; each accepted echo is a report
(`command_applied` True for a command's acknowledgement, False for a set-point change), and the
plant pairs the step's command with the acknowledgement carrying its counter
(bench/plant/attitude_node.py). The echo's set-point is in the DBC's units, so the plant compares
it with the expected dipole as the echo carries it (`as_echoed`), bit for bit.
"""
from __future__ import annotations

import threading
import time
from collections import Counter

import can

from bench.bus.can import protocol as p
from bench.bus.schemas import MtqApplied, header

RECEIVE_POLL_S = 0.05     # how often the listener looks at its stop flag
SOURCES = {"dipole": p.TLM_DIPOLE, "setpoint": p.TLM_SETPOINT}   # which frame makes the reports


def as_echoed(protocol: p.Protocol, dipole_am2) -> list[float]:
    """A set-point as MTQ_TLM_SETPOINT carries it (the DBC's 1e-4 A m^2 step, decoded as a
    receiver decodes it): what the echo of a command applying `dipole_am2` holds, to the bit."""
    frame = protocol.decode(protocol.encode(p.TLM_SETPOINT, {f"Setpoint{a}": float(v) for a, v in zip(p.AXES, dipole_am2)},
                                            counter=0))
    return [float(frame.signals[f"Setpoint{a}"]) for a in p.AXES]


class BoardTelemetry:
    """Listens on `bus` on its own thread; each accepted frame of `source` ("dipole":
    MTQ_TLM_DIPOLE, "setpoint": MTQ_TLM_SETPOINT) goes to `on_report`."""

    def __init__(self, bus: can.BusABC, protocol: p.Protocol, run_id: str, on_report, max_delta_counter: int = 1,
                 source: str = "dipole"):
        if source not in SOURCES:
            raise ValueError(f"board telemetry source {source!r} is not one of {', '.join(SOURCES)}")
        self.bus = bus
        self.protocol = protocol
        self.run_id = run_id
        self.on_report = on_report
        self.source = source
        self._report_frame = SOURCES[source]
        self._e2e = {name: p.E2EReceiver(max_delta_counter) for name in (p.TLM_DIPOLE, p.TLM_COIL, p.TLM_SETPOINT)}
        self._coil: dict | None = None
        self.frames: Counter = Counter()       # frames seen, by DBC name
        self.refused: Counter = Counter()      # telemetry frames not used, by E2E status
        self.reports = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="board-telemetry", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)

    def summary(self) -> dict:
        return {"source": self._report_frame, "frames": dict(self.frames), "refused": dict(self.refused),
                "reports": self.reports, "bad_frames": dict(self.protocol.bad.counts)}

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(timeout=RECEIVE_POLL_S)
            if msg is not None:
                self.handle(msg, time.monotonic_ns())

    def handle(self, msg: can.Message, received_ns: int) -> MtqApplied | None:
        """One frame off the bus; the report it makes (MTQ_TLM_DIPOLE accepted) or None."""
        frame = self.protocol.decode(msg)
        if frame is None:
            return None
        self.frames[frame.name] += 1
        if frame.name not in self._e2e:
            return None
        status = self._e2e[frame.name].check(frame.counter, bool(frame.crc_ok))
        if not status.accepted:
            self.refused[f"{frame.name}:{status.name}"] += 1
            return None
        if frame.name == p.TLM_COIL:
            self._coil = frame.signals
            return None
        if frame.name != self._report_frame:
            return None
        s = frame.signals
        coil = self._coil or {}
        currents = [float(coil.get(f"CoilCurrent{a}", 0.0)) for a in p.AXES]
        hdr = header(self.run_id, self.reports, 0.0, applied=received_ns)
        if frame.name == p.TLM_SETPOINT:
            report = MtqApplied(
                header=hdr, dipole_am2=[float(s[f"Setpoint{a}"]) for a in p.AXES], coil_current_a=currents,
                safe_state=bool(s["SafeState"]), actuation_paused=bool(s["ActuationPaused"]),
                alive_counter=int(s["CommandCounter"]), command_applied=bool(s["CommandApplied"]))
        else:
            report = MtqApplied(
                header=hdr, dipole_am2=[float(s[f"AppliedDipole{a}"]) for a in p.AXES], coil_current_a=currents,
                safe_state=bool(s["SafeState"]), actuation_paused=bool(s["ActuationPaused"]),
                alive_counter=int(coil.get("LastCommandCounter", 0)))
        self.reports += 1
        self.on_report(report)
        return report
