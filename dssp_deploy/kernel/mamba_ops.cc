// The fused CPU operators for ONNX Runtime (domain ai.dssp), over the arithmetic of mamba_block.h: the selective
// scan of one Mamba layer, its causal depthwise convolution (CausalConv1d), a whole int8 denoiser block
// (MambaBlockQ8), the end of a DDIM step (DdimStep) and the point encoder's last LayerNorm and max over the points
// (LayerNormMaxOverPoints), further down.
//
//   ai.dssp::SelectiveScan(x, dt, B, C, z, A, D, h0) -> (y, h)
//
//   x, dt, z (batch, L, E)   dt before softplus, with dt_proj's bias added
//   B, C     (batch, L, n)
//   A        (E, n)          A = -exp(A_log): a constant the graph folds at load
//   D        (E)
//   h0       (batch, E, n)   the incoming SSM state
//   y        (batch, L, E)   (C_t . h_t + D * x_t) * silu(z_t)
//   h        (batch, E, n)   the state after the last token (after the first state_at tokens, with the attribute
//                            state_at > 0); (batch, 0, n) with the attribute state_out = 0
//
// with delta_t = softplus(dt_t), h_t = exp(delta_t * A) * h_{t-1} + delta_t * x_t * B_t, per channel e and
// state index k: the arithmetic of dssp_train.model.selective_scan.selective_scan, in one pass over the
// tokens with each channel's state held in registers. The unfused graph does the same work as a chain of
// elementwise ONNX nodes, each reading and writing (batch, L, E, n) tensors.
//
// Channels are split into blocks that run on ONNX Runtime's intra-op threads (KernelContext_ParallelFor).
// Four implementations of the same loops:
//   avx512    16 channels per vector: the SIMD loop of scan_simd.inc for AVX-512F (checked at run time)
//   avx2      8 channels per vector: the same loop for AVX2 + FMA, with the same polynomial exp
//   neon      4 channels per vector: the same loop for NEON (aarch64 builds only, e.g. the robot computers)
//   portable  plain C++ the compiler vectorises for the target (x86-64 without AVX2, any other CPU)
// The environment variable DSSP_SCAN_PATH=auto|avx512|avx2|neon|portable (default auto: the widest this CPU
// runs) chooses, per session.
//
// Built against ONNX Runtime's C API headers (ORT_API_MANUAL_INIT: the library is not linked to
// libonnxruntime; it takes the API from the runtime that loads it).

#define ORT_API_MANUAL_INIT
#include "onnxruntime_cxx_api.h"
#undef ORT_API_MANUAL_INIT
#include "onnxruntime_lite_custom_op.h"
#include "mamba_block.h"

#include <limits>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <tuple>
#include <vector>

