"""DSSP chunk against DP3 chunk on the same CPU, measured in one run.

    python benchmarks/dp3_comparison.py MODEL_DIR [--threads N] [--repeats R] [--quick] [--precision fp32|int8|int4]
                                       [--dp3-dims D1 D2 D3] [--json PATH [--force]]

Times, batch 1, in one process and one after the other (DSSP in ONNX Runtime, then DP3 in ONNX Runtime, then
DP3 in eager PyTorch; 2 warm-up calls each, then ``--repeats`` timed calls; median and p90 in ms):

- DSSP: one action chunk of MODEL_DIR (``OnnxPolicy.act``, the denoiser graph with its K DDIM steps) after a
  few observations. The history update (``OnnxPolicy.observe``) runs once per control tick, not per chunk;
  its median is reported too, and a per-chunk total with ``n_action_steps`` of them.
- DP3: the policy head of DP3 (3D Diffusion Policy) at its RoboTwin configuration: encoding the n_obs = 3
  observation frames, then K evaluations of the conditional 1-D UNet with the deterministic DDIM update
  between them. K is the DSSP model's ``denoise_steps`` (DP3's RoboTwin setting is 10 as well), so both sides
  run the same number of denoiser evaluations; the point count, state and action sizes are the DSSP model's,
  so both solve the same problem. In ONNX Runtime it runs as two graphs exported from the PyTorch modules
  (``torch.onnx.export``, TorchScript-based, opset 17) into a temporary directory: the encoder graph once,
  the one-step UNet graph (timestep an input) K times, the DDIM update in numpy in between. In PyTorch it runs
  eagerly under ``torch.inference_mode()`` with the same DDIM update in torch.

Prints a Markdown table and DP3 / DSSP ratios; ``--json`` writes every figure (a new file; ``--force``
replaces one, checked before measuring).

DP3 architecture as timed (P points, S state size, A action size, H = 8 horizon, T = 3 observation steps):

    point cloud (B, T, P, 3) -> per point Linear 3->64->128->256, each + LayerNorm + ReLU -> max over P
        -> (B*T, 256) -> Linear(256, 128) + LayerNorm -> point feature (B*T, 128)
    agent_pos (B, T, S) -> Linear(S, 64) + ReLU + Linear(64, 64) -> state feature (B*T, 64)
    obs features: concat -> (B*T, 192) -> global cond (B, T*192)
    timestep (B,) -> sinusoidal (B, 64) -> Linear(64, 256) + Mish + Linear(256, 64) -> (B, 64)
    FiLM condition: concat(step embedding, global cond) -> (B, 64 + T*192)
    UNet input (B, H, A) -> (B, A, H)
        down: [2 FiLM residual blocks (Conv1d k5 + GroupNorm(8) + Mish, x2, FiLM scale and bias after the
               first, 1x1 residual conv when the width changes), then Conv1d k3 stride 2] at widths 512 (H),
               1024 (H/2), 2048 (H/4, no downsampling)
        mid: 2 FiLM residual blocks at 2048 (B, 2048, H/4)
        up: [concat skip, 2 FiLM residual blocks, ConvTranspose1d k4 stride 2] to 1024 (H/2), then 512 (H)
        head: Conv1d k5 + GroupNorm + Mish, Conv1d 1x1 -> (B, A, H)
    UNet output (B, H, A): the predicted clean sample (DP3's ``prediction_type: sample``)
    DDIM: 100 training steps, squaredcos_cap_v2 betas, clip_sample, eta 0, K inference steps.

The widths [512, 1024, 2048], kernel 5, 8 groups, step embedding 64, encoder output 128, LayerNorm in the
point encoder with a final LayerNorm, horizon 8 and 3 observation steps are DP3's RoboTwin settings
(``robot_dp3.yaml``; ``--dp3-dims`` changes the widths). The head is written here from DP3's published
architecture for timing only: it has random, untrained weights (speed does not depend on the values) and
contains no DP3 code. DP3's observation/action normalisation (elementwise) is left out.
"""

from __future__ import annotations

