"""Response classes that name their media type, so the OpenAPI schema documents routes that
answer images or streams with their real content type (not an untyped JSON body)."""

from __future__ import annotations

from fastapi.responses import Response, StreamingResponse


class PNGResponse(Response):
    media_type = "image/png"


class JPEGResponse(Response):
    media_type = "image/jpeg"


class MJPEGResponse(StreamingResponse):
    media_type = "multipart/x-mixed-replace"


class EventStreamResponse(StreamingResponse):
    media_type = "text/event-stream"