namespace {

using namespace dssp::mamba;

constexpr const char* kDomain = "ai.dssp";

// ------------------------------------------------------------------ the operators
// The scan path DSSP_SCAN_PATH asks for, or the session fails with the line that says why not.
Path requested_scan_path() {
  std::string problem;
  const Path path = choose_path(&problem);
  if (!problem.empty()) ORT_CXX_API_THROW(std::move(problem), ORT_FAIL);
  return path;
}

// ONNX Runtime's intra-op threads for the arithmetic's ParallelFor
ParallelFor threads_of(Ort::KernelContext& ctx) {
  return [&ctx](void (*fn)(void*, size_t), size_t count, void* data) { ctx.ParallelFor(fn, count, 0, data); };
}

std::string shape_str(const std::vector<int64_t>& s) {
  std::string out = "(";
  for (size_t i = 0; i < s.size(); ++i) out += (i ? ", " : "") + std::to_string(s[i]);
  return out + ")";
}

// The one-line refusal of operator `op`'s input `name` when its shape is not `want`.
void expect_shape(const char* op, const char* name, const std::vector<int64_t>& got, const std::vector<int64_t>& want) {
  if (got != want)
    ORT_CXX_API_THROW(std::string(op) + ": " + name + " has shape " + shape_str(got) + ", expected " + shape_str(want), ORT_INVALID_ARGUMENT);
}

// A node's attribute `name`, or `fallback` when the node has none.
template <class T>
T attribute(const OrtKernelInfo* info, const char* name, T fallback) {
  try {
    return Ort::ConstKernelInfo(info).GetAttribute<T>(name);
  } catch (const Ort::Exception&) {
    return fallback;
  }
}

// The attribute state_at (int, default 0: after the last token) of SelectiveScan and CausalConv1d, checked
// against the tokens of a call: the state out is the state after the first state_at tokens (1..L), the prefix's
// in a pass over [prefix, action tokens] (the denoiser's first DDIM step, which the later steps start from).
int64_t state_at_of(const char* op, int64_t state_at, int64_t L) {
  if (state_at < 0 || state_at > L)
    ORT_CXX_API_THROW(std::string(op) + ": state_at = " + std::to_string(state_at) + " tokens, but the input has " + std::to_string(L), ORT_INVALID_ARGUMENT);
  return state_at;
}

// The attribute state_out (int, default 1): 0 on a node whose state output nothing reads (export sets it on
// the denoiser's action-token scans); h is then (batch, 0, n) and the state is never written back.
struct SelectiveScan {
  SelectiveScan(const OrtApi*, const OrtKernelInfo* info)
      : path(requested_scan_path()), state_out(attribute<int64_t>(info, "state_out", 1) != 0), state_at(attribute<int64_t>(info, "state_at", 0)) {}

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
    expect_shape("SelectiveScan", "dt", dt.Shape(), xs);
    expect_shape("SelectiveScan", "z", z.Shape(), xs);
    expect_shape("SelectiveScan", "B", B.Shape(), {batch, L, n});
    expect_shape("SelectiveScan", "C", C.Shape(), {batch, L, n});
    expect_shape("SelectiveScan", "D", D.Shape(), {E});
    expect_shape("SelectiveScan", "h0", h0.Shape(), {batch, E, n});
    float* h_out = h.Allocate({batch, state_out ? E : 0, n});
    Problem p{x.Data(), dt.Data(), B.Data(), C.Data(), z.Data(), A.Data(), D.Data(), h0.Data(),
              y.Allocate(xs), state_out ? h_out : nullptr, batch, L, E, n};
    p.h_after = state_at_of("SelectiveScan", state_at, L);
    if (batch == 0 || E == 0) return Ort::Status{nullptr};
    if (L == 0) {
      if (!state_out) return Ort::Status{nullptr};
      std::memcpy(p.h, p.h0, sizeof(float) * batch * E * n);
      return Ort::Status{nullptr};
    }
    const int64_t blocks = (E + kBlock - 1) / kBlock;
    ScanTask task{&p, path, blocks};
    Ort::KernelContext(context).ParallelFor(run_scan_task, static_cast<size_t>(batch * blocks), 0, &task);
    return Ort::Status{nullptr};
  }

  Path path;
  bool state_out;
  int64_t state_at;
};

// ai.dssp::CausalConv1d(x (batch, L, E), state (batch, E, W), weight (W, E), bias (E)) -> (y (batch, L, E), new_state (batch, E, W)):
// new_state the last W conv inputs after the last token (after the first state_at tokens, with the attribute state_at > 0)
struct CausalConv1d {
  CausalConv1d(const OrtApi*, const OrtKernelInfo* info) : state_at(attribute<int64_t>(info, "state_at", 0)) {}

