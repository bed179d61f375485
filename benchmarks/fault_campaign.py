"""Fault campaign on ``wpot all-vs-all``: SIGKILL at random moments, rerun, compare with an uninterrupted run.

What it measures (issue 22, "Reliability, measured"): the store's contract under crashes. For each execution
mode (inline, ``--jobs 2``, ``--scheduler local --jobs 2``) it

1. runs the command once without interruption on a small generated dataset (the reference);
2. starts the same command on a fresh run folder, kills its whole process group (the coordinator and its
   workers) with SIGKILL after a random delay (uniform between 0 and the reference's wall time, so kills land
   in every phase: reading meshes, spectra, signatures and their cache writes, pairs, commits), restarts it,
   kills it again, ... and after the last kill reruns it to completion;
3. checks the finished store: D(inf) and D(beta) (every beta) equal to the reference's bit for bit (the
   computation is deterministic), no pair committed twice (the ``computations`` table against ``pairs``), no
   failures, and the final command's exit status 0.

It also counts pairs *recomputed* after a kill: pairs that were in flight when the kill came (started, not
committed) and so ran again. Those are allowed (the work of an unfinished pair is lost); committing a pair
twice is not. The count comes from a start log: a ``sitecustomize`` module put on the subprocesses'
``PYTHONPATH`` wraps ``wpot.runs.workers.pair_task`` to append "i j" to a file at every pair start, in the
coordinator and in every worker process (process pool and Dask alike). The instrumentation lives here only;
nothing in wpot knows about it.

With ``--signals`` it runs the signal campaign instead (issue 43, "Stopping cleanly"): for each mode and each
case (SIGINT once; SIGINT twice, 1-2 s apart, as a user pressing Ctrl-C again; SIGTERM, as ``timeout``, systemd
and SLURM send) it starts the command on a fresh run folder, sends the signals to its process group at a random
moment (uniform from its start to the reference's wall time: startup, meshes, signatures, pairs), and records
whether it hung (no exit within 30 s of the first signal), the seconds to exit, its exit code, the processes of
the run (its descendants, and any process naming the run folder) still alive 10 s after it exited, whether the
store is consistent (SQLite's integrity check, and no pair lost that was stored before the signal), and whether
a rerun resumes to the reference's D(inf) and D(beta) bit for bit with no pair committed twice.

Usage::

    python benchmarks/fault_campaign.py                 # 50 kills: 20 inline, 15 --jobs 2, 15 --scheduler local
    python benchmarks/fault_campaign.py --kills 9 --seed 1
    python benchmarks/fault_campaign.py --signals --tries 5

Prints one table row per mode: kills, reruns, trials (fresh run folders), final matrices equal, pairs
committed twice, pairs recomputed after a kill, failures, time. A few minutes on 2 CPU cores. With
``--signals``, one row per mode and signal case.
"""
from __future__ import annotations

import argparse
import collections
import contextlib
import dataclasses
import os
import random
import signal
import statistics
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
from pathlib import Path

import numpy as np

SETTINGS = ["--max-vertices", "60", "--n-eigen", "40", "--n-energies", "40", "--device", "cpu", "--no-progress"]
MODES = {"inline": [], "--jobs 2": ["--jobs", "2"], "--scheduler local": ["--scheduler", "local", "--jobs", "2"]}
SHARE = {"inline": 0.4, "--jobs 2": 0.3, "--scheduler local": 0.3}

SITECUSTOMIZE = textwrap.dedent('''
    """Fault-campaign instrumentation: log every pair start to $WPOT_CAMPAIGN_LOG (benchmarks/fault_campaign.py)."""
    import os
    if os.environ.get("WPOT_CAMPAIGN_LOG"):
        import functools
        import wpot.runs.workers as _w  # before wpot.runs.loop, which imports pair_task from it
        _orig = _w.pair_task

        @functools.wraps(_orig)
        def pair_task(i, j, *args, **kwargs):
            fd = os.open(os.environ["WPOT_CAMPAIGN_LOG"], os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
            try:
                os.write(fd, f"{i} {j}\\n".encode())
            finally:
                os.close(fd)
            return _orig(i, j, *args, **kwargs)

        _w.pair_task = pair_task  # pickled by name: workers (processes, Dask) unpickle this one too
''')


