"""`bench node mtq --break MODE`: the bench's own board broken on purpose, for the self-test of
`bench contract check board` only (each mode shows that the check fails such a board, naming the
problem); never for a run.

The hook is a wrapper, not a change to the board's logic (board.py): node "mtq" runs as always
(bench/bus/can/nodes.py), with the board class it builds replaced by a subclass that changes its
configuration or wraps one of its parts:

- slow-heartbeat: a heartbeat every two heartbeat periods;
- no-boot-up: no boot-up message (heartbeat with state 0) when it boots or is reset;
- obey-plain-nmt: on the secoc profile, obeys plain NMT (identifier 0, no MAC) as well;
- no-saturation: saturates each axis at 1 A m^2 instead of max_dipole_am2;
- no-safe-state: its command timeout is an hour (the coils hold the last command);
- accept-bad-crc: takes every command's E2E CRC as right;
- accept-stale: takes an authentic command whatever its freshness value says (old, replayed);
- no-echo: sends no MTQ_TLM_SETPOINT.

Light to import (names only): `bench node`'s command line lists the modes.
"""
from __future__ import annotations

BREAKS = ("slow-heartbeat", "no-boot-up", "obey-plain-nmt", "no-saturation", "no-safe-state", "accept-bad-crc",
          "accept-stale", "no-echo")
NO_SATURATION_AM2 = 1.0        # within MTQ_TLM_SETPOINT's +-1.6383, far above the default 0.2
NO_SAFE_STATE_TIMEOUT_S = 3600.0


def broken_config(config, breaks):
    """The board's configuration with the configuration breaks applied."""
    import msgspec

    changes = {}
    if "slow-heartbeat" in breaks:
        changes["heartbeat_period_s"] = 2 * config.heartbeat_period_s
    if "no-saturation" in breaks:
        changes["max_dipole_am2"] = NO_SATURATION_AM2
    if "no-safe-state" in breaks:
        changes["command_timeout_s"] = NO_SAFE_STATE_TIMEOUT_S
    if "no-echo" in breaks:
        changes["setpoint_echo"] = False
    return msgspec.structs.replace(config, **changes)


def broken_board(breaks):
    """A MagnetorquerBoard subclass with `breaks` (a set of BREAKS)."""
    import dataclasses

    from bench.bus.can import protocol as p
    from bench.bus.can import secoc
    from bench.bus.can.board import MagnetorquerBoard

    class BrokenBoard(MagnetorquerBoard):
        built = 0

        def __init__(self, bus, config, protocol, *args, **kwargs):
            super().__init__(bus, broken_config(config, breaks), protocol, *args, **kwargs)
            BrokenBoard.built += 1
            if "accept-bad-crc" in breaks:
                decode = self.protocol.decode

                def crc_blind(msg):
                    frame = decode(msg)
                    return dataclasses.replace(frame, crc_ok=True) if frame is not None and frame.crc_ok is False \
                        and frame.name in p.COMMANDS else frame
                self.protocol.decode = crc_blind
            if "accept-stale" in breaks and self.freshness is not None:
                verify = self.freshness.verify

                def freshness_blind(data, now_s):
                    verdict, freshness, age_s = verify(data, now_s)
                    return (secoc.Verdict.OK if verdict is secoc.Verdict.STALE else verdict), freshness, age_s
                self.freshness.verify = freshness_blind

        if "obey-plain-nmt" in breaks:
            def _nmt_authentic(self, frame, msg, now_s):
                return frame.name == p.NMT or super()._nmt_authentic(frame, msg, now_s)

        if "no-boot-up" in breaks:
            def _send(self, msg):
                if msg.arbitration_id == self.protocol.frame_ids[p.HEARTBEAT] and bytes(msg.data) == bytes([p.NMT_BOOT_UP]):
                    return
                super()._send(msg)

    return BrokenBoard


def run(ctx) -> int:
    """Node "mtq" with ctx.breaks: the node as always, building the broken board."""
    from bench.bus.can import nodes

    board_class = broken_board(set(ctx.breaks))
    nodes.MagnetorquerBoard = board_class     # this process runs one board: the node's wiring builds it
    ctx.log.warning("--break %s: a board broken on purpose (for bench contract check board's self-test only)",
                    ",".join(sorted(ctx.breaks)))
    code = nodes.run(ctx)
    if not board_class.built:
        raise RuntimeError("--break: the board node no longer builds its board through nodes.MagnetorquerBoard")
    return code
