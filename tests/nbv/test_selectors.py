"""``select``: every method's contract, embodied mode, seeding and argument checks."""

from __future__ import annotations

import math

import pytest
import torch

from agilegs.config.selection import (
    FIELD_NAMES,
    SHORTLISTS,
    AnchorConfig,
    ScoringConfig,
    SelectConfig,
)
from agilegs.lab.bench.stages import ANCHOR_STAGES
from agilegs.service.nbv import (
    METHODS,
    Camera,
    GaussianMap,
    Intrinsics,
    accumulate_information,
    eig_scores,
    expected_information_gain,
    fisher_diag,
    init_information,
    select,
)
from agilegs.service.nbv.candidates import capture_pool
from agilegs.service.nbv.methods.base import STAGES
from agilegs.service.nbv.se3 import pose_distance

INTR = Intrinsics.from_fov(55.0, 32, 32)


def build(n: int = 200, d: int = 20, seed: int = 0):
    """Float32 (fast) tiny world: n Gaussians, a pool of d, Hhat from 3 acquired views."""
    g = torch.Generator().manual_seed(seed)
    pts = 0.3 * torch.randn(n, 3, generator=g)
    pts[:, 1] *= 1.6
    cols = torch.rand(n, 3, generator=g)
    gmap = GaussianMap.from_points(pts, cols, scale=0.05, opacity=0.7)
    poses = capture_pool([0.0, 0.0, 0.0], 2.0, d + 3, seed=seed)
    acq = poses[[0, 8, 16]]
    pool = poses[[i for i in range(d + 3) if i not in (0, 8, 16)]]
    h = init_information(gmap, 1e-6)
    with torch.no_grad():
        for p in acq:
            h = accumulate_information(h, fisher_diag(gmap, Camera(c2w=p, intrinsics=INTR)))
    return gmap, h, pool, acq


@pytest.fixture(scope="module")
def world():
    gmap, h, pool, acq = build()
    phi = eig_scores(gmap, h, pool, INTR)
    return gmap, h, pool, acq, phi


def reference_phi(gmap, h, pose) -> float:
    hv = fisher_diag(gmap, Camera(c2w=pose, intrinsics=INTR))
    return float(expected_information_gain(hv, h))


def test_eig_scores_match_expected_information_gain(world) -> None:
    gmap, h, pool, _, phi = world
    for i in (0, 7, 19):
        assert float(phi[i]) == pytest.approx(reference_phi(gmap, h, pool[i]), rel=1e-4)


def test_full_eig_returns_argmax_phi_over_the_pool(world) -> None:
    gmap, h, pool, acq, phi = world
    sel = select("full_eig", gmap, h, pool, INTR, acquired=acq)
    assert sel.index == int(torch.argmax(phi))
    assert sorted(sel.scores) == list(range(len(pool)))
    for i, v in sel.scores.items():
        assert v == pytest.approx(float(phi[i]), rel=1e-4)


def test_agile_returns_the_shortlist_first(world) -> None:
    gmap, h, pool, acq, _ = world
    for shortlist in SHORTLISTS:
        cfg = SelectConfig(shortlist=shortlist)  # type: ignore[arg-type]
        sel = select("agile", gmap, h, pool, INTR, acquired=acq, config=cfg)
        assert len(sel.shortlist) == 10 and len(set(sel.shortlist)) == 10
        assert sel.index == sel.shortlist[0]
        assert sel.anchor_c2w is not None and sel.anchor_c2w.shape == (4, 4)
        assert sel.psi_trace and all(b >= a for a, b in zip(sel.psi_trace, sel.psi_trace[1:]))


def test_agile_plus_returns_argmax_phi_over_the_shortlist(world) -> None:
    gmap, h, pool, acq, phi = world
    for shortlist in SHORTLISTS:
        cfg = SelectConfig(shortlist=shortlist, shortlist_size=6,  # type: ignore[arg-type]
                           probes=0, objective="eig")
        plain = select("agile", gmap, h, pool, INTR, acquired=acq, config=cfg)
        plus = select("agile_plus", gmap, h, pool, INTR, acquired=acq, config=cfg)
        assert plus.shortlist == plain.shortlist
        best = max(plus.shortlist, key=lambda i: (float(phi[i]), -plus.shortlist.index(i)))
        assert plus.index == best
        assert sorted(plus.scores) == sorted(plus.shortlist)
        for i, v in plus.scores.items():
            assert v == pytest.approx(float(phi[i]), rel=1e-4)


