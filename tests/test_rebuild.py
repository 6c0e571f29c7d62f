"""Every committed report and README figure is what its record rebuilds (python -m studies.rebuild --check)."""

from __future__ import annotations

import json
import shutil

import pytest
from conftest import ROOT

from dssp_core.errors import DSSPError
from studies.rebuild import main, rebuild


def test_every_report_and_readme_figure_matches_its_record(capsys):
    assert main(["--check"]) == 0
    out = capsys.readouterr().out
    assert "every report and README figure matches its record" in out


@pytest.fixture
def copy_root(tmp_path):
    shutil.copytree(ROOT / "reports", tmp_path / "reports")
    shutil.copytree(ROOT / "benchmarks", tmp_path / "benchmarks")
    for readme in [ROOT / "README.md", *ROOT.glob("*/README.md")]:
        (tmp_path / readme.relative_to(ROOT)).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(readme, tmp_path / readme.relative_to(ROOT))
    return tmp_path


def test_a_figure_that_differs_from_its_record_is_found_and_rewritten(copy_root, capsys):
    demo = copy_root / "reports/demo/results.json"
    record = json.loads(demo.read_text())
    record["evals"]["dssp"]["successes"] -= 1
    demo.write_text(json.dumps(record))
    sim_eval = sorted((copy_root / "reports/sim/record/evals").glob("*.json"))[0]
    r = json.loads(sim_eval.read_text())
    r["successes"] = r["n"] - r["successes"]
    sim_eval.write_text(json.dumps(r))
    assert main(["--check", "--root", str(copy_root)]) == 1
    out = capsys.readouterr().out
    assert "differs from its record: " in out and "README.md" in out and "reports/sim/sim_memory_tasks.md" in out
    assert "README.md" in rebuild(copy_root, check=False)  # rewritten from the records
    assert rebuild(copy_root, check=True) == []
    dssp = record["evals"]["dssp"]
    assert f"| DSSP (full history) | {dssp['successes']}/{dssp['n']} = " in (copy_root / "README.md").read_text()


def test_a_readme_block_nothing_rebuilds_is_an_error(copy_root):
    readme = copy_root / "README.md"
    readme.write_text(readme.read_text() + "\n<!-- figures: guesswork -->\n| made up |\n<!-- /figures -->\n")
    with pytest.raises(DSSPError, match="'guesswork' that nothing rebuilds"):
        rebuild(copy_root, check=True)


def test_the_fair_memory_block_leaves_pending_rows_out_and_says_its_holm_is_partial(copy_root):
    """The README's fair-study table shows the rows recorded; while some of a task's are pending, the block says that
    Holm's correction is over a partial family (as the report does), and says nothing of it once all are in."""
    from studies.rebuild import readme_blocks

    def tap(block: str) -> str:  # tap's part of the block: up to the next task's table
        return block.split("`tap`, test split:", 1)[1].split(", test split:", 1)[0]

    full = tap(readme_blocks(copy_root)["memory_fair_test"])
    assert "| w/ Transformer denoiser |" in full and "Pending rows" not in full
    for name in ("tap_transformer_denoiser_s0_test.json", "tap_transformer_denoiser_s1_test.json"):
        (copy_root / "reports/memory_fair/record/evals" / name).unlink()
    partial = tap(readme_blocks(copy_root)["memory_fair_test"])
    assert "| w/ Transformer denoiser |" not in partial and "| pending |" not in partial
    assert "Pending rows: 7 of the table's 8 comparisons are recorded" in partial
