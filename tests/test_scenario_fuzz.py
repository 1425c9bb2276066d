"""Strict scenario input (issue 26): scenario files generated from the schema and mutated (wrong
types, non-finite, huge and negative numbers, unknown keys, deep nesting, unicode; issue 44: keys
given twice, integers of thousands of digits, URL-like channels) are either accepted, and then
usable by the nodes' objects, or refused with one ScenarioError line naming a field; never another
exception. Written as TOML and as JSON (the scenario.json of a run directory). The one-by-one checks
are in test_scenario_strict.py and test_input_refusals.py.

Needs hypothesis (the `test` extra); skipped without it.
"""
from __future__ import annotations

import json
import math
import multiprocessing
import re
import tomllib
from importlib import resources

import msgspec
import msgspec.inspect as mi
import pytest

from bench.bus.can.config import SERIAL_INTERFACES
from bench.scenario import (
    BUILTIN_PACKAGE, MAX_NESTING, Scenario, ScenarioError, parse_json_text, parse_scenario, parse_toml_text,
)
from test_scenario_strict import QUOTES_THEN_DEEP

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, example, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

SOURCE = "fuzz.toml"
# Cheap built-ins to mutate: both loops, the CAN section with faults, the smoother.
BASES = ["rendezvous_lqr", "rendezvous_smoother", "rendezvous_mtq_bus", "attitude_quick", "attitude_fault_board_death",
         "attitude_pointing_pd"]
BASE_DATA = {name: tomllib.loads(resources.files(BUILTIN_PACKAGE).joinpath(f"{name}.toml").read_text()) for name in BASES}
# IGRF costs ~0.2 s a build (ppigrf reads its coefficients each time): only mutations choose it.
BASE_DATA["attitude_fault_board_death"]["attitude"]["field"] = {"model": "dipole"}


# --- the schema, walked -----------------------------------------------------------------------
def schema_fields(t=None, path=()):
    """(path, type info) of every field in the scenario schema; list items at index 0."""
    t = mi.type_info(Scenario) if t is None else t
    out = []
    if isinstance(t, mi.StructType):
        for f in t.fields:
            out.append((path + (f.name,), f.type))
            out.extend(schema_fields(f.type, path + (f.name,)))
    elif isinstance(t, mi.UnionType):
        for member in t.types:
            out.extend(schema_fields(member, path))
    elif isinstance(t, mi.ListType):
        out.append((path + (0,), t.item_type))
        out.extend(schema_fields(t.item_type, path + (0,)))
    return out


FIELDS = schema_fields()
# --- TOML text of generated data ----------------------------------------------------------------
class Deep:
    """A list nested `depth` times, written as text (no recursion in the writer)."""

    def __init__(self, depth: int):
        self.depth = depth


class Duplicated:
    """A key written twice, with `first` then `last` (json would keep the last, silently)."""

    def __init__(self, first, last):
        self.first, self.last = first, last


class Digits:
    """An integer of `count` digits, written as text: more than Python converts (4300)."""

    def __init__(self, count: int, negative: bool):
        self.count, self.negative = count, negative

    def text(self) -> str:
        return "-" * self.negative + "9" * self.count


def pairs(table: dict):
    """The table's key/value pairs as written: a Duplicated value is its key twice."""
    for key, value in table.items():
        if isinstance(value, Duplicated):
            yield key, value.first
            yield key, value.last
        else:
            yield key, value


def holds(value, kind) -> bool:
    """Whether plain data holds an instance of `kind` (Duplicated, Digits) anywhere."""
    stack = [value]
    while stack:
        item = stack.pop()
        if isinstance(item, kind):
            return True
        if isinstance(item, Duplicated):
            stack.extend([item.first, item.last])
        elif isinstance(item, dict):
            stack.extend(item.values())
        elif isinstance(item, list):
            stack.extend(item)
    return False


def toml_string(text: str) -> str:
    out = []
    for c in text:
        if c in '"\\':
            out.append("\\" + c)
        elif ord(c) < 0x20 or ord(c) == 0x7F:
            out.append(f"\\u{ord(c):04x}")
        else:
            out.append(c)
    return '"' + "".join(out) + '"'


def toml_value(value) -> str:
    if isinstance(value, Deep):
        return "[" * value.depth + "]" * value.depth
    if isinstance(value, Digits):
        return value.text()
    if isinstance(value, Duplicated):     # in a list: no key to give twice
        return toml_value(value.last)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return toml_string(value)
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{toml_string(str(k))} = {toml_value(v)}" for k, v in pairs(value)) + "}"
    raise TypeError(type(value))