  Ort::Status Compute(OrtKernelContext* context, const Ort::Custom::Tensor<float>& x, const Ort::Custom::Tensor<float>& state,
                      const Ort::Custom::Tensor<float>& weight, const Ort::Custom::Tensor<float>& bias,
                      Ort::Custom::Tensor<float>& y, Ort::Custom::Tensor<float>& new_state) {
    const auto xs = x.Shape();
    if (xs.size() != 3) ORT_CXX_API_THROW("CausalConv1d: x must be (batch, L, E), got " + shape_str(xs), ORT_INVALID_ARGUMENT);
    const int64_t batch = xs[0], L = xs[1], E = xs[2];
    const auto ws = weight.Shape();
    if (ws.size() != 2 || ws[1] != E) ORT_CXX_API_THROW("CausalConv1d: weight must be (W, E) with E = " + std::to_string(E) + ", got " + shape_str(ws), ORT_INVALID_ARGUMENT);
    const int64_t W = ws[0];
    expect_shape("CausalConv1d", "state", state.Shape(), {batch, E, W});
    expect_shape("CausalConv1d", "bias", bias.Shape(), {E});
    ConvProblem p{x.Data(), state.Data(), weight.Data(), bias.Data(), y.Allocate(xs), new_state.Allocate({batch, E, W}), batch, L, E, W};
    p.state_after = state_at_of("CausalConv1d", state_at, L);
    if (batch == 0 || E == 0) return Ort::Status{nullptr};
    const int64_t blocks = (E + 255) / 256;
    ConvTask task{&p, blocks};
    Ort::KernelContext(context).ParallelFor(run_conv_task, static_cast<size_t>(batch * blocks), 0, &task);
    return Ort::Status{nullptr};
  }

  int64_t state_at;
};

// ai.dssp::LayerNormMaxOverPoints(x (batch, P, F), weight (F), bias (F)) -> y (batch, F): the max over the points
// (P >= 1) of each point's LayerNorm (attribute eps): DP3's last LayerNorm and its pooling in one pass. The points
// are split across the threads in runs of 128, each run's max kept apart, then the runs' maxima combined.
constexpr int64_t kPointsPerTask = 128;

struct PoolTask {
  const float *x, *weight, *bias;
  float eps;
  float* partial;  // (batch * runs, F)
  int64_t P, F, runs;
};

void run_pool_task(void* data, size_t index) {
  const PoolTask& t = *static_cast<const PoolTask*>(data);
  const int64_t b = static_cast<int64_t>(index) / t.runs, p0 = (static_cast<int64_t>(index) % t.runs) * kPointsPerTask;
  float* y = t.partial + static_cast<int64_t>(index) * t.F;
  std::fill(y, y + t.F, -std::numeric_limits<float>::infinity());
  layer_norm_max(t.x + b * t.P * t.F, t.F, t.weight, t.bias, t.eps, p0, std::min(p0 + kPointsPerTask, t.P), y);
}

struct LayerNormMaxOverPoints {
  LayerNormMaxOverPoints(const OrtApi*, const OrtKernelInfo* info) : eps(attribute(info, "eps", 1e-5f)) {}

  Ort::Status Compute(OrtKernelContext* context, const Ort::Custom::Tensor<float>& x, const Ort::Custom::Tensor<float>& weight,
                      const Ort::Custom::Tensor<float>& bias, Ort::Custom::Tensor<float>& y) {
    const auto xs = x.Shape();
    if (xs.size() != 3 || xs[1] < 1)
      ORT_CXX_API_THROW("LayerNormMaxOverPoints: x must be (batch, P, F) with P >= 1, got " + shape_str(xs), ORT_INVALID_ARGUMENT);
    const int64_t batch = xs[0], P = xs[1], F = xs[2];
    expect_shape("LayerNormMaxOverPoints", "weight", weight.Shape(), {F});
    expect_shape("LayerNormMaxOverPoints", "bias", bias.Shape(), {F});
    float* out = y.Allocate({batch, F});
    if (batch == 0 || F == 0) return Ort::Status{nullptr};
    const int64_t runs = (P + kPointsPerTask - 1) / kPointsPerTask;
    std::vector<float> partial(static_cast<size_t>(batch * runs * F));
    PoolTask task{x.Data(), weight.Data(), bias.Data(), eps, partial.data(), P, F, runs};
    Ort::KernelContext(context).ParallelFor(run_pool_task, static_cast<size_t>(batch * runs), 0, &task);
    for (int64_t b = 0; b < batch; ++b) {
      float* yb = out + b * F;
      std::memcpy(yb, partial.data() + b * runs * F, sizeof(float) * F);
      for (int64_t r = 1; r < runs; ++r) {
        const float* pr = partial.data() + (b * runs + r) * F;
        for (int64_t f = 0; f < F; ++f) yb[f] = pr[f] > yb[f] ? pr[f] : yb[f];
      }
    }
    return Ort::Status{nullptr};
  }

