"""The anchor's proxy psi (:class:`.proxy.ProxyPsi`) assembled for one event, from the
anchor's settings: its visibility (the deep opacity maps, ``visibility="transmittance"``, or
the z-buffer's occluders), its observation model's weights and rates (``model``: the
``"typical"`` Fisher, or the ``"fitted"`` / ``"directional"`` rates fitted over the acquired
views, :mod:`.fitting`) and, with a fitted model, the unexplored space (:mod:`.unexplored`);
or the previous event's proxy, carried over while ``carry_over_tolerance`` allows
(:mod:`.carry`).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from agilegs.config.selection import AnchorConfig

from ..camera import Intrinsics
from ..candidates import scene_center_radius
from .carry import fingerprint, pack, settings_key, unpack
from .fitting import (
    DirectionalRates,
    directional_rates,
    information_weights,
    observation_rates,
    typical_fisher_from_h_acc,
)
from .proxy import ProxyPsi, pick_occluders
from .records import AnchorInputs, ModelDiagnostics
from .targeted import target_weighted
from .unexplored import unexplored_space
from .visibility import OpacityMaps

__all__ = ["AssembledProxy", "assemble_proxy", "build_proxy", "fit_sample", "proxy_intrinsics",
           "uniform_subset"]


@dataclass
class AssembledProxy:
    """The proxy of one event.

    Attributes:
        proxy: the proxy psi.
        model: what its model is.
        carried: whether it is the previous event's.
        carry: the parts to keep for the next event (with ``carry_over_tolerance`` > 0 and
            no given typical Fisher; the carried parts themselves when reused), else None.
        rates_carry: the directional model's accumulated terms over the acquired views, for
            the next event (``refit_every`` > 1, :func:`.fitting.directional_rates`), else
            None.
        rates_carried: whether this event's rates extended carried terms.
    """

    proxy: ProxyPsi
    model: ModelDiagnostics
    carried: bool
    carry: Any = None
    rates_carry: Any = None
    rates_carried: bool = False


def proxy_intrinsics(intrinsics: Intrinsics, config: AnchorConfig) -> Intrinsics:
    """The proxy's image: the candidates' at ``config.resolution`` pixels wide (the aspect
    kept), or as they are."""
    if config.resolution is None:
        return intrinsics
    return intrinsics.scaled(
        config.resolution,
        max(1, round(config.resolution * intrinsics.height / intrinsics.width)),
    )


def assemble_proxy(inputs: AnchorInputs, radius: float,
                   lap: Callable[[str], None]) -> AssembledProxy:
    """The proxy of ``inputs`` for a pool of ``radius``: the carried parts
    (``inputs.carried``) when they may serve, else :func:`build_proxy`; ``lap`` called after
    each stage (``visibility``, ``rates``, ``unexplored``; at once for carried parts)."""
    cfg = inputs.config
    prox_intr = proxy_intrinsics(inputs.intrinsics, cfg)
    now: dict[str, Any] | None = None
    key = ""
    if cfg.carry_over_tolerance > 0 and inputs.typical is None:
        now = fingerprint(inputs.gmap, inputs.h_acc, inputs.fields, radius)
        key = settings_key(cfg, prox_intr, inputs.fields)
        reused = unpack(inputs.carried, now=now, key=key, tolerance=cfg.carry_over_tolerance,
                        intrinsics=prox_intr, dtype=inputs.gmap.dtype)
        if reused is not None:
            for stage in ("visibility", "rates", "unexplored"):
                lap(stage)
            return AssembledProxy(_targeted(reused[0], inputs, lap), reused[1], carried=True,
                                  carry=inputs.carried, rates_carry=inputs.rates_carried)
    proxy, model, rates = build_proxy(inputs, prox_intr, radius, lap)
    carry = pack(proxy, model.as_dict(), now, key) if now is not None else None
    return AssembledProxy(_targeted(proxy, inputs, lap), model, carried=False, carry=carry,
                          rates_carry=None if rates is None else rates.carry,
                          rates_carried=rates is not None and rates.carried)


def _targeted(proxy: ProxyPsi, inputs: AnchorInputs, lap: Callable[[str], None]
              ) -> ProxyPsi:
    """``proxy`` weighted by the targets' information when ``inputs.targets`` are given
    (:mod:`.targeted`; stage ``targets``)."""
    if inputs.targets is None:
        return proxy
    out = target_weighted(proxy, inputs.targets)
    lap("targets")
    return out


def build_proxy(inputs: AnchorInputs, prox_intr: Intrinsics, radius: float,
                lap: Callable[[str], None]
                ) -> tuple[ProxyPsi, ModelDiagnostics, DirectionalRates | None]:
    """The proxy psi of the anchor's settings on the image ``prox_intr``: its visibility,
    the model's rates and the unexplored space (``lap`` after each stage), what its model
    is, and the directional model's fit (None for the others)."""
    cfg = inputs.config
    common: dict[str, Any] = dict(
        near=cfg.near_fraction * radius,
        edge=cfg.edge_softness * prox_intr.width,
        generator=inputs.generator,
    )
    acquired = inputs.acquired
    fitted = (inputs.typical is None and cfg.model in ("fitted", "directional")
              and acquired is not None and acquired.shape[0] > 0)
    # the fitted models read a sample of the map of fixed size (each Gaussian of it standing
    # for `share` of the map's): the visibility's occluders and the rates
    sample, share = (fit_sample(inputs, cfg.fit_gaussians) if fitted
                     else (inputs, 1.0))
    # the sample's centre and 98% radius, for the visibility's grid and the unexplored space
    extent = functools.cache(lambda: scene_center_radius(sample.gmap.means))
    common.update(_visibility(sample, prox_intr, share, extent))
    lap("visibility")
    if not fitted or acquired is None:
        proxy, model = _typical_model(inputs, prox_intr, common)
        lap("rates")
        lap("unexplored")
        return proxy, model, None
    rated = _directional_model if cfg.model == "directional" else _fitted_model
    proxy, model, prior_rate, per_gaussian, fit = rated(sample, acquired, prox_intr, common)
    if share != 1.0:
        proxy = dataclasses.replace(proxy, weight=proxy.weight * share)
    lap("rates")
    if cfg.unexplored:
        space = unexplored_space(sample.gmap, acquired, proxy, cells=cfg.unexplored_cells,
                                 shells=cfg.unexplored_shells,
                                 count_inside=cfg.unexplored_inside,
                                 generator=inputs.generator, share=share,
                                 extent=extent())
        n = int(space.means.shape[0])
        if n:
            rates = prior_rate.to(inputs.gmap.dtype).expand(n, *prior_rate.shape)
            proxy = proxy.extended(space.means, space.cov, per_gaussian * space.weight, rates)
        model = dataclasses.replace(model, unexplored_fraction=space.unexplored_fraction,
                                    unexplored_points=n)
    lap("unexplored")
    return proxy, model, fit


