"""Run a design study on a Dask cluster; results as Parquet and CSV.

:func:`run_study` builds and validates every case (:mod:`study`), skips the
cases already in the output folder (resume), sends the others in chunks to
a Dask cluster (``distributed``: a ``LocalCluster`` of single-threaded
worker processes, one per core, or the scheduler at ``scheduler``; or,
with ``serial``, this process alone), writes what comes back every few
seconds and, at the end, the results table, the workspace points and the
summary.

Output folder::

    results.parquet, results.csv   one row per case, in case order (see study_case)
    points.parquet                 workspace point clouds (case, case_key, sample, inputs, tip)
    summary.json, summary.md       counts, failures, timings, output ranges, sensitivities
    plots/*.png                    sensitivities, scatter plots, workspace clouds
    study.json                     the study's fingerprint (resume checks it)
    parts/                         rows written while the study runs (merged at the end)

Robustness: a case that fails is a row with ``status = failed`` and its
reason (:func:`study_case.run_case` catches it); a worker that dies loses
its task, which the scheduler runs again on another worker (up to
``distributed.scheduler.allowed-failures``, default 3, after which its cases
are recorded ``status = lost`` and rerun by the next resume); an
interrupted study (Ctrl-C, a crash) keeps the rows already written to
``parts/``, and running it again computes only the cases missing there
(rows are matched by ``case_key``, a hash of the study and the case's
values, so adding grid values or random samples reuses the cases done).
"""

import json
import logging
import math
import os
import shutil
import sys
import time
import uuid
from pathlib import Path

import numpy as np

from soft_twin_core.errors import StudyInterrupted
from soft_twin_core.studies.case import _warm, run_cases
from soft_twin_core.studies.report import write_summary
from soft_twin_core.studies.study import StudyError, make_cases, parameter_columns, validate_cases

META_COLUMNS = ("compute_time_s", "started_unix_s", "worker")


def _stderr(msg):
    print(f"soft-twin-sim: {msg}", file=sys.stderr, flush=True)


# ----------------------------------------------------------------------------
# Tables
# ----------------------------------------------------------------------------

def _column_type(values):
    import pyarrow as pa
    vals = [v for v in values if v is not None]
    if vals and all(isinstance(v, (bool, np.bool_)) for v in vals):
        return pa.bool_()
    if vals and all(isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_)) for v in vals):
        return pa.int64()
    if all(isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))
           for v in vals):
        return pa.float64()
    return pa.string()


def rows_to_table(rows, columns=None, metadata=None):
    """A pyarrow Table of dict rows (missing entries null); column types:
    bool, int64, float64 or string (anything else as text)."""
    import pyarrow as pa
    if columns is None:
        columns = []
        seen = set()
        for r in rows:
            for k in r:
                if k not in seen:
                    seen.add(k)
                    columns.append(k)
    arrays = {}
    for c in columns:
        vals = [r.get(c) for r in rows]
        t = _column_type(vals)
        if t == pa.string():
            vals = [None if v is None else (v if isinstance(v, str) else str(v)) for v in vals]
        elif t == pa.float64():
            vals = [None if v is None else float(v) for v in vals]
        arrays[c] = pa.array(vals, type=t)
    table = pa.table(arrays) if arrays else pa.table({})
    if metadata:
        table = table.replace_schema_metadata({k: json.dumps(v) for k, v in metadata.items()})
    return table


def _write_parquet(table, path):
    import pyarrow.parquet as pq
    tmp = f"{path}.tmp-{os.getpid()}"
    pq.write_table(table, tmp)
    os.replace(tmp, path)           # never a half-written file under the real name


