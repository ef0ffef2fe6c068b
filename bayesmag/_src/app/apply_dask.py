"""``bayesmag apply`` at archive scale: a partitioned Parquet dataset or a glob of CSV files through Dask.

The calibration is loaded and checked once on the client, sent once to every worker
(``Client.scatter(..., broadcast=True)``), and every partition is calibrated on its own by
:meth:`~bayesmag._src.app.artifact.Calibration.predict` (the in-process ``apply``'s code) and written by
the worker that computed it as ``part.<k>.parquet`` into a staging folder beside ``--out``; only a
small per-partition summary returns to the client. The staging folder replaces ``--out`` only when
every partition is written (``outdir.staging_dir``), so a failed run leaves no half-written dataset; it holds the
dataset's unit file too (``_bayesmag_apply.json``: :mod:`~bayesmag._src.app.apply_io`).

Partitions (``pieces``): one per Parquet row group, or one per ``blocksize`` bytes of a CSV file
(a line belongs to the block its first byte lies in), so memory per task is bounded by the
partition, whatever the input size. Bad input is one line naming the file, the partition and the
row. Rows are independent, except the domain's rate check (``|dB/dt|``, ``|dT/dt|``), which compares
each row with its time neighbours, the input transforms (thermal lag, timing offset), which remember
rows on both sides, and a hysteresis state, set by earlier rows: every partition is predicted with the
file rows before and after it that these need (read, predicted, dropped; :func:`_context`), so a
time-sorted file gets the whole-file apply's numbers and flags.
"""

from __future__ import annotations

import glob as globlib
import io
import json
import logging
import time
import warnings
from pathlib import Path

import numpy as np

from bayesmag._src.app.apply_io import DATASET_SIDECAR
from bayesmag._src.core.data import AXES, DataError, check_values
from bayesmag._src.core.domain import REASON_CODES

__all__ = ["apply_dask", "is_archive", "list_pieces", "calibrate_piece"]

# The columns of `bayesmag apply`'s output, in its order (copied from app/apply.py's OUTPUT_COLUMNS so this module
# does not depend on that module's internals; tests/test_apply_dask.py checks both outputs have the same columns).
OUTPUT_COLUMNS = ("calibrated", "aleatoric_physics", "epistemic_physics", "residual_physics", "aleatoric_nn",
                  "epistemic_nn", "transfer", "total", "lower", "upper")
_PARQUET = (".parquet", ".pq")


def is_archive(data: str) -> bool:
    """True when ``--data`` names a folder (a partitioned Parquet dataset, or CSV files) or a glob: the Dask path.
    One CSV or Parquet file stays in process (``apply.apply_calibration``) unless ``--scheduler`` is given."""
    return Path(data).is_dir() or (any(c in str(data) for c in "*?[") and not Path(data).exists())


def _files(data: str) -> list[Path]:
    p = Path(data)
    if p.is_dir():
        files = sorted(q for q in p.rglob("*") if q.is_file() and q.suffix.lower() in _PARQUET + (".csv",)
                       and not any(part.startswith((".", "_")) for part in q.relative_to(p).parts))
    elif any(c in str(data) for c in "*?["):
        files = sorted(Path(q) for q in globlib.glob(str(data), recursive=True) if Path(q).is_file())
    else:
        files = [p] if p.is_file() else []
    if not files:
        raise DataError(f"--data {data} matches no file (give a Parquet dataset folder, a Parquet file or a glob of "
                        f"CSV files such as 'logs/*.csv').")
    kinds = {q.suffix.lower() in _PARQUET for q in files}
    if len(kinds) > 1:
        raise DataError(f"--data {data} mixes Parquet and CSV files; give one kind.")
    bad = [q for q in files if q.suffix.lower() not in _PARQUET + (".csv",)]
    if bad:
        raise DataError(f"--data {data}: {bad[0]} is neither .csv nor .parquet; narrow the glob.")
    return files


