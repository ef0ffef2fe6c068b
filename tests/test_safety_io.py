"""Issue 21 (items 1-4, 16-18) and issue 22.4: nothing overwritten, nothing unusable written, nothing left running.

Every case works in temporary folders; the signal cases start ``python -m bayesmag`` as a real
child process and send it real signals.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bayesmag import write_csv
from bayesmag._src.app import job as job_module
from bayesmag._src.app.cli import main
from bayesmag._src.app.outdir import MARKER, OutputError, marker_status, recover, staging_dir
from bayesmag.simulate import simulate


from helpers import SMALL_JOB_CONFIG as CONFIG  # noqa: E402


def _recording(path: Path, n=200, seed=0) -> Path:
    write_csv(simulate(n, design="iid", seed=seed), path)
    return path


def _config(folder: Path, data: Path, text: str = CONFIG) -> Path:
    p = folder / "cfg.toml"
    p.write_text(text.format(data=data))
    return p


def _err(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


def _tree(folder: Path) -> dict:
    """Every entry below ``folder`` (links not followed): path -> ('file', bytes) | ('link', target) | ('dir',)."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(folder):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            rel = p.relative_to(folder).as_posix()
            if p.is_symlink():
                out[rel] = ("link", os.readlink(p))
            elif p.is_dir():
                out[rel] = ("dir",)
            else:
                out[rel] = ("file", p.read_bytes())
    return out


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


@pytest.fixture
def no_work(monkeypatch):
    """Fail loudly if the computation starts: refusals must come before it."""
    def boom(*a, **k):
        raise AssertionError("the job started computing")
    monkeypatch.setattr(job_module, "_run_job", boom)


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    """One finished physics run folder (copied by the tests that change it)."""
    folder = tmp_path_factory.mktemp("model")
    rec = _recording(folder / "rec.csv")
    assert main(["run", str(_config(folder, rec)), "--out", str(folder / "run"), "--no-progress"]) == 0
    return folder / "run"


def _copy(model: Path, tmp_path: Path) -> tuple[Path, Path]:
    """A copy of the run folder and a config to re-run it (the recording outside the folder)."""
    run = tmp_path / "run"
    shutil.copytree(model, run, symlinks=True)
    return run, _config(tmp_path, _recording(tmp_path / "rec.csv"))


# --------------------------------------------------------------------------- item 2: a marker read in full or "not ours"


def _truncate(m: Path):
    m.write_bytes(m.read_bytes()[: len(m.read_bytes()) // 2])


def _no_files(m: Path):
    doc = json.loads(m.read_text())
    del doc["files"]
    m.write_text(json.dumps(doc))


def _px4(m: Path):            # what `bayesmag export R --format px4 --out R/.bayesmag-run` did before item 1
    m.write_text("# PX4 parameters\n1\t1\tCAL_MAG0_XOFF\t0.1\t9\n")


def _files_not_a_list(m: Path):
    doc = json.loads(m.read_text())
    doc["files"] = "calibration.json"
    m.write_text(json.dumps(doc))


def _not_utf8(m: Path):
    m.write_bytes(b"\xff\xfe\x00garbage")


@pytest.mark.parametrize("damage", [_truncate, _no_files, _px4, _files_not_a_list, _not_utf8])
def test_a_marker_that_cannot_be_read_in_full_means_not_ours(tmp_path, capsys, model, no_work, damage):
    run, cfg = _copy(model, tmp_path)
    (run / "notes.txt").write_text("my notes")
    damage(run / MARKER)
    before = _tree(run)
    rc = main(["run", str(cfg), "--out", str(run), "--no-progress"])
    err = _err(capsys)
    assert rc == 2 and err.count("\n") == 1 and "not its own" in err and MARKER in err, err
    assert _tree(run) == before                           # a refused run changes nothing
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".run.")]


# --------------------------------------------------------------------------- item 3: only listed paths are removed


@pytest.mark.parametrize("extra", ["empty_dir", "symlink_file", "symlink_dir", "marker_bak", "nested_file"])
def test_rerun_refuses_anything_the_marker_does_not_list(tmp_path, capsys, model, no_work, extra):
    run, cfg = _copy(model, tmp_path)
    outside = tmp_path / "outside.txt"
    outside.write_text("keep")
    if extra == "empty_dir":
        (run / "my_empty").mkdir()
    elif extra == "symlink_file":
        (run / "link.txt").symlink_to(outside)
    elif extra == "symlink_dir":
        (run / "linkdir").symlink_to(tmp_path)
    elif extra == "marker_bak":
        shutil.copy(run / MARKER, run / (MARKER + ".bak"))
    else:
        (run / "sub").mkdir()
        (run / "sub" / "data.csv").write_text("x")
    before = _tree(run)
    rc = main(["run", str(cfg), "--out", str(run), "--no-progress"])
    assert rc == 2 and "did not write" in _err(capsys)
    assert _tree(run) == before and outside.read_text() == "keep"


def test_rerun_of_a_clean_run_folder_still_replaces_it(tmp_path, capsys, model):
    run, cfg = _copy(model, tmp_path)
    old = json.loads((run / MARKER).read_text())["written"]
    assert main(["run", str(cfg), "--out", str(run), "--no-progress"]) == 0
    mark = marker_status(run)
    assert mark["complete"] and "calibration.json" in mark["files"] and isinstance(mark["dirs"], list)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["run", "rec.csv", "cfg.toml"]), old


@pytest.mark.parametrize("other", ["fleet", "discover", "study"])
def test_a_run_never_replaces_another_commands_folder(tmp_path, capsys, model, no_work, other):
    """Before: `bayesmag run --out <a fleet folder>` replaced an 8-sensor fleet (fleet.json, sensors/) with one run,
    and `discover --out <a run>` a calibration, silently. The folder's kind: its marker's, or (older markers) its
    files'."""
    from bayesmag._src.app.outdir import KIND_FILES, check_out, folder_kind
    run, cfg = _copy(model, tmp_path)
    name = dict(KIND_FILES)[other]
    (run / name).write_text("{}")
    mark = json.loads((run / MARKER).read_text())
    mark["files"] = sorted(set(mark["files"]) - {"calibration.json"} | {name})
    mark.pop("kind")                                            # a marker written before it kept the command
    (run / "calibration.json").unlink()
    (run / MARKER).write_text(json.dumps(mark))
    assert folder_kind(marker_status(run)) == other
    before = _tree(run)
    rc = main(["run", str(cfg), "--out", str(run), "--no-progress"])
    err = _err(capsys)
    assert rc == 2 and "this command would replace it" in err and f"bayesmag {other}" in err, err
    assert _tree(run) == before
    check_out(run, kind=other)                                  # its own command may replace it


