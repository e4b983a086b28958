"""The contention benchmark maps beside a competing load and reports slowdowns against the fair share."""

import json
import os

from benchmarks.contention import fair_share, main
from h3edge.mapping.threads import PASSIVE_ENVIRONMENT, passive_environment


def test_contention_rows_for_every_setup_and_load(tiny_scene, tmp_path, capsys):
    out = tmp_path / "contention"
    assert main(["--dataset", str(tiny_scene), "--frames", "2", "--warmup", "1", "--rounds", "1",
                 "--setups", "one", "--loads", "none", "busy", "--out", str(out)]) == 0
    assert "| one | busy |" in capsys.readouterr().out
    rec = json.loads(out.with_suffix(".json").read_text())
    rows = {(r["setup"], r["load"]): r for r in rec["rows"]}
    assert set(rows) == {("one", "none"), ("one", "busy")}
    assert all(r["frames"] == 2 and r["frame_ms"] > r["step_ms"] > 0 for r in rows.values())
    assert rows[("one", "none")]["frame_slowdown"] == 1.0 and rows[("one", "none")]["fair_share"] == 1.0
    assert rows[("one", "busy")]["fair_share"] == fair_share("busy", rec["cores"]) == min(2, rec["cores"])
    assert "| setup | load |" in out.with_suffix(".md").read_text()


def test_the_passive_environment_keeps_what_the_user_set():
    env = {"OMP_WAIT_POLICY": "ACTIVE"}
    passive_environment(env)
    assert env["OMP_WAIT_POLICY"] == "ACTIVE"
    assert all(env[k] == v for k, v in PASSIVE_ENVIRONMENT.items() if k != "OMP_WAIT_POLICY")
    fresh: dict = {}
    passive_environment(fresh)
    assert fresh == PASSIVE_ENVIRONMENT
    assert os.environ.get("OMP_WAIT_POLICY")  # the benchmarks package set it for the suite's imports
