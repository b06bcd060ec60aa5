"""The information anchor T* = argmax_T psi(T) on SE(3) (paper section 4.1).

psi(T) = sum_q H_T,qq / Hhat_qq is the trace surrogate of the expected information gain of a
virtual camera at T. It is maximised by Riemannian gradient ascent (:mod:`.ascent`), inside the
pool's envelope (:mod:`.envelope`). Two psi behind one option (``AnchorConfig.psi``):

- ``"proxy"`` (default): rasterization-free (:mod:`.proxy`): each Gaussian's footprint,
  in-frustum and visibility terms at T, with an observation model fitted to Hhat over the
  acquired views (:mod:`.fitting`).
- ``"exact"``: ``trace_surrogate(fisher_diag(gmap, camera(T)), h_acc)`` through the rasterizer
  at reduced resolution (:mod:`.exact`): its values on the compiled Fisher, its twist gradient
  by forward differences of them (six values a gradient); on the torch path, autograd w.r.t.
  the twist. Faithful, but a Fisher pass per value and rough (the rasterizer's hard
  cut-offs).

The proxy of an event is assembled in :mod:`.assembly` (or carried over, :mod:`.carry`), over
a sample of the map of fixed size; the pool's psi, from which the starts are drawn, is ranked
by a coarse psi first (:mod:`.starts`); a call's inputs and its typed diagnostics are the
records of :mod:`.records`. The settings are
:class:`~agilegs.config.selection.AnchorConfig`.
"""