def test_the_marker_records_the_command_that_wrote_the_folder(model):
    assert marker_status(model)["kind"] == "run"


_NAMES = st.sampled_from(["a", "b.txt", "notes.md", MARKER + ".bak", ".hidden", "figure.png", "x y"])


@st.composite
def _user_entries(draw):
    """User additions to a bayesmag folder: files, empty folders, symlinks; and maybe a damaged marker."""
    entries = draw(st.lists(st.tuples(st.sampled_from(["file", "dir", "link", "nested"]), _NAMES), max_size=4))
    damage = draw(st.sampled_from([None, None, "truncate", "no_files", "not_json", "incomplete", "remove_listed"]))
    return entries, damage


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_user_entries())
def test_property_whatever_the_marker_does_not_list_survives_a_rerun(case):
    """Any folder contents: the rerun either replaces only what the marker listed, or is refused and changes nothing."""
    entries, damage = case
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        out = d / "out"
        with staging_dir(out) as tmp:                    # a genuine bayesmag folder: two files, one subfolder
            (tmp / "calibration.json").write_text("{}")
            (tmp / "sub").mkdir()
            (tmp / "sub" / "fig.png").write_text("png")
        listed = set(marker_status(out)["files"]) | {MARKER, "sub"}
        target = d / "target.txt"
        target.write_text("outside")
        for kind, name in entries:
            p = out / name
            if p.exists() or p.is_symlink():
                continue
            if kind == "file":
                p.write_text("user " + name)
            elif kind == "dir":
                p.mkdir()
            elif kind == "link":
                p.symlink_to(target)
            else:
                (out / "sub" / name).write_text("user nested")
        m = out / MARKER
        if damage == "truncate":
            m.write_text(m.read_text()[:20])
        elif damage == "no_files":
            doc = json.loads(m.read_text())
            del doc["files"]
            m.write_text(json.dumps(doc))
        elif damage == "not_json":
            m.write_text("# not json")
        elif damage == "incomplete":
            doc = json.loads(m.read_text())
            doc["complete"] = False
            m.write_text(json.dumps(doc))
        elif damage == "remove_listed":
            (out / "calibration.json").unlink()         # fewer files than listed is still ours
        before = _tree(out)
        unlisted = {k: v for k, v in before.items() if k not in listed and not k.startswith("sub/fig.png")}
        try:
            with staging_dir(out) as tmp:
                (tmp / "new.json").write_text("{}")
        except OutputError:
            assert _tree(out) == before                   # refused: nothing changed
            assert unlisted or damage not in (None, "remove_listed")
        else:
            assert not unlisted and damage in (None, "remove_listed")
            assert (out / "new.json").exists()
        assert target.read_text() == "outside"
        assert sorted(p.name for p in d.iterdir()) == ["out", "target.txt"]    # no staging, .old or lock left


# --------------------------------------------------------------------------- item 18: partial files of dead processes


def test_partial_files_of_dead_processes_are_removed_by_the_next_apply(tmp_path, capsys, model):
    rec = _recording(tmp_path / "rec.csv")
    dead, live = _dead_pid(), os.getppid()
    stale = tmp_path / f".calibrated.csv.partial-{dead}"
    stale.write_text("time,run\n" * 1000)                 # what a killed apply left
    alive = tmp_path / f".calibrated.csv.partial-{live}"
    alive.write_text("another process is writing")
    user_dir = tmp_path / f".thesis.partial-{dead}"      # a folder of that name without a marker: not ours
    user_dir.mkdir()
    assert main(["apply", "--model", str(model), "--data", str(rec), "--out", str(tmp_path / "calibrated.csv"),
                 "--no-progress"]) == 0
    assert not stale.exists() and alive.exists() and user_dir.is_dir()
    assert (tmp_path / "calibrated.csv").exists()


def test_partial_files_of_dead_processes_are_removed_by_the_next_run(tmp_path, capsys, model):
    run, cfg = _copy(model, tmp_path)
    dead = _dead_pid()
    beside = tmp_path / f".calibrated.csv.partial-{dead}"
    beside.write_text("x")
    inside = run / f".report.md.partial-{dead}"          # a killed `bayesmag report` into the run folder
    inside.write_text("x")
    live = run / f".report.md.partial-{os.getppid()}"
    live.write_text("x")
    assert main(["run", str(cfg), "--out", str(run), "--no-progress"]) == 2      # the live one is not ours
    assert live.exists() and inside.exists() is False and beside.exists() is False
    live.unlink()
    assert main(["run", str(cfg), "--out", str(run), "--no-progress"]) == 0


def test_recover_removes_dead_partial_files_only(tmp_path):
    dead = _dead_pid()
    (tmp_path / f".out.csv.partial-{dead}").write_text("x")
    (tmp_path / f".out.csv.partial-{os.getpid()}").write_text("mine")
    (tmp_path / f"out.csv.partial-{dead}").write_text("no leading dot: a user's name")
    (tmp_path / f".link.partial-{dead}").symlink_to(tmp_path / f"out.csv.partial-{dead}")
    done = recover(tmp_path)
    assert done == [f"removed stale .out.csv.partial-{dead}"]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([f".out.csv.partial-{os.getpid()}",
                                                                 f"out.csv.partial-{dead}", f".link.partial-{dead}"])


# --------------------------------------------------------------------------- item 1: export --out


def _export(run, fmt, out=None, *extra):
    return main(["export", str(run), "--format", fmt] + (["--out", str(out)] if out is not None else []) + list(extra))


@pytest.mark.parametrize("target", ["calibration.json", "calibration.npz", MARKER, "metrics.json", "report.md"])
def test_export_never_replaces_a_file_of_the_run_folder(tmp_path, capsys, model, target):
    run, _ = _copy(model, tmp_path)
    before = _tree(run)
    for force in ([], ["--force"]):
        assert _export(run, "px4", run / target, *force) == 2
        err = _err(capsys)
        assert err.count("\n") == 1 and str(run / target) in err
    assert _tree(run) == before
    assert main(["apply", "--model", str(run), "--data", str(_recording(tmp_path / "r.csv")),
                 "--out", str(tmp_path / "o.csv"), "--no-progress"]) == 0


def test_export_never_replaces_the_training_recording(tmp_path, capsys):
    rec = _recording(tmp_path / "rec.csv")
    run = tmp_path / "run"
    assert main(["run", str(_config(tmp_path, rec)), "--out", str(run), "--no-progress"]) == 0
    before = rec.read_bytes()
    for force in ([], ["--force"]):
        assert _export(run, "c-header", rec, *force) == 2
        assert "training recording" in _err(capsys)
    assert rec.read_bytes() == before


