"""The `zenoh` python-can interface and open_can_bus: bus semantics, across processes, bad input."""
from __future__ import annotations

import subprocess
import sys
import time
import uuid
from pathlib import Path

import can
import pytest

from bench.bus.can import zenoh_wire
from bench.bus.can.transport import TransportUnavailable, default_transport, kernel_has_can, open_can_bus
from bench.bus.can.zenoh_interface import ZenohCanBus, channel_key
from bench.bus.session import SessionOptions, free_loopback_port, loopback_endpoint, open_session

PEER = Path(__file__).with_name("can_peer.py")
RECV_S = 5.0
PEER_S = 10.0


@pytest.fixture
def run_id() -> str:
    return f"cantest-{uuid.uuid4().hex[:8]}"


@pytest.fixture
def endpoint() -> str:
    return loopback_endpoint(free_loopback_port())


def zbus(run_id: str, endpoint: str, *, listen: bool = False, channel: str = "vcan0", **kwargs) -> ZenohCanBus:
    where = {"listen": [endpoint]} if listen else {"connect": [endpoint]}
    return can.Bus(interface="zenoh", channel=channel, run_id=run_id, ignore_config=True, **where, **kwargs)


def frame(arbitration_id: int, data: bytes = b"", **kwargs) -> can.Message:
    return can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=kwargs.pop("is_extended_id", False),
                       **kwargs)


