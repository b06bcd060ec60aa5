"""agilegs.schemas: the wire contract (pydantic models and Zenoh key expressions)."""
