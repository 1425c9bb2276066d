"""Starting nodes from one pre-imported parent (a "zygote"), so a run's processes start in about
the time one import takes instead of each importing numpy, scipy, gtsam, proxsuite and zenoh anew.

The zygote is started with fork+exec (`python -m bench.runtime.zygote`): a fresh interpreter
that never opens a Zenoh session, so forking it is safe (forking a process that runs Zenoh's
runtime threads is not). `bench run` starts it first of all, so its imports run beside the
launcher's (`Zygote.start_early`, taken over by `Zygote.for_launcher`). It imports every node's
module once, then forks one child per request. The child takes the node's log file as stdout and
stderr, /dev/null as stdin, joins the run's process group, shows the node's command line in `ps`,
and runs `bench.cli.main` with the same arguments as `python -m bench.cli node NAME ...` would.

Its children are the zygote's, not the launcher's, so the zygote reaps them and reports each exit
status over a pipe; `ForkedProcess` gives the launcher the subprocess.Popen methods it relies on
(poll, returncode, pid, wait(timeout), send_signal, terminate, kill). Owning them (ownership.py):
the zygote gets SIGKILL when the launcher dies (PR_SET_PDEATHSIG), so the nodes get their own
parent-death SIGTERM and their watchdogs' SIGKILL exactly as when the launcher itself was their
parent. Anything the zygote cannot do as the exec path would (another environment or working
directory than the zygote's, a zygote that died or never answered) falls back to the exec path;
BENCH_NODE_START=exec chooses it always.
"""
from __future__ import annotations

import ctypes
import json
import os
import select
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from bench.runtime.ownership import (LAUNCHER_PID_ENV, ORPHAN_EXIT_CODE, PARENT_PID_ENV, CpuProgress,
                                     _set_parent_death_signal, child_environment, process_state)
from bench.runtime.reports import REPORT_KEY_ENV

NODE_START_ENV = "BENCH_NODE_START"          # "exec": every node by fork+exec, as before the zygote
NODE_MODULE_ARGS = ["-m", "bench.cli"]       # what a node command runs; anything else goes by exec
# Variables the launcher gives each node its own value of (its report key: bench/runtime/reports.py);
# the forked child sets them itself, any other difference from the zygote's environment goes by exec.
PER_NODE_ENV = {REPORT_KEY_ENV}
# Modules every node needs or one of them imports (bench.runtime.node.NODES adds the nodes' own).
PRELOAD = ["numpy", "scipy.linalg", "gtsam", "proxsuite", "zenoh", "msgspec", "can", "cantools",
           "bench.cli", "bench.runtime.node_cli"]
# The child rewrites the command line `ps` and /proc/PID/cmdline show with the node's; the
# zygote's own command line reserves the room (the kernel's argument area cannot grow).
CMDLINE_ROOM_CHARS = 4096
STUCK_IDLE_S = 10.0       # a zygote that has not answered and whose CPU time stood still this long is stuck
ANSWER_TIMEOUT_S = 300.0  # a zygote still importing after this is given up on (exec path instead)
CLOSE_GRACE_S = 1.0


_early: "Zygote | None" = None    # started by `bench run` before the launcher's imports (start_early)


class ZygoteFailed(RuntimeError):
    """The zygote died, never answered, or could not fork: start the node by exec instead."""


def enabled() -> bool:
    return os.environ.get(NODE_START_ENV, "zygote").strip().lower() != "exec"


# ================================================================================================
# The launcher's side
# ================================================================================================
class ForkedProcess:
    """A node forked by the zygote, with the subprocess.Popen interface the launcher uses."""

    def __init__(self, zygote: "Zygote", pid: int, args: list[str]):
        self._zygote = zygote
        self.pid = pid
        self.args = args
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            self.returncode = self._zygote.exit_code(self.pid)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            remaining = 0.05 if deadline is None else min(0.05, deadline - time.monotonic())
            if remaining <= 0:
                raise subprocess.TimeoutExpired(self.args, timeout)
            self._zygote.pump(remaining)
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.poll() is not None:     # reaped: its pid may be someone else's now
            return
        try:
            os.kill(self.pid, sig)
        except ProcessLookupError:
            pass

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)

    def __repr__(self) -> str:
        return f"<ForkedProcess pid={self.pid} returncode={self.returncode}>"


