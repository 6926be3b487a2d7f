"""SUMO in its own process, working ahead of the swarms: the two cores used at once.

libsumo holds Python's global interpreter lock while it steps, so SUMO and the swarms cannot
overlap in one process; and the swarms' work between two SUMO steps evicts SUMO's data from the
CPU caches (at city scale SUMO stepped 20% slower beside eight swarms). Here a forked child runs
:meth:`SumoTraffic.maps_here` (SUMO, reads, the observation model, incidents) and sends each map
with the snapshots behind it through a pipe (and each snapshot of the warm-up as it is read: a
long warm-up is never held twice, in the child and in one message); while the swarms decide on
``T^k`` the child already simulates the next step. The maps are the very arrays the same source
computes in one process, so results are identical.

Ending: the child sends ``end`` with the observation model, the stage timer, the applied
incidents and the error that stopped it (a :class:`UserError` on bad input, a
:class:`SumoRunError` mid-run), which the parent raises where the in-process source would. When
the parent stops early (Ctrl-C, a failed swarm), it asks the child to stop, keeps only the
snapshots of the maps it used, and takes the model of the child's last snapshot. The child
ignores Ctrl-C (the parent decides) and dies with the parent, even by ``kill -9``.
A child that dies without its end state (SUMO crashed) is named by the signal that ended it:
before the window's first step an error quoting SUMO's last error, later a partial run whose
MFD model is that of the maps it sent.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import pickle
import re
import shutil
import signal
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from twin.errors import UserError
from twin.processes import STOP_ASKED, exit_with_parent, peak_memory_mb
from twin.sumo.outputs import MESSAGES_NAME
from twin.sumo.session import AGGREGATE_AFTER
from twin.timing import StageTimer


class WorksAhead(Protocol):
    """What the child runs and the parent fills in: the live SUMO source."""

    snapshots: list
    vehicles_seen: list[int]
    detectors: list
    detector_readings: list
    error: str | None
    model: Any
    scenario: Any
    output_dir: Path | None  # SUMO's output folder in the run folder, if the run has one
    timer: StageTimer
    read_seconds: float
    separate_process: bool
    defer_close: bool
    _truth: np.ndarray | None
    _incidents: list[dict[str, Any]] | None
    process_peak_mb: float | None

    def maps_here(self, warmup_too: bool = False) -> Iterator[np.ndarray | None]: ...

    def truth_map(self) -> np.ndarray | None: ...

    def incidents_info(self) -> list[dict[str, Any]]: ...

    def close_deferred(self) -> None: ...

    def model_after(self, snapshots: list) -> Any: ...


#: The SUMO children alive now: killed at the interpreter's exit, before multiprocessing joins
#: them (a child leaves stops to its parent, so multiprocessing's SIGTERM does not end it, and
#: one blocked sending a large map to a parent that no longer reads would be waited for
#: forever: an env left open when its script ends).
_LIVE: set = set()
_KILL_AT_EXIT: list[bool] = []  # registered once, after multiprocessing's own exit function


def _kill_live_children() -> None:
    for child in list(_LIVE):
        with contextlib.suppress(Exception):
            child.kill()
            child.join(timeout=5)


def maps_from_child(source: WorksAhead) -> Iterator[np.ndarray]:
    """The source's maps computed in a forked child process (see the module docstring)."""
    if not _KILL_AT_EXIT:
        import atexit  # registered after multiprocessing's exit function: runs before it

        atexit.register(_kill_live_children)
        _KILL_AT_EXIT.append(True)
    context = multiprocessing.get_context("fork")
    here, there = context.Pipe(duplex=True)
    messages = _messages_file()  # SUMO's stderr in the child: kept out of twin's lines
    child = context.Process(
        target=_produce, args=(source, there, os.getpid(), messages), name="twin-sumo",
        daemon=True,
    )  # fmt: skip
    source.snapshots, source.vehicles_seen, source.error = [], [], None
    source.process_peak_mb = None  # told by the child as it ends
    source.detector_readings = []
    source.timer, source._truth, source._incidents = StageTimer(), None, None
    if sys.stdout is not None:  # else the child writes what this process had not into its
        with contextlib.suppress(Exception):  # messages (None: stdout closed)
            sys.stdout.flush()
    child.start()
    _LIVE.add(child)
    there.close()
    ended = False
    try:
        while True:
            message = here.recv()
            if message[0] == "warm-up":
                _, snapshots, seen, _ = message
                source.snapshots.extend(snapshots)
                source.vehicles_seen.extend(seen)
                if STOP_ASKED.is_set():  # asked to stop after the current step before the
                    raise KeyboardInterrupt  # first: nothing to keep, stop now (a scheduler's
                    # grace period is shorter than a long warm-up)
            elif message[0] == "map":
                _, importance, truth, snapshots, seen, (detectors, readings) = message
                source.snapshots.extend(snapshots)
                source.vehicles_seen.extend(seen)
                source.detectors = detectors
                source.detector_readings.extend(readings)
                source._truth = truth
                yield importance
            else:
                ended = True
                _take_end(source, message)
                if message[1] is not None:
                    raise message[1]
                return
    except EOFError:  # the child died without a word (killed, or SUMO crashed)
        child.join(timeout=30)  # (the model of its maps is made by _stop, below)
        last = _last_error(messages)
        death = how_it_ended(child.exitcode)
        if not any(k >= 1 for k, *_ in source.snapshots):  # no step to keep: no partial run,
            said = f" (its last error: {last})" if last else ""  # and no folder to name
            fix = (
                "give it more memory, or less to simulate (a shorter warm-up, less demand)"
                if child.exitcode == -signal.SIGKILL
                else "run SUMO alone on the same files to see where it fails"
            )
            messages.unlink(missing_ok=True)  # a refused run keeps no folder to name it in
            raise UserError(
                f"SUMO {death} before the first step of scenario {source.scenario.name}{said}; "
                f"{fix}"
            ) from None
        kept = _keep_messages(source, messages)
        source.error = f"SUMO {death}" + (f"; its last words are in {kept}" if kept else "")
        raise RuntimeError(source.error) from None
    except KeyboardInterrupt:  # stop at once: SUMO may be deep in a long advance (a warm-up)
        child.kill()
        ended = True
        raise
    finally:
        if not ended:
            ended = _stop(source, here, child)
        here.close()
        child.join(timeout=None if ended else 30)  # after its end state: SUMO closing
        if child.is_alive():
            child.kill()
            child.join()
        _LIVE.discard(child)
        _keep_messages(source, messages)