def list_pieces(data: str, *, blocksize: int = 16 * 2**20) -> list[tuple]:
    """The partitions of ``data``: ``("parquet", path, row_group, first_row)`` or ``("csv", path, start, end, header)``.

    Only file footers (Parquet) and first lines (CSV) are read here.
    """
    pieces = []
    for f in _files(data):
        if f.suffix.lower() in _PARQUET:
            import pyarrow.parquet as pq
            try:
                meta = pq.ParquetFile(f).metadata
            except Exception as e:
                raise DataError(f"{f} cannot be read as Parquet ({type(e).__name__}: {e}).") from None
            first = 0
            for g in range(meta.num_row_groups):
                pieces.append(("parquet", str(f), g, first, meta.num_row_groups))
                first += meta.row_group(g).num_rows
        else:
            with open(f, "rb") as fh:
                header = fh.readline()
                start = fh.tell()
            size = f.stat().st_size
            if not header.strip():
                raise DataError(f"{f} is empty (no header line).")
            if size <= start:
                pieces.append(("csv", str(f), start, start, header))
            for s in range(start, size, max(int(blocksize), 1)):
                pieces.append(("csv", str(f), s, min(s + int(blocksize), size), header))
    return pieces


def _lines_before(path: str, pos: int) -> int:
    """Newlines in the first ``pos`` bytes of ``path`` (read only on the error path)."""
    n, left = 0, pos
    with open(path, "rb") as fh:
        while left > 0:
            buf = fh.read(min(left, 1 << 24))
            if not buf:
                break
            n += buf.count(b"\n")
            left -= len(buf)
    return n


def _read_piece(piece, index: int) -> tuple:
    """``(DataFrame, where, first_row)``: the rows of partition ``index``, a description, and the file's data-row
    number of its first row (1 = the row after the header; None for a CSV block after the first, found only when a
    row of it is bad)."""
    import pandas as pd
    if piece[0] == "parquet":
        import pyarrow.parquet as pq
        _, path, g, first = piece[:4]
        df = pq.ParquetFile(path).read_row_group(g).to_pandas()
        return df, f"partition {index}: {path} (row group {g})", first + 1
    _, path, start, end, header = piece
    with open(path, "rb") as fh:
        if start > len(header):
            fh.seek(start - 1)
            fh.readline()                     # the line that began before this block belongs to the previous one
        else:
            fh.seek(start)
        pos = fh.tell()
        body = fh.read(max(end - pos, 0))
        if body and not body.endswith(b"\n"):
            body += fh.readline()
    first = 1 if start <= len(header) else None
    where = f"partition {index}: {path} (bytes {start}-{end})"
    if not body.strip():
        return pd.read_csv(io.BytesIO(header)), where, first
    try:
        return pd.read_csv(io.BytesIO(header + body), dtype=np.float64), where, first
    except (ValueError, TypeError):
        raw = pd.read_csv(io.BytesIO(header + body), dtype=str, keep_default_na=False)
        for col in raw.columns:
            num = pd.to_numeric(raw[col].str.strip().replace({"": "nan"}), errors="coerce")
            bad = np.flatnonzero(num.isna().to_numpy() & ~raw[col].str.strip().str.lower()
                                 .isin(["", "nan", "na", "null"]).to_numpy())
            if bad.size:
                first = first or _lines_before(path, pos)
                raise DataError(_row_msg(where, first, int(bad[0]), f"column {col!r} has the non-numeric value "
                                         f"{raw[col].iloc[bad[0]]!r}; fix or remove that row")) from None
        raise


def _halo(piece) -> tuple:
    """The file rows just before and just after a partition (DataFrames of one row, or None at a file's ends or when
    unreadable): the domain's rate check then sees both time neighbours of the partition's first and last row, as
    the whole-file apply does. A bad neighbour is reported by its own partition."""
    import pandas as pd
    try:
        if piece[0] == "parquet":
            import pyarrow.parquet as pq
            _, path, g, _first, n_groups = piece
            pf = pq.ParquetFile(path)
            prev = nxt = None
            if g > 0:
                t = pf.read_row_group(g - 1)
                prev = t.slice(t.num_rows - 1, 1).to_pandas() if t.num_rows else None
            if g < n_groups - 1:
                t = pf.read_row_group(g + 1)
                nxt = t.slice(0, 1).to_pandas() if t.num_rows else None
            return prev, nxt
        _, path, start, end, header = piece
        pos = _block_start(piece)
        prev_line = next_line = b""
        with open(path, "rb") as fh:
            if pos > len(header):
                lo = max(pos - 65536, len(header))
                fh.seek(lo)
                chunk = fh.read(pos - lo)[:-1]                      # ends with the newline before `pos`
                if b"\n" in chunk or lo == len(header):
                    prev_line = chunk.rsplit(b"\n", 1)[-1] + b"\n"
            fh.seek(max(end - 1, 0))
            if end > len(header):
                fh.readline()                                        # rest of this block's last line
                next_line = fh.readline()

        def one(line):
            if not line.strip():
                return None
            return pd.read_csv(io.BytesIO(header + line), dtype=np.float64)
        return one(prev_line), one(next_line)
    except (ValueError, TypeError, OSError):
        return None, None


