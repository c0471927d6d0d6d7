"""Typed, strict configs: YAML files into nested dataclasses, with ``--set`` overrides.

Schemas are plain ``@dataclass`` classes; validation in their ``__post_init__`` uses
check_range (or raises ConfigFieldError) so errors name the file and the full key path.
"""

from recon.config.checks import ConfigFieldError, check_range
from recon.config.loader import from_dict, load_config
from recon.config.serialize import config_hash, dump_resolved, to_dict
from recon.errors import ConfigError

__all__ = [
    "ConfigError",
    "ConfigFieldError",
    "check_range",
    "config_hash",
    "dump_resolved",
    "from_dict",
    "load_config",
    "to_dict",
]
