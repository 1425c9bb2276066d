"""Every input secured (issue 44): a scenario field that names a device or an endpoint never makes
the bench open anything else (channels are devices, never URLs), and every refusal names its field,
one line, exit 2, before anything starts: duplicate keys in JSON and TOML, integers too long to
convert, a channel attributed to the field it came from. The generated cases are in
test_scenario_fuzz.py."""
from __future__ import annotations

import json
import os
import socket
import tty

import msgspec
import pytest

from bench.bus.can import preflight
from bench.bus.deployment import DeploymentError, load_deployment
from bench.scenario import ScenarioError, load_scenario, parse_scenario
from bench.studies.campaign import CampaignError, load_spec
from conftest import bench_processes, run_bench_cli

ATTITUDE_CAN = 'name = "inputs"\nkind = "attitude"\n[run]\nsteps = 2\n[estimator]\nmode = "truth"\n'
HUGE = "9" * 5001


def can_config(**can):
    return parse_scenario({"name": "inputs", "can": can}).can


def bench_run_refused(tmp_path, scenario_path, run_id: str, before_checks=lambda: None) -> str:
    """`bench run` of a scenario it must refuse, in tmp_path: exit 2, one line on stderr
    (returned), nothing written or started. `before_checks`: what must hold first, whatever else."""
    runs = tmp_path / "runs"
    result = run_bench_cli("run", str(scenario_path), "--run-id", run_id, "--runs-dir", str(runs), "--no-progress",
                           cwd=tmp_path, timeout_s=60)
    before_checks()
    assert result.returncode == 2, result.stderr + result.stdout
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in result.stdout, result.stderr
    assert not runs.exists() and bench_processes(run_id) == []
    return lines[0]


# --- the attacks, through `bench run` ---------------------------------------------------
def test_a_spy_url_channel_touches_no_file(tmp_path):
    # pyserial's spy:// handler opened its log file for writing: victim.txt in the working
    # directory was left at 0 bytes, by the launcher's preflight, before it refused the run.
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    path = tmp_path / "spy.toml"
    path.write_text(ATTITUDE_CAN + '[can.driver_bus]\ninterface = "slcan"\nchannel = "spy:///nonexistent?file=victim.txt"\n')

    def untouched():
        assert victim.read_text() == "precious\n"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["spy.toml", "victim.txt"]

    line = bench_run_refused(tmp_path, path, "spy-url", before_checks=untouched)
    assert "can.driver_bus.channel: 'spy:///nonexistent?file=victim.txt' is not a device path" in line


def test_a_socket_url_channel_connects_nowhere(tmp_path):
    # socket://HOST:PORT made the launcher connect out and write "O\rC\r".
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        listener.settimeout(0.5)
        port = listener.getsockname()[1]
        path = tmp_path / "socket.toml"
        path.write_text(ATTITUDE_CAN + f'[can.board_bus]\ninterface = "slcan"\nchannel = "socket://127.0.0.1:{port}"\n'
                        "options = { sleep_after_open = 0 }\n")
        line = bench_run_refused(tmp_path, path, "socket-url")
        assert line.startswith(f"bench: error: {path}: can.board_bus.channel: 'socket://127.0.0.1:{port}'"), line
        with pytest.raises(socket.timeout):
            listener.accept()


def test_a_json_key_given_twice_is_refused_naming_it(tmp_path):
    # json keeps the last: a reviewer reads "secoc" while the run would use "e2e".
    path = tmp_path / "scenario.json"
    path.write_text('{"name": "inputs", "kind": "attitude", "run": {"steps": 2}, "estimator": {"mode": "truth"}, '
                    '"can": {"security": {"profile": "secoc", "profile": "e2e"}}}')
    line = bench_run_refused(tmp_path, path, "json-twice")
    assert f"{path}: can.security.profile: key given twice" in line


@pytest.mark.parametrize("suffix", ["toml", "json"])
def test_an_integer_of_5001_digits_is_refused_naming_its_field(tmp_path, suffix):
    path = tmp_path / f"huge.{suffix}"
    path.write_text(f'name = "inputs"\n[run]\nsteps = {HUGE}\n' if suffix == "toml"
                    else f'{{"name": "inputs", "run": {{"steps": {HUGE}}}}}')
    line = bench_run_refused(tmp_path, path, f"huge-{suffix}")
    assert f"{path}: run.steps: an integer of 5001 digits" in line


