// Mamba's fused CPU operators for ONNX Runtime (domain ai.dssp): the selective scan of one layer, and its
// causal depthwise convolution (CausalConv1d, further down).
//
//   ai.dssp::SelectiveScan(x, dt, B, C, z, A, D, h0) -> (y, h)
//
//   x, dt, z (batch, L, E)   dt before softplus, with dt_proj's bias added
//   B, C     (batch, L, n)
//   A        (E, n)          A = -exp(A_log): a constant the graph folds at load
//   D        (E)
//   h0       (batch, E, n)   the incoming SSM state
//   y        (batch, L, E)   (C_t . h_t + D * x_t) * silu(z_t)
//   h        (batch, E, n)   the state after the last token; (batch, 0, n) with the attribute state_out = 0
//
// with delta_t = softplus(dt_t), h_t = exp(delta_t * A) * h_{t-1} + delta_t * x_t * B_t, per channel e and
// state index k: the arithmetic of dssp_train.model.selective_scan.selective_scan, in one pass over the
// tokens with each channel's state held in registers. The unfused graph does the same work as a chain of
// elementwise ONNX nodes, each reading and writing (batch, L, E, n) tensors.
//
// Channels are split into blocks that run on ONNX Runtime's intra-op threads (KernelContext_ParallelFor).
// Three implementations of the same loops:
//   avx512    16 channels per vector: the SIMD loop of scan_simd.inc for AVX-512F (checked at run time)
//   avx2      8 channels per vector: the same loop for AVX2 + FMA, with the same polynomial exp
//   portable  plain C++ the compiler vectorises for the target (x86-64 without AVX2, aarch64 robot computers)
// The environment variable DSSP_SCAN_PATH=auto|avx512|avx2|portable (default auto: the widest this CPU
// runs) chooses, per session.
//
// Built against ONNX Runtime's C API headers (ORT_API_MANUAL_INIT: the library is not linked to
// libonnxruntime; it takes the API from the runtime that loads it).

#define ORT_API_MANUAL_INIT
#include "onnxruntime_cxx_api.h"
#undef ORT_API_MANUAL_INIT
#include "onnxruntime_lite_custom_op.h"
#include "qgemm.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <tuple>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#if (defined(__x86_64__) || defined(_M_X64)) && defined(__GNUC__) && !defined(__clang__)
#include <immintrin.h>
#define DSSP_HAVE_SIMD_PATHS 1
#endif

