"""Safe output folders: refuse foreign targets, lock, stage, swap in two phases, recover.

One mechanism for every command that writes a folder (``run``, ``study``, ``discover``):

* **Ownership.** Every folder bayesmag writes holds a marker file :data:`MARKER` listing the
  files and subfolders it wrote. An existing target may be replaced only if its marker can be
  read in full (JSON, ``tool`` bayesmag, ``complete`` true, a list of ``files``) and the folder
  holds nothing else: no other file, empty subfolder, symlink or ``.bayesmag-run.bak``. Any
  other non-empty target (a folder with a user's files, ``.``, a damaged or truncated marker, a
  run folder holding the input recording or a file added later) is refused *before* any
  computation by :func:`check_out`. Only paths the marker lists are ever removed
  (:func:`remove_listed`); a refused run changes nothing.
* **Lock.** :func:`reserve` takes ``.<name>.lock`` beside the target (created exclusively,
  holding the owner's pid) for the whole command; a second process writing the same target
  is refused. A lock whose pid is no longer alive is stale and taken over.
* **Staging.** :func:`staging_dir` writes into ``.<name>.partial-<pid>`` (marker ``complete:
  false``), marks it complete only when every file is written, then swaps it in:
  (1) rename the old ``<name>`` to ``.<name>.old-<pid>``; (2) rename the staging folder to
  ``<name>``; (3) delete the old folder. POSIX cannot rename a directory over a non-empty
  one atomically, so between (1) and (2) the complete old folder lives under its ``.old``
  name; :func:`recover`, run at the start of every command writing into the same parent,
  renames it back if the process died there, deletes (the listed files of) ``.old`` folders
  already superseded, and deletes ``.partial`` folders and files of dead processes (an ``apply``
  or ``export`` output or a staging folder left by a killed process). Each step is one ``rename(2)`` of a
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

from bayesmag._src.app import signals

__all__ = ["staging_dir", "reserve", "check_out", "recover", "OutputError", "MARKER", "marker_status",
           "is_staging_name", "marker_problem", "foreign_paths", "remove_listed", "register", "atomic_write_text",
           "partial_name", "folder_kind", "OccupiedError", "REPLACES"]

#: The marker file in every folder bayesmag writes (JSON: tool, version, complete, written, and the files
#: it wrote once complete).
MARKER = ".bayesmag-run"
_SIDE = re.compile(r"^\.(?P<name>.+)\.(?P<kind>partial|old)-(?P<pid>\d+)$")
_HELD: dict[Path, int] = {}          # locks this process holds -> nesting depth


class OutputError(ValueError):
    """An output target that bayesmag refuses to write; the message names it and the fix."""


class OccupiedError(OutputError):
    """The target holds a complete folder bayesmag wrote that this write may not replace (:func:`check_out`'s
    ``replaces``): ``folder``, and ``kind``, the command that wrote it (:data:`KIND_WORDS`; None if not known)."""

    def __init__(self, message: str, folder: Path, kind: str | None):
        super().__init__(message)
        self.folder, self.kind = folder, kind


#: What an existing complete bayesmag folder a write may replace (:func:`check_out`): ``"same"`` one the same command
#: wrote (a rerun), ``"none"`` none, ``"any"`` one of any command (asked for explicitly, e.g. ``overwrite=True``).
REPLACES = ("same", "none", "any")


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


def run_file_owner(path: str | Path) -> Path | None:
    """The bayesmag folder ``path`` is a file of, or None: its folder's marker lists it, the folder holds a
    calibration (``calibration.json``), or it is the marker itself. Such a file is never replaced by a
    command's ``--out`` (``apply``, ``export``): replacing it breaks that run."""
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    if path.name.startswith(MARKER):
        return parent
    mark = marker_status(parent)
    listed = set(mark.get("files", [])) if mark is not None and marker_problem(mark) is None else set()
    if path.name in listed or (parent / "calibration.json").exists():
        return parent
    return None


def same_file(a, b) -> bool:
    """True when ``b`` exists and is the file ``a`` (after resolving links)."""
    try:
        return b is not None and Path(b).exists() and Path(a).resolve() == Path(b).resolve()
    except OSError:
        return False


def read_only(path: str | Path) -> bool:
    """True for an existing file with no write permission bit set (``chmod a-w``): a file its owner protected, which
    bayesmag never replaces, even for a user (such as root) whom the permission would not stop."""
    try:
        return Path(path).is_file() and not (Path(path).stat().st_mode & 0o222)
    except OSError:
        return False


