"""A controller written from the run's contract.json alone (and bus.key): no scenario.json, no docs
beyond the contract, nothing from `bench`, not the example. tests/test_contract_export.py runs it
through `bench contract check controller`: if the contract leaves out a number, a name or a format
an outsider needs, this controller cannot pass.

    python tests/contract_only_controller.py --run-dir runs/<run_id>
"""
from __future__ import annotations

import argparse
import hashlib
import hmac
import json
import queue
import secrets
import sys
import time
from pathlib import Path

import numpy as np
import zenoh
from scipy.linalg import expm, solve_discrete_are

NAME = "controller"


def wait_for(path: Path, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not path.is_file():
        if time.monotonic() > deadline:
            raise SystemExit(f"no {path}")
        time.sleep(0.05)
    time.sleep(0.05)


def lqr_gain(model: dict) -> tuple[np.ndarray, np.ndarray]:
    """(K, V): u = K V x, the LQR on the CWH model the flight side believes, in seed 003's scaling."""
    n = model["believed_mean_motion_radps"]
    a = np.zeros((6, 6))
    a[0:3, 3:6] = np.eye(3)
    a[3, 0], a[3, 4], a[4, 3], a[5, 2] = 3 * n * n, 2 * n, -2 * n, -n * n
    b = np.zeros((6, 3))
    b[3:, :] = np.eye(3) / model["mass_kg"]
    block = np.zeros((9, 9))
    block[:6, :6], block[:6, 6:] = a, b
    phi = expm(block * model["time_step_s"])
    v = np.asarray(model["state_scaling"], dtype=float)
    ad, bd = np.diag(v) @ phi[:6, :6] @ np.diag(1 / v), np.diag(v) @ phi[:6, 6:]
    q = np.diag(model["controller_weights"]["q_diag"])
    r = np.diag(model["controller_weights"]["r_diag"])
    p = solve_discrete_are(ad, bd, q, r)
    return -np.linalg.solve(r + bd.T @ p @ bd, bd.T @ p @ ad), v


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--run-dir", type=Path, required=True)
    run_dir = parser.parse_args().run_dir
    wait_for(run_dir / "bus.key")          # written after contract.json
    contract = json.loads((run_dir / "contract.json").read_text())
    key = bytes.fromhex((run_dir / "bus.key").read_text().strip())
    sig = contract["signing"]
    if sig["version"] != 1:
        raise SystemExit(f"tag version {sig['version']} not implemented")
    topics = contract["keys"]["topics"]
    estimates_key = next(t["key"] for t in topics if NAME in t["readers"] and "TranslationEstimate" in t["messages"])
    commands_key = next(t["key"] for t in topics if t["publishers"] == [NAME] and "ThrustCommand" in t["messages"])
    presence_key = contract["presence"]["answer_key"].replace("<your name>", NAME)
    launcher_key = presence_key.rpartition("/")[0] + "/launcher"
    gain, scaling = lqr_gain(contract["rendezvous_model"])
    u_max = contract["envelopes"]["thrust"]["max_abs_n"]
    counter = [time.time_ns()]

    def tag(key_expr: str, payload: bytes) -> bytes:
        counter[0] += 1
        head = bytes((sig["version"], len(NAME))) + NAME.encode() + counter[0].to_bytes(sig["counter_bytes"], "big")
        return head + hmac.new(key, key_expr.encode() + b"\x00" + head + payload, hashlib.sha256).digest()

    def opened(key_expr: str, payload: bytes, attachment: bytes | None):
        if not attachment or len(attachment) < 2 or attachment[0] != sig["version"]:
            return None
        head_len = 2 + attachment[1] + sig["counter_bytes"]
        if len(attachment) != head_len + sig["mac_bytes"]:
            return None
        head = attachment[:head_len]
        mac = hmac.new(key, key_expr.encode() + b"\x00" + head + payload, hashlib.sha256).digest()
        if not hmac.compare_digest(mac, attachment[head_len:]):
            return None
        return head[2:head_len - sig["counter_bytes"]].decode(), int.from_bytes(head[head_len - sig["counter_bytes"]:], "big")

    config = zenoh.Config()
    for setting, value in contract["zenoh"]["settings"].items():
        config.insert_json5(setting, json.dumps(value))
    session = zenoh.open(config)
    ready = [False]

    def on_query(query) -> None:
        nonce = query.payload.to_bytes().decode("ascii", "replace") if query.payload is not None else ""
        if len(nonce) != 32:
            return
        body = json.dumps({"process": NAME, "host": "outside", "ready": ready[0],
                           "monotonic_ns": time.monotonic_ns(), "nonce": nonce}).encode()
        query.reply(presence_key, body, attachment=tag(presence_key, body))

    def launcher_answers() -> bool:
        nonce = secrets.token_hex(16)
        for reply in session.get(launcher_key, payload=nonce.encode(), timeout=0.5):
            sample = reply.ok
            if sample is None:
                continue
            who = opened(str(sample.key_expr), sample.payload.to_bytes(),
                         None if sample.attachment is None else sample.attachment.to_bytes())
            if who is not None and who[0] == "launcher" and json.loads(sample.payload.to_bytes())["nonce"] == nonce:
                return True
        return False

    inbox: queue.Queue = queue.Queue()
    last: dict[str, int] = {}

    def on_estimate(sample) -> None:
        payload = sample.payload.to_bytes()
        who = opened(str(sample.key_expr), payload, None if sample.attachment is None else sample.attachment.to_bytes())
        if who is None or who[1] <= last.get(who[0], -1):
            return
        last[who[0]] = who[1]
        inbox.put(payload)

    keep = [session.declare_queryable(presence_key, on_query), session.declare_subscriber(estimates_key, on_estimate)]
    publisher = session.declare_publisher(commands_key, congestion_control=zenoh.CongestionControl.BLOCK,
                                          reliability=zenoh.Reliability.RELIABLE)
    while not publisher.matching_status.matching:
        time.sleep(0.005)
    ready[0] = True
    silent_since = None
    while True:
        try:
            payload = inbox.get(timeout=0.25)
        except queue.Empty:
            silent_since = None if launcher_answers() else (silent_since or time.monotonic())
            if silent_since is not None and time.monotonic() - silent_since > 1.0:
                break
            continue
        received_ns = time.monotonic_ns()
        estimate = json.loads(payload)
        hdr = estimate["header"]
        valid = estimate.get("valid", True)
        thrust = np.clip(gain @ (scaling * np.asarray(estimate["state_m_mps"])), -u_max, u_max) if valid else np.zeros(3)
        stamps = dict(hdr["stamps_ns"], controller_received=received_ns, commanded=time.monotonic_ns())
        command = {"type": "thrust",
                   "header": {"schema_version": contract["schema_version"], "run_id": hdr["run_id"], "seq": hdr["seq"],
                              "sim_time_s": hdr["sim_time_s"], "stamps_ns": stamps},
                   "thrust_n": [float(u) for u in thrust], "ctrl_feasible": True,
                   "status": "solved" if valid else "waiting_for_estimate", "solve_time_s": 0.0, "iterations": 0}
        body = json.dumps(command).encode()
        publisher.put(body, attachment=tag(commands_key, body))
    del keep
    session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