def uniform_subset(n: int, size: int, generator: torch.Generator | None) -> Tensor:
    """A uniform random subset of ``size`` of ``range(n)`` (``size`` < n), increasing, in
    O(size log size) where ``size`` <= n / 2: the first ``size`` distinct values of 2 ``size``
    uniform draws (the order in which an i.i.d. sequence meets new values makes every subset
    of a size equally likely); a permutation of ``range(n)`` otherwise, or when the draws
    meet fewer distinct values."""
    if 2 * size <= n:
        m = 2 * size
        draws = torch.randint(0, n, (m,), generator=generator)
        uniq, inv = torch.unique(draws, return_inverse=True)
        if uniq.numel() >= size:
            first = torch.full((uniq.numel(),), m, dtype=torch.long).scatter_reduce(
                0, inv, torch.arange(m), reduce="amin")
            return torch.sort(uniq[torch.argsort(first)[:size]]).values
    return torch.sort(torch.randperm(n, generator=generator)[:size]).values


def fit_sample(inputs: AnchorInputs, size: int) -> tuple[AnchorInputs, float]:
    """``inputs`` with the map and Hhat cut to a seeded uniform sample of ``size`` of the
    map's Gaussians (:func:`uniform_subset`, seeded by the map's count), and the
    number of the map's Gaussians
    each stands for (N / size); ``inputs`` as they are and 1 when ``size`` is 0 or at least
    the map's count."""
    n = inputs.gmap.num_gaussians
    if size <= 0 or size >= n:
        return inputs, 1.0
    # seeded by the map's count alone: the same sample at every event of an unchanged map
    # (the carried rates' terms are its Gaussians')
    gen = torch.Generator().manual_seed(n)
    idx = uniform_subset(n, size, gen).to(inputs.gmap.means.device)
    h_acc = {k: v[idx] if isinstance(v, Tensor) and v.shape[:1] == (n,) else v
             for k, v in inputs.h_acc.items()}
    return dataclasses.replace(inputs, gmap=inputs.gmap.subset(idx), h_acc=h_acc), n / size


