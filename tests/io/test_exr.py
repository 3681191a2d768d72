"""specgpu.io.exr: JCGT 2021 spectral channel names, written in the reference form and read in every form."""

from __future__ import annotations

import pytest
from file_helpers import (
    raises_one_line,
)
from hypothesis import given
from hypothesis import strategies as st

from specgpu.io.exr import format_channel, parse_channel


# ---- channel names ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name, nm", [
    ("T.550,000000nm", 550.0),          # the reference writer's form (six decimals, comma)
    ("T.405,5nm", 405.5),
    ("T.405.5nm", 405.5),               # "." separator from other tools, read leniently
    ("T.400nm", 400.0),
    ("T.0,5505um", 550.5),              # SI prefix u (micro)
    ("T.5,5e2nm", 550.0),               # exponent
    ("T.5505Am", None),                 # unknown prefix
    ("T.550e-9m", 550.0),               # metres, no prefix
    ("T.600THz", 299_792_458.0 / 600e12 * 1e9),  # frequency
    ("T.550,000000nm.600nm", None),     # bi-spectral (re-radiation) channel, not a band
    ("S0.550,000000nm", None),          # emissive
    ("R", None), ("T.nm", None), ("T.550", None), ("T550nm", None), ("T.-550nm", None),
])
def test_parse_channel_follows_the_jcgt_grammar(name, nm):
    got = parse_channel(name)
    if nm is None:
        assert got is None
    else:
        assert got == pytest.approx(nm, rel=1e-12)


def test_format_channel_writes_the_reference_form():
    assert format_channel(550) == "T.550,000000nm"
    assert format_channel(405.5) == "T.405,500000nm"
    assert format_channel(405.12345678) == "T.405,12345678nm"  # six decimals would lose it
    for bad in (0, -1, float("nan"), float("inf"), "x"):
        with raises_one_line(ValueError, "wavelength must be"):
            format_channel(bad)


@given(st.floats(min_value=1e-300, max_value=1e300, allow_nan=False, allow_infinity=False))
def test_channel_name_round_trip_is_exact(wl):
    name = format_channel(wl)
    assert name.startswith("T.") and name.endswith("nm") and "." not in name[2:]  # comma: no OpenEXR layer split
    assert parse_channel(name) == wl


_SI = {"": 0, "da": 1, "h": 2, "k": 3, "M": 6, "d": -1, "c": -2, "m": -3, "u": -6, "n": -9, "p": -12}


@given(st.floats(min_value=1e-3, max_value=1e6, allow_nan=False), st.sampled_from(sorted(_SI)),
       st.sampled_from([",", "."]))
def test_parse_channel_applies_si_prefixes_and_either_separator(value, prefix, sep):
    name = "T." + repr(value).replace(".", sep) + prefix + "m"
    assert parse_channel(name) == pytest.approx(value * 10.0 ** (_SI[prefix] + 9), rel=1e-12)
    hz = parse_channel("T." + repr(value).replace(".", sep) + prefix + "Hz")
    assert hz == pytest.approx(299_792_458.0 / (value * 10.0 ** _SI[prefix]) * 1e9, rel=1e-12)


@given(st.text(max_size=20))
def test_parse_channel_never_raises_and_rejects_non_reflective_names(text):
    got = parse_channel(text)
    if not text.startswith("T."):
        assert got is None
    else:
        assert got is None or got >= 0
