"""An outside controller for the bench's rendezvous loop: the proof that the message contract is enough.

It imports nothing from `bench`: only Zenoh, json, numpy and scipy (scipy for the discrete
algebraic Riccati equation and the matrix exponential, the same routines the built-in LQR uses, so
the two trajectories agree to rounding). Everything it knows comes from the published contract
(`bench contract export DIR`, docs/contract.md) and from the scenario.json, contract.json and
bus.key the launcher writes into the run directory: the Zenoh settings, the schema version, the
thrusters' limit and seed 003's state scaling are read from the run's contract.json, the orbit, mass,
step and weights from its scenario.json. What stays written here is the vocabulary of the contract:
the key and tag names, and the tag format it implements (version 1, which it checks).

    bench run rendezvous_lqr --external controller --run-id demo --port 7447
    python examples/outside_lqr_controller.py --connect tcp/127.0.0.1:7447 --run-id demo \
        --scenario runs/demo/scenario.json

What it does, per the contract:
- opens its Zenoh session from contract.json's `zenoh.settings` (peer, multicast scouting off, the
  launcher's hub as its only connect endpoint, the run's lease; never Zenoh's default configuration);
- answers presence queries on `bench/<run>/presence/controller` (the launcher waits for an answer,
  the plant for one that says ready, which it does once its command publisher is matched by the
  plant's subscriber): each answer carries the query's nonce and is signed like a message;
- takes an estimate only with a valid MAC under the run's key (bus.key beside scenario.json) and a
  counter above the last one taken, and signs each command (the attachment: version, sender,
  counter, HMAC-SHA256 over key expression, those and the payload; stdlib hmac);
- for each TranslationEstimate on `estimate/translation`, publishes one ThrustCommand on
  `command/thrust` whose header is the estimate's (same seq, same sim_time_s, the upstream stamps
  carried) plus its own `controller_received` and `commanded` stamps;
- stops when the launcher's token `alive/launcher` goes (a real outside node would also ask the
  launcher's presence, `presence/launcher`, since a token is no proof).

The law is the bench's LQR: u = K V x with K from the DARE on the scaled CWH model of the orbit the
flight side believes (seed 003: V scales metres to Mm and m/s to km/s, contract.json
`rendezvous_model.state_scaling`; Q and R from the scenario's [controller] weights, on that scaled
state), saturated at the thrusters' limit per axis (contract.json `envelopes.thrust.max_abs_n`).

`--break MODE:STEP` (repeatable) makes a deliberately broken variant for `bench contract check`
(tests/test_contract.py): the command of step STEP goes to a wrong key (wrong-key), carries a field
the schema does not have (bad-field), carries the next step's sequence number (skip-seq), or a MAC
that is not the run's (bad-mac); modes given for the same step all apply to its command.
`--misbehave MODE` (repeatable) breaks it for the whole run: twice the gain and no thrust limit
(no-saturation), no
own stamps (no-stamps), a signed copy of each command on `command/applied`, the plant's key
(foreign-key), estimates taken without checking their tag or counter (trust-all), or no stop
when the launcher leaves (ignore-stop), or a `status` the contract does not have (free-status).
"""
from __future__ import annotations

import argparse
import hashlib
import hmac
import json
import queue
import sys
import threading
import time
from pathlib import Path

import numpy as np
import zenoh
from scipy.linalg import expm, solve_discrete_are

NAME = "controller"
BREAKS = ("wrong-key", "bad-field", "skip-seq", "bad-mac")
MISBEHAVIOURS = ("no-saturation", "no-stamps", "foreign-key", "trust-all", "ignore-stop", "free-status")
MAC_VERSION = 1          # the tag format this example implements; contract.json `signing.version` must say so


# --- signing (docs/contract.md, "Signing") ----------------------------------------------------
def read_bus_key(path: Path, timeout_s: float) -> bytes:
    """The run's data key: 64 hex digits in the run directory's bus.key (mode 0600)."""
    deadline = time.monotonic() + timeout_s
    while not path.is_file():
        if time.monotonic() > deadline:
            raise SystemExit(f"no bus key {path} after {timeout_s} s")
        time.sleep(0.05)
    time.sleep(0.05)
    return bytes.fromhex(path.read_text().strip())


