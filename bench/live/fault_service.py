"""The live view's fault-injection service `/inject_fault` (a part of LiveView, bench/live/node.py):
a call must carry the run's token (service_token, from the run's key); the request, the fields of
a `[[can.faults]]` entry, is forwarded to canbus on the command channel, signed under the run's
key as "live" (bench/bus/fault_command.py), and canbus decides, as for `bench inject`.

FaultService uses LiveView's ctx, sim, signer, token, service_calls and its _log (/events).
"""
from __future__ import annotations

import hashlib
import hmac
import json
from collections import Counter

import msgspec

from bench.bus import fault_command as fc

SERVICE_NAME = "/inject_fault"
TOKEN_LABEL = b"orbit-hil-bench live fault service v1"
AXES = {"x": 0, "y": 1, "z": 2}


def service_token(key: bytes | None) -> str:
    """The token a service call must carry: from the run's key, so whoever can read bus.key (the run's
    user) or sees the terminal of `bench run` can call it, nobody else reaching the loopback port."""
    if key is None:
        return ""
    return hmac.new(key, TOKEN_LABEL, hashlib.sha256).hexdigest()[:24]


class FaultService:
    """The `/inject_fault` service's handler (a mixin of LiveView)."""

    def _service(self, request) -> bytes:
        """`/inject_fault` (the SDK's thread): checked here for the token, decided by canbus."""
        reply = self.inject(request.payload)
        return json.dumps(reply).encode()

    def inject(self, payload: bytes) -> dict:
        try:
            data = json.loads(payload)
            if not isinstance(data, dict):
                raise ValueError("the request is a JSON object")
        except ValueError as exc:
            self.service_calls[fc.INVALID] += 1
            return {"accepted": False, "reason": fc.INVALID, "detail": f"not a JSON object: {exc}", "authentic": False}
        token = data.pop("token", None)
        if self.token and not (isinstance(token, str) and hmac.compare_digest(token, self.token)):
            self.service_calls[fc.FORGED] += 1
            self.ctx.unauthentic.setdefault(fc.FORGED, Counter())["service" + SERVICE_NAME] += 1
            self.ctx.log.warning("fault-injection call without the run's token refused (%d so far)",
                                 self.service_calls[fc.FORGED])
            self._log(self.sim.newest_step_ns, "Error", "injector", "a fault-injection call without the run's token: refused")
            return {"accepted": False, "reason": fc.FORGED, "detail": "no valid token (the one `bench run` printed)",
                    "authentic": False}
        fields = {}
        try:
            kind = data.pop("kind")
            axis = data.pop("axis", None)
            params = dict(data.pop("params", None) or {})
            if axis is not None:
                if axis not in AXES:
                    raise ValueError(f"axis must be x, y or z, not {axis!r}")
                params["axis"] = AXES[axis]
            for name in ("duration_s", "after_s", "frames", "count", "every"):
                if name in data:
                    fields[name] = data.pop(name)
            if data:
                raise ValueError(f"unknown field(s): {', '.join(sorted(data))}")
            request = msgspec.convert({"run_id": self.ctx.run_id, "kind": kind, "nonce": fc.new_request("x", "x").nonce,
                                       "params": params, **fields}, fc.FaultRequest)
        except (KeyError, ValueError, TypeError, msgspec.ValidationError) as exc:
            self.service_calls[fc.INVALID] += 1
            return {"accepted": False, "reason": fc.INVALID, "detail": str(exc), "authentic": False}
        answer, authentic = fc.request_fault(self.ctx.session, request, self.ctx.data_key, self.ctx.name,
                                             signer=self.signer)
        if answer is None:
            self.service_calls["unanswered"] += 1
            return {"accepted": False, "reason": "unanswered", "detail": "no canbus answered (a run without a CAN bus "
                                                                         "has no fault injector)", "authentic": False}
        self.service_calls["accepted" if answer.accepted and authentic else answer.reason or "refused"] += 1
        if not answer.accepted:
            self._log(self.sim.newest_step_ns, "Error", "injector",
                      f"fault {request.kind} refused by canbus ({answer.reason}): {answer.detail}")
        return {**msgspec.to_builtins(answer), "authentic": authentic}
