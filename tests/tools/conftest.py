"""Fixtures of the tests of ``tools/``."""

from estimator_helpers import bundle, prior, spectra  # noqa: F401 (the estimator tests' module-scoped fixtures)
