"""Sessions as ``list_sessions`` shows them: an intact one's summary, a damaged one's entry
(state ``damaged``, what is wrong, what ``repair_session`` would do), and the error a
damaged session's operations answer."""

from __future__ import annotations

from agilegs import schemas as m

from ..errors import ServiceError, session_damaged
from ..store.integrity import Damage
from ..store.records import SessionRecord

__all__ = ["damage_out", "damaged_error", "damaged_summary", "record_summary"]


def record_summary(rec: SessionRecord) -> m.SessionSummary:
    """The listing entry of an intact session."""
    return m.SessionSummary(id=rec.id, version=rec.version, num_gaussians=len(rec.gmap),
                            pool_size=len(rec.pool_ids), num_views=len(rec.views),
                            updated_at=rec.updated_at)


def damage_out(d: Damage) -> m.SessionDamage:
    """What is damaged and what a repair would do."""
    return m.SessionDamage(
        files=[m.FileProblem(file=p.file, problem=p.problem) for p in d.files],
        version=d.version, repairable=d.repairable, rollback_to=d.rollback_to,
        drop_frames=list(d.drop_frames), repair=d.plan(), detected_at=d.detected_at)


def damaged_summary(d: Damage) -> m.SessionSummary:
    """The listing entry of a damaged session: what its checked manifest says (None where
    nothing checked out)."""
    current = d.record if isinstance(d.record, SessionRecord) and d.rollback_to is None else None
    man = d.manifest
    return m.SessionSummary(
        id=d.session, state="damaged", version=d.version,
        num_gaussians=len(current.gmap) if current is not None else None,
        pool_size=len(current.pool_ids) if current is not None else None,
        num_views=len(man["views"]) if man is not None else None,
        updated_at=float(man["updated_at"]) if man is not None else None,
        damage=damage_out(d))


def damaged_error(d: Damage, field: str = "path.session") -> ServiceError:
    """409 ``session_damaged``: what is wrong, and the way back."""
    way = (f"repair_session would {d.plan()}" if d.repairable
           else f"repair is impossible ({d.plan()})")
    return session_damaged(field, f"session {d.session!r} is damaged: {d.reason()}; {way}; "
                                  "delete_session removes it")
