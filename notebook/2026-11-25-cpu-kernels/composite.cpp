// The tile compositing of agilegs.service.nbv.kernels (composite_forward / composite_backward,
// float32 records) ported line by line to C++, for the numba-or-C++ measurement in
// ../2026-11-25-cpu-kernels.md. A plain C ABI (called through ctypes, which releases the
// GIL), one part of the tiles per call, as the numba kernels take them.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {
constexpr int REC = 8;
constexpr double T_MIN = 1e-4;

struct Walk {
  std::vector<double> tr;
  std::vector<int64_t> last;
  std::vector<double> acc, dacc;
};

void live_rect(int x0, int y0, int x1, int y1, int tile, const int64_t* last, int64_t k,
               int& lx0, int& lx1, int& ly0, int& ly1) {
  lx0 = x1; lx1 = x0 - 1; ly0 = y1; ly1 = y0 - 1;
  for (int py = y0; py < y1; ++py)
    for (int px = x0; px < x1; ++px)
      if (k < last[(py - y0) * tile + (px - x0)]) {
        lx0 = std::min(lx0, px); lx1 = std::max(lx1, px);
        ly0 = std::min(ly0, py); ly1 = std::max(ly1, py);
      }
}
}  // namespace

extern "C" void composite_forward_f32(
    const int64_t* offsets, int64_t n_tiles, const float* rec, int64_t rec_w,
    const int32_t* rbox, const float* xs, const float* ys, int width, int height, int tile,
    int part, int nchunks, const int64_t* slots, int record, int32_t* pk, int32_t* pp,
    float* pa, int64_t* npairs, float* out_col, double* out_tf, float* out_dacc) {
  const int nc = static_cast<int>(rec_w) - REC;
  const int tiles_x = (width + tile - 1) / tile;
  const int npix = tile * tile;
  const float half = 0.5f, amin = 1.0f / 255.0f, amax = 0.99f;
  std::vector<double> tr(npix), acc(npix * nc), dacc(npix);
  std::vector<int64_t> last(npix);
  for (int64_t t = part; t < n_tiles; t += nchunks) {
    const int x0 = static_cast<int>(t % tiles_x) * tile, y0 = static_cast<int>(t / tiles_x) * tile;
    const int x1 = std::min(x0 + tile, width), y1 = std::min(y0 + tile, height);
    const int64_t start = offsets[t], length = offsets[t + 1] - start;
    std::fill(tr.begin(), tr.end(), 1.0);
    std::fill(last.begin(), last.end(), length);
    std::fill(acc.begin(), acc.end(), 0.0);
    std::fill(dacc.begin(), dacc.end(), 0.0);
    const int inside = (x1 - x0) * (y1 - y0);
    int ndone = 0, seen = 0;
    int64_t n = 0;
    int lx0 = x0, lx1 = x1 - 1, ly0 = y0, ly1 = y1 - 1;
    for (int64_t k = 0; k < length; ++k) {
      if (ndone != seen) {
        if (ndone == inside) break;
        seen = ndone;
        live_rect(x0, y0, x1, y1, tile, last.data(), k, lx0, lx1, ly0, ly1);
      }
      const int64_t e = start + k;
      const int32_t* b = rbox + 4 * e;
      const int bx0 = std::max<int>(b[0], lx0), bx1 = std::min<int>(b[1], lx1);
      const int by0 = std::max<int>(b[2], ly0), by1 = std::min<int>(b[3], ly1);
      if (bx0 > bx1 || by0 > by1) continue;
      const float* r = rec + rec_w * e;
      const float mx = r[0], my = r[1], a = r[2], bb = r[3], c = r[4], o = r[5], cut = r[7];
      for (int py = by0; py <= by1; ++py) {
        const float dy = ys[py] - my;
        const int row = (py - y0) * tile - x0;
        for (int px = bx0; px <= bx1; ++px) {
          const int p = row + px;
          if (last[p] <= k) continue;
          const float dx = xs[px] - mx;
          const float sigma = half * (a * dx * dx + c * dy * dy) + bb * dx * dy;
          if (sigma < 0 || sigma > cut) continue;
          const float raw = o * std::exp(-sigma);
          if (raw < amin) continue;
          const double al = std::min(raw, amax);
          const double tp = tr[p], tn = tp * (1.0 - al);
          if (tn < T_MIN) { last[p] = k; ++ndone; continue; }
          tr[p] = tn;
          const double w = tp * al;
          for (int ch = 0; ch < nc; ++ch) acc[p * nc + ch] += w * r[REC + ch];
          dacc[p] += w * r[6];
          if (record) { pk[slots[t] + n] = static_cast<int32_t>(k); pp[slots[t] + n] = p; pa[slots[t] + n] = raw; }
          ++n;
        }
      }
    }
    npairs[t] = n;
    for (int py = y0; py < y1; ++py)
      for (int px = x0; px < x1; ++px) {
        const int p = (py - y0) * tile + (px - x0);
        const int64_t pix = static_cast<int64_t>(py) * width + px;
        for (int ch = 0; ch < nc; ++ch) out_col[pix * nc + ch] = static_cast<float>(acc[p * nc + ch]);
        out_tf[pix] = tr[p];
        out_dacc[pix] = static_cast<float>(dacc[p]);
      }
  }
}

