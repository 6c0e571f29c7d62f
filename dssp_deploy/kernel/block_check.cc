// The fused int8 Mamba block (mamba_block.h) without ONNX Runtime: a harness for its parity on any CPU this
// builds for (aarch64 under qemu included) and for the time of its parts on this one.
//
//   block_check CASE OUT [THREADS]   run the block on the tensors in CASE, write its outputs to OUT, print a JSON line
//                                    (or, when CASE holds h, the end of a DDIM step: ai.dssp::DdimStep's arithmetic)
//   block_check --bench [THREADS]    time a denoiser step's blocks and each part of one (robotwin sizes), print JSON
//
// Tensor files (CASE, OUT): "DSSPTENS" then, per tensor, u32 name length, the name, u8 dtype ('f' float32,
// 'b' int8), u32 ndim, ndim int64 dims, the values; little-endian. CASE holds MambaBlockQ8's inputs by their names
// (a, conv_state, ssm_state, mod, norm_w, in_q, in_s, …, fc2_s: mamba_ops.cc), eps (shape ()) and optionally
// plain (shape (), the prefix tokens before the actions, whose states are written); mod (0, d) is the prefix alone,
// whose states are written; OUT holds a, conv, ssm. The scan and product paths are the ones
// DSSP_SCAN_PATH and DSSP_QGEMM_PATH choose. Exit 0 when the block ran, 2 when a path cannot run here (the JSON
// line says why), 1 for a broken file. A DDIM-step CASE holds DdimStep's inputs by their names (h, x, norm_w, mod,
// out_w, out_b, in_w, in_b, pos: mamba_ops.cc) and its attributes as scalars (shape ()): eps, c_t, s_t, c_prev,
// s_prev, sample, clip, tokens; OUT holds x_next and a_next.

#include "mamba_block.h"

#include <atomic>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <map>
#include <random>
#include <thread>

namespace {

namespace m = dssp::mamba;
namespace q = dssp::qgemm;

struct Tensor {
  char dtype = 'f';
  std::vector<int64_t> shape;
  std::vector<char> bytes;

  int64_t numel() const {
    int64_t count = 1;
    for (int64_t s : shape) count *= s;
    return count;
  }
  const float* f() const { return reinterpret_cast<const float*>(bytes.data()); }
  const int8_t* b() const { return reinterpret_cast<const int8_t*>(bytes.data()); }
};

using Tensors = std::map<std::string, Tensor>;

[[noreturn]] void broken(const std::string& what) { throw std::runtime_error(what); }

struct PathError : std::runtime_error {  // a scan or product path this CPU or build cannot run
  using std::runtime_error::runtime_error;
};

Tensors read_tensors(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  char magic[8];
  if (!in.read(magic, 8) || std::string(magic, 8) != "DSSPTENS") broken(path + " is not a tensor file");
  Tensors out;
  uint32_t length;
  while (in.read(reinterpret_cast<char*>(&length), 4)) {
    if (length > 256) broken(path + ": a name of " + std::to_string(length) + " bytes");
    std::string name(length, '\0');
    Tensor t;
    uint32_t ndim;
    if (!in.read(name.data(), length) || !in.read(&t.dtype, 1) || !in.read(reinterpret_cast<char*>(&ndim), 4) || ndim > 8)
      broken(path + ": a cut or damaged header");
    t.shape.resize(ndim);
    if (!in.read(reinterpret_cast<char*>(t.shape.data()), 8 * ndim)) broken(path + ": a cut shape");
    for (int64_t s : t.shape)
      if (s < 0 || s > (int64_t{1} << 28)) broken(path + ": " + name + " has a dimension of " + std::to_string(s));
    const int64_t size = t.numel() * (t.dtype == 'f' ? 4 : 1);
    if ((t.dtype != 'f' && t.dtype != 'b') || size > (int64_t{1} << 30)) broken(path + ": " + name + " has an odd type or size");
    t.bytes.resize(static_cast<size_t>(size));
    if (!in.read(t.bytes.data(), size)) broken(path + ": " + name + " is cut");
    out[name] = std::move(t);
  }
  return out;
}

void write_tensors(const std::string& path, const Tensors& tensors) {
  std::ofstream out(path, std::ios::binary);
  out.write("DSSPTENS", 8);
  for (const auto& [name, t] : tensors) {
    const uint32_t length = static_cast<uint32_t>(name.size()), ndim = static_cast<uint32_t>(t.shape.size());
    out.write(reinterpret_cast<const char*>(&length), 4);
    out.write(name.data(), length);
    out.write(&t.dtype, 1);
    out.write(reinterpret_cast<const char*>(&ndim), 4);
    out.write(reinterpret_cast<const char*>(t.shape.data()), 8 * ndim);
    out.write(t.bytes.data(), static_cast<std::streamsize>(t.bytes.size()));
  }
  if (!out) broken("cannot write " + path);
}

// Threads that wait spinning for work, as ONNX Runtime's intra-op pool does with spinning on: the calling thread
// takes part, and run returns when every worker has finished this run's indices.
class Pool {
 public:
  explicit Pool(int threads) {
    for (int i = 1; i < threads; ++i) workers_.emplace_back([this] { work(); });
  }
  ~Pool() {
    stop_ = true;
    generation_.fetch_add(1);
    for (auto& t : workers_) t.join();
  }
  void run(void (*fn)(void*, size_t), size_t count, void* data) {
    if (workers_.empty() || count < 2) {
      for (size_t i = 0; i < count; ++i) fn(data, i);
      return;
    }
    fn_ = fn, data_ = data, count_ = count;
    next_.store(0);
    finished_.store(0);
    generation_.fetch_add(1);
    drain();
    while (finished_.load() != workers_.size()) {
    }
  }
  m::ParallelFor parallel_for() {
    return [this](void (*fn)(void*, size_t), size_t count, void* data) { run(fn, count, data); };
  }

