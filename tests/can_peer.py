"""A second process on a `zenoh` CAN channel, for the cross-process transport tests.

    python tests/can_peer.py echo   RUN_ID CHANNEL ENDPOINT COUNT   # send back each frame, id + 1
    python tests/can_peer.py burst  RUN_ID CHANNEL ENDPOINT COUNT   # send COUNT numbered frames

Connects to ENDPOINT, waits for one peer on the channel, prints "ready", does its job, exits 0;
exits 1 if the peer or a frame does not come within its time limit.
"""
from __future__ import annotations

import sys

import can

WAIT_S = 10.0


def main(mode: str, run_id: str, channel: str, endpoint: str, count_text: str) -> int:
    count = int(count_text)
    with can.Bus(interface="zenoh", channel=channel, run_id=run_id, connect=[endpoint],
                 ignore_config=True) as bus:
        if not bus.wait_for_peers(1, WAIT_S):
            print("no peer", flush=True)
            return 1
        print("ready", flush=True)
        for i in range(count):
            if mode == "echo":
                msg = bus.recv(WAIT_S)
                if msg is None:
                    print(f"timeout after {i} frames", flush=True)
                    return 1
                msg.arbitration_id += 1
                bus.send(msg)
            else:
                bus.send(can.Message(arbitration_id=0x123, is_extended_id=False,
                                     data=i.to_bytes(4, "little")))
        # Stay until the peer has read everything: leaving closes the session, and frames
        # still in flight would go with it.
        bus.recv(WAIT_S) if mode == "burst" else None
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
