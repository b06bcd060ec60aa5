"""Compiled CPU kernels (numba) of the projection, the tile compositing and the one-pass Fisher.

The compiled modules (:mod:`.binning`, :mod:`.projection`, :mod:`.walks`, :mod:`.coverage`,
:mod:`.proxy`, with :mod:`.common`) take numpy arrays in and give numpy arrays out, no torch;
:mod:`.ops` wraps them in autograd functions and :mod:`.backend` picks them or the pure-torch
reference (and imports them only when they serve, so that a missing numba leaves the torch
path working). Every kernel follows the pure-torch rules of
:mod:`agilegs.service.nbv.projection`, :mod:`agilegs.service.nbv.rasterize` and
:mod:`agilegs.service.nbv.information` exactly:

- projection (:func:`project`): EWA with the 0.3 low-pass, the 1.3× field-of-view clamp of
  the Jacobian, culling (depth ≤ near, det ≤ 0, off screen), radius ceil(3 sqrt(λ_max)),
  colour max(0, 0.5 + Σ_k Y_k sh_k), opacity sigmoid(logit). Per-Gaussian arithmetic is float64;
  the outputs take the input dtype.
- binning (:func:`bin_count`, :func:`visible_order`, :func:`bin_fill`): the visible
  Gaussians sorted front to back (stable), each listed in every tile of the clamped tile
  range its square [u - r, u + r] overlaps that also meets the bounding box of its
  α ≥ 1/255 ellipse (pixels outside that box cannot pass the 1/255 test, so leaving those
  tiles out changes nothing). A list entry is a record of its Gaussian's screen attributes
  and its box within the tile; entries refer to the depth-sorted visible ("compact")
  Gaussians.
- compositing (:func:`composite_forward`, :func:`composite_backward`, :func:`fisher_tiles`):
  per tile, per pixel front to back: σ = ½(a dx² + c dy²) + b dx dy and α = o·exp(-σ) in the
  input dtype (the torch path's per-pair arithmetic, so the same pairs pass), σ < 0 and
  α < 1/255 skipped, α clamped at 0.99, the transmittance T (float64) stops before the
  Gaussian that would take it below 1e-4. The forward can record each tile's composited
  pairs; the backward walks them back to front, recovering T_i = T_{i+1} / (1 - α_i) and the
  colour behind.
- the Fisher's chain (:func:`fisher_chain`) and the projection's vector-Jacobian product
  (:func:`project_backward`) share one analytic per-Gaussian Jacobian (:func:`_gaussian`) of
  the screen attributes (mean2d, conic, opacity, colour) and depth w.r.t. the Gaussian's own
  parameters.

Memory access: the binning writes every tile's list as a run of records (the Gaussian's
screen attributes, depth and colours), so that the walks read memory in order; the backward
walks write one row per list entry, and :func:`reduce_entries` sums each Gaussian's rows.

Threads: the kernels are serial and release the GIL; a kernel with ``part, nchunks``
arguments does part ``part`` of ``nchunks`` (tile t in part t mod nchunks; Gaussians in
contiguous ranges), and the parts write disjoint memory, so the caller runs them on as many
Python threads (:mod:`agilegs.service.nbv.kernels.backend`). No numba threading layer is involved
(none to configure, nothing that breaks across a fork).
"""
