"""The daemon's configuration error, apart so that daemon.config and daemon.security (which
config calls to check the [security] section) both take it from below."""
from lacuna.errors import LacunaError


class ConfigError(LacunaError, ValueError):
    """A config file that cannot be used; the message names the file and the key."""
