"""The board as a standard CANopen tool sees it: a plain `canopen.Network` with a `RemoteNode`
from mtq.eds, on python-can's virtual bus, talking to a MagnetorquerBoard at the other end.

The board runs in a small thread on its own simulated clock (1 ms per step), so what is checked
about its heartbeat is its period on that clock, not the host's timing.
"""
import contextlib
import itertools
import threading
import time

import can
import canopen
import pytest

from bench.bus.can import protocol as p
from bench.bus.can.board import MagnetorquerBoard
from bench.bus.can.canopen_od import EDS_PATH
from bench.bus.can.config import BoardConfig

NODE_ID = 0x10
STEP_S = 0.001
_channels = itertools.count()


class BoardThread:
    """A board stepped on a simulated clock; records the clock at each heartbeat it sends."""

    def __init__(self, channel: str, protocol: p.Protocol | None = None):
        self.bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self.board = MagnetorquerBoard(self.bus, BoardConfig(), protocol or p.Protocol(NODE_ID, "e2e"))
        self.now_s = 0.0
        self.heartbeats: list[tuple[float, int]] = []      # (board clock, NMT state)
        send = self.bus.send

        def recording_send(msg, timeout=None):
            if msg.arbitration_id == 0x700 + NODE_ID:
                self.heartbeats.append((self.now_s, msg.data[0]))
            send(msg, timeout)
        self.bus.send = recording_send
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        while not self.stop.is_set() and self.now_s < 60.0:
            self.board.step(self.now_s)
            self.now_s = round(self.now_s + STEP_S, 9)
            time.sleep(0.0005)

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join(2.0)
        self.bus.shutdown()


@contextlib.contextmanager
def tool_and_board(protocol: p.Protocol | None = None):
    channel = f"canopen-tool-{next(_channels)}"
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel, receive_own_messages=False)
    node = network.add_node(canopen.RemoteNode(NODE_ID, str(EDS_PATH)))
    # canopen's 0.3 s default is a tool's wait for a board on a quiet bus; here the board is a
    # thread of this test on a possibly busy host. A hang bound, not a speed check.
    node.sdo.RESPONSE_TIMEOUT = 10.0
    try:
        with BoardThread(channel, protocol) as board:
            yield network, node, board
    finally:
        network.disconnect()


@pytest.fixture
def tool():
    with tool_and_board() as parts:
        yield parts


def test_on_the_secoc_profile_a_tool_reads_but_cannot_write_the_board():
    """SDO has no authentication: where the board obeys only authenticated commands and NMT, a
    write from anyone on the bus (a longer command timeout, no heartbeat) is refused."""
    with tool_and_board(p.Protocol(NODE_ID, "secoc", key=bytes(range(16)))) as (network, node, board):
        node.nmt.wait_for_heartbeat(timeout=3.0)
        assert node.sdo[0x1018][2].raw == 0x4D545131
        for index, value in ((0x2100, 60_000), (0x1017, 0)):
            with pytest.raises(canopen.SdoAbortedError) as refused:
                node.sdo[index].raw = value
            assert refused.value.code == 0x08000021        # CiA 301: refused by local control
        assert board.board.config.command_timeout_s == 0.1 and board.board.config.heartbeat_period_s == 0.1
        assert board.board.sdo.refused_writes == 2


def _intervals_s(heartbeats):
    return [round(b - a, 6) for (a, _), (b, _) in zip(heartbeats, heartbeats[1:])]


def test_a_canopen_tool_reads_identity_and_sets_the_heartbeat(tool):
    network, node, board = tool
    node.nmt.wait_for_heartbeat(timeout=3.0)
    assert node.nmt.state == "PRE-OPERATIONAL"
    assert node.sdo[0x1018][1].raw == 0x00000000
    assert node.sdo[0x1018][2].raw == 0x4D545131                 # product code "MTQ1"
    assert node.sdo[0x1008].raw == "orbit-hil-bench MTQ"          # a segmented upload
    assert node.sdo[0x1017].raw == 100                            # ms, = BoardConfig's 0.1 s
    assert node.sdo[0x2100].raw == 100                            # command timeout, ms

    while len(board.heartbeats) < 4:        # a few at the EDS's period first
        time.sleep(0.01)
    node.sdo[0x1017].raw = 20
    written_at = len(board.heartbeats)
    assert node.sdo[0x1017].raw == 20
    assert board.board.config.heartbeat_period_s == 0.02
    deadline = time.monotonic() + 5.0
    while len(board.heartbeats) < written_at + 6:
        assert time.monotonic() < deadline, "no heartbeats after the write"
        time.sleep(0.01)
    before, after = board.heartbeats[:written_at], board.heartbeats[written_at:]
    # On the board's clock, each within one of its 1 ms steps (a deadline between two steps is
    # served at the next).
    assert _intervals_s(before) == pytest.approx([0.1] * (len(before) - 1), abs=1.01 * STEP_S)
    assert _intervals_s(after) == pytest.approx([0.02] * (len(after) - 1), abs=1.01 * STEP_S)

    with pytest.raises(canopen.SdoAbortedError):
        node.sdo[0x1018][1].raw = 7                               # identity is read-only
    with pytest.raises(canopen.SdoAbortedError):
        node.sdo[0x2100].raw = 0                                  # a command timeout of 0 is refused


def test_a_canopen_tool_starts_the_board_and_hears_its_command_timeout(tool):
    network, node, board = tool
    node.nmt.wait_for_heartbeat(timeout=3.0)
    node.nmt.state = "OPERATIONAL"             # plain NMT start (the e2e profile obeys it)
    deadline = time.monotonic() + 5.0
    while True:
        node.nmt.wait_for_heartbeat(timeout=1.0)
        if node.nmt.state == "OPERATIONAL":
            break
        assert time.monotonic() < deadline, node.nmt.state
    assert board.heartbeats[-1][1] == p.NMT_OPERATIONAL
    # One command (RPDO1, MTQ_CMD with its E2E protection, which the EDS maps but a generic tool
    # cannot compute), then none: after the command timeout the board reports it (CiA 301 EMCY).
    command = p.Protocol(NODE_ID, "e2e").command([0.05, 0.0, 0.0], counter=0)
    network.send_message(command.arbitration_id, command.data)
    deadline = time.monotonic() + 5.0
    while not [e for e in node.emcy.log if e.code == p.EMCY_COMMAND_TIMEOUT]:
        assert time.monotonic() < deadline, node.emcy.log
        time.sleep(0.01)
    assert board.board.accepted == 1
    emcy = [e for e in node.emcy.log if e.code == p.EMCY_COMMAND_TIMEOUT][0]
    assert emcy.register == 0x10                                  # communication error
    assert emcy.data[0] == 0 and emcy.data[1] == 0                # E2eStatus, RejectedCounter
    assert node.sdo[0x1001].raw == 0x10
    assert node.sdo[0x1003][0].raw >= 1 and node.sdo[0x1003][1].raw == p.EMCY_COMMAND_TIMEOUT
    node.sdo[0x1003][0].raw = 0                                   # CiA 301: clears the history
    assert node.sdo[0x1003][0].raw == 0
    assert board.board.state.safe_state and board.board.state.command_timeout
