"""Faults that arrive while the run runs (issue 48): the canbus process's entry point for live fault
injection, and what the board takes from it.

`LiveFaults` (in canbus, beside the bus model and its FaultInjector) answers the command channel
(bench/bus/fault_command.py): a request signed under the run's key, in a run started with
`--allow-live-faults`, becomes a `FaultSpec` exactly as a scripted `[[can.faults]]` entry is (same
schema), starting at the bus's time now (plus `after_s`) in simulated seconds from the first
command frame, and joins the injector (`FaultInjector.add_live`: the next index, so its records in
can/injections.jsonl and its window in busmodel.json are a scripted fault's). Every fault of the
bus model, scripted (once the first command frame arms the injector) or live (when taken), is
published on `event/fault` as a `FaultWindow` (the recorder writes it to the MCAP, the live view
shows it, and the board takes a live hardware fault from it). can/live_faults.json holds the
faults taken, flagged live, with their windows and who asked, and every refusal counted by reason;
the report and metrics.json read it (bench/report/canbus.py).

The board (node "mtq", its own process on the wall clock) follows `event/fault` for live hardware
faults (its power supply and coils: bench/bus/can/coils.py), `follow_live_hardware_faults`; on
simulated time the board shares the injector's CoilHardware in canbus and needs nothing more.

Clocks: on the wall clock (real time) the injector counts monotonic ns, `wall_s_per_sim_s` of them
per simulated second (bench/bus/can/sim_window.fault_clock_scale); on simulated time (lock-step)
the bus's simulated ns, one per simulated ns.
"""
from __future__ import annotations

import json
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Callable

import msgspec
import zenoh

from bench.bus import data_auth, keys
from bench.bus import fault_command as fc
from bench.bus.can.faults import FaultSpec
from bench.bus.schemas import FaultWindow, header

LIVE_FAULTS_NAME = "live_faults.json"     # in <run_dir>/can/
REFUSALS_KEPT = 50                        # the first refusals, with what was wrong (all are counted)
ANNOUNCE_POLL_S = 0.05


