"""What the flight side detects on the magnetorquer bus, published as it detects it (issue 48):
each driver `FaultEvent` (and the FDIR actuator monitor's, frame "FDIR") becomes a `BusEvent` on
`event/can`, which the recorder writes to the MCAP and the live view shows as a log message. The
same events are written to can/driver.json at the end, as before.

Called on whichever thread detected the events (the driver's command loop in real time, the
controller's in lock-step); the publisher is declared once, under a lock."""
from __future__ import annotations

import threading

from bench.bus import keys
from bench.bus.schemas import BusEvent, header

_lock = threading.Lock()
FDIR_FRAME = "FDIR"


def publish_bus_events(ctx, events) -> None:
    """Publish `events` (driver FaultEvents) on event/can; never raises (the bus goes on if the
    session is closing)."""
    if not events:
        return
    try:
        with _lock:
            if keys.EVENT_CAN not in ctx._publishers:
                ctx.declare_publisher(keys.EVENT_CAN)
        for event in events:
            source = "FDIR" if event.frame == FDIR_FRAME else "driver"
            ctx.publish(keys.EVENT_CAN, BusEvent(header(ctx.run_id, 0, 0.0), source, event.kind, float(event.latency_s),
                                                 int(event.detected_ns), event.frame, event.detail[:400]))
    except Exception as exc:   # noqa: BLE001 - the session is closing: can/driver.json has them
        ctx.log.debug("bus events not published: %s", exc)
