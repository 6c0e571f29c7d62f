"""Parameter counts per component, as printed by ``dssp-params``."""

from __future__ import annotations

from torch import nn

# (row label, parameter-name prefixes it sums); a name is counted by the first row it matches.
GROUPS: list[tuple[str, tuple[str, ...]]] = [
    ("E_obs point encoder (DP3)", ("obs_encoder.point_encoder.",)),
    ("E_obs state MLP", ("obs_encoder.state_encoder.",)),
    ("E_obs fusion projection", ("obs_encoder.projection.",)),
    ("G_psi history encoder", ("history_encoder.",)),
    ("g_phi dynamics predictor", ("dynamics.",)),
    ("f_theta blocks (mixer + MLP)", ("denoiser.layers.",)),
    ("f_theta UNet FiLM projections (DP3)", ()),
    ("f_theta UNet convolutions (DP3)", ("denoiser.down.", "denoiser.mid.", "denoiser.up.", "denoiser.head.")),
    ("f_theta UNet step encoder (DP3)", ("denoiser.step_encoder.",)),
    ("f_theta AdaLN modulation", ("denoiser.final_modulation.",)),
    ("f_theta timestep embedding", ("denoiser.time_embed.",)),
    ("f_theta action in/out + final norm", ("denoiser.",)),
]


def _row(name: str) -> str:
    if ".modulation." in name:
        return "f_theta AdaLN modulation"
    if name.startswith("denoiser.") and ".film." in name:
        return "f_theta UNet FiLM projections (DP3)"
    for label, prefixes in GROUPS:
        if name.startswith(prefixes):
            return label
    return "other"


def parameter_breakdown(model: nn.Module) -> list[tuple[str, int]]:
    """[(component, number of parameters)] in a fixed order, then ("total", n)."""
    counts: dict[str, int] = {label: 0 for label, _ in GROUPS}
    for name, p in model.named_parameters():
        counts[_row(name)] = counts.get(_row(name), 0) + p.numel()
    rows = [(label, n) for label, n in counts.items() if n]
    return rows + [("total", sum(p.numel() for p in model.parameters()))]


def format_breakdown(rows: list[tuple[str, int]]) -> str:
    width = max(len(label) for label, _ in rows)
    lines = [f"{'component':<{width}}  {'parameters':>12}  {'M':>7}"]
    for label, n in rows:
        lines.append(f"{label:<{width}}  {n:>12,}  {n / 1e6:>7.2f}")
    return "\n".join(lines)
