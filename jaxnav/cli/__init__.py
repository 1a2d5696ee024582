"""The command lines: `jaxnav.cli.train`, `evaluate`, `export`, `replay` and `twin`, each a thin
`main(argv)` over the library (`jaxnav.training`, `jaxnav.evaluation`, `jaxnav.export`,
`jaxnav.replay`, `jaxnav.twin`), run by `python -m jaxnav.<command>`; and what they share:
argparse that reports a user mistake as one line (`UsageError`, `Parser`, `print_error`) and
`--help GROUP`.
"""

from __future__ import annotations

import argparse
import sys


class UsageError(ValueError):
    """A user mistake (flag, file, field); printed as one `error: ...` line, exit status 2."""


class Parser(argparse.ArgumentParser):
    """argparse that raises `UsageError` instead of printing usage and exiting."""

    def error(self, message):
        raise UsageError(message)


def print_error(err: BaseException) -> None:
    """`error: <message>` on stderr, folded onto one line whatever the message held."""
    print(f"error: {' '.join(str(err).split())}", file=sys.stderr)


class GroupHelp(argparse.Action):
    """`-h/--help [GROUP]`: the command's own flags and a list of the config groups; with GROUP,
    that group's flags (`all`: every flag)."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs="?", const="", metavar="GROUP", **kwargs)

    def __call__(self, parser, namespace, value, option_string=None):
        groups = {g.title.split()[0].lower().rstrip(":"): g for g in parser._action_groups[2:]}
        if value and value != "all" and value not in groups:
            raise UsageError(f"--help: unknown group '{value}'; valid: all, {', '.join(groups)}")
        chosen = parser._action_groups[:2] if not value else []
        chosen += list(groups.values()) if value == "all" else [groups[value]] if value else []
        formatter = parser._get_formatter()
        formatter.add_usage(parser.usage, parser._actions, [])
        if not value:
            formatter.add_text(parser.description)
        for group in chosen:
            formatter.start_section(group.title)
            formatter.add_text(group.description)
            formatter.add_arguments(group._group_actions)
            formatter.end_section()
        if not value:
            listed = "\n".join(f"  {name:10} {g.description or ''}" for name, g in groups.items())
            formatter.add_text(
                "flag groups (--help GROUP shows one, --help all every flag; the defaults shown "
                "are those of the --env and --preset given, the cpu preset's if none):"
            )
            formatter.add_text(listed)
        parser._print_message(formatter.format_help(), sys.stdout)
        parser.exit()
