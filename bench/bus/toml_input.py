"""What tomllib refused in an input file (a scenario, a deployment, a campaign spec), named by field.

tomllib names a line and a column at most ("Cannot overwrite a value (at line 5, column 20)" for a
key given twice), and an integer of more digits than Python converts (sys.get_int_max_str_digits,
4300) escapes it as a bare ValueError naming nothing. tomllib's own frames know the key it was
parsing: `field` reads them from the exception's traceback, a best effort for the message (the
frames are those of Python 3.11's tomllib; where none is found, the line).
"""
from __future__ import annotations

import re
import sys
import tomllib


def field(exc: BaseException, text: str, quote=str) -> str:
    """The key tomllib was at when it raised `exc`, dotted (each part through `quote`): the table
    header and key of its outermost key/value frame, or the table header being declared; else the
    line it was at; else "<root>"."""
    header = key = declared = pos = None
    tb = exc.__traceback__
    while tb is not None and key is None:
        frame = tb.tb_frame
        if frame.f_globals.get("__name__", "").startswith("tomllib"):
            local, name = frame.f_locals, frame.f_code.co_name
            if isinstance(local.get("pos"), int):
                pos = local["pos"]
            if name == "key_value_rule" and isinstance(local.get("header"), tuple):
                header = local["header"]
                # A key given twice is refused here, after its key/value frame returned.
                declared = local.get("key") if isinstance(local.get("key"), tuple) else None
            elif name == "parse_key_value_pair" and isinstance(local.get("key"), tuple):
                key = local["key"]
            elif name in ("create_dict_rule", "create_list_rule") and isinstance(local.get("key"), tuple):
                header, key = (), local["key"]      # a table header declared twice
        tb = tb.tb_next
    key = key if key is not None else declared
    if key is not None and all(isinstance(part, str) for part in (header or ()) + key):
        return ".".join(quote(part) for part in (header or ()) + key)
    if isinstance(pos, int):
        return f"line {text.count(chr(10), 0, pos) + 1}"
    return "<root>"


def problem(exc: ValueError) -> str:
    """What tomllib's ValueError says, in the bench's words."""
    if isinstance(exc, tomllib.TOMLDecodeError):
        twice = re.match(r"Cannot overwrite a value|Cannot declare .* twice|Duplicate inline table key", str(exc))
        return f"key given twice (not valid TOML: {exc})" if twice else f"not valid TOML: {exc}"
    digits = re.search(r"value has (\d+) digits", str(exc))
    if digits:
        return f"an integer of {digits.group(1)} digits; at most {sys.get_int_max_str_digits()} digits are read"
    return str(exc)
