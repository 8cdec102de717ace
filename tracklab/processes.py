"""A run of several processes (one per host or per GPU), started and ended so that it fails fast.

JAX's multi-process runtime (``jax.distributed``) waits for an unreachable coordinator or a
missing peer for minutes, then aborts the process with a C++ stack trace; processes that run
different experiments find out only inside a collective. So before JAX is asked to connect,
the processes meet over plain TCP on the coordinator's port (process 0 listens there first):

1. every setting is checked where it is given (``settings``): the address is ``HOST:PORT``
   with a port in 1–65535 and a host that resolves, the count is positive, the id is in
   ``[0, N)``;
2. each other process connects to process 0 (retrying while nothing listens yet) and says
   who it is and what it runs (``agree``: the command, its options and the experiment file's
   contents); process 0 waits for all of them and answers each. A peer that never comes, a
   coordinator that never answers, an id given twice or a process that runs something else
   ends every process with one line naming what was waited for or what differs;
3. only then does JAX connect (``start``), with the same timeout;
4. at the end the processes meet once more on the connections kept from step 2
   (``finish``): a peer that died is noticed there at once (its connection closes) instead of
   at JAX's shutdown barrier, and process 0, whose results are complete, ends with a line
   saying so.

Every wait is bounded by one timeout (``TIMEOUT_S``; ``--process-timeout`` or
``TRACKLAB_PROCESS_TIMEOUT``). Faults raise ``ProcessError``: ``exit_status`` 2 for settings
that cannot work, 1 for a peer or coordinator that failed.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import socket
import threading
import time
from dataclasses import dataclass

TIMEOUT_S = 60.0
AFTER_LAST_EXCHANGE_S = 5.0  # how long process 0 goes on after a peer ended without reaching its end
ENV = {"coordinator": "TRACKLAB_COORDINATOR", "processes": "TRACKLAB_PROCESSES", "process_id": "TRACKLAB_PROCESS_ID",
       "timeout": "TRACKLAB_PROCESS_TIMEOUT"}
_HELLO = "tracklab processes 1"  # the first words every message of the meeting carries


class ProcessError(Exception):
    """A multi-process run that cannot start or went wrong: one line, and the exit status."""

    def __init__(self, message: str, exit_status: int):
        super().__init__(message)
        self.exit_status = exit_status


@dataclass(frozen=True)
class Settings:
    """Where process 0 listens, how many processes there are, which one this is, how long to wait."""

    host: str
    port: int
    processes: int
    process_id: int
    timeout: float

    @property
    def coordinator(self) -> str:
        return f"[{self.host}]:{self.port}" if ":" in self.host else f"{self.host}:{self.port}"


class Meeting:
    """The connections kept from the start (process 0: one per peer; a peer: one to process 0),
    each read by a thread of its own (``watch``) that notices a process that ends without
    reaching its end: at once in a peer when it is process 0 (nothing can be written without
    it), and in any process before JAX's runtime has connected them all; otherwise when this
    process has not reached its own end within ``AFTER_LAST_EXCHANGE_S`` (a peer that ends
    between the last exchange of sums and its end leaves process 0 writing what is whole; a
    peer that ends before it leaves process 0 waiting for an exchange that will not come)."""

    def __init__(self, settings: Settings, peers: dict[int, socket.socket]):
        self.settings = settings
        self.peers = peers
        self.done = {pid: threading.Event() for pid in peers}  # the peer reached its end (or ended)
        self.gone: dict[int, str] = {}  # the peers that ended without reaching theirs, and how
        self.ending = threading.Event()  # this process reached its end (``finish``)
        self.started = threading.Event()  # JAX's runtime connected every process
        self.last: dict[int, dict] = {}  # what each said at its end
        self.closed: set[int] = set()  # those whose connection ended after they reached their end

    def watch(self):
        for pid, conn in self.peers.items():
            threading.Thread(target=self._watch, args=(pid, conn), daemon=True, name=f"tracklab-peer-{pid}").start()

    def _watch(self, pid: int, conn: socket.socket):
        try:
            message = _receive(conn, None, f"process {pid}")
        except (TimeoutError, ConnectionError, OSError):
            message = {}
        if message.get("done"):
            self.last[pid] = message
            self.done[pid].set()
            try:  # nothing more comes: the connection's end, once the other process has ended
                _receive(conn, None, f"process {pid}")
            except (TimeoutError, ConnectionError, OSError):
                pass
            self.closed.add(pid)
            return
        failed = message.get("failed")
        self.gone[pid] = f"stopped with exit status {failed}" if failed else "ended"
        self.done[pid].set()
        s = self.settings
        if self.ending.wait(0.0 if failed or pid == 0 or not self.started.is_set() else AFTER_LAST_EXCHANGE_S):
            return
        when = "during the run" if self.started.is_set() else "before the run started"
        what = f"process {pid} of {s.processes} {self.gone[pid]} {when}"
        _abandon(f"error: {what}{' (see its output)' if failed else ''}; process {s.process_id} stops"
                 f"{'' if s.process_id else ' (nothing written)'}", 1)


def _abandon(line: str, status: int):
    """End this process at once with one line: JAX's runtime would wait for the others."""
    import sys

    sys.stdout.flush()
    print(line, file=sys.stderr, flush=True)
    os._exit(status)


