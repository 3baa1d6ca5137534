"""The launcher: the hub, one process per operator replica, restarts, recording, clean shutdown.

The graph is done when every source process has exited 0 (its stream is fully acked); the other
processes are then stopped with SIGTERM. Ctrl-C or SIGTERM stops the graph at any time within
`STOP_AFTER_SIGNAL_S`, the log closed and readable; a second one kills what is left at once. A
recorded run whose log lacks something (`recording.py`) exits with EXIT_INCOMPLETE and a line
naming the channels and counts. A process that crashes
is restarted with exponential backoff up to `max_restarts` times; after that, or when it exits with
the runtime's configuration-error code, the whole graph stops and the launcher exits non-zero.

The launcher answers on the bus: what it runs (`_graph`: name, file, hub, operators), so a command
finds the graph without being told its file, and `umad op start|stop` (`_ctl/_launcher`), each with
what it did. Operators run at a lower CPU priority than the hub and the launcher: on a machine the
graph keeps busy, the bus and the commands that steer it still get the CPU when they need it.
"""

from __future__ import annotations

import json
import logging
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections import defaultdict, deque
from pathlib import Path

import zenoh

from umad_common.dataflow.api.exit_codes import EXIT_CONFIG, EXIT_INCOMPLETE, EXIT_STOPPED
from umad_common.dataflow.api.graph import Graph, GraphError, load_graph
from umad_common.dataflow.launch.access import access_control_file
from umad_common.dataflow.launch.replicas import OPERATOR_NICENESS, Replica, process_cpu_s, replica_command
from umad_common.dataflow.launch.report import ProgressLine, summary_table
from umad_common.dataflow.record.mcap_log import describe_loss
from umad_common.dataflow.record.recorder import Recording
from umad_common.dataflow.transport.bus import HubJoinError, Keys, answer, cleanup_stale_shm, close_session, open_client
from umad_common.dataflow.transport.planes.ring import SWEPT_BY_LAUNCHER, remove_stale_rings

log = logging.getLogger("umad.launch")
STOP_GRACE_S = 10.0  # a graph that finished: its idle replicas get this long to exit on SIGTERM
STOP_AFTER_SIGNAL_S = 4.0  # Ctrl-C / SIGTERM: replicas killed, log closed and hub gone within this
RECORDER_CLOSE_S = 1.0  # after a signal: what the recorder received by then is written, the rest is lost
RECORDER_DRAIN_S = 30.0  # a finished graph: the recorder writes what is still queued (acked frames: little)
RING_GRACE_S = 30.0  # a replica's payload ring outlives it this long, for the recorder
HUB_CONNECT_TIMEOUT_S = 60.0
HUB_MIN_LIFETIME_S = 5.0  # a hub that dies sooner after its start counts as failing to start