def _invalid_rows(table, pieces, limit: int = 10) -> list[str]:
    """The first ``limit`` rows no partition could calibrate, as "FILE data row N" (1-based, the header not counted,
    as the in-process apply names them): each partition's local indices offset by the rows of the same file's
    earlier partitions (partitions of a file are listed in order; every row in is a row out)."""
    shown, seen = [], {}
    for _, r in table.sort_values("partition").iterrows():
        path = str(pieces[int(r["partition"])][1])
        start = seen.get(path, 0)
        seen[path] = start + int(r["rows_in"])
        for i in str(r.get("invalid", "") or "").split(","):
            if i.strip() and len(shown) < limit:
                shown.append(f"{path} data row {start + int(i) + 1}")
    return shown


#: Partitions read before one for a history term's state (:func:`_context`); beyond it, a warning.
MAX_HISTORY_PIECES = 50
#: Partitions read on each side for the input transforms' memory, as ``Calibration.predict``'s 10 chunks.
MAX_MEMORY_PIECES = 10


class _Pieces:
    """Every partition of an apply, sent to the workers as one object (``Client.scatter`` sends a list or tuple
    element by element)."""

    def __init__(self, items):
        self.items = tuple(items)

    def __len__(self):
        return len(self.items)

    def __getitem__(self, j):
        return self.items[j]


def _same_file(pieces, index: int, step: int):
    """Indices of the partitions of ``pieces[index]``'s file before (``step=-1``) or after it, nearest first."""
    j = index + step
    while 0 <= j < len(pieces) and pieces[j][1] == pieces[index][1]:
        yield j
        j += step


def _context(piece, index: int, df, data, cal, opts: dict, pieces) -> tuple:
    """``(before, after, warning)``: the file rows to predict partition ``index`` with, so it gets what the whole-file
    apply gives (``Calibration.predict``), dropped again afterwards.

    * always the row just before and after (the domain's rate check compares time neighbours: :func:`_halo`);
    * with input transforms (thermal lag, timing offset) the rows they remember on each side
      (``PhysicsModel.memory_rows`` at the partition's median time step; a whole partition if not known);
    * with a history term (hysteresis) every earlier partition of the file back to one whose rows set the state
      (``PhysicsModel.history_settled``), at most :data:`MAX_HISTORY_PIECES`; the warning says when that was not
      enough (the state is then that of those partitions alone).
    """
    import pandas as pd
    from bayesmag._src.core.frames import from_frame
    from bayesmag._src.core.physics import inputs_from_data, median_step
    model = cal.model
    need = 1
    if model.transforms and data.n:
        k = model.memory_rows(cal.theta, median_step(data.time) or 1.0)
        need = None if k is None else max(int(k), 1)
    if pieces is None or (need == 1 and not model.has_history):
        return (*_halo(piece), None)

    read: dict = {}

    def frame(js):
        for j in js:
            if j not in read:
                p = _read_piece(pieces[j], j)[0]
                read[j] = p if len(p) and list(p.columns) == list(df.columns) else None
        parts = [read[j] for j in sorted(js) if read[j] is not None]
        return pd.concat(parts, ignore_index=True) if parts else None

    def settled(before) -> bool:
        d = from_frame(before, columns=opts["columns"], temperature_unit=opts["temperature_unit"],
                       time_unit=opts.get("time_unit", "s"), field_unit=opts["field_unit"], source="context")
        ok = np.isfinite(np.column_stack([d.b_meas, d.temperature])).all(axis=1) & np.isfinite(d.time)
        return model.history_settled(inputs_from_data(d.subset(np.flatnonzero(ok))))

    after, nxt = [], None
    for j in _same_file(pieces, index, +1):
        after.append(j)
        nxt = frame(after)
        if need is None or (nxt is not None and len(nxt) >= need) or len(after) >= MAX_MEMORY_PIECES:
            break
    if nxt is not None and need is not None:
        nxt = nxt.iloc[:need]
    before, prev, note = [], None, None
    for j in _same_file(pieces, index, -1):
        before.append(j)
        prev = frame(before)
        enough = need is None or (prev is not None and len(prev) >= need) or len(before) >= MAX_MEMORY_PIECES
        if not model.has_history:
            if enough:
                break
        elif enough and prev is not None and settled(prev):
            break
        elif len(before) >= MAX_HISTORY_PIECES:
            note = (f"partition {index}: the hysteresis state at its first row is not set by the "
                    f"{MAX_HISTORY_PIECES} partitions before it; it is taken from those partitions alone "
                    f"(larger partitions, or one file per run, avoid this)")
            break
    if prev is not None and need is not None and not model.has_history:
        prev = prev.iloc[-need:]
    return prev, nxt, note


