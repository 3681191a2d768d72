"""Reflectance databases, evaluation-chart exclusion, PCA basis tables and their files."""

import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from specgpu.io.tables import load_npz, save_npz
from specgpu.pipeline.evaluate import true_patch_spectra
from specgpu.planning.basis import (
    COLORCHECKER_24_SETS,
    DEFAULT_WAVELENGTHS,
    REFLECTANCE_SETS,
    BasisTable,
    evaluation_exclusions,
    load_basis,
    load_reflectances,
    pca_basis,
    read_reflectance_csv,
    save_basis,
)
from specgpu.rig.scene import colorchecker_scene


@pytest.fixture(scope="module")
def chart():
    return true_patch_spectra(colorchecker_scene(24, 36), DEFAULT_WAVELENGTHS)[1]


@pytest.fixture(scope="module")
def training(chart):
    return load_reflectances(exclude=evaluation_exclusions("ColorChecker N Ohta"), exclude_similar_to=chart)


@pytest.fixture(scope="module")
def basis(training):
    return pca_basis(training)


def test_every_set_loads_on_the_default_grid():
    for name in REFLECTANCE_SETS:
        db = load_reflectances([name])
        assert db.reflectance.shape == (len(db), DEFAULT_WAVELENGTHS.size)
        assert len(db) >= 10, name
        assert db.reflectance.min() >= 0 and db.reflectance.max() <= 1.5
        assert all(lab.startswith(name + "/") for lab in db.labels)


def test_unknown_set_lists_the_valid_ones():
    with pytest.raises(ValueError, match="valid sets: ColorChecker N Ohta"):
        load_reflectances(["Munsell glossy"])
    with pytest.raises(ValueError, match="unknown chart"):
        evaluation_exclusions("not a chart")


def test_the_evaluation_chart_does_not_leak(training, chart):
    assert set(COLORCHECKER_24_SETS) <= set(evaluation_exclusions("BabelColor Average"))
    for lab in training.labels:
        assert lab.split("/")[0] not in COLORCHECKER_24_SETS
    dist = np.sqrt(np.mean((training.reflectance[:, None] - chart[None]) ** 2, axis=-1))
    assert dist.min() >= 0.01
    # Without the similarity rule, near-copies of chart patches (e.g. in the rawtoaces set) would be in.
    loose = load_reflectances(exclude=COLORCHECKER_24_SETS)
    loose_dist = np.sqrt(np.mean((loose.reflectance[:, None] - chart[None]) ** 2, axis=-1))
    assert loose_dist.min() < 0.01
    assert len(training) < len(loose) and len(training) > 200


def test_exact_duplicates_are_kept_once():
    db = load_reflectances(["ColorChecker N Ohta", "ISO 17321-1"])  # the same table twice
    assert len(db) == 24
    assert len(db.excluded) == 24


def test_uncentred_pca_against_numpy(basis, training):
    f = basis.functions
    np.testing.assert_allclose(f.T @ f, np.eye(f.shape[1]), atol=1e-10)
    assert f[:, 0].min() >= 0  # Perron-Frobenius: the paper's non-negative first basis function
    assert not basis.centred and np.all(basis.mean == 0)
    # Independent: eigenvalues of the second-moment matrix R^T R.
    r = training.reflectance
    ev = np.sort(np.linalg.eigvalsh(r.T @ r))[::-1]
    np.testing.assert_allclose(basis.singular_values**2, ev[: basis.singular_values.size], rtol=1e-8, atol=1e-10)
    cv = basis.cumulative_variance
    np.testing.assert_allclose(cv, np.cumsum(ev) / ev.sum(), rtol=1e-9)
    assert np.all(np.diff(cv) >= -1e-15) and cv[-1] == pytest.approx(1.0)
    assert 0.99 < cv[4] < 1.0  # five functions hold over 99 % (paper: 0.9974)
    # The subspace of the first five is the top eigenvectors' subspace.
    _, vec = np.linalg.eigh(r.T @ r)
    top = vec[:, ::-1][:, :5]
    np.testing.assert_allclose(np.abs(np.linalg.svd(top.T @ basis.first(5))[1]), 1.0, atol=1e-8)