import math
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the benchmarks' shared helpers
from bench_output import check_json, emit  # noqa: E402
from dssp_data.cli_runner import ArgumentParser, run_cli  # noqa: E402
from dssp_data import machine
from dssp_data.errors import ConfigError
from dssp_deploy.latency import time_calls
from dssp_deploy.manifest import PRECISIONS
from dssp_deploy.onnx_policy import OnnxPolicy
from dssp_deploy.sessions import check_threads, default_threads
from dssp_train.config import DiffusionConfig
from dssp_train.model.scheduler import DiffusionSchedule

# DP3 at RoboTwin (robot_dp3.yaml, pointnet_extractor.py, conditional_unet1d.py)
DP3_ROBOTWIN = {
    "down_dims": [512, 1024, 2048],
    "kernel_size": 5,
    "n_groups": 8,
    "step_embed_dim": 64,
    "point_widths": [64, 128, 256],
    "point_out": 128,
    "state_mlp": [64, 64],
    "horizon": 8,
    "n_obs_steps": 3,
    "n_action_steps": 6,
    "num_train_timesteps": 100,
}
WARMUP = 2
REPEATS, QUICK_REPEATS = 20, 3
OPSET = 17


# ------------------------------------------------------------------------------------------------ DP3 head
class SinusoidalEmbedding(nn.Module):
    """timestep (B,) -> (B, dim): sin and cos of the timestep at geometrically spaced frequencies."""

    def __init__(self, dim: int):
        super().__init__()
        half = dim // 2
        self.register_buffer("freqs", torch.exp(torch.arange(half, dtype=torch.float32) * -(math.log(10000.0) / (half - 1))))

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        arg = t.to(torch.float32)[:, None] * self.freqs[None, :]
        return torch.cat([arg.sin(), arg.cos()], dim=-1)


class ConvBlock(nn.Sequential):
    """(B, C_in, L) -> (B, C_out, L): Conv1d (same padding) + GroupNorm + Mish."""

    def __init__(self, c_in: int, c_out: int, kernel_size: int, n_groups: int):
        super().__init__(nn.Conv1d(c_in, c_out, kernel_size, padding=kernel_size // 2), nn.GroupNorm(n_groups, c_out), nn.Mish())


class FiLMResidualBlock(nn.Module):
    """(B, C_in, L), cond (B, D) -> (B, C_out, L); per-channel scale and bias from cond after the first conv."""

    def __init__(self, c_in: int, c_out: int, cond_dim: int, kernel_size: int, n_groups: int):
        super().__init__()
        self.c_out = c_out
        self.conv1 = ConvBlock(c_in, c_out, kernel_size, n_groups)
        self.conv2 = ConvBlock(c_out, c_out, kernel_size, n_groups)
        self.film = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * c_out))
        self.skip = nn.Conv1d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        scale, bias = self.film(cond).reshape(cond.shape[0], 2, self.c_out, 1).unbind(1)
        h = self.conv1(x) * scale + bias
        return self.conv2(h) + self.skip(x)


class DP3UNet(nn.Module):
    """sample (B, H, A), timestep (B,) or (1,) int64, global cond (B, G) -> (B, H, A). H divisible by 2^(levels-1)."""

    def __init__(self, action_dim: int, global_cond_dim: int, down_dims=(512, 1024, 2048), kernel_size: int = 5,
                 n_groups: int = 8, step_embed_dim: int = 64):
        super().__init__()
        e = step_embed_dim
        self.step_encoder = nn.Sequential(SinusoidalEmbedding(e), nn.Linear(e, 4 * e), nn.Mish(), nn.Linear(4 * e, e))
        cond = e + global_cond_dim
        widths = [action_dim, *down_dims]
        levels = list(zip(widths[:-1], widths[1:]))

        def block(c_in, c_out):
            return FiLMResidualBlock(c_in, c_out, cond, kernel_size, n_groups)

        self.down = nn.ModuleList(
            nn.ModuleList([block(c_in, c_out), block(c_out, c_out),
                           nn.Conv1d(c_out, c_out, 3, stride=2, padding=1) if i < len(levels) - 1 else nn.Identity()])
            for i, (c_in, c_out) in enumerate(levels)
        )
        self.mid = nn.ModuleList([block(widths[-1], widths[-1]), block(widths[-1], widths[-1])])
        # one up level per downsampling: the coarsest skips, each level back to twice the length
        self.up = nn.ModuleList(
            nn.ModuleList([block(2 * c_out, c_in), block(c_in, c_in), nn.ConvTranspose1d(c_in, c_in, 4, stride=2, padding=1)])
            for c_in, c_out in reversed(levels[1:])
        )
        self.head = nn.Sequential(ConvBlock(down_dims[0], down_dims[0], kernel_size, n_groups), nn.Conv1d(down_dims[0], action_dim, 1))

    def forward(self, sample: torch.Tensor, timestep: torch.Tensor, global_cond: torch.Tensor) -> torch.Tensor:
        cond = torch.cat([self.step_encoder(timestep.expand(sample.shape[0])), global_cond], dim=-1)
        x = sample.transpose(1, 2)
        skips = []
        for first, second, down in self.down:
            x = second(first(x, cond), cond)
            skips.append(x)
            x = down(x)
        for mid in self.mid:
            x = mid(x, cond)
        for first, second, up in self.up:
            x = torch.cat([x, skips.pop()], dim=1)
            x = up(second(first(x, cond), cond))
        return self.head(x).transpose(1, 2)