def make_dataset(folder: Path, n_per_class: int = 3) -> Path:
    """Two classes of small meshes (the example surface and a stretched copy), each a different triangulation."""
    from wpot.examples import example_mesh
    from wpot.io import save_mesh
    from wpot.mesh import Mesh

    folder.mkdir(parents=True, exist_ok=True)
    for k in range(n_per_class):
        m = example_mesh(60 + 7 * k, seed=k)
        save_mesh(m, folder / f"blob{k + 1}.off")
        save_mesh(Mesh(m.vertices * np.array([1.8, 0.6, 1.0]), m.faces), folder / f"flat{k + 1}.off")
    return folder


class Campaign:
    """Runs the commands and keeps the per-mode figures."""

    def __init__(self, work: Path, data: Path, hook_dir: Path) -> None:
        self.work, self.data, self.hook_dir = work, data, hook_dir

    def command(self, mode: str, run: Path) -> list[str]:
        return [sys.executable, "-m", "wpot.cli", "all-vs-all", str(self.data), "--out", str(run), *SETTINGS, *MODES[mode]]

    def start(self, mode: str, run: Path, log: Path | None) -> subprocess.Popen:
        """The command on ``run``; with ``log``, every pair start is appended to it (the instrumentation)."""
        env = dict(os.environ) if log is None else dict(
            os.environ, WPOT_CAMPAIGN_LOG=str(log),
            PYTHONPATH=os.pathsep.join([str(self.hook_dir), os.environ.get("PYTHONPATH", "")]))
        return subprocess.Popen(self.command(mode, run), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                env=env, start_new_session=True)  # its own process group: workers die with it

    def finish(self, mode: str, run: Path, log: Path | None) -> tuple[int, str]:
        p = self.start(mode, run, log)
        _, err = p.communicate(timeout=600)
        return p.returncode, err.decode(errors="replace")


def read_run(run: Path) -> dict:
    """The finished store's matrices and bookkeeping (read with RunStore, as `wpot classify` would)."""
    from wpot.runs.store import RunStore

    with RunStore(run) as s:
        betas, d_beta = s.distance_matrices()
        dup = s.con.execute("SELECT COUNT(*) FROM (SELECT i, j FROM computations GROUP BY i, j HAVING COUNT(*) > 1)").fetchone()[0]
        return {"d": s.distance_matrix(), "betas": betas, "d_beta": d_beta, "n_pairs": len(s.done()),
                "n_tasks": len(s.tasks()), "dup": int(dup), "n_comp": s.n_computations, "failures": len(s.failures())}


def starts(log: Path) -> dict[tuple[int, int], int]:
    """Pair starts per pair from the start log (a line cut by a kill is ignored)."""
    out: dict[tuple[int, int], int] = {}
    if log.is_file():
        for line in log.read_text().splitlines():
            parts = line.split()
            if len(parts) == 2 and all(p.isdigit() for p in parts):
                key = (int(parts[0]), int(parts[1]))
                out[key] = out.get(key, 0) + 1
    return out


def same(a: dict, b: dict) -> bool:
    return (np.array_equal(a["d"], b["d"], equal_nan=True) and np.array_equal(a["betas"], b["betas"])
            and np.array_equal(a["d_beta"], b["d_beta"], equal_nan=True))


# ------------------------------------------------------------------------------------------------- signals
#: the signal cases: what is sent to the run's process group (a second one 1-2 s after the first)
SIGNAL_CASES = {"SIGINT x1": (signal.SIGINT,), "SIGINT x2": (signal.SIGINT, signal.SIGINT), "SIGTERM": (signal.SIGTERM,)}
#: a run still going this long after the first signal is counted as hung (and then killed)
HANG_AFTER = 30.0
#: how long the run's processes get to end after the run exits
SETTLE = 10.0


