"""The rig description: TOML loading, overrides, CSV curves, and the errors bad input gets."""

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu.io.npz import read_spectrum_csv
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import FaultRates, RigDescription, load_rig, rig_from_dict
from specgpu.rig.light import LightParameters
from specgpu.rig.twin import TwinRig


def write(tmp_path, text, name="rig.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_defaults_are_the_papers_rig():
    d = load_rig(None)
    assert d.light.columns == 1024 and d.light.rows == 768
    assert (d.light.wavelength_min_nm, d.light.wavelength_max_nm) == (380.0, 780.0)
    assert d.light.pattern_load_s == 62e-6 and d.light.mirror_settle_s == 18e-6
    assert (d.camera.roi_width, d.camera.roi_height, d.camera.bit_depth) == (640, 480, 10)
    assert d.camera.frame_rate_hz == 90.0
    assert d.scene == "colorchecker" and d.pacing == "free" and not d.faults.any


def test_toml_overrides_and_relative_csv_paths(tmp_path):
    (tmp_path / "curves").mkdir()
    (tmp_path / "curves" / "lamp.csv").write_text("380,1\n780,2\n")
    (tmp_path / "curves" / "v.csv").write_text("380,1\n780,1\n")
    path = write(tmp_path, """
[light]
lamp = "curves/lamp.csv"
illuminance_lux = 20000
spot_centre_mm = [1.5, -2]
fluctuation_rms = 0.01

[camera]
sensitivity = "curves/v.csv"
bit_depth = 12
roi_width = 320
roi_height = 240
frame_rate_hz = 500
exposure_s = 0.0015

[scene]
source = "white"

[twin]
seed = 7
pacing = "paced"

[faults]
drop_rate = 0.01
jitter_s = 1e-6
""")
    d = load_rig(path)
    assert d.light.lamp == str(tmp_path / "curves" / "lamp.csv")
    assert d.light.illuminance_lux == 20000.0 and isinstance(d.light.illuminance_lux, float)
    assert d.light.spot_centre_mm == (1.5, -2)
    assert d.camera.bit_depth == 12 and d.camera.frame_rate_hz == 500.0
    assert d.camera.sensitivity == str(tmp_path / "curves" / "v.csv")
    assert d.scene == "white" and d.seed == 7 and d.pacing == "paced"
    assert d.faults == FaultRates(drop_rate=0.01, jitter_s=1e-6)
    assert d.source == str(path)
    rig = TwinRig(d)
    assert rig.camera.shape == (240, 320)
    # The lamp CSV rises linearly from 1 to 2: the all-on spectrum follows it inside the slit-blurred edges.
    spectrum, wl = rig.light.max_spectrum, rig.light.wavelengths
    ratio = spectrum[wl == 700][0] / spectrum[wl == 450][0]
    assert ratio == pytest.approx((1 + 320 / 400) / (1 + 70 / 400), rel=1e-3)
    assert d.to_dict()["camera"]["bit_depth"] == 12


@pytest.mark.parametrize("text, message", [
    ("[lights]\nrows = 2\n",
     r"unknown table \[lights\]; valid tables: light, camera, scene, twin, faults, spectroradiometer"),
    ("[light]\nrowz = 2\n", r"unknown key light.rowz; valid keys: lamp, "),
    ("[camera]\nbit_depth = 10.5\n", r"camera.bit_depth must be an integer, got 10.5"),
    ("[camera]\nexposure_s = \"fast\"\n", r"camera.exposure_s must be a number, got 'fast'"),
    ("[camera]\nexposure_s = 5e-5\n", r"camera.exposure_s = 50.0 us is shorter than the light source's pattern switch"),
    ("[camera]\nbit_depth = 14\n", r"camera.bit_depth must be one of \(8, 10, 12\)"),
    ("[light]\nfluctuation_rms = nan\n", r"light.fluctuation_rms must be finite"),
    ("[light]\nlamp = \"none.csv\"\n", r"light.lamp file not found: .*none.csv"),
    ("[light]\nspot_centre_mm = [1]\n", r"light.spot_centre_mm must be a list of 2 numbers"),
    ("[scene]\nsource = \"missing.exr\"\n", r"scene.source file not found"),
    ("[scene]\nsrc = \"white\"\n", r"unknown key scene.src; valid keys: source"),
    ("[scene]\nsource = \"natural:moon\"\n", r"scene.source 'natural:moon': unknown image; valid: chelsea"),
    ("[twin]\nseed = -1\n", r"twin.seed must be >= 0"),
    ("[twin]\npacing = \"fast\"\n", r"twin.pacing must be one of free, paced"),
    ("[twin]\nthreads = 2\n", r"unknown key twin.threads"),
    ("[faults]\ndrop_rate = 1.5\n", r"faults.drop_rate must be <= 0.999"),
    ("[light]\nrows = true\n", r"light.rows must be an integer, got True"),
    ("[light\nrows = 2\n", r"invalid TOML"),
    ("light = 3\n", r"\[light\] must be a table"),
])
def test_bad_descriptions_name_the_file_and_key(tmp_path, text, message):
    path = write(tmp_path, text)
    with pytest.raises(ValueError, match=message) as info:
        TwinRig(load_rig(path), scene="white")
    assert str(info.value).startswith(str(path))
    assert "\n" not in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(ValueError, match=r"nope.toml: rig description not found"):
        load_rig(tmp_path / "nope.toml")


def test_exposure_plus_switch_time_must_fit_the_frame_period():
    cam = CameraParameters(frame_rate_hz=100.0, exposure_s=0.00995)
    with pytest.raises(ValueError, match=r"plus the light's 80 us switch time exceeds the frame period 0.01 s"):
        TwinRig(RigDescription(camera=cam), scene="white")
    TwinRig(RigDescription(camera=CameraParameters(frame_rate_hz=100.0, exposure_s=0.0099)), scene="white")


# ---- parsers, property-tested ------------------------------------------------------------------------------------
finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)