def test_a_relative_training_recording_is_protected_from_another_folder(tmp_path, capsys, monkeypatch):
    """The run was given ``data/rec.csv`` from ``tmp_path/work``; apply (and export) run from ``tmp_path`` resolved
    that path there, found nothing to protect and replaced ``work/data/rec.csv`` with --force (outside smoke pass).
    The run's marker now records the folder it started in."""
    work = tmp_path / "work"
    (work / "data").mkdir(parents=True)
    _recording(work / "data" / "rec.csv")
    _recording(tmp_path / "new.csv", seed=1)
    monkeypatch.chdir(work)
    assert main(["run", str(_config(work, Path("data/rec.csv"))), "--out", "run", "--no-progress"]) == 0
    assert marker_status(work / "run")["cwd"] == str(work)
    before = (work / "data" / "rec.csv").read_bytes()
    monkeypatch.chdir(tmp_path)
    assert main(["apply", "--model", "work/run", "--data", "new.csv", "--out", "work/data/rec.csv", "--force",
                 "--no-progress"]) == 2
    assert "trained on" in _err(capsys)
    assert _export(Path("work/run"), "c-header", Path("work/data/rec.csv"), "--force") == 2
    assert "training recording" in _err(capsys)
    assert (work / "data" / "rec.csv").read_bytes() == before


def test_export_refuses_a_users_file_unless_forced_and_replaces_its_own(tmp_path, capsys, model):
    run, _ = _copy(model, tmp_path)
    mine = tmp_path / "params.txt"
    mine.write_text("my own PX4 parameters\n")
    assert _export(run, "px4", mine) == 2
    err = _err(capsys)
    assert "was not written by `bayesmag export`" in err and "--force" in err
    assert mine.read_text() == "my own PX4 parameters\n"
    assert _export(run, "px4", mine, "--force") == 0 and "bayesmag-export" in mine.read_text()
    for fmt in ("json", "magcal", "c-header", "ardupilot", "px4"):     # bayesmag's own exports: replaced freely
        out = tmp_path / f"cal{fmt}"
        assert _export(run, fmt, out) == 0 and _export(run, fmt, out) == 0
    assert _export(run, "px4", tmp_path) == 2 and "is a folder" in _err(capsys)
    link = tmp_path / "link.params"
    link.symlink_to(tmp_path / "calpx4")
    assert _export(run, "px4", link, "--force") == 2 and "symbolic link" in _err(capsys)


def test_export_writes_atomically(tmp_path, capsys, model, monkeypatch):
    """A write that fails halfway leaves the previous export whole and no temporary file."""
    run, _ = _copy(model, tmp_path)
    out = tmp_path / "cal.h"
    assert _export(run, "c-header", out) == 0
    before = out.read_bytes()
    import builtins
    real_open = builtins.open

    def failing_open(path, mode="r", *a, **k):
        f = real_open(path, mode, *a, **k)
        if "w" in mode and ".partial-" in str(path):
            f.write("/* half")
            f.flush()
            raise OSError(28, "No space left on device", str(path))
        return f
    monkeypatch.setattr(builtins, "open", failing_open)
    assert _export(run, "c-header", out) == 2
    monkeypatch.undo()
    assert "No space left on device" in _err(capsys)
    assert out.read_bytes() == before
    assert not [p for p in tmp_path.iterdir() if ".partial-" in p.name]


# --------------------------------------------------------------------------- item 4: report needs a valid marker


def test_report_refuses_a_folder_without_a_valid_marker(tmp_path, capsys, model):
    run, _ = _copy(model, tmp_path)
    (run / "report.md").write_text("my edited report")
    shutil.copy(run / MARKER, tmp_path / "marker")
    (run / MARKER).unlink()
    assert main(["report", str(run)]) == 2 and "not a finished bayesmag run folder" in _err(capsys)
    (run / MARKER).write_text("{")                       # truncated
    assert main(["report", str(run)]) == 2 and "not a finished bayesmag run folder" in _err(capsys)
    assert (run / "report.md").read_text() == "my edited report"
    shutil.copy(tmp_path / "marker", run / MARKER)
    assert main(["report", str(run)]) == 0 and (run / "report.md").read_text().startswith("#")
    (run / "report.md").unlink()                         # absent: written and listed, the folder stays re-runnable
    assert main(["report", str(run)]) == 0 and "report.md" in marker_status(run)["files"]


# --------------------------------------------------------------------------- items 16, 17: signals, nothing left running

TRAINING = """name = "long"
[data]
source = "simulated"
[data.simulate]
design = "campaign"
n = 2400
seed = 0
[split]
kind = "time_blocks"
test_fraction = 0.2
[uq]
method = "analytic"
[network]
enabled = true
likelihoods = ["gaussian"]
width = 16
hidden_layers = 2
max_epochs = 5000
patience = 5000
mc_passes = 5
conformal_folds = 2
[output]
figures = true
progress = false
"""


def _env(worker: bool = True):
    """The child's environment; ``worker``: the figure worker on (BAYESMAG_FIGURE_WORKER=1), so that the kill
    tests have a child process to lose."""
    return {**os.environ, "MPLBACKEND": "Agg", "JAX_PLATFORMS": "cpu", "PYTHONUNBUFFERED": "1",
            "BAYESMAG_FIGURE_WORKER": "1" if worker else "0"}


