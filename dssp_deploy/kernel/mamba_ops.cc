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
//   h        (batch, E, n)   the state after the last token
//
// with delta_t = softplus(dt_t), h_t = exp(delta_t * A) * h_{t-1} + delta_t * x_t * B_t, per channel e and
// state index k: the arithmetic of dssp_train.model.selective_scan.selective_scan, in one pass over the
// tokens with each channel's state held in registers. The unfused graph does the same work as a chain of
// elementwise ONNX nodes, each reading and writing (batch, L, E, n) tensors.
//
// Channels are split into blocks that run on ONNX Runtime's intra-op threads (KernelContext_ParallelFor).
// Two implementations of the same loops:
//   avx2      AVX2 + FMA intrinsics with a polynomial exp (x86-64 CPUs that have both, checked at run time)
//   portable  plain C++ the compiler vectorises for the target (x86-64 without AVX2, aarch64 robot computers)
// The environment variable DSSP_SCAN_PATH=portable|avx2|auto (default auto) chooses, per session.
//
// Built against ONNX Runtime's C API headers (ORT_API_MANUAL_INIT: the library is not linked to
// libonnxruntime; it takes the API from the runtime that loads it).

#define ORT_API_MANUAL_INIT
#include "onnxruntime_cxx_api.h"
#undef ORT_API_MANUAL_INIT
#include "onnxruntime_lite_custom_op.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#if defined(__x86_64__) || defined(_M_X64)
#include <immintrin.h>
#define DSSP_HAVE_AVX2_PATH 1
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
  float *y, *h;
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
    std::memcpy(p.h + (b * E + e) * n, hp, n * sizeof(float));
  }
}

// ------------------------------------------------------------------ AVX2 + FMA path
#ifdef DSSP_HAVE_AVX2_PATH
#define AVX2_FN __attribute__((target("avx2,fma")))

