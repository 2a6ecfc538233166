// Fused CPU kernels of swiftjax.align, called through jax.ffi (XLA's typed FFI).
//
// XLA:CPU emits a multi-output reduction as a scalar loop; these kernels do the same
// one-pass accumulation with 8 independent float32 lanes (each lane sums its own sequence,
// so the compiler vectorises it without fast-math), then add the lane and block partials in
// double.  Built at install (pyproject.toml's [[tool.setuptools.ext-modules]], optional:
// without a C++ compiler the package uses its pure-JAX formulation, swiftjax/align/_kernels.py).
//
// * swiftjax_pixel_moments: per-frame pixel moments of a chunk-pair overlap, the layout of
//   swiftjax.align.chunk_pair._pixel_moments.
// * swiftjax_umeyama_moments: the 18 centred weighted sums and the count of a (batched)
//   Umeyama problem, the layout of swiftjax.align.umeyama._moment_terms.
#include <Python.h>

#include <cmath>
#include <cstdint>
#include <cstring>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;


namespace {

// The loops twice: for AVX2 + FMA (chosen at run time when the CPU has them) and for the
// baseline instruction set, so one build runs on any x86-64 (and elsewhere, baseline only).
#if defined(__x86_64__) && defined(__GNUC__)
#define SWIFTJAX_X86_DISPATCH 1
#pragma GCC push_options
#pragma GCC target("avx2,fma")
namespace avx2 {
#include "kernels_loops.inc"
}  // namespace avx2
#pragma GCC pop_options
#endif
namespace base {
#include "kernels_loops.inc"
}  // namespace base

static bool UseAvx2() {
#ifdef SWIFTJAX_X86_DISPATCH
  static const bool yes = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
  return yes;
#else
  return false;
#endif
}

static void PixelRow(const float* Dp, const float* Dc, const float* Cp, const float* Cc, const float* U, int64_t W,
                     float rp, float rc, float ep, float ec, float tp, float tc, float lam, float* sums,
                     int64_t* count) {
#ifdef SWIFTJAX_X86_DISPATCH
  if (UseAvx2()) return avx2::PixelRow(Dp, Dc, Cp, Cc, U, W, rp, rc, ep, ec, tp, tc, lam, sums, count);
#endif
  base::PixelRow(Dp, Dc, Cp, Cc, U, W, rp, rc, ep, ec, tp, tc, lam, sums, count);
}

static void PointBlock(const float* x, const float* y, const float* w, const float* c, int64_t p0, int64_t p1,
                       double* tot, int64_t* count) {
#ifdef SWIFTJAX_X86_DISPATCH
  if (UseAvx2()) return avx2::PointBlock(x, y, w, c, p0, p1, tot, count);
#endif
  base::PointBlock(x, y, w, c, p0, p1, tot, count);
}

// Pixel moments.  Inputs depth_p, depth_c, conf_p, conf_c [F, H, W]; per-frame parameters
// [F, 7] = (r_p, r_c, e_p, e_c, thr_p, thr_c, lam); u~ [W], v~ [H].  A pixel is reliable when
// |r_p D_p - r_c D_c| < lam, conf_p > thr_p, conf_c > thr_c and all four inputs are finite
// (a frame with lam < 0 keeps nothing).  Outputs S [F, 6, 3, 3] = sum m img u~^k v~^l with
// img in (1, a, b, ab, a^2, b^2), a = r_p D_p - e_p, b = r_c D_c - e_c; the count n [F].
static ffi::Error PixelMomentsImpl(ffi::Buffer<ffi::F32> dp, ffi::Buffer<ffi::F32> dc,
                                   ffi::Buffer<ffi::F32> cp, ffi::Buffer<ffi::F32> cc,
                                   ffi::Buffer<ffi::F32> frame, ffi::Buffer<ffi::F32> ut,
                                   ffi::Buffer<ffi::F32> vt, ffi::ResultBuffer<ffi::F32> out,
                                   ffi::ResultBuffer<ffi::S32> count) {
  auto dims = dp.dimensions();
  const int64_t W = dims[dims.size() - 1], H = dims[dims.size() - 2];
  const int64_t F = (H * W) ? dp.element_count() / (H * W) : 0;
  const float* P = frame.typed_data();
  const float* U = ut.typed_data();
  const float* V = vt.typed_data();
  float* S = out->typed_data();
  int32_t* N = count->typed_data();
  for (int64_t f = 0; f < F; ++f) {
    const float* q = P + 7 * f;
    double tot[6][3][3] = {};
    int64_t n = 0;
    for (int64_t h = 0; h < H; ++h) {
      const int64_t o = (f * H + h) * W;
      float sums[18];
      PixelRow(dp.typed_data() + o, dc.typed_data() + o, cp.typed_data() + o, cc.typed_data() + o, U, W,
               q[0], q[1], q[2], q[3], q[4], q[5], q[6], sums, &n);
      const double v1 = V[h], v2 = v1 * v1;
      for (int i = 0; i < 6; ++i)
        for (int k = 0; k < 3; ++k) {
          const double s = sums[3 * i + k];
          tot[i][k][0] += s;
          tot[i][k][1] += s * v1;
          tot[i][k][2] += s * v2;
        }
    }
    for (int i = 0; i < 6; ++i)
      for (int k = 0; k < 3; ++k)
        for (int l = 0; l < 3; ++l) S[((f * 6 + i) * 3 + k) * 3 + l] = static_cast<float>(tot[i][k][l]);
    N[f] = static_cast<int32_t>(n);
  }
  return ffi::Error::Success();
}

// Umeyama moments.  Inputs src, dst [B, N, 3], w [B, N], centres [B, 6] = (cx, cy).  Outputs
// T [B, 18] = (W, sum w x', sum w y', sum w y' x'^T (row-major), sum w |x'|^2, sum w |y'|^2)
// with x' = x - cx, y' = y - cy, and the count n [B].  Blocks of 2048 points, added in double.
static ffi::Error UmeyamaMomentsImpl(ffi::Buffer<ffi::F32> src, ffi::Buffer<ffi::F32> dst,
                                     ffi::Buffer<ffi::F32> wts, ffi::Buffer<ffi::F32> centres,
                                     ffi::ResultBuffer<ffi::F32> out, ffi::ResultBuffer<ffi::S32> count) {
  auto dims = wts.dimensions();
  const int64_t N = dims.size() ? dims[dims.size() - 1] : 1;
  const int64_t B = N ? wts.element_count() / N : 0;
  constexpr int64_t BLOCK = 2048;
  float* T = out->typed_data();
  int32_t* Nc = count->typed_data();
  for (int64_t bi = 0; bi < B; ++bi) {
    const float* x = src.typed_data() + 3 * N * bi;
    const float* y = dst.typed_data() + 3 * N * bi;
    const float* w = wts.typed_data() + N * bi;
    const float* c = centres.typed_data() + 6 * bi;
    double tot[18] = {};
    int64_t n = 0;
    for (int64_t p0 = 0; p0 < N; p0 += BLOCK) PointBlock(x, y, w, c, p0, (p0 + BLOCK < N) ? p0 + BLOCK : N, tot, &n);
    for (int t = 0; t < 18; ++t) T[18 * bi + t] = static_cast<float>(tot[t]);
    Nc[bi] = static_cast<int32_t>(n);
  }
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(PixelMoments, PixelMomentsImpl,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Ret<ffi::Buffer<ffi::F32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>());

XLA_FFI_DEFINE_HANDLER_SYMBOL(UmeyamaMoments, UmeyamaMomentsImpl,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Ret<ffi::Buffer<ffi::F32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>());

// Python module: handlers() -> {target name: PyCapsule} for jax.ffi.register_ffi_target.
static PyObject* handlers(PyObject*, PyObject*) {
  PyObject* d = PyDict_New();
  if (!d) return nullptr;
  const struct { const char* name; void* fn; } targets[] = {
      {"swiftjax_pixel_moments", reinterpret_cast<void*>(PixelMoments)},
      {"swiftjax_umeyama_moments", reinterpret_cast<void*>(UmeyamaMoments)},
  };
  for (const auto& t : targets) {
    PyObject* c = PyCapsule_New(t.fn, nullptr, nullptr);
    if (!c || PyDict_SetItemString(d, t.name, c) < 0) {
      Py_XDECREF(c);
      Py_DECREF(d);
      return nullptr;
    }
    Py_DECREF(c);
  }
  return d;
}

static PyMethodDef methods[] = {
    {"handlers", handlers, METH_NOARGS, "{FFI target name: PyCapsule} of the alignment kernels."},
    {nullptr, nullptr, 0, nullptr}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_ffi_kernels",
                                    "Fused CPU kernels of swiftjax.align (XLA FFI handlers).", -1, methods};

PyMODINIT_FUNC PyInit__ffi_kernels(void) { return PyModule_Create(&module); }