class LiveFaults:
    """The canbus side of the command channel. injector(): the bus model's FaultInjector, None
    until it exists (lock-step: with the first step); now_ns(): the injector's clock now."""

    def __init__(self, ctx, injector: Callable[[], object | None], now_ns: Callable[[], int | None],
                 allowed: bool, out_dir: Path):
        self.ctx = ctx
        self.injector = injector
        self.now_ns = now_ns
        self.allowed = allowed
        self.path = Path(out_dir) / LIVE_FAULTS_NAME
        self.accepted: list[dict] = []
        self.refused: Counter = Counter()
        self.refusals: list[dict] = []
        self._lock = threading.RLock()      # Zenoh answers queries on several threads
        self._verifier = data_auth.Verifier(ctx.data_key) if ctx.data_key is not None else None
        self._signer = data_auth.Signer(ctx.data_key, ctx.name) if ctx.data_key is not None else None
        self._where = fc.key_expr(ctx.run_id)
        ctx.declare_publisher(keys.EVENT_FAULT)
        self._write()
        self._queryable = ctx.session.declare_queryable(self._where, self._on_query)
        self._announcer = threading.Thread(target=self._announce_scripted, name="fault-windows", daemon=True)
        self._announcer.start()

    # --- the command channel --------------------------------------------------------------
    def _on_query(self, query: zenoh.Query) -> None:
        payload = query.payload.to_bytes() if query.payload is not None else b""
        attachment = query.attachment.to_bytes() if query.attachment is not None else None
        try:
            nonce = msgspec.json.decode(payload, type=fc.FaultRequest).nonce
        except (msgspec.ValidationError, msgspec.DecodeError):
            nonce = ""
        reply = self.handle(payload, attachment)
        if reply is None:
            return
        reply = msgspec.structs.replace(reply, nonce=nonce)
        data = msgspec.json.encode(reply)
        try:
            query.reply(self._where, data, attachment=self._signer(self._where, data) if self._signer else None)
        except Exception:   # noqa: BLE001 - the asker left, or the session is closing
            pass

    def handle(self, payload: bytes, attachment: bytes | None) -> fc.FaultReply | None:
        """One request: its tag, the run's permission, the fault, the injector; the answer (None:
        a request without a run id of ours, which is not this run's to answer)."""
        sender = ""
        if self._verifier is not None:
            reason = self._verifier.check(self._where, payload, attachment)
            if reason is not None:
                counts = self.ctx.unauthentic.setdefault(reason, Counter())
                counts[keys.CONTROL_FAULT] += 1
                return self._refuse(reason, "not signed under the run's key (bus.key)" if reason == fc.FORGED
                                    else "a request already seen (its counter is not above the last taken)")
            sender = data_auth.sender_of(attachment) or ""
        try:
            request = msgspec.json.decode(payload, type=fc.FaultRequest)
        except (msgspec.ValidationError, msgspec.DecodeError) as exc:
            return self._refuse(fc.INVALID, f"not a fault request: {exc}")
        if request.run_id != self.ctx.run_id:
            return self._refuse(fc.INVALID, f"run id {request.run_id!r} is not this run's")
        if not self.allowed:
            return self._refuse(fc.NOT_ALLOWED, "this run was not started with --allow-live-faults")
        with self._lock:
            injector = self.injector()
            now_ns = self.now_ns()
            if injector is None or injector.t0_ns is None or now_ns is None:
                return self._refuse(fc.NOT_ARMED, "the bus has not carried its first command frame yet: fault times "
                                                  "count from it; ask again in a moment")
            now_s = (now_ns - injector.t0_ns) / 1e9 / injector.wall_s_per_sim_s
            try:
                spec = fc.fault_spec(request, round(max(0.0, now_s) + request.after_s, 9))
            except ValueError as exc:
                return self._refuse(fc.INVALID, str(exc))
            fault = injector.add_live(spec)
            end_s = spec.start_s + spec.duration_s if spec.duration_s is not None else None
            entry = {"label": fault.label, "fault": msgspec.to_builtins(spec), "start_sim_s": spec.start_s,
                     "end_sim_s": end_s, "requested_by": sender, "taken_wall_s": time.time()}
            self.accepted.append(entry)
            self._write()
        self.ctx.log.warning("live fault %s taken from %r: %s from %.3f s (simulated)%s", fault.label, sender,
                             spec.name, spec.start_s, f" for {spec.duration_s:g} s" if spec.duration_s else "")
        self._publish(fault.label, spec, True, end_s, sender)
        return fc.FaultReply(nonce=request.nonce, accepted=True, detail=f"{spec.name} from {spec.start_s:.3f} s",
                             label=fault.label, start_sim_s=spec.start_s, end_sim_s=end_s)

    def _refuse(self, reason: str, detail: str) -> fc.FaultReply:
        with self._lock:
            self.refused[reason] += 1
            if len(self.refusals) < REFUSALS_KEPT:
                self.refusals.append({"reason": reason, "detail": detail, "wall_s": time.time()})
            n = self.refused[reason]
            self._write()
        if n <= 5 or n % 100 == 0:
            self.ctx.log.warning("live fault request #%d refused (%s): %s", n, reason, detail)
        return fc.refusal("", reason, detail)

    # --- every fault's window on event/fault ------------------------------------------------
    def _announce_scripted(self) -> None:
        """Once the first command frame arms the injector: each scripted fault's window, as a live
        one's is published when it is taken."""
        while not self.ctx.stop.wait(ANNOUNCE_POLL_S):
            injector = self.injector()
            if injector is None or injector.t0_ns is None:
                continue
            for fault in list(injector.faults):
                if fault.label in injector.live_labels:
                    continue
                spec = fault.spec
                end_s = spec.start_s + spec.duration_s if spec.duration_s is not None else None
                self._publish(fault.label, spec, False, end_s, "")
            return

    def _publish(self, label: str, spec: FaultSpec, live: bool, end_s: float | None, sender: str) -> None:
        try:
            self.ctx.publish(keys.EVENT_FAULT, FaultWindow(header(self.ctx.run_id, 0, spec.start_s), label, spec, live,
                                                          end_s, sender))
        except Exception as exc:   # noqa: BLE001 - the session is closing: the file has it
            self.ctx.log.warning("could not publish fault window %s: %s", label, exc)

    # --- the record -------------------------------------------------------------------------
    def summary(self) -> dict:
        return {"allowed": self.allowed, "accepted": self.accepted, "refused": dict(self.refused),
                "refusals": self.refusals}

    def _write(self) -> None:
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.summary(), indent=1))
        tmp.replace(self.path)

    def close(self) -> None:
        try:
            self._queryable.undeclare()
        except Exception:   # noqa: BLE001 - already closed with its session
            pass
        with self._lock:
            self._write()


def read_live_faults(run_dir: Path) -> dict:
    """can/live_faults.json of a run ({} when the run had no canbus or it wrote none)."""
    path = Path(run_dir) / "can" / LIVE_FAULTS_NAME
    try:
        return json.loads(path.read_text()) if path.is_file() else {}
    except (OSError, ValueError):
        return {}


def live_fault_specs(run_dir: Path) -> list[FaultSpec]:
    """The faults taken live, in the order the injector numbered them (after the scenario's)."""
    out = []
    for entry in read_live_faults(run_dir).get("accepted") or []:
        try:
            out.append(msgspec.convert(entry["fault"], FaultSpec))
        except (msgspec.ValidationError, KeyError, TypeError):
            continue
    return out


def follow_live_hardware_faults(ctx, hardware) -> None:
    """The board's side (node "mtq" on the wall clock): a live hardware fault published by canbus on
    `event/fault` (signed, checked as every input) acts on this board's CoilHardware too, from its
    start_s after the board's own first command, as a scripted one does. Only in a run started with
    --allow-live-faults."""
    if not getattr(ctx, "allow_live_faults", False):
        return

    def on_window(window: FaultWindow) -> None:
        if not window.live or not window.fault.hardware:
            return
        try:
            index = int(window.label.split(":", 1)[0])
        except ValueError:
            return
        if any(i == index for i, _ in hardware.faults):
            return
        hardware.add(index, window.fault)
        ctx.log.warning("live hardware fault %s: %s from %.3f s (simulated)", window.label, window.fault.name,
                        window.fault.start_s)

    ctx.subscribe(keys.EVENT_FAULT, FaultWindow, on_window)
