"""The version of symfunnel (also in pyproject.toml), for manifests, reports and `--version`."""

__version__ = "0.1.0"