namespace {

constexpr const char* kDomain = "ai.dssp";
constexpr int64_t kBlock = 32;  // channels per task: enough tasks for a few threads, enough work per task

// ------------------------------------------------------------------ scalar math (portable path)
// exp by range reduction to [-ln2/2, ln2/2] and a degree-6 polynomial (relative error about 2e-7),
// written without branches so the compiler vectorises the loops that call it.
inline float fast_exp(float x) {
  x = std::min(std::max(x, -87.3f), 88.7f);
  constexpr float kRound = 12582912.0f;  // 1.5 * 2^23: adding and subtracting it rounds to the nearest integer
  const float n = (x * 1.44269504088896341f + kRound) - kRound;
  const float r = x - n * 0.693359375f + n * 2.12194440e-4f;
  float p = 1.9875691500e-4f;
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = p * r * r + r + 1.0f;
  return p * __builtin_bit_cast(float, (static_cast<int32_t>(n) + 127) << 23);
}

inline float softplus(float x) {  // torch.nn.functional.softplus (beta 1, threshold 20)
  return x > 20.0f ? x : std::log1p(std::exp(x));
}

inline float silu(float x) { return x / (1.0f + std::exp(-x)); }

struct Problem {
  const float *x, *dt, *B, *C, *z, *A, *D, *h0;
  float *y, *h;  // h null: the state is not written (state_out 0)
  int64_t batch, L, E, n;
};

// Channels [e0, e1) of batch row b; scratch holds 3 * L * (e1 - e0) floats.
void scan_block_portable(const Problem& p, int64_t b, int64_t e0, int64_t e1, float* scratch) {
  const int64_t L = p.L, E = p.E, n = p.n, w = e1 - e0;
  float* delta = scratch;       // (L, w)
  float* dx = scratch + L * w;  // (L, w) delta * x
  float* gate = dx + L * w;     // (L, w) silu(z)
  for (int64_t t = 0; t < L; ++t) {
    const int64_t row = (b * L + t) * E + e0;
    for (int64_t i = 0; i < w; ++i) {
      const float d = softplus(p.dt[row + i]);
      delta[t * w + i] = d;
      dx[t * w + i] = d * p.x[row + i];
      gate[t * w + i] = silu(p.z[row + i]);
    }
  }
  std::vector<float> h(n);
  for (int64_t i = 0; i < w; ++i) {
    const int64_t e = e0 + i;
    const float* A = p.A + e * n;
    std::memcpy(h.data(), p.h0 + (b * E + e) * n, n * sizeof(float));
    float* hp = h.data();
    for (int64_t t = 0; t < L; ++t) {
      const float d = delta[t * w + i], u = dx[t * w + i];
      const float* Bt = p.B + (b * L + t) * n;
      const float* Ct = p.C + (b * L + t) * n;
      float acc = 0.0f;
#pragma omp simd reduction(+ : acc)
      for (int64_t k = 0; k < n; ++k) {
        const float hk = fast_exp(d * A[k]) * hp[k] + u * Bt[k];
        hp[k] = hk;
        acc += Ct[k] * hk;
      }
      const int64_t at = (b * L + t) * E + e;
      p.y[at] = (acc + p.D[e] * p.x[at]) * gate[t * w + i];
    }
    if (p.h) std::memcpy(p.h + (b * E + e) * n, hp, n * sizeof(float));
  }
}

// ------------------------------------------------------------------ the SIMD paths
// One loop (scan_simd.inc) compiled twice, inside a namespace per instruction set that defines its vector V.
// GCC only: `#pragma GCC target` compiles a region for an instruction set the build's flags do not assume;
// other compilers build the portable path alone.
#ifdef DSSP_HAVE_SIMD_PATHS
#pragma GCC push_options
#pragma GCC target("avx2,fma")
namespace avx2 {
struct V {
  using T = __m256;
  static constexpr int kLanes = 8;
  static T load(const float* p) { return _mm256_load_ps(p); }
  static T loadu(const float* p) { return _mm256_loadu_ps(p); }
  static void store(float* p, T v) { _mm256_store_ps(p, v); }
  static void storeu(float* p, T v) { _mm256_storeu_ps(p, v); }
  static T set1(float v) { return _mm256_set1_ps(v); }
  static T broadcast(const float* p) { return _mm256_broadcast_ss(p); }
  static T mul(T a, T b) { return _mm256_mul_ps(a, b); }
  static T add(T a, T b) { return _mm256_add_ps(a, b); }
  static T sub(T a, T b) { return _mm256_sub_ps(a, b); }
  static T max(T a, T b) { return _mm256_max_ps(a, b); }
  static T fmadd(T a, T b, T c) { return _mm256_fmadd_ps(a, b, c); }
  static T add_exponent(T q, T t) {  // the low bits of t are round(y): shifted into the exponent field they add it
    return _mm256_castsi256_ps(_mm256_add_epi32(_mm256_castps_si256(q), _mm256_slli_epi32(_mm256_castps_si256(t), 23)));
  }
};
#include "scan_simd.inc"
}  // namespace avx2
#pragma GCC pop_options

#pragma GCC push_options
#pragma GCC target("avx512f,avx2,fma")
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"  // GCC 12's avx512fintrin.h (_mm512_undefined_*), not this code
namespace avx512 {
struct V {
  using T = __m512;
  static constexpr int kLanes = 16;
  static T load(const float* p) { return _mm512_load_ps(p); }
  static T loadu(const float* p) { return _mm512_loadu_ps(p); }
  static void store(float* p, T v) { _mm512_store_ps(p, v); }
  static void storeu(float* p, T v) { _mm512_storeu_ps(p, v); }
  static T set1(float v) { return _mm512_set1_ps(v); }
  static T broadcast(const float* p) { return _mm512_set1_ps(*p); }
  static T mul(T a, T b) { return _mm512_mul_ps(a, b); }
  static T add(T a, T b) { return _mm512_add_ps(a, b); }
  static T sub(T a, T b) { return _mm512_sub_ps(a, b); }
  static T max(T a, T b) { return _mm512_max_ps(a, b); }
  static T fmadd(T a, T b, T c) { return _mm512_fmadd_ps(a, b, c); }
  static T add_exponent(T q, T t) {
    return _mm512_castsi512_ps(_mm512_add_epi32(_mm512_castps_si512(q), _mm512_slli_epi32(_mm512_castps_si512(t), 23)));
  }
};
#include "scan_simd.inc"
}  // namespace avx512
#pragma GCC diagnostic pop
#pragma GCC pop_options

bool cpu_has_avx2() {
  __builtin_cpu_init();
  return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
}

bool cpu_has_avx512() { return cpu_has_avx2() && __builtin_cpu_supports("avx512f"); }
#endif

// ------------------------------------------------------------------ the causal depthwise convolution
// y_t = silu(bias + sum_j weight[j] * xe[t + 1 + j]) over xe = [state, x] (W + L steps), new state = the last
// W steps of xe: Mamba's conv branch continuing from its state (zeros at a fresh start). Plain C++: the
// loops over channels vectorise on any target, and the work is small next to the scan.
struct ConvProblem {
  const float *x, *state, *weight, *bias;  // weight (W, E)
  float *y, *new_state;
  int64_t batch, L, E, W;
};

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define CONV_CLONES __attribute__((target_clones("arch=x86-64-v3", "default")))  // an AVX2 + FMA build beside the baseline one
#else
#define CONV_CLONES
#endif

CONV_CLONES void conv_block(const ConvProblem& p, int64_t b, int64_t e0, int64_t e1) {
  const int64_t L = p.L, E = p.E, W = p.W;
  for (int64_t t = 0; t < L; ++t) {
    float* y = p.y + (b * L + t) * E;
    for (int64_t e = e0; e < e1; ++e) y[e] = p.bias ? p.bias[e] : 0.0f;
    for (int64_t j = 0; j < W; ++j) {
      const int64_t i = t + 1 + j;
      const float* w = p.weight + j * E;
      if (i >= W) {
        const float* xi = p.x + (b * L + i - W) * E;
#pragma omp simd
        for (int64_t e = e0; e < e1; ++e) y[e] += w[e] * xi[e];
      } else {
        for (int64_t e = e0; e < e1; ++e) y[e] += w[e] * p.state[(b * E + e) * W + i];
      }
    }
#pragma omp simd
    for (int64_t e = e0; e < e1; ++e) y[e] = y[e] / (1.0f + fast_exp(-y[e]));
  }
  for (int64_t k = 0; k < W; ++k) {  // the new state: the last W steps of [state, x]
    const int64_t i = L + k;
    float* out = p.new_state + b * E * W + k;
    if (i >= W) {
      const float* xi = p.x + (b * L + i - W) * E;
      for (int64_t e = e0; e < e1; ++e) out[e * W] = xi[e];
    } else {
      const float* si = p.state + b * E * W + i;
      for (int64_t e = e0; e < e1; ++e) out[e * W] = si[e * W];
    }
  }
}

// ------------------------------------------------------------------ the operator
enum class Path { kPortable, kAvx2, kAvx512 };

const char* path_name(Path path) {
  return path == Path::kAvx512 ? "avx512" : path == Path::kAvx2 ? "avx2" : "portable";
}

// DSSP_SCAN_PATH: auto (the widest this CPU runs), avx512, avx2 or portable; a path this CPU or build lacks is an error.
Path choose_path() {
  const char* env = std::getenv("DSSP_SCAN_PATH");
  const std::string want = env ? env : "auto";
  if (want != "auto" && want != "avx512" && want != "avx2" && want != "portable")
    ORT_CXX_API_THROW("DSSP_SCAN_PATH=" + want + " is not one of auto, avx512, avx2, portable", ORT_INVALID_ARGUMENT);
  if (want == "portable") return Path::kPortable;
#ifdef DSSP_HAVE_SIMD_PATHS
  const bool avx512 = cpu_has_avx512(), avx2 = cpu_has_avx2();
  if (want == "avx512" && !avx512) ORT_CXX_API_THROW("DSSP_SCAN_PATH=avx512, but this CPU lacks AVX-512; unset it or use avx2 or portable", ORT_FAIL);
  if (want == "avx2" && !avx2) ORT_CXX_API_THROW("DSSP_SCAN_PATH=avx2, but this CPU lacks AVX2 or FMA; unset it or use portable", ORT_FAIL);
  if (want == "avx2") return Path::kAvx2;
  return avx512 ? Path::kAvx512 : avx2 ? Path::kAvx2 : Path::kPortable;
#else
  if (want != "auto") ORT_CXX_API_THROW("DSSP_SCAN_PATH=" + want + ", but this library was built without the SIMD paths (they need x86-64 and GCC); unset it or use portable", ORT_FAIL);
  return Path::kPortable;
#endif
}

struct Task {
  const Problem* problem;
  Path path;
  int64_t blocks_per_row;
};

void run_task(void* data, size_t index) {
  const Task& task = *static_cast<const Task*>(data);
  const Problem& p = *task.problem;
  const int64_t b = static_cast<int64_t>(index) / task.blocks_per_row;
  const int64_t e0 = (static_cast<int64_t>(index) % task.blocks_per_row) * kBlock;
  const int64_t e1 = std::min(e0 + kBlock, p.E);
  // 64-byte aligned (with w a multiple of the lanes the SIMD paths' transposed state and A are too: aligned loads)
  const size_t floats = static_cast<size_t>(3 * p.L * (e1 - e0) + 32 * p.n) + 16;
  std::unique_ptr<float[]> buffer(new float[floats]);
  float* scratch = buffer.get();
  while (reinterpret_cast<uintptr_t>(scratch) % 64) ++scratch;
#ifdef DSSP_HAVE_SIMD_PATHS
  if (task.path == Path::kAvx512 && (e1 - e0) % avx512::V::kLanes == 0) return avx512::scan_block(p, b, e0, e1, scratch);
  if (task.path != Path::kPortable && (e1 - e0) % avx2::V::kLanes == 0) return avx2::scan_block(p, b, e0, e1, scratch);
#endif
  scan_block_portable(p, b, e0, e1, scratch);
}

std::string shape_str(const std::vector<int64_t>& s) {
  std::string out = "(";
  for (size_t i = 0; i < s.size(); ++i) out += (i ? ", " : "") + std::to_string(s[i]);
  return out + ")";
}

void expect_shape(const char* name, const std::vector<int64_t>& got, const std::vector<int64_t>& want) {
  if (got != want)
    ORT_CXX_API_THROW(std::string("SelectiveScan: ") + name + " has shape " + shape_str(got) + ", expected " + shape_str(want), ORT_INVALID_ARGUMENT);
}

// The attribute state_out (int, default 1): 0 on a node whose state output nothing reads (export sets it on
// the denoiser's action-token scans); h is then (batch, 0, n) and the state is never written back.
int64_t state_out_attribute(const OrtKernelInfo* info, int64_t absent = 1) {
  try {
    return Ort::ConstKernelInfo(info).GetAttribute<int64_t>("state_out");
  } catch (const Ort::Exception&) {
    return absent;
  }
}

struct SelectiveScan {
  SelectiveScan(const OrtApi*, const OrtKernelInfo* info) : path(choose_path()), state_out(state_out_attribute(info) != 0) {}

