"""Running avflow as a separate process: its progress to the algorithm's bar, Cancel as
SIGTERM, its one-line error as the algorithm's failure.

Nothing of avflow is imported here: QGIS's Python and the user's avflow environment stay
apart (a plugin that installs into QGIS's Python breaks one or the other).

avflow draws its progress bar only on a terminal, so on Linux and macOS its stderr is a
pseudo-terminal (``pty``) that this module reads; elsewhere the bar stays at "busy" and
only avflow's messages reach the log.
"""

import os
import re
import select
import shutil
import signal
import subprocess
import time

from qgis.core import QgsProcessingException

#: ``[####....] t =   12.50 / 400 s`` (a run) and ``12/21 members`` (ensembles, regions).
_TIME = re.compile(r"t =\s*([0-9.eE+-]+)\s*/\s*([0-9.eE+-]+)\s*s")
_COUNT = re.compile(r"\]\s*(\d+)/(\d+)\s")
#: avflow's own error line (exit code 2 for bad input, 1 for a failed run).
_ERROR = re.compile(r"^avflow: error: ")


def executable():
    """The avflow command: the provider's setting, else $AVFLOW_EXECUTABLE, else the PATH."""
    chosen = ""
    try:
        from processing.core.ProcessingConfig import ProcessingConfig

        from .provider import EXECUTABLE_SETTING

        chosen = ProcessingConfig.getSetting(EXECUTABLE_SETTING) or ""
    except Exception:  # a bare PyQGIS script without the Processing plugin's settings
        pass
    chosen = chosen or os.environ.get("AVFLOW_EXECUTABLE", "")
    if chosen:
        if not (os.path.isfile(chosen) and os.access(chosen, os.X_OK)):
            raise QgsProcessingException(
                f"avflow executable not found or not executable: {chosen} (Settings > "
                "Options > Processing > Providers > avflow)")
        return chosen
    found = shutil.which("avflow")
    if not found:
        raise QgsProcessingException(
            "avflow not found on the PATH: install it in its own environment (pip install "
            "avflow) and give its 'avflow' command in Settings > Options > Processing > "
            "Providers > avflow")
    return found


def _progress(text, feedback):
    """Set the bar from the last progress mark in ``text``."""
    for match in list(_TIME.finditer(text))[-1:]:
        t, end = float(match.group(1)), float(match.group(2))
        if end > 0:
            feedback.setProgress(min(100.0, 100.0 * t / end))
    for match in list(_COUNT.finditer(text))[-1:]:
        done, total = int(match.group(1)), int(match.group(2))
        if total > 0:
            feedback.setProgress(100.0 * done / total)


def run(args, feedback, cwd=None):
    """Run ``avflow ARGS``; returns its stdout lines. Progress goes to ``feedback``, every
    other line of stderr to the log; Cancel stops avflow (SIGTERM, then SIGKILL after 20 s)
    and raises "Cancelled: ..."; a failure raises avflow's error line."""
    command = [executable()] + [str(a) for a in args]
    feedback.pushCommandInfo(" ".join(_quote(c) for c in command))
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env.pop("PYTHONHOME", None)  # QGIS's own Python must not leak into avflow's
    env.pop("PYTHONPATH", None)
    master = slave = None
    try:
        import pty

        master, slave = pty.openpty()
        err_target = slave
    except (ImportError, OSError):
        err_target = subprocess.PIPE
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=err_target,
                            stdin=subprocess.DEVNULL, cwd=cwd, env=env,
                            start_new_session=True)
    if slave is not None:
        os.close(slave)
    err_fd = master if master is not None else proc.stderr.fileno()
    out_fd = proc.stdout.fileno()
    out_text, err_lines, pending = [], [], ""
    open_fds = {out_fd, err_fd}
    cancelled_at = None

    def take_err(chunk):
        nonlocal pending
        pending += chunk.replace("\r\n", "\n")
        *done, pending = pending.split("\n")
        for line in done:
            _line(line, feedback, err_lines)
        if "\r" in pending:  # a progress bar redrawn in place
            _progress(pending, feedback)
            pending = pending.rsplit("\r", 1)[-1]

    try:
        while open_fds:
            if feedback.isCanceled() and cancelled_at is None:
                cancelled_at = time.monotonic()
                feedback.pushInfo("Cancel: stopping avflow (it removes its temporary files)")
                _signal(proc, signal.SIGTERM)
            if cancelled_at is not None and time.monotonic() - cancelled_at > 20:
                _signal(proc, signal.SIGKILL)
            ready, _, _ = select.select(list(open_fds), [], [], 0.2)
            for fd in ready:
                try:
                    data = os.read(fd, 65536)
                except OSError:  # the pty's other end closed (EIO)
                    data = b""
                if not data:
                    open_fds.discard(fd)
                    continue
                text = data.decode("utf-8", "replace")
                if fd == out_fd:
                    out_text.append(text)
                else:
                    take_err(text)
            if proc.poll() is not None and not ready:
                # the process ended; drain what is left without blocking
                for fd in list(open_fds):
                    try:
                        while select.select([fd], [], [], 0.05)[0]:
                            data = os.read(fd, 65536)
                            if not data:
                                break
                            text = data.decode("utf-8", "replace")
                            (out_text.append(text) if fd == out_fd else take_err(text))
                    except OSError:
                        pass
                    open_fds.discard(fd)
        rc = proc.wait()
    finally:
        if proc.poll() is None:
            _signal(proc, signal.SIGKILL)
            proc.wait()
        if master is not None:
            os.close(master)
        proc.stdout.close()
    for line in pending.replace("\r", "\n").split("\n"):
        _line(line, feedback, err_lines)
    out_lines = [line for line in "".join(out_text).splitlines() if line.strip()]
    for line in out_lines:
        feedback.pushInfo(line)
    if cancelled_at is not None:
        # avflow writes to temporary names and renames: a stopped run leaves nothing
        raise QgsProcessingException("Cancelled: avflow stopped, nothing half-written was left")
    if rc != 0:
        errors = [l for l in err_lines if _ERROR.match(l)]
        message = (errors[-1] if errors else (err_lines[-1] if err_lines else
                   f"avflow {args[0]} failed (exit code {rc})"))
        raise QgsProcessingException(message)  # shown once, as the algorithm's failure
    feedback.setProgress(100)
    return out_lines


def _line(line, feedback, err_lines):
    line = line.rstrip()
    if "\r" in line:
        _progress(line, feedback)
        line = line.rsplit("\r", 1)[-1]
    if not line.strip() or _TIME.search(line) or _COUNT.search(line):
        _progress(line, feedback)
        return
    err_lines.append(line.strip())
    if _ERROR.match(line.strip()):
        return  # shown once, as the failure
    feedback.pushInfo(line.strip())


def _signal(proc, sig):
    try:
        os.killpg(proc.pid, sig)  # avflow and any worker it started
    except (ProcessLookupError, PermissionError, AttributeError):
        try:
            proc.send_signal(sig)
        except ProcessLookupError:
            pass


def _quote(text):
    return f"'{text}'" if (" " in text or not text) else text


def written(lines):
    """Paths named on avflow's ``wrote A, B`` lines."""
    paths = []
    for line in lines:
        if line.startswith("wrote "):
            for part in line[len("wrote "):].split(", "):
                part = part.strip().split(" and ")[0].strip()
                if part:
                    paths.append(part)
    return paths