def write_csv(table, path):
    """CSV of a table: floats in Python's shortest round-trip form, nulls
    empty, booleans true/false."""
    import csv
    cols = table.column_names
    data = [table.column(c).to_pylist() for c in cols]

    def text(v):
        if v is None:
            return ""
        if isinstance(v, bool):
            return "true" if v else "false"
        return repr(v) if isinstance(v, float) else str(v)
    tmp = f"{path}.tmp-{os.getpid()}"
    with open(tmp, "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(cols)
        for i in range(table.num_rows):
            w.writerow([text(col[i]) for col in data])
    os.replace(tmp, path)


def read_rows(path):
    import pyarrow.parquet as pq
    return pq.read_table(path).to_pylist()


# ----------------------------------------------------------------------------
# The output folder
# ----------------------------------------------------------------------------

class _Store:
    """The output folder: what earlier runs left (by case key) and the part
    files this run writes."""

    def __init__(self, out_dir, study, overwrite):
        self.dir = Path(out_dir)
        self.parts = self.dir / "parts"
        meta_path = self.dir / "study.json"
        if overwrite and self.dir.exists():
            for name in ("results.parquet", "results.csv", "points.parquet", "summary.json", "summary.md",
                         "study.json"):
                (self.dir / name).unlink(missing_ok=True)
            shutil.rmtree(self.parts, ignore_errors=True)
            shutil.rmtree(self.dir / "plots", ignore_errors=True)
        if meta_path.exists():
            meta = json.loads(meta_path.read_text())
            if meta.get("fingerprint") != study.fingerprint:
                raise StudyError(
                    f"{self.dir} holds the results of another study ({meta.get('name')!r}, fingerprint "
                    f"{meta.get('fingerprint')}; this one: {study.fingerprint}: its robot, scenario, "
                    f"computations or records differ); use --overwrite or another --output")
        self.dir.mkdir(parents=True, exist_ok=True)
        self.parts.mkdir(exist_ok=True)
        meta_path.write_text(json.dumps({"name": study.name, "fingerprint": study.fingerprint,
                                         "source": study.source}, indent=1))
        self.run_id = time.strftime("%Y%m%dT%H%M%S") + "-" + uuid.uuid4().hex[:6]
        self.seq = 0
        self.pending, self.pending_points = [], []

    def previous(self):
        """{case_key: row} and {case_key: points dict} of earlier runs:
        results.parquet, then the part files (a later row wins)."""
        rows, pts = {}, {}
        files = ([self.dir / "results.parquet"] if (self.dir / "results.parquet").exists() else []) + \
            sorted(self.parts.glob("part-*.parquet"))
        for f in files:
            for r in read_rows(f):
                rows[r["case_key"]] = r
        pfiles = ([self.dir / "points.parquet"] if (self.dir / "points.parquet").exists() else []) + \
            sorted(self.parts.glob("points-*.parquet"))
        for f in pfiles:
            by = {}
            for r in read_rows(f):
                by.setdefault(r["case_key"], []).append(r)
            pts.update(by)
        return rows, pts

    def add(self, row):
        pts = row.pop("_points", None)
        self.pending.append(row)
        if pts is not None:
            n = len(pts["sample"])
            for i in range(n):
                self.pending_points.append({"case": row["case"], "case_key": row["case_key"],
                                            **{k: v[i] for k, v in pts.items()}})

    def flush(self):
        if not self.pending:
            return
        self.seq += 1
        tag = f"{self.run_id}-{self.seq:05d}"
        if self.pending_points:       # points first: a part file's cases have their points
            _write_parquet(rows_to_table(self.pending_points), self.parts / f"points-{tag}.parquet")
        _write_parquet(rows_to_table(self.pending), self.parts / f"part-{tag}.parquet")
        self.pending, self.pending_points = [], []


# ----------------------------------------------------------------------------
# Running
# ----------------------------------------------------------------------------

def default_workers():
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def default_chunk_size(study, n_todo, n_workers):
    """Cases per Dask task: one for dynamics and workspaces (seconds each);
    for statics (about 10 ms each) about 16 tasks per worker, at most 25
    cases a task: the scheduler's cost per task (a millisecond or two)
    stays small, the last tasks leave little imbalance between the
    workers, and a lost worker loses little."""
    if "dynamics" in study.compute or "workspace" in study.compute:
        return 1
    return max(1, min(25, math.ceil(n_todo / (16 * max(1, n_workers)))))


def start_local_cluster(n_workers):
    """A LocalCluster of ``n_workers`` worker processes with one thread each
    (the kernels hold the GIL: threads would not run cases in parallel)."""
    from distributed import Client, LocalCluster
    cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                           dashboard_address=":0", silence_logs=logging.ERROR)   # any free port (no bokeh: no dashboard)
    client = Client(cluster)
    # Ctrl-C in a terminal reaches the whole process group: this process
    # saves the rows and closes the cluster; the workers need not (they
    # would print a KeyboardInterrupt traceback each)
    client.run(_ignore_sigint)
    return cluster, client


def _ignore_sigint():
    """In each worker: Ctrl-C is the study's to handle; and the scheduler
    going away with it is no news (:class:`_HeartbeatAfterClose`)."""
    import signal
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logger = logging.getLogger("distributed.worker")
    if not any(isinstance(f, _HeartbeatAfterClose) for f in logger.filters):
        logger.addFilter(_HeartbeatAfterClose())


