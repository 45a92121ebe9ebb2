"""``python -m tests.killhook ARGS``: ``python -m pipeline ARGS`` that SIGKILLs itself at a file-system event.

For the stages whose writes all come within a few milliseconds (``eval``'s report, ``export``'s model
folder), where watching the files from outside cannot land a kill between two of them. An event is a
file opened for writing, a rename or a folder removal inside the folder ``KILL_UNDER`` (not, say, a font
cache a library writes on its first run), named ``kind path`` with the path relative to that folder
and the random part of a temporary name dropped (``write ./m/.model.json.tmp``).

- ``EVENTS_FILE``: one line per event, as they happen (a reference run lists the kill points);
- ``KILL_EVENT`` and ``KILL_OCCURRENCE`` (1-based): SIGKILL the process just before that occurrence of
  that event, none of it done. By name, not by position: what a killed run left (a temporary folder to
  remove, a folder already moved) may add or remove events before it in the next run.
"""
from __future__ import annotations

import builtins
import io
import os
import re
import runpy
import shutil
import signal
import sys

TEMPORARY = re.compile(r"\.[A-Za-z0-9_]{8}\.tmp$")     # atomic writes' .NAME.<random>.tmp


def install(under: str, log: str | None, kill_event: str | None, kill_occurrence: int) -> None:
    out = builtins.open(log, "w", buffering=1) if log else None    # opened before the hook: not an event
    under = os.path.abspath(under)
    seen: dict[str, int] = {}

    def event(kind: str, path) -> None:
        if not isinstance(path, (str, os.PathLike)):
            return                                  # a file descriptor: not a file the stage names
        path = os.path.abspath(os.fspath(path))
        if not path.startswith(under + os.sep):
            return
        name = f"{kind} ./{TEMPORARY.sub('.tmp', os.path.relpath(path, under))}"
        seen[name] = seen.get(name, 0) + 1
        if out is not None:
            out.write(name + "\n")
        if name == kill_event and seen[name] == kill_occurrence:
            os.kill(os.getpid(), signal.SIGKILL)

    real_open, real_replace, real_rename, real_rmtree = builtins.open, os.replace, os.rename, shutil.rmtree

    def opener(file, mode="r", *args, **kwargs):
        if any(c in mode for c in "wax+"):
            event("write", file)
        return real_open(file, mode, *args, **kwargs)

    def replace(src, dst, *args, **kwargs):
        event("rename", dst)
        return real_replace(src, dst, *args, **kwargs)

    def rename(src, dst, *args, **kwargs):
        event("rename", dst)
        return real_rename(src, dst, *args, **kwargs)

    def rmtree(path, *args, **kwargs):
        event("remove", path)          # whether or not it exists: the same calls in every run
        return real_rmtree(path, *args, **kwargs)

    builtins.open = io.open = opener
    os.replace, os.rename, shutil.rmtree = replace, rename, rmtree


if __name__ == "__main__":
    install(os.environ["KILL_UNDER"], os.environ.get("EVENTS_FILE"), os.environ.get("KILL_EVENT"),
            int(os.environ.get("KILL_OCCURRENCE", "1")))
    sys.argv = ["pipeline", *sys.argv[1:]]
    runpy.run_module("pipeline", run_name="__main__", alter_sys=True)