  Ort::Status Compute(OrtKernelContext* context, const Ort::Custom::Tensor<float>& x, const Ort::Custom::Tensor<float>& dt,
                      const Ort::Custom::Tensor<float>& B, const Ort::Custom::Tensor<float>& C,
                      const Ort::Custom::Tensor<float>& z, const Ort::Custom::Tensor<float>& A,
                      const Ort::Custom::Tensor<float>& D, const Ort::Custom::Tensor<float>& h0,
                      Ort::Custom::Tensor<float>& y, Ort::Custom::Tensor<float>& h) {
    const auto xs = x.Shape();
    if (xs.size() != 3) ORT_CXX_API_THROW("SelectiveScan: x must be (batch, L, E), got " + shape_str(xs), ORT_INVALID_ARGUMENT);
    const int64_t batch = xs[0], L = xs[1], E = xs[2];
    const auto as = A.Shape();
    if (as.size() != 2 || as[0] != E) ORT_CXX_API_THROW("SelectiveScan: A must be (E, n) with E = " + std::to_string(E) + ", got " + shape_str(as), ORT_INVALID_ARGUMENT);
    const int64_t n = as[1];
    expect_shape("dt", dt.Shape(), xs);
    expect_shape("z", z.Shape(), xs);
    expect_shape("B", B.Shape(), {batch, L, n});
    expect_shape("C", C.Shape(), {batch, L, n});
    expect_shape("D", D.Shape(), {E});
    expect_shape("h0", h0.Shape(), {batch, E, n});
    float* h_out = h.Allocate({batch, state_out ? E : 0, n});
    Problem p{x.Data(), dt.Data(), B.Data(), C.Data(), z.Data(), A.Data(), D.Data(), h0.Data(),
              y.Allocate(xs), state_out ? h_out : nullptr, batch, L, E, n};
    if (batch == 0 || E == 0) return Ort::Status{nullptr};
    if (L == 0) {
      if (!state_out) return Ort::Status{nullptr};
      std::memcpy(p.h, p.h0, sizeof(float) * batch * E * n);
      return Ort::Status{nullptr};
    }
    const int64_t blocks = (E + kBlock - 1) / kBlock;
    Task task{&p, path, blocks};
    Ort::KernelContext ctx(context);
    ctx.ParallelFor(run_task, static_cast<size_t>(batch * blocks), 0, &task);
    return Ort::Status{nullptr};
  }