class _HeartbeatAfterClose(logging.Filter):
    """Drops a worker's "Failed to communicate with scheduler during
    heartbeat." and its traceback: after Ctrl-C this process closes the
    scheduler while the workers still beat, and the first beat to find it
    gone logs this (seen in CI on an interrupted local study, distributed
    2026.8.0). A worker that really loses its scheduler is counted by the
    study (lost cases, dead workers). Every other record passes."""

    def filter(self, record):
        return "during heartbeat" not in str(record.msg) or "Failed to communicate" not in str(record.msg)


_quiet = {}        # the logger levels to restore once an interrupted study's cluster is closed


class _SyncCancelBug(logging.Filter):
    """Drops the one traceback a known ``distributed`` bug prints on Ctrl-C.

    ``distributed.utils.sync`` answers a KeyboardInterrupt by queueing a
    ``cancel`` callback on the event loop; when the interrupt comes before the
    loop has started the awaited call, that callback reads a variable not yet
    bound and tornado logs ``NameError: cannot access free variable 'future'``
    with its traceback (distributed 2026.8.0, utils.py; seen in CI on an
    interrupted study). Nothing was lost: the call was never started. Every
    other record passes."""

    def filter(self, record):
        exc = record.exc_info[1] if record.exc_info else None
        if not isinstance(exc, NameError) or "'future'" not in str(exc):
            return True
        tb = exc.__traceback__
        while tb is not None and tb.tb_next is not None:
            tb = tb.tb_next
        code = tb.tb_frame.f_code if tb is not None else None
        return not (code is not None and code.co_name == "cancel"
                    and code.co_filename.replace(os.sep, "/").endswith("distributed/utils.py"))


def install_sync_cancel_filter():
    """Attach :class:`_SyncCancelBug` to tornado's callback logger, once per
    process (the loop thread can log after the study returns)."""
    logger = logging.getLogger("tornado.application")
    if not any(isinstance(f, _SyncCancelBug) for f in logger.filters):
        logger.addFilter(_SyncCancelBug())


def _silence_distributed_logs():
    """Raise every ``distributed`` logger above CRITICAL; returns the levels to
    restore. After Ctrl-C the shutdown is ours: the scheduler then logs each
    comm its closing workers broke as CRITICAL, with a traceback, which is
    no news to the user (seen with a few hundred pending cases)."""
    names = ["distributed"] + [n for n in logging.root.manager.loggerDict if n.startswith("distributed.")]
    saved = {n: logging.getLogger(n).level for n in names}
    for n in names:
        logging.getLogger(n).setLevel(logging.CRITICAL + 1)
    return saved


def _restore_logs(saved):
    for n, level in saved.items():
        logging.getLogger(n).setLevel(level)


def _lost_rows(study, chunk, reason):
    return [{"case": i, "case_key": k, **parameter_columns(study, v), "status": "lost", "error": reason}
            for i, v, k in chunk]


