"""Error types shared by every recon package (imports nothing of recon)."""


class ReconError(ValueError):
    """User-facing bad input: the message names the file, key or tensor, expected and actual."""


class ConfigError(ReconError):
    """A config file or override is invalid."""


class DatasetError(ReconError):
    """A dataset folder or one of its files is invalid."""


def warn_user(message: str, kind: str = "warning") -> None:
    """Tell the user something on stderr as 'recon: warning: ...' (or another kind, e.g.
    'note'): a problem that does not stop the run but that they should act on."""
    import sys

    print(f"recon: {kind}: {message}", file=sys.stderr, flush=True)