def mac_attachment(key: bytes, key_expr: str, payload: bytes, counter: int) -> bytes:
    head = bytes((MAC_VERSION, len(NAME))) + NAME.encode() + counter.to_bytes(8, "big")
    return head + hmac.new(key, key_expr.encode() + b"\x00" + head + payload, hashlib.sha256).digest()


def mac_sender_counter(key: bytes, key_expr: str, payload: bytes, attachment: bytes | None):
    """(sender, counter) of a sample with a valid MAC; None otherwise."""
    if not attachment or len(attachment) < 2 or attachment[0] != MAC_VERSION:
        return None
    head_len = 2 + attachment[1] + 8
    if len(attachment) != head_len + 32:
        return None
    head = attachment[:head_len]
    expected = hmac.new(key, key_expr.encode() + b"\x00" + head + payload, hashlib.sha256).digest()
    if not hmac.compare_digest(expected, attachment[head_len:]):
        return None
    return head[2:head_len - 8], int.from_bytes(head[head_len - 8:], "big")


def presence_answer(key: bytes, key_expr: str, nonce: str, ready: bool) -> tuple[bytes, bytes]:
    """Payload and attachment of this node's answer to a presence query (docs/contract.md, "Presence")."""
    payload = json.dumps({"process": NAME, "host": "outside", "ready": ready,
                          "monotonic_ns": time.monotonic_ns(), "nonce": nonce}).encode()
    return payload, mac_attachment(key, key_expr, payload, time.time_ns())


# --- the law ----------------------------------------------------------------------------------
def lqr_gain(scenario: dict, scaling) -> np.ndarray:
    """K (3x6, scaled units) of the infinite-horizon discrete LQR on the believed CWH model."""
    plant, onboard, controller = scenario["plant"], scenario.get("onboard", {}), scenario["controller"]
    if controller.get("type", "lqr") != "lqr":
        raise SystemExit(f"this example flies [controller] type = 'lqr' only, not {controller['type']!r}")
    radius_m = plant["target_radius_m"] * (1.0 + onboard.get("believed_radius_error", 0.0))
    n = float(np.sqrt(plant["gravitational_parameter_m3ps2"] / radius_m**3))
    a_c = np.zeros((6, 6))
    a_c[0:3, 3:6] = np.eye(3)
    a_c[3, 0], a_c[3, 4], a_c[4, 3], a_c[5, 2] = 3.0 * n**2, 2.0 * n, -2.0 * n, -(n**2)
    b_c = np.zeros((6, 3))
    b_c[3:6, :] = np.eye(3) / plant["mass_kg"]
    block = np.zeros((9, 9))                      # exact zero-order hold: expm([[A, B], [0, 0]] dt)
    block[:6, :6], block[:6, 6:] = a_c, b_c
    phi = expm(block * plant["time_step_s"])
    v = np.diag(np.asarray(scaling, dtype=float))
    a = v @ phi[:6, :6] @ np.diag(1.0 / np.asarray(scaling, dtype=float))
    b = v @ phi[:6, 6:]
    q = np.diag(np.asarray(controller["q_diag"], dtype=float))
    r = np.diag(np.asarray(controller["r_diag"], dtype=float))
    p = solve_discrete_are(a, b, q, r)
    return -np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a)


# --- Zenoh ------------------------------------------------------------------------------------
def session_settings(contract: dict, connect: str) -> dict:
    """The contract's Zenoh settings (key -> JSON value), with the hub we were told to connect to."""
    return {**contract["zenoh"]["settings"], "connect/endpoints": [connect]}


