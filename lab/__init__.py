"""The lab: what measures and demonstrates the server but is not it. The benchmark
(:mod:`agilegs.lab.bench`), the closed-loop demo (:mod:`agilegs.lab.demo`) and the benchmark's
scenes (:mod:`agilegs.lab.scenes`); their plotting dependencies come with the ``lab`` extra.
Nothing in :mod:`agilegs.service` imports the lab."""