def test_centred_pca_is_the_covariance_decomposition(training):
    b = pca_basis(training, centred=True)
    r = training.reflectance
    np.testing.assert_allclose(b.mean, r.mean(axis=0))
    ev = np.sort(np.linalg.eigvalsh(np.cov(r.T, bias=True) * r.shape[0]))[::-1]
    np.testing.assert_allclose(b.singular_values**2, ev[: b.singular_values.size], rtol=1e-7, atol=1e-9)


def test_projection_is_exact_in_the_span(basis):
    s = basis.first(5) @ np.array([2.0, 0.3, -0.2, 0.1, 0.05])
    np.testing.assert_allclose(basis.project(s, 5), s, atol=1e-12)
    with pytest.raises(ValueError, match="m must be an integer"):
        basis.first(0)


def test_basis_file_round_trip(tmp_path, basis):
    path = tmp_path / "basis.npz"
    digest = save_basis(path, basis)
    back = load_basis(path)
    np.testing.assert_array_equal(back.functions, basis.functions)
    np.testing.assert_array_equal(back.wavelengths, basis.wavelengths)
    assert back.source == basis.source and back.centred == basis.centred
    assert load_npz(path, "specgpu.basis", (1,))[3] == digest


def test_basis_file_errors_name_the_file(tmp_path, basis):
    path = tmp_path / "b.npz"
    save_basis(path, basis)
    data = path.read_bytes()
    bad = tmp_path / "truncated.npz"
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"truncated\.npz: corrupt"):
        load_basis(bad)
    # Edited content with the old hash.
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["functions"] = arrays["functions"] * 1.001
    edited = tmp_path / "edited.npz"
    np.savez(edited, **arrays)
    with pytest.raises(ValueError, match=r"edited\.npz: corrupt specgpu.basis file \(content does not match"):
        load_basis(edited)
    future = tmp_path / "future.npz"
    save_npz(future, "specgpu.basis", 99, {"x": np.zeros(2)}, {})
    with pytest.raises(ValueError, match=r"future\.npz: unknown specgpu.basis version 99"):
        load_basis(future)
    other = tmp_path / "other.npz"
    save_npz(other, "specgpu.plan", 1, {"x": np.zeros(2)}, {})
    with pytest.raises(ValueError, match=r"other\.npz: not a specgpu.basis file"):
        load_basis(other)
    with pytest.raises(ValueError, match="missing.npz: specgpu.basis file not found"):
        load_basis(tmp_path / "missing.npz")


def test_basis_table_validation():
    wl = np.arange(400.0, 701.0, 10.0)
    with pytest.raises(ValueError, match="basis functions must have shape"):
        BasisTable(wl, np.zeros((5, 2)), np.ones(2), np.zeros(wl.size), False, 3)


# ---- CSV ---------------------------------------------------------------------------------------------------
def test_csv_with_and_without_header(tmp_path):
    p = tmp_path / "tiles.csv"
    p.write_text("# my tiles\nwavelength,red,blue\n400,0.1,0.5\n500,0.2,0.4\n700,0.8,0.1\n")
    rows = read_reflectance_csv(p)
    assert [r[0] for r in rows] == ["red", "blue"]
    np.testing.assert_array_equal(rows[1][2], [0.5, 0.4, 0.1])
    q = tmp_path / "plain.csv"
    q.write_text("700,0.3\n400,0.1\n")  # unsorted rows are sorted
    (name, wl, val), = read_reflectance_csv(q)
    assert name == "plain:1" and wl.tolist() == [400, 700] and val.tolist() == [0.1, 0.3]
    db = load_reflectances(["PMC"], csv_files=[p])
    assert "tiles/red" in db.labels and len(db) == 32


@pytest.mark.parametrize("text, message", [
    ("400,0.1\n", "at least 2 wavelength rows"),
    ("400,0.1\n500\n", "row 2 has 1 cells"),
    ("400,0.1\n500,abc\n", "non-numeric"),
    ("400,0.1\n400,0.2\n", "duplicated wavelengths"),
    ("400,0.1\n500,2.0\n", r"must lie in \[0, 1.5\]"),
    ("400,0.1\n500,nan\n", "NaN or infinite"),
    ("w,a,b\n400,0.1\n500,0.2\n", "header names 2 samples"),
])
def test_csv_errors_name_the_file(tmp_path, text, message):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(ValueError, match=message) as exc:
        read_reflectance_csv(p)
    assert str(exc.value).startswith(str(p))
    assert "\n" not in str(exc.value)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.tuples(st.floats(300, 1000, allow_nan=False), st.floats(0, 1.5, allow_nan=False)),
                min_size=2, max_size=12, unique_by=lambda t: round(t[0], 3)))
