"""Any python-can interface per node ([can.driver_bus], [can.board_bus]) and the launcher's check of
every bus before a process starts: unknown interface, unopenable channel, socketcan without kernel
CAN, virtual across processes; each one line naming the field, exit 2, nothing started."""
from __future__ import annotations

import os
import tty

import pytest

from bench.bus.can import preflight
from bench.bus.can.config import BusSpec
from bench.bus.can.transport import open_bus
from bench.scenario import ScenarioError, parse_scenario
from conftest import run_bench_cli


def can_config(**can):
    return parse_scenario({"name": "can-test", "can": can}).can


@pytest.fixture
def pty_channel():
    """A pseudo-terminal: the slave's path is the channel, nobody answers on the master."""
    master, slave = os.openpty()
    tty.setraw(slave)
    yield os.ttyname(slave)
    os.close(slave)
    os.close(master)


def test_the_transport_shorthand_gives_every_node_its_channel():
    config = can_config(transport="zenoh", flight_channel="f", board_channel="b")
    assert config.bus_spec("driver") == BusSpec("zenoh", "f") == config.bus_spec("busmodel_flight")
    assert config.bus_spec("board") == BusSpec("zenoh", "b") == config.bus_spec("busmodel_board")
    assert config.bus_field("driver") == "can.transport"


def test_a_node_bus_names_a_python_can_interface_with_its_options():
    config = can_config(driver_bus={"interface": "slcan", "channel": "/dev/pts/3", "bitrate": 500_000,
                                    "options": {"tty_baudrate": 115200, "sleep_after_open": 0}})
    spec = config.bus_spec("driver")
    assert (spec.interface, spec.channel, spec.bitrate, spec.fd) == ("slcan", "/dev/pts/3", 500_000, True)
    assert spec.options == {"tty_baudrate": 115200, "sleep_after_open": 0}
    assert config.bus_field("driver") == "can.driver_bus"
    # The bus model's end stays on the transport: the driver's bus is what changed.
    assert config.bus_spec("busmodel_flight") == BusSpec("zenoh", "flight")
    assert config.bus_spec("board") == BusSpec("zenoh", "board")


@pytest.mark.parametrize("bus, message", [
    ({"channel": "x"}, "interface"),
    ({"interface": "slcan", "options": {"channel": "y"}}, "options: channel is set by the bench"),
    ({"interface": "slcan", "options": {"tty_baudrate": [1]}}, "options"),
    ({"interface": "slcan", "fd": False}, "driver_bus.fd: the secoc profile"),
    ({"interface": "slcan", "colour": "red"}, "colour"),
])
def test_bad_bus_fields_are_named_on_load(bus, message):
    with pytest.raises(ScenarioError) as err:
        can_config(driver_bus=bus)
    assert message in str(err.value)


def test_a_classic_can_bus_is_allowed_on_the_e2e_profile():
    config = can_config(driver_bus={"interface": "slcan", "fd": False}, security={"profile": "e2e"})
    assert config.bus_spec("driver").fd is False


def test_unknown_interface_is_refused_naming_the_field():
    with pytest.raises(preflight.CanBusError) as err:
        preflight.check_run_buses(can_config(board_bus={"interface": "carrier_pigeon", "channel": "c"}))
    assert str(err.value).startswith("can.board_bus.interface: 'carrier_pigeon' is not a python-can interface")
    assert "slcan" in str(err.value) and "\n" not in str(err.value)


def test_an_unopenable_channel_is_refused_naming_it(tmp_path):
    missing = str(tmp_path / "no-such-tty")
    with pytest.raises(preflight.CanBusError) as err:
        preflight.check_run_buses(can_config(driver_bus={"interface": "slcan", "channel": missing,
                                                         "options": {"sleep_after_open": 0}}))
    assert str(err.value).startswith(f"can.driver_bus.channel: slcan channel '{missing}' cannot be opened")
    assert "\n" not in str(err.value)


def test_an_openable_channel_passes(pty_channel):
    preflight.check_run_buses(can_config(driver_bus={"interface": "slcan", "channel": pty_channel,
                                                     "bitrate": 500_000, "options": {"sleep_after_open": 0}}))


