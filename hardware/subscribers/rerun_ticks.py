"""The control loop's ticks in Rerun (:class:`dssp_data.rerun_views.TickViews`): depth, cloud, state, command, chunk,
holds, events and latencies, on the views' timeline."""

from __future__ import annotations

from dssp_data.rerun_views import TickViews
from hardware.subscribers import Subscriber, Tick


class RerunTicks(Subscriber):
    """Queues each tick's views (never blocking the loop); the caller closes ``views``. The timeline continues
    after the views' last tick, so that the episodes of an evaluation follow one another."""

    def __init__(self, views: TickViews):
        self.views = views
        self.next_tick = views.last_tick + 1

    def on_start(self, loop) -> None:
        frame = loop.camera.latest() if loop.camera is not None else None
        if frame is not None:  # a source that needs no point cloud may start before the camera's first frame
            self.views.camera(frame.intrinsics.to_dict(), loop.camera_to_base)

    def on_tick(self, tick: Tick) -> None:
        record, frame = tick.record, tick.frame
        events = [f"{e['kind']}: {e['detail']}" for e in record.get("safety", []) if e["kind"] != "clip"]
        events += record.get("events", [])
        self.views.tick(
            self.next_tick,
            depth=frame.depth if frame is not None else None,
            depth_unit=frame.depth_unit if frame is not None else None,
            cloud=tick.cloud,
            state=record["state"],
            command=record["command"],
            chunk=tick.chunk,
            held=record["held"],
            events=events,
            latency_ms={k: record.get(f"{k}_ms") for k in ("cloud", "observe", "chunk", "tick")},
        )
        self.next_tick += 1
