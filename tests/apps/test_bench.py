"""specgpu bench: the size parser, the JSON report at a tiny size, and the CLI command."""

import json
import math
import re

import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu.apps.bench.kernels import TOLERANCES, run_bench
from specgpu.apps.bench.sizes import parse_sizes
from specgpu.apps.cli import main

CASES = {
    ("cube_float32", "planar"), ("cube_float32", "interleaved"),
    ("cube_float16", "planar"), ("cube_float16", "interleaved"),
    ("fused_dE2000", None), ("XYZ_Lab_dE2000", None), ("guided_filter", None),
}

# ------------------------------------------------------------------------------------------------ parse_sizes

dims = st.integers(min_value=1, max_value=10**6)
sizes = st.lists(st.tuples(dims, dims), min_size=1, max_size=6)


@given(sizes, st.sampled_from(["x", "X"]), st.sampled_from(["", " "]))
def test_parse_sizes_round_trips(pairs, sep, pad):
    text = ",".join(f"{pad}{w}{sep}{h}{pad}" for w, h in pairs)
    assert parse_sizes(text) == pairs


def test_parse_sizes_example():
    assert parse_sizes("640x480,2048x2048") == [(640, 480), (2048, 2048)]


def _valid_token(token):
    """Independent statement of what a size token is: WxH, positive ASCII integers, spaces allowed."""
    match = re.fullmatch(r"\s*([0-9]+)\s*[xX]\s*([0-9]+)\s*", token, re.ASCII)
    return match is not None and int(match[1]) > 0 and int(match[2]) > 0


_bad_tokens = st.one_of(
    st.sampled_from(["", " ", "640", "x480", "640x", "0x480", "640x0", "-1x5", "6.4x4", "1x2x3", "axb",
                     "640*480", "+1x2", "1e3x2", "\u0661x2"]),
    st.text(alphabet=st.characters(blacklist_characters=","), max_size=12).filter(lambda t: not _valid_token(t)),
)


@given(sizes, _bad_tokens, st.integers(min_value=0, max_value=6))
@settings(max_examples=200)
def test_parse_sizes_names_the_bad_token(pairs, bad, where):
    tokens = [f"{w}x{h}" for w, h in pairs]
    tokens.insert(min(where, len(tokens)), bad)
    with pytest.raises(ValueError) as info:
        parse_sizes(",".join(tokens))
    assert repr(bad) in str(info.value)


@pytest.mark.parametrize("text", ["", "   ", None])
def test_parse_sizes_rejects_nothing(text):
    with pytest.raises(ValueError, match="no image size"):
        parse_sizes(text)


# -------------------------------------------------------------------------------------------------- run_bench


def test_run_bench_writes_every_case(tmp_path):
    path = tmp_path / "bench.json"
    printed = []
    returned = run_bench(sizes=[(64, 48)], repeats=2, json_path=path, echo=printed.append, progress=False,
                         copy_mib=16)
    report = json.loads(path.read_text())
    assert report == json.loads(json.dumps(returned))
    for key in ("device", "platform", "specgpu_version", "copy_bandwidth_GBps", "numpy_copy_bandwidth_GBps",
                "cases", "targets"):
        assert key in report
    assert report["copy_bandwidth_GBps"] > 0 and report["numpy_copy_bandwidth_GBps"] > 0
    assert {(c["case"], c["layout"]) for c in report["cases"]} == CASES
    for c in report["cases"]:
        assert (c["width"], c["height"], c["repeats"]) == (64, 48, 2)
        for key in ("device_ms", "api_ms", "baseline_ms", "speedup"):
            assert math.isfinite(c[key]) and c[key] > 0, (c["case"], key)
        assert 0 <= c["max_diff"] <= TOLERANCES[c["case"]] and c["within_tolerance"], c
        if c["case"].startswith("cube"):
            assert c["GBps"] > 0 and c["fraction_of_copy"] > 0
        else:
            assert c["GBps"] is None and c["fraction_of_copy"] is None
    assert set(report["targets"]) == {"fused_speedup_vs_colour_science", "cube_fraction_of_copy_bandwidth",
                                      "float16_faster_than_float32", "guided_speedup_vs_numpy"}
    text = printed[0]
    assert report["device"] in text and "copy bandwidth" in text and "MISMATCH" not in text
    assert text.count("PASS") + text.count("MISS") == 6  # 1 fused + 2 cube layouts + 2 float16 layouts + 1 guided
    # the guided filter's line: the device and the NumPy / SciPy filter of the same run, and their ratio
    guided = next(c for c in report["cases"] if c["case"] == "guided_filter")
    line = next(s for s in text.splitlines() if "guided_filter 64x48x9:" in s)
    assert f"device {guided['device_ms']:.2f} ms, NumPy/SciPy {guided['baseline_ms']:.2f} ms" in line
    assert f"{guided['speedup']:.1f}x (median of 2 rounds" in line
    # a timing means little without its conditions: the date and the machine's load ride with the figures
    assert re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d UTC", report["date_utc"])
    load = report["load_avg_1min"]
    assert load["start"] >= 0 and load["end"] >= 0
    assert report["date_utc"] in text and f"load average (1 min) {load['start']:.2f} at start" in text


def test_run_bench_rejects_zero_repeats():
    with pytest.raises(ValueError, match="repeats"):
        run_bench(sizes=[(8, 8)], repeats=0, echo=None, progress=False)


# -------------------------------------------------------------------------------------------------------- CLI


def test_cli_bench(tmp_path):
    path = tmp_path / "out.json"
    result = CliRunner().invoke(main, ["bench", "--sizes", "32x16", "--repeats", "1", "--json", str(path)])
    assert result.exit_code == 0, result.output
    report = json.loads(path.read_text())
    assert {(c["width"], c["height"]) for c in report["cases"]} == {(32, 16)}
    assert "targets:" in result.output and "issue" not in result.output


def test_cli_bench_bad_size_is_a_usage_error():
    result = CliRunner().invoke(main, ["bench", "--sizes", "640x480,64Ox48"])
    assert result.exit_code == 2
    assert "'64Ox48'" in result.output