@settings(max_examples=60, deadline=None)
@given(rows=st.dictionaries(st.integers(200, 2000), finite, min_size=2, max_size=30),
       sep=st.sampled_from([",", ";", "\t", " ", ", "]), header=st.booleans(), comments=st.booleans())
def test_csv_reader_round_trips_any_valid_table(tmp_path_factory, rows, sep, header, comments):
    lines = (["wavelength" + sep + "value"] if header else []) + (["# a comment"] if comments else [])
    lines += [f"{wl}{sep}{val!r}" for wl, val in rows.items()]  # file order as generated (unsorted)
    path = tmp_path_factory.mktemp("csv") / "c.csv"
    path.write_text("\n".join(lines) + "\n")
    wl, val = read_spectrum_csv(path)
    expect = sorted(rows.items())
    np.testing.assert_array_equal(wl, [w for w, _ in expect])
    np.testing.assert_array_equal(val, [v for _, v in expect])


@settings(max_examples=60, deadline=None)
@given(bad=st.sampled_from(["400,1,2", "400", "400,abc", "400,nan", "400,inf", "nan,1"]),
       position=st.integers(0, 2))
def test_csv_reader_rejects_bad_lines_with_file_and_line(tmp_path_factory, bad, position):
    lines = ["380,1", "500,2", "700,3"]
    lines.insert(position + 1, bad)
    path = tmp_path_factory.mktemp("csv") / "bad.csv"
    path.write_text("\n".join(lines))
    with pytest.raises(ValueError, match=rf"bad.csv:{position + 2}: "):
        read_spectrum_csv(path)


@settings(max_examples=60, deadline=None)
@given(lux=st.floats(1.0, 1e6), fwhm=st.floats(0.5, 50.0), bits=st.sampled_from([8, 10, 12]),
       seed=st.integers(0, 2**31))
def test_toml_numbers_round_trip(tmp_path_factory, lux, fwhm, bits, seed):
    text = (f"[light]\nilluminance_lux = {lux!r}\nline_fwhm_nm = {fwhm!r}\n"
            f"[camera]\nbit_depth = {bits}\n[twin]\nseed = {seed}\n")
    path = tmp_path_factory.mktemp("toml") / "r.toml"
    path.write_text(text)
    d = load_rig(path)
    assert d.light.illuminance_lux == lux and d.light.line_fwhm_nm == fwhm
    assert d.camera.bit_depth == bits and d.seed == seed