  Path path;
  bool state_out;
};

struct ConvTask {
  const ConvProblem* problem;
  int64_t blocks_per_row;
};

void run_conv_task(void* data, size_t index) {
  const ConvTask& task = *static_cast<const ConvTask*>(data);
  const int64_t b = static_cast<int64_t>(index) / task.blocks_per_row;
  const int64_t e0 = (static_cast<int64_t>(index) % task.blocks_per_row) * 256;
  conv_block(*task.problem, b, e0, std::min(e0 + 256, task.problem->E));
}

// ai.dssp::CausalConv1d(x (batch, L, E), state (batch, E, W), weight (W, E), bias (E)) -> (y (batch, L, E), new_state (batch, E, W))
struct CausalConv1d {
  CausalConv1d(const OrtApi*, const OrtKernelInfo*) {}

  Ort::Status Compute(OrtKernelContext* context, const Ort::Custom::Tensor<float>& x, const Ort::Custom::Tensor<float>& state,
                      const Ort::Custom::Tensor<float>& weight, const Ort::Custom::Tensor<float>& bias,
                      Ort::Custom::Tensor<float>& y, Ort::Custom::Tensor<float>& new_state) {
    const auto xs = x.Shape();
    if (xs.size() != 3) ORT_CXX_API_THROW("CausalConv1d: x must be (batch, L, E), got " + shape_str(xs), ORT_INVALID_ARGUMENT);
    const int64_t batch = xs[0], L = xs[1], E = xs[2];
    const auto ws = weight.Shape();
    if (ws.size() != 2 || ws[1] != E) ORT_CXX_API_THROW("CausalConv1d: weight must be (W, E) with E = " + std::to_string(E) + ", got " + shape_str(ws), ORT_INVALID_ARGUMENT);
    const int64_t W = ws[0];
    expect_shape("state", state.Shape(), {batch, E, W});
    expect_shape("bias", bias.Shape(), {E});
    ConvProblem p{x.Data(), state.Data(), weight.Data(), bias.Data(), y.Allocate(xs), new_state.Allocate({batch, E, W}), batch, L, E, W};
    if (batch == 0 || E == 0) return Ort::Status{nullptr};
    const int64_t blocks = (E + 255) / 256;
    ConvTask task{&p, blocks};
    Ort::KernelContext(context).ParallelFor(run_conv_task, static_cast<size_t>(batch * blocks), 0, &task);
    return Ort::Status{nullptr};
  }
};

// ------------------------------------------------------------------ a whole denoiser block (int8 weights)
// ai.dssp::MambaBlockQ8: one block of the denoiser — on the action tokens for one DDIM step, or on the prefix —
//
//   h = rmsnorm(a) * (1 + scale) + shift                       AdaLN, mod = [shift; scale; gate] (3, d); the
//                                                              prefix's mod is (0, d): h = rmsnorm(a), gate 1
//   x, z = in_proj(h)                                          x, z (rows, E)
//   x = silu(conv(x)) continuing from conv_state
//   dt, B, C = x_proj(x); dt = dt_proj(dt) + dt_bias
//   y = scan(x, dt, B, C, z) from ssm_state                    SelectiveScan's arithmetic
//   a = a + gate * out_proj(y)
//   a = a + fc2(u * silu(g)), [u, g] = fc1(rmsnorm2(a))        the gated MLP, when fc1 has rows
//
// inputs: a (batch, H, d); conv_state (batch, E, W); ssm_state (batch, E, n); mod (3, d); norm_w (d);
//         in_q (2E, d) int8, in_s (2E); conv_w (W, E), conv_b (E); xp_q (R + 2n, E) int8, xp_s (R + 2n);
//         dt_q (E, R) int8, dt_s (E), dt_b (E); A (E, n); D (E); out_q (d, E) int8, out_s (d);
//         norm2_w (d); fc1_q (2h, d) int8, fc1_s (2h); fc2_q (d, h) int8, fc2_s (d) — the MLP's (0,)/(0, 0) without one
// outputs: a (batch, H, d); the mixer's state after the tokens, conv (batch, E, W) and ssm (batch, E, n), with the
// attribute state_out = 1 (the prefix's node; else both (batch, 0, .), never written). Attribute eps: the norms'.
//
// Every product multiplies the rows (batch * H, a dozen) by int8 weights with the activations quantized per row
// (qgemm.h), the weights packed once for this CPU and shared by every node that reads the same initializer (the
// K DDIM steps run each block's weights K times), the output columns split across ONNX Runtime's threads.

namespace q = dssp::qgemm;

// One packed copy of each weight initializer, shared by the nodes that read it: keyed by its address and shape,
// held by the kernels that use it (the map keeps weak references), checked against a fingerprint of its bytes so a
// buffer that a later session happens to place at the same address is packed anew.
struct PackKey {
  const void* data;
  int64_t n, k;
  int path;
  bool operator<(const PackKey& o) const {
    return std::tie(data, n, k, path) < std::tie(o.data, o.n, o.k, o.path);
  }
};

struct PackEntry {
  std::weak_ptr<const q::PackedWeights> packed;
  uint64_t fingerprint;
};

uint64_t fingerprint(const int8_t* w, const float* scale, int64_t n, int64_t k) {
  uint64_t h = 1469598103934665603ull;  // FNV-1a over the scales and 4096 bytes spread across the weights
  auto mix = [&h](const void* p, size_t bytes) {
    const auto* b = static_cast<const unsigned char*>(p);
    for (size_t i = 0; i < bytes; ++i) h = (h ^ b[i]) * 1099511628211ull;
  };
  mix(scale, sizeof(float) * static_cast<size_t>(n));
  const int64_t total = n * k, stride = std::max<int64_t>(1, total / 4096);
  for (int64_t i = 0; i < total; i += stride) mix(w + i, 1);
  return h;
}

std::shared_ptr<const q::PackedWeights> packed_weights(const int8_t* w, const float* scale, int64_t n, int64_t k,
                                                       q::Path path) {
  static std::mutex mutex;
  static std::map<PackKey, PackEntry> cache;
  const PackKey key{w, n, k, static_cast<int>(path)};
  const uint64_t print = fingerprint(w, scale, n, k);
  std::lock_guard<std::mutex> lock(mutex);
  auto it = cache.find(key);
  if (it != cache.end() && it->second.fingerprint == print)
    if (auto held = it->second.packed.lock()) return held;
  auto packed = std::make_shared<const q::PackedWeights>(q::pack_quantized(w, scale, static_cast<int>(n), static_cast<int>(k), path));
  cache[key] = PackEntry{packed, print};
  for (auto e = cache.begin(); e != cache.end();) e = e->second.packed.expired() ? cache.erase(e) : std::next(e);
  return packed;
}

struct MatmulTask {
  const q::QuantizedRows* x;
  const q::PackedWeights* w;
  const float* bias;
  float* y;
  int ldy;
  int columns;  // per task
};

void run_matmul_task(void* data, size_t index) {
  const MatmulTask& t = *static_cast<const MatmulTask*>(data);
  const int begin = static_cast<int>(index) * t.columns;
  q::matmul_range(*t.x, *t.w, t.bias, t.y, t.ldy, begin, std::min(begin + t.columns, t.w->n));
}

constexpr int kColumnsPerTask = 128;  // a multiple of every path's column block

// y (m, w.n) = x (m, k) @ W.T (+ bias), the columns split across the session's threads
void q8_matmul(Ort::KernelContext& ctx, const float* x, int m, int k, const q::PackedWeights& w, const float* bias,
               float* y, q::QuantizedRows& rows) {
  q::quantize_rows(x, m, k, rows, w.path);
  MatmulTask task{&rows, &w, bias, y, w.n, kColumnsPerTask};
  ctx.ParallelFor(run_matmul_task, static_cast<size_t>((w.n + kColumnsPerTask - 1) / kColumnsPerTask), 0, &task);
}

// out (m, d) = rmsnorm(x) * weight (, then * (1 + scale) + shift when scale is given)
void rms_norm(const float* x, int64_t m, int64_t d, const float* weight, float eps, const float* shift,
              const float* scale, float* out) {
  for (int64_t i = 0; i < m; ++i) {
    const float* xi = x + i * d;
    float ss = 0.0f;
    for (int64_t j = 0; j < d; ++j) ss += xi[j] * xi[j];
    const float r = 1.0f / std::sqrt(ss / static_cast<float>(d) + eps);
    float* oi = out + i * d;
    for (int64_t j = 0; j < d; ++j) {
      const float v = xi[j] * r * weight[j];
      oi[j] = scale ? v * (1.0f + scale[j]) + shift[j] : v;
    }
  }
}

float attribute_float(const OrtKernelInfo* info, const char* name, float fallback) {
  try {
    return Ort::ConstKernelInfo(info).GetAttribute<float>(name);
  } catch (const Ort::Exception&) {
    return fallback;
  }
}

// DSSP_QGEMM_PATH: auto (the fastest this CPU runs) or a path name of qgemm.h; one this CPU lacks is an error.
q::Path choose_qgemm_path() {
  std::string problem;
  const q::Path path = q::choose_path(&problem);
  if (!problem.empty()) ORT_CXX_API_THROW(std::string(problem), ORT_FAIL);
  return path;
}

// One int8 matrix input of a node: its rows and scales, packed on first use and held while the node lives. Runs of
// the same session may overlap (ONNX Runtime allows concurrent Run calls): the first use is guarded, and each run
// holds what it got.
struct Weights {
  std::shared_ptr<const q::PackedWeights> get(const Ort::Custom::Tensor<int8_t>& w, const Ort::Custom::Tensor<float>& s,
                                              q::Path path, const char* name) {
    const auto shape = w.Shape();
    if (shape.size() != 2 || s.Shape() != std::vector<int64_t>{shape[0]})
      ORT_CXX_API_THROW(std::string("MambaBlockQ8: ") + name + " must be (n, k) int8 with (n,) scales, got " +
                            shape_str(shape) + " and " + shape_str(s.Shape()), ORT_INVALID_ARGUMENT);
    std::lock_guard<std::mutex> lock(mutex);
    if (!packed || source != w.Data() || packed->n != shape[0] || packed->k != shape[1]) {
      packed = packed_weights(w.Data(), s.Data(), shape[0], shape[1], path);
      source = w.Data();
    }
    return packed;
  }

