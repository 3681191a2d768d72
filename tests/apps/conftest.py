"""Fixtures of the apps tests."""

from estimator_helpers import bundle, prior, spectra  # noqa: F401 (the estimator tests' module-scoped fixtures)

