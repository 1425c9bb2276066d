"""Which of the board check's genuine frames this host may have delivered too late to be fresh.

On `secoc` the board refuses an authentic frame whose freshness value (the check's clock when it
sent it) is older than the freshness window on arrival: it reports EMCY 0x8100 STALE, and the
command is not applied (no echo; the next one accepted reports OK_SOME_LOST). That is the contract
working. On a loaded host the check's frame can sit in a queue (the check's own process, the bus,
the board's process) past that window, and the check must then not blame the board.

The check cannot see the board's clock, but it can bound a frame's age on arrival from above: a
board takes its frames in order, so the first answer heard that names this frame or a later one
(an EMCY 0x8100 carrying its alive counter, an applied echo) was sent after the board had it.
  age on arrival <= that answer's arrival - the frame's send time
If the bound is within the window, the board refused a frame that was fresh: a fault of the board.
If it is beyond, the host may have held the frame up: the frame is excused, the EMCYs it explains
are too, and the check reports how many it excused.
"""
from __future__ import annotations

from bench.bus.can import protocol as p

# EMCY 0x8100 statuses that a stale-refused genuine frame causes: its own refusal, and the next
# accepted command's report that commands were lost (or, after many, a sequence the E2E receiver
# refuses).
CONSEQUENCES = (p.E2EStatus.OK_SOME_LOST, p.E2EStatus.WRONG_SEQUENCE)


def answered_at_s(index: int, sent: list, heard: list) -> float | None:
    """When the board surely had sent[index]: the first EMCY 0x8100 or applied echo heard after it
    that names its alive counter or that of a frame sent after it. None: nothing names it."""
    frame = sent[index]
    for h in heard:
        if h.t_s <= frame.t_s:
            continue
        # The frames sent from this one until h was heard (the counter wraps after 16: only these).
        counters = {s.counter for s in sent[index:] if s.counter is not None and s.t_s < h.t_s}
        if frame.counter is None:             # NMT: its refusal carries RejectedCounter 0
            counters.add(0)
        if h.name == p.EMCY and h.signals["ErrorCode"] == p.EMCY_E2E_CHECK_FAILED:
            named = int(h.signals["RejectedCounter"])
        elif h.name == p.TLM_SETPOINT and h.signals["CommandApplied"]:
            named = int(h.signals["CommandCounter"])
        else:
            continue
        if named in counters:
            return h.t_s
    return None


def may_have_arrived_stale(index: int, sent: list, heard: list, max_age_s: float) -> bool:
    """Whether sent[index] can have been older than max_age_s when the board had it."""
    t_s = answered_at_s(index, sent, heard)
    return t_s is not None and t_s - sent[index].t_s > max_age_s


def explained_emcys(excused: list, sent: list, heard: list) -> list:
    """The EMCYs 0x8100 that excused frames explain: a STALE naming an excused frame's counter,
    heard after it was sent (NMT: RejectedCounter 0), and an OK_SOME_LOST or WRONG_SEQUENCE for
    the genuine command sent next after an excused one."""
    explained = []
    positions = {id(s): i for i, s in enumerate(sent)}
    for h in heard:
        if h.name != p.EMCY or h.signals["ErrorCode"] != p.EMCY_E2E_CHECK_FAILED:
            continue
        status, named = int(h.signals["E2eStatus"]), int(h.signals["RejectedCounter"])
        for s in excused:
            if s.t_s >= h.t_s:
                continue
            if status == p.E2EStatus.STALE and named == (0 if s.counter is None else s.counter):
                explained.append(h)
                break
            if status in CONSEQUENCES:
                following = next((t for t in sent[positions[id(s)] + 1:] if t.kind == "command"), None)
                if following is not None and following.counter == named and following.t_s < h.t_s:
                    explained.append(h)
                    break
    return explained