 private:
  void drain() {
    for (size_t i; (i = next_.fetch_add(1)) < count_;) fn_(data_, i);
  }
  void work() {
    uint64_t seen = 0;
    while (true) {
      uint64_t now;
      while ((now = generation_.load()) == seen) {
      }
      seen = now;
      if (stop_) return;
      drain();
      finished_.fetch_add(1);
    }
  }
  std::vector<std::thread> workers_;
  std::atomic<uint64_t> generation_{0};
  std::atomic<size_t> next_{0}, finished_{0};
  std::atomic<bool> stop_{false};
  void (*fn_)(void*, size_t) = nullptr;
  void* data_ = nullptr;
  size_t count_ = 0;
};

q::Path product_path() {
  std::string problem;
  const q::Path path = q::choose_path(&problem);
  if (!problem.empty()) throw PathError(problem);
  return path;
}

m::Path scan_path() {
  std::string problem;
  const m::Path path = m::choose_path(&problem);
  if (!problem.empty()) throw PathError(problem);
  return path;
}

const char* arch() {
#if defined(__aarch64__)
  return "aarch64";
#elif defined(__x86_64__)
  return "x86_64";
#else
  return "other";
#endif
}

const Tensor& need(const Tensors& t, const std::string& name, char dtype, size_t ndim) {
  auto it = t.find(name);
  if (it == t.end()) broken("the case has no " + name);
  if (it->second.dtype != dtype || it->second.shape.size() != ndim) broken(name + " has the wrong type or rank");
  return it->second;
}

std::shared_ptr<const q::PackedWeights> pack(const Tensors& t, const std::string& name, q::Path path) {
  const Tensor& w = need(t, name + "_q", 'b', 2);
  const Tensor& s = need(t, name + "_s", 'f', 1);
  if (s.shape[0] != w.shape[0]) broken(name + "'s scales do not fit its rows");
  return std::make_shared<const q::PackedWeights>(
      q::pack_quantized(w.b(), s.f(), static_cast<int>(w.shape[0]), static_cast<int>(w.shape[1]), path));
}

Tensor floats(std::vector<int64_t> shape) {
  Tensor t;
  t.shape = std::move(shape);
  t.bytes.assign(static_cast<size_t>(t.numel()) * 4, 0);
  return t;
}

// The end of one DDIM step on every row of h (batch, H, d) and x (batch, H, A), as ai.dssp::DdimStep runs it.
int ddim_step(const Tensors& t, const std::string& out_path) {
  const Tensor& h = need(t, "h", 'f', 3);
  const Tensor& x = need(t, "x", 'f', 3);
  const Tensor& out_w = need(t, "out_w", 'f', 2);
  const Tensor& mod = need(t, "mod", 'f', 2);
  const Tensor& pos = need(t, "pos", 'f', 2);
  const int64_t batch = h.shape[0], H = h.shape[1], d = h.shape[2], A = out_w.shape[0];
  const Tensor &in_w = need(t, "in_w", 'f', 2), &norm_w = need(t, "norm_w", 'f', 1);
  const Tensor &out_b = need(t, "out_b", 'f', 1), &in_b = need(t, "in_b", 'f', 1);
  if (x.shape != std::vector<int64_t>{batch, H, A} || out_w.shape[1] != d || in_w.shape != out_w.shape ||
      mod.shape != std::vector<int64_t>{2, d} || pos.shape != std::vector<int64_t>{H, d} || norm_w.numel() != d ||
      out_b.numel() != A || in_b.numel() != d)
    broken("the DDIM step's inputs do not fit h (batch, H, d) and out_w (A, d)");
  auto scalar = [&](const char* name) { return need(t, name, 'f', 0).f()[0]; };
  m::DdimStepWeights w;
  w.norm_w = norm_w.f(), w.shift = mod.f(), w.scale = mod.f() + d;
  w.out_w = out_w.f(), w.out_b = out_b.f(), w.in_w = in_w.f(), w.in_b = in_b.f(), w.d = d, w.A = A;
  w.eps = scalar("eps"), w.c_t = scalar("c_t"), w.s_t = scalar("s_t"), w.c_prev = scalar("c_prev");
  w.s_prev = scalar("s_prev"), w.sample = scalar("sample") != 0.0f, w.clip = scalar("clip") != 0.0f;
  const bool tokens = scalar("tokens") != 0.0f;
  Tensors result{{"x_next", floats(x.shape)}, {"a_next", floats({batch, H, tokens ? d : 0})}};
  float* xn = reinterpret_cast<float*>(result["x_next"].bytes.data());
  float* an = reinterpret_cast<float*>(result["a_next"].bytes.data());
  std::vector<float> scratch(static_cast<size_t>(d));
  for (int64_t row = 0; row < batch * H; ++row)
    m::ddim_step_row(w, h.f() + row * d, x.f() + row * A, pos.f() + (row % H) * d, xn + row * A,
                     tokens ? an + row * d : nullptr, scratch.data());
  write_tensors(out_path, result);
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
  const char* clone = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma") ? "x86-64-v3" : "default";
#else
  const char* clone = "none";
#endif
  std::printf("{\"ok\": true, \"arch\": \"%s\", \"ddim_clone\": \"%s\"}\n", arch(), clone);
  return 0;
}

int parity(const std::string& case_path, const std::string& out_path, int threads) {
  const Tensors t = read_tensors(case_path);
  if (t.count("h")) return ddim_step(t, out_path);
  const q::Path qpath = product_path();
  const m::Path spath = scan_path();
  const Tensor& a = need(t, "a", 'f', 3);
  const Tensor& conv_w = need(t, "conv_w", 'f', 2);
  const Tensor& A = need(t, "A", 'f', 2);
  const Tensor& mod = need(t, "mod", 'f', 2);
  const int64_t batch = a.shape[0], L = a.shape[1], d = a.shape[2], W = conv_w.shape[0], E = conv_w.shape[1], n = A.shape[1];
  const bool prefix = mod.shape[0] == 0;
  const bool mlp = need(t, "fc1_q", 'b', 2).numel() > 0;
  auto in = pack(t, "in", qpath), xp = pack(t, "xp", qpath), dt = pack(t, "dt", qpath), out = pack(t, "out", qpath);
  std::shared_ptr<const q::PackedWeights> fc1, fc2;
  if (mlp) fc1 = pack(t, "fc1", qpath), fc2 = pack(t, "fc2", qpath);
  m::BlockWeights w;
  w.in = in.get(), w.xp = xp.get(), w.dt = dt.get(), w.out = out.get(), w.fc1 = fc1.get(), w.fc2 = fc2.get();
  w.norm_w = need(t, "norm_w", 'f', 1).f(), w.conv_w = conv_w.f(), w.conv_b = need(t, "conv_b", 'f', 1).f();
  w.dt_b = need(t, "dt_b", 'f', 1).f(), w.A = A.f(), w.D = need(t, "D", 'f', 1).f();
  w.norm2_w = mlp ? need(t, "norm2_w", 'f', 1).f() : nullptr;
  w.d = d, w.E = E, w.W = W, w.n = n, w.eps = need(t, "eps", 'f', 0).f()[0];
  w.check();
  const Tensor& conv_state = need(t, "conv_state", 'f', 3);
  const Tensor& ssm_state = need(t, "ssm_state", 'f', 3);  // either empty: a start from zeros
  if ((conv_state.numel() && conv_state.numel() != batch * E * W) || (ssm_state.numel() && ssm_state.numel() != batch * E * n) ||
      mod.shape[1] != d || (!prefix && mod.shape[0] != 3))
    broken("the states or mod do not fit a");
  m::BlockInputs inputs;
  inputs.a = a.f(), inputs.conv_state = conv_state.numel() ? conv_state.f() : nullptr;
  inputs.ssm_state = ssm_state.numel() ? ssm_state.f() : nullptr;
  inputs.mod = prefix ? nullptr : mod.f(), inputs.batch = batch, inputs.L = L;
  if (t.count("plain")) inputs.plain = static_cast<int64_t>(need(t, "plain", 'f', 0).f()[0]);
  if (inputs.plain < 0 || inputs.plain > L || (prefix && inputs.plain)) broken("plain does not fit a and mod");
  const bool states = prefix || inputs.plain > 0;  // the states after the prefix
  Tensors result{{"a", floats(a.shape)}, {"conv", floats({batch, states ? E : 0, W})}, {"ssm", floats({batch, states ? E : 0, n})}};
  m::BlockOutputs outputs;
  outputs.a = reinterpret_cast<float*>(result["a"].bytes.data());
  if (states) {
    outputs.conv_state = reinterpret_cast<float*>(result["conv"].bytes.data());
    outputs.ssm_state = reinterpret_cast<float*>(result["ssm"].bytes.data());
  }
  Pool pool(threads);
  m::block_forward(w, inputs, outputs, spath, pool.parallel_for());
  write_tensors(out_path, result);
  std::printf("{\"ok\": true, \"arch\": \"%s\", \"scan_path\": \"%s\", \"qgemm_path\": \"%s\", \"threads\": %d}\n", arch(),
              m::path_name(spath), q::path_name(qpath), threads);
  return 0;
}

// ------------------------------------------------------------------ the bench
struct RandomBlock {
  std::vector<int8_t> in_q, xp_q, dt_q, out_q, fc1_q, fc2_q;
  std::vector<float> in_s, xp_s, dt_s, out_s, fc1_s, fc2_s, norm_w, conv_w, conv_b, dt_b, A, D, norm2_w;
  std::shared_ptr<const q::PackedWeights> in, xp, dt, out, fc1, fc2;
  m::BlockWeights w;
};

std::shared_ptr<const q::PackedWeights> random_pack(std::vector<int8_t>& wq, std::vector<float>& ws, int64_t n, int64_t k,
                                                    std::mt19937& rng, q::Path path) {
  std::uniform_int_distribution<int> byte(-127, 127);
  wq.resize(n * k);
  for (auto& v : wq) v = static_cast<int8_t>(byte(rng));
  ws.assign(n, 1.0f / (127.0f * std::sqrt(static_cast<float>(k))));
  return std::make_shared<const q::PackedWeights>(q::pack_quantized(wq.data(), ws.data(), static_cast<int>(n), static_cast<int>(k), path));
}

std::unique_ptr<RandomBlock> random_block(int64_t d, int64_t E, int64_t n, int64_t R, int64_t W, int64_t hidden,
                                          std::mt19937& rng, q::Path path) {
  auto b = std::make_unique<RandomBlock>();
  std::normal_distribution<float> normal(0.0f, 1.0f);
  auto fill = [&](std::vector<float>& v, int64_t size, float scale, float offset) {
    v.resize(size);
    for (auto& x : v) x = offset + scale * normal(rng);
  };
  b->in = random_pack(b->in_q, b->in_s, 2 * E, d, rng, path);
  b->xp = random_pack(b->xp_q, b->xp_s, R + 2 * n, E, rng, path);
  b->dt = random_pack(b->dt_q, b->dt_s, E, R, rng, path);
  b->out = random_pack(b->out_q, b->out_s, d, E, rng, path);
  b->fc1 = random_pack(b->fc1_q, b->fc1_s, 2 * hidden, d, rng, path);
  b->fc2 = random_pack(b->fc2_q, b->fc2_s, d, hidden, rng, path);
  fill(b->norm_w, d, 0.1f, 1.0f), fill(b->norm2_w, d, 0.1f, 1.0f), fill(b->conv_w, W * E, 0.3f, 0.0f);
  fill(b->conv_b, E, 0.1f, 0.0f), fill(b->dt_b, E, 0.5f, -4.0f), fill(b->D, E, 0.1f, 1.0f);
  b->A.resize(E * n);
  for (int64_t e = 0; e < E; ++e)
    for (int64_t k = 0; k < n; ++k) b->A[e * n + k] = -static_cast<float>(k + 1);
  m::BlockWeights& w = b->w;
  w.in = b->in.get(), w.xp = b->xp.get(), w.dt = b->dt.get(), w.out = b->out.get(), w.fc1 = b->fc1.get(), w.fc2 = b->fc2.get();
  w.norm_w = b->norm_w.data(), w.conv_w = b->conv_w.data(), w.conv_b = b->conv_b.data(), w.dt_b = b->dt_b.data();
  w.A = b->A.data(), w.D = b->D.data(), w.norm2_w = b->norm2_w.data(), w.d = d, w.E = E, w.W = W, w.n = n;
  w.check();
  return b;
}

template <class F>
double median_us(int reps, F&& f) {
  std::vector<double> times;
  for (int r = 0; r < reps; ++r) {
    const auto t0 = std::chrono::steady_clock::now();
    f();
    times.push_back(std::chrono::duration<double, std::micro>(std::chrono::steady_clock::now() - t0).count());
  }
  std::nth_element(times.begin(), times.begin() + reps / 2, times.end());
  return times[reps / 2];
}

// This machine's read bandwidth, bytes a second: one thread summing 512 MB of floats, best of 5 (as the Python
// benchmarks measure it with numpy), so the bench states the floor of reading a step's weights once.
double read_bandwidth() {
  std::vector<float> buffer(size_t{1} << 27, 1.0f);
  double best = 1e30;
  volatile float sink = 0.0f;
  for (int r = 0; r < 5; ++r) {
    const auto t0 = std::chrono::steady_clock::now();
    float lanes[64] = {};  // independent sums the compiler keeps in vector registers
    for (size_t i = 0; i < buffer.size(); i += 64)
      for (int j = 0; j < 64; ++j) lanes[j] += buffer[i + j];
    float total = 0.0f;
    for (float v : lanes) total += v;
    sink = total;
    best = std::min(best, std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  }
  (void)sink;
  return static_cast<double>(buffer.size() * sizeof(float)) / best;
}

int bench(int threads) {
  // robotwin: d 512, expand 2, d_state 64, dt rank 32, conv 4, the gated MLP's hidden 1408; 8 blocks; H = 8 rows
  const int64_t d = 512, E = 1024, n = 64, R = 32, W = 4, hidden = 1408, blocks = 8, rows = 8;
  const q::Path qpath = product_path();
  const m::Path spath = scan_path();
  std::mt19937 rng(0);
  std::vector<std::unique_ptr<RandomBlock>> step;
  for (int64_t i = 0; i < blocks; ++i) step.push_back(random_block(d, E, n, R, W, hidden, rng, qpath));
  std::normal_distribution<float> normal(0.0f, 1.0f);
  auto randoms = [&](int64_t size, float scale) {
    std::vector<float> v(size);
    for (auto& x : v) x = scale * normal(rng);
    return v;
  };
  const auto a = randoms(rows * d, 1.0f), mod = randoms(3 * d, 0.1f), conv_state = randoms(E * W, 1.0f),
             ssm_state = randoms(E * n, 0.3f);
  std::vector<float> out(rows * d);
  Pool pool(threads);
  const m::ParallelFor pf = pool.parallel_for();
  m::BlockInputs inputs;
  inputs.a = a.data(), inputs.conv_state = conv_state.data(), inputs.ssm_state = ssm_state.data(), inputs.mod = mod.data();
  inputs.batch = 1, inputs.L = rows;
  m::BlockOutputs outputs;
  outputs.a = out.data();
  const int reps = 200;
  const double step_us = median_us(reps, [&] {
    for (auto& b : step) m::block_forward(b->w, inputs, outputs, spath, pf);
  });
  // the step's arithmetic alone: block 0 run as often as the step has blocks, its weights (3.9 MB) from the caches
  const double cached_step_us = median_us(reps, [&] {
    for (int64_t i = 0; i < blocks; ++i) m::block_forward(step[0]->w, inputs, outputs, spath, pf);
  });
  // the parts of one block, each on its own (the weights of block 0 from the caches, as the parts are repeated)
  const m::BlockWeights& w = step[0]->w;
  std::vector<float> x(rows * 2 * hidden), y(rows * 2 * hidden), xc(rows * E), dt(rows * E), Bm(rows * n), Cm(rows * n);
  for (auto& v : x) v = normal(rng);
  for (auto& v : dt) v = normal(rng) - 2.0f;
  for (auto& v : Bm) v = normal(rng);
  for (auto& v : Cm) v = normal(rng);
  q::QuantizedRows qrows;
  std::map<std::string, double> parts;
  const std::pair<const char*, const q::PackedWeights*> products[] = {{"in_proj", w.in}, {"x_proj", w.xp}, {"dt_proj", w.dt},
                                                                      {"out_proj", w.out}, {"fc1", w.fc1}, {"fc2", w.fc2}};
  for (const auto& [name, p] : products)
    parts[name] = median_us(reps, [&] { m::q8_matmul(pf, x.data(), rows, p->k, *p, nullptr, y.data(), qrows); });
  parts["quantize_rows(E)"] = median_us(reps, [&] { q::quantize_rows(x.data(), rows, static_cast<int>(E), qrows, qpath); });
  parts["rms_norm"] = median_us(reps, [&] { m::rms_norm(x.data(), rows, d, w.norm_w, w.eps, mod.data(), mod.data() + d, y.data()); });
  std::vector<float> conv_after(E * W);
  m::ConvProblem cp{x.data(), conv_state.data(), w.conv_w, w.conv_b, xc.data(), conv_after.data(), 1, rows, E, W};
  m::ConvTask conv_task{&cp, (E + 255) / 256};
  parts["conv"] = median_us(reps, [&] { pf(m::run_conv_task, static_cast<size_t>(conv_task.blocks_per_row), &conv_task); });
  m::Problem sp{xc.data(), dt.data(), Bm.data(), Cm.data(), x.data(), w.A, w.D, ssm_state.data(), y.data(), nullptr, 1, rows, E, n};
  m::ScanTask scan_task{&sp, spath, (E + m::kBlock - 1) / m::kBlock};
  parts["scan"] = median_us(reps, [&] { pf(m::run_scan_task, static_cast<size_t>(scan_task.blocks_per_row), &scan_task); });
  parts["empty parallel_for"] = median_us(reps, [&] { pf([](void*, size_t) {}, 8, nullptr); });
  double weight_bytes = 0;
  for (auto& b : step)
    for (const q::PackedWeights* p : {b->w.in, b->w.xp, b->w.dt, b->w.out, b->w.fc1, b->w.fc2})
      weight_bytes += static_cast<double>(p->n) * p->k;
  // the floor of one read of the step's weights at this machine's bandwidth, and the step and its arithmetic alone
  // against it: where the arithmetic alone is above a target ratio, no way of reading the weights meets it
  const double read_gbs = read_bandwidth() / 1e9, floor_us = weight_bytes / (read_gbs * 1e3);
  std::printf("{\"arch\": \"%s\", \"scan_path\": \"%s\", \"qgemm_path\": \"%s\", \"threads\": %d, \"rows\": %lld, "
              "\"blocks\": %lld, \"weight_mb\": %.2f, \"read_gbs\": %.1f, \"floor_us\": %.1f, \"step_us\": %.1f, "
              "\"step_over_floor\": %.2f, \"cached_step_us\": %.1f, \"cached_step_over_floor\": %.2f, "
              "\"block_parts_us\": {",
              arch(), m::path_name(spath), q::path_name(qpath), threads, static_cast<long long>(rows),
              static_cast<long long>(blocks), weight_bytes / 1e6, read_gbs, floor_us, step_us, step_us / floor_us,
              cached_step_us, cached_step_us / floor_us);
  const char* sep = "";
  for (const auto& [name, us] : parts) std::printf("%s\"%s\": %.1f", sep, name.c_str(), us), sep = ", ";
  std::printf("}}\n");
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    const std::string first = argc > 1 ? argv[1] : "";
    if (first == "--bench") return bench(argc > 2 ? std::atoi(argv[2]) : 1);
    if (argc < 3 || argc > 4) {
      std::fprintf(stderr, "usage: block_check CASE OUT [THREADS] | block_check --bench [THREADS]\n");
      return 1;
    }
    return parity(argv[1], argv[2], argc > 3 ? std::max(1, std::atoi(argv[3])) : 1);
  } catch (const PathError& e) {
    std::printf("{\"ok\": false, \"path_error\": \"%s\"}\n", e.what());
    return 2;
  } catch (const std::exception& e) {
    std::printf("{\"ok\": false, \"error\": \"%s\"}\n", e.what());
    return 1;
  }
}
