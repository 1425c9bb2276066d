"""The board's CANopen object dictionary: mtq.eds (CiA 306) loaded by the `canopen` package.

The EDS describes the board as a standard CiA 301 node: identity, heartbeat, EMCY, the PDOs
that are mtq.dbc's frames, and the parameters a CANopen tool may read and write over SDO. This
module loads it for a node id and says which object is which board parameter; the board
(board.py) serves it, the driver (driver.py) builds its view of the remote node from it.
"""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import canopen
import msgspec

from bench.bus.can import protocol as p
from bench.bus.can.config import BoardConfig

EDS_PATH = Path(__file__).with_name("mtq.eds")

HEARTBEAT_TIME = 0x1017      # producer heartbeat time, ms (0: no heartbeat)
EMCY_INHIBIT_TIME = 0x1015   # least time between two EMCYs, 100 us
COB_ID_EMCY = 0x1014
COMMAND_TIMEOUT = 0x2100     # no valid command this long: safe state, ms
SDO_REQUEST_BASE = 0x600     # CiA 301 default SDO server: client->server 0x600 + node id

# Board parameters kept in BoardConfig (seconds) and in the object dictionary (integer units):
# field -> (index, units per second). The communication ones (0x1000-0x1FFF) are restored by an
# NMT reset communication, all of them by a reset node (CiA 301 7.2.8.3.1).
PARAMETERS = {
    "heartbeat_period_s": (HEARTBEAT_TIME, 1000),
    "emcy_inhibit_s": (EMCY_INHIBIT_TIME, 10_000),
    "command_timeout_s": (COMMAND_TIMEOUT, 1000),
}
COMMUNICATION_PARAMETERS = tuple(f for f, (index, _) in PARAMETERS.items() if index < 0x2000)

# The frames that are PDOs or CiA 301 services, by their COB-ID object in the dictionary.
PDO_COMMUNICATION = {p.CMD: 0x1400, p.CMD_AUTH: 0x1401, p.NMT_AUTH: 0x1402,
                     p.TLM_DIPOLE: 0x1800, p.TLM_COIL: 0x1801, p.TLM_SETPOINT: 0x1802}


@lru_cache(maxsize=8)
def object_dictionary(node_id: int) -> canopen.ObjectDictionary:
    """mtq.eds for this node id ($NODEID resolved). Shared and read-only: nodes keep written
    values in their own store, never in the dictionary."""
    return canopen.import_od(str(EDS_PATH), node_id)


def cob_ids(od: canopen.ObjectDictionary, node_id: int) -> dict[str, int]:
    """The identifier of each frame of the protocol that is a CANopen object in the dictionary."""
    ids = {name: od[index][1].default & 0x7FF for name, index in PDO_COMMUNICATION.items()}
    ids[p.EMCY] = od[COB_ID_EMCY].default & 0x7FF
    ids[p.HEARTBEAT] = 0x700 + node_id       # CiA 301: fixed, no object
    ids[p.NMT] = 0x000
    return ids


def check_cob_ids(od: canopen.ObjectDictionary, protocol: p.Protocol) -> None:
    """The EDS and the DBC (through the protocol) must give every frame the same identifier."""
    for name, cob_id in cob_ids(od, protocol.node_id).items():
        if cob_id != protocol.frame_ids[name]:
            raise ValueError(f"{EDS_PATH.name} gives {name} COB-ID {cob_id:#05x}, {p.DBC_PATH.name} "
                             f"{protocol.frame_ids[name]:#05x} (node id {protocol.node_id:#04x})")


def parameter_s(od: canopen.ObjectDictionary, field: str) -> float:
    """A board parameter's EDS default in seconds."""
    index, per_s = PARAMETERS[field]
    return od[index].default / per_s     # a division: 100 / 1000 is exactly the float 0.1


def board_config(config: BoardConfig, od: canopen.ObjectDictionary) -> BoardConfig:
    """The board's parameters: the EDS's defaults where the scenario left BoardConfig's default
    (the two are held equal by tests/test_canopen_eds.py), the scenario's value where it set one."""
    defaults = BoardConfig()
    from_eds = {field: parameter_s(od, field) for field in PARAMETERS
                if getattr(config, field) == getattr(defaults, field)}
    return msgspec.structs.replace(config, **from_eds)
