"""The argparse pieces of `romannet`'s command line that help a user who mistyped: invalid choices and
unknown flags get "did you mean ...?" for a near miss, and unknown arguments are reported with the usage of
the verb (and tool) the user named, not the top-level one. Apart from the verb table (romannet/cli.py)
because they hold no verb.
"""

from __future__ import annotations

import argparse
import difflib
import re


def with_choice_hint(message: str) -> str:
    """argparse's "invalid choice: 'replya' (choose from ...)" with "; did you mean replay?" for a near miss."""
    m = re.fullmatch(r"argument .+?: invalid choice: '(.*)' \(choose from (.*)\)", message, re.DOTALL)
    if m is None:
        return message
    close = difflib.get_close_matches(m[1], re.findall(r"'([^']*)'", m[2]), n=1, cutoff=0.6)
    return f"{message}; did you mean {close[0]}?" if close else message


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose invalid-choice errors suggest the choice meant (verbs, tools, --task values).
    Sub-command parsers are of the same class (add_subparsers' default), so every level has it."""

    def error(self, message: str):  # type: ignore[override]
        super().error(with_choice_hint(message))


def chosen_parser(parser: argparse.ArgumentParser, args: argparse.Namespace) -> argparse.ArgumentParser:
    """The (sub-)parser of the verb and tool the user named, e.g. `deploy certs`'s: its usage is the one to show."""
    while True:
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        name = getattr(args, subs[0].dest, None) if subs else None
        if not subs or name not in subs[0].choices:
            return parser
        parser = subs[0].choices[name]


def unknown_args_message(extras: list[str], options: list[str]) -> str:
    """'unrecognized arguments: --lisen x; did you mean --listen?' (the hint for the near misses only)."""
    flags = [a.split("=", 1)[0] for a in extras if a.startswith("--")]
    meant = {f: close[0] for f in flags if (close := difflib.get_close_matches(f, options, n=1, cutoff=0.6))}
    text = f"unrecognized arguments: {' '.join(extras)}"
    if len(meant) == 1 and len(flags) == 1:
        return f"{text}; did you mean {next(iter(meant.values()))}?"
    return text + "".join(f"; {f}: did you mean {m}?" for f, m in meant.items())


def parse_args(parser: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace:
    """parse_args, except that arguments the verb does not know are reported with the verb's own usage
    (argparse would show the top-level one) and, for a near-miss flag, the flag that was meant."""
    args, extras = parser.parse_known_args(argv)
    if extras:
        where = chosen_parser(parser, args)
        options = [o for a in where._actions for o in a.option_strings if o.startswith("--")]
        where.error(unknown_args_message(extras, options))
    return args