  float eps;
};

// ------------------------------------------------------------------ a whole denoiser block (int8 weights)
// ai.dssp::MambaBlockQ8: one block of the denoiser — on the action tokens for one DDIM step, on the prefix, or on
// both in one pass — with int8 weights: mamba_block.h's block_forward, whose comment gives the arithmetic.
//
// inputs: a (batch, H, d); conv_state (batch, E, W); ssm_state (batch, E, n) — (batch, 0, W) and (batch, 0, n): a
//         start from zeros; mod (3, d); norm_w (d);
//         in_q (2E, d) int8, in_s (2E); conv_w (W, E), conv_b (E); xp_q (R + 2n, E) int8, xp_s (R + 2n);
//         dt_q (E, R) int8, dt_s (E), dt_b (E); A (E, n); D (E); out_q (d, E) int8, out_s (d);
//         norm2_w (d); fc1_q (2h, d) int8, fc1_s (2h); fc2_q (d, h) int8, fc2_s (d) — the MLP's (0,)/(0, 0) without one
// outputs: a (batch, H, d); the mixer's state after the tokens, conv (batch, E, W) and ssm (batch, E, n), with the
// attribute state_out = 1 (else both (batch, 0, .), never written). Attribute eps: the norms'.
// Attribute plain (default 0): with mod (3, d), the first `plain` tokens of each row are the prefix, without AdaLN
// and gate 1 — one DDIM step's [prefix, actions] in one pass (K = 1, or the first of K steps); the states out are
// then those after the prefix, which the later steps start from.
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
      : scan_path(requested_scan_path()), qgemm_path(choose_qgemm_path()), eps(attribute(info, "eps", 1e-5f)),
        state_out(attribute<int64_t>(info, "state_out", 0) != 0), plain(attribute<int64_t>(info, "plain", 0)) {}

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
    const int64_t batch = as[0], L = as[1], d = as[2];
    const auto ws = conv_w.Shape(), ns = A.Shape();
    if (ws.size() != 2 || ns.size() != 2) ORT_CXX_API_THROW("MambaBlockQ8: conv_w must be (W, E) and A (E, n)", ORT_INVALID_ARGUMENT);
    const int64_t W = ws[0], E = ws[1], n = ns[1];
    const bool conv_zero = conv_state.Shape() == std::vector<int64_t>{batch, 0, W};  // empty: a start from zeros
    const bool ssm_zero = ssm_state.Shape() == std::vector<int64_t>{batch, 0, n};
    if (!conv_zero) expect_shape("MambaBlockQ8", "conv_state", conv_state.Shape(), {batch, E, W});
    if (!ssm_zero) expect_shape("MambaBlockQ8", "ssm_state", ssm_state.Shape(), {batch, E, n});
    const bool modulated = !mod.Shape().empty() && mod.Shape()[0] != 0;
    expect_shape("MambaBlockQ8", "mod", mod.Shape(), {modulated ? 3 : 0, d});
    expect_shape("MambaBlockQ8", "norm_w", norm_w.Shape(), {d});
    expect_shape("MambaBlockQ8", "A", ns, {E, n});
    const auto held_in = in_w.get(in_q, in_s, qgemm_path, "in_proj");
    const auto held_xp = xp_w.get(xp_q, xp_s, qgemm_path, "x_proj");
    const auto held_dt = dt_w.get(dt_q, dt_s, qgemm_path, "dt_proj");
    const auto held_out = out_w.get(out_q, out_s, qgemm_path, "out_proj");
    const bool mlp = fc1_q.NumberOfElement() > 0;
    std::shared_ptr<const q::PackedWeights> held_fc1, held_fc2;
    if (mlp) {
      expect_shape("MambaBlockQ8", "norm2_w", norm2_w.Shape(), {d});
      held_fc1 = fc1_w.get(fc1_q, fc1_s, qgemm_path, "fc1");
      held_fc2 = fc2_w.get(fc2_q, fc2_s, qgemm_path, "fc2");
    }
    BlockWeights weights;
    weights.in = held_in.get(), weights.xp = held_xp.get(), weights.dt = held_dt.get(), weights.out = held_out.get();
    weights.fc1 = held_fc1.get(), weights.fc2 = held_fc2.get();
    weights.norm_w = norm_w.Data(), weights.conv_w = conv_w.Data(), weights.conv_b = conv_b.Data();
    weights.dt_b = dt_b.Data(), weights.A = A.Data(), weights.D = D.Data(), weights.norm2_w = mlp ? norm2_w.Data() : nullptr;
    weights.d = d, weights.E = E, weights.W = W, weights.n = n, weights.eps = eps;
    try {
      weights.check();
    } catch (const std::invalid_argument& e) {
      ORT_CXX_API_THROW(std::string(e.what()), ORT_INVALID_ARGUMENT);
    }
    BlockInputs inputs;
    inputs.a = a.Data(), inputs.conv_state = conv_zero ? nullptr : conv_state.Data();
    inputs.ssm_state = ssm_zero ? nullptr : ssm_state.Data();
    inputs.mod = modulated ? mod.Data() : nullptr, inputs.batch = batch, inputs.L = L;
    inputs.plain = modulated ? plain : 0;
    if (inputs.plain < 0 || inputs.plain > L)
      ORT_CXX_API_THROW("MambaBlockQ8: plain = " + std::to_string(plain) + " prefix tokens, but a has " + std::to_string(L), ORT_INVALID_ARGUMENT);
    BlockOutputs outputs;
    outputs.a = out.Allocate(as);
    float* conv_after = conv_out.Allocate({batch, state_out ? E : 0, W});
    float* ssm_after = ssm_out.Allocate({batch, state_out ? E : 0, n});
    outputs.conv_state = state_out ? conv_after : nullptr, outputs.ssm_state = state_out ? ssm_after : nullptr;
    Ort::KernelContext ctx(context);
    block_forward(weights, inputs, outputs, scan_path, threads_of(ctx));
    return Ort::Status{nullptr};
  }

  Path scan_path;
  q::Path qgemm_path;
  float eps;
  bool state_out;
  int64_t plain;
  Weights in_w, xp_w, dt_w, out_w, fc1_w, fc2_w;
};

