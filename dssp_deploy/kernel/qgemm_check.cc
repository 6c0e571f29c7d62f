// Parity and speed harness for qgemm.h (tests/test_qgemm.py builds and runs it, natively and under qemu).
//
//   qgemm_check           every path this build and CPU run against a plain C++ reference on random shapes
//                         (m 1..16, n and k odd and even, not multiples of the blocks): exact equality of every
//                         output bit, of the quantised activations, of pack against pack_quantized, and the
//                         quantisation's own checks (constant rows, zeros, huge and tiny magnitudes)
//   qgemm_check --bench   the same, then the time of 12-row products per path (every available path, or the
//                         one DSSP_QGEMM_PATH names) and the weight bytes they read per second
//
// Prints one JSON line; exit status 0 when every path run matched, 1 when one did not, 2 when DSSP_QGEMM_PATH
// names a path this CPU cannot run.

#include "qgemm.h"

#include <algorithm>
#include <chrono>
#include <cinttypes>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <random>
#include <string>
#include <thread>
#include <vector>

using namespace dssp::qgemm;

namespace {

// ------------------------------------------------------------------ the reference: plain C++, written apart
// from the library's code (std::nearbyint for its rounding, int64 sums).
struct RefRows {
  std::vector<uint8_t> q;  // (m, k)
  std::vector<float> scale;
  std::vector<int32_t> zero;
};

RefRows ref_quantize(const std::vector<float>& x, int m, int k) {
  RefRows r{std::vector<uint8_t>(static_cast<size_t>(m) * k), std::vector<float>(m), std::vector<int32_t>(m)};
  for (int i = 0; i < m; ++i) {
    const float* row = x.data() + static_cast<size_t>(i) * k;
    float mn = 0.0f, mx = 0.0f;
    for (int j = 0; j < k; ++j) {
      mn = std::min(mn, row[j]);
      mx = std::max(mx, row[j]);
    }
    float s = static_cast<float>((static_cast<double>(mx) - static_cast<double>(mn)) / 255.0);
    int32_t z = 0;
    if (s > 0.0f)
      z = static_cast<int32_t>(std::nearbyint(std::min(std::max(-mn / s, 0.0f), 255.0f)));
    else
      s = 1.0f;
    r.scale[i] = s;
    r.zero[i] = z;
    for (int j = 0; j < k; ++j) {
      const float v = std::min(std::max(row[j] / s, -256.0f), 256.0f);
      r.q[static_cast<size_t>(i) * k + j] = static_cast<uint8_t>(std::min(std::max(static_cast<int>(std::nearbyint(v)) + z, 0), 255));
    }
  }
  return r;
}

struct RefWeights {
  std::vector<int8_t> q;
  std::vector<float> scale;
  std::vector<int32_t> row_sum;
};

RefWeights ref_weights(const std::vector<float>& w, int n, int k) {
  RefWeights r{std::vector<int8_t>(static_cast<size_t>(n) * k), std::vector<float>(n), std::vector<int32_t>(n, 0)};
  for (int j = 0; j < n; ++j) {
    float amax = 0.0f;
    for (int kk = 0; kk < k; ++kk) amax = std::max(amax, std::fabs(w[static_cast<size_t>(j) * k + kk]));
    r.scale[j] = amax > 0.0f ? amax / 127.0f : 1.0f;
    for (int kk = 0; kk < k; ++kk) {
      const float v = std::nearbyint(w[static_cast<size_t>(j) * k + kk] / r.scale[j]);
      const int8_t q = static_cast<int8_t>(std::min(std::max(v, -127.0f), 127.0f));
      r.q[static_cast<size_t>(j) * k + kk] = q;
      r.row_sum[j] += q;
    }
  }
  return r;
}

// y (m, n): the dequantisation the library promises, from int64 sums that must fit int32.
std::vector<float> ref_matmul(const RefRows& x, const std::vector<int8_t>& wq, const std::vector<float>& ws, const float* bias,
                              int m, int n, int k, bool* overflow) {
  std::vector<float> y(static_cast<size_t>(m) * n);
  for (int i = 0; i < m; ++i)
    for (int j = 0; j < n; ++j) {
      int64_t acc = 0;
      for (int kk = 0; kk < k; ++kk)
        acc += (static_cast<int64_t>(x.q[static_cast<size_t>(i) * k + kk]) - x.zero[i]) * wq[static_cast<size_t>(j) * k + kk];
      if (acc != static_cast<int32_t>(acc)) *overflow = true;
      const float v = static_cast<float>(static_cast<int32_t>(acc)), s = x.scale[i] * ws[j];
      y[static_cast<size_t>(i) * n + j] = bias ? std::fma(v, s, bias[j]) : v * s;
    }
  return y;
}

bool same_bits(float a, float b) { return std::memcmp(&a, &b, sizeof a) == 0; }

std::string json_str(const std::string& s) {
  std::string out = "\"";
  for (char c : s) {
    if (c == '"' || c == '\\') out += '\\';
    out += c;
  }
  return out + "\"";
}

// ------------------------------------------------------------------ the inputs
struct Case {
  int m, n, k;
};

std::vector<float> activations(std::mt19937& rng, int m, int k) {
  std::normal_distribution<float> normal(0.0f, 1.0f);
  std::vector<float> x(static_cast<size_t>(m) * k);
  for (int i = 0; i < m; ++i) {
    float* row = x.data() + static_cast<size_t>(i) * k;
    const int kind = static_cast<int>(rng() % 6);
    const float scale = std::pow(10.0f, static_cast<float>(static_cast<int>(rng() % 9)) - 4.0f);  // 1e-4 .. 1e4
    for (int j = 0; j < k; ++j) {
      const float v = normal(rng) * scale;
      row[j] = kind == 0 ? std::fabs(v) : kind == 1 ? -std::fabs(v) : kind == 2 ? v + 3.0f * scale : v;
    }
    if (kind == 4) std::fill(row, row + k, 0.0f);
    if (kind == 5 && k > 2) row[rng() % k] = scale * 50.0f;  // one outlier
  }
  return x;
}

std::vector<float> weights(std::mt19937& rng, int n, int k) {
  std::normal_distribution<float> normal(0.0f, 1.0f);
  std::vector<float> w(static_cast<size_t>(n) * k);
  for (int j = 0; j < n; ++j) {
    const float scale = std::pow(10.0f, static_cast<float>(static_cast<int>(rng() % 7)) - 3.0f);
    for (int kk = 0; kk < k; ++kk) w[static_cast<size_t>(j) * k + kk] = normal(rng) * scale;
  }
  if (n > 2) std::fill(w.begin() + static_cast<size_t>(n / 2) * k, w.begin() + static_cast<size_t>(n / 2 + 1) * k, 0.0f);
  return w;
}

// The cases: small and odd shapes first, then random ones (kept small: the check also runs under qemu).
std::vector<Case> cases(std::mt19937& rng) {
  std::vector<Case> out = {{1, 1, 1},   {16, 1, 1},   {1, 33, 17},  {16, 33, 17}, {12, 64, 64},  {13, 97, 129},
                           {16, 31, 255}, {5, 1, 300}, {7, 200, 1},  {12, 48, 16}, {2, 65, 80},   {11, 130, 47},
                           {3, 5, 0},     {2, 0, 7}};  // k = 0: y is the bias; n = 0: nothing to write
  for (int t = 0; t < 28; ++t)
    out.push_back({1 + static_cast<int>(rng() % 16), 1 + static_cast<int>(rng() % 160), 1 + static_cast<int>(rng() % 260)});
  return out;
}

// ------------------------------------------------------------------ the checks of one path
struct Result {
  std::string status = "matched";  // or the first mismatch
  int products = 0;
};

void mismatch(Result& r, const std::string& what) {
  if (r.status == "matched") r.status = what;
}

std::string where(const Case& c, const char* what) {
  return std::string(what) + " at m=" + std::to_string(c.m) + " n=" + std::to_string(c.n) + " k=" + std::to_string(c.k);
}

using RangeFn = void (*)(const QuantizedRows&, const PackedWeights&, const float*, float*, int, int, int);

// y over [n_begin, n_end) with leading dimension ldy, the other columns holding a sentinel, against the reference.
void check_product(Result& r, const Case& c, const QuantizedRows& qx, const PackedWeights& pw, RangeFn fn, const float* bias,
                   const std::vector<float>& ref, int n_begin, int n_end, int ldy) {
  const float sentinel = -1234.5f;
  std::vector<float> y(static_cast<size_t>(c.m) * ldy, sentinel);
  fn(qx, pw, bias, y.data(), ldy, n_begin, n_end);
  ++r.products;
  for (int i = 0; i < c.m; ++i)
    for (int j = 0; j < ldy; ++j) {
      const float got = y[static_cast<size_t>(i) * ldy + j];
      const bool inside = j >= n_begin && j < n_end;
      const float want = inside ? ref[static_cast<size_t>(i) * c.n + j] : sentinel;
      if (!same_bits(got, want)) {
        char buf[200];
        std::snprintf(buf, sizeof buf, " (columns %d..%d%s): y[%d, %d] = %.9g, want %.9g", n_begin, n_end, bias ? ", bias" : "", i, j,
                      static_cast<double>(got), static_cast<double>(want));
        return mismatch(r, where(c, inside ? "product" : "a column outside the range was written") + buf);
      }
    }
}

void check_quantized(Result& r, const Case& c, const QuantizedRows& qx, const RefRows& ref) {
  for (int i = 0; i < c.m; ++i) {
    if (!same_bits(qx.scale[i], ref.scale[i]) || qx.zero[i] != ref.zero[i])
      return mismatch(r, where(c, "activation scale or zero point") + " row " + std::to_string(i));
    for (int kk = 0; kk < c.k; ++kk)
      if (qx.data[static_cast<size_t>(i) * qx.stride + kk] != ref.q[static_cast<size_t>(i) * c.k + kk])
        return mismatch(r, where(c, "quantised activation") + " (" + std::to_string(i) + ", " + std::to_string(kk) + ")");
  }
}

void check_path(Result& r, Path path, bool evex_twin, const std::vector<Case>& all, uint32_t seed) {
  std::mt19937 rng(seed);
  for (const Case& c : all) {
    const std::vector<float> x = activations(rng, c.m, c.k), w = weights(rng, c.n, c.k);
    std::vector<float> bias(c.n);
    for (float& b : bias) b = static_cast<float>(static_cast<int>(rng() % 2001) - 1000) / 37.0f;
    const RefRows rx = ref_quantize(x, c.m, c.k);
    const RefWeights rw = ref_weights(w, c.n, c.k);
    bool overflow = false;
    const std::vector<float> y_bias = ref_matmul(rx, rw.q, rw.scale, bias.data(), c.m, c.n, c.k, &overflow);
    const std::vector<float> y_plain = ref_matmul(rx, rw.q, rw.scale, nullptr, c.m, c.n, c.k, &overflow);
    if (overflow) return mismatch(r, where(c, "the reference's int32 sum overflowed"));

    PackedWeights pw;
    if (evex_twin) {
      pw = detail::pack_unchecked(rw.q.data(), rw.scale.data(), c.n, c.k, Path::kAvxVnni);
    } else {
      pw = pack(w.data(), c.n, c.k, path);
      const PackedWeights pq = pack_quantized(rw.q.data(), rw.scale.data(), c.n, c.k, path);
      if (pw.data != pq.data || pw.row_sum != pq.row_sum || pw.row_sum != rw.row_sum || pw.kpad != pq.kpad || pw.block != pq.block)
        return mismatch(r, where(c, "pack and pack_quantized (or the reference's row sums) disagree"));
      for (int j = 0; j < c.n; ++j)
        if (!same_bits(pw.scale[j], rw.scale[j])) return mismatch(r, where(c, "weight scale") + " row " + std::to_string(j));
    }
    QuantizedRows qx;
    quantize_rows(x.data(), c.m, c.k, qx, evex_twin ? Path::kAvx512Vnni : path);
    check_quantized(r, c, qx, rx);
    RangeFn fn = matmul_range;
#if defined(DSSP_QGEMM_X86)
    if (evex_twin) fn = detail::matmul_range_avx_vnni_evex;
#endif
    check_product(r, c, qx, pw, fn, bias.data(), y_bias, 0, c.n, c.n);
    check_product(r, c, qx, pw, fn, nullptr, y_plain, 0, c.n, c.n);
    // a part of the columns, not at block boundaries, into a wider y (as threads splitting the columns write)
    const int a = static_cast<int>(rng() % (c.n + 1)), b = static_cast<int>(rng() % (c.n + 1));
    check_product(r, c, qx, pw, fn, bias.data(), y_bias, std::min(a, b), std::max(a, b), c.n + 3);
    if (c.n >= 3 * pw.block) {  // three threads, one call each, on their own columns (split at blocks and not)
      std::vector<float> y(static_cast<size_t>(c.m) * c.n);
      const int cuts[4] = {0, pw.block, 2 * pw.block + 1, c.n};
      std::vector<std::thread> threads;
      for (int t = 0; t < 3; ++t)
        threads.emplace_back([&, t] { fn(qx, pw, bias.data(), y.data(), c.n, cuts[t], cuts[t + 1]); });
      for (std::thread& t : threads) t.join();
      ++r.products;
      for (size_t e = 0; e < y.size(); ++e)
        if (!same_bits(y[e], y_bias[e])) return mismatch(r, where(c, "columns split across threads"));
    }
    if (!evex_twin) {  // matmul: quantisation and product in one call
      std::vector<float> y(static_cast<size_t>(c.m) * c.n);
      matmul(x.data(), c.m, pw, bias.data(), y.data());
      ++r.products;
      for (size_t e = 0; e < y.size(); ++e)
        if (!same_bits(y[e], y_bias[e])) return mismatch(r, where(c, "matmul"));
    }
    if (r.status != "matched") return;
  }
}

// ------------------------------------------------------------------ the quantisation's own checks
// Returns the first failure, or "".
std::string check_quantiser(Path path) {
  const int k = 37;  // not a multiple of a vector: the SIMD loop and its tail
  auto one_row = [&](const std::vector<float>& row, QuantizedRows& q) { quantize_rows(row.data(), 1, k, q, path); };
  QuantizedRows q;
  auto all_bytes = [&](uint8_t v) {
    for (int j = 0; j < k; ++j)
      if (q.data[j] != v) return false;
    return true;
  };
  one_row(std::vector<float>(k, 3.5f), q);
  if (!same_bits(q.scale[0], static_cast<float>(3.5 / 255.0)) || q.zero[0] != 0 || !all_bytes(255))
    return "a constant positive row: want scale 3.5/255, zero point 0, every byte 255";
  one_row(std::vector<float>(k, -2.0f), q);
  if (!same_bits(q.scale[0], static_cast<float>(2.0 / 255.0)) || q.zero[0] != 255 || !all_bytes(0))
    return "a constant negative row: want scale 2/255, zero point 255, every byte 0";
  one_row(std::vector<float>(k, 0.0f), q);
  if (q.scale[0] != 1.0f || q.zero[0] != 0 || !all_bytes(0)) return "a row of zeros: want scale 1, zero point 0, every byte 0";
  // huge and tiny magnitudes: a finite scale, and every value back within half a step
  const std::vector<std::vector<float>> rows = {
      [&] { std::vector<float> r(k); for (int j = 0; j < k; ++j) r[j] = (j % 3 - 1) * 3.0e38f * (static_cast<float>(j + 1) / k); return r; }(),
      [&] { std::vector<float> r(k); for (int j = 0; j < k; ++j) r[j] = (j % 2 ? 1.0f : -0.25f) * 1.0e-30f * j; return r; }(),
      [&] { std::vector<float> r(k); for (int j = 0; j < k; ++j) r[j] = 1.0e-38f * j; return r; }(),  // subnormal scale
      [&] { std::vector<float> r(k); for (int j = 0; j < k; ++j) r[j] = std::sin(0.7f * j) * 1.0e4f + 100.0f; return r; }(),
  };
  for (size_t t = 0; t < rows.size(); ++t) {
    one_row(rows[t], q);
    if (!(std::isfinite(q.scale[0]) && q.scale[0] > 0.0f) || q.zero[0] < 0 || q.zero[0] > 255)
      return "magnitude row " + std::to_string(t) + ": scale or zero point out of range";
    const double step = q.scale[0];
    const bool subnormal = step < 1.1754944e-38;  // x / scale loses bits when the scale itself has few
    for (int j = 0; j < k; ++j) {
      const double back = (static_cast<double>(q.data[j]) - q.zero[0]) * step;
      if (std::fabs(back - rows[t][j]) > (subnormal ? 2.0 : 0.5001) * step + 1e-6 * std::fabs(rows[t][j]))
        return "magnitude row " + std::to_string(t) + ": value " + std::to_string(j) + " does not come back within half a step";
    }
  }
  // below 255 x the smallest float the range is zero: scale 1, all zeros
  one_row(std::vector<float>(k, 1.0e-45f), q);
  if (q.scale[0] != 1.0f || q.zero[0] != 0 || !all_bytes(0)) return "a row of the smallest subnormal: want scale 1, every byte 0";
  // NaN and infinities: no crash, and the same bytes as the portable quantiser
  std::vector<float> odd(k, 1.0f);
  odd[3] = std::nanf("");
  odd[20] = -7.0f;
  one_row(odd, q);
  QuantizedRows p;
  quantize_rows(odd.data(), 1, k, p, Path::kPortable);
  if (q.data != p.data || !same_bits(q.scale[0], p.scale[0]) || q.zero != p.zero) return "a row with a NaN differs from the portable path";
  odd[5] = INFINITY;
  one_row(odd, q);
  quantize_rows(odd.data(), 1, k, p, Path::kPortable);
  if (q.data != p.data || q.zero != p.zero) return "a row with an infinity differs from the portable path";
  return "";
}

// ------------------------------------------------------------------ the speed of 12-row products
double now() { return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count(); }

struct Timing {
  int m, n, k;
  double hot_us, stream_us, stream_gbps, hot_gbps, gmacs, quantize_us;
};

// hot: one matrix again and again (from the caches); stream: a new matrix each product, enough of them
// (>= 96 MB) that every one comes from memory, as the denoiser's step reads its 32 MB of weights.
Timing bench(Path path, int m, int n, int k) {
  std::mt19937 rng(7);
  const std::vector<float> x = activations(rng, m, k), w = weights(rng, n, k);
  std::vector<float> bias(n, 0.5f), y(static_cast<size_t>(m) * n);
  const PackedWeights first = pack(w.data(), n, k, path);
  const int copies = static_cast<int>(std::max<size_t>(2, (96u << 20) / first.bytes()));
  std::vector<PackedWeights> many(copies, first);
  QuantizedRows qx;
  quantize_rows(x.data(), m, k, qx, path);
  auto best_of = [&](int reps, auto&& fn) {
    double best = 1e30;
    for (int r = 0; r < reps; ++r) {
      const double t0 = now();
      fn();
      best = std::min(best, now() - t0);
    }
    return best;
  };
  const double one = best_of(3, [&] { matmul_range(qx, first, bias.data(), y.data(), n, 0, n); });
  const int inner = std::max(1, static_cast<int>(0.02 / std::max(one, 1e-7)));
  const double hot = best_of(7, [&] { for (int r = 0; r < inner; ++r) matmul_range(qx, first, bias.data(), y.data(), n, 0, n); }) / inner;
  const double stream = best_of(5, [&] { for (const PackedWeights& p : many) matmul_range(qx, p, bias.data(), y.data(), n, 0, n); }) / copies;
  const int qinner = 200;
  const double quant = best_of(5, [&] { for (int r = 0; r < qinner; ++r) quantize_rows(x.data(), m, k, qx, path); }) / qinner;
  const double bytes = static_cast<double>(first.bytes());
  return {m, n, k, hot * 1e6, stream * 1e6, bytes / stream / 1e9, bytes / hot / 1e9, static_cast<double>(m) * n * k / stream / 1e9, quant * 1e6};
}

}  // namespace