def _block_start(piece) -> int:
    """Byte position of the first line of a CSV block (the line after the one running over its start)."""
    _, path, start, _end, header = piece
    if start <= len(header):
        return start
    with open(path, "rb") as fh:
        fh.seek(start - 1)
        fh.readline()
        return fh.tell()


def _row_msg(where: str, first, k: int, what: str) -> str:
    row = f"data row {first + k} of the file" if first is not None else f"row {k + 1} of this block"
    return f"{where}, {row}: {what}."


def calibrate_piece(piece, index: int, cal, opts: dict, out_dir: str, pieces: list | None = None) -> "object":
    """Calibrate partition ``index`` (``piece``) and write ``part.<index>.parquet`` into ``out_dir``; return a one-row
    summary DataFrame (rows in/out, valid, outside domain, reference sums, warnings). ``pieces``: every partition
    (:func:`list_pieces`), for a model whose rows depend on neighbouring rows (:func:`_context`)."""
    import pandas as pd
    from bayesmag._src.core.frames import from_frame

    df, where, first = _read_piece(piece, index)
    try:
        data = from_frame(df, columns=opts["columns"], temperature_unit=opts["temperature_unit"],
                          time_unit=opts.get("time_unit", "s"), field_unit=opts["field_unit"], source=where)
        check_values(data, origin="the partition", allow_nonfinite=True)
    except DataError as e:
        if first is None and piece[0] == "csv":
            first = _lines_before(piece[1], _block_start(piece))
        raise DataError(f"{where} (its row 1 is data row {first} of the file): "
                        f"{' '.join(str(e).split())}") from None
    n = data.n
    warns: list[str] = []
    if n:
        from bayesmag._src.app.apply import check_units, new_session_notes
        try:
            warns = check_units(cal, data, small_ok=True) + new_session_notes(cal)   # mT: on the whole, below
            step = cal.domain.step_note(data) if data.n > 1 else None     # as the in-process apply
            if step:
                warns.append(step)
        except DataError as e:
            raise DataError(f"{where}: {' '.join(str(e).split())}") from None
        prev, nxt, note = _context(piece, index, df, data, cal, opts, pieces)
        if note:
            warns.append(note)
        prev, nxt = (h if h is not None and len(h) and list(h.columns) == list(df.columns) else None
                     for h in (prev, nxt))
        lo, full = (0 if prev is None else len(prev)), data
        if prev is not None or nxt is not None:
            try:
                full = from_frame(pd.concat([h for h in (prev, df, nxt) if h is not None], ignore_index=True),
                                  columns=opts["columns"], temperature_unit=opts["temperature_unit"],
                                  time_unit=opts.get("time_unit", "s"), field_unit=opts["field_unit"], source=where)
            except DataError:
                lo, full = 0, data
        pred = cal.predict(full, level=opts["level"], method=opts["method"], n_params=opts["n_params"],
                           n_qmc=opts["n_qmc"], chunk_size=opts["chunk_size"], seed=opts.get("seed", 0),
                           check_units=False,
                           warn=False)                                                    # checked and said above
        if full is not data:                                      # drop the neighbour rows again
            pred = {k: np.asarray(v)[lo:lo + n] for k, v in pred.items()}
    else:
        pred = {"valid": np.zeros(0, bool), "in_domain": np.zeros(0, bool), "in_domain_reason": np.zeros(0, object),
                **{c: np.zeros((0, 3)) for c in OUTPUT_COLUMNS if c in opts["columns_out"]}}
    cols = {"time": np.asarray(data.time, np.float64), "run": np.asarray(data.run, np.int64)}
    for a, ax in enumerate(AXES):
        for c in opts["columns_out"]:
            cols[f"{ax}_{c}"] = np.asarray(pred[c][:, a], np.float64)
    uniq, inv = np.unique(np.asarray(pred["in_domain_reason"]).astype(str), return_inverse=True)
    cols["in_domain_reason"] = np.array([sum(REASON_CODES[k] for k in w.split(";") if k in REASON_CODES)
                                         for w in uniq], np.int64)[inv.reshape(-1)] if n else np.zeros(0, np.int64)
    cols["in_domain"] = np.asarray(pred["in_domain"], bool)
    cols["valid"] = np.asarray(pred["valid"], bool)
    out = pd.DataFrame(cols)
    if len(out) != len(df):                 # the guarantee, checked where it is made
        raise RuntimeError(f"{where}: {len(df)} rows in but {len(out)} out; nothing was written.")
    out.to_parquet(Path(out_dir) / f"part.{index:06d}.parquet", index=False)
    row = {"partition": index, "rows_in": len(df), "rows_out": len(out), "valid": int(cols["valid"].sum()),
           "outside": int((~cols["in_domain"] & cols["valid"]).sum()), "warnings": " | ".join(warns),
           "p99_meas": _p99(data.b_meas), "p99_ref": _p99(data.b_ref),
           "invalid": ",".join(str(int(i)) for i in np.flatnonzero(~cols["valid"])[:10])}
    from bayesmag._src.app.artifact import out_of_domain_counts
    counts = out_of_domain_counts(np.asarray(pred["in_domain_reason"], dtype=object)[~cols["in_domain"]
                                                                                    & cols["valid"]])
    row.update({f"outside_{k}": int(counts.get(k, 0)) for k in OUTSIDE_REASONS})
    if data.b_ref is not None and n:
        ok = cols["valid"] & np.isfinite(data.b_ref).all(axis=1)
        y, mu = data.b_ref[ok], pred["calibrated"][ok]
        inside = (y >= pred["lower"][ok]) & (y <= pred["upper"][ok])
        for a, ax in enumerate(AXES):
            row[f"sse_{ax}"] = float(np.sum((y[:, a] - mu[:, a]) ** 2))
            row[f"covered_{ax}"] = int(inside[:, a].sum())
        row["n_ref"] = int(ok.sum())
    return pd.DataFrame([row])