class Zygote:
    """The launcher's handle on its zygote: start one (`start`), fork nodes from it (`spawn`), stop it."""

    def __init__(self, process: subprocess.Popen, report_fd: int, env: dict[str, str], cwd: str,
                 show: bool = False):
        self.process = process
        self.show = show                          # say on stderr when the imports are done
        self._started_s = time.monotonic()
        self._answered = False
        self.env = env
        self.cwd = cwd
        self._report_fd = report_fd
        self._lock = threading.RLock()
        self._buffer = b""
        self._started: dict[int, dict] = {}       # request token -> the zygote's answer
        self._exited: dict[int, int] = {}         # pid -> exit code as subprocess reports it
        self._next_token = 0
        self.failure: str | None = None           # why it cannot be used (then: exec path)

    @classmethod
    def start(cls, env: dict[str, str], show: bool = False) -> "Zygote | None":
        """Start a zygote whose nodes get `env` (ownership.child_environment()); None if it cannot
        start. show: say on stderr when its imports are done (the terminal is never blank)."""
        report_r, report_w = os.pipe()
        try:
            process = subprocess.Popen(
                [sys.executable, "-m", "bench.runtime.zygote", str(report_w), "-" * CMDLINE_ROOM_CHARS],
                stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, pass_fds=(report_w,), env=env,
                process_group=0)   # its own group: a terminal's Ctrl-C is for the launcher
        except OSError as exc:
            os.close(report_r)
            print(f"bench: could not start the node start-up server ({exc}); starting nodes by exec", file=sys.stderr)
            return None
        finally:
            os.close(report_w)
        return cls(process, report_r, dict(env), os.getcwd(), show)

    @classmethod
    def start_early(cls) -> None:
        """Start this process's zygote now, before the launcher's own imports and checks, so its
        imports run beside them (`bench run` calls this first). `for_launcher` hands it over."""
        global _early
        if enabled() and _early is None:
            _early = cls.start(child_environment())

    @classmethod
    def for_launcher(cls, env: dict[str, str], show: bool = False) -> "Zygote | None":
        """The launcher's zygote: the one started early if it serves `env` from this directory and
        still runs, else a new one (None with BENCH_NODE_START=exec, or if none can start)."""
        global _early
        early = _early
        if early is not None and early.env == env and early.cwd == os.getcwd() and early.process.poll() is None:
            _early = None
            early.show = show
            return early
        cls.close_early()
        return cls.start(env, show) if enabled() else None

    @staticmethod
    def close_early() -> None:
        """End a zygote started early that no launcher took (the run stopped at bad input): at
        once, it has started nothing and may still be importing."""
        global _early
        early, _early = _early, None
        if early is not None:
            early.process.kill()
            early.close()

    # --- starting a node ---------------------------------------------------------------------
    def extra_env(self, popen_kwargs: dict) -> dict[str, str] | None:
        """The variables a node's environment adds to the zygote's, if it adds only per-node ones
        the child can set itself after the fork (PER_NODE_ENV); None if it differs otherwise."""
        env = popen_kwargs.get("env", os.environ)
        extra = {k: v for k, v in env.items() if self.env.get(k) != v}
        if set(self.env) - set(env) or not set(extra) <= PER_NODE_ENV:
            return None
        return extra

    def can_start(self, cmd: list[str], popen_kwargs: dict) -> bool:
        """Whether a fork of the zygote starts `cmd` exactly as Popen(cmd, **popen_kwargs) would."""
        return (self.failure is None and cmd[0] == sys.executable and cmd[1:3] == NODE_MODULE_ARGS
                and "process_group" in popen_kwargs and set(popen_kwargs) <= {"process_group", "env"}
                and self.extra_env(popen_kwargs) is not None and os.getcwd() == self.cwd)

    def spawn(self, cmd: list[str], log_path: Path, process_group: int = 0,
              extra_env: dict[str, str] | None = None) -> ForkedProcess:
        """Fork `cmd` (a `python -m bench.cli ...` command) logging to log_path, in process group
        process_group (0: a new one it leads), with extra_env added to its environment. Raises
        ZygoteFailed (and marks this zygote failed)."""
        with self._lock:
            token = self._next_token
            self._next_token += 1
            request = {"token": token, "cmd": cmd, "log_path": str(log_path), "process_group": process_group,
                       "env": dict(extra_env or {})}
            try:
                self.process.stdin.write(json.dumps(request).encode() + b"\n")
                self.process.stdin.flush()
            except (OSError, ValueError) as exc:
                raise self._fail(f"cannot send it a request: {exc}") from None
        started = time.monotonic()
        progress = CpuProgress(self.process.pid)
        while token not in self._started:
            self.pump(0.1)
            if token in self._started:
                break
            if self.failure is not None:
                raise ZygoteFailed(self.failure)
            if self.process.poll() is not None:
                raise self._fail(f"it exited with code {self.process.returncode}")
            waited_s = time.monotonic() - started
            if progress.idle_s(time.monotonic()) > STUCK_IDLE_S or waited_s > ANSWER_TIMEOUT_S:
                self.process.kill()     # a node it forks later would have nobody watching it
                raise self._fail(f"no answer after {waited_s:.0f} s")
        answer = self._started.pop(token)
        if "pid" not in answer:
            raise self._fail(f"it could not fork: {answer.get('error')}")
        if not self._answered:
            self._answered = True
            if self.show:
                print(f"bench: node packages imported after {time.monotonic() - self._started_s:.1f} s; "
                      f"forking the nodes from them", file=sys.stderr)
        return ForkedProcess(self, answer["pid"], cmd)

    def _fail(self, reason: str) -> ZygoteFailed:
        if self.failure is None:
            self.failure = f"node start-up server failed ({reason})"
            print(f"bench: {self.failure}; starting nodes by exec", file=sys.stderr)
        return ZygoteFailed(self.failure)

    # --- exit statuses -----------------------------------------------------------------------
    def pump(self, timeout_s: float = 0.0) -> None:
        """Read what the zygote reported, waiting up to timeout_s for something to arrive."""
        with self._lock:
            if self._report_fd < 0:
                time.sleep(max(timeout_s, 0.0))
                return
            readable, _, _ = select.select([self._report_fd], [], [], max(timeout_s, 0.0))
            if not readable:
                return
            chunk = os.read(self._report_fd, 65536)
            if not chunk:                       # the zygote is gone: what it did not report, nobody will
                os.close(self._report_fd)
                self._report_fd = -1
                if self.failure is None:
                    self._fail("its report pipe closed")
                return
            self._buffer += chunk
            *lines, self._buffer = self._buffer.split(b"\n")
            for line in lines:
                report = json.loads(line)
                if "exited" in report:
                    self._exited[report["exited"]] = report["code"]
                elif "token" in report:
                    self._started[report["token"]] = report

    def exit_code(self, pid: int) -> int | None:
        """The exit code of a forked node (negative: killed by that signal); None while it runs."""
        self.pump(0.0)
        if pid in self._exited:
            return self._exited[pid]
        if self._report_fd < 0:
            # The zygote died; its children got their parent-death signal and were reaped by init,
            # their status unknown. Once gone they count as orphaned.
            state = process_state(pid)
            if state is None or state.state == "Z":
                return ORPHAN_EXIT_CODE
        return None

    def close(self) -> None:
        """End the zygote: it exits once it has no children; killed after CLOSE_GRACE_S."""
        try:
            self.process.stdin.close()
        except OSError:
            pass
        try:
            self.process.wait(timeout=CLOSE_GRACE_S)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        with self._lock:
            if self._report_fd >= 0:
                os.close(self._report_fd)
                self._report_fd = -1