def marker_problem(mark: dict | None) -> str | None:
    """Why a marker does not prove the folder is bayesmag's (None when it does).

    A marker proves ownership only when read in full: a JSON object with ``tool`` bayesmag,
    ``complete`` true and ``files`` a list of relative paths. Anything less means "not ours".
    """
    if mark is None:
        return f"no {MARKER} marker"
    if mark.get("damaged"):
        return f"its {MARKER} marker cannot be read (not JSON, truncated or not text)"
    if mark.get("tool") != "bayesmag":
        return f"its {MARKER} marker does not name bayesmag as the writer"
    if mark.get("complete") is not True:
        return f"its {MARKER} marker says the folder is incomplete"
    for key in ("files", "dirs"):
        v = mark.get(key, [])
        if key == "files" and key not in mark:
            return f"its {MARKER} marker lacks the list of files bayesmag wrote"
        if not isinstance(v, list) or not all(_safe_rel(x) for x in v):
            return f"its {MARKER} marker has a damaged '{key}' list"
    return None


def _safe_rel(x) -> bool:
    return (isinstance(x, str) and x not in ("", ".") and not x.startswith("/")
            and ".." not in x.split("/") and "\0" not in x and x != MARKER)


def _walk(folder: Path) -> tuple[dict[str, str], set[str]]:
    """Every entry below ``folder`` without following links: ({rel: 'file'|'link'|'other'}, {rel dirs})."""
    files, dirs = {}, set()
    stack = [(folder, "")]
    while stack:
        d, prefix = stack.pop()
        with os.scandir(d) as it:
            for e in it:
                rel = prefix + e.name
                if e.is_symlink():
                    files[rel] = "link"
                elif e.is_dir(follow_symlinks=False):
                    dirs.add(rel)
                    stack.append((Path(e.path), rel + "/"))
                else:
                    files[rel] = "file" if e.is_file(follow_symlinks=False) else "other"
    return files, dirs


def _files(folder: Path) -> set[str]:
    """The regular files below ``folder`` (what a marker lists), the marker itself excepted."""
    files, _ = _walk(folder)
    return {r for r, kind in files.items() if kind == "file" and r != MARKER}


def _listed_dirs(mark: dict) -> set[str]:
    out = set(mark.get("dirs", []))
    for f in mark.get("files", []):
        parts = f.split("/")[:-1]
        out.update("/".join(parts[:k]) for k in range(1, len(parts) + 1))
    return out


def foreign_paths(folder: str | Path, mark: dict) -> list[str]:
    """Entries of ``folder`` that its (valid) marker does not list: files, symlinks, empty or extra subfolders.

    A listed name that is now a symlink or a folder counts as foreign too (someone replaced it).
    """
    files, dirs = _walk(Path(folder))
    listed, ldirs = set(mark.get("files", [])), _listed_dirs(mark)
    out = [r + (" (symlink)" if kind == "link" else "") for r, kind in files.items()
           if not (r == MARKER and kind == "file") and not (r in listed and kind == "file")]
    out += [r + "/" for r in dirs if r not in ldirs]
    return sorted(out)


def remove_listed(folder: str | Path, mark: dict) -> list[str]:
    """Delete the files and (then empty) subfolders ``mark`` lists, the marker, then ``folder`` if empty.

    Never anything else: a regular file is unlinked only at a listed path, a folder only with
    ``rmdir`` (which cannot delete contents), a symlink never. Returns what is left (normally []).
    """
    folder = Path(folder)
    for rel in mark.get("files", []):
        p = folder / rel
        through_link = any((folder / q).is_symlink() for q in Path(rel).parents if str(q) != ".")
        with contextlib.suppress(OSError):
            if not through_link and p.is_file() and not p.is_symlink():
                p.unlink()
    for rel in sorted(_listed_dirs(mark), key=lambda r: -r.count("/")):
        p = folder / rel
        with contextlib.suppress(OSError):
            if p.is_dir() and not p.is_symlink():
                p.rmdir()
    with contextlib.suppress(OSError):
        (folder / MARKER).unlink()
    left = []
    with contextlib.suppress(OSError):
        left = sorted(os.listdir(folder))
        if not left:
            folder.rmdir()
    return left