class DP3Encoder(nn.Module):
    """point cloud (B, T, P, 3), agent_pos (B, T, S) -> global cond (B, T * (point_out + state_mlp[-1]))."""

    def __init__(self, state_dim: int, point_widths=(64, 128, 256), point_out: int = 128, state_mlp=(64, 64)):
        super().__init__()
        layers, c = [], 3
        for w in point_widths:
            layers += [nn.Linear(c, w), nn.LayerNorm(w), nn.ReLU()]
            c = w
        self.point_mlp = nn.Sequential(*layers)
        self.point_project = nn.Sequential(nn.Linear(c, point_out), nn.LayerNorm(point_out))
        layers, c = [], state_dim
        for w in state_mlp[:-1]:
            layers += [nn.Linear(c, w), nn.ReLU()]
            c = w
        self.state_mlp = nn.Sequential(*layers, nn.Linear(c, state_mlp[-1]))
        self.feature_dim = point_out + state_mlp[-1]

    def forward(self, point_cloud: torch.Tensor, agent_pos: torch.Tensor) -> torch.Tensor:
        points = self.point_mlp(point_cloud.flatten(0, 1)).amax(dim=1)  # (B*T, widths[-1])
        feats = torch.cat([self.point_project(points), self.state_mlp(agent_pos.flatten(0, 1))], dim=-1)
        return feats.reshape(point_cloud.shape[0], -1)


def build_dp3(state_dim: int, action_dim: int, down_dims=None, seed: int = 0, **overrides) -> tuple[DP3Encoder, DP3UNet, dict]:
    """(encoder, UNet, config) at DP3's RoboTwin settings (``overrides`` replace any), random weights, eval mode."""
    cfg = {**DP3_ROBOTWIN, **overrides, "state_dim": state_dim, "action_dim": action_dim}
    if down_dims is not None:
        cfg["down_dims"] = [int(d) for d in down_dims]
    check_dp3_config(cfg)
    torch.manual_seed(seed)
    encoder = DP3Encoder(state_dim, cfg["point_widths"], cfg["point_out"], cfg["state_mlp"]).eval()
    unet = DP3UNet(action_dim, cfg["n_obs_steps"] * encoder.feature_dim, cfg["down_dims"], cfg["kernel_size"],
                   cfg["n_groups"], cfg["step_embed_dim"]).eval()
    return encoder, unet, cfg


def check_dp3_config(cfg: dict) -> None:
    dims, groups, horizon = cfg["down_dims"], cfg["n_groups"], cfg["horizon"]
    if not dims or any(d < groups or d % groups for d in dims):
        raise ConfigError(f"--dp3-dims must be multiples of {groups} (GroupNorm groups), at least {groups}, got {dims}")
    if horizon % 2 ** (len(dims) - 1):
        raise ConfigError(f"--dp3-dims: {len(dims)} levels halve the horizon {len(dims) - 1} times; "
                          f"{horizon} is not divisible by {2 ** (len(dims) - 1)}")


