"""``h3edge profile report``: documents from run directories, tables, comparisons, formats."""

from __future__ import annotations

import json

from h3edge.cli import main
from h3edge.profiling.report import load_document, profile_document, report


def _doc(scale: float, name: str) -> dict:
    comps = {c: {"median_ms": m * scale, "p95_ms": 1.5 * m * scale, "mean_ms": m * scale, "total_s": m * scale / 10,
                 "count": 100} for c, m in (("read", 10.0), ("training", 200.0), ("frame", 300.0), ("mesh", 900.0))}
    return profile_document(name, "cpu", 100, comps, {"keyframes": 2_000_000}, {"queue_full": 3})


def test_report_table_and_comparison():
    a, b = _doc(1.0, "x86-cpu"), _doc(0.5, "orin-agx")
    text = report(a)
    assert "profile x86-cpu on cpu" in text and "power mode" in text
    lines = text.splitlines()
    assert [ln.split("  ")[0] for ln in lines if ln.startswith(("data reading", "map training"))] == [
        "data reading & preprocessing", "map training"]  # the paper's components first
    both = report(a, b)
    assert "0.50x" in both and "vs profile orin-agx" in both
    assert "queue_full 3" in both and "keyframes 2.0 MB" in both
    md = report(a, b, "markdown")
    assert md.count("\n|---") == 1 and "| map training | 200.0 | 300.0 | 100 | 100.0 | 150.0 | 0.50x |" in md
    assert json.loads(report(a, b, "json"))["other"]["profile"] == "orin-agx"


def test_cli_reads_run_directories(tmp_path, capsys):
    for name, scale in (("a", 1.0), ("b", 2.0)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "profile.json").write_text(json.dumps(_doc(scale, name)))
    assert main(["profile", "report", str(tmp_path / "a"), "--vs", str(tmp_path / "b"), "--format", "markdown"]) == 0
    out = capsys.readouterr().out
    assert "2.00x" in out
    assert load_document(str(tmp_path / "a" / "profile.json"))["profile"] == "a"
    assert main(["profile", "report", str(tmp_path / "missing")]) == 2
