// The fused arithmetic for the robot's CPU, free of any runtime: the selective scan, the causal depthwise
// convolution, a whole int8 denoiser block, and the point encoder's last LayerNorm with its max over the points.
// mamba_ops.cc binds them to ONNX Runtime as the ai.dssp operators; block_check.cc runs the block alone (its parity on aarch64 under qemu, and its phases' times natively).
// Header-only, C++17; the int8 products are qgemm.h's.
//
// Threads: every parallel part is handed to a ParallelFor(fn, count, data) that calls fn(data, i) once for each
// i < count, on any threads in any order, and returns when all are done (ONNX Runtime's intra-op pool, or a
// loop). Errors: std::invalid_argument for shapes and settings that cannot work, with one line that says why.

#pragma once

#include "qgemm.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#if (defined(__x86_64__) || defined(_M_X64)) && defined(__GNUC__) && !defined(__clang__)
#include <immintrin.h>
#define DSSP_HAVE_SIMD_PATHS 1
#elif defined(__aarch64__) && defined(__ARM_NEON)
#include <arm_neon.h>
#define DSSP_HAVE_NEON_PATH 1
#endif

namespace dssp::mamba {

using ParallelFor = std::function<void(void (*fn)(void*, size_t), size_t count, void* data)>;

constexpr int64_t kBlock = 32;  // scan channels per task: enough tasks for a few threads, enough work per task

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
  const float *x, *dt, *B, *C, *z, *A, *D, *h0;  // h0 null: the state starts from zeros
  float *y, *h;  // h null: the state is not written (state_out 0)
  int64_t batch, L, E, n;
  int64_t h_after = 0;  // h is the state after this many tokens (1..L); 0: after the last (L)
  int64_t z_stride = 0;  // z's row stride (z inside in_proj's output [x, z]: 2E); 0: E

  int64_t h_at() const { return h_after > 0 ? h_after : L; }
  const float* z_row(int64_t row) const { return z + row * (z_stride > 0 ? z_stride : E); }  // row = b * L + t
};

// Channels [e0, e1) of batch row b; scratch holds 3 * L * (e1 - e0) floats.
inline void scan_block_portable(const Problem& p, int64_t b, int64_t e0, int64_t e1, float* scratch) {
  const int64_t L = p.L, E = p.E, n = p.n, w = e1 - e0;
  float* delta = scratch;       // (L, w)
  float* dx = scratch + L * w;  // (L, w) delta * x
  float* gate = dx + L * w;     // (L, w) silu(z)
  for (int64_t t = 0; t < L; ++t) {
    const int64_t row = (b * L + t) * E + e0;
    const float* z = p.z_row(b * L + t) + e0;
    for (int64_t i = 0; i < w; ++i) {
      const float d = softplus(p.dt[row + i]);
      delta[t * w + i] = d;
      dx[t * w + i] = d * p.x[row + i];
      gate[t * w + i] = silu(z[i]);
    }
  }
  std::vector<float> h(n);
  for (int64_t i = 0; i < w; ++i) {
    const int64_t e = e0 + i;
    const float* A = p.A + e * n;
    if (p.h0)
      std::memcpy(h.data(), p.h0 + (b * E + e) * n, n * sizeof(float));
    else
      std::fill(h.begin(), h.end(), 0.0f);
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
      if (p.h && t + 1 == p.h_at()) std::memcpy(p.h + (b * E + e) * n, hp, n * sizeof(float));
    }
  }
}

