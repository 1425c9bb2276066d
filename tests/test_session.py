"""The Zenoh session factory: never Zenoh's defaults."""
import json
import socket
import time

import pytest

from bench.bus.session import (
    SessionConfigError, SessionOptions, build_config, free_loopback_port, loopback_endpoint, open_session,
)


def setting(config, key):
    return json.loads(config.get_json(key))


def test_default_options_disable_multicast_and_listen_on_loopback_only():
    config = build_config(SessionOptions())
    assert setting(config, "scouting/multicast/enabled") is False
    assert setting(config, "scouting/gossip/enabled") is True
    listen = setting(config, "listen/endpoints")
    assert listen and all(e.startswith("tcp/127.0.0.1:") for e in listen)


def test_user_config_file_cannot_turn_multicast_back_on(tmp_path):
    path = tmp_path / "zenoh.json5"
    path.write_text('{ scouting: { multicast: { enabled: true } }, listen: { endpoints: ["tcp/0.0.0.0:7447"] } }')
    config = build_config(SessionOptions(config_file=path))
    assert setting(config, "scouting/multicast/enabled") is False
    assert setting(config, "listen/endpoints") == ["tcp/127.0.0.1:0"]


def test_missing_or_invalid_config_file_is_named(tmp_path):
    with pytest.raises(SessionConfigError, match="does not exist"):
        build_config(SessionOptions(config_file=tmp_path / "nope.json5"))
    bad = tmp_path / "bad.json5"
    bad.write_text("{ this is not json5")
    with pytest.raises(SessionConfigError, match="invalid"):
        build_config(SessionOptions(config_file=bad))


def test_bad_endpoint_is_named():
    with pytest.raises(SessionConfigError, match="not of the form"):
        build_config(SessionOptions(listen=("127.0.0.1:7447",)))


def test_port_in_use_is_a_clear_error():
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        with pytest.raises(SessionConfigError, match=f"port {port} .* already in use"):
            open_session(SessionOptions(listen=(loopback_endpoint(port),)))


def test_two_sessions_exchange_samples_over_loopback():
    hub = loopback_endpoint(free_loopback_port())
    a = open_session(SessionOptions(listen=(hub,)))
    b = open_session(SessionOptions(connect=(hub,)))
    try:
        received = []
        sub = a.declare_subscriber("bench/test/**", lambda s: received.append(s.payload.to_bytes()))
        pub = b.declare_publisher("bench/test/x")
        deadline = time.monotonic() + 5
        while not pub.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.01)
        pub.put(b"ping")
        while not received and time.monotonic() < deadline:
            time.sleep(0.01)
        assert received == [b"ping"]
        sub.undeclare()
    finally:
        b.close()
        a.close()
