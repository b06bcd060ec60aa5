"""The HTTP transport: the FastAPI app (:mod:`.app`), one route per operation
(:mod:`.routes`), the decisions feed's long poll and event stream (:mod:`.decisions`), the
OpenAPI document (:mod:`.openapi`) and the connection edge on uvicorn (:mod:`.edge`)."""