// ------------------------------------------------------------------ the SIMD paths
// One loop (scan_simd.inc) compiled once per instruction set, inside a namespace that defines its vectors V and P.
// x86-64 (AVX2, AVX-512): GCC only, `#pragma GCC target` compiles a region for an instruction set the build's
// flags do not assume; other compilers build the portable path alone there. aarch64: NEON is part of the
// architecture, so any aarch64 build has the neon path.
#ifdef DSSP_HAVE_SIMD_PATHS
#pragma GCC push_options
#pragma GCC target("avx2,fma")
// The 8-lane AVX vector of both x86 paths' per-token preliminaries and layout changes (scan_simd.inc's P).
struct Avx8 {
  using T = __m256;
  using M = __m256;  // a lane mask: all bits set or all clear
  static constexpr int kLanes = 8;
  static T loadu(const float* p) { return _mm256_loadu_ps(p); }
  static void store(float* p, T v) { _mm256_store_ps(p, v); }
  static void storeu(float* p, T v) { _mm256_storeu_ps(p, v); }
  static T set1(float v) { return _mm256_set1_ps(v); }
  static T add(T a, T b) { return _mm256_add_ps(a, b); }
  static T sub(T a, T b) { return _mm256_sub_ps(a, b); }
  static T mul(T a, T b) { return _mm256_mul_ps(a, b); }
  static T div(T a, T b) { return _mm256_div_ps(a, b); }
  static T min(T a, T b) { return _mm256_min_ps(a, b); }
  static T max(T a, T b) { return _mm256_max_ps(a, b); }
  static T fmadd(T a, T b, T c) { return _mm256_fmadd_ps(a, b, c); }
  static T fnmadd(T a, T b, T c) { return _mm256_fnmadd_ps(a, b, c); }
  static T round(T v) { return _mm256_round_ps(v, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC); }
  static T abs(T v) { return _mm256_andnot_ps(_mm256_set1_ps(-0.0f), v); }
  static M greater(T a, T b) { return _mm256_cmp_ps(a, b, _CMP_GT_OQ); }
  static M equal(T a, T b) { return _mm256_cmp_ps(a, b, _CMP_EQ_OQ); }
  static T select(M m, T a, T b) { return _mm256_blendv_ps(b, a, m); }
  static T and_mask(M m, T v) { return _mm256_and_ps(m, v); }
  static T pow2(T n) {
    return _mm256_castsi256_ps(_mm256_slli_epi32(_mm256_add_epi32(_mm256_cvtps_epi32(n), _mm256_set1_epi32(127)), 23));
  }
  static T exponent(T w) {
    return _mm256_cvtepi32_ps(_mm256_sub_epi32(_mm256_srli_epi32(_mm256_castps_si256(w), 23), _mm256_set1_epi32(127)));
  }
  static T mantissa(T w) {
    return _mm256_castsi256_ps(_mm256_or_si256(_mm256_and_si256(_mm256_castps_si256(w), _mm256_set1_epi32(0x007fffff)),
                                               _mm256_set1_epi32(0x3f800000)));
  }
  static void transpose(const float* src, int64_t stride, float* dst, int64_t dst_stride, T scale) {
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
  static void prefetch(const char* p) { _mm_prefetch(p, _MM_HINT_T0); }
};

namespace avx2 {
using P = Avx8;
struct V {
  using T = __m256;
  static constexpr int kLanes = 8;
  static constexpr bool kScalef = false;
  static float sum(T v) {
    __m128 s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
    s = _mm_add_ps(s, _mm_movehl_ps(s, s));
    return _mm_cvtss_f32(_mm_add_ss(s, _mm_movehdup_ps(s)));
  }
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
using P = Avx8;
struct V {
  using T = __m512;
  static constexpr int kLanes = 16;
  static constexpr bool kScalef = true;
  static float sum(T v) { return _mm512_reduce_add_ps(v); }
  static T round(T v) { return _mm512_roundscale_ps(v, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC); }
  static T scalef(T q, T m) { return _mm512_scalef_ps(q, m); }  // q * 2^floor(m), m an integer here
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

inline bool cpu_has_avx2() {
  __builtin_cpu_init();
  return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
}

inline bool cpu_has_avx512() { return cpu_has_avx2() && __builtin_cpu_supports("avx512f"); }
#endif

#ifdef DSSP_HAVE_NEON_PATH
namespace neon {
// The 128-bit NEON vector, 4 lanes: scan_simd.inc's V and P both.
struct V {
  using T = float32x4_t;
  using M = uint32x4_t;  // a lane mask: all bits set or all clear
  static constexpr int kLanes = 4;
  static constexpr bool kScalef = false;
  static float sum(T v) { return vaddvq_f32(v); }
  static T load(const float* p) { return vld1q_f32(p); }
  static T loadu(const float* p) { return vld1q_f32(p); }
  static void store(float* p, T v) { vst1q_f32(p, v); }
  static void storeu(float* p, T v) { vst1q_f32(p, v); }
  static T set1(float v) { return vdupq_n_f32(v); }
  static T broadcast(const float* p) { return vld1q_dup_f32(p); }
  static T add(T a, T b) { return vaddq_f32(a, b); }
  static T sub(T a, T b) { return vsubq_f32(a, b); }
  static T mul(T a, T b) { return vmulq_f32(a, b); }
  static T div(T a, T b) { return vdivq_f32(a, b); }
  static T min(T a, T b) { return vminq_f32(a, b); }
  static T max(T a, T b) { return vmaxq_f32(a, b); }
  static T fmadd(T a, T b, T c) { return vfmaq_f32(c, a, b); }
  static T fnmadd(T a, T b, T c) { return vfmsq_f32(c, a, b); }
  static T round(T v) { return vrndnq_f32(v); }
  static T abs(T v) { return vabsq_f32(v); }
  static M greater(T a, T b) { return vcgtq_f32(a, b); }
  static M equal(T a, T b) { return vceqq_f32(a, b); }
  static T select(M m, T a, T b) { return vbslq_f32(m, a, b); }
  static T and_mask(M m, T v) { return vreinterpretq_f32_u32(vandq_u32(m, vreinterpretq_u32_f32(v))); }
  static T pow2(T n) { return vreinterpretq_f32_s32(vshlq_n_s32(vaddq_s32(vcvtq_s32_f32(n), vdupq_n_s32(127)), 23)); }
  static T exponent(T w) {
    return vcvtq_f32_s32(vsubq_s32(vreinterpretq_s32_u32(vshrq_n_u32(vreinterpretq_u32_f32(w), 23)), vdupq_n_s32(127)));
  }
  static T mantissa(T w) {
    return vreinterpretq_f32_u32(
        vorrq_u32(vandq_u32(vreinterpretq_u32_f32(w), vdupq_n_u32(0x007fffff)), vdupq_n_u32(0x3f800000)));
  }
  static T add_exponent(T q, T t) {  // the low bits of t are round(y): shifted into the exponent field they add it
    return vreinterpretq_f32_s32(vaddq_s32(vreinterpretq_s32_f32(q), vshlq_n_s32(vreinterpretq_s32_f32(t), 23)));
  }
  static void transpose(const float* src, int64_t stride, float* dst, int64_t dst_stride, T scale) {
    const T r0 = vmulq_f32(vld1q_f32(src), scale), r1 = vmulq_f32(vld1q_f32(src + stride), scale);
    const T r2 = vmulq_f32(vld1q_f32(src + 2 * stride), scale), r3 = vmulq_f32(vld1q_f32(src + 3 * stride), scale);
    // (r0[j], r1[j]) pairs: t0 holds columns 0 and 2, t1 columns 1 and 3 (rows 0 and 1); t2, t3 rows 2 and 3
    const float64x2_t t0 = vreinterpretq_f64_f32(vtrn1q_f32(r0, r1)), t1 = vreinterpretq_f64_f32(vtrn2q_f32(r0, r1));
    const float64x2_t t2 = vreinterpretq_f64_f32(vtrn1q_f32(r2, r3)), t3 = vreinterpretq_f64_f32(vtrn2q_f32(r2, r3));
    vst1q_f32(dst, vreinterpretq_f32_f64(vtrn1q_f64(t0, t2)));
    vst1q_f32(dst + dst_stride, vreinterpretq_f32_f64(vtrn1q_f64(t1, t3)));
    vst1q_f32(dst + 2 * dst_stride, vreinterpretq_f32_f64(vtrn2q_f64(t0, t2)));
    vst1q_f32(dst + 3 * dst_stride, vreinterpretq_f32_f64(vtrn2q_f64(t1, t3)));
  }
  static void prefetch(const char* p) { __builtin_prefetch(p, 0, 3); }
};
using P = V;
#include "scan_simd.inc"
}  // namespace neon
#endif

// ------------------------------------------------------------------ the causal depthwise convolution
// y_t = silu(bias + sum_j weight[j] * xe[t + 1 + j]) over xe = [state, x] (W + L steps), new state = the last
// W steps of xe: Mamba's conv branch continuing from its state (zeros at a fresh start). Plain C++: the
// loops over channels vectorise on any target, and the work is small next to the scan.
struct ConvProblem {
  const float *x, *state, *weight, *bias;  // weight (W, E); state null: zeros
  float *y, *new_state;
  int64_t batch, L, E, W;
  int64_t state_after = 0;  // new_state is the state after this many steps of x (1..L); 0: after the last (L)
  int64_t x_stride = 0;  // x's row stride (x inside in_proj's output [x, z]: 2E); 0: E

