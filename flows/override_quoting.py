"""The command line's overrides, checked before Hydra parses them (issue 49): a value with characters that Hydra's
override grammar accepts only inside quotes (a non-ASCII path such as ``signal.path=/data/données.csv``) is one line
saying how to quote it, instead of Hydra's ``LexerNoViableAltException`` with a caret under the character."""
from __future__ import annotations

_VALUE_FLAGS = ("-cp", "-cn", "-cd", "--config-path", "--config-name", "--config-dir")  # their value is no override


def check_override_quoting(argv: list[str]) -> None:
    """Refuse (``SystemExit``, one line) the first non-ASCII override of ``argv`` that Hydra cannot parse unquoted,
    with the quoted form that it reads (the whole override in single quotes for the shell, the value in double
    quotes for Hydra; in a ``-m`` sweep each comma-separated value).  ASCII overrides are left to Hydra's own
    messages."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import OverrideParseException

    parser, sweep = None, any(a in ("-m", "--multirun") for a in argv)
    for before, arg in zip(["", *argv], argv):
        if arg.isascii() or arg.startswith("-") or before in _VALUE_FLAGS:
            continue
        parser = parser or OverridesParser.create()
        try:
            parser.parse_overrides([arg])
        except OverrideParseException:
            key, _, value = arg.partition("=")
            quote = "'" if '"' in value else '"'
            quoted = ",".join(f"{quote}{v}{quote}" for v in (value.split(",") if sweep else [value]))  # each job's
            raise SystemExit(f"config error: the override {arg} holds characters Hydra reads only inside quotes: "
                             f"quote {'each value' if sweep and ',' in value else 'its value'}, e.g. "
                             f"'{key}={quoted}' (single quotes around it all for the shell)") from None
