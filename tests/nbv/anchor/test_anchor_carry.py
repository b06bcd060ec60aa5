"""The anchor's pose-independent parts carried over between events
(``AnchorConfig.carry_over_tolerance``): off, nothing changes; on, the reused parts are a
rebuild's when nothing changed, and a change beyond the tolerance rebuilds them."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from agilegs.config.selection import AnchorConfig, SelectConfig
from agilegs.service.nbv import (
    Camera,
    GaussianMap,
    Intrinsics,
    accumulate_information,
    fisher_diag,
    init_information,
    select,
)
from agilegs.service.nbv.anchor.ascent import optimize_anchor
from agilegs.service.nbv.anchor.envelope import PoolEnvelope
from agilegs.service.nbv.candidates import capture_pool
from agilegs.service.sessions.convert import storable_state

INTR = Intrinsics.from_fov(55.0, 32, 32)


def world(dtype: torch.dtype = torch.float64):
    g = torch.Generator().manual_seed(3)
    pts = 0.3 * torch.randn(200, 3, generator=g, dtype=torch.float64)
    pts[:, 1] *= 1.6
    cols = torch.rand(200, 3, generator=g, dtype=torch.float64)
    gmap = GaussianMap.from_points(pts, cols, scale=0.05, opacity=0.7).to(dtype=dtype)
    poses = capture_pool([0.0, 0.0, 0.0], 2.0, 23, seed=3, dtype=dtype)
    acq = poses[[0, 8, 16]]
    pool = poses[[i for i in range(23) if i not in (0, 8, 16)]]
    h = init_information(gmap, 1e-6)
    with torch.no_grad():
        for p in acq:
            h = accumulate_information(h, fisher_diag(gmap, Camera(c2w=p, intrinsics=INTR)))
    return gmap, h, pool, acq


def anchor(gmap, h, pool, acq, cfg, carried=None):
    env = PoolEnvelope.from_pool(pool, gmap.means.median(dim=0).values)
    return optimize_anchor(gmap, h, pool, INTR, config=cfg, num_acquired=acq.shape[0],
                           envelope=env, acquired=acq, lam=1e-6, carried=carried,
                           generator=torch.Generator().manual_seed(7))


@pytest.mark.parametrize("model", ["directional", "fitted"])
def test_reused_parts_equal_a_rebuild_when_nothing_changed(model) -> None:
    gmap, h, pool, acq = world()
    on = AnchorConfig(model=model, carry_over_tolerance=0.01)
    first = anchor(gmap, h, pool, acq, on)
    assert first.diagnostics.carried is False
    parts = storable_state({"p": first.carry})["p"]  # as the session store keeps it
    again = anchor(gmap, h, pool, acq, on, carried=parts)
    assert again.diagnostics.carried is True
    rebuilt = anchor(gmap, h, pool, acq, dataclasses.replace(on, carry_over_tolerance=0.0))
    assert rebuilt.diagnostics.carried is False and rebuilt.carry is None
    assert torch.equal(again.c2w, rebuilt.c2w) and again.psi == rebuilt.psi
    assert again.traces == rebuilt.traces
    assert torch.equal(again.pool_psi, rebuilt.pool_psi)
    for key in ("model", "unexplored_fraction", "unexplored_points"):
        assert getattr(again.diagnostics.model, key) == getattr(rebuilt.diagnostics.model, key)
    # the parts kept are those of the build (its fingerprint), not refreshed by the reuse
    assert again.carry is parts


def test_a_change_beyond_the_tolerance_rebuilds() -> None:
    gmap, h, pool, acq = world()
    on = AnchorConfig(carry_over_tolerance=0.05)
    parts = anchor(gmap, h, pool, acq, on).carry
    with torch.no_grad():
        hv = fisher_diag(gmap, Camera(c2w=pool[4], intrinsics=INTR))
    more = accumulate_information(h, hv)
    grown = max(float((more[k].sum() - h[k].sum()) / h[k].sum()) for k in h)
    assert grown > 0.05
    assert anchor(gmap, more, pool, acq, on, carried=parts).diagnostics.carried is False
    # within the tolerance: reused
    loose = dataclasses.replace(on, carry_over_tolerance=min(1.0, 2 * grown))
    parts = anchor(gmap, h, pool, acq, loose).carry
    assert anchor(gmap, more, pool, acq, loose, carried=parts).diagnostics.carried is True
    # other settings, another map size or malformed parts: rebuilt
    other = dataclasses.replace(on, num_gaussians=500)
    assert anchor(gmap, h, pool, acq, other, carried=parts).diagnostics.carried is False
    sub = gmap.subset(torch.arange(150))
    h_sub = {k: v[:150] for k, v in h.items()}
    assert anchor(sub, h_sub, pool, acq, loose, carried=parts).diagnostics.carried is False
    broken = {**parts, "proxy": {**parts["proxy"], "means": parts["proxy"]["means"][:, :2]}}
    assert anchor(gmap, h, pool, acq, loose, carried=broken).diagnostics.carried is False
    assert anchor(gmap, h, pool, acq, loose, carried=[1, 2]).diagnostics.carried is False


def test_off_selections_are_unchanged_by_carried_parts() -> None:
    """Off (the default), the state keeps no parts and carried parts in it are ignored:
    the selection is bit for bit the one without them."""
    gmap, h, pool, acq = world(torch.float32)
    sel = select("agile", gmap, h, pool, INTR, acquired=acq, lam=1e-6)
    assert "anchor_parts" not in sel.state and "anchor_carried" not in sel.details
    on = SelectConfig(anchor=AnchorConfig(carry_over_tolerance=0.5))
    with_parts = select("agile", gmap, h, pool, INTR, acquired=acq, lam=1e-6, config=on)
    assert "anchor_parts" in with_parts.state
    state = dict(sel.state)
    plain = select("agile", gmap, h, pool, INTR, acquired=acq, lam=1e-6, state=state)
    state["anchor_parts"] = with_parts.state["anchor_parts"]
    ignored = select("agile", gmap, h, pool, INTR, acquired=acq, lam=1e-6, state=state)
    assert plain.index == ignored.index and plain.scores == ignored.scores
    assert torch.equal(plain.anchor_c2w, ignored.anchor_c2w)
    assert plain.psi_trace == ignored.psi_trace
    # on: the next event reuses the parts (nothing changed) and says so
    nxt = select("agile", gmap, h, pool, INTR, acquired=acq, lam=1e-6, config=on,
                 state=with_parts.state)
    assert nxt.details["anchor_carried"] is True
    assert with_parts.details["anchor_carried"] is False


def test_the_tolerance_is_checked() -> None:
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="carry_over_tolerance"):
            AnchorConfig(carry_over_tolerance=bad)
