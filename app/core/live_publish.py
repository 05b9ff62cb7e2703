"""What the stream routes call to reach live viewers: a preview, a state change.

The hub (`app.core.live.PreviewHub`) lives on ``app.state.previews``, the Redis relay (with a
Redis broker: `app.core.live_redis`) on ``app.state.preview_relay``; both functions may be
called from the request's thread pool or from the event loop.
"""

from __future__ import annotations

from starlette.applications import Starlette

from app.core.live import PreviewHub, StateChange
from app.core.live_redis import RedisRelay


def preview_hub(app: Starlette) -> PreviewHub:
    hub: PreviewHub = app.state.previews
    return hub


def publish_preview(app: Starlette, stream_id: str, frame_index: int, data: bytes) -> None:
    """Relays a checked ``preview.bin`` (app.core.live.check_preview) of frame-set
    ``frame_index`` to the stream's viewers: through Redis to every gateway's hub when the
    service runs on Redis, else to this gateway's."""
    relay: RedisRelay | None = getattr(app.state, "preview_relay", None)
    if relay is not None:
        relay.publish(stream_id, frame_index, data)  # every gateway's hub, this one's too
    else:
        preview_hub(app).publish(stream_id, frame_index, data)


def publish_state(app: Starlette, stream_id: str, state: str, *, capture_id: str | None = None,
                  error: str | None = None) -> None:
    """Tells the stream's viewers on this gateway at once that it stopped receiving (they
    also read the state from the job store every second, which reaches every gateway)."""
    preview_hub(app).change_state(stream_id, StateChange(state, capture_id, error))
