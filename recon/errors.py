"""Error types shared by every recon package (imports nothing of recon)."""


class ReconError(ValueError):
    """User-facing bad input: the message names the file, key or tensor, expected and actual."""


class ConfigError(ReconError):
    """A config file or override is invalid."""


class DatasetError(ReconError):
    """A dataset folder or one of its files is invalid."""


# What a user can do about the OS errors that writing a run folder meets most.
_OS_ERROR_HINTS = {
    "EROFS": "the file system is read-only; choose another --out",
    "EACCES": "permission denied; choose another --out or fix the folder's permissions",
    "EPERM": "operation not permitted; choose another --out or fix the folder's permissions",
    "ENOSPC": "the disk is full; free space, then continue with --resume where it applies",
    "EDQUOT": "the disk quota is exceeded; free space, then continue with --resume",
}


def describe_os_error(error: OSError, path: object = None) -> str:
    """'PATH: reason (ERRNO_NAME: what to do)' for an OSError, naming `path` when given."""
    import errno

    name = errno.errorcode.get(error.errno or 0, "")
    reason = error.strerror or str(error)
    where = path if path is not None else error.filename if error.filename is not None else "a file"
    hint = _OS_ERROR_HINTS.get(name)
    detail = f" ({name}: {hint})" if hint else f" ({name})" if name else ""
    return f"{where}: {reason}{detail}"


class WriteError(ReconError):
    """A file recon writes could not be written (read-only folder, full disk, permissions)."""


def warn_user(message: str, kind: str = "warning") -> None:
    """Tell the user something on stderr as 'recon: warning: ...' (or another kind, e.g.
    'note'): a problem that does not stop the run but that they should act on."""
    import sys

    print(f"recon: {kind}: {message}", file=sys.stderr, flush=True)