  const float* x_row(int64_t row) const { return x + row * (x_stride > 0 ? x_stride : E); }  // row = b * L + t
};

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define DSSP_AVX2_CLONES __attribute__((target_clones("arch=x86-64-v3", "default")))  // an AVX2 + FMA build beside the baseline one
#else
#define DSSP_AVX2_CLONES
#endif

DSSP_AVX2_CLONES inline void conv_block(const ConvProblem& p, int64_t b, int64_t e0, int64_t e1) {
  const int64_t L = p.L, E = p.E, W = p.W;
  for (int64_t t = 0; t < L; ++t) {
    float* y = p.y + (b * L + t) * E;
    for (int64_t e = e0; e < e1; ++e) y[e] = p.bias ? p.bias[e] : 0.0f;
    for (int64_t j = 0; j < W; ++j) {
      const int64_t i = t + 1 + j;
      const float* w = p.weight + j * E;
      if (i >= W) {
        const float* xi = p.x_row(b * L + i - W);
#pragma omp simd
        for (int64_t e = e0; e < e1; ++e) y[e] += w[e] * xi[e];
      } else {
        if (p.state)
          for (int64_t e = e0; e < e1; ++e) y[e] += w[e] * p.state[(b * E + e) * W + i];
      }
    }
#pragma omp simd
    for (int64_t e = e0; e < e1; ++e) y[e] = y[e] / (1.0f + fast_exp(-y[e]));
  }
  const int64_t after = p.state_after > 0 ? p.state_after : L;
  for (int64_t k = 0; k < W; ++k) {  // the new state: the last W steps of [state, x[:after]]
    const int64_t i = after + k;
    float* out = p.new_state + b * E * W + k;
    if (i >= W) {
      const float* xi = p.x_row(b * L + i - W);
      for (int64_t e = e0; e < e1; ++e) out[e * W] = xi[e];
    } else {
      const float* si = p.state ? p.state + b * E * W + i : nullptr;
      for (int64_t e = e0; e < e1; ++e) out[e * W] = si ? si[e * W] : 0.0f;
    }
  }
}

// ------------------------------------------------------------------ the scan's paths
enum class Path { kPortable, kAvx2, kAvx512, kNeon };

inline const char* path_name(Path path) {
  return path == Path::kAvx512 ? "avx512" : path == Path::kAvx2 ? "avx2" : path == Path::kNeon ? "neon" : "portable";
}

// DSSP_SCAN_PATH: auto (the widest this CPU runs), avx512, avx2, neon or portable. A path this CPU or build lacks:
// the fallback is returned and *error says why (empty when the choice holds).
inline Path choose_path(std::string* error) {
  error->clear();
  const char* env = std::getenv("DSSP_SCAN_PATH");
  const std::string want = env ? env : "auto";
  if (want != "auto" && want != "avx512" && want != "avx2" && want != "neon" && want != "portable") {
    *error = "DSSP_SCAN_PATH=" + want + " is not one of auto, avx512, avx2, neon, portable";
    return Path::kPortable;
  }
  if (want == "portable") return Path::kPortable;
#ifdef DSSP_HAVE_SIMD_PATHS
  if (want == "neon") {
    *error = "DSSP_SCAN_PATH=neon, but neon is aarch64 only (this build is x86-64); unset it or use avx512, avx2 or portable";
    return Path::kPortable;
  }
  const bool avx512 = cpu_has_avx512(), avx2 = cpu_has_avx2();
  if (want == "avx512" && !avx512) *error = "DSSP_SCAN_PATH=avx512, but this CPU lacks AVX-512; unset it or use avx2 or portable";
  if (want == "avx2" && !avx2) *error = "DSSP_SCAN_PATH=avx2, but this CPU lacks AVX2 or FMA; unset it or use portable";
  if (!error->empty()) return Path::kPortable;
  if (want == "avx2") return Path::kAvx2;
  return avx512 ? Path::kAvx512 : avx2 ? Path::kAvx2 : Path::kPortable;
#elif defined(DSSP_HAVE_NEON_PATH)
  if (want == "avx512" || want == "avx2") {
    *error = "DSSP_SCAN_PATH=" + want + ", but " + want + " is x86-64 only (this build is aarch64); unset it or use neon or portable";
    return Path::kPortable;
  }
  return Path::kNeon;
#else
  if (want != "auto") *error = "DSSP_SCAN_PATH=" + want + ", but this library was built without the SIMD paths (they need x86-64 and GCC, or aarch64); unset it or use portable";
  return Path::kPortable;
#endif
}

struct ScanTask {
  const Problem* problem;
  Path path;
  int64_t blocks_per_row;
};

inline void run_scan_task(void* data, size_t index) {
  const ScanTask& task = *static_cast<const ScanTask*>(data);
  const Problem& p = *task.problem;
  const int64_t b = static_cast<int64_t>(index) / task.blocks_per_row;
  const int64_t e0 = (static_cast<int64_t>(index) % task.blocks_per_row) * kBlock;
  const int64_t e1 = std::min(e0 + kBlock, p.E);
#ifdef DSSP_HAVE_SIMD_PATHS
  const bool x86 = task.path == Path::kAvx512 || task.path == Path::kAvx2;
  if (p.L == 1 && task.path == Path::kAvx512 && p.n % avx512::V::kLanes == 0) return avx512::scan_step(p, b, e0, e1);
  if (p.L == 1 && x86 && p.n % avx2::V::kLanes == 0) return avx2::scan_step(p, b, e0, e1);
#endif
#ifdef DSSP_HAVE_NEON_PATH
  if (p.L == 1 && task.path == Path::kNeon && p.n % neon::V::kLanes == 0) return neon::scan_step(p, b, e0, e1);
#endif
  // 64-byte aligned (with w a multiple of the lanes the SIMD paths' transposed state and A are too: aligned loads)
  const size_t floats = static_cast<size_t>(3 * p.L * (e1 - e0) + 32 * p.n) + 16;
  std::unique_ptr<float[]> buffer(new float[floats]);
  float* scratch = buffer.get();
  while (reinterpret_cast<uintptr_t>(scratch) % 64) ++scratch;
#ifdef DSSP_HAVE_SIMD_PATHS
  if (task.path == Path::kAvx512 && (e1 - e0) % avx512::V::kLanes == 0) return avx512::scan_block(p, b, e0, e1, scratch);
  if (x86 && (e1 - e0) % avx2::V::kLanes == 0) return avx2::scan_block(p, b, e0, e1, scratch);
#endif
#ifdef DSSP_HAVE_NEON_PATH
  if (task.path == Path::kNeon && (e1 - e0) % neon::V::kLanes == 0) return neon::scan_block(p, b, e0, e1, scratch);
#endif
  scan_block_portable(p, b, e0, e1, scratch);
}

struct ConvTask {
  const ConvProblem* problem;
  int64_t blocks_per_row;
};

inline void run_conv_task(void* data, size_t index) {
  const ConvTask& task = *static_cast<const ConvTask*>(data);
  const int64_t b = static_cast<int64_t>(index) / task.blocks_per_row;
  const int64_t e0 = (static_cast<int64_t>(index) % task.blocks_per_row) * 256;
  conv_block(*task.problem, b, e0, std::min(e0 + 256, task.problem->E));
}

// The gated MLP's activation, v = u * silu(g) over fc1's rows [u, g] (m, 2h) -> v (m, h), a row per task.
struct GateTask {
  const float* ug;
  float* v;
  int64_t hidden;
};

DSSP_AVX2_CLONES inline void gate_row(const float* u, const float* g, float* v, int64_t hidden) {
#pragma omp simd
  for (int64_t j = 0; j < hidden; ++j) v[j] = u[j] * (g[j] / (1.0f + fast_exp(-g[j])));
}

inline void run_gate_task(void* data, size_t index) {
  const GateTask& t = *static_cast<const GateTask*>(data);
  const int64_t i = static_cast<int64_t>(index);
  const float* u = t.ug + i * 2 * t.hidden;
  gate_row(u, u + t.hidden, t.v + i * t.hidden, t.hidden);
}

// ------------------------------------------------------------------ the point encoder's pooling
// The running max y (F) over points [p0, p1) of x (P, F) after each point's LayerNorm over its F features:
// (x - mean) / sqrt(var + eps) * weight + bias, the variance biased, as torch's layer_norm. In one pass over the
// points in their own layout, nothing written but the max (the graph's LayerNorm + Transpose + GlobalMaxPool
// write and read the (P, F) values twice).
// Four points at a time: their sums are four independent chains (one point's would wait on each add).
DSSP_AVX2_CLONES inline void layer_norm_max(const float* x, int64_t F, const float* weight, const float* bias, float eps,
                                       int64_t p0, int64_t p1, float* y) {
  constexpr int64_t kPoints = 4;
  const float inv_f = 1.0f / static_cast<float>(F);
  int64_t p = p0;
  for (; p + kPoints <= p1; p += kPoints) {
    const float *x0 = x + p * F, *x1 = x0 + F, *x2 = x1 + F, *x3 = x2 + F;
    float s0 = 0.0f, s1 = 0.0f, s2 = 0.0f, s3 = 0.0f;
#pragma omp simd reduction(+ : s0, s1, s2, s3)
    for (int64_t f = 0; f < F; ++f) s0 += x0[f], s1 += x1[f], s2 += x2[f], s3 += x3[f];
    const float m0 = s0 * inv_f, m1 = s1 * inv_f, m2 = s2 * inv_f, m3 = s3 * inv_f;
    float q0 = 0.0f, q1 = 0.0f, q2 = 0.0f, q3 = 0.0f;
#pragma omp simd reduction(+ : q0, q1, q2, q3)
    for (int64_t f = 0; f < F; ++f) {
      q0 += (x0[f] - m0) * (x0[f] - m0), q1 += (x1[f] - m1) * (x1[f] - m1);
      q2 += (x2[f] - m2) * (x2[f] - m2), q3 += (x3[f] - m3) * (x3[f] - m3);
    }
    const float r0 = 1.0f / std::sqrt(q0 * inv_f + eps), r1 = 1.0f / std::sqrt(q1 * inv_f + eps);
    const float r2 = 1.0f / std::sqrt(q2 * inv_f + eps), r3 = 1.0f / std::sqrt(q3 * inv_f + eps);
#pragma omp simd
    for (int64_t f = 0; f < F; ++f) {
      const float v0 = (x0[f] - m0) * r0 * weight[f] + bias[f], v1 = (x1[f] - m1) * r1 * weight[f] + bias[f];
      const float v2 = (x2[f] - m2) * r2 * weight[f] + bias[f], v3 = (x3[f] - m3) * r3 * weight[f] + bias[f];
      const float a = v0 > v1 ? v0 : v1, c = v2 > v3 ? v2 : v3, v = a > c ? a : c;
      y[f] = v > y[f] ? v : y[f];
    }
  }
  for (; p < p1; ++p) {
    const float* xp = x + p * F;
    float sum = 0.0f, squares = 0.0f;
#pragma omp simd reduction(+ : sum)
    for (int64_t f = 0; f < F; ++f) sum += xp[f];
    const float mean = sum * inv_f;
#pragma omp simd reduction(+ : squares)
    for (int64_t f = 0; f < F; ++f) squares += (xp[f] - mean) * (xp[f] - mean);
    const float r = 1.0f / std::sqrt(squares * inv_f + eps);
#pragma omp simd
    for (int64_t f = 0; f < F; ++f) {
      const float v = (xp[f] - mean) * r * weight[f] + bias[f];
      y[f] = v > y[f] ? v : y[f];
    }
  }
}

// out (m, d) = rmsnorm(x) * weight (, then * (1 + scale) + shift when scale is given)
inline void rms_norm(const float* x, int64_t m, int64_t d, const float* weight, float eps, const float* shift,
              const float* scale, float* out) {
  for (int64_t i = 0; i < m; ++i) {
    const float* xi = x + i * d;
    float ss = 0.0f;
#pragma omp simd reduction(+ : ss)
    for (int64_t j = 0; j < d; ++j) ss += xi[j] * xi[j];
    const float r = 1.0f / std::sqrt(ss / static_cast<float>(d) + eps);
    float* oi = out + i * d;
    for (int64_t j = 0; j < d; ++j) {
      const float v = xi[j] * r * weight[j];
      oi[j] = scale ? v * (1.0f + scale[j]) + shift[j] : v;
    }
  }
}

// ------------------------------------------------------------------ the end of one DDIM step
// One action token at the end of a DDIM step (ai.dssp::DdimStep in mamba_ops.cc gives the arithmetic): the readout
// of h (d) to the model's output y (A), the DDIM update of x (A) to x_next (A), and, when a_next is given, the next
// step's token a_next (d) = x_next in_w + in_b + pos. r: d floats of scratch.
struct DdimStepWeights {
  const float *norm_w, *shift, *scale;  // (d), (d), (d)
  const float *out_w, *out_b;           // (A, d), (A)
  const float *in_w, *in_b;             // (A, d): the input layer's weight transposed, (d)
  int64_t d, A;
  float eps, c_t, s_t, c_prev, s_prev;  // the norm's eps; sqrt(abar_t), sqrt(1 - abar_t), the same at the step's end
  bool sample, clip;                    // the model predicts the clean sample (else the noise); x0 clamped to [-1, 1]
};

DSSP_AVX2_CLONES inline void ddim_step_row(const DdimStepWeights& w, const float* h, const float* x, const float* pos,
                                           float* x_next, float* a_next, float* r) {
  const int64_t d = w.d, A = w.A;
  rms_norm(h, 1, d, w.norm_w, w.eps, w.shift, w.scale, r);
  for (int64_t j = 0; j < A; j += 4) {  // four outputs at a time: four independent chains of adds
    const float* w0 = w.out_w + j * d;
    const float *w1 = j + 1 < A ? w0 + d : w0, *w2 = j + 2 < A ? w0 + 2 * d : w0, *w3 = j + 3 < A ? w0 + 3 * d : w0;
    float s0 = 0.0f, s1 = 0.0f, s2 = 0.0f, s3 = 0.0f;
#pragma omp simd reduction(+ : s0, s1, s2, s3)
    for (int64_t k = 0; k < d; ++k) s0 += r[k] * w0[k], s1 += r[k] * w1[k], s2 += r[k] * w2[k], s3 += r[k] * w3[k];
    const float sums[4] = {s0, s1, s2, s3};
    for (int64_t u = 0; u < 4 && j + u < A; ++u) {
      const float y = sums[u] + w.out_b[j + u], xt = x[j + u];
      float x0 = w.sample ? y : (xt - w.s_t * y) / w.c_t;
      const float e = w.sample ? (xt - w.c_t * y) / w.s_t : y;
      if (w.clip) x0 = std::min(1.0f, std::max(-1.0f, x0));
      x_next[j + u] = w.c_prev * x0 + w.s_prev * e;
    }
  }
  if (a_next == nullptr) return;
#pragma omp simd
  for (int64_t k = 0; k < d; ++k) a_next[k] = 0.0f;
  for (int64_t j = 0; j < A; ++j) {
    const float xj = x_next[j], *wj = w.in_w + j * d;
#pragma omp simd
    for (int64_t k = 0; k < d; ++k) a_next[k] += xj * wj[k];
  }
#pragma omp simd
  for (int64_t k = 0; k < d; ++k) a_next[k] = (a_next[k] + w.in_b[k]) + pos[k];
}

// ------------------------------------------------------------------ a whole denoiser block (int8 weights)
// One block of the denoiser, on the action tokens for one DDIM step or on the prefix (ai.dssp::MambaBlockQ8):
//
//   h = rmsnorm(a) * (1 + scale) + shift                       AdaLN, mod = [shift; scale; gate] (3, d); the
//                                                              prefix has none: h = rmsnorm(a), gate 1
//   x, z = in_proj(h)                                          x, z (rows, E)
//   x = silu(conv(x)) continuing from conv_state
//   dt, B, C = x_proj(x); dt = dt_proj(dt) + dt_bias
//   y = scan(x, dt, B, C, z) from ssm_state                    the selective scan above
//   a = a + gate * out_proj(y)
//   a = a + fc2(u * silu(g)), [u, g] = fc1(rmsnorm2(a))        the gated MLP, when the block has one
//
// Every product multiplies the rows (batch * L, a dozen) by int8 weights packed once (qgemm.h), the activations
// quantized per row, the output columns split across the threads.

namespace q = dssp::qgemm;

// The block's parameters: the projections packed (fc1, fc2 null without the MLP), the rest as the graph holds it.
//   in (2E, d), xp (R + 2n, E), dt (E, R), out (d, E), fc1 (2h, d), fc2 (d, h)
//   norm_w (d), conv_w (W, E), conv_b (E), dt_b (E), A (E, n), D (E), norm2_w (d)
struct BlockWeights {
  const q::PackedWeights *in = nullptr, *xp = nullptr, *dt = nullptr, *out = nullptr, *fc1 = nullptr, *fc2 = nullptr;
  const float *norm_w = nullptr, *conv_w = nullptr, *conv_b = nullptr, *dt_b = nullptr, *A = nullptr, *D = nullptr,
              *norm2_w = nullptr;
  int64_t d = 0, E = 0, W = 0, n = 0;
  float eps = 1e-5f;