def toml_text(data: dict) -> str:
    return "".join(f"{toml_string(str(k))} = {toml_value(v)}\n" for k, v in pairs(data))


def json_value(value) -> str:
    """JSON text as a launcher's scenario.json, or a hostile one: NaN and Infinity as Python's json
    reads them, keys given twice, integers of any length."""
    if isinstance(value, Deep):
        return "[" * value.depth + "]" * value.depth
    if isinstance(value, Digits):
        return value.text()
    if isinstance(value, Duplicated):
        return json_value(value.last)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "NaN"
        if math.isinf(value):
            return "Infinity" if value > 0 else "-Infinity"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(json_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))}: {json_value(v)}" for k, v in pairs(value)) + "}"
    raise TypeError(type(value))


# --- values and mutations --------------------------------------------------------------------
def in_range(info):
    """Values the schema allows at this field (or close to it)."""
    if isinstance(info, mi.FloatType):
        low = info.ge if info.ge is not None else info.gt
        high = info.le if info.le is not None else info.lt
        return st.floats(min_value=low, max_value=high, exclude_min=info.gt is not None and info.ge is None,
                         exclude_max=info.lt is not None and info.le is None, allow_nan=False, allow_infinity=False)
    if isinstance(info, mi.IntType):
        low = info.ge if info.ge is not None else (info.gt + 1 if info.gt is not None else -10**6)
        high = info.le if info.le is not None else (info.lt - 1 if info.lt is not None else 10**6)
        return st.integers(low, high)
    if isinstance(info, mi.LiteralType):
        return st.sampled_from(info.values)
    if isinstance(info, mi.BoolType):
        return st.booleans()
    if isinstance(info, mi.StrType):
        if info.pattern:
            return st.from_regex(info.pattern, fullmatch=True)
        return st.text(max_size=min(info.max_length or 40, 40))
    if isinstance(info, mi.UnionType):
        members = [m for m in info.types if not isinstance(m, mi.NoneType)]
        return st.one_of([in_range(m) for m in members])
    if isinstance(info, mi.ListType):
        low = info.min_length or 0
        return st.lists(in_range(info.item_type), min_size=low, max_size=max(low, min(info.max_length or 5, 5)))
    if isinstance(info, mi.StructType):
        return st.just({})
    return st.none()


HOSTILE = st.one_of(
    st.sampled_from([float("inf"), float("-inf"), float("nan"), 1e300, -1e300, 1e308, 5e-324, -1.0, 0.0, -0.0,
                     10**20, 2**63, 2**64, -(10**30), -1, 0, True, False, "20", "nan", "inf", "1e300", "",
                     [], {}, [[]], {"x": 1}, "\u202e\u2028\n\x1b[31m"]),
    st.integers(), st.floats(), st.text(max_size=30), st.lists(st.integers(), max_size=3),
)


def set_path(data: dict, path: tuple, value) -> None:
    node = data
    for key, next_key in zip(path, path[1:]):
        default = [] if isinstance(next_key, int) else {}
        if isinstance(node, list):
            while len(node) <= key:
                node.append(default)
            if not isinstance(node[key], (dict, list)):
                node[key] = default
            node = node[key]
        else:
            if not isinstance(node.get(key), (dict, list)):
                node[key] = default
            node = node[key]
    last = path[-1]
    if isinstance(node, list):
        if isinstance(last, int):
            while len(node) <= last:
                node.append(None)
            node[last] = value
    elif isinstance(node, dict) and not isinstance(last, int):
        node[last] = value


def remove_nones(value):
    """TOML has no null: what set_path padded lists with is dropped."""
    if isinstance(value, dict):
        return {k: remove_nones(v) for k, v in value.items() if v is not None}
    if isinstance(value, list):
        return [remove_nones(v) for v in value if v is not None]
    return value