// ------------------------------------------------------------------ the end of one DDIM step
// ai.dssp::DdimStep: what the denoiser does between its last block of one DDIM step and its first block of the next —
// the readout, the DDIM update and the next step's action tokens — in one node instead of about sixteen small ones
// (dssp_train.model.denoiser.Denoiser.readout, dssp_train.model.scheduler.DiffusionSchedule.ddim_step with eta = 0
// and no inpainting, Denoiser.embed_actions without committed actions), fp32, a row at a time (mamba_block.h's
// ddim_step_row):
//
//   r   = rmsnorm(h) * norm_w * (1 + scale) + shift                  h: the last block's output on the action tokens
//   y   = r out_w^T + out_b                                          (batch, H, A): the model's output
//   x0, eps = y, (x - c_t y) / s_t          with the attribute sample = 1 (the model predicts the clean sample)
//   x0, eps = (x - s_t y) / c_t, y          with sample = 0 (it predicts the noise)
//   x0  = clamp(x0, -1, 1)                  with the attribute clip = 1
//   x'  = c_prev x0 + s_prev eps                                     (batch, H, A): the sample of the next step
//   a'  = x' in_w + in_b + pos                                       (batch, H, d): the next step's action tokens
//
// inputs: h (batch, H, d); x (batch, H, A); norm_w (d); mod (2, d): shift, scale; out_w (A, d), out_b (A);
//         in_w (A, d) (the transpose of the layer's), in_b (d), pos (H, d)
// outputs: x' (batch, H, A); a' (batch, H, d) — (batch, H, 0) with the attribute tokens = 0 (the chunk's last step)
// attributes: eps (the norm's), c_t, s_t, c_prev, s_prev (sqrt(abar_t), sqrt(1 - abar_t), sqrt(abar_prev),
//             sqrt(1 - abar_prev)), sample, clip, tokens (default 1).
// The arithmetic is in the order of the standard graph's nodes (each a float32 operation); the two products sum in
// another order than ONNX Runtime's MatMul, so the outputs agree to rounding, not bit for bit.
struct DdimStep {
  DdimStep(const OrtApi*, const OrtKernelInfo* info)
      : eps(attribute(info, "eps", 1e-5f)), c_t(attribute(info, "c_t", 1.0f)), s_t(attribute(info, "s_t", 0.0f)),
        c_prev(attribute(info, "c_prev", 1.0f)), s_prev(attribute(info, "s_prev", 0.0f)),
        sample(attribute<int64_t>(info, "sample", 1) != 0), clip(attribute<int64_t>(info, "clip", 0) != 0),
        tokens(attribute<int64_t>(info, "tokens", 1) != 0) {}