@dataclasses.dataclass
class Stop:
    """What a run did with the signals it was sent (`signal_run`)."""

    returncode: int | None  # None: hung (still running HANG_AFTER s after the first signal; then killed)
    seconds: float  # from the first signal to the run's exit (HANG_AFTER when hung)
    pairs_before: int  # pairs stored when the first signal was sent
    left: list[str]  # the run's processes still alive SETTLE s after it exited ("pid cmdline")
    stderr: str
    sent: int  # signals sent (a later one only while the run still ran)


def stored_pairs(run: Path) -> int:
    """Pairs in the run's store, read without writing anything (0 before the store exists)."""
    import sqlite3

    db = run / "wpot.sqlite"
    if not db.is_file():
        return 0
    try:
        with contextlib.closing(sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5)) as con:
            return int(con.execute("SELECT COUNT(*) FROM pairs").fetchone()[0])
    except sqlite3.Error:  # not created yet
        return 0


def _run_processes(proc: subprocess.Popen, run: Path, seen: dict) -> None:
    """Add to ``seen`` (pid -> psutil.Process) the run's descendants now and every process naming its folder."""
    import psutil

    with contextlib.suppress(psutil.Error):
        for c in psutil.Process(proc.pid).children(recursive=True):
            seen.setdefault(c.pid, c)
    for q in psutil.process_iter(["cmdline"]):
        if q.pid != os.getpid() and any(str(run) in part for part in (q.info["cmdline"] or [])):
            seen.setdefault(q.pid, q)


def _alive(seen: dict) -> list[str]:
    import psutil

    out = []
    for q in seen.values():
        with contextlib.suppress(psutil.Error):
            if q.is_running() and q.status() != psutil.STATUS_ZOMBIE:
                out.append(f"{q.pid} {' '.join(q.cmdline())[:120]}")
    return out


def signal_run(cmd: list[str], run: Path, signals: tuple[int, ...], *, after: float | None = None,
               ready_text: str | None = None, gap: float = 1.5, env: dict | None = None) -> Stop:
    """Start ``cmd`` (a ``wpot`` command on the run folder ``run``) in its own process group, wait (``after``
    seconds; else until ``ready_text`` is on its standard error; else until a first pair is stored), send
    ``signals`` to the group ``gap`` seconds apart (a later one only while the run still runs), and watch it end:
    the time to exit, and which of its processes (its descendants, seen while it ran, and any process naming
    ``run``) are alive `SETTLE` s later."""
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, start_new_session=True)
    err: list[bytes] = []
    reader = threading.Thread(target=lambda: err.extend(iter(lambda: p.stderr.read1(65536), b"")), daemon=True)
    reader.start()

    def waiting() -> bool:
        if after is not None:
            return time.monotonic() - t_start < after
        if ready_text is not None:
            return ready_text.encode() not in b"".join(err)
        return stored_pairs(run) < 1

    seen: dict = {}
    t_start = time.monotonic()
    while p.poll() is None and waiting():
        _run_processes(p, run, seen)
        time.sleep(0.2)
    _run_processes(p, run, seen)
    pairs_before, t0, sent = stored_pairs(run), time.monotonic(), 0
    for k, sig in enumerate(signals):
        if k:
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(timeout=gap)
        if p.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, sig)
                sent += 1
    try:
        p.wait(timeout=max(0.0, HANG_AFTER - (time.monotonic() - t0)))
        code, seconds = p.returncode, time.monotonic() - t0
    except subprocess.TimeoutExpired:
        code, seconds = None, HANG_AFTER
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGKILL)
        p.wait()
    deadline = time.monotonic() + SETTLE
    while _alive(seen) and time.monotonic() < deadline:
        time.sleep(0.1)
    reader.join(timeout=5)
    return Stop(code, seconds, pairs_before, _alive(seen), b"".join(err).decode(errors="replace"), sent)


def store_consistent(run: Path) -> bool:
    """The store opens as a run (`RunStore`) and SQLite's integrity check passes (or no store was made yet)."""
    from wpot.runs.store import RunStore

    if not (run / "wpot.sqlite").is_file():
        return True
    try:
        with RunStore(run) as s:
            return [r[0] for r in s.con.execute("PRAGMA integrity_check")] == ["ok"]
    except Exception:
        return False