# ================================================================================================
# The zygote's side
# ================================================================================================
def _preload() -> None:
    """Import what the nodes import; a module that fails here fails in the node as it would by exec."""
    import importlib

    names = list(PRELOAD)
    try:
        from bench.runtime.node import NODES
        names += list(dict.fromkeys(NODES.values()))
    except Exception:  # noqa: BLE001
        pass
    for name in names:
        try:
            importlib.import_module(name)
        except Exception:  # noqa: BLE001
            pass


def _set_cmdline(args: list[str]) -> None:
    """Show `args` as this process's command line (ps, /proc/PID/cmdline), within the room the
    zygote's own command line left (arg_start..arg_end of /proc/self/stat)."""
    try:
        with open("/proc/self/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        start, end = int(fields[45]), int(fields[46])     # fields 48 and 49 of proc(5)
        if start <= 0 or end <= start:
            return
        size = end - start
        data = b"\0".join(a.encode(errors="replace") for a in args)[:size - 1]
        ctypes.memmove(start, data + b"\0" * (size - len(data)), size)
    except (OSError, ValueError, IndexError):
        pass


def _run_node(request: dict, zygote_pid: int, close_fds: list[int]) -> None:
    """In the forked child: become `python -m bench.cli ARGS` writing to its log file. Never returns."""
    code = 1
    try:
        try:
            os.setpgid(0, request["process_group"])
        except OSError:
            pass
        signal.set_wakeup_fd(-1)
        for fd in close_fds:          # the zygote's pipes: its death must show as their end-of-file
            os.close(fd)
        for sig in (signal.SIGCHLD, signal.SIGTERM):
            signal.signal(sig, signal.SIG_DFL)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        log_fd = os.open(request["log_path"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)
        null_fd = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null_fd, 0)
        os.dup2(log_fd, 1)
        os.dup2(log_fd, 2)
        for fd in {log_fd, null_fd} - {0, 1, 2}:
            os.close(fd)
        os.environ[PARENT_PID_ENV] = str(zygote_pid)    # ownership.die_with_launcher: its parent
        os.environ.update({k: v for k, v in request.get("env", {}).items() if k in PER_NODE_ENV})
        cmd = request["cmd"]
        _set_cmdline(cmd)
        # The module the command names (`-m bench.cli`), by name as `python -m` finds it: the
        # runtime starts the command line, it does not depend on the CLI (tests/test_layers.py).
        import importlib
        cli = importlib.import_module(cmd[2])
        sys.argv = [cli.__file__, *cmd[3:]]
        code = _exit_code_of_main(cli.main, cmd[3:])
    except BaseException:  # noqa: BLE001 - nothing may return into the zygote's loop
        try:
            import traceback
            traceback.print_exc()
        except BaseException:  # noqa: BLE001
            pass
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except BaseException:  # noqa: BLE001
                pass
        os._exit(code & 0xFF)


def _exit_code_of_main(main, args: list[str]) -> int:
    """What `sys.exit(main(args))` at the end of a fresh interpreter would make the exit status:
    SystemExit's code, a traceback and 1 for an exception, death by SIGINT for an uncaught
    KeyboardInterrupt; non-daemon threads joined and atexit handlers run first."""
    import atexit
    import traceback

    interrupted = False
    try:
        code = main(args)
    except SystemExit as exc:
        code = exc.code
    except KeyboardInterrupt:
        traceback.print_exc()
        code, interrupted = 1, True
    except BaseException:  # noqa: BLE001
        traceback.print_exc()
        code = 1
    if code is None:
        code = 0
    elif not isinstance(code, int):
        print(code, file=sys.stderr)
        code = 1
    try:
        threading._shutdown()       # as the interpreter does at exit: non-daemon threads finish
    except BaseException:  # noqa: BLE001
        pass
    atexit._run_exitfuncs()
    if interrupted:
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGINT)
    return code


