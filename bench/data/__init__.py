"""Reference numbers, one TOML file per reference (`rendezvous.toml`: seed 003 and its 2022
parameter file). Code reads them through `load_reference` and cites them instead of repeating
the values."""
from __future__ import annotations

import tomllib
from functools import cache
from importlib import resources


@cache
def _text(name: str) -> str:
    return resources.files(__name__).joinpath(f"{name}.toml").read_text()


def load_reference(name: str = "rendezvous") -> dict:
    """The reference `bench/data/<name>.toml` as a fresh dict (callers may change their copy)."""
    try:
        return tomllib.loads(_text(name))
    except FileNotFoundError:
        raise ValueError(f"no reference data named {name!r} in bench/data") from None
