"""The parity report of :mod:`export.verify` in words: the table ``format_report`` prints, the worst figure
(``describe_worst``) and the one-line :class:`~dssp_core.errors.ParityError` ``check_report`` raises when a figure
exceeds the bound.
"""

from __future__ import annotations

from typing import Any

from dssp_core.errors import ParityError

FIGURES = ("z_t", "c_t", "state", "action")
ACTION_UNITS = "normalised action units (1 = half the channel's fitted range)"
MODEL_UNITS = "model units"


def _place(w: dict[str, Any]) -> str:
    """Where a figure's worst error is, in words: ' at step 417, horizon 2, action channel 3' (or '')."""
    place = [f"step {w['step']}"] if "step" in w else []
    if "channel" in w:
        place.append(f"horizon {w['horizon']}, action channel {w['channel']}")
    elif "input" in w:
        place.append(f"{w['input']} channel {w['index']}")
    elif "index" in w:
        place.append(f"feature {w['index']}")
    return f" at {', '.join(place)}" if place else ""


def _units(figure: str) -> str:
    return "normalised action units" if figure == "action" else MODEL_UNITS


def describe_worst(report: dict[str, Any]) -> str:
    """The worst figure in words: 'onnx action 3.10e-05 normalised action units at step 417, horizon 2, action channel 3'."""
    w = report["worst_at"]
    return f"{w['backend']} {w['figure']} {report['worst']:.2e} {_units(w['figure'])}{_place(w)}"


def format_report(report: dict[str, Any]) -> str:
    """The report as a few aligned lines."""
    ticks = report["chunk_ticks"]
    shown = ", ".join(map(str, ticks)) if len(ticks) <= 8 else ", ".join(map(str, ticks[:6])) + f", ..., {ticks[-1]}"
    total = report.get("chunk_ticks_total", report["chunks"])
    lines = [
        (
            f"parity over {report['steps']} steps x batch {report['batch']} ({report['trajectory']}): the exported graphs "
            f"vs PyTorch fp32 on the training path, max abs error, bound {report['bound']:g}"
        ),
        (
            f"  reference: z_t and c_t of every step (c_t from the sequence path over the whole trajectory), "
            f"{report['chunks']} of {total} chunks (steps {shown}) in one batch, same noise"
        ),
        f"  {'':<12}" + "".join(f"{f:>11}" for f in FIGURES),
    ]
    for name, e in report["errors"].items():
        how = (
            f"one batch at steps {', '.join(map(str, report['batch_checked'][name]))}, denoiser on the reference's inputs"
            if name in report["batch_checked"]
            else "streamed; state after the last step"
        )
        cells = "".join(f"{e[f]:>11.2e}" if e[f] is not None else f"{'-':>11}" for f in FIGURES)
        lines.append(f"  {name:<12}{cells}   ({how})")
    lines.append(f"  units: z_t, c_t, state in {MODEL_UNITS}; action in {ACTION_UNITS}")
    check = report.get("action_float64_check")
    if check:
        graphs = ", ".join(f"{k} {v:.2e}" for k, v in check["graphs_vs_float64"].items())
        lines.append(
            f"  {check['chunks_checked']} chunk(s) above the bound (steps {', '.join(map(str, check['steps']))}) evaluated in "
            f"float64 on their own inputs: PyTorch fp32 is {check['torch_fp32_vs_float64']:.2e} away, {graphs} (normalised units)"
        )
    threads = f"{report['threads']} thread{'s' if report['threads'] != 1 else ''}"
    lines.append(f"  median latency, ms ({threads}):   history step      chunk")
    for name, lat in report["latency_ms"].items():
        hs, dn = lat["history_step"], lat["denoiser"]
        lines.append(f"  {name:<16}{'':16}{hs if hs is not None else '-':>12}{dn if dn is not None else '-':>11}")
    for name, q in report.get("quantized", {}).items():
        lines.append(
            f"  {name} vs {q['against']}: action max abs {q['action_max_abs_vs_fp32']:.2e} "
            f"({100 * q['action_max_abs_over_range']:.2f} % of the action range), c_t {q['c_t_max_abs_vs_fp32']:.2e}; "
            f"speed-up history step {q['speedup_history_step']}x, chunk {q['speedup_denoiser']}x (not bounded)"
        )
    if "seconds" in report:
        lines.append("  time, s: " + ", ".join(f"{k.replace('_', ' ')} {v:.1f}" for k, v in report["seconds"].items()))
    verdict = "<=" if report["passed"] else ">"
    lines.append(
        f"  {'PASS' if report['passed'] else 'FAIL'}: worst {describe_worst(report)} {verdict} bound {report['bound']:g}"
    )
    return "\n".join(lines)


def check_report(report: dict[str, Any]) -> None:
    """Raise :class:`ParityError` (one line: what exceeded the bound, where, in which units, what to do)."""
    if report["passed"]:
        return
    w = report["worst_at"]
    what = (
        f"{w['backend']} {w['figure']} differs from PyTorch fp32 by {report['worst']:.2e} {_units(w['figure'])}"
        f"{_place(w)}, above the bound {report['bound']:g}"
    )
    check = report.get("action_float64_check")
    others = [v for e in report["errors"].values() for f, v in e.items() if f != "action" and v is not None]
    if w["figure"] == "action" and check and check["graphs_vs_float64"] and max(others, default=0.0) <= report["bound"]:
        torch64 = check["torch_fp32_vs_float64"]
        name, graph64 = max(check["graphs_vs_float64"].items(), key=lambda kv: kv[1])
        ratio = graph64 / torch64 if torch64 > 0 else float("inf")
        measured = f"redone in float64 on each one's own inputs, PyTorch fp32 is {torch64:.1e} away and {name} {graph64:.1e} ({ratio:.1f}x)"
        if ratio <= 2.0:
            advice = (
                f"{measured}: the model amplifies fp32 rounding as much in PyTorch, not the export; "
                "to keep the graphs anyway, export with --skip-verify"
            )
        else:
            advice = f"{measured}: the exported graph loses precision; please report it with the run's config.json"
    else:
        advice = "this is an export bug, please report it with the run's config.json"
    raise ParityError(f"{what}; {advice}")