def how_it_ended(exitcode: int | None) -> str:
    """How SUMO's process ended, from its exit code (negative: the signal that ended it)."""
    if exitcode is None:
        return "stopped answering"
    if exitcode >= 0:
        return f"ended unexpectedly (exit code {exitcode})"
    number = -exitcode
    try:
        name = f"{signal.Signals(number).name}, {signal.strsignal(number)}"
    except ValueError:
        name = f"signal {number}"
    if number == signal.SIGKILL:
        return f"was killed ({name}: by the system when memory ran out, or by a user)"
    return f"crashed ({name})"


def _stop(source: WorksAhead, here, child) -> bool:
    """Ask the child to stop after its current snapshot (it may have ended already) and take
    its end state (False when it died without one); the snapshots of maps the parent never
    used are dropped."""
    used = len(source.snapshots)
    got_end = False
    with contextlib.suppress(OSError):
        here.send("stop")
    try:
        while True:
            message = here.recv()
            if message[0] == "end":
                _take_end(source, message)
                got_end = True
                break
    except (EOFError, OSError):
        child.kill()
    del source.snapshots[used:]  # one vehicle count per snapshot
    del source.vehicles_seen[used:]
    ahead = source.model is not None and source.model.observed > len(source.snapshots)
    if ahead or not got_end:  # the child's MFD saw snapshots the run never used (sent, or not
        source.model = source.model_after(source.snapshots)  # yet), or it sent none
    last = source.snapshots[-1][0] if source.snapshots else -1
    source.detector_readings[:] = [r for r in source.detector_readings if r[0] <= last]
    return got_end


def _take_end(source: WorksAhead, message) -> None:
    _, _, snapshots, seen, model, timer, read_seconds, error, incidents, det, notices, peak = (
        message
    )
    from twin.notices import notify

    for line in notices:  # said in the child (its stderr is SUMO's messages file)
        notify(line)
    source.snapshots.extend(snapshots)
    source.vehicles_seen.extend(seen)
    source.detectors = det[0]
    source.detector_readings.extend(det[1])
    source.model, source.timer, source.read_seconds = model, timer, read_seconds
    source.error, source._incidents = error, incidents
    source.process_peak_mb = peak  # SUMO's process, as it measured itself


def _messages_file() -> Path:
    """A fresh temporary file for SUMO's messages (the child's stderr)."""
    from twin.resources import scratch_dir

    fd, name = tempfile.mkstemp(prefix="twin-sumo-", suffix=".log", dir=scratch_dir())
    os.close(fd)
    return Path(name)


def _last_error(path: Path) -> str:
    """SUMO's last error line in its messages file ``path`` (without "Error: "), or ""."""
    last = ""
    with contextlib.suppress(OSError), open(path, errors="replace") as fh:
        for line in fh:
            if line.startswith("Error:"):
                last = line[len("Error:") :].strip()[:200]
    return last