# Channels that are no device: pyserial's URL handlers (spy:// wrote a file, socket:// connected
# out), any scheme, relative and climbing paths; and interfaces of every kind of channel.
URL_LIKE = st.one_of(
    st.sampled_from(["spy:///dev/ttyACM0?file=victim.txt", "loop://", "socket://127.0.0.1:7", "rfc2217://127.0.0.1:7",
                     "alt:///dev/ttyACM0?class=Serial", "hwgrep://.*", "cp2110://0001:0002:00", "victim.txt",
                     "../victim.txt", "/dev/../victim.txt", "**", "a/b", "tcp/127.0.0.1:7447", "http://x/"]),
    st.from_regex(r"[a-z][a-z0-9+.-]{0,10}://[ -~]{0,30}", fullmatch=True),
)
INTERFACES = ["slcan", "serial", "robotell", "seeedstudio", "socketcan", "socketcand", "udp_multicast", "zenoh", "pcan",
              "kvaser", "virtual"]
STR_FIELDS = [(path, info) for path, info in FIELDS if isinstance(path[-1], str)]


@st.composite
def mutation(draw):
    path, info = draw(st.sampled_from(FIELDS))
    kind = draw(st.sampled_from(["valid", "valid", "valid", "hostile", "unknown_key", "nesting", "unicode_key",
                                 "duplicate_key", "huge_integer", "url_channel"]))
    if kind == "duplicate_key":
        path, info = draw(st.sampled_from(STR_FIELDS))
        return path, Duplicated(draw(st.one_of(in_range(info), HOSTILE).filter(lambda v: v is not None)), draw(HOSTILE))
    if kind == "huge_integer":
        return path, Digits(draw(st.integers(4301, 6000)), draw(st.booleans()))
    if kind == "url_channel":
        where = draw(st.sampled_from(["flight_channel", "board_channel", "driver_bus", "board_bus"]))
        if where.endswith("_channel"):
            return ("can", where), draw(URL_LIKE)
        bus = {"interface": draw(st.sampled_from(INTERFACES)), "channel": draw(URL_LIKE)}
        if draw(st.booleans()):
            bus["options"] = {draw(st.sampled_from(["host", "connect", "state", "dll"])): draw(URL_LIKE)}
        return ("can", where), bus
    if kind == "valid":
        return path, draw(in_range(info))
    if kind == "hostile":
        return path, draw(HOSTILE)
    if kind == "unknown_key":
        return path[:-1] + (draw(st.text(min_size=1, max_size=12)),), draw(HOSTILE)
    if kind == "unicode_key":
        return path[:-1] + (draw(st.sampled_from(["st\u00e9ps", "\u0440un", "a\nb", "\u202e", "\U0001f680"])),), 1
    return path, Deep(draw(st.sampled_from([2, MAX_NESTING - 3, MAX_NESTING + 1, 200, 600])))


def mutated(draw) -> dict:
    data = json.loads(json.dumps(BASE_DATA[draw(st.sampled_from(BASES))]))   # a deep copy
    for path, value in draw(st.lists(mutation(), min_size=1, max_size=3)):
        set_path(data, path, value)
    return remove_nones(data)


@st.composite
def scenario_files(draw):
    """(TOML text, its top-level keys, whether it must be refused)."""
    data = mutated(draw)
    return toml_text(data), {str(k) for k in data}, holds(data, (Duplicated, Digits))


@st.composite
def json_scenario_files(draw):
    """(JSON text, its top-level keys, whether it must be refused)."""
    data = mutated(draw)
    return json_value(data), {str(k) for k in data}, holds(data, (Duplicated, Digits))


# --- what an accepted scenario must allow ----------------------------------------------------------
def use_in_process(scenario: Scenario) -> None:
    """What the nodes build from a validated scenario, and a few steps of the loop, without processes."""
    assert 1 <= scenario.n_steps <= 100_000 and math.isfinite(scenario.step_s)
    # The launcher writes scenario.json; every node loads it back.
    again = parse_scenario(json.loads(msgspec.json.encode(scenario)), "scenario.json")
    assert again == scenario
    # Two steps, lock-step: real-time mode runs the law in a solver worker process, which is the
    # controller process's business; this check starts no process.
    few = msgspec.structs.replace(scenario, run=msgspec.structs.replace(scenario.run, steps=2, mode="lock-step"))
    if scenario.can is not None:
        assert_channels_are_devices(scenario.can)
        from bench.bus.can.injector import FaultInjector

        injector = FaultInjector(scenario.can.faults, scenario.can.protocol(), seed=scenario.run.seed)
        injector.arm(10**18)
        for fault in scenario.can.faults:
            fault.window_ns(10**18)
        scenario.can.dipole_at(12.3)
    if scenario.kind == "rendezvous":
        from bench.sim import simulate_in_process

        simulate_in_process(few)
    else:
        from bench.config.controller import PLANNED_LAWS
        from bench.sim import simulate_attitude_in_process

        if scenario.attitude_control.law in PLANNED_LAWS:
            from bench.planner.planner import planner_config

            planner_config(scenario)   # building and running MILQR is the planner process's test
            few = msgspec.structs.replace(few, attitude_control=msgspec.structs.replace(few.attitude_control, law="bdot"))
        simulate_attitude_in_process(few)
    assert multiprocessing.active_children() == []