def session_config(contract: dict, connect: str) -> zenoh.Config:
    """Built explicitly from the contract's settings (peer, no multicast scouting, gossip on, listen on
    loopback, the hub as the only connect endpoint, the run's lease); never Zenoh's defaults."""
    config = zenoh.Config()
    for key, value in session_settings(contract, connect).items():
        config.insert_json5(key, json.dumps(value))
    return config


def contract_numbers(contract: dict) -> tuple[int, np.ndarray, float]:
    """(schema version, seed 003's state scaling V, the thrusters' limit per axis in N) from contract.json;
    refuses a contract whose tag format is not the one implemented here."""
    if contract["signing"]["version"] != MAC_VERSION:
        raise SystemExit(f"contract.json: tag version {contract['signing']['version']}, "
                         f"this example speaks {MAC_VERSION}")
    return (int(contract["schema_version"]), np.asarray(contract["rendezvous_model"]["state_scaling"], dtype=float),
            float(contract["envelopes"]["thrust"]["max_abs_n"]))


def wait_for_file(path: Path, timeout_s: float) -> dict:
    deadline = time.monotonic() + timeout_s
    while not path.is_file():
        if time.monotonic() > deadline:
            raise SystemExit(f"no file {path} after {timeout_s} s (is `bench run` started?)")
        time.sleep(0.05)
    time.sleep(0.05)    # the launcher writes it in one go; let the write finish
    return json.loads(path.read_text())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--connect", required=True, help="the launcher's hub endpoint, e.g. tcp/127.0.0.1:7447")
    parser.add_argument("--run-id", required=True)
    parser.add_argument("--scenario", required=True, type=Path, help="the run directory's scenario.json")
    parser.add_argument("--bus-key", type=Path, help="the run's data key (default: bus.key beside --scenario)")
    parser.add_argument("--contract", type=Path, help="the run's contract.json (default: beside --scenario)")
    parser.add_argument("--wait-s", type=float, default=60.0, help="how long to wait for the scenario and the hub")
    parser.add_argument("--break", dest="breaks", action="append", default=[], metavar="MODE:STEP",
                        help=f"break the contract at a step, MODE one of {', '.join(BREAKS)} (for the check's tests)")
    parser.add_argument("--misbehave", action="append", default=[], choices=MISBEHAVIOURS,
                        help="break the contract for the whole run (for the check's tests)")
    args = parser.parse_args(argv)
    misbehave = set(args.misbehave)
    breaks: dict[int, set[str]] = {}
    for item in args.breaks:
        mode, _, step = item.partition(":")
        if mode not in BREAKS or not step.isdigit():
            parser.error(f"--break {item!r}: expected MODE:STEP with MODE one of {', '.join(BREAKS)}")
        breaks.setdefault(int(step), set()).add(mode)

    scenario = wait_for_file(args.scenario, args.wait_s)
    contract = wait_for_file(args.contract or args.scenario.parent / "contract.json", args.wait_s)
    bus_key = read_bus_key(args.bus_key or args.scenario.parent / "bus.key", args.wait_s)
    schema_version, scaling, max_abs_thrust_n = contract_numbers(contract)
    gain = lqr_gain(scenario, scaling)
    prefix = f"bench/{args.run_id}/"

    deadline = time.monotonic() + args.wait_s
    while True:      # the hub may not listen yet
        try:
            session = zenoh.open(session_config(contract, args.connect))
            break
        except Exception as exc:   # noqa: BLE001 - zenoh raises its own error type
            if time.monotonic() > deadline:
                raise SystemExit(f"cannot open a Zenoh session to {args.connect}: {exc}")
            time.sleep(0.2)

    estimates: queue.Queue = queue.Queue()
    launcher_gone = threading.Event()
    try:
        ready = threading.Event()
        presence_key = prefix + f"presence/{NAME}"

        def on_presence(query) -> None:
            nonce = query.payload.to_bytes().decode("ascii", "replace") if query.payload is not None else ""
            payload, attachment = presence_answer(bus_key, presence_key, nonce, ready.is_set())
            query.reply(presence_key, payload, attachment=attachment)

        keep = [session.declare_queryable(presence_key, on_presence)]
        last_counter: dict[bytes, int] = {}

        def on_estimate(sample) -> None:
            payload = sample.payload.to_bytes()
            attachment = None if sample.attachment is None else sample.attachment.to_bytes()
            opened = mac_sender_counter(bus_key, str(sample.key_expr), payload, attachment)
            if "trust-all" in misbehave:
                estimates.put(payload)
                return
            if opened is None or opened[1] <= last_counter.get(opened[0], -1):
                print(f"dropped an estimate without a valid, fresh MAC: {payload[:80]!r}", file=sys.stderr)
                return
            last_counter[opened[0]] = opened[1]
            estimates.put(payload)

        keep.append(session.declare_subscriber(prefix + "estimate/translation", on_estimate))
        keep.append(session.liveliness().declare_subscriber(
            prefix + "alive/launcher",
            lambda sample: launcher_gone.set() if sample.kind == zenoh.SampleKind.DELETE else None))

        def publisher(topic: str):
            return session.declare_publisher(prefix + topic, congestion_control=zenoh.CongestionControl.BLOCK,
                                             reliability=zenoh.Reliability.RELIABLE)

        commands = publisher("command/thrust")
        foreign = publisher("command/applied")            # used by --misbehave foreign-key only
        wrong = publisher("command/thrust_cmd")          # used by --break wrong-key only
        while not commands.matching_status.matching:     # the plant's subscriber
            if time.monotonic() > deadline or launcher_gone.is_set():
                raise SystemExit("no subscriber for command/thrust: is the plant running?")
            time.sleep(0.005)
        ready.set()

        counter = time.time_ns()     # goes up by one per message, and on from a restart
        while not launcher_gone.is_set() or "ignore-stop" in misbehave:
            try:
                payload = estimates.get(timeout=0.2)
            except queue.Empty:
                continue
            received_ns = time.monotonic_ns()
            estimate = json.loads(payload)
            header = estimate.get("header", {})
            if estimate.get("type") != "estimate_translation" or header.get("run_id") != args.run_id:
                print(f"ignored a message that is not this run's estimate: {payload[:80]!r}", file=sys.stderr)
                continue
            start = time.perf_counter()
            thrust_n = gain @ (scaling * np.asarray(estimate["state_m_mps"], dtype=float))
            if "no-saturation" in misbehave:
                thrust_n = 2.0 * thrust_n     # a hotter law, and no limit: over the limit in the first steps
            else:
                thrust_n = np.clip(thrust_n, -max_abs_thrust_n, max_abs_thrust_n)
            solve_time_s = time.perf_counter() - start
            stamps = dict(header.get("stamps_ns", {}), controller_received=received_ns)
            seq = header["seq"]
            broken = breaks.get(seq, set())
            command = {
                "type": "thrust",
                "header": {"schema_version": schema_version, "run_id": args.run_id,
                           "seq": seq + 1 if "skip-seq" in broken else seq,
                           "sim_time_s": header["sim_time_s"], "stamps_ns": stamps},
                "thrust_n": [float(u) for u in thrust_n],
                "ctrl_feasible": True, "status": "ok" if "free-status" in misbehave else "solved", "solve_time_s": solve_time_s, "iterations": 0,
            }
            if "bad-field" in broken:
                command["thrust_vec"] = command["thrust_n"]
            stamps["commanded"] = time.monotonic_ns()
            if "no-stamps" in misbehave:
                stamps.pop("commanded"), stamps.pop("controller_received")
            publisher_used = wrong if "wrong-key" in broken else commands
            payload = json.dumps(command).encode()
            counter += 1
            attachment = mac_attachment(bus_key, str(publisher_used.key_expr), payload, counter)
            if "bad-mac" in broken:
                attachment = attachment[:-32] + bytes(32)
            publisher_used.put(payload, attachment=attachment)
            if "foreign-key" in misbehave:
                counter += 1
                foreign.put(payload, attachment=mac_attachment(bus_key, str(foreign.key_expr), payload, counter))
    finally:
        session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