def _keep_messages(source: WorksAhead, path: Path) -> Path | None:
    """SUMO's messages once its process ended: moved to ``RUN/sumo/sumo-messages.log`` when
    there are any and the run has a folder (the path returned), one notice for its errors;
    the temporary file is removed. A second call does nothing."""
    if not path.exists():
        return None
    errors, first, ignored, first_ignored = 0, "", 0, ""
    with contextlib.suppress(OSError), open(path, errors="replace") as fh:
        for line in fh:
            if line.startswith("Error:"):
                errors += 1
                first = first or line[len("Error:") :].strip()
            elif line.startswith("Warning:") and IGNORED.search(line):
                total = AGGREGATED.match(line)  # past 20 of a kind: "N total messages ..."
                ignored += int(total[1]) - AGGREGATE_AFTER if total else 1
                first_ignored = first_ignored or line[len("Warning:") :].strip()
    kept = None
    if path.stat().st_size and source.output_dir is not None:
        with contextlib.suppress(OSError):
            Path(source.output_dir).mkdir(parents=True, exist_ok=True)
            # copied, not moved: a run's file like its others (mkstemp's is private)
            kept = shutil.copyfile(path, Path(source.output_dir) / MESSAGES_NAME)
    path.unlink(missing_ok=True)
    _say_sumo_errors(source, errors, first, None if kept is None else str(kept))
    _say_sumo_errors(source, ignored, first_ignored, None if kept is None else str(kept), True)
    return None if kept is None else Path(kept)


def _produce(source: WorksAhead, conn, parent: int, messages: Path) -> None:
    """The child: every map with the snapshots behind it, then ``end``; SUMO's messages
    (this process's stderr) into the file ``messages``."""
    exit_with_parent(parent, ignore_sigint=True)
    fd = os.open(messages, os.O_WRONLY | os.O_APPEND)
    os.dup2(fd, 2)
    os.dup2(fd, 1)  # what SUMO prints (a verbose sumocfg, its statistics) is its message too
    if fd > 2:  # (with stdout or stderr closed, the file took its number)
        os.close(fd)
    source.separate_process = False
    source.messages_kept = True
    source.defer_close = True  # SUMO is closed after the end state is sent (below)
    failure: BaseException | None = None
    from twin.notices import drop_notices, hold_notices

    drop_notices()  # the parent's held lines stay the parent's; this process's go with its end
    hold_notices()
    maps = source.maps_here(warmup_too=True)
    try:
        for importance in maps:
            if importance is None:  # a snapshot of the warm-up
                conn.send(("warm-up", *_unsent(source)))
            else:
                conn.send(("map", importance, source.truth_map(), *_unsent(source)))
            if conn.poll() and conn.recv() == "stop":
                break
    except BaseException as exc:  # sent to the parent, which raises it
        failure = exc if _picklable(exc) else RuntimeError(f"{type(exc).__name__}: {exc}")
    # The end state goes to the parent before SUMO is closed: what the run keeps (the MFD
    # model, stage times, incidents, detector readings) never depends on SUMO's teardown, which
    # can crash in a process forked from one that ran libsumo before. The parent waits for this
    # process to end before it collects SUMO's configured outputs, written when SUMO closes.
    snapshots, seen, detectors = _unsent(source)
    try:
        conn.send(
            (
                "end",
                failure,
                snapshots,
                seen,
                source.model,
                source.timer,
                source.read_seconds,
                source.error,
                source.incidents_info(),
                detectors,
                drop_notices(),
                peak_memory_mb(),
            )
        )
    except (BrokenPipeError, OSError):
        pass
    finally:
        with contextlib.suppress(BaseException):
            maps.close()  # ends the maps; SUMO stays open until it is closed here:
        with contextlib.suppress(BaseException):
            source.close_deferred()  # SUMO writes out its configured outputs as it closes
        conn.close()
        os._exit(0)  # no atexit handlers of the parent's modules in the child


#: A warning of SUMO's that it ignored something of the scenario ("Route file should be sorted
#: by departure time, ignoring 'f1'!", "Unknown vehicle class 'x' ignored."): said in a notice,
#: as its errors are.
IGNORED = re.compile(r"\bignor(ed|ing)\b", re.IGNORECASE)
#: SUMO's count of the warnings of a kind it stopped writing (``--aggregate-warnings``).
AGGREGATED = re.compile(r"Warning: (\d+) total messages of type")


def _say_sumo_errors(
    source: WorksAhead, count: int, first: str, kept: str | None, warnings: bool = False
) -> None:
    """One notice for SUMO's errors while it ran, or (``warnings``) for its warnings that it
    ignored part of the scenario (none: nothing said)."""
    if not count:
        return
    from twin.boundary import notify

    where = f"all in {kept}" if kept else "not kept: the run has no folder"
    plural = "s" * (count != 1)
    said = (
        f"SUMO warned that it ignored something of the scenario ({count} warning{plural}; "
        if warnings
        else f"SUMO reported {count} error{plural} while loading or running, which it did not "
        "stop for ("
    )
    notify(f"twin: notice: {source.scenario.name}: {said}first: {first[:160]}); {where}")


def _unsent(source: WorksAhead) -> tuple[list, list[int], tuple[list, list]]:
    """The snapshots, vehicle counts and detector readings the child has not sent yet, taken
    out of its lists (the parent keeps them: the child holds each only until it is sent)."""
    snapshots, seen = source.snapshots[:], source.vehicles_seen[:]
    readings = source.detector_readings[:]
    source.snapshots.clear()
    source.vehicles_seen.clear()
    source.detector_readings.clear()
    return snapshots, seen, (source.detectors, readings)


def _picklable(exc: BaseException) -> bool:
    try:
        pickle.loads(pickle.dumps(exc))
    except Exception:
        return False
    return True