AVX2_FN inline __m256 exp8(__m256 x) {
  x = _mm256_min_ps(_mm256_max_ps(x, _mm256_set1_ps(-87.3f)), _mm256_set1_ps(88.7f));
  const __m256 n = _mm256_round_ps(_mm256_mul_ps(x, _mm256_set1_ps(1.44269504088896341f)),
                                   _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  __m256 r = _mm256_fnmadd_ps(n, _mm256_set1_ps(0.693359375f), x);
  r = _mm256_fmadd_ps(n, _mm256_set1_ps(2.12194440e-4f), r);
  __m256 q = _mm256_set1_ps(1.9875691500e-4f);
  q = _mm256_fmadd_ps(q, r, _mm256_set1_ps(1.3981999507e-3f));
  q = _mm256_fmadd_ps(q, r, _mm256_set1_ps(8.3334519073e-3f));
  q = _mm256_fmadd_ps(q, r, _mm256_set1_ps(4.1665795894e-2f));
  q = _mm256_fmadd_ps(q, r, _mm256_set1_ps(1.6666665459e-1f));
  q = _mm256_fmadd_ps(q, r, _mm256_set1_ps(5.0000001201e-1f));
  q = _mm256_fmadd_ps(_mm256_mul_ps(q, r), r, _mm256_add_ps(r, _mm256_set1_ps(1.0f)));
  const __m256i bits = _mm256_slli_epi32(_mm256_add_epi32(_mm256_cvtps_epi32(n), _mm256_set1_epi32(127)), 23);
  return _mm256_mul_ps(q, _mm256_castsi256_ps(bits));
}

// log(1 + v) for v in [0, 1]: log(w) * v / (w - 1) with w = 1 + v rounded (exact where w - 1 == v is not),
// log by frexp and the Cephes logf polynomial.
AVX2_FN inline __m256 log1p8_unit(__m256 v) {
  const __m256 one = _mm256_set1_ps(1.0f);
  const __m256 w = _mm256_add_ps(one, v);
  // w in [1, 2]: w = m * 2^e with m in [sqrt(0.5), sqrt(2))
  __m256i wi = _mm256_castps_si256(w);
  __m256 e = _mm256_cvtepi32_ps(_mm256_sub_epi32(_mm256_srli_epi32(wi, 23), _mm256_set1_epi32(127)));
  __m256 m = _mm256_castsi256_ps(_mm256_or_si256(_mm256_and_si256(wi, _mm256_set1_epi32(0x007fffff)),
                                                 _mm256_set1_epi32(0x3f800000)));  // [1, 2)
  const __m256 big = _mm256_cmp_ps(m, _mm256_set1_ps(1.41421356f), _CMP_GT_OQ);
  m = _mm256_blendv_ps(m, _mm256_mul_ps(m, _mm256_set1_ps(0.5f)), big);
  e = _mm256_add_ps(e, _mm256_and_ps(big, one));
  const __m256 f = _mm256_sub_ps(m, one);
  __m256 q = _mm256_set1_ps(7.0376836292e-2f);
  q = _mm256_fmadd_ps(q, f, _mm256_set1_ps(-1.1514610310e-1f));
  q = _mm256_fmadd_ps(q, f, _mm256_set1_ps(1.1676998740e-1f));
  q = _mm256_fmadd_ps(q, f, _mm256_set1_ps(-1.2420140846e-1f));
  q = _mm256_fmadd_ps(q, f, _mm256_set1_ps(1.4249322787e-1f));
  q = _mm256_fmadd_ps(q, f, _mm256_set1_ps(-1.6668057665e-1f));
  q = _mm256_fmadd_ps(q, f, _mm256_set1_ps(2.0000714765e-1f));
  q = _mm256_fmadd_ps(q, f, _mm256_set1_ps(-2.4999993993e-1f));
  q = _mm256_fmadd_ps(q, f, _mm256_set1_ps(3.3333331174e-1f));
  const __m256 f2 = _mm256_mul_ps(f, f);
  __m256 lg = _mm256_mul_ps(_mm256_mul_ps(q, f), f2);
  lg = _mm256_fnmadd_ps(f2, _mm256_set1_ps(0.5f), lg);
  lg = _mm256_add_ps(lg, f);
  lg = _mm256_fmadd_ps(e, _mm256_set1_ps(0.693147180559945f), lg);
  const __m256 wm1 = _mm256_sub_ps(w, one);
  const __m256 exact = _mm256_cmp_ps(wm1, _mm256_setzero_ps(), _CMP_EQ_OQ);  // v below half an ulp of 1
  const __m256 corrected = _mm256_mul_ps(lg, _mm256_div_ps(v, _mm256_blendv_ps(wm1, one, exact)));
  return _mm256_blendv_ps(corrected, v, exact);
}

AVX2_FN inline __m256 softplus8(__m256 x) {  // max(x, 0) + log1p(exp(-|x|)); x beyond 20 is x itself
  const __m256 absx = _mm256_andnot_ps(_mm256_set1_ps(-0.0f), x);
  const __m256 sp = _mm256_add_ps(_mm256_max_ps(x, _mm256_setzero_ps()), log1p8_unit(exp8(_mm256_sub_ps(_mm256_setzero_ps(), absx))));
  return _mm256_blendv_ps(sp, x, _mm256_cmp_ps(x, _mm256_set1_ps(20.0f), _CMP_GT_OQ));
}

AVX2_FN inline __m256 silu8(__m256 x) {
  const __m256 one = _mm256_set1_ps(1.0f);
  return _mm256_div_ps(x, _mm256_add_ps(one, exp8(_mm256_sub_ps(_mm256_setzero_ps(), x))));
}

AVX2_FN inline float hsum8(__m256 v) {
  const __m128 s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
  const __m128 t = _mm_add_ps(s, _mm_movehl_ps(s, s));
  return _mm_cvtss_f32(_mm_add_ss(t, _mm_shuffle_ps(t, t, 1)));
}

// 2^y for y <= 0 (clamped at -125): y = m + f with m an integer, f in [-0.5, 0.5]; 2^f by a degree-5
// polynomial fitted to the relative error (at most 1.8e-7 in float32), 2^m added to its exponent bits
// (an integer add instead of a multiply: the multiply ports are what the scan is short of).
AVX2_FN inline __m256 exp2_8(__m256 y) {
  const __m256 magic = _mm256_set1_ps(12582912.0f);  // 1.5 * 2^23: t = y + magic holds round(y) in its low bits
  y = _mm256_max_ps(y, _mm256_set1_ps(-125.0f));
  const __m256 t = _mm256_add_ps(y, magic);
  const __m256 f = _mm256_sub_ps(y, _mm256_sub_ps(t, magic));
  __m256 q = _mm256_set1_ps(1.3218674575909972e-3f);
  q = _mm256_fmadd_ps(q, f, _mm256_set1_ps(9.671702980995178e-3f));
  q = _mm256_fmadd_ps(q, f, _mm256_set1_ps(5.550893023610115e-2f));
  q = _mm256_fmadd_ps(q, f, _mm256_set1_ps(2.4022237956523895e-1f));
  q = _mm256_fmadd_ps(q, f, _mm256_set1_ps(6.931468844413757e-1f));
  q = _mm256_fmadd_ps(q, f, _mm256_set1_ps(1.0f));
  // the low bits of t are round(y) in two's complement; shifted into the exponent field they add round(y)
  return _mm256_castsi256_ps(_mm256_add_epi32(_mm256_castps_si256(q), _mm256_slli_epi32(_mm256_castps_si256(t), 23)));
}

// dst[j * dst_stride + c] = src[c * stride + j] * scale for an 8 x 8 block.
AVX2_FN inline void transpose8x8(const float* src, int64_t stride, float* dst, int64_t dst_stride, __m256 scale) {
  __m256 r[8], t[8];
  for (int c = 0; c < 8; ++c) r[c] = _mm256_mul_ps(_mm256_loadu_ps(src + c * stride), scale);
  for (int c = 0; c < 8; c += 2) {
    t[c] = _mm256_unpacklo_ps(r[c], r[c + 1]);
    t[c + 1] = _mm256_unpackhi_ps(r[c], r[c + 1]);
  }
  for (int c = 0; c < 8; c += 4) {
    r[c] = _mm256_shuffle_ps(t[c], t[c + 2], _MM_SHUFFLE(1, 0, 1, 0));
    r[c + 1] = _mm256_shuffle_ps(t[c], t[c + 2], _MM_SHUFFLE(3, 2, 3, 2));
    r[c + 2] = _mm256_shuffle_ps(t[c + 1], t[c + 3], _MM_SHUFFLE(1, 0, 1, 0));
    r[c + 3] = _mm256_shuffle_ps(t[c + 1], t[c + 3], _MM_SHUFFLE(3, 2, 3, 2));
  }
  for (int j = 0; j < 4; ++j) {
    _mm256_storeu_ps(dst + j * dst_stride, _mm256_permute2f128_ps(r[j], r[j + 4], 0x20));
    _mm256_storeu_ps(dst + (j + 4) * dst_stride, _mm256_permute2f128_ps(r[j], r[j + 4], 0x31));
  }
}

// rows (8, n) with row stride `stride` → (n, 8) times scale, 8 x 8 blocks by AVX and the rest scalar.
AVX2_FN inline void gather8(const float* src, int64_t stride, int64_t n, float* dst, float scale) {
  int64_t k = 0;
  for (; k + 8 <= n; k += 8) transpose8x8(src + k, stride, dst + k * 8, 8, _mm256_set1_ps(scale));
  for (; k < n; ++k)
    for (int c = 0; c < 8; ++c) dst[k * 8 + c] = src[c * stride + k] * scale;
}

// Channels [e0, e1) of batch row b, e1 - e0 a multiple of 8: eight channels per vector, the state of a
// group of eight held transposed (n rows of 8) in scratch that stays in L1, A scaled by log2(e) once.
// scratch holds 3 * L * w + 2 * 8 * n floats.
AVX2_FN void scan_block_avx2(const Problem& p, int64_t b, int64_t e0, int64_t e1, float* scratch) {
  const int64_t L = p.L, E = p.E, n = p.n, w = e1 - e0;
  float* delta = scratch;
  float* dx = scratch + L * w;
  float* gate = dx + L * w;
  float* At = gate + L * w;  // (n, 8) A * log2(e) of the group
  float* ht = At + 8 * n;    // (n, 8) the group's state
  for (int64_t t = 0; t < L; ++t) {
    const int64_t row = (b * L + t) * E + e0;
    for (int64_t i = 0; i < w; i += 8) {
      const __m256 d = softplus8(_mm256_loadu_ps(p.dt + row + i));
      _mm256_storeu_ps(delta + t * w + i, d);
      _mm256_storeu_ps(dx + t * w + i, _mm256_mul_ps(d, _mm256_loadu_ps(p.x + row + i)));
      _mm256_storeu_ps(gate + t * w + i, silu8(_mm256_loadu_ps(p.z + row + i)));
    }
  }
  for (int64_t g = 0; g < w; g += 8) {
    const int64_t e = e0 + g;
    gather8(p.A + e * n, n, n, At, 1.44269504088896341f);
    gather8(p.h0 + (b * E + e) * n, n, n, ht, 1.0f);
    const __m256 D = _mm256_loadu_ps(p.D + e);
    for (int64_t t = 0; t < L; ++t) {
      const __m256 d = _mm256_loadu_ps(delta + t * w + g), u = _mm256_loadu_ps(dx + t * w + g);
      const float* Bt = p.B + (b * L + t) * n;
      const float* Ct = p.C + (b * L + t) * n;
      __m256 acc[4] = {_mm256_setzero_ps(), _mm256_setzero_ps(), _mm256_setzero_ps(), _mm256_setzero_ps()};
      int64_t k = 0;
      for (; k + 4 <= n; k += 4) {  // four independent state rows in flight
        for (int64_t j = 0; j < 4; ++j) {
          const __m256 a = exp2_8(_mm256_mul_ps(d, _mm256_load_ps(At + 8 * (k + j))));
          const __m256 h = _mm256_fmadd_ps(a, _mm256_load_ps(ht + 8 * (k + j)), _mm256_mul_ps(u, _mm256_broadcast_ss(Bt + k + j)));
          _mm256_store_ps(ht + 8 * (k + j), h);
          acc[j] = _mm256_fmadd_ps(_mm256_broadcast_ss(Ct + k + j), h, acc[j]);
        }
      }
      for (; k < n; ++k) {
        const __m256 a = exp2_8(_mm256_mul_ps(d, _mm256_load_ps(At + 8 * k)));
        const __m256 h = _mm256_fmadd_ps(a, _mm256_load_ps(ht + 8 * k), _mm256_mul_ps(u, _mm256_broadcast_ss(Bt + k)));
        _mm256_store_ps(ht + 8 * k, h);
        acc[0] = _mm256_fmadd_ps(_mm256_broadcast_ss(Ct + k), h, acc[0]);
      }
      const __m256 sum = _mm256_add_ps(_mm256_add_ps(acc[0], acc[1]), _mm256_add_ps(acc[2], acc[3]));
      const int64_t at = (b * L + t) * E + e;
      const __m256 y = _mm256_fmadd_ps(D, _mm256_loadu_ps(p.x + at), sum);
      _mm256_storeu_ps(p.y + at, _mm256_mul_ps(y, _mm256_loadu_ps(gate + t * w + g)));
    }
    // (n, 8) back to rows (8, n): the same transpose with the roles swapped, in 8 x 8 blocks
    int64_t k = 0;
    for (; k + 8 <= n; k += 8) transpose8x8(ht + k * 8, 8, p.h + (b * E + e) * n + k, n, _mm256_set1_ps(1.0f));
    for (; k < n; ++k)
      for (int64_t c = 0; c < 8; ++c) p.h[(b * E + e + c) * n + k] = ht[k * 8 + c];
  }
}

bool cpu_has_avx2() {
  __builtin_cpu_init();
  return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
}
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
enum class Path { kPortable, kAvx2 };

Path choose_path() {
  const char* env = std::getenv("DSSP_SCAN_PATH");
  const std::string want = env ? env : "auto";
#ifdef DSSP_HAVE_AVX2_PATH
  if (want == "portable") return Path::kPortable;
  if (cpu_has_avx2()) return Path::kAvx2;
  if (want == "avx2") ORT_CXX_API_THROW("DSSP_SCAN_PATH=avx2, but this CPU lacks AVX2 or FMA; unset it or use portable", ORT_FAIL);
  return Path::kPortable;
#else
  if (want == "avx2") ORT_CXX_API_THROW("DSSP_SCAN_PATH=avx2, but this library was built for a CPU without AVX2; unset it", ORT_FAIL);
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
  // 32-byte aligned (with w a multiple of 8 the AVX2 path's transposed state and A are too: aligned loads)
  const size_t floats = static_cast<size_t>(3 * p.L * (e1 - e0) + 16 * p.n) + 8;
  std::unique_ptr<float[]> buffer(new float[floats]);
  float* scratch = buffer.get();
  while (reinterpret_cast<uintptr_t>(scratch) % 32) ++scratch;
#ifdef DSSP_HAVE_AVX2_PATH
  if (task.path == Path::kAvx2 && (e1 - e0) % 8 == 0) {
    scan_block_avx2(p, b, e0, e1, scratch);
    return;
  }
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

struct SelectiveScan {
  SelectiveScan(const OrtApi*, const OrtKernelInfo*) : path(choose_path()) {}

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
    Problem p{x.Data(), dt.Data(), B.Data(), C.Data(), z.Data(), A.Data(), D.Data(), h0.Data(),
              y.Allocate(xs), h.Allocate({batch, E, n}), batch, L, E, n};
    if (batch == 0 || E == 0) return Ort::Status{nullptr};
    if (L == 0) {
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

}  // namespace

// The library's entry point, called by SessionOptions.register_custom_ops_library.
extern "C" __attribute__((visibility("default"))) OrtStatus* ORT_API_CALL RegisterCustomOps(OrtSessionOptions* options,
                                                                                           const OrtApiBase* api_base) {
  const OrtApi* api = api_base->GetApi(ORT_API_VERSION);
  if (api == nullptr) return nullptr;  // an older runtime: the session fails to load the graph, the caller falls back
  Ort::InitApi(api);
  static std::unique_ptr<Ort::Custom::OrtLiteCustomOp> scan_op, conv_op;
  static Ort::CustomOpDomain domain{nullptr};
  static std::once_flag once;
  try {
    std::call_once(once, [] {
      scan_op.reset(Ort::Custom::CreateLiteCustomOp<SelectiveScan>("SelectiveScan", "CPUExecutionProvider"));
      conv_op.reset(Ort::Custom::CreateLiteCustomOp<CausalConv1d>("CausalConv1d", "CPUExecutionProvider"));
      domain = Ort::CustomOpDomain(kDomain);
      domain.Add(scan_op.get());
      domain.Add(conv_op.get());
    });
    Ort::UnownedSessionOptions(options).Add(domain);
  } catch (const std::exception& e) {
    return api->CreateStatus(ORT_FAIL, e.what());
  }
  return nullptr;
}

// Which implementation a session would use on this CPU now ("avx2" or "portable"), for start-up logs.
extern "C" __attribute__((visibility("default"))) const char* DsspScanPath() {
  try {
    return choose_path() == Path::kAvx2 ? "avx2" : "portable";
  } catch (...) {
    return "invalid";
  }
}
