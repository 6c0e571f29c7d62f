// int8 matrix products for a few rows: y = x W^T (+ bias) with x (m, k) fp32 activations quantised per row
// (asymmetric uint8) and W (n, k) weights quantised per output row (symmetric int8), packed once.
//
// Made for the denoiser's action tokens: m = 1..16 rows against large n, k, where each weight byte is read
// once per product and the activations stay in registers and L1. Header-only, C++17, no dependency.
//
// Paths (one build holds every path of its architecture; the CPU's own decides at run time):
//   avx512_vnni  vpdpbusd on 512-bit vectors (AVX-512F/BW + AVX512_VNNI): 32 columns x 4 k per 128 bytes
//   avx_vnni     vpdpbusd on 256-bit vectors (AVX-VNNI, VEX encoded): 16 columns x 4 k per 64 bytes
//   avx2         vpmaddwd on sign-extended 16-bit weights and zero-extended 16-bit activations: 16 columns x 2 k
//   neon_dot     sdot by element (armv8.2-a dotprod; activations - 128 as int8): 8 columns x 4 k per 32 bytes
//   neon         smlal by element on 16-bit values (any aarch64): 8 columns x 1 k per 8 bytes
//   portable     plain C++ (16 columns x 1 k) that compilers vectorise
// DSSP_QGEMM_PATH=auto|<path name> chooses for best_path() (auto, the default: the fastest this CPU runs).
//
// Every path gives bit-identical results: the integer sums are exact in int32 (no instruction that saturates:
// AVX2's vpmaddubsw would add two u8 x s8 products in int16, up to 2 * 255 * 128 > 32767, so the avx2 path
// multiplies 16-bit values with vpmaddwd instead, about 20 % slower than vpmaddubsw on activations kept to 7
// bits: README.md beside this file), and the dequantisation is one float expression everywhere:
//   y[i, j] = fma(float(acc), x_scale[i] * w_scale[j], bias[j])      with bias
//   y[i, j] = float(acc) * (x_scale[i] * w_scale[j])                  without
// acc = sum_k (xq[i, k] - zero[i]) * wq[j, k], exact for k <= 65536 (255 * 128 * 65536 < 2^31).
// Built with -ffast-math the compiler may reassociate or contract these; it is refused below.
//
// Threads: pack once, then any number of threads may call matmul_range on the same weights and rows, each
// for its own columns (best split at multiples of PackedWeights::block); matmul and the avx2 path keep their
// scratch per thread.

#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <new>
#include <stdexcept>
#include <string>
#include <vector>

#if defined(__FAST_MATH__)
#error "qgemm.h promises bit-identical results on every path: build it without -ffast-math / -Ofast"
#endif

#if defined(__x86_64__) && defined(__GNUC__)
#define DSSP_QGEMM_X86 1
#include <immintrin.h>
#define DSSP_QGEMM_TARGET_AVX2 __attribute__((target("avx2,fma")))
#define DSSP_QGEMM_TARGET_AVX_VNNI __attribute__((target("avx2,fma,avxvnni")))
#define DSSP_QGEMM_TARGET_AVX512_VNNI __attribute__((target("avx2,fma,avx512f,avx512bw,avx512vnni")))
// The avx_vnni kernel with the EVEX encoding of the same instruction (AVX512_VNNI + VL): lets a CPU with
// AVX-512 VNNI but no AVX-VNNI check that kernel's layout and arithmetic (qgemm_check does).
#define DSSP_QGEMM_TARGET_AVX_VNNI_EVEX __attribute__((target("avx2,fma,avx512f,avx512vl,avx512vnni")))
#elif defined(__aarch64__) && defined(__GNUC__)
#define DSSP_QGEMM_ARM 1
#include <arm_neon.h>
#if defined(__linux__)
#include <sys/auxv.h>
#endif
// arm_neon.h defines the dot-product intrinsics for armv8.2-a+dotprod; a function that inlines them needs it too.
#define DSSP_QGEMM_TARGET_NEON_DOT __attribute__((target("arch=armv8.2-a+dotprod")))
#endif

#if defined(__GNUC__)
#define DSSP_QGEMM_UNROLL _Pragma("GCC unroll 16")
#else
#define DSSP_QGEMM_UNROLL
#endif