#: The reasons whose row counts every partition's summary holds (``outside_<reason>``), for the warning.
OUTSIDE_REASONS = ("field_range", "temperature", "field_rate", "temperature_rate")


def _p99(b) -> float:
    """The 99th percentile of |component| over the finite rows of ``b`` (NaN without any): a partition's field size."""
    if b is None:
        return float("nan")
    b = np.asarray(b, np.float64)
    ok = np.isfinite(b).all(axis=1)
    return float(np.percentile(np.abs(b[ok]), 99)) if ok.any() else float("nan")


def _check_small_field(table, cal, field_unit) -> None:
    """The mT / gauss test of :func:`~bayesmag._src.core.data.check_field_unit` on the whole recording: every
    partition's field is small against the training field (a partition alone is not refused: a near-zero-field run
    in one partition was, though the in-process apply accepts the file)."""
    from bayesmag._src.app.apply import train_max_ut
    top = train_max_ut(cal)
    if field_unit is not None or top <= 10:
        return
    for col, label in (("p99_meas", "measured field (bx_meas, by_meas, bz_meas)"),
                       ("p99_ref", "reference field (bx_ref, by_ref, bz_ref)")):
        v = np.asarray(table[col], np.float64) if col in table else np.zeros(0)
        v = v[np.isfinite(v)]
        if v.size and v.max() < top / 50:
            raise DataError(f"The {label} of every partition is at most {v.max():.3g} (99th percentile) while the "
                            f"calibration was trained on |B| up to {top:.3g} uT: the data look like mT (/1000) or "
                            f"gauss (/100). Convert them to uT, or --field-unit uT if they really are (e.g. a "
                            f"magnetically shielded recording); nothing was written.")


def _declared_unit_files(table, pieces, cal, field_unit) -> list[str]:
    """The files whose every partition's field (99th percentile, uT after the declared ``field_unit``) is over 50x
    below or above the training field: a declared unit is trusted, but one wrong for some files of an archive gave
    wrong values marked in domain without a word (sixth outside pass)."""
    from bayesmag._src.app.apply import train_max_ut
    top = train_max_ut(cal)
    if field_unit is None or top <= 10 or "p99_meas" not in table:
        return []
    by_file: dict = {}
    for _, r in table.iterrows():
        v = float(r["p99_meas"])
        if np.isfinite(v):
            by_file.setdefault(str(pieces[int(r["partition"])][1]), []).append(v < top / 50 or v > 50 * top)
    return sorted(f for f, odd in by_file.items() if all(odd))