  int64_t rank() const { return dt->k; }
  int64_t hidden() const { return fc2 ? fc2->k : 0; }

  // The projections' shapes against d, E and n: one line that says which does not fit.
  void check() const {
    if (!in || !xp || !dt || !out || (fc1 == nullptr) != (fc2 == nullptr))
      throw std::invalid_argument("MambaBlockQ8: a projection is missing (fc1 and fc2 come together)");
    const int64_t R = rank();
    if (in->n != 2 * E || in->k != d || xp->n != R + 2 * n || xp->k != E || dt->n != E || out->n != d || out->k != E)
      throw std::invalid_argument("MambaBlockQ8: the projections' shapes do not fit d = " + std::to_string(d) +
                                  ", E = " + std::to_string(E) + ", n = " + std::to_string(n));
    if (fc1 && (fc1->n != 2 * fc2->k || fc1->k != d || fc2->n != d))
      throw std::invalid_argument("MambaBlockQ8: fc1 must be (2h, d) and fc2 (d, h) with d = " + std::to_string(d));
  }
};

// a (batch, L, d); conv_state (batch, E, W); ssm_state (batch, E, n), both null for a start from zeros; mod (3, d)
// or null (the prefix alone).
// plain: the first `plain` tokens of each row are the prefix, without AdaLN and gate 1, the rest the action
// tokens (one DDIM step's [prefix, actions] in one pass); 0 when mod is null.
struct BlockInputs {
  const float *a = nullptr, *conv_state = nullptr, *ssm_state = nullptr, *mod = nullptr;
  int64_t batch = 0, L = 0, plain = 0;
};

// a (batch, L, d); the states after the L tokens (after the `plain` prefix tokens when plain > 0: what the later
// DDIM steps start from), conv (batch, E, W) and ssm (batch, E, n), or null: not written
struct BlockOutputs {
  float *a = nullptr, *conv_state = nullptr, *ssm_state = nullptr;
};

struct MatmulTask {
  const q::QuantizedRows* x;
  const q::PackedWeights* w;
  const float* bias;
  float* y;
  int ldy;
  int columns;  // per task
};

inline void run_matmul_task(void* data, size_t index) {
  const MatmulTask& t = *static_cast<const MatmulTask*>(data);
  const int begin = static_cast<int>(index) * t.columns;
  q::matmul_range(*t.x, *t.w, t.bias, t.y, t.ldy, begin, std::min(begin + t.columns, t.w->n));
}

constexpr int kColumnsPerTask = 128;  // at most; a multiple of every path's column block

// y (m, w.n) = x (m, k) @ W.T (+ bias), the columns split across the threads in tasks of kColumnsPerTask columns, or
// of a quarter of them rounded up to the path's column block where that is less (x_proj's 160 columns: 64, 64, 32,
// not 128 and 32); rows holds x quantized
inline void q8_matmul(const ParallelFor& parallel_for, const float* x, int64_t m, int64_t k, const q::PackedWeights& w,
                      const float* bias, float* y, q::QuantizedRows& rows) {
  q::quantize_rows(x, static_cast<int>(m), static_cast<int>(k), rows, w.path);
  const int quarter = (w.n + 3) / 4;
  const int columns = std::min(kColumnsPerTask, (quarter + w.block - 1) / w.block * w.block);
  MatmulTask task{&rows, &w, bias, y, w.n, columns};
  parallel_for(run_matmul_task, static_cast<size_t>((w.n + columns - 1) / columns), &task);
}

// The block on in.L tokens of each of in.batch rows (see above); the weights checked by BlockWeights::check.
inline void block_forward(const BlockWeights& w, const BlockInputs& in, const BlockOutputs& out, Path scan_path,
                          const ParallelFor& parallel_for) {
  const int64_t batch = in.batch, L = in.L, m = batch * L, d = w.d, E = w.E, W = w.W, n = w.n, R = w.rank();
  if (m == 0) return;
  q::QuantizedRows rows;  // this call's quantized activations
  const float* shift = in.mod;
  const float *scale = shift ? shift + d : nullptr, *gate = shift ? shift + 2 * d : nullptr;
  // one uninitialised buffer for the call's activations (each is written before it is read)
  const int64_t hidden = w.hidden(), xpn = w.xp->n;
  const int64_t sizes[] = {m * d, m * 2 * E, m * E, out.conv_state ? 0 : batch * E * W, m * xpn, m * R,
                           m * E, m * n, m * n, m * E, m * d, m * d, m * 2 * hidden, m * hidden};
  int64_t total = 0;
  for (int64_t size : sizes) total += (size + 15) / 16 * 16;
  std::unique_ptr<float[]> buffer(new float[total]);
  float* next = buffer.get();
  auto take = [&next](int64_t size) {
    float* at = next;
    next += (size + 15) / 16 * 16;
    return at;
  };
  float *h = take(sizes[0]), *xz = take(sizes[1]), *xc = take(sizes[2]), *conv_after = take(sizes[3]),
        *dbc = take(sizes[4]), *dt_in = take(sizes[5]), *dt = take(sizes[6]), *Bm = take(sizes[7]), *Cm = take(sizes[8]),
        *y = take(sizes[9]), *o = take(sizes[10]), *g = take(sizes[11]), *u = take(sizes[12]), *v = take(sizes[13]);
  for (int64_t b = 0; b < batch; ++b) {  // the prefix's tokens unmodulated, the actions' with AdaLN
    const int64_t row = b * L, plain = shift ? in.plain : L;
    rms_norm(in.a + row * d, plain, d, w.norm_w, w.eps, nullptr, nullptr, h + row * d);
    rms_norm(in.a + (row + plain) * d, L - plain, d, w.norm_w, w.eps, shift, scale, h + (row + plain) * d);
  }
  q8_matmul(parallel_for, h, m, d, *w.in, nullptr, xz, rows);  // each row [x, z]: the conv and the scan read them there
  ConvProblem cp{xz, in.conv_state, w.conv_w, w.conv_b, xc,
                 out.conv_state ? out.conv_state : conv_after, batch, L, E, W, in.plain, 2 * E};
  const int64_t conv_blocks = (E + 255) / 256;
  ConvTask conv_task{&cp, conv_blocks};
  parallel_for(run_conv_task, static_cast<size_t>(batch * conv_blocks), &conv_task);
  q8_matmul(parallel_for, xc, m, E, *w.xp, nullptr, dbc, rows);
  for (int64_t i = 0; i < m; ++i) {
    const float* row = dbc + i * w.xp->n;
    std::memcpy(dt_in + i * R, row, sizeof(float) * R);
    std::memcpy(Bm + i * n, row + R, sizeof(float) * n);
    std::memcpy(Cm + i * n, row + R + n, sizeof(float) * n);
  }
  q8_matmul(parallel_for, dt_in, m, R, *w.dt, w.dt_b, dt, rows);
  Problem sp{xc, dt, Bm, Cm, xz + E, w.A, w.D, in.ssm_state, y, out.ssm_state,
             batch, L, E, n, in.plain, 2 * E};
  const int64_t scan_blocks = (E + kBlock - 1) / kBlock;
  ScanTask scan_task{&sp, scan_path, scan_blocks};
  parallel_for(run_scan_task, static_cast<size_t>(batch * scan_blocks), &scan_task);
  q8_matmul(parallel_for, y, m, E, *w.out, nullptr, o, rows);
  for (int64_t i = 0; i < m; ++i) {
    const float* gi = gate && i % L >= in.plain ? gate : nullptr;
    if (gi)
      for (int64_t j = 0; j < d; ++j) out.a[i * d + j] = in.a[i * d + j] + gi[j] * o[i * d + j];
    else
      for (int64_t j = 0; j < d; ++j) out.a[i * d + j] = in.a[i * d + j] + o[i * d + j];
  }
  if (!w.fc1) return;

  rms_norm(out.a, m, d, w.norm2_w, w.eps, nullptr, nullptr, g);
  q8_matmul(parallel_for, g, m, d, *w.fc1, nullptr, u, rows);
  GateTask gate_task{u, v, hidden};
  parallel_for(run_gate_task, static_cast<size_t>(m), &gate_task);
  q8_matmul(parallel_for, v, m, hidden, *w.fc2, nullptr, o, rows);
  for (int64_t i = 0; i < m * d; ++i) out.a[i] += o[i];
}

}  // namespace dssp::mamba