namespace dssp::qgemm {

enum class Path { kPortable, kAvx2, kAvxVnni, kAvx512Vnni, kNeon, kNeonDot };

constexpr Path kAllPaths[] = {Path::kPortable, Path::kAvx2, Path::kAvxVnni, Path::kAvx512Vnni, Path::kNeon, Path::kNeonDot};
constexpr int kMaxK = 65536;  // the int32 sums are exact up to here

inline const char* path_name(Path path) {
  switch (path) {
    case Path::kPortable: return "portable";
    case Path::kAvx2: return "avx2";
    case Path::kAvxVnni: return "avx_vnni";
    case Path::kAvx512Vnni: return "avx512_vnni";
    case Path::kNeon: return "neon";
    case Path::kNeonDot: return "neon_dot";
  }
  return "unknown";
}

// The path of that name (as path_name writes it); false when there is none.
inline bool parse_path(const std::string& name, Path* out) {
  for (Path p : kAllPaths)
    if (name == path_name(p)) {
      *out = p;
      return true;
    }
  return false;
}

// Why this build or CPU cannot run `path` ("" when it can): the other architecture, or the CPU's missing feature.
inline std::string path_unavailable_reason(Path path) {
  switch (path) {
    case Path::kPortable: return "";
#if defined(DSSP_QGEMM_X86)
    case Path::kAvx2:
    case Path::kAvxVnni:
    case Path::kAvx512Vnni: {
      __builtin_cpu_init();
      if (!__builtin_cpu_supports("avx2") || !__builtin_cpu_supports("fma")) return "this CPU lacks AVX2 or FMA";
      if (path == Path::kAvxVnni && !__builtin_cpu_supports("avxvnni")) return "this CPU lacks AVX-VNNI";
      if (path == Path::kAvx512Vnni &&
          !(__builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512bw") && __builtin_cpu_supports("avx512vnni")))
        return "this CPU lacks AVX-512 VNNI (avx512f, avx512bw, avx512vnni)";
      return "";
    }
    case Path::kNeon:
    case Path::kNeonDot: return "aarch64 only (this build is x86-64)";
#elif defined(DSSP_QGEMM_ARM)
    case Path::kNeon: return "";
    case Path::kNeonDot: {
#if defined(__linux__)
      constexpr unsigned long kHwcapAsimdDp = 1ul << 20;  // HWCAP_ASIMDDP (asm/hwcap.h): the dot-product instructions
      return (getauxval(AT_HWCAP) & kHwcapAsimdDp) ? "" : "this CPU lacks the dot-product instructions (asimddp)";
#else
      return "the CPU's features are only read on Linux (getauxval)";
#endif
    }
    case Path::kAvx2:
    case Path::kAvxVnni:
    case Path::kAvx512Vnni: return "x86-64 only (this build is aarch64)";
#else
    default: return "this build has the portable path only (it needs GCC or Clang on x86-64 or aarch64)";
#endif
  }
  return "unknown path";
}

inline bool path_available(Path path) { return path_unavailable_reason(path).empty(); }

// The fastest path this CPU runs.
inline Path fastest_path() {
  for (Path p : {Path::kAvx512Vnni, Path::kAvxVnni, Path::kAvx2, Path::kNeonDot, Path::kNeon})
    if (path_available(p)) return p;
  return Path::kPortable;
}

// The path DSSP_QGEMM_PATH asks for (unset or auto: the fastest available). An unknown name or a path this
// CPU cannot run leaves *error with one line saying why (the fastest path is then returned); else *error is "".
inline Path choose_path(std::string* error) {
  error->clear();
  const char* env = std::getenv("DSSP_QGEMM_PATH");
  const std::string want = env ? env : "";
  if (want.empty() || want == "auto") return fastest_path();
  Path p;
  if (!parse_path(want, &p)) {
    *error = "DSSP_QGEMM_PATH=" + want + " is not one of auto, portable, avx2, avx_vnni, avx512_vnni, neon, neon_dot";
    return fastest_path();
  }
  const std::string why = path_unavailable_reason(p);
  if (!why.empty()) {
    *error = "DSSP_QGEMM_PATH=" + want + ", but " + why + "; unset it or name an available path";
    return fastest_path();
  }
  return p;
}

// choose_path, refusing what it cannot run: std::runtime_error with choose_path's line.
inline Path best_path() {
  std::string error;
  const Path p = choose_path(&error);
  if (!error.empty()) throw std::runtime_error(error);
  return p;
}

// std::vector storage aligned to 64 bytes (a cache line, a 512-bit vector).
template <class T>
struct AlignedAllocator {
  using value_type = T;
  AlignedAllocator() = default;
  template <class U>
  AlignedAllocator(const AlignedAllocator<U>&) {}
  T* allocate(std::size_t n) { return static_cast<T*>(::operator new(n * sizeof(T), std::align_val_t(64))); }
  void deallocate(T* p, std::size_t) { ::operator delete(p, std::align_val_t(64)); }
  template <class U>
  bool operator==(const AlignedAllocator<U>&) const { return true; }
  template <class U>
  bool operator!=(const AlignedAllocator<U>&) const { return false; }
};
template <class T>
using AlignedVector = std::vector<T, AlignedAllocator<T>>;

// How a path lays its weights out: blocks of `block` output columns, each kpad / group groups of
// (block columns x group consecutive k) bytes, column-major inside a group; max_rows rows per register tile.
struct Layout {
  int block, group, max_rows;
};

constexpr Layout layout(Path path) {
  switch (path) {
    case Path::kAvx512Vnni: return {32, 4, 12};  // 24 zmm accumulators + 2 weight vectors + 1 broadcast
    case Path::kAvxVnni: return {16, 4, 6};      // 16 ymm registers: 12 accumulators + 2 + 1
    case Path::kAvx2: return {16, 2, 6};
    case Path::kNeonDot: return {8, 4, 8};       // 16 accumulators + 8 activation vectors + 2 weight vectors
    case Path::kNeon: return {8, 1, 8};
    case Path::kPortable: break;
  }
  return {16, 1, 4};
}

constexpr int padded_k(int k) { return (k + 15) / 16 * 16; }  // every path reads k in steps that divide 16

struct PackedWeights {
  int n = 0, k = 0;
  Path path = Path::kPortable;
  int block = 0;  // output columns per packed block: threads that split the columns split at multiples of it
  int kpad = 0;   // k rounded up to 16, zero weights beyond k
  AlignedVector<int8_t> data;    // ceil(n / block) blocks of block * kpad bytes (Layout), zeros beyond n
  std::vector<float> scale;      // per output row n
  std::vector<int32_t> row_sum;  // sum_k q[n, k]
  std::size_t bytes() const { return data.size(); }  // what one product reads of the weights
};

struct QuantizedRows {
  int m = 0, k = 0;
  int stride = 0;               // bytes from one row to the next: k rounded up to 16, zeros beyond k
  AlignedVector<uint8_t> data;  // (m, stride)
  std::vector<float> scale;     // per row
  std::vector<int32_t> zero;    // per row, 0..255
};

namespace detail {

[[noreturn]] inline void fail(const std::string& what) { throw std::invalid_argument("qgemm: " + what); }

// Round half to even of |v| <= 2^22 (here |v| <= 256): adding and subtracting 1.5 * 2^23 leaves the float's
// round-to-nearest-even of v, as roundps / frintn do.
inline float round_even(float v) {
  constexpr float kMagic = 12582912.0f;
  return (v + kMagic) - kMagic;
}

inline float clamp_not_nan(float v, float lo, float hi) {  // NaN -> lo, as the SIMD paths' max(v, lo) gives
  v = v > lo ? v : lo;
  return v < hi ? v : hi;
}

// A row's scale and zero point from its minimum (<= 0) and maximum (>= 0). The range is taken in double so
// that one of +-3e38 neither overflows nor underflows; a range below 255 x the smallest float (a row of
// zeros) gets scale 1 and zero point 0: every value quantises to 0 and dequantises to exactly 0.
inline void row_parameters(float mn, float mx, float* scale, int32_t* zero) {
  const float s = static_cast<float>((static_cast<double>(mx) - static_cast<double>(mn)) / 255.0);
  if (!(s > 0.0f)) {
    *scale = 1.0f;
    *zero = 0;
    return;
  }
  *scale = s;
  *zero = static_cast<int32_t>(round_even(clamp_not_nan(-mn / s, 0.0f, 255.0f)));
}

inline uint8_t quantize_value(float x, float scale, int32_t zero) {
  const int32_t q = static_cast<int32_t>(round_even(clamp_not_nan(x / scale, -256.0f, 256.0f))) + zero;
  return static_cast<uint8_t>(q < 0 ? 0 : q > 255 ? 255 : q);
}

inline void minmax_scalar(const float* x, int k, float* mn, float* mx) {
  float lo = 0.0f, hi = 0.0f;  // 0 is always inside the range, so it is exactly representable
  for (int i = 0; i < k; ++i) {
    lo = x[i] < lo ? x[i] : lo;  // NaN compares false: ignored, as minps / fminnm ignore it
    hi = x[i] > hi ? x[i] : hi;
  }
  *mn = lo;
  *mx = hi;
}

inline void quantize_row_scalar(const float* x, int k, uint8_t* q, float* scale, int32_t* zero) {
  float mn, mx;
  minmax_scalar(x, k, &mn, &mx);
  row_parameters(mn, mx, scale, zero);
  for (int i = 0; i < k; ++i) q[i] = quantize_value(x[i], *scale, *zero);
}

// The row's parameters from the vector part's min and max and the scalar tail after it.
inline void row_parameters_with_tail(const float* tail, int n, float mn, float mx, float* scale, int32_t* zero) {
  float tail_mn, tail_mx;
  minmax_scalar(tail, n, &tail_mn, &tail_mx);
  row_parameters(tail_mn < mn ? tail_mn : mn, tail_mx > mx ? tail_mx : mx, scale, zero);
}

#if defined(DSSP_QGEMM_X86)
// The same quantisation with AVX2, 16 values a step (every operation exact or correctly rounded: the same bytes).
DSSP_QGEMM_TARGET_AVX2 inline void quantize_row_avx2(const float* x, int k, uint8_t* q, float* scale, int32_t* zero) {
  __m256 lo = _mm256_setzero_ps(), hi = _mm256_setzero_ps();
  int i = 0;
  for (; i + 8 <= k; i += 8) {
    const __m256 v = _mm256_loadu_ps(x + i);
    lo = _mm256_min_ps(v, lo);  // minps(a, b) = a < b ? a : b: a NaN in v keeps lo
    hi = _mm256_max_ps(v, hi);
  }
  alignas(32) float l8[8], h8[8];
  _mm256_store_ps(l8, lo);
  _mm256_store_ps(h8, hi);
  float mn = 0.0f, mx = 0.0f;
  for (int j = 0; j < 8; ++j) {
    mn = l8[j] < mn ? l8[j] : mn;
    mx = h8[j] > mx ? h8[j] : mx;
  }
  row_parameters_with_tail(x + i, k - i, mn, mx, scale, zero);
  const __m256 s = _mm256_set1_ps(*scale), vlo = _mm256_set1_ps(-256.0f), vhi = _mm256_set1_ps(256.0f);
  const __m256i z = _mm256_set1_epi32(*zero);
  i = 0;
  for (; i + 16 <= k; i += 16) {
    __m256i r[2];
    DSSP_QGEMM_UNROLL
    for (int h = 0; h < 2; ++h) {
      __m256 v = _mm256_div_ps(_mm256_loadu_ps(x + i + 8 * h), s);
      v = _mm256_min_ps(_mm256_max_ps(v, vlo), vhi);  // maxps(v, lo): a NaN v gives lo, as clamp_not_nan
      v = _mm256_round_ps(v, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
      r[h] = _mm256_add_epi32(_mm256_cvtps_epi32(v), z);
    }
    // saturating packs clamp to 0..255; the permutes undo their per-128-bit-lane order
    const __m256i w = _mm256_permute4x64_epi64(_mm256_packs_epi32(r[0], r[1]), 0xD8);
    const __m256i b = _mm256_permute4x64_epi64(_mm256_packus_epi16(w, w), 0x08);
    _mm_storeu_si128(reinterpret_cast<__m128i*>(q + i), _mm256_castsi256_si128(b));
  }
  for (; i < k; ++i) q[i] = quantize_value(x[i], *scale, *zero);
}
#endif

#if defined(DSSP_QGEMM_ARM)
inline void quantize_row_neon(const float* x, int k, uint8_t* q, float* scale, int32_t* zero) {
  float32x4_t lo = vdupq_n_f32(0.0f), hi = vdupq_n_f32(0.0f);
  int i = 0;
  for (; i + 4 <= k; i += 4) {
    const float32x4_t v = vld1q_f32(x + i);
    lo = vminnmq_f32(v, lo);  // fminnm: a NaN in v keeps lo
    hi = vmaxnmq_f32(v, hi);
  }
  row_parameters_with_tail(x + i, k - i, vminvq_f32(lo), vmaxvq_f32(hi), scale, zero);
  const float32x4_t s = vdupq_n_f32(*scale), vlo = vdupq_n_f32(-256.0f), vhi = vdupq_n_f32(256.0f);
  const int32x4_t z = vdupq_n_s32(*zero);
  i = 0;
  for (; i + 8 <= k; i += 8) {
    int32x4_t r[2];
    DSSP_QGEMM_UNROLL
    for (int h = 0; h < 2; ++h) {
      float32x4_t v = vdivq_f32(vld1q_f32(x + i + 4 * h), s);
      v = vminnmq_f32(vmaxnmq_f32(v, vlo), vhi);
      r[h] = vaddq_s32(vcvtq_s32_f32(vrndnq_f32(v)), z);
    }
    // saturating narrows clamp to 0..255
    vst1_u8(q + i, vqmovn_u16(vcombine_u16(vqmovun_s32(r[0]), vqmovun_s32(r[1]))));
  }
  for (; i < k; ++i) q[i] = quantize_value(x[i], *scale, *zero);
}
#endif

// Where one product writes: y[i, j] for rows [row0, row0 + MR) and the columns of block c0 inside [n_begin, n_end).
struct Out {
  const float* x_scale;
  const int32_t* zero;
  int32_t zero_offset;  // subtracted from each zero point: 128 where the kernel summed (xq - 128) * w
  const float* w_scale;
  const int32_t* row_sum;
  const float* bias;
  float* y;
  int ldy, n_begin, n_end;
};

// The dequantisation of one output, the expression every path computes.
inline float dequantize(int32_t acc, float x_scale, float w_scale, const float* bias) {
  const float v = static_cast<float>(acc), s = x_scale * w_scale;
  return bias ? std::fma(v, s, *bias) : v * s;
}

// The weights a tile reads kPrefetch bytes ahead are asked into L2 while it computes: the hardware
// prefetchers alone left the 12-row products 35-55 % slower from memory than from the caches. Only tiles of
// kPrefetchRows rows or more ask (a product of 1..3 rows is memory-bound, its stream better left to the
// hardware), and of a block's tiles only the first (the others find its bytes in L1/L2: they ask for the
// bytes they are reading, which costs a load slot and no branch in the loop).
constexpr int kPrefetch = 16384, kPrefetchRows = 4;

inline const int8_t* prefetch_base(const int8_t* w, int row0) { return row0 == 0 ? w + kPrefetch : w; }

inline void prefetch_l2(const int8_t* base, std::size_t offset) {
#if defined(__GNUC__)
  __builtin_prefetch(base + offset, 0, 2);  // read, keep in L2 (prefetcht1 / prfm pldl2keep)
#else
  (void)base, (void)offset;
#endif
}

// ------------------------------------------------------------------ portable
template <int MR>
inline void tile_portable(const uint8_t* x, int ldx, const int8_t* w, int kpad, const Out& o, int row0, int c0) {
  constexpr int B = 16;
  int32_t acc[MR][B] = {};
  for (int kk = 0; kk < kpad; ++kk) {
    const int8_t* wk = w + kk * B;
    DSSP_QGEMM_UNROLL
    for (int i = 0; i < MR; ++i) {
      const int32_t xv = x[(row0 + i) * ldx + kk];
      for (int c = 0; c < B; ++c) acc[i][c] += xv * wk[c];  // a fixed 16: vectorised whole
    }
  }
  const int lo = std::max(o.n_begin, c0), hi = std::min(o.n_end, c0 + B);
  DSSP_QGEMM_UNROLL
  for (int i = 0; i < MR; ++i) {
    const int r = row0 + i;
    const int32_t z = o.zero[r] - o.zero_offset;
    for (int j = lo; j < hi; ++j) {
      const int32_t v = static_cast<int32_t>(static_cast<uint32_t>(acc[i][j - c0]) - static_cast<uint32_t>(z * o.row_sum[j]));
      o.y[static_cast<std::ptrdiff_t>(r) * o.ldy + j] = dequantize(v, o.x_scale[r], o.w_scale[j], o.bias ? o.bias + j : nullptr);
    }
  }
}

#if defined(DSSP_QGEMM_X86)
// ------------------------------------------------------------------ x86: the 256-bit epilogue (avx2, avx_vnni)
DSSP_QGEMM_TARGET_AVX2 inline __m256i lane_mask(int lo, int hi) {  // all-ones in the lanes j with lo <= j < hi
  const __m256i j = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
  return _mm256_and_si256(_mm256_cmpgt_epi32(j, _mm256_set1_epi32(lo - 1)), _mm256_cmpgt_epi32(_mm256_set1_epi32(hi), j));
}

// sums (rows x 16 int32, 64-byte aligned) -> y, for the block of 16 columns starting at c0. Apart from the
// tiles and not inlined into them: with the epilogue's vectors live beside the accumulators, GCC 12 copies
// and spills accumulators inside the k loop.
DSSP_QGEMM_TARGET_AVX2 __attribute__((noinline)) inline void epilogue_256(const int32_t* sums, int rows, const Out& o, int row0, int c0) {
  const int lo = std::max(o.n_begin, c0) - c0, hi = std::min(o.n_end, c0 + 16) - c0;
  const bool full = lo == 0 && hi == 16;
  __m256i mask[2];
  __m256 ws[2], bias[2];
  __m256i rs[2];
  DSSP_QGEMM_UNROLL
  for (int h = 0; h < 2; ++h) {
    mask[h] = lane_mask(lo - 8 * h, hi - 8 * h);
    const int at = c0 + 8 * h;
    if (full) {
      ws[h] = _mm256_loadu_ps(o.w_scale + at);
      rs[h] = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(o.row_sum + at));
      bias[h] = o.bias ? _mm256_loadu_ps(o.bias + at) : _mm256_setzero_ps();
    } else {  // masked loads: no read past n
      ws[h] = _mm256_maskload_ps(o.w_scale + at, mask[h]);
      rs[h] = _mm256_maskload_epi32(o.row_sum + at, mask[h]);
      bias[h] = o.bias ? _mm256_maskload_ps(o.bias + at, mask[h]) : _mm256_setzero_ps();
    }
  }
  for (int i = 0; i < rows; ++i) {
    const int r = row0 + i;
    const __m256i z = _mm256_set1_epi32(o.zero[r] - o.zero_offset);
    const __m256 xs = _mm256_set1_ps(o.x_scale[r]);
    float* y = o.y + static_cast<std::ptrdiff_t>(r) * o.ldy + c0;
    DSSP_QGEMM_UNROLL
    for (int h = 0; h < 2; ++h) {
      const __m256i acc = _mm256_load_si256(reinterpret_cast<const __m256i*>(sums + 16 * i + 8 * h));
      const __m256 v = _mm256_cvtepi32_ps(_mm256_sub_epi32(acc, _mm256_mullo_epi32(z, rs[h])));
      const __m256 s = _mm256_mul_ps(xs, ws[h]);
      const __m256 out = o.bias ? _mm256_fmadd_ps(v, s, bias[h]) : _mm256_mul_ps(v, s);
      if (full)
        _mm256_storeu_ps(y + 8 * h, out);
      else
        _mm256_maskstore_ps(y + 8 * h, mask[h], out);
    }
  }
}

inline int32_t load_u32(const void* p) {
  int32_t v;
  std::memcpy(&v, p, 4);
  return v;
}

// ------------------------------------------------------------------ avx2: vpmaddwd on 16-bit values
// x16: the activations zero-extended to int16 (m, ldx); per group of 2 k, 32 weight bytes = 16 columns x 2 k,
// sign-extended to two vectors of 8 columns x (k, k + 1) pairs; a broadcast pair of activations times them
// is 8 exact int32 sums of two products (|255 * 128 * 2| < 2^31), added to the accumulators.
template <int MR>
DSSP_QGEMM_TARGET_AVX2 inline void tile_avx2(const int16_t* x16, int ldx, const int8_t* w, int kpad, const Out& o, int row0, int c0) {
  __m256i acc[MR][2];
  DSSP_QGEMM_UNROLL
  for (int i = 0; i < MR; ++i) acc[i][0] = acc[i][1] = _mm256_setzero_si256();
  const int16_t* x = x16 + static_cast<std::ptrdiff_t>(row0) * ldx;
  const int8_t* pf = prefetch_base(w, row0);
  for (int g = 0; g < kpad / 2; ++g) {
    if constexpr (MR >= kPrefetchRows) prefetch_l2(pf, 32 * g);
    const __m256i w0 = _mm256_cvtepi8_epi16(_mm_load_si128(reinterpret_cast<const __m128i*>(w + 32 * g)));
    const __m256i w1 = _mm256_cvtepi8_epi16(_mm_load_si128(reinterpret_cast<const __m128i*>(w + 32 * g + 16)));
    DSSP_QGEMM_UNROLL
    for (int i = 0; i < MR; ++i) {
      const __m256i xb = _mm256_set1_epi32(load_u32(x + i * ldx + 2 * g));
      acc[i][0] = _mm256_add_epi32(acc[i][0], _mm256_madd_epi16(xb, w0));
      acc[i][1] = _mm256_add_epi32(acc[i][1], _mm256_madd_epi16(xb, w1));
    }
  }
  alignas(64) int32_t sums[MR * 16];
  DSSP_QGEMM_UNROLL
  for (int i = 0; i < MR; ++i) {
    _mm256_store_si256(reinterpret_cast<__m256i*>(sums + 16 * i), acc[i][0]);
    _mm256_store_si256(reinterpret_cast<__m256i*>(sums + 16 * i + 8), acc[i][1]);
  }
  epilogue_256(sums, MR, o, row0, c0);
}

DSSP_QGEMM_TARGET_AVX2 inline void widen_avx2(const uint8_t* src, int16_t* dst, std::size_t count) {  // count: a multiple of 16
  for (std::size_t i = 0; i < count; i += 16)
    _mm256_store_si256(reinterpret_cast<__m256i*>(dst + i),
                       _mm256_cvtepu8_epi16(_mm_load_si128(reinterpret_cast<const __m128i*>(src + i))));
}

// ------------------------------------------------------------------ avx_vnni: vpdpbusd on 256-bit vectors
// per group of 4 k, 64 weight bytes = 16 columns x 4 k; a broadcast of 4 activation bytes, u8 x s8, four
// products added into each int32 lane (exact: no saturation in vpdpbusd). Written once for both encodings.
#define DSSP_QGEMM_VNNI256_TILE(NAME, TARGET, DPBUSD)                                                            \
  template <int MR>                                                                                              \
  TARGET inline void NAME(const uint8_t* x, int ldx, const int8_t* w, int kpad, const Out& o, int row0, int c0) { \
    __m256i acc[MR][2];                                                                                          \
    DSSP_QGEMM_UNROLL                                                                                            \
    for (int i = 0; i < MR; ++i) acc[i][0] = acc[i][1] = _mm256_setzero_si256();                                 \
    const uint8_t* xr = x + static_cast<std::ptrdiff_t>(row0) * ldx;                                             \
    const int8_t* pf = prefetch_base(w, row0);                                                               \
    for (int g = 0; g < kpad / 4; ++g) {                                                                         \
      if constexpr (MR >= kPrefetchRows) prefetch_l2(pf, 64 * g);                                                \
      const __m256i w0 = _mm256_load_si256(reinterpret_cast<const __m256i*>(w + 64 * g));                        \
      const __m256i w1 = _mm256_load_si256(reinterpret_cast<const __m256i*>(w + 64 * g + 32));                   \
      DSSP_QGEMM_UNROLL                                                                                          \
      for (int i = 0; i < MR; ++i) {                                                                             \
        const __m256i xb = _mm256_set1_epi32(load_u32(xr + i * ldx + 4 * g));                                    \
        acc[i][0] = DPBUSD(acc[i][0], xb, w0);                                                                   \
        acc[i][1] = DPBUSD(acc[i][1], xb, w1);                                                                   \
      }                                                                                                          \
    }                                                                                                            \
    alignas(64) int32_t sums[MR * 16];                                                                           \
    DSSP_QGEMM_UNROLL                                                                                            \
    for (int i = 0; i < MR; ++i) {                                                                               \
      _mm256_store_si256(reinterpret_cast<__m256i*>(sums + 16 * i), acc[i][0]);                                  \
      _mm256_store_si256(reinterpret_cast<__m256i*>(sums + 16 * i + 8), acc[i][1]);                              \
    }                                                                                                            \
    epilogue_256(sums, MR, o, row0, c0);                                                                         \
  }

DSSP_QGEMM_VNNI256_TILE(tile_avx_vnni, DSSP_QGEMM_TARGET_AVX_VNNI, _mm256_dpbusd_avx_epi32)
DSSP_QGEMM_VNNI256_TILE(tile_avx_vnni_evex, DSSP_QGEMM_TARGET_AVX_VNNI_EVEX, _mm256_dpbusd_epi32)
#undef DSSP_QGEMM_VNNI256_TILE

// ------------------------------------------------------------------ avx512_vnni: vpdpbusd on 512-bit vectors
#if !defined(__clang__)
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wuninitialized"  // GCC 12's avx512fintrin.h (_mm512_undefined_*), not this code
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#endif
// sums (rows x 32 int32, 64-byte aligned) -> y, for the block of 32 columns starting at c0 (as epilogue_256).
DSSP_QGEMM_TARGET_AVX512_VNNI __attribute__((noinline)) inline void epilogue_512(const int32_t* sums, int rows, const Out& o, int row0,
                                                                                int c0) {
  const int lo = std::max(o.n_begin, c0) - c0, hi = std::min(o.n_end, c0 + 32) - c0;
  const uint32_t bits = static_cast<uint32_t>((hi >= 32 ? ~0ull : (1ull << hi) - 1) & ~((1ull << lo) - 1));
  const __mmask16 mask[2] = {static_cast<__mmask16>(bits), static_cast<__mmask16>(bits >> 16)};
  __m512 ws[2], bias[2];
  __m512i rs[2];
  DSSP_QGEMM_UNROLL
  for (int h = 0; h < 2; ++h) {  // masked loads: no read past n
    ws[h] = _mm512_maskz_loadu_ps(mask[h], o.w_scale + c0 + 16 * h);
    rs[h] = _mm512_maskz_loadu_epi32(mask[h], o.row_sum + c0 + 16 * h);
    bias[h] = o.bias ? _mm512_maskz_loadu_ps(mask[h], o.bias + c0 + 16 * h) : _mm512_setzero_ps();
  }
  for (int i = 0; i < rows; ++i) {
    const int r = row0 + i;
    const __m512i z = _mm512_set1_epi32(o.zero[r] - o.zero_offset);
    const __m512 xs = _mm512_set1_ps(o.x_scale[r]);
    float* y = o.y + static_cast<std::ptrdiff_t>(r) * o.ldy + c0;
    DSSP_QGEMM_UNROLL
    for (int h = 0; h < 2; ++h) {
      const __m512i acc = _mm512_load_si512(sums + 32 * i + 16 * h);
      const __m512 v = _mm512_cvtepi32_ps(_mm512_sub_epi32(acc, _mm512_mullo_epi32(z, rs[h])));
      const __m512 s = _mm512_mul_ps(xs, ws[h]);
      const __m512 out = o.bias ? _mm512_fmadd_ps(v, s, bias[h]) : _mm512_mul_ps(v, s);
      _mm512_mask_storeu_ps(y + 16 * h, mask[h], out);
    }
  }
}
#if !defined(__clang__)
#pragma GCC diagnostic pop
#endif

// per group of 4 k, 128 weight bytes = 32 columns x 4 k (two vectors); MR rows x 2 accumulators.
template <int MR>
DSSP_QGEMM_TARGET_AVX512_VNNI inline void tile_avx512_vnni(const uint8_t* x, int ldx, const int8_t* w, int kpad, const Out& o,
                                                          int row0, int c0) {
  __m512i acc[MR][2];
  DSSP_QGEMM_UNROLL
  for (int i = 0; i < MR; ++i) acc[i][0] = acc[i][1] = _mm512_setzero_si512();
  const uint8_t* xr = x + static_cast<std::ptrdiff_t>(row0) * ldx;
  const int8_t* pf = prefetch_base(w, row0);
  for (int g = 0; g < kpad / 4; ++g) {
    if constexpr (MR >= kPrefetchRows) prefetch_l2(pf, 128 * g);
    if constexpr (MR >= kPrefetchRows) prefetch_l2(pf, 128 * g + 64);
    const __m512i w0 = _mm512_load_si512(w + 128 * g);
    const __m512i w1 = _mm512_load_si512(w + 128 * g + 64);
    DSSP_QGEMM_UNROLL
    for (int i = 0; i < MR; ++i) {
      const __m512i xb = _mm512_set1_epi32(load_u32(xr + i * ldx + 4 * g));
      acc[i][0] = _mm512_dpbusd_epi32(acc[i][0], xb, w0);
      acc[i][1] = _mm512_dpbusd_epi32(acc[i][1], xb, w1);
    }
  }
  alignas(64) int32_t sums[MR * 32];
  DSSP_QGEMM_UNROLL
  for (int i = 0; i < MR; ++i) {
    _mm512_store_si512(sums + 32 * i, acc[i][0]);
    _mm512_store_si512(sums + 32 * i + 16, acc[i][1]);
  }
  epilogue_512(sums, MR, o, row0, c0);
}
#endif  // DSSP_QGEMM_X86

#if defined(DSSP_QGEMM_ARM)
// ------------------------------------------------------------------ aarch64: the 128-bit epilogue (neon, neon_dot)
// sums (rows x 8 int32) -> y, for the block of 8 columns starting at c0 (as epilogue_256).
__attribute__((noinline)) inline void epilogue_neon(const int32_t* sums, int rows, const Out& o, int row0, int c0) {
  const int lo = std::max(o.n_begin, c0) - c0, hi = std::min(o.n_end, c0 + 8) - c0;
  const bool full = lo == 0 && hi == 8;
  float ws_buf[8] = {}, bias_buf[8] = {};
  int32_t rs_buf[8] = {};
  for (int j = lo; j < hi; ++j) {  // only the columns inside the range: no read past n
    ws_buf[j] = o.w_scale[c0 + j];
    rs_buf[j] = o.row_sum[c0 + j];
    if (o.bias) bias_buf[j] = o.bias[c0 + j];
  }
  float32x4_t ws[2], bias[2];
  int32x4_t rs[2];
  DSSP_QGEMM_UNROLL
  for (int h = 0; h < 2; ++h) {
    ws[h] = vld1q_f32(ws_buf + 4 * h);
    rs[h] = vld1q_s32(rs_buf + 4 * h);
    bias[h] = vld1q_f32(bias_buf + 4 * h);
  }
  for (int i = 0; i < rows; ++i) {
    const int r = row0 + i;
    const int32x4_t z = vdupq_n_s32(o.zero[r] - o.zero_offset);
    float* y = o.y + static_cast<std::ptrdiff_t>(r) * o.ldy + c0;
    float out[8];
    DSSP_QGEMM_UNROLL
    for (int h = 0; h < 2; ++h) {
      const float32x4_t v = vcvtq_f32_s32(vmlsq_s32(vld1q_s32(sums + 8 * i + 4 * h), z, rs[h]));  // wraps like int32: exact result
      const float32x4_t s = vmulq_n_f32(ws[h], o.x_scale[r]);
      vst1q_f32(out + 4 * h, o.bias ? vfmaq_f32(bias[h], v, s) : vmulq_f32(v, s));
    }
    if (full)
      std::memcpy(y, out, sizeof out);
    else
      for (int j = lo; j < hi; ++j) y[j] = out[j];
  }
}

// ------------------------------------------------------------------ neon: smlal by element on 16-bit values
// 8 k of each row zero-extended to 16 bits in a register; per k, 8 weight bytes = 8 columns sign-extended
// to 16 bits, times lane kk of each row, accumulated in int32 (exact: |255 * 128| per product).
template <int MR, int L>
inline void neon_step(int32x4_t (&acc)[MR][2], const int16x8_t (&xv)[MR], const int8_t* wk) {
  const int16x8_t wv = vmovl_s8(vld1_s8(wk));
  DSSP_QGEMM_UNROLL
  for (int i = 0; i < MR; ++i) {
    acc[i][0] = vmlal_laneq_s16(acc[i][0], vget_low_s16(wv), xv[i], L);
    acc[i][1] = vmlal_high_laneq_s16(acc[i][1], wv, xv[i], L);
  }
}

template <int MR>
inline void tile_neon(const uint8_t* x, int ldx, const int8_t* w, int kpad, const Out& o, int row0, int c0) {
  int32x4_t acc[MR][2];
  DSSP_QGEMM_UNROLL
  for (int i = 0; i < MR; ++i) acc[i][0] = acc[i][1] = vdupq_n_s32(0);
  const uint8_t* xr = x + static_cast<std::ptrdiff_t>(row0) * ldx;
  const int8_t* pf = prefetch_base(w, row0);
  for (int kk = 0; kk < kpad; kk += 8) {
    if constexpr (MR >= kPrefetchRows) prefetch_l2(pf, 8 * kk);
    int16x8_t xv[MR];
    DSSP_QGEMM_UNROLL
    for (int i = 0; i < MR; ++i) xv[i] = vreinterpretq_s16_u16(vmovl_u8(vld1_u8(xr + i * ldx + kk)));
    const int8_t* wk = w + 8 * kk;
    neon_step<MR, 0>(acc, xv, wk);
    neon_step<MR, 1>(acc, xv, wk + 8);
    neon_step<MR, 2>(acc, xv, wk + 16);
    neon_step<MR, 3>(acc, xv, wk + 24);
    neon_step<MR, 4>(acc, xv, wk + 32);
    neon_step<MR, 5>(acc, xv, wk + 40);
    neon_step<MR, 6>(acc, xv, wk + 48);
    neon_step<MR, 7>(acc, xv, wk + 56);
  }
  int32_t sums[MR * 8];
  DSSP_QGEMM_UNROLL
  for (int i = 0; i < MR; ++i) {
    vst1q_s32(sums + 8 * i, acc[i][0]);
    vst1q_s32(sums + 8 * i + 4, acc[i][1]);
  }
  epilogue_neon(sums, MR, o, row0, c0);
}

// ------------------------------------------------------------------ neon_dot: sdot by element
// sdot multiplies int8 by int8, so the activations enter as xq - 128 (an exclusive-or of the top bit) and
// the epilogue adds 128 * row_sum back (zero_offset). 16 k of each row in a register (4 groups of 4); per
// group, 32 weight bytes = 8 columns x 4 k, two vectors, times group L of each row.
template <int MR, int L>
DSSP_QGEMM_TARGET_NEON_DOT inline void neon_dot_step(int32x4_t (&acc)[MR][2], const int8x16_t (&xv)[MR], const int8_t* wg) {
  const int8x16_t w0 = vld1q_s8(wg), w1 = vld1q_s8(wg + 16);
  DSSP_QGEMM_UNROLL
  for (int i = 0; i < MR; ++i) {
    acc[i][0] = vdotq_laneq_s32(acc[i][0], w0, xv[i], L);
    acc[i][1] = vdotq_laneq_s32(acc[i][1], w1, xv[i], L);
  }
}

template <int MR>
DSSP_QGEMM_TARGET_NEON_DOT inline void tile_neon_dot(const uint8_t* x, int ldx, const int8_t* w, int kpad, const Out& o, int row0, int c0) {
  int32x4_t acc[MR][2];
  DSSP_QGEMM_UNROLL
  for (int i = 0; i < MR; ++i) acc[i][0] = acc[i][1] = vdupq_n_s32(0);
  const uint8_t* xr = x + static_cast<std::ptrdiff_t>(row0) * ldx;
  const uint8x16_t flip = vdupq_n_u8(0x80);
  const int8_t* pf = prefetch_base(w, row0);
  for (int kk = 0; kk < kpad; kk += 16) {
    if constexpr (MR >= kPrefetchRows) prefetch_l2(pf, 8 * kk);
    if constexpr (MR >= kPrefetchRows) prefetch_l2(pf, 8 * kk + 64);
    int8x16_t xv[MR];
    DSSP_QGEMM_UNROLL
    for (int i = 0; i < MR; ++i) xv[i] = vreinterpretq_s8_u8(veorq_u8(vld1q_u8(xr + i * ldx + kk), flip));
    const int8_t* wg = w + 8 * kk;  // 4 groups of 32 bytes
    neon_dot_step<MR, 0>(acc, xv, wg);
    neon_dot_step<MR, 1>(acc, xv, wg + 32);
    neon_dot_step<MR, 2>(acc, xv, wg + 64);
    neon_dot_step<MR, 3>(acc, xv, wg + 96);
  }
  int32_t sums[MR * 8];
  DSSP_QGEMM_UNROLL
  for (int i = 0; i < MR; ++i) {
    vst1q_s32(sums + 8 * i, acc[i][0]);
    vst1q_s32(sums + 8 * i + 4, acc[i][1]);
  }
  epilogue_neon(sums, MR, o, row0, c0);
}
#endif  // DSSP_QGEMM_ARM

// One row tile of `rows` rows for one block of columns: K<MR>, a path's tile for MR rows (a compile-time
// constant, so that its accumulators live in registers), chosen among MR = 1..MR_MAX.
template <template <int> class K, int MR_MAX, class X>
inline void run_tile(int rows, const X* x, int ldx, const int8_t* w, int kpad, const Out& o, int row0, int c0) {
  if constexpr (MR_MAX >= 1) {
    if (rows == MR_MAX) return K<MR_MAX>::run(x, ldx, w, kpad, o, row0, c0);
    return run_tile<K, MR_MAX - 1>(rows, x, ldx, w, kpad, o, row0, c0);
  }
}

#define DSSP_QGEMM_KERNEL(NAME, FN, X)                                                                      \
  template <int MR>                                                                                         \
  struct NAME {                                                                                             \
    static void run(const X* x, int ldx, const int8_t* w, int kpad, const Out& o, int row0, int c0) {       \
      FN<MR>(x, ldx, w, kpad, o, row0, c0);                                                                 \
    }                                                                                                       \
  };
DSSP_QGEMM_KERNEL(KernelPortable, tile_portable, uint8_t)
#if defined(DSSP_QGEMM_X86)
DSSP_QGEMM_KERNEL(KernelAvx2, tile_avx2, int16_t)
DSSP_QGEMM_KERNEL(KernelAvxVnni, tile_avx_vnni, uint8_t)
DSSP_QGEMM_KERNEL(KernelAvxVnniEvex, tile_avx_vnni_evex, uint8_t)
DSSP_QGEMM_KERNEL(KernelAvx512Vnni, tile_avx512_vnni, uint8_t)
#endif
#if defined(DSSP_QGEMM_ARM)
DSSP_QGEMM_KERNEL(KernelNeon, tile_neon, uint8_t)
DSSP_QGEMM_KERNEL(KernelNeonDot, tile_neon_dot, uint8_t)
#endif
#undef DSSP_QGEMM_KERNEL

// Every block touching [n_begin, n_end), and in each the rows in balanced tiles of at most MR_MAX (a tile
// streams its block's weights once; the second tile of 13..16 rows finds them in L1/L2).
template <template <int> class K, int MR_MAX, class X>
inline void run_blocks(int m, const X* x, int ldx, const PackedWeights& w, const Out& o) {
  const int block = w.block;
  const int tiles = (m + MR_MAX - 1) / MR_MAX;
  const std::size_t block_bytes = static_cast<std::size_t>(block) * w.kpad;
  for (int b = o.n_begin / block; b * block < o.n_end; ++b) {
    const int8_t* wb = w.data.data() + b * block_bytes;
    for (int t = 0, row0 = 0; t < tiles; ++t) {
      const int rows = (m - row0) / (tiles - t);
      run_tile<K, MR_MAX>(rows, x, ldx, wb, w.kpad, o, row0, b * block);
      row0 += rows;
    }
  }
}

// The packing every path shares (its Layout): q (n, k) row-major -> blocks, zeros beyond n and k.
inline void pack_into(PackedWeights& p, const int8_t* q) {
  const Layout L = layout(p.path);
  p.block = L.block;
  p.kpad = padded_k(p.k);
  const int blocks = (p.n + L.block - 1) / L.block;
  p.data.assign(static_cast<std::size_t>(blocks) * L.block * p.kpad, 0);
  p.row_sum.assign(p.n, 0);
  for (int j = 0; j < p.n; ++j) {
    int8_t* blk = p.data.data() + static_cast<std::size_t>(j / L.block) * L.block * p.kpad;
    const int c = j % L.block;
    int32_t sum = 0;
    for (int kk = 0; kk < p.k; ++kk) {
      const int8_t v = q[static_cast<std::size_t>(j) * p.k + kk];
      blk[(kk / L.group) * (L.block * L.group) + c * L.group + kk % L.group] = v;
      sum += v;
    }
    p.row_sum[j] = sum;
  }
}

inline void check_shape(const char* rows, int n, int k) {
  if (n < 0 || k < 0) fail(std::string("negative shape (") + rows + " " + std::to_string(n) + ", k " + std::to_string(k) + ")");
  if (k > kMaxK) fail("k = " + std::to_string(k) + " is above " + std::to_string(kMaxK) + ", where the int32 sums could overflow");
}

// pack_quantized for any path, runnable here or not (qgemm_check packs avx_vnni's layout for its EVEX twin).
inline PackedWeights pack_unchecked(const int8_t* q, const float* scale, int n, int k, Path path) {
  check_shape("n", n, k);
  PackedWeights p;
  p.n = n;
  p.k = k;
  p.path = path;
  p.scale.assign(scale, scale + n);
  pack_into(p, q);
  return p;
}

inline void check_range(const QuantizedRows& x, const PackedWeights& w, int ldy, int n_begin, int n_end) {
  if (x.k != w.k) fail("the activations have k = " + std::to_string(x.k) + ", the weights " + std::to_string(w.k));
  if (n_begin < 0 || n_end > w.n || n_begin > n_end)
    fail("columns [" + std::to_string(n_begin) + ", " + std::to_string(n_end) + ") are not inside [0, " + std::to_string(w.n) + ")");
  if (ldy < n_end) fail("ldy = " + std::to_string(ldy) + " is below the last column written (" + std::to_string(n_end) + ")");
}

inline Out make_out(const QuantizedRows& x, const PackedWeights& w, const float* bias, float* y, int ldy, int n_begin, int n_end,
                    int32_t zero_offset) {
  return Out{x.scale.data(), x.zero.data(), zero_offset, w.scale.data(), w.row_sum.data(), bias, y, ldy, n_begin, n_end};
}

#if defined(DSSP_QGEMM_X86)
// avx_vnni's kernel through the EVEX encoding of vpdpbusd (AVX512_VNNI + VL): w packed for kAvxVnni.
inline void matmul_range_avx_vnni_evex(const QuantizedRows& x, const PackedWeights& w, const float* bias, float* y, int ldy,
                                       int n_begin, int n_end) {
  check_range(x, w, ldy, n_begin, n_end);
  if (w.path != Path::kAvxVnni) fail("the EVEX check needs weights packed for avx_vnni");
  if (x.m == 0 || n_begin == n_end) return;
  const Out o = make_out(x, w, bias, y, ldy, n_begin, n_end, 0);
  run_blocks<KernelAvxVnniEvex, layout(Path::kAvxVnni).max_rows>(x.m, x.data.data(), x.stride, w, o);
}
#endif

}  // namespace detail

// x (m, k) row-major fp32 -> per-row asymmetric uint8 with the quantiser of `path`'s instruction set (all
// give the same bytes; a path this CPU cannot run is refused): scale = (max - min) / 255 over the row with 0 included, zero point round(-min /
// scale) in 0..255, q = clamp(round(x / scale) + zero, 0, 255), rounding half to even.
inline void quantize_rows(const float* x, int m, int k, QuantizedRows& out, Path path) {
  detail::check_shape("m", m, k);
  const std::string why = path_unavailable_reason(path);  // its quantiser's instructions
  if (!why.empty()) detail::fail(std::string("cannot quantise for ") + path_name(path) + ": " + why);
  out.m = m;
  out.k = k;
  out.stride = padded_k(k);
  out.data.resize(static_cast<std::size_t>(m) * out.stride);
  out.scale.resize(m);
  out.zero.resize(m);
  for (int i = 0; i < m; ++i) {
    const float* xi = x + static_cast<std::ptrdiff_t>(i) * k;
    uint8_t* qi = out.data.data() + static_cast<std::size_t>(i) * out.stride;
    if (out.stride > k) std::memset(qi + k, 0, out.stride - k);  // the weights are zero there: any value would do
    switch (path) {
#if defined(DSSP_QGEMM_X86)
      case Path::kAvx2:
      case Path::kAvxVnni:
      case Path::kAvx512Vnni: detail::quantize_row_avx2(xi, k, qi, &out.scale[i], &out.zero[i]); break;
#endif
#if defined(DSSP_QGEMM_ARM)
      case Path::kNeon:
      case Path::kNeonDot: detail::quantize_row_neon(xi, k, qi, &out.scale[i], &out.zero[i]); break;
#endif
      default: detail::quantize_row_scalar(xi, k, qi, &out.scale[i], &out.zero[i]);
    }
  }
}

// The same with best_path()'s quantiser.
inline void quantize_rows(const float* x, int m, int k, QuantizedRows& out) { quantize_rows(x, m, k, out, best_path()); }

// Already-quantized weights, int8 (n, k) row-major and their per-row scales, packed for `path`. A path this
// CPU cannot run is refused (std::invalid_argument), so packed weights always run where they were packed.
inline PackedWeights pack_quantized(const int8_t* q, const float* scale, int n, int k, Path path) {
  const std::string why = path_unavailable_reason(path);
  if (!why.empty()) detail::fail(std::string("cannot pack for ") + path_name(path) + ": " + why);
  return detail::pack_unchecked(q, scale, n, k, path);
}

// W (n, k) row-major fp32 -> symmetric int8 per output row: scale = max|W[n, :]| / 127, q = round half to
// even of W / scale (in -127..127); a row of zeros gets scale 1. Non-finite weights are refused.
inline PackedWeights pack(const float* w, int n, int k, Path path) {
  detail::check_shape("n", n, k);
  std::vector<int8_t> q(static_cast<std::size_t>(n) * k);
  std::vector<float> scale(n);
  for (int j = 0; j < n; ++j) {
    const float* row = w + static_cast<std::size_t>(j) * k;
    float amax = 0.0f;
    for (int kk = 0; kk < k; ++kk) {
      if (!std::isfinite(row[kk])) detail::fail("weight (" + std::to_string(j) + ", " + std::to_string(kk) + ") is not finite");
      amax = std::max(amax, std::fabs(row[kk]));
    }
    scale[j] = amax > 0.0f ? amax / 127.0f : 1.0f;
    for (int kk = 0; kk < k; ++kk) {
      const float v = detail::round_even(detail::clamp_not_nan(row[kk] / scale[j], -127.0f, 127.0f));
      q[static_cast<std::size_t>(j) * k + kk] = static_cast<int8_t>(v);
    }
  }
  return pack_quantized(q.data(), scale.data(), n, k, path);
}

// y[i, j] = x_scale[i] * w_scale[j] * sum_k (xq[i, k] - zero[i]) * wq[j, k] (+ bias[j] if bias), for the
// output columns j in [n_begin, n_end) (threads split the columns, best at multiples of w.block); y has
// leading dimension ldy. The columns outside the range are not touched.
inline void matmul_range(const QuantizedRows& x, const PackedWeights& w, const float* bias, float* y, int ldy, int n_begin, int n_end) {
  detail::check_range(x, w, ldy, n_begin, n_end);
  if (x.m == 0 || n_begin == n_end) return;
  const uint8_t* xq = x.data.data();
  const detail::Out o = detail::make_out(x, w, bias, y, ldy, n_begin, n_end, w.path == Path::kNeonDot ? 128 : 0);
  using namespace detail;
  switch (w.path) {
#if defined(DSSP_QGEMM_X86)
    case Path::kAvx512Vnni: return run_blocks<KernelAvx512Vnni, layout(Path::kAvx512Vnni).max_rows>(x.m, xq, x.stride, w, o);
    case Path::kAvxVnni: return run_blocks<KernelAvxVnni, layout(Path::kAvxVnni).max_rows>(x.m, xq, x.stride, w, o);
    case Path::kAvx2: {
      // vpmaddwd takes the activations as 16-bit pairs: widened once per call (m x k x 2 bytes, L1-sized
      // for the shapes here), into a buffer of this thread's, so threads sharing x never share it
      thread_local AlignedVector<int16_t> wide;
      const std::size_t count = static_cast<std::size_t>(x.m) * x.stride;
      if (wide.size() < count) wide.resize(count);
      widen_avx2(xq, wide.data(), count);
      return run_blocks<KernelAvx2, layout(Path::kAvx2).max_rows>(x.m, wide.data(), x.stride, w, o);
    }
#endif
#if defined(DSSP_QGEMM_ARM)
    case Path::kNeonDot: return run_blocks<KernelNeonDot, layout(Path::kNeonDot).max_rows>(x.m, xq, x.stride, w, o);
    case Path::kNeon: return run_blocks<KernelNeon, layout(Path::kNeon).max_rows>(x.m, xq, x.stride, w, o);
#endif
    case Path::kPortable: return run_blocks<KernelPortable, layout(Path::kPortable).max_rows>(x.m, xq, x.stride, w, o);
    default: fail(std::string("weights packed for ") + path_name(w.path) + ", which this build cannot run");
  }
}

// quantize_rows (the weights' path's quantiser) + matmul_range over all columns, on this thread; y is (m, n).
inline void matmul(const float* x, int m, const PackedWeights& w, const float* bias, float* y) {
  thread_local QuantizedRows rows;
  quantize_rows(x, m, w.k, rows, w.path);
  matmul_range(rows, w, bias, y, w.n, 0, w.n);
}

}  // namespace dssp::qgemm