extern "C" void composite_backward_f32(
    const int64_t* offsets, int64_t n_tiles, const float* rec, int64_t rec_w,
    const float* xs, const float* ys, int width, int height, int tile, int part, int nchunks,
    const int64_t* slots, const int32_t* pk, const int32_t* pp, const float* pa,
    const int64_t* npairs, const double* t_final, const float* bg, const float* g_col,
    const float* g_alpha, const float* g_depth, double* grads) {
  const int nc = static_cast<int>(rec_w) - REC;
  const int tiles_x = (width + tile - 1) / tile;
  const int npix = tile * tile;
  const float amax = 0.99f;
  std::vector<double> tr(npix), behind(npix), tail(npix), pg(npix * nc), pgd(npix), gcl(nc);
  for (int64_t t = part; t < n_tiles; t += nchunks) {
    const int x0 = static_cast<int>(t % tiles_x) * tile, y0 = static_cast<int>(t / tiles_x) * tile;
    const int x1 = std::min(x0 + tile, width), y1 = std::min(y0 + tile, height);
    const int64_t start = offsets[t];
    for (int py = y0; py < y1; ++py)
      for (int px = x0; px < x1; ++px) {
        const int p = (py - y0) * tile + (px - x0);
        const int64_t pix = static_cast<int64_t>(py) * width + px;
        tr[p] = t_final[pix];
        behind[p] = 0.0;
        double s = -static_cast<double>(g_alpha[pix]);
        for (int ch = 0; ch < nc; ++ch) {
          pg[p * nc + ch] = g_col[pix * nc + ch];
          s += static_cast<double>(bg[ch]) * g_col[pix * nc + ch];
        }
        pgd[p] = g_depth[pix];
        tail[p] = t_final[pix] * s;
      }
    const int64_t first = slots[t];
    int64_t j = first + npairs[t] - 1;
    while (j >= first) {
      const int64_t k = pk[j], e = start + k;
      const float* r = rec + rec_w * e;
      const float mx = r[0], my = r[1];
      const double af = r[2], bf = r[3], cf = r[4], zg = r[6];
      double gm0 = 0, gm1 = 0, ga = 0, gb = 0, gc = 0, go = 0, gz = 0;
      std::fill(gcl.begin(), gcl.end(), 0.0);
      while (j >= first && pk[j] == k) {
        const int p = pp[j];
        const float raw = pa[j];
        --j;
        const double dxf = xs[x0 + p % tile] - mx, dyf = ys[y0 + p / tile] - my;
        const double al = std::min(raw, amax);
        const double inv = 1.0 / (1.0 - al);
        const double tp = tr[p] * inv;
        tr[p] = tp;
        const double w = tp * al;
        const double gd = pgd[p];
        double uu = gd * zg;
        for (int ch = 0; ch < nc; ++ch) {
          const double gch = pg[p * nc + ch];
          uu += static_cast<double>(r[REC + ch]) * gch;
          gcl[ch] += w * gch;
        }
        gz += w * gd;
        const double gal = tp * uu - (behind[p] + tail[p]) * inv;
        behind[p] += w * uu;
        const double gp = raw <= amax ? gal * al : 0.0;
        gm0 += gp * (af * dxf + bf * dyf);
        gm1 += gp * (bf * dxf + cf * dyf);
        ga -= 0.5 * gp * dxf * dxf;
        gb -= gp * dxf * dyf;
        gc -= 0.5 * gp * dyf * dyf;
        go += gp;
      }
      double* g = grads + (7 + nc) * e;
      g[0] = gm0; g[1] = gm1; g[2] = ga; g[3] = gb; g[4] = gc;
      g[5] = go / std::max(static_cast<double>(r[5]), 1e-30);
      g[6] = gz;
      for (int ch = 0; ch < nc; ++ch) g[7 + ch] = gcl[ch];
    }
  }
}
