"""The anchor under the target objective: each proxy sample weighted by its information at the
views of interest (first order of the target objective's term)."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from conftest import proxy_scene

from agilegs.service.nbv.anchor.targeted import sample_information, target_weighted


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_samples_information_sums_to_psi_at_the_targets(dtype: torch.dtype) -> None:
    poses, proxies = proxy_scene(dtype)
    tol = 1e-10 if dtype == torch.float64 else 2e-4
    for tag, proxy in proxies:
        info = sample_information(proxy, poses)  # [S]
        assert info.shape == proxy.weight.shape, tag
        with torch.no_grad():
            psi = proxy(poses).sum()
        got = (info * proxy.weight.to(info.dtype)).sum()
        assert torch.allclose(got, psi.to(got.dtype), rtol=tol, atol=tol), (tag, got, psi)
        # one target at a time: each sample's share is its own term at that pose
        for k in range(poses.shape[0]):
            one = sample_information(proxy, poses[k:k + 1])
            assert (one >= 0).all(), tag


def test_the_weighted_psi_is_the_sum_of_weighted_terms() -> None:
    poses, proxies = proxy_scene(torch.float64)
    targets, probe = poses[:2], poses[2:3]
    for tag, proxy in proxies:
        tau = sample_information(proxy, targets)
        w = proxy.weight
        mean = (w * tau).sum() / w.sum()
        weighted = target_weighted(proxy, targets)
        assert torch.allclose(weighted.weight, w * tau / mean, rtol=1e-12), tag
        assert torch.allclose((weighted.weight).sum(), (w * tau).sum() / mean), tag
        # psi of the weighted proxy at a pose = sum over samples of the new weights x terms
        terms = sample_information(dataclasses.replace(proxy, weight=torch.ones_like(w)), probe)
        with torch.no_grad():
            psi = weighted(probe)[0]
        assert torch.allclose(psi, (weighted.weight * terms).sum(), rtol=1e-10), tag


def test_targets_worth_nothing_leave_the_proxy_as_it_is() -> None:
    poses, proxies = proxy_scene(torch.float64)
    for tag, proxy in proxies:
        none = dataclasses.replace(proxy, weight=torch.zeros_like(proxy.weight))
        assert target_weighted(none, poses) is none, tag  # no weighted mean to scale by
        assert target_weighted(proxy, poses) is not proxy, tag
