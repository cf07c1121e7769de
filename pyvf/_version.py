"""pyvf's version (pyproject.toml states the same number; the tests check that show_config prints it)."""

__version__ = "0.1.0"