def test_a_bad_flight_channel_is_attributed_to_its_field(tmp_path):
    path = tmp_path / "channel.toml"
    path.write_text(ATTITUDE_CAN + '[can]\nflight_channel = "**"\n')
    line = bench_run_refused(tmp_path, path, "flight-channel")
    assert f"{path}: can.flight_channel: '**'" in line and "can.transport" not in line


# --- channels are devices: every field naming one, every interface ------------------------------
PYSERIAL_URLS = ["spy:///dev/ttyACM0?file=victim.txt", "loop://", "socket://127.0.0.1:7", "rfc2217://127.0.0.1:7",
                 "alt:///dev/ttyACM0?class=PosixPollSerial", "hwgrep://.*", "cp2110://0001:0002:00", "/dev/x://y"]


@pytest.mark.parametrize("interface", ["robotell", "seeedstudio", "serial", "slcan"])   # pyserial opens their channel
@pytest.mark.parametrize("channel", PYSERIAL_URLS + ["victim.txt", "./ttyACM0", "/dev/../home/victim.txt", "/dev/tty ACM0"])
@pytest.mark.parametrize("role", ["driver", "board"])
def test_a_serial_channel_is_a_device_path(interface, channel, role):
    with pytest.raises(ScenarioError) as refused:
        can_config(**{f"{role}_bus": {"interface": interface, "channel": channel}})
    assert str(refused.value).startswith(f"<scenario>: can.{role}_bus.channel: {channel!r} is not a device path")


@pytest.mark.parametrize("bus, field", [
    ({"interface": "slcan", "channel": "/dev/ttyACM0@11520O"}, "can.driver_bus.channel"),      # a baud rate in digits
    ({"interface": "socketcan", "channel": "vcan0/../x"}, "can.driver_bus.channel"),
    ({"interface": "socketcand", "channel": "can0", "options": {"host": "http://10.0.0.2/"}}, "can.driver_bus.options.host"),
    ({"interface": "udp_multicast", "channel": "10.0.0.2"}, "can.driver_bus.channel"),       # unicast: not its group
    ({"interface": "pcan", "channel": "socket://127.0.0.1:7"}, "can.driver_bus.channel"),
    ({"interface": "kvaser", "channel": "/tmp/x"}, "can.driver_bus.channel"),
    ({"interface": "zenoh", "channel": "flight", "options": {"connect": "tcp/10.0.0.2:7447"}}, "can.driver_bus.options.connect"),
    ({"interface": "neovi", "channel": "1", "options": {"override_library_name": "libevil.so"}},
     "can.driver_bus.options.override_library_name"),
    ({"interface": "pcan", "channel": "PCAN_USBBUS1", "options": {"state": "/home/x"}}, "can.driver_bus.options.state"),
])
def test_every_field_naming_a_device_or_an_endpoint_is_checked(bus, field):
    with pytest.raises(ScenarioError, match=rf"^<scenario>: {field}: "):
        can_config(driver_bus=bus)


@pytest.mark.parametrize("transport, fields", [
    ("zenoh", {"flight_channel": "a/b"}), ("zenoh", {"board_channel": "**"}),
    ("socketcan", {"flight_channel": "vcan0", "board_channel": "spy://x"}),
])
def test_the_transport_channels_are_checked_on_load(transport, fields):
    field = list(fields)[-1]
    with pytest.raises(ScenarioError, match=rf"^<scenario>: can.{field}: "):
        can_config(transport=transport, **fields)


def test_devices_and_endpoints_the_interfaces_name_are_accepted():
    for bus in [{"interface": "slcan", "channel": "/dev/ttyACM0@115200"},
                {"interface": "serial", "channel": "/dev/serial/by-id/usb-CANable.io_canable2_208C32A0-if00"},
                {"interface": "seeedstudio", "channel": "/dev/serial/by-path/pci-0000:00:14.0-usb-0:2:1.0"},
                {"interface": "socketcan", "channel": "can0"},
                {"interface": "socketcand", "channel": "can0", "options": {"host": "rig.lab", "port": 29536}},
                {"interface": "udp_multicast", "channel": "239.74.163.2"},
                {"interface": "pcan", "channel": "PCAN_USBBUS1"}]:
        assert can_config(driver_bus=bus).bus_spec("driver").channel == bus["channel"]


@pytest.fixture
def pty_channel():
    master, slave = os.openpty()
    tty.setraw(slave)
    yield os.ttyname(slave)
    os.close(slave)
    os.close(master)