def start_peer(mode: str, run_id: str, endpoint: str, count: int) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, str(PEER), mode, str(count), "--interface", "zenoh", "--channel", "vcan0",
                             "--run-id", run_id, "--connect", endpoint],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_until(condition, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def finish(peer: subprocess.Popen) -> None:
    out, err = peer.communicate(timeout=PEER_S)
    assert peer.returncode == 0, f"peer failed: {out} {err}"


def test_entry_point_gives_the_zenoh_bus(run_id, endpoint):
    with zbus(run_id, endpoint, listen=True) as bus:
        assert isinstance(bus, ZenohCanBus)
        assert bus.channel_info == f"Zenoh CAN channel {channel_key(run_id, 'vcan0')}"


def test_frames_cross_processes_with_every_field(run_id, endpoint):
    sent = [
        frame(0x100, b"\x01\x02\x03"),
        frame(0x1ABCDEF0, bytes(range(8)), is_extended_id=True),
        frame(0x200, b""),
        frame(0x300, dlc=4, is_remote_frame=True),
        frame(0x0, b"\x00" * 8, is_error_frame=True),
    ]
    with zbus(run_id, endpoint, listen=True) as bus:
        peer = start_peer("echo", run_id, endpoint, len(sent))
        assert bus.wait_for_peers(1, PEER_S)
        for msg in sent:
            bus.send(msg)
        echoed = [bus.recv(RECV_S) for _ in sent]
        finish(peer)
    for original, back in zip(sent, echoed):
        assert back is not None
        assert back.arbitration_id == original.arbitration_id + 1
        assert back.is_extended_id == original.is_extended_id
        assert back.is_error_frame == original.is_error_frame
        assert back.is_remote_frame == original.is_remote_frame
        assert back.dlc == original.dlc
        assert bytes(back.data) == bytes(original.data)
        assert back.is_rx and back.channel == "vcan0"
        assert back.timestamp > 0


def test_frames_of_one_sender_arrive_in_order(run_id, endpoint):
    count = 2000
    with zbus(run_id, endpoint, listen=True) as bus:
        peer = start_peer("burst", run_id, endpoint, count)
        assert bus.wait_for_peers(1, PEER_S)
        got = [bus.recv(RECV_S) for _ in range(count)]
        bus.send(frame(0x7FF))  # tells the peer it may leave
        finish(peer)
        assert bus.stats.sequence_gaps == 0
    assert [int.from_bytes(m.data, "little") for m in got if m is not None] == list(range(count))


def test_every_other_bus_on_the_channel_sees_a_frame_and_the_sender_does_not(run_id, endpoint):
    with zbus(run_id, endpoint, listen=True) as a, zbus(run_id, endpoint) as b, zbus(run_id, endpoint) as c:
        assert a.wait_for_peers(2, PEER_S) and b.wait_for_peers(2, PEER_S) and c.wait_for_peers(2, PEER_S)
        a.send(frame(0x10, b"\xaa"))
        assert bytes(b.recv(RECV_S).data) == b"\xaa"
        assert bytes(c.recv(RECV_S).data) == b"\xaa"
        assert a.recv(0.2) is None


def test_receive_own_messages_when_asked(run_id, endpoint):
    with zbus(run_id, endpoint, listen=True, receive_own_messages=True) as a, zbus(run_id, endpoint) as b:
        assert a.wait_for_peers(1, PEER_S)
        a.send(frame(0x11, b"\x01"))
        own = a.recv(RECV_S)
        assert own is not None and own.arbitration_id == 0x11 and not own.is_rx
        assert b.recv(RECV_S).arbitration_id == 0x11


def test_channels_and_runs_are_kept_apart(run_id, endpoint):
    with zbus(run_id, endpoint, listen=True) as a, zbus(run_id, endpoint, channel="vcan1") as other_channel, \
            zbus(run_id + "x", endpoint) as other_run, zbus(run_id, endpoint) as same:
        assert a.wait_for_peers(1, PEER_S) and same.wait_for_peers(1, PEER_S)
        a.send(frame(0x12, b"\x02"))
        assert same.recv(RECV_S).arbitration_id == 0x12
        assert other_channel.recv(0.2) is None
        assert other_run.recv(0.2) is None


def test_filters_apply(run_id, endpoint):
    with zbus(run_id, endpoint, listen=True) as a, \
            zbus(run_id, endpoint, can_filters=[{"can_id": 0x20, "can_mask": 0x7FF, "extended": False}]) as b:
        assert a.wait_for_peers(1, PEER_S)
        a.send(frame(0x21))
        a.send(frame(0x20, b"\x05"))
        assert b.recv(RECV_S).arbitration_id == 0x20


def test_malformed_payloads_are_counted_and_dropped(run_id, endpoint):
    good = zenoh_wire.encode(frame(0x30, b"\x01"), timestamp_s=1.0, sender_id=7, sequence=0)
    garbage = [
        b"",
        b"\x01\x02",
        b"\x09" + good[1:],                                   # unknown wire version
        good[:-1],                                            # data shorter than announced
        good + b"\x00",                                       # longer than announced
        good[:1] + b"\x80" + good[2:],                        # unknown flag bit
        zenoh_wire._HEADER.pack(1, 0, 9, 9, 0x30, 1.0, 7, 1) + bytes(9),   # classic frame, 9 bytes
        zenoh_wire._HEADER.pack(1, 0, 1, 1, 0x800, 1.0, 7, 2) + b"\x00",   # 11-bit id out of range
        zenoh_wire._HEADER.pack(1, 0, 1, 1, 0x30, float("nan"), 7, 3) + b"\x00",
    ]
    with zbus(run_id, endpoint, listen=True) as bus:
        raw = open_session(SessionOptions(connect=(endpoint,)))
        try:
            # Malformed payloads first, then one good frame: once the good one is read, every
            # earlier payload has been through the decoder (one publisher, in order).
            pub = raw.declare_publisher(channel_key(run_id, "vcan0"))
            assert wait_until(lambda: pub.matching_status.matching, PEER_S)
            for payload in garbage:
                pub.put(payload)
            pub.put(good)
            got = bus.recv(RECV_S)
        finally:
            raw.close()
        assert got is not None and got.arbitration_id == 0x30
        assert bus.stats.malformed == len(garbage)
        assert bus.stats.received == 1


@pytest.mark.parametrize("bad", [
    frame(0x800, b"\x00"),                                    # 11-bit id too large
    frame(0x20000000, b"\x00", is_extended_id=True),          # 29-bit id too large
    frame(0x10, bytes(9)),                                    # classic CAN carries 8 bytes
    frame(0x10, b"\x00", is_fd=True),                         # FD on a classic bus
])
def test_sending_an_invalid_frame_is_refused(run_id, endpoint, bad):
    with zbus(run_id, endpoint, listen=True) as bus:
        with pytest.raises(ValueError):
            bus.send(bad)
        assert bus.stats.sent == 0


def test_use_after_shutdown_and_bad_construction(run_id, endpoint):
    bus = zbus(run_id, endpoint, listen=True)
    bus.shutdown()
    bus.shutdown()  # twice is fine, as python-can requires
    with pytest.raises(can.CanOperationError):
        bus.send(frame(0x1))
    with pytest.raises(can.CanOperationError):
        bus.recv(0.1)
    with pytest.raises(can.CanInitializationError, match="run_id"):
        can.Bus(interface="zenoh", channel="vcan0", ignore_config=True)
    with pytest.raises(can.CanInitializationError, match="channel"):
        can.Bus(interface="zenoh", channel="vcan/0", run_id=run_id, ignore_config=True)
    with pytest.raises(can.CanInitializationError, match="endpoint"):
        can.Bus(interface="zenoh", channel="vcan0", run_id=run_id, connect=["127.0.0.1"], ignore_config=True)


def test_open_can_bus_per_transport(run_id):
    with open_can_bus("virtual", "vcan0", run_id=run_id) as a, open_can_bus("virtual", "vcan0", run_id=run_id) as b:
        a.send(frame(0x40, b"\x04"))
        assert b.recv(RECV_S).arbitration_id == 0x40
    with open_can_bus("zenoh", "vcan0", run_id=run_id, receive_own_messages=True) as z:
        assert isinstance(z, ZenohCanBus)
        z.send(frame(0x41))
        assert z.recv(RECV_S).arbitration_id == 0x41
    with pytest.raises(ValueError, match="not one of"):
        open_can_bus("carrier-pigeon", "vcan0", run_id=run_id)
    if not kernel_has_can():
        assert default_transport() == "zenoh"
        with pytest.raises(TransportUnavailable, match="zenoh"):
            open_can_bus("socketcan", "vcan0", run_id=run_id)


def test_buses_sharing_a_node_session(run_id, endpoint):
    session = open_session(SessionOptions(listen=(endpoint,)))
    try:
        a = can.Bus(interface="zenoh", channel="vcan0", run_id=run_id, session=session, ignore_config=True)
        b = can.Bus(interface="zenoh", channel="vcan0", run_id=run_id, session=session, ignore_config=True)
        assert a.wait_for_peers(1, PEER_S)
        a.send(frame(0x50, b"\x05"))
        assert b.recv(RECV_S).arbitration_id == 0x50
        assert a.recv(0.2) is None
        a.shutdown()
        b.shutdown()
        # The session belongs to the node: still usable after its buses are gone.
        assert not session.is_closed()
    finally:
        session.close()


def test_a_bus_follows_a_bounded_number_of_senders(run_id, endpoint):
    """A frame under a new sender id each time (anyone on the channel can) grows nothing without
    bound: the oldest ids are forgotten past MAX_TRACKED_SENDERS."""
    from bench.bus.can.zenoh_interface import MAX_TRACKED_SENDERS

    class Sample:
        def __init__(self, payload):
            self.payload = type("P", (), {"to_bytes": lambda _self: payload})()

    with zbus(run_id, endpoint, listen=True) as bus:
        for sender in range(1, 10 * MAX_TRACKED_SENDERS):
            payload = zenoh_wire.encode(frame(0x10), timestamp_s=1.0, sender_id=sender, sequence=0)
            bus._on_sample(Sample(payload))
        assert len(bus._rx_sequence) == MAX_TRACKED_SENDERS
        assert bus.stats.sequence_gaps == 0