 private:
  std::mutex mutex;
  std::shared_ptr<const q::PackedWeights> packed;
  const int8_t* source = nullptr;
};

struct MambaBlockQ8 {
  MambaBlockQ8(const OrtApi*, const OrtKernelInfo* info)
      : scan_path(choose_path()), qgemm_path(choose_qgemm_path()), eps(attribute_float(info, "eps", 1e-5f)),
        state_out(state_out_attribute(info, 0) != 0) {}

  Ort::Status Compute(OrtKernelContext* context, const Ort::Custom::Tensor<float>& a,
                      const Ort::Custom::Tensor<float>& conv_state, const Ort::Custom::Tensor<float>& ssm_state,
                      const Ort::Custom::Tensor<float>& mod, const Ort::Custom::Tensor<float>& norm_w,
                      const Ort::Custom::Tensor<int8_t>& in_q, const Ort::Custom::Tensor<float>& in_s,
                      const Ort::Custom::Tensor<float>& conv_w, const Ort::Custom::Tensor<float>& conv_b,
                      const Ort::Custom::Tensor<int8_t>& xp_q, const Ort::Custom::Tensor<float>& xp_s,
                      const Ort::Custom::Tensor<int8_t>& dt_q, const Ort::Custom::Tensor<float>& dt_s,
                      const Ort::Custom::Tensor<float>& dt_b, const Ort::Custom::Tensor<float>& A,
                      const Ort::Custom::Tensor<float>& D, const Ort::Custom::Tensor<int8_t>& out_q,
                      const Ort::Custom::Tensor<float>& out_s, const Ort::Custom::Tensor<float>& norm2_w,
                      const Ort::Custom::Tensor<int8_t>& fc1_q, const Ort::Custom::Tensor<float>& fc1_s,
                      const Ort::Custom::Tensor<int8_t>& fc2_q, const Ort::Custom::Tensor<float>& fc2_s,
                      Ort::Custom::Tensor<float>& out, Ort::Custom::Tensor<float>& conv_out,
                      Ort::Custom::Tensor<float>& ssm_out) {
    const auto as = a.Shape();
    if (as.size() != 3) ORT_CXX_API_THROW("MambaBlockQ8: a must be (batch, H, d), got " + shape_str(as), ORT_INVALID_ARGUMENT);
    const int64_t batch = as[0], L = as[1], d = as[2], m = batch * L;
    const auto ws = conv_w.Shape(), ns = A.Shape();
    if (ws.size() != 2 || ns.size() != 2) ORT_CXX_API_THROW("MambaBlockQ8: conv_w must be (W, E) and A (E, n)", ORT_INVALID_ARGUMENT);
    const int64_t W = ws[0], E = ws[1], n = ns[1];
    expect_shape("conv_state", conv_state.Shape(), {batch, E, W});
    expect_shape("ssm_state", ssm_state.Shape(), {batch, E, n});
    const bool modulated = !mod.Shape().empty() && mod.Shape()[0] != 0;
    expect_shape("mod", mod.Shape(), {modulated ? 3 : 0, d});
    expect_shape("norm_w", norm_w.Shape(), {d});
    expect_shape("A", ns, {E, n});
    Ort::KernelContext ctx(context);
    const auto held_in = in_w.get(in_q, in_s, qgemm_path, "in_proj");
    const q::PackedWeights& w_in = *held_in;
    const auto held_xp = xp_w.get(xp_q, xp_s, qgemm_path, "x_proj");
    const q::PackedWeights& w_xp = *held_xp;
    const auto held_dt = dt_w.get(dt_q, dt_s, qgemm_path, "dt_proj");
    const q::PackedWeights& w_dt = *held_dt;
    const auto held_out = out_w.get(out_q, out_s, qgemm_path, "out_proj");
    const q::PackedWeights& w_out = *held_out;
    const int64_t R = w_dt.k;
    if (w_in.n != 2 * E || w_in.k != d || w_xp.n != R + 2 * n || w_xp.k != E || w_dt.n != E || w_out.n != d || w_out.k != E)
      ORT_CXX_API_THROW("MambaBlockQ8: the projections' shapes do not fit d = " + std::to_string(d) + ", E = " +
                            std::to_string(E) + ", n = " + std::to_string(n), ORT_INVALID_ARGUMENT);
    const bool mlp = fc1_q.NumberOfElement() > 0;
    float* result = out.Allocate(as);
    float* conv_after = conv_out.Allocate({batch, state_out ? E : 0, W});
    float* ssm_after = ssm_out.Allocate({batch, state_out ? E : 0, n});
    if (m == 0) return Ort::Status{nullptr};
    q::QuantizedRows rows;  // this run's quantized activations
    const float* shift = modulated ? mod.Data() : nullptr;
    const float *scale = modulated ? shift + d : nullptr, *gate = modulated ? shift + 2 * d : nullptr;

    std::vector<float> h(m * d), xz(m * 2 * E), x(m * E), z(m * E), xc(m * E), state_after(state_out ? 0 : batch * E * W),
        dbc(m * w_xp.n), dt_in(m * R), dt(m * E), Bm(m * n), Cm(m * n), y(m * E), o(m * d);
    rms_norm(a.Data(), m, d, norm_w.Data(), eps, shift, scale, h.data());
    q8_matmul(ctx, h.data(), m, d, w_in, nullptr, xz.data(), rows);
    for (int64_t i = 0; i < m; ++i) {
      std::memcpy(x.data() + i * E, xz.data() + i * 2 * E, sizeof(float) * E);
      std::memcpy(z.data() + i * E, xz.data() + i * 2 * E + E, sizeof(float) * E);
    }
    ConvProblem cp{x.data(), conv_state.Data(), conv_w.Data(), conv_b.Data(), xc.data(),
                   state_out ? conv_after : state_after.data(), batch, L, E, W};
    const int64_t conv_blocks = (E + 255) / 256;
    ConvTask conv_task{&cp, conv_blocks};
    ctx.ParallelFor(run_conv_task, static_cast<size_t>(batch * conv_blocks), 0, &conv_task);
    q8_matmul(ctx, xc.data(), m, E, w_xp, nullptr, dbc.data(), rows);
    for (int64_t i = 0; i < m; ++i) {
      const float* row = dbc.data() + i * w_xp.n;
      std::memcpy(dt_in.data() + i * R, row, sizeof(float) * R);
      std::memcpy(Bm.data() + i * n, row + R, sizeof(float) * n);
      std::memcpy(Cm.data() + i * n, row + R + n, sizeof(float) * n);
    }
    q8_matmul(ctx, dt_in.data(), m, R, w_dt, dt_b.Data(), dt.data(), rows);
    Problem sp{xc.data(), dt.data(), Bm.data(), Cm.data(), z.data(), A.Data(), D.Data(), ssm_state.Data(),
               y.data(), state_out ? ssm_after : nullptr, batch, L, E, n};
    const int64_t scan_blocks = (E + kBlock - 1) / kBlock;
    Task scan_task{&sp, scan_path, scan_blocks};
    ctx.ParallelFor(run_task, static_cast<size_t>(batch * scan_blocks), 0, &scan_task);
    q8_matmul(ctx, y.data(), m, E, w_out, nullptr, o.data(), rows);
    const float* a_in = a.Data();
    for (int64_t i = 0; i < m; ++i)
      for (int64_t j = 0; j < d; ++j) result[i * d + j] = a_in[i * d + j] + (gate ? gate[j] : 1.0f) * o[i * d + j];
    if (!mlp) return Ort::Status{nullptr};

    expect_shape("norm2_w", norm2_w.Shape(), {d});
    const auto held_fc1 = fc1_w.get(fc1_q, fc1_s, qgemm_path, "fc1");
    const q::PackedWeights& w_fc1 = *held_fc1;
    const auto held_fc2 = fc2_w.get(fc2_q, fc2_s, qgemm_path, "fc2");
    const q::PackedWeights& w_fc2 = *held_fc2;
    const int64_t hidden = w_fc2.k;
    if (w_fc1.n != 2 * hidden || w_fc1.k != d || w_fc2.n != d)
      ORT_CXX_API_THROW("MambaBlockQ8: fc1 must be (2h, d) and fc2 (d, h) with d = " + std::to_string(d), ORT_INVALID_ARGUMENT);
    std::vector<float> g(m * d), u(m * 2 * hidden), v(m * hidden);
    rms_norm(result, m, d, norm2_w.Data(), eps, nullptr, nullptr, g.data());
    q8_matmul(ctx, g.data(), m, d, w_fc1, nullptr, u.data(), rows);
    for (int64_t i = 0; i < m; ++i)
      for (int64_t j = 0; j < hidden; ++j) {
        const float gj = u[i * 2 * hidden + hidden + j];
        v[i * hidden + j] = u[i * 2 * hidden + j] * (gj / (1.0f + fast_exp(-gj)));
      }
    q8_matmul(ctx, v.data(), m, hidden, w_fc2, nullptr, o.data(), rows);
    for (int64_t i = 0; i < m * d; ++i) result[i] += o[i];
    return Ort::Status{nullptr};
  }

