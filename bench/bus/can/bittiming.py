"""How long a classical CAN frame occupies the bus, bit for bit (ISO 11898-1).

vcan and the Zenoh transport deliver frames instantly; a real bus does not. The time a frame
takes depends on its identifier and data through bit stuffing: after five equal bits the
transmitter inserts one of the opposite value, from the start-of-frame bit to the end of the
CRC. The stuffed count is therefore computed on the frame's actual bits, including its CRC-15.
"""
from __future__ import annotations

import re
from functools import lru_cache

import can

CRC15_POLY = 0x4599
# Unstuffed tail: CRC delimiter, ACK slot, ACK delimiter, 7 end-of-frame bits, 3 intermission.
TAIL_BITS = 1 + 1 + 1 + 7 + 3
# An error frame: 6-bit error flag (others may echo it, up to 6 more), 8-bit delimiter,
# intermission. The frame it destroys is assumed to have run up to its CRC.
ERROR_FRAME_BITS = 6 + 6 + 8 + 3
BUS_OFF_RECOVERY_BITS = 128 * 11
DEFAULT_BITRATE_BPS = 1_000_000


def crc15(bits: list[int]) -> int:
    crc = 0
    for bit in bits:
        feedback = bit ^ ((crc >> 14) & 1)
        crc = (crc << 1) & 0x7FFF
        if feedback:
            crc ^= CRC15_POLY
    return crc


def _field(value: int, width: int) -> list[int]:
    return [(value >> (width - 1 - i)) & 1 for i in range(width)]


def frame_bits_unstuffed(arbitration_id: int, data: bytes, *, extended: bool = False, remote: bool = False) -> list[int]:
    """The bits from start of frame to the end of the CRC, before stuffing (dominant = 0)."""
    dlc = len(data)
    if extended:
        head = [0] + _field(arbitration_id >> 18, 11) + [1, 1] + _field(arbitration_id & 0x3FFFF, 18) \
            + [int(remote), 0, 0]
    else:
        head = [0] + _field(arbitration_id, 11) + [int(remote), 0, 0]
    body = head + _field(dlc, 4)
    if not remote:
        for byte in data:
            body += _field(byte, 8)
    return body + _field(crc15(body), 15)


def stuff(bits: list[int]) -> list[int]:
    """Insert a complementary bit after every run of five equal bits."""
    out: list[int] = []
    run_value, run_length = None, 0
    for bit in bits:
        out.append(bit)
        if bit == run_value:
            run_length += 1
        else:
            run_value, run_length = bit, 1
        if run_length == 5:
            out.append(1 - bit)
            run_value, run_length = 1 - bit, 1
    return out


# --- the same counts, fast: every frame on a simulated bus is timed (sim_window.py) -------------
_RUNS = re.compile(r"0+|1+")


def _crc15_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte << 7
        for _ in range(8):
            crc = ((crc << 1) ^ CRC15_POLY) if crc & 0x4000 else (crc << 1)
            crc &= 0x7FFF
        table.append(crc)
    return table


_CRC15_TABLE = _crc15_table()