  Ort::Status Compute(const Ort::Custom::Tensor<float>& h, const Ort::Custom::Tensor<float>& x,
                      const Ort::Custom::Tensor<float>& norm_w, const Ort::Custom::Tensor<float>& mod,
                      const Ort::Custom::Tensor<float>& out_w, const Ort::Custom::Tensor<float>& out_b,
                      const Ort::Custom::Tensor<float>& in_w, const Ort::Custom::Tensor<float>& in_b,
                      const Ort::Custom::Tensor<float>& pos, Ort::Custom::Tensor<float>& x_next,
                      Ort::Custom::Tensor<float>& a_next) {
    const auto hs = h.Shape(), xs = x.Shape();
    if (hs.size() != 3 || xs.size() != 3 || xs[0] != hs[0] || xs[1] != hs[1])
      ORT_CXX_API_THROW("DdimStep: h must be (batch, H, d) and x (batch, H, A), got " + shape_str(hs) + " and " +
                            shape_str(xs), ORT_INVALID_ARGUMENT);
    const int64_t batch = hs[0], d = hs[2], H = xs[1], A = xs[2];
    expect_shape("DdimStep", "norm_w", norm_w.Shape(), {d});
    expect_shape("DdimStep", "mod", mod.Shape(), {2, d});
    expect_shape("DdimStep", "out_w", out_w.Shape(), {A, d});
    expect_shape("DdimStep", "out_b", out_b.Shape(), {A});
    expect_shape("DdimStep", "in_w", in_w.Shape(), {A, d});
    expect_shape("DdimStep", "in_b", in_b.Shape(), {d});
    expect_shape("DdimStep", "pos", pos.Shape(), {H, d});
    float* xn = x_next.Allocate(xs);
    float* an = a_next.Allocate({batch, H, tokens ? d : 0});
    DdimStepWeights w;
    w.norm_w = norm_w.Data(), w.shift = mod.Data(), w.scale = mod.Data() + d;
    w.out_w = out_w.Data(), w.out_b = out_b.Data(), w.in_w = in_w.Data(), w.in_b = in_b.Data(), w.d = d, w.A = A;
    w.eps = eps, w.c_t = c_t, w.s_t = s_t, w.c_prev = c_prev, w.s_prev = s_prev, w.sample = sample, w.clip = clip;
    std::vector<float> r(static_cast<size_t>(d));
    for (int64_t row = 0; row < batch * H; ++row)
      ddim_step_row(w, h.Data() + row * d, x.Data() + row * A, pos.Data() + (row % H) * d, xn + row * A,
                    tokens ? an + row * d : nullptr, r.data());
    return Ort::Status{nullptr};
  }