@settings(max_examples=60, deadline=None)
@given(key=st.text(st.characters(min_codepoint=97, max_codepoint=122), min_size=1, max_size=12),
       table=st.sampled_from(["light", "camera", "faults"]))
def test_any_unknown_key_is_rejected(key, table):
    valid = {"light": LightParameters, "camera": CameraParameters, "faults": FaultRates}[table]
    if key in {f for f in valid.__dataclass_fields__}:
        return
    with pytest.raises(ValueError, match=rf"unknown key {table}\.{key}; valid keys"):
        rig_from_dict({table: {key: 1.0}})


def test_fault_rates_validation():
    assert not FaultRates().any and FaultRates(missed_trigger_rate=0.1).any
    with pytest.raises(ValueError, match="faults.jitter_s must be >= 0"):
        FaultRates(jitter_s=-1.0)
    assert math.isclose(FaultRates(duplicate_rate=0.5).duplicate_rate, 0.5)


def test_dump_rig_writes_every_key_and_reads_back_equal(tmp_path):
    from specgpu.rig.config import dump_rig

    text = dump_rig()
    for key in list(LightParameters.__dataclass_fields__) + list(CameraParameters.__dataclass_fields__):
        assert f"\n{key} = " in text
    path = write(tmp_path, text)
    assert load_rig(path) == RigDescription(source=str(path))


@settings(max_examples=60, deadline=None)
@given(lux=st.floats(1.0, 1e6), centre=st.tuples(finite, finite), bits=st.sampled_from([8, 10, 12]),
       fluct=st.floats(0.0, 0.5), drop=st.floats(0.0, 0.999), seed=st.integers(0, 2**63 - 1),
       scene=st.sampled_from(["colorchecker", "white", "natural"]), pacing=st.sampled_from(["free", "paced"]))
def test_dump_and_load_round_trip_any_description(tmp_path_factory, lux, centre, bits, fluct, drop, seed, scene,
                                                 pacing):
    import dataclasses

    from specgpu.rig.config import dump_rig

    d = RigDescription(light=dataclasses.replace(LightParameters(), illuminance_lux=lux, spot_centre_mm=centre,
                                                 fluctuation_rms=fluct),
                       camera=dataclasses.replace(CameraParameters(), bit_depth=bits), scene=scene, seed=seed,
                       pacing=pacing, faults=FaultRates(drop_rate=drop))
    path = tmp_path_factory.mktemp("dump") / "rig.toml"
    path.write_text(dump_rig(d))
    assert load_rig(path) == dataclasses.replace(d, source=str(path))


def _keys_read_by_load_rig() -> dict:
    """Every key of every table ``load_rig`` accepts (the [camera] preset included)."""
    from dataclasses import fields

    from specgpu.hardware.rig import HardwareConfig
    from specgpu.rig.config import _TABLES, _TWIN_KEYS
    from specgpu.rig.motion import MOTION_KEYS
    from specgpu.rig.realism import Drift, Realism
    from specgpu.rig.spectroradiometer import SpectroradiometerParameters

    def names(cls):
        return {f.name for f in fields(cls)}

    keys = {"light": names(LightParameters), "camera": names(CameraParameters) | {"preset"}, "scene": {"source"},
            "twin": set(_TWIN_KEYS), "faults": names(FaultRates),
            "spectroradiometer": names(SpectroradiometerParameters),
            "realism": names(Realism), "drift": names(Drift), "hardware": names(HardwareConfig),
            "motion": set(MOTION_KEYS)}
    assert set(keys) == set(_TABLES)  # a new table must be listed here too
    return keys


def _keys_written(text: str) -> dict:
    """table -> keys written in a dump, as values or as commented ``# key = value`` lines."""
    import re

    out, table = {}, None
    for line in text.splitlines():
        head = re.match(r"^\[(\w+)\]", line)
        if head:
            table = out.setdefault(head.group(1), set())
            continue
        key = re.match(r"^(?:# )?(\w+) = ", line)
        if key and table is not None:
            table.add(key.group(1))
    return out


