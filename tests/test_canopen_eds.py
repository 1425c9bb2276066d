"""mtq.eds against mtq.dbc and BoardConfig: two descriptions of one board must agree.

Independent of bench/bus/can/canopen_od.py: the PDO table below is written from CiA 301's
predefined connection set and the DBC's comments, and the DBC is read through cantools.
"""
import canopen
import cantools
import pytest

from bench.bus.can.config import BoardConfig
from bench.bus.can.protocol import DBC_PATH

EDS = DBC_PATH.with_name("mtq.eds")
NODE_ID = 0x10     # the DBC's identifiers are written for this node id
DUMMY_TYPES = {0x0001: 1, 0x0005: 8}   # CiA 301 dummy mapping: BOOLEAN, UNSIGNED8

# PDO communication parameter -> its mapping parameter and the DBC frame it is.
PDOS = {0x1400: (0x1600, "MTQ_CMD"), 0x1401: (0x1601, "MTQ_CMD_AUTH"), 0x1402: (0x1602, "MTQ_NMT_AUTH"),
        0x1800: (0x1A00, "MTQ_TLM_DIPOLE"), 0x1801: (0x1A01, "MTQ_TLM_COIL"), 0x1802: (0x1A02, "MTQ_TLM_SETPOINT")}


@pytest.fixture(scope="module")
def od():
    return canopen.import_od(str(EDS), NODE_ID)


@pytest.fixture(scope="module")
def dbc():
    return cantools.database.load_file(str(DBC_PATH))


def _mapped(od, mapping_index):
    """(object, bit length) of each mapping entry, in order."""
    record = od[mapping_index]
    entries = []
    for sub in range(1, record[0].default + 1):
        value = record[sub].default
        index, subindex, bits = value >> 16, (value >> 8) & 0xFF, value & 0xFF
        entries.append(((index, subindex), bits))
    return entries


@pytest.mark.parametrize("comm_index", sorted(PDOS))
def test_every_pdo_is_its_dbc_frame(od, dbc, comm_index):
    mapping_index, name = PDOS[comm_index]
    message = dbc.get_message_by_name(name)
    assert od[comm_index][1].default == message.frame_id, f"{name} COB-ID"
    # Walk the frame: each DBC signal (Intel order, start bit = first bit) is one mapped object
    # of its length; the bits between signals are dummy entries (together as long as the gap).
    expected, bit = [], 0
    for signal in sorted(message.signals, key=lambda s: s.start):
        assert signal.byte_order == "little_endian"
        if signal.start > bit:
            expected.append(("dummy", signal.start - bit))
        expected.append((signal.name.lower(), signal.length))
        bit = signal.start + signal.length
    got = []
    for (index, subindex), bits in _mapped(od, mapping_index):
        if index in DUMMY_TYPES:
            assert bits == DUMMY_TYPES[index]
            if got and got[-1][0] == "dummy":
                got[-1] = ("dummy", got[-1][1] + bits)
            else:
                got.append(("dummy", bits))
            continue
        entry = od[index] if subindex == 0 else od[index][subindex]
        assert entry.pdo_mappable, f"{name}: {entry.name} is mapped but not PDO-mappable"
        got.append((entry.name.split(".")[-1].split(" ")[-1].lower(), bits))
    # The DBC's signal name ends with the object's last word (Crc, AliveCounter, Mode, the axis
    # of "Dipole set-point X" for DipoleX...), lengths equal, in the same order.
    assert [bits for _, bits in got] == [bits for _, bits in expected], f"{name}: {got} vs {expected}"
    for (object_word, _), (signal_name, _) in zip(got, expected):
        assert signal_name.endswith(object_word), f"{name}: {object_word!r} mapped where the DBC has {signal_name!r}"
    assert sum(bits for _, bits in got) == 8 * message.length, f"{name}: mapped bits fill the frame"


def test_heartbeat_and_emcy(od, dbc):
    assert od[0x1014].default == dbc.get_message_by_name("MTQ_EMCY").frame_id
    assert 0x700 + NODE_ID == dbc.get_message_by_name("MTQ_HEARTBEAT").frame_id
    assert od[0x1017].default == dbc.get_message_by_name("MTQ_HEARTBEAT").cycle_time     # ms


def test_parameters_equal_board_defaults(od):
    board = BoardConfig()
    assert od[0x1017].default / 1000 == board.heartbeat_period_s
    assert od[0x2100].default / 1000 == board.command_timeout_s
    assert od[0x1015].default / 10_000 == board.emcy_inhibit_s


def test_eds_follows_the_node_id():
    moved = canopen.import_od(str(EDS), 0x22)
    assert moved[0x1400][1].default == 0x222 and moved[0x1800][1].default == 0x1A2
    assert moved[0x1014].default == 0xA2


def test_board_refuses_an_eds_that_disagrees_with_the_dbc(monkeypatch):
    from bench.bus.can import canopen_od
    from bench.bus.can import protocol as p
    protocol = p.Protocol()
    od = canopen_od.object_dictionary(NODE_ID)
    canopen_od.check_cob_ids(od, protocol)          # as shipped: agree
    monkeypatch.setitem(protocol.frame_ids, p.TLM_COIL, 0x291)
    with pytest.raises(ValueError, match="MTQ_TLM_COIL COB-ID 0x290"):
        canopen_od.check_cob_ids(od, protocol)