int main(int argc, char** argv) {
  const bool do_bench = argc > 1 && std::strcmp(argv[1], "--bench") == 0;
  std::string path_error;
  const Path best = choose_path(&path_error);
  const char* forced = std::getenv("DSSP_QGEMM_PATH");
  if (!path_error.empty()) {
    std::printf("{\"ok\": false, \"path_error\": %s}\n", json_str(path_error).c_str());
    return 2;
  }
#if defined(DSSP_QGEMM_X86)
  const char* arch = "x86_64";
#elif defined(DSSP_QGEMM_ARM)
  const char* arch = "aarch64";
#else
  const char* arch = "other";
#endif
  std::mt19937 rng(2024);
  const std::vector<Case> all = cases(rng);
  std::string available, unavailable, run, matched, failures;
  bool ok = true;
  auto add = [](std::string& list, const std::string& item) { list += (list.empty() ? "" : ", ") + item; };
  for (Path p : kAllPaths) {
    const std::string why = path_unavailable_reason(p);
    if (!why.empty()) {
      add(unavailable, json_str(path_name(p)) + ": " + json_str(why));
      continue;
    }
    add(available, json_str(path_name(p)));
    add(run, json_str(path_name(p)));
    Result r;
    check_path(r, p, false, all, 99);
    const std::string quant = check_quantiser(p);
    if (!quant.empty()) mismatch(r, "quantisation: " + quant);
    if (r.status == "matched")
      add(matched, json_str(path_name(p)));
    else {
      ok = false;
      add(failures, json_str(path_name(p)) + ": " + json_str(r.status));
    }
  }
  std::string extra;
#if defined(DSSP_QGEMM_X86)
  // avx_vnni's kernel, with the EVEX encoding of its instruction, where AVX-512 VNNI (with VL) runs it
  __builtin_cpu_init();
  if (path_available(Path::kAvx512Vnni) && __builtin_cpu_supports("avx512vl")) {
    Result r;
    check_path(r, Path::kAvxVnni, true, all, 99);
    extra = ", \"avx_vnni_kernel_evex\": " + json_str(r.status);
    if (r.status != "matched") ok = false;
  }
#endif
  std::printf("{\"ok\": %s, \"arch\": \"%s\", \"best\": \"%s\", \"cases\": %zu, \"available\": [%s], \"run\": [%s], \"matched\": [%s], "
              "\"unavailable\": {%s}, \"mismatched\": {%s}%s",
              ok ? "true" : "false", arch, path_name(best), all.size(), available.c_str(), run.c_str(), matched.c_str(),
              unavailable.c_str(), failures.c_str(), extra.c_str());
  if (do_bench) {
    std::string out;
    std::fprintf(stderr, "%-12s %4s %5s %5s %10s %10s %13s %9s %12s\n", "path", "m", "n", "k", "hot us", "stream us", "stream GB/s",
                 "GMAC/s", "quantize us");
    for (Path p : kAllPaths) {
      if (!path_available(p) || (forced && *forced && std::strcmp(forced, "auto") != 0 && p != best)) continue;
      std::string rows;
      for (const Case& c : std::vector<Case>{{12, 1024, 2048}, {12, 2048, 1024}, {12, 4096, 1024}, {1, 1024, 2048}, {16, 1024, 2048}}) {
        const Timing t = bench(p, c.m, c.n, c.k);
        char buf[400];
        std::snprintf(buf, sizeof buf,
                      "{\"m\": %d, \"n\": %d, \"k\": %d, \"hot_us\": %.1f, \"stream_us\": %.1f, \"stream_GBps\": %.2f, \"hot_GBps\": %.2f, "
                      "\"GMACps\": %.1f, \"quantize_us\": %.2f}",
                      t.m, t.n, t.k, t.hot_us, t.stream_us, t.stream_gbps, t.hot_gbps, t.gmacs, t.quantize_us);
        add(rows, buf);
        std::fprintf(stderr, "%-12s %4d %5d %5d %10.1f %10.1f %13.2f %9.1f %12.2f\n", path_name(p), t.m, t.n, t.k, t.hot_us, t.stream_us,
                     t.stream_gbps, t.gmacs, t.quantize_us);
      }
      add(out, json_str(path_name(p)) + ": [" + rows + "]");
    }
    std::printf(", \"bench\": {%s}", out.c_str());
  }
  std::printf("}\n");
  return ok ? 0 : 1;
}