def run_study(study, out_dir, *, scheduler=None, n_workers=None, serial=False, client=None,
              chunk_size=None, retry_failed=False, overwrite=False, flush_seconds=2.0, log=_stderr,
              summary=True, on_progress=None):
    """Compute every case of ``study`` missing in ``out_dir`` and write the
    results (see the module docstring). ``client``: an existing
    ``distributed.Client`` (kept open); else ``scheduler`` (an address) or
    a new LocalCluster of ``n_workers`` (default: one per core); ``serial``:
    this process, no Dask. Raises :class:`study.CaseValidationError` before
    anything runs if a case is invalid, :class:`StudyInterrupted` on
    Ctrl-C (after saving). Returns a dict: ``cases``, ``computed``,
    ``reused``, ``ok``, ``failed``, ``lost``, timings and the paths."""
    t_start = time.monotonic()
    cases = make_cases(study)
    validate_cases(study, cases)
    t_valid = time.monotonic() - t_start
    store = _Store(out_dir, study, overwrite)
    prev_rows, prev_pts = store.previous()
    keep = {"ok", "failed"} if not retry_failed else {"ok"}
    todo = [c for c in cases if prev_rows.get(c.key, {}).get("status") not in keep]
    n_reused = len(cases) - len(todo)
    log(f"study {study.name!r}: {len(cases)} cases ({study.design['type']}), validated in {t_valid:.2f} s; "
        + (f"{n_reused} already in {out_dir}, " if n_reused else "") + f"{len(todo)} to compute")
    new_rows = {}
    counts = {"ok": 0, "failed": 0, "lost": 0}
    worker_losses = []            # workers that died under a chunk (dead_workers)
    timing = {"validate_s": t_valid, "cluster_start_s": 0.0, "workers_ready_s": 0.0, "compute_s": 0.0}
    where = "this process (serial)"
    if todo:
        cluster = own_client = None
        try:
            if not serial:
                t0 = time.monotonic()
                if client is None:
                    if scheduler:
                        from distributed import Client
                        client = own_client = Client(scheduler, timeout="30s")
                        where = f"the Dask scheduler at {scheduler}"
                    else:
                        n_workers = n_workers or default_workers()
                        cluster, client = start_local_cluster(n_workers)
                        own_client = client
                        where = f"a local Dask cluster of {n_workers} single-threaded worker processes"
                else:
                    where = f"the Dask scheduler at {client.scheduler.address}"
                timing["cluster_start_s"] = time.monotonic() - t0
                t0 = time.monotonic()
                # every worker loads the kernels once, in parallel; a worker that
                # cannot (soft_twin_core missing there) is named, its tasks will fail
                warm = client.run(_warm, on_error="return")
                timing["workers_ready_s"] = time.monotonic() - t0
                bad = {w: v for w, v in warm.items() if isinstance(v, BaseException)}
                for w, e in bad.items():
                    log(f"worker {w} cannot load soft_twin_core's kernels: {type(e).__name__}: {e}")
                n_w = max(1, len(warm))
                log(f"{where}: {len(warm) - len(bad)} workers ready in "
                    f"{timing['cluster_start_s'] + timing['workers_ready_s']:.1f} s (kernels from numba's cache: "
                    f"{', '.join(f'{v:.2f}' for v in warm.values() if not isinstance(v, BaseException))} s)")
            else:
                n_w = 1
            chunk = chunk_size or default_chunk_size(study, len(todo), n_w)
            chunks = [[(c.index, c.values, c.key) for c in todo[j:j + chunk]] for j in range(0, len(todo), chunk)]
            t0 = time.monotonic()
            state = {"done": 0, "last_log": t0, "last_flush": t0}

            def take(rows):
                for r in rows:
                    counts[r["status"]] += 1
                    new_rows[r["case_key"]] = {k: v for k, v in r.items() if k != "_points"}
                    store.add(r)
                state["done"] += len(rows)
                now = time.monotonic()
                if now - state["last_flush"] >= flush_seconds:
                    store.flush()
                    state["last_flush"] = now
                if on_progress is not None:
                    on_progress(state["done"], len(todo))
                if now - state["last_log"] >= 1.0 or state["done"] == len(todo):
                    el = now - t0
                    left = el / state["done"] * (len(todo) - state["done"]) if state["done"] else float("nan")
                    log(f"{state['done']}/{len(todo)} cases computed ({counts['failed']} failed"
                        + (f", {counts['lost']} lost" if counts["lost"] else "") + f"), {el:.1f} s, ~{left:.0f} s left")
                    state["last_log"] = now
            try:
                if serial:
                    for ch in chunks:
                        take(run_cases(study, ch))
                else:
                    _run_on_dask(client, study, chunks, take, log, worker_losses)
            except KeyboardInterrupt:
                store.flush()
                raise StudyInterrupted(
                    f"interrupted: {n_reused + state['done']} of {len(cases)} cases saved in {out_dir}; "
                    f"run the same command again to compute the other {len(todo) - state['done']}") from None
            store.flush()
            timing["compute_s"] = time.monotonic() - t0
        finally:
            # bounded: after Ctrl-C to the whole process group a close could wait for ever on a worker
            # process that is shutting down too (seen once in 2 full runs: the command hung)
            for closing in (own_client, cluster):
                if closing is not None:
                    try:
                        closing.close(timeout=15)
                    except Exception:            # a timeout or an already-dead worker: we are leaving anyway
                        pass
            if _quiet.get("saved"):
                _restore_logs(_quiet.pop("saved"))
    # --- merge: every case of this study, in case order
    rows, pts = [], []
    for c in cases:
        r = new_rows.get(c.key) or dict(prev_rows[c.key])
        r["case"] = c.index
        rows.append(r)
    if "workspace" in study.compute:
        new_pts = {}
        for f in sorted(store.parts.glob(f"points-{store.run_id}-*.parquet")):
            for r in read_rows(f):
                new_pts.setdefault(r["case_key"], []).append(r)
        for c in cases:
            for p in new_pts.get(c.key) or prev_pts.get(c.key, []):
                pts.append({**p, "case": c.index})
    meta = {"soft_twin_study": {"name": study.name, "fingerprint": study.fingerprint, "source": study.source}}
    table = rows_to_table(rows, metadata=meta)
    out = Path(out_dir)
    _write_parquet(table, out / "results.parquet")
    write_csv(table, out / "results.csv")
    if pts:
        _write_parquet(rows_to_table(pts, metadata=meta), out / "points.parquet")
    shutil.rmtree(store.parts, ignore_errors=True)
    n_status = {s: sum(r["status"] == s for r in rows) for s in ("ok", "failed", "lost")}
    timing["total_s"] = time.monotonic() - t_start
    result = {"cases": len(cases), "computed": len(todo), "reused": n_reused, **n_status,
              "timing": timing, "where": where, "results": str(out / "results.parquet"),
              "csv": str(out / "results.csv"), "points": str(out / "points.parquet") if pts else None,
              "worker_losses": worker_losses}
    if summary:
        result["summary"] = write_summary(study, rows, pts, out, result)
    log(f"study {study.name!r}: {n_status['ok']} ok, {n_status['failed']} failed"
        + (f", {n_status['lost']} lost" if n_status["lost"] else "")
        + (f"; {len({w['worker'] for w in worker_losses})} worker(s) died during the run (cases re-run: "
           f"{sorted(c for w in worker_losses if w['rerun'] for c in w['cases'])})" if worker_losses else "")
        + f" of {len(cases)} cases; {len(todo)} computed in {timing['compute_s']:.2f} s on {where}; "
        f"results in {out / 'results.parquet'} (and .csv)")
    return result


