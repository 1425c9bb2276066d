"""`bench inject RUN_ID KIND [--duration S] [--axis x] ...`: add a fault to a running run from another
terminal (issue 48; docs/live.md).

The fault is any kind `[[can.faults]]` takes (`bench faults` lists them with their parameters),
with the same fields; it starts now (or `--after S` simulated seconds from now), on the run's
simulated time. The request goes to the run's canbus process on the command channel
(bench/bus/fault_command.py), signed under the run's key (runs/<id>/bus.key, or the deployment's
key beside the certificates); canbus takes it only in a run started with `--allow-live-faults`,
and answers, signed. What this command finds of the run: the hub endpoint in runs/<id>/contract.json
(or --connect), the key in runs/<id>/bus.key (or --key-file), and for a run with certificates
(--secure: runs/.certs/<id>/, or --cert-dir) the identity "operator", which the access control
allows to ask for faults and nothing else.

Exit codes: 0 the fault was taken (answer authentic), 1 refused or no answer, 2 bad input.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from bench.bus import data_auth, keys
from bench.bus import fault_command as fc

EXIT_REFUSED = 1
EXIT_BAD_INPUT = 2
SENDER = "inject"
OPERATOR = "operator"          # the certificate identity of `bench inject` (bench/bus/acl.py)
AXES = {"x": 0, "y": 1, "z": 2}
FIND_CANBUS_S = 10.0


def _value(text: str):
    lowered = text.lower()
    if lowered in ("true", "false"):
        return lowered == "true"
    try:
        return int(text, 0)
    except ValueError:
        return float(text)


def build_request(args) -> fc.FaultRequest:
    params = {}
    for item in args.param or ():
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise ValueError(f"--param {item!r}: NAME=VALUE")
        try:
            params[name] = _value(value)
        except ValueError:
            raise ValueError(f"--param {item!r}: the value is a number, true or false") from None
    if args.axis is not None:
        params["axis"] = AXES[args.axis]
    fields = {"params": params, "after_s": args.after, "count": args.count, "every": args.every,
              "frames": list(args.frames or ())}
    if args.duration is not None:
        fields["duration_s"] = args.duration
    request = fc.new_request(keys.check_run_id(args.run_id), args.kind, **fields)
    fc.fault_spec(request, 0.0)       # the same check canbus makes: a bad field is named here, exit 2
    return request


def _hub(run_dir: Path, connect: str | None) -> str:
    if connect:
        return connect
    try:
        return json.loads((run_dir / "contract.json").read_text())["zenoh"]["connect"]
    except (OSError, ValueError, KeyError, TypeError):
        raise ValueError(f"no hub endpoint: {run_dir / 'contract.json'} is not there (give --connect ENDPOINT, "
                         f"the one `bench run` printed)") from None


def _cert_dir(args, runs_dir: Path) -> Path | None:
    if args.cert_dir:
        return Path(args.cert_dir)
    local = runs_dir / ".certs" / args.run_id          # `bench run --secure`'s
    return local if (local / "ca.pem").is_file() else None


def cmd_inject(args) -> int:
    from bench.bus.certs import CertificateError, identity_files
    from bench.bus.presence import PresenceQuery
    from bench.bus.session import SessionConfigError, SessionOptions, open_session

    try:
        request = build_request(args)
        runs_dir = Path(args.runs_dir)
        run_dir = runs_dir / args.run_id
        hub = _hub(run_dir, args.connect)
        cert_dir = _cert_dir(args, runs_dir)
        if args.key_file:
            key = data_auth.read_key_file(Path(args.key_file))
        else:
            try:
                key = data_auth.node_key(run_dir, cert_dir)
            except data_auth.KeyFileError as exc:
                print(f"bench inject: {exc}", file=sys.stderr)
                key = None
        if key is None:
            print(f"bench inject: no key ({run_dir / data_auth.KEY_FILE}): the request goes unsigned, and the run "
                  f"refuses it", file=sys.stderr)
        identity = identity_files(cert_dir, OPERATOR) if cert_dir is not None else None
        session = open_session(SessionOptions(connect=(hub,), identity=identity))
    except (ValueError, SessionConfigError, CertificateError) as exc:
        print(f"bench inject: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        # Until the run's canbus is reachable (its presence answer), so the query finds its queryable.
        presence = PresenceQuery(session, args.run_id, key)
        deadline = time.monotonic() + FIND_CANBUS_S
        while fc.CANBUS not in presence.ask(fc.CANBUS, timeout_s=0.5) and time.monotonic() < deadline:
            time.sleep(0.1)
        answer, authentic = fc.request_fault(session, request, key, SENDER, timeout_s=args.timeout)
    finally:
        session.close()
    if answer is None:
        print(f"bench inject: no answer from run {args.run_id!r}'s canbus at {hub} (is it running? a run without a "
              f"CAN bus has no fault injector)", file=sys.stderr)
        return EXIT_REFUSED
    where = "" if authentic else " (answer not authenticated: no key to check it)"
    if answer.accepted and authentic:
        until = f" to {answer.end_sim_s:.3f} s" if answer.end_sim_s is not None else " (no end)"
        print(f"bench inject: fault {answer.label} taken: {args.kind} from {answer.start_sim_s:.3f} s{until} "
              f"(simulated), flagged live")
        return 0
    print(f"bench inject: refused ({answer.reason}){where}: {answer.detail}", file=sys.stderr)
    return EXIT_REFUSED


def add_commands(subparsers) -> None:
    p = subparsers.add_parser("inject", help="add a fault to a running run (one started with --allow-live-faults)")
    p.add_argument("run_id", metavar="RUN_ID")
    p.add_argument("kind", metavar="KIND", help="a [[can.faults]] name (`bench faults` lists them)")
    p.add_argument("--duration", type=float, help="simulated seconds (window faults and board_power_loss need it)")
    p.add_argument("--after", type=float, default=0.0, help="simulated seconds from now to its start (default 0)")
    p.add_argument("--axis", choices=sorted(AXES), help="coil faults: the body axis")
    p.add_argument("--frames", nargs="+", metavar="FRAME", help="DBC frame names (frame faults)")
    p.add_argument("--count", type=int, default=0, help="frames affected, 0 = no limit (frame faults)")
    p.add_argument("--every", type=int, default=1, help="act on every n-th matching frame (frame faults)")
    p.add_argument("--param", action="append", metavar="NAME=VALUE", help="a parameter of the kind (repeatable)")
    p.add_argument("--runs-dir", default="runs", help="where run directories are (default: runs)")
    p.add_argument("--connect", help="the hub endpoint (default: the run's contract.json)")
    p.add_argument("--key-file", help="the run's key (default: the run directory's bus.key)")
    p.add_argument("--cert-dir", help="certificates of a run with mutual TLS (default: runs/.certs/RUN_ID if there)")
    p.add_argument("--timeout", type=float, default=3.0, help="seconds to wait for the answer")
    p.set_defaults(func=cmd_inject)
