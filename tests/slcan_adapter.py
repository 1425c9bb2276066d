"""An SLCAN (Lawicel serial-line CAN) adapter emulated on a pseudo-terminal, for the hardware-path test.

What a USB-CAN adapter does on its serial side, written here from the protocol (not from python-can's
host-side slcan.py, which is what it is tested against): ASCII lines ending in CR; commands
`O` open, `L` open listen-only, `C` close, `Sn` bitrate, `Yn` FD data bitrate, `V`/`N` version and
serial number, each answered by CR; frames `tIIILDD..` (standard), `TIIIIIIIILDD..` (extended), `r`/`R`
remote, and the CAN FD forms of the CANable 2.0 firmware `d`/`D` (no bit-rate switch) and `b`/`B`
(with), whose length digit is the FD DLC code (hex, 9-F for 12..64 bytes). A transmitted frame is
answered `z` (standard) or `Z` (extended) and CR; an unknown command by BEL.

The adapter's other side is a python-can bus (here the bench's Zenoh CAN channel): frames from the
tty go onto it while the channel is open, and frames from it go to the tty as received lines.
"""
from __future__ import annotations

import os
import select
import threading

import can

FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
CR, BEL = b"\r", b"\a"


def parse_frame(line: str) -> can.Message:
    """One SLCAN frame line (without its CR) as a python-can Message; ValueError if malformed."""
    kind = line[0]
    extended = kind in "TRDB"
    id_digits = 8 if extended else 3
    arbitration_id = int(line[1:1 + id_digits], 16)
    code = int(line[1 + id_digits], 16)
    is_fd = kind in "dDbB"
    if is_fd:
        length = FD_LENGTHS[code]
    elif code > 8:
        raise ValueError(f"classic CAN length {code} > 8")
    else:
        length = code
    payload = line[2 + id_digits:]
    if kind in "rR":
        return can.Message(arbitration_id=arbitration_id, is_extended_id=extended, is_remote_frame=True, dlc=length)
    if len(payload) != 2 * length:
        raise ValueError(f"{len(payload) // 2} data bytes for length {length}")
    return can.Message(arbitration_id=arbitration_id, is_extended_id=extended, data=bytes.fromhex(payload),
                       is_fd=is_fd, bitrate_switch=kind in "bB")


def format_frame(msg: can.Message) -> bytes:
    """A received frame as the adapter writes it to the tty (with its CR)."""
    ident = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
    if msg.is_remote_frame:
        return f"{'R' if msg.is_extended_id else 'r'}{ident}{msg.dlc}".encode() + CR
    data = bytes(msg.data)
    if msg.is_fd:
        code = FD_LENGTHS.index(len(data))      # the bench's FD frames have exact FD lengths
        kind = ("B" if msg.is_extended_id else "b") if msg.bitrate_switch else ("D" if msg.is_extended_id else "d")
        return f"{kind}{ident}{code:X}{data.hex().upper()}".encode() + CR
    return f"{'T' if msg.is_extended_id else 't'}{ident}{len(data)}{data.hex().upper()}".encode() + CR


class SlcanAdapter:
    """The adapter on the master side of a pty; `bus` is attached later (`attach`), when the bench's
    bus exists. Counts what it carried each way and what it could not parse."""

    def __init__(self, master_fd: int):
        self.fd = master_fd
        self.bus: can.BusABC | None = None
        self.is_open = False
        self.commands: list[str] = []
        self.to_bus = 0
        self.to_tty = 0
        self.dropped_closed = 0       # frames from the tty while the channel was closed or unattached
        self.bad_lines: list[str] = []
        self._stop = threading.Event()
        self._write_lock = threading.Lock()
        self._threads = [threading.Thread(target=self._tty_loop, daemon=True, name="slcan-tty")]
        self._threads[0].start()

    def attach(self, bus: can.BusABC) -> None:
        self.bus = bus
        thread = threading.Thread(target=self._bus_loop, daemon=True, name="slcan-bus")
        self._threads.append(thread)
        thread.start()

    def _write(self, data: bytes) -> None:
        with self._write_lock:
            os.write(self.fd, data)

    def _tty_loop(self) -> None:
        buffer = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self.fd], [], [], 0.05)
            if not ready:
                continue
            try:
                chunk = os.read(self.fd, 4096)
            except OSError:          # EIO: no process has the slave open right now
                self._stop.wait(0.01)
                continue
            buffer += chunk
            *lines, buffer = buffer.split(CR)
            for raw in lines:
                self._handle(raw.decode("ascii", errors="replace"))

    def _handle(self, line: str) -> None:
        if not line:
            return
        kind = line[0]
        if kind in "tTrRdDbB":
            try:
                msg = parse_frame(line)
            except (ValueError, IndexError):
                self.bad_lines.append(line)
                self._write(BEL)
                return
            if self.is_open and self.bus is not None:
                self.bus.send(msg)
                self.to_bus += 1
            else:
                self.dropped_closed += 1
            self._write((b"Z" if msg.is_extended_id else b"z") + CR)
            return
        self.commands.append(line)
        if kind in "OL":
            self.is_open = True
        elif kind == "C":
            self.is_open = False
        elif kind == "V":
            self._write(b"V1013" + CR)
            return
        elif kind == "N":
            self._write(b"NA123" + CR)
            return
        elif kind not in "SYsF":
            self.bad_lines.append(line)
            self._write(BEL)
            return
        self._write(CR)

    def _bus_loop(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(0.05)
            if msg is not None and self.is_open:
                self._write(format_frame(msg))
                self.to_tty += 1

    def stop(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=2.0)
