"""The file a calibration is kept in, named before or after it is made: the one the cache writes and reads."""

from dataclasses import replace

from small_rig import DESC

import specgpu.calibration.cache as cache
from specgpu.calibration import oracle_calibration
from specgpu.calibration.cache import cached_calibration, calibration_file, find_calibration


def test_the_file_named_is_the_one_the_cache_writes_and_finds(monkeypatch, tmp_path):
    monkeypatch.setattr(cache, "calibrate", lambda description, **options: oracle_calibration(description))
    monkeypatch.setenv(cache.CACHE_ENV, "")
    path = calibration_file(DESC, tmp_path / "run", seed=4)
    assert path.parent == tmp_path / "run" and not path.exists()
    bundle, loaded = cached_calibration(DESC, [tmp_path / "run"], seed=4)
    assert loaded is None and path.is_file()
    assert list((tmp_path / "run").glob("calibration-*.npz")) == [path]
    found = find_calibration(DESC, [tmp_path / "run"], seed=4)
    assert found[1] == path and found[0].hash == bundle.hash
    # another seed or another rig: another file
    assert calibration_file(DESC, tmp_path / "run", seed=5) != path
    other = replace(DESC, camera=replace(DESC.camera, exposure_s=DESC.camera.exposure_s / 2))
    assert calibration_file(other, tmp_path / "run", seed=4) != path