def dead_workers(client, chunk_of, lost_keys, log):
    """The workers that died (not a clean close) while computing chunks of
    this run, from the scheduler's ``remove-worker`` events: one record per
    worker and chunk, {worker, time_unix_s, cases, rerun} (rerun: the chunk
    was computed again on another worker, else its cases are ``lost``), each
    also logged, so that a killed worker leaves a trace in the output."""
    try:
        events = client.get_events("all")
    except Exception as e:                   # an old or unreachable scheduler: say so, do not fail the study
        log(f"could not read the scheduler's worker events ({type(e).__name__}: {e}); "
            f"a worker that died during the run is not reported")
        return []
    out = []
    for stamp, msg in events:
        if not isinstance(msg, dict) or msg.get("action") != "remove-worker" or msg.get("expected"):
            continue
        for key in sorted(k for k in msg.get("processing-tasks", ()) if k in chunk_of):
            cases = [c[0] for c in chunk_of[key]]
            rec = {"worker": str(msg.get("worker")), "time_unix_s": float(stamp), "cases": cases,
                   "rerun": key not in lost_keys}
            out.append(rec)
            log(f"worker {rec['worker']} died while computing cases {cases[0]}..{cases[-1]}; "
                + ("they were re-run on another worker" if rec["rerun"] else "they are recorded lost"))
    return out


def _run_on_dask(client, study, chunks, take, log, worker_losses=None):
    """Submit the chunks (one task each) and hand every chunk's rows to
    ``take`` as it completes. A task whose workers kept dying
    (KilledWorker) gives ``lost`` rows; other task errors (not raised by a
    case, which records its own failure) give ``lost`` rows with the reason."""
    from distributed import as_completed
    install_sync_cancel_filter()
    futures = {}
    tag = uuid.uuid4().hex[:8]
    for j, ch in enumerate(chunks):
        f = client.submit(run_cases, study, ch, key=f"soft_twin-study-{tag}-{j}", pure=False)
        futures[f] = ch
    lost_keys = set()
    try:
        for f in as_completed(list(futures)):
            ch = futures[f]
            try:
                rows = f.result()
            except Exception as e:       # KilledWorker, a worker-side crash outside the cases
                reason = f"{type(e).__name__}: {e}"[:2000]
                log(f"cases {ch[0][0]}..{ch[-1][0]} lost: {reason}")
                rows = _lost_rows(study, ch, reason)
                lost_keys.add(f.key)
            take(rows)
        if worker_losses is not None:
            worker_losses += dead_workers(client, {f.key: ch for f, ch in futures.items()}, lost_keys, log)
    except KeyboardInterrupt:
        _quiet["saved"] = _quiet.get("saved") or _silence_distributed_logs()
        raise
    finally:
        client.cancel(list(futures))
