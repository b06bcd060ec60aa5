"""The anchor under the ``target`` objective: the proxy's samples weighted by how much the
views of interest would learn of them.

The target objective values a view v by the fall of the targets' predicted render variance,
``sum_i T_i H_v,i / (Hhat_i (Hhat_i + H_v,i))`` (:mod:`agilegs.service.nbv.targets`), with T_i
the targets' summed Fisher. In the proxy's units ``u_i = H_v,i / Hhat_i`` a Gaussian's term is
``tau_i u_i / (1 + u_i)`` with ``tau_i = T_i / Hhat_i = sum_t u_i(t)``, and the EIG's is
``log(1 + u_i)``; to first order in ``u_i`` (a view's information small against what is
known) the first is the second times ``tau_i``. So the anchor keeps its psi and its kernels and
weights each sample by its ``tau``, the proxy's own information at the targets (no Fisher
pass: the targets cost one proxy evaluation each), normalised to the samples' weighted mean.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from .proxy import ProxyPsi

__all__ = ["sample_information", "target_weighted"]


def sample_information(proxy: ProxyPsi, c2w: Tensor) -> Tensor:
    """Each sample's term of the proxy's psi at the poses [T, 4, 4], summed over them -> [S]
    (``sum_t sum_q log(1 + rate_sq w_s(t) f_q)`` by the proxy's model; the bare terms
    ``w_s(t)`` without rates)."""
    with torch.no_grad():
        terms = proxy(c2w, per_sample=True)  # [T, S]
        rate = proxy.rate
        if rate is not None and rate.ndim == 2:
            assert proxy.slot_kinds is not None
            f = proxy.direction_factors(c2w)[..., proxy.slot_kinds]  # [T, S, Q]
            terms = torch.log1p(terms.unsqueeze(-1) * f * rate.to(terms.dtype)).sum(-1)
        elif rate is not None:
            terms = torch.log1p(terms * rate.to(terms.dtype))
        return terms.sum(0)


def target_weighted(proxy: ProxyPsi, targets: Tensor) -> ProxyPsi:
    """``proxy`` with each sample's weight times its information at ``targets`` [T, 4, 4]
    (:func:`sample_information`) over the samples' weighted mean of it; ``proxy`` itself when
    the targets see none of the samples."""
    tau = sample_information(proxy, targets.to(proxy.means.dtype))
    weight = proxy.weight.to(tau.dtype)
    mean = float((weight * tau).sum() / weight.sum().clamp_min(1e-300))
    if not mean > 0.0:
        return proxy
    return dataclasses.replace(proxy, weight=(proxy.weight * (tau / mean).to(proxy.weight.dtype)))
