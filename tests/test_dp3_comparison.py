"""benchmarks/dp3_comparison.py: DSSP and DP3 built, exported and run by the same code, timed like for like."""

import importlib.util
import json

import pytest
from conftest import ROOT

TINY = {
    "n_points": 32,
    "state_dim": 3,
    "action_dim": 3,
    "models": {
        "dssp": ("DSSP (tiny)", "tiny", ["model.d_model=32", "model.n_denoiser_layers=2"]),
        "dp3_equal": ("DP3 (small)", "dp3_sim", ["model.unet_down_dims=[16,32]"]),
    },
}


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_dp3_comparison", ROOT / "benchmarks" / "dp3_comparison.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_both_run_through_the_same_runtime_with_the_same_settings(bench, tmp_path, monkeypatch, capsys):
    from dssp_core.machine import describe

    monkeypatch.setitem(bench.SCALES, "tiny", TINY)
    out = tmp_path / "dp3.json"
    args = ["--scale", "tiny", "--quick", "--threads", "1", "--json", str(out)]
    assert bench.main(args) == 0
    text = capsys.readouterr().out
    report = json.loads(out.read_text())
    assert report["machine"]["cpu"] == describe()["cpu"] and report["settings"]["threads"] == 1
    dssp, dp3 = report["models"]["dssp"], report["models"]["dp3_equal"]
    assert dssp["params"] > 0 and dp3["params"] > 0
    for precision in ("fp32", "int8"):
        a, b = dssp["precisions"][precision], dp3["precisions"][precision]
        assert a["graphs"].startswith(precision) and b["graphs"].startswith(precision)
        assert a["spinning"] == b["spinning"] is False  # one thread: the runtime spins for neither
        assert a["tick_ms"] == pytest.approx(a["step_ms"] + a["chunk_ms"] / a["n_action_steps"])
        assert len(a["chunk_samples_ms"]) == bench.QUICK_REPEATS
        ratio = report["ratios"][precision]["dp3_equal"]
        assert ratio["tick_ms"] == pytest.approx(b["tick_ms"] / a["tick_ms"])
        assert ratio["chunk_ms"] == pytest.approx(b["chunk_ms"] / a["chunk_ms"])
    assert text.count("| DP3 (small) |") == 2 and text.count("| DSSP (tiny) |") == 2
    # like for like: DP3's int8 graph quantizes its UNet's convolutions too, and its row says int8 alone
    assert "and Conv" in dp3["precisions"]["int8"]["quantization"] and dp3["precisions"]["fp32"]["quantization"] is None
    assert "| DP3 (small) | " in text and "UNet convolutions fp32" not in text
    old = {**dp3, "precisions": {"int8": {k: v for k, v in dp3["precisions"]["int8"].items() if k != "quantization"}}}
    assert bench.precision_cell(old, "int8", old["precisions"]["int8"]) == "int8 (UNet convolutions fp32)"
    # an existing --json is kept unless --force
    before = out.read_text()
    assert bench.main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "--force" in err[0]
    assert out.read_text() == before


@pytest.mark.parametrize(
    "extra", [["--repeats", "0"], ["--threads", "0"], ["--scale", "huge"], ["--precisions", "fp16"]]
)
def test_bad_input_is_one_error_line(bench, capsys, extra):
    try:
        code = bench.main(["--quick", *extra])
    except SystemExit as exc:  # argparse's choices: its one-line error, then exit 2
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