class Launcher:
    def __init__(
        self,
        graph: Graph,
        graph_file: Path,
        *,
        sets: list[str] | None = None,
        record: Path | None = None,
        max_frames: int | None = None,
        hub: str | None = None,
        replay_log: Path | None = None,
        allow_truncated: bool = False,
        max_restarts: int = 3,
        quiet: bool = False,
    ):
        self.quiet = quiet
        self.hub_replica: Replica | None = None
        self.access_file: Path | None = None  # the hub's access control, removed when the hub stops for good
        self.hub_cpu_s: float | None = None  # the hub process's CPU over its life, read as it is stopped
        self.tails: dict[str, deque[str]] = defaultdict(lambda: deque(maxlen=30))
        self.graph = graph
        self.graph_file = Path(graph_file)
        self.hub = hub or graph.spec.hub
        self.record = record
        self.max_restarts = max_restarts
        self.stats: dict[str, dict] = {}
        self._stop = threading.Event()
        self._print_lock = threading.Lock()
        self.sets = sets or []
        self.keys = Keys(graph.name)
        self.recording: Recording | None = None
        self._hurry = threading.Event()  # a second signal: kill, do not wait
        self._exited: dict[int, float] = {}  # pid -> when a replica exited, until its ring is swept
        self._control: queue.Queue = queue.Queue()
        sources = set(graph.sources())
        self.replicas: list[Replica] = []
        for spec in graph.spec.operators:
            for index in range(spec.replicas):
                cmd = replica_command(graph, self.graph_file, spec, index, hub=self.hub, sets=self.sets)
                if spec.id in sources:
                    if max_frames is not None:
                        cmd += ["--max-frames", str(max_frames)]
                    if replay_log is not None:
                        cmd += ["--replay-log", str(replay_log)]
                        if allow_truncated:
                            cmd.append("--allow-truncated")
                self.replicas.append(Replica(op_id=spec.id, index=index, command=cmd, is_source=spec.id in sources))

    def _hub_command(self) -> list[str]:
        """The hub's command line. A graph's access control goes to the hub in a file only this user
        may read (`access_control_file`), not on the command line, which every local user sees."""
        cmd = [sys.executable, "-m", "umad_common.dataflow.transport.hub", "--listen", self.hub]
        tls = self.graph.tls_config()
        if tls is not None:
            cmd += ["--root-ca", tls.root_ca, "--cert", tls.cert, "--key", tls.key]
        if self.graph.spec.security is not None:
            self.access_file = access_control_file(self.graph)
            cmd += ["--access-control", str(self.access_file)]
        return cmd

    # -- processes ----------------------------------------------------------------------------------

    def _say(self, name: str, line: str) -> None:
        self.tails[name].append(line.rstrip())
        if self.quiet:
            log.debug("[%s] %s", name, line.rstrip())
            return
        with self._print_lock:
            sys.stdout.write(f"[{name}] {line}" if line.endswith("\n") else f"[{name}] {line}\n")
            sys.stdout.flush()

    def _spawn(self, rep: Replica, niceness: int = OPERATOR_NICENESS) -> None:
        env = {**os.environ, "PYTHONUNBUFFERED": "1", SWEPT_BY_LAUNCHER: "1"}
        rep.started_at = time.monotonic()
        try:
            rep.proc = subprocess.Popen(
                rep.command,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
                bufsize=1,
                start_new_session=True,
                env=env,
            )
        except OSError as exc:  # e.g. an operator's `python:` interpreter that does not exist
            self._say(rep.name, f"cannot start {rep.command[0]}: {exc}")
            rep.proc, rep.failed, rep.restart_at = None, True, None
            return
        if niceness:  # before the interpreter starts its threads, which inherit it
            try:
                os.setpriority(os.PRIO_PROCESS, rep.proc.pid, os.getpriority(os.PRIO_PROCESS, 0) + niceness)
            except OSError:
                pass  # the replica already exited; _watch reports it
        reader = threading.Thread(target=self._pump, args=(rep, rep.proc), daemon=True)
        reader.start()
        rep.readers.append(reader)
        rep.restart_at = None

    def _pump(self, rep: Replica, proc: subprocess.Popen) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            self._say(rep.name, line)

    def _watch(self, rep: Replica) -> None:
        """Check one replica: finished, crashed (schedule a restart), or failed for good."""
        if rep.proc is None or rep.finished or rep.failed:
            if rep.restart_at is not None and time.monotonic() >= rep.restart_at:
                self._spawn(rep)
            return
        code = rep.proc.poll()
        if code is None:
            return
        self._exited[rep.proc.pid] = time.monotonic()
        if code == 0:  # a source whose stream is acked, or an operator stopped on purpose
            rep.finished = True
            return
        if code == EXIT_CONFIG:
            self._say(rep.name, "failed on its configuration; not restarting")
            rep.failed = True
            return
        if rep.restarts >= self.max_restarts:
            self._say(rep.name, f"exited with {code} after {rep.restarts} restarts; giving up")
            rep.failed = True
            return
        delay = 0.5 * 2**rep.restarts
        rep.restarts += 1
        self._say(rep.name, f"exited with {code}; restart {rep.restarts}/{self.max_restarts} in {delay:.1f}s")
        rep.proc = None
        rep.restart_at = time.monotonic() + delay

    def _watch_hub(self) -> bool:
        """The hub is restarted whenever it dies (clients reconnect on their own), with backoff; a
        hub that dies within seconds of each of `max_restarts` starts (say, its port is taken)
        fails the graph. Returns False then."""
        hub = self.hub_replica
        if hub is None or hub.proc is None or hub.proc.poll() is None:
            return True
        now = time.monotonic()
        if hub.restart_at is None:
            lived = now - hub.started_at
            hub.restarts = hub.restarts + 1 if lived < HUB_MIN_LIFETIME_S else 1
            if hub.restarts > self.max_restarts:
                self._say("hub", f"exited with {hub.proc.returncode} {hub.restarts - 1} times in a row at start")
                return False
            delay = 0.5 * 2 ** (hub.restarts - 1)
            self._say("hub", f"exited with {hub.proc.returncode}; restarting in {delay:.1f}s")
            hub.restart_at = now + delay
        if now >= hub.restart_at:
            hub.restart_at = None
            self._spawn(hub, niceness=0)
        return True

    def _stop_hub(self, grace_s: float) -> None:
        if self.hub_replica is not None and self.hub_replica.proc is not None:
            self.hub_cpu_s = process_cpu_s(self.hub_replica.proc.pid)
            self.hub_replica.proc.send_signal(signal.SIGTERM)
            try:
                self.hub_replica.proc.wait(timeout=0 if self._hurry.is_set() else grace_s)
            except subprocess.TimeoutExpired:
                self.hub_replica.proc.kill()
                self.hub_replica.proc.wait()
        if self.access_file is not None:
            self.access_file.unlink(missing_ok=True)
        cleanup_stale_shm()

    def _signal_all(self, sig: signal.Signals) -> None:
        """Send `sig` to every running replica: SIGTERM to the replica, SIGKILL to its process group.
        Consumers first: an operator stops before the producers it waits on leave the graph, so no
        frame in flight is completed without a producer's output (operators started by `umad op
        start` from another graph file, unknown to this one, count as consumers)."""
        rank = {op_id: i for i, op_id in enumerate(self.graph.topological_order())}
        for rep in sorted(self.replicas, key=lambda r: -rank.get(r.op_id, len(rank))):
            if rep.proc is not None and rep.proc.poll() is None:
                try:
                    if sig == signal.SIGKILL:
                        os.killpg(rep.proc.pid, signal.SIGKILL)
                    else:
                        rep.proc.send_signal(sig)
                except ProcessLookupError:
                    pass

    def _wait_all(self, deadline: float) -> None:
        """Wait for every replica until `deadline` (or a second signal), then kill what is left."""
        for rep in self.replicas:
            if rep.proc is None:
                continue
            while rep.proc.poll() is None and not self._hurry.is_set() and time.monotonic() < deadline:
                time.sleep(0.05)
            if rep.proc.poll() is None:
                self._say(rep.name, "did not stop after SIGTERM; killing")
                try:
                    os.killpg(rep.proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                rep.proc.wait()
        for rep in self.replicas:
            for reader in rep.readers:
                reader.join(timeout=0.2 if self._stop.is_set() else 1.0)

    # -- the run ------------------------------------------------------------------------------------

    def run(self) -> int:
        """Run the graph until its sources finish, an operator fails for good, or SIGINT/SIGTERM."""

        def on_signal(signum, _frame):
            if self._stop.is_set():  # the second one: nothing more is waited for
                self._hurry.set()
                self._signal_all(signal.SIGKILL)
                return
            log.info("stopping the graph (%s); again to kill it at once", signal.Signals(signum).name)
            self._stop.set()

        tls = self.graph.tls_config()
        try:
            taken = open_client(self.hub, tls, retry=False, timeout_s=HUB_CONNECT_TIMEOUT_S, shared_memory=False)
            listening = taken is not None
        except HubJoinError:  # a TLS hub that does not take our certificate
            taken, listening = None, True
        if listening:  # our hub could not listen there, and our replicas would join that one
            if taken is not None:
                close_session(taken)
            log.error(
                "a hub already listens at %s (another graph, or one that did not stop): stop it, or give "
                "this graph another `hub:` endpoint",
                self.hub,
            )
            return 1
        previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
        self.hub_replica = Replica(op_id="hub", index=0, command=self._hub_command(), is_source=False)
        self._spawn(self.hub_replica, niceness=0)
        refused = None
        try:
            hub = open_client(self.hub, tls, cancel=self._stop, timeout_s=HUB_CONNECT_TIMEOUT_S, shared_memory=False)
        except HubJoinError as exc:  # the hub's certificate and ours are not of one CA
            hub, refused = None, exc
        if hub is None:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
            self._stop_hub(grace_s=1.0)
            if refused is not None:
                log.error("%s", refused)
                return EXIT_CONFIG
            if self._stop.is_set():
                return EXIT_STOPPED
            log.error("no hub answered at %s within %.0fs", self.hub, HUB_CONNECT_TIMEOUT_S)
            return 1
        declared = []
        code = 1
        try:
            keys = self.keys
            declared.append(hub.declare_subscriber(f"{keys.root}/_stats/**", self._on_stats))
            declared.append(hub.declare_queryable(keys.control_all, self._on_command))
            declared.append(hub.declare_queryable(keys.graph_info, self._on_graph_info))
            if self.record:
                metadata = {"graph": self.graph_file.read_text(), "base_dir": str(self.graph.base_dir)}
                self.recording = Recording(hub, self.graph, self.record, {**metadata, "sets": json.dumps(self.sets)})
            for rep in self.replicas:
                self._spawn(rep)
            code = self._supervise()
            if code == 0 and self.recording is not None and not self.recording.drain(RECORDER_DRAIN_S):
                log.warning("the recorder did not catch up within %.0fs", RECORDER_DRAIN_S)
        finally:  # also when something above raised: no operator outlives the launcher
            code = self._shut_down(hub, declared, code)
            for sig, handler in previous.items():
                signal.signal(sig, handler)
            self._print_summary()
        return code

    def _shut_down(self, hub: zenoh.Session, declared: list, code: int) -> int:
        """Stop the replicas, close the log, stop the hub. After a signal all of it takes at most
        STOP_AFTER_SIGNAL_S at any load (replicas that do not exit in time are killed); a second
        signal kills at once. Returns the exit code, EXIT_INCOMPLETE for a finished graph whose log
        lacks something."""
        signalled = self._stop.is_set()
        started = time.monotonic()
        deadline = started + (STOP_AFTER_SIGNAL_S - 1.0 if signalled else STOP_GRACE_S)
        self._signal_all(signal.SIGTERM)
        if self.recording is not None:
            outcome = self.recording.close(RECORDER_CLOSE_S if signalled else RECORDER_DRAIN_S, stopped=signalled)
            log.info("recorded %d messages to %s", self.recording.count, self.record)
            loss = describe_loss(outcome)
            if loss and signalled:
                log.warning("the run was stopped; what was in flight is not in %s: %s", self.record, loss)
            elif loss:
                log.error("the recording %s is incomplete: %s", self.record, loss)
                code = EXIT_INCOMPLETE if code == 0 else code
        self._wait_all(deadline)
        for item in declared:
            item.undeclare()
        hub.close()
        self._stop_hub(grace_s=0.5 if signalled else STOP_GRACE_S)
        log.info("graph stopped in %.1f s", time.monotonic() - started)
        return code

    def _supervise(self) -> int:
        sources = [r for r in self.replicas if r.is_source]
        progress = ProgressLine()
        while not self._stop.is_set():
            if not self.quiet:
                line = progress.update([self.stats.get(f"{r.op_id}.r{r.index}") for r in sources])
                if line:
                    self._say("progress", line)
            self._apply_control()
            if not self._watch_hub():
                log.error("graph failed: the hub at %s cannot start", self.hub)
                return 1
            for rep in self.replicas:
                self._watch(rep)
            self._sweep_rings()
            if any(r.failed for r in self.replicas):
                failed = [r.name for r in self.replicas if r.failed]
                if self.quiet:
                    for name in failed:
                        sys.stderr.write("".join(f"[{name}] {line}\n" for line in self.tails[name]))
                log.error("graph failed: %s", ", ".join(failed))
                return 1
            if sources and all(r.finished for r in sources):
                log.info("all sources finished")
                return 0
            time.sleep(0.1)
        return EXIT_STOPPED

    def _sweep_rings(self) -> None:
        """Remove the payload rings of replicas that exited more than RING_GRACE_S ago. Until then
        the recorder, whose callbacks may lag behind on a busy machine, can still copy the payloads
        a replica published just before it exited (the replica itself leaves its ring to this)."""
        now = time.monotonic()
        recent = {pid for pid, when in self._exited.items() if now - when < RING_GRACE_S}
        if len(recent) < len(self._exited):
            remove_stale_rings(spare_pids=recent)
            if self.recording is not None:
                self.recording.sweep_gone_rings()
            self._exited = {pid: self._exited[pid] for pid in recent}

    def _running(self) -> list[str]:
        return sorted({r.op_id for r in list(self.replicas) if r.proc is not None and r.proc.poll() is None})

    def _on_graph_info(self, query: zenoh.Query) -> None:
        """What this launcher runs, for commands that were not told the graph file."""
        info = {
            "name": self.graph.name,
            "graph": str(self.graph_file.resolve()),
            "hub": self.hub,
            "operators": self._running(),
        }
        answer(query, self.keys.graph_info, info)

    def _on_command(self, query: zenoh.Query) -> None:
        """Every command to this graph is recorded (the log says what changed and when); those for
        the launcher (`umad op start|stop ID`) are applied on the supervisor thread and answered
        there. Commands for an operator are answered by its replicas."""
        key = str(query.key_expr)
        payload = query.payload.to_bytes() if query.payload else b""
        if self.recording is not None:
            self.recording.write_command(key, payload)
        if key == self.keys.launcher:
            self._control.put((payload, query))
        else:
            query.drop()

    def _apply_control(self) -> None:
        while not self._control.empty():
            payload, query = self._control.get()
            try:
                command = json.loads(payload)
                if "stop" in command:
                    outcome = self._stop_operator(str(command["stop"]))
                else:
                    outcome = self._start_operator(str(command["start"]), command.get("graph"))
            except (ValueError, KeyError, TypeError) as exc:
                outcome = {
                    "status": "refused",
                    "reason": f"expected {{'start'|'stop': ID}}, got {payload[:200]!r}: {exc}",
                }
            answer(query, self.keys.launcher, outcome)

    def _stop_operator(self, op_id: str) -> dict[str, str]:
        stopping = [r for r in self.replicas if r.op_id == op_id and r.proc and r.proc.poll() is None]
        if not stopping:
            return {"status": "refused", "reason": f"{op_id} is not running (running: {', '.join(self._running())})"}
        for rep in stopping:
            self._say(rep.name, "stopping on request")
            rep.proc.send_signal(signal.SIGTERM)
        return {"status": "applied", "message": f"stopping {op_id} ({len(stopping)} replicas)"}

    def _start_operator(self, op_id: str, graph_file: str | None) -> dict[str, str]:
        """Start `op_id` from `graph_file`, or from the launched graph's file read again (an
        operator added to it after launch)."""
        try:
            graph = load_graph(graph_file or self.graph_file)
            spec = graph.op(op_id)
        except GraphError as exc:
            log.error("cannot start %s: %s", op_id, exc)
            return {"status": "refused", "reason": str(exc)}
        self.replicas = [r for r in self.replicas if not (r.op_id == op_id and (r.finished or r.failed))]
        if any(r.op_id == op_id for r in self.replicas):
            return {"status": "refused", "reason": f"{op_id} is already running"}
        for index in range(spec.replicas):
            command = replica_command(
                graph, Path(graph_file or self.graph_file), spec, index, hub=self.hub, sets=self.sets
            )
            rep = Replica(op_id=op_id, index=index, command=command, is_source=False)
            self.replicas.append(rep)
            self._spawn(rep)
            self._say(rep.name, "started on request")
        return {"status": "applied", "message": f"started {op_id} ({spec.replicas} replicas)"}

    def _on_stats(self, sample: zenoh.Sample) -> None:
        """A replica's stats, taken only where the key names the replica the stats claim to be."""
        try:
            data = json.loads(sample.payload.to_bytes())
            if self.keys.sender(str(sample.key_expr), "_stats") == (data["op"], data["replica"]):
                self.stats[f"{data['op']}.{data['replica']}"] = data
        except (ValueError, KeyError, TypeError):
            pass

    def _print_summary(self) -> None:
        if not self.stats or self.quiet:
            return
        with self._print_lock:
            print(summary_table(self.stats), flush=True)