def _cmdline(pid: int) -> str:
    """The command line of ``pid`` ('' when it is gone)."""
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def _children(pid: int) -> list[int]:
    """Live (not zombie) direct children of ``pid``, from /proc."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            fields = stat[stat.rindex(")") + 2:].split()
            if int(fields[1]) == pid and fields[0] != "Z":
                out.append(int(d.name))
    return out


def _running(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat[stat.rindex(")") + 2:].split()[0] != "Z"


def _start_training(tmp_path: Path, out: Path) -> tuple[subprocess.Popen, list[int]]:
    """``python -m bayesmag run`` of a long training job; returns once its figure worker is up and 6 s more."""
    cfg = tmp_path / "long.toml"
    cfg.write_text(TRAINING)
    p = subprocess.Popen([sys.executable, "-m", "bayesmag", "run", str(cfg), "--out", str(out), "--no-progress"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env(), cwd=tmp_path)
    deadline = time.monotonic() + 120
    kids = []
    while time.monotonic() < deadline and p.poll() is None and not kids:
        time.sleep(0.1)
        kids = _children(p.pid)
    assert kids, f"no figure worker started: {p.poll()} {p.stderr.read().decode() if p.poll() is not None else ''}"
    time.sleep(6.0)                                      # into the training (max_epochs 5000)
    assert p.poll() is None
    return p, kids


def _fake_old_run(out: Path) -> dict:
    with staging_dir(out) as tmp:
        (tmp / "calibration.json").write_text("{\"old\": true}")
    return _tree(out)


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
@pytest.mark.extended
def test_interrupt_is_one_line_exit_status_and_a_safe_folder(tmp_path, sig, code):
    out = tmp_path / "out"
    before = _fake_old_run(out)
    p, kids = _start_training(tmp_path, out)
    t0 = time.monotonic()
    p.send_signal(sig)
    stdout, stderr = p.communicate(timeout=30)          # returns: nothing holds the pipes any more
    took = time.monotonic() - t0
    err = stderr.decode()
    assert p.returncode == code, err
    assert took < 2.0, took
    assert err.count("\n") == 1 and "interrupted by" in err and "Traceback" not in err, err
    assert _tree(out) == before                          # the old result, untouched
    assert sorted(x.name for x in tmp_path.iterdir()) == ["long.toml", "out"]    # no staging, lock or .old
    time.sleep(1.0)
    assert not [k for k in kids if _running(k)]


def test_no_process_outlives_a_sigkilled_run_and_capture_output_returns(tmp_path):
    """The issue's case: subprocess.run(capture_output=True) of a SIGKILLed `bayesmag run` returns at once and
    no child of it (figure worker, resource tracker) survives. SIGTERM: the test above."""
    import threading

    cfg = tmp_path / "long.toml"
    cfg.write_text(TRAINING)
    cmd = [sys.executable, "-m", "bayesmag", "run", str(cfg), "--out", str(tmp_path / "out"), "--no-progress"]
    result = {}

    def run():
        result["r"] = subprocess.run(cmd, capture_output=True, env=_env(), cwd=tmp_path, timeout=120)
    t = threading.Thread(target=run, daemon=True)
    t.start()
    deadline = time.monotonic() + 120
    cmd_pid, kids = None, []
    while time.monotonic() < deadline and not kids:
        time.sleep(0.1)
        # this test's command among the suite's children (earlier tests may have left others, e.g. Dask)
        cmd_pid = next((c for c in _children(os.getpid()) if str(tmp_path / "out") in _cmdline(c)), None)
        kids = _children(cmd_pid) if cmd_pid else []
    assert kids, "no figure worker started"
    time.sleep(2.0)
    os.kill(cmd_pid, signal.SIGKILL)
    t.join(timeout=30)                                   # hung forever before: the worker held the pipes
    assert not t.is_alive() and result["r"].returncode == -signal.SIGKILL
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and [k for k in kids if _running(k)]:
        time.sleep(0.1)
    assert not [k for k in kids if _running(k)], "a child of `bayesmag run` outlived it"


def test_bayesmag_run_spawns_no_process_with_the_worker_off(tmp_path):
    """With BAYESMAG_FIGURE_WORKER=0 the command draws its figures itself: no child at any time."""
    cfg = tmp_path / "long.toml"
    cfg.write_text(TRAINING)
    p = subprocess.Popen([sys.executable, "-m", "bayesmag", "run", str(cfg), "--out", str(tmp_path / "out"),
                          "--no-progress"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         env=_env(worker=False), cwd=tmp_path)
    seen = []
    t0 = time.monotonic()
    while time.monotonic() - t0 < 8 and p.poll() is None:
        seen += _children(p.pid)
        time.sleep(0.1)
    p.send_signal(signal.SIGINT)
    p.communicate(timeout=30)
    assert p.returncode == 130 and seen == []


# --------------------------------------------------------------------------- issue 22.4: nothing spawned from Python


def test_a_script_without_main_guard_fits_once_and_spawns_nothing(tmp_path):
    script = tmp_path / "user_script.py"
    script.write_text(textwrap.dedent(f"""
        import os, sys
        import bayesmag
        from bayesmag.simulate import simulate
        def children():             # this process's children (a process may exit between listdir and open)
            out = []
            for p in os.listdir("/proc"):
                try:
                    stat = open(f"/proc/{{p}}/stat").read() if p.isdigit() else ""
                except OSError:
                    continue
                if stat and stat.rsplit(")", 1)[1].split()[1] == str(os.getpid()):
                    out.append(p)
            return out
        print("script body ran", os.getpid())
        d = simulate(600, design="campaign", seed=0)
        cal = bayesmag.Calibrator("paper_physics", overrides=["uq.n_params=20", "uq.n_qmc=32"],
                                  out={str(tmp_path / 'api')!r}).fit(d)
        kids = children()
        print("children", kids)
        print("multiprocessing", "multiprocessing.resource_tracker" in sys.modules)
        cfg = bayesmag.load_config({str(Path(__file__).resolve().parents[1] / 'configs' / 'paper_physics.toml')!r},
                                   ["uq.n_params=20", "uq.n_qmc=32", "output.progress=false"])
        bayesmag.run_job(cfg, {str(tmp_path / 'job')!r})                  # a job from Python draws its figures here
        kids = children()
        print("children after the job", kids)
        print("figures", sorted(p.name for p in __import__("pathlib").Path({str(tmp_path / 'job')!r}).glob("*.png")))
    """))
    r = subprocess.run([sys.executable, str(script)], capture_output=True, timeout=300, env=_env(), cwd=tmp_path)
    out = r.stdout.decode()
    assert r.returncode == 0, r.stderr.decode()[-3000:]
    assert out.count("script body ran") == 1
    assert "children []" in out and "children after the job []" in out and "multiprocessing False" in out
    assert ".png" in out.split("figures", 1)[1]           # paper_physics draws figures: here, in this process


def test_figure_worker_refuses_functions_of_main():
    from bayesmag._src.app.figure_worker import FigureWorker

    def f(folder):
        pass
    f.__module__ = "__main__"
    with FigureWorker() as figs, pytest.raises(ValueError, match="__main__"):
        figs.submit(f)


def test_signal_handlers_are_left_alone_by_import_and_by_calls_from_python(tmp_path):
    script = textwrap.dedent("""
        import signal
        # Python's own SIGINT handler, whatever this process inherited (a shell starts background jobs with SIGINT
        # ignored, and Python then keeps it ignored instead of installing its handler)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        before = (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM), signal.set_wakeup_fd(-1))
        import bayesmag
        from bayesmag._src.app.cli import main
        main(["report", "/nonexistent"])                 # a call from Python: no handlers, not even briefly kept
        after = (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM), signal.set_wakeup_fd(-1))
        print(before == after, after[0] is signal.default_int_handler, after[1] == signal.SIG_DFL)
    """)
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, timeout=120, env=_env(), cwd=tmp_path)
    assert r.stdout.decode().split() == ["True", "True", "True"], r.stderr.decode()[-2000:]


def test_apply_never_replaces_a_run_file_the_training_recording_or_a_read_only_file(tmp_path, capsys, model):
    """``apply --out`` follows export's rules: a file of another run folder, the calibration's training recording and
    a read-only file are never replaced (not even with --force); a user's file only with --force; its own output
    freely. Before, each of these was overwritten with exit status 0."""
    other, _ = _copy(model, tmp_path)
    new = _recording(tmp_path / "new.csv", seed=3)
    training = model.parent / "rec.csv"
    before = {p: p.read_bytes() for p in (other / "calibration.json", other / "metrics.json", training)}

    def apply(out, *extra):
        return main(["apply", "--model", str(model), "--data", str(new), "--out", str(out), "--no-progress", *extra])

    for force in ([], ["--force"]):
        for target in (other / "calibration.json", other / "metrics.json"):
            assert apply(target, *force) == 2 and "run folder" in _err(capsys)
        assert apply(training, *force) == 2
        err = _err(capsys)     # seventh outside pass: "Or add --force to replace it", then --force was refused
        assert "trained on" in err and "--force" not in err, err
    assert {p: p.read_bytes() for p in before} == before
    mine = tmp_path / "notes.txt"
    mine.write_text("mine\n")
    assert apply(mine) == 2 and "--force" in _err(capsys) and mine.read_text() == "mine\n"
    assert apply(mine, "--force") == 0 and mine.read_text().startswith("time,run,x_")
    out = tmp_path / "calibrated.csv"
    assert apply(out) == 0 and apply(out) == 0                     # its own output: replaced freely
    locked = tmp_path / "locked.csv"
    locked.write_text("protected\n")
    locked.chmod(0o444)
    assert apply(locked, "--force") == 2 and "read-only" in _err(capsys)
    assert _export(model, "px4", locked, "--force") == 2 and "read-only" in _err(capsys)
    assert locked.read_text() == "protected\n"


def test_a_named_datasets_file_is_protected_as_the_training_recording(tmp_path, monkeypatch):
    """A run on a named dataset (``[data] source``) has no ``data.path``: its file, found through BAYESMAG_DATA_DIR,
    is protected all the same (``export --force`` once replaced the Belsten recording with a PX4 parameter file)."""
    from bayesmag._src.app.apply import check_apply_paths
    from bayesmag._src.app.export import ExportError, check_export_out
    from bayesmag._src.app.inputs import recording_paths
    from bayesmag._src.core.data import DataError
    f = tmp_path / "data" / "belsten2023" / "full_data.csv"
    f.parent.mkdir(parents=True)
    f.write_text("stand-in\n")
    monkeypatch.setenv("BAYESMAG_DATA_DIR", str(tmp_path / "data"))
    paths = recording_paths({"source": "belsten2023"})
    assert [p.resolve() for p in paths] == [f.resolve()]
    assert recording_paths({"source": "simulated"}) == [] and recording_paths(None) == []
    with pytest.raises(ExportError, match="training recording"):
        check_export_out(tmp_path, f, inputs=paths, force=True, suffix=".params")
    with pytest.raises(DataError, match="trained on"):
        check_apply_paths(tmp_path / "model", tmp_path / "new.csv", f, force=True, protected=paths)
    assert f.read_text() == "stand-in\n"


def test_a_field_run_given_to_export_or_report_says_what_it_is(tmp_path, capsys):
    """A field-calibration run folder has field_params.json and no calibration.json: export said "incomplete ...
    Re-run `bayesmag run`" (a rerun never adds one) and report "has no params.json". ``apply`` calibrates with it
    (tests/test_field_apply.py); a damaged field_params.json is named there."""
    run = tmp_path / "field_run"
    run.mkdir()
    (run / "field_params.json").write_text("{}")
    rec = _recording(tmp_path / "rec.csv")
    for argv in (["export", str(run), "--format", "px4", "--out", str(tmp_path / "o.params")],
                 ["report", str(run)]):
        assert main(argv) == 2, argv
        err = _err(capsys)
        assert "field-calibration run" in err and "Re-run" not in err, err
    assert main(["apply", "--model", str(run), "--data", str(rec), "--out", str(tmp_path / "o.csv"),
                 "--no-progress"]) == 2
    err = _err(capsys)
    assert "field_params.json lacks" in err and not (tmp_path / "o.csv").exists(), err


# ---------------------------------------------------------------------------------------------------------- data fetch
def _unreachable_dataset(monkeypatch, tmp_path, url="http://127.0.0.1:9/full_data.csv"):
    """belsten2023 pointed at ``url`` (nothing listens on the discard port: refused at once, no real network) and
    the cache in ``tmp_path``; returns the path ``fetch`` would write."""
    import dataclasses

    from bayesmag._src.core import datasets
    monkeypatch.setitem(datasets.DATASETS, "belsten2023",
                        dataclasses.replace(datasets.DATASETS["belsten2023"], url=url))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    return tmp_path / "cache" / "bayesmag" / "belsten2023" / "full_data.csv"


def test_data_fetch_without_network_is_one_line_naming_the_url_the_path_and_the_fixes(tmp_path, monkeypatch, capsys):
    """Seventh outside pass: it printed only urllib's '<urlopen error [Errno 111] Connection refused>'."""
    url = "http://127.0.0.1:9/full_data.csv"
    target = _unreachable_dataset(monkeypatch, tmp_path, url)
    assert main(["data", "fetch", "belsten2023"]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and err.startswith("bayesmag: error: Could not download dataset 'belsten2023'")
    assert url in err and "Connection refused" in err and f"nothing was written to {target}" in err
    assert f"Download {url} by hand to {target}" in err
    assert "set BAYESMAG_DATA_DIR to a folder holding belsten2023/full_data.csv" in err
    assert not (tmp_path / "cache" / "bayesmag").exists()         # no partial file, no folder it made


def test_data_fetch_dropped_midway_leaves_no_partial_file(tmp_path, monkeypatch, capsys):
    """A connection that drops after the first megabyte: one line, and neither the file nor its partial sibling."""
    import urllib.request

    target = _unreachable_dataset(monkeypatch, tmp_path)
    target.parent.mkdir(parents=True)
    (target.parent / "notes.txt").write_text("mine\n")            # a folder that existed keeps what it held

    class Dropping:
        def __init__(self):
            self.sent = False

        def read(self, n=-1):
            if self.sent or n is None or n < 0:       # reading to the end runs into the drop
                raise ConnectionResetError(104, "Connection reset by peer")
            self.sent = True
            return b"t" * n

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

    monkeypatch.setattr(urllib.request, "urlopen", lambda *a, **k: Dropping())
    assert main(["data", "fetch", "belsten2023"]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "Connection reset by peer" in err and "by hand to" in err
    assert sorted(p.name for p in target.parent.iterdir()) == ["notes.txt"]


# ------------------------------------------------------------------------------- interrupts: children, and the one line
def _sigint_blocked(status: str) -> bool:
    """Whether a /proc/<pid>/status text shows SIGINT blocked (SigBlk, bit 2 - 1)."""
    line = next(x for x in status.splitlines() if x.startswith("SigBlk:"))
    return bool(int(line.split()[1], 16) & (1 << (signal.SIGINT - 1)))


@pytest.mark.skipif(not hasattr(signal, "pthread_sigmask") or not Path("/proc/self/status").exists(),
                    reason="POSIX signal masks and /proc")
def test_children_started_under_parent_decides_never_take_sigint():
    """Seventh outside pass: a Ctrl-C during a Dask apply printed the workers' KeyboardInterrupt tracebacks (36-80
    lines) before the one line: the terminal sends SIGINT to the whole process group. A child started in the block,
    or later by a thread started in it (a cluster restarting a worker), has SIGINT blocked; this thread's mask is
    restored after it, and a SIGINT sent meanwhile is not lost."""
    import threading

    from bayesmag._src.app.signals import parent_decides
    probe = [sys.executable, "-c", "print(open('/proc/self/status').read())"]
    got, go = {}, threading.Event()

    def later():                    # a thread started in the block starts its child after the block ended
        go.wait(10)
        got["later"] = subprocess.run(probe, capture_output=True, text=True).stdout

    caught = []
    old = signal.signal(signal.SIGINT, lambda s, f: caught.append(s))
    try:
        with parent_decides():
            got["inside"] = subprocess.run(probe, capture_output=True, text=True).stdout
            t = threading.Thread(target=later)
            t.start()
            os.kill(os.getpid(), signal.SIGINT)            # taken by another thread, or pending until the block ends
        go.set()
        t.join(10)
        got["after"] = subprocess.run(probe, capture_output=True, text=True).stdout
        deadline = time.monotonic() + 2
        while not caught and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        signal.signal(signal.SIGINT, old)
    assert _sigint_blocked(got["inside"]) and _sigint_blocked(got["later"])
    assert not _sigint_blocked(got["after"])               # the caller's own mask, as before the block
    assert caught == [signal.SIGINT]


def test_after_an_interrupt_the_one_line_is_all_that_stderr_gets(tmp_path):
    """What other threads print while the command stops (a Dask scheduler's 'Task exception was never retrieved' as
    its workers went) came before the one line; from the signal on, stderr is /dev/null but for that line."""
    script = tmp_path / "stop.py"
    script.write_text(textwrap.dedent("""
        import os, signal, sys, threading, time
        from bayesmag._src.app import signals
        print("before the signal", file=sys.stderr)
        with signals.handling():
            try:
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(5)
            except signals.Interrupted as e:
                t = threading.Thread(target=lambda: print("noise from a thread", file=sys.stderr))
                t.start()
                t.join()
                print("noise from the unwinding", file=sys.stderr)
                signals.announce(e.signum)
                sys.stderr.flush()
                os._exit(e.code)
    """))
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=60, env=_env())
    assert r.returncode == 130, r.stderr
    assert r.stderr.splitlines() == ["before the signal", "bayesmag: interrupted by SIGINT; stopped without leaving "
                                     "a partial result."], r.stderr


# ------------------------------------------------------------------------------------------------ apply's unit file
def test_apply_writes_a_unit_file_beside_its_csv(tmp_path, capsys, model):
    """Seventh outside pass: the apply CSV carried no unit. Now ``<out>.json`` beside it: the unit of every column,
    the calibration (folder, certificate ID, sha256), level, recording, bayesmag version and the CSV's sha256; the
    CSV reads as before. A rerun replaces it; a user's file of that name is refused (checked before any work) unless
    --force."""
    import pandas as pd

    from bayesmag._src.app.apply_io import is_apply_output
    from bayesmag._src.core.datasets import sha256_of
    from bayesmag._src.core.version import __version__
    rec = _recording(tmp_path / "new.csv", n=150, seed=5)
    out = tmp_path / "calibrated.csv"
    assert main(["apply", "--model", str(model), "--data", str(rec), "--out", str(out), "--no-progress"]) == 0
    _err(capsys)
    df = pd.read_csv(out)                                       # a reader of today's columns: unchanged
    assert len(df) == 150 and list(df.columns)[:3] == ["time", "run", "x_calibrated"] and is_apply_output(out)
    doc = json.loads((tmp_path / "calibrated.csv.json").read_text())
    assert doc["tool"] == "bayesmag" and doc["kind"] == "apply-output" and doc["bayesmag_version"] == __version__
    assert list(doc["units"]) == list(df.columns)              # every column, in the file's order
    assert doc["units"]["time"] == "s" and doc["units"]["valid"] == "1"
    assert {doc["units"][c] for c in df.columns if c[:2] in ("x_", "y_", "z_")} == {"uT"}
    assert "16 magnitude" in doc["meaning"]["in_domain_reason"]
    cert = json.loads((model / "metrics.json").read_text())["certificate"]
    assert doc["calibration"]["calibration_id"] == cert["calibration_id"] and doc["calibration"]["kind"] == "vector"
    assert doc["calibration"]["folder"] == str(model.resolve())
    assert doc["calibration"]["sha256"] == sha256_of(model / "calibration.json")
    assert doc["files"] == {"calibrated.csv": {"rows": 150, "sha256": sha256_of(out)}} and doc["level"] == 0.95
    assert doc["data"] == str(rec.resolve())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibrated.csv", "calibrated.csv.json", "new.csv"]

    assert main(["apply", "--model", str(model), "--data", str(rec), "--out", str(out), "--level", "0.9"]) == 0
    assert json.loads((tmp_path / "calibrated.csv.json").read_text())["level"] == 0.9     # its own: replaced
    _err(capsys)

    mine = tmp_path / "mine.csv.json"
    mine.write_text('{"my": "notes"}')
    rc = main(["apply", "--model", str(model), "--data", str(rec), "--out", str(tmp_path / "mine.csv")])
    err = _err(capsys)
    assert rc == 2 and len(err.splitlines()) == 1 and f"its unit file {mine}" in err and "--force" in err, err
    assert mine.read_text() == '{"my": "notes"}' and not (tmp_path / "mine.csv").exists()
    assert main(["apply", "--model", str(model), "--data", str(rec), "--out", str(tmp_path / "mine.csv"),
                 "--force"]) == 0
    assert json.loads(mine.read_text())["kind"] == "apply-output"


def test_the_unit_file_states_the_intervals_family_the_conversions_and_the_recording(tmp_path, capsys, model):
    """Seventh outside pass, unit file: it named no predictive family (a Laplace hybrid's intervals rebuilt as 1.96 x
    total are 8 % too narrow), not the declared --field-unit / --temperature-unit / --time-unit / --columns, nor the
    input recording's sha256. Now it states all three."""
    import pandas as pd

    from bayesmag._src.core.datasets import sha256_of
    rec = _recording(tmp_path / "new.csv", n=120, seed=6)
    df = pd.read_csv(rec).rename(columns={"temperature": "T_K", "time": "t_ms"})
    df["T_K"] += 273.15
    df["t_ms"] *= 1000.0
    df.to_csv(tmp_path / "odd.csv", index=False)
    out = tmp_path / "o.csv"
    assert main(["apply", "--model", str(model), "--data", str(tmp_path / "odd.csv"), "--out", str(out),
                 "--columns", "temperature=T_K,time=t_ms", "--temperature-unit", "K", "--time-unit", "ms",
                 "--no-progress"]) == 0
    _err(capsys)
    doc = json.loads((tmp_path / "o.csv.json").read_text())
    iv = doc["intervals"]
    assert iv["family"] == "gaussian" and abs(iv["interval_factor"] - 1.959964) < 1e-5 and iv["level"] == 0.95
    got = pd.read_csv(out)
    np.testing.assert_allclose(got["x_upper"] - got["x_calibrated"], iv["interval_factor"] * got["x_total"],
                               rtol=1e-6)                         # the rule it states is the file's
    c = doc["conversions"]
    assert c["field_unit"] is None and c["temperature_unit"] == "K" and c["time_unit"] == "ms"
    assert c["columns"] == {"temperature": "T_K", "time": "t_ms"}
    assert doc["data_sha256"] == sha256_of(tmp_path / "odd.csv") and "data_sha256_not_recorded" not in doc


def test_the_unit_file_names_a_hybrids_family_and_its_shape():
    """A hybrid's intervals are its likelihood's: the unit file names the family (``hybrid_family``, as
    predictions.csv), a fixed shape (Student-t df) and the half-width factor where it is one for every row (Laplace
    2.118 at 95 %, not 1.96); a learned dof is named as learned per row, with no factor."""
    from types import SimpleNamespace

    from bayesmag._src.app.apply_io import interval_family
    from bayesmag._src.core.network import NetworkSpec

    def cal(fusion="moment_match", **spec):
        return SimpleNamespace(network={"meta": {"spec": NetworkSpec(**spec).to_dict(), "fusion": fusion}})

    assert interval_family(SimpleNamespace(network=None), 0.95)["family"] == "gaussian"
    lap = interval_family(cal(likelihood="laplace"), 0.95)
    assert lap["family"] == lap["hybrid_family"] == "laplace" and abs(lap["interval_factor"] - 2.1183) < 1e-3
    t = interval_family(cal(likelihood="student_t", student_t_df=5.0), 0.9)
    import scipy.stats
    unit_sd = scipy.stats.t.ppf(0.95, 5) * np.sqrt(3 / 5)                   # the 90 % quantile of a unit-sd t(5)
    assert t["family"] == "student_t" and t["shape"] == {"df": 5.0} and abs(t["interval_factor"] - unit_sd) < 1e-9
    learned = interval_family(cal(likelihood="student_t", student_t_df="learn"), 0.95)
    assert learned["interval_factor"] is None and learned["shape_learned_per_row"] == ["df"]
    assert "use lower and upper as written" in learned["rule"]
    paper = interval_family(cal(fusion="paper", likelihood="laplace"), 0.95)
    assert paper["family"] == "gaussian" and paper["hybrid_family"] == "laplace"


def test_a_field_unit_file_describes_the_field_columns():
    """A field apply's unit file described the vector columns ("uT columns": aleatoric, residual, ...) and stated uT
    for a relative calibration (``field = "free"``). Now: each field column's meaning, the bits 1/2/16, and
    "1 (relative)" for every field value of a relative one."""
    from bayesmag._src.app.apply_io import RELATIVE_UNIT, field_intervals, sidecar_doc
    from bayesmag._src.app.field_apply import FIELD_OUTPUT_COLUMNS
    cols = ["time", "run", *FIELD_OUTPUT_COLUMNS, "in_domain_reason", "in_domain", "valid"]
    about = {"calibration": {"kind": "field"}, "level": 0.95,
             "intervals": field_intervals({"level": 0.95, "kind": "field", "measurement": "scalar"})}
    doc = sidecar_doc(about, cols, rows=3, files={})
    m = doc["meaning"]
    assert "uT columns" not in m and set(FIELD_OUTPUT_COLUMNS) <= set(m)
    assert "clipped at 0" in m["magnitude_lower"] and "transfer" in m["magnitude_total"]
    assert "1 field_range" in m["in_domain_reason"] and "16 magnitude" in m["in_domain_reason"]
    assert "4 field_rate" not in m["in_domain_reason"]
    assert doc["units"]["magnitude_total"] == "uT" and doc["intervals"]["family"] == "gaussian"
    rel = sidecar_doc({**about, "relative": "fitted with field = free"}, cols, rows=3, files={})
    assert {rel["units"][c] for c in FIELD_OUTPUT_COLUMNS} == {RELATIVE_UNIT} and rel["units"]["time"] == "s"
    assert RELATIVE_UNIT in rel["meaning"]["magnitude"]


def test_applying_to_the_training_recording_says_its_rows_are_the_training_sessions(tmp_path, capsys, model):
    """Seventh outside pass: apply on the calibration's own training recording gave no word that its rows got the
    new-session intervals (transfer added). Its sha256 is the certificate's data_sha256: a note says so and where
    the same-session intervals are; a new recording gets no such note."""
    training = model.parent / "rec.csv"
    assert main(["apply", "--model", str(model), "--data", str(training), "--out", str(tmp_path / "o.csv"),
                 "--no-progress"]) == 0
    out = capsys.readouterr().out
    note = [ln for ln in out.splitlines() if "trained on" in ln]
    assert len(note) == 1 and "new_session=False" in note[0] and "predictions.csv" in note[0], out
    rec = _recording(tmp_path / "new.csv", n=100, seed=9)
    assert main(["apply", "--model", str(model), "--data", str(rec), "--out", str(tmp_path / "n.csv"),
                 "--no-progress"]) == 0
    assert "trained on" not in capsys.readouterr().out


def test_every_apply_column_has_a_unit():
    """The vector, field and archive outputs' columns all get a unit from one table (a new column must add one)."""
    from bayesmag._src.app.apply import OUTPUT_COLUMNS
    from bayesmag._src.app.apply_io import column_units
    from bayesmag._src.app.field_apply import FIELD_OUTPUT_COLUMNS
    vector = [f"{a}_{c}" for a in "xyz" for c in OUTPUT_COLUMNS]
    units = column_units(["time", "run", *vector, *FIELD_OUTPUT_COLUMNS, "in_domain_reason", "in_domain", "valid"])
    assert units["time"] == "s" and units["magnitude_total"] == "uT" and units["x_lower"] == "uT"
    with pytest.raises(ValueError, match="'heading' has no known unit"):
        column_units(["heading"])


@pytest.mark.extended
def test_a_field_apply_writes_its_unit_file_and_a_stale_one_never_stays(tmp_path, capsys):
    """The field apply's CSV gets the same unit file (calibration kind 'field'); the CSV writer removes an earlier
    apply's unit file before the new CSV is renamed into place, so none ever describes another result (15-25 s: a
    field run)."""
    import numpy as np

    import bayesmag
    from bayesmag._src.app.apply_io import write_apply_csv
    from bayesmag.simulate import simulate_field
    c = simulate_field("dance", n=900, seed=4, temperature=(15.0, 35.0))
    rows = {"time": c.data.time, "run": c.data.run, "bx_meas": c.data.b_meas[:, 0], "by_meas": c.data.b_meas[:, 1],
            "bz_meas": c.data.b_meas[:, 2], "temperature": c.data.temperature, "F_ovh": c.f_ref}
    import pandas as pd
    pd.DataFrame(rows).iloc[:700].to_csv(tmp_path / "train.csv", index=False)
    pd.DataFrame(rows).iloc[700:].to_csv(tmp_path / "new.csv", index=False)
    from bayesmag._src.app.config import config_from_dict
    cfg = config_from_dict({"name": "f", "data": {"path": str(tmp_path / "train.csv")},
                            "measurement": {"kind": "scalar", "scalar_column": "F_ovh", "exports": []},
                            "split": {"kind": "time_blocks", "test_fraction": 0.2, "n_blocks": 2},
                            "physics": {"t0": "mean"}, "output": {"figures": False, "progress": False}})
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        bayesmag.run_job(cfg, tmp_path / "run")
    out = tmp_path / "f.csv"
    assert main(["apply", "--model", str(tmp_path / "run"), "--data", str(tmp_path / "new.csv"), "--out",
                 str(out)]) == 0
    capsys.readouterr()
    doc = json.loads((tmp_path / "f.csv.json").read_text())
    assert doc["calibration"]["kind"] == "field" and doc["calibration"]["file"] == "field_params.json"
    assert list(doc["units"]) == list(pd.read_csv(out).columns) and doc["units"]["magnitude_upper"] == "uT"
    from bayesmag._src.core.datasets import sha256_of
    assert "uT columns" not in doc["meaning"] and "magnitude_transfer" in doc["meaning"]      # the field's columns
    assert doc["intervals"]["family"] == "gaussian" and doc["intervals"]["measurement"] == "scalar"
    assert doc["data_sha256"] == sha256_of(tmp_path / "new.csv") and doc["conversions"]["field_unit"] is None
    for force in ([], ["--force"]):                 # its training recording: refused, never with a --force hint
        assert main(["apply", "--model", str(tmp_path / "run"), "--data", str(tmp_path / "new.csv"), "--out",
                     str(tmp_path / "train.csv"), *force]) == 2
        err = capsys.readouterr().err
        assert "trained on" in err and "--force" not in err, err
    data = bayesmag.load_csv(tmp_path / "new.csv", require_reference=False)
    pred = {"in_domain_reason": [""] * data.n, "in_domain": np.ones(data.n, bool), "valid": np.ones(data.n, bool)}
    write_apply_csv(out, data, [("x_calibrated", np.zeros(data.n))], pred)
    assert not (tmp_path / "f.csv.json").exists()               # a CSV without its file, never with another's


@pytest.mark.extended
def test_a_relative_field_calibrations_unit_file_says_relative(tmp_path, capsys):
    """A field calibration fitted with ``field = "free"`` is relative (trace(S) = 3), and apply's summary says so;
    its unit file stated uT for every field column. Now "1 (relative)" (10-20 s: a field run)."""
    import warnings

    import pandas as pd

    import bayesmag
    from bayesmag._src.app.apply_io import RELATIVE_UNIT
    from bayesmag._src.app.config import config_from_dict
    from bayesmag.simulate import simulate_field
    c = simulate_field("dance", n=900, seed=1, temperature=(15.0, 35.0))
    pd.DataFrame({"time": c.data.time, "run": c.data.run, "bx_meas": c.data.b_meas[:, 0],
                  "by_meas": c.data.b_meas[:, 1], "bz_meas": c.data.b_meas[:, 2],
                  "temperature": c.data.temperature}).to_csv(tmp_path / "r.csv", index=False)
    cfg = config_from_dict({"name": "free", "data": {"path": str(tmp_path / "r.csv")},
                            "measurement": {"kind": "constant", "field": "free", "exports": []},
                            "split": {"kind": "time_blocks", "test_fraction": 0.2, "n_blocks": 2},
                            "physics": {"t0": "mean"}, "output": {"figures": False, "progress": False}})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        bayesmag.run_job(cfg, tmp_path / "run")
    assert main(["apply", "--model", str(tmp_path / "run"), "--data", str(tmp_path / "r.csv"), "--out",
                 str(tmp_path / "o.csv")]) == 0
    out = capsys.readouterr()
    assert "relative" in out.err and "trained on" in out.out         # the summary's warning; its training recording
    doc = json.loads((tmp_path / "o.csv.json").read_text())
    assert {doc["units"][c] for c in doc["units"] if c.startswith(("x_", "y_", "z_", "magnitude"))} == {RELATIVE_UNIT}
    assert "relative" in doc and RELATIVE_UNIT in doc["meaning"]["magnitude"]
