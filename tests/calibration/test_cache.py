"""Calibrations kept on disk under their key and reused: made once, loaded after with every check of a bundle
file, made again when the file fails them or anything the key covers changes."""

from dataclasses import replace

import pytest
from small_rig import DESC

import specgpu.calibration.cache as cache
from specgpu.calibration import oracle_calibration
from specgpu.calibration.cache import cached_calibration, calibration_key, find_calibration, user_cache_dir


@pytest.fixture
def made(monkeypatch, tmp_path):
    """The calibrations the cache runs, counted (the oracle's bundle of the rig: what is kept is a real bundle,
    made in milliseconds); the user's cache in ``tmp_path/user``."""
    calls = []

    def calibrate(description, **options):
        calls.append(options)
        return oracle_calibration(description)

    monkeypatch.setattr(cache, "calibrate", calibrate)
    monkeypatch.setenv(cache.CACHE_ENV, str(tmp_path / "user"))
    return calls


def test_made_once_then_loaded_from_the_folder_or_the_user_cache(made, tmp_path):
    bundle, path = cached_calibration(DESC, [tmp_path / "run"], seed=3)
    assert path is None and len(made) == 1 and made[0] == {"seed": 3}
    kept = sorted(p.relative_to(tmp_path).parts[0] for p in tmp_path.rglob("calibration-*.npz"))
    assert kept == ["run", "user"]  # saved in the folder named and in the user's cache
    again, path = cached_calibration(DESC, [tmp_path / "run"], seed=3)
    assert len(made) == 1 and path.parent == tmp_path / "run" and again.hash == bundle.hash
    elsewhere, path = cached_calibration(DESC, [tmp_path / "other"], seed=3)  # another folder: the user's cache
    assert len(made) == 1 and path.parent == tmp_path / "user" and elsewhere.hash == bundle.hash
    assert find_calibration(DESC, [], seed=3, user_cache=False) is None


def test_another_seed_option_exposure_or_bench_is_another_calibration(made, tmp_path):
    folder = [tmp_path / "run"]
    cached_calibration(DESC, folder, seed=3)
    key = calibration_key(DESC, seed=3)
    others = [calibration_key(DESC, seed=4), calibration_key(DESC, seed=3, repeats=2),
              calibration_key(replace(DESC, camera=replace(DESC.camera, exposure_s=0.005)), seed=3),
              calibration_key(replace(DESC, seed=DESC.seed + 1), seed=3),
              calibration_key(replace(DESC, realism=replace(DESC.realism, white_error=0.01)), seed=3)]
    assert len({key, *others}) == 6
    cached_calibration(DESC, folder, seed=4)
    assert len(made) == 2


def test_a_corrupt_or_foreign_file_under_the_key_is_calibrated_again_and_replaced(made, tmp_path, monkeypatch):
    monkeypatch.setenv(cache.CACHE_ENV, "")  # no user cache: the folder alone
    folder = tmp_path / "run"
    cached_calibration(DESC, [folder], seed=3)
    path, = folder.glob("calibration-*.npz")
    path.write_bytes(path.read_bytes()[:-200])  # cut short: its content no longer matches its hash
    assert find_calibration(DESC, [folder], seed=3) is None
    bundle, found = cached_calibration(DESC, [folder], seed=3)
    assert found is None and len(made) == 2
    assert find_calibration(DESC, [folder], seed=3)[0].hash == bundle.hash  # replaced by a good one
    # a bundle of another rig copied under this rig's key: refused by the rig's fingerprint
    other = replace(DESC, seed=DESC.seed + 1)  # another camera: its fixed pattern
    cached_calibration(other, [tmp_path / "other"], seed=3)
    path.write_bytes(next((tmp_path / "other").glob("calibration-*.npz")).read_bytes())
    assert find_calibration(DESC, [folder], seed=3) is None
    cached_calibration(DESC, [folder], seed=3)
    assert len(made) == 4


def test_a_folder_that_cannot_be_written_is_passed_over(made, tmp_path, monkeypatch):
    monkeypatch.setenv(cache.CACHE_ENV, "")
    blocked = tmp_path / "file"
    blocked.write_text("not a folder")
    bundle, found = cached_calibration(DESC, [blocked, tmp_path / "run"], seed=3)
    assert found is None and len(list((tmp_path / "run").glob("calibration-*.npz"))) == 1


def test_the_user_cache_folder(monkeypatch, tmp_path):
    monkeypatch.setenv(cache.CACHE_ENV, str(tmp_path / "mine"))
    assert user_cache_dir() == tmp_path / "mine"
    monkeypatch.setenv(cache.CACHE_ENV, "")
    assert user_cache_dir() is None
    monkeypatch.delenv(cache.CACHE_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert user_cache_dir() == tmp_path / "xdg" / "specgpu"
