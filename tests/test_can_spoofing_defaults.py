"""A spoofer without the key gets nothing through on any built-in scenario's default settings (issue 26).

Each built-in scenario's [can] settings (security, board, driver; the distinct combinations, named
by the first scenario that has them) run on the simulated clock of tests/can_sim.py with the key
the launcher would hand the run (none is built in; here one drawn from the seed). A spoofer on the
bus knows everything but the key: the DBC, the E2E data ids, the freshness scheme, the genuine
frames it hears. Its attacks, interleaved with the genuine command stream:
- a forged command with a valid E2E CRC and the next alive counter (and a MAC of its own key);
- the replay of captured genuine commands, immediately and 0.6 s later;
- NMT stop, enter-pre-operational, reset node and reset communication, to this node and to all;
- a command and an authenticated NMT stop with the current freshness value and a zero MAC.
Every case asserts that the attack acted (the board refused its frames), that every command the
board applied is one the driver sent, within the freshness bound, that the coils were never
switched off (no safe state, no NMT state change) and that every genuine command was applied.
The e2e profile, chosen explicitly, is shown to obey the same NMT stop (CiA 301).
"""
from __future__ import annotations

import msgspec
import pytest

from bench.bus.can import protocol as p
from bench.bus.can import secoc
from bench.bus.can.config import SecurityConfig
from bench.bus.can.faults import FaultSpec
from bench.scenario import builtin_names, load_scenario
from can_sim import SimBench

ATTACK_START_S = 0.3
ATTACK_S = 0.6
SPOOFED_DIPOLE_AM2 = (0.15, 0.15, 0.15)


def _default_can_settings() -> dict[str, object]:
    """Built-in scenario name -> its CanConfig, one per distinct (security, board, driver, node id)."""
    seen: dict[bytes, str] = {}
    configs = {}
    for name in builtin_names():
        can = load_scenario(name).can
        if can is None:
            continue
        key = msgspec.json.encode((can.security, can.board, can.driver, can.node_id))
        if key not in seen:
            seen[key] = name
            configs[name] = can
    return configs


CAN_DEFAULTS = _default_can_settings()


def bench_for(can, *faults: FaultSpec) -> SimBench:
    bench = SimBench(*faults, security=can.security, board_config=can.board, driver_config=can.driver)
    bench.run(ATTACK_START_S)
    return bench


def inject(bench: SimBench, make_frame, every_s: float = 0.013) -> int:
    """The spoofer's frames, one every every_s during the attack, heard by board and driver."""
    sent = 0
    end_s = bench.clock() + ATTACK_S
    while bench.clock() < end_s:
        msg = make_frame(bench)
        for side in ("board", "flight"):
            bench.buses[side].inbox.append(msg)
        sent += 1
        bench.run(every_s)
    bench.run(0.1)
    return sent


def assert_nothing_got_through(bench: SimBench) -> None:
    board = bench.board
    ages = bench.applied_ages_s()            # raises if a dipole the driver never sent was applied
    assert ages and max(ages) <= bench.max_age_s, f"applied a command {max(ages) * 1e3:.1f} ms old"
    assert not any(tuple(a.dipole_am2) == SPOOFED_DIPOLE_AM2 for _, a in bench.applied)
    first_applied_s = bench.applied[0][0]
    assert [t for t in bench.coils_off_s if t > first_applied_s] == [], "the coils were switched off"
    assert board.nmt_state == p.NMT_OPERATIONAL and not board.ignored and not board.state.safe_state
    assert board.accepted == len(bench.sent), "a genuine command was not applied"
    assert "board_command_timeout" not in bench.kinds()


def test_every_built_in_scenario_authenticates_its_bus_and_carries_no_key():
    assert CAN_DEFAULTS
    for name in builtin_names():
        can = load_scenario(name).can
        if can is not None:
            assert can.security.profile == "secoc" and can.security.key_hex == "", name


@pytest.mark.parametrize("name", sorted(CAN_DEFAULTS))
def test_forged_command_with_valid_e2e_and_counter_is_never_applied(name):
    spoof = FaultSpec("spoof", start_s=ATTACK_START_S, duration_s=ATTACK_S,
                      params={"knows_data_id": True, "dipole_am2": SPOOFED_DIPOLE_AM2[0]})
    bench = bench_for(CAN_DEFAULTS[name], spoof)
    bench.run(ATTACK_S + 0.1)
    assert bench.board.rejected["WRONG_MAC"] >= 10 and set(bench.board.rejected) == {"WRONG_MAC"}
    assert_nothing_got_through(bench)
    assert "spoofed_command" in bench.kinds()