def partial_name(path: Path) -> Path:
    """The temporary sibling ``.NAME.partial-PID`` a file is written to before its rename into place."""
    return path.with_name(f".{path.name}.partial-{os.getpid()}")


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to a temporary sibling, flush it to disk, then rename it over ``path`` (one ``rename(2)``)."""
    path = Path(path)
    tmp = partial_name(path)
    try:
        with open(tmp, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def register(folder: str | Path, path: str | Path) -> bool:
    """List ``path`` (a file bayesmag just wrote inside ``folder``) in the folder's marker; False if not listed.

    Only a valid marker is updated (rewritten atomically), so a later run may still replace the folder.
    """
    folder = Path(folder)
    mark = marker_status(folder)
    if marker_problem(mark) is not None:
        return False
    try:
        rel = Path(path).resolve().relative_to(folder.resolve()).as_posix()
    except ValueError:
        return False
    if rel in mark["files"]:
        return True
    mark["files"] = sorted(set(mark["files"]) | {rel})
    atomic_write_text(folder / MARKER, json.dumps(mark) + "\n")
    return True


#: What each command leaves in its folder, in the order checked: the kind of an older folder whose marker predates
#: the marker's ``kind`` field is read from its files.
KIND_FILES = (("fleet", "fleet.json"), ("study", "simulation_study.md"), ("discover", "findings.json"),
              ("run", "calibration.json"), ("run", "field_params.json"))
KIND_WORDS = {"run": "a calibration run (`bayesmag run`)", "fleet": "a fleet result (`bayesmag fleet`)",
              "study": "a simulation study (`bayesmag study`)", "discover": "a discovery result (`bayesmag discover`)",
              "apply": "a calibrated recording (`bayesmag apply`)",
              "calibrator": "a calibration saved from Python (`Calibrator.save`)"}


def folder_kind(mark: dict | None) -> str | None:
    """The command that wrote a bayesmag folder (its marker's ``kind``, else read from the files it lists)."""
    if not isinstance(mark, dict):
        return None
    if isinstance(mark.get("kind"), str):
        return mark["kind"]
    files = set(mark.get("files") or ())
    return next((k for k, f in KIND_FILES if f in files), None)


def _write_marker(folder: Path, complete: bool, kind: str | None = None) -> None:
    from bayesmag._src.core.version import __version__
    doc = {"tool": "bayesmag", "version": __version__, "complete": complete,
           "written": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}
    if kind:
        doc["kind"] = kind
    with contextlib.suppress(OSError):      # a relative [data] path of the run's config resolves against it
        doc["cwd"] = os.getcwd()
    if complete:
        files, dirs = _walk(folder)
        doc["files"] = sorted(r for r, kind in files.items() if kind == "file" and r != MARKER)
        doc["dirs"] = sorted(dirs)
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


def check_out(out: str | Path, *, inputs=(), kind: str | None = None, replaces: str = "same") -> Path:
    """Refuse an output folder bayesmag may not replace, and check it can be written; before any work.

    Allowed: a path that does not exist, an empty folder, or a folder bayesmag wrote earlier
    (it holds :data:`MARKER`) that contains none of ``inputs``. Everything else raises
    :class:`OutputError` naming the folder and suggesting a new name. ``replaces`` (:data:`REPLACES`) says which
    of bayesmag's own complete folders may go: by default (``"same"``) one the same command wrote (``kind``: the
    command writing now; :func:`folder_kind`), so a run never replaces a fleet; a refusal for that reason alone is an
    :class:`OccupiedError`. Files bayesmag did not write are never replaced, whatever ``replaces`` says. The parent
    folder is created and a probe folder with the longest name the swap uses is made and removed, so an
    unwritable, read-only or over-long target fails here, not after the computation.
    """
    if replaces not in REPLACES:
        raise ValueError(f"replaces = {replaces!r} must be one of {list(REPLACES)}.")
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
        problem = marker_problem(mark) if mark is not None else None
        if problem is not None:
            raise OutputError(f"--out {out}: {problem}, so bayesmag cannot tell which files it wrote and treats the "
                              f"folder as not its own; it will not be replaced. Give a new folder name, e.g. --out "
                              f"{_suggest(out)} (or delete the folder yourself).")
        for p in inputs:
            if p is not None and _inside(Path(p), out):
                raise OutputError(f"--out {out} contains the input {p}; replacing the folder would delete it. "
                                  f"Give a new folder name, e.g. --out {_suggest(out)}.")
        foreign = foreign_paths(out, mark) if mark is not None else []
        if foreign:
            shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
            raise OutputError(f"--out {out} is a bayesmag run folder, but it also holds files bayesmag did not write "
                              f"({shown}); replacing it would delete them. Move them out, or give a new folder "
                              f"name, e.g. --out {_suggest(out)}.")
        had = folder_kind(mark) if mark is not None else None
        other = kind is not None and had is not None and had != kind
        if mark is not None and (replaces == "none" or (replaces == "same" and other)):
            raise OccupiedError(f"--out {out} holds {KIND_WORDS.get(had, had or 'a complete bayesmag result')}; this "
                                f"command would replace it with {KIND_WORDS.get(kind, kind or 'its own result')}. "
                                f"Give a new folder name, e.g. --out {_suggest(out)} (or delete the folder yourself if "
                                f"it is no longer needed).", out, had)
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


def recover(parent: str | Path, *, files_only: bool = False) -> list[str]:
    """Finish or undo swaps that a killed process left in ``parent``; returns what was done.

    ``.x.old-N`` of a dead process (a complete folder with a valid marker): renamed back to ``x``
    if ``x`` is missing (the process died between the two renames), else its listed files are
    deleted. ``.x.partial-N`` folder of a dead process holding a bayesmag marker (a staging
    folder): deleted. ``.x.partial-N`` regular file of a dead process (an ``apply``/``export``
    output cut short): deleted. Nothing else is touched; the pid of a live process never.
    ``files_only``: only the partial files (inside a run folder being replaced).
    """
    parent = Path(parent)
    done = []
    if not parent.is_dir():
        return done
    for p in sorted(parent.iterdir()):
        m = _SIDE.match(p.name)
        if m is None or p.is_symlink() or _alive(int(m["pid"])):
            continue
        if not p.is_dir():
            if m["kind"] == "partial" and p.is_file():
                with contextlib.suppress(OSError):
                    p.unlink()
                    done.append(f"removed stale {p.name}")
            continue
        mark = marker_status(p)
        if files_only or mark is None or mark.get("tool") != "bayesmag":
            continue
        target = parent / m["name"]
        if m["kind"] == "old":
            if marker_problem(mark) is not None:
                continue                        # a complete folder was renamed: anything else is not ours
            if not target.exists():
                p.rename(target)
                done.append(f"restored {target} from {p.name}")
            else:
                left = remove_listed(p, mark)
                done.append(f"removed stale {p.name}" + (f" (kept {len(left)} unlisted entries)" if left else ""))
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
def reserve(out: str | Path, *, inputs=(), kind: str | None = None, replaces: str = "same"):
    """Hold ``out`` for this process for the whole block: recover, check (:func:`check_out`), lock (re-entrant)."""
    out = Path(out)
    if out.name in ("", ".", ".."):
        out = out.resolve()
    key = out.resolve()
    if key in _HELD:
        check_out(out, inputs=inputs, kind=kind, replaces=replaces)
        _HELD[key] += 1
        try:
            yield out
        finally:
            _HELD[key] -= 1
        return
    recover(out.parent)
    if out.is_dir() and not out.is_symlink() and marker_problem(marker_status(out)) is None:
        recover(out, files_only=True)           # partial files of killed `export`/`report` into the run folder
    check_out(out, inputs=inputs, kind=kind, replaces=replaces)
    _acquire(out)
    _HELD[key] = 1
    lock = _lock_path(out)
    forget = signals.on_abort(lambda: lock.unlink(missing_ok=True))     # an interrupted command releases it too
    try:
        yield out
    finally:
        _HELD[key] -= 1
        if _HELD[key] == 0:
            del _HELD[key]
            lock.unlink(missing_ok=True)
        forget()


@contextlib.contextmanager
def staging_dir(out: str | Path, *, kind: str | None = None, replaces: str = "same"):
    """Yield a staging folder; on success it replaces ``out`` (two-phase swap), on failure it is removed.

    See the module docstring for the scheme. A failed run leaves ``out`` untouched. ``kind``: the command writing
    (:data:`KIND_WORDS`), kept in the marker; ``replaces``: which complete bayesmag folder it may replace
    (:func:`check_out`; by default one of the same kind).
    """
    out = Path(out)
    if out.name in ("", ".", ".."):
        out = out.resolve()
    with reserve(out, kind=kind, replaces=replaces):
        tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
        if tmp.exists():
            if marker_status(tmp) is None:
                raise OutputError(f"{tmp} exists and was not written by bayesmag; move it away and retry.")
            shutil.rmtree(tmp)
        tmp.mkdir()
        forget = signals.on_abort(lambda: shutil.rmtree(tmp, ignore_errors=True))
        try:
            _write_marker(tmp, complete=False, kind=kind)
            yield tmp
            _write_marker(tmp, complete=True, kind=kind)
            check_out(out, kind=kind, replaces=replaces)    # the target may have changed during the computation
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            forget()
            raise
        with signals.critical():                # a signal here is acted on after the swap, never inside it
            old = old_mark = None
            try:
                if out.exists():
                    old_mark = marker_status(out)
                    if old_mark is None:        # an empty folder (check_out): remove it, never its contents
                        out.rmdir()
                    else:
                        old = out.parent / f".{out.name}.old-{os.getpid()}"
                        out.rename(old)         # phase 1: the complete old folder under its .old name
                tmp.rename(out)                 # phase 2: the complete new folder under its name
            except BaseException:
                if old is not None and not out.exists():
                    old.rename(out)
                shutil.rmtree(tmp, ignore_errors=True)
                raise
            finally:
                forget()
            if old is not None:
                left = remove_listed(old, old_mark)     # only what the old marker lists, never a newer user file
                if left:
                    import warnings
                    warnings.warn(f"kept {old}: it holds {len(left)} entries bayesmag did not write "
                                  f"({', '.join(left[:3])}), added while the run computed; move them back by hand.",
                                  stacklevel=3)