def test_agile_plus_reranks_the_model_s_shortlist_and_uniform_probes(world) -> None:
    gmap, h, pool, acq, phi = world
    for probes in (1, 2):
        cfg = SelectConfig(shortlist_size=6, probes=probes, seed=3, objective="eig")
        model = select("agile", gmap, h, pool, INTR, acquired=acq,
                       config=SelectConfig(shortlist_size=6 - probes, probes=0, seed=3,
                                           objective="eig"))
        plus = select("agile_plus", gmap, h, pool, INTR, acquired=acq, config=cfg)
        assert plus.shortlist[: 6 - probes] == model.shortlist
        drawn = plus.shortlist[6 - probes:]
        assert len(drawn) == probes and not set(drawn) & set(model.shortlist)
        assert plus.index == max(plus.shortlist, key=lambda i: (float(phi[i]),
                                                                -plus.shortlist.index(i)))
        d = plus.details
        assert d["probes"] == probes
        assert d["model_best_phi"] == pytest.approx(max(float(phi[i]) for i in model.shortlist),
                                                    rel=1e-4)
        assert d["probe_best_phi"] == pytest.approx(max(float(phi[i]) for i in drawn), rel=1e-4)
        assert d["probe_won"] == (d["probe_best_phi"] > d["model_best_phi"])
        # the next event's probes: doubled when a probe won, halved (not below the least)
        nxt = int(plus.state["probes"])
        assert nxt == (min(2 * probes, 3) if d["probe_won"] else max(probes // 2, probes))


def test_probe_counts_follow_the_model_s_record(world) -> None:
    """Along a session: a probe that wins raises the next count, a model that wins lowers it,
    always within [config.probes, N // 2]; probes=0 draws none."""
    gmap, h, pool, acq, phi = world
    cfg = SelectConfig(shortlist_size=8, probes=1)
    # a warm state that already holds more probes than the bound is clamped to N // 2
    sel = select("agile_plus", gmap, h, pool, INTR, acquired=acq, config=cfg,
                 state={"probes": torch.tensor(9)})
    assert sel.details["probes"] == 4 and len(sel.shortlist) == 8
    # probes are drawn uniformly outside the model's shortlist: over many seeds, many
    # different candidates, never one of the model's
    seen: set[int] = set()
    for seed in range(40):
        c = SelectConfig(shortlist_size=8, probes=1, seed=seed)
        m = select("agile", gmap, h, pool, INTR, acquired=acq,
                   config=SelectConfig(shortlist_size=7, probes=0, seed=seed)).shortlist
        p = select("agile_plus", gmap, h, pool, INTR, acquired=acq, config=c)
        assert p.shortlist[:7] == m
        seen.add(p.shortlist[7])
        assert p.shortlist[7] not in m
    assert len(seen) >= 6
    none = select("agile_plus", gmap, h, pool, INTR, acquired=acq,
                  config=SelectConfig(shortlist_size=8, probes=0))
    assert "probes" not in none.details and "probes" not in none.state


@pytest.mark.parametrize(("phi", "probes", "won", "nxt"), [
    ([5.0, 4.0, 3.0, 9.0], 1, True, 2),     # a probe beats the model: doubled
    ([5.0, 4.0, 9.0, 1.0], 2, True, 4),     # up to N // 2 = 4
    ([9.0, 4.0, 3.0, 1.0], 4, False, 2),    # the model wins: halved
    ([9.0, 4.0, 3.0, 9.0], 1, False, 1),    # a tie is the model's; never below the least
])
def test_the_next_probe_count(phi, probes, won, nxt) -> None:
    from types import SimpleNamespace

    from agilegs.service.nbv.methods.agile import _judge_model
    ctx = SimpleNamespace(config=SelectConfig(shortlist_size=8, probes=1))
    out: dict = {"state": {}, "details": {}}
    n_model = len(phi) - (2 if probes >= 2 else 1)
    _judge_model(ctx, torch.tensor(phi, dtype=torch.float64), n_model, probes, out)  # type: ignore[arg-type]
    assert out["details"]["probe_won"] is won
    assert int(out["state"]["probes"]) == nxt


def test_the_paper_preset_draws_no_probes() -> None:
    from agilegs.config.selection import preset_config
    assert preset_config("paper").probes == 0
    assert SelectConfig().probes == 1


def test_latency_breakdown_and_selection_fields(world) -> None:
    gmap, h, pool, acq, _ = world
    for method in METHODS:
        sel = select(method, gmap, h, pool, INTR, acquired=acq)
        assert {k for k in sel.latency_ms if "." not in k} == set(STAGES)
        assert all(v >= 0 for v in sel.latency_ms.values())
        assert sel.latency_ms["total"] >= max(v for k, v in sel.latency_ms.items() if k != "total")
        # the anchor's own stages, apart: within the anchor
        sub = [v for k, v in sel.latency_ms.items() if k.startswith("anchor.")
               and k.count(".") == 1]
        if method in ("agile", "agile_plus"):
            assert {f"anchor.{s}" for s in ANCHOR_STAGES} <= set(sel.latency_ms)
            assert 0 < sum(sub) <= sel.latency_ms["anchor"]
        else:
            assert not sub
        assert 0 <= sel.index < len(pool)
        assert sel.eligible == list(range(len(pool)))
        assert sel.method == method
    sel = select("agile_plus", gmap, h, pool, INTR, acquired=acq)
    assert sel.latency_ms["anchor"] > 0 and sel.latency_ms["rerank"] > 0


@pytest.mark.parametrize("method", METHODS)
def test_embodied_mode_never_picks_outside_the_k_nearest(world, method: str) -> None:
    gmap, h, pool, acq, _ = world
    radius = 2.0
    for current in (0, 11):
        for metric in ("position", "se3"):
            cfg = SelectConfig(embodied_k=5, embodied_metric=metric,  # type: ignore[arg-type]
                               scoring=ScoringConfig(rot_weight=radius))
            sel = select(method, gmap, h, pool, INTR, acquired=acq, current=current, config=cfg)
            if metric == "se3":
                dist = pose_distance(pool, pool[current].expand_as(pool), radius)
            else:  # camera centres only, as COVER's protocol
                dist = (pool[:, :3, 3] - pool[current, :3, 3]).norm(dim=1)
            dist[current] = math.inf
            nearest = set(torch.argsort(dist)[:5].tolist())
            assert set(sel.eligible) == nearest
            assert sel.index in nearest and sel.index != current
            assert set(sel.shortlist) <= nearest


def test_embodied_metrics_differ_where_orientation_matters() -> None:
    from agilegs.service.nbv import look_at
    from agilegs.service.nbv.selectors import eligible_candidates

    z = torch.zeros(3)
    here = look_at(torch.tensor([2.0, 0.0, 0.0]), z)
    # nearer, but facing away; a little farther, facing the same target
    away = look_at(torch.tensor([2.0, 0.1, 0.0]), torch.tensor([4.0, 0.1, 0.0]))
    along = look_at(torch.tensor([2.0, 0.0, 0.3]), z)
    pool = torch.stack([here, away, along])
    pos = eligible_candidates(pool, embodied_k=1, current=0, metric="position")
    se3 = eligible_candidates(pool, embodied_k=1, current=0, metric="se3", rot_weight=2.0)
    assert pos == [1] and se3 == [2]
    with pytest.raises(ValueError, match="metric"):
        eligible_candidates(pool, embodied_k=1, current=0, metric="bogus")


def test_embodied_mode_with_a_current_pose_outside_the_pool(world) -> None:
    gmap, h, pool, acq, _ = world
    here = acq[1]
    sel = select(
        "agile_plus",
        gmap,
        h,
        pool,
        INTR,
        acquired=acq,
        current_pose=here,
        config=SelectConfig(embodied_k=3),
    )
    assert len(sel.eligible) == 3 and sel.index in sel.eligible


@pytest.mark.parametrize("method", METHODS)
def test_a_fixed_seed_gives_the_same_selection_twice(world, method: str) -> None:
    gmap, h, pool, acq, _ = world
    cfg = SelectConfig(seed=7, shortlist="online")
    a = select(method, gmap, h, pool, INTR, acquired=acq, config=cfg)
    b = select(method, gmap, h, pool, INTR, acquired=acq, config=cfg)
    assert a.index == b.index and a.shortlist == b.shortlist
    if a.anchor_c2w is not None:
        assert b.anchor_c2w is not None
        assert torch.equal(a.anchor_c2w, b.anchor_c2w)


def test_random_depends_on_seed_and_event(world) -> None:
    gmap, h, pool, acq, _ = world
    picks = {
        select("random", gmap, h, pool, INTR, config=SelectConfig(seed=s)).index for s in range(12)
    }
    assert len(picks) > 3
    first = select("random", gmap, h, pool, INTR)
    following = {
        select("random", gmap, h, pool, INTR, state={"event": e}).index for e in range(1, 12)
    }
    assert len(following | {first.index}) > 3
    assert first.state["event"] == 1


def test_warm_start_state_is_passed_on(world) -> None:
    gmap, h, pool, acq, _ = world
    first = select("agile", gmap, h, pool, INTR, acquired=acq)
    assert torch.equal(first.state["anchor_c2w"], first.anchor_c2w)
    second = select("agile", gmap, h, pool, INTR, acquired=acq, state=first.state)
    assert second.details["anchor_starts"]  # pool starts, plus the warm start
    assert second.state["event"] == 2


def test_typical_fisher_from_a_start_view_is_cached(world) -> None:
    gmap, h, pool, acq, _ = world
    cfg = SelectConfig(anchor=AnchorConfig(typical_fisher="start_view"))
    first = select("agile", gmap, h, pool, INTR, acquired=acq, config=cfg)
    assert set(first.state["typical_fisher"]) == set(FIELD_NAMES)
    second = select("agile", gmap, h, pool, INTR, acquired=acq, config=cfg, state=first.state)
    assert second.state["typical_fisher"] is first.state["typical_fisher"]


def test_fields_restrict_phi(world) -> None:
    gmap, h, pool, acq, _ = world
    sel = select("full_eig", gmap, h, pool[:4], INTR, config=SelectConfig(fields=("sh",)))
    hv = fisher_diag(gmap, Camera(c2w=pool[2], intrinsics=INTR))
    ref = float(expected_information_gain(hv, h, fields=("sh",)))
    assert sel.scores[2] == pytest.approx(ref, rel=1e-4)


def _bad_rotation(pool: torch.Tensor) -> torch.Tensor:
    out = pool.clone()
    out[3, :3, :3] *= 1.1
    return out


def _nan_pose(pool: torch.Tensor) -> torch.Tensor:
    out = pool.clone()
    out[2, 0, 3] = float("nan")
    return out


def test_bad_arguments_raise_value_errors_naming_them(world) -> None:
    gmap, h, pool, acq, _ = world
    cases = [
        (dict(method="bogus"), "method"),
        (dict(candidates=pool[:0]), "candidates"),
        (dict(candidates=pool[0]), "candidates"),
        (dict(candidates=_nan_pose(pool)), "candidates.*NaN"),
        (dict(candidates=_bad_rotation(pool)), "candidates.*orthonormal"),
        (dict(config=SelectConfig(embodied_k=3)), "current"),
        (dict(config=_mutated(shortlist_size=0)), "shortlist_size"),
        (dict(h_acc={k: v for k, v in h.items() if k != "sh"}), "h_acc"),
        (dict(h_acc={**h, "means": h["means"][:-1]}), "h_acc"),
        (dict(h_acc={**h, "means": torch.zeros_like(h["means"])}), "h_acc"),
        (dict(current=len(pool)), "current"),
        (dict(acquired=_nan_pose(acq)), "acquired"),
        (dict(lam=0.0), "lam"),
        (dict(lam=float("nan")), "lam"),
    ]
    for kwargs, word in cases:
        args = dict(
            method="agile", gmap=gmap, h_acc=h, candidates=pool, intrinsics=INTR, acquired=acq
        )
        args.update(kwargs)
        method = args.pop("method")
        with pytest.raises(ValueError, match=word):
            select(method, **args)  # type: ignore[arg-type]
    # a bad setting cannot even be built: the error names the field
    for kwargs, word in [({"shortlist_size": 0}, "shortlist_size"),
                         ({"embodied_k": 0}, "embodied_k"), ({"shortlist": "bogus"}, "shortlist"),
                         ({"fields": ("bogus",)}, "fields"), ({"fields": ()}, "fields"),
                         ({"fields": ("sh", "sh")}, "fields"), ({"seed": -1}, "seed"),
                         ({"shortlist_size": "3"}, "shortlist_size"),
                         ({"embodied_metric": "euclid"}, "embodied_metric"),
                         ({"cover_radius_clip": -1.0}, "cover_radius_clip"),
                         ({"fisherrf": {"reg_lambda": 0.0}}, "reg_lambda")]:
        with pytest.raises(ValueError, match=word):
            SelectConfig(**kwargs)  # type: ignore[arg-type]


def _mutated(**changes: object) -> SelectConfig:
    """A valid config changed by attribute assignment (which does not validate)."""
    cfg = SelectConfig()
    for k, v in changes.items():
        setattr(cfg, k, v)
    return cfg


def test_single_candidate_pool(world) -> None:
    gmap, h, pool, acq, _ = world
    for method in METHODS:
        sel = select(method, gmap, h, pool[:1], INTR, acquired=acq)
        assert sel.index == 0


def test_leverage_shortlist_is_conditioned_on_the_acquired_views(world) -> None:
    """A candidate at an acquired pose repeats its coverage: conditioned, it is not picked."""
    gmap, h, pool, acq, _ = world
    plain_cfg = SelectConfig(scoring=ScoringConfig(condition_on_acquired=False))
    first = select("agile", gmap, h, pool, INTR, config=plain_cfg, acquired=acq)
    k = first.index
    held = torch.cat([acq, pool[k : k + 1]])  # the plain pick, as if acquired already
    cond = select("agile", gmap, h, pool, INTR, acquired=held)
    plain = select("agile", gmap, h, pool, INTR, config=plain_cfg, acquired=held)
    assert cond.anchor_c2w is not None and plain.anchor_c2w is not None
    torch.testing.assert_close(cond.anchor_c2w, plain.anchor_c2w)  # same anchor, same rows
    assert k not in cond.shortlist[:1]
    # the gains are the conditional leverages: lower with the acquired rows in S_0
    assert cond.scores[cond.shortlist[0]] <= plain.scores[plain.shortlist[0]] + 1e-12


def test_paper_preset() -> None:
    from agilegs.config.selection import PRESETS, preset_config

    cfg = preset_config("paper")
    assert cfg.anchor.psi == "exact" and cfg.scoring.condition_on_acquired is False
    # the paper's one anchor, whatever the defaults
    assert (cfg.anchor.anchors, cfg.anchor.model, cfg.anchor.unexplored) == (1, "fitted", False)
    # everything else is the default; overrides merge over the preset
    assert cfg.shortlist_size == SelectConfig().shortlist_size
    cfg = preset_config("paper", shortlist_size=5, anchor={"resolution": 32})
    assert (cfg.shortlist_size, cfg.anchor.resolution, cfg.anchor.psi) == (5, 32, "exact")
    assert set(PRESETS) == {"paper"}
    with pytest.raises(ValueError, match="preset"):
        preset_config("bogus")


def test_the_anchor_gets_hhat_s_lambda_and_background(world, monkeypatch) -> None:
    """``select`` hands the anchor the lambda inside Hhat and the Fisher background."""
    from agilegs.service.nbv.anchor import assembly

    seen: dict[str, object] = {}

    def spying(name: str):
        real = getattr(assembly, name)

        def spy(*args, **kwargs):
            seen[name] = kwargs.get("lam")
            return real(*args, **kwargs)
        return spy

    for name in ("observation_rates", "directional_rates"):
        monkeypatch.setattr(assembly, name, spying(name))
    gmap, h, pool, acq, _ = world
    select("agile", gmap, h, pool, INTR, acquired=acq, lam=1e-6)
    assert seen == {"directional_rates": 1e-6}
    select("agile", gmap, h, pool, INTR, acquired=acq, lam=1e-6,
           config=SelectConfig(anchor=AnchorConfig(model="fitted")))
    assert seen["observation_rates"] == 1e-6
    # the exact psi renders on the background the config gives
    from agilegs.service.nbv import trace_surrogate

    bg = (0.9, 0.8, 0.7)
    cfg = SelectConfig(fisher_background=bg, anchor=AnchorConfig(
        psi="exact", num_starts=1, iterations=1, backtracks=1, resolution=16))
    sel = select("agile", gmap, h, pool, INTR, acquired=acq, config=cfg, lam=1e-6)
    assert sel.anchor_c2w is not None
    small = INTR.scaled(16, 16)
    with torch.no_grad():
        cam = Camera(c2w=sel.anchor_c2w, intrinsics=small)
        with_bg = float(trace_surrogate(fisher_diag(gmap, cam, background=torch.tensor(bg)), h))
        black = float(trace_surrogate(fisher_diag(gmap, cam), h))
    # psi at the anchor is the render on the given background, not on black
    assert abs(with_bg - black) > 1e-4 * abs(black)
    assert abs(sel.psi_trace[-1] - with_bg) < 0.01 * abs(with_bg - black)


def test_the_anchor_reports_under_the_wire_s_names(world) -> None:
    """The anchor's typed diagnostics reach a selection as the same named entries, in the
    same order (the HTTP response and the benchmark's JSON are built from them), with the
    numbers of the anchor found on the same inputs."""
    from agilegs.service.nbv.anchor.ascent import find_anchor
    from agilegs.service.nbv.anchor.envelope import PoolEnvelope
    from agilegs.service.nbv.anchor.records import AnchorInputs
    from agilegs.service.nbv.candidates import scene_center_radius

    gmap, h, pool, acq, _ = world
    cfg = SelectConfig(anchor=AnchorConfig(carry_over_tolerance=0.01), objective="eig")
    sel = select("agile", gmap, h, pool, INTR, acquired=acq, config=cfg, lam=1e-6)
    assert [k for k in sel.latency_ms if k.startswith("anchor.")] == [
        "anchor.envelope", "anchor.visibility", "anchor.rates", "anchor.unexplored",
        "anchor.starts", "anchor.ascent", "anchor.ascent.gradients", "anchor.ascent.values"]
    anchor_keys = ["ascent_evaluations", "anchor_modes", "anchor_psi", "best_candidate_psi",
                   "psi_evaluations", "anchor_starts", "proxy_samples", "anchor_carried",
                   "rates_carried", "pool_proxy_psi"]
    assert list(sel.details)[:len(anchor_keys)] == anchor_keys
    # the same anchor, found directly: its diagnostics are the selection's entries
    aim, _ = scene_center_radius(gmap.means)
    env = PoolEnvelope.from_pool(pool.to(gmap.dtype), aim, cfg.anchor.envelope_margin)
    gen = torch.Generator().manual_seed(0)
    res = find_anchor(AnchorInputs(
        gmap, dict(h), pool.to(gmap.dtype), INTR, cfg.anchor, num_acquired=acq.shape[0],
        envelope=env, generator=gen, acquired=acq.to(gmap.dtype), lam=1e-6))
    stages, details = res.report(list(range(len(pool))), cfg.anchor)
    assert list(stages) == [k for k in sel.latency_ms if k.startswith("anchor.")][1:]
    assert list(details) == anchor_keys
    d = res.diagnostics
    assert details["ascent_evaluations"] == {"gradient": d.ascent.gradient_evaluations,
                                             "value": d.ascent.value_evaluations}
    assert details["anchor_starts"] == d.start_indices
    assert details["proxy_samples"] == d.proxy_samples
    assert details["anchor_carried"] is d.carried is False
    assert details["rates_carried"] is d.rates_carried is False
    assert details["psi_evaluations"] == res.evaluations
    assert stages["anchor.ascent.values"] == d.ascent.value_s * 1e3


@pytest.mark.parametrize("method", ["random", "agile_plus"])
def test_select_from_inputs_selects_as_select(world, method) -> None:
    """A caller that validated its inputs builds a SelectInputs and selects through
    select_from: the selection of select on the same inputs."""
    from agilegs.service.nbv.selectors import SelectInputs, select_from

    gmap, h, pool, acq, _ = world
    cfg = SelectConfig(shortlist_size=4, seed=5)
    state = {"event": 2}
    a = select(method, gmap, h, pool, INTR, config=cfg, acquired=acq, state=state, lam=1e-6)
    b = select_from(SelectInputs(method, gmap, h, pool, INTR, cfg, acquired=acq, lam=1e-6),
                    state=state)
    assert (a.index, a.shortlist, a.scores, a.eligible, a.details.keys()) == (
        b.index, b.shortlist, b.scores, b.eligible, b.details.keys())
    assert a.state.keys() == b.state.keys() and a.state["event"] == b.state["event"] == 3
