"""Run a flow's main under a Python audit hook (PEP 578) that watches one folder:

    python -m tests.flows.audit_writes <folder> <log> <module> [args...]

Every operation that would change something under ``<folder>`` - an ``open`` for writing (any of ``O_WRONLY``,
``O_RDWR``, ``O_CREAT``, ``O_TRUNC``, ``O_APPEND``), ``mkdir``, ``rename``/``replace``, ``remove``, ``rmdir``, a hard
link from or into it, a symlink, ``truncate``, a change of mode, owner, times or extended attributes, ``shutil``'s
``rmtree``/``move``/``copy*``, a temporary file or folder, an SQLite database - is written to ``<log>`` as one line
``<event>\t<path>`` and refused with ``OSError(EROFS)``, as a read-only mount would refuse it.  Tests run as root, whom
file modes do not stop: this makes the folder read-only to the process's Python code (not to C code writing on its
own: a real read-only mount is the test of that).
"""
from __future__ import annotations

import errno
import os
import runpy
import sys

WRITE_FLAGS = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_APPEND
# event -> positions of the paths it changes (events of the standard library, docs.python.org "Audit events table")
CHANGED = {"os.mkdir": (0,), "os.rename": (0, 1), "os.remove": (0,), "os.rmdir": (0,), "os.link": (0, 1),
           "os.symlink": (1,), "os.truncate": (0,), "os.chmod": (0,), "os.chown": (0,), "os.utime": (0,),
           "os.setxattr": (0,), "os.removexattr": (0,), "os.mkfifo": (0,), "os.mknod": (0,),
           "shutil.rmtree": (0,), "shutil.move": (0, 1), "shutil.copyfile": (1,), "shutil.copymode": (1,),
           "shutil.copystat": (1,), "shutil.copytree": (1,), "tempfile.mkstemp": (0,), "tempfile.mkdtemp": (0,),
           "sqlite3.connect": (0,)}


def main() -> None:
    folder, log, module, *args = sys.argv[1:]
    roots = {os.path.abspath(folder), os.path.realpath(folder)}
    out = open(log, "a", buffering=1)  # opened before the hook: its writes are no events

    def inside(path) -> bool:
        if isinstance(path, int) or path is None:  # a descriptor: its open was seen
            return False
        try:
            p = os.path.abspath(os.fsdecode(path))
        except TypeError:
            return False
        return any(p == r or p.startswith(r + os.sep) for r in roots)

    def hook(event: str, hook_args: tuple) -> None:
        if event == "open":
            path, mode, flags = hook_args
            writes = (flags or 0) & WRITE_FLAGS or any(c in (mode or "") for c in "wax+")
            paths = (path,) if writes else ()
        else:
            paths = tuple(hook_args[i] for i in CHANGED.get(event, ()) if i < len(hook_args))
        for path in paths:
            if inside(path):
                out.write(f"{event}\t{os.fsdecode(path)}\n")
                raise OSError(errno.EROFS, os.strerror(errno.EROFS), os.fsdecode(path))

    sys.addaudithook(hook)
    sys.argv = [module, *args]
    runpy.run_module(module, run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main()
