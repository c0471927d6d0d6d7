"""Error types shared by every recon package (imports nothing of recon)."""


class ReconError(ValueError):
    """User-facing bad input: the message names the file, key or tensor, expected and actual."""


class ConfigError(ReconError):
    """A config file or override is invalid."""


class DatasetError(ReconError):
    """A dataset folder or one of its files is invalid."""