def test_a_serial_channel_that_is_no_device_is_not_opened(tmp_path, pty_channel):
    # A path, but a regular file: pyserial would open it read-write. The preflight looks first.
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    before = victim.stat()
    with pytest.raises(preflight.CanBusError) as refused:
        preflight.check_run_buses(can_config(driver_bus={"interface": "slcan", "channel": str(victim)}))
    assert str(refused.value) == (f"can.driver_bus.channel: slcan channel '{victim}' cannot be opened: "
                                  "not a character device (a tty)")
    after = victim.stat()
    assert victim.read_text() == "precious\n" and (after.st_mtime_ns, after.st_atime_ns) == (before.st_mtime_ns, before.st_atime_ns)
    # A tty (here a pseudo-terminal) is one, with its baud rate after '@' too.
    preflight.check_run_buses(can_config(driver_bus={"interface": "slcan", "channel": f"{pty_channel}@115200",
                                                     "options": {"sleep_after_open": 0}}))


def test_the_preflight_names_the_transport_channel_field(monkeypatch):
    monkeypatch.setattr(preflight, "kernel_has_can", lambda: True)
    monkeypatch.setattr(preflight, "interface_exists", lambda name: name == "vcan0")
    with pytest.raises(preflight.CanBusError, match=r"^can.board_channel: CAN interface 'vcan9' does not exist"):
        preflight.check_run_buses(can_config(transport="socketcan", flight_channel="vcan0", board_channel="vcan9"))


# --- duplicate keys and long integers in every loader ------------------------------------------
@pytest.mark.parametrize("text, message", [
    ('name = "inputs"\n[can.security]\nprofile = "secoc"\nprofile = "e2e"\n', "can.security.profile: key given twice"),
    ('name = "inputs"\n[run]\nsteps = 2\n[run]\nseed = 3\n', "run: key given twice"),
    ('name = "inputs"\nname = "other"\n', "name: key given twice"),
    ('name = "inputs"\n[can]\n[[can.faults]]\nname = "drop"\ncount = -' + HUGE + "\n", "can.faults.count: an integer of 5001 digits"),
])
def test_toml_refusals_name_the_key(tmp_path, text, message):
    path = tmp_path / "s.toml"
    path.write_text(text)
    with pytest.raises(ScenarioError) as refused:
        load_scenario(path)
    assert str(refused.value).startswith(f"{path}: {message}"), refused.value


@pytest.mark.parametrize("text, message", [
    ('{"name": "inputs", "name": "other"}', "name: key given twice"),
    ('{"name": "inputs", "can": {"faults": [{"name": "drop", "name": "drop"}]}}', "can.faults[0].name: key given twice"),
    ('{"name": "inputs", "plant": {"initial_state_m_mps": [1, -' + HUGE + ', 0, 0, 0, 0]}}',
     "plant.initial_state_m_mps[1]: an integer of 5001 digits"),
])
def test_json_refusals_name_the_key(tmp_path, text, message):
    path = tmp_path / "s.json"
    path.write_text(text)
    with pytest.raises(ScenarioError) as refused:
        load_scenario(path)
    assert str(refused.value).startswith(f"{path}: {message}"), refused.value


def test_a_json_scenario_a_launcher_wrote_loads_again(tmp_path):
    # The hooks refuse only what they must: scenario.json as the launcher writes it loads back.
    scenario = load_scenario("attitude_quick")
    path = tmp_path / "scenario.json"
    path.write_bytes(msgspec.json.encode(scenario))
    assert load_scenario(path) == scenario


DEPLOYMENT = 'name = "lab"\nlauncher = "sim"\n[hosts.sim]\nendpoints = ["tcp/127.0.0.1:7447"]\nnodes = ["plant"]\n'


@pytest.mark.parametrize("text, message", [
    (DEPLOYMENT + 'nodes = ["controller"]\n', "hosts.sim.nodes: key given twice"),
    (DEPLOYMENT.replace('launcher = "sim"', f"secure = {HUGE}"), "secure: an integer of 5001 digits"),
])
def test_deployment_refusals_name_the_key(tmp_path, text, message):
    path = tmp_path / "deploy.toml"
    path.write_text(text)
    with pytest.raises(DeploymentError) as refused:
        load_deployment(path)
    assert f"deployment file {str(path)!r}: {message}" in str(refused.value), refused.value


def test_campaign_spec_refusals_name_the_key(tmp_path):
    path = tmp_path / "spec.toml"
    path.write_text(f'name = "c"\nseeds = {HUGE}\n')
    with pytest.raises(CampaignError, match=rf"^{path}: seeds: an integer of 5001 digits"):
        load_spec(path)
    path.write_text('name = "c"\nname = "d"\n')
    with pytest.raises(CampaignError, match=rf"^{path}: name: key given twice"):
        load_spec(path)
