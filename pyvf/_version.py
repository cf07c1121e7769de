"""pyvf's version, in one place for the package (pyproject.toml states the same number; the tests check
that show_config prints pyproject's)."""

__version__ = "0.1.0"