def cluster_size() -> int:
    """The processes a Slurm or Open MPI launch started (1 outside one): where JAX finds the
    coordinator, the process count and this process's id by itself."""
    for var in ("SLURM_NTASKS", "OMPI_COMM_WORLD_SIZE"):
        try:
            n = int(os.environ.get(var, "1"))
        except ValueError:
            continue
        if n > 1:
            return n
    return 1


def coordinator_address(text: str) -> tuple[str, int]:
    """(host, port) of ``HOST:PORT`` (``[IPv6]:PORT`` too); ValueError in one line otherwise."""
    text = str(text).strip()
    host, sep, port = text.rpartition(":")
    if not sep or not host:
        raise ValueError(f"coordinator {text!r} must be HOST:PORT (e.g. 127.0.0.1:7777)")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    try:
        number = int(port)
    except ValueError:
        raise ValueError(f"coordinator {text!r}: the port {port!r} is not a number (1–65535)") from None
    if not 1 <= number <= 65535:
        raise ValueError(f"coordinator {text!r}: the port {number} is not in 1–65535")
    try:
        socket.getaddrinfo(host, number, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as e:
        why = e.strerror if isinstance(e, socket.gaierror) and e.strerror else str(e)
        raise ValueError(f"coordinator {text!r}: the host {host!r} cannot be resolved ({why})") from None
    return host, number


def _env(name):
    v = os.environ.get(ENV[name])
    return None if v is None or v.strip() == "" else v.strip()


def _integer(value, what):
    if value is None or isinstance(value, int):
        return value
    try:
        return int(value)
    except ValueError:
        raise ValueError(f"{what} {value!r} must be an integer") from None


def settings(coordinator: str | None = None, processes: int | None = None, process_id: int | None = None,
             timeout: float | None = None) -> Settings | None:
    """The settings of a run of several processes from the arguments, else the ``TRACKLAB_*``
    variables; None for one process (nothing given, or one process). ValueError in one line for
    settings that cannot work."""
    coordinator = coordinator or _env("coordinator")
    processes = _integer(processes if processes is not None else _env("processes"), ENV["processes"])
    process_id = _integer(process_id if process_id is not None else _env("process_id"), ENV["process_id"])
    timeout = timeout if timeout is not None else _env("timeout")
    try:
        timeout = TIMEOUT_S if timeout is None else float(timeout)
    except ValueError:
        raise ValueError(f"{ENV['timeout']}={timeout!r} must be a number of seconds") from None
    if not (timeout > 0 and timeout < 1e6):
        raise ValueError(f"the process timeout {timeout:g} s must be positive (and under 10⁶ s)")
    if processes is not None and processes < 1:
        raise ValueError(f"the process count {processes} must be at least 1")
    if process_id is not None and process_id < 0:
        raise ValueError(f"the process id {process_id} must be at least 0")
    if processes is not None and process_id is not None and process_id >= processes:
        raise ValueError(f"the process id {process_id} must be in 0 … {processes - 1} (--processes {processes})")
    given = [v is not None for v in (coordinator, processes, process_id)]
    if processes == 1 and process_id in (None, 0):
        if coordinator is not None:
            coordinator_address(coordinator)
        return None
    if not any(given):
        return None
    if not all(given):
        missing = [n for n, g in zip(("the coordinator address (--coordinator)", "the process count (--processes)",
                                      "this process's id (--process-id)"), given) if not g]
        raise ValueError("a multi-process run needs the coordinator address, the process count and this process's id "
                         f"(options or {ENV['coordinator']}, {ENV['processes']}, {ENV['process_id']}): "
                         f"{' and '.join(missing)} {'is' if len(missing) == 1 else 'are'} missing")
    host, port = coordinator_address(coordinator)
    return Settings(host, port, processes, process_id, timeout)


def digest(what: dict) -> dict:
    """What a process runs, as it is compared between processes: each entry as text (a file's
    contents by its SHA-256)."""
    out = {}
    for k, v in what.items():
        if isinstance(v, bytes):
            out[k] = hashlib.sha256(v).hexdigest()
        else:
            out[k] = json.dumps(v, sort_keys=True, default=str)
    return out


def _send(sock, message: dict):
    sock.sendall((json.dumps({"hello": _HELLO, **message}) + "\n").encode())


def _receive(sock, deadline: float | None, what: str) -> dict:
    """One message, read before ``deadline`` (None: however long the connection stays open);
    TimeoutError, or ConnectionError naming ``what``."""
    data = b""
    while not data.endswith(b"\n"):
        left = None if deadline is None else deadline - time.monotonic()
        if left is not None and left <= 0:
            raise TimeoutError
        sock.settimeout(left)
        try:
            chunk = sock.recv(65536)
        except socket.timeout:
            raise TimeoutError from None
        if not chunk:
            raise ConnectionError(f"{what} closed the connection")
        data += chunk
        if len(data) > 1 << 20:
            raise ConnectionError(f"{what} is not a tracklab process (it sent too much)")
    try:
        message = json.loads(data)
    except ValueError:
        raise ConnectionError(f"{what} is not a tracklab process (it sent something else)") from None
    if not isinstance(message, dict) or message.get("hello") != _HELLO:
        raise ConnectionError(f"{what} is not a tracklab process of this version")
    return message


def _differences(mine: dict, theirs: dict) -> str:
    names = sorted(set(mine) | set(theirs))
    differ = [n for n in names if mine.get(n) != theirs.get(n)]
    shown = []
    for n in differ[:3]:
        a, b = (_option(x) for x in (mine.get(n), theirs.get(n)))
        if n == "experiment file contents":
            shown.append(n)
        else:
            shown.append(f"{n} ({b} there, {a} in process 0)")
    return ", ".join(shown) + (", …" if len(differ) > 3 else "")


def _option(text) -> str:
    """An option's value as ``digest`` wrote it, as a person reads it."""
    return "not given" if text in (None, "null") else str(text)


def _listen(s: Settings) -> socket.socket:
    try:
        if socket.has_dualstack_ipv6():
            return socket.create_server(("", s.port), family=socket.AF_INET6, dualstack_ipv6=True, reuse_port=False)
        return socket.create_server(("", s.port))
    except OSError as e:
        why = os.strerror(e.errno).lower() if e.errno else str(e)
        raise ProcessError(f"process 0 cannot listen on port {s.port} ({s.coordinator}): {why} (another process 0, or "
                           f"another program, listens there?): choose another port", 2) from None


def _meet_as_coordinator(s: Settings, what: dict) -> Meeting:
    deadline = time.monotonic() + s.timeout
    server = _listen(s)
    peers: dict[int, socket.socket] = {}
    strays: list[socket.socket] = []
    why = None
    try:
        while len(peers) < s.processes - 1 and why is None:
            left = deadline - time.monotonic()
            if left <= 0:
                missing = [str(i) for i in range(1, s.processes) if i not in peers]
                why = (f"process 0 waited {s.timeout:g} s at {s.coordinator} for process{'es' if len(missing) > 1 else ''} "
                       f"{', '.join(missing)} of {s.processes}: never connected", 1)
                break
            server.settimeout(min(left, 1.0))
            try:
                conn, addr = server.accept()
            except socket.timeout:
                continue
            try:
                hello = _receive(conn, time.monotonic() + min(5.0, max(left, 0.1)), f"a connection from {addr[0]}")
            except (TimeoutError, ConnectionError, OSError):
                conn.close()  # a stray connection: not one of ours
                continue
            pid, count = hello.get("process_id"), hello.get("processes")
            if count != s.processes:
                why = (f"process {pid} was started with --processes {count}, process 0 with {s.processes}", 2)
            elif not isinstance(pid, int) or not 1 <= pid < s.processes:
                why = (f"a process gave the id {pid!r}: beside process 0 the ids are 1 … {s.processes - 1}", 2)
            elif pid in peers:
                why = (f"two processes were given the id {pid}", 2)
            elif hello.get("what") != what:
                why = (f"process {pid} runs something else than process 0: {_differences(what, hello.get('what') or {})} "
                       f"differ", 2)
            if why is None:
                peers[pid] = conn
            else:
                strays.append(conn)
    except BaseException:
        why = why or ("process 0 stopped waiting", 1)
        raise
    finally:
        server.close()
        if why is not None:
            for conn in [*peers.values(), *strays]:
                _answer(conn, {"ok": False, "why": why[0], "status": why[1]})
    if why is not None:
        raise ProcessError(why[0], why[1])
    for conn in peers.values():
        _answer(conn, {"ok": True}, close=False)
    return Meeting(s, peers)


def _answer(conn: socket.socket, message: dict, close=True):
    try:
        _send(conn, message)
    except OSError:
        pass
    if close:
        conn.close()


def _meet_as_peer(s: Settings, what: dict) -> Meeting:
    deadline = time.monotonic() + s.timeout
    last = None
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            raise ProcessError(f"process {s.process_id} waited {s.timeout:g} s for process 0 at {s.coordinator}: "
                               f"{last or 'no answer'}", 1)
        try:
            conn = socket.create_connection((s.host, s.port), timeout=min(left, 5.0))
        except OSError as e:
            last = (e.strerror or str(e) or type(e).__name__).lower()
            time.sleep(min(0.2, max(0.0, deadline - time.monotonic())))
            continue
        break
    try:
        _send(conn, {"process_id": s.process_id, "processes": s.processes, "what": what})
        # process 0 answers once every process is in, within its timeout from when it began to listen
        answer = _receive(conn, time.monotonic() + s.timeout + 2.0, f"the process at {s.coordinator}")
    except TimeoutError:
        conn.close()
        raise ProcessError(f"process {s.process_id} connected to {s.coordinator} but had no answer within "
                           f"{s.timeout:g} s (is it tracklab's process 0?)", 1) from None
    except (ConnectionError, OSError) as e:
        conn.close()
        raise ProcessError(f"process {s.process_id}: {e}", 1) from None
    if not answer.get("ok"):
        conn.close()
        status = answer.get("status")
        raise ProcessError(str(answer.get("why") or "process 0 refused the run"), status if status in (1, 2) else 1)
    return Meeting(s, {0: conn})


def agree(s: Settings, what: dict) -> Meeting:
    """Meet every other process before JAX connects (see the module's doc); ProcessError in one
    line for a process that never comes or runs something else."""
    what = digest(what)
    return _meet_as_coordinator(s, what) if s.process_id == 0 else _meet_as_peer(s, what)


def start(s: Settings | None, what: dict | None = None) -> Meeting | None:
    """Join a run of several processes through ``jax.distributed``, once every process is known
    to run ``what`` (``agree``); returns the meeting ``finish`` ends. ``s`` None: one process,
    or under Slurm or Open MPI with more than one task (JAX finds the settings itself; the
    processes are not met first)."""
    if s is None and cluster_size() == 1:
        return None
    meeting = agree(s, what or {}) if s is not None else None
    import jax

    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    timeout = int(max(1, round(s.timeout if s is not None else TIMEOUT_S)))
    if s is not None:
        meeting.watch()
        jax.distributed.initialize(s.coordinator, num_processes=s.processes, process_id=s.process_id,
                                   initialization_timeout=timeout)
        meeting.started.set()
    else:
        jax.distributed.initialize(initialization_timeout=timeout)
    return meeting


def finish(meeting: Meeting | None, status: int = 0) -> tuple[int, str] | None:
    """This process's end (``status``: its exit status so far). The processes meet once more
    (see the module's doc) and, when all are there, leave ``jax.distributed`` together: None.
    Otherwise (another process ended first, or this one failed) JAX's shutdown, which would wait
    for the missing ones, is skipped and the caller ends the process with ``os._exit``: returns
    the exit status and a line to print ("" when there is nothing to add).

    The peers say they are done and wait for process 0; process 0 waits for every peer (within
    the timeout), checks that none has gone since, and then tells them all whether they leave
    JAX's runtime together or each on its own (a peer gone: its barrier would wait forever)."""
    if meeting is None:
        return None
    s = meeting.settings
    meeting.ending.set()
    if status != 0:
        for conn in meeting.peers.values():
            _answer(conn, {"failed": status}, close=False)
        until = time.monotonic() + min(5.0, s.timeout)  # the others stop when they read it: a moment for them to
        for event in meeting.done.values():  # read it, before JAX's service is gone with this process
            event.wait(max(0.0, until - time.monotonic()))
        return status, ""
    if s.process_id != 0:
        _answer(meeting.peers[0], {"done": True}, close=False)
        meeting.done[0].wait(10 * s.timeout)
        together = 0 not in meeting.gone and meeting.done[0].is_set() and meeting.last.get(0, {}).get("together")
        meeting.peers[0].close()
        if together:
            import jax

            jax.distributed.shutdown()
            return None
        if 0 in meeting.last:  # process 0 ended, with another process gone
            return 0, ""
        return 1, f"error: process 0 at {s.coordinator} ended before the end of the run (see its own output)"
    deadline = time.monotonic() + s.timeout
    for event in meeting.done.values():
        event.wait(max(0.0, deadline - time.monotonic()))
    gone = sorted(pid for pid in meeting.peers
                  if pid in meeting.gone or pid in meeting.closed or not meeting.done[pid].is_set())
    for conn in meeting.peers.values():
        _answer(conn, {"done": True, "together": not gone})
    if not gone:
        import jax

        jax.distributed.shutdown()
        return None
    # every exchange of sums is behind process 0 here: what it wrote is whole
    return 0, (f"note: process{'es' if len(gone) > 1 else ''} {', '.join(map(str, gone))} of {s.processes} ended "
               f"before the end, after the last exchange of results: the results are complete")


_RUNTIME_NOISE = re.compile(rb"^(\s*$|[IWEF]\d{4} |\*\*\* |\s+@\s+0x|\[Gloo\]|Additional GRPC error|:UNKNOWN:|RPC: /)")


def quiet_runtime_logs():
    """Keep the log lines of JAX's multi-process runtime and its collectives off the terminal
    (the command line's choice: each fault is said in one line of tracklab's). Python keeps
    writing to standard output and error as before; what the C++ runtime writes to them goes
    through a filter that drops its log lines and stack traces and passes on anything else."""
    import sys

    sys.stdout = _filtered(1, sys.stdout)
    sys.stderr = _filtered(2, sys.stderr)


def _filtered(fd: int, stream):
    """A stream on a copy of ``fd`` for Python; ``fd`` itself now goes through ``_forward``."""
    stream.flush()
    terminal = os.dup(fd)
    read, write = os.pipe()
    os.dup2(write, fd)
    os.close(write)
    threading.Thread(target=_forward, args=(read, terminal), daemon=True, name=f"tracklab-runtime-{fd}").start()
    return open(terminal, "w", buffering=1, encoding=stream.encoding, errors="backslashreplace", closefd=False)


def _forward(read: int, terminal: int):
    with open(read, "rb", buffering=0) as pipe:
        for line in pipe:
            if not _RUNTIME_NOISE.match(line):
                os.write(terminal, line)


def writes() -> bool:
    """Whether this process writes results and prints them: process 0 of a multi-process run,
    or the only one."""
    import jax

    return jax.process_index() == 0