def _reference_note(table, cal, field_unit) -> str | None:
    """Why the archive's reference columns are not scored (the in-process apply's
    :func:`~bayesmag._src.app.apply_io.reference_unit_note`, on the partitions' largest 99th percentiles), or None."""
    from bayesmag._src.app.apply import train_max_ut
    from bayesmag._src.app.apply_io import reference_unit_note
    if field_unit is None or "p99_ref" not in table:
        return None
    def top(col) -> float:
        v = np.asarray(table[col], np.float64)
        v = v[np.isfinite(v)]
        return float(v.max()) if v.size else float("nan")
    return reference_unit_note(top("p99_ref"), top("p99_meas"), train_max_ut(cal), field_unit)


def _write_sidecar(folder: Path, table, opts: dict, about: dict) -> None:
    """The dataset's unit file (:data:`~bayesmag._src.app.apply_io.DATASET_SIDECAR`): the in-process apply's, for every
    part (its rows) in the staging ``folder``, so it is swapped in with them."""
    from bayesmag._src.app.apply_io import sidecar_doc
    from bayesmag._src.app.outdir import atomic_write_text
    columns = (["time", "run"] + [f"{ax}_{c}" for ax in AXES for c in opts["columns_out"]]
               + ["in_domain_reason", "in_domain", "valid"])
    files = {f"part.{int(r['partition']):06d}.parquet": {"rows": int(r["rows_out"])} for _, r in table.iterrows()}
    doc = sidecar_doc(about, columns, rows=int(table["rows_out"].sum()), files=dict(sorted(files.items())))
    atomic_write_text(folder / DATASET_SIDECAR, json.dumps(doc, indent=2) + "\n")


def _children() -> set:
    """This process's multiprocessing children now (a local cluster's workers are such children)."""
    import multiprocessing
    return set(multiprocessing.active_children())


def _kill_children(before: set) -> None:
    """SIGKILL the multiprocessing children started since ``before`` (:func:`_children`): an interrupted apply's
    workers, also one still importing (it would otherwise outlive this process until it noticed)."""
    import contextlib
    for p in _children() - before:
        with contextlib.suppress(Exception):
            p.kill()


def _check_paths(model_dir, data, out) -> Path:
    out, model = Path(out), Path(model_dir).resolve()
    if out.suffix.lower() in _PARQUET + (".csv",) and not out.is_dir():
        raise DataError(f"--out {out}: an archive apply writes a partitioned Parquet dataset (a folder); give a folder "
                        f"name such as {out.with_suffix('')}.")
    ro = out.resolve()
    roots = {Path(p).resolve() for p in _files(data)}
    d = Path(data)
    if d.is_dir():
        roots.add(d.resolve())
    for r in roots | {model}:
        if ro == r or r.is_relative_to(ro) or (ro.is_relative_to(r) and r.is_dir()):
            raise DataError(f"--out {out} overlaps {'the calibration folder' if r == model else 'the input data'} {r}; "
                            f"writing there could overwrite it. Give an output folder outside both.")
    if not ro.parent.is_dir():
        raise DataError(f"--out {out}: the folder {ro.parent} does not exist; create it or give another path.")
    return out