def test_csv_round_trip_property(tmp_path, rows):
    rows = sorted({round(w, 3): v for w, v in rows}.items())
    if len(rows) < 2:
        return
    p = tmp_path / "prop.csv"
    p.write_text("".join(f"{w!r},{v!r}\n" for w, v in rows))
    (_, wl, val), = read_reflectance_csv(p)
    np.testing.assert_array_equal(wl, [w for w, _ in rows])
    np.testing.assert_array_equal(val, [v for _, v in rows])


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.binary(max_size=300))
def test_csv_garbage_is_a_one_line_value_error_or_valid(tmp_path, blob):
    p = tmp_path / "garbage.csv"
    p.write_bytes(blob)
    try:
        rows = read_reflectance_csv(p)
    except ValueError as exc:
        assert str(exc).startswith(str(p)) and "\n" not in str(exc)
    else:
        for _, wl, val in rows:
            assert np.all(np.diff(wl) > 0) and val.min() >= 0 and val.max() <= 1.5


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.binary(max_size=400))
def test_npz_garbage_is_a_one_line_value_error(tmp_path, blob):
    p = tmp_path / "garbage.npz"
    p.write_bytes(blob)
    with pytest.raises(ValueError) as exc:
        load_npz(p, "specgpu.basis", (1,))
    assert str(exc.value).startswith(str(p)) and "\n" not in str(exc.value)


def test_npz_with_a_damaged_member_is_refused(tmp_path, basis):
    path = tmp_path / "b.npz"
    save_basis(path, basis)
    with zipfile.ZipFile(path) as z:
        members = {n: z.read(n) for n in z.namelist()}
    name = "functions.npy"
    members[name] = members[name][:-16]  # a truncated array inside a valid archive
    damaged = tmp_path / "damaged.npz"
    with zipfile.ZipFile(damaged, "w") as z:
        for n, data in members.items():
            z.writestr(n, data)
    with pytest.raises(ValueError, match=r"damaged\.npz: .*corrupt"):
        load_basis(damaged)


def test_an_interrupted_save_keeps_the_previous_file(tmp_path, monkeypatch):
    from specgpu.io.tables import load_npz, save_npz

    path = tmp_path / "table.npz"
    digest = save_npz(path, "specgpu.test", 1, {"a": np.arange(3)}, {"k": 1})

    def fail(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(np.lib.format, "write_array", fail)  # mid-write: the archive is already open
    with pytest.raises(OSError, match="disk full"):
        save_npz(path, "specgpu.test", 1, {"a": np.arange(5)}, {"k": 2})
    arrays, meta, version, loaded = load_npz(path, "specgpu.test", (1,))
    assert loaded == digest and arrays["a"].tolist() == [0, 1, 2]
    assert [p.name for p in tmp_path.iterdir()] == ["table.npz"]  # no temporary left behind


def test_cie_2017_ces_set_is_colour_sciences_table():
    import colour
    from colour.quality.cfi2017 import load_TCS_CIE2017

    db = load_reflectances(["CIE 2017 CES"])
    ref = load_TCS_CIE2017(colour.SpectralShape(380, 780, 5))
    assert len(db) == 99 and db.labels[0].endswith("TCS0 (CIE 2017)")
    i = int(np.flatnonzero(np.asarray(ref.wavelengths) == 550.0)[0])
    j = int(np.flatnonzero(DEFAULT_WAVELENGTHS == 550.0)[0])
    np.testing.assert_allclose(db.reflectance[:, j], np.asarray(ref.values, np.float64)[i], rtol=0, atol=1e-12)
    # in the default training: the held-out charts' own sets stay out, the CES set stays in
    full = load_reflectances(exclude=evaluation_exclusions("CIE 1995 TCS"))
    assert sum(label.startswith("CIE 2017 CES/") for label in full.labels) == 99