  Path scan_path;
  q::Path qgemm_path;
  float eps;
  bool state_out;
  Weights in_w, xp_w, dt_w, out_w, fc1_w, fc2_w;
};

}  // namespace

// The library's entry point, called by SessionOptions.register_custom_ops_library.
extern "C" __attribute__((visibility("default"))) OrtStatus* ORT_API_CALL RegisterCustomOps(OrtSessionOptions* options,
                                                                                           const OrtApiBase* api_base) {
  const OrtApi* api = api_base->GetApi(ORT_API_VERSION);
  if (api == nullptr) return nullptr;  // an older runtime: the session fails to load the graph, the caller falls back
  Ort::InitApi(api);
  static std::unique_ptr<Ort::Custom::OrtLiteCustomOp> scan_op, conv_op, block_op;
  static Ort::CustomOpDomain domain{nullptr};
  static std::once_flag once;
  try {
    std::call_once(once, [] {
      scan_op.reset(Ort::Custom::CreateLiteCustomOp<SelectiveScan>("SelectiveScan", "CPUExecutionProvider"));
      conv_op.reset(Ort::Custom::CreateLiteCustomOp<CausalConv1d>("CausalConv1d", "CPUExecutionProvider"));
      block_op.reset(Ort::Custom::CreateLiteCustomOp<MambaBlockQ8>("MambaBlockQ8", "CPUExecutionProvider"));
      domain = Ort::CustomOpDomain(kDomain);
      domain.Add(scan_op.get());
      domain.Add(conv_op.get());
      domain.Add(block_op.get());
    });
    Ort::UnownedSessionOptions(options).Add(domain);
  } catch (const std::exception& e) {
    return api->CreateStatus(ORT_FAIL, e.what());
  }
  return nullptr;
}

// Which implementation a session would use on this CPU now ("avx512", "avx2" or "portable"), for start-up logs.
// The implementation DSSP_SCAN_PATH selects here, or "invalid: " and why it cannot run (for the loader's message).
extern "C" __attribute__((visibility("default"))) const char* DsspScanPath() {
  static thread_local std::string answer;
  try {
    answer = path_name(choose_path());
  } catch (const std::exception& exc) {
    answer = std::string("invalid: ") + exc.what();
  } catch (...) {
    answer = "invalid: DSSP_SCAN_PATH cannot be used here";
  }
  return answer.c_str();
}
