"""The demo's Table 1: one function over a list of methods, mean +- std over draws, per patch and per pixel."""

from pathlib import Path

from specgpu.demo import DemoResult, demo_profiles, table1_lines
from specgpu.rig.config import RigDescription


def result():
    r = DemoResult(Path("."), 0.0, {}, [], main="lab")
    r.draws = {"lab": {"narrowband": {"rmse": [0.004, 0.006], "dEab": [0.5, 0.7], "dE00": [0.3, 0.5],
                                      "px_rmse": [0.01, 0.01], "px_dE00": [1.3, 1.5], "K": 32},
                       "mine": {"dEab": [1.0], "dE00": [0.9], "px_dE00": [2.0], "K": 4}},
                "ideal": {"narrowband": {"rmse": [0.002, 0.002], "dEab": [0.2, 0.2], "dE00": [0.1, 0.1],
                                         "px_rmse": [0.004, 0.004], "px_dE00": [0.5, 0.5], "K": 31}}}
    return r


def test_table1_rows_for_the_methods_given():
    lines = table1_lines(result(), ["narrowband", "mine"])
    text = "\n".join(lines)
    assert "0.0050+-0.0014" in text and "1.40+-0.14" in text  # mean +- sample std of two draws
    assert "0.0020+-0.0000" in text
    assert any(line.split()[:2] == ["narrowband", "lab"] for line in lines)
    assert any(line.split()[:2] == ["narrowband", "ideal"] for line in lines)
    assert any("paper" in line and "0.0194" in line for line in lines)
    mine = [line for line in lines if line.startswith("mine")]
    assert len(mine) == 1 and mine[0].split()[2] == "-"  # no RMSE for an XYZ method
    assert "mine" not in "\n".join(table1_lines(result(), ["narrowband"]))


def test_demo_profiles():
    default = demo_profiles()
    assert list(default) == ["lab", "ideal"] and default["lab"].realism.any and not default["ideal"].realism.any
    assert list(demo_profiles(RigDescription())) == ["ideal"]
