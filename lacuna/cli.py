"""The `lacuna` command.  Each package adds its own subcommands through ``add_commands(cli)``.

A command module defines::

    def add_commands(cli: lacuna.cli.CLI) -> None:
        p = cli.command("eval", help="...")          # top-level: lacuna eval
        p = cli.train("hlm", help="...")             # lacuna train hlm
        p = cli.generate("crbm", help="...")         # lacuna generate crbm
        p.add_argument(...)
        p.set_defaults(func=run)                      # run(args) -> int exit status

Errors derived from lacuna.errors.LacunaError (and ValueError/OSError raised by readers) are
printed as one line ``lacuna: error: ...`` with exit status 2, never a traceback.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from lacuna import __version__
from lacuna.errors import LacunaError

COMMAND_MODULES = ["mocap.cli", "mocap.data_cli", "hlm.cli", "crbm.cli", "daemon.cli", "daemon.keys_cli", "clients.cli", "blend.cli", "blend.withhlm_cli", "view.cli",
                   "archive.cli"]


class CLI:
    def __init__(self) -> None:
        self.parser = argparse.ArgumentParser(
            prog="lacuna", description="Real-time gap filling for live motion capture."
        )
        self.parser.add_argument("--version", action="version", version=f"lacuna {__version__}")
        self._sub = self.parser.add_subparsers(dest="command", metavar="COMMAND")
        self._groups: dict[str, argparse._SubParsersAction] = {}

    def command(self, name: str, **kw) -> argparse.ArgumentParser:
        kw.setdefault("description", kw.get("help"))
        return self._sub.add_parser(name, **kw)

    def _group(self, group: str, help: str) -> argparse._SubParsersAction:
        if group not in self._groups:
            p = self._sub.add_parser(group, help=help, description=help)
            self._groups[group] = p.add_subparsers(dest=f"{group}_what", metavar="MODEL")
            p.set_defaults(func=lambda a, p=p: (p.print_help(), 2)[1])
        return self._groups[group]

    def train(self, name: str, **kw) -> argparse.ArgumentParser:
        kw.setdefault("description", kw.get("help"))
        return self._group("train", "train a model from motion files").add_parser(name, **kw)

    def generate(self, name: str, **kw) -> argparse.ArgumentParser:
        kw.setdefault("description", kw.get("help"))
        return self._group("generate", "generate motion from a trained model").add_parser(name, **kw)


def build() -> CLI:
    cli = CLI()
    for mod in COMMAND_MODULES:
        try:
            m = importlib.import_module(mod)
        except ModuleNotFoundError as e:
            if e.name and mod.startswith(e.name):
                continue  # that package has no commands yet
            raise
        m.add_commands(cli)
    return cli


def main(argv: Sequence[str] | None = None) -> int:
    cli = build()
    args = cli.parser.parse_args(argv)
    if not getattr(args, "func", None):
        cli.parser.print_help()
        return 2
    try:
        rc = args.func(args)
    except KeyboardInterrupt:
        print("lacuna: interrupted", file=sys.stderr)
        return 130
    except (LacunaError, ValueError, OSError, KeyError) as e:
        msg = e.args[0] if isinstance(e, KeyError) and e.args else e
        print(f"lacuna: error: {msg}", file=sys.stderr)
        return 2
    return int(rc or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