@pytest.mark.parametrize("after_s", [0.0, 0.6])
@pytest.mark.parametrize("name", sorted(CAN_DEFAULTS))
def test_replayed_genuine_commands_are_never_applied(name, after_s):
    # Recording from the attack's start; replays from after_s later, for ATTACK_S.
    replay = FaultSpec("replay", start_s=ATTACK_START_S, duration_s=after_s + ATTACK_S, params={"after_s": after_s})
    bench = bench_for(CAN_DEFAULTS[name], replay)
    bench.run(after_s + ATTACK_S + 0.1)
    assert bench.board.rejected["STALE"] >= 10 and set(bench.board.rejected) == {"STALE"}
    assert_nothing_got_through(bench)


def _plain_nmt(command: int, node_id: int):
    return lambda bench: p.Protocol(bench.board.protocol.node_id).encode(p.NMT, {"Command": command, "NodeId": node_id})


@pytest.mark.parametrize("command", [p.NMT_STOP, p.NMT_ENTER_PRE_OPERATIONAL, p.NMT_RESET_NODE,
                                     p.NMT_RESET_COMMUNICATION])
@pytest.mark.parametrize("name", sorted(CAN_DEFAULTS))
def test_plain_nmt_from_a_spoofer_changes_nothing(name, command):
    bench = bench_for(CAN_DEFAULTS[name])
    node_id = bench.board.protocol.node_id
    sent = inject(bench, lambda b: _plain_nmt(command, node_id if len(b.sent) % 2 else 0)(b))
    assert bench.board.rejected == {"NMT_NOT_AUTHENTICATED": sent}
    assert_nothing_got_through(bench)
    assert "spoofed_command" in bench.kinds()


def _zero_mac(msg):
    data = bytearray(msg.data)
    data[secoc.MAC_OFFSET:secoc.MAC_OFFSET + secoc.MAC_BYTES] = bytes(secoc.MAC_BYTES)
    msg.data = data
    return msg


def _outsider(bench: SimBench) -> p.Protocol:
    """The frame layout with a key of the spoofer's own (its MAC is then replaced)."""
    return p.Protocol(bench.board.protocol.node_id, "secoc", key=bytes(16))


@pytest.mark.parametrize("name", sorted(CAN_DEFAULTS))
def test_zero_mac_command_and_nmt_stop_change_nothing(name):
    bench = bench_for(CAN_DEFAULTS[name])

    def forged(b: SimBench):
        if len(b.sent) % 2:
            # Valid E2E CRC, the next alive counter, the current freshness value, MAC zero.
            return _zero_mac(_outsider(b).command(SPOOFED_DIPOLE_AM2, counter=b.sent[-1].counter + 1, sent_s=b.clock()))
        return _zero_mac(_outsider(b).nmt(p.NMT_STOP, sent_s=b.clock()))

    sent = inject(bench, forged)
    assert sum(bench.board.rejected.values()) == sent
    assert bench.board.rejected["WRONG_MAC"] > 10 and bench.board.rejected["NMT_WRONG_MAC"] > 10
    assert_nothing_got_through(bench)


def test_a_captured_authentic_nmt_stop_replayed_later_is_stale():
    """The driver's own authenticated NMT frames, replayed: refused by the freshness check."""
    bench = bench_for(CAN_DEFAULTS[sorted(CAN_DEFAULTS)[0]])
    insider = p.Protocol(bench.board.protocol.node_id, "secoc", key=bench.key)
    captured = insider.nmt(p.NMT_STOP, sent_s=bench.clock() - 0.2)     # a stop sent 0.2 s ago, heard
    sent = inject(bench, lambda b: captured)
    assert bench.board.rejected == {"NMT_STALE": sent}
    assert_nothing_got_through(bench)


def test_the_driver_still_stops_and_restarts_its_board_with_authenticated_nmt():
    """The key holder keeps CiA 301 control: its MTQ_NMT_AUTH stop is obeyed, and a reset boots the
    board, which the driver then starts again (boot-up heartbeat -> authenticated start)."""
    bench = bench_for(CAN_DEFAULTS[sorted(CAN_DEFAULTS)[0]])
    bench.driver.nmt(p.NMT_STOP)
    bench.run(0.05, commanding=False)
    assert bench.board.nmt_state == p.NMT_STOPPED and bench.board.state.safe_state
    bench.driver.nmt(p.NMT_RESET_NODE)
    bench.run(0.3)
    assert bench.board.nmt_state == p.NMT_OPERATIONAL and not bench.board.state.safe_state
    assert bench.driver.nmt_sent[p.NMT_START] == 2 and not bench.board.rejected


def test_on_the_explicit_e2e_profile_a_plain_nmt_stop_switches_the_coils_off():
    """What the e2e profile does not protect: CiA 301 NMT from anyone is obeyed."""
    bench = bench_for(msgspec.structs.replace(CAN_DEFAULTS[sorted(CAN_DEFAULTS)[0]], security=SecurityConfig(profile="e2e")))
    inject(bench, _plain_nmt(p.NMT_STOP, 0))
    assert bench.board.nmt_state == p.NMT_STOPPED and bench.coils_off_s and bench.board.accepted < len(bench.sent)