def signal_campaign(a: argparse.Namespace, camp: Campaign, rng: random.Random) -> bool:
    """SIGINT once, SIGINT twice (1-2 s apart) and SIGTERM at random moments of each mode's run; prints a table."""
    rows, ok_all = [], True
    for mode in a.modes:
        ref_run = a.work / f"sigref-{mode.strip('-').replace(' ', '_')}"
        t0 = time.perf_counter()
        rc, err = camp.finish(mode, ref_run, None)
        t_ref = time.perf_counter() - t0
        if rc != 0:
            print(f"{mode}: the uninterrupted run failed (exit {rc}):\n{err[-3000:]}", file=sys.stderr)
            return False
        ref = read_run(ref_run)
        for case, signals in SIGNAL_CASES.items():
            stops, consistent, resumed, dup = [], 0, 0, 0
            for k in range(a.tries):
                run = a.work / f"{ref_run.name}-{case.replace(' ', '')}-{k}"
                st = signal_run(camp.command(mode, run), run, signals, after=rng.uniform(0.0, t_ref),
                                gap=rng.uniform(1.0, 2.0))
                stops.append(st)
                run.with_name(run.name + ".stderr").write_text(st.stderr)  # kept with --work
                consistent += store_consistent(run) and stored_pairs(run) >= st.pairs_before
                rc, err = camp.finish(mode, run, None)  # the rerun resumes
                if rc == 0:
                    got = read_run(run)
                    resumed += same(got, ref) and got["n_pairs"] == got["n_tasks"]
                    dup += got["dup"]
                else:
                    print(f"{mode} {case} try {k}: the rerun failed (exit {rc}):\n{err[-2000:]}", file=sys.stderr)
            rows.append((mode, case, stops, consistent, resumed, dup))
            ok_all &= (all(st.returncode is not None and not st.left for st in stops) and consistent == a.tries
                       and resumed == a.tries and dup == 0)
    print(f"signal campaign: SIGINT once, SIGINT twice (1-2 s apart), SIGTERM to the run's process group at a random "
          f"moment of the run (uniform from its start to an uninterrupted run's wall time), then rerun; seed {a.seed}; "
          f"dataset: 6 meshes of 60-74 vertices, 15 pairs; {' '.join(SETTINGS)}")
    head = ("mode", "signal", "tries", "finished before the signal", "hung (no exit in 30 s)",
            "seconds to exit (median / max)", "exit codes", "a traceback printed", "processes left after 10 s",
            "store consistent", "resumed bit-identical", "pairs committed twice")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for mode, case, stops, consistent, resumed, dup in rows:
        hit = [st for st in stops if st.sent]  # the others had finished when their moment came
        secs = [st.seconds for st in hit] or [float("nan")]
        codes = ", ".join(f"{c} x{n}" if n > 1 else str(c) for c, n in
                          sorted(collections.Counter("hung" if st.returncode is None else st.returncode
                                                     for st in hit).items(), key=str)) or "-"
        print(f"| {mode} | {case} | {len(stops)} | {len(stops) - len(hit)} | {sum(st.returncode is None for st in hit)} | "
              f"{statistics.median(secs):.1f} / {max(secs):.1f} | {codes} | {sum('Traceback' in st.stderr for st in hit)} | "
              f"{sum(len(st.left) for st in stops)} | "
              f"{consistent}/{len(stops)} | {resumed}/{len(stops)} | {dup} |")
    return ok_all


