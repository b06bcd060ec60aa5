"""The operations every client offers, once for blocking clients and once for asyncio.

Each method builds its request (:mod:`agilegs.client._requests`) and hands it to the
transport's ``_send``; method names equal the operation names of
:data:`agilegs.schemas.ops.OPERATIONS` and the last chunk of their Zenoh keys.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from pydantic import BaseModel

from agilegs import schemas as m
from agilegs.schemas import Bounds, Intrinsics
from agilegs.schemas import decisions as d

from . import _requests as rq
from ._requests import Call, PoseLike

__all__ = ["AsyncOperations", "SyncOperations"]

T = TypeVar("T", bound=BaseModel)

PoolLike = m.PoolIn | np.ndarray | Sequence[PoseLike]
GaussiansLike = m.GaussiansIn | str | Path | Mapping[str, Any]
ObservationLike = m.ObservationIn | Mapping[str, Any]


class SyncOperations:
    """Blocking operations; a subclass implements ``_send(call) -> response model``."""

    def _send(self, call: Call) -> Any:  # pragma: no cover - abstract
        raise NotImplementedError

    def health(self) -> m.Health:
        """Liveness, version and session count."""
        return self._send(rq.call("health"))  # type: ignore[no-any-return]

    def create_session(
        self,
        intrinsics: Intrinsics | Mapping[str, Any],
        *,
        id: str | None = None,
        bounds: Bounds | Mapping[str, Any] | None = None,
        gaussians: GaussiansLike | None = None,
        frames: Sequence[ObservationLike] = (),
        init_gaussians: int = 1000,
        seed: int = 0,
        pool: PoolLike | None = None,
        defaults: m.SelectDefaults | Mapping[str, Any] | None = None,
        information: m.InformationConfig | Mapping[str, Any] | None = None,
        mapper: m.MapperOptions | Mapping[str, Any] | None = None,
        instance: str | None = None,
    ) -> m.SessionInfo:
        """Create a session: with ``bounds`` (random Gaussians inside), from ``gaussians``
        (a .ply / .splat path, a GaussiansIn, or a dict of arrays), or from posed ``frames``.
        ``mapper`` (MapperOptions) says how the service trains the map from the images;
        ``instance`` names the server instance to create it on (several instances joined
        over Zenoh; default: the placement policy)."""
        return self._send(rq.create_session(  # type: ignore[no-any-return]
            intrinsics, id=id, bounds=bounds, gaussians=gaussians, frames=frames,
            init_gaussians=init_gaussians, seed=seed, pool=pool, defaults=defaults,
            information=information, mapper=mapper, instance=instance))

    def list_sessions(self) -> m.SessionList:
        return self._send(rq.call("list_sessions"))  # type: ignore[no-any-return]

    def get_session(self, session: str) -> m.SessionInfo:
        return self._send(rq.call("get_session", session))  # type: ignore[no-any-return]

    def delete_session(self, session: str) -> m.Deleted:
        return self._send(rq.call("delete_session", session))  # type: ignore[no-any-return]

    def repair_session(self, session: str) -> m.Repaired:
        """Bring a damaged session back (see ``SessionSummary.damage``): roll it back to its
        last intact version and drop damaged frames; nothing changes if it is intact."""
        return self._send(rq.call("repair_session", session))  # type: ignore[no-any-return]

    def set_gaussians(self, session: str, gaussians: GaussiansLike) -> m.SessionInfo:
        """Replace the session's Gaussians (Ĥ follows the new map)."""
        return self._send(rq.call(  # type: ignore[no-any-return]
            "set_gaussians", session, rq.to_gaussians(gaussians)))

    def add_observations(self, session: str,
                         observations: ObservationLike | Sequence[ObservationLike]
                         ) -> m.ViewsOut:
        """Add posed frames (see ObservationIn): new acquired views update Ĥ."""
        return self._send(rq.add_observations(session, observations))  # type: ignore[no-any-return]

    def list_views(self, session: str) -> m.ViewsOut:
        return self._send(rq.call("list_views", session))  # type: ignore[no-any-return]

    def get_frames(self, session: str, view_id: int | None = None, *, depth: bool = True
                   ) -> m.FramesOut:
        """Acquired views with their images (``frame.image.to_numpy()``: RGB [H, W, 3]; png
        and jpeg files as they came) and depth maps (``frame.depth.to_numpy()``: [H, W]
        float32, 0 where missing): the view ``view_id``, or every view."""
        return self._send(rq.get_frames(  # type: ignore[no-any-return]
            session, view_id, depth=depth))

    def commit(self, session: str, candidate_id: int | None = None, *,
               pose: PoseLike | None = None, keep_in_pool: bool = False) -> m.View:
        """Acquire a candidate (by id) or a pose as a view; updates Ĥ."""
        return self._send(rq.commit(  # type: ignore[no-any-return]
            session, candidate_id, pose=pose, keep_in_pool=keep_in_pool))

    def set_pool(self, session: str, poses: PoolLike, ids: Sequence[int] | None = None
                 ) -> m.PoolOut:
        """Replace the candidate pool with ``poses`` ([D, 4, 4] camera-to-world)."""
        return self._send(rq.call(  # type: ignore[no-any-return]
            "set_pool", session, rq.to_pool(poses, ids)))

    def extend_pool(self, session: str, poses: PoolLike, ids: Sequence[int] | None = None
                    ) -> m.PoolOut:
        """Add candidates to the pool."""
        return self._send(rq.call(  # type: ignore[no-any-return]
            "extend_pool", session, rq.to_pool(poses, ids)))

    def get_pool(self, session: str) -> m.PoolOut:
        return self._send(rq.call("get_pool", session))  # type: ignore[no-any-return]

    def select(
        self,
        session: str,
        *,
        method: str | None = None,
        shortlist_size: int | None = None,
        shortlist: str | None = None,
        embodied_k: int | None = None,
        seed: int | None = None,
        fields: Sequence[str] | None = None,
        config: Mapping[str, Any] | None = None,
        current_id: int | None = None,
        current_pose: PoseLike | None = None,
        pool: PoolLike | None = None,
        commit: bool = False,
        targets: np.ndarray | Sequence[PoseLike] | None = None,
    ) -> m.SelectResponse:
        """Choose the next view (unset arguments take the session's defaults); ``targets``:
        the views of interest [T, 4, 4] of the target objective (the default of ``agile`` and
        ``agile_plus``; ``config={"objective": "target"}`` for ``full_eig``)."""
        return self._send(rq.select(  # type: ignore[no-any-return]
            session, method=method, shortlist_size=shortlist_size, shortlist=shortlist,
            embodied_k=embodied_k, seed=seed, fields=fields, config=config,
            current_id=current_id, current_pose=current_pose, pool=pool, commit=commit,
            targets=targets))

    def get_information(self, session: str) -> m.InformationOut:
        """Ĥ per parameter block (``.arrays()`` gives numpy arrays)."""
        return self._send(rq.call("get_information", session))  # type: ignore[no-any-return]

    def get_gaussians(self, session: str) -> m.GaussiansOut:
        """The session's current Gaussians (``.to_numpy()`` gives the five arrays): the map
        the service's mapper last published, or the one last set."""
        return self._send(rq.call("get_gaussians", session))  # type: ignore[no-any-return]

    def save_gaussians(self, session: str, path: str | Path) -> Path:
        """Write the session's current Gaussians to ``path``: an Inria 3DGS ``.ply`` (the
        float32 parameters as they are; SuperSplat, gsplat, nerfstudio read it) or an
        antimatter15 ``.splat`` (quantised), by its suffix; returns ``path``."""
        return rq.write_file(path, self._send(rq.gaussians_file(session, path)))

    def get_decisions(self, session: str, *, after: int = 0, wait: float = 0.0,
                      limit: int = 100) -> d.DecisionsOut:
        """The session's decisions with a sequence number above ``after``, oldest first;
        with none newer, the server waits up to ``wait`` s for one (a long poll; keep
        ``wait`` below the client's timeout). Follow a session by passing the last
        ``next_after`` back, and start over from 0 when ``epoch`` changes."""
        return self._send(rq.get_decisions(  # type: ignore[no-any-return]
            session, after=after, wait=wait, limit=limit))


