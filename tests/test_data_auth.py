"""The data topics' MAC (bench/bus/data_auth.py): a tag checks out only under its key, on its key
expression, over its payload, whole; a subscription takes a sender's counter once, upwards; the
outside example signs and checks the same bytes with its own stdlib code."""
from __future__ import annotations

import hashlib
import hmac
import importlib.util
import os

import pytest

from bench.bus import data_auth
from bench.bus.data_auth import FORGED, REPLAYED, Signer, Verifier, open_tag, tag
from conftest import REPO

KEY = bytes(range(32))
KEY_EXPR = "bench/r1/command/thrust"
PAYLOAD = b'{"type":"thrust","header":{"seq":3}}'


def _example():
    spec = importlib.util.spec_from_file_location("outside_lqr_controller", REPO / "examples" / "outside_lqr_controller.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_tag_is_the_documented_hmac():
    # Independent reference: the layout written out by hand (docs/contract.md), stdlib hmac.
    counter = 1234567890123
    head = b"\x01" + bytes([len(b"controller")]) + b"controller" + counter.to_bytes(8, "big")
    expected = head + hmac.new(KEY, KEY_EXPR.encode() + b"\x00" + head + PAYLOAD, hashlib.sha256).digest()
    assert tag(KEY, KEY_EXPR, PAYLOAD, b"controller", counter) == expected
    assert open_tag(KEY, KEY_EXPR, PAYLOAD, expected) == (b"controller", counter)


def test_wrong_key_moved_topic_altered_payload_truncated_or_missing_mac_are_forged():
    attachment = tag(KEY, KEY_EXPR, PAYLOAD, b"controller", 7)
    assert open_tag(KEY, KEY_EXPR, PAYLOAD, attachment) is not None
    other_key = bytes(32)
    cases = {
        "wrong key": (other_key, KEY_EXPR, PAYLOAD, attachment),
        "moved topic": (KEY, "bench/r1/command/dipole", PAYLOAD, attachment),
        "other run": (KEY, "bench/r2/command/thrust", PAYLOAD, attachment),
        "altered payload": (KEY, KEY_EXPR, PAYLOAD.replace(b"3", b"4"), attachment),
        "truncated MAC": (KEY, KEY_EXPR, PAYLOAD, attachment[:-1]),
        "half MAC": (KEY, KEY_EXPR, PAYLOAD, attachment[:-16]),
        "extra byte": (KEY, KEY_EXPR, PAYLOAD, attachment + b"\x00"),
        "zero MAC": (KEY, KEY_EXPR, PAYLOAD, attachment[:-32] + bytes(32)),
        "other counter": (KEY, KEY_EXPR, PAYLOAD, attachment[:-33] + b"\x08" + attachment[-32:]),
        "other sender": (KEY, KEY_EXPR, PAYLOAD, attachment.replace(b"controller", b"controlleR")),
        "other version": (KEY, KEY_EXPR, PAYLOAD, b"\x02" + attachment[1:]),
        "no attachment": (KEY, KEY_EXPR, PAYLOAD, None),
        "empty attachment": (KEY, KEY_EXPR, PAYLOAD, b""),
        "one byte": (KEY, KEY_EXPR, PAYLOAD, b"\x01"),
    }
    for name, args in cases.items():
        assert open_tag(*args) is None, name
        assert Verifier(args[0]).check(*args[1:]) == FORGED, name


def test_a_subscription_takes_each_senders_counter_once_and_upwards():
    plant, controller = Signer(KEY, "plant"), Signer(KEY, "controller")
    verifier = Verifier(KEY)
    first = plant(KEY_EXPR, PAYLOAD)
    second = plant(KEY_EXPR, PAYLOAD)
    other = controller(KEY_EXPR, PAYLOAD)       # another sender on the same key: its own counter
    assert verifier.check(KEY_EXPR, PAYLOAD, first) is None
    assert verifier.check(KEY_EXPR, PAYLOAD, other) is None
    assert verifier.check(KEY_EXPR, PAYLOAD, first) == REPLAYED      # the captured message again
    assert verifier.check(KEY_EXPR, PAYLOAD, second) is None
    assert verifier.check(KEY_EXPR, PAYLOAD, first) == REPLAYED      # older than the last taken
    assert verifier.check(KEY_EXPR, PAYLOAD, second) == REPLAYED
    # Another subscription (its own guard) takes the same message once.
    assert Verifier(KEY).check(KEY_EXPR, PAYLOAD, second) is None


def test_the_outside_example_signs_and_checks_the_same_bytes():
    example = _example()
    attachment = example.mac_attachment(KEY, KEY_EXPR, PAYLOAD, 99)
    assert attachment == tag(KEY, KEY_EXPR, PAYLOAD, b"controller", 99)
    genuine = tag(KEY, KEY_EXPR, PAYLOAD, b"estimator", 5)
    assert example.mac_sender_counter(KEY, KEY_EXPR, PAYLOAD, genuine) == (b"estimator", 5)
    assert example.mac_sender_counter(KEY, KEY_EXPR, PAYLOAD, genuine[:-1]) is None
    assert example.mac_sender_counter(bytes(32), KEY_EXPR, PAYLOAD, genuine) is None


def test_key_files(tmp_path):
    from bench.bus.can.run_key import write_private
    assert data_auth.node_key(tmp_path) is None
    path = tmp_path / data_auth.KEY_FILE
    write_private(path, (KEY.hex() + "\n").encode())
    assert data_auth.node_key(tmp_path) == KEY
    os.chmod(path, 0o644)
    with pytest.raises(data_auth.KeyFileError, match="readable by others"):
        data_auth.node_key(tmp_path)
    write_private(path, b"abcd\n")
    with pytest.raises(data_auth.KeyFileError, match="64 hexadecimal digits"):
        data_auth.node_key(tmp_path)
    # A deployment's key: derived from its secoc.key, the same on every host, not the SecOC key itself.
    from bench.bus.certs import write_secoc_key
    cert_dir = tmp_path / "certs"
    write_secoc_key(cert_dir)
    derived = data_auth.node_key(tmp_path, cert_dir)
    secoc_hex = (cert_dir / "secoc.key").read_text().strip()
    assert derived == hmac.new(bytes.fromhex(secoc_hex), data_auth.DEPLOYMENT_LABEL, hashlib.sha256).digest()
    assert derived != KEY and len(derived) == data_auth.KEY_BYTES
    # A secure node (certificates) with no key at all is refused, naming both places.
    empty_certs, empty_run = tmp_path / "other-certs", tmp_path / "other-run"
    empty_certs.mkdir()
    empty_run.mkdir()
    with pytest.raises(data_auth.KeyFileError, match="secoc.key.*bus.key"):
        data_auth.node_key(empty_run, empty_certs)


def test_unauthentic_samples_are_left_out_of_the_report_and_named_by_the_contract_check(tmp_path):
    from bench.bus.schemas import ThrustCommand, encode, header
    from bench.contract_check.check import read_samples
    from bench.recorder import RECORDING_FILE, Recording
    from bench.report.rundata import read_recording

    genuine = encode(ThrustCommand(header("r1", 0, 0.0), [0.1, 0.0, 0.0], True, "solved", 0.0))
    forged = encode(ThrustCommand(header("r1", 0, 0.0), [0.9, -0.9, 0.9], True, "rogue", 0.0))
    recording = Recording(tmp_path / RECORDING_FILE, "r1")
    recording.write("command/thrust", genuine, 1)
    recording.write("command/thrust", forged, 2, FORGED)
    recording.write("command/thrust", genuine, 3, REPLAYED)
    recording.close()
    unauthentic: dict[str, int] = {}
    samples = read_samples(tmp_path / RECORDING_FILE, unauthentic)
    assert unauthentic == {"command/thrust": 2}
    assert [(s.topic, s.payload) for s in samples] == [("command/thrust", genuine)]
    messages, malformed, truncated = read_recording(tmp_path / RECORDING_FILE)
    assert [m.body["thrust_n"] for m in messages] == [[0.1, 0.0, 0.0]] and malformed == 0 and not truncated