def assert_channels_are_devices(can) -> None:
    """No accepted scenario makes a node open a URL or a file: a serial interface's channel is
    empty or an absolute path without '.' or '..', no channel has a scheme, no option is a path."""
    for role in ("driver", "board", "busmodel_flight", "busmodel_board"):
        spec = can.bus_spec(role)
        assert "://" not in spec.channel, spec
        if spec.interface in SERIAL_INTERFACES and spec.channel:
            assert spec.channel.startswith("/") and not {".", ".."} & set(spec.channel.split("/")), spec
        assert not {"dll", "connect", "listen", "override_library_name"} & set(spec.options), spec
        assert all("/" not in v for v in spec.options.values() if isinstance(v, str)), spec


# "fuzz.toml: FIELD: problem", FIELD a path of bare or quoted ("a b") keys and [i] indices.
QUOTED = r'"(?:[^"\\]|\\.)*"'


def field_at_start(source: str) -> re.Pattern:
    return re.compile(rf"^{re.escape(source)}: (?P<field>(?:{QUOTED}|[^ :\"])+|line \d+): \S")


def assert_names_a_field(message: str, top_keys: set[str], source: str = SOURCE) -> None:
    """One printable line whose field's first key is in the file or in the schema."""
    assert "\n" not in message and message.isprintable(), repr(message)
    match = field_at_start(source).match(message)
    assert match, message
    field = match.group("field")
    if field.startswith("line "):
        return
    quoted = re.match(QUOTED, field)
    top = quoted.group(0) if quoted else re.split(r"[.\[]", field, maxsplit=1)[0]
    assert top in {shown_key(k) for k in top_keys | set(Scenario.__struct_fields__)}, message


def shown_key(key: str) -> str:
    """A key as messages show it: bare if plain, else quoted with what cannot print escaped."""
    if re.fullmatch(r"[A-Za-z0-9_-]+", key):
        return key
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in json.dumps(key, ensure_ascii=False))


@settings(max_examples=600, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(scenario_files())
@example(('name = "x"\n[run]\nsteps = "20"\n', {"name", "run"}))
@example(('name = "x"\n[can]\n[[can.faults]]\nname = "drop"\nstart_s = 1e300\n', {"name", "can"}))
@example(('name = "x"\n[can]\n[[can.faults]]\nname = "drop"\ncount = 100000000000000000000\n', {"name", "can"}))
@example((QUOTES_THEN_DEEP, {"name", "z"}))
def test_fuzzed_scenarios_are_accepted_and_usable_or_refused_naming_a_field(case):
    text, top_keys, *must_refuse = case
    try:
        scenario = parse_scenario(parse_toml_text(text, SOURCE), SOURCE)
    except ScenarioError as exc:
        assert_names_a_field(str(exc), top_keys)
        return
    assert not any(must_refuse), text
    use_in_process(scenario)


JSON_SOURCE = "fuzz.json"


@settings(max_examples=300, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(json_scenario_files())
@example(('{"name": "x", "can": {"security": {"profile": "secoc", "profile": "e2e"}}}', {"name", "can"}, True))
@example(('{"name": "x", "run": {"steps": ' + "9" * 5001 + "}}", {"name", "run"}, True))
def test_fuzzed_json_scenarios_are_accepted_or_refused_naming_a_field(case):
    """The scenario.json a run directory holds, the way the nodes load it; what an accepted one
    makes the nodes do is the TOML fuzz's (the same data)."""
    text, top_keys, must_refuse = case
    try:
        scenario = parse_scenario(parse_json_text(text, JSON_SOURCE), JSON_SOURCE)
    except ScenarioError as exc:
        assert_names_a_field(str(exc), top_keys, JSON_SOURCE)
        return
    assert not must_refuse, text
    if scenario.can is not None:
        assert_channels_are_devices(scenario.can)