class AsyncOperations:
    """The same operations as :class:`SyncOperations`, as coroutines."""

    async def _send(self, call: Call) -> Any:  # pragma: no cover - abstract
        raise NotImplementedError

    async def health(self) -> m.Health:
        return await self._send(rq.call("health"))  # type: ignore[no-any-return]

    async def create_session(
        self,
        intrinsics: Intrinsics | Mapping[str, Any],
        *,
        id: str | None = None,
        bounds: Bounds | Mapping[str, Any] | None = None,
        gaussians: GaussiansLike | None = None,
        frames: Sequence[ObservationLike] = (),
        init_gaussians: int = 1000,
        seed: int = 0,
        pool: PoolLike | None = None,
        defaults: m.SelectDefaults | Mapping[str, Any] | None = None,
        information: m.InformationConfig | Mapping[str, Any] | None = None,
        mapper: m.MapperOptions | Mapping[str, Any] | None = None,
        instance: str | None = None,
    ) -> m.SessionInfo:
        return await self._send(rq.create_session(  # type: ignore[no-any-return]
            intrinsics, id=id, bounds=bounds, gaussians=gaussians, frames=frames,
            init_gaussians=init_gaussians, seed=seed, pool=pool, defaults=defaults,
            information=information, mapper=mapper, instance=instance))

    async def list_sessions(self) -> m.SessionList:
        return await self._send(rq.call("list_sessions"))  # type: ignore[no-any-return]

    async def get_session(self, session: str) -> m.SessionInfo:
        return await self._send(rq.call("get_session", session))  # type: ignore[no-any-return]

    async def delete_session(self, session: str) -> m.Deleted:
        return await self._send(rq.call("delete_session", session))  # type: ignore[no-any-return]

    async def repair_session(self, session: str) -> m.Repaired:
        return await self._send(rq.call("repair_session", session))  # type: ignore[no-any-return]

    async def set_gaussians(self, session: str, gaussians: GaussiansLike) -> m.SessionInfo:
        return await self._send(rq.call(  # type: ignore[no-any-return]
            "set_gaussians", session, rq.to_gaussians(gaussians)))

    async def add_observations(self, session: str,
                               observations: ObservationLike | Sequence[ObservationLike]
                               ) -> m.ViewsOut:
        return await self._send(  # type: ignore[no-any-return]
            rq.add_observations(session, observations))

    async def list_views(self, session: str) -> m.ViewsOut:
        return await self._send(rq.call("list_views", session))  # type: ignore[no-any-return]

    async def get_frames(self, session: str, view_id: int | None = None, *, depth: bool = True
                         ) -> m.FramesOut:
        return await self._send(rq.get_frames(  # type: ignore[no-any-return]
            session, view_id, depth=depth))

    async def commit(self, session: str, candidate_id: int | None = None, *,
                     pose: PoseLike | None = None, keep_in_pool: bool = False) -> m.View:
        return await self._send(rq.commit(  # type: ignore[no-any-return]
            session, candidate_id, pose=pose, keep_in_pool=keep_in_pool))

    async def set_pool(self, session: str, poses: PoolLike, ids: Sequence[int] | None = None
                       ) -> m.PoolOut:
        return await self._send(rq.call(  # type: ignore[no-any-return]
            "set_pool", session, rq.to_pool(poses, ids)))

    async def extend_pool(self, session: str, poses: PoolLike, ids: Sequence[int] | None = None
                          ) -> m.PoolOut:
        return await self._send(rq.call(  # type: ignore[no-any-return]
            "extend_pool", session, rq.to_pool(poses, ids)))

    async def get_pool(self, session: str) -> m.PoolOut:
        return await self._send(rq.call("get_pool", session))  # type: ignore[no-any-return]

    async def select(
        self,
        session: str,
        *,
        method: str | None = None,
        shortlist_size: int | None = None,
        shortlist: str | None = None,
        embodied_k: int | None = None,
        seed: int | None = None,
        fields: Sequence[str] | None = None,
        config: Mapping[str, Any] | None = None,
        current_id: int | None = None,
        current_pose: PoseLike | None = None,
        pool: PoolLike | None = None,
        commit: bool = False,
        targets: np.ndarray | Sequence[PoseLike] | None = None,
    ) -> m.SelectResponse:
        return await self._send(rq.select(  # type: ignore[no-any-return]
            session, method=method, shortlist_size=shortlist_size, shortlist=shortlist,
            embodied_k=embodied_k, seed=seed, fields=fields, config=config,
            current_id=current_id, current_pose=current_pose, pool=pool, commit=commit,
            targets=targets))

    async def get_information(self, session: str) -> m.InformationOut:
        return await self._send(rq.call("get_information", session))  # type: ignore[no-any-return]

    async def get_gaussians(self, session: str) -> m.GaussiansOut:
        return await self._send(rq.call("get_gaussians", session))  # type: ignore[no-any-return]

    async def save_gaussians(self, session: str, path: str | Path) -> Path:
        return rq.write_file(path, await self._send(rq.gaussians_file(session, path)))

    async def get_decisions(self, session: str, *, after: int = 0, wait: float = 0.0,
                            limit: int = 100) -> d.DecisionsOut:
        return await self._send(rq.get_decisions(  # type: ignore[no-any-return]
            session, after=after, wait=wait, limit=limit))