def serve(report_fd: int) -> int:
    """The zygote: requests on stdin (one JSON line each), reports on report_fd, until stdin closes
    and every child has exited."""
    import gc

    launcher = os.environ.get(LAUNCHER_PID_ENV, "")
    _set_parent_death_signal(signal.SIGKILL)    # its children then get their own death signal
    if launcher.isdigit() and os.getppid() != int(launcher):
        return 1                                # the launcher died before prctl took effect
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _preload()
    gc.freeze()                                 # the preloaded objects stay shared with the children
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_r, False)
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGCHLD, lambda *_: None)
    children: set[int] = set()
    pending = b""
    closing = False

    def report(message: dict) -> None:
        os.write(report_fd, json.dumps(message).encode() + b"\n")

    while not (closing and not children):
        readable = [wake_r] if closing else [0, wake_r]
        ready, _, _ = select.select(readable, [], [], 1.0)
        if wake_r in ready:
            try:
                while os.read(wake_r, 512):
                    pass
            except BlockingIOError:
                pass
        while children:
            try:
                pid, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                break
            if pid == 0:
                break
            children.discard(pid)
            report({"exited": pid, "code": os.waitstatus_to_exitcode(status)})
        if 0 in ready:
            chunk = os.read(0, 65536)
            if not chunk:
                closing = True
                continue
            pending += chunk
            *lines, pending = pending.split(b"\n")
            for line in lines:
                request = json.loads(line)
                for stream in (sys.stdout, sys.stderr):
                    stream.flush()
                try:
                    pid = os.fork()
                except OSError as exc:
                    report({"token": request["token"], "error": str(exc)})
                    continue
                if pid == 0:
                    _run_node(request, os.getppid(), [report_fd, wake_r, wake_w])
                try:                            # also here: the launcher may signal the group at once
                    os.setpgid(pid, request["process_group"] or pid)
                except OSError:
                    pass
                children.add(pid)
                report({"token": request["token"], "pid": pid})
    return 0


if __name__ == "__main__":
    sys.exit(serve(int(sys.argv[1])))
