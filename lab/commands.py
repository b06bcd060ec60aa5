"""The lab's ``agilegs`` commands: the demo and the benchmarks. ``agilegs.service.cli`` finds
this module through the ``agilegs.commands`` entry point (pyproject.toml), so the server's
package names none of the lab. Light: it imports nothing, and ``agilegs --help`` reads it."""

from __future__ import annotations

# (command path, module, help)
COMMANDS: list[tuple[tuple[str, ...], str, str]] = [
    (("demo",), "agilegs.lab.demo.run", "closed-loop demo on the bundled scene"),
    (("bench", "render"), "agilegs.lab.bench.render_bench", "rasterizer and Fisher timings"),
    (("bench", "latency"), "agilegs.lab.bench.latency", "selection latency of every method"),
    (("bench", "run"), "agilegs.lab.bench.run_cli", "the paper's progressive protocol"),
    (("bench", "service"), "agilegs.lab.bench.service_bench", "transport overhead"),
    (("bench", "bigmap"), "agilegs.lab.bench.bigmap",
     "a server holding a session of a million Gaussians: memory and time per method"),
    (("bench", "edge"), "agilegs.lab.bench.edge",
     "slow and idle connections, and large bodies at once: what they cost the server"),
    (("bench", "value"), "agilegs.lab.bench.value",
     "what each candidate is worth, and which scores predict it"),
    (("bench", "proxy"), "agilegs.lab.bench.proxy_check",
     "how the anchor's choices follow the exact EIG on trained maps"),
    (("bench", "firstcall"), "agilegs.lab.bench.firstcall",
     "a fresh server's first selection against its tenth (the kernels' compile)"),
    (("bench", "coverage"), "agilegs.lab.bench.coverage_report",
     "where a bench run's picks went, the test views' coverage, and their EIG's mass"),
    (("bench", "fleet"), "agilegs.lab.bench.fleet",
     "instances sharing an object store, killed and paused under load: takeover, losses"),
]

GROUPS: dict[str, str] = {
    "bench": "the benchmarks: render, latency, run, service, bigmap, edge, value, proxy, "
             "firstcall, coverage, fleet",
}
"""The help of each command that groups subcommands."""

OPTIONS: dict[str, str] = {
    "agilegs.lab.bench.latency": "agilegs.lab.bench.options:add_latency_arguments",
    "agilegs.lab.bench.run_cli": "agilegs.lab.bench.options:add_run_arguments",
    "agilegs.lab.bench.value": "agilegs.lab.bench.options:add_value_arguments",
    "agilegs.lab.bench.proxy_check": "agilegs.lab.bench.options:add_proxy_arguments",
}
"""``module:function`` that adds the options of a command whose module imports torch (the
others' ``add_arguments`` is used)."""