def crc15_of_bit_string(bits: str) -> int:
    """crc15 of a '0'/'1' string, a byte at a time (leading zeros do not change a zero-initialised
    CRC, so the string is padded at the front to whole bytes)."""
    padded = bits.zfill(-(-len(bits) // 8) * 8)
    crc = 0
    for byte in int(padded, 2).to_bytes(len(padded) // 8, "big"):
        crc = ((crc << 8) & 0x7FFF) ^ _CRC15_TABLE[((crc >> 7) ^ byte) & 0xFF]
    return crc


def stuffed_length(bits: str) -> int:
    """len(stuff(bits)) of a '0'/'1' string, from its runs of equal bits. A run of n equal bits
    (counting a stuff bit of its value just before it) gets n // 5 stuff bits; when the last one
    falls on the run's last bit, that stuff bit has the next run's value and counts for it."""
    inserted, carry = 0, 0
    for run in _RUNS.finditer(bits):
        n = run.end() - run.start() + carry
        inserted += n // 5
        carry = 1 if n >= 5 and n % 5 == 0 else 0
    return len(bits) + inserted


def _head_string(arbitration_id: int, extended: bool, remote: bool, fd: bool) -> str:
    if extended:
        return f"0{arbitration_id >> 18:011b}11{arbitration_id & 0x3FFFF:018b}" + ("0" if fd else f"{int(remote)}00")
    return f"0{arbitration_id:011b}" + ("00" if fd else f"{int(remote)}00")


def _data_string(data: bytes) -> str:
    return f"{int.from_bytes(data, 'big'):0{8 * len(data)}b}" if data else ""


@lru_cache(maxsize=4096)
def _frame_bits(arbitration_id: int, data: bytes, extended: bool, remote: bool) -> int:
    body = _head_string(arbitration_id, extended, remote, fd=False) + f"{len(data):04b}"
    if not remote:
        body += _data_string(data)
    return stuffed_length(body + f"{crc15_of_bit_string(body):015b}") + TAIL_BITS


def arbitration_bits(arbitration_id: int, *, extended: bool = False, remote: bool = False) -> tuple[int, ...]:
    """The bits a transmitter sends in the arbitration field (dominant = 0, so the lowest
    sequence wins), with the IDE bit that settles standard against extended:
    standard: ID10..ID0, RTR, IDE(0); extended: ID28..ID18, SRR(1), IDE(1), ID17..ID0, RTR.
    Hence a standard frame beats an extended one with the same base identifier, a data frame (RTR
    dominant) beats a remote frame with the same identifier, and a CAN FD frame (RRS dominant)
    competes like a classic data frame."""
    if extended:
        return tuple(_field(arbitration_id >> 18, 11) + [1, 1] + _field(arbitration_id & 0x3FFFF, 18) + [int(remote)])
    return tuple(_field(arbitration_id, 11) + [int(remote), 0])


def message_arbitration_bits(msg: can.Message) -> tuple[int, ...]:
    return arbitration_bits(msg.arbitration_id, extended=msg.is_extended_id, remote=msg.is_remote_frame)


def fd_bits_unstuffed(arbitration_id: int, data: bytes, extended: bool = False) -> list[int]:
    """A CAN FD frame's bits from start of frame to the end of the data field."""
    if extended:
        head = [0] + _field(arbitration_id >> 18, 11) + [1, 1] + _field(arbitration_id & 0x3FFFF, 18) + [0]
    else:
        head = [0] + _field(arbitration_id, 11) + [0, 0]          # RRS, IDE
    head += [1, 0, 0, 0] + _field(can.util.len2dlc(len(data)), 4)  # FDF, res, BRS, ESI, DLC
    for byte in data:
        head += _field(byte, 8)
    return head


def stuffed_bits(msg: can.Message) -> list[int]:
    """The frame's bits as they go on the wire from start of frame (dynamic stuffing applied)."""
    if msg.is_fd:
        return stuff(fd_bits_unstuffed(msg.arbitration_id, bytes(msg.data), msg.is_extended_id))
    data = bytes(msg.data) if not msg.is_remote_frame else bytes(msg.dlc)
    return stuff(frame_bits_unstuffed(msg.arbitration_id, data, extended=msg.is_extended_id, remote=msg.is_remote_frame))


@lru_cache(maxsize=4096)
def _fd_frame_bits(arbitration_id: int, data: bytes, extended: bool) -> int:
    """A CAN FD frame without bit-rate switch (the whole frame at the nominal rate, as this model
    has one bitrate). Dynamic stuffing from SOF to the end of the data field; then the stuff count
    (3-bit Gray code and parity) and the CRC (17 bits up to 16 data bytes, 21 beyond) with fixed
    stuff bits, one before the stuff count and one after every 4 bits (ISO 11898-1:2015 10.5)."""
    head = (_head_string(arbitration_id, extended, False, fd=True) + f"1000{can.util.len2dlc(len(data)):04b}"
            + _data_string(data))
    crc_bits = 17 if len(data) <= 16 else 21
    checked = 4 + crc_bits
    fixed_stuff = 1 + checked // 4
    return stuffed_length(head) + checked + fixed_stuff + TAIL_BITS


def frame_bits(msg: can.Message) -> int:
    """Bits on the wire for this frame, stuff bits and intermission included."""
    if msg.is_fd:
        return _fd_frame_bits(msg.arbitration_id, bytes(msg.data), msg.is_extended_id)
    data = bytes(msg.data) if not msg.is_remote_frame else bytes(msg.dlc)
    return _frame_bits(msg.arbitration_id, data, msg.is_extended_id, msg.is_remote_frame)


def worst_case_bits(dlc: int, extended: bool = False) -> int:
    """Upper bound of the textbook formula (Davis et al. 2007): stuffable bits g + 8 dlc, at most
    one stuff bit per four after the first."""
    g = 54 if extended else 34
    return g + 8 * dlc + TAIL_BITS + (g + 8 * dlc - 1) // 4


def duration_ns(bits: int, bitrate_bps: int) -> int:
    return round(bits * 1e9 / bitrate_bps)