  float eps, c_t, s_t, c_prev, s_prev;
  bool sample, clip, tokens;
};

}  // namespace

// The library's entry point, called by SessionOptions.register_custom_ops_library.
extern "C" __attribute__((visibility("default"))) OrtStatus* ORT_API_CALL RegisterCustomOps(OrtSessionOptions* options,
                                                                                           const OrtApiBase* api_base) {
  const OrtApi* api = api_base->GetApi(ORT_API_VERSION);
  if (api == nullptr) return nullptr;  // an older runtime: the session fails to load the graph, the caller falls back
  Ort::InitApi(api);
  static std::unique_ptr<Ort::Custom::OrtLiteCustomOp> scan_op, conv_op, block_op, pool_op, step_op;
  static Ort::CustomOpDomain domain{nullptr};
  static std::once_flag once;
  try {
    std::call_once(once, [] {
      scan_op.reset(Ort::Custom::CreateLiteCustomOp<SelectiveScan>("SelectiveScan", "CPUExecutionProvider"));
      conv_op.reset(Ort::Custom::CreateLiteCustomOp<CausalConv1d>("CausalConv1d", "CPUExecutionProvider"));
      block_op.reset(Ort::Custom::CreateLiteCustomOp<MambaBlockQ8>("MambaBlockQ8", "CPUExecutionProvider"));
      pool_op.reset(Ort::Custom::CreateLiteCustomOp<LayerNormMaxOverPoints>("LayerNormMaxOverPoints", "CPUExecutionProvider"));
      step_op.reset(Ort::Custom::CreateLiteCustomOp<DdimStep>("DdimStep", "CPUExecutionProvider"));
      domain = Ort::CustomOpDomain(kDomain);
      domain.Add(scan_op.get());
      domain.Add(conv_op.get());
      domain.Add(block_op.get());
      domain.Add(pool_op.get());
      domain.Add(step_op.get());
    });
    Ort::UnownedSessionOptions(options).Add(domain);
  } catch (const std::exception& e) {
    return api->CreateStatus(ORT_FAIL, e.what());
  }
  return nullptr;
}

// The library's revision: what its operators know (dssp_deploy/mamba_kernel.py's KERNEL_REVISION is the one the
// exported graphs need; a library without this function predates revision 1). 1: MambaBlockQ8's `plain`, and
// SelectiveScan's and CausalConv1d's `state_at` (the state after a prefix, from a pass over more tokens). 2: DdimStep.
extern "C" __attribute__((visibility("default"))) int DsspKernelRevision() { return 2; }

// Which implementation a session would use on this CPU now ("avx512", "avx2", "neon" or "portable"), for start-up logs.
// The implementation DSSP_SCAN_PATH selects here, or "invalid: " and why it cannot run (for the loader's message).
extern "C" __attribute__((visibility("default"))) const char* DsspScanPath() {
  static thread_local std::string answer;
  try {
    std::string problem;
    const Path path = choose_path(&problem);
    answer = problem.empty() ? std::string(path_name(path)) : "invalid: " + problem;
  } catch (const std::exception& exc) {
    answer = std::string("invalid: ") + exc.what();
  } catch (...) {
    answer = "invalid: DSSP_SCAN_PATH cannot be used here";
  }
  return answer.c_str();
}