@pytest.mark.parametrize("profile", ["ideal", "lab"])
def test_dump_rig_shows_every_key_load_rig_reads(tmp_path, profile):
    # [realism], [drift], [twin] capture_delay_s, [camera] preset and [hardware] included: the dump is where a
    # user finds the keys of a rig file
    from specgpu.hardware.rig import HardwareConfig
    from specgpu.rig.config import dump_rig
    from specgpu.rig.realism import CAPTURE_DELAY_S, profile_realism

    d = rig_from_dict({"twin": {"profile": profile}})
    assert "\nlight = " not in dump_rig(d).split("[hardware]")[1]  # the rig does not know the devices' keys ...
    text = dump_rig(d, hardware_defaults={f.name: f.default for f in dataclasses.fields(HardwareConfig)})
    assert _keys_written(text) == _keys_read_by_load_rig()  # ... its caller gives them
    path = write(tmp_path, text)
    back = load_rig(path)
    assert back == RigDescription(profile=profile, source=str(path))
    assert back.realism == profile_realism(profile) and back.capture_delay == CAPTURE_DELAY_S[profile]
    # keys that follow the profile are comments holding the value in force: switching the profile still acts
    other = "lab" if profile == "ideal" else "ideal"
    switched = load_rig(write(tmp_path, text.replace(f'profile = "{profile}"', f'profile = "{other}"'), "b.toml"))
    assert switched.realism == profile_realism(other) and switched.capture_delay == CAPTURE_DELAY_S[other]


def _realism_values():
    """Per [realism] key, the ideal and the lab value (both valid): combinations no profile has."""
    from specgpu.rig.realism import LAB, Realism

    ideal = Realism()
    return {k: st.sampled_from(sorted({getattr(ideal, k), getattr(LAB, k)})) for k in Realism.keys()}


@settings(max_examples=40, deadline=None)
@given(profile=st.sampled_from(["ideal", "lab"]), realism=st.fixed_dictionaries({}, optional=_realism_values()),
       delay=st.none() | st.floats(0.0, 1e7), drift=st.tuples(st.floats(-1500, 1500), st.floats(-0.5, 0.5),
                                                               st.floats(-30, 30)),
       preset=st.none() | st.sampled_from(["cmv4000", "imx250", "imx304"]),
       hardware=st.fixed_dictionaries({}, optional={"light": st.sampled_from(["dlpc900", "dlpc900-simulated"]),
                                                    "exposure_s": st.floats(1e-4, 1.0), "camera_first_frame_id":
                                                    st.integers(-1, 1), "camera_cti": st.text(max_size=20)}))
def test_dump_and_load_round_trip_every_table(tmp_path_factory, profile, realism, delay, drift, preset, hardware):
    from specgpu.rig.config import dump_rig

    data = {"twin": {"profile": profile, **({} if delay is None else {"capture_delay_s": delay})},
            "realism": realism, "drift": dict(zip(("lamp_cct_K", "lamp_output", "cut_on_nm"), drift)),
            "hardware": hardware, **({"camera": {"preset": preset}} if preset else {})}
    d = rig_from_dict(data, source="rig.toml")
    path = tmp_path_factory.mktemp("dump") / "rig.toml"
    path.write_text(dump_rig(d))
    back = load_rig(path)
    assert back == __import__("dataclasses").replace(d, source=str(path))
    assert back.capture_delay_s == d.capture_delay_s and back.hardware == d.hardware


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**63 - 1))
def test_any_seed_is_kept_exactly(seed):
    assert rig_from_dict({"twin": {"seed": seed}}).seed == seed


@pytest.mark.parametrize("table, key", [("light", "lamp"), ("camera", "sensitivity"), ("scene", "source")])
def test_a_missing_files_path_with_a_control_character_is_refused_on_one_line(tmp_path, table, key):
    """A path value holding a carriage return or a newline (TOML's escapes) is named quoted, so the refusal stays
    one line."""
    path = tmp_path / "rig.toml"
    path.write_text(f'[{table}]\n{key} = "gone\\r\\nx.csv"\n')
    with pytest.raises(ValueError) as err:
        load_rig(path)
    msg = str(err.value)
    assert "\n" not in msg and "\r" not in msg and f"{table}.{key} file not found: " in msg and "\\r\\n" in msg