# ---------------------------------------------------------------------------------------------------- kills
def kill_campaign(a: argparse.Namespace, camp: Campaign, rng: random.Random) -> bool:
    """SIGKILLs at random moments, reruns to completion, and the finished stores checked; prints a table."""
    shares = {m: SHARE[m] for m in a.modes}
    total = sum(shares.values())
    targets = {m: round(a.kills * s / total) for m, s in shares.items()}
    targets[a.modes[0]] += a.kills - sum(targets.values())

    rows, refs, ok_all = [], {}, True
    for mode in a.modes:
        t_mode = time.perf_counter()
        ref_run = a.work / f"ref-{mode.strip('-').replace(' ', '_')}"
        t0 = time.perf_counter()
        rc, err = camp.finish(mode, ref_run, a.work / "ref.log")
        t_ref = time.perf_counter() - t0
        if rc != 0:
            print(f"{mode}: the uninterrupted run failed (exit {rc}):\n{err[-3000:]}", file=sys.stderr)
            return False
        refs[mode] = ref = read_run(ref_run)
        kills = reruns = trials = dup = recomputed = failures = early = 0
        equal = True
        while kills < targets[mode]:
            trials += 1
            run, log = a.work / f"{ref_run.name}-trial{trials}", a.work / f"{ref_run.name}-trial{trials}.log"
            trial_kills = 0
            while True:
                if trial_kills:
                    reruns += 1
                p = camp.start(mode, run, log)
                delay = rng.uniform(0.0, t_ref)
                try:
                    p.wait(timeout=delay)
                except subprocess.TimeoutExpired:
                    os.killpg(p.pid, signal.SIGKILL)
                    p.wait()
                    kills += 1
                    trial_kills += 1
                    if kills < targets[mode] and trial_kills < a.kills_per_trial:
                        continue
                    reruns += 1
                    rc, err = camp.finish(mode, run, log)  # after the trial's last kill: run to completion
                else:
                    early += 1  # the run finished before its kill moment
                    rc, err = p.returncode, p.stderr.read().decode(errors="replace")
                break
            if rc != 0:
                print(f"{mode} trial {trials}: the final run failed (exit {rc}):\n{err[-3000:]}", file=sys.stderr)
                equal = False
                continue
            got = read_run(run)
            equal &= same(got, ref) and got["n_pairs"] == got["n_tasks"]
            dup += got["dup"]
            failures += got["failures"]
            recomputed += sum(c - 1 for c in starts(log).values())
        rows.append((mode, kills, reruns, trials, "yes" if equal else "NO", dup, recomputed, failures,
                     time.perf_counter() - t_mode))
        ok_all &= equal and dup == 0 and failures == 0

    names = list(refs)
    cross = all(same(refs[names[0]], refs[m]) for m in names[1:])
    print(f"fault campaign: {a.kills} SIGKILLs (whole process group) at random moments, seed {a.seed}; dataset: 6 meshes "
          f"of 60-74 vertices, 15 pairs; {' '.join(SETTINGS)}")
    head = ("mode", "kills", "reruns", "trials", "final D(inf), D(beta) equal", "pairs committed twice",
            "pairs recomputed after a kill", "failures", "time")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]} | {r[3]} | {r[4]} | {r[5]} | {r[6]} | {r[7]} | {r[8]:.0f} s |")
    print(f"uninterrupted runs of the modes equal to each other: {'yes' if cross else 'NO'}")
    return ok_all and cross


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kills", type=int, default=50, help="SIGKILLs in all, shared 40/30/30 %% by the modes (default 50)")
    ap.add_argument("--kills-per-trial", type=int, default=5, help="kills on one run folder before it is run to completion")
    ap.add_argument("--signals", action="store_true",
                    help="the signal campaign instead: SIGINT once, SIGINT twice, SIGTERM (see --tries)")
    ap.add_argument("--tries", type=int, default=5, help="--signals: tries of each signal case in each mode (default 5)")
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", type=Path, default=None, help="working folder (default: a temporary one, removed)")
    a = ap.parse_args(argv)
    rng = random.Random(a.seed)
    tmp = None
    if a.work is None:
        tmp = tempfile.TemporaryDirectory(prefix="wpot-faults-")
        a.work = Path(tmp.name)
    a.work.mkdir(parents=True, exist_ok=True)
    hook = a.work / "hook"
    hook.mkdir(exist_ok=True)
    (hook / "sitecustomize.py").write_text(SITECUSTOMIZE)
    camp = Campaign(a.work, make_dataset(a.work / "data"), hook)
    ok = (signal_campaign if a.signals else kill_campaign)(a, camp, rng)
    if tmp is not None:
        tmp.cleanup()
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
