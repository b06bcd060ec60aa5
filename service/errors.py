"""The error every part of the service raises for a request it refuses, and its helpers.

A :class:`ServiceError` carries what the wire's :class:`~agilegs.schemas.errors.ErrorBody`
says: the HTTP status, a stable :class:`~agilegs.schemas.errors.ErrorCode`, a message and the
path of the offending input (``body.poses[3].matrix``, ``path.session``, ``header.accept``).
The gateway turns it into the same body over HTTP and Zenoh.
"""

from __future__ import annotations

import errno
from collections.abc import Iterable

from pydantic import ValidationError

from agilegs.schemas import ErrorBody, ErrorInfo, ErrorItem
from agilegs.schemas.errors import ERROR_STATUS, ErrorCode

__all__ = [
    "ServiceError",
    "conflict",
    "field_path",
    "insufficient_storage",
    "invalid",
    "is_disk_full",
    "not_found",
    "too_large",
    "session_damaged",
    "too_many",
    "validation_error",
]


class ServiceError(Exception):
    """A request the service refuses: HTTP status, stable code, message, the field, and (405,
    406, 415) what the server supports instead."""

    def __init__(
        self,
        status: int,
        code: ErrorCode | str,
        message: str,
        field: str | None = None,
        errors: list[ErrorItem] | None = None,
        supported: list[str] | None = None,
        *,
        limit: str | None = None,
        retry_after: float | None = None,
        estimate: dict[str, float] | None = None,
    ) -> None:
        super().__init__(message)
        self.status = status
        self.code = ErrorCode(code)
        self.message = message
        self.field = field
        self.errors = errors if errors is not None else [ErrorItem(field=field, message=message)]
        self.supported = supported
        self.limit = limit
        self.retry_after = retry_after
        self.estimate = estimate

    @classmethod
    def of(cls, code: ErrorCode, message: str, field: str | None = None) -> ServiceError:
        """The error of ``code`` with its status."""
        return cls(ERROR_STATUS[code], code, message, field)

    def body(self) -> ErrorBody:
        return ErrorBody(
            error=ErrorInfo(
                status=self.status,
                code=self.code.value,
                message=self.message,
                field=self.field,
                errors=self.errors,
                supported=self.supported,
                limit=self.limit,
                retry_after=self.retry_after,
                estimate=self.estimate,
            )
        )

    def __repr__(self) -> str:
        return f"ServiceError({self.status}, {self.code!r}, {self.message!r}, field={self.field!r})"


def invalid(field: str | None, message: str) -> ServiceError:
    return ServiceError.of(ErrorCode.INVALID, message, field)


def not_found(field: str | None, message: str) -> ServiceError:
    return ServiceError.of(ErrorCode.NOT_FOUND, message, field)


def conflict(field: str | None, message: str, code: ErrorCode = ErrorCode.CONFLICT
             ) -> ServiceError:
    return ServiceError(409, code, message, field)


def too_large(field: str | None, message: str) -> ServiceError:
    return ServiceError.of(ErrorCode.LIMIT_EXCEEDED, message, field)


def too_many(field: str | None, message: str) -> ServiceError:
    return ServiceError.of(ErrorCode.TOO_MANY, message, field)


def session_damaged(field: str | None, message: str) -> ServiceError:
    return ServiceError.of(ErrorCode.SESSION_DAMAGED, message, field)


DISK_FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})
"""``errno`` values of a write refused for lack of space (the disk, or a quota)."""


def is_disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` (or what it was raised from) is a write refused for lack of space."""
    seen = 0
    cur: BaseException | None = exc
    while cur is not None and seen < 8:
        if isinstance(cur, OSError) and cur.errno in DISK_FULL_ERRNOS:
            return True
        cur = cur.__cause__ or cur.__context__
        seen += 1
    return False


def insufficient_storage(exc: BaseException | None = None) -> ServiceError:
    """507: the state folder is full; nothing was changed."""
    why = f" ({exc.strerror})" if isinstance(exc, OSError) and exc.strerror else ""
    return ServiceError.of(
        ErrorCode.INSUFFICIENT_STORAGE,
        f"the server's state folder is full{why}: the change was not made; reads keep "
        "working, and writes succeed again once space is freed")


def field_path(prefix: str, loc: Iterable[int | str]) -> str:
    """``body`` + ``('poses', 3, 'matrix')`` -> ``body.poses[3].matrix``."""
    out = prefix
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += f".{part}" if out else str(part)
    return out


def validation_error(exc: ValidationError, prefix: str = "body",
                     rename: dict[str, str] | None = None) -> ServiceError:
    """A pydantic ValidationError as a 422 naming every field (``prefix`` + its location).

    ``rename``: top-level location names mapped to another path (``{"shortlist_size":
    "body.shortlist_size"}``) for fields that the request carries elsewhere.
    """
    items = []
    for e in exc.errors(include_url=False, include_input=False):
        msg = str(e.get("msg", "invalid"))
        for lead in ("Value error, ", "Assertion failed, "):
            if msg.startswith(lead):
                msg = msg[len(lead):]
        loc = tuple(e.get("loc", ()))
        if rename and loc and isinstance(loc[0], str) and loc[0] in rename:
            path = field_path(rename[loc[0]], loc[1:])
        else:
            path = field_path(prefix, loc)
        items.append(ErrorItem(field=path, message=msg))
    first = items[0] if items else ErrorItem(field=prefix, message="invalid")
    more = f" (and {len(items) - 1} more)" if len(items) > 1 else ""
    return ServiceError(422, ErrorCode.INVALID, f"{first.field}: {first.message}{more}",
                        first.field, items)
