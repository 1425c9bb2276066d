"""A second process on a CAN channel, for the cross-process transport tests (host and UML guest).

    python tests/can_peer.py MODE COUNT --interface zenoh --channel vcan0 --run-id R --connect EP
    python tests/can_peer.py MODE COUNT --interface socketcan --channel vcan0

MODE echo: send back each frame received, arbitration id + 1. MODE burst: send COUNT frames
numbered 0..COUNT-1 (4 data bytes, little-endian), then wait for one frame meaning "done".
Prints "ready" once on the bus; exits 1 if a peer or a frame does not come within WAIT_S.
"""
from __future__ import annotations

import argparse
import sys

import can

WAIT_S = 10.0
BURST_ID = 0x123


def open_bus(args: argparse.Namespace) -> can.BusABC:
    if args.interface == "zenoh":
        bus = can.Bus(interface="zenoh", channel=args.channel, run_id=args.run_id, connect=[args.connect],
                      ignore_config=True)
        if not bus.wait_for_peers(1, WAIT_S):
            bus.shutdown()
            raise SystemExit("no peer on the zenoh channel")
        return bus
    return can.Bus(interface=args.interface, channel=args.channel, ignore_config=True)


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("mode", choices=("echo", "burst"))
    parser.add_argument("count", type=int)
    parser.add_argument("--interface", default="zenoh")
    parser.add_argument("--channel", default="vcan0")
    parser.add_argument("--run-id")
    parser.add_argument("--connect")
    args = parser.parse_args()
    with open_bus(args) as bus:
        print("ready", flush=True)
        if args.mode == "echo":
            for i in range(args.count):
                msg = bus.recv(WAIT_S)
                if msg is None:
                    print(f"timeout after {i} frames", flush=True)
                    return 1
                msg.arbitration_id += 1
                bus.send(msg)
        else:
            for i in range(args.count):
                bus.send(can.Message(arbitration_id=BURST_ID, is_extended_id=False, data=i.to_bytes(4, "little")))
            # Stay until the reader has everything: closing a zenoh session drops frames in flight.
            if bus.recv(WAIT_S) is None:
                print("no done frame", flush=True)
                return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
