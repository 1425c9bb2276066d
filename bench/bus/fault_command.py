"""The command channel of live fault injection (issue 48): a request to the canbus process to add a
fault of any kind `[[can.faults]]` takes while the run runs, and its answer, both signed under the
run's key as the data topics are (bench/bus/data_auth.py).

    query  bench/<run_id>/control/fault   payload: FaultRequest (JSON)
                                          attachment: data_auth tag, sender = who asks ("inject", "live")
    reply  bench/<run_id>/control/fault   payload: FaultReply (JSON), echoing the request's nonce
                                          attachment: data_auth tag, sender = "canbus"

The canbus process answers (bench/bus/can/live_faults.py). It takes a request only with a valid tag
under the run's key whose counter it has not seen from that sender (a replayed request is refused
as "replayed", one without the key as "forged"; both are counted, in can/live_faults.json and in
its ProcessStats as data_auth counts them), and only in a run started with `--allow-live-faults`
("not_allowed" otherwise, for every request). The fault is built as a scripted one is
(`msgspec.convert` into `FaultSpec`: the same fields, ranges, kinds and parameters as `[[can.faults]]`;
"invalid" with the field named otherwise), its start the bus's time now plus `after_s`, on the
run's simulated time from the first command frame, as a scripted fault's `start_s` is.

The answer is signed by canbus and carries the request's nonce, so the asker knows it is genuine
and this request's. A Zenoh query rather than a put: the asker learns at once whether its fault
was taken and where its window is; queryables and queries have their own rows in the access
control of a deployment with certificates (bench/bus/acl.py: "operator", the identity `bench
inject` presents, and "live", the live view's node).
"""
from __future__ import annotations

import secrets
import threading
from typing import Annotated, Callable

import msgspec
import zenoh

from bench.bus import data_auth, keys
from bench.bus.can.faults import FaultSpec

CANBUS = "canbus"                 # the process that answers (the fault injector's)
NONCE_HEX = 32
# Why a request was refused, each counted by the canbus process.
FORGED, REPLAYED = data_auth.FORGED, data_auth.REPLAYED      # no valid tag under the run's key / seen before
NOT_ALLOWED = "not_allowed"       # the run was not started with --allow-live-faults
INVALID = "invalid"               # not a fault [[can.faults]] takes (the field and the problem named)
NOT_ARMED = "not_armed"           # the bus has not seen its first command frame yet: no time base for a window
REFUSALS = (FORGED, REPLAYED, NOT_ALLOWED, INVALID, NOT_ARMED)

Name = Annotated[str, msgspec.Meta(max_length=64)]


class FaultRequest(msgspec.Struct, forbid_unknown_fields=True):
    """A fault to add now: `kind` is a [[can.faults]] name, the other fields those of a scripted fault
    (bench/bus/can/faults.py), `after_s` simulated seconds from now to its start."""
    run_id: Name
    kind: Name
    nonce: Annotated[str, msgspec.Meta(min_length=NONCE_HEX, max_length=NONCE_HEX, pattern="^[0-9a-f]*$")]
    frames: Annotated[list[Name], msgspec.Meta(max_length=64)] = []
    duration_s: float | None = None
    count: int = 0
    every: int = 1
    params: Annotated[dict[Name, bool | int | float], msgspec.Meta(max_length=16)] = {}
    after_s: Annotated[float, msgspec.Meta(ge=0.0, le=1e6)] = 0.0


class FaultReply(msgspec.Struct, forbid_unknown_fields=True):
    """canbus's answer: taken (with the fault's label and window on simulated time) or refused (why)."""
    nonce: str
    accepted: bool
    reason: str = ""                 # refused: one of REFUSALS; taken: ""
    detail: str = ""                 # what was wrong, or what was done
    label: str = ""                  # "<index>:<name>" as in busmodel.json and can/injections.jsonl
    start_sim_s: float | None = None
    end_sim_s: float | None = None   # None: no end (a count of frames, or a hardware fault to the run's end)


def new_request(run_id: str, kind: str, **fields) -> FaultRequest:
    """A request with a fresh nonce; its fields are checked when canbus builds the fault."""
    return FaultRequest(run_id=run_id, kind=kind, nonce=secrets.token_hex(NONCE_HEX // 2), **fields)


def fault_spec(request: FaultRequest, start_s: float) -> FaultSpec:
    """The request as a scripted fault starting at start_s (simulated s from the first command frame),
    through the scenario loader's schema (bounds, kinds, parameters, frames); ValueError naming the problem."""
    data = {"name": request.kind, "frames": request.frames, "start_s": start_s, "count": request.count,
            "every": request.every, "params": request.params}
    if request.duration_s is not None:
        data["duration_s"] = request.duration_s
    try:
        return msgspec.convert(data, FaultSpec)
    except msgspec.ValidationError as exc:
        raise ValueError(str(exc)) from None


def key_expr(run_id: str) -> str:
    return keys.key(run_id, keys.CONTROL_FAULT)


def request_fault(session: zenoh.Session, request: FaultRequest, key: bytes | None, sender: str,
                  timeout_s: float = 3.0, signer: Callable[[str, bytes], bytes] | None = None) -> tuple[FaultReply | None, bool]:
    """Ask the run's canbus for the fault. Returns (its answer or None if nobody answered, whether the
    answer is authentic: signed by canbus under the run's key and carrying this request's nonce).
    key None: the request goes unsigned (canbus refuses it, as "forged")."""
    where = key_expr(request.run_id)
    payload = msgspec.json.encode(request)
    if key is not None:
        signer = signer or data_auth.Signer(key, sender)
        attachment = signer(where, payload)
    else:
        attachment = None
    replies: list[tuple[FaultReply, bool]] = []
    done = threading.Event()

    def on_reply(reply: zenoh.Reply) -> None:
        sample = reply.ok
        if sample is None:
            return
        data = sample.payload.to_bytes()
        try:
            answer = msgspec.json.decode(data, type=FaultReply)
        except (msgspec.ValidationError, msgspec.DecodeError):
            return
        opened = data_auth.open_tag(key, str(sample.key_expr), data, data_auth.attachment_bytes(sample)) \
            if key is not None else None
        authentic = (opened is not None and opened[0] == CANBUS.encode() and str(sample.key_expr) == where
                     and answer.nonce == request.nonce)
        replies.append((answer, authentic))

    session.get(where, zenoh.handlers.Callback(on_reply, done.set), payload=payload, attachment=attachment,
                target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s)
    done.wait(timeout_s + 1.0)
    authentic = [r for r in replies if r[1]]
    if authentic:
        return authentic[0]
    return replies[0] if replies else (None, False)


def refusal(request_nonce: str, reason: str, detail: str) -> FaultReply:
    return FaultReply(nonce=request_nonce, accepted=False, reason=reason, detail=detail)