def apply_dask(model_dir, data, out, *, scheduler: str | None = None, n_workers: int = 2, threads_per_worker: int = 1,
               memory_limit: str = "900MB", blocksize: int = 16 * 2**20, level=None, method: str = "auto",
               n_params: int = 100, n_qmc: int = 256, temperature_unit: str = "C", field_unit: str | None = None,
               columns: dict | None = None, chunk_size: int = 50_000, progress: bool = False,
               time_unit: str = "s") -> dict:
    """Calibrate every row of an archive (Parquet dataset folder, Parquet file, or glob of CSV files) on Dask.

    ``scheduler``: address of a running Dask scheduler (its workers must see ``data`` and ``out`` at the same paths);
    None starts a local cluster of ``n_workers`` processes with ``threads_per_worker`` threads and ``memory_limit``
    each. Writes a Parquet dataset (``part.<k>.parquet``, one per input partition, in input order) to ``out``; returns
    a summary like :func:`~bayesmag._src.app.apply.apply_calibration`'s. ``field_unit``: as ``apply``'s (None, the
    default: checked to be uT, on the whole archive; a declared unit is converted and trusted).
    """
    try:
        import dask
        import dask.dataframe as dd
        from distributed import Client, LocalCluster
    except ImportError as e:
        raise DataError(f"applying to an archive needs Dask: pip install 'bayesmag[dask]' ({e}).") from None
    import pandas as pd
    from bayesmag._src.app.apply import method_note, run_seed
    from bayesmag._src.app.apply_io import apply_about, declared_conversions, interval_family
    from bayesmag._src.app.artifact import load
    from bayesmag._src.app.outdir import reserve, staging_dir
    from bayesmag._src.app.signals import on_abort, parent_decides

    from bayesmag._src.app.artifact import is_field_run
    if is_field_run(model_dir):
        raise DataError(f"{model_dir} is a field-calibration run: `bayesmag apply` calibrates one CSV or Parquet file "
                        f"with it (--data FILE, no --scheduler); applying it to an archive on Dask is not built yet.")
    t0 = time.perf_counter()
    out = _check_paths(model_dir, data, out)
    cal = load(model_dir)
    level = cal.level if level is None else level
    if not 0 < level < 1:
        raise DataError(f"--level {level} must be in (0, 1).")
    pieces = list_pieces(data, blocksize=blocksize)
    names = ["calibrated", "aleatoric_physics", "epistemic_physics", "residual_physics", "total", "lower", "upper"]
    if cal.network is not None:
        names += ["aleatoric_nn", "epistemic_nn"]
    # as Calibration.predict's parts: a saved transfer sd, the hierarchical session model's row-wise one, or the
    # networks' own (before, a hierarchical calibration lost its transfer column here, unlike the in-process apply)
    if (cal.transfer_sd is not None or cal.sessions is not None
            or (cal.network is not None and cal.network_transfer_sd is not None)):
        names.append("transfer")
    opts = dict(columns=columns, temperature_unit=temperature_unit, field_unit=field_unit, level=level, method=method,
                time_unit=time_unit, seed=run_seed(cal),
                n_params=n_params, n_qmc=n_qmc, chunk_size=chunk_size,
                columns_out=[c for c in OUTPUT_COLUMNS if c in names])
    meta = pd.DataFrame({"partition": pd.Series(dtype="int64"), "rows_in": pd.Series(dtype="int64"),
                         "rows_out": pd.Series(dtype="int64"), "valid": pd.Series(dtype="int64"),
                         "outside": pd.Series(dtype="int64"), "warnings": pd.Series(dtype="object"),
                         "p99_meas": pd.Series(dtype="float64"), "p99_ref": pd.Series(dtype="float64"),
                         "invalid": pd.Series(dtype="object")})
    # Tasks hold no data between them: spilling and pausing would only stall a worker whose JAX runtime sits near the
    # limit; a worker past 95 % of --memory-limit is still restarted (and a partition that cannot fit is named below).
    memory = {"distributed.worker.memory.target": False, "distributed.worker.memory.spill": False,
              "distributed.worker.memory.pause": False}
    with reserve(out, inputs=[], kind="apply"), staging_dir(out, kind="apply") as tmp, dask.config.set(memory):
        cluster = client = None
        before = _children()
        forget = on_abort(lambda: _kill_children(before))     # the watchdog's exit takes the workers with it
        try:
            if scheduler:
                client = Client(scheduler, timeout="30s")
            else:
                # the workers (started by the cluster's threads) leave a Ctrl-C to this process, which stops them:
                # they printed their KeyboardInterrupt tracebacks (36-80 lines) before the one line (signals)
                with warnings.catch_warnings(), parent_decides():
                    warnings.simplefilter("ignore", UserWarning)     # "port 8787 is already in use": harmless
                    cluster = LocalCluster(n_workers=int(n_workers), threads_per_worker=int(threads_per_worker),
                                           memory_limit=memory_limit, processes=True, dashboard_address=None,
                                           silence_logs=logging.CRITICAL)   # a failed task: one line, once
                    client = Client(cluster)
            with dask.config.set({"dataframe.convert-string": False}):
                # sent once to every worker, under a key of its own (hash=False): with the default content-hash
                # key, a second apply of the same calibration on a running cluster reuses the key the previous
                # client has just released, and the scheduler can handle that release after the new scatter and
                # forget the data (dask/distributed#8576): an intermittent lost-dependency failure
                cal_f = client.scatter(cal, broadcast=True, hash=False)
                # a model whose rows depend on neighbouring rows reads neighbouring partitions (_context)
                ctx = (client.scatter(_Pieces(pieces), broadcast=True, hash=False)
                       if cal.model.needs_series else None)
                stats = dd.from_map(calibrate_piece, pieces, range(len(pieces)), args=(cal_f, opts, str(tmp), ctx),
                                    meta=meta, enforce_metadata=False, label="bayesmag-apply")
                fut = client.compute(stats)
                if progress:
                    from distributed import progress as show
                    show(fut)
                try:
                    table = fut.result()
                except Exception as e:
                    if type(e).__name__ != "KilledWorker":
                        raise
                    raise DataError(f"a Dask worker died (out of memory?) on {e}: give it more memory (--memory-limit), "
                                    f"or smaller partitions (Parquet row groups, --blocksize-mb).") from None
                _check_small_field(table, cal, opts["field_unit"])     # inside the staging: a refusal writes nothing
                about = apply_about(model_dir, data, level, intervals=interval_family(cal, level),
                                    conversions=declared_conversions(field_unit=field_unit,
                                                                     temperature_unit=temperature_unit,
                                                                     time_unit=time_unit, columns=columns))
                _write_sidecar(Path(tmp), table, opts, about)          # swapped in with the parts
        except BaseException as e:
            if not isinstance(e, Exception):          # Ctrl-C: nothing of the workers' is kept; stop them now
                _kill_children(before)
            raise
        finally:
            forget()
            if client is not None:
                client.close()
            if cluster is not None:
                cluster.close()
    rows_in, rows_out = int(table["rows_in"].sum()), int(table["rows_out"].sum())
    warns = sorted({w for s in table["warnings"] for w in str(s).split(" | ") if w})
    summary = {"n_rows": rows_out, "n_rows_in": rows_in, "n_partitions": len(pieces),
               "n_valid": int(table["valid"].sum()), "n_outside_domain": int(table["outside"].sum()),
               "warnings": warns, "level": level, "out": str(out), "units_file": str(Path(out) / DATASET_SIDECAR),
               "seconds": time.perf_counter() - t0}
    if rows_out - summary["n_valid"]:
        n_bad = rows_out - summary["n_valid"]
        shown = _invalid_rows(table, pieces)
        more = f" and {n_bad - len(shown)} more" if n_bad > len(shown) else ""
        summary["warnings"].append(f"{n_bad} row(s) have non-finite inputs or outputs and were not calibrated "
                                   f"(valid=false)" + (f": {'; '.join(shown)}{more}." if shown else "."))
    odd = _declared_unit_files(table, pieces, cal, opts["field_unit"])
    if odd:
        summary["warnings"].append(f"with the declared --field-unit {opts['field_unit']}, the measured field of "
                                   f"{', '.join(odd[:5])}{' and more' if len(odd) > 5 else ''} is over 50x smaller "
                                   f"or larger than the calibration's training field: if those files are in another "
                                   f"unit (uT already?), their calibrated values are wrong by that factor.")
    note = method_note(cal, method)
    if note:
        summary["notes"] = [note]
    if summary["n_outside_domain"]:
        from bayesmag._src.app.artifact import out_of_domain_note
        by = {k: int(table[f"outside_{k}"].sum()) for k in OUTSIDE_REASONS if f"outside_{k}" in table}
        summary["outside_domain_by_reason"] = {k: v for k, v in by.items() if v}
        summary["warnings"].append(out_of_domain_note(summary["n_outside_domain"], rows_out,
                                                      summary["outside_domain_by_reason"]))
    ref_note = _reference_note(table, cal, opts["field_unit"])
    if ref_note:
        summary["warnings"].append(ref_note)
    elif "n_ref" in table and table["n_ref"].sum() > 0:
        n_ref = float(table["n_ref"].sum())
        summary["metrics"] = {"rmse": {ax: float(np.sqrt(table[f"sse_{ax}"].sum() / n_ref)) for ax in AXES},
                              "coverage": {ax: float(table[f"covered_{ax}"].sum() / n_ref) for ax in AXES}}
    return summary

