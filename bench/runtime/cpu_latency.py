"""A PM QoS request that keeps the CPUs out of deep idle while a real-time loop runs.

A flight thread that sleeps until the solver worker answers, and a worker that sleeps until the
next request, each pay the CPU's wake-up from idle on every cycle. On this VM the idle driver is
`haltpoll`: a halted vCPU takes ~70 us to wake, more than the whole solve of a small MPC. Linux
lets a process cap that exit latency for as long as it holds /dev/cpu_dma_latency open with the
cap written to it (Documentation/power/pm_qos_interface.rst); cyclictest does the same by
default. Needs root (the device is 0600); refused, the run goes on and says so.
"""
from __future__ import annotations

import os
import struct

PM_QOS_DEVICE = "/dev/cpu_dma_latency"


class CpuWakeupLatencyRequest:
    """Holds a cap on the CPUs' idle exit latency, in microseconds, until close()."""

    def __init__(self, max_latency_us: int, device: str = PM_QOS_DEVICE):
        if max_latency_us < 0:
            raise ValueError(f"max_latency_us must be >= 0, got {max_latency_us}")
        self.max_latency_us = int(max_latency_us)
        self.refused: str | None = None
        self._fd: int | None = None
        try:
            self._fd = os.open(device, os.O_WRONLY)
            os.write(self._fd, struct.pack("i", self.max_latency_us))
        except OSError as exc:          # no such device, not root: the loop runs without it
            self.refused = f"{device}: {exc.strerror or exc}"
            self.close()

    @property
    def held(self) -> bool:
        return self._fd is not None

    def close(self) -> None:
        """Release the request (the kernel drops it when the file is closed, also at exit)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> "CpuWakeupLatencyRequest":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
