"""Safe output folders: refuse foreign targets, lock, stage, swap in two phases, recover.

One mechanism for every command that writes a folder (``run``, ``study``, ``discover``):

* **Ownership.** Every folder bayesmag writes holds a marker file :data:`MARKER` listing the
  files it wrote. An existing target may be replaced only if it holds the marker and no other
  files; any other non-empty target (a folder with a user's files, ``.``, a run folder holding
  the input recording or a file added later) is refused *before* any computation by
  :func:`check_out`. Nothing bayesmag did not write is ever deleted.
* **Lock.** :func:`reserve` takes ``.<name>.lock`` beside the target (created exclusively,
  holding the owner's pid) for the whole command; a second process writing the same target
  is refused. A lock whose pid is no longer alive is stale and taken over.
* **Staging.** :func:`staging_dir` writes into ``.<name>.partial-<pid>`` (marker ``complete:
  false``), marks it complete only when every file is written, then swaps it in:
  (1) rename the old ``<name>`` to ``.<name>.old-<pid>``; (2) rename the staging folder to
  ``<name>``; (3) delete the old folder. POSIX cannot rename a directory over a non-empty
  one atomically, so between (1) and (2) the complete old folder lives under its ``.old``
  name; :func:`recover`, run at the start of every command writing into the same parent,
  renames it back if the process died there, deletes ``.old`` folders already superseded,
  and deletes ``.partial`` folders of dead processes. Each step is one ``rename(2)`` of a
  directory, so at every instant a complete old or new folder exists.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import re
import shutil
from pathlib import Path

__all__ = ["staging_dir", "reserve", "check_out", "recover", "OutputError", "MARKER", "marker_status",
           "is_staging_name"]

#: The marker file in every folder bayesmag writes (JSON: tool, version, complete, written, and the files
#: it wrote once complete).
MARKER = ".bayesmag-run"
_SIDE = re.compile(r"^\.(?P<name>.+)\.(?P<kind>partial|old)-(?P<pid>\d+)$")
_HELD: dict[Path, int] = {}          # locks this process holds -> nesting depth


class OutputError(ValueError):
    """An output target that bayesmag refuses to write; the message names it and the fix."""


def is_staging_name(name: str) -> bool:
    """True for the temporary names of a staging (``.x.partial-N``) or superseded (``.x.old-N``) folder."""
    return _SIDE.match(name) is not None


def marker_status(folder: str | Path) -> dict | None:
    """The marker of a bayesmag folder, or None if ``folder`` holds none (not written by bayesmag)."""
    m = Path(folder) / MARKER
    if not m.is_file():
        return None
    try:
        doc = json.loads(m.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return {"complete": False, "damaged": True}
    return doc if isinstance(doc, dict) else {"complete": False, "damaged": True}


def _files(folder: Path) -> set[str]:
    return {p.relative_to(folder).as_posix() for p in folder.rglob("*")
            if not p.is_dir() and not p.name.startswith(MARKER)}


def _write_marker(folder: Path, complete: bool) -> None:
    from bayesmag._src.core.version import __version__
    doc = {"tool": "bayesmag", "version": __version__, "complete": complete,
           "written": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}
    if complete:
        doc["files"] = sorted(_files(folder))
    tmp = folder / (MARKER + ".tmp")
    tmp.write_text(json.dumps(doc) + "\n")
    os.replace(tmp, folder / MARKER)


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _inside(child: Path, parent: Path) -> bool:
    try:
        child.resolve().relative_to(parent.resolve())
        return True
    except ValueError:
        return False


def _suggest(out: Path) -> str:
    k = 2
    while (out.parent / f"{out.name}_{k}").exists():
        k += 1
    return str(out.parent / f"{out.name}_{k}")


def check_out(out: str | Path, *, inputs=()) -> Path:
    """Refuse an output folder bayesmag may not replace, and check it can be written; before any work.

    Allowed: a path that does not exist, an empty folder, or a folder bayesmag wrote earlier
    (it holds :data:`MARKER`) that contains none of ``inputs``. Everything else raises
    :class:`OutputError` naming the folder and suggesting a new name. The parent folder is
    created and a probe folder with the longest name the swap uses is made and removed, so an
    unwritable, read-only or over-long target fails here, not after the computation.
    """
    out = Path(out)
    if out.name in ("", ".", ".."):
        out = out.resolve()
    if out.exists() or out.is_symlink():
        if not out.is_dir() or out.is_symlink():
            raise OutputError(f"--out {out} exists and is not a folder bayesmag wrote; it will not be replaced. "
                              f"Give a new folder name, e.g. --out {_suggest(out)}.")
        mark = marker_status(out)
        if mark is None and any(out.iterdir()):
            raise OutputError(f"--out {out} is an existing folder that bayesmag did not write (no {MARKER} marker) "
                              f"and it is not empty; bayesmag never replaces such a folder. Give a new folder name, "
                              f"e.g. --out {_suggest(out)}.")
        for p in inputs:
            if p is not None and _inside(Path(p), out):
                raise OutputError(f"--out {out} contains the input {p}; replacing the folder would delete it. "
                                  f"Give a new folder name, e.g. --out {_suggest(out)}.")
        foreign = sorted(_files(out) - set(mark.get("files", []))) if mark and "files" in mark else []
        if foreign:
            shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
            raise OutputError(f"--out {out} is a bayesmag run folder, but it also holds files bayesmag did not write "
                              f"({shown}); replacing it would delete them. Move them out, or give a new folder "
                              f"name, e.g. --out {_suggest(out)}.")
    if is_staging_name(out.name):
        raise OutputError(f"--out {out} has the name of a bayesmag temporary folder; choose another name.")
    probe = out.parent / f".{out.name}.partial-{os.getpid()}-probe"
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        probe.mkdir()
        try:
            (probe / MARKER).write_text("probe\n")
            (probe / MARKER).unlink()
        finally:
            with contextlib.suppress(OSError):
                probe.rmdir()
    except OSError as e:
        raise OutputError(f"--out {out} cannot be written ({e.strerror or e}: {e.filename}); checked before any "
                          f"computation. Give a writable folder (with a shorter name if the name is too long).") from None
    return out


def recover(parent: str | Path) -> list[str]:
    """Finish or undo swaps that a killed process left in ``parent``; returns what was done.

    ``.x.old-N`` of a dead process: renamed back to ``x`` if ``x`` is missing (the process died
    between the two renames), else deleted. ``.x.partial-N`` of a dead process: deleted. Only
    folders holding :data:`MARKER` are touched.
    """
    parent = Path(parent)
    done = []
    if not parent.is_dir():
        return done
    for p in sorted(parent.iterdir()):
        m = _SIDE.match(p.name)
        if m is None or not p.is_dir() or p.is_symlink() or _alive(int(m["pid"])):
            continue
        mark = marker_status(p)
        if mark is None:
            continue
        target = parent / m["name"]
        if m["kind"] == "old" and mark.get("complete") and not target.exists():
            p.rename(target)
            done.append(f"restored {target} from {p.name}")
        else:
            shutil.rmtree(p, ignore_errors=True)
            done.append(f"removed stale {p.name}")
    return done


def _lock_path(out: Path) -> Path:
    return out.parent / f".{out.name}.lock"


def _acquire(out: Path) -> None:
    lock = _lock_path(out)
    tmp = out.parent / f".{out.name}.lock-{os.getpid()}"
    tmp.write_text(f"{os.getpid()}\n")
    try:
        for _ in range(2):
            try:
                os.link(tmp, lock)              # atomic: fails if the lock exists
                return
            except FileExistsError:
                try:
                    pid = int(lock.read_text().split()[0])
                except (OSError, ValueError, IndexError):
                    pid = -1
                if pid > 0 and _alive(pid):
                    raise OutputError(f"another bayesmag process (pid {pid}) is writing {out} right now (lock "
                                      f"{lock}); wait for it to finish or give another --out.") from None
                lock.unlink(missing_ok=True)    # stale: its owner is gone
        raise OutputError(f"could not take the lock {lock}; another process keeps creating it.")
    finally:
        tmp.unlink(missing_ok=True)


@contextlib.contextmanager
def reserve(out: str | Path, *, inputs=()):
    """Hold ``out`` for this process for the whole block: recover, check, lock (re-entrant)."""
    out = Path(out)
    if out.name in ("", ".", ".."):
        out = out.resolve()
    key = out.resolve()
    if key in _HELD:
        check_out(out, inputs=inputs)
        _HELD[key] += 1
        try:
            yield out
        finally:
            _HELD[key] -= 1
        return
    recover(out.parent)
    check_out(out, inputs=inputs)
    _acquire(out)
    _HELD[key] = 1
    try:
        yield out
    finally:
        _HELD[key] -= 1
        if _HELD[key] == 0:
            del _HELD[key]
            _lock_path(out).unlink(missing_ok=True)


@contextlib.contextmanager
def staging_dir(out: str | Path):
    """Yield a staging folder; on success it replaces ``out`` (two-phase swap), on failure it is removed.

    See the module docstring for the scheme. A failed run leaves ``out`` untouched.
    """
    out = Path(out)
    if out.name in ("", ".", ".."):
        out = out.resolve()
    with reserve(out):
        tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
        if tmp.exists():
            if marker_status(tmp) is None:
                raise OutputError(f"{tmp} exists and was not written by bayesmag; move it away and retry.")
            shutil.rmtree(tmp)
        tmp.mkdir()
        try:
            _write_marker(tmp, complete=False)
            yield tmp
            _write_marker(tmp, complete=True)
            check_out(out)                      # the target may have changed during the computation
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        old = None
        if out.exists():
            if marker_status(out) is None:      # an empty folder (check_out): remove it, never its contents
                out.rmdir()
            else:
                old = out.parent / f".{out.name}.old-{os.getpid()}"
                out.rename(old)                 # phase 1: the complete old folder under its .old name
        try:
            tmp.rename(out)                     # phase 2: the complete new folder under its name
        except BaseException:
            if old is not None and not out.exists():
                old.rename(out)
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
