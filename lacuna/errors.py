"""Exceptions shared across layers.  Each layer raises one kind, with context in the message."""


class LacunaError(Exception):
    """Base for errors that the CLI reports as one clear line (exit status 2)."""


class ParseError(LacunaError, ValueError):
    """Malformed input file; the message names the file and, where it can, the line."""

    def __init__(self, path: str, line: int | None, message: str):
        self.path, self.line, self.message = path, line, message
        where = f"{path}:{line}" if line is not None else str(path)
        super().__init__(f"{where}: {message}")


class DataError(LacunaError):
    """The data directory or a data set in it is missing or incomplete."""