def test_socketcan_without_kernel_can_is_refused(monkeypatch):
    monkeypatch.setattr(preflight, "kernel_has_can", lambda: False)   # this host has none anyway; CI may
    with pytest.raises(preflight.CanBusError, match=r'^can.transport: "socketcan" needs kernel CAN'):
        preflight.check_run_buses(can_config(transport="socketcan"))
    with pytest.raises(preflight.CanBusError, match=r'^can.board_bus.interface: "socketcan" needs kernel CAN'):
        preflight.check_run_buses(can_config(board_bus={"interface": "socketcan", "channel": "can0"}))


def test_socketcan_on_a_missing_interface_is_refused(monkeypatch):
    monkeypatch.setattr(preflight, "kernel_has_can", lambda: True)
    with pytest.raises(preflight.CanBusError, match=r"^can.driver_bus.channel: CAN interface 'nocan9' does not"):
        preflight.check_run_buses(can_config(driver_bus={"interface": "socketcan", "channel": "nocan9"}))


def test_virtual_is_refused_across_processes():
    with pytest.raises(preflight.CanBusError, match=r'^can.transport: python-can\'s "virtual" bus is in-process'):
        preflight.check_run_buses(can_config(transport="virtual"))


def test_zenoh_channels_are_checked_without_a_session():
    preflight.check_run_buses(can_config(transport="zenoh"))
    # A channel that is no key-expression chunk is refused on load (config.channel_problem).
    with pytest.raises(ScenarioError, match=r"^<scenario>: can.driver_bus.channel: 'a/b' is not a zenoh CAN channel"):
        can_config(driver_bus={"interface": "zenoh", "channel": "a/b"})


def test_open_bus_passes_the_interface_its_options(pty_channel):
    bus = open_bus(BusSpec("slcan", pty_channel, bitrate=250_000, options={"sleep_after_open": 0, "tty_baudrate": 9600}),
                   run_id="r1")
    try:
        assert bus.serialPortOrig.baudrate == 9600
    finally:
        bus.shutdown()


def write_scenario(tmp_path, can_toml: str):
    path = tmp_path / "bad_can.toml"
    path.write_text('name = "bad_can"\nkind = "attitude"\n[run]\nsteps = 2\n[estimator]\nmode = "truth"\n'
                    f'[can]\n{can_toml}\n')
    return path


@pytest.mark.parametrize("can_toml, first_words", [
    ('transport = "virtual"', "can.transport: python-can's \"virtual\" bus"),
    ('[can.driver_bus]\ninterface = "slcan"\nchannel = "/nonexistent/tty"\noptions = { sleep_after_open = 0 }',
     "can.driver_bus.channel: slcan channel '/nonexistent/tty' cannot be opened"),
])
def test_bench_run_refuses_a_bus_before_starting_anything(tmp_path, can_toml, first_words):
    runs = tmp_path / "runs"
    result = run_bench_cli("run", str(write_scenario(tmp_path, can_toml)), "--run-id", "refused", "--runs-dir",
                           str(runs), "--no-progress", timeout_s=60)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert lines == [f"bench: error: {lines[0].removeprefix('bench: error: ')}"]
    assert lines[0].removeprefix("bench: error: ").startswith(first_words)
    assert not (runs / "refused").exists()     # nothing written, nothing started


def test_only_the_buses_of_nodes_started_here_are_checked():
    config = can_config(driver_bus={"interface": "slcan", "channel": "/dev/ttyACM0"},
                        board_bus={"interface": "carrier_pigeon"})
    # A deployment runs the controller (the driver) and the board on other hosts: their channels are theirs.
    assert preflight.roles_on_this_host(config, {"controller": "obc", "mtq": "rig"}) == ["busmodel_flight", "busmodel_board"]
    preflight.check_run_buses(config, preflight.roles_on_this_host(config, {"controller": "obc", "mtq": "rig"}))
    with pytest.raises(preflight.CanBusError, match="^can.board_bus.interface"):
        preflight.check_run_buses(config, preflight.roles_on_this_host(config, {"controller": "obc"}))