def n_params(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


# ------------------------------------------------------------------------------------------------ DDIM
def ddim_steps(k: int, num_train_timesteps: int = 100) -> list[tuple[int, float, float]]:
    """[(timestep, alpha_prod_t, alpha_prod_prev)] of DP3's DDIM schedule with K inference steps."""
    schedule = DiffusionSchedule(DiffusionConfig(num_train_timesteps=num_train_timesteps, num_inference_steps=k))
    return [(t, *schedule.ddim_coefficients(t, k)) for t in schedule.inference_timesteps(k)]


def ddim_update(x0, x, a_t: float, a_prev: float):
    """x_t -> x_prev for a predicted clean sample x0 (eta 0, x0 clipped to [-1, 1]); numpy arrays or torch tensors."""
    eps = (x - a_t**0.5 * x0) / (1.0 - a_t) ** 0.5
    return a_prev**0.5 * x0.clip(-1.0, 1.0) + (1.0 - a_prev) ** 0.5 * eps


def dp3_chunk_torch(encoder: DP3Encoder, unet: DP3UNet, steps, point_cloud, agent_pos, noise) -> torch.Tensor:
    """One DP3 chunk in PyTorch: encode the T frames, K UNet evaluations with DDIM updates -> (B, H, A)."""
    cond = encoder(point_cloud, agent_pos)
    x = noise
    for t, a_t, a_prev in steps:
        x = ddim_update(unet(x, torch.tensor([t], dtype=torch.int64), cond), x, a_t, a_prev)
    return x


def export_graph(module: nn.Module, example: tuple, path: Path, inputs: list[str], outputs: list[str]) -> Path:
    """The module as an ONNX graph (TorchScript-based exporter, opset 17), batch dimension dynamic."""
    from export.to_onnx import quiet_tracing

    with torch.no_grad(), quiet_tracing():
        torch.onnx.export(module, example, str(path), dynamo=False, opset_version=OPSET, input_names=inputs,
                          output_names=outputs, dynamic_axes={n: {0: "B"} for n in inputs + outputs},
                          do_constant_folding=True)
    return path


def ort_session(path: Path, threads: int):
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


class DP3OnnxChunk:
    """DP3's chunk in ONNX Runtime: the encoder graph once, the one-step UNet graph K times, DDIM in numpy."""

    def __init__(self, encoder: DP3Encoder, unet: DP3UNet, cfg: dict, n_points: int, steps, threads: int, folder: Path):
        t, s, h, a = cfg["n_obs_steps"], cfg["state_dim"], cfg["horizon"], cfg["action_dim"]
        # traced at batch 2, so that no size-1 batch dimension is baked into the graphs
        pc, pos = torch.zeros(2, t, n_points, 3), torch.zeros(2, t, s)
        with torch.no_grad():
            cond = encoder(pc, pos)
        enc_path = export_graph(encoder, (pc, pos), folder / "dp3_encoder.onnx", ["point_cloud", "agent_pos"], ["global_cond"])
        unet_path = export_graph(unet, (torch.zeros(2, h, a), torch.zeros(2, dtype=torch.int64), cond),
                                 folder / "dp3_unet.onnx", ["sample", "timestep", "global_cond"], ["x0"])
        self.graph_mib = {"encoder": enc_path.stat().st_size / 2**20, "unet": unet_path.stat().st_size / 2**20}
        self.encoder, self.unet = ort_session(enc_path, threads), ort_session(unet_path, threads)
        self.steps = [(np.array([t_], np.int64), a_t, a_prev) for t_, a_t, a_prev in steps]

    def __call__(self, point_cloud: np.ndarray, agent_pos: np.ndarray, noise: np.ndarray) -> np.ndarray:
        cond = self.encoder.run(None, {"point_cloud": point_cloud, "agent_pos": agent_pos})[0]
        x = noise
        for t, a_t, a_prev in self.steps:
            x0 = self.unet.run(None, {"sample": x, "timestep": t, "global_cond": cond})[0]
            x = ddim_update(x0, x, a_t, a_prev)
        return x


# ------------------------------------------------------------------------------------------------ measuring
def summary(samples: list[float]) -> dict:
    p50, p90 = np.percentile(samples, [50, 90])
    return {"median": float(p50), "p90": float(p90), "n": len(samples), "samples": [float(s) for s in samples]}


def compare(model_dir: Path, threads: int | None, repeats: int, precision: str = "fp32", dp3_dims=None) -> dict:
    import onnxruntime

    n_threads = threads or default_threads()
    torch.set_num_threads(n_threads)
    policy = OnnxPolicy(model_dir, threads=n_threads, precision=precision, kernel="auto")
    k, p, s, a = policy.denoise_steps, policy.n_points, policy.state_dim, policy.action_dim
    rng = np.random.default_rng(0)

    # DSSP: a few observations, then time one chunk; the per-tick history update on its own
    pc1, pos1 = policy.example_observation(rng, p)  # inside the trained ranges (the runtime refuses others)
    policy.reset()
    for _ in range(policy.n_obs_steps + 2):
        policy.observe(pc1, pos1)
    dssp_chunk = time_calls(lambda: policy.act(seed=0), repeats, warmup=WARMUP)
    dssp_observe = time_calls(lambda: policy.observe(pc1, pos1), repeats, warmup=WARMUP)

    # DP3 at RoboTwin, the DSSP model's P, S, A and K
    encoder, unet, cfg = build_dp3(s, a, dp3_dims)
    steps = ddim_steps(k, cfg["num_train_timesteps"])
    t, h = cfg["n_obs_steps"], cfg["horizon"]
    pc = rng.standard_normal((1, t, p, 3), dtype=np.float32)
    pos = rng.standard_normal((1, t, s), dtype=np.float32)
    noise = rng.standard_normal((1, h, a), dtype=np.float32)
    with tempfile.TemporaryDirectory(prefix="dp3_onnx_") as folder:
        chunk = DP3OnnxChunk(encoder, unet, cfg, p, steps, n_threads, Path(folder))
        dp3_ort = time_calls(lambda: chunk(pc, pos, noise), repeats, warmup=WARMUP)
        ort_out = chunk(pc, pos, noise)
        graph_mib = chunk.graph_mib
        chunk = None  # the sessions close before their folder is removed
    tpc, tpos, tnoise = (torch.from_numpy(x) for x in (pc, pos, noise))
    with torch.inference_mode():
        dp3_torch = time_calls(lambda: dp3_chunk_torch(encoder, unet, steps, tpc, tpos, tnoise), repeats, warmup=WARMUP)
        torch_out = dp3_chunk_torch(encoder, unet, steps, tpc, tpos, tnoise).numpy()

    lat = {"dssp_ort_chunk": summary(dssp_chunk), "dssp_ort_history_step": summary(dssp_observe),
           "dp3_ort_chunk": summary(dp3_ort), "dp3_torch_chunk": summary(dp3_torch)}
    med = {key: v["median"] for key, v in lat.items()}
    dssp_per_chunk = med["dssp_ort_chunk"] + policy.n_action_steps * med["dssp_ort_history_step"]
    params = {"encoder": n_params(encoder), "unet": n_params(unet)}
    return {
        "model_dir": str(model_dir), "precision": policy.precision, "kernel_note": policy.kernel_note,
        "machine": {"cpu": machine.cpu()[0], "threads": n_threads, "torch": torch.__version__,
                    "torch_threads": torch.get_num_threads(), "onnxruntime": onnxruntime.__version__},
        "problem": {"n_points": p, "state_dim": s, "action_dim": a, "denoise_steps": k,
                    "dssp_horizon": policy.horizon, "dssp_n_obs_steps": policy.n_obs_steps,
                    "dssp_n_action_steps": policy.n_action_steps, "dp3_horizon": h, "dp3_n_obs_steps": t},
        "dp3": {"config": cfg, "params": {**params, "total": params["encoder"] + params["unet"]},
                "onnx": f"encoder graph once + one-step UNet graph x{k} + numpy DDIM update (opset {OPSET})",
                "onnx_graph_mib": graph_mib, "ddim_timesteps": [st[0] for st in steps],
                "ort_vs_torch_max_abs_diff": float(np.abs(ort_out - torch_out).max())},
        "settings": {"warmup": WARMUP, "repeats": repeats},
        "latency_ms": lat,
        "median_ms": med,
        "dssp_per_chunk_with_history_ms": dssp_per_chunk,
        "ratio": {"dp3_ort_over_dssp_ort": med["dp3_ort_chunk"] / med["dssp_ort_chunk"],
                  "dp3_torch_over_dssp_ort": med["dp3_torch_chunk"] / med["dssp_ort_chunk"],
                  "dp3_ort_over_dssp_with_history": med["dp3_ort_chunk"] / dssp_per_chunk},
    }


def markdown(r: dict) -> str:
    lat, ratio, prob, dp3 = r["latency_ms"], r["ratio"], r["problem"], r["dp3"]
    k = prob["denoise_steps"]
    lines = [
        f"CPU: {r['machine']['cpu']}; {r['machine']['threads']} threads (ORT intra-op, torch {r['machine']['torch']}); "
        f"{r['settings']['repeats']} timed calls after {r['settings']['warmup']} warm-up, batch 1",
        f"Problem: {prob['n_points']} points, state {prob['state_dim']}, action {prob['action_dim']}, K = {k} denoiser "
        f"evaluations per chunk (the DSSP model's denoise_steps, used for DP3 too)",
        f"DSSP: {r['model_dir']} ({r['precision']}; {r['kernel_note']}), horizon {prob['dssp_horizon']}",
        f"DP3 (RoboTwin settings, random weights): horizon {prob['dp3_horizon']}, {prob['dp3_n_obs_steps']} obs steps, "
        f"UNet widths {dp3['config']['down_dims']}; parameters: encoder {dp3['params']['encoder']:,}, "
        f"UNet {dp3['params']['unet']:,}; ONNX: {dp3['onnx']}",
        "",
        "| chunk | median ms | p90 ms | DP3 / DSSP |",
        "|---|---:|---:|---:|",
        f"| DSSP (ONNX Runtime) | {lat['dssp_ort_chunk']['median']:.2f} | {lat['dssp_ort_chunk']['p90']:.2f} | 1.0x |",
        f"| DP3 (ONNX Runtime) | {lat['dp3_ort_chunk']['median']:.2f} | {lat['dp3_ort_chunk']['p90']:.2f} | "
        f"{ratio['dp3_ort_over_dssp_ort']:.1f}x |",
        f"| DP3 (PyTorch eager) | {lat['dp3_torch_chunk']['median']:.2f} | {lat['dp3_torch_chunk']['p90']:.2f} | "
        f"{ratio['dp3_torch_over_dssp_ort']:.1f}x |",
        "",
        f"DSSP history update (ORT, once per control tick): median {lat['dssp_ort_history_step']['median']:.2f} ms; "
        f"chunk + {prob['dssp_n_action_steps']} updates = {r['dssp_per_chunk_with_history_ms']:.2f} ms "
        f"(DP3 ORT / that: {ratio['dp3_ort_over_dssp_with_history']:.1f}x)",
        f"DP3 ORT vs PyTorch chunk, same input: max |difference| {dp3['ort_vs_torch_max_abs_diff']:.2e}",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog="dp3_comparison.py", description=__doc__.split("\n\n")[0])
    p.add_argument("model_dir", type=Path, help="a DSSP model directory (python -m export.to_onnx)")
    p.add_argument("--threads", type=int, help="ONNX Runtime and torch intra-op threads (default: all CPUs)")
    p.add_argument("--repeats", type=int, help=f"timed calls per measurement (default {REPEATS}; --quick {QUICK_REPEATS})")
    p.add_argument("--quick", action="store_true", help=f"short run: {QUICK_REPEATS} timed calls (tests)")
    p.add_argument("--precision", choices=list(PRECISIONS), default="fp32", help="the DSSP graphs to time (DP3 runs in fp32)")
    p.add_argument("--dp3-dims", type=int, nargs="+", metavar="D", default=None,
                   help=f"DP3 UNet widths per level (default RoboTwin's {' '.join(map(str, DP3_ROBOTWIN['down_dims']))}; "
                        "smaller for tests)")
    p.add_argument("--json", type=Path, help="write every figure here (a new file; --force replaces one)")
    p.add_argument("--force", action="store_true", help="replace an existing --json file")
    args = p.parse_args(argv)

    def _main() -> int:
        check_threads(args.threads)
        repeats = args.repeats if args.repeats is not None else QUICK_REPEATS if args.quick else REPEATS
        if repeats < 1:
            raise ConfigError(f"--repeats must be at least 1, got {repeats}")
        if args.dp3_dims is not None:
            check_dp3_config({**DP3_ROBOTWIN, "down_dims": args.dp3_dims})
        check_json(args.json, args.force)
        report = compare(args.model_dir, args.threads, repeats, args.precision, args.dp3_dims)
        return emit(report, markdown(report), args.json, args.force)

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())
