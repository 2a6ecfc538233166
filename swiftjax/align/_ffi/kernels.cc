// Fused CPU kernels of swiftjax.align, called through jax.ffi (XLA's typed FFI).
//
// XLA:CPU emits a multi-output reduction as a scalar loop; these kernels do the same
// one-pass accumulation with 8 or 16 independent float32 lanes (each lane sums its own
// sequence, so the compiler vectorises it without fast-math), then add the lane and block
// partials in double, on the calling thread and XLA's intra-op thread pool (ParallelFor).
// Built at install (pyproject.toml's [[tool.setuptools.ext-modules]], optional: without a
// C++ compiler the package uses its pure-JAX formulation, swiftjax/align/_kernels.py).
//
// * swiftjax_pixel_moments: per-frame pixel moments of a chunk-pair overlap, the layout of
//   swiftjax.align.chunk_pair._pixel_moments.
// * swiftjax_umeyama_moments: the 18 centred weighted sums and the count of a (batched)
//   Umeyama problem, the layout of swiftjax.align.umeyama._moment_terms.
#include <Python.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <condition_variable>
#include <cstdint>
#include <cstring>
#include <memory>
#include <mutex>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;


namespace {

// The loops three times: for AVX-512 (16 lanes, 32 vector registers) and AVX2 + FMA (8
// lanes), chosen at run time by what the CPU has, and for the baseline instruction set (8
// lanes in whatever vectors it has), so one build runs on any x86-64 (elsewhere, baseline).
#if defined(__x86_64__) && defined(__GNUC__)
#define SWIFTJAX_X86_DISPATCH 1
#pragma GCC push_options
#pragma GCC target("avx512f,avx512dq,avx512vl,avx2,fma")
#define SWIFTJAX_LANES 16
namespace avx512 {
#include "kernels_loops.inc"
}  // namespace avx512
#undef SWIFTJAX_LANES
#pragma GCC pop_options
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

// The instruction set the kernels run with: the best the CPU has, or the one set_isa chose
// (tests and benchmarks compare them on one machine).
enum Isa { kBase = 0, kAvx2 = 1, kAvx512 = 2 };
static const char* const kIsaNames[] = {"base", "avx2", "avx512"};

static Isa BestIsa() {
#ifdef SWIFTJAX_X86_DISPATCH
  __builtin_cpu_init();  // this may run from a static initialiser, before libgcc's own
  if (__builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512dq") &&
      __builtin_cpu_supports("avx512vl"))
    return kAvx512;
  if (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma")) return kAvx2;
#endif
  return kBase;
}

static std::atomic<int> g_isa{BestIsa()};

#ifdef SWIFTJAX_X86_DISPATCH
#define SWIFTJAX_DISPATCH(fn, ...)                                    \
  switch (g_isa.load(std::memory_order_relaxed)) {                  \
    case kAvx512: return avx512::fn(__VA_ARGS__);                   \
    case kAvx2: return avx2::fn(__VA_ARGS__);                       \
    default: return base::fn(__VA_ARGS__);                          \
  }
#else
#define SWIFTJAX_DISPATCH(fn, ...) return base::fn(__VA_ARGS__);
#endif

static void PixelRow(const float* Dp, const float* Dc, const float* Cp, const float* Cc, const float* U1,
                     const float* U2, int64_t W, float rp, float rc, float ep, float ec, float tp, float tc,
                     float lam, float* sums, int64_t* count) {
  SWIFTJAX_DISPATCH(PixelRow, Dp, Dc, Cp, Cc, U1, U2, W, rp, rc, ep, ec, tp, tc, lam, sums, count)
}

static void PointBlock(const float* x, const float* y, const float* w, const float* c, int64_t p0, int64_t p1,
                       double* tot, int64_t* count) {
  SWIFTJAX_DISPATCH(PointBlock, x, y, w, c, p0, p1, tot, count)
}

static double RowSum(const float* C, int64_t W, bool finite_only, int64_t* cnt) {
  SWIFTJAX_DISPATCH(RowSum, C, W, finite_only, cnt)
}

// Mean of the finite values of one [H, W] image (NaN if none): one plain pass, and a second
// that skips non-finite values only when the first sum is not finite (the semantics of
// swiftjax.align.frame_conf_mean).  The frame then sits in cache for the moment pass.
static float FrameMean(const float* C, int64_t H, int64_t W) {
  for (bool finite_only : {false, true}) {
    double s = 0.0;
    int64_t n = 0;
    for (int64_t h = 0; h < H; ++h) s += RowSum(C + h * W, W, finite_only, &n);
    if (std::isfinite(s) || finite_only) return n ? static_cast<float>(s / static_cast<double>(n)) : NAN;
  }
  return NAN;
}

// body(i) for i in [0, n) on the calling thread and XLA's intra-op thread pool.  Items are
// claimed from a shared counter, so the caller never waits for a task that has not started
// (no deadlock when the pool is busy or the caller is one of its threads): it works until
// every item is claimed, then waits only for the items other threads are running.  A task
// that starts after that finds nothing to claim and returns; the shared state outlives it.
// Each item writes its own output slots, so results do not depend on the thread count.
template <typename F>
static void ParallelFor(ffi::ThreadPool& pool, int64_t n, const F& body) {
  const int64_t helpers = std::min<int64_t>(pool.num_threads(), n) - 1;
  if (helpers <= 0) {
    for (int64_t i = 0; i < n; ++i) body(i);
    return;
  }
  struct State {
    std::atomic<int64_t> next{0};
    int64_t done = 0;  // guarded by mu
    std::mutex mu;
    std::condition_variable cv;
  };
  auto state = std::make_shared<State>();
  // Runs items until none is left to claim; body is only touched for a claimed item, and an
  // item can only be claimed while the caller is still inside ParallelFor.
  auto work = [state, n, &body]() {
    int64_t finished = 0;
    for (int64_t i; (i = state->next.fetch_add(1)) < n; ++finished) body(i);
    if (finished) {
      std::lock_guard<std::mutex> lock(state->mu);
      state->done += finished;
      if (state->done == n) state->cv.notify_all();
    }
  };
  for (int64_t t = 0; t < helpers; ++t) pool.Schedule(decltype(work)(work));
  work();
  std::unique_lock<std::mutex> lock(state->mu);
  state->cv.wait(lock, [&] { return state->done == n; });
}

// Pixel moments.  Inputs depth_p, depth_c, conf_p, conf_c [F, H, W]; per-frame parameters
// [F, 6] = (r_p, r_c, e_p, e_c, gamma, lam); u~ [W], v~ [H].  A pixel is reliable when
// |r_p D_p - r_c D_c| < lam, conf_p > gamma mean(conf_p), conf_c > gamma mean(conf_c) (the
// frame's mean over finite confidences, FrameMean) and all four inputs are finite (a frame
// with lam < 0 keeps nothing).  One frame per parallel item.  Outputs S [F, 6, 3, 3] = sum m img u~^k v~^l with
// img in (1, a, b, ab, a^2, b^2), a = r_p D_p - e_p, b = r_c D_c - e_c; the count n [F].
static ffi::Error PixelMomentsImpl(ffi::ThreadPool pool, ffi::Buffer<ffi::F32> dp, ffi::Buffer<ffi::F32> dc,
                                   ffi::Buffer<ffi::F32> cp, ffi::Buffer<ffi::F32> cc,
                                   ffi::Buffer<ffi::F32> frame, ffi::Buffer<ffi::F32> ut,
                                   ffi::Buffer<ffi::F32> vt, ffi::ResultBuffer<ffi::F32> out,
                                   ffi::ResultBuffer<ffi::S32> count) {
  auto dims = dp.dimensions();
  const int64_t W = dims[dims.size() - 1], H = dims[dims.size() - 2];
  const int64_t F = (H * W) ? dp.element_count() / (H * W) : 0;
  const float* P = frame.typed_data();
  const float* V = vt.typed_data();
  float* S = out->typed_data();
  int32_t* N = count->typed_data();
  std::vector<float> U1((W + 15) / 16 * 16, 0.f), U2(U1.size(), 0.f);  // u~, u~^2, zero-padded
  for (int64_t w = 0; w < W; ++w) U1[w] = ut.typed_data()[w], U2[w] = U1[w] * U1[w];
  ParallelFor(pool, F, [&](int64_t f) {  // one frame per item
    const float* q = P + 6 * f;
    const int64_t o0 = f * H * W;
    const float tp = q[4] * FrameMean(cp.typed_data() + o0, H, W), tc = q[4] * FrameMean(cc.typed_data() + o0, H, W);
    double tot[6][3][3] = {};
    int64_t n = 0;
    for (int64_t h = 0; h < H; ++h) {
      const int64_t o = (f * H + h) * W;
      float sums[18];
      PixelRow(dp.typed_data() + o, dc.typed_data() + o, cp.typed_data() + o, cc.typed_data() + o, U1.data(),
               U2.data(), W, q[0], q[1], q[2], q[3], tp, tc, q[5], sums, &n);
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
  });
  return ffi::Error::Success();
}

// Umeyama moments.  Inputs src, dst [B, N, 3], w [B, N], centres [B, 6] = (cx, cy).  Outputs
// T [B, 18] = (W, sum w x', sum w y', sum w y' x'^T (row-major), sum w |x'|^2, sum w |y'|^2)
// with x' = x - cx, y' = y - cy, and the count n [B].  Blocks of 2048 points (the parallel
// items), their partials added in double in block order.
static ffi::Error UmeyamaMomentsImpl(ffi::ThreadPool pool, ffi::Buffer<ffi::F32> src, ffi::Buffer<ffi::F32> dst,
                                     ffi::Buffer<ffi::F32> wts, ffi::Buffer<ffi::F32> centres,
                                     ffi::ResultBuffer<ffi::F32> out, ffi::ResultBuffer<ffi::S32> count) {
  auto dims = wts.dimensions();
  const int64_t N = dims.size() ? dims[dims.size() - 1] : 1;
  const int64_t B = N ? wts.element_count() / N : 0;
  constexpr int64_t BLOCK = 2048;
  float* T = out->typed_data();
  int32_t* Nc = count->typed_data();
  const int64_t blocks = (N + BLOCK - 1) / BLOCK;
  std::vector<double> part(B * blocks * 18, 0.0);
  std::vector<int64_t> part_n(B * blocks, 0);
  ParallelFor(pool, B * blocks, [&](int64_t item) {
    const int64_t bi = item / blocks, p0 = (item % blocks) * BLOCK;
    PointBlock(src.typed_data() + 3 * N * bi, dst.typed_data() + 3 * N * bi, wts.typed_data() + N * bi,
               centres.typed_data() + 6 * bi, p0, std::min(p0 + BLOCK, N), &part[18 * item], &part_n[item]);
  });
  for (int64_t bi = 0; bi < B; ++bi) {
    double tot[18] = {};
    int64_t n = 0;
    for (int64_t k = bi * blocks; k < (bi + 1) * blocks; ++k) {
      for (int t = 0; t < 18; ++t) tot[t] += part[18 * k + t];
      n += part_n[k];
    }
    for (int t = 0; t < 18; ++t) T[18 * bi + t] = static_cast<float>(tot[t]);
    Nc[bi] = static_cast<int32_t>(n);
  }
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(PixelMoments, PixelMomentsImpl,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
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
                                  .Ctx<ffi::ThreadPool>()
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

// isa() -> the instruction set in use; isas() -> those the CPU has; set_isa(name) chooses one.
static PyObject* isa(PyObject*, PyObject*) { return PyUnicode_FromString(kIsaNames[g_isa.load()]); }

static PyObject* set_isa(PyObject*, PyObject* arg) {
  const char* name = PyUnicode_AsUTF8(arg);
  if (!name) return nullptr;
  for (int i = kBase; i <= BestIsa(); ++i)
    if (!std::strcmp(name, kIsaNames[i])) {
      g_isa.store(i);
      Py_RETURN_NONE;
    }
  PyErr_Format(PyExc_ValueError, "isa: %R is not one of this CPU's instruction sets (base .. %s)", arg,
               kIsaNames[BestIsa()]);
  return nullptr;
}

static PyObject* isas(PyObject*, PyObject*) {
  PyObject* out = PyList_New(0);
  for (int i = kBase; out && i <= BestIsa(); ++i) {
    PyObject* name = PyUnicode_FromString(kIsaNames[i]);
    if (!name || PyList_Append(out, name) < 0) Py_CLEAR(out);
    Py_XDECREF(name);
  }
  return out;
}

static PyMethodDef methods[] = {
    {"handlers", handlers, METH_NOARGS, "{FFI target name: PyCapsule} of the alignment kernels."},
    {"isa", isa, METH_NOARGS, "The instruction set the kernels run with: 'avx512', 'avx2' or 'base'."},
    {"isas", isas, METH_NOARGS, "The instruction sets this CPU can run the kernels with, best last."},
    {"set_isa", set_isa, METH_O, "Run the kernels with another instruction set the CPU has (tests, benchmarks)."},
    {nullptr, nullptr, 0, nullptr}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_ffi_kernels",
                                    "Fused CPU kernels of swiftjax.align (XLA FFI handlers).", -1, methods};

PyMODINIT_FUNC PyInit__ffi_kernels(void) { return PyModule_Create(&module); }
