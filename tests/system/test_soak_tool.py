"""tools/maintenance/soak.py: a short soak passes with its checks listed; bad arguments are refused."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

SOAK = Path(__file__).resolve().parents[2] / "tools" / "maintenance" / "soak.py"


def soak_module():
    spec = importlib.util.spec_from_file_location("soak", SOAK)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_short_soak_balances(tmp_path, capsys):
    soak = soak_module()
    rc = soak.main(["--minutes", "0.05", "--sample-s", "0.5", "--warm-up-s", "1", "--max-growth-mb", "256",
                    "--drop-rate", "0.02", "--duplicate-rate", "0.02", "--stall-rate", "0.05", "--stall-ms", "50",
                    "--json", str(tmp_path / "soak.json")])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "soak passed" in out and "FAIL" not in out
    assert out.count("  ok   ") == 9
    import json

    figures = json.loads((tmp_path / "soak.json").read_text())
    assert figures["report"]["frames_in"] > 0 and figures["report"]["accounting"]["balanced"] is True
    assert figures["sink"]["count"] == figures["report"]["sequences_out"] > 0


def test_injected_counts_follow_the_schedule():
    soak = soak_module()
    schedule = soak.FaultSchedule(dropped=frozenset({2, 5}), duplicated=frozenset({3}),
                                  missed_triggers=frozenset({4}))
    assert soak.injected(schedule, 9) == {"dropped": 2, "duplicated": 1, "missed_triggers": 1}
    assert soak.injected(schedule, 2) == {"dropped": 1, "duplicated": 0, "missed_triggers": 0}


@pytest.mark.parametrize("args", [["--minutes", "nan"], ["--minutes", "0"], ["--drop-rate", "1.5"],
                                  ["--stall-rate", "-0.1"]])
def test_bad_arguments_are_refused(args, capsys):
    soak = soak_module()
    with pytest.raises(SystemExit) as exc:
        soak.main(args)
    assert exc.value.code == 2
    assert "must" in capsys.readouterr().err