def _visibility(inputs: AnchorInputs, prox_intr: Intrinsics, share: float,
                extent: Callable[[], tuple[Tensor, float]]) -> dict[str, Any]:
    """The proxy's visibility arguments: the deep opacity maps (``grid``; each occluder's
    mass times ``share``, the map's Gaussians each of ``inputs``' stands for; ``extent()``
    the map's centre [3] and 98% radius), or the z-buffer's occluders and its settings."""
    cfg = inputs.config
    if cfg.visibility == "transmittance":
        center, r98 = extent()
        grid = OpacityMaps.build(
            inputs.gmap, prox_intr, center, r98, cells=cfg.transmittance_cells,
            bins=cfg.transmittance_bins, max_occluders=cfg.occluders,
            generator=inputs.generator)
        if share != 1.0:
            grid = dataclasses.replace(grid, mass=grid.mass * share)
        return {"grid": grid}
    return dict(
        num_occluders=cfg.occluders,
        occ_grid=cfg.occlusion_grid,
        occ_tests=cfg.occlusion_tests,
        occluders=pick_occluders(inputs.gmap, cfg.occluders, inputs.generator),
    )


def _typical_model(inputs: AnchorInputs, prox_intr: Intrinsics, common: dict[str, Any]
                   ) -> tuple[ProxyPsi, ModelDiagnostics]:
    """The typical model: every view adds the typical Fisher m_q (given, or from Hhat)."""
    typical = inputs.typical
    source = "given"
    if typical is None:
        typical = typical_fisher_from_h_acc(inputs.h_acc, inputs.num_acquired, inputs.fields,
                                            lam=inputs.lam)
        source = "h_acc"
    c = information_weights(inputs.h_acc, typical, inputs.fields)
    proxy = ProxyPsi.build(inputs.gmap, c, prox_intr, num_samples=inputs.config.num_gaussians,
                           **common)
    return proxy, ModelDiagnostics("typical", typical_source=source)


def _directional_model(inputs: AnchorInputs, acquired: Tensor, prox_intr: Intrinsics,
                       common: dict[str, Any]
                       ) -> tuple[ProxyPsi, ModelDiagnostics, Tensor, float, DirectionalRates]:
    """The directional model fitted over the acquired views [A, 4, 4] (extending the
    carried terms, ``inputs.rates_carried``, while ``refit_every`` allows); with the
    unexplored points' rates [Q], weight scale and the fit."""
    drate = directional_rates(inputs.gmap, inputs.h_acc, acquired, prox_intr, inputs.fields,
                              lam=inputs.lam, near=common["near"], edge=common["edge"],
                              grid=common.get("grid"), generator=inputs.generator,
                              carried=inputs.rates_carried,
                              refit_every=inputs.config.refit_every)
    c = torch.log1p(drate.rate * drate.typical).sum(1)
    proxy = ProxyPsi.build(
        inputs.gmap, c, prox_intr, num_samples=inputs.config.num_gaussians, rate=drate.rate,
        slot_kinds=drate.kinds, **common,
    )
    return (proxy, ModelDiagnostics("directional", typical_term=drate.typical),
            drate.prior_rate, 1.0, drate)


def _fitted_model(inputs: AnchorInputs, acquired: Tensor, prox_intr: Intrinsics,
                  common: dict[str, Any]
                  ) -> tuple[ProxyPsi, ModelDiagnostics, Tensor, float, None]:
    """The fitted model over the acquired views [A, 4, 4]; with the unexplored points'
    rate [] and weight scale."""
    fit = observation_rates(inputs.gmap, inputs.h_acc, acquired, prox_intr, inputs.fields,
                            lam=inputs.lam, unseen=inputs.config.unseen, **common)
    c = fit.slots * torch.log1p(fit.rate * fit.typical)
    proxy = ProxyPsi.build(
        inputs.gmap, c, prox_intr, num_samples=inputs.config.num_gaussians, rate=fit.rate,
        slots=fit.slots, **common,
    )
    return (proxy, ModelDiagnostics("fitted", typical_term=fit.typical),
            torch.tensor(fit.prior_rate, dtype=inputs.gmap.dtype), float(fit.slots), None)
